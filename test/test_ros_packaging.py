"""ROS packaging: package.xml parses with catkin_pkg, and `colcon build` installs every
executable under lib/cdmp_ros, the ament index marker, share/cdmp_ros/package.xml, the
parameter files and the launch files (share/cdmp_ros/launch)."""
import ast
import os
import shutil
import subprocess
import sys

from catkin_pkg.package import parse_package

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
DESIGN_EXECUTABLES = {'learner', 'adapter', 'streamer', 'sim', 'recorder', 'player', 'cdmp'}


def console_scripts():
    """Names and targets of the console scripts declared in setup.py."""
    tree = ast.parse(open(os.path.join(ROOT, 'setup.py')).read())
    for node in ast.walk(tree):
        if isinstance(node, ast.Assign) and any(
                getattr(t, 'id', None) == 'CONSOLE_SCRIPTS' for t in node.targets):
            entries = ast.literal_eval(node.value)
            return {e.split('=')[0].strip(): e.split('=')[1].strip() for e in entries}
    raise AssertionError('setup.py declares no CONSOLE_SCRIPTS')


def test_package_xml_parses():
    pkg = parse_package(os.path.join(ROOT, 'package.xml'))
    assert pkg.name == 'cdmp_ros'
    assert pkg.package_format == 3
    assert pkg.get_build_type() == 'ament_python'
    assert any(d.name == 'rclpy' for d in pkg.exec_depends)


def test_console_scripts_are_real_and_named_in_design():
    scripts = console_scripts()
    assert 'cdmp' in scripts
    for name, target in scripts.items():
        assert name in DESIGN_EXECUTABLES, f'{name} is not an executable of the design'
        module, func = target.split(':')
        code = f'import {module} as m; assert callable(m.{func})'
        proc = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                              timeout=300)
        assert proc.returncode == 0, f'entry point {name} -> {target} broken: {proc.stderr}'


def test_colcon_build_installs_package(tmp_path, monkeypatch):
    src = tmp_path / 'src' / 'cdmp_ros'
    shutil.copytree(ROOT, src, ignore=shutil.ignore_patterns(
        '.venv', '.git', 'build', 'install', 'log', 'out', '__pycache__', '*.egg-info',
        '.pytest_cache', '.hypothesis'))
    env = dict(os.environ)
    env['PATH'] = os.path.dirname(sys.executable) + os.pathsep + env.get('PATH', '')
    proc = subprocess.run(
        [os.path.join(os.path.dirname(sys.executable), 'colcon'), 'build',
         '--base-paths', str(tmp_path / 'src'),
         '--build-base', str(tmp_path / 'build'), '--install-base', str(tmp_path / 'install'),
         '--event-handlers', 'console_direct-'],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    prefix = tmp_path / 'install' / 'cdmp_ros'
    assert (prefix / 'share' / 'ament_index' / 'resource_index' / 'packages' /
            'cdmp_ros').is_file()
    assert (prefix / 'share' / 'cdmp_ros' / 'package.xml').is_file()
    for name in console_scripts():
        exe = prefix / 'lib' / 'cdmp_ros' / name
        assert exe.is_file(), f'missing executable {exe}'
        assert os.access(exe, os.X_OK)
    schemas = list((prefix / 'share' / 'cdmp_ros' / 'msg_schemas').glob('*.json'))
    assert schemas, 'msg_schemas/*.json not installed under share/cdmp_ros'
    share = prefix / 'share' / 'cdmp_ros'
    for f in ['config/streamer.yaml', 'config/sim.yaml', 'config/graphs/demo.yaml',
              'config/recorder_fastdds.xml', 'bags/panda_reach/demo_00/metadata.yaml',
              'launch/cdmp.launch.py', 'launch/demo.launch.py',
              # robot:=planar4 (issue 31, item 7): its URDF, overlays, graph and bags
              'urdf/planar4.urdf', 'config/graphs/planar4.yaml',
              'bags/planar4_reach/demo_02/metadata.yaml',
              *[f'config/robots/planar4/{n}.yaml' for n in ('sim', 'streamer', 'adapter',
                                                            'learner')],
              # and robot:=dual_panda
              'urdf/dual_panda.urdf', 'config/graphs/dual_panda.yaml',
              'config/graphs/dual_demo.yaml',
              'bags/dual_panda/demo_00/metadata.yaml',
              *[f'config/robots/dual_panda/{n}.yaml' for n in ('sim', 'streamer', 'adapter',
                                                               'learner')]]:
        assert (share / f).is_file(), f'{f} not installed under share/cdmp_ros'
    # the nodes' urdf_path package://cdmp_ros/urdf/planar4.urdf names the installed file
    from cdmp_ros.ros.robot_model import resolve_urdf_path
    monkeypatch.setenv('AMENT_PREFIX_PATH', str(prefix))
    assert resolve_urdf_path('package://cdmp_ros/urdf/planar4.urdf') == str(
        share / 'urdf' / 'planar4.urdf')
    assert (share / 'urdf' / 'planar4.urdf').read_text() == open(
        os.path.join(ROOT, 'urdf', 'planar4.urdf')).read()
    # every design executable is a console script
    assert set(console_scripts()) >= {'cdmp', 'learner', 'adapter', 'streamer', 'sim',
                                      'recorder', 'player'}
