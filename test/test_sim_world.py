"""World lifecycle, robots loaded from URDF (limits, planar arm, dual-Panda cell), stepping."""
import math
import time
import xml.etree.ElementTree as ET

import numpy as np
import pybullet
import pytest

from cdmp_ros.core.errors import CdmpError, ValidationError
from cdmp_ros.sim import (add_dual_panda, ComputedTorqueController, panda_spec, planar_arm_spec,
                          planar_arm_urdf, World, WorldConfig)
from cdmp_ros.sim.robot_specs import PANDA_URDF


def urdf_limits(path, joints):
    """(lower, upper, velocity, effort) of the named joints, parsed independently of pybullet."""
    root = ET.parse(path).getroot()
    out = []
    for name in joints:
        lim = root.find(f"joint[@name='{name}']/limit")
        out.append([float(lim.get(k)) for k in ('lower', 'upper', 'velocity', 'effort')])
    return np.array(out).T


def test_world_closes_its_client():
    with World() as world:
        cid = world.client_id
        assert pybullet.getConnectionInfo(cid)['isConnected'] == 1
    assert not world.connected
    assert pybullet.getConnectionInfo(cid)['isConnected'] == 0
    with pytest.raises(CdmpError, match='closed'):
        world.step()
    world.close()  # idempotent


def test_world_closes_on_exception_and_worlds_are_independent():
    with pytest.raises(RuntimeError):
        with World() as world:
            cid = world.client_id
            raise RuntimeError('boom')
    assert pybullet.getConnectionInfo(cid)['isConnected'] == 0
    with World() as a, World() as b:
        ra = a.add_robot(planar_arm_spec())
        b.add_robot(planar_arm_spec())
        ra.set_reference([0.5, 0.0, 0.0, 0.0])
        a.run(0.5)
        assert a.t == pytest.approx(0.5) and b.t == 0.0
        assert b.robot('planar_arm').q[0] == 0.0 and ra.q[0] > 0.1


def test_panda_limits_come_from_the_urdf():
    with World() as world:
        robot = world.add_robot(panda_spec())
        lo, hi, vel, eff = urdf_limits(PANDA_URDF, robot.joint_names)
        np.testing.assert_array_equal(robot.lower, lo)
        np.testing.assert_array_equal(robot.upper, hi)
        np.testing.assert_array_equal(robot.velocity_limits, vel)
        np.testing.assert_array_equal(robot.effort_limits, eff)
        assert robot.n_dofs == 7 and robot.ee_link == 'panda_hand'
        np.testing.assert_allclose(robot.q, robot.spec.home, atol=1e-12)
        held = world.add_robot(panda_spec(fingers='held'), name='held')
        np.testing.assert_array_equal(held.lower, lo)
        # both variants have the same arm kinematics
        np.testing.assert_allclose(held.ee_position(), robot.ee_position(), atol=1e-9)


def test_planar_arm_kinematics_and_limits(rng):
    with World() as world:
        arm = world.add_robot(planar_arm_spec(lower=[-1, -2, -2, -2], upper=[1, 2, 2, 2.5]))
        np.testing.assert_array_equal(arm.lower, [-1, -2, -2, -2])
        np.testing.assert_array_equal(arm.upper, [1, 2, 2, 2.5])
        for _ in range(3):
            q = rng.uniform(-1, 1, 4)
            arm.reset(q)
            a = np.cumsum(q)
            np.testing.assert_allclose(arm.ee_position(),
                                       [np.cos(a).sum(), np.sin(a).sum(), 0.0], atol=1e-9)
        # planar: gravity along -z produces no joint torque
        np.testing.assert_allclose(arm.gravity(q), 0.0, atol=1e-9)
    text = planar_arm_urdf(link_lengths=(0.5, 0.7))
    assert text.count('type="revolute"') == 2 and 'name="ee"' in text
    with pytest.raises(ValidationError, match='link_lengths'):
        planar_arm_urdf(link_lengths=(1.0, -1.0))


def test_dual_panda_cell_bases_face_each_other():
    with World() as world:
        left, right = add_dual_panda(world)
        np.testing.assert_allclose(right.link_pose('panda_link0')[0], [1.13, 0.0, 0.0])
        # same joint angles: the right hand is the left one rotated by pi about the z axis
        # through the midpoint of the bases
        pl, pr = left.ee_position(), right.ee_position()
        np.testing.assert_allclose(pr, [1.13 - pl[0], -pl[1], pl[2]], atol=1e-9)
        assert set(world.robots) == {'left', 'right'}


def test_robot_input_validation():
    with World() as world:
        robot = world.add_robot(panda_spec())
        with pytest.raises(ValidationError, match='name'):
            world.add_robot(panda_spec())
        with pytest.raises(ValidationError, match=r'q: expected shape \(7\)'):
            robot.set_reference(np.zeros(6))
        bad = np.array(robot.spec.home)
        bad[3] = 0.5
        with pytest.raises(ValidationError, match=r'q\[3\] \(panda_joint4\)'):
            robot.reset(bad)
        with pytest.raises(ValidationError, match='link'):
            robot.link_pose('nope')
    with pytest.raises(ValidationError, match='time_step'):
        WorldConfig(time_step=0.0)


class FakeTime:
    """Stands in for the ``time`` module of cdmp_ros.sim.world: a clock that only ``sleep`` and
    the steps advance (``step_cost`` s per step: the paced loop reads the clock once a step)."""

    def __init__(self, step_cost=0.0):
        self.now = 1000.0
        self.step_cost = step_cost
        self.slept = []

    def perf_counter(self):
        self.now += self.step_cost
        return self.now

    def sleep(self, seconds):
        assert seconds > 0.0
        self.slept.append(seconds)
        self.now += seconds


def test_fixed_step_mode_never_waits_for_the_wall_clock(monkeypatch):
    """Fixed-step mode steps as fast as the machine allows: no sleep, no clock read; one
    simulated second is exactly 1000 steps of 1 ms.  How much faster than real time it runs
    is a figure of the machine (benchmarks/bench_sim.py prints it)."""
    import cdmp_ros.sim.world as world_module

    class NoClock:
        def __getattr__(self, name):
            raise AssertionError(f'fixed-step mode used time.{name}')
    monkeypatch.setattr(world_module, 'time', NoClock())
    with World(WorldConfig(time_step=1e-3)) as world:
        robot = world.add_robot(panda_spec())
        robot.set_controller(ComputedTorqueController())
        assert world.run(1.0) == pytest.approx(1.0)
        assert world._n_steps == 1000


@pytest.mark.parametrize('step_cost', [0.0, 2e-4])
def test_real_time_pacing_follows_the_wall_clock(monkeypatch, step_cost):
    """On a clock that only the pacing's sleeps and the steps advance, simulated time never
    runs ahead of the wall clock and the pacing sleeps exactly the rest of every step: 0.3 s
    simulated take 0.3 s of that clock from the first (anchoring) step on."""
    import cdmp_ros.sim.world as world_module
    fake = FakeTime(step_cost)
    monkeypatch.setattr(world_module, 'time', fake)
    with World(WorldConfig(time_step=1e-3, real_time=True)) as world:
        world.add_robot(planar_arm_spec())
        start = fake.now
        world.run(0.3)
        wall = fake.now - start
    assert world.t == pytest.approx(0.3)
    assert wall == pytest.approx(step_cost + 0.3 - 1e-3, abs=1e-9)
    assert len(fake.slept) == 299
    np.testing.assert_allclose(fake.slept, 1e-3 - step_cost, atol=1e-9)


def test_real_time_pacing_does_not_burst_after_a_stall(monkeypatch):
    """A stall of more than 100 ms (the machine was busy) restarts the pacing from now instead
    of stepping flat out to catch up: the steps after it are paced again."""
    import cdmp_ros.sim.world as world_module
    fake = FakeTime()
    monkeypatch.setattr(world_module, 'time', fake)
    with World(WorldConfig(time_step=1e-3, real_time=True)) as world:
        world.add_robot(planar_arm_spec())
        world.run(0.05)
        fake.now += 0.5  # stalled for 0.5 s
        n_slept = len(fake.slept)
        world.run(0.05)
    # the step after the stall re-anchors (no sleep), every later one sleeps one step
    assert len(fake.slept) - n_slept == 49
    np.testing.assert_allclose(fake.slept[n_slept:], 1e-3, atol=1e-9)


def test_real_time_pacing_on_the_real_clock_never_runs_ahead():
    """The same on the real clock: a lower bound only (a loaded machine is later, never
    earlier)."""
    with World(WorldConfig(time_step=1e-3, real_time=True)) as world:
        world.add_robot(planar_arm_spec())
        start = time.perf_counter()
        world.run(0.3)
        wall = time.perf_counter() - start
    assert world.t == pytest.approx(0.3)
    assert wall >= 0.3 - 2e-3, wall


def test_home_is_validated():
    with pytest.raises(ValidationError, match='home'):
        panda_spec(home=(0.0,) * 6)
    with pytest.raises(ValidationError, match='fingers'):
        panda_spec(fingers='loose')
    assert math.isclose(panda_spec().home[3], -3 * math.pi / 4)


def test_ee_point_is_the_tool_centre_point_of_core_kinematics(rng):
    """Robot.ee_position() is the same point as core.kinematics' PointOfInterest('ee')
    (panda_hand frame + PANDA_EE_OFFSET), and the chain's FK matches pybullet's links."""
    from cdmp_ros.core.kinematics import panda_chain, PointOfInterest
    with World() as world:
        robot = world.add_robot(panda_spec())
        chain = panda_chain(robot.spec.urdf_path)
        points = [PointOfInterest('ee'), PointOfInterest('panda_link4')]
        for _ in range(3):
            q = robot.lower + (robot.upper - robot.lower) * rng.uniform(0.1, 0.9, 7)
            robot.reset(q)
            X = chain.forward(q, points)
            np.testing.assert_allclose(X[0], robot.ee_position(), atol=1e-6)
            np.testing.assert_allclose(X[1], robot.link_pose('panda_link4')[0], atol=1e-6)
