#!/usr/bin/env python3
"""Reproduce "the sim's hung stop" (issue 31 item 3): SIGKILL a peer of the sim, then stop it.

Once, in a CI soak, the sim did not exit within 10 s of SIGINT after the graph test had
SIGKILLed the adapter and restarted it (benchmarks/RESULTS.md, "CI soak, 2026-11-27 (tenth
session)"). Each trial of this script:

1. starts the sim, a streamer and an adapter (and with ``--learner`` the learner, as the
   graph test does) as processes from ``config/<node>.yaml`` (plus ``--param`` overrides), each
   in its own session, stdout+stderr in ``<logdir>/trial<i>_<node>.log``;
2. waits until the sim logs ``ready X s after start`` (it has a publisher on
   ``joint_reference``, i.e. it discovered the streamer), then a random settle time
   (``--settle``);
3. runs the trial's scenario: SIGKILL (of the process group) of the adapter, the streamer, or
   both (or nobody: the baseline); with ``+restart`` the killed node(s) are started again, and
   half of those trials (random) wait until the restarted node logged its first line;
4. waits a random delay in [0, ``--max-delay``] s, then stops: ``stop=sim`` sends SIGINT to
   the sim alone, ``stop=all`` SIGINT to every running node at once (as ``cdmp bringup``
   stops a graph, the sim first);
5. measures the time from that SIGINT to the sim's exit and its exit code (``--watch NODE``:
   that node's instead; ``--watch learner`` for the learner's stop in a graph stop,
   scenario ``none/all``). A sim still running
   after ``--hang-after`` s is a *hang*: it gets SIGUSR1 (the node writes every thread's stack
   to stderr), 2 s, then SIGKILL. The other nodes are then stopped the same way (SIGINT,
   10 s, SIGUSR1, 2 s, SIGKILL).

The node's own stop watchdog (``cdmp_ros/ros/node_main.py``, ``STOP_LIMIT`` 4 s) ends a stuck
node before ``--hang-after`` and writes a ``[node_main] ...`` line and the stacks (or, when
the GIL is held by a thread blocked in C, faulthandler's backstop does: a ``Timeout
(0:00:05)!`` line, the stacks, exit code 1): such a trial is counted in the ``watchdog``
column (the sim's exit code is then 3 if its ``close()`` never started). Every such line of
any node's log is listed at the end.

The rng (``--seed``) draws the scenario order (every scenario in turn, shuffled per round),
the delays and the restart waits, so a run is repeatable up to timing. Trial ``i`` runs on
domain ``--domain + i % --domains`` (the DDS participants of a SIGKILLed process stay known to
its peers for the lease duration, 20 s with Fast DDS: a fresh domain keeps them out of the next
trial). Every process runs with ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST.

``--hogs K`` starts K busy loops (``python -c "while True: pass"``) for the whole run and
kills them on exit. ``--max-minutes`` bounds the run: no trial starts after it.

Printed at the end: a markdown table per scenario (trials, the sim's exit time p50 / p95 / max
after SIGINT, hangs, watchdog lines, exit codes) and the logs of any hang or watchdog line.
Every trial is also one JSON line in ``<logdir>/trials.jsonl``.

Usage::

    .venv/bin/python scripts/repro_sim_stop.py --trials 30 --domain 170 --seed 1
    .venv/bin/python scripts/repro_sim_stop.py --trials 40 --hogs 2 --learner \\
        --param sim:control:=position --param sim:diagnostics_period:=0.25 \\
        --param streamer:rate:=500.0 --param adapter:diagnostics_period:=0.25
    .venv/bin/python scripts/repro_sim_stop.py --scenarios kill-adapter+restart/all
"""
import argparse
import atexit
import collections
import json
import math
import os
import random
import re
import signal
import subprocess
import sys
import tempfile
import time

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
READY_LINE = re.compile(r'\bready (\d+\.\d+) s after start\b')   # core.readiness.READY_LINE
#: a line of the Python stop watchdog, or the header of faulthandler's GIL-free backstop
MARK_LINE = re.compile(r'^(.*\[node_main\].*|Timeout \(\d+:\d\d:\d\d(\.\d+)?\)!)$', re.M)
KILLS = {'none': (), 'kill-adapter': ('adapter',), 'kill-streamer': ('streamer',),
         'kill-both': ('adapter', 'streamer')}
SCENARIOS = tuple(f'{k}{r}/{s}' for k in KILLS for r in (('',) if k == 'none'
                                                         else ('', '+restart'))
                  for s in ('sim', 'all'))
DUMP_WAIT = 2.0      # s between SIGUSR1 and SIGKILL
PEER_STOP = 10.0     # s a peer gets to stop after SIGINT (the graph's stop_timeout)

_hogs = []
_live = []           # every node process started and not yet reaped


#: NODE -> {VAR: VALUE}: extra environment of a node's process (--env)
NODE_ENV = collections.defaultdict(dict)


def ros_env(domain, node=None):
    e = dict(os.environ)
    e.update(NODE_ENV.get('all', {}))
    e.update(NODE_ENV.get(node, {}))
    e['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    e['ROS_DOMAIN_ID'] = str(domain)
    e['AMENT_PREFIX_PATH'] = sys.prefix
    e['PYTHONUNBUFFERED'] = '1'
    e['PYTHONPATH'] = REPO + (os.pathsep + e['PYTHONPATH'] if e.get('PYTHONPATH') else '')
    return e


def node_cmd(name, params):
    cmd = [sys.executable, '-m', f'cdmp_ros.nodes.{name}', '--ros-args', '--params-file',
           os.path.join(REPO, 'config', f'{name}.yaml')]
    for p in params.get(name, ()):
        cmd += ['-p', p]
    return cmd


def start(name, domain, params, log_path):
    log = open(log_path, 'a')
    p = subprocess.Popen(node_cmd(name, params), env=ros_env(domain, name), cwd=REPO, stdout=log,
                         stderr=subprocess.STDOUT, start_new_session=True)
    log.close()
    _live.append(p)
    return p


def signal_group(p, sig):
    try:
        os.killpg(p.pid, sig)
    except ProcessLookupError:
        pass


def note(log_path, text):
    with open(log_path, 'a') as f:
        f.write(f'[repro] [{time.time():.6f}] {text}\n')


def signal_state(pid):
    """The signal masks of every thread of ``pid`` (/proc/<pid>/task/*/status), one line
    each: which of SIGINT (2) / SIGTERM (15) are pending, blocked, ignored or caught."""
    lines = []
    try:
        tids = sorted(os.listdir(f'/proc/{pid}/task'), key=int)
    except OSError:
        return ['(gone)']
    for tid in tids:
        try:
            with open(f'/proc/{pid}/task/{tid}/status') as f:
                st = dict(line.rstrip('\n').split(':\t', 1) for line in f if ':\t' in line)
        except OSError:
            continue
        bits = {}
        for key in ('SigPnd', 'ShdPnd', 'SigBlk', 'SigIgn', 'SigCgt'):
            mask = int(st.get(key, '0'), 16)
            bits[key] = ','.join(str(s) for s in (2, 15) if mask >> (s - 1) & 1) or '-'
        lines.append(f'tid {tid} {st.get("Name", "?")}: ' +
                     ' '.join(f'{k}={v}' for k, v in bits.items()))
    return lines


def read(path):
    try:
        with open(path, errors='replace') as f:
            return f.read()
    except FileNotFoundError:
        return ''


def wait_line(path, pattern, proc, timeout):
    """Poll ``path`` until ``pattern`` matches; False if ``proc`` exits or on timeout."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if pattern.search(read(path)):
            return True
        if proc.poll() is not None:
            return bool(pattern.search(read(path)))
        time.sleep(0.05)
    return False


#: gdb Python run in the same attach as the backtraces: for every thread that waits in
#: pthread_mutex_lock / _clocklock, the mutex and its owner (glibc's ``__owner``, the kernel id
#: of the thread that holds it; also kept for a process-shared mutex in shared memory, such
#: as a Fast DDS shared-memory port's).
GDB_OWNERS = r'''
import gdb
print('mutex waits (pthread_mutex_t.__owner):')
for th in gdb.selected_inferior().threads():
    th.switch()
    f = gdb.newest_frame()
    while f is not None:
        name = f.name() or ''
        if 'pthread_mutex' in name or 'lll_lock_wait' in name:
            try:
                m = f.read_var('mutex')
                owner = int(gdb.parse_and_eval('*(int *)(%d + 8)' % int(m)))
                print('  thread %d (%s) waits for mutex %s held by tid %d'
                      % (th.ptid[1], th.name, hex(int(m)), owner))
                break
            except Exception:
                pass
        f = f.older()
'''


def native_stacks(pid):
    """Every thread's native stack of ``pid`` and the owner of every mutex a thread waits for
    (one ``gdb -batch`` attach; the process is paused meanwhile), with whether each owner
    thread still exists and to which process it belongs."""
    script = os.path.join(tempfile.gettempdir(), f'repro_sim_stop_gdb_{os.getpid()}.py')
    with open(script, 'w') as f:
        f.write(GDB_OWNERS)
    try:
        out = subprocess.run(['gdb', '-batch', '-nx', '-p', str(pid), '-ex',
                              'thread apply all bt 30', '-x', script],
                             capture_output=True, text=True, timeout=90)
        text = out.stdout + out.stderr[-2000:]
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f'(gdb failed: {exc})'

    def whose(match):
        tid = int(match.group(1))
        if tid <= 0:
            return 'not held (any more)'
        try:
            with open(f'/proc/{tid}/status') as f:
                tgid = next(line.split()[1] for line in f if line.startswith('Tgid'))
            return f'held by tid {tid}, alive, of process {tgid}'
        except (OSError, StopIteration):
            return f'held by tid {tid}, WHICH NO LONGER EXISTS (its process died holding it)'
    return re.sub(r'held by tid (-?\d+)', whose, text)


#: x86_64 syscall numbers seen in a node (/proc/<pid>/task/<tid>/syscall).
SYSCALLS = {'running': 'running', '0': 'read', '7': 'poll', '23': 'select', '35': 'nanosleep',
            '45': 'recvfrom', '47': 'recvmsg', '61': 'wait4', '230': 'clock_nanosleep',
            '232': 'epoll_wait', '270': 'pselect6', '271': 'ppoll', '281': 'epoll_pwait'}


def futex_waits(pid):
    """Which threads of ``pid`` wait on a futex, and for a mutex who holds it (read from
    /proc without stopping the process; ptrace-level access, i.e. root): per thread the
    futex address (first argument of the futex syscall in /proc/<pid>/task/<tid>/syscall),
    the file mapped there (e.g. a Fast DDS shared-memory port under /dev/shm), the lock word
    and the int at +8, which for a locked glibc ``pthread_mutex_t`` (word != 0) is
    ``__owner``: the kernel id of the holder. A holder id that no longer exists is a mutex
    whose owner died holding it. The other threads: their current system call."""
    lines = []
    try:
        tids = sorted(os.listdir(f'/proc/{pid}/task'), key=int)
        with open(f'/proc/{pid}/maps') as f:
            maps = []
            for line in f:
                parts = line.split()
                lo, hi = (int(x, 16) for x in parts[0].split('-'))
                maps.append((lo, hi, parts[5] if len(parts) > 5 else '[anon]'))
        mem = open(f'/proc/{pid}/mem', 'rb')
    except OSError as exc:
        return [f'(cannot read /proc/{pid}: {exc})']
    with mem:
        for tid in tids:
            try:
                with open(f'/proc/{pid}/task/{tid}/syscall') as f:
                    fields = f.read().split()
                with open(f'/proc/{pid}/task/{tid}/comm') as f:
                    comm = f.read().strip()
            except OSError:
                continue
            if not fields or fields[0] != '202':   # SYS_futex on x86_64
                call = SYSCALLS.get(fields[0], f'syscall {fields[0]}') if fields else '?'
                lines.append(f'tid {tid} ({comm}): {call}')
                continue
            addr = int(fields[1], 16)
            where = next((m for lo, hi, m in maps if lo <= addr < hi), '?')
            try:
                mem.seek(addr)
                raw = mem.read(12)
                word = int.from_bytes(raw[0:4], 'little')
                owner = int.from_bytes(raw[8:12], 'little')
            except (OSError, ValueError):
                lines.append(f'tid {tid} ({comm}): futex {addr:#x} in {where} (unreadable)')
                continue
            state = ''
            if word and 0 < owner < 1 << 22:   # a locked mutex: +8 is its holder
                state = (f'alive, in process {_tgid(owner)}' if _tgid(owner)
                         else 'NO LONGER EXISTS: its process died holding it')
            lines.append(f'tid {tid} ({comm}): futex {addr:#x} in {where}; word {word}, '
                         f'int at +8 {owner}' + (f' = holder tid, {state}' if state else ''))
    return lines or ['(no thread waits on a futex)']


def _tgid(tid):
    try:
        with open(f'/proc/{tid}/status') as f:
            return next(line.split()[1] for line in f if line.startswith('Tgid'))
    except (OSError, StopIteration):
        return None


def wait_exit(p, timeout, log_path, name, dump_after=None, native=False):
    """Wait up to ``timeout`` for ``p``; else SIGUSR1, DUMP_WAIT, SIGKILL. With
    ``dump_after``: if ``p`` still runs that many seconds in, SIGUSR1 (Python stacks into its
    log) and with ``native`` gdb's native stacks, then wait on. Returns
    (seconds waited, exit code, hung)."""
    t0 = time.monotonic()
    if dump_after is not None and dump_after < timeout:
        try:
            p.wait(dump_after)
            return time.monotonic() - t0, p.returncode, False
        except subprocess.TimeoutExpired:
            note(log_path, f'{name} still running {dump_after:g} s after SIGINT: '
                           'its stacks follow (--dump-after)')
            note(log_path, f'futex waits of {name}:\n' + '\n'.join(futex_waits(p.pid)))
            try:
                os.kill(p.pid, signal.SIGUSR1)
            except ProcessLookupError:
                pass
            if native:
                time.sleep(0.2)
                stacks = native_stacks(p.pid)
                note(log_path, f'native stacks of {name} (gdb):\n{stacks}')
    try:
        p.wait(max(0.0, t0 + timeout - time.monotonic()))
        return time.monotonic() - t0, p.returncode, False
    except subprocess.TimeoutExpired:
        pass
    note(log_path, f'{name} still running {timeout:g} s after SIGINT: SIGUSR1, then SIGKILL; '
                   'signals 2 / 15 per thread:\n' + '\n'.join(signal_state(p.pid)))
    try:
        os.kill(p.pid, signal.SIGUSR1)
        p.wait(DUMP_WAIT)
    except (ProcessLookupError, subprocess.TimeoutExpired):
        signal_group(p, signal.SIGKILL)
        p.wait()
    return time.monotonic() - t0, p.returncode, True


def reap_all():
    for p in list(_live):
        if p.poll() is None:
            signal_group(p, signal.SIGKILL)
            try:
                p.wait(5)
            except subprocess.TimeoutExpired:
                pass
        _live.remove(p)


def start_hogs(k):
    for _ in range(k):
        _hogs.append(subprocess.Popen([sys.executable, '-c', 'while True: pass'],
                                      start_new_session=True))


def stop_hogs():
    for h in _hogs:
        if h.poll() is None:
            h.kill()
            h.wait()
    _hogs.clear()


def cleanup():
    reap_all()
    stop_hogs()


def trial(i, scenario, domain, args, params, rng):
    """One trial; returns its record (a dict)."""
    kill, stop = scenario.split('/')
    restart = kill.endswith('+restart')
    victims = KILLS[kill.replace('+restart', '')]
    nodes = ['sim', 'streamer', 'adapter'] + (['learner'] if args.learner else [])
    logs = {n: os.path.join(args.logdir, f'trial{i:03d}_{n}.log') for n in nodes}
    rec = {'trial': i, 'scenario': scenario, 'domain': domain, 'logs': logs}
    procs = {n: start(n, domain, params, logs[n]) for n in nodes}
    t_start = time.monotonic()
    if not wait_line(logs['sim'], READY_LINE, procs['sim'], args.startup_timeout):
        rec['result'] = 'sim not ready'
        rec['code'] = procs['sim'].poll()
        reap_all()
        return rec
    rec['ready_s'] = round(time.monotonic() - t_start, 2)
    time.sleep(rng.uniform(0.0, args.settle))
    for v in victims:
        note(logs['sim'], f'SIGKILL {v}')
        signal_group(procs[v], signal.SIGKILL)
        procs[v].wait()
    rec['restart_wait'] = False
    if restart and victims:
        for v in victims:
            procs[v] = start(v, domain, params, logs[v])
        if rng.random() < 0.5:   # wait until every restarted node wrote its first line
            rec['restart_wait'] = all(
                wait_line(logs[v], re.compile(rf'\[{v}\]'), procs[v], args.startup_timeout)
                for v in victims)
    delay = rng.uniform(0.0, args.max_delay)
    rec['delay_s'] = round(delay, 3)
    time.sleep(delay)
    note(logs['sim'], f'SIGINT ({stop})')
    targets = nodes if stop == 'all' else ['sim']
    for n in targets:
        if procs[n].poll() is None:
            signal_group(procs[n], signal.SIGINT)
    w = args.watch
    t_exit, code, hung = wait_exit(procs[w], args.hang_after, logs[w], w,
                                   args.dump_after, args.native)
    rec.update(exit_s=round(t_exit, 3), code=code, hang=hung,
               dumped='(--dump-after)' in read(logs[w]))
    peers = {}
    for n in nodes:
        if n == w:
            continue
        p = procs[n]
        if n in victims and not restart:
            peers[n] = 'killed'   # our SIGKILL of step 3
            continue
        if p.poll() is None and n not in targets:
            signal_group(p, signal.SIGINT)
        _, c, h = wait_exit(p, PEER_STOP, logs[n], n, args.dump_after, args.native)
        peers[n] = c if not h else f'hung({c})'
    rec['peer_codes'] = peers
    reap_all()
    rec['marks'] = {}
    for n in nodes:
        lines = [m.group(0).strip() for m in MARK_LINE.finditer(read(logs[n]))]
        if lines:
            rec['marks'][n] = lines
    rec['watchdog'] = bool(rec['marks'].get(w))
    rec['result'] = 'hang' if hung else ('watchdog' if rec['watchdog'] else 'ok')
    return rec


def pct(values, q):
    if not values:
        return float('nan')
    v = sorted(values)   # nearest rank
    return v[max(0, math.ceil(q / 100.0 * len(v)) - 1)]


def table(records, watch='sim'):
    by = collections.OrderedDict((s, []) for s in SCENARIOS)
    for r in records:
        by.setdefault(r['scenario'], []).append(r)
    lines = ['| scenario | trials | exit p50 / p95 / max [s] | hangs (> hang-after) | '
             f'watchdog ({watch}) | {watch} exit codes | other exit codes of the peers |',
             '|---|---|---|---|---|---|---|']
    for name, rs in list(by.items()) + [('**all**', records)]:
        if not rs:
            continue
        ex = [r['exit_s'] for r in rs if 'exit_s' in r]
        codes = collections.Counter(str(r.get('code')) if 'exit_s' in r else r['result']
                                    for r in rs)
        peers = collections.Counter(f'{n}:{c}' for r in rs
                                    for n, c in r.get('peer_codes', {}).items()
                                    if c not in (0, 'killed'))
        lines.append(
            f'| {name} | {len(rs)} | {pct(ex, 50):.2f} / {pct(ex, 95):.2f} / '
            f'{max(ex) if ex else float("nan"):.2f} | {sum(bool(r.get("hang")) for r in rs)} | '
            f'{sum(bool(r.get("watchdog")) for r in rs)} | '
            f'{", ".join(f"{c} x{n}" for c, n in sorted(codes.items()))} | '
            f'{", ".join(f"{c} x{n}" for c, n in sorted(peers.items())) or "-"} |')
    return '\n'.join(lines)


def parse_params(items):
    params = collections.defaultdict(list)
    for item in items:
        node, _, assignment = item.partition(':')
        if not assignment or ':=' not in assignment:
            raise SystemExit(f'--param {item!r}: expected NODE:NAME:=VALUE')
        params[node].append(assignment)
    return params


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog='Scenarios: ' + ', '.join(SCENARIOS))
    ap.add_argument('--trials', type=int, default=30, help='number of trials (default 30)')
    ap.add_argument('--domain', type=int, default=170, help='first ROS_DOMAIN_ID (170)')
    ap.add_argument('--domains', type=int, default=10,
                    help='trial i uses domain + i %% domains (10: 170-179)')
    ap.add_argument('--seed', type=int, default=0, help='rng seed (0)')
    ap.add_argument('--scenarios', nargs='+', default=list(SCENARIOS), choices=SCENARIOS,
                    metavar='SCENARIO', help='subset of the scenarios (default: all)')
    ap.add_argument('--max-delay', type=float, default=2.0,
                    help='s, upper bound of the random delay kill -> SIGINT (2.0)')
    ap.add_argument('--settle', type=float, default=1.0,
                    help='s, upper bound of the random wait after the sim is ready (1.0)')
    ap.add_argument('--hang-after', type=float, default=15.0,
                    help='s after SIGINT before the sim counts as hung (15)')
    ap.add_argument('--dump-after', type=float, default=None,
                    help='s after SIGINT (for the other nodes: after the wait for their stop '
                         'began): a node still running then writes its Python stacks '
                         '(SIGUSR1) to its log, once; diagnosis of slow stops (default off)')
    ap.add_argument('--native', action='store_true',
                    help='with --dump-after: also the native stacks (gdb -batch -p)')
    ap.add_argument('--startup-timeout', type=float, default=120.0,
                    help="s to wait for the sim's ready line (120)")
    ap.add_argument('--hogs', type=int, default=0, help='busy-loop processes to run (0)')
    ap.add_argument('--learner', action='store_true', help='also run the learner (as CI)')
    ap.add_argument('--watch', default='sim', choices=('sim', 'streamer', 'adapter', 'learner'),
                    help='the node whose stop is timed, dumped (--dump-after) and counted in '
                         'the table (default sim; learner implies --learner)')
    ap.add_argument('--param', action='append', default=[], metavar='NODE:NAME:=VALUE',
                    help='an extra -p parameter of one node (repeatable)')
    ap.add_argument('--env', action='append', default=[], metavar='NODE:VAR=VALUE',
                    help="an environment variable of one node's process, NODE all: of every "
                         'node (repeatable), e.g. sim:FASTDDS_BUILTIN_TRANSPORTS=UDPv4')
    ap.add_argument('--max-minutes', type=float, default=60.0,
                    help='no trial starts after this many minutes (60)')
    ap.add_argument('--logdir', default=None,
                    help='where the logs go (default: a new /tmp/repro_sim_stop_* dir)')
    args = ap.parse_args(argv)
    params = parse_params(args.param)
    args.learner = args.learner or args.watch == 'learner'
    for item in args.env:
        node, _, assignment = item.partition(':')
        var, eq, value = assignment.partition('=')
        if not eq or not var:
            raise SystemExit(f'--env {item!r}: expected NODE:VAR=VALUE')
        NODE_ENV[node][var] = value
    args.logdir = args.logdir or tempfile.mkdtemp(prefix='repro_sim_stop_')
    os.makedirs(args.logdir, exist_ok=True)
    atexit.register(cleanup)
    for sig in (signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, lambda s, f: sys.exit(128 + s))
    rng = random.Random(args.seed)
    order = []
    while len(order) < args.trials:
        rnd = list(args.scenarios)
        rng.shuffle(rnd)
        order += rnd
    order = order[:args.trials]
    start_hogs(args.hogs)
    print(f'# repro_sim_stop: {args.trials} trials, seed {args.seed}, hogs {args.hogs}, '
          f'learner {args.learner}, params {dict(params)}, env {dict(NODE_ENV)}, '
          f'logs in {args.logdir}',
          file=sys.stderr, flush=True)
    records = []
    t0 = time.monotonic()
    jsonl = os.path.join(args.logdir, 'trials.jsonl')
    try:
        for i, scenario in enumerate(order):
            if time.monotonic() - t0 > args.max_minutes * 60:
                print(f'# --max-minutes reached after {i} trials', file=sys.stderr)
                break
            rec = trial(i, scenario, args.domain + i % args.domains, args, params, rng)
            records.append(rec)
            with open(jsonl, 'a') as f:
                f.write(json.dumps(rec) + '\n')
            print(f'trial {i:3d} {scenario:26s} ready {rec.get("ready_s", "-")} s, delay '
                  f'{rec.get("delay_s", "-")} s, exit {rec.get("exit_s", "-")} s, code '
                  f'{rec.get("code")}, peers {rec.get("peer_codes", {})}: {rec["result"]}',
                  file=sys.stderr, flush=True)
    finally:
        cleanup()
    wall = time.monotonic() - t0
    print(f'\n{len(records)} trials in {wall / 60:.1f} min, seed {args.seed}, hogs {args.hogs}, '
          f'learner {args.learner}, env {dict(NODE_ENV)}, hang after {args.hang_after:g} s, '
          f'logs {args.logdir}\n')
    print(table(records, args.watch))
    flagged = [r for r in records if r.get('hang') or r.get('marks')
               or r['result'] not in ('ok',)]
    if flagged:
        print('\nTrials with a hang, a watchdog line or no start:')
        for r in flagged:
            print(f'- trial {r["trial"]} ({r["scenario"]}): {r["result"]}, {args.watch} code '
                  f'{r.get("code")}; its log {r["logs"][args.watch]}')
            for n, marks in r.get('marks', {}).items():
                for m in marks:
                    print(f'  - {n}: {m.strip()}  ({r["logs"][n]})')
    else:
        print('\nNo hang, no `[node_main]` line in any node log.')
    return 1 if any(r.get('hang') or r.get('watchdog') for r in records) else 0


if __name__ == '__main__':
    sys.exit(main())
