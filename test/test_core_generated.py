"""The checked-in generated kernels (cdmp_ros/core/generated/): regenerated, they are the same
to the letter; the streamer's default coupling on the Panda runs them; any other configuration
is compiled at run time by the same generator."""
import importlib.util
import math
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

from conftest import REPO_ROOT

SCRIPT = os.path.join(REPO_ROOT, 'scripts', 'gen_kernels.py')


def _script():
    spec = importlib.util.spec_from_file_location('gen_kernels', SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope='module')
def panda():
    import pybullet_data
    from cdmp_ros.core.kinematics import panda_chain
    return panda_chain(os.path.join(pybullet_data.getDataPath(), 'franka_panda', 'panda.urdf'))


def test_regenerated_kernels_equal_the_checked_in_modules():
    env = dict(os.environ, PYTHONPATH=REPO_ROOT + os.pathsep + os.environ.get('PYTHONPATH', ''))
    proc = subprocess.run([sys.executable, SCRIPT, '--check'], cwd=REPO_ROOT, env=env,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]


def test_the_check_fails_on_any_difference(tmp_path, monkeypatch, capsys):
    gen = _script()
    out = tmp_path / 'generated'
    shutil.copytree(gen.OUT, out)
    monkeypatch.setattr(gen, 'OUT', str(out))
    assert gen.main(['--check']) == 0
    path = out / 'panda_coupling.py'
    path.write_text(path.read_text().replace('v5 = v0 * v3', 'v5 = v0 * v3 * 1.0', 1))
    assert gen.main(['--check']) == 1
    assert 'v5 = v0 * v3 * 1.0' in capsys.readouterr().out
    assert gen.main([]) == 0 and gen.main(['--check']) == 0            # rewritten


def test_the_default_streamer_coupling_runs_the_checked_in_modules(panda):
    from cdmp_ros.core.streaming.streamer import StreamerConfig, streamer_coupling
    coupling = streamer_coupling(panda, StreamerConfig())
    fn = coupling._coupled
    assert fn.__module__ == 'cdmp_ros.core.generated.panda_coupling'
    assert fn.__code__.co_filename == os.path.join(REPO_ROOT, 'cdmp_ros', 'core', 'generated',
                                                   'panda_coupling.py')
    # another tool centre point: other source, compiled at run time by the same generator
    other = streamer_coupling(panda, StreamerConfig(tcp_offset=(0.0, 0.0, 0.2)))
    assert other._coupled.__code__.co_filename.startswith('<generated')
    assert other._coupled.source != coupling._coupled.source


def test_the_checked_in_coupling_computes_what_its_source_computes(panda):
    """The module (wrapped lines) and the generated source compiled at run time give the same
    floats, on random configurations and obstacles near the arm, also near the limits."""
    from cdmp_ros.core.coupling.terms import _inverse_h3
    from cdmp_ros.core.kinematics import PointOfInterest
    from cdmp_ros.core.kinematics.closest import Box, Sphere
    from cdmp_ros.core.streaming.streamer import StreamerConfig, streamer_coupling
    coupling = streamer_coupling(panda, StreamerConfig())
    scope = {}
    exec(compile(coupling._coupled.source, '<test>', 'exec'),  # noqa: S102
         {'cos': math.cos, 'sin': math.sin, 'inverse_h3': _inverse_h3}, scope)
    fresh = scope['coupled']
    rng = np.random.default_rng(5)
    gate, eps2, lam2 = coupling._gate, coupling._eps2, coupling._lam2
    n_active = 0
    for trial in range(40):
        u = rng.uniform(0.02, 0.995 if trial % 2 else 0.8, 7)
        q = (panda.lower + (panda.upper - panda.lower) * u).tolist()
        X = panda.forward(np.array(q), [PointOfInterest('ee'), PointOfInterest('panda_link4')])
        obstacles = [Sphere(tuple(X[0] + rng.normal(0, 0.08, 3)), 0.04),
                     Box.from_center(X[1] + rng.normal(0, 0.08, 3), (0.1, 0.1, 0.1))]
        a = coupling._coupled(q, gate, obstacles, eps2, lam2, coupling._limit)
        b = fresh(q, gate, obstacles, eps2, lam2, coupling._limit)
        assert (a is None) == (b is None)
        if a is not None:
            n_active += 1
            assert a == b
    assert n_active >= 10
