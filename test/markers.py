"""Obstacle markers (visualization_msgs/Marker) of the node tests, and the table of malformed
markers that every node subscribing ``obstacles`` (adapter, streamer, sim) rejects with the
same diagnostics text (:mod:`cdmp_ros.ros.convert` parses them for all three)."""
import time


def marker(ns='obs', id=1, kind='sphere', position=(0.6, 0.0, 0.5), size=0.1,
           frame='panda_link0', **kw):
    """An unstamped ADD marker: a SPHERE (``kind`` 'sphere') or CUBE of edge / diameter
    ``size`` [m] at ``position`` in ``frame``, identity orientation.

    Other keywords set fields: ``scale_x`` / ``scale_y`` / ``scale_z``, ``x`` (the position's
    x), ``stamp`` (the header stamp: now + this many seconds), any Marker attribute (``type``,
    ``action``, ``id``)."""
    from visualization_msgs.msg import Marker
    m = Marker(ns=ns, id=id, type=Marker.SPHERE if kind == 'sphere' else Marker.CUBE,
               action=Marker.ADD)
    m.header.frame_id = frame
    m.pose.position.x, m.pose.position.y, m.pose.position.z = map(float, position)
    m.pose.orientation.w = 1.0
    m.scale.x = m.scale.y = m.scale.z = float(size)
    for k, v in kw.items():
        if k.startswith('scale_'):
            setattr(m.scale, k[6:], v)
        elif k == 'x':
            m.pose.position.x = v
        elif k == 'stamp':
            m.header.stamp.sec = int(time.time() + v)
        else:
            setattr(m, k, v)
    return m


#: case -> (keywords of :func:`marker` that break a valid marker, expected diagnostics text)
MARKER_CASES = {
    'negative_scale': (dict(scale_x=-0.1), 'scale.x: expected a finite positive size'),
    'zero_scale': (dict(scale_x=0.0), 'scale.x: expected a finite positive size'),
    'huge_scale': (dict(scale_x=1e6), 'scale.x: expected at most 10.0 m'),
    'nan_scale': (dict(scale_x=float('nan')), 'scale.x: expected a finite positive size'),
    'nan_position': (dict(x=float('nan')), 'pose.position.x: expected a finite value'),
    'far_away': (dict(x=1e9), 'expected within 100.0 m'),
    'unknown_type': (dict(type=3), 'type: expected SPHERE (2) or CUBE (1), got 3 (CYLINDER)'),
    'unsupported_type': (dict(type=11), 'got 11 (TRIANGLE_LIST)'),
    'unknown_action': (dict(action=5), 'action: expected ADD/MODIFY (0), DELETE (2) or '
                                       'DELETEALL (3), got 5'),
    'delete_unknown': (dict(action=2, id=999), 'DELETE of unknown obstacle'),
    'cube_bad_scale': (dict(type=1, scale_z=-1.0), 'scale.z: expected a finite positive size'),
    'other_frame': (dict(frame='camera'), "expected the robot base frame 'panda_link0'"),
    'past_stamp': (dict(stamp=-86400), 'markers[0].header.stamp: stamp 86400'),
    'future_stamp': (dict(stamp=3600), 'in the future'),
}


def bad_marker(case):
    """(marker, expected diagnostics text) of :data:`MARKER_CASES` [case]: a 0.1 m sphere
    (ns 'bad', id 7) 2 m in front of the robot, broken as the case says."""
    kw, text = MARKER_CASES[case]
    return marker(**dict(dict(ns='bad', id=7, position=(2.0, 0.0, 0.0)), **kw)), text
