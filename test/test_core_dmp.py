"""DMP/CDMP equations (paper 000, Eq. 13-29) against independent computations."""
import json

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from cdmp_ros.core.dmp.basis import PhaseBasis, U_END
from cdmp_ros.core.dmp.dmp import CDMP, DMP, DmpConfig, limit_usage
from cdmp_ros.core.errors import CdmpError, ValidationError
from cdmp_ros.core.primitive_io import primitive_to_dict
from cdmp_ros.core.dmp.stepper import StepStatus
from cdmp_ros.core.dmp.transform import TanhTransform, XI_SAT


def min_jerk(T, y0, y1):
    s = (T - T[0]) / (T[-1] - T[0])
    p = 10 * s ** 3 - 15 * s ** 4 + 6 * s ** 5
    return y0 + np.outer(p, np.asarray(y1) - np.asarray(y0))


def bump_demo(n=201):
    T = np.linspace(0.0, 1.0, n)
    Y = min_jerk(T, [0.0, 0.5, -0.2], [1.0, -0.4, 0.3])
    Y[:, 0] += 0.3 * np.sin(np.pi * T) ** 2
    return T, Y


def test_phase_matches_canonical_ode():
    """Eq. (18): tau ds/dt = -alpha_s s, integrated numerically, equals exp(-alpha_s t/tau)."""
    b = PhaseBasis(10, alpha_s=3.0)
    tau = 1.7
    sol = solve_ivp(lambda t, s: -b.alpha_s * s / tau, (0, 2.0), [1.0], rtol=1e-11,
                    atol=1e-13, dense_output=True)
    t = np.linspace(0, 2.0, 50)
    np.testing.assert_allclose(b.phase(t / tau), sol.sol(t)[0], rtol=1e-8)


def test_features_sum_to_phase_and_tail_is_continuous():
    """Eq. (16): normalised kernels times s sum to s; the tail continues it smoothly."""
    b = PhaseBasis(25, alpha_s=4.0)
    u = np.linspace(0, U_END, 400)
    np.testing.assert_allclose(b.features(u).sum(axis=1), b.phase(u), rtol=1e-12)
    eps = 1e-9
    np.testing.assert_allclose(b.features(U_END + eps), b.features(U_END - eps), rtol=1e-6)
    assert np.all(b.features(U_END + 5.0) < b.features(U_END))


def _continuous_rhs(prim, goal_x, x0):
    cfg = prim.config
    tau = prim.tau_

    def rhs(t, state):
        n = prim.n_dims
        x, z, g = state[:n], state[n:2 * n], state[2 * n:]
        f = (prim.basis.features(t / tau) @ prim.weights_.T) * (g - x0)
        zdot = (cfg.alpha_y * (cfg.beta_y * (g - x) - z) + f) / tau
        return np.concatenate([z / tau, zdot, cfg.alpha_g * (goal_x - g) / tau])
    return rhs


@pytest.mark.parametrize('kind', ['dmp', 'cdmp'])
def test_rollout_converges_to_continuous_solution(kind):
    """Eq. (13)-(18)/(21)-(26) by semi-implicit Euler vs scipy's RK45 on the continuous ODE,
    including a goal change handled by the goal dynamics (Eq. 14/22)."""
    T, Y = bump_demo()
    prim = DMP(3) if kind == 'dmp' else CDMP([-1, -1, -1], [1.5, 1, 1])
    prim.fit(T, Y)
    new_goal = prim.goal_y_ + np.array([0.2, -0.1, 0.1])
    x0 = prim.to_internal(prim.start_y_)
    g_init = prim.to_internal(prim.goal_y_)
    gx = prim.to_internal(new_goal)
    # rollout: goal state starts at the new goal; emulate a changing goal with the stepper
    st = prim.stepper(1e-4)
    st.set_goal(new_goal)
    n_steps = 12000
    X = np.empty((n_steps, 3))
    for k in range(n_steps):
        o, _ = st.update(st.input)
        X[k] = o.xi
    sol = solve_ivp(_continuous_rhs(prim, gx, x0), (0, n_steps * 1e-4),
                    np.concatenate([x0, np.zeros(3), g_init]), rtol=1e-9, atol=1e-11,
                    t_eval=np.arange(1, n_steps + 1) * 1e-4, max_step=1e-3)
    err = np.max(np.abs(sol.y[:3].T - X))
    assert err < 5e-3, err


def test_learns_trajectory_generated_by_a_dmp():
    """Weights fitted to a DMP's own rollout reproduce it (regression of Eq. 13 solved for f)."""
    rng = np.random.default_rng(0)
    src = DMP(2, DmpConfig(n_weights_per_dim=15))
    src.set_parameters(rng.normal(0, 50, (2, 15)), [0.0, 1.0], [1.0, -1.0], 1.0)
    tr = src.rollout(dt=0.002)
    fitted = DMP(2, DmpConfig(n_weights_per_dim=15)).fit(tr.T, tr.Y)
    tr2 = fitted.rollout(dt=0.002)
    # The fitted goal is the demonstration's last sample (0.9 % short of the source's goal),
    # which bounds how closely the source can be reproduced.
    assert np.max(np.abs(tr2.Y - tr.Y)) < 1e-2
    assert fitted.fit_rms_error_ < 5e-3


def test_fit_several_demonstrations_of_different_lengths():
    T1 = np.linspace(0, 1.0, 101)
    T2 = np.linspace(0, 1.4, 141)
    d1 = min_jerk(T1, [0.0], [1.0])
    d2 = min_jerk(T2, [0.1], [1.1])
    prim = CDMP([-2], [2]).fit_demonstrations([(T1, d1), (T2, d2)])
    assert prim.tau_ == pytest.approx(1.2)
    np.testing.assert_allclose(prim.start_y_, [0.05])
    tr = prim.rollout(dt=0.001, tau=1.0, start_y=[0.0], goal_y=[1.0])
    ref = min_jerk(tr.T, [0.0], [1.0])
    assert np.sqrt(np.mean((tr.Y - ref) ** 2)) < 0.02


def test_temporal_scaling():
    """Doubling tau produces the same path in twice the time."""
    T, Y = bump_demo()
    prim = CDMP([-1, -1, -1], [1.5, 1, 1]).fit(T, Y)
    a = prim.rollout(dt=0.001, tau=1.0)
    b = prim.rollout(dt=0.002, tau=2.0)
    np.testing.assert_allclose(a.Y, b.Y, atol=1e-12)
    np.testing.assert_allclose(a.Yd, 2.0 * b.Yd, atol=1e-9)


def test_step_matches_vectorised_rollout():
    T, Y = bump_demo()
    for prim in (DMP(3).fit(T, Y), CDMP([-1, -1, -1], [1.5, 1, 1]).fit(T, Y)):
        tr = prim.rollout(dt=0.001, duration=2.5)
        st = prim.stepper(0.001)
        rows = []
        for _ in range(len(tr.T) - 1):
            o, status = st.update(st.input)
            rows.append(list(o.y) + list(o.yd) + list(o.ydd))
        rows = np.array(rows)
        np.testing.assert_allclose(rows[:, :3], tr.Y[1:], atol=1e-10)
        np.testing.assert_allclose(rows[:, 3:6], tr.Yd[1:], atol=1e-8)
        np.testing.assert_allclose(rows[:, 6:], tr.Ydd[1:], atol=1e-6)
        assert status & StepStatus.FINISHED


def test_cdmp_velocity_and_acceleration_are_derivatives():
    """Eq. (28)-(29) against finite differences of the produced positions."""
    T, Y = bump_demo()
    prim = CDMP([-0.2, -0.5, -0.3], [1.2, 0.6, 0.35]).fit(T, Y)
    dt = 1e-4
    tr = prim.rollout(dt=dt)
    fd_v = np.gradient(tr.Y, dt, axis=0)
    fd_a = np.gradient(tr.Yd, dt, axis=0)
    sl = slice(5, -5)
    scale_v = np.max(np.abs(tr.Yd))
    scale_a = np.max(np.abs(tr.Ydd))
    assert np.max(np.abs(fd_v[sl] - tr.Yd[sl])) < 1e-2 * scale_v
    assert np.max(np.abs(fd_a[sl] - tr.Ydd[sl])) < 1e-2 * scale_a


def test_transform_round_trip_and_clipping():
    tr = TanhTransform([-1.0, 0.0], [1.0, 3.0], margin=1e-3)
    y = np.array([[0.3, 2.9], [-0.99, 0.01]])
    np.testing.assert_allclose(tr.to_joint(tr.to_exogenous(y)), y, atol=1e-12)
    xi = tr.to_exogenous([[5.0, -7.0], [1.0, 0.0]])  # beyond and at the limits
    assert np.all(np.isfinite(xi))
    np.testing.assert_allclose(tr.to_joint(xi)[0], [1 - 1e-3, 1.5 - 1.5 * (1 - 1e-3)])
    huge = tr.to_joint([[1e300, -1e300]])
    assert np.all(huge > tr.y_min) and np.all(huge < tr.y_max)
    assert np.tanh(XI_SAT) < 1.0


def test_joint_coupling_to_exogenous_inverts_eq29():
    from cdmp_ros.core.dmp.stepper import joint_coupling_to_exogenous
    tr = TanhTransform([-1.0, -2.0], [1.0, 2.0])
    xi, xid, xidd = np.array([0.4, -1.2]), np.array([0.3, 0.7]), np.array([1.0, -2.0])
    dydd = np.array([0.5, -0.25])
    tau = 1.5
    P = [0.0, 0.0]
    joint_coupling_to_exogenous(dydd.tolist(), xi.tolist(), tau, tr.y_delta.tolist(), P)
    dxidd = np.array(P) / tau ** 2          # xi is far from saturation: the floor is inactive
    np.testing.assert_allclose(tr.acceleration(xi, xid, xidd + dxidd)
                               - tr.acceleration(xi, xid, xidd), dydd, rtol=1e-12)


def test_goal_beyond_limits_cdmp_stays_inside_dmp_does_not():
    T = np.linspace(0, 1, 101)
    Y = min_jerk(T, [0.0], [0.5])
    lo, hi = [-1.0], [1.0]
    cd = CDMP(lo, hi).fit(T, Y)
    dm = DMP(1).fit(T, Y)
    a = cd.rollout(goal_y=[3.0], duration=3.0)
    b = dm.rollout(goal_y=[3.0], duration=3.0)
    assert limit_usage(a.Y, lo, hi) < 1.0
    assert limit_usage(b.Y, lo, hi) > 1.0


def test_velocity_limit_coupling_holds_limits_and_recovers():
    T = np.linspace(0, 1, 201)
    Y = min_jerk(T, [0.0, 0.0], [1.0, -0.5])
    prim = CDMP([-2, -2], [2, 2]).fit(T, Y)
    free = prim.rollout(dt=0.001, duration=3.0)
    vmax = np.array([1.2, 1.0])
    assert np.any(np.abs(free.Yd) > vmax)  # the nominal motion is too fast
    lim = prim.rollout(dt=0.001, duration=3.0, velocity_limits=vmax)
    assert np.all(np.abs(lim.Yd) <= vmax)  # exactly: a driver may check it strictly
    fd = np.diff(lim.Y, axis=0) / 0.001
    assert np.all(np.abs(fd) <= vmax * 1.01)
    np.testing.assert_allclose(lim.Y[-1], [1.0, -0.5], atol=0.02)  # still reaches the goal
    st = prim.stepper(0.001, velocity_limits=vmax)
    kappas, flags = [], 0
    for _ in range(3000):
        o, s = st.update(st.input)
        kappas.append(o.kappa)
        flags |= s
    assert min(kappas) < 0.95 and kappas[-1] == 1.0  # slowed, then back to nominal speed
    assert flags & StepStatus.VELOCITY_LIMITED


def test_velocity_limits_hold_under_a_strong_coupling_term():
    """An obstacle coupling term (internal units) that alone would drive the joints far
    beyond their velocity limits: the reported velocities stay within them, exactly."""
    T = np.linspace(0, 1, 201)
    Y = min_jerk(T, [0.0, 0.0], [1.0, -0.5])
    prim = CDMP([-2, -2], [2, 2]).fit(T, Y)
    vmax = np.array([1.2, 1.0])
    rng = np.random.default_rng(3)
    for _ in range(20):
        c = rng.normal(0.0, 1.0, 2) * 10.0 ** rng.uniform(1, 6)
        st, free = prim.stepper(0.001, velocity_limits=vmax), prim.stepper(0.001)
        peak, free_peak = np.zeros(2), np.zeros(2)
        for k in range(1500):
            for s_ in (st, free):
                s_.input.coupling[:] = c if 200 <= k < 600 else [0.0, 0.0]
            o, _ = st.update(st.input)
            peak = np.maximum(peak, np.abs(o.yd))
            free_peak = np.maximum(free_peak, np.abs(free.update(free.input)[0].yd))
        assert np.all(peak <= vmax), (c, peak)
        assert np.all(np.isfinite(peak))
    assert np.any(free_peak > vmax)  # without the limits the same term is too fast


def test_stepper_never_raises_on_garbage_input():
    T, Y = bump_demo()
    prim = CDMP([-1, -1, -1], [1.5, 1, 1]).fit(T, Y)
    st = prim.stepper(0.002)
    for bad in ([np.nan, 0.0, 1.0], [np.inf, -np.inf, 0.0], [1.0], ['x', None, 2.0], None,
                [1e308, 1e308, 1e308]):
        st.input.coupling = bad
        o, s = st.update(st.input)
        assert s & StepStatus.INPUT_REJECTED, bad
        assert np.all(np.isfinite(o.y)) and np.all(np.isfinite(o.yd))
        assert np.all(np.isfinite(o.ydd))
    st.input.coupling = [0.0, 0.0, 0.0]
    o, s = st.update(st.input)
    assert not s & StepStatus.INPUT_REJECTED


def test_invalid_configuration_is_named():
    with pytest.raises(ValidationError, match='alpha_y'):
        DmpConfig(alpha_y=-1.0)
    with pytest.raises(ValidationError, match='n_weights_per_dim'):
        DmpConfig(n_weights_per_dim=0)
    with pytest.raises(ValidationError, match='y_min'):
        CDMP([0.0, 1.0], [1.0, 1.0])
    with pytest.raises(ValidationError, match=r'demos\[0\].Y'):
        DMP(2).fit(np.linspace(0, 1, 10), np.zeros((10, 3)))
    with pytest.raises(ValidationError, match='finite'):
        DMP(1).fit(np.linspace(0, 1, 10), np.full((10, 1), np.nan))
    with pytest.raises(CdmpError, match='not fitted'):
        DMP(1).rollout()
    T, Y = bump_demo()
    with pytest.raises(ValueError, match='dt'):
        DMP(3).fit(T, Y).stepper(0.1, tau=0.1)


def recompute_from_file(d, dt, n_steps):
    """Independent implementation of the schema's formulas, from the file alone."""
    b, dm = d['basis'], d['dmp']
    c, h_w = np.array(b['centers']), np.array(b['widths'])
    W = np.array(dm['weights'])
    tau, a_s = d['duration'], d['phase']['alpha_s']
    if d['kind'] == 'cdmp':
        lo, hi = np.array(d['limits']['lower']), np.array(d['limits']['upper'])
        yo, yde = (lo + hi) / 2, (hi - lo) / 2
        m = dm['demo_margin']

        def to_x(y):
            return np.arctanh((np.clip(y, yo - (1 - m) * yde, yo + (1 - m) * yde) - yo) / yde)

        def to_y(x):
            return yde * np.tanh(x) + yo
    else:
        def to_x(y):
            return np.array(y, dtype=float)

        def to_y(x):
            return x
    x = to_x(np.array(dm['start']))
    x0 = x.copy()
    g = to_x(np.array(dm['goal']))
    g0 = g.copy()
    z = np.zeros_like(x)
    u = 0.0
    out = [to_y(x)]
    for _ in range(n_steps - 1):
        s = np.exp(-a_s * u)
        psi = np.exp(-0.5 * h_w * (s - c) ** 2)
        f = (W @ (psi * s / psi.sum())) * (g - x0)
        rate = dm['alpha_y'] * (dm['beta_y'] * (g - x) - z) + f
        z = z + dt / tau * rate
        x = x + dt / tau * z
        g = g + dt / tau * dm['alpha_g'] * (g0 - g)
        u += dt / tau
        out.append(to_y(x))
    return np.array(out)


@pytest.mark.parametrize('kind', ['dmp', 'cdmp'])
def test_trajectory_recomputable_from_file_alone(kind):
    T, Y = bump_demo()
    prim = DMP(3) if kind == 'dmp' else CDMP([-1, -1, -1], [1.5, 1, 1])
    prim.fit(T, Y)
    d = json.loads(json.dumps(primitive_to_dict(prim)))
    tr = prim.rollout(dt=0.002)
    np.testing.assert_allclose(recompute_from_file(d, 0.002, len(tr.T)), tr.Y, atol=1e-9)
