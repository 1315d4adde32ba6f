"""Adaptation requests of the adapter node: obstacles, goals and the current state turned into
a constrained ProMP problem (paper 003), and joint goals for DMPs / CDMPs (paper 000).

Pure numpy (no ROS): the adapter node snapshots its inputs into an :class:`AdaptRequest`, and
:func:`run_request` (in a worker thread) builds and solves the problem:

- the prior ProMP is conditioned on the current joint state at phase 0 and on the joint goal
  at phase 1 (Gaussian conditioning in weight space, paper 003 Eq. 1-3);
- the points that avoid obstacles (:func:`avoided_points`): each arm's tool centre point, and
  each link of ``avoid_links`` as the balls that cover its collision geometry
  (:func:`link_balls`, ``AdaptRequest.link_balls``) or as its frame origin;
- every sphere obstacle near the prior mean path becomes a repeller (Eq. 18) on each of those
  points that comes within ``influence_distance`` of it along the prior mean, of radius
  ``radius + obstacle_margin`` plus the point's ball radius;
- every box obstacle near the path becomes a virtual wall (Eq. 16) on the same points: the
  plane of the box face, pushed out by ``obstacle_margin`` and the ball radius, that leaves
  the prior mean path the most room (a convex box is avoided by staying on the free side of
  one of its faces);
- the joint limits (the tighter of the primitive's and the robot's, ``AdaptRequest.limits``)
  become two-sided joint-limit constraints (Eq. 12);
- the user's constraint set (``msg_schemas/constraints.schema.json``) is added as is.
"""
import dataclasses
import json
from dataclasses import dataclass, field
from typing import Any, Callable, Dict, List, Mapping, Optional, Sequence, Tuple, Union

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdmp_ros.core.adaptation.guarantee import adapt
from cdmp_ros.core.adaptation.solver import AdaptationConfig, AdaptationReport
from cdmp_ros.core.adaptation.config import AdaptRequestConfig
from cdmp_ros.core.adaptation.constraints import (ChainPoint, Hyperplane, JointLimit,
                                                  MutualAvoidance, Repeller)
from cdmp_ros.core.adaptation.warm import Suspended, WarmStarts
from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.kinematics.arms import arms_of, split_by_arm
from cdmp_ros.core.kinematics.ik import IkResult, solve_position_ik
from cdmp_ros.core.kinematics import Box, OrientedBox, PointOfInterest, Sphere
from cdmp_ros.core.kinematics.closest import box_signed_distance
from cdmp_ros.core.promp.promp import ProMP
from cdmp_ros.core.validation import as_array, name_permutation

Obstacle = Union[Sphere, Box, OrientedBox]
EE = PointOfInterest('ee')
#: Per avoided link, the balls ``(centre in the link frame [m], radius [m])`` that stand for
#: its collision geometry in the obstacle constraints (:func:`link_balls`).
LinkBalls = Mapping[str, Sequence[Tuple[Tuple[float, float, float], float]]]

#: Outcomes reported by the adapter (diagnostics key ``outcome``).
OUTCOMES = ('converged', 'infeasible', 'unconverged', 'rejected', 'retargeted')


# -- joint order and goals ---------------------------------------------------------------------
def permutation(received: Sequence[str], joint_names: Sequence[str], name: str = 'primitive'
                ) -> List[int]:
    """Index into ``received`` of each of ``joint_names``; raises naming the differences."""
    return name_permutation(joint_names, received,
                            f'{name}.joint_names: expected the robot joints')


def reorder_promp(promp: ProMP, joint_names: Sequence[str]) -> ProMP:
    """``promp`` with its dimensions (weight blocks of mean and covariance) in the order of
    ``joint_names``; the same object when the order already matches."""
    perm = permutation(promp.joint_names, joint_names)
    if perm == list(range(len(perm))):
        return promp
    M = promp.n_basis
    idx = (np.asarray(perm)[:, None] * M + np.arange(M)[None, :]).ravel()
    out = ProMP(promp.n_dims, promp.basis, promp.mean_w[idx], promp.cov_w[np.ix_(idx, idx)],
                promp.sigma_y[perm], promp.duration, list(joint_names))
    out.metadata = dict(promp.metadata)
    lim = out.metadata.get('limits')
    if isinstance(lim, dict):  # per-joint lists (see promp_to_dict): reordered too
        out.metadata['limits'] = {k: [lim[k][i] for i in perm] for k in ('lower', 'upper')}
    return out


def clip_goal(goal_y: ArrayLike, lower: ArrayLike, upper: ArrayLike, margin: float
              ) -> Tuple[NDArray[np.float64], List[int]]:
    """Clip a joint goal to centre +- (1 - margin) * half range; returns (goal, clipped joints)."""
    g = np.asarray(goal_y, dtype=float)
    lo, hi = np.asarray(lower, dtype=float), np.asarray(upper, dtype=float)
    mid, half = 0.5 * (lo + hi), 0.5 * (hi - lo) * (1.0 - margin)
    out = np.clip(g, mid - half, mid + half)
    return out, [int(j) for j in np.flatnonzero(out != g)]


def solve_goal_point(chain, target: ArrayLike, seeds: Sequence[ArrayLike], tol: float = 1e-3,
                     max_iter: int = 200, margin: float = 1e-3) -> IkResult:
    """Joint goal putting the end effector at ``target`` (3,) [m] in the base frame.

    Damped least-squares IK (:func:`cdmp_ros.core.kinematics.ik.solve_position_ik`) from each
    seed in
    turn (e.g. the current joint state, the primitive's goal); the first solution within
    ``tol`` is returned.

    Raises
    ------
    ValidationError
        ``target`` is not 3 finite numbers, or no seed reaches it; the message gives the
        smallest residual [m].
    """
    if len(arms_of(chain)) > 1:
        raise ValidationError('goal_point: a robot of several arms has no one end effector to '
                              'place; give the joint goal on goal')
    target = as_array('goal_point.point', target, (3,))
    best: Optional[IkResult] = None
    for seed in seeds:
        res = solve_position_ik(chain, EE, target, seed, tol=tol, max_iter=max_iter,
                                margin=margin)
        if res.error <= tol:
            return res
        if best is None or res.error < best.error:
            best = res
    residual = best.error if best is not None else float('inf')
    raise ValidationError(f'goal_point: {np.round(target, 4).tolist()} is unreachable inside '
                          f'the joint limits (IK residual {residual:.4f} m > {tol} m)')


def retarget_primitive_dict(d: Dict[str, Any], goal_y: ArrayLike,
                            joint_names: Sequence[str], margin: Optional[float] = None
                            ) -> Dict[str, Any]:
    """A copy of a dmp/cdmp primitive dict with the goal ``goal_y`` (given in the order of
    ``joint_names``) written into ``dmp.goal`` in the primitive's own joint order; the
    weights are unchanged (paper 000: the goal is a parameter of the transformation system).

    With ``margin``, the goal is first clipped into the primitive's own ``limits`` (if any;
    a CDMP's may be tighter than the robot's): see :func:`retarget_clipped`.
    """
    return retarget_clipped(d, goal_y, joint_names, margin)[0]


def retarget_clipped(d: Dict[str, Any], goal_y: ArrayLike, joint_names: Sequence[str],
                     margin: Optional[float] = None) -> Tuple[Dict[str, Any], List[int]]:
    """:func:`retarget_primitive_dict` and the joints (robot order) clipped into the
    primitive's limits with ``margin`` (none when ``margin`` is None or there are no limits)."""
    perm = permutation(d['joint_names'], joint_names)
    g = np.asarray(goal_y, dtype=float)
    clipped: List[int] = []
    if margin is not None and 'limits' in d:
        lim = d['limits']
        g, clipped = clip_goal(g, np.asarray(lim['lower'], float)[perm],
                               np.asarray(lim['upper'], float)[perm], margin)
    goal = [0.0] * len(perm)
    for i, p in enumerate(perm):
        goal[p] = float(g[i])
    out = dict(d)
    out['dmp'] = dict(d['dmp'], goal=goal)
    return out, clipped


# -- obstacles -> constraints ------------------------------------------------------------------
def obstacle_distance(obstacle: Obstacle, X: ArrayLike) -> NDArray[np.float64]:
    """Signed distance [m] of points X (..., 3) to the obstacle surface (< 0 inside)."""
    X = np.asarray(X, dtype=float)
    if isinstance(obstacle, Sphere):
        return np.linalg.norm(X - np.asarray(obstacle.center), axis=-1) - obstacle.radius
    if isinstance(obstacle, OrientedBox):
        return obstacle.signed_distance(X)[0]
    return box_signed_distance(X, obstacle.lower, obstacle.upper)[0]


def _box_frame(box: Union[Box, OrientedBox]):
    """(R, c, lo, hi): the box is ``[lo, hi]`` in the frame ``x_b = R^T (x - c)``."""
    if isinstance(box, OrientedBox):
        half = np.asarray(box.half)
        return np.asarray(box.rotation), np.asarray(box.center), -half, half
    return np.eye(3), np.zeros(3), np.asarray(box.lower), np.asarray(box.upper)


def box_wall(box: Union[Box, OrientedBox], X: ArrayLike, margin: float = 0.0
             ) -> Tuple[NDArray[np.float64], NDArray[np.float64], float]:
    """The face plane of ``box`` that leaves the points X (n, 3) the most room (faces of an
    :class:`OrientedBox` are its rotated ones).

    Returns
    -------
    normal : (3,)
        Unit normal pointing into the forbidden side (into the box), as
        :class:`~cdmp_ros.core.adaptation.constraints.Hyperplane` expects: the wall holds when
        ``normal . (x - offset) <= 0``.
    offset : (3,)
        A point of the plane (the face centre moved out by ``margin``).
    clearance : float
        min over X of the distance to the plane on the free side (negative: some points are
        on the forbidden side).
    """
    R, c, lo, hi = _box_frame(box)
    X = (np.asarray(X, dtype=float).reshape(-1, 3) - c) @ R  # in the box frame
    centre = 0.5 * (lo + hi)
    best = None
    for axis in range(3):
        for sign, face in ((1.0, hi[axis]), (-1.0, lo[axis])):
            clearance = float(np.min(sign * (X[:, axis] - face))) - margin
            if best is None or clearance > best[2]:
                u = np.zeros(3)
                u[axis] = sign
                offset = centre.copy()
                offset[axis] = face + sign * margin
                best = (-u, offset, clearance)
    normal, offset, clearance = best
    return R @ normal, c + R @ offset, clearance


def link_balls(capsules: Sequence) -> Dict[str, List[Tuple[Tuple[float, float, float], float]]]:
    """Per capsule's link, the balls that cover it
    (:meth:`~cdmp_ros.core.kinematics.capsules.Capsule.covering_balls`): the geometry of the
    avoided links (``adaptation.link_geometry``)."""
    return {c.link: c.covering_balls() for c in capsules}


@dataclass(frozen=True)
class AvoidedPoint:
    """A point with which an arm avoids obstacles, and the ball around it that must stay clear.

    Attributes
    ----------
    arm : int
        Index into :func:`~cdmp_ros.core.kinematics.arms.arms_of` of the robot.
    name : str
        ``ee`` (one arm) or ``<tip link>_tcp`` for the tool centre point; the link's name for
        its origin or its only ball; ``<link>_<i>`` for its ball ``i`` of several.
    poi : PointOfInterest
    radius : float
        [m] added to an obstacle's radius (0: the point itself).
    """

    arm: int
    name: str
    poi: PointOfInterest
    radius: float = 0.0


def avoided_points(model, links: Sequence[str], balls: Optional[LinkBalls] = None
                   ) -> List[AvoidedPoint]:
    """The points of ``model`` (a Chain or Arms) that the obstacle constraints act on: per arm
    its tool centre point, then each of its ``links`` (``adaptation.avoid_links``) as the balls
    of ``balls[link]`` (its collision geometry), or as its frame origin when ``balls`` is None.

    Raises
    ------
    ValidationError
        A link of no arm, or a link that ``balls`` does not cover.
    """
    arms = arms_of(model)
    own = split_by_arm(model, links, 'adaptation.avoid_links')
    out: List[AvoidedPoint] = []
    for k, ((arm, _), arm_links) in enumerate(zip(arms, own)):
        out.append(AvoidedPoint(k, 'ee' if len(arms) == 1 else f'{arm.ee_link}_tcp', EE))
        for link in arm_links:
            if balls is None:
                out.append(AvoidedPoint(k, link, PointOfInterest(link)))
                continue
            if link not in balls:
                raise ValidationError(f'adaptation.avoid_links: no collision balls of {link!r} '
                                      f'(given for {sorted(balls)})')
            several = len(balls[link]) > 1
            out += [AvoidedPoint(k, f'{link}_{i}' if several else link,
                                 PointOfInterest(link, tuple(centre)), float(radius))
                    for i, (centre, radius) in enumerate(balls[link])]
    return out


@dataclass(frozen=True)
class AdaptRequest:
    """A snapshot of the adapter's inputs (everything in the robot's joint order).

    Attributes
    ----------
    prior : ProMP
        The primitive to adapt (dimensions in the chain's joint order).
    obstacles : tuple of Sphere or Box
        In the robot base frame.
    constraint_doc : dict, optional
        The user's constraint set.
    goal_y : (n_dims,), optional
        Joint goal (conditioning at phase 1).
    start_y : (n_dims,), optional
        Current joint state (conditioning at phase 0).
    continues : bool
        The request reshapes the running motion (obstacles, constraints), which the streamer
        continues at its phase: ``start_y`` is then not a phase-0 observation and the prior is
        not conditioned on it (conditioning on it would describe a motion restarted from
        there, one the streamer does not execute).
    limits : ((n_dims,), (n_dims,)), optional
        Lower and upper bounds of the joint-limit constraints: the tighter of the primitive's
        and the robot's (:func:`cdmp_ros.core.joint_limits.merge_limits`). None: the chain's.
    link_balls : mapping, optional
        The balls that stand for each link of ``avoid_links`` (:func:`link_balls`; the node's
        ``adaptation.link_geometry``). None: each link's frame origin.
    """

    prior: ProMP
    obstacles: Tuple[Obstacle, ...] = ()
    constraint_doc: Optional[dict] = None
    goal_y: Optional[NDArray[np.float64]] = None
    start_y: Optional[NDArray[np.float64]] = None
    limits: Optional[Tuple[NDArray[np.float64], NDArray[np.float64]]] = None
    continues: bool = False
    link_balls: Optional[LinkBalls] = None


@dataclass
class BuiltProblem:
    """A request turned into an optimisation problem (:func:`build_problem`)."""

    prior: ProMP
    constraints: list
    config: AdaptationConfig
    notes: List[str] = field(default_factory=list)
    obstacles_used: int = 0
    obstacles_ignored: int = 0
    infeasible: List[str] = field(default_factory=list)


def build_problem(req: AdaptRequest, chain, cfg: AdaptRequestConfig) -> BuiltProblem:
    """Condition the prior and collect the constraints of a request (see the module docstring).

    Raises
    ------
    ValidationError / ConstraintSetError
        A link of ``cfg.avoid_links`` that the chain does not have, or a user constraint set
        that does not fit the primitive.
    """
    from cdmp_ros.core.adaptation.constraints.parse import RobotContext, parse_constraint_set
    prior = req.prior
    n = prior.n_dims
    if n != chain.n_dofs:
        raise ValidationError(f'primitive.n_dims: expected {chain.n_dofs} (the robot), got {n}')
    notes = []
    s_obs, y_obs, var = [], [], []
    condition_start = req.start_y is not None and cfg.condition_start and not req.continues
    if condition_start:
        s_obs.append(0.0)
        y_obs.append(np.asarray(req.start_y, float))
        var.append(cfg.start_var)
    if req.goal_y is not None:
        s_obs.append(1.0)
        y_obs.append(np.asarray(req.goal_y, float))
        var.append(cfg.goal_var)
    if s_obs:  # Gaussian conditioning on via-points (paper 003, Section II-A)
        prior = prior.condition(np.array(s_obs), np.array(y_obs),
                                np.repeat(np.array(var)[:, None], n, axis=1))
        notes.append('conditioned on ' + ' and '.join(
            name for name, on in (('the current state', condition_start),
                                  ('the goal', req.goal_y is not None)) if on))
    avoided = avoided_points(chain, cfg.avoid_links, req.link_balls)
    arms = arms_of(chain)
    # each point shared by its constraints: one FK / UT per time step
    points = [ChainPoint(arms[p.arm][0], p.poi, arms[p.arm][1]) for p in avoided]
    grid = np.linspace(0.0, 1.0, int(cfg.n_steps))
    mean = prior.mean(grid)
    # one forward pass per arm over its points (avoided_points lists them arm by arm)
    X = np.concatenate([arm.forward(mean[:, idx], [p.poi for p in avoided if p.arm == k])
                        for k, (arm, idx) in enumerate(arms)], axis=1)  # (n_steps, points, 3)
    radii = [p.radius for p in avoided]
    constraints: list = []
    if cfg.joint_limits:  # Eq. (12), paper 003
        lower, upper = req.limits if req.limits is not None else (chain.lower, chain.upper)
        constraints += [JointLimit(j, float(lower[j]), float(upper[j]),
                                   alpha=cfg.alpha, name=f'limit_{chain.joint_names[j]}')
                        for j in range(n)]
    if cfg.arm_clearance > 0.0:  # Eq. 22 between every two points (balls) of different arms
        constraints += [MutualAvoidance(points[i], points[j],
                                        float(cfg.arm_clearance + radii[i] + radii[j]),
                                        alpha=cfg.alpha,
                                        name=f'arms_{avoided[i].name}_{avoided[j].name}')
                        for i in range(len(points)) for j in range(i + 1, len(points))
                        if avoided[i].arm != avoided[j].arm]
    # phases pinned by the conditioning: an obstacle there makes the problem infeasible
    pinned = [(i, label) for i, label, on in ((0, 'start', 0.0 in s_obs),
                                              (-1, 'goal', 1.0 in s_obs)) if on]
    used = ignored = 0
    infeasible = []
    for k, ob in enumerate(req.obstacles):
        d = obstacle_distance(ob, X) - np.asarray(radii)  # (n_steps, n_points), to the balls
        if float(d.min()) > cfg.influence_distance:
            ignored += 1
            continue
        used += 1
        for i, (pt, av) in enumerate(zip(points, avoided)):
            if float(d[:, i].min()) > cfg.influence_distance:
                continue  # this point stays far from it: no constraint (as for an obstacle)
            margin = cfg.obstacle_margin + av.radius
            if isinstance(ob, Sphere):
                constraints.append(Repeller(pt, ob.center, ob.radius + margin,
                                            alpha=cfg.alpha, name=f'obstacle_{k}_{av.name}'))
                clear = d[:, i] - cfg.obstacle_margin
            else:
                normal, offset, _ = box_wall(ob, X[:, i], margin)
                constraints.append(Hyperplane(pt, normal, offset, alpha=cfg.alpha,
                                              name=f'obstacle_{k}_{av.name}'))
                clear = (X[:, i] - offset) @ -normal
            infeasible += [f'obstacle {k} (with its margin) contains the {av.name} at the '
                           f'conditioned {label}' for j, label in pinned if clear[j] <= 0.0]
    overrides: Dict[str, Any] = {}
    if req.constraint_doc is not None:
        ctx = RobotContext.of_robot(chain)
        user, overrides = parse_constraint_set(req.constraint_doc, prior, ctx)
        constraints += user
    opt = dict(n_steps=int(cfg.n_steps), max_outer=int(cfg.max_outer),
               max_inner=int(cfg.max_inner), lambda0=float(cfg.lambda0),
               guarantee=cfg.guarantee,
               verification_samples=int(cfg.verification_samples) or None)
    opt.update(overrides)
    return BuiltProblem(prior, constraints, AdaptationConfig(**opt), notes, used, ignored,
                        infeasible)


def classify(report: AdaptationReport, infeasible: Sequence[str] = ()) -> str:
    """``converged``; ``infeasible`` (the optimiser stalled with violated constraints, or
    ``infeasible`` names a known reason, e.g. an obstacle at the conditioned start);
    otherwise ``unconverged`` (the iteration budget ran out)."""
    if report.converged:
        return 'converged'
    if report.status == 'stalled_infeasible' or infeasible:
        return 'infeasible'
    return 'unconverged'


@dataclass
class AdaptResult:
    """Outcome of :func:`run_request`: the adapted ProMP (also when not converged), the
    optimiser report and the built problem."""

    adapted: ProMP
    report: AdaptationReport
    outcome: str
    problem: BuiltProblem


def run_request(req: AdaptRequest, chain, cfg: AdaptRequestConfig,
                should_stop: Optional[Callable[[], bool]] = None,
                warm: Optional[WarmStarts] = None) -> AdaptResult:
    """Build and solve one request (paper 003, Algorithm 1).

    A request known to be infeasible (:attr:`BuiltProblem.infeasible`) gets a short solve
    only (one outer iteration, at most 50 L-BFGS iterations), enough to report the
    satisfaction probabilities without keeping the solver thread from newer requests.
    ``should_stop`` is passed to :func:`cdmp_ros.core.adaptation.guarantee.adapt` (raises
    :class:`~cdmp_ros.core.errors.Cancelled` when it returns True). ``warm``: the warm
    starts of the caller's stream of requests (:mod:`cdmp_ros.core.adaptation.warm`; with
    ``cfg.warm_start``).
    """
    prob = build_problem(req, chain, cfg)
    config = prob.config
    if prob.infeasible:
        config = dataclasses.replace(config, max_outer=1, max_inner=min(config.max_inner, 50))
    if warm is not None and not prob.infeasible:
        adapted, report = warm.solve(req, prob, cfg, should_stop)
    else:
        if warm is not None:
            warm.forget()
        adapted, report = adapt(prob.prior, prob.constraints, config, should_stop=should_stop)
    return AdaptResult(adapted, report, classify(report, prob.infeasible), prob)


def refine_request(req: AdaptRequest, chain, cfg: AdaptRequestConfig, warm: WarmStarts,
                   kl: float, should_stop: Optional[Callable[[], bool]] = None,
                   resume: Optional[Suspended] = None) -> Optional[AdaptResult]:
    """Solve ``req`` again, cold (or continuing the suspended refinement ``resume``), after a
    warm solve of KL ``kl`` (:meth:`cdmp_ros.core.adaptation.warm.WarmStarts.refine`, within
    ``cfg.warm_start_check_max_evaluations`` over its resumptions): the result if its KL is
    lower by REFINE_GAIN at least, else None. ``should_stop`` cancels it
    (:class:`~cdmp_ros.core.errors.Cancelled`; :func:`~cdmp_ros.core.adaptation.warm.suspend`
    gives where it was)."""
    prob = build_problem(req, chain, cfg)
    out = warm.refine(req, prob, kl, should_stop, resume,
                      int(cfg.warm_start_check_max_evaluations))
    if out is None:
        return None
    return AdaptResult(out[0], out[1], classify(out[1], prob.infeasible), prob)


def promp_message(promp: ProMP) -> str:
    """JSON text of a ProMP primitive, as :func:`cdmp_ros.core.primitive_io.dumps_primitive`
    writes it but with the covariance in compact form (``cov_w_base64``: 0.3 ms for a 7-DoF
    ProMP's 70 x 70 matrix, against 2.9 ms as rows of numbers, and as much again to parse) and
    without validating it against the schema again (the object is valid by construction). A
    test checks both give the same primitive."""
    from cdmp_ros.core.primitive_io import FORMAT_VERSION
    from cdmp_ros.core.promp.primitive_file import promp_to_dict
    d: Dict[str, Any] = {'format_version': FORMAT_VERSION, 'kind': 'promp',
                         'joint_names': list(promp.joint_names), 'n_dims': promp.n_dims}
    d.update(promp_to_dict(promp, compact=True))
    return json.dumps(d)


# -- visualisation -----------------------------------------------------------------------------
def ee_path(chain, Y: ArrayLike) -> NDArray[np.float64]:
    """End-effector positions (n, 3) of joint positions Y (n, n_dofs); of several arms
    (:class:`~cdmp_ros.core.kinematics.arms.Arms`), the first arm's."""
    arm, idx = arms_of(chain)[0]
    return arm.forward(np.asarray(Y, dtype=float)[:, idx], [EE])[:, 0]


def ee_band(promp: ProMP, chain, s: ArrayLike, n_sigma: float = 2.0, arm: int = 0
            ) -> Tuple[NDArray[np.float64], NDArray[np.float64]]:
    """End-effector mean and an uncertainty radius at phases ``s`` (n,); of several arms
    (:class:`~cdmp_ros.core.kinematics.arms.Arms`), arm ``arm``'s (default the first).

    Linearised: Cov[x_t] ~ J(E[z_t]) Cov[z_t] J(E[z_t])^T (paper 003 Eq. 2 through the
    kinematics Jacobian); radius = ``n_sigma`` * sqrt(largest eigenvalue).

    Returns
    -------
    centres : (n, 3); radii : (n,)
    """
    s = np.atleast_1d(np.asarray(s, dtype=float))
    arm_chain, idx = arms_of(chain)[arm]
    m = promp.mean(s)[:, idx]
    X, J = arm_chain.forward_and_jacobian(m, [EE])
    J = J[:, 0]                                            # (n, 3, d)
    S = promp.cov(s)[:, idx[:, None], idx[None, :]]        # the arm's joints
    C = J @ S @ np.swapaxes(J, 1, 2)                       # (n, 3, 3)
    lam = np.linalg.eigvalsh(0.5 * (C + np.swapaxes(C, 1, 2)))[:, -1]
    return X[:, 0], n_sigma * np.sqrt(np.maximum(lam, 0.0))


def rollout_path(prim, perm: Sequence[int], chain, start_y: Optional[ArrayLike] = None,
                 n_points: int = 50, dt: float = 0.01) -> NDArray[np.float64]:
    """End-effector path (n_points, 3) of a DMP / CDMP rollout over 1.2 durations.

    Parameters
    ----------
    prim : DMP or CDMP
        In its own joint order.
    perm : sequence of int
        ``perm[i]``: index in ``prim`` of the chain's joint i.
    start_y : (n_dims,), optional
        Start in the chain's joint order (default: the primitive's start).
    """
    perm = np.asarray(perm)
    start = None
    if start_y is not None:
        start = np.empty(perm.size)
        start[perm] = np.asarray(start_y, dtype=float)
    tr = prim.rollout(dt=dt, start_y=start, duration=1.2 * prim.tau_)
    Y = tr.Y[:, perm]
    idx = np.linspace(0, len(Y) - 1, int(n_points)).round().astype(int)
    return ee_path(chain, Y[idx])
