"""The cdmp_ros node graph: sim (optional), streamer, adapter and learner.

    ros2 launch cdmp_ros cdmp.launch.py robot:=panda rate:=500.0 use_sim:=true
    ros2 launch cdmp_ros cdmp.launch.py robot:=planar4   # the planar 4-link arm, nothing else
    ros2 launch cdmp_ros cdmp.launch.py robot:=dual_panda   # two Pandas (paper 003, III-C)
    ros2 launch cdmp_ros cdmp.launch.py use_sim:=false namespace:=/arm   # a real robot

Every node reads its parameter file from ``share/cdmp_ros/config`` (override one with
``<node>_params:=/path/to/file.yaml``); ``rate`` sets the streamer's ``rate`` and ``robot`` the
sim's ``robot``, ``robot_description`` (URDF XML) the model every node takes its joint limits
from. The files of ``config/`` are the Panda's; for ``robot:=planar4`` every node also gets
``config/robots/planar4/<node>.yaml`` after its own file (a later file wins): the joint
names, ``urdf_path: package://cdmp_ros/urdf/planar4.urdf`` (the file the sim loads),
``tip_link``, ``tcp_offset``, base frame, coupling links, initial pose and demonstration bags
of the planar arm. ``robot:=dual_panda`` likewise gets ``config/robots/dual_panda/``: 14
joints, ``urdf/dual_panda.urdf`` (the sim's cell as one URDF), ``tip_links`` (one chain per
arm), base frame ``world``, both arms' coupling links and ``bags/dual_panda``. With
``use_sim:=false`` the sim node is not started: the streamer, the
adapter and the learner read the measured state from the robot's own ``joint_states``. The
graph without ROS is ``cdmp bringup`` (``config/graphs/<robot>.yaml`` is ``robot:=<robot>``);
``demo.launch.py`` is the graph of ``cdmp demo``.
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, GroupAction, OpaqueFunction
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node, PushRosNamespace
from launch_ros.parameter_descriptions import ParameterValue

PACKAGE = 'cdmp_ros'
#: Node (and executable) name -> its parameter file in config/ (and in config/robots/<robot>/).
PARAMS = {'sim': 'sim.yaml', 'streamer': 'streamer.yaml', 'adapter': 'adapter.yaml',
          'learner': 'learner.yaml'}
#: Robots with parameter files in config/robots/<robot>/, applied after each node's own file
#: (the files of config/ are the Panda's).
ROBOT_OVERLAYS = ('planar4', 'dual_panda')


def generate_launch_description():
    config = os.path.join(get_package_share_directory(PACKAGE), 'config')
    args = [
        DeclareLaunchArgument(
            'robot', default_value='panda', choices=['panda', 'dual_panda', 'planar4'],
            description="Robot simulated by the sim node (its 'robot' parameter). The files "
                        'in config/ are written for the Panda; planar4 and dual_panda add '
                        "config/robots/<robot>/<node>.yaml after every node's file (its joints, "
                        'URDF, tip links, frames, initial pose, bags).'),
        DeclareLaunchArgument(
            'rate', default_value='500.0',
            description='Hz at which the streamer publishes joint_reference (1 kHz supported).'),
        DeclareLaunchArgument(
            'namespace', default_value='',
            description="Namespace of every node and topic, e.g. '/arm' ('' = none)."),
        DeclareLaunchArgument(
            'robot_description', default_value='',
            description='URDF XML of the robot that runs (as robot_state_publisher takes it, '
                        'e.g. robot_description:="$(xacro my_robot.urdf.xacro)"); given to '
                        'every node, which then take their joint limits and kinematics from it '
                        "instead of urdf_path (the sim: robot 'panda' only). '' = the "
                        "parameter files' urdf_path."),
        DeclareLaunchArgument(
            'use_sim', default_value='true', choices=['true', 'false'],
            description='Start the pybullet sim node (false: a real robot publishes '
                        'joint_states and consumes the references).'),
    ]
    overlay = "the robot's file of config/robots/<robot>/, if any, is applied after it"
    args += [DeclareLaunchArgument(
        f'{node}_params', default_value=os.path.join(config, file),
        description=f'Parameter file of the {node} node ({overlay}).')
        for node, file in PARAMS.items()]

    description = {'robot_description': ParameterValue(
        LaunchConfiguration('robot_description'), value_type=str)}

    def graph(context):
        robot = LaunchConfiguration('robot').perform(context)

        def params(node):
            files = [LaunchConfiguration(f'{node}_params')]
            if robot in ROBOT_OVERLAYS:
                files.append(os.path.join(config, 'robots', robot, PARAMS[node]))
            return files

        nodes = [
            Node(package=PACKAGE, executable='sim', name='sim', output='screen',
                 parameters=[*params('sim'), description,
                             {'robot': ParameterValue(LaunchConfiguration('robot'),
                                                      value_type=str)}],
                 condition=IfCondition(LaunchConfiguration('use_sim'))),
            Node(package=PACKAGE, executable='streamer', name='streamer', output='screen',
                 parameters=[*params('streamer'), description,
                             {'rate': ParameterValue(LaunchConfiguration('rate'),
                                                     value_type=float)}]),
            Node(package=PACKAGE, executable='adapter', name='adapter', output='screen',
                 parameters=[*params('adapter'), description]),
            Node(package=PACKAGE, executable='learner', name='learner', output='screen',
                 parameters=[*params('learner'), description]),
        ]
        return [GroupAction([PushRosNamespace(LaunchConfiguration('namespace')), *nodes])]

    return LaunchDescription(args + [OpaqueFunction(function=graph)])
