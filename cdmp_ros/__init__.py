"""cdmp_ros: constrained movement primitives (CDMP, constrained ProMP) for ROS 2.

The numerical core (:mod:`cdmp_ros.core`) depends on numpy and scipy only.
"""

__version__ = '0.1.0'
