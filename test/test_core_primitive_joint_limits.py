"""A primitive file may carry joint_limits (ROS convention): validated with the field named,
kept through a file round trip, and merged tighter-of-two with the robot's by the streamer's
output stage while that primitive is active."""
import json

import numpy as np
import pytest

from cdmp_ros.core.errors import PrimitiveFileError
from cdmp_ros.core.joint_limits import panda_limits
from cdmp_ros.core.primitive_io import dumps_primitive, loads_primitive
from cdmp_ros.core.run_metrics import stamped_differences
from cdmp_ros.core.streaming.config import StreamerConfig
from cdmp_ros.core.streaming.primitives import prepare_primitive
from cdmp_ros.core.streaming.streamer import ReferenceStreamer
from streamer_harness import reach_cdmp

LIMITS = {'panda_joint2': {'has_acceleration_limits': True, 'max_acceleration': 1.5,
                           'max_effort': 87.0},
          'panda_joint5': {'has_jerk_limits': True, 'max_jerk': 400}}


def _text(limits=LIMITS, duration=0.8):
    prim = reach_cdmp(duration=duration)
    prim.joint_limits = limits
    return dumps_primitive(prim)


def test_round_trip_keeps_the_joint_limits():
    prim = loads_primitive(_text())
    assert prim.joint_limits == LIMITS


@pytest.mark.parametrize('joint, entry, field', [
    ('panda_joint2', {'has_acceleration_limits': True}, 'panda_joint2.max_acceleration'),
    ('panda_joint2', {'has_jerk_limits': 'yes', 'max_jerk': 3.0}, 'has_jerk_limits'),
    ('panda_joint2', {'max_speed': 3.0}, 'max_speed'),
    ('elbow', {'has_jerk_limits': True, 'max_jerk': 3.0}, 'elbow'),
    ('panda_joint2', {'has_velocity_limits': True, 'max_velocity': 0.0}, 'max_velocity'),
])
def test_bad_joint_limits_are_refused_naming_the_field(joint, entry, field):
    d = json.loads(_text())
    d['joint_limits'] = {joint: entry}
    with pytest.raises(PrimitiveFileError, match=field):
        loads_primitive(json.dumps(d))


def test_the_streamer_keeps_the_primitive_limits_while_it_is_active():
    robot = panda_limits()
    cfg = StreamerConfig(joint_states_timeout=0.0)
    st = ReferenceStreamer(robot.lower, robot.upper, cfg, limits=robot)
    prep = prepare_primitive(_text(), robot.joint_names, cfg.dt, robot.lower, robot.upper,
                             robot.velocity)
    assert prep.kinematic.acceleration[1] == 1.5 and prep.kinematic.jerk[4] == 400.0
    st.activate(prep, 0.0)
    assert st.active_limits.acceleration[1] == 1.5
    assert st.active_limits.acceleration[0] == robot.acceleration[0]
    P = []
    for k in range(1500):
        st.advance(1, k * cfg.dt)
        P.append(list(st.out_y))
    P = np.array(P)
    stamps = np.arange(len(P)) * round(cfg.dt * 1e9)
    V, A, J = stamped_differences(stamps, P)
    assert np.abs(A[:, 1]).max() <= 1.5 * (1 + 1e-9)
    assert np.abs(A[:, 1]).max() > 1.4  # the reach needed it: the limit was what held it
    assert np.abs(J[:, 4]).max() <= 400.0 * (1 + 1e-9)
    assert np.all(np.abs(A) <= robot.acceleration * (1 + 1e-9))
    # the next primitive without joint_limits: the robot's again
    plain = prepare_primitive(dumps_primitive(reach_cdmp()), robot.joint_names, cfg.dt,
                              robot.lower, robot.upper, robot.velocity)
    st.activate(plain, 3.0)
    np.testing.assert_array_equal(st.active_limits.acceleration, robot.acceleration)
    np.testing.assert_array_equal(st.stage.max_acceleration, robot.acceleration)
