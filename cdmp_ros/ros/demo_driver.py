"""The scripted user of ``cdmp demo``: drops an obstacle into the moving robot's path, changes
the goal, asks the sim for a snapshot, and writes what it saw to ``driver.json``.

Run by ``cdmp demo`` as ``python -m cdmp_ros.ros.demo_driver --out DIR`` next to the node
graph of ``config/graphs/demo.yaml`` (``--robot dual_panda``: ``config/graphs/dual_demo.yaml``;
it is not a product executable). The robot's geometry is a :class:`~cdmp_ros.core.demo_robot.
DemoRobot`; of two arms, "the hand" below is the point midway between the two hands, and the
arm under the sphere either arm. Timeline:

1. wait until every node of the graph is up and connected (the recorder too), call
   ``/learner/refit``, wait for the latched ``primitive``; plan the hand's path of the
   primitive from the current reference (core kinematics) and pick the point at
   ``--obstacle-at`` of its arc length;
2. with ``--wait-adapter`` (``cdmp demo --kind promp``), wait until the adapter has answered
   that primitive (an ``adapted_primitive`` whose ``metadata.adapter`` names it as its source)
   and the streamer streams that answer (its diagnostics' ``adapted_generation``): then every
   obstacle message of the drop finds the adapter holding the primitive and the adapter's
   results reach the streamer, however late a loaded machine's DDS discovery matched the
   learner, adapter and streamer with each other (the driver's own view of the graph says
   nothing about those pairs). The answer restarts the motion from the current state, so the
   path is planned (step 1) only then;
3. when the reference has covered ``--drop-at`` of that path, drop a sphere onto the point;
   while the arm is under the sphere's first position (its capsules closer than
   ``SPAWN_CLEARANCE``) the
   sphere appears at its landing point instead if that is clear, else the drop waits (for at
   most ``SPAWN_WAIT`` more of the path)
   (``--drop-height`` above it, ``--drop-messages`` stamped ``obstacles`` messages, one every
   ``DROP_PERIOD``), or with ``--motion cross`` move it horizontally across the path through
   the point (``--cross-length`` at ``--cross-speed``, ``--cross-rate`` messages per second);
4. when the reference rests (with ``--wait-adapter``: once the streamer streams the adapter's
   answer to the last obstacle message, or ``LAST_ANSWER_WAIT`` after it without one, and
   counted from then), publish ``goal`` (the
   primitive's goal + ``--goal-offset``; skipped with ``--no-goal-change``);
5. when it rests again (or ``--timeout``), call ``/sim/snapshot`` and write ``driver.json``
   with the event times, the obstacle, and the last ``/diagnostics`` status of every node.
"""
import argparse
import functools
import json
import os
import sys
import time

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from std_srvs.srv import Trigger
from visualization_msgs.msg import Marker, MarkerArray

from cdmp_ros.core.demo_robot import ROBOTS, DemoRobot, between_hands
from cdmp_ros.core.run_metrics import drop_positions, path_progress, point_at_progress
from cdmp_ros.core.streaming.primitives import prepare_primitive
from cdmp_ros.core.streaming.selection import primitive_id, read_provenance
from cdmp_ros.core.topics import DIAGNOSTICS_TOPIC
from cdmp_ros.ros import qos
from cdmp_ros.ros.recorder_take import ThreadTakenGroup, never_called, take_newest
from cdmp_ros.ros.robot_model import default_urdf_path

#: A reference whose velocity stays below this for REST_TIME is at rest (rad/s).
REST_SPEED = 0.01
REST_TIME = 0.3
#: Period of the falling obstacle's messages (s): below the adapter's input rate limit.
DROP_PERIOD = 0.06
#: Least distance (m) from the arm to the sphere's surface where it appears
#: (:meth:`DemoRobot.clearance`).
SPAWN_CLEARANCE = 0.02
#: Fraction of the path the drop may wait beyond --drop-at for the arm to clear.
SPAWN_WAIT = 0.15
#: s after the last obstacle message that --wait-adapter waits for the streamer to stream the
#: answer to it (solves take 0.5-3.5 s in the demos); an answer the adapter withheld (its
#: sampled check failed) never comes: the run then ends, and the summary's adapter_current
#: says so.
LAST_ANSWER_WAIT = 15.0


@functools.lru_cache(maxsize=None)
def demo_robot(name: str) -> DemoRobot:
    """The :class:`DemoRobot` ``name`` (read once: the arguments' check and the node share it)."""
    return DemoRobot(name, default_urdf_path())


def parse_args(argv):
    ap = argparse.ArgumentParser(prog='python -m cdmp_ros.ros.demo_driver',
                                 description=__doc__.split('\n\n')[0])
    ap.add_argument('--out', required=True, help='directory for driver.json and the snapshot')
    ap.add_argument('--robot', choices=ROBOTS, default='panda',
                    help='panda (default) or dual_panda (the sphere lands midway between the '
                         'two hands)')
    ap.add_argument('--obstacle-at', type=float, default=0.65,
                    help='fraction of the planned path where the sphere lands (default 0.65)')
    ap.add_argument('--drop-at', type=float, default=0.1,
                    help='fraction of the path covered when the drop starts (default 0.1)')
    ap.add_argument('--drop-height', type=float, default=0.15, help='m (default 0.15)')
    ap.add_argument('--drop-messages', type=int, default=8,
                    help='obstacle messages of the fall, one per DROP_PERIOD (default 8)')
    ap.add_argument('--radius', type=float, default=0.04, help='sphere radius, m (default 0.04)')
    ap.add_argument('--lateral', type=float, default=0.07,
                    help='horizontal offset of the landing point from the path, across the '
                         'path, m (default 0.07: the planned hand would touch the sphere)')
    ap.add_argument('--vertical', type=float, default=0.0,
                    help='vertical offset of the landing point from the path, m (default 0)')
    ap.add_argument('--goal-offset', type=float, nargs='+',
                    default=[0.4, 0.0, 0.0, 0.3, 0.0, -0.3, 0.0],
                    help='rad added to the primitive goal for the goal change, one per joint '
                         '(default, for the Panda: the hand ~25 cm to the left and ~10 cm '
                         'higher, every link outside the field of the sphere at the new goal)')
    ap.add_argument('--motion', choices=('drop', 'cross'), default='drop',
                    help='drop (default): the sphere falls onto the path; cross: it moves '
                         'horizontally across the path through the landing point at '
                         '--cross-speed, published at --cross-rate')
    ap.add_argument('--cross-speed', type=float, default=0.2, help='m/s (default 0.2)')
    ap.add_argument('--cross-rate', type=float, default=30.0,
                    help='obstacle messages per second while crossing (default 30)')
    ap.add_argument('--cross-length', type=float, default=0.6,
                    help='m travelled, centred on the landing point (default 0.6)')
    ap.add_argument('--no-goal-change', action='store_true',
                    help='end after the first motion rests (cdmp demo --kind promp)')
    ap.add_argument('--wait-adapter', action='store_true',
                    help='drop only after the adapter answered the primitive with an '
                         'adapted_primitive (cdmp demo --kind promp)')
    ap.add_argument('--frame', default=None,
                    help="the obstacles' frame (default: the robot's root, panda_link0 or "
                         'world)')
    ap.add_argument('--timeout', type=float, default=40.0, help='s for the whole script')
    args = ap.parse_args(argv)
    n = demo_robot(args.robot).n_dofs
    if not args.no_goal_change and len(args.goal_offset) != n:
        ap.error(f'--goal-offset: expected {n} values (one per joint of {args.robot}), got '
                 f'{len(args.goal_offset)}')
    return args


class DemoDriver(Node):
    def __init__(self, args):
        super().__init__('demo_driver')
        self.args = args
        self.robot = demo_robot(args.robot)
        self.frame = args.frame or self.robot.frame
        self.events = {}
        self.diagnostics = {}
        self.prim = None
        self.prim_id = None
        self.answer = None              # provenance of the newest adapted_primitive
        self.adapter_ready = not args.wait_adapter
        self.final_answer_at = None     # when the answer to the last obstacle streamed
        self.drop_end_at = None
        self.path = None
        self.obstacle = None
        self.ref = None
        self.still_since = None
        self.phase = 'wait_graph'
        self.drop = []
        self.snapshot = None
        self.done = False
        self.obs_pub = self.create_publisher(MarkerArray, 'obstacles', qos.COMMAND)
        self.goal_pub = self.create_publisher(JointState, 'goal', qos.COMMAND)
        self.create_subscription(String, 'primitive', self._on_primitive, qos.LATCHED)
        if args.wait_adapter:
            self.create_subscription(String, 'adapted_primitive', self._on_adapted,
                                     qos.LATCHED)
        # the newest reference is taken at every step (50 Hz): served by the executor, the
        # 500 Hz references took about 40 % of a core, which the demo's adapter then lacked
        self._ref_sub = self.create_subscription(JointState, 'joint_reference', never_called,
                                                 qos.REFERENCE,
                                                 callback_group=ThreadTakenGroup(), raw=True)
        self.create_subscription(DiagnosticArray, DIAGNOSTICS_TOPIC, self._on_diag,
                                 qos.COMMAND)
        self.snap = self.create_client(Trigger, '/sim/snapshot')
        self.refit = self.create_client(Trigger, '/learner/refit')
        self.refit_future = None
        self.t0 = time.monotonic()
        self.create_timer(0.02, self._step)

    def _event(self, name):
        self.events[name] = self.get_clock().now().nanoseconds
        self.get_logger().info(f'{name} at {time.monotonic() - self.t0:.2f} s')

    def _on_primitive(self, msg):
        if self.prim is not None:
            return
        c = self.robot.model
        try:
            prepared = prepare_primitive(msg.data, c.joint_names, 0.01, c.lower, c.upper)
        except Exception as exc:  # noqa: BLE001 -- the demo reports any failure
            self.get_logger().error(f'cannot use the primitive: {exc}')
            return
        self.prim = prepared.prim
        self.prim_id = primitive_id(msg.data)
        self._event('primitive')

    def _on_adapted(self, msg):
        # the newest answer, kept whatever arrives first: it may overtake the primitive here
        try:
            self.answer = read_provenance(json.loads(msg.data).get('metadata'))
        except Exception as exc:  # noqa: BLE001 -- the demo reports any failure
            self.get_logger().error(f'cannot read the adapted_primitive: {exc}')

    def _streams(self, prov) -> bool:
        """The streamer streams the adaptation ``prov`` (its diagnostics'
        ``adapted_generation``)."""
        streamed = next((st['values'].get('adapted_generation')
                         for name, st in self.diagnostics.items()
                         if name.lstrip('/').startswith('streamer')
                         and 'adapted_generation' in st['values']), None)
        return prov is not None and streamed == str(prov.generation)

    def _check_adapter(self) -> bool:
        """``--wait-adapter``: the adapter answered the current primitive and the streamer
        streams that answer."""
        if not self.adapter_ready:
            prov = self.answer
            if prov is not None and self.prim_id is not None and \
                    prov.source_id == self.prim_id and self._streams(prov):
                self.adapter_ready = True
                self._event('adapter_ready')
        return self.adapter_ready

    def _last_answer_streamed(self) -> bool:
        """``--wait-adapter``: the newest adaptation answers the last obstacle message and the
        streamer streams it (a solve may take longer than the rest of the motion: the run
        ends only after the robot followed the answer to the last obstacle message)."""
        if not self.args.wait_adapter:
            return True
        if self.final_answer_at is None:
            prov, last = self.answer, self.events.get('last_obstacle_stamp')
            if prov is not None and prov.trigger_stamp_ns == last and self._streams(prov):
                self.final_answer_at = time.monotonic()
                self._event('last_answer_streamed')
            elif time.monotonic() - self.drop_end_at > LAST_ANSWER_WAIT:
                self.final_answer_at = time.monotonic()
                self._event('last_answer_missing')
                self.get_logger().warning(
                    f'no answer to the last obstacle message streamed within '
                    f'{LAST_ANSWER_WAIT:.0f} s (see the diagnostics of the adapter)')
        return self.final_answer_at is not None

    def _clear_of_arm(self, p) -> bool:
        """A sphere appearing at ``p`` would be clear of the arms: farther than
        SPAWN_CLEARANCE from them (:meth:`DemoRobot.clearance`). The first drop position lies
        above the path, where the arm may still be; a sphere appearing inside the arm is not
        this demo's scenario (and made the streamer's coupling jump the reference, a defect of
        its own)."""
        return self.robot.clearance(self.ref[0], p, self.args.radius) > SPAWN_CLEARANCE

    def _plan(self, start_y):
        traj = self.prim.rollout(0.01, start_y=start_y)
        self.hand_paths = self.robot.hands(traj.Y)                       # (n, arms, 3)
        self.path = between_hands(np.swapaxes(self.hand_paths, 0, 1))
        a = self.args
        p = point_at_progress(self.path, a.obstacle_at)
        p2 = point_at_progress(self.path, min(1.0, a.obstacle_at + 0.05))
        across = np.cross(p2 - p, [0.0, 0.0, 1.0])
        across /= max(np.linalg.norm(across), 1e-9)
        self.obstacle = p + a.lateral * across + [0.0, 0.0, a.vertical]
        self.drop = list(drop_positions(self.obstacle, a.drop_height, a.drop_messages))
        self.across = across

    def _take_ref(self):
        newest, _ = take_newest(self._ref_sub, 4 * qos.REFERENCE.depth)
        if newest is not None:
            self._on_ref(deserialize_message(newest[0], JointState))

    def _on_ref(self, msg):
        q = np.array(msg.position)
        qd = np.array(msg.velocity)
        if q.shape != (self.robot.n_dofs,):
            return
        self.ref = (q, qd)
        now = time.monotonic()
        moving = qd.shape == q.shape and np.abs(qd).max() > REST_SPEED
        if moving:
            self.still_since = None
        elif self.still_since is None:
            self.still_since = now

    def _on_diag(self, msg):
        for st in msg.status:
            self.diagnostics[st.name] = {'level': int.from_bytes(st.level, 'little')
                                         if isinstance(st.level, bytes) else int(st.level),
                                         'message': st.message,
                                         'values': {kv.key: kv.value for kv in st.values}}

    def _rested(self, since: float = 0.0):
        """The reference has been at rest for REST_TIME, counted from ``since`` at the
        earliest (time.monotonic())."""
        return self.still_since is not None and \
            time.monotonic() - max(self.still_since, since) > REST_TIME

    def _publish_sphere(self, p, i):
        m = Marker(ns='demo', id=0, type=Marker.SPHERE, action=Marker.ADD)
        m.header.frame_id = self.frame
        now = self.get_clock().now()
        m.header.stamp = now.to_msg()
        self.events['last_obstacle_stamp'] = now.nanoseconds
        self.n_obstacle_messages = getattr(self, 'n_obstacle_messages', 0) + 1
        m.pose.position.x, m.pose.position.y, m.pose.position.z = (float(v) for v in p)
        m.pose.orientation.w = 1.0
        m.scale.x = m.scale.y = m.scale.z = 2.0 * self.args.radius
        m.color.r, m.color.a = 1.0, 1.0
        self.obs_pub.publish(MarkerArray(markers=[m]))

    def _step(self):
        self._take_ref()
        a = self.args
        if (time.monotonic() - self.t0 > a.timeout and 'timeout_phase' not in self.events
                and self.phase not in ('finish', 'snapshot', 'diagnostics')):
            waiting = {'wait_adapter': ' (the adapter has not answered the primitive, or the '
                                       'streamer does not stream its answer)',
                       'wait_rest_1': '' if self.final_answer_at or not a.wait_adapter else
                       ' (the adapter has not answered the last obstacle message, or the '
                       'streamer does not stream its answer)'}.get(self.phase, '')
            self.get_logger().error(f'timeout in phase {self.phase}{waiting}')
            self.events['timeout_phase'] = self.phase
            self.phase = 'finish'
        if self.phase == 'wait_graph':
            # every node is up before the motion starts, as this node sees the graph (its own
            # subscriptions count): joint_reference by sim, recorder and this node; obstacles
            # by streamer, adapter, sim and recorder; primitive by streamer, adapter, recorder
            # and this node; and this node's publishers matched (goal: streamer, adapter,
            # recorder). Pairs of other nodes may match later (see --wait-adapter).
            ready = (self.refit.service_is_ready() and self.snap.service_is_ready()
                     and self.count_subscribers('joint_reference') >= 3
                     and self.count_publishers('joint_states') >= 1
                     and self.count_subscribers('obstacles') >= 4
                     and self.obs_pub.get_subscription_count() >= 4
                     and self.goal_pub.get_subscription_count() >= 3
                     and self.count_subscribers('primitive') >= 4 and self.ref is not None)
            if ready:
                self._event('graph_ready')
                self.refit_future = self.refit.call_async(Trigger.Request())
                self.phase = 'wait_primitive'
        elif self.phase == 'wait_primitive':
            if self.prim is not None and self.ref is not None:
                self.phase = 'wait_adapter'
        elif self.phase == 'wait_adapter':
            # the adapter's answer restarts the motion from the current state (the streamer
            # switches it in): plan the path, the landing point and the drop from here on, so
            # the sphere lands ahead of the arm however late the answer came
            if self._check_adapter():
                self._plan(self.ref[0])
                self.phase = 'wait_motion'
        elif self.phase == 'wait_motion':
            progress = path_progress(self.path, between_hands(self.robot.hands(self.ref[0])))
            start = progress >= a.drop_at
            if start and a.motion == 'drop' and not self._clear_of_arm(self.drop[0]):
                if self._clear_of_arm(self.obstacle):
                    # the arm is under the fall: the sphere appears at its landing point
                    self.drop = [self.obstacle]
                    self.events['drop_mode'] = 'appeared at the landing point (arm under the fall)'
                elif progress < a.drop_at + SPAWN_WAIT:
                    start = False  # wait for the arm to clear (bounded: then it falls anyway)
            if start:
                self._event('drop_start')
                self.phase = 'drop' if a.motion == 'drop' else 'cross'
                self.cross_t0 = self.next_drop = time.monotonic()
                self.crossed = []
        elif self.phase == 'cross':
            now = time.monotonic()
            if now < self.next_drop:
                return
            self.next_drop += 1.0 / a.cross_rate  # an average of cross_rate messages/s
            travelled = a.cross_speed * (now - self.cross_t0)
            p = self.obstacle + (travelled - 0.5 * a.cross_length) * self.across
            self._publish_sphere(p, 0)
            self.crossed.append([float(v) for v in p])
            if travelled >= a.cross_length:
                self._event('drop_end')
                self.drop_end_at = time.monotonic()
                self.phase = 'wait_rest_1'
        elif self.phase == 'drop':
            if time.monotonic() < getattr(self, 'next_drop', 0.0):
                return
            self.next_drop = time.monotonic() + DROP_PERIOD
            self._publish_sphere(self.drop.pop(0), len(self.drop))
            if not self.drop:
                self._event('drop_end')
                self.drop_end_at = time.monotonic()
                self.phase = 'wait_rest_1'
        elif self.phase == 'wait_rest_1':
            if not self._last_answer_streamed():
                return
            # one reading of the clock: two could disagree (at rest by the second, not by the
            # first) and change the goal of a run asked not to (a CI failure, 2026-12-08)
            if not self._rested(self.final_answer_at or 0.0):
                return
            self._event('first_motion_rest')
            if a.no_goal_change:
                self.phase = 'finish'
            else:
                goal = np.asarray(self.prim.goal_y_) + np.asarray(a.goal_offset)
                msg = JointState(name=self.robot.joint_names,
                                 position=[float(v) for v in goal])
                msg.header.stamp = self.get_clock().now().to_msg()
                self.goal_pub.publish(msg)
                self.events['goal'] = [float(v) for v in goal]
                self._event('goal_change')
                self.still_since = None
                self.phase = 'wait_rest_2'
        elif self.phase == 'wait_rest_2':
            if self._rested() and time.monotonic() - self.t0 > 1.0:
                self._event('second_motion_rest')
                self.phase = 'finish'
        elif self.phase == 'finish':
            self.phase = 'snapshot'
            if self.snap.service_is_ready():
                self.future = self.snap.call_async(Trigger.Request())
                self.snap_deadline = time.monotonic() + 10.0
            else:
                self.get_logger().warning('/sim/snapshot is not available')
                self.future = None
        elif self.phase == 'snapshot':
            if self.future is None or self.future.done() or \
                    time.monotonic() > self.snap_deadline:
                if self.future is not None and self.future.done():
                    res = self.future.result()
                    self.snapshot = res.message if res.success else None
                self.phase = 'diagnostics'
                self.diag_until = time.monotonic() + 1.2  # two more reports of every node
        elif self.phase == 'diagnostics':
            if time.monotonic() > self.diag_until:
                self._write()
                self.done = True

    def _write(self):
        out = {'events_ns': self.events,
               'obstacle': {'center': None if self.obstacle is None else
                            [float(v) for v in self.obstacle], 'radius': self.args.radius,
                            'frame': self.frame},
               'robot': self.robot.name,
               'planned_path': None if self.path is None else self.path[::5].tolist(),
               'planned_hand_paths': None if self.path is None else
               np.swapaxes(self.hand_paths[::5], 0, 1).tolist(),
               'crossing': getattr(self, 'crossed', []),
               'obstacle_messages': getattr(self, 'n_obstacle_messages', 0),
               'snapshot': self.snapshot, 'diagnostics': self.diagnostics}
        with open(os.path.join(self.args.out, 'driver.json'), 'w') as f:
            json.dump(out, f, indent=1)


def main(argv=None) -> int:
    args = parse_args(sys.argv[1:] if argv is None else argv)
    os.makedirs(args.out, exist_ok=True)
    rclpy.init()
    node = DemoDriver(args)
    try:
        while rclpy.ok() and not node.done:
            rclpy.spin_once(node, timeout_sec=0.05)
    except KeyboardInterrupt:
        pass
    finally:
        timed_out = 'timeout_phase' in node.events
        node.destroy_node()
        rclpy.try_shutdown()
    return 1 if timed_out or not node.done else 0


if __name__ == '__main__':
    sys.exit(main())
