"""Paper 000, section IV-A: toy comparison of DMPs and CDMPs (Fig. 3).

Demonstrations (1-D, joint angle in degrees, 1 s sampled at 500 Hz):

- goal adaptation: a minimum-jerk move from 0 to 20 deg plus a bump ``17.5 sin(pi t)^2`` deg
  (peak 29.5 deg, inside the 35 deg limit); both primitives are then asked for the goal 33 deg.
- steep change ("improper acceleration"): a logistic step ``52 / (1 + exp(-60 (t - 0.5)))`` deg
  shifted to start at 0 (inside the 55 deg limit), reproduced as demonstrated.

Both primitives use the same constants (alpha_y = 25, beta_y = 6.25, alpha_s = 4, 10 kernels);
the CDMP limits are [-10, 35] deg and [-10, 55] deg. Maxima are taken over 1.5 tau.
"""
import os

import numpy as np

from cdmp_ros.core.dmp.dmp import CDMP, DMP, DmpConfig
from cdmp_ros.experiments.results import row, write_results

NAME = 'toy'
HELP = 'paper 000 IV-A: DMP vs CDMP under goal adaptation and a steep change (Fig. 3)'

GOAL_LIMIT_DEG = 35.0
STEEP_LIMIT_DEG = 55.0
PAPER = {'goal_dmp': 48.5, 'goal_cdmp': 34.4, 'steep_dmp': 58.9, 'steep_cdmp': 52.8}


def add_arguments(parser):
    parser.add_argument('--out', required=True, help='output directory')
    parser.add_argument('--no-plot', action='store_true', help='skip the PNG figure')


def demonstrations():
    """The two demonstrations: ``T`` (n,), goal-adaptation ``Y`` and steep ``Y`` in degrees."""
    T = np.linspace(0.0, 1.0, 501)
    mj = 10 * T ** 3 - 15 * T ** 4 + 6 * T ** 5
    y_goal = 20.0 * mj + 17.5 * np.sin(np.pi * T) ** 2
    steep = 52.0 / (1.0 + np.exp(-60.0 * (T - 0.5)))
    return T, y_goal, steep - steep[0]


def _rms_deg(prim, T, Y_rad):
    tr = prim.rollout(dt=float(T[1] - T[0]))
    return float(np.rad2deg(np.sqrt(np.mean((tr.Y[:, 0] - Y_rad) ** 2))))


def _case(key, prefix, T, y_deg, limit_deg, cfg, lo, **rollout):
    """Fit a DMP and a CDMP (limits ``[lo, limit_deg]``) to the demonstration ``y_deg``
    [deg] and roll both out over 1.5 s with ``rollout`` (e.g. a new goal); returns the rows
    named ``prefix.*`` (paper values ``PAPER[key_dmp]``, ``PAPER[key_cdmp]``) and the
    curves to plot."""
    Y = np.deg2rad(y_deg)[:, None]
    dmp = DMP(1, cfg).fit(T, Y)
    cdmp = CDMP([lo], [np.deg2rad(limit_deg)], cfg).fit(T, Y)
    a = dmp.rollout(dt=0.002, duration=1.5, **rollout)
    b = cdmp.rollout(dt=0.002, duration=1.5, **rollout)
    curve = (T, y_deg, a.T, np.rad2deg(a.Y[:, 0]), np.rad2deg(b.Y[:, 0]), limit_deg)
    rows = [
        row(f'{prefix}.limit_deg', limit_deg, limit_deg, 'deg'),
        row(f'{prefix}.dmp_max_deg', float(np.rad2deg(a.Y.max())), PAPER[f'{key}_dmp'],
            'deg'),
        row(f'{prefix}.cdmp_max_deg', float(np.rad2deg(b.Y.max())), PAPER[f'{key}_cdmp'],
            'deg'),
        row(f'{prefix}.rms_error_deg', _rms_deg(cdmp, T, Y[:, 0]), None, 'deg'),
        row(f'{prefix}.dmp_rms_error_deg', _rms_deg(dmp, T, Y[:, 0]), None, 'deg'),
    ]
    return rows, curve


def compute():
    """Run both cases; returns (rows, curves for plotting)."""
    T, y_goal, y_steep = demonstrations()
    cfg = DmpConfig(n_weights_per_dim=10)
    lo = np.deg2rad(-10.0)
    # goal adaptation
    goal_rows, goal_curve = _case('goal', 'goal_adaptation', T, y_goal, GOAL_LIMIT_DEG, cfg,
                                  lo, goal_y=[np.deg2rad(33.0)])
    # steep change
    steep_rows, steep_curve = _case('steep', 'steep_change', T, y_steep, STEEP_LIMIT_DEG, cfg,
                                    lo)
    return goal_rows + steep_rows, {'goal': goal_curve, 'steep': steep_curve}


def plot(curves, path):
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    titles = {'goal': '(a) goal adaptation to 33 deg', 'steep': '(b) steep change'}
    for ax, key in zip(axes, ('goal', 'steep')):
        T, demo, Tr, ydmp, ycdmp, limit = curves[key]
        ax.plot(T, demo, 'k--', label='demonstration')
        ax.plot(Tr, ydmp, 'tab:red', label='DMP')
        ax.plot(Tr, ycdmp, 'tab:blue', label='CDMP')
        ax.axhline(limit, color='gray', ls=':', label=f'limit {limit:g} deg')
        ax.set_title(titles[key])
        ax.set_xlabel('t [s]')
        ax.set_ylabel('joint angle [deg]')
        ax.legend(loc='lower right', fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def run(args):
    rows, curves = compute()
    os.makedirs(args.out, exist_ok=True)
    notes = [__doc__.split('\n\n', 1)[1].strip()]
    if not args.no_plot:
        plot(curves, os.path.join(args.out, 'toy.png'))
        notes.append('![toy](toy.png)')
    md = write_results(args.out, 'paper 000 IV-A toy examples', rows, notes)
    print(md)
    return 0
