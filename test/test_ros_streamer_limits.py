"""The streamer as a process runs a primitive within the tighter of its limits and the robot's
(issue 14, item 3): a CDMP wider than the URDF on panda_joint1 (goal beyond the robot's limit)
and narrower on panda_joint2. The diagnostics name the URDF the limits came from and both
differing joints with both values; every reference stays inside the tighter limits, held by
the CDMP's transform (the streamer's last-resort clamp never acts).
"""
import numpy as np
import pytest

from conftest import module_domain
from cdmp_ros.core.primitive_io import dumps_primitive
from node_harness import running
from streamer_harness import (Q_START, TIGHT_LOWER, TIGHT_UPPER, UPPER, Harness, start_streamer,
                              wide_narrow_cdmp)

pytestmark = pytest.mark.ros
DOMAIN = module_domain(31)
STARTUP = 60.0  # s; interpreter + rclpy start-up on a loaded 2-core machine


def test_primitive_limits_are_merged_reported_and_held(tmp_path):
    from std_msgs.msg import String
    from cdmp_ros.ros.robot_model import default_urdf_path
    log = tmp_path / 'streamer.log'
    proc = start_streamer(DOMAIN, ['rate:=100.0', 'diagnostics_period:=0.2'],
                          log_path=str(log), params_file='config/streamer.yaml')
    h = Harness(DOMAIN)
    with running(proc, h, log, lambda: h.n_refs() > 10, STARTUP, 'streamer'):
        assert np.abs(h.last_ref()[2] - Q_START).max() == 0.0
        n0 = h.n_refs()
        h.publish('primitive', String(data=dumps_primitive(wide_narrow_cdmp())))

        def mismatch():
            return h.last_state()[1].get('limit_mismatch', 'none')
        assert h.wait(lambda: mismatch() != 'none', STARTUP), h.last_state()
        text = mismatch()
        assert 'panda_joint1 upper: primitive 3.5, robot 2.9671 -> 2.9671 (robot)' in text
        assert 'panda_joint2 lower: primitive -0.8, robot -1.8326 -> -0.8 (primitive)' in text
        assert 'panda_joint2 upper: primitive 0.4, robot 1.8326 -> 0.4 (primitive)' in text
        m, kv = h.last_state()
        assert kv['limits_source'] == default_urdf_path()
        assert 'the tighter are used' in m
        # the reach towards panda_joint1 = 3.2 ends near the robot's limit, not beyond it
        assert h.wait(lambda: h.last_ref()[2][0] > UPPER[0] - 0.05 or proc.poll() is not None,
                      STARTUP), h.last_ref()
        refs = h.refs_since(n0)
        Q = np.array([r[2] for r in refs])
        assert np.all(Q >= TIGHT_LOWER) and np.all(Q <= TIGHT_UPPER), (
            Q.min(axis=0), Q.max(axis=0))
        assert h.wait(lambda: h.last_state()[1].get('clamped') is not None, 10.0)
        assert h.last_state()[1]['clamped'] == '0'
    assert not h.violations, h.violations[:5]
