"""``cdmp demo``: the project's main demonstration (the node graph end to end).

Learns a reach from ``bags/panda_reach``, streams it to the simulated Panda at 500 Hz, drops a
sphere into the path mid-motion, changes the goal, records every topic to an MCAP bag, and
prints a summary (see :mod:`cdmp_ros.cli.demo_run`). The paper-000 toy reproduction that this
command ran before the node graph existed is ``cdmp reproduce toy``.
"""
NAME = 'demo'
#: rad a measured joint may pass a limit (the sim node's default ``limit_tolerance``): the
#: tracking controller's overshoot of a reference held at a limit, not a violation.
LIMIT_TOLERANCE = 1e-4
HELP = ('learn a reach from bags/, stream it to the simulated Panda, drop an obstacle into the '
        'path, change the goal, record a bag, and summarise (summary.json, plots, snapshot)')


def add_arguments(parser):
    parser.add_argument('--out', default='out/demo', help='output directory (default out/demo)')
    parser.add_argument('--timeout', type=float, default=45.0,
                        help='seconds allowed for the scripted run (default 45)')
    parser.add_argument('--kind', choices=('cdmp', 'promp', 'dual'), default='cdmp',
                        help='cdmp (default): the learner fits a CDMP; a sphere dropped into '
                             'the path is avoided by the coupling terms, then the goal changes. '
                             'promp: the learner fits a ProMP; the arm starts with the '
                             "adapter's answer to it (streamer stream_unadapted false), and "
                             'every obstacle message triggers a constrained adaptation (paper '
                             '003) that the streamer follows; exits non-zero if none happened. '
                             'dual: as promp on two Pandas (config/graphs/dual_demo.yaml, a '
                             'hand-over learnt from bags/dual_panda): the sphere lands between '
                             'the hands, and every adaptation also keeps the arms '
                             'adaptation.arm_clearance apart (mutual avoidance); exits non-zero '
                             'if the arms touched')
    parser.add_argument('--motion', choices=('drop', 'cross'), default='drop',
                        help='drop (default): the sphere falls onto the path; cross: it moves '
                             'horizontally across the path at 0.2 m/s, published at 30 Hz '
                             '(the adapter keeps up: the latest obstacle wins)')
    parser.add_argument('--rate', type=float, default=None,
                        help="the streamer's rate [Hz] (default: the graph's, 500; 1000 "
                             'supported)')
    parser.add_argument('--graph', default=None,
                        help='graph file to start instead of config/graphs/demo.yaml')


def run(args):
    import json
    import math
    from cdmp_ros.cli.demo_run import markdown, run_demo
    s = run_demo(args.out, timeout=args.timeout, graph_file=args.graph, kind=args.kind,
                 driver_args=['--motion', args.motion],
                 streamer_parameters={'rate': args.rate} if args.rate else None)
    print()
    print(markdown(s))
    print(f'wall time {s["wall_time_s"]:.1f} s; summary: {args.out}/summary.json, plots: '
          f'{", ".join(s["plots"])}' + (f', snapshot: {s["snapshot"]}' if s['snapshot'] else ''))
    bad = []
    if not s['reference_limit_usage'] < 1.0:
        bad.append('a reference left the joint limits')
    if not s['limit_violations'] == 0 or not s['max_limit_excess_rad'] <= LIMIT_TOLERANCE:
        bad.append(f'a joint left its limits by more than {LIMIT_TOLERANCE} rad')
    kin = s['kinematic_limits']
    for order in ('velocity', 'acceleration', 'jerk'):
        if kin[order]['over']:
            bad.append(f'{kin[order]["over"]} references broke the {order} limit (worst '
                       f'{kin[order]["worst_ratio"]:.2f} x the limit)')
    if s['reflex_errors'] > 0:  # NaN (not reported) passes: the sim may predate the check
        bad.append(f'the sim counted {s["reflex_errors"]:.0f} reflex errors')
    if math.isnan(s['min_obstacle_distance_m']) or s['min_obstacle_distance_m'] <= 0.0:
        bad.append('the robot touched the obstacle (or the distance is unknown)')
    adapted = 'promp' in s
    if adapted and not s['promp']['adaptations']:
        bad.append('no constrained adaptation was published after the obstacle appeared')
    if adapted and s['promp'].get('adapter_current') is False:
        bad.append("the adapter's last adaptation does not answer the last obstacle message")
    if 'min_robot_distance_m' in s and not s['min_robot_distance_m'] > 0.0:
        bad.append('the arms touched each other (or their distance is unknown)')
    if bad:
        print('demo: FAILED: ' + '; '.join(bad))
        print(json.dumps({k: s[k] for k in ('min_obstacle_distance_m', 'max_limit_usage',
                                            'reference_limit_usage', 'limit_violations',
                                            'max_limit_excess_rad')}))
        return 1
    return 0
