"""cdmp_ros.sim: the pybullet simulation layer (robots, control laws, obstacles, camera).

Public API (see each module's docstring)::

    World, WorldConfig                      # world.py: private DIRECT client, stepping, pacing
    Robot                                    # robot.py: state, reference, dynamics
    RobotSpec, panda_spec, planar_arm_spec,  # robots.py: what to load
    add_dual_panda, planar_arm_urdf
    PositionController, ComputedTorqueController, PDController,
    JointLimitAvoidingController, make_controller (+ their *Gains)   # control.py
    ObstacleInfo, LinkDistance, DistanceReport, Contact              # obstacles.py
    CameraConfig, render, snapshot                                   # camera.py
"""
from cdmp_ros.sim.camera import CameraConfig, render, snapshot
from cdmp_ros.sim.control import (ComputedTorqueController, ComputedTorqueGains,
                                  JointLimitAvoidingController, JointLimitAvoidingGains,
                                  make_controller, PDController, PDGains, PositionControlGains,
                                  PositionController)
from cdmp_ros.sim.obstacles import Contact, DistanceReport, LinkDistance, ObstacleInfo
from cdmp_ros.sim.robot import JointReference, Robot
from cdmp_ros.sim.robot_specs import (add_dual_panda, panda_spec, planar_arm_spec, planar_arm_urdf,
                                      planar_arm_urdf_path, RobotSpec)
from cdmp_ros.sim.world import World, WorldConfig

__all__ = [
    'CameraConfig', 'render', 'snapshot',
    'ComputedTorqueController', 'ComputedTorqueGains', 'JointLimitAvoidingController',
    'JointLimitAvoidingGains', 'make_controller', 'PDController', 'PDGains',
    'PositionControlGains', 'PositionController',
    'Contact', 'DistanceReport', 'LinkDistance', 'ObstacleInfo',
    'JointReference', 'Robot',
    'add_dual_panda', 'panda_spec', 'planar_arm_spec', 'planar_arm_urdf', 'planar_arm_urdf_path',
    'RobotSpec', 'World', 'WorldConfig',
]
