"""flake8 with ament's settings (99 columns, single quotes) over the whole project."""
import os
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_flake8_clean():
    targets = [p for p in ('cdmp_ros', 'test', 'benchmarks', 'scripts', 'launch', 'setup.py')
               if os.path.exists(os.path.join(ROOT, p))]
    proc = subprocess.run([sys.executable, '-m', 'flake8', *targets], cwd=ROOT,
                          capture_output=True, text=True)
    assert proc.returncode == 0, 'flake8 found problems:\n' + proc.stdout + proc.stderr


def test_flake8_checks_quotes():
    """The quotes plugin is active: a double-quoted string is reported."""
    proc = subprocess.run([sys.executable, '-m', 'flake8', '--stdin-display-name', 'x.py', '-'],
                          cwd=ROOT, input='x = "a"\n', capture_output=True, text=True)
    assert 'Q000' in proc.stdout
