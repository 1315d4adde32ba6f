"""``streamer`` executable: the fast path, joint_reference at ``rate`` from the active primitive.

Run: ``ros2 run cdmp_ros streamer --ros-args --params-file config/streamer.yaml`` or
``python -m cdmp_ros.nodes.streamer --ros-args -p rate:=1000.0``. The logic is in
:mod:`cdmp_ros.core.streaming.streamer`, the ROS glue in :mod:`cdmp_ros.ros.streamer_node`.

The references are published by the node's own tick thread (sleeping to absolute deadlines,
optionally under SCHED_FIFO: ``-p realtime_priority:=50``, see
:mod:`cdmp_ros.ros.streamer_node`). The subscriptions, the diagnostics timer and the parameter
services are spun by rclpy's EventsExecutor (far less CPU per timer callback than the
SingleThreadedExecutor, which rebuilds its wait set per callback; it also runs the tick with
``tick_thread:=false``), in the
spin loop of :func:`cdmp_ros.ros.node_main.run_node` (SIGINT/SIGTERM set a flag;
``EventsExecutor.spin()`` does not return on SIGINT in this rclpy); the node's ``close()``
stops the tick thread before the node is destroyed.

BLAS is limited to one thread (``OPENBLAS_NUM_THREADS=1``, ``OMP_NUM_THREADS=1`` unless set by
the caller) before numpy is imported, as in :mod:`cdmp_ros.nodes.adapter`: the streamer's
numerical work is small, and a second BLAS thread would compete with the adapter's solve for
the cores.
"""
import os
import sys

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')
os.environ.setdefault('OMP_NUM_THREADS', '1')

from cdmp_ros.ros.node_main import catch_stop_signals, make_executor, run_node  # noqa: E402


def main(args=None) -> int:
    catch_stop_signals()  # first: a signal during the imports below ends the node cleanly
    from cdmp_ros.ros.streamer_node import StreamerNode
    return run_node(StreamerNode, args, executor=make_executor())


if __name__ == '__main__':
    sys.exit(main())
