"""Sampled verification of an adapted ProMP against its constraints.

The optimiser (paper 003) enforces every constraint through an approximation of its
satisfaction probability (Gaussian CDFs, a tail approximation of |x_t - c|^2, the unscented
transform of the kinematics). :func:`verify` checks the result without any approximation:
it samples weight vectors w ~ N(mu, Sigma) of the adapted ProMP, maps them to trajectories on
the constraint time grid (one matrix product per time grid; link points through one batched
forward-kinematics call per chain), evaluates every constraint on every sample and time step,
and reports per constraint

- ``per_step_max``: the largest sampled violation frequency over the time steps of its support
  (what the paper's per-step confidence alpha bounds);
- ``trajectory``: the fraction of sampled trajectories that violate it at any step of its
  support, with ``upper95``, its one-sided 95 % Clopper-Pearson upper confidence bound;

and overall the fraction of trajectories violating any constraint (and its upper bound), in a
:class:`~cdmp_ros.core.adaptation.verification_report.Verification`.

Each report also says what its test can detect (:func:`detectable_violation`): the smallest
true violation probability at which the constraint's rule fails with 95 % power, in absolute
terms (``detectable``) and as a multiple of the asked level 1 - alpha
(``detectable_excess``). For the per-step rule that is the per-step probability of one step
at which its count exceeds the Bonferroni-corrected critical count 95 % of the time (more
samples or fewer tested steps make it smaller); ``holds`` with ``detectable_excess`` 2.5 says
that a step violated 2.5 times as often as asked would have been caught, not one violated
twice as often.

Decision rules (``Verification.holds``), chosen so that a calibrated solution does not fail by
Monte Carlo noise:

- ``per_step`` (the paper's semantics, P(step t holds) >= alpha at every t): each time step's
  violation count is tested against Binomial(n_samples, 1 - alpha) with a one-sided exact test;
  the test is Bonferroni-corrected over all tested steps of all constraints at the family-wise
  level ``significance`` (default 1 %). A constraint fails when its worst step's count exceeds
  the critical count, i.e. when the sample shows the per-step level is exceeded beyond
  Monte Carlo noise. A solution whose every step is exactly at its level fails at most
  ``significance`` of the time (less in practice: most steps are far below their level and
  steps are positively correlated).
- ``trajectory`` (P(whole trajectory satisfies every constraint) >= alpha): the overall
  trajectory-level violation's 95 % upper bound must be <= 1 - min(alpha); this is the
  conservative direction (a solution exactly at the level fails), which is what a guarantee
  needs.
"""
import functools
import os
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np
from numpy.typing import NDArray
from scipy import special  # not scipy.stats: its import costs the adapter's start 0.4 s

from cdmp_ros.core.adaptation.constraints.base import Constraint, WeightConstraint
from cdmp_ros.core.adaptation.constraints.points import ChainPoint, DifferencePoint, DofPoint
from cdmp_ros.core.adaptation.verification_report import (DETECTION_POWER, GUARANTEES,
                                                          ConstraintVerification, Verification)
from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.promp.promp import ProMP

__all__ = ['clopper_pearson_upper', 'critical_count', 'detectable_violation',
           'trajectory_accepted', 'sample_points', 'verify', 'worker_cpu_seconds']

# (sample, step) pairs evaluated per chunk: bounds the memory of the batched evaluation
_CHUNK_POINTS = 50_000

#: Threads that evaluate the chunks of samples (:func:`verify`'s ``threads``). numpy releases
#: the GIL in the batched kinematics and constraint checks, so a second core that is free
#: shortens the verification; results do not depend on it (counts are summed).
THREADS = min(2, os.cpu_count() or 1)
_pool: Optional[ThreadPoolExecutor] = None
_pool_lock = threading.Lock()
_pool_cpu = [0.0]   # CPU seconds spent in the worker threads (worker_cpu_seconds)


def worker_cpu_seconds() -> float:
    """CPU time [s] the verification's worker threads have used since the process started
    (a caller adds the difference across a solve to its own thread's CPU time)."""
    with _pool_lock:
        return _pool_cpu[0]


def _executor() -> ThreadPoolExecutor:
    """The verification's worker threads (created at the first threaded verification)."""
    global _pool
    with _pool_lock:
        if _pool is None:
            _pool = ThreadPoolExecutor(max_workers=THREADS, thread_name_prefix='cdmp-verify')
        return _pool


def clopper_pearson_upper(k: NDArray, n: int, confidence: float = 0.95) -> NDArray:
    """One-sided Clopper-Pearson upper confidence bound of a binomial proportion.

    Parameters
    ----------
    k : array-like of int
        Observed counts, each in [0, n].
    n : int
        Number of trials.
    confidence : float
        One-sided confidence level.

    Returns
    -------
    ndarray
        p_u with P(Bin(n, p_u) <= k) = 1 - confidence (1 where k == n).
    """
    k = np.asarray(k, dtype=float)
    out = np.ones_like(k)
    m = k < n
    out[m] = special.betaincinv(k[m] + 1.0, n - k[m], confidence)  # Beta(k+1, n-k).ppf
    return out


@functools.lru_cache(maxsize=256)
def critical_count(n: int, p: float, level: float) -> int:
    """Smallest count c with P(Bin(n, p) > c) <= ``level`` (counts above c reject p); cached
    (a stream of adaptations asks for the same few). ``level`` in (0, 1), ``p`` in [0, 1].

    ``special.bdtrc(c, n, p)`` is P(Bin(n, p) > c), decreasing in c: a bisection over
    ``[0, n]`` (what ``scipy.stats.binom.isf(level, n, p)`` returns, tested)."""
    if not (0.0 < level < 1.0 and 0.0 <= p <= 1.0 and n >= 1):
        raise ValidationError(f'critical_count: expected n >= 1, p in [0, 1] and level in '
                              f'(0, 1), got n={n}, p={p}, level={level}')
    lo, hi = -1, int(n)  # P(Bin > n) = 0 <= level: hi satisfies, lo does not
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if special.bdtrc(mid, n, p) <= level:
            hi = mid
        else:
            lo = mid
    return hi


@functools.lru_cache(maxsize=256)
def detectable_violation(n: int, accepted: int, power: float = DETECTION_POWER) -> float:
    """The smallest violation probability p at which a rule that accepts at most ``accepted``
    violations in ``n`` Bernoulli trials rejects with probability ``power``.

    The rule rejects when the count X > ``accepted``; P(X >= k | p) with k = accepted + 1 is
    the regularised incomplete beta function I_p(k, n - k + 1), increasing in p, so
    p = Beta(k, n - k + 1).ppf(power) (1 when no count rejects).
    """
    k = int(accepted) + 1
    if k > n:
        return 1.0
    return float(special.betaincinv(k, n - k + 1, power))  # Beta(k, n-k+1).ppf(power)


@functools.lru_cache(maxsize=256)
def trajectory_accepted(n: int, level: float, confidence: float = 0.95) -> int:
    """The largest count k of violating trajectories (of ``n``) whose one-sided
    Clopper-Pearson upper bound is <= ``level`` (the trajectory rule accepts at most k; -1
    when even 0 does not pass)."""
    if clopper_pearson_upper([0], n, confidence)[0] > level:
        return -1
    lo, hi = 0, n   # bisection on the monotone upper bound
    while lo < hi:
        mid = (lo + hi + 1) // 2
        if clopper_pearson_upper([mid], n, confidence)[0] <= level:
            lo = mid
        else:
            hi = mid - 1
    return lo


def sample_points(promp: ProMP, c, n_samples: int, rng: np.random.Generator,
                  grid: NDArray, W: Optional[NDArray] = None) -> NDArray:
    """Sampled x_t of constraint ``c`` at its times: (n_samples, n, k)."""
    times = c.times(grid)
    if W is None:
        W = promp.sample_weights(n_samples, rng)
    phi = promp.basis.features(times)
    dofs = list(c.point.dofs)
    W3 = W.reshape(-1, promp.n_dims, promp.n_basis)[:, dofs, :]
    Z = (W3.reshape(-1, promp.n_basis) @ phi.T).reshape(W.shape[0], len(dofs), -1)
    return c.point.forward(np.ascontiguousarray(Z.transpose(0, 2, 1)))


def _grid_times(constraints, grid) -> Dict[bytes, NDArray]:
    out = {}
    for c in constraints:
        if isinstance(c, Constraint):
            t = c.times(grid)
            out.setdefault(t.tobytes(), t)
    return out


def _trajectory_map(promp: ProMP, times: NDArray) -> NDArray:
    """Phi^T (M, n) at ``times``: ``_trajectories`` maps a batch of weight vectors with it."""
    return np.ascontiguousarray(promp.basis.features(times).T)


def _trajectories(promp: ProMP, W: NDArray, phi_t: NDArray) -> NDArray:
    """y_t = Phi_t w of every sample: (c, n, D), a view of joint-major memory (D, n, c).

    One product of Phi (n, M) with each joint's weights (M, c): the first-order screen
    (:class:`_KinematicGroup`) works on this layout, where the samples of a joint and step
    are contiguous; arranging the (c, D M) weights costs far less than rearranging the
    (c, n, D) trajectories (the block-diagonal (D M, n D) map this replaced did D times the
    flops on zeros)."""
    c = W.shape[0]
    Wt = np.ascontiguousarray(W.reshape(c, promp.n_dims, promp.n_basis).transpose(1, 2, 0))
    return np.matmul(phi_t.T, Wt).transpose(2, 1, 0)


class _KinematicGroup:
    """The chain points of one chain, ``dofs`` and time grid: one batched forward-kinematics
    call per chunk of samples.

    The screen: the points of the mean trajectory, ``Xbar``, and their Jacobians ``J`` are
    computed once. For a sample's joints z (deviation dz = z - zbar from the mean's) a ball
    that contains the sample's point is known without its kinematics:

    - first order (chains of revolute joints): centre ``Xbar + J dz``, radius
      ``1/2 sum_jk M_jk |dz_j| |dz_k|`` (:meth:`~cdmp_ros.core.kinematics.chain.Chain.
      curvature_bound`: Taylor's theorem with a bound of the second derivatives);
    - zeroth order (a chain with a prismatic joint): centre ``Xbar``, radius
      ``sum_j rho_j |dz_j|``, with ``rho_j`` the norm of Jacobian column j at the mean (the
      point's distance from joint j's axis; 1 for a prismatic joint). Why: move the joints
      from the mean to the sample one at a time, base first. When joint j moves, the joints
      after it are still at the mean, so the point is at distance ``rho_j`` from joint j's
      axis (the joints before j move that axis and the point rigidly together), and a
      rotation by dz moves it along a chord ``2 rho_j sin(|dz| / 2) <= rho_j |dz|``; the
      triangle inequality sums the steps.

    Where every constraint on the group's points gives that whole ball the outcome of its
    centre (:meth:`~cdmp_ros.core.adaptation.constraints.base.Constraint.decided_near`), the
    centre stands in for the sample's point: the verdicts are exactly those of the full
    kinematics, which runs only on the undecided (sample, step) pairs. A group with a
    constraint that cannot tell is evaluated in full. On the Panda problem of the adapter
    (2,000 samples, three spheres) the first-order screen leaves 2-7 % of the pairs open,
    the zeroth-order one 33-57 %.

    When every constraint of a screened group holds per step (``reduce == 'each'``),
    :meth:`violations` evaluates the constraints at the centres and, on the undecided pairs
    only, at the points of the full kinematics (each pair as one point at its own time)."""

    def __init__(self, promp: ProMP, members: List[ChainPoint], users: List[List[Constraint]],
                 times: NDArray, screen: bool = True):
        p = members[0]
        self.chain, self.dofs, self.times = p.chain, list(p.dofs), times
        self.members, self.users = members, users
        self.pois = [m.point for m in members]
        self.screen = screen and all(type(c).decided_near is not Constraint.decided_near
                                     for cs in users for c in cs)
        self.pairs = self.screen and all(c.reduce == 'each' for cs in users for c in cs)
        if self.screen:
            self.zbar = promp.mean(times)[:, self.dofs]                    # (n, nd)
            self.Xbar, J = self.chain.forward_and_jacobian(self.zbar, self.pois)
            self.M = self.chain.curvature_bound(self.pois)                 # (P, nd, nd)
            if self.M is None:   # zeroth order: the verdict at Xbar, once per step
                self.rho_t = np.linalg.norm(J, axis=2).transpose(0, 2, 1).copy()  # (n, nd, P)
                self.bar_violated = {}
                for i, cs in enumerate(users):
                    Xi = self._axes(self.Xbar, i)[None]                     # (1, n, k)
                    for c in cs:
                        self.bar_violated[id(c)] = ~np.asarray(c.satisfied(Xi, times),
                                                               bool)[0]
            else:   # first order: per step the map (nd, 3 P) of dz to the points' moves
                n, P, _, nd = J.shape
                self.JT = np.ascontiguousarray(J).reshape(n, 3 * P, nd)
                # Dt[i, k]: member i's reach from joint k (M[i, j, k] = Dt[i, max(j, k)])
                self.Dt = np.ascontiguousarray(self.M.diagonal(axis1=1, axis2=2))

    def _axes(self, X: NDArray, i: int) -> NDArray:
        """Member i's coordinates of the points X (..., P, 3)."""
        axes = self.members[i].axes
        return X[..., i, :] if tuple(axes) == (0, 1, 2) else X[..., i, list(axes)]

    def _balls(self, Zg: NDArray) -> Tuple[Optional[NDArray], NDArray]:
        """The screen's balls of the pairs of Zg (c, n, nd): centres (c, n, P, 3) (None: the
        zeroth order's ``Xbar``) and radii (c, n, P)."""
        if self.M is None:
            dev = Zg - self.zbar                                         # (c, n, nd)
            np.abs(dev, out=dev)
            # R[c, t, i] = sum_j dev[c, t, j] rho[t, i, j], one matrix product per time step
            return None, np.matmul(dev.transpose(1, 0, 2), self.rho_t).transpose(1, 0, 2)
        # first order, joint-major with the samples innermost (the layout of
        # _trajectories): per step one BLAS product (3 P, nd) @ (nd, c) for the centres, and
        # one product (P, nd) @ (nd, n c) for the radii,
        # 1/2 sum_jk D[max(j, k)] a_j a_k = sum_k D_k a_k (a_k / 2 + sum_{j<k} a_j)
        c, n, nd = Zg.shape
        P = self.Dt.shape[0]
        dz = Zg.transpose(2, 1, 0) - self.zbar.T[:, :, None]            # (nd, n, c)
        moved = np.matmul(self.JT, dz.transpose(1, 0, 2))               # (n, 3 P, c)
        moved += self.Xbar.reshape(n, -1, 1)
        np.abs(dz, out=dz)
        q = np.empty_like(dz)
        run = np.zeros((n, c))
        for j in range(nd):
            a, qj = dz[j], q[j]
            np.multiply(a, 0.5, out=qj)
            qj += run
            qj *= a
            run += a
        radii = self.Dt @ q.reshape(nd, -1)                              # (P, n c)
        # views in (sample, step, ...) order
        return (moved.reshape(n, P, 3, c).transpose(3, 0, 1, 2),
                radii.reshape(P, n, c).transpose(2, 1, 0))

    def _undecided(self, Zg: NDArray) -> Tuple[NDArray, Optional[NDArray]]:
        """(c, n) bool: the (sample, step) pairs of Zg (c, n, nd) whose verdict the screen
        leaves open for some constraint of the group; and the balls' centres (c, n, P, 3) of
        the first-order screen (None: zeroth order, the centres are ``Xbar``)."""
        centres, R = self._balls(Zg)
        todo = np.zeros(R.shape[:2], bool)
        for i, cs in enumerate(self.users):
            Xi = self._axes(self.Xbar if centres is None else centres, i)
            for c in cs:
                todo |= ~c.decided_near(Xi, R[..., i], self.times)
        return todo, centres

    def violations(self, Zg: NDArray) -> Tuple[Dict[int, NDArray], int]:
        """Group with :attr:`pairs`: the violation indicators (c, n) of every constraint of
        the group (by ``id``) on the samples' joint positions Zg (c, n, nd), and the number of
        (sample, step) pairs whose kinematics ran."""
        out = {}
        if self.M is None:
            todo, _ = self._undecided(Zg)
            for cs in self.users:
                for c in cs:
                    out[id(c)] = np.broadcast_to(self.bar_violated[id(c)], todo.shape).copy()
        else:    # the verdicts at the centres, from the distances that decide the pairs
            centres, R = self._balls(Zg)
            todo = np.zeros(R.shape[:2], bool)
            for i, cs in enumerate(self.users):
                Ci = self._axes(centres, i)
                for c in cs:
                    decided, out[id(c)] = c.screened(Ci, R[..., i], self.times)
                    todo |= ~decided
        steps = np.nonzero(todo)[1]
        if steps.size:
            X = self.chain.forward(Zg[todo], self.pois)                      # (m, P, 3)
            tp = self.times[steps]
            for i, cs in enumerate(self.users):
                Xi = self._axes(X, i)[None]                                   # (1, m, k)
                for c in cs:
                    out[id(c)][todo] = ~np.asarray(c.satisfied(Xi, tp), bool)[0]
        return out, int(steps.size)

    def positions(self, Zg: NDArray) -> Tuple[NDArray, int]:
        """World points (c, n, P, 3) of the samples' joint positions Zg (c, n, nd) (the
        screen's centre where it decides the pair), and the number of (sample, step) pairs
        whose kinematics ran."""
        full = Zg.shape[0] * Zg.shape[1]
        if not self.screen:
            return self.chain.forward(Zg, self.pois), full
        todo, centres = self._undecided(Zg)
        if todo.all():
            return self.chain.forward(Zg, self.pois), full
        if centres is None:
            X = np.empty(todo.shape + self.Xbar.shape[1:])
            X[...] = self.Xbar
        else:
            X = centres
        if todo.any():
            X[todo] = self.chain.forward(Zg[todo], self.pois)
        return X, int(np.count_nonzero(todo))


def _columns(Z: NDArray, dofs: Sequence[int]) -> NDArray:
    """Z[..., dofs]: a view when ``dofs`` are consecutive (no copy of the samples)."""
    dofs = list(dofs)
    if dofs and dofs == list(range(dofs[0], dofs[0] + len(dofs))):
        return Z[..., dofs[0]:dofs[0] + len(dofs)]
    return Z[..., dofs]


def _kinematic_groups(promp: ProMP, constraints: Sequence, grid: NDArray, screen: bool
                      ) -> List[_KinematicGroup]:
    """The :class:`_KinematicGroup` of every (chain, dofs, time grid) the constraints use
    (``screen``: with the screen where the constraints allow it)."""
    found: Dict[tuple, Tuple[list, list, NDArray]] = {}
    for c in constraints:
        if isinstance(c, Constraint) and type(c.point) is ChainPoint:
            p = c.point
            times = c.times(grid)
            members, users, _ = found.setdefault((id(p.chain), p.dofs, times.tobytes()),
                                                 ([], [], times))
            i = next((k for k, m in enumerate(members) if m is p), None)
            if i is None:
                members.append(p)
                users.append([])
                i = len(members) - 1
            users[i].append(c)
    return [_KinematicGroup(promp, m, u, t, screen) for m, u, t in found.values()]


def _evaluate_chunk(promp: ProMP, constraints: Sequence, W: NDArray, grid: NDArray,
                    features: Dict[bytes, NDArray], groups: Sequence[_KinematicGroup]
                    ) -> Tuple[List[NDArray], int]:
    """Violation indicators of every constraint on the samples W: (c, n) or (c,) bool; and
    the number of (sample, step) pairs of the kinematic groups whose kinematics ran."""
    Z = {key: _trajectories(promp, W, phi_t)
         for key, phi_t in features.items()}                    # (c, n, D) per time grid
    X_of: Dict[Tuple[int, bytes], NDArray] = {}
    violated: Dict[int, NDArray] = {}     # of the constraints of groups with ``pairs``
    ran = 0
    for g in groups:
        tkey = g.times.tobytes()
        Zg = _columns(Z[tkey], g.dofs)
        if g.pairs:
            v, n_run = g.violations(Zg)
            violated.update(v)
        else:
            X, n_run = g.positions(Zg)
            for i, m in enumerate(g.members):
                X_of[(id(m), tkey)] = g._axes(X, i)
        ran += n_run
    ends = _difference_ends(constraints, grid, Z, violated)
    out = []
    for c in constraints:
        if isinstance(c, WeightConstraint):
            out.append(~np.asarray(c.satisfied_w(W), bool))
            continue
        if id(c) in violated:
            out.append(violated[id(c)])
            continue
        times = c.times(grid)
        tkey = times.tobytes()
        p = c.point
        X = X_of.get((id(p), tkey))
        if X is None and type(p) is DifferencePoint:
            Xa, Xb = ends.get((id(p.a), tkey)), ends.get((id(p.b), tkey))
            if Xa is not None and Xb is not None:
                X = Xa - Xb
        if X is None:
            Zc = _columns(Z[tkey], p.dofs)
            X = Zc if type(p) is DofPoint else p.forward(Zc)
        out.append(~np.asarray(c.satisfied(X, times), bool))
    return out, ran


def _difference_ends(constraints: Sequence, grid: NDArray, Z: Dict[bytes, NDArray],
                     violated: Dict[int, NDArray]) -> Dict[Tuple[int, bytes], NDArray]:
    """The exact positions of the chain points of differences (mutual avoidance), keyed
    ``(id(point), time key)``: one forward-kinematics call per chain, dofs and time grid for
    all of them (the pairs share them: two arms, a few points each). Exact, never a screened
    group's centres: a group's screen decides only its own constraints."""
    pending: Dict[tuple, list] = {}
    for c in constraints:
        if (not isinstance(c, Constraint) or id(c) in violated
                or type(c.point) is not DifferencePoint):
            continue
        tkey = c.times(grid).tobytes()
        for cp in (c.point.a, c.point.b):
            if type(cp) is ChainPoint:
                members = pending.setdefault((id(cp.chain), cp.dofs, cp.axes, tkey), [])
                if all(m is not cp for m in members):
                    members.append(cp)
    ends: Dict[Tuple[int, bytes], NDArray] = {}
    for (_, dofs, axes, tkey), members in pending.items():
        X = members[0].chain.forward(_columns(Z[tkey], dofs), [m.point for m in members])
        for i, m in enumerate(members):
            ends[(id(m), tkey)] = X[..., i, list(axes)] if axes != (0, 1, 2) else X[..., i, :]
    return ends


def verify(promp: ProMP, constraints: Sequence, n_samples: int, rng: np.random.Generator,
           n_steps: int = 101, guarantee: str = 'per_step', significance: float = 0.01,
           screen: bool = True, threads: Optional[int] = None) -> Verification:
    """Monte Carlo check of the constraints on trajectories sampled from ``promp``.

    Parameters
    ----------
    promp : ProMP
        The (adapted) distribution to check.
    constraints : sequence of Constraint / WeightConstraint
        With their own confidences alpha.
    n_samples : int
        Sampled trajectories (>= 1).
    rng : numpy.random.Generator
    n_steps : int
        Time grid s = linspace(0, 1, n_steps), the optimiser's (``AdaptationConfig.n_steps``).
    guarantee : {'per_step', 'trajectory'}
        What alpha claims; selects the decision rule (module docstring).
    significance : float
        Family-wise level of the per-step rule, in (0, 1).
    screen : bool
        Skip the forward kinematics of (sample, step) pairs whose verdicts the mean
        trajectory's points already decide (exact; :class:`_KinematicGroup`). False: run it
        on every pair (the reference the tests compare with).
    threads : int, optional
        Chunks of samples evaluated at once (default :data:`THREADS`, at most 2; 1: in the
        calling thread). The samples are split into at least this many chunks.

    Returns
    -------
    Verification
    """
    t0 = time.perf_counter()
    if guarantee not in GUARANTEES:
        raise ValidationError(f'guarantee: expected one of {list(GUARANTEES)}, got '
                              f'{guarantee!r}')
    n_samples = int(n_samples)
    if n_samples < 1:
        raise ValidationError(f'n_samples: expected an integer >= 1, got {n_samples}')
    if not 0.0 < significance < 1.0:
        raise ValidationError(f'significance: expected a value in (0, 1), got {significance!r}')
    constraints = list(constraints)
    grid = np.linspace(0.0, 1.0, int(n_steps))
    times = _grid_times(constraints, grid)
    features = {key: _trajectory_map(promp, t) for key, t in times.items()}
    n_per = max((t.size for t in times.values()), default=1)
    W = promp.sample_weights(n_samples, rng)
    threads = max(1, min(int(THREADS if threads is None else threads), THREADS))
    chunk = max(1, min(_CHUNK_POINTS // n_per, -(-n_samples // threads)))
    groups = _kinematic_groups(promp, constraints, grid, screen)
    ran = 0
    step_counts: List[Optional[NDArray]] = [None] * len(constraints)
    traj_counts = np.zeros(len(constraints), dtype=np.int64)
    any_count = 0
    starts = range(0, n_samples, chunk)

    def evaluate(a):
        return _evaluate_chunk(promp, constraints, W[a:a + chunk], grid, features, groups)

    def evaluate_timed(a):   # in a worker thread: its CPU time is accounted for
        c = time.thread_time()
        out = evaluate(a)
        with _pool_lock:
            _pool_cpu[0] += time.thread_time() - c
        return out
    chunks = (_executor().map(evaluate_timed, starts) if threads > 1 and len(starts) > 1
              else map(evaluate, starts))
    for a, (bad, n_run) in zip(starts, chunks):
        ran += n_run
        union = np.zeros(min(chunk, n_samples - a), bool)
        for i, v in enumerate(bad):
            per = np.count_nonzero(v, axis=0)
            step_counts[i] = per if step_counts[i] is None else step_counts[i] + per
            row = v.any(axis=1) if v.ndim == 2 else v
            traj_counts[i] += int(row.sum())
            union |= row
        any_count += int(union.sum())
    # per-step rule: Bonferroni over every tested step of every constraint
    n_tests = sum(int(np.size(s)) for s in step_counts) or 1
    upper = clopper_pearson_upper(traj_counts, n_samples)
    overall = any_count / n_samples
    overall_upper = float(clopper_pearson_upper([any_count], n_samples)[0])
    eps = 1.0 - min((c.alpha for c in constraints), default=1.0)
    reports = []
    for i, c in enumerate(constraints):
        counts = np.atleast_1d(step_counts[i])
        crit = critical_count(n_samples, 1.0 - c.alpha, significance / n_tests)
        if guarantee == 'per_step':
            holds = bool(counts.max() <= crit)
            found = detectable_violation(n_samples, crit)
        else:
            holds = bool(upper[i] <= 1.0 - c.alpha)
            found = detectable_violation(n_samples,
                                         trajectory_accepted(n_samples, 1.0 - c.alpha))
        reports.append(ConstraintVerification(
            c.name, c.kind, c.alpha, int(counts.size), float(counts.max() / n_samples),
            crit / n_samples, float(traj_counts[i] / n_samples), float(upper[i]), holds,
            found, found / (1.0 - c.alpha)))
    if guarantee == 'per_step':
        holds = all(r.holds for r in reports)
    else:
        holds = (not constraints) or overall_upper <= eps
    pairs = n_samples * sum(g.times.size for g in groups)
    kinematics = ran / pairs if pairs else 1.0
    return Verification(n_samples, guarantee, float(overall), overall_upper, bool(holds),
                        time.perf_counter() - t0, reports, kinematics)
