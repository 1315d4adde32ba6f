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


def compute():
    """Run both cases; returns (rows, curves for plotting)."""
    T, y_goal, y_steep = demonstrations()
    cfg = DmpConfig(n_weights_per_dim=10)
    lo = np.deg2rad(-10.0)
    rows, curves = [], {}
    # goal adaptation
    Y = np.deg2rad(y_goal)[:, None]
    dmp = DMP(1, cfg).fit(T, Y)
    cdmp = CDMP([lo], [np.deg2rad(GOAL_LIMIT_DEG)], cfg).fit(T, Y)
    new_goal = [np.deg2rad(33.0)]
    a = dmp.rollout(dt=0.002, goal_y=new_goal, duration=1.5)
    b = cdmp.rollout(dt=0.002, goal_y=new_goal, duration=1.5)
    curves['goal'] = (T, y_goal, a.T, np.rad2deg(a.Y[:, 0]), np.rad2deg(b.Y[:, 0]),
                      GOAL_LIMIT_DEG)
    rows += [
        row('goal_adaptation.limit_deg', GOAL_LIMIT_DEG, GOAL_LIMIT_DEG, 'deg'),
        row('goal_adaptation.dmp_max_deg', float(np.rad2deg(a.Y.max())), PAPER['goal_dmp'],
            'deg'),
        row('goal_adaptation.cdmp_max_deg', float(np.rad2deg(b.Y.max())), PAPER['goal_cdmp'],
            'deg'),
        row('goal_adaptation.rms_error_deg', _rms_deg(cdmp, T, Y[:, 0]), None, 'deg'),
        row('goal_adaptation.dmp_rms_error_deg', _rms_deg(dmp, T, Y[:, 0]), None, 'deg'),
    ]
    # steep change
    Y = np.deg2rad(y_steep)[:, None]
    dmp = DMP(1, cfg).fit(T, Y)
    cdmp = CDMP([lo], [np.deg2rad(STEEP_LIMIT_DEG)], cfg).fit(T, Y)
    a = dmp.rollout(dt=0.002, duration=1.5)
    b = cdmp.rollout(dt=0.002, duration=1.5)
    curves['steep'] = (T, y_steep, a.T, np.rad2deg(a.Y[:, 0]), np.rad2deg(b.Y[:, 0]),
                       STEEP_LIMIT_DEG)
    rows += [
        row('steep_change.limit_deg', STEEP_LIMIT_DEG, STEEP_LIMIT_DEG, 'deg'),
        row('steep_change.dmp_max_deg', float(np.rad2deg(a.Y.max())), PAPER['steep_dmp'],
            'deg'),
        row('steep_change.cdmp_max_deg', float(np.rad2deg(b.Y.max())), PAPER['steep_cdmp'],
            'deg'),
        row('steep_change.rms_error_deg', _rms_deg(cdmp, T, Y[:, 0]), None, 'deg'),
        row('steep_change.dmp_rms_error_deg', _rms_deg(dmp, T, Y[:, 0]), None, 'deg'),
    ]
    return rows, curves


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
