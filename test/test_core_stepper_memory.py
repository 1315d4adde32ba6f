"""The stepper's memory does not grow with the duration (issue 31, item 5).

The forcing profile is held on a grid over the phase whose size depends on the basis only
(quintic Hermite interpolation between its nodes, see :mod:`cdmp_ros.core.dmp.stepper`).

Stated tolerance: a stepper's positions equal those of the same semi-implicit Euler scheme run
with the forcing evaluated exactly (``basis.features(u) @ weights.T`` at every step) within
``1e-9`` rad, for 1 s and 300 s primitives, both streaming periods, the velocity-limited time
scaling and ``reset(phase_u=...)``. Justification: the forcing of joint ``d`` is within
``feature_error * sum_j |w_dj|`` of the exact one (checked below), and the transformation system
(critically damped, static gain ``1 / (alpha_y beta_y)``) maps a forcing error ``e`` on
``f (g - x0)`` to at most ``e |g - x0| / (alpha_y beta_y)`` in ``x`` (and ``y_delta`` times that
in ``y``): about 1e-11 rad for these primitives. The measured differences are below 1e-13 rad.
"""
import math
import tracemalloc

import numpy as np
import pytest

from cdmp_ros.core.dmp.basis import PhaseBasis, U_END
from cdmp_ros.core.dmp.dmp import CDMP, DMP, DmpConfig
from cdmp_ros.core.dmp.stepper import (FEATURE_TOL, MAX_GRID_INTERVALS, VMAX_BACKOFF,
                                       DmpStepper, StepStatus, feature_derivatives,
                                       grid_intervals, hermite_weights)
from cdmp_ros.core.joint_limits import PANDA_DATASHEET

LOWER = np.asarray(PANDA_DATASHEET['lower'])
UPPER = np.asarray(PANDA_DATASHEET['upper'])
VMAX = np.asarray(PANDA_DATASHEET['velocity'])
Q_START = np.array([0.0, -0.5, 0.0, -2.0, 0.0, 1.5, 0.7])
Q_GOAL = np.array([0.8, 0.2, 0.3, -1.2, 0.2, 2.0, 0.3])
#: Largest position difference from the exact-forcing integration [rad].
TOL_RAD = 1e-9

_FITTED = {}


def reach(duration, kind='cdmp', config=None):
    """A 7-joint Panda reach with a wiggle, fitted on the normalised time and stretched to
    ``duration`` (the weights do not depend on it)."""
    key = (kind, config)
    if key not in _FITTED:
        T = np.linspace(0.0, 1.0, 1001)
        s = 10 * T ** 3 - 15 * T ** 4 + 6 * T ** 5
        Y = Q_START + np.outer(s, Q_GOAL - Q_START)
        Y += 0.1 * np.outer(np.sin(2 * np.pi * T) * np.sin(np.pi * T), np.linspace(1, -1, 7))
        cfg = config or DmpConfig()
        _FITTED[key] = (CDMP(LOWER, UPPER, cfg) if kind == 'cdmp' else DMP(7, cfg)).fit(T, Y)
    f = _FITTED[key]
    cfg = config or DmpConfig()
    new = CDMP(LOWER, UPPER, cfg) if kind == 'cdmp' else DMP(7, cfg)
    return new.set_parameters(f.weights_, f.start_y_, f.goal_y_, duration)


def exact_run(prim, dt, n_steps, start_y=None, start_yd=None, phase_u=0.0, vmax=None,
              recovery_rate=2.0):
    """Positions of ``n_steps`` ticks of the stepper's scheme with the exact forcing (no
    coupling): an independent implementation of Eq. 13-18/21-29, paper 000, and of the
    velocity-limit time scaling documented in :mod:`cdmp_ros.core.dmp.stepper`."""
    cfg, tau = prim.config, prim.tau_
    h = dt / tau
    a, ab = cfg.alpha_y, cfg.alpha_y * cfg.beta_y
    W = prim.weights_
    sy = prim.start_y_ if start_y is None else np.asarray(start_y, dtype=float)
    syd = np.zeros(7) if start_yd is None else np.asarray(start_yd, dtype=float)
    x = prim.to_internal(sy)
    z = tau * prim.internal_velocity(x, syd)
    g = prim.to_internal(prim.goal_y_)
    g0 = g.copy()
    origin = prim.to_internal(prim.start_y_) if phase_u > 0 else x.copy()
    k = int(round(phase_u / h))
    u = k * h
    U = (k + 1 + np.arange(n_steps)) * h
    table = prim.basis.features(U) @ W.T if vmax is None else None  # exact at every step

    def forcing(u):
        return prim.basis.features(np.array([u]))[0] @ W.T

    cdmp = prim.kind == 'cdmp'
    ydel = prim.transform.y_delta if cdmp else None

    def scaled(kappa):  # after every step and at the start: recover, then respect the limits
        kappa = min(1.0, kappa + recovery_rate * dt)
        v = np.abs(z / tau * (ydel * (1.0 - np.tanh(x) ** 2) if cdmp else 1.0))
        for d in range(7):
            if v[d] * kappa > vmax[d]:
                kappa = vmax[d] / v[d] * VMAX_BACKOFF
        return kappa

    base = ab * (g - x) - a * z + forcing(u) * (g - origin)
    kappa = 1.0 if vmax is None else scaled(1.0)
    Y = np.empty((n_steps, 7))
    for i in range(n_steps):
        hk = h * kappa
        if vmax is None:
            u = U[i]
            f = table[i]
        else:
            u = u + hk
            f = forcing(u)
        z = z + hk * base
        x = x + hk * z
        g = g + (hk * cfg.alpha_g) * (g0 - g)
        base = ab * (g - x) - a * z + f * (g - origin)
        if vmax is not None:
            kappa = scaled(kappa)
        Y[i] = prim.from_internal(x, z, z)[0]
    return Y


def stepper_run(st, n_steps):
    inp = st.input
    Y = np.empty((n_steps, 7))
    flags = 0
    for i in range(n_steps):
        out, status = st.update(inp)
        Y[i] = out.y
        flags |= status
    return Y, flags


def float_count(st):
    """Floats held in the stepper's own lists and tuples (nested), the primitive excluded."""
    seen = set()

    def count(obj):
        if id(obj) in seen:
            return 0
        seen.add(id(obj))
        if isinstance(obj, float):
            return 1
        if isinstance(obj, (list, tuple)):
            return sum(count(v) for v in obj)
        return 0
    return sum(count(v) for k, v in vars(st).items() if k != 'prim')


# -- memory --------------------------------------------------------------------------------------
def test_the_forcing_grid_does_not_grow_with_the_duration():
    """Durations from 1 s to 3000 s at 2, 1 and 0.1 ms: the grid has at most the basis' phase
    grid of intervals (2048 for the default 30 kernels), and every long primitive the same."""
    m, err = grid_intervals(reach(1.0).basis)
    assert m == 2048 and err <= FEATURE_TOL
    bound = 3 * (m + 1) * 7
    sizes = {}
    for duration in (1.0, 30.0, 300.0, 3000.0):
        for dt in (0.002, 0.001, 0.0001):
            st = DmpStepper(reach(duration), dt, velocity_limits=VMAX)
            held = float_count(st)
            assert st.n_grid_intervals <= m
            assert st.table_floats == 3 * (st.n_grid_intervals + 1) * 7 <= bound
            assert held <= st.table_floats + 200  # + the state vectors of n_dims floats
            sizes[duration, dt] = held
            if U_END * duration / dt > m:  # a long primitive: the phase grid
                assert st.n_grid_intervals == m
                assert st.grid_step == U_END / m
            else:  # a short one: the nodes are the steps
                assert st.grid_step == dt / duration
    assert len({v for (d, dt), v in sizes.items() if d >= 30.0}) == 1


def test_the_retained_memory_does_not_grow_with_the_duration():
    """tracemalloc: what a stepper of 300 s at 1 ms keeps equals what one of 30 s keeps (the
    earlier table took 165 MB), about 1.8 MB for the default basis."""
    kept = []
    for duration in (30.0, 300.0):
        prim = reach(duration)
        grid_intervals(prim.basis)  # cached per basis
        tracemalloc.start()
        base = tracemalloc.get_traced_memory()[0]
        st = DmpStepper(prim, 0.001, velocity_limits=VMAX)
        kept.append(tracemalloc.get_traced_memory()[0] - base)
        tracemalloc.stop()
        del st
    assert kept[1] < 3_000_000
    assert abs(kept[1] - kept[0]) < 0.05 * kept[0]


def test_a_narrow_basis_is_capped_and_exact_at_the_steps_of_a_short_primitive():
    """A basis whose features no grid of MAX_GRID_INTERVALS resolves to FEATURE_TOL: the grid
    stays capped for a long primitive; a short one uses its steps as nodes (exact there)."""
    cfg = DmpConfig(basis_width=0.05)
    m, err = grid_intervals(reach(1.0, config=cfg).basis)
    assert m == MAX_GRID_INTERVALS and err > FEATURE_TOL
    long_ = DmpStepper(reach(300.0, config=cfg), 0.001)
    assert long_.n_grid_intervals == MAX_GRID_INTERVALS
    assert long_.table_floats == 3 * (MAX_GRID_INTERVALS + 1) * 7
    short = reach(1.0, config=cfg)
    st = DmpStepper(short, 0.002)
    assert st.n_grid_intervals == 1000 and st.grid_step == 0.002
    Y, _ = stepper_run(st, 600)
    np.testing.assert_allclose(Y, exact_run(short, 0.002, 600), rtol=0, atol=1e-12)


# -- the forcing ---------------------------------------------------------------------------------
def test_feature_derivatives_are_those_of_the_basis():
    """First and second derivatives in u against central differences of basis.features, on
    the exact formula and on the exponential tail beyond U_END."""
    for basis in (PhaseBasis(30, 4.0, 1.0), PhaseBasis(7, 2.5, 1.7), PhaseBasis(1, 4.0, 1.0)):
        u = np.concatenate([np.linspace(0.01, U_END - 0.01, 300), [2.3, 3.0, 5.0]])
        P, D, E = feature_derivatives(basis, u)
        np.testing.assert_allclose(P, basis.features(u), rtol=0, atol=1e-15)
        e = 1e-5
        fd1 = (basis.features(u + e) - basis.features(u - e)) / (2 * e)
        fd2 = (basis.features(u + e) - 2 * basis.features(u) + basis.features(u - e)) / e ** 2
        np.testing.assert_allclose(D, fd1, rtol=0, atol=1e-7 * max(1.0, np.abs(D).max()))
        np.testing.assert_allclose(E, fd2, rtol=0, atol=1e-4 * max(1.0, np.abs(E).max()))


def test_hermite_weights_reproduce_quintics():
    """The quintic Hermite basis interpolates any polynomial of degree 5 exactly."""
    c = np.array([0.3, -1.2, 2.0, 0.7, -0.4, 1.1])
    p = np.polynomial.Polynomial(c)
    data = [p(0.0), p.deriv(1)(0.0), p.deriv(2)(0.0), p(1.0), p.deriv(1)(1.0), p.deriv(2)(1.0)]
    for t in np.linspace(0.0, 1.0, 11):
        assert np.dot(hermite_weights(t), data) == pytest.approx(p(t), abs=1e-14)
    assert hermite_weights(0.0) == (1.0, 0.0, 0.0, 0.0, -0.0, 0.0)


@pytest.mark.parametrize('duration,dt', [(1.0, 0.002), (1.0, 0.001), (1.0, 0.0005),
                                         (30.0, 0.001), (300.0, 0.002), (300.0, 0.001)])
def test_the_interpolated_forcing_is_the_exact_one_at_random_phases(duration, dt):
    """|phi_d(u) - exact| <= (feature_error + 1e-14) sum_j |w_dj| at 3000 random phases in
    [0, 3] (the tail included), and feature_error <= FEATURE_TOL on a phase grid."""
    prim = reach(duration)
    st = DmpStepper(prim, dt)
    rng = np.random.default_rng(31)
    u = np.concatenate([rng.uniform(0.0, 3.0, 3000), np.arange(50) * st.grid_step])
    exact = prim.basis.features(u) @ prim.weights_.T
    got = np.array([st.forcing_profile(v) for v in u])
    bound = (st.feature_error + 1e-14) * np.abs(prim.weights_).sum(axis=1)
    assert np.all(np.abs(got - exact) <= bound), np.max(np.abs(got - exact) / bound)
    if st.grid_step != dt / duration:
        assert st.feature_error <= FEATURE_TOL
    assert np.max(np.abs(got - exact)) < 1e-9  # |f| up to 167; 2e-10 at most measured


# -- the trajectory ------------------------------------------------------------------------------
@pytest.mark.parametrize('kind,duration,dt', [('cdmp', 1.0, 0.002), ('cdmp', 1.0, 0.001),
                                              ('cdmp', 1.0, 0.0005), ('dmp', 1.0, 0.001),
                                              ('cdmp', 300.0, 0.002)])
def test_the_rollout_equals_the_exact_forcing_integration(kind, duration, dt):
    """The whole movement and part of the tail (1.2 tau), nominal speed."""
    prim = reach(duration, kind)
    n = int(round(1.2 * duration / dt))
    Y, flags = stepper_run(DmpStepper(prim, dt), n)
    ref = exact_run(prim, dt, n)
    assert np.max(np.abs(Y - ref)) <= TOL_RAD, np.max(np.abs(Y - ref))
    assert flags & StepStatus.FINISHED
    assert np.max(np.abs(Y[-1] - Y[0])) > 0.5  # it moved


@pytest.mark.parametrize('phase_u,n', [(0.5, 20000), (1.99, 14000)])
def test_a_300_s_primitive_at_1_ms_continues_at_a_phase_like_the_exact_integration(phase_u, n):
    """reset(phase_u=...) of a 300 s primitive at 1 ms from a state off its path (mid-motion,
    and across U_END into the basis' tail) against the exact forcing."""
    prim = reach(300.0)
    st = DmpStepper(prim, 0.001)
    y0 = Q_START + 0.4 * (Q_GOAL - Q_START) + 0.01
    yd0 = np.full(7, 0.02)
    st.reset(start_y=y0, start_yd=yd0, phase_u=phase_u)
    assert st.output.u == pytest.approx(phase_u, abs=1e-6)
    Y, _ = stepper_run(st, n)
    ref = exact_run(prim, 0.001, n, start_y=y0, start_yd=yd0, phase_u=phase_u)
    assert np.max(np.abs(Y - ref)) <= TOL_RAD, np.max(np.abs(Y - ref))
    assert st.output.u > U_END or phase_u < 1.0


@pytest.mark.parametrize('duration,dt', [(1.0, 0.002), (1.0, 0.001), (300.0, 0.002),
                                         (300.0, 0.001)])
def test_velocity_limited_time_scaling_equals_the_exact_integration(duration, dt):
    """Limits at half the nominal peak speed: the phase runs slower (off the nodes), from the
    start (1 s) or from the nominal state at reset(phase_u=0.3) (300 s, 4000 ticks)."""
    prim = reach(duration)
    free = prim.rollout(dt=dt)
    vmax = 0.5 * np.max(np.abs(free.Yd), axis=0) + 1e-9
    st = DmpStepper(prim, dt, velocity_limits=vmax)
    phase_u, n = (0.0, int(round(1.5 * duration / dt))) if duration < 10 else (0.3, 4000)
    k0 = int(round(phase_u * duration / dt))
    start, start_yd = free.Y[k0], free.Yd[k0]
    st.reset(start_y=start, start_yd=start_yd, phase_u=phase_u)
    Y, flags = stepper_run(st, n)
    assert flags & StepStatus.VELOCITY_LIMITED
    assert 0.0 < st.output.kappa < 1.0 or duration < 10
    ref = exact_run(prim, dt, n, start_y=start, start_yd=start_yd, phase_u=phase_u, vmax=vmax)
    assert np.max(np.abs(Y - ref)) <= TOL_RAD, np.max(np.abs(Y - ref))


def test_a_huge_phase_is_clamped_and_the_tick_stays_finite():
    st = DmpStepper(reach(300.0), 0.001, velocity_limits=VMAX)
    st.reset(phase_u=1e300)
    for _ in range(3):
        out, status = st.update(st.input)
        assert status & StepStatus.FINISHED
        assert all(math.isfinite(v) for v in out.y + out.yd + out.ydd)
