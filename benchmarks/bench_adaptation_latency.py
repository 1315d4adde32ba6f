"""Obstacle message -> first joint_reference computed from the adapted ProMP, across processes.

Issue 13 item 1. Starts the adapter (``config/adapter.yaml``) and the streamer
(``config/streamer.yaml``) as two processes; this process is the user and the robot: it
publishes the 7-DoF Panda ProMP of bench_adapter on ``primitive``, ``joint_states`` at
``--js-rate`` (50 Hz; the sim publishes 250 Hz), then ``--n`` obstacle events, one at a time: a
MarkerArray of ``--spheres`` spheres (default 3, radius 5-10 cm; near the prior mean
end-effector path, the last near the elbow path, as panda_problem), each event placing every
sphere N(0, 2 cm) around its place, so the adapter re-solves the problem with limits and the
spheres on the end effector and panda_link4, conditioned on the current joint_states.
``--robot start`` (default): before each event the joint_states move to that event's start
state, and spheres and start states are exactly the events of ``bench_adaptation_solve.py``
(same ``--seed``): the problems do not depend on what earlier events did, and the in-process
figures of that benchmark are this one's solve part. ``--robot echo``: the joint_states echo
the last ``joint_reference`` (a perfect robot; the measurements before 2026-11-24 14:00 UTC),
so each event starts where the earlier adaptations led and two code versions see different
problems.

``--motion track``: instead of re-placing the spheres, every event moves each sphere by
``--speed / --rate`` (default 0.2 m/s at 30 Hz: 6.7 mm) along a horizontal line through its
place, as an obstacle tracker reports a moving obstacle; events follow each other after
``1 / --rate`` s (the adapter's refinement of a warm solve then mostly gives way to the next
event). The adapter starts these solves warm (``adaptation.warm_start``; compare with
``--param adaptation.warm_start:=false``). The start of every published solve (warm / cold,
diagnostics key ``start``) is printed.

For each event it records the latency from the obstacle stamp (= publish time, same host
clock) to the stamp of the first ``joint_reference`` computed from the adaptation it caused.
After the change of issue 13 the streamer reports that stamp on ``/diagnostics``
(``adapted_reference_stamp_ns`` with ``adapted_trigger_stamp_ns`` = the obstacle stamp); the
benchmark checks it received a ``joint_reference`` with that stamp and also gives the time at
which it received it. ``--before`` measures code without those keys (``--code DIR``: a tree
of an older commit): the switch is then read from the streamer's log line
``adapted_primitive: switched in`` (its ROS-time log stamp; the first reference of the new
primitive is computed in the same tick). The adapter's ``solve_time_ms`` / ``solve_cpu_ms``
(CPU time of its solver thread: the solve on an idle core), its evaluations of the
Lagrangian, the time of its sampled verification, its ``latency_ms`` (from the obstacle
callback to the publication: the solve, the wait before it and the message), the KL of the
solve answering the event and the load average are printed beside every event. An event that
was not adapted and streamed within ``--timeout`` counts as an infinite latency in the
percentiles and in the share within 100 ms. After the events it prints the CPU used over
them, in cores, by this process, the adapter and the streamer (this process should leave the
CPU to the nodes), and the KL of the solves answering the events.

Every process runs with ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST and a private domain id.
Bounded: start-up + n * (at most --timeout) seconds.

    .venv/bin/python benchmarks/bench_adaptation_latency.py [--n 25] [--seed 0] [--domain 133]
        [--robot start|echo] [--motion replace|track] [--speed 0.2] [--rate 30]
        [--code DIR --before] [--param adaptation.n_steps:=30 ...]
"""
import argparse
import os
import re
import signal
import subprocess
import sys
import threading
import time

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)
sys.path.insert(0, os.path.join(REPO, 'benchmarks'))
os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')

import numpy as np  # noqa: E402

from bench_adapter import User, child_env, panda_prior  # noqa: E402

SWITCH_LINE = re.compile(r'\[INFO\] \[(\d+)\.(\d+)\] \[streamer\]: adapted_primitive: switched in')


class Robot(User):
    """bench_adapter's user plus a joint_reference listener that echoes it as joint_states.

    The references (500 Hz) are taken by a thread every 10 ms, outside the executor: served
    by the executor, they took about half a core of this process, which competed with the
    nodes being measured. They are decoded by the bag's CDR reader, without rclpy."""

    def __init__(self, domain, js_rate=50.0):
        super().__init__(domain, js_rate)
        import copy
        from sensor_msgs.msg import JointState
        from cdmp_ros.ros import qos
        from cdmp_ros.ros.recorder_take import ThreadTakenGroup, never_called
        self.refs = {}  # stamp ns -> receive time.monotonic()
        self.echo = True  # joint_states echo the references (--robot echo)
        profile = copy.copy(qos.REFERENCE)
        profile.depth = 200  # 0.4 s of references between two takes at least
        self._ref_sub = self.node.create_subscription(
            JointState, 'joint_reference', never_called, profile,
            callback_group=ThreadTakenGroup(), raw=True)
        self._ref_thread = threading.Thread(target=self._take_refs, daemon=True)
        self._ref_thread.start()

    def _take_refs(self):
        from cdmp_ros.bag.cdr import decode_joint_state
        from cdmp_ros.ros.recorder_take import drain_subscription, to_monotonic
        taken = []

        def keep(topic, data, received_ns, publish_ns):
            taken.append((decode_joint_state(data), to_monotonic(received_ns)))
        while not self.stop.wait(0.01):
            drain_subscription('joint_reference', self._ref_sub, keep)
            if not taken:
                continue
            with self.changed:
                for ref, received in taken:
                    self.refs[ref.stamp_ns] = received
                if self.echo:
                    self.q = np.array(taken[-1][0].position)
                self.changed.notify_all()
            taken.clear()

    def close(self):
        self.stop.set()
        self._ref_thread.join(5)
        super().close()

    def streamer_state(self, since):
        with self.lock:
            return [kv for t, kv in self.states if t >= since and 'adapted_generation' in kv]

    def sphere_markers(self, centres, radii, stamp):
        from visualization_msgs.msg import MarkerArray
        ms = []
        for i, (c, r) in enumerate(zip(centres, radii)):
            m = self.sphere(c, r, stamp).markers[0]
            m.id = i + 1
            ms.append(m)
        return MarkerArray(markers=ms)


def cpu_seconds(procs):
    """(monotonic time, CPU seconds of this process, of each child in ``procs``): user +
    system time, children's from /proc (the measuring process should leave the CPU to them)."""
    tick = os.sysconf('SC_CLK_TCK')
    out = [time.monotonic(), sum(os.times()[:2])]
    for p in procs:
        try:
            with open(f'/proc/{p.pid}/stat') as f:
                fields = f.read().rsplit(')', 1)[1].split()
            out.append((int(fields[11]) + int(fields[12])) / tick)
        except (OSError, IndexError, ValueError):
            out.append(float('nan'))
    return out


def start(code, module, params_file, params, domain, log):
    cmd = [sys.executable, '-m', module, '--ros-args', '--params-file',
           os.path.join(code, 'config', params_file)]
    for p in params:
        cmd += ['-p', p]
    env = child_env(domain)
    env['PYTHONPATH'] = code
    return subprocess.Popen(cmd, env=env, cwd=code, stdout=log, stderr=subprocess.STDOUT,
                            start_new_session=True)


def stop(proc):
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(5)


def log_switches(path):
    """ROS-time stamps [ns] of the streamer's 'adapted_primitive: switched in' log lines."""
    try:
        text = open(path).read()
    except OSError:
        return []
    return [int(a) * 1_000_000_000 + int(b.ljust(9, '0')[:9])
            for a, b in SWITCH_LINE.findall(text)]


def run(args):
    from std_msgs.msg import String
    from cdmp_ros.core.adaptation.requests import ee_path
    from cdmp_ros.core.kinematics import PointOfInterest
    from cdmp_ros.core.primitive_io import dumps_primitive
    rng = np.random.default_rng(args.seed)
    prior, chain = panda_prior(rng)
    code = os.path.abspath(args.code)
    logdir = args.logdir or '/tmp'
    alog_path = os.path.join(logdir, f'bench_adaptlat_adapter_{os.getpid()}.log')
    slog_path = os.path.join(logdir, f'bench_adaptlat_streamer_{os.getpid()}.log')
    alog, slog = open(alog_path, 'w'), open(slog_path, 'w')
    procs = [start(code, 'cdmp_ros.nodes.adapter', 'adapter.yaml', args.param, args.domain,
                   alog),
             start(code, 'cdmp_ros.nodes.streamer', 'streamer.yaml',
                   ['diagnostics_period:=0.1'] + args.streamer_param, args.domain, slog)]
    user = Robot(args.domain, args.js_rate)
    rows = []
    try:
        user.q = prior.mean([0.0])[0]
        user.pub_prim.publish(String(data=dumps_primitive(prior)))

        def first_solve():  # of this run's primitive (not a latched one of an earlier run)
            with user.lock:
                return (any(m.get('trigger') == 'primitive' for _, m in user.adapted)
                        or any(kv.get('trigger') == 'primitive' and 'solve_cpu_ms' in kv
                               for _, kv in user.states))
        if not user.wait(first_solve, 90.0):
            raise SystemExit(f'no adaptation of the primitive within 90 s; see {alog_path}')
        if not user.wait(lambda: user.refs, 60.0):
            raise SystemExit(f'no joint_reference within 60 s; see {slog_path}')

        def streamer_heard_adapter():  # the latched adaptation of the primitive reached it
            with user.lock:
                return any(kv.get('adapted_generation', 'none') != 'none' or any(
                    int(kv.get(k, 0)) for k in ('adapted_held', 'adapted_ignored_stale',
                                                'adapted_ignored_old'))
                    for _, kv in user.states if 'adapted_generation' in kv)
        # DDS discovery between the adapter and the streamer can take a second after start-up:
        # an event before it would time the discovery (in 4 of about 40 runs the first event's
        # adaptation reached the streamer 0.4-0.8 s after it was published)
        t_heard = time.monotonic()
        if not user.wait(streamer_heard_adapter, 60.0):
            raise SystemExit(f'the streamer received no adapted_primitive within 60 s; see '
                             f'{slog_path}')
        print(f"the streamer received the adapter's first adaptation "
              f'{time.monotonic() - t_heard:.2f} s after the first joint_reference')
        # three spheres: two near the end-effector path, one near the elbow path
        elbow = PointOfInterest('panda_link4')
        centres, radii = [], []
        for k in range(args.spheres):
            s = rng.uniform(0.3, 0.7)
            q = prior.mean([s])
            x = (ee_path(chain, q)[0] if k < args.spheres - 1 or args.spheres == 1
                 else chain.forward(q, [elbow])[0, 0])
            centres.append(x + rng.normal(0.0, 0.04, 3))
            radii.append(rng.uniform(0.05, 0.1))
        base = np.array(centres)
        if args.robot == 'start':  # the event set of bench_adaptation_solve (same seed)
            from bench_adaptation_solve import events
            _, reqs = events(args.n, args.seed, args.spheres)
            user.echo = False
        if args.motion == 'track':  # every sphere crosses its place on a horizontal line
            step = args.speed / args.rate
            heading = rng.uniform(0.0, 2 * np.pi, len(base))
            direction = np.stack([np.cos(heading), np.sin(heading), 0 * heading], axis=1)
            track0 = (np.array([ob.center for ob in reqs[0].obstacles])
                      if args.robot == 'start' else base) - direction * step * args.n / 2
        cpu0 = cpu_seconds(procs)
        for k in range(args.n):
            centres = base + rng.normal(0.0, 0.02, base.shape)  # moved around its place
            if args.motion == 'track':
                centres = track0 + direction * step * k
                if args.robot == 'start':
                    radii = [ob.radius for ob in reqs[0].obstacles]
            elif args.robot == 'start':
                centres = np.array([ob.center for ob in reqs[k].obstacles])
                radii = [ob.radius for ob in reqs[k].obstacles]
                with user.lock:
                    user.q = np.array(reqs[k].start_y)
                time.sleep(args.gap)  # joint_states carry the new start to the adapter
            with user.lock:
                n_a, n_s = len(user.adapted), len(user.states)
            n_sw = len(log_switches(slog_path))
            load = os.getloadavg()[0]
            stamp = user.node.get_clock().now()
            stamp_ns = stamp.nanoseconds
            t0 = time.monotonic()
            user.pub_obs.publish(user.sphere_markers(centres, radii, stamp.to_msg()))

            def adapted():
                with user.lock:
                    for t, meta in user.adapted[n_a:]:
                        if meta.get('trigger_stamp_ns') == stamp_ns:
                            return meta
                    for t, kv in user.states[n_s:]:
                        if kv.get('outcome') in ('infeasible', 'unconverged', 'rejected') \
                                and kv.get('trigger') == 'obstacles' and 'adapted_generation' \
                                not in kv:
                            return {'outcome': kv['outcome']}
                return None
            meta = user.wait(adapted, args.timeout)
            outcome = (meta or {}).get('outcome', 'timeout')
            row = {'k': k + 1, 'outcome': outcome, 'load': load}
            if meta and outcome == 'converged':
                if args.before:
                    sw = user.wait(lambda: log_switches(slog_path)[n_sw:], args.timeout)
                    if sw:
                        row['latency_ms'] = (sw[0] - stamp_ns) * 1e-6
                else:
                    def first_ref():
                        with user.lock:
                            for t, kv in user.states[n_s:]:
                                if kv.get('adapted_trigger_stamp_ns') == str(stamp_ns):
                                    ref = int(kv['adapted_reference_stamp_ns'])
                                    if ref in user.refs:
                                        return ref, user.refs[ref]
                                    if time.monotonic() - t > 2.0:  # reported, not received
                                        return ref, None
                        return None
                    got = user.wait(first_ref, args.timeout)
                    if got and got[1] is None:
                        row['outcome'] = 'reference not received'
                        row['unverified_ms'] = (got[0] - stamp_ns) * 1e-6
                    elif got:
                        row['latency_ms'] = (got[0] - stamp_ns) * 1e-6
                        row['received_ms'] = (got[1] - t0) * 1e3

                def solve():  # the adapter's diagnostics of the request that was published
                    with user.lock:
                        for _, kv in user.states[n_s:]:
                            if kv.get('request_id') == str(meta.get('request_id')) \
                                    and 'solve_cpu_ms' in kv:
                                return (float(kv['solve_time_ms']), float(kv['solve_cpu_ms']),
                                        kv.get('start', '-'), float(kv.get('kl', 'nan')),
                                        float(kv.get('latency_ms', 'nan')),
                                        kv.get('evaluations', '-'),
                                        float(kv.get('verification.time_ms', 'nan')))
                    return None
                (row['solve_ms'], row['solve_cpu_ms'], row['start'], row['kl'],
                 row['adapter_ms'], row['evaluations'], row['verification_ms']) = (
                    user.wait(solve, 5.0)
                    or (None, None, '-', float('nan'), float('nan'), '-', float('nan')))
            rows.append(row)
            print(f'event {k + 1}: {row["outcome"]} ({row.get("start", "-")} start), latency '
                  f'{row.get("latency_ms", float("nan")):.0f} ms (received '
                  f'{row.get("received_ms", float("nan")):.0f} ms), solve '
                  f'{row.get("solve_ms")} ms (CPU {row.get("solve_cpu_ms")} ms; '
                  f'{row.get("evaluations", "-")} evaluations; verification '
                  f'{row.get("verification_ms", float("nan")):.0f} ms; callback to publish '
                  f'{row.get("adapter_ms", float("nan")):.0f} ms), KL '
                  f'{row.get("kl", float("nan")):.4g}, load {load:.1f}', file=sys.stderr,
                  flush=True)
            time.sleep(args.gap)
        cpu1 = cpu_seconds(procs)
        wall = cpu1[0] - cpu0[0]
        with user.lock:
            last = next((kv for _, kv in reversed(user.states) if 'starts_warm' in kv), {})
        print('adapter: ' + ', '.join(f'{k} {v}' for k, v in sorted(last.items())
                                      if k.startswith(('starts_', 'refinements_'))))
        print('CPU over the events, in cores (of ' + str(os.cpu_count()) + '): ' + ', '.join(
            f'{name} {(b - a) / wall:.2f}' for name, a, b in zip(
                ('this process', 'adapter', 'streamer'), cpu0[1:], cpu1[1:])))
    finally:
        user.close()
        for p in procs:
            stop(p)
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--n', type=int, default=25, help='obstacle events (one at a time)')
    ap.add_argument('--seed', type=int, default=0)
    ap.add_argument('--domain', type=int, default=int(os.environ.get('ROS_DOMAIN_ID', 133)))
    ap.add_argument('--timeout', type=float, default=15.0, help='s to wait per event')
    ap.add_argument('--spheres', type=int, default=3,
                    help='spheres per event (the last near the elbow path when > 1)')
    ap.add_argument('--gap', type=float, default=None,
                    help='s between events (default 0.5; --motion track: 1 / --rate)')
    ap.add_argument('--motion', choices=('replace', 'track'), default='replace',
                    help='"replace" (default): every event re-places every sphere N(0, 2 cm) '
                         'around its place; "track": every sphere moves --speed / --rate '
                         'per event along a horizontal line through its place, as a tracker '
                         'at --rate would report it (the adapter starts warm)')
    ap.add_argument('--speed', type=float, default=0.2, help='m/s of --motion track')
    ap.add_argument('--rate', type=float, default=30.0, help='Hz of --motion track')
    ap.add_argument('--js-rate', type=float, default=50.0,
                    help='Hz of the joint_states this process publishes (default 50; the sim '
                         'publishes 250)')
    ap.add_argument('--robot', choices=('echo', 'start'), default='start',
                    help='joint_states: "start" (default) holds the robot at the start state '
                         'of each event of bench_adaptation_solve (prior mean at a phase in '
                         '[0, 0.1]; the same problems whatever earlier events did, so runs of '
                         'two code versions compare); "echo" echoes the references (a perfect '
                         'robot; each event then starts where the previous adaptations led)')
    ap.add_argument('--code', default=REPO, help='tree the nodes run from (default: this one)')
    ap.add_argument('--before', action='store_true',
                    help='code without the adaptation diagnostics: read the streamer log')
    ap.add_argument('--param', action='append', default=[],
                    help='adapter parameter name:=value (repeatable)')
    ap.add_argument('--streamer-param', action='append', default=[],
                    help='streamer parameter name:=value (repeatable)')
    ap.add_argument('--logdir', default='', help='directory of the node logs (default /tmp)')
    args = ap.parse_args()
    if args.gap is None:
        args.gap = 1.0 / args.rate if args.motion == 'track' else 0.5
    print(f'machine: {os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f}; code '
          f'{args.code}{" (before)" if args.before else ""}; adapter: config/adapter.yaml '
          f'{" ".join(args.param)}')
    rows = run(args)
    # an event that was not adapted and streamed counts as an infinite latency: the
    # percentiles and the share within 100 ms are over all events
    lat = np.array([r.get('latency_ms', np.inf) for r in rows])
    streamed = int(np.isfinite(lat).sum())
    cpu = np.array([r['solve_cpu_ms'] for r in rows if r.get('solve_cpu_ms') is not None])
    wall = np.array([r['solve_ms'] for r in rows if r.get('solve_ms') is not None])
    over = np.array([r['latency_ms'] - r['solve_ms'] for r in rows
                     if 'latency_ms' in r and r.get('solve_ms') is not None])
    loads = [r['load'] for r in rows]
    starts = {k: sum(r.get('start') == k for r in rows) for k in ('warm', 'cold')}

    def pct(a, q):
        if not a.size:
            return '-'
        if np.isinf(a).any():   # the higher of the two neighbours (linear would give nan)
            v = np.sort(a)[int(np.ceil(q / 100.0 * (a.size - 1)))]
            return f'{v:.0f}' if np.isfinite(v) else 'inf'
        return f'{np.percentile(a, q):.0f}'
    print()
    print('| events | adapted and streamed | latency p50 / p95 / max [ms] | <= 100 ms | '
          'solve wall p50 [ms] | solve CPU p50 / p95 [ms] | latency - solve wall p50 / p95 '
          '[ms] | load average |')
    print('|---|---|---|---|---|---|---|---|')
    within = f'{np.mean(lat <= 100.0) * 100:.0f} %' if lat.size else '-'
    print(f'| {len(rows)} | {streamed} | {pct(lat, 50)} / {pct(lat, 95)} / {pct(lat, 100)} | '
          f'{within} | {pct(wall, 50)} | {pct(cpu, 50)} / {pct(cpu, 95)} | '
          f'{pct(over, 50)} / {pct(over, 95)} | {min(loads):.1f}-{max(loads):.1f} |')
    print(f'starts of the published solves: {starts["warm"]} warm, {starts["cold"]} cold')
    kls = np.array([r['kl'] for r in rows if np.isfinite(r.get('kl', np.nan))])
    if kls.size:
        print(f'KL of the solves answering the events: p50 {np.median(kls):.4g}, mean '
              f'{kls.mean():.4g}, max {kls.max():.4g} (refinements published later not '
              f'included)')


if __name__ == '__main__':
    main()
