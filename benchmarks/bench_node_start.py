"""Node start benchmark: how long a node process takes from exec to working.

For each node (``--nodes``, default sim, streamer, adapter, learner) and each of ``--runs``
runs, one at a time on an otherwise idle machine: the node is started from its parameter file
(``config/<node>.yaml``) as ``python -m cdmp_ros.nodes.<node>``, and the time from the spawn to
its first ``[INFO]`` log line is taken (every node logs one at the end of its construction:
the streamer its tick thread, the adapter its topics, the sim what it simulates, the learner
its first fit). The node is then stopped with SIGINT. Also measured: the CPU time of importing
the node's module alone (``python -c "import cdmp_ros.ros.<node>_node"``, user + sys of the
child).

The first run of each node starts with an empty cache (``CDMP_ROS_CACHE``, a new temporary
directory; cold), the others reuse it (warm): the streamer's fitted link capsules are
cached there (cdmp_ros.core.cache). Printed: a markdown table per node of the cold run and the
median and largest warm run.

Every ROS process runs with ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST and a private domain id.

    .venv/bin/python benchmarks/bench_node_start.py [--runs 6] [--domain 77]
        [--nodes streamer adapter] [--code DIR]   # DIR: another checkout (before/after)
"""
import argparse
import os
import resource
import shutil
import signal
import subprocess
import sys
import tempfile
import time

import numpy as np

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
NODES = ('sim', 'streamer', 'adapter', 'learner')
START_TIMEOUT = 60.0


def ros_env(domain: int, code: str, cache: str) -> dict:
    e = dict(os.environ)
    e.update(ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST', ROS_DOMAIN_ID=str(domain),
             AMENT_PREFIX_PATH=sys.prefix, PYTHONUNBUFFERED='1', PYTHONPATH=code,
             CDMP_ROS_CACHE=cache, XDG_CACHE_HOME=cache)  # XDG: code older than CDMP_ROS_CACHE
    e.pop('CDMP_ROS_KERNEL_CACHE', None)
    return e


def start_time(node: str, code: str, env: dict, logdir: str, run: int) -> float:
    """Seconds from the spawn of ``node`` to its first [INFO] line; the node is stopped."""
    cmd = [sys.executable, '-m', f'cdmp_ros.nodes.{node}', '--ros-args', '--params-file',
           os.path.join(code, 'config', f'{node}.yaml')]
    log_path = os.path.join(logdir, f'{node}_{run}.log')
    with open(log_path, 'w') as log:
        t0 = time.monotonic()
        proc = subprocess.Popen(cmd, env=env, cwd=code, stdout=log, stderr=subprocess.STDOUT,
                                start_new_session=True)
        try:
            while True:
                with open(log_path) as f:
                    if '[INFO]' in f.read():
                        took = time.monotonic() - t0
                        break
                if proc.poll() is not None:
                    raise SystemExit(f'{node} exited with {proc.returncode}; see {log_path}')
                if time.monotonic() - t0 > START_TIMEOUT:
                    raise SystemExit(f'{node}: no [INFO] line in {START_TIMEOUT} s; '
                                     f'see {log_path}')
                time.sleep(0.005)
        finally:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGINT)
                try:
                    proc.wait(20)
                except subprocess.TimeoutExpired:
                    os.killpg(proc.pid, signal.SIGKILL)
                    proc.wait()
    return took


def import_cpu(node: str, code: str, env: dict) -> float:
    """CPU seconds (user + sys) of a child that only imports the node's module."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    subprocess.run([sys.executable, '-c', f'import cdmp_ros.ros.{node}_node'], env=env,
                   cwd=code, check=True, capture_output=True)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog=__doc__.split('\n\n', 1)[1])
    ap.add_argument('--runs', type=int, default=6, help='starts per node, the first cold')
    ap.add_argument('--domain', type=int, default=77, help='private ROS_DOMAIN_ID')
    ap.add_argument('--nodes', nargs='+', default=list(NODES), choices=NODES)
    ap.add_argument('--code', default=REPO, help='checkout the nodes run from')
    args = ap.parse_args(argv)
    if args.runs < 2:
        ap.error('--runs: at least 2 (one cold, one warm)')
    code = os.path.abspath(args.code)
    logdir = tempfile.mkdtemp(prefix='bench_node_start_')
    print(f'node start (code {code}, domain {args.domain}, {args.runs} runs per node; '
          f'logs in {logdir})\n')
    print('| node | import CPU [s] | cold start [s] | warm start median [s] | warm max [s] |')
    print('|---|---|---|---|---|')
    for node in args.nodes:
        cache = tempfile.mkdtemp(prefix='bench_node_start_cache_')
        try:
            env = ros_env(args.domain, code, cache)
            cpu = import_cpu(node, code, env)
            times = [start_time(node, code, env, logdir, k) for k in range(args.runs)]
        finally:
            shutil.rmtree(cache, True)
        warm = np.array(times[1:])
        print(f'| {node} | {cpu:.2f} | {times[0]:.2f} | {np.median(warm):.2f} | '
              f'{warm.max():.2f} |', flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
