"""The streamer's promise to a robot, fuzzed: whatever the primitive, the goals and the coupling
term, every published reference (``out_y``) stays strictly inside the position limits, its
differences stay within the velocity, acceleration and jerk limits, and the published velocity
is the one the positions imply. Random limits, random CDMP weights and goals (beyond the
limits too), coupling terms up to 1e9 rad/s^2 that change every tick, stale inputs (a stop) and
a resume, at 500 Hz and 1 kHz."""
import numpy as np
from hypothesis import HealthCheck, given, settings, strategies as st
from hypothesis.extra.numpy import arrays

from cdmp_ros.core.dmp.dmp import CDMP, DmpConfig
from cdmp_ros.core.joint_limits import KinematicLimits
from cdmp_ros.core.primitive_io import dumps_primitive
from cdmp_ros.core.streaming.config import StreamerConfig
from cdmp_ros.core.streaming.primitives import prepare_primitive
from cdmp_ros.core.streaming.streamer import ReferenceStreamer

N_TICKS = 400


class RandomCoupling:
    """A coupling term drawn anew every call (the Coupling contract)."""

    def __init__(self, rng, scale):
        self.rng, self.scale = rng, scale
        self.last_distances = [0.05]

    def joint_acceleration(self, q, qd, obstacles):
        return (self.rng.standard_normal(len(q)) * self.scale).tolist()


@st.composite
def cases(draw):
    n = draw(st.integers(1, 7))
    lo = draw(arrays(np.float64, n, elements=st.floats(-3, 0)))
    width = draw(arrays(np.float64, n, elements=st.floats(0.2, 6)))
    vel = draw(arrays(np.float64, n, elements=st.floats(0.1, 5)))
    acc = draw(arrays(np.float64, n, elements=st.floats(1, 50)))
    jerk = draw(arrays(np.float64, n, elements=st.floats(100, 20000)))
    weights = draw(arrays(np.float64, (n, 5), elements=st.floats(-1e4, 1e4)))
    goals = draw(st.lists(arrays(np.float64, n, elements=st.floats(-20, 20)), min_size=1,
                          max_size=3))
    scale = draw(st.sampled_from([0.0, 10.0, 1e3, 1e9]))
    rate = draw(st.sampled_from([500.0, 1000.0]))
    seed = draw(st.integers(0, 2**31 - 1))
    return lo, lo + width, vel, acc, jerk, weights, goals, scale, rate, seed


@settings(max_examples=40, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow])
@given(cases())
def test_published_references_keep_every_limit(case):
    lo, hi, vel, acc, jerk, weights, goals, scale, rate, seed = case
    n = lo.size
    names = tuple(f'j{i}' for i in range(n))
    limits = KinematicLimits(names, lo, hi, vel, acc, jerk)
    prim = CDMP(lo, hi, DmpConfig(n_weights_per_dim=5), names)
    prim.set_parameters(weights, 0.5 * (lo + hi), goals[0], 1.0)
    cfg = StreamerConfig(rate=rate, joint_names=names, joint_states_timeout=0.05)
    rng = np.random.default_rng(seed)
    st_ = ReferenceStreamer(lo, hi, cfg, coupling=RandomCoupling(rng, scale), limits=limits)
    st_.obstacles = ['sphere']
    prep = prepare_primitive(dumps_primitive(prim), names, cfg.dt, lo, hi, vel)
    dt = cfg.dt
    P, V, A = [], [], []
    q_measured = 0.5 * (lo + hi)
    for k in range(N_TICKS):
        now = k * dt
        stale = N_TICKS // 2 <= k < N_TICKS // 2 + int(0.2 / dt)  # no joint_states: a stop
        if not stale:
            st_.note_joint_states(q_measured, now)
        if k == 0:
            st_.activate(prep, now)
        if k in (N_TICKS // 4, 3 * N_TICKS // 4):
            st_.set_goal(goals[(k // (N_TICKS // 4)) % len(goals)])
        st_.advance(1, now)
        P.append(list(st_.out_y))
        V.append(list(st_.out_yd))
        A.append(list(st_.out_ydd))
        q_measured = np.array(st_.out_y)  # a robot that follows
    P, V, A = np.array(P), np.array(V), np.array(A)
    assert np.all(np.isfinite(P))
    assert np.all(P > lo) and np.all(P < hi), 'a published position left the limits'
    dv = np.diff(P, axis=0) / dt
    da = np.diff(dv, axis=0) / dt
    dj = np.diff(da, axis=0) / dt
    tol = 1 + 1e-9
    assert np.all(np.abs(dv) <= vel * tol + 1e-9), np.abs(dv / vel).max()
    assert np.all(np.abs(da) <= acc * tol + 1e-6), np.abs(da / acc).max()
    assert np.all(np.abs(dj) <= jerk * tol + 1e-3), np.abs(dj / jerk).max()
    np.testing.assert_allclose(V[1:], dv, rtol=0, atol=1e-9 * max(1.0, np.abs(dv).max()))
    np.testing.assert_allclose(A[2:], da, rtol=0, atol=1e-6 * max(1.0, np.abs(da).max()))
    assert st_.stage.clamped == 0
    assert st_.steps == N_TICKS and st_.active is prep  # it streamed every tick
