"""The node executables limit BLAS to one thread unless the caller set it (issue 13 item 4)."""
import os
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))  # this checkout's package

PROBE = (
    'import os, sys\n'
    'import cdmp_ros.nodes.{name}\n'
    'import numpy\n'
    'print(os.environ.get("OPENBLAS_NUM_THREADS"), os.environ.get("OMP_NUM_THREADS"))\n'
)


def _run(name, env_extra):
    env = {k: v for k, v in os.environ.items()
           if k not in ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS')}
    env.update(env_extra)
    env['PYTHONPATH'] = ROOT
    out = subprocess.run([sys.executable, '-c', PROBE.format(name=name)], env=env,
                         capture_output=True, text=True, timeout=120, check=True)
    return out.stdout.split()


@pytest.mark.parametrize('name', ['adapter', 'streamer'])
def test_node_process_defaults_to_one_blas_thread(name):
    assert _run(name, {}) == ['1', '1']


@pytest.mark.parametrize('name', ['adapter', 'streamer'])
def test_node_process_keeps_a_callers_setting(name):
    assert _run(name, {'OPENBLAS_NUM_THREADS': '2', 'OMP_NUM_THREADS': '3'}) == ['2', '3']


@pytest.mark.parametrize('name', ['adapter', 'streamer'])
def test_numpy_is_not_imported_before_the_setting(name):
    probe = ('import sys\nimport cdmp_ros.nodes.{name}\n'
             'print("numpy" in sys.modules)\n').format(name=name)
    env = dict(os.environ, PYTHONPATH=ROOT)
    out = subprocess.run([sys.executable, '-c', probe], env=env, capture_output=True,
                         text=True, timeout=120, check=True)
    assert out.stdout.strip() == 'False'
