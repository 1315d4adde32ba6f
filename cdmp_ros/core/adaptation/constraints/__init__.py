"""Probabilistic constraints of the constrained ProMP (paper 003, Sections II-D and II-E)."""
from cdmp_ros.core.adaptation.constraints.base import Constraint, WeightConstraint
from cdmp_ros.core.adaptation.constraints.hyperplane import Hyperplane, NonConvexCorner
from cdmp_ros.core.adaptation.constraints.limits import JointLimit
from cdmp_ros.core.adaptation.constraints.points import (ChainPoint, DifferencePoint, DofPoint,
                                                         Point)
from cdmp_ros.core.adaptation.constraints.smoothness import SmoothnessConstraint
from cdmp_ros.core.adaptation.constraints.spheres import (MutualAvoidance, Repeller,
                                                          UnboundWaypoint, Waypoint)

__all__ = ['Constraint', 'WeightConstraint', 'Hyperplane', 'NonConvexCorner', 'JointLimit',
           'ChainPoint', 'DifferencePoint', 'DofPoint', 'Point', 'SmoothnessConstraint',
           'MutualAvoidance', 'Repeller', 'UnboundWaypoint', 'Waypoint']
