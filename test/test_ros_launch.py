"""The launch files (launch/*.launch.py) and the topic table of docs/nodes.md, checked without ROS.

``launch`` / ``launch_ros`` are not installable here, so each launch file is executed with small
stand-ins for the modules it imports (:func:`stub_modules`): they accept exactly the keyword
arguments of the Jazzy API and record them. :func:`evaluate` then plays the launch description
as ``ros2 launch`` would (arguments with their defaults or overrides, conditions, namespaces,
included files) and returns the nodes it would start: package, executable, name, namespace,
parameter files, parameter overrides and remappings. The tests compare those with setup.py
(console scripts, installed files) and with ``config/graphs/demo.yaml`` (``cdmp bringup``).

The topic and service tables of docs/nodes.md (section "Topics and services") are compared with
the publishers, subscriptions and services the node classes create (found with ``ast`` in
``cdmp_ros/ros/``, QoS profiles evaluated in their module), so neither can change without the
other.
"""
import ast
import glob
import os
import re
import runpy
import sys
import types

import pytest
import yaml

from cdmp_ros.cli.cmd_bringup import load_graph, package_config_dir

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
LAUNCH_DIR = os.path.join(ROOT, 'launch')
#: What the stand-in of get_package_share_directory('cdmp_ros') returns.
SHARE = '/opt/ros/share-of/cdmp_ros'
LAUNCH_FILES = sorted(os.path.basename(f) for f in glob.glob(os.path.join(LAUNCH_DIR, '*.py')))
#: Modules a launch file may import (the standard Jazzy launch API and the ament index).
ALLOWED_IMPORTS = {'os', 'launch', 'launch.actions', 'launch.conditions',
                   'launch.substitutions', 'launch.launch_description_sources',
                   'launch_ros.actions', 'launch_ros.parameter_descriptions',
                   'ament_index_python.packages'}


# -- setup.py ----------------------------------------------------------------------------------
def setup_kwargs():
    """The keyword arguments setup.py passes to ``setuptools.setup`` (run in the source tree)."""
    import setuptools
    captured = {}
    saved, cwd = setuptools.setup, os.getcwd()
    setuptools.setup = lambda **kw: captured.update(kw)
    try:
        os.chdir(ROOT)
        runpy.run_path(os.path.join(ROOT, 'setup.py'), run_name='__main__')
    finally:
        setuptools.setup = saved
        os.chdir(cwd)
    return captured


def installed_files():
    """Install path (``share/cdmp_ros/...``) -> source path, from setup.py ``data_files``."""
    out = {}
    for dest, files in setup_kwargs()['data_files']:
        for f in files:
            out[os.path.join(dest, os.path.basename(f))] = os.path.join(ROOT, f)
    return out


def console_scripts():
    return {e.split('=')[0].strip()
            for e in setup_kwargs()['entry_points']['console_scripts']}


# -- stand-ins for launch / launch_ros / ament_index_python ------------------------------------
class Substitution:
    """Base of the substitution stand-ins."""


class LaunchConfiguration(Substitution):
    def __init__(self, variable_name, *, default=None):
        self.variable_name = variable_name
        self.default = default

    def perform(self, context):
        return resolve(self, context.launch_configurations)


class LaunchContext:
    """What an OpaqueFunction's function receives: the launch configurations in force."""

    def __init__(self, launch_configurations):
        self.launch_configurations = launch_configurations

    def perform_substitution(self, substitution):
        return resolve(substitution, self.launch_configurations)


class LaunchDescription:
    def __init__(self, initial_entities=None, *, deprecated_reason=None):
        self.entities = list(initial_entities or [])

    def add_action(self, action):
        self.entities.append(action)


class Action:
    def __init__(self, *, condition=None):
        self.condition = condition


class DeclareLaunchArgument(Action):
    def __init__(self, name, *, default_value=None, description=None, choices=None, **kwargs):
        super().__init__(**kwargs)
        self.name, self.default_value = name, default_value
        self.description, self.choices = description, choices


class GroupAction(Action):
    def __init__(self, actions, *, scoped=True, forwarding=True, launch_configurations=None,
                 **kwargs):
        super().__init__(**kwargs)
        self.actions, self.scoped = list(actions), scoped
        self.launch_configurations = launch_configurations or {}


class OpaqueFunction(Action):
    def __init__(self, *, function, args=None, kwargs=None, **left_over_kwargs):
        super().__init__(**left_over_kwargs)
        if not callable(function):
            raise TypeError('OpaqueFunction(function=...) must be callable')
        self.function, self.args, self.kwargs = function, list(args or []), dict(kwargs or {})


class IncludeLaunchDescription(Action):
    def __init__(self, launch_description_source, *, launch_arguments=None, **kwargs):
        super().__init__(**kwargs)
        self.source = launch_description_source
        self.launch_arguments = list(launch_arguments or [])


class PythonLaunchDescriptionSource:
    def __init__(self, launch_file_path):
        self.path = launch_file_path


class IfCondition:
    negate = False

    def __init__(self, predicate_expression):
        self.predicate = predicate_expression

    def evaluate(self, configs):
        value = resolve(self.predicate, configs).strip().lower()
        if value not in ('true', 'false', '1', '0'):
            raise AssertionError(f'condition on {value!r}: launch expects true/false/1/0')
        return (value in ('true', '1')) != self.negate


class UnlessCondition(IfCondition):
    negate = True


#: The keyword arguments launch_ros.actions.Node passes on to launch.actions.ExecuteProcess.
EXECUTE_PROCESS_KWARGS = {'condition', 'output', 'emulate_tty', 'respawn', 'respawn_delay',
                          'sigterm_timeout', 'sigkill_timeout', 'additional_env', 'env', 'cwd',
                          'prefix', 'shell', 'log_cmd', 'on_exit', 'cached_output'}


class Node(Action):
    def __init__(self, *, executable, package=None, name=None, namespace=None, exec_name=None,
                 parameters=None, remappings=None, ros_arguments=None, arguments=None,
                 **kwargs):
        unknown = set(kwargs) - EXECUTE_PROCESS_KWARGS
        if unknown:
            raise TypeError(f'Node() got unexpected keyword arguments {sorted(unknown)}')
        super().__init__(condition=kwargs.get('condition'))
        if parameters is not None and not isinstance(parameters, list):
            raise TypeError('Node(parameters=...) must be a list')
        self.executable, self.package, self.name = executable, package, name
        self.namespace, self.parameters = namespace, parameters or []
        self.remappings = list(remappings or [])
        self.ros_arguments, self.arguments = ros_arguments, arguments


class PushRosNamespace(Action):
    def __init__(self, namespace, **kwargs):
        super().__init__(**kwargs)
        self.namespace = namespace


class ParameterValue:
    def __init__(self, value, *, value_type=None):
        self.value, self.value_type = value, value_type


def get_package_share_directory(package_name):
    if package_name != 'cdmp_ros':
        raise LookupError(f'package {package_name!r} not found (only cdmp_ros is expected)')
    return SHARE


def stub_modules():
    """sys.modules entries for the modules a launch file imports."""
    def module(name, **attrs):
        m = types.ModuleType(name)
        m.__dict__.update(attrs)
        return m
    mods = {
        'launch.actions': module('launch.actions', DeclareLaunchArgument=DeclareLaunchArgument,
                                 GroupAction=GroupAction,
                                 IncludeLaunchDescription=IncludeLaunchDescription,
                                 OpaqueFunction=OpaqueFunction),
        'launch.substitutions': module('launch.substitutions',
                                       LaunchConfiguration=LaunchConfiguration),
        'launch.conditions': module('launch.conditions', IfCondition=IfCondition,
                                    UnlessCondition=UnlessCondition),
        'launch.launch_description_sources': module(
            'launch.launch_description_sources',
            PythonLaunchDescriptionSource=PythonLaunchDescriptionSource),
        'launch_ros.actions': module('launch_ros.actions', Node=Node,
                                     PushRosNamespace=PushRosNamespace),
        'launch_ros.parameter_descriptions': module('launch_ros.parameter_descriptions',
                                                    ParameterValue=ParameterValue),
        'ament_index_python.packages': module(
            'ament_index_python.packages',
            get_package_share_directory=get_package_share_directory),
    }
    mods['launch'] = module('launch', LaunchDescription=LaunchDescription,
                            actions=mods['launch.actions'],
                            substitutions=mods['launch.substitutions'],
                            conditions=mods['launch.conditions'],
                            launch_description_sources=mods['launch.launch_description_sources'])
    mods['launch_ros'] = module('launch_ros', actions=mods['launch_ros.actions'],
                                parameter_descriptions=mods['launch_ros.parameter_descriptions'])
    mods['ament_index_python'] = module('ament_index_python',
                                        packages=mods['ament_index_python.packages'])
    return mods


# -- playing a launch description --------------------------------------------------------------
def resolve(value, configs):
    """A substitution (or a list of them, or a plain value) as launch would expand it."""
    if isinstance(value, LaunchConfiguration):
        if value.variable_name in configs:
            return configs[value.variable_name]
        if value.default is not None:
            return resolve(value.default, configs)
        raise AssertionError(f'LaunchConfiguration {value.variable_name!r} is not declared')
    if isinstance(value, (list, tuple)) and value and all(
            isinstance(v, (str, Substitution)) for v in value) and any(
            isinstance(v, Substitution) for v in value):
        return ''.join(resolve(v, configs) for v in value)
    if isinstance(value, Substitution):
        raise AssertionError(f'unsupported substitution {type(value).__name__}')
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    return value


def parameter_value(value, configs):
    """A value of a parameter dict as the node receives it (launch_ros evaluate_parameters)."""
    if isinstance(value, ParameterValue):
        text = resolve(value.value, configs)
        if value.value_type is None:
            return yaml.safe_load(text) if isinstance(text, str) else text
        return value.value_type(text)
    if isinstance(value, Substitution):
        return yaml.safe_load(resolve(value, configs))
    if isinstance(value, (list, tuple)):
        return [parameter_value(v, configs) for v in value]
    return value


def flatten(params, prefix=''):
    out = {}
    for k, v in params.items():
        if isinstance(v, dict):
            out.update(flatten(v, f'{prefix}{k}.'))
        else:
            out[f'{prefix}{k}'] = v
    return out


def join_namespace(base, ns):
    """launch_ros prefix_namespace + make_namespace_absolute."""
    ns = ns or ''
    combined = ns if (not base or ns.startswith('/')) else base.rstrip('/') + '/' + ns
    combined = '/' + combined.lstrip('/')
    return combined if combined == '/' else combined.rstrip('/')


def share_to_source(path, installed):
    """The source file of an installed share/cdmp_ros path (AssertionError if not installed)."""
    assert path.startswith(SHARE + '/'), f'{path!r} is not under the package share directory'
    rel = os.path.join('share', 'cdmp_ros', os.path.relpath(path, SHARE))
    assert rel in installed, f'{rel} is not installed by setup.py'
    src = installed[rel]
    assert os.path.isfile(src), f'{src} (installed as {rel}) does not exist'
    return src


class Played:
    """What playing a launch file declares and starts."""

    def __init__(self):
        self.arguments = {}   # name -> DeclareLaunchArgument (every file)
        self.nodes = []       # dicts, see _node


def launch_module(path, monkeypatch):
    """The globals of a launch file run with the stand-ins."""
    for name, mod in stub_modules().items():
        monkeypatch.setitem(sys.modules, name, mod)
    return runpy.run_path(path)


def load_description(path, monkeypatch):
    g = launch_module(path, monkeypatch)
    ld = g['generate_launch_description']()
    assert isinstance(ld, LaunchDescription), f'{path}: not a LaunchDescription'
    return ld


def evaluate(file, monkeypatch, arguments=None):
    """Play ``launch/<file>`` with command-line ``arguments`` (name -> string)."""
    installed = installed_files()
    played = Played()

    def visit(entities, configs, scope):
        for e in entities:
            if e.condition is not None and not e.condition.evaluate(configs):
                continue
            if isinstance(e, DeclareLaunchArgument):
                played.arguments.setdefault(e.name, e)
                if e.name not in configs:
                    assert e.default_value is not None, f'argument {e.name!r} has no default'
                    configs[e.name] = resolve(e.default_value, configs)
                if e.choices is not None:
                    assert configs[e.name] in e.choices, \
                        f'{e.name}:={configs[e.name]!r} is not one of {e.choices}'
            elif isinstance(e, GroupAction):
                inner = dict(configs) if e.scoped else configs
                inner.update({k: resolve(v, configs)
                              for k, v in e.launch_configurations.items()})
                visit(e.actions, inner, dict(scope) if e.scoped else scope)
            elif isinstance(e, PushRosNamespace):
                scope['ns'] = join_namespace(scope.get('ns'), resolve(e.namespace, configs))
            elif isinstance(e, IncludeLaunchDescription):
                assert isinstance(e.source, PythonLaunchDescriptionSource)
                src = share_to_source(resolve(e.source.path, configs), installed)
                for k, v in e.launch_arguments:
                    configs[resolve(k, configs)] = resolve(v, configs)
                visit(load_description(src, monkeypatch).entities, configs, scope)
            elif isinstance(e, OpaqueFunction):  # its actions run in the same scope
                out = e.function(LaunchContext(configs), *e.args, **e.kwargs)
                visit(out or [], configs, scope)
            elif isinstance(e, Node):
                played.nodes.append(_node(e, configs, scope, installed))
            else:
                raise AssertionError(f'unexpected launch entity {type(e).__name__}')

    ld = load_description(os.path.join(LAUNCH_DIR, file), monkeypatch)
    visit(ld.entities, dict(arguments or {}), {})
    return played


def _node(e, configs, scope, installed):
    files, params = [], {}
    for p in e.parameters:
        if isinstance(p, dict):
            params.update(flatten({k: parameter_value(v, configs) for k, v in p.items()}))
        else:
            files.append(os.path.relpath(share_to_source(resolve(p, configs), installed),
                                         os.path.join(ROOT, 'config')))
    ns = join_namespace(scope.get('ns'), resolve(e.namespace, configs))
    return {'package': resolve(e.package, configs), 'executable': resolve(e.executable, configs),
            'name': resolve(e.name, configs), 'namespace': ns, 'params_files': files,
            'parameters': params,
            'remappings': {resolve(a, configs): resolve(b, configs) for a, b in e.remappings}}


def by_name(played):
    names = [n['name'] for n in played.nodes]
    assert len(names) == len(set(names)), f'duplicate node names {names}'
    return {n['name']: n for n in played.nodes}


# -- the launch files --------------------------------------------------------------------------
def test_launch_files_exist_and_are_installed():
    assert {'cdmp.launch.py', 'demo.launch.py'} <= set(LAUNCH_FILES)
    installed = installed_files()
    for f in LAUNCH_FILES:
        assert f.endswith('.launch.py'), f'{f}: launch files are named <graph>.launch.py'
        assert os.path.join('share', 'cdmp_ros', 'launch', f) in installed, \
            f'launch/{f} is not installed into share/cdmp_ros/launch by setup.py'


def test_package_xml_declares_the_launch_dependencies():
    from catkin_pkg.package import parse_package
    deps = {d.name for d in parse_package(os.path.join(ROOT, 'package.xml')).exec_depends}
    assert {'launch', 'launch_ros', 'ament_index_python'} <= deps


@pytest.mark.parametrize('file', LAUNCH_FILES)
def test_launch_file_imports_only_the_standard_api(file):
    tree = ast.parse(open(os.path.join(LAUNCH_DIR, file)).read())
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            names = [node.module]
        else:
            continue
        for name in names:
            assert name in ALLOWED_IMPORTS, f'{file} imports {name}'


@pytest.mark.parametrize('file', LAUNCH_FILES)
def test_launch_file_nodes_arguments_and_parameter_files(file, monkeypatch):
    played = evaluate(file, monkeypatch)
    assert played.nodes, f'{file} starts no node'
    scripts = console_scripts()
    for n in played.nodes:
        assert n['package'] == 'cdmp_ros'
        assert n['executable'] in scripts, f'{file}: {n["executable"]} is not a console script'
        assert n['params_files'], f'{file}: node {n["name"]} has no parameter file'
    for name, arg in played.arguments.items():
        assert arg.default_value is not None, f'{file}: argument {name} has no default'
        assert isinstance(arg.description, str) and len(arg.description) > 10, \
            f'{file}: argument {name} has no description'


def test_cdmp_launch_default_graph(monkeypatch):
    played = evaluate('cdmp.launch.py', monkeypatch)
    assert {'robot', 'rate', 'namespace', 'use_sim', 'robot_description'} <= set(played.arguments)
    nodes = by_name(played)
    assert set(nodes) == {'sim', 'streamer', 'adapter', 'learner'}
    for name, n in nodes.items():
        assert n['executable'] == name
        assert n['params_files'] == [f'{name}.yaml']
        assert n['namespace'] == '/'
        assert n['remappings'] == {}
    assert nodes['streamer']['parameters'] == {'rate': 500.0, 'robot_description': ''}
    assert nodes['sim']['parameters'] == {'robot': 'panda', 'robot_description': ''}
    assert nodes['adapter']['parameters'] == nodes['learner']['parameters'] == {
        'robot_description': ''}
    # the defaults are those of the parameter files
    assert yaml.safe_load(open(os.path.join(ROOT, 'config', 'streamer.yaml')))[
        '/**']['ros__parameters']['rate'] == 500.0
    for name in nodes:
        assert yaml.safe_load(open(os.path.join(ROOT, 'config', f'{name}.yaml')))[
            '/**']['ros__parameters'].get('robot_description', '') == ''


def test_cdmp_launch_arguments(monkeypatch):
    played = evaluate('cdmp.launch.py', monkeypatch, {
        'robot': 'planar4', 'rate': '1000', 'namespace': 'arm', 'use_sim': 'true',
        'learner_params': SHARE + '/config/adapter.yaml', 'robot_description': '<robot/>'})
    nodes = by_name(played)
    assert nodes['sim']['parameters'] == {'robot': 'planar4', 'robot_description': '<robot/>'}
    assert nodes['streamer']['parameters'] == {'rate': 1000.0, 'robot_description': '<robot/>'}
    assert {n['parameters']['robot_description'] for n in nodes.values()} == {'<robot/>'}
    assert isinstance(nodes['streamer']['parameters']['rate'], float)
    assert {n['namespace'] for n in nodes.values()} == {'/arm'}
    assert nodes['learner']['params_files'] == ['adapter.yaml', 'robots/planar4/learner.yaml']
    real = by_name(evaluate('cdmp.launch.py', monkeypatch, {'use_sim': 'false'}))
    assert set(real) == {'streamer', 'adapter', 'learner'}
    with pytest.raises(AssertionError, match='not one of'):
        evaluate('cdmp.launch.py', monkeypatch, {'use_sim': 'maybe'})


@pytest.mark.parametrize('robot', ['planar4', 'dual_panda'])
def test_cdmp_launch_robot_layers_its_files_over_the_nodes_files(monkeypatch, robot):
    """robot:=planar4 or dual_panda: every node gets config/<node>.yaml, then
    config/robots/<robot>/<node>.yaml (ROS applies them in order, the later wins); the Panda
    gets its node's file alone (or the user's <node>_params)."""
    nodes = by_name(evaluate('cdmp.launch.py', monkeypatch, {'robot': robot}))
    assert set(nodes) == {'sim', 'streamer', 'adapter', 'learner'}
    for name, n in nodes.items():
        assert n['params_files'] == [f'{name}.yaml', f'robots/{robot}/{name}.yaml'], name
    assert nodes['sim']['parameters']['robot'] == robot
    for name, n in by_name(evaluate('cdmp.launch.py', monkeypatch, {'robot': 'panda'})).items():
        assert n['params_files'] == [f'{name}.yaml'], name
    # the robots the launch file layers are those with a directory in config/robots, and each
    # has a file for every node the launch file starts
    launch = launch_module(os.path.join(LAUNCH_DIR, 'cdmp.launch.py'), monkeypatch)
    robots_dir = os.path.join(ROOT, 'config', 'robots')
    assert sorted(launch['ROBOT_OVERLAYS']) == sorted(os.listdir(robots_dir))
    for robot in launch['ROBOT_OVERLAYS']:
        assert sorted(os.listdir(os.path.join(robots_dir, robot))) == sorted(
            launch['PARAMS'].values()), robot


@pytest.mark.parametrize('robot', ['planar4', 'dual_panda'])
def test_the_robots_graph_is_cdmp_launch_with_that_robot(monkeypatch, robot):
    """config/graphs/<robot>.yaml (``cdmp bringup <robot>``) starts the nodes of
    ``cdmp.launch.py robot:=<robot>`` with the same parameter files in the same order."""
    graph = graph_nodes(os.path.join(ROOT, 'config', 'graphs', f'{robot}.yaml'))
    launched = by_name(evaluate('cdmp.launch.py', monkeypatch, {'robot': robot}))
    assert set(graph) == set(launched)
    for name, n in launched.items():
        for key in ('executable', 'namespace', 'params_files', 'remappings'):
            assert graph[name][key] == n[key], (name, key)


def graph_nodes(path):
    """The nodes of a bringup graph file in the form of :func:`_node`."""
    config = package_config_dir()
    out = {}
    for s in load_graph(path).nodes:
        out[s.name] = {'package': 'cdmp_ros', 'executable': s.executable, 'name': s.name,
                       'namespace': join_namespace(None, s.namespace),
                       'params_files': [os.path.relpath(f, config) for f in s.params_files],
                       'parameters': dict(s.parameters), 'remappings': dict(s.remappings)}
    return out


def assert_same_graph(launched, graph):
    assert set(launched) == set(graph), 'the launch file and the graph start different nodes'
    for name in graph:
        for key in ('executable', 'namespace', 'params_files', 'remappings', 'parameters'):
            a, b = launched[name][key], graph[name][key]
            assert a == b, f'node {name}: {key} {a!r} in the launch file, {b!r} in the graph'
            if key == 'parameters':
                for k in a:
                    assert type(a[k]) is type(b[k]), f'node {name}: parameter {k} type'


def test_demo_launch_is_the_demo_graph(monkeypatch):
    demo = os.path.join(ROOT, 'config', 'graphs', 'demo.yaml')
    assert_same_graph(by_name(evaluate('demo.launch.py', monkeypatch)), graph_nodes(demo))


def test_cdmp_launch_starts_the_demo_graph_without_the_recorder(monkeypatch):
    demo = graph_nodes(os.path.join(ROOT, 'config', 'graphs', 'demo.yaml'))
    for name, n in by_name(evaluate('cdmp.launch.py', monkeypatch)).items():
        assert demo[name]['executable'] == n['executable']
        assert demo[name]['params_files'] == n['params_files']
    assert set(demo) - set(by_name(evaluate('cdmp.launch.py', monkeypatch))) == {'recorder'}


def test_graph_comparison_detects_a_difference(monkeypatch, tmp_path):
    """The comparison above fails when the launch file and the graph differ."""
    text = open(os.path.join(ROOT, 'config', 'graphs', 'demo.yaml')).read()
    assert 'rate: 500.0' in text
    changed = tmp_path / 'demo.yaml'
    changed.write_text(text.replace('rate: 500.0', 'rate: 400.0'))
    launched = by_name(evaluate('demo.launch.py', monkeypatch))
    with pytest.raises(AssertionError, match='parameters'):
        assert_same_graph(launched, graph_nodes(str(changed)))
    graph = graph_nodes(os.path.join(ROOT, 'config', 'graphs', 'demo.yaml'))
    graph['recorder']['remappings'] = {'joint_states': '/arm/joint_states'}
    with pytest.raises(AssertionError, match='remappings'):
        assert_same_graph(launched, graph)


# -- the topic table of docs/nodes.md ------------------------------------------------------------
#: Node classes of cdmp_ros/ros -> executable. Classes creating topics that are not listed here
#: fail the test (add them here and to the table of docs/nodes.md).
NODE_CLASSES = {'SimNode': 'sim', 'StreamerNode': 'streamer', 'AdapterNode': 'adapter',
                'LearnerNode': 'learner', 'RecorderNode': 'recorder', 'PlayerNode': 'player'}
#: Not product executables: the scripted user of ``cdmp demo``; the input gate's generic
#: subscriptions (its callers' ``gate.subscribe(type, topic, callback, qos)`` and
#: ``gate.subscribe_polled(...)`` are read instead).
IGNORED_CLASSES = {'DemoDriver', 'InputGate'}
#: Nodes whose topics are only known at run time (the bag's or the graph's topics); docs/nodes.md
#: describes their QoS rule in prose.
DYNAMIC_NODES = {'recorder', 'player'}
CREATE = {'create_publisher': 'publishes', 'create_subscription': 'subscribes',
          'subscribe': 'subscribes', 'subscribe_polled': 'subscribes',
          'create_service': 'service'}


def _message_name(cls):
    """``sensor_msgs/JointState`` for the class ``sensor_msgs.msg.JointState``."""
    return f'{cls.__module__.split(".")[0]}/{cls.__name__}'


def _qos_tuple(qos):
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, ReliabilityPolicy
    assert qos.history == HistoryPolicy.KEEP_LAST, f'{qos}: expected keep last'
    rel = {ReliabilityPolicy.RELIABLE: 'reliable',
           ReliabilityPolicy.BEST_EFFORT: 'best effort'}[qos.reliability]
    dur = {DurabilityPolicy.VOLATILE: 'volatile',
           DurabilityPolicy.TRANSIENT_LOCAL: 'transient local'}[qos.durability]
    return rel, dur, int(qos.depth)


def local_imports(tree, known):
    """Names bound by ``from X import Y [as Z]`` inside functions of ``tree``."""
    out = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.col_offset > 0:
            for alias in node.names:
                name = alias.asname or alias.name
                if name not in known:
                    module = __import__(node.module, fromlist=[alias.name])
                    out[name] = getattr(module, alias.name)
    return out


def code_endpoints():
    """``(topics, services)`` the node classes of cdmp_ros/ros create.

    topics: set of (topic, type, node, role, reliability, durability, depth); services: set of
    (name, type, node). Topic names, types and QoS are evaluated in the module's namespace;
    a name bound by a ``for`` loop over a module constant gives one entry per value.
    """
    topics, services = set(), set()
    for path in sorted(glob.glob(os.path.join(ROOT, 'cdmp_ros', 'ros', '*.py'))):
        tree = ast.parse(open(path).read())
        calls = []
        parents = {}
        for node in ast.walk(tree):
            for child in ast.iter_child_nodes(node):
                parents[child] = node
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and \
                    node.func.attr in CREATE:
                calls.append(node)
        if not calls:
            continue
        module = __import__(
            'cdmp_ros.ros.' + os.path.basename(path)[:-3], fromlist=['_'])
        namespace = dict(vars(module))
        namespace.update(local_imports(tree, namespace))
        for call in calls:
            where = f'{os.path.relpath(path, ROOT)}:{call.lineno}'
            enclosing, loops = call, {}
            cls = None
            while enclosing in parents:
                enclosing = parents[enclosing]
                if isinstance(enclosing, ast.For) and isinstance(enclosing.target, ast.Name):
                    loops.setdefault(enclosing.target.id, enclosing.iter)
                if isinstance(enclosing, ast.ClassDef):
                    cls = enclosing.name
                    break
            if cls in IGNORED_CLASSES:
                continue
            assert cls in NODE_CLASSES, \
                f'{where}: {call.func.attr} in {cls or "no class"}; add it to NODE_CLASSES'
            node = NODE_CLASSES[cls]
            role = CREATE[call.func.attr]

            def value(expr):
                if isinstance(expr, ast.Name) and expr.id in loops:
                    return list(eval(compile(ast.Expression(loops[expr.id]), where, 'eval'),
                                     namespace))
                return [eval(compile(ast.Expression(expr), where, 'eval'), namespace)]
            try:
                types_ = value(call.args[0])
                try:
                    names = value(call.args[1])
                except NameError:
                    # a topic named by a parameter, read as an attribute (``self.X`` or
                    # ``cfg.X``): docs/nodes.md lists it as ``<X>``
                    if not isinstance(call.args[1], ast.Attribute):
                        raise
                    names = [f'<{call.args[1].attr}>']
                qos_expr = None
                if role != 'service':
                    kw = {k.arg: k.value for k in call.keywords}
                    qos_expr = call.args[2 if role == 'publishes' else 3] \
                        if len(call.args) > (2 if role == 'publishes' else 3) \
                        else kw.get('qos_profile', kw.get('qos'))
                    qos = value(qos_expr)
            except NameError as exc:  # a local variable: known only at run time
                assert node in DYNAMIC_NODES, (
                    f'{where}: {node} {role} with a type, name or QoS known only at run time '
                    f'({exc}); a topic name taken from a parameter is read from an attribute '
                    f'(self.X = the parameter value; create_publisher(T, self.X, qos)) and '
                    f'listed in the table of docs/nodes.md as <X>')
                continue
            for msg_type in types_:
                for name in names:
                    if role == 'service':
                        services.add((name, _message_name(msg_type), node))
                    else:
                        for q in qos:
                            topics.add((name, _message_name(msg_type), node, role,
                                        *_qos_tuple(q)))
    return topics, services


def readme_tables():
    """The topic and service tables of the section "Topics and services" of docs/nodes.md."""
    text = open(os.path.join(ROOT, 'docs', 'nodes.md')).read()
    section = text.split('### Topics and services', 1)
    assert len(section) == 2, 'docs/nodes.md has no "### Topics and services" section'
    section = section[1].split('\n#', 1)[0]
    tables, current = [], None
    for line in section.splitlines():
        if line.startswith('|'):
            cells = [c.strip().strip('`').strip() for c in line.strip().strip('|').split('|')]
            if current is None:
                current = {'header': cells, 'rows': []}
                tables.append(current)
            elif not set(''.join(cells)) <= set('-: '):
                current['rows'].append(dict(zip(current['header'], cells)))
        else:
            current = None
    by_first = {t['header'][0]: t for t in tables}
    assert {'topic', 'service'} <= set(by_first), f'tables found: {list(by_first)}'
    topics, services = set(), set()
    for row in by_first['topic']['rows']:
        depth = re.fullmatch(r'keep last (\d+)', row['history'])
        assert depth, f'docs/nodes.md topic {row["topic"]}: history {row["history"]!r}'
        assert row['role'] in ('publishes', 'subscribes'), row
        if row['role'] == 'publishes':
            assert row['rate'], f'docs/nodes.md topic {row["topic"]}: no rate for the publisher'
        for node in row['node'].split(','):
            topics.add((row['topic'], row['type'], node.strip(), row['role'],
                        row['reliability'], row['durability'], int(depth.group(1))))
    for row in by_first['service']['rows']:
        for node in row['node'].split(','):
            services.add((row['service'], row['type'].replace('/srv/', '/'), node.strip()))
    return topics, services


def test_readme_topic_table_matches_the_code():
    code_topics, code_services = code_endpoints()
    readme_topics, readme_services = readme_tables()
    assert {t[2] for t in code_topics} >= {'sim', 'streamer', 'adapter', 'learner'}
    missing = sorted(code_topics - readme_topics)
    stale = sorted(readme_topics - code_topics)
    assert not missing and not stale, (
        f'docs/nodes.md topic table out of date.\nIn the code, not in docs/nodes.md: {missing}\n'
        f'In docs/nodes.md, not in the code: {stale}')
    assert readme_services == code_services, (
        f'docs/nodes.md services: {sorted(readme_services ^ code_services)} differ from the code')


def test_readme_table_check_detects_a_difference():
    """The table parser really reads the QoS columns: a changed depth is seen."""
    readme_topics, _ = readme_tables()
    row = next(t for t in readme_topics if t[0] == 'joint_reference' and t[3] == 'publishes')
    assert row[4:] == ('reliable', 'volatile', 10)
    code_topics, _ = code_endpoints()
    assert row in code_topics
    assert (*row[:6], 11) not in code_topics
