"""``recorder``: record topics into a rosbag2-compatible MCAP bag.

    ros2 run cdmp_ros recorder --ros-args -p output:=my_bag -p topics:="['/joint_states']"

SIGINT / SIGTERM stop it cleanly: every message received is written and the bag closed.
Unless a Fast DDS profile file is already set in the environment, the recorder process loads
config/recorder_fastdds.xml (deeper receive buffers, loopback-only UDP; see
:func:`cdmp_ros.ros.recorder_take.apply_dds_profile`); ``CDMP_RECORDER_DDS_PROFILE=''``
disables it.
"""
import sys

from cdmp_ros.ros.node_main import catch_stop_signals, run_node


def main(args=None) -> int:
    catch_stop_signals()  # first: a signal during the imports below ends the node cleanly
    from cdmp_ros.ros.bag_bridge import RecorderNode
    from cdmp_ros.ros.recorder_take import apply_dds_profile
    apply_dds_profile()  # before rclpy.init: Fast DDS reads it when the participant is made
    return run_node(RecorderNode, args)


if __name__ == '__main__':
    sys.exit(main())
