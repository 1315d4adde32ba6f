"""The central promise: CDMP positions stay strictly inside the limits, whatever the input.

For any finite weights, any goal (also beyond the limits), any joint-space coupling term up to
1e9 and any exploration noise, every produced position lies strictly inside (y_min, y_max) and
nothing is NaN or inf. Plain DMPs given the same inputs leave the limits.
"""
import numpy as np
from hypothesis import given, HealthCheck, settings, strategies as st
from hypothesis.extra.numpy import arrays

from cdmp_ros.core.dmp.dmp import CDMP, DMP, DmpConfig, limit_usage

N_W = 5
DT = 0.02
N_STEPS = 61
finite = st.floats(allow_nan=False, allow_infinity=False)


@st.composite
def cases(draw):
    n = draw(st.integers(1, 7))
    lo = draw(arrays(np.float64, n, elements=st.floats(-5, 5)))
    width = draw(arrays(np.float64, n, elements=st.floats(1e-3, 10)))
    weights = draw(arrays(np.float64, (n, N_W), elements=finite))
    goal = draw(arrays(np.float64, n, elements=st.floats(-1e6, 1e6)))
    start = draw(arrays(np.float64, n, elements=st.floats(-1e3, 1e3)))
    coupling = draw(arrays(np.float64, n, elements=st.floats(-1e9, 1e9)))
    freq = draw(st.floats(0, 50))
    noise_std = draw(st.sampled_from([0.0, 1.0, 1e3, 1e6]))
    goal_noise = draw(arrays(np.float64, n, elements=st.floats(-1e3, 1e3)))
    seed = draw(st.integers(0, 2 ** 32 - 1))
    return lo, lo + width, weights, goal, start, coupling, freq, noise_std, goal_noise, seed


class Oscillating:
    """A Coupling: ``amplitude cos(freq t)`` [rad/s^2] at its k-th call, ``t = k DT``."""

    def __init__(self, amplitude, freq):
        self.amplitude, self.freq, self.k = amplitude, freq, 0
        self.last_distances = []

    def joint_acceleration(self, q, qd, obstacles):
        t = self.k * DT
        self.k += 1
        return (self.amplitude * np.cos(self.freq * t)).tolist()


def run(prim_cls, case):
    lo, hi, weights, goal, start, coupling, freq, noise_std, goal_noise, seed = case
    cfg = DmpConfig(n_weights_per_dim=N_W)
    n = lo.shape[0]
    prim = CDMP(lo, hi, cfg) if prim_cls is CDMP else DMP(n, cfg)
    prim.set_parameters(weights, np.clip(start, lo, hi), goal, 1.0)
    rng = np.random.default_rng(seed)
    eps = rng.normal(0.0, noise_std, (N_STEPS, n, N_W)) if noise_std else None

    return prim.rollout(dt=DT, duration=DT * (N_STEPS - 1), start_y=start, goal_y=goal,
                        coupling=Oscillating(coupling, freq) if np.any(coupling) else None,
                        weight_noise=eps, goal_noise=goal_noise)


@settings(max_examples=2500, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(cases())
def test_cdmp_positions_strictly_inside_limits(case):
    lo, hi = case[0], case[1]
    tr = run(CDMP, case)
    for name in ('Y', 'Yd', 'Ydd', 'X', 'Xd'):
        assert np.all(np.isfinite(getattr(tr, name))), name
    assert np.all(tr.Y > lo) and np.all(tr.Y < hi)


def test_plain_dmp_violates_on_the_same_kind_of_input():
    """Same input distribution, seeded: the CDMP never leaves the limits, the DMP often does."""
    rng = np.random.default_rng(7)
    n_cases, dmp_viol, cdmp_viol = 300, 0, 0
    for _ in range(n_cases):
        n = int(rng.integers(1, 8))
        lo = rng.uniform(-2, 0, n)
        hi = lo + rng.uniform(0.5, 3, n)
        case = (lo, hi, rng.normal(0, 200, (n, N_W)), rng.uniform(-5, 5, n),
                rng.uniform(lo, hi), rng.normal(0, 300, n), rng.uniform(0, 10), 10.0,
                rng.normal(0, 1, n), int(rng.integers(0, 2 ** 31)))
        dmp_viol += limit_usage(run(DMP, case).Y, lo, hi) >= 1.0
        cdmp_viol += limit_usage(run(CDMP, case).Y, lo, hi) >= 1.0
    assert cdmp_viol == 0
    assert dmp_viol > n_cases // 2, dmp_viol
