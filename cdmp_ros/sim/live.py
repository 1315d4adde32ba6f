"""The simulated robot behind the ``sim`` node, without ROS: robots, reference, obstacles,
monitoring.

:class:`LiveSim` owns a :class:`~cdmp_ros.sim.world.World` (pybullet DIRECT, fixed step
``1 / physics_rate``) with the robot(s) of a :class:`~cdmp_ros.sim.node_config.SimConfig`, and

- tracks one joint reference ``(q_ref, qd_ref)`` of all controlled joints (``joint_names``
  order; for ``dual_panda`` the joints of ``left`` then ``right``, prefixed ``left_`` /
  ``right_``) with the configured control law, held between two :meth:`set_reference` calls;
- keeps every joint inside its limits whatever it is commanded, as a real arm does (see
  *Hard limits* below);
- keeps its obstacles (spheres, axis-aligned boxes of :mod:`cdmp_ros.core.kinematics.closest`)
  in sync with a named set (:meth:`sync_obstacles`);
- measures, after every physics step, limit violations, the largest limit usage
  ``|q - centre| / half-range`` and the tracking error ``max |q_ref - q|``; and, when
  :meth:`monitor` is called, the minimum link-obstacle distance and the contacts (in a cell
  of several robots, ``dual_panda``, also the robots' links against each other).

Every figure of :class:`SimStats` is what the node reports on ``/diagnostics`` (same key names).

Hard limits. Left to pybullet, a flood of references jumping across the range carried joints
through their limits by up to 76 mrad (measured, panda, position control; 31 passes in a
fuzz run of the node), for three reasons: nothing bounded the joint speed (the position motors
and the torque laws drove joints at up to pybullet's default cap of 100 rad/s, 46 times the
Panda's 2.175 rad/s); pybullet's joint stops act only once a joint is past them (a joint
arriving at speed ``v`` ends ``v dt`` beyond, then is pushed back slowly, or not at all while
the motor or gravity pushes on: a wrist joint stayed 75 mrad outside); and a reference at a
limit with a velocity pointing outward moves the equilibrium of the position motors
(``velocity_gain qd_ref dt / position_gain`` = 22 mrad at 2.175 rad/s) and of computed torque
(``kd qd_ref / kp``) beyond it. So:

- joint speeds are capped at the velocity limits (pybullet's ``maxJointVelocity`` is one value
  per body: the largest limit of its joints), and pybullet's joint stops sit at the limits
  the sim holds (the tighter of the model's and ``robot_limits``);
- :meth:`LiveSim.set_reference` clips the position into the limits, and a joint whose
  reference is at a limit gets no velocity pointing beyond it;
- after every physics step, an **end stop** puts a joint that crossed its limit during the step
  back at the limit and removes its outward velocity (an inelastic stop; counted as
  ``limit_stops``, its depth as ``limit_stop_depth_max_rad``). A joint moved beyond its limit
  from outside the physics (a teleport) is never let further out, is left to pybullet's stop
  to come back, and counts as a ``limit_violations`` while it is out.

Typical use::

    sim = LiveSim(SimConfig(robot='panda', control='computed_torque'))
    sim.set_reference(q_ref, qd_ref)
    sim.step(4)                        # 4 physics steps of 1 ms
    q, qd, effort = sim.state()
    sim.sync_obstacles({'ball': Sphere((0.5, 0.0, 0.5), 0.1)})
    sim.monitor()
    sim.close()
"""
import math
import os
import tempfile
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence, Set, Tuple, Union

import numpy as np
from numpy.typing import ArrayLike, NDArray
import pybullet

from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.joint_limits import merge_limits
from cdmp_ros.core.kinematics.closest import Box, OrientedBox, Sphere
from cdmp_ros.core.validation import as_array
from cdmp_ros.sim.camera import CameraConfig, snapshot
from cdmp_ros.sim.control import (ComputedTorqueController, ComputedTorqueGains,
                                  inertia_scaled_gains, JointLimitAvoidingController,
                                  JointLimitAvoidingGains, PositionControlGains,
                                  PositionController)
from cdmp_ros.sim.node_config import SimConfig
from cdmp_ros.sim.robot_specs import add_dual_panda, panda_spec, planar4_spec
from cdmp_ros.sim.world import World, WorldConfig

Obstacle = Union[Sphere, Box, OrientedBox]

#: Camera of the snapshots per robot kind.
CAMERAS = {
    'panda': CameraConfig(target=(0.35, 0.1, 0.4), distance=1.4, yaw=60.0, pitch=-25.0),
    'dual_panda': CameraConfig(target=(0.56, 0.0, 0.4), distance=2.4, yaw=20.0, pitch=-30.0),
    'planar4': CameraConfig(target=(1.0, 0.0, 0.0), distance=6.0, yaw=0.0, pitch=-89.0),
}


def build_robots(world: World, robot: str) -> Tuple[list, Tuple[str, ...], str]:
    """Load ``robot`` (a :data:`~cdmp_ros.sim.node_config.ROBOTS` name) into ``world``.

    Returns
    -------
    robots : list of Robot
    joint_names : tuple of str
        All controlled joints, robot after robot (prefixed ``<robot>_`` for several robots).
    base_frame : str
        The frame of positions: the base link of a single robot, ``'world'`` for the cell.
    """
    if robot == 'panda':
        r = world.add_robot(panda_spec())
        return [r], tuple(r.joint_names), r.link_names[0]
    if robot == 'planar4':
        r = world.add_robot(planar4_spec())
        return [r], tuple(r.joint_names), r.link_names[0]
    if robot == 'dual_panda':
        robots = list(add_dual_panda(world))
        names = tuple(f'{r.name}_{j}' for r in robots for j in r.joint_names)
        return robots, names, 'world'
    raise ValidationError(f'robot: expected one of panda, dual_panda, planar4, got {robot!r}')


def _same_rotation(q1, q2) -> bool:
    """Two unit quaternions describe the same rotation (q and -q do)."""
    return abs(abs(float(np.dot(q1, q2))) - 1.0) < 1e-12


@dataclass
class SimStats:
    """Figures since the start (or the current value), reported on ``/diagnostics``.

    Attributes
    ----------
    min_obstacle_distance_m : float
        Current smallest link-obstacle distance [m] (inf: no obstacle within range).
    min_obstacle_distance_since_start_m : float
        Smallest value of the above over every :meth:`LiveSim.monitor` call [m].
    closest_pair_since_start : str
        ``link/obstacle`` of that smallest distance (``robot/link/obstacle`` in a cell of
        several robots; empty: none yet): which part of the arm came closest, or touched.
    contacts : int
        Link-obstacle pairs, and in a cell link-link pairs of two robots, in contact now
        (distance <= contact_threshold).
    contacts_since_start : int
        Contact onsets since the start: a pair in contact that was not at the previous
        monitor call.
    limit_violations : int
        Physics steps after which a measured joint (after the end stops acted) was more than
        ``limit_tolerance`` outside its limits.
    limit_stops : int
        Physics steps in which an end stop put a joint that crossed its limit back at it.
    limit_stop_depth_max_rad : float
        The largest distance beyond its limit [rad or m] a joint had reached in a step when
        its end stop put it back.
    max_limit_usage_since_start : float
        Largest ``|q - centre| / half-range`` over joints and steps (1 = at a limit).
    tracking_error_rad : float
        ``max |q_ref - q|`` over joints after the last step [rad or m].
    tracking_error_max_rad : float
        Largest tracking error over every step since the start.
    min_robot_distance_m : float
        Cells only: current smallest distance between the links of two robots [m] (inf: one
        robot, or none within ``distance_range``).
    min_robot_distance_since_start_m : float
        Smallest value of the above over every :meth:`LiveSim.monitor` call [m].
    """

    min_obstacle_distance_m: float = math.inf
    min_obstacle_distance_since_start_m: float = math.inf
    closest_pair_since_start: str = ''
    contacts: int = 0
    contacts_since_start: int = 0
    limit_violations: int = 0
    limit_stops: int = 0
    limit_stop_depth_max_rad: float = 0.0
    max_limit_usage_since_start: float = 0.0
    tracking_error_rad: float = 0.0
    tracking_error_max_rad: float = 0.0
    min_robot_distance_m: float = math.inf
    min_robot_distance_since_start_m: float = math.inf
    contact_pairs: List[Tuple[str, str, float]] = field(default_factory=list)

    def as_values(self) -> Dict[str, str]:
        """The figures as diagnostics key/values (strings)."""
        return {
            'min_obstacle_distance_m': f'{self.min_obstacle_distance_m:.5f}',
            'min_obstacle_distance_since_start_m':
                f'{self.min_obstacle_distance_since_start_m:.5f}',
            'closest_pair_since_start': self.closest_pair_since_start,
            'contacts': str(self.contacts),
            'contacts_since_start': str(self.contacts_since_start),
            'limit_violations': str(self.limit_violations),
            'limit_stops': str(self.limit_stops),
            'limit_stop_depth_max_rad': f'{self.limit_stop_depth_max_rad:.6f}',
            'max_limit_usage_since_start': f'{self.max_limit_usage_since_start:.5f}',
            'tracking_error_rad': f'{self.tracking_error_rad:.6f}',
            'tracking_error_max_rad': f'{self.tracking_error_max_rad:.6f}',
            'min_robot_distance_m': f'{self.min_robot_distance_m:.5f}',
            'min_robot_distance_since_start_m': f'{self.min_robot_distance_since_start_m:.5f}',
        }


class LiveSim:
    """The simulated robot(s) of a :class:`SimConfig` (see the module docstring).

    Parameters
    ----------
    config : SimConfig
        ``initial_positions`` (if given) must have one value per joint, inside the limits.
    robot_limits : (lower, upper, velocity_limits), each (n_dofs,), optional
        The limits of the robot that runs (its ``robot_description`` or ``urdf_path``): the
        simulated robot holds the tighter of these and its pybullet model's, per joint and
        bound (references are clipped into them, violations counted against them).

    Attributes
    ----------
    joint_names : tuple of str
    n_dofs : int
    lower, upper, velocity_limits : (n_dofs,) ndarray
        From the URDF(s) pybullet loads, tightened by ``robot_limits``.
    limit_mismatches : list of LimitMismatch
        Where ``robot_limits`` differ from the pybullet model's (``robot`` = ``robot_limits``,
        ``primitive`` = the pybullet model).
    base_frame : str
        ``config.base_frame`` or the robot base (see :func:`build_robots`).
    initial_positions : (n_dofs,) ndarray
    n_steps : int
        Physics steps since the start.
    stats : SimStats
    """

    def __init__(self, config: SimConfig,
                 robot_limits: Optional[Tuple[ArrayLike, ArrayLike, ArrayLike]] = None):
        self.config = config
        self.world = World(WorldConfig(time_step=config.physics_dt, real_time=False))
        try:
            self.robots, self.joint_names, base = build_robots(self.world, config.robot)
            self.base_frame = config.base_frame or base
            self.n_dofs = len(self.joint_names)
            self.lower = np.concatenate([r.lower for r in self.robots])
            self.upper = np.concatenate([r.upper for r in self.robots])
            self.velocity_limits = np.concatenate([r.velocity_limits for r in self.robots])
            self.limit_mismatches = []
            if robot_limits is not None:  # the tighter of the two, never wider
                lo, hi, vmax = robot_limits
                self.lower, self.upper, self.limit_mismatches = merge_limits(
                    self.joint_names, lo, hi, self.lower, self.upper)
                self.velocity_limits = np.minimum(
                    self.velocity_limits, as_array('robot_limits[2]', vmax, (self.n_dofs,)))
            self._joints = [(r.body_id, j) for r in self.robots for j in r._arm_idx]
            self._set_stops()
            self._centre = 0.5 * (self.upper + self.lower)
            self._half = 0.5 * (self.upper - self.lower)
            self._inv_half = 1.0 / self._half
            self._slices = []
            i = 0
            for r in self.robots:
                self._slices.append(slice(i, i + r.n_dofs))
                i += r.n_dofs
            home = np.concatenate([np.asarray(r.spec.home) for r in self.robots])
            self.initial_positions = self.check_positions(
                'initial_positions', home if config.initial_positions is None
                else config.initial_positions)
            r0 = self.robots[0]
            offset = np.asarray(r0.spec.ee_offset, dtype=np.float64)
            self._ee_offset = offset if np.any(offset != 0.0) else None
            self._base_identity = self.base_frame == 'world' or (
                np.allclose(r0.base_position, 0.0)
                and np.allclose(r0.base_orientation, [0.0, 0.0, 0.0, 1.0]))
            self._base_inv = pybullet.invertTransform(r0.base_position.tolist(),
                                                      r0.base_orientation.tolist())
            self.n_steps = 0
            self.stats = SimStats()
            self._contact_keys: Set[Tuple[str, str, str]] = set()
            self.reset()
            self.set_control(config)
        except Exception:
            self.world.close()
            raise

    def _set_stops(self) -> None:
        """pybullet's joint stops at the limits the sim holds; joint speeds capped at the
        velocity limits (one cap per body in pybullet: the largest limit of its joints)."""
        cid = self.world.client_id
        i = 0
        for r in self.robots:
            cap = float(np.max(self.velocity_limits[i:i + r.n_dofs]))
            for j in r._arm_idx:
                pybullet.changeDynamics(r.body_id, j, jointLowerLimit=float(self.lower[i]),
                                        jointUpperLimit=float(self.upper[i]),
                                        maxJointVelocity=cap, physicsClientId=cid)
                i += 1

    # -- configuration ---------------------------------------------------------------------
    def check_positions(self, name: str, q: ArrayLike) -> NDArray[np.float64]:
        """``q`` as ``(n_dofs,)``, finite and inside the limits (else ValidationError)."""
        q = np.asarray(q, dtype=np.float64) if not isinstance(q, np.ndarray) else q
        if q.shape != (self.n_dofs,):
            raise ValidationError(f'{name}: expected {self.n_dofs} values (one per joint of '
                                  f'{self.config.robot}: {list(self.joint_names)}), got '
                                  f'{q.size}')
        q = as_array(name, q, (self.n_dofs,))
        bad = np.flatnonzero((q < self.lower) | (q > self.upper))
        if bad.size:
            j = int(bad[0])
            raise ValidationError(f'{name}[{j}] ({self.joint_names[j]}): expected a value in '
                                  f'[{self.lower[j]}, {self.upper[j]}], got {q[j]}')
        return q.copy()

    def set_control(self, config: SimConfig) -> None:
        """Apply the control law and gains of ``config`` (raises ValidationError)."""
        for r, sl in zip(self.robots, self._slices):
            if config.control == 'position':
                ctrl = PositionController(PositionControlGains(
                    config.position_gain, config.velocity_gain))
            elif config.control == 'computed_torque':
                ctrl = ComputedTorqueController(ComputedTorqueGains(config.kp, config.kd))
            elif config.control == 'exogenous':
                kp, kd = inertia_scaled_gains(r, config.kp, config.kd,
                                              self.initial_positions[sl])
                ctrl = JointLimitAvoidingController(JointLimitAvoidingGains(
                    kp, kd, config.exogenous_margin))
            else:
                raise ValidationError(f'control: expected position, computed_torque or '
                                      f'exogenous, got {config.control!r}')
            r.set_controller(ctrl)
        self.config = config

    def set_initial_positions(self, q: ArrayLike) -> None:
        """The pose of the next :meth:`reset` (validated)."""
        self.initial_positions = self.check_positions('initial_positions', q)

    # -- reference and state ---------------------------------------------------------------
    def reset(self) -> None:
        """Teleport to ``initial_positions`` at rest; the reference becomes that pose."""
        for r, sl in zip(self.robots, self._slices):
            r.reset(self.initial_positions[sl])
        self.q_ref = self.initial_positions.copy()
        self.qd_ref = np.zeros(self.n_dofs)
        self._q, self._qd, self._effort = self._read()

    def set_reference(self, q: NDArray[np.float64], qd: Optional[NDArray[np.float64]] = None
                      ) -> None:
        """Track ``(q, qd)`` (``(n_dofs,)`` each, finite) from the next step on.

        ``q`` is clipped into the limits; where it is at a limit, a velocity pointing beyond
        it is dropped (it would move the control law's equilibrium outside: the position
        motors settle ``velocity_gain qd dt / position_gain`` beyond their target, computed
        torque ``kd qd / kp``).
        """
        lo, hi = self.lower, self.upper
        if (q < lo).any() or (q > hi).any():
            q = np.clip(q, lo, hi)
        if qd is None:
            qd = np.zeros(self.n_dofs)
        else:
            out = ((q >= hi) & (qd > 0.0)) | ((q <= lo) & (qd < 0.0))
            if out.any():
                qd = np.where(out, 0.0, qd)
        self.q_ref = q
        self.qd_ref = qd
        for r, sl in zip(self.robots, self._slices):
            r.set_reference(q[sl], self.qd_ref[sl])

    def hold(self) -> None:
        """Keep the reference position with zero velocity (a stale reference)."""
        self.set_reference(self.q_ref, None)

    def halt(self) -> None:
        """Hold the current measured position at rest (what a Panda does after a reflex)."""
        self.set_reference(self._q.copy(), None)

    def _read(self):
        if len(self.robots) == 1:
            return self.robots[0].joint_state_effort()
        parts = [r.joint_state_effort() for r in self.robots]
        return tuple(np.concatenate([p[k] for p in parts]) for k in range(3))

    def state(self) -> Tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """Measured ``(q, qd, effort)`` after the last step, ``(n_dofs,)`` each."""
        return self._q, self._qd, self._effort

    @property
    def t(self) -> float:
        """Simulated time [s]."""
        return self.world.t

    def step(self, n_steps: int = 1) -> None:
        """``n_steps`` physics steps; after each, update the limit and tracking figures."""
        st = self.stats
        centre, inv_half = self._centre, self._inv_half
        lower, upper = self.lower, self.upper
        outside = self._half + self.config.limit_tolerance
        step = self.world.step
        # the state before the first step as pybullet holds it (a joint may have been moved
        # from outside since the last step: it did not cross its limit in the physics)
        prev = self._read()[0] if n_steps > 0 else self._q
        for _ in range(int(n_steps)):
            step(1)
            self.n_steps += 1
            q, qd, effort = self._read()
            if (q > upper).any() or (q < lower).any():  # rare: a joint beyond a limit
                q, qd = self._end_stops(prev, q, qd)
            dev = np.abs(q - centre)
            if (dev > outside).any():
                st.limit_violations += 1
            prev = q
            usage = float((dev * inv_half).max())
            if usage > st.max_limit_usage_since_start:
                st.max_limit_usage_since_start = usage
            err = float(np.abs(self.q_ref - q).max())
            st.tracking_error_rad = err
            if err > st.tracking_error_max_rad:
                st.tracking_error_max_rad = err
        if n_steps > 0:
            self._q, self._qd, self._effort = q, qd, effort

    def _end_stops(self, prev: NDArray[np.float64], q: NDArray[np.float64],
                   qd: NDArray[np.float64]) -> Tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The end stops after a physics step: a joint beyond its limit and further out than
        before the step (``prev``) is put back at the limit (or where it was, if it was
        already beyond: moved there from outside the physics) without its outward velocity;
        returns ``(q, qd)``."""
        hi = np.maximum(self.upper, prev)
        lo = np.minimum(self.lower, prev)
        above = q > hi
        below = q < lo
        crossed = np.flatnonzero(above | below)
        if crossed.size == 0:
            return q, qd
        q, qd = q.copy(), qd.copy()
        cid = self.world.client_id
        depth = 0.0
        for i in crossed.tolist():
            if above[i]:
                depth = max(depth, q[i] - self.upper[i])
                q[i], qd[i] = hi[i], min(qd[i], 0.0)
            else:
                depth = max(depth, self.lower[i] - q[i])
                q[i], qd[i] = lo[i], max(qd[i], 0.0)
            body, joint = self._joints[i]
            pybullet.resetJointState(body, joint, float(q[i]), float(qd[i]),
                                     physicsClientId=cid)
        st = self.stats
        st.limit_stops += 1
        if depth > st.limit_stop_depth_max_rad:
            st.limit_stop_depth_max_rad = float(depth)
        return q, qd

    def ee_pose(self) -> Tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Position ``(3,)`` [m] and quaternion ``(4,)`` (x, y, z, w) of the end effector of
        the first robot, in the base frame (its ``ee_link`` orientation at the tool point)."""
        r = self.robots[0]
        pos, orn = r.link_pose(r.ee_link)
        if self._ee_offset is not None:  # the tool point: ee_offset in the ee_link frame
            R = np.array(pybullet.getMatrixFromQuaternion(orn.tolist())).reshape(3, 3)
            pos = pos + R @ self._ee_offset
        if self._base_identity:
            return pos, orn
        p, q = pybullet.multiplyTransforms(self._base_inv[0], self._base_inv[1], pos.tolist(),
                                           orn.tolist())
        return np.array(p), np.array(q)

    # -- obstacles --------------------------------------------------------------------------
    def sync_obstacles(self, obstacles: Dict[str, Obstacle]) -> None:
        """Make the world's obstacles exactly ``obstacles`` (name -> Sphere, Box or OrientedBox).

        Unchanged ones are kept, moved ones moved, changed shapes replaced, the rest removed.
        """
        obs = self.world.obstacles
        collide = self.config.obstacles_collide
        for name in obs.names:
            if name not in obstacles:
                obs.remove(name)
        for name, item in obstacles.items():
            orn = (0.0, 0.0, 0.0, 1.0)
            if isinstance(item, Sphere):
                shape, size, pos = 'sphere', (float(item.radius),), item.center
            elif isinstance(item, OrientedBox):
                shape, size, pos = 'box', tuple(item.half), item.center
                orn = item.quaternion()
            else:
                lo, hi = np.asarray(item.lower), np.asarray(item.upper)
                shape, size, pos = 'box', tuple((0.5 * (hi - lo)).tolist()), 0.5 * (lo + hi)
            pos = tuple(float(v) for v in pos)
            if name in obs:
                info = obs.get(name)
                if (info.shape == shape and info.collide == collide
                        and np.allclose(info.size, size, rtol=0.0, atol=1e-12)):
                    if not (np.allclose(info.position, pos, rtol=0.0, atol=1e-12)
                            and _same_rotation(info.orientation, orn)):
                        obs.move(name, pos, orn)
                    continue
            if shape == 'sphere':
                if size[0] > 0.0:
                    obs.add_sphere(name, pos, size[0], collide=collide, replace=True)
                elif name in obs:  # a zero-radius sphere is a point: no body to collide with
                    obs.remove(name)
            else:
                obs.add_box(name, pos, size, orientation=orn, collide=collide, replace=True)

    def monitor(self) -> SimStats:
        """Update the obstacle distance, robot-robot distance and contact figures from the
        current state."""
        st = self.stats
        cfg = self.config
        best = math.inf
        best_pair = ''
        keys = set()
        pairs = []
        if len(self.world.obstacles):
            for r in self.robots:
                report = self.world.obstacles.distances(r, cfg.distance_range)
                for (link, obstacle), p in report.pairs.items():
                    if p.distance < best:
                        best = p.distance
                        best_pair = (f'{link}/{obstacle}' if len(self.robots) == 1
                                     else f'{r.name}/{link}/{obstacle}')
                    if p.distance <= cfg.contact_threshold:
                        keys.add((r.name, link, obstacle))
                        pairs.append((link, obstacle, p.distance))
        st.min_obstacle_distance_m = best
        if best < st.min_obstacle_distance_since_start_m:
            st.min_obstacle_distance_since_start_m = best
            st.closest_pair_since_start = best_pair
        if len(self.robots) > 1:
            closest = math.inf
            for a, b, link_a, link_b, d in self._robot_distances():
                closest = min(closest, d)
                if d <= cfg.contact_threshold:
                    keys.add((a, link_a, f'{b}/{link_b}'))
                    pairs.append((f'{a}/{link_a}', f'{b}/{link_b}', d))
            st.min_robot_distance_m = closest
            if closest < st.min_robot_distance_since_start_m:
                st.min_robot_distance_since_start_m = closest
        st.contacts = len(keys)
        st.contacts_since_start += len(keys - self._contact_keys)
        st.contact_pairs = sorted(pairs, key=lambda c: c[2])
        self._contact_keys = keys
        return st

    def _robot_distances(self):
        """(robot a, robot b, link of a, link of b, distance) for the closest link pairs of
        every two robots of the cell (within ``distance_range``)."""
        cid = self.world.client_id
        out = {}
        for i, a in enumerate(self.robots):
            for b in self.robots[i + 1:]:
                for pt in pybullet.getClosestPoints(a.body_id, b.body_id,
                                                    self.config.distance_range,
                                                    physicsClientId=cid):
                    key = (a.name, b.name, a.link_names[pt[3] + 1], b.link_names[pt[4] + 1])
                    if pt[8] < out.get(key, math.inf):
                        out[key] = pt[8]
        return [(ra, rb, la, lb, d) for (ra, rb, la, lb), d in out.items()]

    # -- output ----------------------------------------------------------------------------
    def snapshot(self, path: str = '') -> str:
        """Render the world (TinyRenderer) to a PNG at ``path`` (empty: a new temporary file);
        returns the path."""
        if not path:
            fd, path = tempfile.mkstemp(prefix='cdmp_sim_snapshot_', suffix='.png')
            os.close(fd)
        snapshot(self.world, path, CAMERAS[self.config.robot])
        return os.path.abspath(path)

    def close(self) -> None:
        self.world.close()


def limit_clip(q: NDArray[np.float64], lower: NDArray[np.float64], upper: NDArray[np.float64]
               ) -> Tuple[NDArray[np.float64], Sequence[int]]:
    """``q`` clipped into ``[lower, upper]`` and the indices that were outside."""
    bad = np.flatnonzero((q < lower) | (q > upper))
    if bad.size:
        return np.clip(q, lower, upper), bad.tolist()
    return q, ()
