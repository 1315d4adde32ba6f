"""``streamer`` executable: the fast path, joint_reference at ``rate`` from the active primitive.

Run: ``ros2 run cdmp_ros streamer --ros-args --params-file config/streamer.yaml`` or
``python -m cdmp_ros.nodes.streamer --ros-args -p rate:=1000.0``. The logic is in
:mod:`cdmp_ros.core.streaming`, the ROS glue in :mod:`cdmp_ros.ros.streamer_node`.
"""
import sys

from cdmp_ros.ros.node_main import run_node


def main(args=None) -> int:
    from cdmp_ros.ros.streamer_node import StreamerNode
    return run_node(StreamerNode, args)


if __name__ == '__main__':
    sys.exit(main())
