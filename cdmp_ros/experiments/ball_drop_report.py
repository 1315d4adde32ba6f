"""Rows and figures of the ball-drop experiment (paper 000, IV-C; see ``exp_ball_drop``)."""
from typing import List, Optional, Sequence, Tuple

import numpy as np

from cdmp_ros.experiments.results import row


def summarize(trials: Sequence[dict], firsts: Sequence[float], finals: Sequence[dict],
              dmp_viol: Optional[Tuple[int, int]], args, bounded_joint: int,
              bound: Tuple[float, float], n_reuse: int, wall_time: float) -> List[dict]:
    """Result rows side by side with the paper.

    Parameters
    ----------
    trials : list of dict
        Every exploratory trial of every run (``cost``, ``success``, ``limit_usage``,
        ``measured_usage``).
    firsts : sequence of float
        Per run, the 1-based index of the first successful trial (NaN if none).
    finals : list of dict
        Per run, the noiseless evaluation of the learned policy (``success``, ``Y`` (n, 7)).
    dmp_viol : (int, int) or None
        Plain-DMP baseline: rollouts leaving the limits and rollouts in all.
    """
    usage = max(t['limit_usage'] for t in trials)
    viol = sum(t['limit_usage'] >= 1.0 for t in trials)
    jmin = min(float(f['Y'][:, bounded_joint].min()) for f in finals)
    jmax = max(float(f['Y'][:, bounded_joint].max()) for f in finals)
    found = np.isfinite(np.asarray(firsts, dtype=float))
    first = float(np.nanmean(firsts)) if np.any(found) else None
    worst = float(np.nanmax(firsts)) if np.any(found) else None
    rows = [
        row('runs', args.runs, 10, ''),
        row('rollouts_per_update', args.rollouts, 5, ''),
        row('updates_per_run', args.updates, None, ''),
        row('reused_trials_per_update', n_reuse, 0, ''),
        row('first_success_trial', first, 12, 'trial'),
        row('first_success_trial.max', worst, None, 'trial'),
        row('runs_with_a_success', int(np.sum(found)), 10, ''),
        row('final_success_rate', float(np.mean([f['success'] for f in finals])), 1.0, ''),
        row('limit_violations', int(viol), 0, 'rollouts'),
        row('max_limit_usage', float(usage), None, ''),
        row('bounded_joint.min_rad', jmin, -0.25, 'rad'),
        row('bounded_joint.max_rad', jmax, 0.29, 'rad'),
        row('bounded_joint.lower_limit_rad', bound[0], -0.27, 'rad'),
        row('bounded_joint.upper_limit_rad', bound[1], 0.32, 'rad'),
        row('measured_max_limit_usage', float(max(t['measured_usage'] for t in trials)), None,
            ''),
    ]
    if dmp_viol is not None:
        rows.append(row('dmp_baseline.rollouts_leaving_limits', dmp_viol[0], None, 'rollouts'))
        rows.append(row('dmp_baseline.rollouts', dmp_viol[1], None, 'rollouts'))
    rows.append(row('wall_time', float(wall_time), None, 's'))
    return rows


def plot_costs(curves: np.ndarray, n_rollouts: int, path: str) -> None:
    """Fig. 6: mean +- std over runs of the mean cost of each update; curves (runs, updates)."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    x = (np.arange(curves.shape[1]) + 1) * n_rollouts
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.errorbar(x, curves.mean(axis=0), yerr=curves.std(axis=0), capsize=3)
    ax.set_xlabel('trials')
    ax.set_ylabel('cost (mean over rollouts of an update)')
    ax.set_title(f'PI2 on CDMP, {curves.shape[0]} runs (mean +- std)')
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_bounded_joint(finals: Sequence[dict], path: str, bounded_joint: int,
                       bound: Tuple[float, float], horizon: float) -> None:
    """Fig. 5: the bounded joint of every learned policy with its limits."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(6, 4))
    for f in finals:
        Y = f['Y']
        ax.plot(np.arange(len(Y)) * horizon / (len(Y) - 1), Y[:, bounded_joint], lw=1)
    for b in bound:
        ax.axhline(b, color='k', ls=':')
    ax.set_xlabel('t [s]')
    ax.set_ylabel('joint 2 [rad]')
    ax.set_title('bounded joint after learning (limits dotted)')
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
