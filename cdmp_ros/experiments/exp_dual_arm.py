"""Paper 003, Section III-C: mutual avoidance of two Franka Pandas at a shared table.

Two Pandas with their bases 1.13 m apart, facing each other, each reach across the shared
workspace (``bags/dual_panda``: three demonstrations of both arms at once; the paths of the
end effectors cross, the original primitives collide). As in the paper, one ProMP is learned per
arm (EM, ``n_basis`` RBFs per joint) and the two are combined into the factorising joint ProMP
p0(w1) p0(w2) over the 14 joints, which is then adapted (Algorithm 1) with

- mutual avoidance between three points of interest per robot, x^{i,1} the tool centre point
  (between the fingertips), x^{i,2} the hand (flange, ``panda_hand`` origin), x^{i,3} the elbow
  (``panda_link4`` origin), for the paper's index pairs and distances
  G = {(1, 2, 0.1), (2, 1, 0.1), (2, 2, 0.1), (2, 3, 0.3), (3, 2, 0.3)} (Eq. 22, 24), each
  distance enlarged by ``clearance`` (the paper's distances are between points on the link
  axes; the Panda's links are about 0.06 m thick, so the paper's 0.1 m alone lets the hands
  touch; with 0.15 the adapted mean keeps the link geometry about 6 cm apart);
- the table as a hyperplane n = (0, 0, -1), b = (0, 0, 0.01) (Eq. 16) for every point of
  interest of both arms (the paper: the end effectors);
- the URDF joint limits of all 14 joints (Eq. 12, III-C2);
- objective (ii) of Section II-E5, the sum of the marginal KLs
  KL[p(w1) || p0(w1)] + KL[p(w2) || p0(w2)] (``AdaptationConfig.kl_blocks``);
- alpha = 0.999 for every constraint (the paper's alpha_c = alpha_hp).

Every figure is checked by sampling trajectories from the adapted ProMP (``n_samples``):
per-step collision probability (the largest over time of the fraction of samples closer than
d_ij, the paper's guarantee), trajectory-level collision probability (closer at some step),
joint-limit and table violations the same way, and, with pybullet, the smallest distance
between the two robots' link geometry along the adapted mean and in ``n_geometric`` samples.
The Figure 9 points of interest are only drawn in the paper; the choice above is ours.
"""
import os
from typing import Dict, Optional, Sequence, Tuple

import numpy as np
from numpy.typing import NDArray

from cdmp_ros.experiments.results import row, write_results

NAME = 'dual-arm'
HELP = 'paper 003 III-C: two Pandas at a table, mutual avoidance of link pairs (joint ProMP)'

ALPHA = 0.999
#: Points of interest x^{i,k}, k = 1..3, on each robot (name, chain link).
POINTS = (('tcp', 'ee'), ('hand', 'panda_hand'), ('elbow', 'panda_link4'))
#: The paper's pairs (i, j, d_ij): point i of the left robot vs point j of the right one [m].
PAIRS = ((1, 2, 0.1), (2, 1, 0.1), (2, 2, 0.1), (2, 3, 0.3), (3, 2, 0.3))
#: Table hyperplane n^T (x - b) <= 0 (paper 003, III-C1).
TABLE_NORMAL = (0.0, 0.0, -1.0)
TABLE_OFFSET = (0.0, 0.0, 0.01)
#: Default enlargement of every d_ij [m] (see the module docstring).
CLEARANCE = 0.15
#: Prior standard deviation of the weights when learning from three demonstrations [rad].
PRIOR_SD = 0.1
ARMS = ('left', 'right')


def add_arguments(parser):
    parser.add_argument('--out', required=True, help='output directory')
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--bags', default=None,
                        help='demonstrations (default: bags/dual_panda of the package)')
    parser.add_argument('--n-basis', type=int, default=8, help='basis functions per joint')
    parser.add_argument('--n-steps', type=int, default=50, help='time grid of the constraints')
    parser.add_argument('--n-samples', type=int, default=10000,
                        help='sampled trajectories for the collision/violation probabilities')
    parser.add_argument('--n-geometric', type=int, default=100,
                        help='sampled trajectories checked with the pybullet link geometry')
    parser.add_argument('--clearance', type=float, default=CLEARANCE,
                        help='added to every pair distance d_ij [m]')
    parser.add_argument('--no-limits', action='store_true',
                        help='leave the joint-limit constraints out (paper III-C1)')
    parser.add_argument('--no-plot', action='store_true', help='skip the PNG figures')
    parser.add_argument('--no-progress', action='store_true', help='no tqdm progress bars')


# -- problem ---------------------------------------------------------------------------------
def load_demonstrations(path: Optional[str] = None):
    """The dual-Panda demonstrations ``[(T, Y (n, 14), names)]`` (default ``bags/dual_panda``)."""
    from cdmp_ros.bag.demos import read_demonstrations
    from cdmp_ros.core.resources import data_path
    return read_demonstrations(path or data_path('bags', 'dual_panda'))


def learn_prior(demos, n_basis: int = 8, prior_sd: float = PRIOR_SD):
    """One ProMP per arm (EM), combined into p0(w1) p0(w2) over the 14 joints.

    Parameters
    ----------
    demos : list of (T, Y (n, 14), joint_names)
    n_basis : int
    prior_sd : float
        Mode of the inverse-Wishart prior of each arm's weights: ``prior_sd**2 * I`` (three
        demonstrations leave the covariance of 7 * n_basis weights rank-deficient; the fit's
        default mode, each joint's variance over the whole movement, is far wider than the
        spread of the demonstrations).

    Returns
    -------
    ProMP
        14 dimensions (left joints, then right joints), block-diagonal weight covariance.
    """
    from cdmp_ros.core.errors import ValidationError
    from cdmp_ros.core.kinematics import PANDA_JOINTS
    from cdmp_ros.core.promp.promp import ProMP, RbfBasis
    if not demos:
        raise ValidationError('demonstrations: expected at least one, got 0')
    expected = [f'{arm}_{j}' for arm in ARMS for j in PANDA_JOINTS]
    for i, (_, _, names) in enumerate(demos):
        if list(names) != expected:
            raise ValidationError(f'demonstrations[{i}]: expected the joints {expected} (the '
                                  f'dual_panda sim order), got {list(names)}')
    names = expected
    basis = RbfBasis.uniform(n_basis)
    n = 7 * n_basis
    arms = [ProMP.fit([(T, Y[:, 7 * a:7 * a + 7]) for T, Y, _ in demos], basis,
                      prior_cov=prior_sd ** 2 * np.eye(n), prior_strength=1.0)
            for a in range(2)]
    cov = np.zeros((2 * n, 2 * n))
    cov[:n, :n] = arms[0].cov_w
    cov[n:, n:] = arms[1].cov_w
    return ProMP(14, basis, np.r_[arms[0].mean_w, arms[1].mean_w], cov,
                 np.r_[arms[0].sigma_y, arms[1].sigma_y], arms[0].duration, names)


def cell_chains():
    """Kinematic chains of the left and the right Panda of the cell (world frame)."""
    from cdmp_ros.core.kinematics import dual_panda_chains
    from cdmp_ros.sim.robot_specs import panda_urdf_path
    return dual_panda_chains(panda_urdf_path())


def constraints(chains, clearance: float = CLEARANCE, limits: bool = True
                ) -> Dict[str, list]:
    """The constraint groups of the experiment: ``'pairs'`` (MutualAvoidance, one per entry of
    :data:`PAIRS`), ``'table'`` (Hyperplane per point and arm), ``'limits'`` (JointLimit per
    joint; empty with ``limits=False``)."""
    from cdmp_ros.core.adaptation.constraints import (ChainPoint, Hyperplane, JointLimit,
                                                      MutualAvoidance)
    from cdmp_ros.core.kinematics import PointOfInterest
    pts = [[ChainPoint(chain, PointOfInterest(link), range(7 * a, 7 * a + 7))
            for _, link in POINTS] for a, chain in enumerate(chains)]
    pairs = [MutualAvoidance(pts[0][i - 1], pts[1][j - 1], d + clearance, alpha=ALPHA,
                             name=f'pair_{i}{j}_{POINTS[i - 1][0]}_{POINTS[j - 1][0]}')
             for i, j, d in PAIRS]
    table = [Hyperplane(pts[a][k], TABLE_NORMAL, TABLE_OFFSET, alpha=ALPHA,
                        name=f'table_{ARMS[a]}_{POINTS[k][0]}')
             for a in range(2) for k in range(len(POINTS))]
    lims = []
    if limits:
        for a, chain in enumerate(chains):
            for j in range(7):
                lims.append(JointLimit(7 * a + j, chain.lower[j], chain.upper[j], alpha=ALPHA,
                                       name=f'limit_{ARMS[a]}_{j + 1}'))
    return {'pairs': pairs, 'table': table, 'limits': lims}


def adaptation_config(n_basis: int, n_steps: int):
    """Objective (ii): the sum of the two arms' marginal KLs (paper 003, II-E5)."""
    from cdmp_ros.core.adaptation.solver import AdaptationConfig
    n = 7 * n_basis
    return AdaptationConfig(n_steps=n_steps, kl_blocks=((0, n), (n, 2 * n)))


# -- sampled check ---------------------------------------------------------------------------
def sample_cell(promp, chains, n_samples: int, rng: np.random.Generator, grid: NDArray,
                chunk: int = 500, progress=None) -> Tuple[NDArray, NDArray]:
    """Sampled trajectories and their points of interest.

    Returns
    -------
    Q : (n_samples, n_steps, 14)
        Joint trajectories on ``grid``.
    X : (2, n_samples, n_steps, len(POINTS), 3)
        World positions of the points of interest of the left and the right robot (one batched
        forward-kinematics call per arm and chunk of ``chunk`` samples).
    """
    from cdmp_ros.core.kinematics import PointOfInterest
    pts = [PointOfInterest(link) for _, link in POINTS]
    Q = promp.sample_trajectories(grid, n_samples, rng)
    X = np.empty((2, n_samples, grid.size, len(pts), 3))
    for k in range(0, n_samples, chunk):
        sl = slice(k, min(k + chunk, n_samples))
        for a, chain in enumerate(chains):
            Qa = Q[sl, :, 7 * a:7 * a + 7]
            X[a, sl] = chain.forward(Qa.reshape(-1, 7), pts).reshape(Qa.shape[:2] + (len(pts), 3))
        if progress is not None:
            progress.update(sl.stop - sl.start)
    return Q, X


def pair_distances(X: NDArray) -> Dict[Tuple[int, int], NDArray]:
    """|x^{1,i}_t - x^{2,j}_t| per pair (i, j) of :data:`PAIRS`: (n_samples, n_steps)."""
    return {(i, j): np.linalg.norm(X[0, :, :, i - 1] - X[1, :, :, j - 1], axis=-1)
            for i, j, _ in PAIRS}


def sampled_check(groups: Dict[str, list], Q: NDArray, X: NDArray, grid: NDArray
                  ) -> Dict[str, Tuple[int, int]]:
    """Violations counted on sampled trajectories (the constraints' own ``satisfied`` tests).

    Returns
    -------
    dict
        Constraint name -> (largest number of violating samples at one time step, number of
        samples violating at some step of the support).
    """
    out = {}

    def count(c, Xc):
        sat = c.satisfied(Xc, c.times(grid))
        bad = ~sat
        return int(bad.sum(axis=0).max()), int(bad.any(axis=1).sum())
    for c, (i, j, _) in zip(groups['pairs'], PAIRS):
        out[c.name] = count(c, X[0, :, :, i - 1] - X[1, :, :, j - 1])
    for c, (a, k) in zip(groups['table'], [(a, k) for a in range(2)
                                           for k in range(len(POINTS))]):
        out[c.name] = count(c, X[a, :, :, k])
    for c in groups['limits']:
        out[c.name] = count(c, Q[:, :, c.joint:c.joint + 1])
    return out


def cross_correlation(promp) -> float:
    """Mean |correlation| between the weights of the left and of the right arm (0 for the
    factorising original; objective (ii) leaves room for it, paper 003 III-C4)."""
    C = promp.cov_w
    sd = np.sqrt(np.diag(C))
    n = C.shape[0] // 2
    return float(np.mean(np.abs(C[:n, n:] / np.outer(sd[:n], sd[n:]))))


# -- pybullet --------------------------------------------------------------------------------
class Cell:
    """The dual-Panda cell in a private pybullet world, with the table as a visual box: link
    geometry distances and snapshots."""

    def __init__(self):
        from cdmp_ros.sim.robot_specs import add_dual_panda
        from cdmp_ros.sim.world import World, WorldConfig
        self.world = World(WorldConfig(real_time=False))
        self.robots = add_dual_panda(self.world)
        self.world.obstacles.add_box('table', (0.565, 0.0, -0.0125), (0.9, 0.6, 0.01),
                                     collide=False, rgba=(0.6, 0.45, 0.3, 1.0))

    def set(self, q: NDArray) -> None:
        """Both arms to ``q`` (14,), clipped into the limits (a sample may leave them)."""
        for r, qa in zip(self.robots, (q[:7], q[7:])):
            r.reset(np.clip(qa, r.lower, r.upper))

    def robot_distance(self, max_distance: float = 1.0) -> float:
        """Smallest distance between the two robots' link geometry [m] (<= 0: contact)."""
        import pybullet
        pts = pybullet.getClosestPoints(self.robots[0].body_id, self.robots[1].body_id,
                                        max_distance, physicsClientId=self.world.client_id)
        return min((p[8] for p in pts), default=float('inf'))

    def snapshot(self, path: str = '') -> NDArray[np.uint8]:
        from cdmp_ros.sim.camera import CameraConfig, render, snapshot
        cam = CameraConfig(width=480, height=360, target=(0.565, 0.0, 0.3), distance=1.55,
                           yaw=25.0, pitch=-28.0)
        return snapshot(self.world, path, cam) if path else render(self.world, cam)

    def close(self) -> None:
        self.world.close()


def geometric_check(cell: Cell, Q: NDArray, progress=None) -> NDArray:
    """Smallest robot-robot link distance of each trajectory ``Q`` (n_traj, n_steps, 14)."""
    out = np.empty(Q.shape[0])
    for k, traj in enumerate(Q):
        best = np.inf
        for q in traj:
            cell.set(q)
            best = min(best, cell.robot_distance())
        out[k] = best
        if progress is not None:
            progress.update(1)
    return out


# -- figures ---------------------------------------------------------------------------------
def plot_distances(path: str, grid: NDArray, prior_d: Dict[Tuple[int, int], NDArray],
                   adapted_d: Dict[Tuple[int, int], NDArray], pairs: Sequence) -> str:
    """Pairwise distances over the phase: mean and 5-95 % band, prior vs adapted."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, len(pairs), figsize=(4 * len(pairs), 3.6), sharey=True)
    for ax, c, (i, j, _) in zip(np.atleast_1d(axes), pairs, PAIRS):
        for d, colour, label in ((prior_d[(i, j)], 'tab:blue', 'original'),
                                 (adapted_d[(i, j)], 'tab:red', 'adapted')):
            lo, hi = np.percentile(d, [5, 95], axis=0)
            ax.fill_between(grid, lo, hi, color=colour, alpha=0.25)
            ax.plot(grid, d.mean(axis=0), color=colour, label=label)
        ax.axhline(c.radius, color='k', ls='--', lw=1, label='d_ij')
        ax.set_title(c.name)
        ax.set_xlabel('phase s')
    np.atleast_1d(axes)[0].set_ylabel('distance [m] (mean, 5-95 %)')
    np.atleast_1d(axes)[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def snapshots(path: str, cell: Cell, prior, adapted, samples: NDArray,
              phases: Sequence[float] = (0.0, 0.25, 0.5, 0.75, 1.0)) -> str:
    """A grid of pybullet renders: rows original mean, adapted mean, adapted samples overlaid
    (the per-pixel average of one render per sample, a ghosted overlay); columns phases."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    s = np.asarray(phases, dtype=float)
    rows = [('original mean', prior.mean(s)), ('adapted mean', adapted.mean(s))]
    images = []
    for _, Q in rows:
        line = []
        for q in Q:
            cell.set(q)
            line.append(cell.snapshot())
        images.append(line)
    overlay = []
    for i in range(s.size):
        acc = None
        for Q in samples:
            cell.set(Q[i])
            img = cell.snapshot().astype(np.float64)
            acc = img if acc is None else acc + img
        overlay.append((acc / len(samples)).astype(np.uint8))
    images.append(overlay)
    titles = [r[0] for r in rows] + [f'{len(samples)} adapted samples']
    fig, axes = plt.subplots(3, s.size, figsize=(3.2 * s.size, 7.5))
    for r, (line, title) in enumerate(zip(images, titles)):
        for c, img in enumerate(line):
            ax = axes[r, c]
            ax.imshow(img)
            ax.set_xticks([])
            ax.set_yticks([])
            if r == 0:
                ax.set_title(f's = {s[c]:g}')
            if c == 0:
                ax.set_ylabel(title)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


# -- experiment ------------------------------------------------------------------------------
def solve(seed: int = 0, n_basis: int = 8, n_steps: int = 50, n_samples: int = 10000,
          n_geometric: int = 100, clearance: float = CLEARANCE, limits: bool = True,
          bags: Optional[str] = None, progress: bool = True):
    """Learn, adapt and check; returns (rows, artefacts for the figures and the tests)."""
    from tqdm import tqdm
    from cdmp_ros.core.adaptation.guarantee import adapt
    from cdmp_ros.core.adaptation.verification import clopper_pearson_upper
    rng = np.random.default_rng(seed)
    prior = learn_prior(load_demonstrations(bags), n_basis)
    chains = cell_chains()
    groups = constraints(chains, clearance, limits)
    # the joint limits are always checked, constrained or not
    checked = dict(groups, limits=constraints(chains, clearance, True)['limits'])
    allc = [c for g in groups.values() for c in g]
    adapted, report = adapt(prior, allc, adaptation_config(n_basis, n_steps))
    grid = np.linspace(0.0, 1.0, n_steps)
    checks, dists = {}, {}
    with tqdm(total=2 * n_samples, desc='dual-arm sampled check', unit='traj',
              disable=not progress) as bar:
        for tag, p in (('original', prior), ('adapted', adapted)):
            Q, X = sample_cell(p, chains, n_samples, rng, grid, progress=bar)
            checks[tag] = sampled_check(checked, Q, X, grid)
            dists[tag] = pair_distances(X)
            del Q, X
    cell = Cell()
    try:
        with tqdm(total=n_geometric + 1, desc='dual-arm link geometry', unit='traj',
                  disable=not progress) as bar:
            mean_geo = float(geometric_check(cell, adapted.mean(grid)[None], bar)[0])
            geo = geometric_check(cell, adapted.sample_trajectories(grid, n_geometric, rng),
                                  bar)
    finally:
        cell.close()
    rows = [row('adapted.kl', report.kl, None, 'nats'),
            row('adapted.kl_per_basis', report.kl_per_basis, None, 'nats'),
            row('adapted.solve_s', report.time_s, None, 's'),
            row('adapted.converged', report.converged, None, ''),
            row('adapted.n_outer', report.n_outer, None, ''),
            row('adapted.mean_abs_cross_correlation', cross_correlation(adapted), None, '')]
    pct = 100.0 / n_samples
    for c, (i, j, _) in zip(groups['pairs'], PAIRS):
        for tag in ('original', 'adapted'):
            step, traj = checks[tag][c.name]
            rows += [row(f'{tag}.{c.name}.collision_step_pct', step * pct, None, '%'),
                     row(f'{tag}.{c.name}.collision_traj_pct', traj * pct, None, '%')]
        upper = float(clopper_pearson_upper(checks['adapted'][c.name][0], n_samples))
        rows += [row(f'adapted.{c.name}.collision_step_upper95_pct', 100 * upper, None, '%'),
                 row(f'adapted.{c.name}.min_mean_distance_m',
                     float(dists['adapted'][(i, j)].mean(axis=0).min()), None, 'm')]
    for key in ('table', 'limits'):
        for tag in ('original', 'adapted'):
            names = [c.name for c in checked[key]]
            step = max(checks[tag][n][0] for n in names)
            traj = max(checks[tag][n][1] for n in names)
            rows += [row(f'{tag}.{key}.worst_violation_step_pct', step * pct, None, '%'),
                     row(f'{tag}.{key}.worst_violation_traj_pct', traj * pct, None, '%')]
    rows += [row('adapted.mean.robot_distance_m', mean_geo, None, 'm'),
             row('adapted.samples.robot_contact_pct', 100 * float(np.mean(geo <= 0.0)),
                 None, '%'),
             row('adapted.samples.robot_distance_min_m', float(geo.min()), None, 'm')]
    art = {'prior': prior, 'adapted': adapted, 'report': report, 'groups': groups,
           'checks': checks, 'distances': dists, 'grid': grid, 'rng': rng,
           'n_samples': n_samples}
    return rows, art


def run(args):
    os.makedirs(args.out, exist_ok=True)
    rows, art = solve(args.seed, args.n_basis, args.n_steps, args.n_samples, args.n_geometric,
                      args.clearance, not args.no_limits, args.bags, not args.no_progress)
    notes = [__doc__.strip().splitlines()[0],
             f'alpha = {ALPHA}; pairs (i, j, d_ij + clearance): '
             + ', '.join(f'({i}, {j}, {d + args.clearance:g})' for i, j, d in PAIRS)
             + f'; points 1..3: {", ".join(n for n, _ in POINTS)}.',
             f'collision_step_pct: the largest over the {args.n_steps} time steps of the '
             f"fraction of {args.n_samples} sampled trajectories closer than d_ij (the paper's "
             'per-step guarantee, at most 0.1 %); collision_traj_pct: closer at some step.',
             'table / limits: the worst constraint of the group, the same two ways.',
             f'robot_distance: pybullet link geometry, along the adapted mean and in '
             f'{args.n_geometric} sampled trajectories (contact: distance <= 0).',
             'The paper reports these experiments as figures only (no numbers).']
    if not args.no_plot:
        from tqdm import tqdm
        grid = art['grid']
        figs = [plot_distances(os.path.join(args.out, 'pair_distances.png'), grid,
                               art['distances']['original'], art['distances']['adapted'],
                               art['groups']['pairs'])]
        cell = Cell()
        try:
            with tqdm(total=1, desc='snapshots', disable=args.no_progress) as bar:
                samples = art['adapted'].sample_trajectories([0.0, 0.25, 0.5, 0.75, 1.0], 6,
                                                             art['rng'])
                figs.append(snapshots(os.path.join(args.out, 'snapshots.png'), cell,
                                      art['prior'], art['adapted'], samples))
                bar.update(1)
        finally:
            cell.close()
        notes.append('Figures: ' + ', '.join(os.path.basename(f) for f in figs))
    print(write_results(args.out, 'dual-arm', rows, notes))
    return 0 if art['report'].converged else 1
