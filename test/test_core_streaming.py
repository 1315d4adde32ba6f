"""ReferenceStreamer / SmoothStop / prepare_primitive: the streamer's logic without ROS."""
import json
import math
import os

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from cdmp_ros.core.errors import PrimitiveFileError, ValidationError
from cdmp_ros.core.primitive_io import dumps_primitive, primitive_to_dict
from cdmp_ros.core.streaming.primitives import prepare_primitive
from cdmp_ros.core.streaming.streamer import (ReferenceStreamer, SmoothStop,
                                              StreamerConfig, StreamFlags, StreamState, _H, _h)
from cdmp_ros.core.dmp.transform import SAT_MARGIN, TanhTransform
from streamer_harness import (LOWER, PANDA_JOINTS, Q_GOAL, Q_START, UPPER, VMAX, reach_cdmp,
                              reach_dmp)

DT = 0.002


@pytest.fixture(scope='module')
def cdmp_text():
    return dumps_primitive(reach_cdmp())


class FnCoupling:
    """A Coupling from a function ``fn(q, qd)`` (the obstacle set is not looked at)."""

    def __init__(self, fn):
        self.fn = fn
        self.last_distances = [1.0]

    def joint_acceleration(self, q, qd, obstacles):
        return self.fn(q, qd)


#: A stand-in obstacle set for couplings that ignore it (the streamer calls none without one).
SOME_OBSTACLE = (object(),)


def make_streamer(text, timeout=0.5, coupling=None, obstacles=SOME_OBSTACLE, **kw):
    """``coupling``: a Coupling (evaluated for ``obstacles``) or a function ``(q, qd)``."""
    cfg = StreamerConfig(joint_states_timeout=timeout, **kw)
    if coupling is not None and not hasattr(coupling, 'joint_acceleration'):
        coupling = FnCoupling(coupling)
    rs = ReferenceStreamer(LOWER, UPPER, cfg, coupling=coupling)
    rs.obstacles = obstacles
    prep = prepare_primitive(text, PANDA_JOINTS, cfg.dt, LOWER, UPPER, VMAX)
    return rs, prep


def run(rs, n, t0, measure=True, record=None):
    """Advance n ticks from time t0 with fresh joint_states (if measure); returns the time."""
    t = t0
    for _ in range(n):
        t += rs.dt
        if measure:
            rs.note_joint_states(rs.y, t)
        rs.advance(1, t)
        if record is not None:
            record.append((list(rs.y), list(rs.yd), rs.state))
    return t


def max_step_changes(rec):
    Y = np.array([r[0] for r in rec])
    Yd = np.array([r[1] for r in rec])
    return np.abs(np.diff(Y, axis=0)).max(axis=1), np.abs(np.diff(Yd, axis=0)).max(axis=1)


# -- configuration -----------------------------------------------------------------------------
@pytest.mark.parametrize('field,value', [('rate', 0.0), ('rate', float('nan')), ('rate', 5000.0),
                                         ('max_catch_up', 1.5), ('stop_time', -1.0),
                                         ('accept_unstamped', 1), ('rate', 'fast'),
                                         ('joint_names', ('a', 'a')), ('joint_names', ())])
def test_config_rejects_bad_values_naming_the_field(field, value):
    with pytest.raises(ValidationError, match=field):
        StreamerConfig(**{field: value})


def test_config_limits_match_the_urdf():
    import pybullet_data
    from cdmp_ros.core.kinematics import panda_chain
    chain = panda_chain(os.path.join(pybullet_data.getDataPath(), 'franka_panda/panda.urdf'))
    assert tuple(chain.joint_names) == StreamerConfig().joint_names == PANDA_JOINTS
    np.testing.assert_allclose(chain.lower, LOWER)
    np.testing.assert_allclose(chain.upper, UPPER)
    np.testing.assert_allclose(chain.velocity_limits, VMAX)


# -- smooth stop -------------------------------------------------------------------------------
def test_stop_profile_integral_is_exact():
    s = np.linspace(0.0, 1.0, 20001)
    h = np.array([_h(v) for v in s])
    num = np.concatenate([[0.0], np.cumsum(0.5 * (h[1:] + h[:-1]) * np.diff(s))])
    np.testing.assert_allclose(num, [_H(v) for v in s], atol=1e-9)
    assert _h(0.0) == 1.0 and _h(1.0) == 0.0 and _H(1.0) == 0.5


def test_smooth_stop_is_continuous_and_ends_at_rest():
    tr = TanhTransform(LOWER, UPPER, margin=SAT_MARGIN)
    y0 = Q_START.copy()
    yd0 = np.array([1.0, -0.5, 0.3, 0.8, -1.2, 0.4, 2.0])
    stop = SmoothStop(tr, y0, yd0, 0.5)
    y, yd, ydd = [0.0] * 7, [0.0] * 7, [0.0] * 7
    Y, Yd = [y0], [yd0]
    done = False
    for k in range(260):
        done = stop.advance(DT, y, yd, ydd)
        Y.append(list(y))
        Yd.append(list(yd))
        if done:
            break
    assert done and k == 249  # 0.5 s at 2 ms
    Y, Yd = np.array(Y), np.array(Yd)
    np.testing.assert_allclose(Yd[-1], 0.0, atol=1e-12)
    # velocity continuous at the start: the first step changes it by at most a_max * dt
    a_max = np.abs(np.diff(Yd, axis=0)).max() / DT
    assert np.abs(Yd[1] - yd0).max() <= 0.01 and a_max < 3.0 * 2.0 / 0.5 * 1.5
    # positions are consistent with the velocities (trapezoidal integral)
    np.testing.assert_allclose(Y[-1] - Y[0], np.trapezoid(Yd, dx=DT, axis=0), atol=2e-4)


@settings(max_examples=30, deadline=None)
@given(st.lists(st.floats(-0.999, 0.999), min_size=7, max_size=7),
       st.lists(st.floats(-50.0, 50.0), min_size=7, max_size=7),
       st.floats(0.01, 2.0))
def test_smooth_stop_never_leaves_the_limits(frac, vel, T):
    tr = TanhTransform(LOWER, UPPER, margin=SAT_MARGIN)
    y0 = tr.y_o + np.array(frac) * tr.y_delta
    stop = SmoothStop(tr, y0, vel, T)
    y, yd, ydd = [0.0] * 7, [0.0] * 7, [0.0] * 7
    for _ in range(int(T / 0.01) + 2):
        stop.advance(0.01, y, yd, ydd)
        assert np.all(np.isfinite(y)) and np.all(np.isfinite(yd))
        assert np.all(np.array(y) >= LOWER) and np.all(np.array(y) <= UPPER)
    np.testing.assert_allclose(yd, 0.0, atol=1e-12)


# -- streaming ---------------------------------------------------------------------------------
def test_follows_the_primitive_from_the_measured_start(cdmp_text):
    rs, prep = make_streamer(cdmp_text)
    assert rs.state is StreamState.WAITING and rs.advance(1, 0.0) == 0
    rs.note_joint_states(Q_START, 0.0)
    assert rs.state is StreamState.HOLDING and 'no primitive' in rs.reason
    assert 'switched in' in rs.activate(prep, 0.0)
    rec = []
    run(rs, 1500, 0.0, record=rec)
    ref = prep.prim.rollout(DT, duration=3.0, start_y=Q_START, velocity_limits=VMAX)
    np.testing.assert_allclose(rec[-1][0], ref.Y[1500], atol=1e-9)
    assert rs.state is StreamState.RUNNING


def test_open_loop_starts_at_the_primitive_start(cdmp_text):
    rs, prep = make_streamer(cdmp_text, timeout=0.0)
    rs.activate(prep, 0.0)
    rs.advance(1, 100.0)  # no joint_states ever: fine in open loop
    assert rs.state is StreamState.RUNNING
    np.testing.assert_allclose(rs.y, Q_START, atol=1e-3)


def test_new_primitive_switches_without_a_jump(cdmp_text):
    rs, prep = make_streamer(cdmp_text)
    rs.note_joint_states(Q_START, 0.0)
    rs.activate(prep, 0.0)
    rec = []
    t = run(rs, 400, 0.0, record=rec)  # mid-motion, fast
    speed = np.abs(rec[-1][1]).max()
    assert speed > 0.3
    q_other = np.array([-0.4, -0.1, -0.15, -1.5, -0.1, 1.0, -0.15])
    other = prepare_primitive(dumps_primitive(reach_cdmp(Q_START, q_other, 1.5)),
                              PANDA_JOINTS, DT, LOWER, UPPER, VMAX)
    rs.activate(other, t)
    run(rs, 300, t, record=rec)
    dy, dyd = max_step_changes(rec)
    k = 399  # the step across the switch
    assert dy[k] <= 1.5 * speed * DT
    assert dyd[k] <= 0.1 * speed, (dyd[k], speed)  # a restart at rest would change by speed
    # and the new goal is reached
    run(rs, 2000, t + 0.6)
    np.testing.assert_allclose(rs.y, q_other, atol=2e-2)


def test_goal_change_is_smooth_and_clipped_into_the_limits(cdmp_text):
    rs, prep = make_streamer(cdmp_text)
    rs.note_joint_states(Q_START, 0.0)
    rs.activate(prep, 0.0)
    rec = []
    t = run(rs, 300, 0.0, record=rec)
    goal = Q_GOAL.copy()
    goal[1] = 5.0  # beyond the upper limit 1.8326
    goal[3] = -4.0
    clipped = rs.set_goal(goal)
    assert clipped == [1, 3]
    half = 0.5 * (UPPER - LOWER)
    assert math.isclose(rs.goal_override[1], 0.5 * (UPPER[1] + LOWER[1]) + (1 - 1e-3) * half[1])
    run(rs, 3000, t, record=rec)
    dy, dyd = max_step_changes(rec)
    assert dyd[299] < 0.01 and dyd.max() < 0.1  # no velocity step (accel < 50 rad/s^2)
    np.testing.assert_allclose(rs.y, rs.goal_override, atol=5e-3)
    Y = np.array([r[0] for r in rec])
    assert np.all(Y >= LOWER) and np.all(Y <= UPPER)


def test_stale_joint_states_stop_smoothly_hold_and_resume(cdmp_text):
    rs, prep = make_streamer(cdmp_text, stop_time=0.4)
    rs.note_joint_states(Q_START, 0.0)
    rs.activate(prep, 0.0)
    rec = []
    t = run(rs, 400, 0.0, record=rec)
    speed = np.abs(rec[-1][1]).max()
    t = run(rs, 250 + 200 + 20, t, measure=False, record=rec)  # 0.5 s timeout + 0.4 s stop
    states = [r[2] for r in rec]
    first_stop = states.index(StreamState.STOPPING)
    assert 400 + 248 <= first_stop <= 400 + 252
    assert rs.state is StreamState.HOLDING and 'joint_states stale' in rs.reason
    assert np.abs(rec[-1][1]).max() == 0.0
    dy, dyd = max_step_changes(rec)
    assert dyd[first_stop - 1] < 0.05 * speed + 0.02
    held = list(rs.y)
    run(rs, 10, t, measure=False, record=rec)
    assert rs.y == held
    # fresh input: resumes from the held position, at rest, without a jump
    run(rs, 500, t + 0.02, record=rec)
    assert rs.state is StreamState.RUNNING
    dy, dyd = max_step_changes(rec)
    assert dyd.max() < 0.1 and dy.max() < 2.0 * np.abs([r[1] for r in rec]).max() * DT + 1e-12


def test_catch_up_equals_single_steps(cdmp_text):
    a, prep_a = make_streamer(cdmp_text, timeout=0.0)
    b, prep_b = make_streamer(cdmp_text, timeout=0.0)
    a.activate(prep_a, 0.0)
    b.activate(prep_b, 0.0)
    for k in range(50):
        a.advance(3, 0.0)
        for _ in range(3):
            b.advance(1, 0.0)
    assert a.y == b.y and a.yd == b.yd and a.steps == b.steps == 150
    seen = []
    a.advance(4, 0.0, on_step=lambda i: seen.append((i, list(a.y))))
    assert [i for i, _ in seen] == [0, 1, 2, 3]
    for _, y in seen:  # every intermediate step is exposed, as the single steps produce it
        b.advance(1, 0.0)
        assert y == b.y


def test_coupling_is_mapped_into_the_exogenous_space(cdmp_text):
    from cdmp_ros.core.dmp.stepper import joint_coupling_to_exogenous
    acc = [0.0, 3.0, 0.0, -2.0, 0.0, 0.0, 1.0]
    rs, prep = make_streamer(cdmp_text, timeout=0.0, coupling=lambda y, yd: acc)
    rs.activate(prep, 0.0)
    run(rs, 100, 0.0, measure=False)
    st_ = prep.stepper
    xi_before = list(st_.output.xi)
    assert rs.advance(1, 0.0) & StreamFlags.COUPLED
    expected = [0.0] * 7
    joint_coupling_to_exogenous(acc, xi_before, st_.tau, prep.prim.transform.y_delta.tolist(),
                                expected)
    assert np.abs(expected).max() > 0.0
    np.testing.assert_allclose(st_.input.coupling, expected, rtol=1e-12)


def test_coupling_decimation_holds_the_term(cdmp_text):
    calls = []

    def coupling(y, yd):
        calls.append(1)
        return [0.0] * 6 + [-4.0]
    rs, prep = make_streamer(cdmp_text, timeout=0.0, coupling=coupling, coupling_decimation=5)
    rs.activate(prep, 0.0)
    flags = [rs.advance(1, 0.0) for _ in range(50)]
    assert len(calls) == 10 and all(f & StreamFlags.COUPLED for f in flags)
    assert prep.stepper.input.coupling[6] < 0.0


def test_coupling_changes_the_motion_in_its_direction(cdmp_text):
    push = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -4.0]
    free, prep_f = make_streamer(cdmp_text, timeout=0.0)
    pushed, prep_p = make_streamer(cdmp_text, timeout=0.0, coupling=lambda y, yd: push)
    free.activate(prep_f, 0.0)
    pushed.activate(prep_p, 0.0)
    run(free, 200, 0.0, measure=False)
    run(pushed, 200, 0.0, measure=False)
    d = np.array(pushed.y) - np.array(free.y)
    assert d[6] < -0.05 and np.abs(d[:6]).max() < 1e-9


@pytest.mark.parametrize('bad', [[float('nan')] * 7, [1.0] * 3, 'x', [float('inf')] + [0.0] * 6,
                                 RuntimeError])
def test_bad_coupling_is_dropped_not_raised(cdmp_text, bad):
    def coupling(y, yd):
        if bad is RuntimeError:
            raise RuntimeError('kinematics failed')
        return bad
    rs, prep = make_streamer(cdmp_text, timeout=0.0, coupling=coupling)
    ref, prep_r = make_streamer(cdmp_text, timeout=0.0)
    rs.activate(prep, 0.0)
    ref.activate(prep_r, 0.0)
    for _ in range(50):
        assert rs.advance(1, 0.0) & StreamFlags.COUPLING_REJECTED
        ref.advance(1, 0.0)
    assert rs.y == ref.y


@settings(max_examples=12, deadline=None)
@given(st.lists(st.floats(-1e9, 1e9), min_size=7, max_size=7))
def test_any_strong_coupling_keeps_a_cdmp_inside_the_limits(acc):
    rs, prep = make_streamer(TEXT_CACHE['cdmp'], timeout=0.0, coupling=lambda y, yd: acc,
                             coupling_max_acceleration=0.0)  # unbounded: the stepper alone
    rs.activate(prep, 0.0)
    for _ in range(100):
        rs.advance(1, 0.0)
        y = np.array(rs.y)
        assert np.all(y >= LOWER) and np.all(y <= UPPER) and np.all(np.isfinite(rs.yd))


TEXT_CACHE = {'cdmp': dumps_primitive(reach_cdmp())}


def test_coupling_turning_away_from_a_saturated_limit_does_not_jump(cdmp_text):
    """A joint pushed into its upper limit (exogenous state saturated), then a coupling away
    from it: with the stepper's cap near saturation the reference leaves the limit
    continuously (uncapped it would jump to the other limit in one tick:
    test_core_coupling.py)."""

    def largest_step():
        push = {'a': 1e5}
        rs, prep = make_streamer(cdmp_text, timeout=0.0,
                                 coupling=lambda y, yd: [0.0, 0.0, 0.0, push['a'], 0.0, 0.0,
                                                         0.0],
                                 coupling_max_acceleration=0.0)  # the stepper's cap alone
        rs.activate(prep, 0.0)
        rec = []
        run(rs, 400, 0.0, measure=False, record=rec)
        assert UPPER[3] - rec[-1][0][3] < 1e-6  # held at (inside) the limit
        push['a'] = -10.0
        rec2 = [rec[-1]]
        run(rs, 400, 1.0, measure=False, record=rec2)
        assert all(LOWER[3] < r[0][3] < UPPER[3] for r in rec2)
        return max_step_changes(rec2)[0].max()
    assert largest_step() < 0.01  # rad per 2 ms tick


def test_plain_dmp_is_clamped_to_the_limits():
    rs, prep = make_streamer(dumps_primitive(reach_dmp()), timeout=0.0,
                             coupling=lambda y, yd: [0.0, 0.0, 0.0, 200.0, 0.0, 0.0, 0.0],
                             coupling_max_acceleration=0.0)
    rs.activate(prep, 0.0)
    flags = 0
    for _ in range(500):
        flags |= rs.advance(1, 0.0)
        y = np.array(rs.y)
        assert np.all(y >= LOWER) and np.all(y <= UPPER)
    assert flags & StreamFlags.CLAMPED and rs.y[3] == UPPER[3]


def test_bound_into_scales_the_largest_joint_to_the_limit_keeping_the_direction():
    from cdmp_ros.core.streaming.streamer import bound_into
    a = [3.0, -400.0, 0.0, 100.0, 0.0, 0.0, -1.0]
    out = [0.0] * 7
    assert bound_into(a, 50.0, out) == 400.0
    np.testing.assert_allclose(out, [0.375, -50.0, 0.0, 12.5, 0.0, 0.0, -0.125], rtol=1e-15)
    assert bound_into(a, 400.0, out) == 400.0 and out == a   # within the bound
    assert bound_into(a, 0.0, out) == 400.0 and out == a     # no bound
    assert bound_into(np.array(a), 50.0, out) == 400.0
    # not 7 finite numbers: -1 (the streamer hands the stepper a rejection)
    for bad in ([float('nan')] + [1e6] * 6, [1e6] * 6 + [float('inf')], [1.0] * 6,
                [1.0] * 8, 'xxxxxxx', 3.0, np.ones((1, 7)), [None] * 7):
        assert bound_into(bad, 50.0, out) == -1.0, bad


def _sphere_inside_link_case():
    """The streamed reach at tick 450 and a sphere (4 cm) centred on the axis of panda_link4,
    inside its 6 cm capsule, appearing then (the demo's drop that starts in the arm)."""
    import pybullet_data
    from cdmp_ros.core.kinematics import panda_chain
    from cdmp_ros.core.kinematics.closest import Sphere
    chain = panda_chain(os.path.join(pybullet_data.getDataPath(), 'franka_panda/panda.urdf'))
    free, prep = make_streamer(TEXT_CACHE['cdmp'], timeout=0.0)
    free.activate(prep, 0.0)
    run(free, 450, 0.0, measure=False)
    (name, a, b), = [seg for seg in chain.link_segments() if seg[0] == 'panda_link4']
    from cdmp_ros.core.kinematics import PointOfInterest
    pa, pb = chain.forward(np.array(free.y), [PointOfInterest(name, a), PointOfInterest(name, b)])
    return chain, Sphere(tuple(0.5 * (pa + pb)), 0.04)


@pytest.mark.parametrize('bound', [500.0, 50.0, 0.0])
def test_a_sphere_inside_a_link_gives_a_bounded_push(bound):
    """A sphere appearing inside a link's capsule: the repeller asks for a joint acceleration
    of ~1e5 rad/s^2 or more. Bounded (500 rad/s^2, the default, or 50) the coupling the
    stepper gets is the bound at most (flagged COUPLING_BOUNDED, the request reported in
    ``coupling_peak``) and the reference moves at most (vmax + bound dt) dt per tick;
    unbounded
    (0) the same sphere moves the reference by more than 0.1 rad in one tick (the defect the
    bound removes, seen in the demo as a 3 rad jump onto the limits)."""
    from cdmp_ros.core.coupling.obstacle import CouplingConfig, ObstacleCoupling
    from cdmp_ros.core.coupling.potential_fields import RepellerField
    chain, sphere = _sphere_inside_link_case()
    coupling = ObstacleCoupling(chain, ['panda_link4', 'panda_link6'],
                                RepellerField(gain=0.03, influence_distance=0.25),
                                config=CouplingConfig(link_radius=0.06))
    rs, prep = make_streamer(TEXT_CACHE['cdmp'], timeout=0.0, coupling=coupling,
                             obstacles=(), coupling_max_acceleration=bound)
    rs.activate(prep, 0.0)
    rec = []
    run(rs, 450, 0.0, measure=False, record=rec)
    rs.obstacles = (sphere,)
    flags, applied, first = 0, 0.0, None
    for _ in range(300):
        flags |= rs.advance(1, 0.0)
        first = rs.min_distance if first is None else first
        applied = max(applied, float(np.abs(rs._coupling_joint).max()))
        rec.append((list(rs.y), list(rs.yd), rs.state))
        assert np.all(np.array(rs.y) > LOWER) and np.all(np.array(rs.y) < UPPER)
    dy = max_step_changes(rec)[0]
    assert first < -0.05  # inside the capsule at the first evaluation
    if bound:
        assert flags & StreamFlags.COUPLING_BOUNDED and rs.coupling_peak > 100 * bound
        assert applied == pytest.approx(bound, rel=1e-9)
        assert dy.max() <= (VMAX.max() + bound * DT) * DT * (1 + 1e-9), dy.max()
        assert np.all(np.abs(np.array([r[1] for r in rec])) <= VMAX)
    else:
        assert not flags & StreamFlags.COUPLING_BOUNDED and rs.coupling_peak == 0.0
        assert applied > 1e4 and dy.max() > 0.1, (applied, dy.max())


def _free_ee_path(chain, text, n=1000):
    """End-effector positions of the uncoupled stream, one per tick."""
    from cdmp_ros.core.kinematics import PointOfInterest
    free, prep_f = make_streamer(text, timeout=0.0)
    free.activate(prep_f, 0.0)
    path = []
    for _ in range(n):
        free.advance(1, 0.0)
        path.append(chain.forward(np.array(free.y), [PointOfInterest('ee')])[0])
    return path


def test_streamed_coupling_with_a_sphere_keeps_the_hand_away():
    import pybullet_data
    from cdmp_ros.core.kinematics import PointOfInterest, panda_chain
    from cdmp_ros.core.kinematics.closest import Sphere
    from cdmp_ros.core.coupling.obstacle import ObstacleCoupling
    from cdmp_ros.core.coupling.potential_fields import RepellerField
    chain = panda_chain(os.path.join(pybullet_data.getDataPath(), 'franka_panda/panda.urdf'))
    text = TEXT_CACHE['cdmp']
    path = _free_ee_path(chain, text)
    mid = path[450]
    sphere = Sphere(tuple(mid), 0.04)
    coupling = ObstacleCoupling(chain, sphere_field=RepellerField(gain=0.05))
    rs, prep = make_streamer(text, timeout=0.0, coupling=coupling, obstacles=(sphere,))
    rs.activate(prep, 0.0)
    d_free = min(np.linalg.norm(p - mid) for p in path) - 0.04
    d_coupled = math.inf
    for _ in range(1000):
        rs.advance(1, 0.0)
        x = chain.forward(np.array(rs.y), [PointOfInterest('ee')])[0]
        d_coupled = min(d_coupled, np.linalg.norm(x - mid) - 0.04)
    assert d_free < 0.0 < d_coupled
    assert math.isfinite(rs.min_distance)


def test_limit_aware_streamed_coupling_keeps_joint_4_off_its_limit():
    """Issue 10.4 through the streamer: the reach and sphere of test_core_coupling.LIMIT_CASES
    where link avoidance (Eq. 12) drives panda_joint4 onto its limit (usage > 0.999); with the
    limit-aware Eq. 12 (the default) every joint stays below 0.98 and the links keep clear of
    the sphere (farther than without coupling)."""
    import pybullet_data
    from cdmp_ros.core.coupling.potential_fields import RepellerField
    from cdmp_ros.core.kinematics import panda_chain
    from cdmp_ros.core.kinematics.closest import Sphere
    from cdmp_ros.core.coupling.obstacle import CouplingConfig, ObstacleCoupling
    from test_core_coupling import LIMIT_CASES
    chain = panda_chain(os.path.join(pybullet_data.getDataPath(), 'franka_panda/panda.urdf'))
    joint, start, goal, center = LIMIT_CASES['panda_joint4']
    text = dumps_primitive(reach_cdmp(np.array(start), np.array(goal)))
    centre, delta = (LOWER + UPPER) / 2, (UPPER - LOWER) / 2

    def stream(config, gain):
        field = RepellerField(gain=gain, influence_distance=0.2, min_distance=0.005)
        coupling = ObstacleCoupling(chain, ['panda_link3', 'panda_link5'], field, config=config)
        rs, prep = make_streamer(text, timeout=0.0, coupling=coupling,
                                 obstacles=(Sphere(center, 0.03),))
        rs.activate(prep, 0.0)
        usage, dist = np.zeros(7), math.inf
        for _ in range(1500):
            rs.advance(1, 0.0)
            usage = np.maximum(usage, np.abs(np.array(rs.y) - centre) / delta)
            dist = min(dist, min(coupling.last_distances[1:]))
        return usage, dist

    u_old, _ = stream(CouplingConfig(limit_aware=False), 0.01)
    u_new, d_new = stream(CouplingConfig(), 0.01)
    _, d_free = stream(CouplingConfig(), 0.0)
    assert u_old[joint] > 0.999
    assert u_new.max() < 0.98
    assert d_new > d_free + 0.01


def test_streamed_coupling_with_a_rotated_box_keeps_the_hand_out():
    """A box rotated 30 deg about z (an oriented CUBE marker) across the free path: the
    streamed end effector stays outside it (signed distance from OrientedBox)."""
    import pybullet_data
    from cdmp_ros.core.kinematics import OrientedBox, PointOfInterest, panda_chain
    from cdmp_ros.core.coupling.potential_fields import ConstantField
    from cdmp_ros.core.coupling.obstacle import ObstacleCoupling
    chain = panda_chain(os.path.join(pybullet_data.getDataPath(), 'franka_panda/panda.urdf'))
    text = TEXT_CACHE['cdmp']
    path = _free_ee_path(chain, text)
    q = (0.0, 0.0, math.sin(math.pi / 12), math.cos(math.pi / 12))
    box = OrientedBox.from_quaternion(tuple(path[450]), (0.06, 0.06, 0.06), q)
    coupling = ObstacleCoupling(chain, links=(),
                                box_field=ConstantField(magnitude=20.0, influence_distance=0.1))
    rs, prep = make_streamer(text, timeout=0.0, coupling=coupling, obstacles=(box,))
    rs.activate(prep, 0.0)
    d_free = min(box.signed_distance(np.array(path))[0])
    X = []
    for _ in range(1000):
        rs.advance(1, 0.0)
        X.append(chain.forward(np.array(rs.y), [PointOfInterest('ee')])[0])
    d_coupled = min(box.signed_distance(np.array(X))[0])
    assert d_free < 0.0 < d_coupled, (d_free, d_coupled)


# -- prepare_primitive -------------------------------------------------------------------------
def test_prepare_rejects_malformed_json(cdmp_text):
    with pytest.raises(PrimitiveFileError, match='primitive: not valid JSON'):
        prepare_primitive(cdmp_text[:-3], PANDA_JOINTS, DT, LOWER, UPPER)
    with pytest.raises(PrimitiveFileError, match='JSON object'):
        prepare_primitive('[1, 2]', PANDA_JOINTS, DT, LOWER, UPPER)


def test_prepare_rejects_schema_violations_naming_the_field(cdmp_text):
    d = json.loads(cdmp_text)
    d['dmp']['alpha_y'] = 'stiff'
    with pytest.raises(PrimitiveFileError, match=r'primitive\.dmp\.alpha_y'):
        prepare_primitive(json.dumps(d), PANDA_JOINTS, DT, LOWER, UPPER)
    d = json.loads(cdmp_text)
    d['duration'] = 2e-3  # a valid duration that cannot be integrated at 2 ms
    with pytest.raises(PrimitiveFileError, match='dt'):
        prepare_primitive(json.dumps(d), PANDA_JOINTS, DT, LOWER, UPPER)


def test_prepare_rejects_other_joints(cdmp_text):
    d = json.loads(cdmp_text)
    d['joint_names'][2] = 'elbow'
    with pytest.raises(PrimitiveFileError, match=r"missing \['panda_joint3'\].*unknown \['elbow"):
        prepare_primitive(json.dumps(d), PANDA_JOINTS, DT, LOWER, UPPER)


def test_prepare_reorders_shuffled_joints():
    perm = [3, 0, 6, 1, 5, 2, 4]
    names = [PANDA_JOINTS[i] for i in perm]
    from cdmp_ros.core.dmp.dmp import CDMP
    from streamer_harness import reach_demo
    T, Y = reach_demo()
    shuffled = CDMP(LOWER[perm], UPPER[perm], joint_names=names).fit(T, Y[:, perm])
    prep = prepare_primitive(dumps_primitive(shuffled), PANDA_JOINTS, DT, LOWER, UPPER)
    assert prep.prim.joint_names == list(PANDA_JOINTS) and 'reordered' in prep.notes[0]
    a = prep.prim.rollout(DT)
    b = shuffled.rollout(DT)
    np.testing.assert_allclose(a.Y[:, perm], b.Y, atol=1e-12)


def test_prepare_streams_a_promp_through_its_mean():
    from cdmp_ros.core.promp.promp import ProMP, RbfBasis
    from streamer_harness import reach_demo
    T, Y = reach_demo(duration=2.0, n=201)
    basis = RbfBasis.uniform(15)
    promp = ProMP.fit([(T, Y)], basis, duration=2.0, joint_names=PANDA_JOINTS)
    prep = prepare_primitive(dumps_primitive(promp), PANDA_JOINTS, DT, LOWER, UPPER, VMAX)
    assert prep.kind == 'promp' and prep.prim.kind == 'cdmp'
    tr = prep.prim.rollout(DT, velocity_limits=VMAX)
    mean = promp.mean(tr.T / 2.0)
    assert np.abs(tr.Y - mean).max() < 0.02
    assert primitive_to_dict(prep.prim)['kind'] == 'cdmp'


# -- the streamer's coupling from its parameters (tcp_offset, box_field_kind) -----------------
def _pybullet_link_positions(q, links):
    """World positions of ``links`` of pybullet's Panda at the arm configuration ``q``."""
    import pybullet as p
    import pybullet_data
    cid = p.connect(p.DIRECT)
    try:
        body = p.loadURDF(os.path.join(pybullet_data.getDataPath(), 'franka_panda/panda.urdf'),
                          useFixedBase=True, physicsClientId=cid)
        index = {}
        for j in range(p.getNumJoints(body, physicsClientId=cid)):
            info = p.getJointInfo(body, j, physicsClientId=cid)
            index[info[12].decode()] = j
            name = info[1].decode()
            if name in PANDA_JOINTS:
                p.resetJointState(body, j, q[PANDA_JOINTS.index(name)], physicsClientId=cid)
        return [np.array(p.getLinkState(body, index[link], computeForwardKinematics=True,
                                        physicsClientId=cid)[4]) for link in links]
    finally:
        p.disconnect(cid)


def test_streamer_coupling_acts_on_the_fingertips_by_default():
    """The end-effector term (Eq. 7) of the streamer's coupling acts on the tool centre point
    tcp_offset, by default the Panda's fingertips (pybullet's panda_grasptarget), not on the
    flange (panda_hand): a sphere centred on the point has distance -radius from it."""
    import pybullet_data
    from cdmp_ros.core.kinematics import panda_chain
    from cdmp_ros.core.kinematics.closest import Sphere
    from cdmp_ros.core.streaming.streamer import streamer_coupling
    chain = panda_chain(os.path.join(pybullet_data.getDataPath(), 'franka_panda/panda.urdf'))
    q = np.array([0.3, -0.5, 0.2, -2.1, 0.1, 1.8, 0.6])
    tips, flange = _pybullet_link_positions(q, ['panda_grasptarget', 'panda_hand'])
    assert np.linalg.norm(tips - flange) == pytest.approx(0.105, abs=1e-6)  # pybullet: float32
    for cfg, point in ((StreamerConfig(), tips), (StreamerConfig(tcp_offset=(0, 0, 0)), flange)):
        coupling = streamer_coupling(chain, cfg)
        coupling.joint_acceleration(q, None, [Sphere(tuple(point), 0.01)])
        assert coupling.last_distances[0] == pytest.approx(-0.01, abs=1e-6)
    with pytest.raises(ValidationError, match='tcp_offset'):
        StreamerConfig(tcp_offset=(0.0, 0.1))


def test_streamer_coupling_uses_the_board_field_when_selected():
    """box_field_kind 'board': boxes get the board field of Eq. 30-31 (numpy oracle: the field
    at the fingertips mapped by Eq. 7); 'constant' (default): the constant field of IV-B."""
    import pybullet_data
    from cdmp_ros.core.coupling.potential_fields import BoardField, ConstantField
    from coupling_oracle import end_effector_term
    from cdmp_ros.core.kinematics import PointOfInterest, panda_chain
    from cdmp_ros.core.kinematics.closest import Box, box_signed_distance
    from cdmp_ros.core.streaming.streamer import streamer_coupling
    chain = panda_chain(os.path.join(pybullet_data.getDataPath(), 'franka_panda/panda.urdf'))
    q = np.array([0.3, -0.5, 0.2, -2.1, 0.1, 1.8, 0.6])
    X, J = chain.forward_and_jacobian(q[None], [PointOfInterest('ee')])
    x, J_e = X[0, 0], J[0, 0]
    board = Box(tuple(x + [-0.2, -0.3, 0.05]), tuple(x + [0.2, 0.05, 0.07]))  # just above
    field = BoardField(beta_y=0.02, beta_z=0.01, alpha=0.5, goal_height=float(x[2]) - 0.2)
    with pytest.raises(ValidationError, match='box_field_kind'):
        StreamerConfig(box_field_kind='wall')
    cfg = StreamerConfig(box_field_kind='board', coupling_links=())
    coupling = streamer_coupling(chain, cfg, board_field=field)
    assert coupling.box_field is field
    got = coupling.joint_acceleration(q, None, [board])
    d, _, n = box_signed_distance(x, board.lower, board.upper)
    dx = field.acceleration(x, (0.0, 0.0, 0.0), board, float(d), n)
    assert dx[1] > 0.0 and dx[2] < 0.0                    # Eq. 30: towards the edge, down
    expected = end_effector_term(J_e, np.array(dx), coupling.config.damping)
    np.testing.assert_allclose(got, expected, rtol=1e-9, atol=1e-12)
    constant = streamer_coupling(chain, StreamerConfig(coupling_links=()),
                                 box_field=ConstantField(magnitude=2.0, influence_distance=0.1))
    assert isinstance(constant.box_field, ConstantField)
    assert np.abs(np.subtract(constant.joint_acceleration(q, None, [board]), got)).max() > 1e-3


# -- acceleration across a switch (issue 13) ---------------------------------------------------
def fd_acceleration_changes(blend_time, coupling=None, switch_at=400, n=700):
    """Stream a reach, switch to another primitive at step ``switch_at``; returns the largest
    tick-to-tick change of the finite-difference acceleration [rad/s^2] before the switch, in
    the 60 steps after it, and the largest |yd| change over the run."""
    cfg = StreamerConfig(joint_states_timeout=0.0, switch_blend_time=blend_time)
    rs = ReferenceStreamer(LOWER, UPPER, cfg, coupling=coupling)
    if coupling is not None:
        rs.obstacles = ('an obstacle',)  # the coupling is only asked with obstacles
    other = np.array([-0.4, -0.1, -0.15, -1.5, -0.1, 1.0, -0.15])
    a, b = (prepare_primitive(dumps_primitive(reach_cdmp(Q_START, g, 2.0)), PANDA_JOINTS,
                              cfg.dt, LOWER, UPPER, VMAX) for g in (Q_GOAL, other))
    t = 0.0
    rs.activate(a, t)
    rec = []
    for k in range(n):
        t += cfg.dt
        if k == switch_at:
            assert 'switched in' in rs.activate(b, t)
        rs.advance(1, t)
        rec.append((list(rs.y), list(rs.yd), rs.state))
    Y = np.array([r[0] for r in rec])
    assert np.all((Y > LOWER) & (Y < UPPER))
    acc = np.diff(Y, 2, axis=0) / cfg.dt ** 2
    dacc = np.abs(np.diff(acc, axis=0)).max(axis=1)
    _, dyd = max_step_changes(rec)
    return dacc[:switch_at - 5].max(), dacc[switch_at - 5:switch_at + 60].max(), dyd.max()


class ConstantCoupling:
    """A Coupling (core/coupling/contract.py) of constant joint acceleration."""
    last_distances = [0.5]

    def joint_acceleration(self, q, qd, obstacles):
        return [3.0, -2.0, 2.0, 0.0, 1.0, 0.0, 0.0]


@pytest.mark.parametrize('coupling', [None, ConstantCoupling()], ids=['free', 'coupled'])
def test_switch_keeps_the_acceleration_continuous(coupling):
    normal, jump, _ = fd_acceleration_changes(0.0, coupling)
    assert jump > 100 * normal  # without blending the acceleration jumps at the switch
    blend = 0.05
    normal_b, switched, dyd = fd_acceleration_changes(blend, coupling)
    assert normal_b == pytest.approx(normal)
    # the difference fades out with a quintic weight: per step at most 1.875 dt / T of it
    # (+ the normal change), here about 14 x smaller than the jump
    assert switched < 1.875 * 0.002 / blend * jump * 1.1 + 2 * normal
    assert dyd < 0.05  # rad/s per step: velocity continuous throughout


# -- an adaptation continues the running motion at its phase (issue 13) -------------------------
def test_a_continuing_switch_keeps_the_phase_and_does_not_replay_the_motion(cdmp_text):
    """Switching in the same motion with ``continues`` at 40 % of it changes nothing (the
    stepper resumes at the current phase: the streamed reference equals the uninterrupted
    one), while a restart at phase 0 replays the whole movement from the current state (it
    arrives about as late as the full duration after the switch)."""
    def stream(continues):
        rs, prep = make_streamer(cdmp_text, timeout=0.0, switch_blend_time=0.05)
        same = prepare_primitive(cdmp_text, PANDA_JOINTS, rs.dt, LOWER, UPPER, VMAX)
        rs.activate(prep, 0.0)
        rec = []
        t = run(rs, 400, 0.0, measure=False, record=rec)  # 0.8 s of the 2 s reach
        text = rs.activate(same, t, continues=continues)
        run(rs, 1200, t, measure=False, record=rec)
        return text, np.array([r[0] for r in rec]), np.array([r[1] for r in rec])

    text_c, Y_c, Yd_c = stream(True)
    assert 'at phase 0.4' in text_c
    rs, prep = make_streamer(cdmp_text, timeout=0.0)
    rs.activate(prep, 0.0)
    rec = []
    run(rs, 1600, 0.0, measure=False, record=rec)
    Y_ref = np.array([r[0] for r in rec])
    np.testing.assert_allclose(Y_c, Y_ref, atol=1e-9)
    _, Y_r, Yd_r = stream(False)
    # the restart replays the reach: still far from the goal 1.2 s after the switch, while
    # the continued motion is there
    err_c = np.abs(Y_c[1000] - Q_GOAL).max()
    err_r = np.abs(Y_r[1000] - Q_GOAL).max()
    assert err_c < 0.02 and err_r > 5 * err_c, (err_c, err_r)


def test_a_continuing_switch_to_a_reshaped_motion_is_jump_free():
    """An adaptation that bends the rest of the motion, switched in mid-motion at its phase:
    position and velocity continuous, the acceleration blended (as any switch), and the rest
    follows the new primitive's own trajectory from that phase on."""
    cfg = StreamerConfig(joint_states_timeout=0.0, switch_blend_time=0.05)
    rs = ReferenceStreamer(LOWER, UPPER, cfg)
    other = np.array([-0.4, -0.1, -0.15, -1.5, -0.1, 1.0, -0.15])
    a = prepare_primitive(dumps_primitive(reach_cdmp(Q_START, Q_GOAL, 2.0)), PANDA_JOINTS,
                          cfg.dt, LOWER, UPPER, VMAX)
    b = prepare_primitive(dumps_primitive(reach_cdmp(Q_START, other, 2.0)), PANDA_JOINTS,
                          cfg.dt, LOWER, UPPER, VMAX)
    rs.activate(a, 0.0)
    rec = []
    t = run(rs, 500, 0.0, measure=False, record=rec)
    rs.activate(b, t, continues=True)
    assert rs.active.stepper.output.u == pytest.approx(500 * cfg.dt / a.prim.tau_, abs=1e-9)
    run(rs, 1500, t, measure=False, record=rec)
    Y = np.array([r[0] for r in rec])
    dy, dyd = max_step_changes(rec)
    assert dy[499] <= 1.5 * dy[497] + 1e-9 and dyd[499] <= 0.05
    acc = np.diff(Y, 2, axis=0) / cfg.dt ** 2
    dacc = np.abs(np.diff(acc, axis=0)).max(axis=1)
    assert dacc[495:560].max() < 20 * dacc[400:490].max() + 50.0
    np.testing.assert_allclose(Y[-1], other, atol=2e-2)


def test_stepper_reset_at_a_phase_continues_the_integration():
    """``DmpStepper.reset(phase_u=u)`` from the state at step K equals the uninterrupted
    integration (CDMP and DMP), and bad phases are refused."""
    from cdmp_ros.core.dmp.stepper import DmpStepper, StepInput
    from streamer_harness import reach_dmp
    for prim, vmax in ((reach_cdmp(), None), (reach_dmp(), None), (reach_cdmp(), 10 * VMAX)):
        run_a = DmpStepper(prim, 0.002, velocity_limits=vmax)   # 10 VMAX: kappa stays 1
        inp = StepInput(7)
        Y = []
        for k in range(900):
            out, _ = run_a.update(inp)
            Y.append(list(out.y))
            if k == 299:
                y, yd, u = list(out.y), list(out.yd), out.u
        b = DmpStepper(prim, 0.002, velocity_limits=vmax)
        b.reset(start_y=y, start_yd=yd, phase_u=np.float64(u))
        assert b.output.u == pytest.approx(u)
        Yb = [list(b.update(inp)[0].y) for _ in range(600)]
        np.testing.assert_allclose(Yb, Y[300:], atol=1e-8)
    for bad in (-0.1, float('nan'), float('inf'), 'x', True, None):
        with pytest.raises(ValidationError, match='phase_u'):
            b.reset(phase_u=bad)


def test_a_stop_keeps_the_tighter_limits_of_the_active_cdmp():
    """A stale-input stop from speed next to a primitive limit that is tighter than the
    robot's (panda_joint2 at 0.39, moving up at 0.8 rad/s, the primitive's limit 0.4) stays
    inside it; the robot's limits (1.83) would let it run 0.2 rad past it (checked here), and
    the next start then clipped the reference back in one tick."""
    from streamer_harness import wide_narrow_cdmp
    rs, prep = make_streamer(dumps_primitive(wide_narrow_cdmp()), timeout=0.5)
    rs.note_joint_states(Q_START, 0.0)
    rs.activate(prep, 0.0)
    t = run(rs, 200, 0.0)
    assert rs.state is StreamState.RUNNING
    rs.y[1], rs.yd[1] = 0.39, 0.8
    wide = SmoothStop(rs.transform, rs.y, rs.yd, rs.config.stop_time)
    y, yd, ydd = list(rs.y), list(rs.yd), [0.0] * 7
    while not wide.advance(rs.dt, y, yd, ydd):
        pass
    assert y[1] > 0.5                       # the robot's limits: far past the primitive's
    top = []
    t += 0.6                                # no joint_states for 0.6 s: stop, then hold
    for _ in range(600):
        t += rs.dt
        rs.advance(1, t)
        top.append(rs.y[1])
    assert rs.state is StreamState.HOLDING
    assert max(top) < 0.4 and max(top) > 0.39
    # fresh inputs again: the motion restarts from the held reference without a clip
    rs.note_joint_states(rs.y, t)
    text = rs.activate(prep, t)
    assert 'clipped' not in text, text


def _settle(epsilon, seconds=15.0):
    """Stream the fixture of a demo run that went round a limit cycle (test/data/
    limit_cycle.json) with the demo graph's coupling and ``damping.epsilon``; returns the
    largest joint speed of the last 2 s."""
    import dataclasses
    from cdmp_ros.cli.cmd_bringup import streamer_configs
    here = os.path.dirname(__file__)
    from cdmp_ros.core.kinematics import panda_chain
    from cdmp_ros.core.kinematics.closest import Sphere
    from cdmp_ros.core.streaming.streamer import streamer_coupling
    from cdmp_ros.ros.robot_model import default_urdf_path, load_collision_capsules
    with open(os.path.join(here, 'data', 'limit_cycle.json')) as f:
        fix = json.load(f)
    configs = streamer_configs(os.path.join(here, '..', 'config', 'graphs', 'demo.yaml'))
    chain = panda_chain(default_urdf_path())
    cfg = dataclasses.replace(configs[''], joint_states_timeout=0.0)
    damping = dataclasses.replace(configs['damping'], epsilon=epsilon)
    coupling = streamer_coupling(
        chain, cfg, configs['coupling'], damping=damping, repeller=configs['repeller'],
        capsules=load_collision_capsules('', cfg.coupling_capsule_links, chain=chain))
    rs = ReferenceStreamer(chain.lower, chain.upper, cfg, coupling)
    prep = prepare_primitive(json.dumps(fix['primitive']), chain.joint_names, cfg.dt,
                             chain.lower, chain.upper, chain.velocity_limits)
    rs.activate(prep, 0.0)                     # open loop: holds its start
    rs.y[:], rs.yd[:] = fix['y'], fix['yd']    # the live reference after the last input
    rs.active.stepper.reset(start_y=fix['y'], start_yd=fix['yd'], phase_u=3.0)
    rs.state = StreamState.RUNNING
    rs.obstacles = (Sphere(tuple(fix['sphere']['center']), fix['sphere']['radius']),)
    n = int(seconds / cfg.dt)
    speeds = []
    for k in range(n):
        rs.advance(1, 0.0)
        if k >= n - int(2.0 / cfg.dt):
            speeds.append(max(abs(v) for v in rs.yd))
    return max(speeds)


def test_the_demo_coupling_comes_to_rest_beside_the_sphere():
    """The coupling's damped pseudo-inverses (damping.epsilon) decide whether a reference
    next to an obstacle comes to rest: with the default 0.02 the demo's reference went round a
    limit cycle for 85 s (a CI run); with the demo graph's 0.1 it rests."""
    assert _settle(0.1) < 1e-3
    # the default cycles from this state: the defect the demo's setting works around (when
    # the coupling is made stable for every damping, this line goes)
    assert _settle(0.02) > 0.1
