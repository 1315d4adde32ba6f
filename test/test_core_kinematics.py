"""Batched kinematics (cdmp_ros.core.kinematics) and the URDF parser
(cdmp_ros.core.kinematics.urdf).

Independent references: the planar closed form, a double-precision homogeneous-matrix chain
built with scipy's rotations straight from the URDF, pybullet (FK and calculateJacobian), and
central finite differences of our own FK for the Jacobians.
"""
import xml.etree.ElementTree as ET

import numpy as np
import pybullet
import pybullet_data
import pytest
from scipy.spatial.transform import Rotation

from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.kinematics.closest import (Box, Sphere, box_signed_distance, point_box,
                                              segment_sphere)
from cdmp_ros.core.kinematics import (PANDA_EE_OFFSET, PointOfInterest, chain_from_urdf,
                                      dual_panda_chains, panda_chain, planar_chain, pose)
from cdmp_ros.core.kinematics.urdf import parse_urdf, parse_urdf_string
from closest_oracle import closest_distances, link_closest_point, segment_box, segment_obstacle

PANDA_URDF = pybullet_data.getDataPath() + '/franka_panda/panda.urdf'

# pybullet returns the URDF link-frame position (getLinkState[4]) through a single-precision
# inertial offset (the Panda's first joint at z = 0.333 comes back as float32(0.333); see
# test_pybullet_is_single_precision); its centre-of-mass poses and Jacobians are double.
PYBULLET_TOL = 5e-7
DOUBLE_TOL = 1e-9


def link_frames(chain, Q):
    """World poses (..., n_links, 4, 4) of the URDF frames of ``chain.link_names``, from the
    chain's batched joint frames (the reference the tests compare with pybullet and the
    matrix chain)."""
    Q = chain._check_q(Q)
    lead = Q.shape[:-1]
    R, p = chain._frames(Q.reshape(-1, chain.n_dofs))
    Rb = R[..., :3].transpose(0, 2, 1, 3)               # (n+1, B, 3, 3)
    pb = p.transpose(0, 2, 1)                           # (n+1, B, 3)
    out = np.zeros((Q.reshape(-1, chain.n_dofs).shape[0], len(chain.link_names), 4, 4))
    out[..., 3, 3] = 1.0
    for i, link in enumerate(chain.link_names):
        k, C = chain.attachments[link]
        out[:, i, :3, :3] = Rb[k] @ C[:3, :3]
        out[:, i, :3, 3] = pb[k] + Rb[k] @ C[:3, 3]
    return out.reshape(lead + out.shape[1:])


CUSTOM_URDF = '''<?xml version="1.0"?>
<robot name="mixed">
  <link name="base"/><link name="l1"/><link name="l2"/><link name="l3"/><link name="l4"/>
  <link name="tool"/><link name="side"/>
  <joint name="j1" type="revolute">
    <parent link="base"/><child link="l1"/>
    <origin xyz="0.1 0 0.2" rpy="0 0 0.3"/><axis xyz="0 0 1"/>
    <limit lower="-2" upper="2" velocity="1.5" effort="1"/>
  </joint>
  <joint name="j2" type="prismatic">
    <parent link="l1"/><child link="l2"/>
    <origin xyz="0 0.2 0.1" rpy="0.4 -0.2 0.1"/><axis xyz="1 1 0"/>
    <limit lower="-0.1" upper="0.3" velocity="0.5" effort="1"/>
  </joint>
  <joint name="fixed1" type="fixed">
    <parent link="l2"/><child link="l3"/><origin xyz="0 0 0.15" rpy="1.2 0 0"/>
  </joint>
  <joint name="j3" type="continuous">
    <parent link="l3"/><child link="l4"/>
    <origin xyz="0.3 0 0" rpy="0 0.7 0"/><axis xyz="0 -1 0"/>
    <limit velocity="3.0" effort="1"/>
  </joint>
  <joint name="j4" type="revolute">
    <parent link="l4"/><child link="tool"/>
    <origin xyz="0 0 0.25" rpy="0 0 0"/><axis xyz="0.2 0.3 -0.9"/>
    <limit lower="-1" upper="1.5" velocity="2.0" effort="1"/>
  </joint>
  <joint name="j5" type="revolute">
    <parent link="l1"/><child link="side"/>
    <axis xyz="1 0 0"/><limit lower="-1" upper="1" velocity="1" effort="1"/>
  </joint>
</robot>
'''


@pytest.fixture(scope='module')
def panda():
    return panda_chain(PANDA_URDF)


@pytest.fixture(scope='module')
def custom_path(tmp_path_factory):
    path = tmp_path_factory.mktemp('urdf') / 'mixed.urdf'
    path.write_text(CUSTOM_URDF)
    return str(path)


@pytest.fixture(scope='module')
def bullet():
    cid = pybullet.connect(pybullet.DIRECT)
    robot = pybullet.loadURDF(PANDA_URDF, useFixedBase=True, physicsClientId=cid)
    index = {pybullet.getJointInfo(robot, i, physicsClientId=cid)[12].decode(): i
             for i in range(pybullet.getNumJoints(robot, physicsClientId=cid))}
    yield cid, robot, index
    pybullet.disconnect(cid)


def reference_frames(path, tip, q, base=np.eye(4)):
    """Double-precision URDF FK with scipy rotations: world pose of every link on the path."""
    robot = parse_urdf(path)
    T = base.copy()
    out = {}
    i = 0
    for joint in robot.path(tip):
        origin = np.eye(4)
        origin[:3, :3] = Rotation.from_euler('xyz', joint.rpy).as_matrix()  # extrinsic = URDF
        origin[:3, 3] = joint.xyz
        motion = np.eye(4)
        if joint.type in ('revolute', 'continuous'):
            motion[:3, :3] = Rotation.from_rotvec(np.array(joint.axis) * q[i]).as_matrix()
        elif joint.type == 'prismatic':
            motion[:3, 3] = np.array(joint.axis) * q[i]
        i += joint.type != 'fixed'
        T = T @ origin @ motion
        out[joint.child] = T
    return out


def finite_difference_jacobian(chain, q, points, h=1e-6):
    J = np.empty((len(points), 3, chain.n_dofs))
    for j in range(chain.n_dofs):
        dq = np.zeros(chain.n_dofs)
        dq[j] = h
        J[:, :, j] = (chain.forward(q + dq, points) - chain.forward(q - dq, points)) / (2 * h)
    return J


# ------------------------------------------------------------------ planar chain
def test_planar_chain_matches_closed_form(rng):
    lengths = np.array([1.0, 1.0, 1.0, 1.0])
    chain = planar_chain(lengths)
    Q = rng.uniform(-np.pi, np.pi, (5, 6, 4))
    X, J = chain.forward_and_jacobian(Q, [PointOfInterest('ee'), PointOfInterest('link3')])
    theta = np.cumsum(Q, axis=-1)
    ee = np.stack([(lengths * np.cos(theta)).sum(-1), (lengths * np.sin(theta)).sum(-1),
                   np.zeros(theta.shape[:-1])], -1)
    np.testing.assert_allclose(X[..., 0, :], ee, atol=1e-12)
    # link3's frame is at joint 3: sum of the first two links
    np.testing.assert_allclose(X[..., 1, 0], (np.cos(theta) * lengths)[..., :2].sum(-1),
                               atol=1e-12)
    # dx/dq_j = -sum_{i >= j} l_i sin(theta_i), dy/dq_j = sum_{i >= j} l_i cos(theta_i)
    tail_sin = np.flip(np.cumsum(np.flip(lengths * np.sin(theta), -1), -1), -1)
    tail_cos = np.flip(np.cumsum(np.flip(lengths * np.cos(theta), -1), -1), -1)
    np.testing.assert_allclose(J[..., 0, 0, :], -tail_sin, atol=1e-12)
    np.testing.assert_allclose(J[..., 0, 1, :], tail_cos, atol=1e-12)
    np.testing.assert_array_equal(J[..., 0, 2, :], 0.0)
    np.testing.assert_array_equal(J[..., 1, :, 2:], 0.0)   # link3 is not moved by joints 3, 4
    assert chain.task_axes == (0, 1)
    np.testing.assert_array_equal(chain.lower, -np.pi)


def test_planar_chain_rejects_bad_lengths():
    with pytest.raises(ValidationError, match='link_lengths'):
        planar_chain([1.0, -1.0])
    with pytest.raises(ValidationError, match='limits'):
        planar_chain([1.0, 1.0], lower=[0.0, 0.0], upper=[1.0, -1.0])


# ------------------------------------------------------------------ Panda
def test_pybullet_is_single_precision(bullet):
    """Why PYBULLET_TOL is not 1e-9: pybullet returns the URDF's 0.333 m as float32."""
    cid, robot, index = bullet
    for i in range(7):
        pybullet.resetJointState(robot, i, 0.0, physicsClientId=cid)
    z = pybullet.getLinkState(robot, index['panda_link1'], computeForwardKinematics=1,
                              physicsClientId=cid)[4][2]
    assert z == float(np.float32(0.333)) and z != 0.333


def test_panda_limits_from_urdf(panda):
    assert panda.joint_names == [f'panda_joint{i}' for i in range(1, 8)]
    np.testing.assert_allclose(panda.lower, [-2.9671, -1.8326, -2.9671, -3.1416, -2.9671,
                                             -0.0873, -2.9671])
    np.testing.assert_allclose(panda.upper, [2.9671, 1.8326, 2.9671, 0.0, 2.9671, 3.8223,
                                             2.9671])
    np.testing.assert_allclose(panda.velocity_limits, [2.175] * 4 + [2.61] * 3)
    assert panda.ee_link == 'panda_hand'


def test_panda_fk_matches_double_reference(panda, rng):
    Q = rng.uniform(panda.lower, panda.upper, (30, 7))
    frames = link_frames(panda, Q)
    for q, F in zip(Q, frames):
        ref = reference_frames(PANDA_URDF, 'panda_hand', q)
        for i, link in enumerate(panda.link_names[1:], start=1):
            np.testing.assert_allclose(F[i], ref[link], atol=DOUBLE_TOL, err_msg=link)
        tcp = ref['panda_hand'] @ np.r_[PANDA_EE_OFFSET, 1.0]
        np.testing.assert_allclose(panda.forward(q, [PointOfInterest('ee')])[0], tcp[:3],
                                   atol=DOUBLE_TOL)


def _inertial_origins(path):
    """URDF <inertial><origin xyz> of every link (pybullet's centre-of-mass frame)."""
    out = {}
    for link in ET.parse(path).getroot().findall('link'):
        origin = link.find('inertial/origin')
        xyz = origin.get('xyz', '0 0 0') if origin is not None else '0 0 0'
        out[link.get('name')] = np.array([float(v) for v in xyz.split()])
    return out


def test_panda_fk_and_jacobian_match_pybullet(panda, bullet, rng):
    """pybullet's centre-of-mass poses (getLinkState[0], [1]) and calculateJacobian are double
    precision, so they are compared to 1e-9; its URDF-frame position getLinkState[4] carries
    the single-precision inertial offset and is compared to PYBULLET_TOL."""
    cid, robot, index = bullet
    inertial = _inertial_origins(PANDA_URDF)
    links = ['panda_link1', 'panda_link2', 'panda_link4', 'panda_link6', 'panda_link7',
             'panda_hand']
    offset = (0.03, -0.02, 0.05)
    points = [PointOfInterest(link, offset) for link in links] + [PointOfInterest('ee')]
    Q = rng.uniform(panda.lower, panda.upper, (15, 7))
    X, J = panda.forward_and_jacobian(Q, points)
    for q, Xq, Jq in zip(Q, X, J):
        for i in range(7):
            pybullet.resetJointState(robot, i, q[i], physicsClientId=cid)
        state = pybullet.getLinkState(robot, index['panda_grasptarget'],
                                      computeForwardKinematics=1, physicsClientId=cid)
        assert not inertial['panda_grasptarget'].any()
        np.testing.assert_allclose(Xq[-1], state[0], atol=DOUBLE_TOL)   # the TCP
        frames = link_frames(panda, q)
        for i, link in enumerate(links):
            state = pybullet.getLinkState(robot, index[link], computeForwardKinematics=1,
                                          physicsClientId=cid)
            F = frames[panda.link_names.index(link)]
            np.testing.assert_allclose(F[:3, :3] @ inertial[link] + F[:3, 3], state[0],
                                       atol=DOUBLE_TOL, err_msg=link)
            R_bullet = np.array(pybullet.getMatrixFromQuaternion(state[1])).reshape(3, 3)
            np.testing.assert_allclose(F[:3, :3], R_bullet, atol=DOUBLE_TOL, err_msg=link)
            np.testing.assert_allclose(F[:3, 3], state[4], atol=PYBULLET_TOL, err_msg=link)
            np.testing.assert_allclose(Xq[i], F[:3, :3] @ offset + F[:3, 3], atol=1e-12)
            # pybullet 3.2.7 takes localPosition in the URDF link frame
            lin, _ = pybullet.calculateJacobian(robot, index[link], list(offset),
                                                list(q) + [0.0, 0.0], [0.0] * 9, [0.0] * 9,
                                                physicsClientId=cid)
            np.testing.assert_allclose(Jq[i], np.array(lin)[:, :7], atol=DOUBLE_TOL,
                                       err_msg=link)
        lin, _ = pybullet.calculateJacobian(robot, index['panda_grasptarget'], [0.0] * 3,
                                            list(q) + [0.0, 0.0], [0.0] * 9, [0.0] * 9,
                                            physicsClientId=cid)
        np.testing.assert_allclose(Jq[-1], np.array(lin)[:, :7], atol=DOUBLE_TOL)


def test_panda_jacobian_matches_finite_differences(panda, rng):
    points = [PointOfInterest('ee'), PointOfInterest('panda_link4', (0.1, 0.0, -0.05)),
              PointOfInterest('panda_link3')]
    for q in rng.uniform(panda.lower, panda.upper, (5, 7)):
        _, J = panda.forward_and_jacobian(q, points)
        np.testing.assert_allclose(J, finite_difference_jacobian(panda, q, points), atol=1e-8)


def test_single_path_equals_batched(panda, rng):
    points = (PointOfInterest('ee'), PointOfInterest('panda_link5', (0.0, 0.1, 0.0)),
              PointOfInterest('panda_link0'), PointOfInterest('panda_link1', (0.1, 0, 0)))
    Q = rng.uniform(panda.lower, panda.upper, (2, 3, 7))
    X, J = panda.forward_and_jacobian(Q, points)
    assert X.shape == (2, 3, 4, 3) and J.shape == (2, 3, 4, 3, 7)
    np.testing.assert_allclose(panda.forward(Q, points), X, atol=0)
    for idx in np.ndindex(2, 3):
        x1, j1 = panda.forward_and_jacobian(Q[idx], points)
        np.testing.assert_allclose(x1, X[idx], atol=1e-13)
        np.testing.assert_allclose(j1, J[idx], atol=1e-13)
        np.testing.assert_allclose(panda.forward(list(Q[idx]), points), X[idx], atol=1e-13)
    np.testing.assert_array_equal(J[..., 2, :, :], 0.0)    # the base link does not move
    np.testing.assert_array_equal(J[..., 3, :, 1:], 0.0)   # link1 only moves with joint 1


def test_mixed_joint_types_against_reference(custom_path, rng):
    base = pose((0.5, -0.2, 0.1), (0.1, 0.2, 0.3))
    chain = chain_from_urdf(custom_path, 'tool', base_transform=base,
                            ee_offset=(0.0, 0.05, 0.1))
    assert chain.joint_names == ['j1', 'j2', 'j3', 'j4']
    assert list(chain.prismatic) == [False, True, False, False]
    np.testing.assert_array_equal(chain.lower, [-2.0, -0.1, -np.inf, -1.0])
    np.testing.assert_array_equal(chain.upper, [2.0, 0.3, np.inf, 1.5])
    np.testing.assert_array_equal(chain.velocity_limits, [1.5, 0.5, 3.0, 2.0])
    points = [PointOfInterest('ee'), PointOfInterest('l3', (0.1, 0.2, 0.3)),
              PointOfInterest('l2')]
    Q = rng.uniform(-1.0, 1.0, (6, 4)) * [1.0, 0.1, 3.0, 1.0]
    X, J = chain.forward_and_jacobian(Q, points)
    for q, Xq, Jq in zip(Q, X, J):
        ref = reference_frames(custom_path, 'tool', q, base)
        np.testing.assert_allclose(Xq[0], (ref['tool'] @ [0.0, 0.05, 0.1, 1.0])[:3],
                                   atol=DOUBLE_TOL)
        np.testing.assert_allclose(Xq[1], (ref['l3'] @ [0.1, 0.2, 0.3, 1.0])[:3],
                                   atol=DOUBLE_TOL)
        frames = link_frames(chain, q)
        for i, link in enumerate(chain.link_names[1:], start=1):
            np.testing.assert_allclose(frames[i], ref[link], atol=DOUBLE_TOL)
        np.testing.assert_allclose(Jq, finite_difference_jacobian(chain, q, points),
                                   atol=1e-8)
        x1, j1 = chain.forward_and_jacobian(q, points)
        np.testing.assert_allclose(j1, Jq, atol=1e-13)
        np.testing.assert_allclose(x1, Xq, atol=1e-13)


def test_dual_panda_cell(rng):
    left, right = dual_panda_chains(PANDA_URDF)
    q = rng.uniform(left.lower, left.upper)
    xl = left.forward(q, [PointOfInterest('ee')])[0]
    xr = right.forward(q, [PointOfInterest('ee')])[0]
    # same configuration, mirrored cell: turned by pi about z around x = 1.13 / 2
    np.testing.assert_allclose(xr, [1.13 - xl[0], -xl[1], xl[2]], atol=1e-12)
    np.testing.assert_allclose(right.joint_origins(q)[0], [1.13, 0.0, 0.0], atol=1e-15)


def test_link_segments_join_joint_origins(panda, rng):
    q = rng.uniform(panda.lower, panda.upper)
    origins = panda.joint_origins(q)[1:]
    segments = panda.link_segments()
    assert len(segments) == 7
    ends = panda.forward(q, [PointOfInterest(link, end) for link, _, end in segments])
    starts = panda.forward(q, [PointOfInterest(link, start) for link, start, _ in segments])
    np.testing.assert_allclose(starts, origins, atol=1e-12)
    np.testing.assert_allclose(ends[:-1], origins[1:], atol=1e-12)
    np.testing.assert_allclose(ends[-1], panda.forward(q, [PointOfInterest('ee')])[0],
                               atol=1e-12)


def test_input_validation(panda):
    with pytest.raises(ValidationError, match=r'Q: expected shape \(\.\.\., 7\)'):
        panda.forward(np.zeros(6), [PointOfInterest('ee')])
    with pytest.raises(ValidationError, match='points\\[0\\].link'):
        panda.forward(np.zeros(7), [PointOfInterest('nope')])
    with pytest.raises(ValidationError, match='PointOfInterest.offset'):
        PointOfInterest('ee', (1.0, 2.0))
    with pytest.raises(ValidationError, match='Q: expected finite'):
        panda.forward_and_jacobian(np.full((2, 7), np.nan), [PointOfInterest('ee')])
    with pytest.raises(ValidationError, match='Q: expected finite'):
        panda.forward(np.full(7, np.inf), [PointOfInterest('ee')])
    with pytest.raises(ValidationError, match='tip_link'):
        chain_from_urdf(PANDA_URDF, 'no_such_link')
    with pytest.raises(ValidationError, match='base_transform'):
        panda_chain(PANDA_URDF, base_transform=np.ones((4, 4)))


# ------------------------------------------------------------------ URDF parser
def _joint(body, name='j1', jtype='revolute'):
    return (f'<robot name="r"><link name="a"/><link name="b"/>'
            f'<joint name="{name}" type="{jtype}">{body}</joint></robot>')


GOOD = '<parent link="a"/><child link="b"/>'
LIMIT = '<limit lower="-1" upper="1" velocity="1" effort="1"/>'


@pytest.mark.parametrize('text, match', [
    (_joint(GOOD + LIMIT, jtype='floating'), "joint 'j1': type"),
    (_joint('<child link="b"/>' + LIMIT), "joint 'j1': missing <parent"),
    (_joint('<parent link="x"/><child link="b"/>' + LIMIT), "joint 'j1': parent link 'x'"),
    (_joint(GOOD), "joint 'j1': missing <limit>"),
    (_joint(GOOD + '<limit lower="-1" upper="1" effort="1"/>'),
     "joint 'j1': missing limit velocity"),
    (_joint(GOOD + '<limit lower="1" upper="-1" velocity="1"/>'),
     "joint 'j1': limit expected lower < upper"),
    (_joint(GOOD + '<limit lower="a" upper="1" velocity="1"/>'),
     "joint 'j1': limit lower expected a number"),
    (_joint(GOOD + LIMIT + '<origin xyz="0 0"/>'), "joint 'j1': origin xyz expected 3"),
    (_joint(GOOD + LIMIT + '<origin rpy="0 0 nan"/>'), "joint 'j1': origin rpy expected 3"),
    (_joint(GOOD + LIMIT + '<axis xyz="0 0 0"/>'), "joint 'j1': axis xyz expected a non-zero"),
    ('<robot><link name="a"/>', 'malformed XML'),
    ('<robt/>', 'root element expected <robot>'),
    ('<robot><link name="a"/><link name="a"/></robot>', "link 'a' defined twice"),
])
def test_urdf_errors_name_the_element(text, match):
    with pytest.raises(ValidationError, match=match):
        parse_urdf_string(text)


def test_urdf_parses_panda():
    robot = parse_urdf(PANDA_URDF)
    joint = {j.name: j for j in robot.joints}['panda_joint4']
    assert (joint.type, joint.parent, joint.child) == ('revolute', 'panda_link3', 'panda_link4')
    assert joint.xyz == (0.0825, 0.0, 0.0) and joint.rpy == (1.57079632679, 0.0, 0.0)
    assert (joint.lower, joint.upper, joint.velocity) == (-3.1416, 0.0, 2.175)
    assert robot.root_link() == 'panda_link0'
    with pytest.raises(ValidationError, match='urdf path'):
        parse_urdf('/nonexistent/robot.urdf')


# ------------------------------------------------------------------ closest points
def _box_sd_reference(X, lo, hi):
    """Signed distance to a box written face by face (independent of the module's formula)."""
    gap = np.maximum(np.maximum(lo - X, 0.0), X - hi)
    outside = np.sqrt((gap ** 2).sum(-1))
    inside = np.all((X > lo) & (X < hi), axis=-1)
    depth = np.minimum(X - lo, hi - X).min(-1)
    return np.where(inside, -depth, outside)


def _random_segments(rng, n, center, spread):
    A = center + rng.normal(0.0, spread, (n, 3))
    B = A + rng.normal(0.0, spread, (n, 3))
    return A, B


def test_segment_box_matches_brute_force(rng):
    lo, hi = np.array([-0.3, -0.1, 0.2]), np.array([0.4, 0.05, 0.25])   # a board
    A, B = _random_segments(rng, 200, (lo + hi) / 2, 0.3)
    A[:50], B[:50] = A[:50] * 0.05 + (lo + hi) / 2, B[:50] * 0.1    # many through the box
    A[50:60] = B[50:60]                                             # degenerate segments
    t, dist, surface, normal = segment_box(A, B, lo, hi, link_radius=0.01)
    ts = np.linspace(0.0, 1.0, 4001)
    P = A[:, None] + ts[None, :, None] * (B - A)[:, None]
    brute = _box_sd_reference(P, lo, hi).min(-1) - 0.01
    resolution = np.linalg.norm(B - A, axis=-1) / 4000
    assert np.all(dist <= brute + 1e-12)
    assert np.all(dist >= brute - resolution - 1e-12)
    assert (brute < 0).sum() > 20 and (brute > 0).sum() > 100     # both regimes exercised
    X = A + t[:, None] * (B - A)
    np.testing.assert_allclose(_box_sd_reference(X, lo, hi) - 0.01, dist, atol=1e-12)
    # the surface point is on the surface, the normal points from it towards the outside
    np.testing.assert_allclose(_box_sd_reference(surface, lo, hi), 0.0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(normal, axis=-1), 1.0)
    out = dist + 0.01 > 1e-9
    np.testing.assert_allclose(X[out], surface[out] + (dist[out, None] + 0.01) * normal[out],
                               atol=1e-12)
    assert np.all(_box_sd_reference(surface + 1e-6 * normal, lo, hi) > 0)


def test_single_segment_box_matches_batched_candidates(rng):
    """The scalar path of segment_box (one segment: slab clipping, then the max of lines
    inside or the piecewise quadratic outside) against the batched candidate enumeration and
    a 4001-sample brute force, with axis-parallel and degenerate segments and segments
    crossing the board's mid-plane."""
    lo, hi = np.array([-0.3, -0.1, 0.2]), np.array([0.4, 0.05, 0.25])
    A, B = _random_segments(rng, 400, (lo + hi) / 2, 0.3)
    A[:100], B[:100] = A[:100] * 0.05 + (lo + hi) / 2, B[:100] * 0.1
    A[100:120] = B[100:120]                                         # degenerate
    for k in range(3):                                              # axis-parallel pieces
        B[120 + 20 * k:140 + 20 * k, k] = A[120 + 20 * k:140 + 20 * k, k]
    t_b, d_b, s_b, n_b = segment_box(A, B, lo, hi, link_radius=0.01)
    ts = np.linspace(0.0, 1.0, 4001)
    inside = 0
    for i in range(len(A)):
        t, d, surface, normal = segment_box(A[i], B[i], lo, hi, link_radius=0.01)
        assert np.shape(t) == () and surface.shape == (3,) and normal.shape == (3,)
        assert 0.0 <= t <= 1.0
        # same minimum distance as the batched path (t may differ on a flat minimum)
        assert d == pytest.approx(d_b[i], abs=1e-12)
        P = A[i] + ts[:, None] * (B[i] - A[i])
        assert d <= _box_sd_reference(P, lo, hi).min() - 0.01 + 1e-12
        X = A[i] + t * (B[i] - A[i])
        assert _box_sd_reference(X, lo, hi) - 0.01 == pytest.approx(d, abs=1e-12)
        np.testing.assert_allclose(np.linalg.norm(normal), 1.0)
        if d + 0.01 > 1e-9:
            np.testing.assert_allclose(X, surface + (d + 0.01) * normal, atol=1e-12)
        else:
            inside += 1
            assert _box_sd_reference(surface + 1e-6 * normal, lo, hi) > 0
    assert inside > 30


def test_point_box_matches_box_signed_distance(rng):
    lo, hi = np.array([-0.3, -0.1, 0.2]), np.array([0.4, 0.05, 0.25])
    X = (lo + hi) / 2 + rng.normal(0.0, 0.3, (2000, 3))
    X[:300] = (lo + hi) / 2 + rng.uniform(-0.5, 0.5, (300, 3)) * (hi - lo)   # inside
    X[300:310] = lo                                                          # on a corner
    D, S, N = box_signed_distance(X, lo, hi)
    for i in range(len(X)):
        d, surface, normal = point_box(X[i].tolist(), lo.tolist(), hi.tolist())
        assert d == pytest.approx(D[i], abs=1e-15)
        np.testing.assert_allclose(surface, S[i], atol=1e-15)
        np.testing.assert_allclose(normal, N[i], atol=1e-15)


def test_oriented_box_closest_points(rng):
    """OrientedBox: with the identity it is the axis-aligned Box; rotated, the batched path
    (segment_obstacle) and the plain-float methods agree with a brute force on a signed
    distance written in the box frame from scipy's rotation."""
    from cdmp_ros.core.kinematics import OrientedBox
    center, size = np.array([0.3, -0.1, 0.5]), np.array([0.4, 0.05, 0.3])
    A, B = _random_segments(rng, 150, center, 0.25)
    A[:40], B[:40] = center + 0.05 * A[:40], center + 0.2 * (B[:40] - A[:40])
    same = OrientedBox(center, size)
    ref = segment_box(A, B, center - size / 2, center + size / 2, 0.01)
    got = segment_obstacle(A, B, same, 0.01)
    out = ref[1] + 0.01 > 1e-9          # inside, the deepest point of a board is on a tie
    for k in range(4):                  # between two faces: compare surface/normal outside
        np.testing.assert_allclose(got[k][out] if k > 1 else got[k],
                                   ref[k][out] if k > 1 else ref[k], atol=1e-12)
    quat = Rotation.random(random_state=3).as_quat()                  # (x, y, z, w)
    box = OrientedBox.from_quaternion(center, size, quat)
    R = Rotation.from_quat(quat).as_matrix()
    np.testing.assert_allclose(box.rotation, R, atol=1e-12)

    def sd_reference(X):
        return _box_sd_reference((X - center) @ R, -size / 2, size / 2)

    t, dist, surface, normal = segment_obstacle(A, B, box, 0.01)
    ts = np.linspace(0.0, 1.0, 4001)
    P = A[:, None] + ts[None, :, None] * (B - A)[:, None]
    brute = sd_reference(P).min(-1) - 0.01
    assert np.all(dist <= brute + 1e-12)
    assert np.all(dist >= brute - np.linalg.norm(B - A, axis=-1) / 4000 - 1e-12)
    assert (brute < 0).sum() > 10 and (brute > 0).sum() > 50
    X = A + t[:, None] * (B - A)
    np.testing.assert_allclose(sd_reference(X) - 0.01, dist, atol=1e-12)
    np.testing.assert_allclose(sd_reference(surface), 0.0, atol=1e-12)
    out = dist + 0.01 > 1e-9
    np.testing.assert_allclose(X[out], surface[out] + (dist[out, None] + 0.01) * normal[out],
                               atol=1e-12)
    d_pts, _, n_pts = box.signed_distance(X)
    for i in range(len(A)):
        ti = box.segment(A[i].tolist(), B[i].tolist())
        di = sd_reference(A[i] + ti * (B[i] - A[i])) - 0.01
        assert di == pytest.approx(dist[i], abs=1e-12)
        d, n = box.point(X[i].tolist())
        assert d == pytest.approx(d_pts[i], abs=1e-12)
        if out[i]:                                   # (inside: a tie between two faces)
            np.testing.assert_allclose(n, n_pts[i], atol=1e-12)
    with pytest.raises(ValidationError, match='OrientedBox.rotation'):
        OrientedBox(center, size, np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(ValidationError, match='OrientedBox.size'):
        OrientedBox(center, (0.1, 0.0, 0.1))


def test_segment_sphere_matches_brute_force(rng):
    center, radius = np.array([0.3, 0.1, 0.5]), 0.08
    A, B = _random_segments(rng, 300, center, 0.2)
    t, dist, surface, normal = segment_sphere(A, B, center, radius, link_radius=0.02)
    ts = np.linspace(0.0, 1.0, 4001)
    P = A[:, None] + ts[None, :, None] * (B - A)[:, None]
    brute = np.linalg.norm(P - center, axis=-1).min(-1) - radius - 0.02
    resolution = np.linalg.norm(B - A, axis=-1) / 4000
    assert np.all(dist <= brute + 1e-12) and np.all(dist >= brute - resolution - 1e-12)
    np.testing.assert_allclose(np.linalg.norm(surface - center, axis=-1), radius)
    X = A + t[:, None] * (B - A)
    np.testing.assert_allclose(X, center + (dist[:, None] + radius + 0.02) * normal, atol=1e-12)


def test_link_closest_point_gives_attached_point_and_jacobian(panda, rng):
    q = rng.uniform(panda.lower, panda.upper)
    segment = panda.link_segments()[1]                    # panda_link2: the upper arm
    a, b = panda.forward(q, [PointOfInterest(segment[0], segment[1]),
                             PointOfInterest(segment[0], segment[2])])
    board = Box.from_center(a + 0.4 * (b - a) + [0.03, 0.0, 0.0], (0.02, 0.4, 0.4))
    ball = Sphere(tuple(a + 0.7 * (b - a) + [0.0, 0.12, 0.0]), 0.05)
    for obstacle in (board, ball):
        cp = link_closest_point(panda, q, segment, obstacle, link_radius=0.04)
        x, J_o = panda.forward_and_jacobian(q, [cp.poi])
        np.testing.assert_allclose(x[0], cp.point, atol=1e-12)
        np.testing.assert_allclose(J_o[0], finite_difference_jacobian(panda, q, [cp.poi])[0],
                                   atol=1e-8)
        ts = np.linspace(0.0, 1.0, 5001)[:, None]
        P = a + ts * (b - a)
        if isinstance(obstacle, Box):
            brute = _box_sd_reference(P, np.array(obstacle.lower), np.array(obstacle.upper))
        else:
            brute = np.linalg.norm(P - obstacle.center, axis=-1) - obstacle.radius
        assert abs(cp.distance - (brute.min() - 0.04)) < np.linalg.norm(b - a) / 5000
    assert link_closest_point(panda, q, segment, board, 0.04).distance < 0   # penetrates
    D = closest_distances(panda, np.stack([q, q]), panda.link_segments(), [board, ball], 0.04)
    assert D.shape == (2, 7, 2)
    np.testing.assert_allclose(D[0, 1], [link_closest_point(panda, q, segment, o, 0.04).distance
                                         for o in (board, ball)], atol=1e-12)


def test_obstacle_validation():
    with pytest.raises(ValidationError, match='Box'):
        Box((0, 0, 0), (1, -1, 1))
    with pytest.raises(ValidationError, match='Sphere.radius'):
        Sphere((0, 0, 0), -1.0)
    with pytest.raises(ValidationError, match='Sphere.center'):
        Sphere((0, 0), 1.0)


def test_batched_results_survive_later_calls(panda, rng):
    """The batched path reuses scratch arrays: returned arrays must not alias them."""
    Q1, Q2 = rng.uniform(panda.lower, panda.upper, (2, 50, 7))
    points = [PointOfInterest('ee'), PointOfInterest('panda_link4')]
    X1, J1 = panda.forward_and_jacobian(Q1, points)
    O1, F1 = panda.joint_origins(Q1), link_frames(panda, Q1)
    keep = [a.copy() for a in (X1, J1, O1, F1)]
    panda.forward_and_jacobian(Q2, points)
    panda.joint_origins(Q2)
    link_frames(panda, Q2)
    for a, b in zip((X1, J1, O1, F1), keep):
        np.testing.assert_array_equal(a, b)


def test_sub_chain_starting_with_a_fixed_joint(custom_path, rng):
    """base_link below the root, first joint fixed: poses relative to base_link."""
    sub = chain_from_urdf(custom_path, 'tool', base_link='l2')
    assert sub.joint_names == ['j3', 'j4'] and sub.link_names == ['l2', 'l3', 'l4', 'tool']
    for _ in range(5):
        q = rng.uniform(-1.0, 1.0, 4)
        ref = reference_frames(custom_path, 'tool', q)
        expected = np.linalg.inv(ref['l2']) @ ref['tool']
        np.testing.assert_allclose(link_frames(sub, q[2:])[-1], expected, atol=DOUBLE_TOL)
        np.testing.assert_allclose(link_frames(sub, q[2:][None])[0, -1], expected,
                                   atol=DOUBLE_TOL)
