"""The simulation behind the sim node without ROS: SimConfig validation and LiveSim
(robots, reference tracking, limit and tracking figures, obstacles, distances, contacts)."""
import math
import os
import xml.etree.ElementTree as ET

import numpy as np
import pybullet
import pytest

from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.kinematics.closest import Box, Sphere
from cdmp_ros.sim.live import limit_clip, LiveSim
from cdmp_ros.sim.node_config import SimConfig
from cdmp_ros.sim.robot_specs import PANDA_HOME as _HOME, PANDA_URDF

PLANAR = SimConfig(robot='planar4')
PANDA_HOME = np.array(_HOME)


@pytest.fixture
def panda():
    sim = LiveSim(SimConfig())
    yield sim
    sim.close()


@pytest.fixture
def planar():
    sim = LiveSim(PLANAR)
    yield sim
    sim.close()


# -- configuration ----------------------------------------------------------------------------
def test_config_defaults_and_derived_values():
    cfg = SimConfig()
    assert cfg.physics_dt == 1e-3 and cfg.publish_decimation == 4
    assert cfg.monitor_decimation == 2  # 250 Hz publishing, 100 Hz queries -> every 2nd
    assert SimConfig(physics_rate=500.0, publish_rate=500.0).publish_decimation == 1


@pytest.mark.parametrize('kwargs, text', [
    (dict(control='velocity'), "control: expected one of ['position', 'computed_torque'"),
    (dict(robot='ur5'), "robot: expected one of ['panda'"),
    (dict(publish_rate=300.0), 'publish_rate: expected physics_rate (1000) / publish_rate'),
    (dict(physics_rate=500.0, publish_rate=1000.0), 'publish_rate'),
    (dict(physics_rate=50.0), 'physics_rate: expected a value in [100.0, 10000.0], got 50.0'),
    (dict(kp=-1.0), 'kp: expected a value in [0.0, 1000000.0]'),
    (dict(reference_timeout=math.nan), 'reference_timeout'),
    (dict(real_time=1), 'real_time: expected a bool, got 1'),
    (dict(max_obstacles=2.5), 'max_obstacles: expected int, got 2.5'),
    (dict(snapshot_path=3), 'snapshot_path: expected a string'),
    (dict(initial_positions=[0.0, math.inf]), 'initial_positions: expected finite values'),
])
def test_config_rejects_bad_values(kwargs, text):
    with pytest.raises(ValidationError) as exc:
        SimConfig(**kwargs)
    assert text in str(exc.value)


# -- robots -----------------------------------------------------------------------------------
def _urdf_limits(path, joints):
    root = ET.parse(path).getroot()
    return np.array([[float(root.find(f"joint[@name='{j}']/limit").get(k)) for j in joints]
                     for k in ('lower', 'upper')])


def test_panda_joints_limits_and_home(panda):
    assert panda.joint_names == tuple(f'panda_joint{i}' for i in range(1, 8))
    assert panda.base_frame == 'panda_link0'
    lo, hi = _urdf_limits(PANDA_URDF, panda.joint_names)
    assert np.array_equal(panda.lower, lo) and np.array_equal(panda.upper, hi)
    q, qd, effort = panda.state()
    assert np.abs(q - PANDA_HOME).max() < 1e-12 and np.all(qd == 0.0)
    assert effort.shape == (7,)


def test_dual_panda_and_planar_arm():
    sim = LiveSim(SimConfig(robot='dual_panda', control='computed_torque'))
    try:
        assert sim.n_dofs == 14 and sim.base_frame == 'world'
        assert sim.joint_names[0] == 'left_panda_joint1'
        assert sim.joint_names[7] == 'right_panda_joint1'
        q_ref = sim.initial_positions.copy()
        q_ref[[0, 7]] = [0.2, -0.3]  # one joint of each robot
        sim.set_reference(q_ref)
        sim.step(1000)
        assert np.abs(sim.state()[0] - q_ref).max() < 1e-3
    finally:
        sim.close()
    sim = LiveSim(PLANAR)
    try:
        assert sim.joint_names == ('joint1', 'joint2', 'joint3', 'joint4')
        assert sim.base_frame == 'base'
        pos, quat = sim.ee_pose()  # stretched along +x: tip at 4 m
        assert np.abs(pos - [4.0, 0.0, 0.0]).max() < 1e-9
    finally:
        sim.close()


def test_dual_panda_reports_contacts_between_the_two_robots():
    sim = LiveSim(SimConfig(robot='dual_panda'))
    try:
        st = sim.monitor()   # home poses: apart, no contact
        assert st.contacts == 0 and 0.1 < st.min_robot_distance_m < 1.0
        assert st.as_values()['min_robot_distance_m'] == f'{st.min_robot_distance_m:.5f}'
        reach = [0.0, 1.0, 0.0, -0.6, 0.0, 1.6, 0.8]   # both arms stretched into the middle
        sim.set_initial_positions(reach + reach)
        sim.reset()
        st = sim.monitor()
        assert st.contacts > 0 and st.contacts_since_start == st.contacts
        assert st.min_robot_distance_m < 0.0
        assert st.min_robot_distance_since_start_m == st.min_robot_distance_m
        a, b, d = st.contact_pairs[0]
        assert a.startswith('left/panda_link') and b.startswith('right/panda_link')
        assert d == st.min_robot_distance_m
    finally:
        sim.close()
    sim = LiveSim(SimConfig(robot='panda'))
    try:
        assert sim.monitor().min_robot_distance_m == np.inf   # one robot: no pair
    finally:
        sim.close()


def test_initial_positions_are_checked():
    with pytest.raises(ValidationError, match='initial_positions: expected 7 values'):
        LiveSim(SimConfig(initial_positions=(0.0, 0.0)))
    with pytest.raises(ValidationError, match=r'initial_positions\[3\] \(panda_joint4\)'):
        LiveSim(SimConfig(initial_positions=(0.0, 0.0, 0.0, 0.5, 0.0, 1.0, 0.0)))
    q0 = (0.1, -0.5, 0.0, -2.0, 0.0, 1.5, 0.5)
    sim = LiveSim(SimConfig(initial_positions=q0))
    try:
        assert np.abs(sim.state()[0] - q0).max() < 1e-12
    finally:
        sim.close()


def test_ee_pose_matches_core_kinematics(panda):
    from cdmp_ros.core.kinematics import panda_chain, PointOfInterest
    chain = panda_chain(PANDA_URDF)
    goal = PANDA_HOME + np.array([0.3, 0.2, -0.2, 0.3, 0.1, -0.2, 0.4])
    panda.set_reference(goal)
    panda.step(300)
    pos, quat = panda.ee_pose()
    ee = chain.forward(panda.state()[0], [PointOfInterest('ee')])[0]
    assert np.abs(pos - ee).max() < 1e-6
    assert abs(np.linalg.norm(quat) - 1.0) < 1e-6


# -- tracking, limits ---------------------------------------------------------------------------
@pytest.mark.parametrize('control, tol', [('position', 1e-4), ('computed_torque', 1e-6),
                                          ('exogenous', 5e-3)])
def test_step_tracks_the_reference_and_reports_the_error(control, tol):
    sim = LiveSim(SimConfig(control=control))
    try:
        goal = PANDA_HOME + np.array([0.2, 0.1, -0.1, 0.2, 0.1, -0.1, 0.2])
        sim.set_reference(goal)
        sim.step(1)
        q = sim.state()[0]
        assert sim.stats.tracking_error_rad == pytest.approx(np.abs(goal - q).max(), abs=0)
        sim.step(1999)
        q = sim.state()[0]
        assert np.abs(goal - q).max() < tol
        assert sim.stats.tracking_error_rad == pytest.approx(np.abs(goal - q).max(), abs=0)
        assert sim.stats.tracking_error_max_rad >= 0.19  # the step itself
        assert sim.n_steps == 2000 and sim.t == pytest.approx(2.0)
    finally:
        sim.close()


@pytest.mark.parametrize('control, tol', [('position', 5e-3), ('computed_torque', 0.01)])
def test_tracking_error_on_a_smooth_ramp(control, tol):
    # a minimum-jerk reach sampled at 250 Hz with velocities (as from the streamer), held
    # between samples: the largest error over the whole motion stays below tol [rad]
    sim = LiveSim(SimConfig(control=control))
    try:
        goal = PANDA_HOME + np.array([0.4, -0.3, 0.2, 0.4, 0.1, 0.2, -0.3])
        n = 250
        for k in range(n + 50):
            s = min(k / n, 1.0)
            sim.set_reference(PANDA_HOME + (10 * s ** 3 - 15 * s ** 4 + 6 * s ** 5)
                              * (goal - PANDA_HOME),
                              (30 * s ** 2 - 60 * s ** 3 + 30 * s ** 4) * (goal - PANDA_HOME))
            sim.step(4)
        assert sim.stats.tracking_error_max_rad < tol
        assert sim.stats.tracking_error_rad < 1e-3
    finally:
        sim.close()


def test_limit_usage_and_violations(panda):
    panda.step(1)
    # at home joint 4 is at -3 pi / 4 in [-3.1416, 0]: |q - centre| / half range = 0.5
    assert panda.stats.max_limit_usage_since_start == pytest.approx(
        abs(-0.75 * math.pi + 1.5708) / 1.5708, abs=1e-6)
    assert panda.stats.limit_violations == 0
    # push joint 7 beyond its limit (as a collision would): counted while it is outside
    robot = panda.robots[0]
    pybullet.resetJointState(robot.body_id, 6, 2.9671 + 0.01, 0.0,
                             physicsClientId=panda.world.client_id)
    panda.step(1)
    assert panda.stats.limit_violations == 1
    assert panda.stats.max_limit_usage_since_start > 1.0
    panda.reset()
    panda.step(10)
    assert panda.stats.limit_violations == 1


def test_reset_and_hold(panda):
    panda.set_reference(PANDA_HOME + 0.1, np.full(7, 0.5))
    panda.step(200)
    assert np.abs(panda.state()[0] - PANDA_HOME).max() > 0.05
    panda.hold()
    assert np.all(panda.qd_ref == 0.0) and np.all(panda.q_ref == PANDA_HOME + 0.1)
    panda.reset()
    q, qd, _ = panda.state()
    assert np.abs(q - PANDA_HOME).max() < 1e-12 and np.all(qd == 0)
    assert np.array_equal(panda.q_ref, PANDA_HOME)


def test_control_switch_and_bad_gains(panda):
    panda.set_control(SimConfig(control='exogenous'))
    with pytest.raises(ValidationError, match='kp'):
        panda.set_control(SimConfig(control='exogenous', kp=0.0))
    panda.set_control(SimConfig(control='computed_torque', kp=100.0, kd=20.0))
    goal = PANDA_HOME + 0.05
    panda.set_reference(goal)
    panda.step(1500)
    assert np.abs(panda.state()[0] - goal).max() < 1e-4


def test_limit_clip():
    lo, hi = np.array([-1.0, -1.0]), np.array([1.0, 1.0])
    q, bad = limit_clip(np.array([0.5, 2.0]), lo, hi)
    assert q.tolist() == [0.5, 1.0] and bad == [1]
    q0 = np.array([0.1, 0.2])
    q, bad = limit_clip(q0, lo, hi)
    assert q is q0 and not bad


# -- obstacles ---------------------------------------------------------------------------------
def test_distance_to_a_sphere_matches_the_closed_form(planar):
    # link 2 is a capsule of radius 0.05 around the segment (1, 0, 0)-(2, 0, 0)
    planar.sync_obstacles({'s': Sphere((1.5, 0.5, 0.0), 0.1)})
    st = planar.monitor()
    assert st.min_obstacle_distance_m == pytest.approx(0.5 - 0.05 - 0.1, abs=1e-4)
    planar.sync_obstacles({'s': Sphere((1.5, 0.3, 0.0), 0.1)})  # moved
    assert planar.monitor().min_obstacle_distance_m == pytest.approx(0.15, abs=1e-4)
    planar.sync_obstacles({'s': Sphere((1.5, 0.3, 0.0), 0.05)})  # new radius: replaced
    assert planar.monitor().min_obstacle_distance_m == pytest.approx(0.2, abs=1e-4)
    assert st.min_obstacle_distance_since_start_m == pytest.approx(0.15, abs=1e-4)
    assert st.closest_pair_since_start == 'link2/s'
    planar.sync_obstacles({'b': Box((1.2, 0.2, -0.1), (1.8, 0.4, 0.1))})
    assert planar.world.obstacles.names == ('b',)
    assert planar.monitor().min_obstacle_distance_m == pytest.approx(0.15, abs=1e-4)
    planar.sync_obstacles({})
    assert math.isinf(planar.monitor().min_obstacle_distance_m)
    assert len(planar.world.obstacles) == 0


def test_oriented_box_is_placed_with_its_orientation(planar):
    """A box rotated 45 deg about z above link 2: pybullet's body has the rotation, and its
    closest corner is sqrt(2) * half-width closer than the axis-aligned box's face."""
    import pybullet
    from cdmp_ros.core.kinematics import OrientedBox
    q = (0.0, 0.0, math.sin(math.pi / 8), math.cos(math.pi / 8))
    planar.sync_obstacles({'b': OrientedBox.from_quaternion((1.5, 0.5, 0.0), (0.2, 0.2, 0.2),
                                                            q)})
    info = planar.world.obstacles.get('b')
    _, orn = pybullet.getBasePositionAndOrientation(info.body_id,
                                                    physicsClientId=planar.world.client_id)
    assert abs(abs(np.dot(orn, q)) - 1.0) < 1e-9
    # link 2: capsule of radius 0.05 around y = 0; the rotated box reaches down to
    # y = 0.5 - 0.1 * sqrt(2)
    assert planar.monitor().min_obstacle_distance_m == pytest.approx(
        0.5 - 0.1 * math.sqrt(2) - 0.05, abs=1e-3)
    body = info.body_id
    planar.sync_obstacles({'b': OrientedBox.from_quaternion((1.5, 0.5, 0.0), (0.2, 0.2, 0.2),
                                                            (0, 0, 0, 1))})
    assert planar.world.obstacles.get('b').body_id == body  # same shape: turned, not rebuilt
    assert planar.monitor().min_obstacle_distance_m == pytest.approx(0.5 - 0.1 - 0.05,
                                                                     abs=1e-3)


def test_contacts_count_onsets(planar):
    overlap = {'s': Sphere((1.5, 0.1, 0.0), 0.1)}  # 5 cm into link 2
    planar.sync_obstacles(overlap)
    st = planar.monitor()
    assert st.contacts == 1 and st.contacts_since_start == 1
    assert st.contact_pairs[0][:2] == ('link2', 's')
    assert st.min_obstacle_distance_m == pytest.approx(-0.05, abs=1e-3)
    planar.monitor()  # still the same contact: no new onset
    assert st.contacts == 1 and st.contacts_since_start == 1
    planar.sync_obstacles({})
    planar.monitor()
    assert st.contacts == 0 and st.contacts_since_start == 1
    planar.sync_obstacles(overlap)
    planar.monitor()
    assert st.contacts_since_start == 2


def test_ghost_obstacles_do_not_collide():
    sim = LiveSim(SimConfig(robot='planar4', obstacles_collide=False))
    try:
        sim.sync_obstacles({'s': Sphere((1.5, 0.1, 0.0), 0.1)})
        assert not sim.world.obstacles.get('s').collide
        sim.step(10)
        assert np.abs(sim.state()[0]).max() < 1e-6  # not pushed
        assert sim.monitor().contacts == 1  # but reported
    finally:
        sim.close()


def test_snapshot_writes_a_png(planar, tmp_path):
    path = planar.snapshot(str(tmp_path / 'a.png'))
    with open(path, 'rb') as f:
        assert f.read(8) == b'\x89PNG\r\n\x1a\n'
    path = planar.snapshot()
    try:
        assert os.path.getsize(path) > 1000
    finally:
        os.remove(path)
