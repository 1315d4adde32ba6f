"""The reflex monitor (cdmp_ros.core.reflex): every received reference checked against the
joint limits as a Panda checks its commands, differenced on the stamps."""
import math

import numpy as np
import pytest
from hypothesis import given, strategies as st

from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.joint_limits import KinematicLimits, panda_limits
from cdmp_ros.core.reflex import (ACCEPTED, REFUSED, STOP, VIOLATION, ReflexMonitor,
                                  describe_violations)
from cdmp_ros.core.run_metrics import stamped_differences

DT_NS = 1_000_000  # 1 kHz, the Panda's interface
LIMITS = panda_limits()
HOME = np.array([0.0, -np.pi / 4, 0.0, -3 * np.pi / 4, 0.0, np.pi / 2, np.pi / 4])


def one_joint(lower=-1.0, upper=1.0, v=2.0, a=10.0, j=1000.0):
    return KinematicLimits(('j',), [lower], [upper], [v], [a], [j])


def feed(monitor, stamps, Q):
    """Feed every row; returns the list of (status, violations)."""
    return [monitor.update(int(t), list(map(float, q))) for t, q in zip(stamps, Q)]


def smooth_reach(n=1500, fraction=0.9):
    """A minimum-jerk reach of 1.5 s at 1 kHz whose peak velocity, acceleration and jerk stay
    below ``fraction`` of the Panda's limits on every joint."""
    T = np.arange(n) * DT_NS
    s = np.linspace(0.0, 1.0, n)
    shape = 10 * s ** 3 - 15 * s ** 4 + 6 * s ** 5
    dur = (n - 1) * 1e-3
    # peaks of the minimum-jerk profile: v 1.875 d/T, a 5.774 d/T^2, j 60 d/T^3
    d = fraction * np.minimum.reduce([LIMITS.velocity * dur / 1.875,
                                      LIMITS.acceleration * dur ** 2 / 5.774,
                                      LIMITS.jerk * dur ** 3 / 60.0])
    return T, HOME + shape[:, None] * d


def test_a_stream_inside_the_limits_gives_no_error():
    T, Q = smooth_reach()
    m = ReflexMonitor(LIMITS)
    out = feed(m, T, Q)
    assert all(s == ACCEPTED and v == () for s, v in out)
    assert m.errors == 0 and m.checked == len(T) and sum(m.counts.values()) == 0
    # the worst ratios are those of the stream (independent numpy computation)
    V, A, J = stamped_differences(T, Q)
    for order, X, lim in (('velocity', V, LIMITS.velocity),
                          ('acceleration', A, LIMITS.acceleration), ('jerk', J, LIMITS.jerk)):
        assert m.worst[order] == pytest.approx(float(np.max(np.abs(X) / lim)), rel=1e-9)
        assert m.worst[order] < 0.95
    assert max(m.worst[o] for o in ('velocity', 'acceleration', 'jerk')) > 0.85
    assert m.as_values()['reflex_errors'] == '0'


def integrate(jerks, q0=0.0, dt=1e-3):
    """Positions whose backward differences are exactly ``jerks`` (from rest at ``q0``)."""
    a = v = 0.0
    q, out = q0, []
    for j in jerks:
        a += j * dt
        v += a * dt
        q += v * dt
        out.append(q)
    return np.array(out)


def stream(q1, n0=40):
    """References of the Panda at HOME, joint 1 following ``q1`` after ``n0`` resting ones."""
    Q = np.tile(HOME, (n0 + len(q1), 1))
    Q[n0:, 0] = q1
    return np.arange(len(Q)) * DT_NS, Q


def test_a_jump_is_a_velocity_error():
    T, Q = stream(HOME[0] + np.full(20, 0.01))   # 10 mrad in one step of 1 ms: 10 rad/s
    m = ReflexMonitor(LIMITS)
    out = feed(m, T, Q)
    k0 = 40
    assert all(s == ACCEPTED for s, _ in out[:k0])
    s, viol = out[k0]
    assert s == VIOLATION   # mode count: applied
    assert {v.order for v in viol} == {'velocity', 'acceleration', 'jerk'}
    assert {v.joint for v in viol} == {'panda_joint1'}
    v = next(v for v in viol if v.order == 'velocity')
    assert v.value == pytest.approx(10.0) and v.limit == 2.175
    assert v.ratio == pytest.approx(10.0 / 2.175)
    # then the velocity comes back to zero: acceleration and jerk errors, no velocity error
    assert m.counts['velocity'] == 1 and m.counts['position'] == 0
    assert [sorted({v.order for v in vs}) for _, vs in out[k0 + 1:k0 + 4]] == [
        ['acceleration', 'jerk'], ['jerk'], []]
    assert m.errors == 3
    assert m.as_values()['reflex_errors_velocity'] == '1'


def test_an_acceleration_step_is_an_acceleration_error():
    # joint 1 (15 rad/s^2, 7500 rad/s^3): ramp to 30 rad/s^2 at 5000 rad/s^3, hold 20 ms,
    # ramp back: only the acceleration breaks (the velocity peaks at 0.78 rad/s)
    jerks = [5000.0] * 6 + [0.0] * 20 + [-5000.0] * 6 + [0.0] * 10
    q1 = integrate(jerks, HOME[0])
    T, Q = stream(q1)
    m = ReflexMonitor(LIMITS)
    out = feed(m, T, Q)
    acc = np.cumsum(jerks) * 1e-3
    want = int(np.count_nonzero(np.abs(acc) > 15.0 * 1.02))
    assert want == 20 + 2 * 3 - 1
    assert m.errors == want == m.counts['acceleration']
    assert m.counts['velocity'] == m.counts['jerk'] == m.counts['position'] == 0
    viol = [v for _, vs in out for v in vs]
    assert {(v.joint, v.order) for v in viol} == {('panda_joint1', 'acceleration')}
    assert max(v.value for v in viol) == pytest.approx(30.0, rel=1e-6)
    assert m.worst['acceleration'] == pytest.approx(2.0, rel=1e-6)


def test_a_jerk_step_is_a_jerk_error():
    # joint 1: one tick of +10000 rad/s^3 (limit 7500), one of -10000: the acceleration
    # peaks at 10 rad/s^2 (limit 15): exactly two jerk errors, at those two ticks
    jerks = [0.0] * 5 + [10000.0, -10000.0] + [0.0] * 10
    T, Q = stream(integrate(jerks, HOME[0]))
    m = ReflexMonitor(LIMITS)
    out = feed(m, T, Q)
    bad = [(k, vs) for k, (_, vs) in enumerate(out) if vs]
    assert [k for k, _ in bad] == [45, 46]
    assert [[(v.joint, v.order) for v in vs] for _, vs in bad] == [
        [('panda_joint1', 'jerk')]] * 2
    assert bad[0][1][0].value == pytest.approx(10000.0, rel=1e-6)
    assert bad[1][1][0].value == pytest.approx(-10000.0, rel=1e-6)
    assert bad[0][1][0].ratio == pytest.approx(10000.0 / 7500.0, rel=1e-6)
    assert m.counts == {'position': 0, 'velocity': 0, 'acceleration': 0, 'jerk': 2}
    assert 'panda_joint1 jerk -10000 exceeds the limit 7500' in m.last_error


def test_a_position_outside_is_named_even_on_the_first_reference():
    m = ReflexMonitor(LIMITS)
    q = HOME.copy()
    q[3] = 0.1   # joint 4's upper limit is -0.0698
    s, v = m.update(0, q.tolist())
    assert s == VIOLATION and len(v) == 1
    assert v[0].joint == 'panda_joint4' and v[0].order == 'position'
    assert v[0].value == pytest.approx(0.1) and v[0].limit == pytest.approx(-0.0698)
    assert v[0].ratio > 1.0
    assert m.counts['position'] == 1 and m.errors == 1
    assert 'panda_joint4 position 0.1 outside the limit -0.0698' in m.last_error
    q[3] = -3.2  # below the lower limit -3.0718, and at rest (the history restarts)
    m.reset()
    s, v = m.update(DT_NS, q.tolist())
    assert s == VIOLATION and v[0].limit == pytest.approx(-3.0718)


def test_a_difference_within_the_tolerance_passes():
    lim = one_joint(v=1.0, a=1e9, j=1e12)
    m = ReflexMonitor(lim, tolerance=0.02)
    # 1.019 rad/s: within 2 %; 1.021: over
    assert m.update(0, [0.0])[0] == ACCEPTED
    assert m.update(DT_NS, [1.019e-3])[0] == ACCEPTED
    s, v = m.update(2 * DT_NS, [1.019e-3 + 1.021e-3])
    assert s == VIOLATION and v[0].order == 'velocity'
    assert v[0].value == pytest.approx(1.021)
    m.set_tolerance(0.05)
    assert m.update(3 * DT_NS, [2.040e-3 + 1.021e-3])[0] == ACCEPTED
    with pytest.raises(ValidationError, match='tolerance'):
        m.set_tolerance(-0.1)
    with pytest.raises(ValidationError, match='mode'):
        m.set_mode('panic')


@given(st.lists(st.integers(200_000, 5_000_000), min_size=8, max_size=40),
       st.integers(0, 2 ** 31))
def test_uneven_stamp_gaps_match_an_independent_computation(gaps, seed):
    rng = np.random.default_rng(seed)
    T = 1_700_000_000_000_000_000 + np.concatenate([[0], np.cumsum(gaps)])
    n = T.size
    lim = KinematicLimits(('a', 'b'), [-100.0, -100.0], [100.0, 100.0], [1e-9, 1e-9],
                          [1e-9, 1e-9], [1e-9, 1e-9])   # every difference is a violation
    Q = np.cumsum(rng.normal(0.0, 1e-3, (n, 2)), axis=0)
    m = ReflexMonitor(lim, tolerance=0.0)
    out = feed(m, T, Q)
    V, A, J = stamped_differences(T, Q)
    for k, (_, viol) in enumerate(out):
        got = {(v.joint, v.order): v.value for v in viol}
        for d, name in enumerate(('a', 'b')):
            for order, X, lag in (('velocity', V, 1), ('acceleration', A, 2), ('jerk', J, 3)):
                if k >= lag:
                    want = X[k - lag, d]
                    assert got[(name, order)] == pytest.approx(want, rel=1e-7, abs=1e-9 * (
                        1.0 + abs(want))), (k, name, order)
                else:
                    assert (name, order) not in got


def test_a_gap_that_is_not_positive_reseeds():
    lim = one_joint(v=1.0, a=1.0, j=1.0)
    m = ReflexMonitor(lim)
    assert m.update(10 * DT_NS, [0.0])[0] == ACCEPTED
    # same stamp, and an older one: re-seed, no difference taken (a jump would break all)
    assert m.update(10 * DT_NS, [0.5])[0] == ACCEPTED
    assert m.update(5 * DT_NS, [-0.5])[0] == ACCEPTED
    # the next difference is taken from the re-seeded reference (-0.5 at 5 ms)
    s, v = m.update(6 * DT_NS, [-0.5 + 0.5e-3])
    assert s == ACCEPTED and m.worst['velocity'] == pytest.approx(0.5)
    s, v = m.update(7 * DT_NS, [-0.5 + 0.5e-3 + 0.6e-3])  # 0.6 rad/s; 100 rad/s^2
    assert s == VIOLATION and [x.order for x in v] == ['acceleration']
    assert m.errors == 1


def test_stop_mode_halts_refuses_and_reset_reseeds():
    lim = one_joint(v=1.0, a=10.0, j=1000.0)
    m = ReflexMonitor(lim, mode='stop')
    assert m.update(0, [0.0])[0] == ACCEPTED
    s, v = m.update(DT_NS, [0.1])   # 100 rad/s
    assert s == STOP and m.stopped and 'j velocity 100 exceeds the limit 1' in m.stop_reason
    assert {x.order for x in v} == {'velocity'}   # the second reference: no acceleration yet
    for k in range(2, 6):   # refused, not checked
        assert m.update(k * DT_NS, [0.1]) == (REFUSED, ())
    assert m.refused == 4 and m.checked == 2 and m.errors == 1
    vals = m.as_values()
    assert vals['reflex_stopped'] == 'true' and vals['references_refused_reflex'] == '4'
    m.reset()
    assert not m.stopped and m.stop_reason == ''
    # re-seeded: the first reference after the reset takes no difference, wherever it is
    assert m.update(10 * DT_NS, [0.9])[0] == ACCEPTED
    assert m.update(11 * DT_NS, [0.9 + 0.5e-3])[0] == ACCEPTED
    assert m.errors == 1   # counts are kept across a reset


def test_reset_in_count_mode_reseeds_the_history():
    lim = one_joint(v=1.0, a=10.0, j=1000.0)
    m = ReflexMonitor(lim)
    m.update(0, [0.0])
    m.update(DT_NS, [0.0])
    m.reset()
    assert m.update(2 * DT_NS, [0.5])[0] == ACCEPTED   # a jump, but the first after a reset
    assert m.update(3 * DT_NS, [0.5])[0] == ACCEPTED
    assert m.errors == 0


def test_infinite_limits_are_not_checked():
    lim = KinematicLimits.unlimited(('j',), [-1.0], [1.0])
    m = ReflexMonitor(lim)
    for k, q in enumerate([0.0, 0.9, -0.9, 0.9]):
        assert m.update(k * DT_NS, [q])[0] == ACCEPTED
    assert m.worst['velocity'] == 0.0
    assert m.update(10 * DT_NS, [math.nan])[0] == VIOLATION  # not finite: outside


def test_wrong_length_and_describe():
    m = ReflexMonitor(LIMITS)
    with pytest.raises(ValidationError, match='expected 7 positions'):
        m.update(0, [0.0])
    assert describe_violations(()) == 'none'
    q = HOME.copy()
    q[1] = 5.0
    q[3] = 0.5
    q[5] = 4.0
    _, v = m.update(0, q.tolist())
    text = describe_violations(v, most=2)
    assert text.startswith('panda_joint2 position 5') and '(+' in text


def test_the_check_is_cheap():
    """Python floats, no numpy per message: one 7-joint check costs microseconds (a generous
    bound on operations, not on time: it allocates nothing that grows with the stream)."""
    import tracemalloc
    T, Q = smooth_reach(400)
    rows = Q.tolist()
    m = ReflexMonitor(LIMITS)
    for t, q in zip(T[:10].tolist(), rows[:10]):
        m.update(t, q)
    tracemalloc.start()
    before = tracemalloc.take_snapshot()
    for t, q in zip(T[10:].tolist(), rows[10:]):
        m.update(t, q)
    after = tracemalloc.take_snapshot()
    tracemalloc.stop()
    grown = sum(s.size_diff for s in after.compare_to(before, 'filename')
                if s.traceback[0].filename.endswith('reflex.py'))
    assert grown < 2000, grown


@given(st.lists(st.integers(200_000, 5_000_000), min_size=4, max_size=30),
       st.floats(-3.0, 3.0), st.floats(-3.0, 3.0), st.floats(-3.0, 3.0), st.floats(-3.0, 3.0))
def test_differences_are_exact_for_a_cubic_whatever_the_gaps(gaps, c0, c1, c2, c3):
    T = 1_700_000_000_000_000_000 + np.concatenate([[0], np.cumsum(gaps)])
    t = (T - T[0]) * 1e-9
    Q = (c0 + c1 * t + c2 * t ** 2 + c3 * t ** 3)[:, None]
    V, A, J = stamped_differences(T, Q)
    # rounding: the k-th difference of values of size |Q| on gaps of h is off by ~eps |Q| / h^k
    h = min(gaps) * 1e-9
    rounding = 100.0 * np.finfo(float).eps * (1.0 + np.abs(Q).max())
    np.testing.assert_allclose(J[:, 0], 6.0 * c3, rtol=1e-9, atol=6.0 * rounding / h ** 3)
    # the acceleration of a cubic is linear: the second difference is its value at the mean
    # of the three stamps
    tm = (t[2:] + t[1:-1] + t[:-2]) / 3.0
    np.testing.assert_allclose(A[:, 0], 2.0 * c2 + 6.0 * c3 * tm, rtol=1e-9,
                               atol=2.0 * rounding / h ** 2)


@given(st.integers(0, 2 ** 31), st.lists(st.booleans(), min_size=60, max_size=60))
def test_a_missed_sample_never_raises_a_difference_above_the_full_grids(seed, keep):
    """A subscriber that misses references (a gap of whole periods) sees differences that
    are weighted means of the full grid's: never above their maximum."""
    rng = np.random.default_rng(seed)
    n = 60
    T = 1_700_000_000_000_000_000 + DT_NS * np.arange(n)
    Q = np.cumsum(np.cumsum(np.cumsum(rng.normal(0.0, 1.0, (n, 2)), axis=0), axis=0), axis=0)
    keep = np.array(keep)
    keep[:4] = True
    full = stamped_differences(T, Q)
    sub = stamped_differences(T[keep], Q[keep])
    for F, S in zip(full, sub):
        assert np.abs(S).max() <= np.abs(F).max() * (1.0 + 1e-9)
