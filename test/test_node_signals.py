"""What a node's exit says (cdmp_ros.common.node_signals.teardown_hang): the stop backstop
ending a hang inside rclpy's middleware teardown after close() returned, told apart from every
other non-zero exit by the node's own stack dump.

The dumps are faulthandler's format; the first is the adapter's, as captured by
scripts/repro_sim_stop.py (2026-12-08), with the paths shortened.
"""
import io

from cdmp_ros.cli.cmd_bringup import Bringup, parse_graph
from cdmp_ros.common.node_signals import EXIT_BACKSTOP, teardown_hang

WATCHDOG = '''Thread 0x00007f1ec11466c0 (most recent call first):
  File "/w/cdmp_ros/ros/node_main.py", line 120 in _watch_stop
  File "/py/lib/python3.11/threading.py", line 982 in run
  File "/py/lib/python3.11/threading.py", line 1045 in _bootstrap_inner
  File "/py/lib/python3.11/threading.py", line 1002 in _bootstrap
'''
ENTRY = '''  File "/w/cdmp_ros/nodes/adapter.py", line 23 in main
  File "/w/cdmp_ros/nodes/adapter.py", line 27 in <module>
  File "<frozen runpy>", line 88 in _run_code
  File "<frozen runpy>", line 198 in _run_module_as_main
'''
RUN_NODE = '  File "/w/cdmp_ros/ros/node_main.py", line 268 in run_node\n'


def dump(*main_frames, header='Timeout (0:00:05)!\n', current=''):
    """A backstop dump: the watchdog thread, then the main thread with ``main_frames`` (most
    recent first) above run_node and the executable's entry."""
    return (header + WATCHDOG + '\n' + f'{current}Thread 0x00007f1ec1dfd4c0 (most recent call '
            'first):\n' + ''.join(main_frames) + RUN_NODE + ENTRY)


IN_RCLPY = ('  File "/w/.venv/lib/python3.11/site-packages/rclpy/node.py", line 1965 in '
            'destroy_node\n')
REAL = ('[INFO] [1796686645.246576420] [adapter]: adapting primitives from /primitive to '
        '/adapted_primitive\n' + dump(IN_RCLPY))


def test_the_captured_dump_of_a_hang_in_rclpys_destroy_node_is_one():
    assert teardown_hang(EXIT_BACKSTOP, REAL)


def test_only_the_backstops_exit_code_counts():
    assert not teardown_hang(0, REAL)       # a clean stop needs no excuse
    assert not teardown_hang(3, REAL)       # the watchdog's "main loop stuck"
    assert not teardown_hang(-9, REAL)      # SIGKILL


def test_every_teardown_call_of_run_node_counts_and_nothing_else():
    for call in ('remove_node', 'shutdown', 'destroy_node', 'try_shutdown'):
        frame = f'  File "/w/site-packages/rclpy/executors.py", line 1 in {call}\n'
        assert teardown_hang(EXIT_BACKSTOP, dump(frame)), call
    # rclpy deeper than the call run_node made: still inside rclpy
    deeper = '  File "/w/site-packages/rclpy/impl/x.py", line 5 in _fini\n'
    assert teardown_hang(EXIT_BACKSTOP, dump(deeper, IN_RCLPY))
    # the spin loop is not the teardown
    spin = '  File "/w/site-packages/rclpy/executors.py", line 1 in spin_once\n'
    assert not teardown_hang(EXIT_BACKSTOP, dump(spin))


def test_a_hang_in_the_nodes_own_code_is_not_one():
    own_close = '  File "/w/cdmp_ros/ros/learner_node.py", line 380 in close\n'
    assert not teardown_hang(EXIT_BACKSTOP, dump(own_close))
    # the node's own destroy_node override, or own code called from rclpy's teardown
    own = '  File "<string>", line 40 in hang_holding_the_gil\n'
    override = '  File "<string>", line 70 in destroy_node\n'
    assert not teardown_hang(EXIT_BACKSTOP, dump(own, override))
    assert not teardown_hang(EXIT_BACKSTOP, dump(own, IN_RCLPY))


def test_without_the_backstops_header_or_the_main_stack_it_is_not_one():
    assert not teardown_hang(EXIT_BACKSTOP, dump(IN_RCLPY, header=''))
    assert not teardown_hang(EXIT_BACKSTOP, 'Timeout (0:00:05)!\n' + WATCHDOG)   # cut short
    assert not teardown_hang(EXIT_BACKSTOP, '')
    # the main thread's stack without the run_node frame (not a node of run_node)
    assert not teardown_hang(EXIT_BACKSTOP, dump(IN_RCLPY).replace(RUN_NODE, ''))


def test_the_last_dump_decides():
    """A SIGUSR1 dump (the main thread marked "Current thread") of a spin-loop stack, then the
    backstop's: the backstop's is read; and the other way round it is not one."""
    spin = '  File "/w/site-packages/rclpy/executors.py", line 1 in spin_once\n'
    earlier = dump(spin, header='', current='Current ')
    assert teardown_hang(EXIT_BACKSTOP, earlier + '\n' + REAL)
    assert not teardown_hang(EXIT_BACKSTOP, REAL + '\n' + dump(spin))
    # fractional timeouts in the header (the first part of a stop arms the rest of its bound)
    assert teardown_hang(EXIT_BACKSTOP, dump(IN_RCLPY, header='Timeout (0:00:04.987000)!\n'))


class _Exited:
    """A finished process as Bringup sees it."""
    def __init__(self, code):
        self.returncode = code

    def poll(self):
        return self.returncode


def test_bringup_names_the_nodes_whose_teardown_hung_from_their_output():
    graph = parse_graph({'nodes': [{'name': 'learner', 'executable': 'learner'},
                                   {'name': 'sim', 'executable': 'sim'},
                                   {'name': 'adapter', 'executable': 'adapter'}]})
    out = io.StringIO()
    b = Bringup(graph, log=out)
    b.procs = {'learner': _Exited(EXIT_BACKSTOP), 'sim': _Exited(0),
               'adapter': _Exited(EXIT_BACKSTOP)}
    b._pump('learner', io.StringIO(REAL))
    b._pump('sim', io.StringIO('[INFO] [sim]: stopped\n'))
    b._pump('adapter', io.StringIO(dump('  File "/w/cdmp_ros/ros/adapter_node.py", line 9 in '
                                        'close\n')))
    assert b.teardown_hangs() == ['learner']
    assert '[learner] Timeout (0:00:05)!' in out.getvalue()   # the output still reaches the log


class _FakeBringup:
    """A Bringup whose nodes have already ended with ``CODES``, ``HUNG`` of them by the
    teardown hang (what run_graph decides its exit code from)."""
    CODES, HUNG, READY = {}, [], True

    def __init__(self, graph, log=None):
        self.env = {'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST'}
        self.ready, self.procs = {}, {}

    def start(self):
        pass

    def wait_ready(self, timeout, stop):
        return None if self.READY else 'timeout'

    def not_ready(self):
        return [] if self.READY else ['streamer']

    def wait(self, stop, timeout):
        return None

    def stop(self, sig):
        return dict(self.CODES)

    def teardown_hangs(self):
        return list(self.HUNG)


def test_bringups_exit_code_tells_a_teardown_hang_from_a_failure(monkeypatch, tmp_path):
    from cdmp_ros.cli import cmd_bringup
    graph = tmp_path / 'g.yaml'
    graph.write_text('nodes:\n  - {name: sim, executable: sim}\n'
                     '  - {name: learner, executable: learner}\n')
    monkeypatch.setattr(cmd_bringup, 'Bringup', _FakeBringup)

    def run(codes, hung, ready=True):
        monkeypatch.setattr(_FakeBringup, 'CODES', codes)
        monkeypatch.setattr(_FakeBringup, 'HUNG', hung)
        monkeypatch.setattr(_FakeBringup, 'READY', ready)
        out = io.StringIO()
        return cmd_bringup.run_graph(str(graph), duration=0.0, log=out, wait_ready=1.0), \
            out.getvalue()

    code, text = run({'sim': 0, 'learner': 0}, [])
    assert code == 0 and 'all nodes stopped cleanly' in text
    code, text = run({'sim': 0, 'learner': EXIT_BACKSTOP}, ['learner'])
    assert code == cmd_bringup.TEARDOWN_HANG_EXIT_CODE == 4, text
    assert cmd_bringup.TEARDOWN_HANG_LINE.format(nodes='learner') in text
    assert "nodes that did not stop cleanly: {'learner': 1}" in text
    code, text = run({'sim': 2, 'learner': EXIT_BACKSTOP}, ['learner'])   # sim failed
    assert code == 1, text
    code, text = run({'sim': 0, 'learner': EXIT_BACKSTOP}, [])            # not recognised
    assert code == 1 and 'teardown hung' not in text, text
    code, text = run({'sim': 0, 'learner': EXIT_BACKSTOP}, ['learner'], ready=False)
    assert code == cmd_bringup.NOT_READY_EXIT_CODE, text
