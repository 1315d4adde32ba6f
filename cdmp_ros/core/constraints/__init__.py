"""Probabilistic constraints of the constrained ProMP (paper 003, Sections II-D and II-E)."""
from cdmp_ros.core.constraints.base import Constraint, WeightConstraint
from cdmp_ros.core.constraints.hyperplane import Hyperplane, NonConvexCorner
from cdmp_ros.core.constraints.limits import JointLimit
from cdmp_ros.core.constraints.points import ChainPoint, DifferencePoint, DofPoint, Point
from cdmp_ros.core.constraints.smoothness import SmoothnessConstraint
from cdmp_ros.core.constraints.spheres import (MutualAvoidance, Repeller, UnboundWaypoint,
                                               Waypoint)

__all__ = ['Constraint', 'WeightConstraint', 'Hyperplane', 'NonConvexCorner', 'JointLimit',
           'ChainPoint', 'DifferencePoint', 'DofPoint', 'Point', 'SmoothnessConstraint',
           'MutualAvoidance', 'Repeller', 'UnboundWaypoint', 'Waypoint']
