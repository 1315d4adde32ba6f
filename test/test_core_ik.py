"""Position IK (damped least squares within limits) against forward kinematics."""
import numpy as np

from cdmp_ros.core.kinematics.ik import solve_position_ik
from cdmp_ros.core.kinematics import planar_chain, PointOfInterest


def test_planar_ik_reaches_reachable_targets_within_limits():
    chain = planar_chain([1.0, 1.0, 1.0], lower=[-2.0] * 3, upper=[2.0] * 3)
    ee = PointOfInterest('ee')
    rng = np.random.default_rng(0)
    for _ in range(20):
        q_true = rng.uniform(-1.5, 1.5, 3)
        target = chain.forward(q_true, [ee])[0]
        res = solve_position_ik(chain, ee, target, np.zeros(3) + 0.1)
        assert res.converged, res
        np.testing.assert_allclose(chain.forward(res.q, [ee])[0], target, atol=1e-4)
        assert np.all(res.q >= chain.lower) and np.all(res.q <= chain.upper)


def test_unreachable_target_reports_not_converged():
    chain = planar_chain([1.0, 1.0])
    res = solve_position_ik(chain, PointOfInterest('ee'), [5.0, 0.0, 0.0], [0.3, 0.3])
    assert not res.converged and res.error > 2.9
