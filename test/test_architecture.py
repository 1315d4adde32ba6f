"""The layer table of ../shared/design.md, enforced on the import statements of cdmp_ros
(module level and inside functions), and the import graph of cdmp_ros without a cycle.

| layer       | may import (besides the standard library)                        |
|-------------|------------------------------------------------------------------|
| common      | nothing else (standard library only; no other layer of cdmp_ros) |
| core        | common, numpy, scipy (+ jsonschema, yaml for file validation)    |
| sim         | core, pybullet, plotting                                          |
| bag         | core, mcap                                                        |
| ros         | everything above, rclpy, *_msgs                                   |
| nodes       | ros and below                                                     |
| cli, experiments | core, sim, bag, experiments, cli (start ROS nodes as processes) |

Every layer may import common. rclpy and message packages are used only by cdmp_ros/ros and
cdmp_ros/nodes. Inside the package nothing imports the public API of ``cdmp_ros/__init__.py``
(only ``__version__``): every module imports the module that defines a name.
"""
import ast
import os
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PKG = os.path.join(ROOT, 'cdmp_ros')

BASE = {'numpy', 'scipy', 'jsonschema', 'yaml'}
PLOT = {'matplotlib', 'PIL', 'tqdm'}
ROS_LIBS = {'rclpy', 'builtin_interfaces', 'rosidl_runtime_py', 'ament_index_python',
            'rosgraph_msgs', 'rcl_interfaces'}
ALLOWED_THIRD_PARTY = {
    'common': set(),
    'core': BASE,
    'sim': BASE | PLOT | {'pybullet', 'pybullet_data'},
    'bag': BASE | PLOT | {'mcap', 'mcap_ros2', 'zstandard', 'lz4'},
    'ros': None,  # anything
    'nodes': None,
    'cli': BASE | PLOT | {'pybullet', 'pybullet_data', 'mcap', 'mcap_ros2', 'psutil'},
    'experiments': BASE | PLOT | {'pybullet', 'pybullet_data', 'psutil'},
}
ALLOWED_INTERNAL = {
    'common': {'common'},
    'core': {'common', 'core'},
    'sim': {'common', 'core', 'sim'},
    'bag': {'common', 'core', 'bag'},
    'ros': {'common', 'core', 'sim', 'bag', 'ros'},
    'nodes': {'common', 'core', 'sim', 'bag', 'ros', 'nodes'},
    'cli': {'common', 'core', 'sim', 'bag', 'cli', 'experiments'},
    'experiments': {'common', 'core', 'sim', 'bag', 'experiments'},
}
STDLIB = set(sys.stdlib_module_names)


def _python_files():
    for dirpath, _, files in os.walk(PKG):
        for f in files:
            if f.endswith('.py'):
                yield os.path.join(dirpath, f)


def _layer(path):
    rel = os.path.relpath(path, PKG).split(os.sep)
    return rel[0] if len(rel) > 1 else None


def _imports(path):
    """(imported name, line) of every import of the file, module level and inside functions;
    ``from a import b`` gives ``a.b`` (a module or a name of ``a``; relative imports
    resolved against the file's package)."""
    tree = ast.parse(open(path).read(), filename=path)
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                yield a.name, node.lineno
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative import: resolve against the file's package
                rel = os.path.relpath(path, ROOT)[:-len('.py')].split(os.sep)
                base = rel[:len(rel) - node.level]
                module = '.'.join(base + ([node.module] if node.module else []))
            else:
                module = node.module
            for a in node.names:
                yield (module if a.name == '*' else f'{module}.{a.name}'), node.lineno


def _violations():
    out = []
    for path in _python_files():
        layer = _layer(path)
        if layer is None:
            continue
        assert layer in ALLOWED_INTERNAL, f'{path}: unknown layer {layer!r}; add it to the table'
        for name, line in _imports(path):
            top = name.split('.')[0]
            where = f'{os.path.relpath(path, ROOT)}:{line} imports {name}'
            if top == 'cdmp_ros':
                parts = name.split('.')
                if len(parts) > 1 and parts[1] in ALLOWED_INTERNAL:
                    if parts[1] not in ALLOWED_INTERNAL[layer]:
                        out.append(where + f' (layer {layer} may not import {parts[1]})')
                elif len(parts) > 1 and parts[1] != '__version__':
                    out.append(where + ' (the public API: import the defining module)')
                continue
            if top in STDLIB or top == '__future__':
                continue
            allowed = ALLOWED_THIRD_PARTY[layer]
            if allowed is None:
                continue
            is_ros = top in ROS_LIBS or top.endswith('_msgs') or top.endswith('_srvs')
            if is_ros or top not in allowed:
                out.append(where + f' (layer {layer} may not import {top})')
    return out


def _module_name(path):
    rel = os.path.relpath(path, ROOT)[:-len('.py')].split(os.sep)
    return '.'.join(rel[:-1] if rel[-1] == '__init__' else rel)


def import_graph():
    """Module -> the cdmp_ros modules it imports (module level and inside functions, also
    under ``if TYPE_CHECKING``). ``from package import name`` is an edge to the submodule
    ``package.name`` when there is one, else to the package; the implicit import of a
    module's parent packages is not an edge."""
    modules = {_module_name(p): p for p in _python_files()}
    graph = {}
    for module, path in modules.items():
        edges = set()
        for name, _ in _imports(path):
            if name.split('.')[0] != 'cdmp_ros':
                continue
            while name and name not in modules:  # a name of a module -> the module
                name = name.rpartition('.')[0]
            if name and name != module:
                edges.add(name)
        graph[module] = edges
    return graph


def import_cycles(graph):
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    index, low, stack, on_stack, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                out.append(sorted(component))
    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_layers_respected():
    bad = _violations()
    assert not bad, 'layer violations:\n' + '\n'.join(bad)


def test_common_imports_only_the_standard_library():
    """cdmp_ros/common: standard library and other common modules only (the layer rule,
    stated on its own because every node process imports it)."""
    common = os.path.join(PKG, 'common')
    bad = []
    for path in _python_files():
        if not path.startswith(common + os.sep):
            continue
        for name, line in _imports(path):
            top = name.split('.')[0]
            if not (top in STDLIB or top == '__future__' or name.startswith('cdmp_ros.common.')):
                bad.append(f'{os.path.relpath(path, ROOT)}:{line} imports {name}')
    assert not bad, '\n'.join(bad)


def test_no_import_cycle():
    """No cycle in the import graph of cdmp_ros, counting imports inside functions (the usual
    way to hide one): a cycle means two modules that must be understood together."""
    graph = import_graph()
    assert len(graph) > 100 and graph['cdmp_ros.core.primitive_io']
    cycles = import_cycles(graph)
    assert not cycles, 'import cycles:\n' + '\n'.join(' <-> '.join(c) for c in cycles)


def test_checker_detects_violation(tmp_path, monkeypatch):
    """The checkers are not vacuous: a core file importing rclpy, pybullet and sim, a common
    file importing numpy and core, an import of the public API, and a cycle hidden in a
    function are reported."""
    fake_pkg = tmp_path / 'cdmp_ros'
    for layer in ('core', 'common', 'sim'):
        (fake_pkg / layer).mkdir(parents=True)
    (fake_pkg / 'core' / 'bad.py').write_text('import rclpy\nimport pybullet\n'
                                              'from cdmp_ros.sim import world\n')
    (fake_pkg / 'common' / 'bad.py').write_text('import numpy\nfrom cdmp_ros.core import bad\n'
                                                'from cdmp_ros import CDMP\n')
    (fake_pkg / 'sim' / 'world.py').write_text('def f():\n    from cdmp_ros.sim import a\n')
    (fake_pkg / 'sim' / 'a.py').write_text('from . import world\n')
    monkeypatch.setattr(sys.modules[__name__], 'PKG', str(fake_pkg))
    monkeypatch.setattr(sys.modules[__name__], 'ROOT', str(tmp_path))
    bad = _violations()
    assert len(bad) == 6, bad
    assert import_cycles(import_graph()) == [['cdmp_ros.sim.a', 'cdmp_ros.sim.world']]
    with pytest.raises(AssertionError, match='cdmp_ros/common/bad.py:1 imports numpy'):
        test_common_imports_only_the_standard_library()


@pytest.mark.parametrize('module, banned', [
    ('cdmp_ros.core', ('rclpy', 'pybullet')),
    ('cdmp_ros.common', ('rclpy', 'pybullet', 'numpy', 'scipy')),
])
def test_layer_importable_without_ros(module, banned):
    """Importing every core module pulls in neither rclpy nor pybullet; every common module
    not even numpy or scipy."""
    import subprocess
    code = (f'import importlib, pkgutil, sys, {module} as c\n'
            'for m in pkgutil.iter_modules(c.__path__):\n'
            f'    importlib.import_module("{module}." + m.name)\n'
            f'bad = [m for m in sys.modules if m.split(".")[0] in {banned!r}]\n'
            'assert not bad, bad\n')
    proc = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr


@pytest.mark.parametrize('module, banned', [
    ('cdmp_ros.ros.streamer_node', ('scipy.signal', 'scipy.stats', 'scipy.optimize')),
    ('cdmp_ros.ros.learner_node', ('scipy.signal', 'scipy.stats', 'scipy.optimize')),
    ('cdmp_ros.ros.sim_node', ('scipy.signal', 'scipy.stats', 'scipy.optimize')),
    ('cdmp_ros.ros.adapter_node', ('scipy.signal', 'scipy.stats')),
    ('cdmp_ros.cli.main', ('scipy', 'rclpy', 'pybullet', 'matplotlib')),
])
def test_start_imports_stay_light(module, banned):
    """What a process imports before it can work: scipy.signal alone costs about 1.1 s of CPU
    (it pulls in scipy.stats, interpolate, ndimage), paid by every node start and ``cdmp``
    command. The nodes import only what they use (the adapter needs scipy.optimize), and
    ``cdmp``'s subcommands import theirs inside ``run``."""
    import subprocess
    code = (f'import sys, {module}\n'
            f'bad = [m for m in sys.modules if m in {banned!r} or m.split(".")[0] in {banned!r}]\n'
            'assert not bad, bad\n')
    from conftest import ros_env
    proc = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                          timeout=300, env=ros_env())
    assert proc.returncode == 0, proc.stderr
