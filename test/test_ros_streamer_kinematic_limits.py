"""The streamer as a process publishes references inside the joint_limits.* it is given (issue
28): a fast reach, a sphere next to the tool and a goal beyond the limits, with panda_joint2's
acceleration limit lowered by a parameter. Judged on the published messages, differenced on
their stamps, as the robot's controller sees them; the diagnostics report the limits in force
and where they came from."""
import numpy as np
import pytest

from conftest import module_domain
from cdmp_ros.core.joint_limits import shipped_limits
from cdmp_ros.core.kinematics import PointOfInterest, panda_chain
from cdmp_ros.core.primitive_io import dumps_primitive
from cdmp_ros.core.run_metrics import kinematic_report
from cdmp_ros.ros.robot_model import default_urdf_path
from streamer_harness import Harness, reach_cdmp, start_streamer, stop_process
from node_harness import assert_clean_stop

pytestmark = pytest.mark.ros
DOMAIN = module_domain(47)
STARTUP = 60.0


@pytest.mark.parametrize('rate', [500.0, 1000.0])
def test_published_references_keep_the_given_limits(tmp_path, rate):
    from geometry_msgs.msg import Point
    from sensor_msgs.msg import JointState
    from std_msgs.msg import String
    from visualization_msgs.msg import Marker, MarkerArray
    log = tmp_path / 'streamer.log'
    proc = start_streamer(DOMAIN, [f'rate:={rate}', 'diagnostics_period:=0.2',
                                   'joint_limits.panda_joint2.max_acceleration:=2.0'],
                          log_path=str(log), params_file='config/streamer.yaml')
    h = Harness(DOMAIN)
    chain = panda_chain(default_urdf_path())
    entries = {'panda_joint2': {'has_acceleration_limits': True, 'max_acceleration': 2.0}}
    expected = shipped_limits(chain.joint_names, chain.lower, chain.upper,
                              chain.velocity_limits, 'urdf')
    expected = expected.merged(shipped_limits(chain.joint_names, chain.lower, chain.upper,
                                              None, 'param', entries))
    try:
        assert h.wait(lambda: h.n_refs() > 10 or proc.poll() is not None, STARTUP), \
            log.read_text()
        assert h.wait(lambda: 'limits' in h.last_state()[1], STARTUP)
        kv = h.last_state()[1]
        assert 'acceleration [15, 2, 10, 12.5, 15, 20, 20]' in kv['limits'], kv['limits']
        assert 'joint_limits parameters' in kv['limits_sources']
        n0 = h.n_refs()
        h.publish('primitive', String(data=dumps_primitive(reach_cdmp(duration=0.6))))
        # the tool is moving: a sphere appears right next to it
        assert h.wait(lambda: np.abs(h.last_ref()[3]).max() > 0.5, STARTUP)
        x = chain.forward(h.last_ref()[2][None], [PointOfInterest('ee')])[0, 0]
        m = Marker(type=Marker.SPHERE, action=Marker.ADD, id=1)
        m.pose.position = Point(x=float(x[0]) + 0.08, y=float(x[1]), z=float(x[2]))
        m.pose.orientation.w = 1.0
        m.scale.x = m.scale.y = m.scale.z = 0.1
        h.publish('obstacles', MarkerArray(markers=[m]))
        n1 = h.n_refs()
        assert h.wait(lambda: h.n_refs() > n1 + int(0.5 * rate), STARTUP)
        goal = JointState(name=list(chain.joint_names),
                          position=(chain.upper + 0.5).tolist())  # beyond: clipped
        h.publish('goal', goal)
        n2 = h.n_refs()
        assert h.wait(lambda: h.n_refs() > n2 + int(2.0 * rate), STARTUP)
        refs = h.refs_since(n0)
    finally:
        h.close()
        code = stop_process(proc)
    assert_clean_stop(code, log.read_text(), 'streamer')
    assert not h.violations, h.violations[:5]
    stamps = np.array([r[1] for r in refs])
    Q = np.array([r[2] for r in refs])
    Qd = np.array([r[3] for r in refs])
    # the stamps are the slots of the grid (a message the test's subscription missed leaves a
    # gap of whole periods: the differences are divided by the actual gaps)
    gaps = np.diff(stamps)
    off = np.flatnonzero((gaps % round(1e9 / rate) != 0) | (gaps <= 0))
    assert off.size == 0, [(int(i), gaps[max(0, i - 3):i + 4].tolist()) for i in off[:5]]
    rep = kinematic_report(stamps, Q, expected, tolerance=1e-6)
    assert rep['ok'], rep
    # the stream moved and the acceleration of joint 2 reached its lowered limit
    assert rep['acceleration']['worst_ratio'] > 0.9, rep
    # the published velocity is the one the positions imply
    one = gaps == round(1e9 / rate)
    implied = np.diff(Q, axis=0) * rate
    np.testing.assert_allclose(Qd[1:][one], implied[one], atol=1e-9 * rate)
