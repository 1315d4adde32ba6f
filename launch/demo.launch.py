"""The node graph of ``cdmp demo``, the same graph as ``config/graphs/demo.yaml``.

    ros2 launch cdmp_ros demo.launch.py
    ros2 service call /learner/refit std_srvs/srv/Trigger   # fit from bags/, start the reach

sim (pybullet Panda, computed-torque control), streamer at 500 Hz with link avoidance,
adapter, learner (waits for ``~/refit``, as the demo's scripted user calls it) and recorder
(every topic into ``rosbag2_<date>`` in the working directory). ``cdmp bringup demo`` starts
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
        node('streamer', 'streamer.yaml', **{
            'rate': 500.0,
            # the arm from the elbow to the hand avoids obstacles too: see demo.yaml
            'coupling_capsule_links': ['panda_link3', 'panda_link4', 'panda_link5',
                                       'panda_link6', 'panda_link7', 'panda_hand'],
            'coupling_links': ['panda_link7'],
            'damping.epsilon': 0.1,
            'coupling.link_radius': 0.06,
            'repeller.gain': 0.03,
            'repeller.influence_distance': 0.25}),
        node('recorder', 'bag.yaml'),
        node('adapter', 'adapter.yaml'),
        # the URDF's soft limits (safety_controller) as the task's limits: see demo.yaml
        node('learner', 'learner.yaml', **{
            'fit_on_start': False,
            'limits.lower': [-2.8973, -1.7628, -2.8973, -3.0718, -2.8973, -0.0175, -2.8973],
            'limits.upper': [2.8973, 1.7628, 2.8973, -0.0698, 2.8973, 3.7525, 2.8973]}),
    ])
