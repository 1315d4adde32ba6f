"""Our output stage against ruckig, side by side, on the same target streams (issue 28 item 2).

Both follow a target position per tick on the 7 Panda joints (datasheet limits,
:func:`~cdmp_ros.core.joint_limits.panda_limits`) and publish one position per tick:

* ``ours``: :class:`~cdmp_ros.core.streaming.output_stage.OutputStage` (``update(target)``);
* ``ruckig pva``: ``ruckig.Ruckig(7, dt)`` replanned every tick towards the target position
  with the target's own first-order backward differences as target velocity and
  acceleration (clipped to the limits and to ruckig's check of a target state, see
  :func:`clip_target_state`), every joint on its own (``Synchronization.No``);
* ``ruckig pva2 sync``: second-order one-sided differences, ``Synchronization.Time`` and
  ``minimum_duration = dt`` (the plan ends at the next tick when it can: without it ruckig
  reaches the target state early and runs ahead of it; with ``Synchronization.No`` ruckig
  does not apply the minimum duration);
* ``ruckig p``: the target position only (target velocity and acceleration 0),
  ``Synchronization.No``;
* ``ruckig p, raw``: (only on the streams beyond the limits) the target position not clipped,
  and ``min_position`` / ``max_position`` set to the joint limits.

The ruckig variants get the target position clipped into ``[lower + 1e-6, upper - 1e-6]``
(ruckig Community has no position limits of its own: see ``--facts``); ``ours`` gets the
raw target. After each ``update`` the output is passed to the input
(``output.pass_to_input(input)``), as ruckig's online loop does. When ``update`` raises
(``RuckigError``), the tick is retried with zero target velocity and acceleration (holding
the last position instead breaks the acceleration limit a hundredfold).

Streams (start: the Panda's ready pose; ``--seed`` draws the random parts):

* ``a smooth``: a minimum-jerk move of +0.8 rad in 1.5 s on every joint (inside all limits;
  the ideal output is the target itself, no lag);
* ``b spikes``: the same plus coupling-like bursts: per joint 3 bursts of +-500 rad/s^2 for
  20-60 ms at random times, through a critically damped spring (``e'' = u - w^2 e - 2 w e'``,
  ``w`` = 20 rad/s: the target returns to the reach);
* ``c jumps``: the target jumps by 0.3-1.0 rad (random sign, kept 0.2 rad inside the limits)
  every 0.5 s on every joint;
* ``d beyond``: minimum-jerk moves in 2.5 s; joints 2 and 4 to 0.3 rad beyond their upper
  limits, the others +0.8 rad;
* ``d' beyond, jump``: the same goals as one jump at 0.1 s.

Measured per filter and stream, all on the *published* positions (differenced on the tick
grid, from rest at the start; never on a filter's internal state):

* ``us p50`` / ``us p99``: the tick for all 7 joints, ``time.perf_counter`` around the call
  only (ruckig: copying the target into the input, ``update``, ``pass_to_input`` and reading
  ``new_position``; the target's clipping and differences are computed outside, in pure
  Python, their median cost is ``prep us``); the first of ``--repeat`` runs is a warm-up;
* ``lag RMS`` / ``lag max``: ``|published - target|`` over the stream, all joints, the target
  clipped into the limits (what can be reached);
* ``time lag``: (``a`` only) the worst joint's delay of the published position's crossing of
  the move's midpoint behind the target's;
* ``overshoot``: how far the published position goes beyond the hull of the (clipped) target
  since the last jump (``a``, ``b``, ``d``: since the start, so beyond the final value or the
  target's range); after a jump, braking on the side the published position came from is
  not counted;
* ``v/V``, ``a/A``, ``j/J``: the worst ratio of the published positions' 1st, 2nd, 3rd
  backward differences (over ``dt^k``) to the velocity, acceleration, jerk limits;
* ``beyond lim``: the largest excursion of a published position outside ``[lower, upper]``;
* ``spike follow``: (``b`` only) how far the published position follows the spikes (its
  largest deviation from the unperturbed reach over the target's, per joint and direction;
  the median);
* ``err``: ticks on which ruckig raised.

    .venv/bin/python benchmarks/bench_output_stage.py [--dt 0.002 0.001] [--seed 1]
        [--repeat 3] [--facts]

No ROS. ruckig (a development requirement, ``requirements-dev.txt``) is needed for its rows.
"""
import argparse
import math
import os
import sys
import time

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)

import numpy as np  # noqa: E402

from cdmp_ros.core.joint_limits import panda_limits  # noqa: E402
from cdmp_ros.core.streaming.output_stage import OutputStage  # noqa: E402

try:
    import ruckig
except ImportError:  # pragma: no cover - the rows of ours still run
    ruckig = None

LIM = panda_limits()
LOWER, UPPER = LIM.lower, LIM.upper
VEL, ACC, JERK = LIM.velocity, LIM.acceleration, LIM.jerk
VEL_L, ACC_L, JERK_L = VEL.tolist(), ACC.tolist(), JERK.tolist()
#: The Panda's ready pose.
Q0 = np.array([0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785])
MARGIN = 1e-6
N = 7


# -- target streams ------------------------------------------------------------------------
def min_jerk(t, t0, duration):
    """The minimum-jerk blend 0 -> 1 between ``t0`` and ``t0 + duration``."""
    s = np.clip((t - t0) / duration, 0.0, 1.0)
    return s ** 3 * (10.0 - 15.0 * s + 6.0 * s * s)


def stream_smooth(dt):
    t = np.arange(0.0, 2.4, dt)
    r = Q0 + 0.8 * min_jerk(t, 0.1, 1.5)[:, None]
    return r, [0]


def stream_spikes(dt, rng):
    r, breaks = stream_smooth(dt)
    n = len(r)
    w = 20.0
    u = np.zeros_like(r)
    for d in range(N):
        for _ in range(3):
            k0 = int(rng.uniform(0.1, 1.4) / dt)
            length = int(round(rng.uniform(0.020, 0.060) / dt))
            u[k0:k0 + length, d] += 500.0 * rng.choice((-1.0, 1.0))
    e = np.zeros(N)
    de = np.zeros(N)
    pert = np.zeros_like(r)
    for k in range(n):   # semi-implicit Euler of the spring on the tick grid
        de = de + (u[k] - w * w * e - 2.0 * w * de) * dt
        e = e + de * dt
        pert[k] = e
    return r + pert, breaks


def stream_jumps(dt, rng):
    t = np.arange(0.0, 4.1, dt)
    r = np.empty((len(t), N))
    goal = Q0.copy()
    breaks = [0]
    k_next = int(round(0.1 / dt))
    for k in range(len(t)):
        if k == k_next:
            step = rng.uniform(0.3, 1.0, N) * rng.choice((-1.0, 1.0), N)
            new = goal + step
            out = (new < LOWER + 0.2) | (new > UPPER - 0.2)
            new[out] = goal[out] - step[out]
            goal = new
            breaks.append(k)
            k_next += int(round(0.5 / dt))
        r[k] = goal
    return r, breaks


def beyond_goal():
    goal = Q0 + 0.8
    for d in (1, 3):   # joints 2 and 4
        goal[d] = UPPER[d] + 0.3
    return goal


def stream_beyond(dt):
    t = np.arange(0.0, 3.6, dt)
    r = Q0 + (beyond_goal() - Q0) * min_jerk(t, 0.1, 2.5)[:, None]
    return r, [0]


def stream_beyond_jump(dt):
    t = np.arange(0.0, 2.1, dt)
    k = int(round(0.1 / dt))
    r = np.tile(Q0, (len(t), 1))
    r[k:] = beyond_goal()
    return r, [0, k]


def streams(dt, seed):
    rng = np.random.default_rng(seed)
    return [('a smooth', *stream_smooth(dt)), ('b spikes', *stream_spikes(dt, rng)),
            ('c jumps', *stream_jumps(dt, rng)), ('d beyond', *stream_beyond(dt)),
            ("d' beyond, jump", *stream_beyond_jump(dt))]


# -- the filters ---------------------------------------------------------------------------
def run_ours(targets, dt):
    """Published positions (n, 7), per-tick seconds, notes."""
    st = OutputStage(LOWER, UPPER, VEL, ACC, JERK, dt, margin=MARGIN)
    st.reset(Q0.tolist())
    rows = targets.tolist()
    out = np.empty_like(targets)
    times = np.empty(len(rows))
    clock = time.perf_counter
    update = st.update
    for k, tgt in enumerate(rows):
        t0 = clock()
        update(tgt)
        t1 = clock()
        times[k] = t1 - t0
        out[k] = st.p
    return out, times, 0, np.zeros(len(rows))


#: ruckig variants: target differences (0: position only; 1: first-order backward
#: differences; 2: second-order one-sided), synchronization, ``minimum_duration = dt``.
RUCKIG_VARIANTS = {
    'ruckig pva': (1, 'none', False),
    'ruckig pva2 sync': (2, 'time', True),
    'ruckig p': (0, 'none', False),
}


def clip_target_state(v, a, d):
    """Target velocity and acceleration of joint ``d`` that ruckig accepts: ``|v| <= V``,
    ``|a| <= A`` and the velocity the target came from (``v - a|a| / 2J``: the acceleration
    ramped from 0 at the jerk limit) inside ``[-V, V]`` (ruckig's check of a target state)."""
    vmax, amax, jmax = VEL_L[d], ACC_L[d], JERK_L[d]
    v = min(max(v, -vmax), vmax)
    a = min(max(a, -amax), amax)
    a = min(max(a, -math.sqrt(2.0 * jmax * (vmax - v))), math.sqrt(2.0 * jmax * (vmax + v)))
    return v, a


def ruckig_targets(targets, dt, order, clip):
    """Per tick: target position (clipped into the limits if ``clip``), velocity and
    acceleration (the clipped position's differences of ``order``; 0: zero), and the seconds
    this preparation took per tick (pure Python, as a tick would do it)."""
    prep = np.empty(len(targets))
    tp, tv, ta = [], [], []
    clock = time.perf_counter
    lo = (LOWER + MARGIN).tolist()
    hi = (UPPER - MARGIN).tolist()
    h1, h2, h3 = Q0.tolist(), Q0.tolist(), Q0.tolist()   # p_{k-1}, p_{k-2}, p_{k-3}
    inv, inv2 = 1.0 / dt, 1.0 / (dt * dt)
    for k, r in enumerate(targets.tolist()):
        t0 = clock()
        p = [min(max(x, lo[d]), hi[d]) for d, x in enumerate(r)] if clip else r
        if order == 0:
            v = a = [0.0] * N
        else:
            v, a = [0.0] * N, [0.0] * N
            for d in range(N):
                if order == 1:
                    vd = (p[d] - h1[d]) * inv
                    ad = (p[d] - 2.0 * h1[d] + h2[d]) * inv2
                else:
                    vd = (3.0 * p[d] - 4.0 * h1[d] + h2[d]) * 0.5 * inv
                    ad = (2.0 * p[d] - 5.0 * h1[d] + 4.0 * h2[d] - h3[d]) * inv2
                v[d], a[d] = clip_target_state(vd, ad, d)
            h1, h2, h3 = p, h1, h2
        tp.append(p)
        tv.append(v)
        ta.append(a)
        prep[k] = clock() - t0
    return tp, tv, ta, prep


def run_ruckig(targets, dt, variant, clip=True, position_limits=False):
    """Published positions, per-tick seconds, ticks on which ``update`` raised (then retried
    with zero target velocity and acceleration; if that raises too, the last position is
    held), per-tick preparation seconds."""
    order, sync, min_duration = RUCKIG_VARIANTS[variant]
    tp, tv, ta, prep = ruckig_targets(targets, dt, order, clip)
    otg = ruckig.Ruckig(N, dt)
    inp = ruckig.InputParameter(N)
    res = ruckig.OutputParameter(N)
    inp.current_position = Q0.tolist()
    inp.current_velocity = [0.0] * N
    inp.current_acceleration = [0.0] * N
    inp.max_velocity = VEL_L
    inp.max_acceleration = ACC_L
    inp.max_jerk = JERK_L
    inp.synchronization = (ruckig.Synchronization.No if sync == 'none'
                           else ruckig.Synchronization.Time)
    if min_duration:
        inp.minimum_duration = dt
    if position_limits:
        inp.min_position = LOWER.tolist()
        inp.max_position = UPPER.tolist()
    out = np.empty_like(targets)
    times = np.empty(len(targets))
    errors = 0
    last = Q0.tolist()
    zero = [0.0] * N
    clock = time.perf_counter
    update = otg.update
    for k in range(len(targets)):
        a, b, c = tp[k], tv[k], ta[k]
        t0 = clock()
        try:
            inp.target_position = a
            inp.target_velocity = b
            inp.target_acceleration = c
            update(inp, res)
            res.pass_to_input(inp)
            last = res.new_position
        except ruckig.RuckigError:
            errors += 1
            try:   # the position-only target; else hold the last position
                inp.target_velocity = zero
                inp.target_acceleration = zero
                update(inp, res)
                res.pass_to_input(inp)
                last = res.new_position
            except ruckig.RuckigError:
                pass
        t1 = clock()
        times[k] = t1 - t0
        out[k] = last
    return out, times, errors, prep


# -- metrics -------------------------------------------------------------------------------
def metrics(name, pub, targets, breaks, dt, times, prep):
    m = {}
    m['p50'] = float(np.median(times)) * 1e6
    m['p99'] = float(np.percentile(times, 99)) * 1e6
    m['prep'] = float(np.median(prep)) * 1e6
    ref = np.clip(targets, LOWER, UPPER)
    err = pub - ref
    m['rms'] = float(np.sqrt(np.mean(err ** 2))) * 1e3
    m['max'] = float(np.max(np.abs(err))) * 1e3
    m['tlag'] = time_lag(pub, ref, dt) * 1e3 if name.startswith('a') else None
    m['follow'] = spike_following(pub, ref, dt) if name.startswith('b') else None
    m['over'] = overshoot(pub, ref, breaks) * 1e3
    hist = np.vstack([np.tile(Q0, (3, 1)), pub])
    for k, key, lim in ((1, 'v', VEL), (2, 'a', ACC), (3, 'j', JERK)):
        m[key] = float(np.max(np.abs(np.diff(hist, k, axis=0)) / dt ** k / lim))
    m['beyond'] = float(max(0.0, np.max(pub - UPPER), np.max(LOWER - pub))) * 1e3
    return m


def crossing_time(x, level, sign, dt):
    """The first time ``sign * (x - level)`` reaches 0, linearly interpolated [s]."""
    s = sign * (x - level)
    k = int(np.argmax(s >= 0.0))
    if s[k] < 0.0:
        return math.inf
    if k == 0:
        return 0.0
    return (k - 1 + (-s[k - 1]) / (s[k] - s[k - 1])) * dt


def time_lag(pub, ref, dt):
    """The worst joint's delay of the published midpoint crossing behind the target's [s]."""
    worst = -math.inf
    for d in range(N):
        lo, hi = ref[0, d], ref[-1, d]
        sign = 1.0 if hi >= lo else -1.0
        mid = 0.5 * (lo + hi)
        worst = max(worst, crossing_time(pub[:, d], mid, sign, dt)
                    - crossing_time(ref[:, d], mid, sign, dt))
    return worst


def spike_following(pub, ref, dt):
    """How far the published position follows the spikes: per joint and direction, its
    largest deviation from the unperturbed reach over the target's (directions in which the
    target deviates by more than 0.05 rad); the median over those."""
    smooth, _ = stream_smooth(dt)
    ratios = []
    for d in range(N):
        for sign in (-1.0, 1.0):
            den = float(np.max(sign * (ref[:, d] - smooth[:, d])))
            if den > 0.05:
                ratios.append(float(np.max(sign * (pub[:, d] - smooth[:, d]))) / den)
    return float(np.median(ratios)) if ratios else None


def overshoot(pub, ref, breaks):
    """Worst excursion of ``pub`` beyond the hull of the target since the last break (a
    jump); on the side the published position came from at the jump, braking is not
    overshoot (from the start: the target's hull on both sides)."""
    worst = 0.0
    ends = list(breaks[1:]) + [len(ref)]
    for s, e in zip(breaks, ends):
        before = pub[s - 1] if s > 0 else Q0
        hi = np.maximum.accumulate(ref[s:e], axis=0)
        lo = np.minimum.accumulate(ref[s:e], axis=0)
        hi[:, before > ref[s]] = np.inf
        lo[:, before < ref[s]] = -np.inf
        seg = pub[s:e]
        worst = max(worst, float(np.max(seg - hi)), float(np.max(lo - seg)))
    return worst


# -- output --------------------------------------------------------------------------------
def fmt(x, digits=2):
    if x is None:
        return '-'
    return f'{x:.{digits}f}'


HEADER = ('| stream | filter | us p50 | us p99 | prep us | lag RMS [mrad] | lag max [mrad] '
          '| time lag [ms] | spike follow | overshoot [mrad] | v/V | a/A | j/J '
          '| beyond lim [mrad] | err |')


def row(stream, filt, m, errors):
    return (f'| {stream} | {filt} | {fmt(m["p50"], 1)} | {fmt(m["p99"], 1)} | '
            f'{fmt(m["prep"], 1) if m["prep"] > 0 else "-"} | {fmt(m["rms"])} | '
            f'{fmt(m["max"])} | {fmt(m["tlag"])} | {fmt(m["follow"])} | {fmt(m["over"])} | '
            f'{fmt(m["v"], 3)} | {fmt(m["a"], 3)} | {fmt(m["j"], 3)} | {fmt(m["beyond"])} | '
            f'{errors} |')


def measure(fn, repeat):
    """Run ``fn`` ``repeat`` times; the published stream of the last, the times of all but
    the first (warm-up)."""
    runs = [fn() for _ in range(max(repeat, 1))]
    pub, _, errors, _ = runs[-1]
    keep = runs[1:] if len(runs) > 1 else runs
    times = np.concatenate([r[1] for r in keep])
    prep = np.concatenate([r[3] for r in keep])
    return pub, times, errors, prep


def filters_for(name, targets, dt):
    out = [('ours', lambda: run_ours(targets, dt))]
    if ruckig is None:
        return out
    for variant in RUCKIG_VARIANTS:
        out.append((variant, lambda v=variant: run_ruckig(targets, dt, v)))
    if name.startswith('d'):
        out.append(('ruckig p, raw', lambda: run_ruckig(
            targets, dt, 'ruckig p', clip=False, position_limits=True)))
    return out


def table(dt, seed, repeat):
    print(f'\n### dt = {dt * 1e3:g} ms (seed {seed}, {repeat} runs per row, the first a '
          f'warm-up)\n')
    print(HEADER)
    print('|' + '---|' * 15)
    best = {}
    worst = {}
    for name, targets, breaks in streams(dt, seed):
        for filt, fn in filters_for(name, targets, dt):
            pub, times, errors, prep = measure(fn, repeat)
            m = metrics(name, pub, targets, breaks, dt, times, prep)
            print(row(name, filt, m, errors))
            w = worst.setdefault(filt, [0.0, 0.0, 0.0])
            for i, key in enumerate('vaj'):
                w[i] = max(w[i], m[key])
            if filt in RUCKIG_VARIANTS:
                best.setdefault(name, []).append((m['rms'], filt))
    print('\nworst ratios of the published differences to the limits over all streams '
          '(v/V, a/A, j/J): ' + '; '.join(
              f'{f}: ' + ' '.join(f'{x:.15g}' for x in w) for f, w in worst.items()))
    if best:
        print('\nruckig variant with the lowest lag RMS: ' + '; '.join(
            f'{name}: {min(v)[1]}' for name, v in best.items()))


def facts():
    """What ruckig Community does with what it is given (printed, no network)."""
    print(f'ruckig {ruckig.__version__}')
    otg = ruckig.Ruckig(1, 0.001)
    print(f'Ruckig(1, 0.001).max_number_of_waypoints = {otg.max_number_of_waypoints}')
    inp = ruckig.InputParameter(1)
    res = ruckig.OutputParameter(1)
    inp.current_position = [0.0]
    inp.target_position = [2.0]
    inp.max_velocity = [2.0]
    inp.max_acceleration = [10.0]
    inp.max_jerk = [1000.0]
    inp.min_position = [-1.0]
    inp.max_position = [1.0]
    print(f'min_position {inp.min_position}, max_position {inp.max_position}, '
          f'target_position {inp.target_position}: '
          f'validate(False, True) = {inp.validate(False, True)}')
    top = -math.inf
    result = None
    for _ in range(5000):
        result = otg.update(inp, res)
        res.pass_to_input(inp)
        top = max(top, res.new_position[0])
        if result != ruckig.Result.Working:
            break
    print(f'update() until {result}: largest new_position {top:.6f} (max_position 1.0)')
    inp.intermediate_positions = [[0.5]]
    try:
        otg.update(inp, res)
        print('intermediate_positions: accepted')
    except ruckig.RuckigError as exc:
        print(f'intermediate_positions: RuckigError: {str(exc).strip()}')


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--dt', type=float, nargs='+', default=[0.002, 0.001],
                    help='tick periods [s] (default 0.002 0.001)')
    ap.add_argument('--seed', type=int, default=1, help='seed of the random streams')
    ap.add_argument('--repeat', type=int, default=3,
                    help='runs per filter and stream; the first is a warm-up (default 3)')
    ap.add_argument('--facts', action='store_true',
                    help='print what ruckig does with position limits and waypoints')
    args = ap.parse_args(argv)
    if ruckig is None:
        print('ruckig is not installed: only our rows (pip install -r requirements-dev.txt)')
    elif args.facts:
        facts()
    for dt in args.dt:
        table(dt, args.seed, args.repeat)


if __name__ == '__main__':
    main()
