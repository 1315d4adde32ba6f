"""Paper 003, Section III-A: constrained ProMP adaptation on a planar 4-link arm (links of 1 m).

Original ProMPs are learned (EM, 8 basis functions per joint) from noisy movements of the joints
from a fixed start configuration to an end configuration that puts the end effector at
(1.73, 0), then conditioned on the end configuration. Every adaptation adds the paper's start
constraint (narrow joint limits at t = 0, lambda0 = 100) and end-effector waypoint
((1.73, 0), radius 0.05 at t = 1, lambda0 = 100); the task constraints start at lambda0 = 1;
alpha = 0.999. Each task is solved with the KL objective alone and with the smoothness
regulariser (kappa = 0.1, joint weights 2, 0.1, 0.1, 0.1). Mutual avoidance (III-A5) adapts a
joint ProMP of two arms with both objectives of Section II-E5.

Demonstrations are synthetic (minimum-jerk joint motion plus random smooth bumps), not the
paper's linear-system samples, so the figures show the same behaviour, not the same curves.
"""
import os

import numpy as np

from cdmp_ros.experiments.results import row, verification_rows, write_results

NAME = 'planar'
HELP = 'paper 003 III-A: planar 4-link arm (waypoint, repeller, corner, wall, mutual avoidance)'

ALPHA = 0.999
START_A = np.array([np.pi / 2 - 0.3, 0.3, 0.3, 0.3])
START_H = np.array([-1.5, 0.5, 0.5, 0.5])
END_XY = np.array([1.73, 0.0])
END_VAR = 0.02   # conditioning variance of the final joint configuration [rad^2]


def add_arguments(parser):
    parser.add_argument('--out', required=True, help='output directory')
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--n-samples', type=int, default=10000,
                        help='sampled trajectories for the violation probabilities')
    parser.add_argument('--n-steps', type=int, default=50, help='time grid of the constraints')
    parser.add_argument('--no-plot', action='store_true', help='skip the PNG figures')


def _ik(chain, q_guess, target):
    from scipy.optimize import least_squares
    from cdmp_ros.core.kinematics import PointOfInterest
    ee = [PointOfInterest('ee')]
    res = least_squares(lambda q: chain.forward(q, ee)[0, :2] - target, q_guess)
    return res.x


ELBOW_UP = np.array([1.2, -0.9, -0.9, -0.6])
ELBOW_DOWN = np.array([-1.0, 0.6, 0.6, 0.6])


def original_promp(chain, start, rng, n_basis=8, n_demos=12, spread=0.25, end_guess=ELBOW_UP):
    """Learn the original ProMP from synthetic demonstrations and condition on the end
    configuration (inverse kinematics of (1.73, 0) from ``end_guess``)."""
    from cdmp_ros.core.promp.promp import ProMP, RbfBasis
    end = _ik(chain, np.asarray(end_guess, float), END_XY)
    T = np.linspace(0.0, 1.0, 80)
    s = 10 * T ** 3 - 15 * T ** 4 + 6 * T ** 5
    demos = []
    for _ in range(n_demos):
        bumps = rng.normal(0.0, spread, (2, 4))
        Y = (start + np.outer(s, end - start) + np.outer(np.sin(np.pi * T), bumps[0])
             + np.outer(np.sin(2 * np.pi * T), bumps[1]))
        demos.append((T, Y))
    p = ProMP.fit(demos, RbfBasis.uniform(n_basis), prior_strength=1.0,
                  joint_names=[f'joint{i + 1}' for i in range(4)])
    return p.condition([1.0], end[None], var=END_VAR), end


def base_constraints(chain, start, ee, offset=None):
    """Start joint limits (t = 0) and the end-effector waypoint at t = 1 (lambda0 = 100)."""
    from cdmp_ros.core.adaptation.constraints import JointLimit, Waypoint
    dofs = range(4) if offset is None else range(offset, offset + 4)
    cons = [JointLimit(d, start[i] - 0.05, start[i] + 0.05, support=(0.0, 0.0), alpha=ALPHA,
                       lambda0=100.0, name=f'start_q{i + 1}') for i, d in enumerate(dofs)]
    cons.append(Waypoint(ee, END_XY, 0.05, support=(1.0, 1.0), alpha=ALPHA, lambda0=100.0,
                         name='end_point'))
    return cons


def tasks(chain):
    """The four task constraint sets of Fig. 3 (name -> (start, end guess, constraints)).
    The corner and the wall use an elbow-down end configuration: with the elbow-up one the
    final arm itself violates them (its links 2-3 end inside the corner / beyond the wall)."""
    from cdmp_ros.core.adaptation.constraints import (ChainPoint, Hyperplane, NonConvexCorner,
                                                      Repeller, Waypoint)
    from cdmp_ros.core.kinematics import PointOfInterest
    ee = ChainPoint(chain, PointOfInterest('ee'), axes=(0, 1))
    x2 = ChainPoint(chain, PointOfInterest('link3'), axes=(0, 1))
    x3 = ChainPoint(chain, PointOfInterest('link4'), axes=(0, 1))
    kw = {'alpha': ALPHA, 'lambda0': 1.0}
    corner = [NonConvexCorner(p, [1, 0], [0.5, 0.5], [0, 1], [0.5, 0.5], name=f'corner_{n}',
                              **kw) for p, n in ((ee, 'ee'), (x2, 'x2'), (x3, 'x3'))]
    return ee, {
        'waypoint': (START_A, ELBOW_UP, [Waypoint(ee, [3.4, 2.0], 0.05, support=(0.65, 0.75),
                                                  name='waypoint', **kw)]),
        'repeller': (START_A, ELBOW_UP, [Repeller(ee, [2.0, 3.0], 1.0, name='repeller',
                                                  **kw)]),
        'corner': (START_A, ELBOW_DOWN, corner),
        'hyperplane': (START_H, ELBOW_DOWN, [Hyperplane(p, [1.0, 1.0], [0.0, 2.0],
                                                        name=f'wall_{n}', **kw)
                                             for p, n in ((ee, 'ee'), (x3, 'x3'))]),
    }


def solve_all(seed=0, n_samples=10000, n_steps=50):
    """Run every experiment; returns (rows, artefacts for plotting)."""
    from cdmp_ros.core.adaptation.guarantee import adapt
    from cdmp_ros.core.adaptation.solver import AdaptationConfig, monte_carlo_satisfaction
    from cdmp_ros.core.kinematics import planar_chain
    rng = np.random.default_rng(seed)
    chain = planar_chain([1.0] * 4)
    ee, task_sets = tasks(chain)
    originals = {}
    rows, art = [], {'chain': chain, 'ee': ee, 'fig3': {}, 'originals': originals}
    for name, (start, end_guess, cons) in task_sets.items():
        key = (tuple(start), tuple(end_guess))
        if key not in originals:
            originals[key] = original_promp(chain, start, rng, end_guess=end_guess)
        prior, _ = originals[key]
        allc = base_constraints(chain, start, ee) + cons
        for smooth in (False, True):
            cfg = AdaptationConfig(n_steps=n_steps, kappa=0.1 if smooth else 0.0,
                                   smoothness_weights=(2.0, 0.1, 0.1, 0.1))
            q, rep = adapt(prior, allc, cfg)
            _, _, ok_task = monte_carlo_satisfaction(q, cons, n_samples, rng, n_steps)
            _, _, ok_all = monte_carlo_satisfaction(q, allc, n_samples, rng, n_steps)
            tag = f'{name}.{"smooth" if smooth else "kl"}'
            rows += [row(f'{tag}.violation_pct', (1 - ok_task) * 100, None, '%'),
                     row(f'{tag}.violation_all_pct', (1 - ok_all) * 100, None, '%'),
                     row(f'{tag}.kl', rep.kl, None, 'nats'),
                     row(f'{tag}.converged', rep.converged, None, ''),
                     row(f'{tag}.solve_s', rep.time_s, None, 's')]
            rows += verification_rows(tag, rep)
            art['fig3'][(name, smooth)] = (prior, q, cons)
    rows_m, art['mutual'] = mutual(chain, rng, n_samples, n_steps)
    return rows + rows_m, art


def mutual(chain, rng, n_samples, n_steps):
    """III-A5: two planar arms (bases 3 m apart, facing) with crossing reaching movements."""
    from cdmp_ros.core.adaptation.guarantee import adapt
    from cdmp_ros.core.adaptation.solver import AdaptationConfig, monte_carlo_satisfaction
    from cdmp_ros.core.adaptation.constraints import ChainPoint, MutualAvoidance
    from cdmp_ros.core.kinematics import PointOfInterest, planar_chain
    from cdmp_ros.core.promp.promp import ProMP
    p1, _ = original_promp(chain, START_A, rng)
    # robot 2: mirrored about x = 1.5 (base at (3, 0), facing -x), same movement mirrored
    M, D = p1.n_basis, 8
    mean2 = p1.mean_w.reshape(4, M).copy()
    mean2[0] = np.pi - mean2[0]
    mean2[1:] = -mean2[1:]
    J = np.diag([-1.0, -1.0, -1.0, -1.0])
    J[0, 0] = -1.0
    cov2 = np.kron(J, np.eye(M)) @ p1.cov_w @ np.kron(J, np.eye(M)).T
    cov = np.zeros((D * M, D * M))
    cov[:4 * M, :4 * M] = p1.cov_w
    cov[4 * M:, 4 * M:] = cov2
    time_shift = 0.25
    joint = ProMP(D, p1.basis, np.r_[p1.mean_w, mean2.ravel()], cov)
    # the second robot's base: 3 m along x
    chain2 = planar_chain([1.0] * 4)
    shift = np.array([3.0, 0.0])

    class Shifted(ChainPoint):
        def forward_and_jacobian(self, Z):
            X, Jac = super().forward_and_jacobian(Z)
            return X + shift, Jac

    e1 = ChainPoint(chain, PointOfInterest('ee'), range(4), (0, 1))
    j1 = ChainPoint(chain, PointOfInterest('link4'), range(4), (0, 1))
    e2 = Shifted(chain2, PointOfInterest('ee'), range(4, 8), (0, 1))
    j2 = Shifted(chain2, PointOfInterest('link4'), range(4, 8), (0, 1))
    cons = [MutualAvoidance(e1, e2, 0.4, alpha=ALPHA, lambda0=20.0, name='ee_ee'),
            MutualAvoidance(j1, e2, 0.8, alpha=ALPHA, lambda0=20.0, name='x4_ee'),
            MutualAvoidance(e1, j2, 0.8, alpha=ALPHA, lambda0=20.0, name='ee_x4')]
    del time_shift
    rows, art = [], {'prior': joint, 'points': (e1, e2), 'adapted': {}}
    _, _, ok0 = monte_carlo_satisfaction(joint, cons, n_samples, rng, n_steps)
    rows.append(row('mutual.original.violation_pct', (1 - ok0) * 100, None, '%'))
    for objective, blocks in (('joint_kl', None), ('marginal_kl', ((0, 4 * M), (4 * M, 8 * M)))):
        # a gentler multiplier step (clip 1 instead of 3): both robots' constraints interact
        # confidence margin 0.2: the unscented Gaussian of the relative position of two arms
        # under-states the per-step violations (up to 5 (1 - alpha) with marginal_kl at margin
        # 1, with either tail law); the tails of |x1 - x2|^2 themselves are accurate
        q, rep = adapt(joint, cons, AdaptationConfig(n_steps=n_steps, kl_blocks=blocks,
                                                     max_log_step=1.0, confidence_margin=0.2))
        _, _, ok = monte_carlo_satisfaction(q, cons, n_samples, rng, n_steps)
        C = q.cov_w
        sd = np.sqrt(np.diag(C))
        R = C / np.outer(sd, sd)
        cross = float(np.mean(np.abs(R[:4 * M, 4 * M:])))
        rows += [row(f'mutual.{objective}.violation_pct', (1 - ok) * 100, None, '%'),
                 row(f'mutual.{objective}.kl', rep.kl, None, 'nats'),
                 row(f'mutual.{objective}.mean_abs_cross_correlation', cross, None, ''),
                 row(f'mutual.{objective}.converged', rep.converged, None, '')]
        rows += verification_rows(f'mutual.{objective}', rep)
        art['adapted'][objective] = (q, R)
    return rows, art


def _ut_ellipses(p, point, s):
    from cdmp_ros.core.promp.gaussian import UnscentedTransform
    dofs = list(point.dofs)
    m = p.mean(s)[:, dofs]
    S = p.cov(s)[:, dofs][:, :, dofs]
    ut = UnscentedTransform(len(dofs))
    Z, _ = ut.points(m, S)
    return ut.moments(point.forward(Z))


def _draw(ax, p, point, colour, label):
    from matplotlib.patches import Ellipse
    s = np.linspace(0, 1, 60)
    mx, Sx = _ut_ellipses(p, point, s)
    ax.plot(mx[:, 0], mx[:, 1], color=colour, lw=2, label=label)
    for i in range(0, s.size, 6):
        vals, vecs = np.linalg.eigh(Sx[i])
        w, h = 2 * np.sqrt(5.991 * np.maximum(vals, 0))   # 0.95 level set
        ang = np.degrees(np.arctan2(vecs[1, 1], vecs[0, 1]))
        ax.add_patch(Ellipse(mx[i], w, h, angle=ang, color=colour, alpha=0.15))


def _draw_arm(ax, chain, q, colour):
    from cdmp_ros.core.kinematics import PointOfInterest
    pts = chain.forward(q, [PointOfInterest(n) for n in ('link1', 'link2', 'link3', 'link4',
                                                         'ee')])
    ax.plot(pts[:, 0], pts[:, 1], '-o', color=colour, ms=3, lw=1, alpha=0.6)


def _draw_constraints(ax, cons):
    from matplotlib.patches import Circle
    for c in cons:
        if c.kind in ('waypoint', 'repeller'):
            ax.add_patch(Circle(c.center, c.radius, fill=False, color='k'))
        elif c.kind == 'hyperplane':
            n = c.normal / np.linalg.norm(c.normal)
            t = np.array([-n[1], n[0]])
            seg = np.stack([c.offset - 6 * t, c.offset + 6 * t])
            ax.plot(seg[:, 0], seg[:, 1], 'k-')
        elif c.kind == 'corner':
            ax.plot([c.b1[0], c.b1[0], 5], [5, c.b2[1], c.b2[1]], 'k-')


def plot(out_dir, art):
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    chain, ee = art['chain'], art['ee']
    names = ['waypoint', 'repeller', 'corner', 'hyperplane']
    fig, axes = plt.subplots(3, 4, figsize=(16, 12))
    for j, name in enumerate(names):
        prior, _, cons = art['fig3'][(name, False)]
        for i, (title, p) in enumerate((('original', prior),
                                        ('KL', art['fig3'][(name, False)][1]),
                                        ('KL + smoothness', art['fig3'][(name, True)][1]))):
            ax = axes[i, j]
            _draw(ax, p, ee, 'tab:blue' if i == 0 else 'tab:red', title)
            for s in (0.0, 0.5, 1.0):
                _draw_arm(ax, chain, p.mean([s])[0], 'gray')
            _draw_constraints(ax, cons)
            ax.plot(*END_XY, 'kx')
            ax.set_xlim(-4.2, 4.2)
            ax.set_ylim(-4.2, 4.2)
            ax.set_aspect('equal')
            ax.set_title(f'{name}: {title}')
    fig.tight_layout()
    fig.savefig(os.path.join(out_dir, 'fig3_planar.png'), dpi=80)
    plt.close(fig)
    m = art['mutual']
    fig, axes = plt.subplots(1, 3, figsize=(18, 6))
    e1, e2 = m['points']
    for ax, (title, p) in zip(axes, (('original', m['prior']),
                                     ('adapted (joint KL)', m['adapted']['joint_kl'][0]),
                                     ('adapted (marginal KLs)',
                                      m['adapted']['marginal_kl'][0]))):
        _draw(ax, p, e1, 'tab:blue', 'robot 1')
        _draw(ax, p, e2, 'tab:orange', 'robot 2')
        ax.set_aspect('equal')
        ax.set_xlim(-2, 5)
        ax.set_ylim(-3, 4.5)
        ax.set_title(title)
        ax.legend()
    fig.tight_layout()
    fig.savefig(os.path.join(out_dir, 'fig4_mutual.png'), dpi=80)
    plt.close(fig)
    fig, axes = plt.subplots(1, 2, figsize=(12, 6))
    for ax, obj in zip(axes, ('joint_kl', 'marginal_kl')):
        ax.imshow(m['adapted'][obj][1], cmap='coolwarm', vmin=-1, vmax=1)
        ax.set_title(f'weight correlations, {obj}')
    fig.tight_layout()
    fig.savefig(os.path.join(out_dir, 'fig5_correlations.png'), dpi=80)
    plt.close(fig)
    return ['fig3_planar.png', 'fig4_mutual.png', 'fig5_correlations.png']


def run(args):
    os.makedirs(args.out, exist_ok=True)
    rows, art = solve_all(args.seed, args.n_samples, args.n_steps)
    notes = [__doc__.strip().splitlines()[0],
             'violation_pct: sampled trajectories (of n_samples) violating a task constraint at '
             'any step; violation_all_pct also counts the start and end constraints.']
    if not args.no_plot:
        notes.append('Figures: ' + ', '.join(plot(args.out, art)))
    print(write_results(args.out, 'planar', rows, notes))
    return 0
