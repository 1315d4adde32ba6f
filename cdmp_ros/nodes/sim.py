"""``sim`` executable: the pybullet robot tracking ``joint_reference``.

Run: ``ros2 run cdmp_ros sim --ros-args --params-file config/sim.yaml`` or
``python -m cdmp_ros.nodes.sim --ros-args -p control:=computed_torque``. The simulation is in
:mod:`cdmp_ros.sim.live` (configuration :mod:`cdmp_ros.sim.node_config`), the ROS glue in
:mod:`cdmp_ros.ros.sim_node`.

Spun by rclpy's EventsExecutor (as the streamer; far less CPU per timer callback than the
SingleThreadedExecutor) in the spin loop of :func:`cdmp_ros.ros.node_main.run_node`:
SIGINT / SIGTERM end the node with exit code 0; a bad parameter at start-up ends it with
exit code 2 and the reason on stderr.
"""
import sys

from cdmp_ros.ros.node_main import catch_stop_signals, make_executor, run_node


def main(args=None) -> int:
    catch_stop_signals()  # first: a signal during the imports below ends the node cleanly
    from cdmp_ros.ros.sim_node import SimNode
    return run_node(SimNode, args, executor=make_executor())


if __name__ == '__main__':
    sys.exit(main())
