"""``recorder``: record topics into a rosbag2-compatible MCAP bag.

    ros2 run cdmp_ros recorder --ros-args -p output:=my_bag -p topics:="['/joint_states']"

SIGINT / SIGTERM stop it cleanly: every message received is written and the bag closed.
"""
import sys

from cdmp_ros.ros.bag_bridge import RecorderNode
from cdmp_ros.ros.node_main import run_node


def main(args=None) -> int:
    return run_node(RecorderNode, args, graceful=True)


if __name__ == '__main__':
    sys.exit(main())
