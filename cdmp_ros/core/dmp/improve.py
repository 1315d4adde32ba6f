"""Improving a learned (C)DMP with PI2 (paper 000, III-C): the learner's ``~/improve``.

:class:`Improver` runs ``updates`` PI2 updates (:class:`cdmp_ros.core.dmp.pi2.Pi2`, Eq. 32-39) of
``rollouts_per_update`` exploratory rollouts each on a copy of the primitive, against a cost
function ``cost(trajectory) -> (n_steps,)`` (immediate costs, terminal cost on the last
entry). Exploration is on the internal parameters, so for a CDMP it happens in the exogenous
space and every exploratory rollout stays strictly inside the joint limits (Eq. 32-33, tested);
the improver measures it anyway (``max_limit_usage``, ``rollouts_outside_limits``).

:class:`ScriptedCost` is the pure-numpy cost (no simulator), per rollout step ``t``::

    r_t = jerk_weight * |dddy_t|^2 dt                                  (smoothness)
        + obstacle_weight * max(0, radius + clearance - d_t)^2 dt      (clearance)
    r_N += goal_weight * |y_N - goal|^2                                (reaching the goal)

with ``dddy`` the third finite difference of the joint positions [rad/s^3] and ``d_t`` the
distance between the end effector (tool centre point, core kinematics) and the centre of a
spherical obstacle. ``goal`` is the primitive's goal when the improvement starts, so the
improvement bends the path around the obstacle and keeps the goal. The same terms evaluated on
the *measured* joints of a pybullet rollout, plus a torque term, give the ``sim`` cost
(:mod:`cdmp_ros.sim.rollout_cost`).
"""
import copy
import threading
from dataclasses import dataclass, field
from typing import Callable, List, Optional

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdmp_ros.core.dmp.dmp import Trajectory, limit_usage
from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.learning import check_fields, param
from cdmp_ros.core.dmp.pi2 import Pi2, Pi2Config
from cdmp_ros.core.validation import check_limits

COSTS = ('scripted', 'sim')


@dataclass(frozen=True)
class ImproveConfig:
    """PI2 settings of ``~/improve``; mirrored by the learner's ``improve.*`` parameters."""

    updates: int = param(10, 'PI2 updates per ~/improve call.', 1, 100000)
    rollouts_per_update: int = param(5, 'Exploratory rollouts per update (K).', 2, 10000)
    shape_std: float = param(
        30.0, 'Exploration standard deviation of the shape weights (internal units, i.e. '
        'exogenous space for a CDMP).', 0.0, 1e9)
    goal_std: float = param(0.0, 'Exploration standard deviation of the goal (internal '
                            'units); 0 keeps the goal.', 0.0, 100.0)
    h: float = param(10.0, 'Sharpness of the cost-to-probability map (PI2 lambda from the '
                     'cost range).', 1e-3, 1e3)
    noise_decay: float = param(0.95, 'Factor of both exploration deviations after every '
                               'update.', 1e-6, 1.0)
    control_cost: float = param(0.0, 'R = control_cost * I of PI2 (Eq. 34).', 0.0, 1e6)
    dt: float = param(0.01, 'Rollout step [s] (also the physics step of the sim cost).',
                      1e-4, 0.1)
    cost: str = param('scripted', "Cost of a rollout: 'scripted' (pure numpy) or 'sim' "
                      '(rollouts tracked in a headless pybullet sim).', choices=COSTS)
    seed: int = param(0, 'Seed of the exploration noise (numpy default_rng).', 0, 2 ** 31 - 1)

    def __post_init__(self):
        check_fields(self)

    def pi2_config(self) -> Pi2Config:
        return Pi2Config(n_rollouts=int(self.rollouts_per_update), shape_std=self.shape_std,
                         goal_std=self.goal_std, h=self.h, control_cost=self.control_cost,
                         noise_decay=self.noise_decay)


@dataclass(frozen=True)
class CostConfig:
    """Terms of the scripted cost (and the sim cost); the learner's ``cost.*`` parameters."""

    jerk_weight: float = param(1e-4, 'Weight of the squared joint jerk [1/(rad^2 s^5)].',
                               0.0, 1e9)
    goal_weight: float = param(100.0, 'Weight of the squared final joint error [1/rad^2].',
                               0.0, 1e9)
    obstacle_weight: float = param(1e4, 'Weight of the squared clearance violation '
                                   '[1/(m^2 s)]; 0 disables the obstacle.', 0.0, 1e12)
    obstacle_x: float = param(0.45, 'Obstacle centre x in the base frame [m].', -100.0, 100.0)
    obstacle_y: float = param(0.12, 'Obstacle centre y in the base frame [m].', -100.0, 100.0)
    obstacle_z: float = param(0.40, 'Obstacle centre z in the base frame [m].', -100.0, 100.0)
    obstacle_radius: float = param(0.05, 'Obstacle (sphere) radius [m].', 0.0, 100.0)
    obstacle_clearance: float = param(0.05, 'Wanted end-effector clearance from the '
                                      'obstacle surface [m].', 0.0, 100.0)
    torque_weight: float = param(1e-5, 'sim cost: weight of the squared commanded torques '
                                 '[1/(N^2 m^2 s)].', 0.0, 1e9)

    def __post_init__(self):
        check_fields(self)

    @property
    def obstacle_center(self) -> NDArray[np.float64]:
        return np.array([self.obstacle_x, self.obstacle_y, self.obstacle_z])


class ScriptedCost:
    """The pure-numpy rollout cost of the module docstring.

    Parameters
    ----------
    chain : cdmp_ros.core.kinematics.Chain
        Kinematics of the robot (end-effector position for the clearance term).
    config : CostConfig
    goal_y : array-like, shape (n_dims,)
        Joint goal of the terminal term.
    dt : float
        Rollout step [s].
    ee : PointOfInterest, optional
        Default: the chain's end effector.
    """

    def __init__(self, chain, config: CostConfig, goal_y: ArrayLike, dt: float, ee=None):
        from cdmp_ros.core.kinematics import PointOfInterest
        self.chain = chain
        self.config = config
        self.goal_y = np.asarray(goal_y, dtype=np.float64).copy()
        self.dt = float(dt)
        self.ee = ee if ee is not None else PointOfInterest('ee')

    def terms(self, Y: ArrayLike) -> dict:
        """Per-step cost terms of joint positions ``Y`` (n_steps, n_dims) sampled at ``dt``:
        ``jerk``, ``obstacle`` (n_steps,) and the scalar ``goal``; ``min_distance`` [m]."""
        Y = np.asarray(Y, dtype=np.float64)
        cfg, dt = self.config, self.dt
        n = Y.shape[0]
        jerk = np.zeros(n)
        if n >= 4:
            J = np.diff(Y, n=3, axis=0) / dt ** 3
            jerk[3:] = cfg.jerk_weight * np.einsum('ij,ij->i', J, J) * dt
        X = self.chain.forward(Y, [self.ee])[:, 0]
        d = np.linalg.norm(X - cfg.obstacle_center, axis=1)
        viol = np.maximum(0.0, cfg.obstacle_radius + cfg.obstacle_clearance - d)
        obstacle = cfg.obstacle_weight * viol ** 2 * dt
        e = Y[-1] - self.goal_y
        return {'jerk': jerk, 'obstacle': obstacle,
                'goal': float(cfg.goal_weight * (e @ e)),
                'min_distance': float(d.min() - cfg.obstacle_radius)}

    def per_step(self, Y: ArrayLike) -> NDArray[np.float64]:
        """Immediate costs (n_steps,) with the terminal goal cost on the last step."""
        t = self.terms(Y)
        r = t['jerk'] + t['obstacle']
        r[-1] += t['goal']
        return r

    def __call__(self, traj: Trajectory) -> NDArray[np.float64]:
        return self.per_step(traj.Y)


@dataclass
class UpdateReport:
    """Progress of one PI2 update."""

    update: int                 # 1-based
    n_updates: int
    mean_cost: float            # mean total cost (of ``cost``) of the update's rollouts
    min_cost: float
    max_limit_usage: float      # over the update's rollouts (>= 1: outside a limit)
    rollouts_outside_limits: int


@dataclass
class ImproveResult:
    """Outcome of :meth:`Improver.run`."""

    primitive: object
    cost_before: float          # total cost of the noiseless rollout before
    cost_after: float
    updates: int
    rollouts: int
    rollouts_outside_limits: int
    max_limit_usage: float
    stopped: bool = False       # ended early by the stop event
    history: List[UpdateReport] = field(default_factory=list)


class Improver:
    """PI2 on a copy of ``prim`` against ``cost`` (see the module docstring).

    Parameters
    ----------
    prim : DMP or CDMP
        Fitted primitive (left untouched; the improved copy is in the result).
    config : ImproveConfig
    cost : callable
        ``cost(trajectory) -> (n_steps,)`` per-step costs.
    lower, upper : array-like, shape (n_dims,)
        Limits the rollouts are checked against.
    rng : numpy.random.Generator, optional
        Default ``default_rng(config.seed)``.
    """

    def __init__(self, prim, config: ImproveConfig,
                 cost: Callable[[Trajectory], ArrayLike], lower: ArrayLike, upper: ArrayLike,
                 rng: Optional[np.random.Generator] = None):
        if getattr(prim, 'kind', None) not in ('dmp', 'cdmp'):
            raise ValidationError(f'primitive: PI2 improves dmp and cdmp primitives, got '
                                  f'{getattr(prim, "kind", type(prim).__name__)!r}')
        self.lower, self.upper = check_limits(lower, upper, prim.n_dims)
        self.prim = copy.deepcopy(prim)
        self.config = config
        self.cost = cost
        rng = rng if rng is not None else np.random.default_rng(config.seed)
        self.pi2 = Pi2(self.prim, config.pi2_config(), rng=rng, dt=config.dt)
        self.rollouts = 0
        self.outside = 0
        self.max_usage = 0.0

    def evaluate(self) -> float:
        """Total cost of the current primitive's noiseless rollout."""
        tr = self.prim.rollout(dt=self.config.dt, duration=self.pi2.duration)
        return float(np.sum(self._costs(tr)))

    def _costs(self, tr: Trajectory) -> NDArray[np.float64]:
        c = np.asarray(self.cost(tr), dtype=np.float64)
        if c.shape != (tr.Y.shape[0],) or not np.all(np.isfinite(c)):
            raise ValidationError(f'cost: expected {tr.Y.shape[0]} finite per-step costs, got '
                                  f'shape {c.shape}')
        return c

    def step(self) -> UpdateReport:
        """One PI2 update (K rollouts, Eq. 32-39)."""
        trials = self.pi2.ask()
        costs = []
        usage = []
        for trial in trials:
            Y = trial.trajectory.Y
            usage.append(limit_usage(Y, self.lower, self.upper) if np.all(np.isfinite(Y))
                         else np.inf)
            costs.append(self._costs(trial.trajectory))
        self.pi2.tell(costs)
        totals = [float(np.sum(c)) for c in costs]
        n_out = int(sum(u >= 1.0 for u in usage))
        self.rollouts += len(trials)
        self.outside += n_out
        self.max_usage = max(self.max_usage, max(usage))
        return UpdateReport(self.pi2.n_updates, int(self.config.updates),
                            float(np.mean(totals)), float(np.min(totals)), float(max(usage)),
                            n_out)

    def run(self, progress: Optional[Callable[[UpdateReport], None]] = None,
            stop: Optional[threading.Event] = None) -> ImproveResult:
        """All ``config.updates`` updates; ``progress(report)`` after each; ``stop`` ends
        early (the result then holds the updates made so far)."""
        before = self.evaluate()
        history = []
        stopped = False
        for _ in range(int(self.config.updates)):
            if stop is not None and stop.is_set():
                stopped = True
                break
            rep = self.step()
            history.append(rep)
            if progress is not None:
                progress(rep)
        after = self.evaluate()
        meta = dict(getattr(self.prim, 'metadata', None) or {})
        meta['pi2'] = {'updates': len(history), 'rollouts': self.rollouts,
                       'cost_before': before, 'cost_after': after, 'cost': self.config.cost}
        self.prim.metadata = meta
        return ImproveResult(self.prim, before, after, len(history), self.rollouts,
                             self.outside, self.max_usage, stopped, history)
