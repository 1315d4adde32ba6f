"""Random 2-D adaptation problems of paper 003, Section III-B (Tables II-IV), generated exactly
as ../shared/promp_benchmark_protocol.md specifies, and their evaluation metrics."""
from dataclasses import dataclass
from typing import List

import numpy as np

from cdmp_ros.core.adaptation.solver import AdaptationConfig, sample_points
from cdmp_ros.core.adaptation.constraints import DofPoint, Hyperplane, Repeller, UnboundWaypoint
from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.promp.promp import ProMP, RbfBasis

ALPHA = 0.999
XY = DofPoint([0, 1])

# table -> (n_steps, n_basis, lambda0)
SETTINGS = {'table2': (101, 10, 20.0), 'table3': (40, 20, 20.0), 'table4': (20, 10, 40.0)}


@dataclass
class TableProblem:
    table: str
    prior: ProMP              # the conditioned "original" primitive
    constraints: list
    config: AdaptationConfig
    start: np.ndarray
    end: np.ndarray


def original_promp(n_basis: int, rng: np.random.Generator, prior: str = 'scripts'):
    """The conditioned original ProMP and its start and end points (protocol, all tables)."""
    basis = RbfBasis.uniform(n_basis, extension=0.1)
    M = n_basis
    if prior == 'scripts':
        p = ProMP(2, basis, np.r_[np.linspace(-3.0, 3.0, M), np.zeros(M)],
                  0.8 ** 2 * np.eye(2 * M))
    elif prior == 'paper-text':
        p = ProMP(2, basis, np.zeros(2 * M), np.eye(2 * M))
    else:
        raise ValidationError(f'prior: expected "scripts" or "paper-text", got {prior!r}')
    start = np.array([-3.0, rng.uniform(-3.0, 3.0)])
    end = np.array([3.0, rng.uniform(-3.0, 3.0)])
    return p.condition([0.0, 1.0], np.stack([start, end]), var=1e-3), start, end


def make_problem(table: str, K: int, rng: np.random.Generator,
                 prior: str = 'scripts', relative_step: bool = False,
                 confidence_margin: float = 1.0, alpha: float = ALPHA) -> TableProblem:
    """One random problem of ``table`` ('table2', 'table3', 'table4') with K constraints,
    each at confidence ``alpha`` (the protocol's 0.999 by default), with the authors'
    optimiser settings (``relative_step=False``: the paper's EMM step; ``confidence_margin``:
    see AdaptationConfig)."""
    n_steps, n_basis, lambda0 = SETTINGS[table]
    p0, start, end = original_promp(n_basis, rng, prior)
    cons: List = []
    if table == 'table2':
        for k in range(K):
            t = rng.uniform(0.2, 0.8)
            centre = p0.mean([t])[0] + np.array([0.0, rng.uniform(-1.5, 1.5)])
            cons.append(Repeller(XY, centre, rng.uniform(0.3, 0.6), alpha=alpha,
                                 name=f'obstacle_{k + 1}'))
    elif table == 'table3':
        grid = np.linspace(0.0, 1.0, n_steps)
        mean = p0.mean(grid)
        xs = np.linspace(-3.0, 3.0, K + 3)[1:K + 1]
        for k, x in enumerate(xs):
            x = x + rng.uniform(0.4, 0.6) * 6.0 / (K + 2)
            i = int(np.argmin(np.abs(mean[:, 0] - x)))
            y = mean[i, 1] + rng.uniform(-0.7, 0.7)
            cons.append(UnboundWaypoint(XY, [x, y], rng.uniform(0.05, 0.2), alpha=alpha,
                                        name=f'waypoint_{k + 1}'))
    elif table == 'table4':
        m = 0.5 * (start + end)
        e = end - start
        perp = np.array([-e[1], e[0]]) / np.linalg.norm(e)
        k = 0
        while k < K:
            side = 1.0 if rng.uniform() < 0.5 else -1.0
            d = side * perp * rng.uniform(0.2, 1.5)
            b = m + d
            a = rng.uniform(-3.0 * np.pi, np.pi)
            n = np.array([np.cos(a) * d[0] - np.sin(a) * d[1],
                          np.sin(a) * d[0] + np.cos(a) * d[1]])
            if n @ (start - b) > 0 or n @ (end - b) > 0:
                continue          # reject walls that forbid the start or the end
            cons.append(Hyperplane(XY, n, b, alpha=alpha, name=f'wall_{k + 1}'))
            k += 1
    else:
        raise ValidationError(f'table: expected table2, table3 or table4, got {table!r}')
    cfg = AdaptationConfig(n_steps=n_steps, lambda0=lambda0, eta=1.0, max_outer=10,
                           max_inner=500, objective_tol=1e-2, relative_step=relative_step,
                           confidence_margin=confidence_margin)
    return TableProblem(table, p0, cons, cfg, start, end)


def sampled_violations(promp: ProMP, problem: TableProblem, rng: np.random.Generator,
                       n_samples: int = 200_000, chunk: int = 20_000):
    """Per-constraint sampled violation frequencies of ``promp`` on the problem's grid.

    Returns
    -------
    per_step : ndarray, shape (n_constraints,)
        For constraints imposed at every step, the largest violation frequency over the steps
        (what the constraint's confidence alpha bounds); for temporally unbound waypoints
        (Eq. 19, one multiplier at the best step), the violation frequency at the best step.
    trajectory : ndarray, shape (n_constraints,)
        Frequency of trajectories violating the constraint at some step (never inside the
        ball, for an unbound waypoint).
    any_violation : float
        Frequency of trajectories violating at least one constraint.
    """
    grid = np.linspace(0.0, 1.0, problem.config.n_steps)
    nc = len(problem.constraints)
    ok_steps = [None] * nc
    bad_traj = np.zeros(nc)
    bad_any = 0
    done = 0
    while done < n_samples:
        n = min(chunk, n_samples - done)
        W = promp.sample_weights(n, rng)
        ok_all = np.ones(n, bool)
        for i, c in enumerate(problem.constraints):
            times = c.times(grid)
            X = sample_points(promp, c, n, rng, grid, W)
            if c.reduce == 'max':
                D = X - c.centers(times)[None]
                sat_t = np.einsum('...i,...i->...', D, D) <= c.radius ** 2   # inside, per step
                ok = sat_t.any(axis=1)
            else:
                sat_t = c.satisfied(X, times)
                ok = sat_t.all(axis=1)
            cnt = sat_t.sum(axis=0)
            ok_steps[i] = cnt if ok_steps[i] is None else ok_steps[i] + cnt
            bad_traj[i] += n - ok.sum()
            ok_all &= ok
        bad_any += n - ok_all.sum()
        done += n
    per_step = np.array([1.0 - (cnt.max() if c.reduce == 'max' else cnt.min()) / n_samples
                         for c, cnt in zip(problem.constraints, ok_steps)])
    return per_step, bad_traj / n_samples, bad_any / n_samples


def panda_problem(chain, rng: np.random.Generator, n_basis: int = 10, n_steps: int = 100,
                  n_spheres: int = 3, n_demos: int = 8):
    """The 7-DoF benchmark problem: a joint-space Panda ProMP (``n_basis`` per joint) learned
    by EM from noisy minimum-jerk demonstrations, adapted to two-sided joint limits (the URDF's)
    and ``n_spheres`` sphere repellers on the end effector and the elbow (panda_link4 origin),
    placed near the original mean path.

    Returns
    -------
    prior : ProMP; constraints : list; config : AdaptationConfig
    """
    from cdmp_ros.core.adaptation.constraints import ChainPoint, JointLimit
    from cdmp_ros.core.kinematics import PointOfInterest
    lo, hi = np.asarray(chain.lower), np.asarray(chain.upper)
    mid, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
    q0 = mid + rng.uniform(-0.4, 0.4, 7) * half
    q1 = mid + rng.uniform(-0.4, 0.4, 7) * half
    T = np.linspace(0.0, 1.0, 60)
    s = 10 * T ** 3 - 15 * T ** 4 + 6 * T ** 5
    demos = []
    for _ in range(n_demos):
        a = q0 + 0.03 * rng.standard_normal(7)
        b = q1 + 0.03 * rng.standard_normal(7)
        bump = 0.1 * rng.standard_normal(7)
        demos.append((T, a + np.outer(s, b - a) + np.outer(np.sin(np.pi * T), bump)))
    prior = ProMP.fit(demos, RbfBasis.uniform(n_basis), prior_strength=2.0)
    ee = ChainPoint(chain, PointOfInterest('ee'))
    elbow = ChainPoint(chain, PointOfInterest('panda_link4'))
    cons: List = [JointLimit(j, lo[j], hi[j], alpha=ALPHA, name=f'limit_{j + 1}')
                  for j in range(7)]
    grid = np.linspace(0.0, 1.0, n_steps)
    for k in range(n_spheres):
        t = rng.uniform(0.3, 0.7)
        target = ee if k < n_spheres - 1 else elbow
        x = target.forward(prior.mean([t]))[0]
        centre = x + rng.normal(0.0, 0.04, 3)
        radius = rng.uniform(0.05, 0.1)
        for name, pt in (('ee', ee), ('elbow', elbow)):
            cons.append(Repeller(pt, centre, radius, alpha=ALPHA, name=f'sphere_{k + 1}_{name}'))
    # lambda0 = 40 (instead of the Table II protocol's 20): the first inner loop is feasible
    # more often, ~15 % fewer Lagrangian evaluations (median over 4 x 20 problems)
    cfg = AdaptationConfig(n_steps=n_steps, lambda0=40.0)
    del grid
    return prior, cons, cfg
