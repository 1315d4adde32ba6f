"""The ``robot_description`` topic in the streamer, the adapter and the sim: ROS glue around
:class:`cdmp_ros.ros.robot_model.RobotModelSelector`, which decides.

One subscription of ``robot_description`` (std_msgs/String, the URDF XML; QoS
:data:`~cdmp_ros.ros.qos.LATCHED`: reliable, transient local, keep last 1, as
robot_state_publisher publishes it in Jazzy), serialized (``raw=True``), created by the node
(its topics are declared in its own file) with :meth:`RobotDescriptionInput.on_raw` as the
callback and handed to :meth:`RobotDescriptionInput.load`::

    self.robot = RobotDescriptionInput(self, RobotModelSelector(...))
    model = self.robot.load(self.create_subscription(
        String, 'robot_description', self.robot.on_raw, qos.LATCHED, raw=True))
    ...
    self.robot.attach(self.gate, self.reporter)   # once the gate exists

- at start-up (:meth:`RobotDescriptionInput.load`, in the node's constructor, before the node
  joins an executor), with the ``robot_description`` parameter empty and
  ``robot_description_timeout`` > 0, the node waits up to that long for a message (a
  robot_state_publisher already running delivers its latched message within the discovery
  time: well under a second on an idle host, up to a few seconds measured on a loaded
  2-core one; the wait ends then, and the log says after how long). The message is bounded
  (:func:`~cdmp_ros.ros.input_gate.description_bytes`) before it is deserialised, and the
  model is chosen by the selector: the parameter, the message, else ``urdf_path`` (logged).
  A stop signal ends the wait;
- afterwards (:meth:`RobotDescriptionInput.attach`, once the node has its
  :class:`~cdmp_ros.ros.input_gate.InputGate`) every message passes the gate (rate limit
  :data:`RATE`, the same size bound, deserialisation) and is compared with the model in
  use, which is never swapped: a rejection (not a URDF, other joints) is counted and reported
  as for any input (``<node>: input robot_description``, ``rejected_<category>``); a model
  that differs is logged as a warning; either stays on the state status (WARN, the reason or
  the differences and "a restart of the node applies it") until a message matching the
  model in use arrives;
  diagnostics key ``robot_description_topic`` says what the last message was (``none
  received``, ``in use``, ``matches the model in use (...)``, ``differs from ...``,
  ``rejected: ...``). With the parameter set, a differing topic is reported without a
  warning: the parameter takes precedence by design.
"""
import time
from typing import Optional

from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from std_msgs.msg import String

from cdmp_ros.ros.diagnostics import WARN
from cdmp_ros.ros.input_gate import description_bytes, read_raw
from cdmp_ros.ros.node_main import stop_requested
from cdmp_ros.ros.recorder_take import take_newest
from cdmp_ros.ros.robot_model import REJECTED, RobotModel, RobotModelSelector

#: The topic (relative: remappable, namespaced with the node).
TOPIC = 'robot_description'
#: Messages per second accepted on ``robot_description`` after start-up (bursts of 10): a
#: robot_state_publisher publishes once, and again when its parameter changes.
RATE = 1.0
#: [s] How often a start-up wait looks for a stop signal.
WAIT_SLICE = 0.1
#: Diagnostics key of the last message's verdict, and the standing condition's name.
KEY = 'robot_description_topic'


class RobotDescriptionInput:
    """The ``robot_description`` subscription of a node (see the module docstring).

    Parameters
    ----------
    node : rclpy.node.Node
    selector : RobotModelSelector
    """

    def __init__(self, node, selector: RobotModelSelector):
        self.node = node
        self.selector = selector
        self.size = description_bytes()
        self.gate = None
        self.reporter = None
        self.sub = None
        self._on_raw = None   # the gate's checks, from attach()
        self._taken = 0       # messages taken while waiting at start-up

    def load(self, sub) -> RobotModel:
        """The model the node runs with, waiting for a message of ``sub`` (the node's
        serialized subscription of ``robot_description``, whose callback is :meth:`on_raw`)
        if the selector says so.

        Raises
        ------
        ValidationError
            The parameter or ``urdf_path`` cannot be loaded (the node does not start).
        """
        self.sub = sub
        text, rejection = None, None
        wait_s = self.selector.wait_s
        if wait_s > 0.0:
            t0 = time.monotonic()
            data = self._wait(wait_s)
            if data is not None:
                msg, reason, category = read_raw(String, TOPIC, data, self.size)
                if msg is None:
                    rejection = self.selector.reject(reason, category)
                else:
                    text = msg.data
                self.node.get_logger().info(f'robot_description received '
                                            f'{time.monotonic() - t0:.2f} s after the start of '
                                            f'the wait')
        model, note, warn = self.selector.start(text, rejection)
        if note and warn:
            self.node.get_logger().warning(note)
        elif note:
            self.node.get_logger().info(note)
        return model

    def _wait(self, timeout: float) -> Optional[bytes]:
        """The first message within ``timeout`` s (None: none, or a stop signal)."""
        end = time.monotonic() + timeout
        wait_set = _rclpy.WaitSet(1, 0, 0, 0, 0, 0, self.node.context.handle)
        handle = self.sub.handle
        while True:
            newest, n = take_newest(self.sub, 4)
            if newest is not None:
                self._taken += n
                return newest[0]
            left = end - time.monotonic()
            if left <= 0.0 or stop_requested():
                return None
            with handle:
                wait_set.clear_entities()
                wait_set.add_subscription(handle)
                wait_set.wait(int(min(left, WAIT_SLICE) * 1e9))

    def attach(self, gate, reporter) -> None:
        """From now on, judge every message through ``gate`` and report on ``reporter``
        (call it in the constructor, once the gate exists); a message rejected at start-up is
        reported now."""
        self.gate, self.reporter = gate, reporter
        gate.set_rates({TOPIC: RATE})
        if self._taken:
            gate.received[TOPIC] = gate.received.get(TOPIC, 0) + self._taken
        self._on_raw = gate.raw_callback(String, TOPIC, self._on_message, self.size)
        self._report()
        verdict = self.selector.verdict
        if verdict is not None and verdict.status == REJECTED:
            gate.reject(TOPIC, verdict.message, verdict.category)

    def on_raw(self, data: bytes) -> None:
        """The callback of the subscription: the gate's checks, then the selector."""
        if self._on_raw is not None:  # always, once the node spins
            self._on_raw(data)

    def _on_message(self, msg: String) -> None:
        verdict = self.selector.offer(msg.data)
        self._report()  # before the rejection, which may publish the diagnostics at once
        if verdict.status == REJECTED:
            self.gate.reject(TOPIC, verdict.message, verdict.category)
        elif not verdict.repeat:  # one call site per severity (rclpy refuses a change)
            if verdict.warn:
                self.node.get_logger().warning(f'robot_description topic: {verdict.message}')
            else:
                self.node.get_logger().info(f'robot_description topic: {verdict.message}')

    def _report(self) -> None:
        verdict, state = self.selector.verdict, self.selector.topic_state
        with self.gate.lock:
            self.reporter.values[KEY] = state
            self.reporter.set_condition(KEY, WARN, (f'robot_description topic {state}' if
                                                    verdict is not None and verdict.warn
                                                    else None))
