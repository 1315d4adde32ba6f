"""Replay a recorded demo run through the core streamer, offline, for several coupling bounds.

Reads the bag of a ``cdmp demo`` run (``OUT/bag``) and feeds its ``primitive``,
``adapted_primitive``, ``goal`` and ``obstacles`` messages, at their recorded (log) times, to a
:class:`~cdmp_ros.core.streaming.streamer.ReferenceStreamer` built with the streamer
parameters of the graph (``--graph``, default ``config/graphs/demo.yaml``: its top-level,
``coupling.*``, ``damping.*`` and ``repeller.*`` parameters, the capsules of
``coupling_capsule_links`` included; ``stream_unadapted`` false for a ProMP run, as ``cdmp demo
--kind promp`` sets it), choosing what to switch in with the node's
:class:`~cdmp_ros.core.streaming.selection.AdaptationSelector` (an adaptation that
``continues`` the motion is switched in at the current phase), stepping 2 ms ticks from the
first recorded reference; no sim, no ROS graph (the reference is open loop:
``joint_states_timeout`` 0). For every
``--bound`` (``coupling_max_acceleration``, 0 = unbounded) it prints the largest change of
the reference in one tick, the largest reported velocity, the largest requested coupling, and
the smallest capsule distance of the reference to the obstacles and the largest speed in the
last second (a reference that should rest and does not: a coupling that makes it oscillate), as
a markdown table.

This is how the 3 rad one-tick jump of the demo (benchmarks/RESULTS.md, "The obstacle
coupling is bounded") was reproduced without ROS, and how the bound was checked on the
recorded runs. Deterministic: the same bag gives the same figures.

    .venv/bin/python benchmarks/replay_coupling.py out/demo_promp --bound 0 50 500
"""
import argparse
import dataclasses
import json
import math
import os
import sys

import numpy as np

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), '..')
sys.path.insert(0, ROOT)

from cdmp_ros.bag.cdr import decode_joint_state, decode_string  # noqa: E402
from cdmp_ros.bag.reader import BagReader  # noqa: E402
from cdmp_ros.core.config_fields import chain_tips  # noqa: E402
from cdmp_ros.core.streaming.primitives import prepare_primitive  # noqa: E402
from cdmp_ros.core.streaming.selection import AdaptationSelector, read_provenance  # noqa: E402
from cdmp_ros.core.streaming.streamer import ReferenceStreamer, coupling_of  # noqa: E402
from cdmp_ros.cli.cmd_bringup import streamer_configs  # noqa: E402
from cdmp_ros.ros.robot_model import load_chain, load_collision_capsules  # noqa: E402

TOPICS = ['/primitive', '/adapted_primitive', '/goal', '/obstacles', '/joint_reference']
DT_NS = 2_000_000
#: Ticks at the end over which the largest speed is reported (1 s): does the reference rest?
REST_TICKS = 500


def replay(msgs, chain, configs: dict, bound: float) -> dict:
    """Stream the recorded inputs with ``coupling_max_acceleration = bound``."""
    from rclpy.serialization import deserialize_message
    from visualization_msgs.msg import MarkerArray
    from cdmp_ros.ros.convert import ObstacleSet
    cfg = dataclasses.replace(configs[''], joint_states_timeout=0.0,
                              coupling_max_acceleration=bound)
    capsules = load_collision_capsules(cfg.urdf_path, cfg.coupling_capsule_links, chain=chain)
    coupling = coupling_of(chain, dict(configs, **{'': cfg}), capsules)
    rs = ReferenceStreamer(chain.lower, chain.upper, cfg, coupling)
    selection = AdaptationSelector(cfg.stream_unadapted)
    obstacles = ObstacleSet(cfg.base_frame, cfg.max_obstacles, cfg.max_obstacle_size,
                            cfg.max_obstacle_distance)
    first = next(m for m in msgs if m.topic == '/joint_reference')
    rs.note_joint_states(decode_joint_state(first.data).position, 0.0)
    t, end, i = first.log_time, msgs[-1].log_time, 0
    Y, V, dmin, peak = [], [], math.inf, 0.0
    while t < end:
        while i < len(msgs) and msgs[i].log_time <= t:
            m = msgs[i]
            i += 1
            if m.topic in ('/primitive', '/adapted_primitive'):
                topic = m.topic[1:]
                prep = prepare_primitive(decode_string(m.data), chain.joint_names, cfg.dt,
                                         chain.lower, chain.upper, chain.velocity_limits,
                                         source=topic)
                if topic != 'primitive':
                    prep.provenance = read_provenance(prep.metadata)
                dec = selection.offer(topic, prep)
                if dec.activate is not None:
                    rs.activate(dec.activate, 0.0, dec.continues)
            elif m.topic == '/goal':
                rs.set_goal(decode_joint_state(m.data).position)
            elif m.topic == '/obstacles':
                obstacles.apply(deserialize_message(m.data, MarkerArray).markers, 0.0)
                rs.obstacles = obstacles.snapshot.items
        rs.advance(1, 0.0)
        if rs.obstacles:
            dmin = min(dmin, rs.min_distance)
        peak = max(peak, rs.coupling_peak, float(np.abs(rs._coupling_joint).max()))
        Y.append(list(rs.y))
        V.append(list(rs.yd))
        t += DT_NS
    Y, V = np.array(Y), np.array(V)
    return {'max_step_rad': float(np.abs(np.diff(Y, axis=0)).max()),
            'max_velocity': float(np.abs(V).max()),
            'peak_request': peak, 'min_distance_m': dmin,
            'final_speed': float(np.abs(V[-REST_TICKS:]).max())}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('run', help='output directory of a cdmp demo run (with bag/)')
    ap.add_argument('--bound', type=float, nargs='+', default=[0.0, 500.0],
                    help='coupling_max_acceleration values [rad/s^2] (0 = unbounded)')
    ap.add_argument('--graph', default=os.path.join(ROOT, 'config', 'graphs', 'demo.yaml'),
                    help='graph file whose streamer parameters are replayed (default the '
                    'demo; config/graphs/dual_demo.yaml for a cdmp demo --kind dual run)')
    ap.add_argument('--stream-unadapted', choices=('auto', 'true', 'false'), default='auto',
                    help='auto: false for a ProMP run, as cdmp demo --kind promp and dual set '
                    'it since 2026-11-26 (runs recorded before streamed the raw primitive: '
                    'true)')
    a = ap.parse_args(argv)
    kind = 'cdmp'
    summary = os.path.join(a.run, 'summary.json')
    if os.path.exists(summary):
        with open(summary) as f:
            kind = json.load(f).get('kind', 'cdmp')
    unadapted = {'auto': kind == 'cdmp', 'true': True, 'false': False}[a.stream_unadapted]
    configs = streamer_configs(a.graph, {'stream_unadapted': unadapted})
    bag = os.path.join(a.run, 'bag')
    msgs = sorted(BagReader(bag).messages(TOPICS), key=lambda m: m.log_time)
    cfg = configs['']  # the graph's robot: one Panda, or the arms of tip_links
    chain = load_chain(cfg.urdf_path, cfg.joint_names, chain_tips(cfg), cfg.tcp_offset)
    print(f'{bag}: {len(msgs)} messages\n')
    print('| bound [rad/s^2] | largest step in one 2 ms tick [rad] | largest velocity [rad/s] '
          '| largest coupling requested [rad/s^2] | smallest capsule distance [cm] '
          '| largest speed in the last second [rad/s] |')
    print('|---|---|---|---|---|---|')
    for bound in a.bound:
        r = replay(msgs, chain, configs, bound)
        print(f"| {bound:g} | {r['max_step_rad']:.4f} | {r['max_velocity']:.2f} | "
              f"{r['peak_request']:.3g} | {100 * r['min_distance_m']:.2f} | "
              f"{r['final_speed']:.4f} |")
    return 0


if __name__ == '__main__':
    sys.exit(main())
