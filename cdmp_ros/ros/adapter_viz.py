"""The adapter's ``visualization`` topic (visualization_msgs/MarkerArray, for RViz / Foxglove).

One MarkerArray replaces the previous one (its first marker is a DELETEALL):

- ns ``path``: LINE_STRIP of the planned end-effector path (the ProMP mean, or the DMP/CDMP
  rollout from the current state), green;
- ns ``uncertainty`` (ProMPs): one SPHERE per sample time, diameter 2 * band_sigma standard
  deviations of the end effector (linearised, :func:`cdmp_ros.core.adaptation.requests.ee_band`);
- ns ``obstacles``: the obstacles as the adapter understood them (SPHERE / CUBE), red;
- ns ``goal``: the Cartesian goal (goal_point), if any.
"""
from typing import Optional, Sequence, Tuple

import numpy as np
from geometry_msgs.msg import Point
from std_msgs.msg import ColorRGBA
from visualization_msgs.msg import Marker, MarkerArray

from cdmp_ros.core.kinematics import OrientedBox, Sphere


def _marker(ns: str, mid: int, mtype: int, frame: str, stamp, rgba) -> Marker:
    m = Marker(ns=ns, id=mid, type=mtype, action=Marker.ADD)
    m.header.frame_id = frame
    m.header.stamp = stamp
    m.pose.orientation.w = 1.0
    m.color = ColorRGBA(r=float(rgba[0]), g=float(rgba[1]), b=float(rgba[2]),
                        a=float(rgba[3]))
    return m


def build_markers(frame: str, stamp, path: Optional[np.ndarray] = None,
                  band: Optional[Tuple[np.ndarray, np.ndarray]] = None,
                  obstacles: Sequence = (), goal_point: Optional[np.ndarray] = None
                  ) -> MarkerArray:
    """The MarkerArray described in the module docstring.

    Parameters
    ----------
    frame : str
        Robot base frame.
    stamp : builtin_interfaces/Time
    path : (n, 3), optional
    band : ((k, 3), (k,)), optional
        Centres and radii of the uncertainty spheres.
    obstacles : sequence of Sphere or Box
    goal_point : (3,), optional
    """
    clear = Marker(action=Marker.DELETEALL)
    clear.header.frame_id = frame
    clear.header.stamp = stamp
    out = [clear]
    if path is not None and len(path) >= 2:
        m = _marker('path', 0, Marker.LINE_STRIP, frame, stamp, (0.1, 0.8, 0.2, 1.0))
        m.scale.x = 0.01
        m.points = [Point(x=float(p[0]), y=float(p[1]), z=float(p[2])) for p in path]
        out.append(m)
    if band is not None:
        for i, (c, r) in enumerate(zip(*band)):
            m = _marker('uncertainty', i, Marker.SPHERE, frame, stamp, (0.2, 0.4, 1.0, 0.25))
            m.pose.position = Point(x=float(c[0]), y=float(c[1]), z=float(c[2]))
            m.scale.x = m.scale.y = m.scale.z = max(2.0 * float(r), 1e-4)
            out.append(m)
    for i, ob in enumerate(obstacles):
        if isinstance(ob, Sphere):
            m = _marker('obstacles', i, Marker.SPHERE, frame, stamp, (1.0, 0.1, 0.1, 0.5))
            c = ob.center
            m.scale.x = m.scale.y = m.scale.z = max(2.0 * ob.radius, 1e-4)
        elif isinstance(ob, OrientedBox):
            m = _marker('obstacles', i, Marker.CUBE, frame, stamp, (1.0, 0.1, 0.1, 0.5))
            c = ob.center
            m.scale.x, m.scale.y, m.scale.z = (float(v) for v in ob.size)
            o = m.pose.orientation
            o.x, o.y, o.z, o.w = ob.quaternion()
        else:
            m = _marker('obstacles', i, Marker.CUBE, frame, stamp, (1.0, 0.1, 0.1, 0.5))
            lo, hi = np.asarray(ob.lower), np.asarray(ob.upper)
            c = 0.5 * (lo + hi)
            m.scale.x, m.scale.y, m.scale.z = (float(v) for v in hi - lo)
        m.pose.position = Point(x=float(c[0]), y=float(c[1]), z=float(c[2]))
        out.append(m)
    if goal_point is not None:
        m = _marker('goal', 0, Marker.SPHERE, frame, stamp, (1.0, 0.8, 0.0, 0.9))
        m.pose.position = Point(x=float(goal_point[0]), y=float(goal_point[1]),
                                z=float(goal_point[2]))
        m.scale.x = m.scale.y = m.scale.z = 0.03
        out.append(m)
    return MarkerArray(markers=out)
