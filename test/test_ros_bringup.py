"""``cdmp bringup``: graph files are validated with errors naming the key, the nodes run as
separate processes, and Ctrl-C / SIGTERM / --duration stop them all cleanly (exit 0)."""
import os
import signal
import subprocess
import sys

import pytest
import yaml

from bag_ros_util import Lines, recoverable_count
from conftest import wait_for
from node_harness import WAIT_S, assert_bringup_stopped
from cdmp_ros.bag import BagReader
from cdmp_ros.cli.cmd_bringup import (CLEAN_EXIT_CODES, Bringup, load_graph, package_config_dir,
                                      parse_graph)
from cdmp_ros.core.errors import ValidationError
from conftest import ros_env

pytestmark = pytest.mark.ros


@pytest.mark.parametrize('data, needle', [
    ([], 'graph: expected a mapping'),
    ({'nodes': []}, 'graph.nodes'),
    ({'nodes': [{'executable': 'nope'}]}, 'nodes[0].executable'),
    ({'nodes': [{'executable': 'sim', 'colour': 1}]}, "nodes[0]: unknown keys ['colour']"),
    ({'nodes': [{'executable': 'sim', 'params_file': 'missing.yaml'}]}, 'nodes[0].params_file'),
    ({'nodes': [{'executable': 'sim', 'params_file': []}]}, 'nodes[0].params_file: expected'),
    ({'nodes': [{'executable': 'sim', 'params_file': ['sim.yaml', 3]}]},
     'nodes[0].params_file: expected'),
    ({'nodes': [{'executable': 'sim', 'params_file': ['sim.yaml', 'missing.yaml']}]},
     "nodes[0].params_file[1]: 'missing.yaml' not found"),
    ({'nodes': [{'executable': 'sim', 'parameters': {'x': {'a': 1}}}]}, 'parameter value'),
    ({'nodes': [{'executable': 'sim', 'delay': -1}]}, 'nodes[0].delay'),
    ({'nodes': [{'executable': 'sim'}, {'executable': 'sim'}]}, "duplicate names ['sim']"),
    ({'nodes': [{'executable': 'sim'}], 'stop_timeout': 0}, 'graph.stop_timeout'),
    ({'nodes': [{'executable': 'sim'}], 'extra': 1}, "unknown keys ['extra']"),
])
def test_bad_graphs_are_rejected_naming_the_key(data, needle):
    with pytest.raises(ValidationError, match=None) as err:
        parse_graph(data)
    assert needle in str(err.value)


def test_commands_carry_params_remaps_and_namespace(tmp_path):
    g = parse_graph({'nodes': [{'name': 'arm', 'executable': 'streamer',
                                'params_file': 'streamer.yaml',
                                'parameters': {'rate': 250.0, 'coupling_enabled': False,
                                               'joint_names': ['a', 'b'], 'urdf_path': ''},
                                'remappings': {'goal': '/arm/goal'}, 'namespace': '/left'}]})
    cmd = g.nodes[0].command()
    assert cmd[1:3] == ['-m', 'cdmp_ros.nodes.streamer']
    assert cmd[cmd.index('--params-file') + 1].endswith(os.path.join('config', 'streamer.yaml'))
    for piece in ['rate:=250.0', 'coupling_enabled:=false', "joint_names:=['a', 'b']",
                  "urdf_path:=''", 'goal:=/arm/goal', '__ns:=/left']:
        assert piece in cmd


PARAMETER_PROBE = '''
import sys, rclpy
from rclpy.node import Node
rclpy.init(args=sys.argv)
node = Node('adapter')
node.declare_parameter('adaptation.avoid_links', ['none'])
node.declare_parameter('adaptation.alpha', 0.0)
print(list(node.get_parameter('adaptation.avoid_links').value),
      node.get_parameter('adaptation.alpha').value)
'''


def test_inline_parameters_win_over_every_parameter_file(tmp_path):
    """A graph's inline ``parameters`` win over every ``params_file``, as the graph file
    promises, in a real ROS process: rclpy applies ``-p`` over the first parameter file only
    (a later file's value won, and the dual demo's adapter kept the robot file's
    avoid_links), so with two or more files they also come as a last file."""
    for name, links in (('one.yaml', ['aa', 'bb']), ('two.yaml', ['cc', 'dd'])):
        (tmp_path / name).write_text(yaml.safe_dump({'/**': {'ros__parameters': {
            'adaptation': {'avoid_links': links, 'alpha': 0.9}}}}))
    spec, = parse_graph({'nodes': [{'name': 'adapter', 'executable': 'adapter',
                                    'params_file': ['one.yaml', 'two.yaml'],
                                    'parameters': {'adaptation.avoid_links': ['ee', 'y'],
                                                   'adaptation.alpha': 0.99}}]},
                        str(tmp_path)).nodes
    cmd = spec.command()
    ros_args = cmd[cmd.index('--ros-args'):]
    r = subprocess.run([sys.executable, '-c', PARAMETER_PROBE, *ros_args],
                       env=ros_env(), capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert r.stdout.split() == ["['ee',", "'y']", '0.99'], r.stdout  # 'y' stays a string
    # the same without the inline file: the defect it works around
    from cdmp_ros.cli.cmd_bringup import inline_parameters_file
    k = ros_args.index(inline_parameters_file(spec.parameters))
    assert ros_args[k - 1] == '--params-file' and ros_args[k + 1] == '-p'  # last, before -p
    plain = ros_args[:k - 1] + ros_args[k + 1:]
    r = subprocess.run([sys.executable, '-c', PARAMETER_PROBE, *plain],
                       env=ros_env(), capture_output=True, text=True, timeout=60)
    assert r.stdout.split()[:2] == ["['cc',", "'dd']"], r.stdout


def test_the_inline_parameter_file_refuses_a_name_under_another():
    from cdmp_ros.cli.cmd_bringup import inline_parameters_file
    for params in ({'a': 1.0, 'a.b': 2.0}, {'a.b': 2.0, 'a': 1.0}):
        with pytest.raises(ValidationError, match="parameters: 'a"):
            inline_parameters_file(params)
    assert inline_parameters_file({'names': []}) is None  # rcl: [] in a file is unset


def test_a_node_takes_several_parameter_files_in_order(tmp_path):
    """``params_file`` as a list: one ``--params-file`` each, in the given order (ROS applies
    them so, a later file wins; config/graphs/planar4.yaml layers the robot's files so), and
    the demo reads the adapter's parameters the same way."""
    from cdmp_ros.cli.demo_promp import adapter_parameters
    (tmp_path / 'mine.yaml').write_text(yaml.safe_dump({'/**': {'ros__parameters': {
        'base_frame': 'base', 'adaptation': {'alpha': 0.99}}}}))
    spec, = parse_graph({'nodes': [{'name': 'adapter', 'executable': 'adapter',
                                    'params_file': ['adapter.yaml', 'mine.yaml'],
                                    'parameters': {'adaptation.n_steps': 20}}]},
                        str(tmp_path)).nodes
    cmd = spec.command()
    files = [cmd[i + 1] for i, a in enumerate(cmd) if a == '--params-file']
    assert files[:2] == [os.path.join(package_config_dir(), 'adapter.yaml'),
                         str(tmp_path / 'mine.yaml')]
    assert len(files) == 3  # then the inline parameters (see the next test)
    params = adapter_parameters(spec)
    assert params['base_frame'] == 'base' and params['joint_names'][0] == 'panda_joint1'
    assert params['adaptation']['alpha'] == 0.99                  # the later file
    assert params['adaptation']['obstacle_margin'] == 0.02        # kept from the first
    assert params['adaptation']['n_steps'] == 20                  # inline parameters on top
    planar, = [s for s in load_graph(os.path.join(package_config_dir(), 'graphs',
                                                  'planar4.yaml')).nodes if s.name == 'sim']
    assert [os.path.relpath(f, package_config_dir()) for f in planar.params_files] == [
        'sim.yaml', os.path.join('robots', 'planar4', 'sim.yaml')]


def test_streamer_configs_are_the_node_parameters_of_its_files_and_graph(tmp_path):
    """The configs a tool reads off a graph (the kernel generator, the coupling replay) are
    the streamer's: its parameter files in order (config/streamer.yaml's capsules), then the
    graph's inline parameters, then the overrides; the files' parameters of no section
    (``joint_limits.*``) are not configs."""
    from cdmp_ros.cli.cmd_bringup import streamer_configs
    (tmp_path / 'mine.yaml').write_text(yaml.safe_dump({'/**/streamer': {'ros__parameters': {
        'repeller': {'gain': 0.05}, 'joint_limits': {'panda_joint1': {'max_jerk': 1.0}}}}}))
    graph = tmp_path / 'graph.yaml'
    graph.write_text(yaml.safe_dump({'nodes': [{
        'name': 'streamer', 'executable': 'streamer',
        'params_file': ['streamer.yaml', 'mine.yaml'],
        'parameters': {'rate': 1000.0, 'repeller.influence_distance': 0.3}}]}))
    c = streamer_configs(str(graph), {'damping.epsilon': 0.05})
    with open(os.path.join(package_config_dir(), 'streamer.yaml')) as f:
        shipped = yaml.safe_load(f)['/**']['ros__parameters']
    assert c[''].coupling_capsule_links == tuple(shipped['coupling_capsule_links'])
    assert c[''].coupling_capsule_links and c['coupling'].link_radius == 0.06
    assert c[''].rate == 1000.0                                   # inline
    assert c['repeller'].gain == 0.05                             # the later file
    assert c['repeller'].influence_distance == 0.3                # inline over the files
    assert c['damping'].epsilon == 0.05                           # the override
    with pytest.raises(ValidationError, match='nosuch.x'):
        streamer_configs(str(graph), {'nosuch.x': 1})


def test_the_documented_graph_format_is_the_parsed_one():
    """The example graph of the module docstring parses and names every key the parser
    accepts, no other; a node is renamed by a ``__node`` remapping (there is no other key)."""
    import textwrap
    from cdmp_ros.cli import cmd_bringup
    block = cmd_bringup.__doc__.split('A graph file::', 1)[1].split('\n\n', 2)[1]
    data = yaml.safe_load(textwrap.dedent(block))
    spec, = parse_graph(data).nodes
    assert set(data) == cmd_bringup._GRAPH_KEYS
    assert set(data['nodes'][0]) == cmd_bringup._NODE_KEYS
    cmd = spec.command()
    assert cmd[cmd.index('--ros-args') - 1] == 'cdmp_ros.nodes.sim'
    for arg in ['publish_rate:=250.0', 'joint_reference:=/arm/joint_reference', '__ns:=/arm']:
        assert arg in cmd, cmd
    renamed, = parse_graph({'nodes': [{'name': 'left', 'executable': 'sim',
                                       'remappings': {'__node': 'left_sim'}}]}).nodes
    assert renamed.command()[-2:] == ['-r', '__node:=left_sim']
    with pytest.raises(ValidationError, match="unknown keys \\['rename'\\]"):
        parse_graph({'nodes': [{'executable': 'sim', 'rename': True}]})


def test_unreadable_graph_file(tmp_path):
    p = tmp_path / 'g.yaml'
    p.write_text('nodes: [\n')
    with pytest.raises(ValidationError, match='not valid YAML'):
        load_graph(str(p))
    with pytest.raises(ValidationError, match='No such file'):
        load_graph(str(tmp_path / 'missing.yaml'))


def _graph(tmp_path, bag):
    p = tmp_path / 'graph.yaml'
    p.write_text(yaml.safe_dump({
        'stop_timeout': WAIT_S,
        'nodes': [{'name': 'streamer', 'executable': 'streamer', 'params_file': 'streamer.yaml',
                   'parameters': {'rate': 100.0}},
                  {'name': 'recorder', 'executable': 'recorder',
                   'parameters': {'output': str(bag), 'topics': ['/diagnostics']}}]}))
    return str(p)


def test_a_graph_runs_and_ctrl_c_stops_every_node(tmp_path):
    bag = tmp_path / 'bag'
    proc = subprocess.Popen([sys.executable, '-m', 'cdmp_ros.cli.main', 'bringup',
                             _graph(tmp_path, bag)], env=ros_env(), stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, start_new_session=True)
    out = Lines(proc.stdout)
    try:
        # both nodes run: the streamer streams, the recorder found its diagnostics ...
        assert wait_for(lambda: out.seen('streaming 7 joints', 'subscribed to /diagnostics'),
                        WAIT_S), out.text(0)
        # ... and some of them are already on disk
        probe = str(tmp_path / 'probe')
        assert wait_for(lambda: recoverable_count(str(bag), probe) > 0, WAIT_S, period=0.1)
        os.killpg(proc.pid, signal.SIGINT)  # Ctrl-C in a terminal reaches the whole group
        proc.wait(timeout=2 * WAIT_S)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    text = out.text()
    assert_bringup_stopped(proc.returncode, text)
    assert (bag / 'metadata.yaml').is_file(), text
    assert {m.topic for m in BagReader(str(bag)).messages()} == {'/diagnostics'}


def test_sigterm_and_duration_stop_the_graph(tmp_path):
    graph = load_graph(_graph(tmp_path, tmp_path / 'bag2'))
    log = tmp_path / 'graph.log'
    b = Bringup(graph, log=open(log, 'w'), extra_env=ros_env())
    b.start()
    try:
        # positive evidence that both nodes run, then that none of them exited meanwhile
        assert wait_for(lambda: 'streaming 7 joints' in log.read_text()
                        and 'recording to' in log.read_text(), WAIT_S), log.read_text()
        assert b.wait(timeout=0.0) is None  # nothing required exited
        assert not b.exited()
    finally:
        codes = b.stop()
    assert set(codes) == {'streamer', 'recorder'}
    assert all(c in CLEAN_EXIT_CODES for c in codes.values()), codes
    assert all(p.poll() is not None for p in b.procs.values())


def test_a_required_node_that_fails_stops_the_graph(tmp_path):
    p = tmp_path / 'g.yaml'
    p.write_text(yaml.safe_dump({'nodes': [
        {'name': 'bad', 'executable': 'streamer', 'parameters': {'rate': -5.0}},
        {'name': 'ok', 'executable': 'streamer', 'required': False}]}))
    proc = subprocess.run([sys.executable, '-m', 'cdmp_ros.cli.main', 'bringup', str(p)],
                          env=ros_env(), capture_output=True, text=True, timeout=180)
    assert proc.returncode == 1, proc.stdout + proc.stderr
    assert "required node 'bad' exited" in proc.stdout
    assert 'rate' in proc.stdout


SIGTERM_SCRIPT = '''
import signal, subprocess, sys
from cdmp_ros.cli.cmd_bringup import signal_flag
child = subprocess.Popen([sys.executable, '-c', 'import signal; signal.pause()'],
                         start_new_session=True)
with signal_flag(signal.SIGTERM) as (terminated, received):
    try:
        print(child.pid, flush=True)  # the handler is in place
        terminated.wait()  # the loop of a graph run (cdmp demo) waits on the flag
    finally:
        child.kill()  # the stop of the graph
        child.wait()
print('stopped by', received, flush=True)
sys.exit(3)
'''


def test_sigterm_lets_a_graph_run_stop_its_processes():
    """``cdmp demo`` and ``cdmp bringup`` run their graph under :func:`signal_flag`: SIGTERM
    only sets a flag, their loop sees it and stops the graph (by default SIGTERM ended the
    interpreter at once and left the node processes, each in its own session, running). The
    stand-in child here is such a process."""
    proc = subprocess.Popen([sys.executable, '-c', SIGTERM_SCRIPT], stdout=subprocess.PIPE,
                            text=True)
    child = None
    try:
        child = int(proc.stdout.readline())  # the child runs: the script is in its loop
        proc.send_signal(signal.SIGTERM)
        out, _ = proc.communicate(timeout=WAIT_S)
        try:
            os.kill(child, 0)
            child_left = True
        except ProcessLookupError:
            child_left = False
    finally:
        if proc.poll() is None:
            proc.kill()
        if child is not None:
            try:
                os.killpg(child, signal.SIGKILL)  # its own session: its group (a failed run)
            except ProcessLookupError:
                pass
    assert proc.returncode == 3 and f'stopped by [{int(signal.SIGTERM)}]' in out, out
    assert not child_left


def test_a_killed_bringup_takes_its_nodes_with_it(tmp_path):
    """SIGKILL of ``cdmp bringup`` (no handler, no ``finally`` runs): the kernel sends every
    node SIGTERM (``PR_SET_PDEATHSIG``), so no node keeps running on the domain. Each node has
    its own session, so without it they all stayed (a killed ``cdmp demo`` left its whole
    graph publishing)."""
    import psutil
    proc = subprocess.Popen([sys.executable, '-m', 'cdmp_ros.cli.main', 'bringup',
                             _graph(tmp_path, tmp_path / 'bag')], env=ros_env(),
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    out = Lines(proc.stdout)
    nodes = []
    try:
        assert wait_for(lambda: out.seen('streaming 7 joints', 'subscribed to /diagnostics'),
                        WAIT_S), out.text(0)
        nodes = psutil.Process(proc.pid).children()
        assert len(nodes) == 2, nodes
        proc.kill()
        proc.wait(timeout=WAIT_S)
        gone, alive = psutil.wait_procs(nodes, timeout=2 * WAIT_S)
    finally:
        for p in nodes:
            try:
                os.killpg(p.pid, signal.SIGKILL)  # own session: its group (a failed run)
            except ProcessLookupError:
                pass
    assert not alive and len(gone) == 2, (gone, alive)


def test_the_node_preexec_loads_nothing_in_the_child(monkeypatch):
    """The ``preexec_fn`` runs in the child of a multi-threaded parent (the output pumps),
    where loading a library may deadlock (``find_library`` even starts ``ldconfig``): the
    parent loads the C library when it makes the function, so the child only calls prctl."""
    import cdmp_ros.common.prctl as prctl_mod
    from cdmp_ros.cli.cmd_bringup import _terminate_with_parent
    monkeypatch.setattr(prctl_mod, '_libc', None)
    preexec = _terminate_with_parent(os.getpid())
    assert prctl_mod._libc and hasattr(prctl_mod._libc, 'prctl')
    loaded = prctl_mod._libc

    def no_loading(*a, **k):
        raise AssertionError('a library was loaded in the child')
    monkeypatch.setattr(prctl_mod.ctypes, 'CDLL', no_loading)
    monkeypatch.setattr(prctl_mod.ctypes.util, 'find_library', no_loading)
    assert prctl_mod.load() and prctl_mod._libc is loaded
    # a real child (fork copies the patched module: loading there would raise in preexec_fn)
    r = subprocess.run([sys.executable, '-c', 'import os; print(os.getppid())'],
                       preexec_fn=preexec, capture_output=True, text=True, timeout=WAIT_S)
    assert r.returncode == 0 and int(r.stdout) == os.getpid(), r


STUCK_NODE = '''
import threading
from cdmp_ros.ros.node_main import catch_stop_signals
catch_stop_signals()


def stuck_in_shutdown():
    print('ready', flush=True)
    threading.Event().wait()   # SIGINT sets the stop flag; nothing here looks at it


stuck_in_shutdown()
'''


def test_a_node_that_does_not_stop_shows_where_it_is_stuck_and_is_killed(tmp_path):
    """A node still running ``stop_timeout`` after SIGINT is asked for the stack of every
    thread (SIGUSR1, written by the C signal handler that catch_stop_signals registers) and
    then killed: the graph's output shows where it was stuck. The stand-in node is a process
    that ran catch_stop_signals and then waits forever."""
    import io
    import threading
    graph = parse_graph({'stop_timeout': 0.5, 'nodes': [{'name': 'stuck', 'executable': 'sim'}]})
    log = io.StringIO()
    b = Bringup(graph, log=log)
    proc = subprocess.Popen([sys.executable, '-c', STUCK_NODE], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, start_new_session=True)
    try:
        b.procs['stuck'] = proc
        pump = threading.Thread(target=b._pump, args=('stuck', proc.stdout), daemon=True)
        pump.start()
        b._threads.append(pump)
        assert wait_for(lambda: 'ready' in log.getvalue() or proc.poll() is not None, WAIT_S)
        assert proc.poll() is None, log.getvalue()
        codes = b.stop()
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    text = log.getvalue()
    assert codes == {'stuck': -signal.SIGKILL}, text
    assert '[bringup] stuck did not stop within 0.5 s: its threads follow' in text, text
    assert 'in stuck_in_shutdown' in text, text
