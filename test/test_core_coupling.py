"""Obstacle coupling terms (paper 000, Eq. 7, 11, 12), damped pseudo-inverses, potential fields
(Eq. 30-31, IV-B constant field, repellers) and their assembly with the kinematics: the
generated kernels against the numpy oracle (test/coupling_oracle.py)."""
import math

import numpy as np
import pybullet_data
import pytest

from cdmp_ros.core.coupling.kernel import inverse_h3
from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.coupling.potential_fields import BoardField, ConstantField, RepellerField
from cdmp_ros.core.kinematics import PointOfInterest, panda_chain, planar_chain
from cdmp_ros.core.kinematics.closest import Box, OrientedBox, Sphere
from cdmp_ros.core.coupling.obstacle import CouplingConfig, DampingConfig, ObstacleCoupling
from cdmp_ros.core.dmp.transform import TanhTransform
from closest_oracle import link_closest_point, segment_obstacle
from coupling_oracle import (damped_pinv, end_effector_term, limit_scale, link_term,
                             null_space_projector)

PANDA_URDF = pybullet_data.getDataPath() + '/franka_panda/panda.urdf'
DAMP = DampingConfig(epsilon=0.02, lambda_max=0.05)


@pytest.fixture(scope='module')
def panda():
    return panda_chain(PANDA_URDF)


def kernel_pinv_apply(M, v, damping=DAMP):
    """``M^+ v`` as the generated kernels compute it: ``M^T h(M M^T)^-1 v`` with the closed-form
    ``inverse_h3``; M of 1 to 3 rows, padded to 3 with zero rows (as a kernel does with the
    rows outside a chain's task axes)."""
    M = np.asarray(M, dtype=float)
    m = M.shape[0]
    M3 = np.zeros((3, M.shape[1]))
    M3[:m] = M
    v3 = np.zeros(3)
    v3[:m] = v
    A = M3 @ M3.T
    inv, _ = inverse_h3(A[0, 0], A[0, 1], A[0, 2], A[1, 1], A[1, 2], A[2, 2],
                        damping.epsilon ** 2, damping.lambda_max ** 2)
    return M3.T @ (np.array(inv).reshape(3, 3) @ v3)


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
        np.testing.assert_allclose(kernel_pinv_apply(M, v), np.linalg.pinv(M) @ v,
                                   atol=1e-10)
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
    dq = kernel_pinv_apply(J2, v)
    assert all(math.isfinite(x) for x in dq)
    np.testing.assert_allclose(dq, P @ v, atol=1e-9)
    # the gain on a vanishing singular value is sigma / (sigma^2 + lambda^2(sigma)) -> 0
    for sigma in (1e-2, 1e-3, 1e-6, 0.0):
        M = np.diag([1.0, sigma, 0.5])
        lam2 = DAMP.lambda_max ** 2 * (1 - (sigma / DAMP.epsilon) ** 2)
        expected = sigma / (sigma ** 2 + lam2)
        assert damped_pinv(M, DAMP)[1, 1] == pytest.approx(expected, abs=1e-15)


def test_kernel_pinv_matches_numpy_near_singularities(rng):
    """The closed-form damped inverse of the kernels against the SVD oracle, also with one or
    two zero rows (planar chains) and singular values at, below and far below epsilon."""
    for _ in range(300):
        m = int(rng.integers(1, 4))
        S = rng.uniform(0.0, 2.0, m) * rng.choice([1.0, 1e-2, 1e-3, 0.0], m)
        M = _with_singular_values(rng, m, 7, S)
        v = rng.normal(size=m)
        ref = damped_pinv(M, DAMP) @ v
        got = kernel_pinv_apply(M, v)
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
def _reference_coupling(chain, q, obstacles, segments, sphere_field, box_field, link_radius,
                        limits=(0.9, 0.95)):
    """Numpy reference: closest points from cdmp_ros.core.kinematics.closest, Jacobians from
    the batched path, Eq. 7 and Eq. 12 from the SVD pseudo-inverse; ``limits = (onset,
    lock)`` (the CouplingConfig defaults) gives the limit-aware Eq. 12, None Eq. 12 as is."""
    scale = None if limits is None else limit_scale(q, chain.lower, chain.upper, *limits)
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
        dq += link_term(J_e[ax], J_o[0, 0][ax], dx[ax], DAMP, scale=scale)
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
    # a fresh coupling (nothing cached) and qd None (zero velocity) give the same result
    fresh = ObstacleCoupling(panda, ['panda_link3', 'panda_link5'], sphere_field, box_field,
                             config)
    np.testing.assert_allclose(fresh.joint_acceleration(q, None, obstacles), got, atol=1e-12)
    # nothing within reach: exactly zero
    assert coupling.joint_acceleration(q, None, [Sphere((5.0, 5.0, 5.0), 0.1)]) == [0.0] * 7


def _batched_reference(chain, q, obstacles, segments, sphere_field, box_field, link_radius,
                       damping, end_effector=True, limits=(0.9, 0.95)):
    """Numpy reference of the whole coupling through the batched paths only: closest points
    by segment_sphere / segment_box on a batch of one (the candidate enumeration), Jacobians
    of the closest points from the batched kinematics, Eq. 7 / Eq. 12 by SVD
    (damped_pinv); ``limits = (onset, lock)`` (the CouplingConfig defaults): the limit-aware
    Eq. 12 with the weights of ``limit_scale``, None: Eq. 12 as is. Returns (dq, distances)."""
    scale = None if limits is None else limit_scale(q, chain.lower, chain.upper, *limits)
    from cdmp_ros.core.kinematics.closest import box_signed_distance
    Q = np.array([q])
    x, J = chain.forward_and_jacobian(Q, [PointOfInterest('ee')])
    x, J_e = x[0, 0], J[0, 0]
    dx_e, d_ee = np.zeros(3), np.inf
    for obs in obstacles:
        if isinstance(obs, Sphere):
            v = x - np.array(obs.center)
            d, n, f = np.linalg.norm(v) - obs.radius, v / np.linalg.norm(v), sphere_field
        elif isinstance(obs, Box):
            d, _, n = box_signed_distance(x, obs.lower, obs.upper)
            d, f = float(d), box_field
        else:
            d, _, n = obs.signed_distance(x)
            d, f = float(d), box_field
        d_ee = min(d_ee, d)
        if end_effector:
            dx_e += f.acceleration(x, (0, 0, 0), obs, d, n)
    dq = end_effector_term(J_e, dx_e, damping)
    dists = [d_ee]
    for link, start, end in segments:
        ends = chain.forward(Q, [PointOfInterest(link, start), PointOfInterest(link, end)])[0]
        best = None
        for obs in obstacles:
            t, d, _, n = segment_obstacle(ends[:1], ends[1:], obs, link_radius)
            if best is None or d[0] < best[1]:
                best = (float(t[0]), float(d[0]), n[0], obs)
        t, d, n, obs = best
        dists.append(d)
        f = sphere_field if isinstance(obs, Sphere) else box_field
        point = ends[0] + t * (ends[1] - ends[0])
        dx = np.array(f.acceleration(point, (0, 0, 0), obs, d, n))
        local = tuple(np.asarray(start) + t * (np.asarray(end) - np.asarray(start)))
        _, J_o = chain.forward_and_jacobian(Q, [PointOfInterest(link, local)])
        dq = dq + link_term(J_e, J_o[0, 0], dx, damping, scale=scale)
    return dq, dists


@pytest.mark.parametrize('epsilon', [0.02, 0.3])
def test_generated_coupling_matches_batched_reference_to_1e9(panda, rng, epsilon):
    """The generated single-configuration kernel (kinematics, gate, unrolled Eq. 7/12) against
    the batched numpy reference, with spheres and boxes,
    oriented boxes, a non-degenerate explicit segment and, at epsilon = 0.3, damping active on
    the end effector and on the links."""
    damping = DampingConfig(epsilon=epsilon, lambda_max=0.05)
    sphere_field = RepellerField(gain=0.05, influence_distance=0.4, min_distance=0.01)
    box_field = ConstantField(magnitude=2.0, influence_distance=0.3)
    config = CouplingConfig(damping=damping, link_radius=0.04)
    links = ['panda_link3', 'panda_link5', ('panda_link6', (0.0, 0.0, -0.05), (0.08, 0.0, 0.0))]
    coupling = ObstacleCoupling(panda, links, sphere_field, box_field, config)
    assert coupling._coupled is not None
    segments = coupling.segments
    ends = [PointOfInterest(s[0], s[2]) for s in segments]
    n_active = n_ee_damped = n_box = n_oriented = 0
    for trial in range(40):
        q = rng.uniform(panda.lower, panda.upper)
        X = panda.forward(q, [PointOfInterest('ee')] + ends)
        obstacles = [Sphere(tuple(p + rng.normal(size=3) * 0.12), 0.05) for p in X]
        if trial % 2:
            obstacles.append(Box.from_center(X[int(rng.integers(4))] + rng.normal(size=3) * 0.15,
                                             (0.05, 0.4, 0.3)))
        if trial % 3 == 1:
            obstacles.append(OrientedBox.from_quaternion(
                X[int(rng.integers(4))] + rng.normal(size=3) * 0.15, (0.3, 0.05, 0.2),
                rng.normal(size=4)))
        got = coupling.joint_acceleration(q, None, obstacles)
        dists = list(coupling.last_distances)
        ref, ref_dists = _batched_reference(panda, q, obstacles, segments, sphere_field,
                                            box_field, 0.04, damping)
        scale = max(1.0, np.abs(ref).max())
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-9 * scale)
        np.testing.assert_allclose(dists, ref_dists, rtol=0, atol=1e-12)
        n_active += np.abs(ref).max() > 0
        _, J = panda.forward_and_jacobian(q, [PointOfInterest('ee')])
        n_ee_damped += np.linalg.svd(J[0], compute_uv=False).min() < epsilon
        n_box += len(obstacles) > 4 and min(dists) < 0.3
        n_oriented += isinstance(obstacles[-1], OrientedBox) and min(dists) < 0.3
    assert n_active >= 30 and n_box >= 5 and n_oriented >= 5
    if epsilon > 0.1:
        assert n_ee_damped >= 5
    # no field within reach: exact zeros, and the generated function stops before any
    # Jacobian (the gate returns None)
    far = [Sphere((5.0, 5.0, 5.0), 0.1), Box((4.0, 4.0, 4.0), (4.5, 4.5, 4.5))]
    assert coupling.joint_acceleration(q, None, far) == [0.0] * 7
    assert coupling._coupled(q.tolist(), None, coupling._gate, far, 1.0, 1.0) is None
    assert len(coupling.last_distances) == 4 and min(coupling.last_distances) > 3.0


def test_generated_coupling_without_end_effector_term_and_velocity_fields(panda, rng):
    """end_effector=False (links only), and a velocity-dependent repeller: its kernel also
    computes the point velocities; at rest it equals the kernel without them."""
    field = RepellerField(gain=0.05, influence_distance=0.4, min_distance=0.01)
    config = CouplingConfig(damping=DAMP, end_effector=False)
    coupling = ObstacleCoupling(panda, ['panda_link3', 'panda_link5'], field, config=config)
    damped_field = RepellerField(gain=0.05, influence_distance=0.4, min_distance=0.01,
                                 damping=2.0)
    slow = ObstacleCoupling(panda, ['panda_link3', 'panda_link5'], damped_field)
    assert 'qd0' in slow._coupled.source and 'qd0' not in coupling._coupled.source
    for _ in range(10):
        q = _well_conditioned_q(panda, rng)
        X = panda.forward(q, [PointOfInterest('ee'), PointOfInterest('panda_link5')])
        obstacles = [Sphere(tuple(p + rng.normal(size=3) * 0.1), 0.05) for p in X]
        got = coupling.joint_acceleration(q, None, obstacles)
        ref, _ = _batched_reference(panda, q, obstacles, coupling.segments, field, None, 0.0,
                                    DAMP, end_effector=False)
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-9 * max(1.0, np.abs(ref).max()))
        # at rest the damping term vanishes
        np.testing.assert_allclose(slow.joint_acceleration(q, np.zeros(7), obstacles),
                                   ObstacleCoupling(panda, ['panda_link3', 'panda_link5'],
                                                    field).joint_acceleration(q, None,
                                                                              obstacles),
                                   rtol=0, atol=1e-9)


def test_damped_fields_get_the_point_velocities(panda, rng):
    """Velocity-dependent fields: the one closest-point routine (ClosestPointGate) gets the
    end-effector velocity J qd and the link point's J_o qd (interpolated between the segment
    ends' velocities by the kernel), against the numpy oracle; limit-aware and not."""
    field = RepellerField(gain=0.02, influence_distance=0.4, min_distance=0.01, damping=2.0)
    for aware in (False, True):
        coupling = ObstacleCoupling(panda, ['panda_link3'], field,
                                    config=CouplingConfig(damping=DAMP, limit_aware=aware))
        q = np.array([0.1, -0.4, 0.2, -2.0, 0.1, 1.7, 0.6])
        qd = rng.normal(size=7)
        ee = PointOfInterest('ee')
        X = panda.forward(q, [ee, PointOfInterest('panda_link3')])
        obstacles = [Sphere(tuple(X[0] + [0.1, 0.05, 0.0]), 0.05),
                     Sphere(tuple(X[1] + [0.08, 0.0, 0.05]), 0.05)]
        got = np.array(coupling.joint_acceleration(q, qd, obstacles))
        x, J = panda.forward_and_jacobian(q[None], [ee])
        x, J_e = x[0, 0], J[0, 0]
        dx_e = np.zeros(3)
        for obs in obstacles:
            v = x - np.array(obs.center)
            d = np.linalg.norm(v)
            dx_e += field.acceleration(x, J_e @ qd, obs, d - obs.radius, v / d)
        ref = end_effector_term(J_e, dx_e, DAMP)
        cps = [link_closest_point(panda, q, coupling.segments[0], obs) for obs in obstacles]
        i = int(np.argmin([cp.distance for cp in cps]))
        _, J_o = panda.forward_and_jacobian(q[None], [cps[i].poi])
        dx = field.acceleration(cps[i].point, J_o[0, 0] @ qd, obstacles[i], cps[i].distance,
                                cps[i].normal)
        scale = limit_scale(q, panda.lower, panda.upper, 0.9, 0.95) if aware else None
        ref += link_term(J_e, J_o[0, 0], np.array(dx), DAMP, scale=scale)
        np.testing.assert_allclose(got, ref, rtol=1e-7, atol=1e-9)
        at_rest = np.array(coupling.joint_acceleration(q, None, obstacles))
        assert np.abs(got - at_rest).max() > 0.1                 # the damping acted


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


def _map(dq, xi, tau, y_delta, floor=None):
    from cdmp_ros.core.dmp.stepper import joint_coupling_to_exogenous
    out = [0.0] * len(dq)
    kw = {} if floor is None else {'floor': floor}
    joint_coupling_to_exogenous(list(dq), list(xi), tau, y_delta, out, **kw)
    return out


def test_joint_coupling_map_inverts_eq29(panda, rng):
    """The stepper's map is the change of xi_dd that reproduces dq through Eq. (29)."""
    transform = TanhTransform(panda.lower, panda.upper)
    xi = rng.normal(size=7)
    dq = rng.normal(size=7)
    tau = 1.7
    P = _map(dq, xi, tau, transform.y_delta.tolist())
    xid, xidd = rng.normal(size=7), rng.normal(size=7)
    np.testing.assert_allclose(
        transform.acceleration(xi, xid, xidd + np.array(P) / tau ** 2)
        - transform.acceleration(xi, xid, xidd), dq, atol=1e-9)
    assert _map([1.0, 2.0], [0.0, 0.0], 2.0, None) == [4.0, 8.0]


def test_joint_coupling_map_caps_the_coupling_near_saturation(panda):
    """Near the saturation bound the map divides by 1 - tanh(xi)^2 ~ 2e-9. A joint pushed
    into its upper limit (xi saturated) whose coupling then turns away from the limit: the
    uncapped map (floor 0) makes it jump to the other limit in one tick; with the default
    floor the term is bounded by tau^2 |dq| / (y_delta floor) and the joint leaves the limit
    continuously. Inside 1 - tanh^2 >= floor the map is unchanged."""
    from cdmp_ros.core.dmp.dmp import CDMP
    from cdmp_ros.core.dmp.stepper import SATURATION_FLOOR
    from cdmp_ros.core.dmp.transform import XI_SAT
    transform = TanhTransform(panda.lower, panda.upper)
    y_delta = transform.y_delta.tolist()
    tau = 1.3
    xi = [XI_SAT, 0.0, 1.0, -2.0, 2.5, -XI_SAT, 0.3]
    dq = [-10.0, 1.0, 1.0, 1.0, 1.0, 10.0, 1.0]
    P = _map(dq, xi, tau, y_delta)
    bound = [tau ** 2 * abs(a) / (yd * SATURATION_FLOOR) for a, yd in zip(dq, y_delta)]
    assert all(abs(p) <= b * (1 + 1e-12) for p, b in zip(P, bound))
    assert P[0] == pytest.approx(-bound[0], rel=1e-12) and P[5] == pytest.approx(bound[5])
    exact = tau ** 2 * np.array(dq) / transform.jacobian(np.array(xi))
    np.testing.assert_allclose(P[1:5] + P[6:], np.r_[exact[1:5], exact[6:]], rtol=1e-12)
    assert abs(exact[0]) > 1e6 * abs(P[0])                   # what the cap removes
    np.testing.assert_allclose(_map(dq, xi, tau, y_delta, floor=0.0), exact, rtol=1e-12)

    T = np.linspace(0.0, 1.0, 201)
    prim = CDMP(panda.lower, panda.upper).fit(T, np.tile((panda.lower + panda.upper) / 2,
                                                         (201, 1)))

    def run(floor):
        stepper = prim.stepper(0.001)
        inp, out = stepper.input, stepper.output
        y0, xi0 = [], []
        for k in range(1000):
            push = 1e5 if k < 500 else -10.0           # into the upper limit, then away
            inp.coupling[:] = _map([push] + [0.0] * 6, out.xi, stepper.tau, y_delta, floor)
            stepper.update(inp)
            y0.append(out.y[0])
            xi0.append(out.xi[0])
        assert xi0[499] == pytest.approx(XI_SAT)               # saturated at the limit
        return np.abs(np.diff(y0[499:])).max()

    half_range = y_delta[0]
    assert run(0.0) > 1.9 * half_range                           # limit-to-limit jump
    assert run(SATURATION_FLOOR) < 0.01 * half_range


class _Push:
    """A Coupling that pushes joint 0 with ``push(k)`` [rad/s^2] at its k-th call."""

    def __init__(self, push):
        self.push = push
        self.k = 0
        self.last_distances = []

    def joint_acceleration(self, q, qd, obstacles):
        a = self.push(self.k)
        self.k += 1
        return [a]


def test_ball_drop_bound_no_jump_when_the_coupling_turns_away_from_saturation():
    """Issue 11: a one-joint CDMP on the ball-drop bounds [-0.27, 0.32], pushed into
    saturation at the upper bound, then given -1 rad/s^2. The uncapped copy of the map that the
    ball-drop experiment used asked for P = -6.8e9 and the reference jumped 0.320 -> -0.270 in
    one tick; through the stepper's one map (with the floor) the reference leaves the bound by
    at most 0.01 rad per tick, in the rollout and when the stepper is driven directly."""
    from cdmp_ros.core.dmp.dmp import CDMP
    from cdmp_ros.core.dmp.stepper import CouplingResult
    from cdmp_ros.core.dmp.transform import XI_SAT
    lo, hi = -0.27, 0.32
    T = np.linspace(0.0, 1.0, 201)
    prim = CDMP([lo], [hi]).fit(T, np.full((201, 1), 0.3))
    dt, n_push = 0.004, 200
    push = _Push(lambda k: 1e3 if k < n_push else -1.0)    # into the upper bound, then away
    tr = prim.rollout(dt=dt, duration=1.6, coupling=push, obstacles=())
    assert push.k == len(tr.Y) - 1
    assert tr.X[n_push, 0] == pytest.approx(XI_SAT)          # saturated at the upper bound
    assert tr.Y[n_push, 0] == pytest.approx(hi, abs=1e-6)
    steps = np.abs(np.diff(tr.Y[n_push:, 0]))
    assert steps.max() <= 0.01, steps.max()
    assert np.all(tr.Y > lo) and np.all(tr.Y < hi)
    # the uncapped map (floor 0) at that state: the jump the issue describes
    stepper = prim.stepper(dt)
    for _ in range(n_push):
        assert stepper.set_joint_coupling([1e3]) is CouplingResult.APPLIED
        out, _ = stepper.update(stepper.input)
    assert out.y[0] == pytest.approx(hi, abs=1e-6)
    P = _map([-1.0], out.xi, stepper.tau, prim.transform.y_delta.tolist(), floor=0.0)
    assert P[0] < -1e9                                       # -6.8e9 in the issue
    stepper.input.coupling[:] = P
    stepper.update(stepper.input)
    assert out.y[0] < lo + 0.01                              # bound to bound in one tick
    # the stepper's own map at the same state moves it by at most 0.01 rad
    stepper = prim.stepper(dt)
    for _ in range(n_push):
        stepper.set_joint_coupling([1e3])
        out, _ = stepper.update(stepper.input)
    y_before = out.y[0]
    stepper.set_joint_coupling([-1.0])
    assert abs(stepper.input.coupling[0]) < 1e-3 * abs(P[0])
    stepper.update(stepper.input)
    assert abs(out.y[0] - y_before) <= 0.01


def test_set_joint_coupling_rejects_bad_values(panda):
    from cdmp_ros.core.dmp.dmp import CDMP
    from cdmp_ros.core.dmp.stepper import CouplingResult
    T = np.linspace(0.0, 1.0, 101)
    prim = CDMP(panda.lower, panda.upper).fit(T, np.tile((panda.lower + panda.upper) / 2,
                                                         (101, 1)))
    stepper = prim.stepper(0.002)
    assert stepper.set_joint_coupling([1.0] * 7) is CouplingResult.APPLIED
    assert any(stepper.input.coupling)
    for bad in ([1.0] * 6, [float('nan')] + [0.0] * 6, [1e13] + [0.0] * 6, ['a'] * 7, 3.0):
        assert stepper.set_joint_coupling(bad) is CouplingResult.REJECTED, bad
        assert stepper.input.coupling == [0.0] * 7
    stepper.set_joint_coupling([1.0] * 7)
    assert stepper.set_joint_coupling(None) is CouplingResult.ZERO
    assert stepper.input.coupling == [0.0] * 7


def _run_coupled(prim, coupling, obstacles, steps=600, dt=0.002):
    stepper = prim.stepper(dt)
    inp, out = stepper.input, stepper.output
    Y, dists = [], []
    for _ in range(steps):
        if coupling is not None:
            stepper.set_joint_coupling(coupling.joint_acceleration(out.y, out.yd, obstacles))
            dists.append(coupling.last_distances[0])
        stepper.update(inp)
        Y.append(list(out.y))
    return np.array(Y), dists


def test_coupled_cdmp_avoids_obstacle_and_holds_limits_under_any_field(panda):
    """Paper 000, III-B/IV-B at core level: the end-effector repeller pushes the end
    effector away from a sphere on its path; with a far stronger field the CDMP still
    stays strictly inside the joint limits while a plain DMP with the same coupling does not."""
    from cdmp_ros.core.dmp.dmp import CDMP, DMP, limit_usage
    T = np.linspace(0.0, 1.0, 201)
    s = 10 * T ** 3 - 15 * T ** 4 + 6 * T ** 5
    start = np.array([0.0, -0.3, 0.0, -2.2, 0.0, 2.0, 0.8])
    goal = np.array([0.8, 0.3, 0.0, -1.6, 0.0, 2.0, 0.8])
    Y = start + np.outer(s, goal - start)
    cdmp = CDMP(panda.lower, panda.upper).fit(T, Y)
    dmp = DMP(7).fit(T, Y)
    mid = panda.forward(Y[100], [PointOfInterest('ee')])[0]
    sphere = Sphere(tuple(mid + [0.0, 0.0, -0.12]), 0.05)      # just below the path
    free = ObstacleCoupling(panda, (), RepellerField(gain=0.0))
    _, d_free = _run_coupled(cdmp, free, [sphere])
    field = RepellerField(gain=0.01, influence_distance=0.25, min_distance=0.01)
    _, d_coupled = _run_coupled(cdmp, ObstacleCoupling(panda, (), field), [sphere])
    assert min(d_coupled) > min(d_free) + 0.01
    # "very high strength": a constant 2000 m/s^2 push wherever the sphere is within 2 m
    strong = ObstacleCoupling(panda, (), ConstantField(magnitude=2000.0, influence_distance=2.0))
    Y_cdmp, _ = _run_coupled(cdmp, strong, [sphere])
    Y_dmp, _ = _run_coupled(dmp, strong, [sphere])
    assert np.all(np.isfinite(Y_cdmp))
    assert limit_usage(Y_cdmp, panda.lower, panda.upper) < 1.0
    assert limit_usage(Y_dmp, panda.lower, panda.upper) > 1.0


# ------------------------------------------------------------------ limit-aware null space
def _near_limits_q(panda, rng, joints=(3, 4), low=0.85, high=0.995):
    """A random Panda configuration with the given joints at limit usages in [low, high]."""
    q = rng.uniform(panda.lower, panda.upper)
    centre, delta = (panda.lower + panda.upper) / 2, (panda.upper - panda.lower) / 2
    for j in joints:
        q[j] = centre[j] + rng.choice([-1.0, 1.0]) * rng.uniform(low, high) * delta[j]
    return q


def _inline_weights(lower, upper, onset, lock):
    """``weights(q)``: the limit weights as a generated kernel computes them
    (``kernel._limit_weights``), None while no joint is beyond the onset."""
    from cdmp_ros.core.coupling.kernel import _limit_weights
    outside, lines, sn = _limit_weights(lower, upper, onset, lock)
    n = len(sn)
    src = (f'def weights({", ".join(f"q{k}" for k in range(n))}):\n'
           + (f'    if {" or ".join(outside)}:\n' if outside else '    if False:\n')
           + ''.join(f'        {line}\n' for line in lines)
           + f'        return [{", ".join(map(str, sn))}]\n    return None\n')
    scope = {}
    exec(compile(src, '<weights>', 'exec'), scope)  # noqa: S102
    return lambda q: scope['weights'](*q)


def test_limit_scale_is_one_below_the_onset_c1_and_zero_from_the_lock(panda, rng):
    """s = 1 up to the onset, (1 - rho)^2 (1 + 2 rho) in the band, 0 from the lock on; its
    derivative (-6 rho (1 - rho) / (lock - onset) / y_delta) matches central differences and
    vanishes at both ends of the band (C^1); the weights the kernels compute inline equal the
    numpy ones and are not computed (Eq. 12 untouched) while every joint is below the onset."""
    onset, lock = 0.9, 0.95
    lo, hi = panda.lower, panda.upper
    centre, delta = (lo + hi) / 2, (hi - lo) / 2
    scale = _inline_weights(lo, hi, onset, lock)
    U = np.linspace(-1.0, 1.0, 2001)
    Q = centre + np.outer(U, delta)
    S = limit_scale(Q, lo, hi, onset, lock)
    band = (np.abs(U) > onset + 1e-9) & (np.abs(U) < lock - 1e-9)     # (rounding of u)
    assert np.all(S[np.abs(U) < onset - 1e-9] == 1.0)
    assert np.all(S[np.abs(U) > lock + 1e-9] == 0.0)
    rho = (np.abs(U[band]) - onset) / (lock - onset)
    np.testing.assert_allclose(S[band], np.tile(((1 - rho) ** 2 * (1 + 2 * rho))[:, None],
                                                (1, 7)), rtol=1e-9)
    for u, q in zip(U, Q):
        got = scale(q.tolist())
        if abs(u) < onset - 1e-9:
            assert got is None
        elif abs(u) > onset + 1e-9:
            np.testing.assert_allclose(got, limit_scale(q, lo, hi, onset, lock), atol=1e-15)
    h = 1e-7
    for u in np.r_[np.linspace(onset - 0.01, lock + 0.01, 23), -np.linspace(0.91, 0.94, 4)]:
        r = min(max((abs(u) - onset) / (lock - onset), 0.0), 1.0)
        ds_du = -6 * r * (1 - r) / (lock - onset) * np.sign(u)
        fd = (limit_scale(centre + (u + h) * delta, lo, hi, onset, lock)
              - limit_scale(centre + (u - h) * delta, lo, hi, onset, lock)) / (2 * h)
        np.testing.assert_allclose(fd, ds_du, atol=1e-6)
    # a joint without finite limits is never weighted
    inf = np.array([-np.inf, -1.0]), np.array([np.inf, 1.0])
    np.testing.assert_array_equal(limit_scale([1e6, 0.99], *inf, onset, lock), [1.0, 0.0])
    assert _inline_weights(*inf, onset, lock)([1e6, 0.99]) == [1.0, 0.0]
    assert _inline_weights(*inf, onset, lock)([1e6, 0.5]) is None


def test_limit_aware_link_term_is_the_weighted_least_norm_null_space_motion(panda, rng):
    """Undamped, the limit-aware Eq. 12 is the solution of min dq^T W dq subject to
    J dq = 0 and J_o dq = dx (KKT system), W = diag(1 / s): it keeps the end effector still,
    reaches the link acceleration, and moves a joint with s = 0 not at all."""
    exact = DampingConfig(epsilon=1e-5, lambda_max=1e-5)
    n_checked = 0
    for _ in range(40):
        q = _near_limits_q(panda, rng)
        _, J = panda.forward_and_jacobian(q, [PointOfInterest('ee'),
                                              PointOfInterest('panda_link4', (-0.04, 0.2, 0.0))])
        J_e, J_o = J[0], J[1]
        if np.linalg.svd(np.r_[J_e, J_o], compute_uv=False).min() < 0.01:
            continue                                 # the KKT system needs rank 6
        dx = rng.normal(size=3)
        s = np.clip(limit_scale(q, panda.lower, panda.upper, 0.9, 0.95), 1e-3, 1.0)
        dq = link_term(J_e, J_o, dx, exact, scale=s)
        A = np.r_[J_e, J_o]
        K = np.block([[np.diag(1.0 / s), A.T], [A, np.zeros((6, 6))]])
        ref = np.linalg.solve(K, np.r_[np.zeros(7), np.zeros(3), dx])[:7]
        np.testing.assert_allclose(dq, ref, atol=1e-8 * max(1.0, np.abs(ref).max()))
        np.testing.assert_allclose(J_e @ dq, 0.0, atol=1e-9 * np.abs(dq).max())
        np.testing.assert_allclose(J_o @ dq, dx, atol=1e-8 * np.abs(dx).max())
        s[3] = 0.0                                          # joint 4 locked
        assert link_term(J_e, J_o, dx, exact, scale=s)[3] == 0.0
        n_checked += 1
    assert n_checked >= 10


@pytest.mark.parametrize('epsilon', [0.02, 0.3])
def test_generated_limit_aware_coupling_matches_batched_reference(panda, rng, epsilon):
    """Near the limits of joints 4 and 5 (and of random others) the generated kernel and the
    numpy reference agree on the limit-aware Eq. 12; without the
    weighting they agree on Eq. 12, and the two differ (the weighting is active)."""
    damping = DampingConfig(epsilon=epsilon, lambda_max=0.05)
    sphere_field = RepellerField(gain=0.05, influence_distance=0.4, min_distance=0.01)
    box_field = ConstantField(magnitude=2.0, influence_distance=0.3)
    links = ['panda_link3', 'panda_link5', ('panda_link6', (0.0, 0.0, -0.05), (0.08, 0.0, 0.0))]
    aware = ObstacleCoupling(panda, links, sphere_field, box_field,
                             CouplingConfig(damping=damping, link_radius=0.04))
    plain = ObstacleCoupling(panda, links, sphere_field, box_field,
                             CouplingConfig(damping=damping, link_radius=0.04,
                                            limit_aware=False))
    ends = [PointOfInterest(s[0], s[2]) for s in aware.segments]
    n_weighted = n_locked = 0
    for trial in range(30):
        joints = (3, 4) + tuple(rng.choice(7, size=trial % 3, replace=False))
        q = _near_limits_q(panda, rng, joints, 0.88, 0.97)
        X = panda.forward(q, [PointOfInterest('ee')] + ends)
        obstacles = [Sphere(tuple(p + rng.normal(size=3) * 0.12), 0.05) for p in X]
        if trial % 2:
            obstacles.append(Box.from_center(X[int(rng.integers(4))] + rng.normal(size=3) * 0.15,
                                             (0.05, 0.4, 0.3)))
        got = aware.joint_acceleration(q, None, obstacles)
        ref, _ = _batched_reference(panda, q, obstacles, aware.segments, sphere_field,
                                    box_field, 0.04, damping, limits=(0.9, 0.95))
        scale = max(1.0, np.abs(ref).max())
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-9 * scale)
        unweighted = plain.joint_acceleration(q, None, obstacles)
        ref0, _ = _batched_reference(panda, q, obstacles, aware.segments, sphere_field,
                                     box_field, 0.04, damping, limits=None)
        np.testing.assert_allclose(unweighted, ref0, rtol=0, atol=1e-9 * scale)
        s = limit_scale(q, panda.lower, panda.upper, 0.9, 0.95)
        if np.abs(np.subtract(got, unweighted)).max() > 1e-6 * scale:
            n_weighted += 1
        n_locked += bool(np.any(s == 0.0))
    assert n_weighted >= 20 and n_locked >= 5


def test_limit_aware_coupling_is_eq12_below_the_onset(panda, rng):
    """Every joint below the onset (usage < 0.9): the limit-aware coupling is the plain one,
    bit for bit; just above the onset it differs from
    it by O(h^2) (s is C^1), so the coupling is continuous across the onset."""
    field = RepellerField(gain=0.05, influence_distance=0.4, min_distance=0.01)
    links = ['panda_link3', 'panda_link5']
    aware = ObstacleCoupling(panda, links, field)
    plain = ObstacleCoupling(panda, links, field, config=CouplingConfig(limit_aware=False))
    centre, delta = (panda.lower + panda.upper) / 2, (panda.upper - panda.lower) / 2
    n_active = 0
    for _ in range(30):
        q = centre + rng.uniform(-0.9, 0.9, size=7) * delta
        j = int(rng.integers(7))
        q[j] = centre[j] + rng.choice([-1.0, 1.0]) * 0.8999 * delta[j]     # just below
        X = panda.forward(q, [PointOfInterest('ee'), PointOfInterest('panda_link5')])
        obstacles = [Sphere(tuple(p + rng.normal(size=3) * 0.1), 0.05) for p in X]
        a = aware.joint_acceleration(q, None, obstacles)
        assert a == plain.joint_acceleration(q, None, obstacles)
        n_active += any(a)
    assert n_active >= 25
    q = _well_conditioned_q(panda, rng)
    X = panda.forward(q, [PointOfInterest('ee'), PointOfInterest('panda_link5')])
    obstacles = [Sphere(tuple(X[1] + [0.05, 0.05, 0.0]), 0.05)]
    gaps = []
    for h in (1e-2, 1e-3):
        q[3] = centre[3] + (0.9 + h * 0.05) * delta[3]
        gaps.append(np.abs(np.subtract(aware.joint_acceleration(q, None, obstacles),
                                       plain.joint_acceleration(q, None, obstacles))).max())
    assert 0.0 < gaps[1] < 0.02 * gaps[0]                    # O(h^2): 100x for 10x


def test_coupling_config_rejects_bad_limit_band():
    for kw, name in [({'limit_onset': 0.0}, 'limit_onset'), ({'limit_onset': 1.0}, 'limit_onset'),
                     ({'limit_onset': 0.95, 'limit_lock': 0.9}, 'limit_lock'),
                     ({'limit_lock': 1.5}, 'limit_lock'),
                     ({'limit_lock': float('nan')}, 'limit_lock')]:
        with pytest.raises(ValidationError, match=f'CouplingConfig.{name}'):
            CouplingConfig(**kw)


#: Reaches (start, goal) and a sphere near a link where link avoidance through the null space
#: (Eq. 12, default streamer fields) drove panda_joint5 (index 4) resp. panda_joint4 (index 3)
#: onto its limit (found by a random search over reaches and spheres, then frozen).
LIMIT_CASES = {
    'panda_joint5': (4, [0.21, 0.52, -1.76, -1.3, -1.69, 1.25, -0.64],
                     [0.55, 0.5, -1.46, -1.16, 2.13, 1.63, -0.75], (0.491, -0.198, 0.853)),
    'panda_joint4': (3, [-0.3, 0.29, -0.01, -1.79, 0.89, 1.33, 0.51],
                     [-0.53, 0.3, 0.41, -0.26, 0.29, 0.95, 0.34], (0.207, -0.084, 1.093)),
}


def _limit_rollout(panda, case, config, field, steps=1500, dt=0.002):
    """Coupled CDMP rollout of a LIMIT_CASES reach: (largest limit usage per joint, smallest
    link-obstacle distance)."""
    from cdmp_ros.core.dmp.dmp import CDMP
    _, start, goal, center = LIMIT_CASES[case]
    T = np.linspace(0.0, 2.0, 401)
    s = T / 2.0
    s = 10 * s ** 3 - 15 * s ** 4 + 6 * s ** 5
    prim = CDMP(panda.lower, panda.upper).fit(T, np.outer(1 - s, start) + np.outer(s, goal))
    coupling = ObstacleCoupling(panda, ['panda_link3', 'panda_link5'], field, config=config)
    obstacles = [Sphere(center, 0.03)]
    Y, dists = [], []
    stepper = prim.stepper(dt)
    inp, out = stepper.input, stepper.output
    for _ in range(steps):
        stepper.set_joint_coupling(coupling.joint_acceleration(out.y, out.yd, obstacles))
        dists.append(min(coupling.last_distances[1:]))
        stepper.update(inp)
        Y.append(list(out.y))
    centre, delta = (panda.lower + panda.upper) / 2, (panda.upper - panda.lower) / 2
    return (np.abs(np.array(Y) - centre) / delta).max(axis=0), min(dists)


@pytest.mark.parametrize('case', sorted(LIMIT_CASES))
def test_limit_aware_null_space_keeps_the_joint_off_its_limit(panda, case):
    """Issue 10.4: with Eq. 12 as is, link avoidance drives the joint onto its limit (usage
    above 0.999: the CDMP holds it just inside, saturated); with the limit-aware Eq. 12 every
    joint stays below 0.98, and the link still keeps clear of the sphere (closer than with
    Eq. 12 as is by at most a few mm, farther than without coupling)."""
    joint = LIMIT_CASES[case][0]
    field = RepellerField(gain=0.01, influence_distance=0.2, min_distance=0.005)
    u_old, d_old = _limit_rollout(panda, case, CouplingConfig(limit_aware=False), field)
    u_new, d_new = _limit_rollout(panda, case, CouplingConfig(), field)
    _, d_free = _limit_rollout(panda, case, CouplingConfig(), RepellerField(gain=0.0))
    assert u_old[joint] > 0.999 and u_old.argmax() == joint
    assert u_new.max() < 0.98
    assert d_new > d_free + 0.01 and d_new > d_old - 0.005


def test_an_end_effector_ball_is_a_larger_obstacle(panda, rng):
    """``end_effector_radius`` r: Eq. 7 on a ball of radius r around the tool centre point
    equals Eq. 7 on the point with every sphere grown by r and every box face moved out by r
    (closed form: the distances to the ball's surface are those to the point, less r)."""
    field = RepellerField(gain=0.03, influence_distance=0.25)
    boxes = ConstantField(magnitude=1.0, influence_distance=0.1)
    r = 0.08
    ball = ObstacleCoupling(panda, [], sphere_field=field, box_field=boxes,
                            config=CouplingConfig(end_effector_radius=r))
    point = ObstacleCoupling(panda, [], sphere_field=field, box_field=boxes)
    active = 0
    for _ in range(8):
        q = _well_conditioned_q(panda, rng)
        x = panda.forward(q, [PointOfInterest('ee')])[0]
        c = x + rng.normal(size=3) * 0.1
        got = ball.joint_acceleration(q, None, [Sphere(tuple(c), 0.04)])
        want = point.joint_acceleration(q, None, [Sphere(tuple(c), 0.04 + r)])
        np.testing.assert_allclose(got, want, atol=1e-9 * max(1.0, np.abs(want).max()))
        assert ball.last_distances[0] == pytest.approx(point.last_distances[0], abs=1e-12)
        active += np.abs(want).max() > 0
        lo = x + [0.1, -0.5, -0.5]
        got = ball.joint_acceleration(q, None, [Box(tuple(lo), tuple(lo + 1.0))])
        want = point.joint_acceleration(q, None, [Box(tuple(lo - [r, 0, 0]), tuple(lo + 1.0))])
        np.testing.assert_allclose(got, want, atol=1e-9 * max(1.0, np.abs(want).max()))
        assert np.abs(want).max() > 0
    assert active >= 4
    with pytest.raises(ValidationError, match='end_effector_radius'):
        CouplingConfig(end_effector_radius=-0.1)


# ------------------------------------------------------------------ every kernel variant
def _prismatic_planar():
    """A 3-joint planar chain whose middle joint slides along z (a prismatic column)."""
    from cdmp_ros.core.kinematics import Chain
    p = planar_chain([1.0, 0.8, 0.5])
    return Chain(p.joint_names, [False, True, False], p.B, p.base_transform, p.attachments,
                 p.link_names, p.ee_link, p.ee_offset, p.lower, p.upper, p.velocity_limits)


@pytest.mark.parametrize('case', ['planar near the limits', 'prismatic joint'])
def test_planar_and_prismatic_kernels_match_the_oracle(case, rng):
    """The generated kernel with task axes (0, 1) (zero third rows) near the joint limits (the
    limit-aware Eq. 12 active), and on a chain with a prismatic joint, against the numpy
    oracle."""
    chain = planar_chain([1.0, 0.8, 0.5]) if case.startswith('planar') else _prismatic_planar()
    field = RepellerField(gain=0.5, influence_distance=1.0, min_distance=0.01)
    coupling = ObstacleCoupling(chain, ['link1', 'link2'], field,
                                config=CouplingConfig(damping=DAMP))
    centre, delta = (chain.lower + chain.upper) / 2, (chain.upper - chain.lower) / 2
    n_weighted = 0
    for _ in range(15):
        q = rng.uniform(-0.8, 0.8, 3) * delta + centre
        if case.startswith('planar'):
            j = int(rng.integers(3))
            q[j] = centre[j] + rng.choice([-1.0, 1.0]) * rng.uniform(0.9, 0.97) * delta[j]
        X = chain.forward(q, [PointOfInterest('ee'), PointOfInterest('link2')])
        obstacles = [Sphere((X[0, 0] + 0.3, X[0, 1] - 0.2, X[0, 2]), 0.1),
                     Sphere((X[1, 0] - 0.2, X[1, 1] + 0.3, X[1, 2]), 0.1)]
        got = coupling.joint_acceleration(q, None, obstacles)
        ref = _reference_coupling(chain, q, obstacles, coupling.segments, field, None, 0.0)
        assert np.abs(ref).max() > 1e-3
        np.testing.assert_allclose(got, ref, atol=1e-9 * max(1.0, np.abs(ref).max()))
        s = limit_scale(q, chain.lower, chain.upper, 0.9, 0.95)
        n_weighted += bool(np.any(s < 1.0))
    if case.startswith('planar'):
        assert n_weighted == 15


def test_an_end_effector_task_adds_eq7_without_the_obstacle_fields(panda, rng):
    """``ee_task`` with ``end_effector=False``: Eq. 7 of the task's acceleration (at the
    velocity J qd) plus the links' Eq. 12, against the numpy oracle; the task alone (no
    obstacle within reach) still acts."""
    field = RepellerField(gain=0.05, influence_distance=0.4, min_distance=0.01)
    target = np.array([0.4, 0.1, 0.5])

    def hold(x, xd):
        return tuple(20.0 * (target - np.asarray(x)) - 4.0 * np.asarray(xd))

    coupling = ObstacleCoupling(panda, ['panda_link3', 'panda_link5'], field,
                                config=CouplingConfig(damping=DAMP, end_effector=False),
                                ee_task=hold)
    assert 'qd0' in coupling._coupled.source
    for _ in range(6):
        q = _well_conditioned_q(panda, rng)
        qd = rng.normal(size=7)
        X = panda.forward(q, [PointOfInterest('ee'), PointOfInterest('panda_link5')])
        obstacles = [Sphere(tuple(X[1] + rng.normal(size=3) * 0.08), 0.05)]
        got = coupling.joint_acceleration(q, qd, obstacles)
        links, _ = _batched_reference(panda, q, obstacles, coupling.segments, field, None,
                                      0.0, DAMP, end_effector=False)
        x, J = panda.forward_and_jacobian(q[None], [PointOfInterest('ee')])
        ref = links + end_effector_term(J[0, 0], hold(x[0, 0], J[0, 0] @ qd), DAMP)
        np.testing.assert_allclose(got, ref, atol=1e-9 * max(1.0, np.abs(ref).max()))
    far = [Sphere((5.0, 5.0, 5.0), 0.1)]
    alone = coupling.joint_acceleration(q, qd, far)
    np.testing.assert_allclose(alone, end_effector_term(J[0, 0], hold(x[0, 0], J[0, 0] @ qd),
                                                        DAMP), atol=1e-9)
