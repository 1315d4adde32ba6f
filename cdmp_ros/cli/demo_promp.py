"""The constrained-ProMP part of ``cdmp demo --kind promp`` and ``--kind dual``: what the
adaptations did, read back from the recorded bag and checked by sampling.

In these demos the learner fits a ProMP (paper 003) to the demonstrations; the adapter
adapts it to every obstacle message (repellers on each hand and on the links of
``adaptation.avoid_links``, two-sided joint limits; ``config/adapter.yaml``; of two arms also
``adaptation.arm_clearance`` between them), and the streamer follows the adapted mean. The
robot is a :class:`~cdmp_ros.core.demo_robot.DemoRobot` (one Panda or two). From the bag:

- ``adaptations``: the ``adapted_primitive`` messages published after the drop started;
  ``adapter_current``: whether the last of them answers the last obstacle message (its
  ``metadata.adapter.trigger_stamp_ns``), ``adapter_requests`` and ``adapter_queued`` (requests
  neither solved nor dropped at the end: the latest request wins, none waits in a queue);
- ``adapted_violation``: for the last of them and for the prior, the fraction of 2,000
  trajectories sampled from the distribution (independently of the adapter's own check) in
  which a hand or an avoided link (the points and balls the adapter constrains:
  :func:`~cdmp_ros.core.adaptation.requests.avoided_points`) comes within the adapter's
  ``obstacle_margin`` of the sphere at any of 100 phases (``trajectory``), and the largest such
  fraction at one phase (``per_step_max``), each with a 95 % upper bound (Clopper-Pearson);
- ``arm_violation`` (two arms, ``arm_clearance`` > 0): the same for two of those points of
  different arms closer than ``arm_clearance``, and
  ``min_arm_distance_mean_path_m`` the least such distance along the mean;
- ``adapted_laws``: per probability law, the constraints of the last adaptation that used it
  (its report's ``ConstraintReport.law``: 'gaussian' for the joint limits, under the default
  tail 'gamma, importance-sampled check' for the end effector and the links);
- ``adaptation_latency_ms``: per obstacle message answered, the streamer's own figure (the
  stamp of its first reference computed from the first adapted primitive answering it minus
  the stamp of that message), from its diagnostics in the bag;
- ``promp_paths.png``: the prior's and the last adaptation's mean paths of each hand with
  their 2-sigma bands (linearised through the kinematics Jacobian), and the obstacle.
"""
import json
from typing import Dict, List, Optional, Sequence

import numpy as np
from numpy.typing import NDArray

from cdmp_ros.bag import BagReader
from cdmp_ros.bag.cdr import decode_string
from cdmp_ros.core.adaptation.config import AdaptRequestConfig
from cdmp_ros.core.adaptation.requests import (AvoidedPoint, avoided_points, ee_band,
                                               link_balls)
from cdmp_ros.core.primitive_io import promp_from_dict, validate_primitive_dict
from cdmp_ros.core.topics import DIAGNOSTICS_TOPIC

#: Trajectories sampled per distribution and phases per trajectory in the violation check.
N_SAMPLES = 2000
N_PHASES = 100


def _primitives(bag: str, topic: str) -> List[tuple]:
    """``(log_time_ns, dict)`` of every primitive message on ``topic`` in the bag."""
    out = []
    for m in BagReader(bag).messages([topic]):
        d = json.loads(decode_string(m.data))
        validate_primitive_dict(d)
        out.append((m.log_time, d))
    return out


def upper95(k: int, n: int) -> float:
    """One-sided 95 % Clopper-Pearson upper bound of a binomial proportion k / n."""
    from cdmp_ros.core.adaptation.verification import clopper_pearson_upper
    return float(clopper_pearson_upper(k, n))


def demo_points(robot, links: Sequence[str], geometry: bool = True) -> List[AvoidedPoint]:
    """The points the adapter of the demo graph constrains: each hand, and the links of
    ``links`` as the balls covering their collision geometry in the robot's URDF (``geometry``:
    the adapter's ``link_geometry``) or as their frame origins."""
    balls = None
    if geometry and links:
        from cdmp_ros.core.kinematics.capsules import collision_capsules
        balls = link_balls(collision_capsules(robot.urdf, list(links)))
    return avoided_points(robot.model, links, balls)


def _by_arm(robot, points: Sequence[AvoidedPoint]) -> List[List[AvoidedPoint]]:
    return [[p for p in points if p.arm == k] for k in range(robot.n_arms)]


def _positions(robot, Y, points: Sequence[AvoidedPoint]) -> NDArray:
    """Positions ``(..., P, 3)`` of ``points`` (listed arm by arm) at joint positions ``Y``."""
    return np.concatenate(robot.positions(Y, [[p.poi for p in own]
                                              for own in _by_arm(robot, points)]), axis=-2)


def _rates(inside: NDArray, n_samples: int) -> Dict[str, float]:
    """Trajectory and worst per-step fractions of ``inside (K, n)`` with 95 % bounds."""
    k_traj = int(inside.any(axis=1).sum())
    k_step = int(inside.sum(axis=0).max())
    return {'trajectory': k_traj / n_samples, 'trajectory_upper95': upper95(k_traj, n_samples),
            'per_step_max': k_step / n_samples,
            'per_step_max_upper95': upper95(k_step, n_samples)}


def sphere_violation(promp, robot, points: Sequence[AvoidedPoint], center, radius: float,
                     rng: np.random.Generator, n_samples: int = N_SAMPLES,
                     n_phases: int = N_PHASES) -> Dict[str, float]:
    """Sampled probability that one of ``points`` (:func:`demo_points`) comes within
    ``radius`` of ``center``, plus its own radius (see the module docstring); ``promp`` in the
    robot's joint order. ``min_distance_mean_path_m``: along the mean, the least distance from
    ``center`` to a point's ball."""
    s = np.linspace(0.0, 1.0, n_phases)
    c = np.asarray(center, dtype=float)
    pad = np.array([p.radius for p in points])
    X = _positions(robot, promp.sample_trajectories(s, n_samples, rng), points)  # (K, n, P, 3)
    inside = (np.linalg.norm(X - c, axis=-1) < radius + pad).any(axis=2)          # (K, n)
    mean = _positions(robot, promp.mean(s), points)
    return {'n_samples': n_samples, 'n_phases': n_phases, **_rates(inside, n_samples),
            'min_distance_mean_path_m': float((np.linalg.norm(mean - c, axis=-1)
                                               - pad).min())}


def arm_distances(robot, Y, points: Sequence[AvoidedPoint]) -> NDArray:
    """Least distance between two of ``points`` (:func:`demo_points`) of different arms, less
    their radii (between the balls), at joint positions ``Y (..., n_dofs)``: shape
    ``Y.shape[:-1]``."""
    per_arm = _by_arm(robot, points)
    pad = [np.array([p.radius for p in own]) for own in per_arm]
    X = robot.positions(Y, [[p.poi for p in own] for own in per_arm])
    best = np.full(np.shape(Y)[:-1], np.inf)
    for a in range(len(X)):
        for b in range(a + 1, len(X)):
            d = (np.linalg.norm(X[a][..., :, None, :] - X[b][..., None, :, :], axis=-1)
                 - pad[a][:, None] - pad[b][None, :])
            best = np.minimum(best, d.min(axis=(-2, -1)))
    return best


def arm_violation(promp, robot, points: Sequence[AvoidedPoint], clearance: float,
                  rng: np.random.Generator, n_samples: int = N_SAMPLES,
                  n_phases: int = N_PHASES) -> Dict[str, float]:
    """Sampled probability that two points of different arms come closer than ``clearance``
    (the adapter's ``arm_clearance``; see the module docstring)."""
    s = np.linspace(0.0, 1.0, n_phases)
    inside = arm_distances(robot, promp.sample_trajectories(s, n_samples, rng),
                           points) < clearance
    return {'n_samples': n_samples, 'n_phases': n_phases, **_rates(inside, n_samples),
            'min_arm_distance_mean_path_m': float(arm_distances(robot, promp.mean(s),
                                                                points).min())}


def _diagnostic_values(bag: str, prefix: str) -> List[Dict[str, str]]:
    """Key/values of every recorded diagnostics status whose name starts with ``prefix``."""
    from cdmp_ros.bag.cdr import decode_diagnostic_array
    out = []
    for m in BagReader(bag).messages([DIAGNOSTICS_TOPIC]):
        for st in decode_diagnostic_array(m.data):
            if st['name'].split(':')[0].strip().lstrip('/').startswith(prefix):
                out.append(st['values'])
    return out


def adaptation_latencies(bag: str) -> List[float]:
    """The streamer's obstacle -> first adapted reference latencies [ms], one per timed
    adaptation (its diagnostics carry the last one with the stamp of that first reference,
    ``adapted_reference_stamp_ns``; a second adaptation answering the same obstacle message,
    the adapter's refinement of a warm solve, is switched in but not timed)."""
    seen, out = set(), []
    for values in _diagnostic_values(bag, 'streamer'):
        ref = values.get('adapted_reference_stamp_ns')
        lat = values.get('adaptation_latency_ms_last')
        if ref is None or lat is None or ref in seen:
            continue
        try:
            ms = float(lat)
        except ValueError:
            continue
        if np.isfinite(ms):
            seen.add(ref)
            out.append(ms)
    return out


def promp_summary(bag: str, driver: Dict, robot, adapter_params: Dict,
                  rng: Optional[np.random.Generator] = None) -> Dict:
    """The ProMP figures of the summary (see the module docstring)."""
    rng = rng or np.random.default_rng(0)
    drop = driver.get('events_ns', {}).get('drop_start')
    prior = _primitives(bag, '/primitive')
    adapted = _primitives(bag, '/adapted_primitive')
    after = [d for t, d in adapted if isinstance(drop, int) and t >= drop]
    obs = driver.get('obstacle', {})
    ad = adapter_params.get('adaptation', {})
    defaults = AdaptRequestConfig()
    links = list(ad.get('avoid_links', defaults.avoid_links))
    points = demo_points(robot, links, bool(ad.get('link_geometry', defaults.link_geometry)))
    margin = float(ad.get('obstacle_margin', defaults.obstacle_margin))
    radius = float(obs.get('radius', 0.0)) + margin
    out = {'adaptations': len(after), 'adaptation_latency_ms': adaptation_latencies(bag),
           'violation_radius_m': radius, 'violation_margin_m': margin,
           'violation_points': {p.name: p.radius for p in points},
           'obstacle_messages': int(driver.get('obstacle_messages', 0))}
    # the adapter stays current: its last adaptation answers the last obstacle message
    last_stamp = driver.get('events_ns', {}).get('last_obstacle_stamp')
    if after:
        trigger = (after[-1].get('metadata') or {}).get('adapter', {}).get('trigger_stamp_ns')
        out['last_adaptation_trigger_stamp_ns'] = trigger
        out['adapter_current'] = bool(trigger is not None and trigger == last_stamp)
    # latest request wins, none queued: every request was solved or dropped unsolved, at most
    # one in flight (the adapter's counters in its last diagnostics)
    adapter = {}
    for name, st in driver.get('diagnostics', {}).items():
        if name.split(':')[0].strip().lstrip('/').startswith('adapter') and \
                'requests_received' in st['values']:
            adapter = st['values']
    if adapter:
        counts = {k: int(adapter[k]) for k in ('requests_received', 'requests_solved',
                                               'requests_dropped') if k in adapter}
        out['adapter_requests'] = counts
        out['adapter_queued'] = (counts.get('requests_received', 0)
                                 - counts.get('requests_solved', 0)
                                 - counts.get('requests_dropped', 0))
    if prior and obs.get('center') is not None:
        out['prior_violation'] = sphere_violation(
            _promp(prior[0][1], robot), robot, points, obs['center'], radius, rng)
    # the last adaptation answers the sphere's last position (a crossing sphere moved on)
    last = driver['crossing'][-1] if driver.get('crossing') else obs.get('center')
    if after and last is not None:
        out['adapted_violation'] = sphere_violation(
            _promp(after[-1], robot), robot, points, last, radius, rng)
    clearance = float(ad.get('arm_clearance', 0.0))
    if robot.n_arms > 1 and clearance > 0.0:
        out['arm_clearance_m'] = clearance
        for key, d in (('prior_arm_violation', prior[0][1] if prior else None),
                       ('adapted_arm_violation', after[-1] if after else None)):
            if d is not None:
                out[key] = arm_violation(_promp(d, robot), robot, points, clearance, rng)
    if after:
        out['adapted_laws'] = constraint_laws(after[-1])
    return out


def constraint_laws(d: Dict) -> Dict[str, List[str]]:
    """Per probability law (``ConstraintReport.law``), the constraints of an adapted
    primitive dict whose report used it (its ``metadata.adaptation.constraints``)."""
    out: Dict[str, List[str]] = {}
    for c in ((d.get('metadata') or {}).get('adaptation') or {}).get('constraints') or []:
        if isinstance(c, dict) and 'name' in c:
            out.setdefault(str(c.get('law') or 'not reported'), []).append(str(c['name']))
    return out


def _promp(d: Dict, robot):
    """The ProMP of a primitive dict, in the robot's joint order."""
    from cdmp_ros.core.adaptation.requests import reorder_promp
    p = promp_from_dict(d)
    p.joint_names = list(d['joint_names'])
    return reorder_promp(p, robot.joint_names)


def adapter_parameters(spec) -> Dict:
    """The adapter's parameters in a graph (:meth:`~cdmp_ros.cli.cmd_bringup.NodeSpec.
    effective_parameters`: its files, then its inline parameters)."""
    return spec.effective_parameters()


def plot_promp_paths(path: str, bag: str, driver: Dict, robot) -> None:
    """``promp_paths.png``: prior and adapted mean paths of each hand with 2-sigma bands."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    drop = driver.get('events_ns', {}).get('drop_start')
    prior = _primitives(bag, '/primitive')
    adapted = [d for t, d in _primitives(bag, '/adapted_primitive')
               if isinstance(drop, int) and t >= drop]
    s = np.linspace(0.0, 1.0, 100)
    fig, axes = plt.subplots(1, 3, figsize=(13, 4.2))
    obs = driver.get('obstacle', {})
    for label, d, color in (('prior', prior[0][1] if prior else None, 'tab:blue'),
                            ('adapted (last)', adapted[-1] if adapted else None, 'tab:orange')):
        if d is None:
            continue
        p = _promp(d, robot)
        for arm in range(robot.n_arms):
            X, r = ee_band(p, robot.model, s, arm=arm)
            which = f', hand {arm + 1}' if robot.n_arms > 1 else ''
            for ax, (i, j) in zip(axes, ((0, 1), (0, 2), (1, 2))):
                ax.plot(X[:, i], X[:, j], color=color, ls=('-', '--')[arm % 2],
                        label=f'{label} mean{which}')
                for k in range(0, len(s), 3):
                    ax.add_patch(plt.Circle((X[k, i], X[k, j]), r[k], color=color,
                                            alpha=0.06, lw=0))
    names = 'xyz'
    for ax, (i, j) in zip(axes, ((0, 1), (0, 2), (1, 2))):
        if obs.get('center') is not None:
            c = obs['center']
            ax.add_patch(plt.Circle((c[i], c[j]), obs['radius'], color='r', alpha=0.5,
                                    label='obstacle'))
        ax.set_xlabel(f'{names[i]} [m]')
        ax.set_ylabel(f'{names[j]} [m]')
        ax.set_aspect('equal', adjustable='datalim')
    axes[0].legend(fontsize=7)
    fig.suptitle('mean hand paths with 2-sigma bands (shaded), prior and adapted')
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
