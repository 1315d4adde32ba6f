"""The layer table of ../shared/design.md, enforced on the import statements of cdmp_ros.

| layer       | may import (besides the standard library)                        |
|-------------|------------------------------------------------------------------|
| core        | numpy, scipy (+ jsonschema, yaml for file validation)            |
| sim         | core, pybullet, plotting                                          |
| bag         | core, mcap                                                        |
| ros         | everything above, rclpy, *_msgs                                   |
| nodes       | ros and below                                                     |
| cli, experiments | core, sim, bag, experiments, cli (start ROS nodes as processes) |

rclpy and message packages are used only by cdmp_ros/ros and cdmp_ros/nodes.
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
    'core': BASE,
    'sim': BASE | PLOT | {'pybullet', 'pybullet_data'},
    'bag': BASE | PLOT | {'mcap', 'mcap_ros2', 'zstandard', 'lz4'},
    'ros': None,  # anything
    'nodes': None,
    'cli': BASE | PLOT | {'pybullet', 'pybullet_data', 'mcap', 'mcap_ros2', 'psutil'},
    'experiments': BASE | PLOT | {'pybullet', 'pybullet_data', 'psutil'},
}
ALLOWED_INTERNAL = {
    'core': {'core'},
    'sim': {'core', 'sim'},
    'bag': {'core', 'bag'},
    'ros': {'core', 'sim', 'bag', 'ros'},
    'nodes': {'core', 'sim', 'bag', 'ros', 'nodes'},
    'cli': {'core', 'sim', 'bag', 'cli', 'experiments'},
    'experiments': {'core', 'sim', 'bag', 'experiments'},
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
    tree = ast.parse(open(path).read(), filename=path)
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                yield a.name, node.lineno
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative import: resolve against the file's package
                rel = os.path.relpath(os.path.dirname(path), ROOT).split(os.sep)
                base = rel[:len(rel) - node.level + 1]
                name = '.'.join(base + ([node.module] if node.module else []))
                yield name, node.lineno
            else:
                yield node.module, node.lineno


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


def test_layers_respected():
    bad = _violations()
    assert not bad, 'layer violations:\n' + '\n'.join(bad)


def test_checker_detects_violation(tmp_path, monkeypatch):
    """The checker is not vacuous: a core file importing rclpy is reported."""
    fake_pkg = tmp_path / 'cdmp_ros'
    (fake_pkg / 'core').mkdir(parents=True)
    (fake_pkg / 'core' / 'bad.py').write_text('import rclpy\nimport pybullet\n'
                                              'from cdmp_ros.sim import world\n')
    monkeypatch.setattr(sys.modules[__name__], 'PKG', str(fake_pkg))
    monkeypatch.setattr(sys.modules[__name__], 'ROOT', str(tmp_path))
    bad = _violations()
    assert len(bad) == 3, bad


@pytest.mark.parametrize('module', ['cdmp_ros.core'])
def test_core_importable_without_ros(module):
    """Importing every core module pulls in neither rclpy nor pybullet."""
    import subprocess
    code = ('import importlib, pkgutil, sys, cdmp_ros.core as c\n'
            'for m in pkgutil.iter_modules(c.__path__):\n'
            '    importlib.import_module("cdmp_ros.core." + m.name)\n'
            'bad = [m for m in sys.modules if m.split(".")[0] in ("rclpy", "pybullet")]\n'
            'assert not bad, bad\n')
    proc = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr
