"""``cdmp bag info|record|play|recover``: inspect, record, replay and repair bags.

``record`` and ``play`` start the ``recorder`` / ``player`` nodes as child processes (the CLI
never imports rclpy); SIGINT / SIGTERM are forwarded so the recorder closes its bag cleanly.
"""
import os
import signal
import subprocess
import sys
import time

NAME = 'bag'
#: ``play``: default of --wait-subscribers and --ack-timeout, and their upper bound [s] (the
#: player node's ``wait_subscribers`` / ``ack_timeout``, cdmp_ros/ros/bag_bridge.py).
WAIT_S = 10.0
MAX_WAIT_S = 86400.0
HELP = 'inspect (info), record, play and recover rosbag2 MCAP bags'


def add_arguments(parser):
    sub = parser.add_subparsers(dest='bag_command', metavar='<info|record|play|recover>')
    sub.required = True
    p = sub.add_parser('info', help='topics, types, counts and duration (verifies every CRC)')
    p.add_argument('bag', help='bag directory or .mcap file')
    p.set_defaults(_bag=_info)

    p = sub.add_parser('record', help='record topics with the recorder node (Ctrl-C stops)')
    p.add_argument('topics', nargs='*', help='topics to record (default: all discovered)')
    p.add_argument('-o', '--output', required=True, help='bag directory to create')
    p.add_argument('--duration', type=float, default=None,
                   help='stop after this many seconds')
    p.add_argument('--flush-period', type=float, default=0.1,
                   help='max age of an open chunk in s (bounds the loss on a crash)')
    p.add_argument('--compression', choices=['zstd', 'lz4', 'none'], default='zstd')
    p.add_argument('--queue-depth', type=int, default=10000,
                   help='subscription queue depth per topic (absorbs scheduling stalls)')
    p.set_defaults(_bag=_record)

    p = sub.add_parser('play', help='replay a bag with the player node')
    p.add_argument('bag', help='bag directory or .mcap file')
    p.add_argument('--rate', type=float, default=1.0, help='rate factor (default 1.0)')
    p.add_argument('--loop', action='store_true', help='play again and again')
    p.add_argument('--topics', nargs='+', default=[], help='topics to play (default all)')
    p.add_argument('--remap', nargs='+', default=[], metavar='FROM:=TO',
                   help='topic remappings, e.g. /demonstration:=/goal')
    p.add_argument('--clock', action='store_true', help='publish /clock')
    p.add_argument('--wait-subscribers', type=float, default=WAIT_S, metavar='S',
                   help='before playing, wait up to S seconds until every played topic (and '
                        '/clock with --clock) has a subscriber; then play anyway and name '
                        'the topics without one (log and /diagnostics). Default %(default)g; '
                        '0 = play at once')
    p.add_argument('--ack-timeout', type=float, default=WAIT_S, metavar='S',
                   help='after the last message, wait up to S seconds until every reliable '
                        'subscriber acknowledged every message, then exit, naming the topics '
                        'not acknowledged. Default %(default)g; 0 = exit at once')
    p.add_argument('--start-delay', type=float, default=0.0, metavar='S',
                   help='seconds before the first message, after the subscriber wait')
    p.set_defaults(_bag=_play)

    p = sub.add_parser('recover', help='make a crashed recording readable and report the loss')
    p.add_argument('bag', help='bag directory (with one .mcap) or the .mcap file')
    p.add_argument('-o', '--output', default=None,
                   help='write the recovered bag here (default: repair in place)')
    p.add_argument('--no-backup', action='store_true',
                   help='in place: do not keep the crashed file as <file>.crashed')
    p.set_defaults(_bag=_recover)


def run(args) -> int:
    return args._bag(args)


def _info(args) -> int:
    from cdmp_ros.bag import bag_info
    info = bag_info(args.bag)
    t0 = info['starting_time_ns']
    print(f'Files:        {", ".join(info["files"])}')
    print(f'Bag size:     {_size(args.bag)}')
    print('Storage id:   mcap')
    print(f'Duration:     {info["duration_ns"] / 1e9:.3f} s')
    print(f'Start:        {time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime(t0 / 1e9))}'
          f'.{t0 % 10 ** 9:09d} UTC ({t0} ns)')
    print(f'Messages:     {info["message_count"]}')
    print('Topics:')
    width = max([len(t['name']) for t in info['topics']] + [5])
    for t in info['topics']:
        print(f'  {t["name"]:<{width}}  {t["type"]:<40} {t["count"]:>8} msgs  '
              f'{t["serialization_format"]}')
    return 0


def _size(path) -> str:
    if os.path.isfile(path):
        n = os.path.getsize(path)
    else:
        n = sum(os.path.getsize(os.path.join(path, f)) for f in os.listdir(path))
    return f'{n / 1024:.1f} KiB'


def _node_cmd(node: str, params: dict, remaps=()) -> list:
    cmd = [sys.executable, '-m', f'cdmp_ros.nodes.{node}', '--ros-args']
    for k, v in params.items():
        if isinstance(v, bool):
            v = 'true' if v else 'false'
        elif isinstance(v, (list, tuple)):
            v = '[' + ', '.join(f"'{x}'" for x in v) + ']'
        cmd += ['-p', f'{k}:={v}']
    for r in remaps:
        cmd += ['-r', r]
    return cmd


def _run_child(cmd, duration=None) -> int:
    """Run a node process; forward SIGINT/SIGTERM; stop it after ``duration`` seconds."""
    proc = subprocess.Popen(cmd)
    forwarded = []

    def forward(sig, _frame):
        forwarded.append(sig)
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)

    old = {s: signal.signal(s, forward) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        deadline = None if duration is None else time.monotonic() + duration
        while proc.poll() is None:
            if deadline is not None and time.monotonic() >= deadline:
                proc.send_signal(signal.SIGINT)
                deadline = None
            try:
                proc.wait(timeout=0.1)
            except subprocess.TimeoutExpired:
                pass
        return proc.returncode
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def _record(args) -> int:
    params = {'output': os.path.abspath(args.output), 'flush_period': float(args.flush_period),
              'compression': args.compression, 'queue_depth': args.queue_depth}
    if args.topics:
        params['topics'] = args.topics
    return _run_child(_node_cmd('recorder', params), args.duration)


def _play(args) -> int:
    from cdmp_ros.bag import BagReader
    BagReader(args.bag).verify()  # refuse a bad bag here with a clear message
    for option in ('wait_subscribers', 'ack_timeout'):
        value = getattr(args, option)
        if not 0.0 <= value <= MAX_WAIT_S:  # also refuses nan
            from cdmp_ros.core.errors import ValidationError
            raise ValidationError(f'--{option.replace("_", "-")}: expected seconds in '
                                  f'[0, {MAX_WAIT_S:g}], got {value}')
    params = {'bag': os.path.abspath(args.bag), 'rate': float(args.rate), 'loop': args.loop,
              'clock': args.clock, 'wait_subscribers': float(args.wait_subscribers),
              'ack_timeout': float(args.ack_timeout), 'start_delay': float(args.start_delay)}
    if args.topics:
        params['topics'] = args.topics
    for r in args.remap:
        if ':=' not in r:
            from cdmp_ros.core.errors import ValidationError
            raise ValidationError(f'--remap: expected FROM:=TO, got {r!r}')
    return _run_child(_node_cmd('player', params, args.remap))


def _recover(args) -> int:
    from cdmp_ros.bag import recover_bag
    report = recover_bag(args.bag, output=args.output, keep_original=not args.no_backup)
    print(report.summary())
    return 0
