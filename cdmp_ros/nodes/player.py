"""``player``: replay a bag with its original timing.

    ros2 run cdmp_ros player --ros-args -p bag:=bags/panda_reach/demo_00 -p rate:=2.0 \\
        -p loop:=true -p clock:=true -p wait_subscribers:=5.0 -r /demonstration:=/goal

A corrupted or truncated bag is refused before anything is published (exit code 2). Before
playing, the player waits up to ``wait_subscribers`` seconds (default 10; 0 = not at all) for
a subscriber on every topic it plays, ``/clock`` included, then plays anyway, naming the topics
without one; after the last message it waits up to ``ack_timeout`` seconds for every reliable
subscriber to acknowledge every message, then ends (cdmp_ros/ros/bag_bridge.py).
"""
import sys

from cdmp_ros.ros.node_main import catch_stop_signals, run_node


def main(args=None) -> int:
    catch_stop_signals()  # first: a signal during the imports below ends the node cleanly
    from cdmp_ros.ros.bag_bridge import PlayerNode
    return run_node(PlayerNode, args)


if __name__ == '__main__':
    sys.exit(main())
