"""A pybullet world on a private DIRECT client: robots, obstacles, fixed-step or paced stepping.

Typical use::

    from cdmp_ros.sim import World, WorldConfig, panda_spec, ComputedTorqueController

    with World(WorldConfig(time_step=1e-3)) as world:
        robot = world.add_robot(panda_spec())
        robot.set_controller(ComputedTorqueController())
        robot.set_reference(q_ref, qd_ref, qdd_ref)   # joint reference, (n_dofs,)
        world.step()                                  # one physics step of ``time_step``
        q, qd = robot.joint_state()
        world.obstacles.add_sphere('ball', (0.5, 0.0, 0.5), radius=0.1)
        report = world.obstacles.distances(robot)

Each :class:`World` owns its own pybullet client (``pybullet.connect(pybullet.DIRECT)``), so any
number of worlds coexist in one process. Always close it (``with`` block or :meth:`World.close`).
"""
from dataclasses import dataclass
import time
from typing import Dict, Optional, Sequence

import pybullet

from cdmp_ros.core.errors import CdmpError, ValidationError
from cdmp_ros.core.validation import as_array, check_positive, lookup
from cdmp_ros.sim.obstacles import Obstacles
from cdmp_ros.sim.robot import Robot
from cdmp_ros.sim.robot_specs import RobotSpec


@dataclass(frozen=True)
class WorldConfig:
    """Physics settings of a :class:`World`.

    Attributes
    ----------
    time_step : float
        Fixed physics step [s] (1 kHz by default).
    gravity : tuple of float
        Gravity vector in the world frame [m/s^2].
    real_time : bool
        If True, :meth:`World.step` sleeps so that simulated time follows wall-clock time
        (for a live robot behind ROS); if False, steps run as fast as possible (tests,
        experiments, benchmarks).
    solver_iterations : int
        Constraint solver iterations per step (pybullet ``numSolverIterations``).
    """

    time_step: float = 1e-3
    gravity: tuple = (0.0, 0.0, -9.81)
    real_time: bool = False
    solver_iterations: int = 50

    def __post_init__(self):
        check_positive('time_step', self.time_step)
        if self.time_step > 0.1:
            raise ValidationError(f'time_step: expected <= 0.1 s, got {self.time_step}')
        object.__setattr__(self, 'gravity', tuple(
            float(g) for g in as_array('gravity', self.gravity, (3,))))
        if int(self.solver_iterations) != self.solver_iterations or self.solver_iterations < 1:
            raise ValidationError('solver_iterations: expected a positive integer, got '
                                  f'{self.solver_iterations!r}')


class World:
    """Physics world owning one private pybullet client in DIRECT mode.

    Parameters
    ----------
    config : WorldConfig, optional
        Physics settings.

    Attributes
    ----------
    config : WorldConfig
    robots : dict of str to Robot
        Robots by name, in insertion order.
    obstacles : Obstacles
        Spheres and boxes added, moved and removed at run time; distance and contact queries.
    t : float
        Simulated time since creation [s].
    """

    def __init__(self, config: Optional[WorldConfig] = None):
        self.config = config if config is not None else WorldConfig()
        self._cid = pybullet.connect(pybullet.DIRECT)
        if self._cid < 0:
            raise CdmpError('pybullet: could not connect a DIRECT client')
        try:
            pybullet.resetSimulation(physicsClientId=self._cid)
            pybullet.setGravity(*self.config.gravity, physicsClientId=self._cid)
            pybullet.setPhysicsEngineParameter(
                fixedTimeStep=self.config.time_step,
                numSolverIterations=int(self.config.solver_iterations),
                numSubSteps=0, physicsClientId=self._cid)
        except Exception:
            pybullet.disconnect(self._cid)
            raise
        self.robots: Dict[str, Robot] = {}
        self.obstacles = Obstacles(self)
        self.t = 0.0
        self._n_steps = 0
        self._pace_anchor: Optional[tuple] = None

    # -- lifetime -------------------------------------------------------------------------
    @property
    def client_id(self) -> int:
        """The pybullet client id (``physicsClientId`` of every call on this world)."""
        self._check_open()
        return self._cid

    @property
    def connected(self) -> bool:
        """True until :meth:`close` was called."""
        return self._cid is not None

    def close(self) -> None:
        """Disconnect the pybullet client. Idempotent."""
        if self._cid is not None:
            try:
                pybullet.disconnect(physicsClientId=self._cid)
            finally:
                self._cid = None

    def __enter__(self) -> 'World':
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self):
        try:
            self.close()
        except Exception:  # interpreter shutdown: pybullet may already be gone
            pass

    def _check_open(self) -> None:
        if self._cid is None:
            raise CdmpError('World: the pybullet client is closed')

    # -- content ---------------------------------------------------------------------------
    def add_robot(self, spec: RobotSpec, base_position: Sequence[float] = (0.0, 0.0, 0.0),
                  base_orientation: Sequence[float] = (0.0, 0.0, 0.0, 1.0),
                  name: Optional[str] = None, joint_stops: bool = True) -> Robot:
        """Load a robot from its URDF and hold it at ``spec.home``.

        Parameters
        ----------
        spec : RobotSpec
            What to load (see :func:`cdmp_ros.sim.robot_specs.panda_spec`, ``planar_arm_spec``).
        base_position : (3,) array-like
            Base position in the world frame [m].
        base_orientation : (4,) array-like
            Base orientation as a quaternion (x, y, z, w).
        name : str, optional
            Unique robot name (default ``spec.name``).
        joint_stops : bool
            Keep pybullet's hard joint stops at the URDF limits (the physical robot). False
            widens them so that a controller can drive a joint beyond its limits (to show a
            violation); the limits reported by :class:`Robot` stay the URDF ones.
        """
        self._check_open()
        name = spec.name if name is None else str(name)
        if name in self.robots:
            raise ValidationError(f'name: expected a new robot name, got {name!r} '
                                  f'(existing: {sorted(self.robots)})')
        robot = Robot(self, spec, name, base_position, base_orientation, joint_stops)
        self.robots[name] = robot
        return robot

    def robot(self, name: str) -> Robot:
        """The robot called ``name``."""
        return lookup('name', self.robots, name, sort=True)

    # -- stepping ----------------------------------------------------------------------------
    def step(self, n_steps: int = 1) -> float:
        """Advance the simulation by ``n_steps`` fixed steps.

        Before every physics step each robot's controller computes and applies its command
        from the current state and reference. With ``config.real_time`` the call sleeps so that
        simulated time does not run ahead of wall-clock time.

        Returns
        -------
        float
            The simulated time after the steps [s].
        """
        self._check_open()
        cid = self._cid
        robots = list(self.robots.values())
        for _ in range(int(n_steps)):
            for robot in robots:
                robot.apply_control()
            pybullet.stepSimulation(physicsClientId=cid)
            self._n_steps += 1
            self.t = self._n_steps * self.config.time_step
            if self.config.real_time:
                self._pace()
        return self.t

    def run(self, duration: float, callback=None) -> float:
        """Step for ``duration`` seconds of simulated time.

        Parameters
        ----------
        duration : float
            Simulated time to run [s] (rounded to whole steps).
        callback : callable, optional
            Called as ``callback(world)`` before every step (e.g. to update references).
        """
        n = int(round(check_positive('duration', duration, allow_zero=True)
                      / self.config.time_step))
        for _ in range(n):
            if callback is not None:
                callback(self)
            self.step()
        return self.t

    def _pace(self) -> None:
        now = time.perf_counter()
        if self._pace_anchor is None:
            self._pace_anchor = (now, self.t)
            return
        wall0, sim0 = self._pace_anchor
        ahead = (self.t - sim0) - (now - wall0)
        if ahead > 0.0:
            time.sleep(ahead)
        elif ahead < -0.1:  # more than 100 ms behind: do not try to catch up in a burst
            self._pace_anchor = (now, self.t)


class WorldOwner:
    """Base of the objects that own a private :class:`World` (``self.world``): :meth:`close`
    closes it, and the object is a context manager that closes it on exit."""

    def close(self) -> None:
        self.world.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()
