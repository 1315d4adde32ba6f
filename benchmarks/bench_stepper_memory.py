"""Benchmark of the streaming stepper's memory and build time against the primitive's duration.

Issue 31, item 5: the stepper's memory must not grow with the duration. For every duration
(default 1, 30 and 300 s) and streaming period (default 2 ms and 1 ms) a 7-joint CDMP with the
Panda's limits (fitted to a minimum-jerk reach from ``Q_START`` to ``Q_GOAL`` with a wiggle,
stretched to the duration: the same weights, ``tau`` = the duration) is turned into a stepper
as the streamer does (``prim.stepper(dt, velocity_limits=vmax)``), each in a fresh process:

- build time: the first build in the process (which also sizes the forcing grid of the basis,
  once per basis and process, where the stepper has one) and the median of ``--builds`` later
  builds, without tracing;
- memory: the ``tracemalloc`` peak during one build and the size it retains (the stepper
  alive), and the process RSS growth of the first build;
- per-step cost of ``update`` [us]: ``--repeat`` runs of ``--steps`` ticks from the start, the
  median of the runs' means and the p99 of all ticks, with the velocity limits (the streamer's
  path) and without them (the fast path);
- the largest joint difference [rad] of the stepper's positions from the vectorised rollout
  (``prim.rollout``: the forcing evaluated exactly at every step, integrated by the equivalent
  second-order recursion, ``cdmp_ros.core.dmp.recursion``) over the whole movement. Over 1e5
  steps the two recursions' rounding alone differs by up to 1e-8 rad (the same with the
  earlier stepper); the tests compare with the stepper's own scheme run with the exact forcing
  instead (test/test_core_stepper_memory.py).

With ``--reference FILE`` (another version of ``cdmp_ros/core/dmp/stepper.py``, e.g.
``git show <commit>:cdmp_ros/core/dmp/stepper.py > /tmp/old_stepper.py``) the per-step cost of
both versions is also measured interleaved in one process (``--rounds`` alternations; the
medians of the runs' means), which cancels most of the drift of a shared machine.

Run: .venv/bin/python benchmarks/bench_stepper_memory.py [--durations 1 30 300] [--dts ...]
[--reference /tmp/old_stepper.py]
"""
import argparse
import importlib.util
import json
import os
import platform
import subprocess
import sys
import time
import tracemalloc

import numpy as np

from cdmp_ros.core.dmp.dmp import CDMP
from cdmp_ros.core.joint_limits import PANDA_DATASHEET

Q_START = np.array([0.0, -0.5, 0.0, -2.0, 0.0, 1.5, 0.7])
Q_GOAL = np.array([0.8, 0.2, 0.3, -1.2, 0.2, 2.0, 0.3])


def make_cdmp(duration: float) -> CDMP:
    """A 7-joint CDMP (Panda limits) of a minimum-jerk reach with a wiggle, lasting
    ``duration`` seconds (fitted on the normalised time, then stretched)."""
    lower = np.asarray(PANDA_DATASHEET['lower'], dtype=float)
    upper = np.asarray(PANDA_DATASHEET['upper'], dtype=float)
    T = np.linspace(0.0, 1.0, 1001)
    s = 10 * T ** 3 - 15 * T ** 4 + 6 * T ** 5
    Y = Q_START + np.outer(s, Q_GOAL - Q_START)
    Y += 0.1 * np.outer(np.sin(2 * np.pi * T) * np.sin(np.pi * T), np.linspace(1.0, -1.0, 7))
    fitted = CDMP(lower, upper).fit(T, Y)
    return CDMP(lower, upper).set_parameters(fitted.weights_, fitted.start_y_, fitted.goal_y_,
                                             duration)


def rss_bytes() -> int:
    with open('/proc/self/statm') as f:
        return int(f.read().split()[1]) * os.sysconf('SC_PAGE_SIZE')


def step_costs(st, n_steps: int, repeat: int):
    """Median over ``repeat`` runs of the mean per-call latency [us] of ``st.update`` over
    ``n_steps`` ticks from the start, and the p99 of all calls."""
    pc = time.perf_counter_ns
    samples = np.empty((repeat, n_steps))
    inp = st.input
    for r in range(repeat):
        st.reset()
        upd = st.update
        row = samples[r]
        for i in range(n_steps):
            t0 = pc()
            upd(inp)
            row[i] = pc() - t0
    samples /= 1e3
    return float(np.median(samples.mean(axis=1))), float(np.percentile(samples, 99))


def deviation(prim: CDMP, dt: float) -> float:
    """Largest |y_stepper - y_rollout| [rad] over the whole movement (no velocity limits)."""
    tr = prim.rollout(dt=dt)
    st = prim.stepper(dt)
    inp = st.input
    upd = st.update
    Y = np.empty_like(tr.Y)
    Y[0] = st.output.y
    for k in range(1, len(tr.T)):
        Y[k] = upd(inp)[0].y
    return float(np.max(np.abs(Y - tr.Y)))


def measure_one(duration: float, dt: float, builds: int, n_steps: int, repeat: int,
                accuracy: bool) -> dict:
    """All the figures of one (duration, dt), in this process."""
    prim = make_cdmp(duration)
    vmax = np.asarray(PANDA_DATASHEET['velocity'], dtype=float)
    r0 = rss_bytes()
    t0 = time.perf_counter()
    keep = prim.stepper(dt, velocity_limits=vmax)
    first = time.perf_counter() - t0
    rss = rss_bytes() - r0
    times = []
    for _ in range(builds):
        t0 = time.perf_counter()
        prim.stepper(dt, velocity_limits=vmax)
        times.append(time.perf_counter() - t0)
    del keep
    tracemalloc.start()
    base = tracemalloc.get_traced_memory()[0]
    tracemalloc.reset_peak()
    st = prim.stepper(dt, velocity_limits=vmax)
    current, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    limited = step_costs(st, n_steps, repeat)
    fast = step_costs(prim.stepper(dt), n_steps, repeat)
    return {'duration': duration, 'dt': dt, 'first_build_s': first,
            'build_s': float(np.median(times)), 'peak_bytes': peak - base,
            'retained_bytes': current - base, 'rss_bytes': rss,
            'step_limited_mean': limited[0], 'step_limited_p99': limited[1],
            'step_fast_mean': fast[0], 'step_fast_p99': fast[1],
            'deviation_rad': deviation(prim, dt) if accuracy else None}


def load_stepper_module(path: str):
    """The module of another version of the stepper, loaded from its file."""
    spec = importlib.util.spec_from_file_location('reference_stepper', path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def ab_step_costs(reference: str, durations, dts, n_steps: int, rounds: int):
    """Interleaved per-step cost [us] of this version and of ``reference``: rows of
    (duration, dt, path, this mean, reference mean), medians over ``rounds`` runs each."""
    from cdmp_ros.core.dmp.stepper import DmpStepper
    ref = load_stepper_module(reference)
    vmax = np.asarray(PANDA_DATASHEET['velocity'], dtype=float)
    rows = []
    for duration in durations:
        prim = make_cdmp(duration)
        for dt in dts:
            for path, vl in (('vel. limits', vmax), ('no limits', None)):
                steppers = (DmpStepper(prim, dt, velocity_limits=vl),
                            ref.DmpStepper(prim, dt, velocity_limits=vl))
                means = ([], [])
                for _ in range(rounds):
                    for st, out in zip(steppers, means):
                        out.append(step_costs(st, n_steps, 1)[0])
                rows.append((duration, dt, path, float(np.median(means[0])),
                             float(np.median(means[1]))))
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--durations', type=float, nargs='+', default=[1.0, 30.0, 300.0],
                    help='primitive durations tau [s]')
    ap.add_argument('--dts', type=float, nargs='+', default=[0.002, 0.001],
                    help='streaming periods [s]')
    ap.add_argument('--builds', type=int, default=5,
                    help='builds timed per configuration after the first')
    ap.add_argument('--steps', type=int, default=5000, help='ticks per timed run')
    ap.add_argument('--repeat', type=int, default=5, help='timed runs of --steps ticks')
    ap.add_argument('--reference', metavar='FILE',
                    help='another stepper.py: also time both interleaved in one process')
    ap.add_argument('--rounds', type=int, default=15,
                    help='interleaved runs of --steps ticks per version (--reference)')
    ap.add_argument('--no-accuracy', action='store_true',
                    help='skip the difference from prim.rollout')
    ap.add_argument('--one', type=float, nargs=2, metavar=('DURATION', 'DT'),
                    help=argparse.SUPPRESS)  # internal: one configuration, JSON on stdout
    args = ap.parse_args()
    if args.one:
        print(json.dumps(measure_one(args.one[0], args.one[1], args.builds, args.steps,
                                     args.repeat, not args.no_accuracy)))
        return
    rows = []
    for duration in args.durations:
        for dt in args.dts:
            cmd = [sys.executable, os.path.abspath(__file__), '--one', str(duration), str(dt),
                   '--builds', str(args.builds), '--steps', str(args.steps),
                   '--repeat', str(args.repeat)]
            if args.no_accuracy:
                cmd.append('--no-accuracy')
            res = subprocess.run(cmd, check=True, capture_output=True, text=True)
            rows.append(json.loads(res.stdout.strip().splitlines()[-1]))
    print(f'machine: {platform.machine()}, {platform.python_implementation()} '
          f'{platform.python_version()}, numpy {np.__version__}; each row in a fresh process: '
          f'{args.builds} builds after the first, {args.repeat} x {args.steps} ticks')
    print()
    print('| tau [s] | dt [ms] | first build [ms] | build [ms] | tracemalloc peak [MB] | '
          'retained [MB] | RSS growth [MB] | step, vel. limits: mean / p99 [us] | '
          'step, no limits: mean / p99 [us] | max diff. from prim.rollout [rad] |')
    print('|---|---|---|---|---|---|---|---|---|---|')
    mb = 1024.0 ** 2
    for r in rows:
        dev = '-' if r['deviation_rad'] is None else f'{r["deviation_rad"]:.1e}'
        print(f'| {r["duration"]:g} | {r["dt"] * 1e3:g} | {r["first_build_s"] * 1e3:.1f} | '
              f'{r["build_s"] * 1e3:.1f} | {r["peak_bytes"] / mb:.2f} | '
              f'{r["retained_bytes"] / mb:.2f} | {r["rss_bytes"] / mb:.1f} | '
              f'{r["step_limited_mean"]:.2f} / {r["step_limited_p99"]:.2f} | '
              f'{r["step_fast_mean"]:.2f} / {r["step_fast_p99"]:.2f} | {dev} |')
    if args.reference:
        print()
        print(f'Per-step cost interleaved with {args.reference} in one process '
              f'({args.rounds} x {args.steps} ticks each, median of the means):')
        print()
        print('| tau [s] | dt [ms] | path | reference [us] | this version [us] | ratio |')
        print('|---|---|---|---|---|---|')
        for duration, dt, path, mine, theirs in ab_step_costs(
                args.reference, args.durations, args.dts, args.steps, args.rounds):
            print(f'| {duration:g} | {dt * 1e3:g} | {path} | {theirs:.2f} | {mine:.2f} | '
                  f'{mine / theirs:.2f} |')


if __name__ == '__main__':
    main()
