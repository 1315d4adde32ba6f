"""Obstacle coupling terms (paper 000, Eq. 7, 11, 12), damped pseudo-inverses, potential fields
(Eq. 30-31, IV-B constant field, repellers) and their assembly with the kinematics."""
import math

import numpy as np
import pybullet_data
import pytest

from cdmp_ros.core.coupling import (DampingConfig, coupling_3d, damped_pinv,
                                    damped_pinv_apply, end_effector_term, link_term,
                                    null_space_projector, scalar_coupling)
from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.fields import BoardField, ConstantField, RepellerField
from cdmp_ros.core.kinematics import PointOfInterest, panda_chain, planar_chain
from cdmp_ros.core.kinematics.closest import Box, Sphere, link_closest_point
from cdmp_ros.core.obstacle_coupling import CouplingConfig, ObstacleCoupling, joint_coupling
from cdmp_ros.core.transform import TanhTransform

PANDA_URDF = pybullet_data.getDataPath() + '/franka_panda/panda.urdf'
DAMP = DampingConfig(epsilon=0.02, lambda_max=0.05)


@pytest.fixture(scope='module')
def panda():
    return panda_chain(PANDA_URDF)


def _with_singular_values(rng, m, n, S):
    U, _ = np.linalg.qr(rng.normal(size=(m, m)))
    V, _ = np.linalg.qr(rng.normal(size=(n, m)))
    return (U * S) @ V.T


def _well_conditioned_q(panda, rng):
    """A random Panda configuration whose end-effector Jacobian is far from singular."""
    while True:
        q = rng.uniform(panda.lower, panda.upper)
        _, J = panda.forward_and_jacobian(q, [PointOfInterest('ee')])
        if np.linalg.svd(J[0], compute_uv=False).min() > 0.1:
            return q


# ------------------------------------------------------------------ pseudo-inverses
def test_damped_pinv_is_pinv_far_from_singularities(rng):
    for m in (1, 2, 3):
        M = _with_singular_values(rng, m, 7, rng.uniform(0.05, 2.0, m))
        np.testing.assert_allclose(damped_pinv(M, DAMP), np.linalg.pinv(M), atol=1e-12)
        v = rng.normal(size=m)
        np.testing.assert_allclose(damped_pinv_apply(M.tolist(), v.tolist(), DAMP),
                                   np.linalg.pinv(M) @ v, atol=1e-10)
    # exactly zero singular values are dropped, as by np.linalg.pinv
    M = _with_singular_values(rng, 3, 7, [1.0, 0.5, 0.0])
    np.testing.assert_allclose(damped_pinv(M, DAMP), np.linalg.pinv(M, rcond=1e-12), atol=1e-9)


def test_damped_pinv_finite_at_exact_singularity():
    chain = planar_chain([1.0, 1.0, 1.0, 1.0])
    _, J = chain.forward_and_jacobian(np.zeros(4), [PointOfInterest('ee')])
    J2 = J[0, :2]                                   # stretched arm: rank 1, sigma_min = 0
    assert np.linalg.svd(J2, compute_uv=False)[1] < 1e-12
    P = damped_pinv(J2, DAMP)
    assert np.all(np.isfinite(P)) and np.abs(P).max() < 1.0 / DAMP.lambda_max
    v = [1.0, 1.0]
    dq = damped_pinv_apply(J2.tolist(), v, DAMP)
    assert all(math.isfinite(x) for x in dq)
    np.testing.assert_allclose(dq, P @ v, atol=1e-9)
    # the gain on a vanishing singular value is sigma / (sigma^2 + lambda^2(sigma)) -> 0
    for sigma in (1e-2, 1e-3, 1e-6, 0.0):
        M = np.diag([1.0, sigma, 0.5])
        lam2 = DAMP.lambda_max ** 2 * (1 - (sigma / DAMP.epsilon) ** 2)
        expected = sigma / (sigma ** 2 + lam2)
        assert damped_pinv(M, DAMP)[1, 1] == pytest.approx(expected, abs=1e-15)


def test_scalar_pinv_matches_numpy_near_singularities(rng):
    for _ in range(300):
        m = int(rng.integers(1, 4))
        S = rng.uniform(0.0, 2.0, m) * rng.choice([1.0, 1e-2, 1e-3, 0.0], m)
        M = _with_singular_values(rng, m, 7, S)
        v = rng.normal(size=m)
        ref = damped_pinv(M, DAMP) @ v
        got = damped_pinv_apply(M.tolist(), v.tolist(), DAMP)
        np.testing.assert_allclose(got, ref, atol=1e-6 * max(1.0, np.abs(ref).max()))


# ------------------------------------------------------------------ Eq. 7, 11, 12
def test_eq11_equals_eq12_and_link_term_keeps_end_effector(panda, rng):
    checked = 0
    for _ in range(10):
        q = _well_conditioned_q(panda, rng)
        points = [PointOfInterest('ee'), PointOfInterest('panda_link5', (0.0, 0.1, 0.0))]
        _, J = panda.forward_and_jacobian(q, points)
        J_e, J_o = J[0], J[1]
        dx = rng.normal(size=3)
        dq11 = link_term(J_e, J_o, dx, DAMP, form=11)
        dq12 = link_term(J_e, J_o, dx, DAMP, form=12)
        np.testing.assert_allclose(dq11, dq12, atol=1e-10)                # Eq. 11 == 12
        np.testing.assert_allclose(J_e @ dq12, 0.0, atol=1e-10)           # EE unaffected
        N = null_space_projector(J_e, DAMP)
        np.testing.assert_allclose(N @ N, N, atol=1e-12)
        # Eq. 12 is the least-norm solution of J_o N dq = dx: its residual is orthogonal to
        # the range of J_o N, and the end-effector term realises dx_e exactly (Eq. 7)
        # (when J_o N is undamped: singular values either structurally zero or >= epsilon;
        # for this link point J_o N has rank 2)
        S = np.linalg.svd(J_o @ N, compute_uv=False)
        if np.all((S < 1e-12) | (S > DAMP.epsilon)):
            checked += 1
            np.testing.assert_allclose(dq12, np.linalg.pinv(J_o @ N, rcond=1e-10) @ dx,
                                       atol=1e-9)
            res = J_o @ N @ dq12 - dx
            np.testing.assert_allclose((J_o @ N).T @ res, 0.0, atol=1e-9)
        dq7 = end_effector_term(J_e, dx, DAMP)
        np.testing.assert_allclose(J_e @ dq7, dx, atol=1e-10)
    assert checked >= 3
    with pytest.raises(ValidationError, match='form'):
        link_term(J_e, J_o, dx, DAMP, form=10)


def test_eq12_batched_over_leading_axes(panda, rng):
    Q = rng.uniform(panda.lower, panda.upper, (4, 5, 7))
    _, J = panda.forward_and_jacobian(Q, [PointOfInterest('ee'), PointOfInterest('panda_link3')])
    dx = rng.normal(size=(4, 5, 3))
    batched = link_term(J[..., 0, :, :], J[..., 1, :, :], dx, DAMP)
    for idx in np.ndindex(4, 5):
        np.testing.assert_allclose(batched[idx], link_term(J[idx][0], J[idx][1], dx[idx], DAMP),
                                   atol=1e-12)


def test_scalar_coupling_matches_numpy_reference(panda, rng):
    for trial in range(40):
        if trial % 2:
            q = rng.uniform(panda.lower, panda.upper)
        else:
            q = _well_conditioned_q(panda, rng)
        points = [PointOfInterest('ee'), PointOfInterest('panda_link3', (0.0, 0.0, -0.1)),
                  PointOfInterest('panda_link5', (0.0, 0.1, 0.0))]
        _, J = panda.forward_and_jacobian(q, points)
        dx = rng.normal(size=(3, 3))
        ref = (end_effector_term(J[0], dx[0], DAMP) + link_term(J[0], J[1], dx[1], DAMP)
               + link_term(J[0], J[2], dx[2], DAMP))
        # J_o of link3 only has 3 non-zero columns: the scalar code accepts truncated rows
        links = [(J[1][:, :3].tolist(), dx[1].tolist()), (J[2].tolist(), dx[2].tolist())]
        fast = coupling_3d(J[0].tolist(), dx[0].tolist(), links, DAMP)
        generic = scalar_coupling(J[0].tolist(), dx[0].tolist(),
                                  [(J[1].tolist(), dx[1].tolist()),
                                   (J[2].tolist(), dx[2].tolist())], DAMP)
        tol = 1e-8 * max(1.0, np.abs(ref).max())
        np.testing.assert_allclose(fast, ref, atol=tol)
        np.testing.assert_allclose(generic, ref, atol=tol)


# ------------------------------------------------------------------ fields
def test_repeller_is_minus_gradient_of_its_potential(rng):
    field = RepellerField(gain=0.02, influence_distance=0.3, min_distance=0.01)
    center, radius = np.array([0.2, -0.1, 0.4]), 0.05

    def potential(x):
        return field.potential(np.linalg.norm(x - center) - radius)

    for _ in range(20):
        x = center + rng.normal(size=3) * 0.12
        d = np.linalg.norm(x - center) - radius
        if not 0.012 < d < 0.29:
            continue
        n = (x - center) / np.linalg.norm(x - center)
        a = np.array(field.acceleration(x, (0, 0, 0), None, d, n))
        h = 1e-7
        grad = np.array([(potential(x + h * e) - potential(x - h * e)) / (2 * h)
                         for e in np.eye(3)])
        np.testing.assert_allclose(a, -grad, rtol=1e-5, atol=1e-9)
    n = (1.0, 0.0, 0.0)
    assert field.acceleration(None, (0, 0, 0), None, 0.3, n) == (0.0, 0.0, 0.0)
    assert field.acceleration(None, (0, 0, 0), None, 0.3 - 1e-9, n)[0] < 1e-6   # C1 at d0
    capped = field.acceleration(None, (0, 0, 0), None, -0.05, n)[0]
    assert capped == field.acceleration(None, (0, 0, 0), None, 0.01, n)[0] > 0
    damped = RepellerField(gain=0.02, influence_distance=0.3, damping=2.0)
    approaching = damped.acceleration(None, (-1.0, 0, 0), None, 0.1, n)[0]
    leaving = damped.acceleration(None, (1.0, 0, 0), None, 0.1, n)[0]
    assert approaching > leaving == field.acceleration(None, (0, 0, 0), None, 0.1, n)[0]
    with pytest.raises(ValidationError, match='min_distance < influence_distance'):
        RepellerField(influence_distance=0.1, min_distance=0.2)
    with pytest.raises(ValidationError, match='RepellerField.gain'):
        RepellerField(gain=-1.0)


def test_constant_field_of_section_IV_B():
    field = ConstantField(magnitude=3.0, influence_distance=0.1)
    assert field.acceleration(None, None, None, 0.05, (0.0, 0.6, 0.8)) == pytest.approx(
        (0.0, 1.8, 2.4))
    assert field.acceleration(None, None, None, 0.1, (0.0, 0.6, 0.8)) == (0.0, 0.0, 0.0)
    fixed = ConstantField(magnitude=2.0, influence_distance=0.1, direction=(0, 0, 5))
    assert fixed.acceleration(None, None, None, -0.01, (1.0, 0.0, 0.0)) == (0.0, 0.0, 2.0)
    with pytest.raises(ValidationError, match='ConstantField.direction'):
        ConstantField(direction=(0, 0, 0))


def test_board_field_eq30_eq31():
    board = Box((0.0, -0.5, 0.6), (0.6, 0.2, 0.62))       # horizontal board, edge at y = 0.2
    field = BoardField(beta_y=0.3, beta_z=0.2, alpha=1.5, goal_height=0.9)
    # under the board, before the edge: Eq. (30)
    x = (0.3, 0.05, 0.5)
    dy, dz = 0.2 - 0.05, 0.6 - 0.5
    assert field.acceleration(x, None, board) == pytest.approx((0.0, 0.3 * dy / dz,
                                                                -0.2 / dz))
    # past the edge: Eq. (31), towards the goal height
    x = (0.3, 0.25, 0.5)
    assert field.acceleration(x, None, board) == pytest.approx(
        (0.0, 0.0, 1.5 * math.sqrt(0.4)))
    assert field.acceleration((0.3, 0.25, 1.0), None, board)[2] == pytest.approx(
        -1.5 * math.sqrt(0.1))
    # the escape force grows without bound towards the board (floored at min_distance)
    near = field.acceleration((0.3, 0.0, 0.6 - 1e-4), None, board)
    assert near[2] == pytest.approx(-0.2 / field.min_distance)
    with pytest.raises(ValidationError, match='BoardField axes'):
        BoardField(horizontal_axis=2, vertical_axis=2)
    with pytest.raises(ValidationError, match='BoardField.edge_side'):
        BoardField(edge_side=0)
    with pytest.raises(ValidationError, match='Box obstacle'):
        field.acceleration(x, None, Sphere((0, 0, 0), 0.1))


# ------------------------------------------------------------------ assembly
def _reference_coupling(chain, q, obstacles, segments, sphere_field, box_field, link_radius):
    """Numpy reference: closest points from cdmp_ros.core.kinematics.closest, Jacobians from
    the batched path, Eq. 7 and Eq. 12 from the SVD pseudo-inverse."""
    ee = PointOfInterest('ee')
    x, J = chain.forward_and_jacobian(np.array([q]), [ee])
    x, J_e = x[0, 0], J[0, 0]
    ax = list(chain.task_axes)
    dx_e = np.zeros(3)
    for obs in obstacles:
        if isinstance(obs, Sphere):
            v = x - np.array(obs.center)
            d, n = np.linalg.norm(v) - obs.radius, v / np.linalg.norm(v)
            dx_e += sphere_field.acceleration(x, (0, 0, 0), obs, d, n)
        else:
            from cdmp_ros.core.kinematics.closest import box_signed_distance
            d, _, n = box_signed_distance(x, obs.lower, obs.upper)
            dx_e += box_field.acceleration(x, (0, 0, 0), obs, float(d), n)
    dq = end_effector_term(J_e[ax], dx_e[ax], DAMP)
    for seg in segments:
        cps = [link_closest_point(chain, q, seg, obs, link_radius) for obs in obstacles]
        i = int(np.argmin([cp.distance for cp in cps]))
        cp, obs = cps[i], obstacles[i]
        f = sphere_field if isinstance(obs, Sphere) else box_field
        dx = np.array(f.acceleration(cp.point, (0, 0, 0), obs, cp.distance, cp.normal))
        _, J_o = chain.forward_and_jacobian(np.array([q]), [cp.poi])
        dq += link_term(J_e[ax], J_o[0, 0][ax], dx[ax], DAMP)
    return dq


def test_obstacle_coupling_matches_reference_panda(panda, rng):
    sphere_field = RepellerField(gain=0.05, influence_distance=0.4, min_distance=0.01)
    box_field = ConstantField(magnitude=2.0, influence_distance=0.3)
    config = CouplingConfig(damping=DAMP, link_radius=0.04)
    coupling = ObstacleCoupling(panda, ['panda_link3', 'panda_link5'], sphere_field,
                                box_field, config)
    segments = coupling.segments
    n_active = 0
    for trial in range(12):
        q = _well_conditioned_q(panda, rng)
        ends = [PointOfInterest(s[0], s[2]) for s in segments]
        X = panda.forward(q, [PointOfInterest('ee')] + ends)
        obstacles = [Sphere(tuple(p + rng.normal(size=3) * 0.1), 0.05) for p in X]
        if trial % 3 == 0:
            obstacles.append(Box.from_center(X[1] + [0.1, 0.0, 0.0], (0.05, 0.5, 0.5)))
        got = coupling.joint_acceleration(q, np.zeros(7), obstacles)
        ref = _reference_coupling(panda, q, obstacles, segments, sphere_field, box_field, 0.04)
        np.testing.assert_allclose(got, ref, atol=1e-7 * max(1.0, np.abs(ref).max()))
        n_active += np.abs(ref).max() > 0
        assert len(coupling.last_distances) == 3
    assert n_active >= 8
    np.testing.assert_allclose(
        joint_coupling(panda, q, None, obstacles, ['panda_link3', 'panda_link5'], sphere_field,
                       box_field, config), got, atol=1e-12)
    # nothing within reach: exactly zero
    assert coupling.joint_acceleration(q, None, [Sphere((5.0, 5.0, 5.0), 0.1)]) == [0.0] * 7


def test_obstacle_coupling_planar_chain(rng):
    chain = planar_chain([1.0, 1.0, 1.0, 1.0])
    field = RepellerField(gain=0.5, influence_distance=1.0, min_distance=0.01)
    coupling = ObstacleCoupling(chain, ['link2'], field, config=CouplingConfig(damping=DAMP))
    q = np.array([0.3, 0.5, -0.4, 0.6])
    X = chain.forward(q, [PointOfInterest('ee'), PointOfInterest('link3')])
    obstacles = [Sphere((X[0, 0] + 0.3, X[0, 1] - 0.2, 0.0), 0.1),
                 Sphere((X[1, 0] - 0.2, X[1, 1] + 0.3, 0.0), 0.1)]
    got = coupling.joint_acceleration(q, None, obstacles)
    ref = _reference_coupling(chain, q, obstacles, coupling.segments, field, None, 0.0)
    assert np.abs(ref).max() > 0.1
    np.testing.assert_allclose(got, ref, atol=1e-9)


def test_to_internal_matches_tanh_transform(panda, rng):
    transform = TanhTransform(panda.lower, panda.upper)
    xi = rng.normal(size=7)
    dq = rng.normal(size=7)
    tau = 1.7
    P = ObstacleCoupling.to_internal(dq.tolist(), xi.tolist(), tau, transform.y_delta.tolist())
    np.testing.assert_allclose(P, tau ** 2 * transform.joint_accel_to_exogenous(xi, 0 * xi, dq),
                               rtol=1e-12)
    # and it is the change of xi_dd that reproduces dq through Eq. (29)
    xid, xidd = rng.normal(size=7), rng.normal(size=7)
    np.testing.assert_allclose(
        transform.acceleration(xi, xid, xidd + np.array(P) / tau ** 2)
        - transform.acceleration(xi, xid, xidd), dq, atol=1e-9)
    assert ObstacleCoupling.to_internal([1.0, 2.0], None, 2.0) == [4.0, 8.0]


def _run_coupled(prim, coupling, obstacles, y_delta, steps=600, dt=0.002):
    stepper = prim.stepper(dt)
    inp, out = stepper.input, stepper.output
    Y, dists = [], []
    for _ in range(steps):
        if coupling is not None:
            dq = coupling.joint_acceleration(out.y, out.yd, obstacles)
            inp.coupling[:] = coupling.to_internal(dq, out.xi, stepper.tau, y_delta)
            dists.append(coupling.last_distances[0])
        stepper.update(inp)
        Y.append(list(out.y))
    return np.array(Y), dists


def test_coupled_cdmp_avoids_obstacle_and_holds_limits_under_any_field(panda):
    """Paper 000, III-B/IV-B at core level: the end-effector repeller pushes the end
    effector away from a sphere on its path; with a far stronger field the CDMP still
    stays strictly inside the joint limits while a plain DMP with the same coupling does not."""
    from cdmp_ros.core.dmp import CDMP, DMP, limit_usage
    T = np.linspace(0.0, 1.0, 201)
    s = 10 * T ** 3 - 15 * T ** 4 + 6 * T ** 5
    start = np.array([0.0, -0.3, 0.0, -2.2, 0.0, 2.0, 0.8])
    goal = np.array([0.8, 0.3, 0.0, -1.6, 0.0, 2.0, 0.8])
    Y = start + np.outer(s, goal - start)
    cdmp = CDMP(panda.lower, panda.upper).fit(T, Y)
    dmp = DMP(7).fit(T, Y)
    mid = panda.forward(Y[100], [PointOfInterest('ee')])[0]
    sphere = Sphere(tuple(mid + [0.0, 0.0, -0.12]), 0.05)      # just below the path
    y_delta = cdmp.transform.y_delta.tolist()
    free = ObstacleCoupling(panda, (), RepellerField(gain=0.0))
    _, d_free = _run_coupled(cdmp, free, [sphere], y_delta)
    field = RepellerField(gain=0.01, influence_distance=0.25, min_distance=0.01)
    _, d_coupled = _run_coupled(cdmp, ObstacleCoupling(panda, (), field), [sphere], y_delta)
    assert min(d_coupled) > min(d_free) + 0.01
    # "very high strength": a constant 2000 m/s^2 push wherever the sphere is within 2 m
    strong = ObstacleCoupling(panda, (), ConstantField(magnitude=2000.0, influence_distance=2.0))
    Y_cdmp, _ = _run_coupled(cdmp, strong, [sphere], y_delta)
    Y_dmp, _ = _run_coupled(dmp, strong, [sphere], None)
    assert np.all(np.isfinite(Y_cdmp))
    assert limit_usage(Y_cdmp, panda.lower, panda.upper) < 1.0
    assert limit_usage(Y_dmp, panda.lower, panda.upper) > 1.0
