"""``cdmp demo --kind promp`` repeated: obstacle -> first adapted reference of every adaptation.

Issue 29 item 2 asks for at most 150 ms for every adaptation of the ProMP demo in 10 runs.
Runs the demo ``--runs`` times (each in its own output directory below ``--out``, on
``--domain``, localhost discovery) and prints, per run, the streamer's figure for every
obstacle message answered (``promp.adaptation_latency_ms`` of its summary.json: the stamp of the
first reference computed from the first adapted primitive answering the message minus the
stamp of the message), the number of adaptations, the sampled per-step violation of the last
one and, from the adapter's diagnostics in the run's bag, the Lagrangian evaluations and the
solve's CPU time of each obstacle-triggered request; then all latencies together: p50, max and
how many are within ``--budget`` ms, and the requests' evaluations and CPU (p50 / max).

Run: ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST .venv/bin/python benchmarks/bench_demo_promp.py \
         --runs 10 --domain 166 --out /tmp/bench_demo_promp
"""
import argparse
import json
import os
import subprocess
import sys
import time

import numpy as np

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)


def obstacle_requests(bag):
    """(evaluations, solve CPU [ms]) of every obstacle-triggered request the adapter solved,
    from its diagnostics in ``bag`` (each request once)."""
    from cdmp_ros.cli.demo_promp import _diagnostic_values
    seen, out = set(), []
    for v in _diagnostic_values(bag, 'adapter'):
        rid = v.get('request_id')
        if v.get('trigger') != 'obstacles' or 'evaluations' not in v or rid in seen:
            continue
        seen.add(rid)
        out.append((int(v['evaluations']), float(v['solve_cpu_ms'])))
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--runs', type=int, default=10)
    ap.add_argument('--domain', type=int, default=166, help='ROS_DOMAIN_ID of the demos')
    ap.add_argument('--out', default='/tmp/bench_demo_promp')
    ap.add_argument('--budget', type=float, default=150.0, help='ms')
    ap.add_argument('--timeout', type=float, default=300.0, help='s per run')
    args = ap.parse_args(argv)
    if args.runs < 1:
        ap.error('--runs: expected at least 1')
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST',
               ROS_DOMAIN_ID=str(args.domain),
               AMENT_PREFIX_PATH=os.environ.get('AMENT_PREFIX_PATH', sys.prefix),
               MPLBACKEND='Agg')
    cdmp = os.path.join(os.path.dirname(sys.executable), 'cdmp')
    everything = []
    print('| run | adaptations | obstacle -> first adapted reference [ms] | adapted per-step '
          'max (2,000 samples) | adapter: evaluations (solve CPU [ms]) per obstacle request | '
          'wall [s] |')
    print('|---|---|---|---|---|---|')
    requests = []
    for i in range(1, args.runs + 1):
        out = os.path.join(args.out, f'run{i}')
        t = time.monotonic()
        r = subprocess.run([cdmp, 'demo', '--kind', 'promp', '--out', out], env=env, cwd=REPO,
                           capture_output=True, text=True, timeout=args.timeout)
        wall = time.monotonic() - t
        if r.returncode != 0:
            print(f'| {i} | demo failed (exit {r.returncode}): '
                  f'{(r.stderr or r.stdout)[-300:]!r} | | | | {wall:.0f} |', flush=True)
            everything.append(float('inf'))
            continue
        p = json.load(open(os.path.join(out, 'summary.json')))['promp']
        lat = [float(v) for v in p['adaptation_latency_ms']]
        everything += lat
        v = p.get('adapted_violation') or {}
        reqs = obstacle_requests(os.path.join(out, 'bag'))
        requests += reqs
        print(f'| {i} | {p["adaptations"]} | {", ".join(f"{x:.0f}" for x in lat)} | '
              f'{v.get("per_step_max", float("nan")):.4f} | '
              f'{", ".join(f"{e} ({c:.0f})" for e, c in reqs)} | {wall:.0f} |', flush=True)
    a = np.asarray(everything)
    print(f'\n{a.size} latencies over {args.runs} runs: p50 {np.median(a):.1f} ms, max '
          f'{a.max():.1f} ms; {int(np.sum(a <= args.budget))} within {args.budget:g} ms')
    if requests:
        e, c = np.asarray(requests).T
        print(f'{e.size} obstacle requests: evaluations p50 {np.median(e):.0f}, max '
              f'{e.max():.0f}; solve CPU p50 {np.median(c):.0f} ms, max {c.max():.0f} ms')


if __name__ == '__main__':
    main()
