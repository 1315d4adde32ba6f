"""``player``: replay a bag with its original timing.

    ros2 run cdmp_ros player --ros-args -p bag:=bags/panda_reach/demo_00 -p rate:=2.0 \\
        -p loop:=true -p clock:=true -r /demonstration:=/goal

A corrupted or truncated bag is refused before anything is published (exit code 2).
"""
import sys

from cdmp_ros.ros.node_main import catch_stop_signals, run_node


def main(args=None) -> int:
    catch_stop_signals()  # first: a signal during the imports below ends the node cleanly
    from cdmp_ros.ros.bag_bridge import PlayerNode
    return run_node(PlayerNode, args, graceful=True)


if __name__ == '__main__':
    sys.exit(main())
