"""The node graph of ``cdmp demo``, the same graph as ``config/graphs/demo.yaml``.

    ros2 launch cdmp_ros demo.launch.py
    ros2 service call /learner/refit std_srvs/srv/Trigger   # fit from bags/, start the reach

sim (pybullet Panda, computed-torque control), streamer at 500 Hz (the whole arm avoids
obstacles: config/streamer.yaml), adapter, learner (waits for ``~/refit``, as the demo's
scripted user calls it) and recorder (every topic into ``rosbag2_<date>`` in the working
directory). ``cdmp bringup demo`` starts
the same graph without ROS; test/test_ros_launch.py keeps the two in step.
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch_ros.actions import Node

PACKAGE = 'cdmp_ros'


def generate_launch_description():
    config = os.path.join(get_package_share_directory(PACKAGE), 'config')

    def node(name, params_file, **parameters):
        return Node(package=PACKAGE, executable=name, name=name, output='screen',
                    parameters=[os.path.join(config, params_file)] +
                    ([parameters] if parameters else []))

    return LaunchDescription([
        # the simulated robot stands for hardware with its own real-time controller: see
        # demo.yaml
        node('sim', 'sim.yaml', control='computed_torque', real_time=True,
             realtime_priority=45),
        # the coupling of streamer.yaml: capsules around the arm from the elbow to the fingers
        node('streamer', 'streamer.yaml', rate=500.0),
        node('recorder', 'bag.yaml'),
        node('adapter', 'adapter.yaml'),
        # the URDF's soft limits (safety_controller) as the task's limits: see demo.yaml
        node('learner', 'learner.yaml', **{
            'fit_on_start': False,
            'limits.lower': [-2.8973, -1.7628, -2.8973, -3.0718, -2.8973, -0.0175, -2.8973],
            'limits.upper': [2.8973, 1.7628, 2.8973, -0.0698, 2.8973, 3.7525, 2.8973]}),
    ])
