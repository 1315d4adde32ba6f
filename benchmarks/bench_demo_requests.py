"""The obstacle requests of ``cdmp demo --kind promp`` runs, solved again in this process.

``benchmarks/bench_demo_promp.py`` measures the demo end to end, where the machine's load moves
a request's CPU time by up to 2x from batch to batch. This benchmark takes the requests out of
that noise: for each demo output directory given, it reads from the run's bag the learner's
primitive, the sphere of every ``obstacles`` message and which of them the adapter solved (its
diagnostics: ``request_id``, ``trigger`` obstacles), then solves the same sequence as the
adapter did (``run_request`` with one ``WarmStarts`` stream, after one request without
obstacles as the adapter's first; the requests continue the motion, as the demo's do), with the
adapter's default request settings (``AdaptRequestConfig``) and the sampled verification.

Printed: per run, each request as ``evaluations start`` (``w`` warm, ``c`` cold; ``+`` a warm
solve continued where the first ran out, ``*`` a warm solve replaced by a cold one) with the
adapter's evaluations in the demo in brackets; then the solve CPU time per request (p50, p90,
max), the evaluations and the warm-start counts. Run it on two trees to compare code (the
requests are the same).

Run: OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/bench_demo_requests.py \
         /tmp/bench_demo_promp/run* [--repeats 1]
"""
import argparse
import glob
import os
import sys
import time

import numpy as np

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')
REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)

from cdmp_ros.bag.cdr import decode_marker_array  # noqa: E402
from cdmp_ros.bag import BagReader  # noqa: E402
from cdmp_ros.cli.demo_promp import _diagnostic_values, _primitives, _promp  # noqa: E402
from cdmp_ros.core.adaptation.config import AdaptRequestConfig  # noqa: E402
from cdmp_ros.core.adaptation.requests import AdaptRequest, run_request  # noqa: E402
from cdmp_ros.core.adaptation.warm import WarmStarts  # noqa: E402
from cdmp_ros.core.kinematics import Sphere, panda_chain  # noqa: E402
from cdmp_ros.sim.robot_specs import panda_urdf_path  # noqa: E402

SPHERE, ADD = 2, 0   # visualization_msgs/Marker type and action


def demo_requests(out):
    """(prior, [(spheres, evaluations in the demo, start in the demo)]) of the obstacle
    requests the adapter of the demo run in ``out`` solved, in order."""
    bag = os.path.join(out, 'bag')
    if not glob.glob(os.path.join(bag, '*.mcap')):
        raise SystemExit(f'{out}: no bag (an output directory of bench_demo_promp.py?)')
    obstacles = []
    for m in BagReader(bag).messages(['/obstacles']):
        spheres = []
        for mk in decode_marker_array(m.data).markers:
            if mk.action != ADD:
                continue
            if mk.type != SPHERE:
                raise SystemExit(f'{out}: marker type {mk.type}: only spheres are replayed')
            p = mk.pose.position
            spheres.append(Sphere((p.x, p.y, p.z), 0.5 * mk.scale.x))
        obstacles.append(tuple(spheres))
    solved, seen = [], set()
    for v in _diagnostic_values(bag, 'adapter'):
        rid = v.get('request_id')
        if v.get('trigger') != 'obstacles' or 'evaluations' not in v or rid in seen:
            continue
        seen.add(rid)
        # request 1 is the primitive's; request k >= 2 answers the (k - 1)-th obstacles message
        solved.append((obstacles[int(rid) - 2], int(v['evaluations']), v.get('start', '?')))
    prior = _promp(_primitives(bag, '/primitive')[0][1], panda_chain(panda_urdf_path()))
    return prior, solved


def replay(prior, requests, chain, cfg):
    """Solve the stream; per request (evaluations, start label, CPU [s], converged)."""
    warm = WarmStarts()
    run_request(AdaptRequest(prior, (), continues=False), chain, cfg, warm=warm)
    rows = []
    for spheres, _, _ in requests:
        t = time.process_time()
        rep = run_request(AdaptRequest(prior, spheres, continues=True), chain, cfg,
                          warm=warm).report
        cpu = time.process_time() - t
        note = rep.start_note or ''
        label = rep.start[0] + ('+' if 'continued where' in note else '') + \
            ('*' if 'replaced' in note else '')
        rows.append((rep.n_evaluations, label, cpu, rep.converged))
    return rows, warm.counts


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('outs', nargs='+', help='output directories of cdmp demo --kind promp')
    ap.add_argument('--repeats', type=int, default=1,
                    help='solve every stream this many times; CPU: the least per request')
    args = ap.parse_args(argv)
    if args.repeats < 1:
        ap.error('--repeats: expected at least 1')
    chain = panda_chain(panda_urdf_path())
    cfg = AdaptRequestConfig()
    cpu, evals, counts = [], [], {}
    for out in args.outs:
        prior, requests = demo_requests(out)
        best = None
        for _ in range(args.repeats):
            rows, c = replay(prior, requests, chain, cfg)
            best = rows if best is None else [r if r[2] < b[2] else b for r, b in zip(rows, best)]
        for k, v in c.items():
            counts[k] = counts.get(k, 0) + v
        cpu += [r[2] for r in best]
        evals += [r[0] for r in best]
        print(os.path.basename(os.path.normpath(out)), ' '.join(
            f'{n}{label}{"" if ok else "!"} ({dn}{ds[0]})'
            for (n, label, _, ok), (_, dn, ds) in zip(best, requests)), flush=True)
    if not cpu:
        raise SystemExit('no obstacle requests in these runs')
    ms = np.array(cpu) * 1e3
    ev = np.array(evals)
    print(f'{ms.size} requests: solve CPU p50 {np.median(ms):.0f} ms, p90 '
          f'{np.percentile(ms, 90):.0f} ms, max {ms.max():.0f} ms; evaluations p50 '
          f'{np.median(ev):.0f}, p90 {np.percentile(ev, 90):.0f}, max {ev.max()}, sum {ev.sum()}')
    print('starts:', ', '.join(f'{k} {v}' for k, v in counts.items()))


if __name__ == '__main__':
    main()
