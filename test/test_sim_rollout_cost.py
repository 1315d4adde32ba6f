"""The ``sim`` rollout cost of the learner's ~/improve (cdmp_ros.sim.rollout_cost): rollouts
tracked by the Panda in pybullet, cost recomputed independently from what was measured."""
import os

import numpy as np
import pytest

from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.dmp.improve import CostConfig, ImproveConfig, Improver, ScriptedCost
from cdmp_ros.core.learning import fit_primitive
from conftest import REPO_ROOT

JOINTS = tuple(f'panda_joint{i}' for i in range(1, 8))


@pytest.fixture(scope='module')
def setup():
    import pybullet_data
    from cdmp_ros.bag import read_demonstrations
    from cdmp_ros.core.kinematics import panda_chain
    chain = panda_chain(os.path.join(pybullet_data.getDataPath(), 'franka_panda', 'panda.urdf'))
    demos = [(T, Y) for T, Y, _ in read_demonstrations(os.path.join(REPO_ROOT, 'bags',
                                                                    'panda_reach'))]
    return chain, fit_primitive('cdmp', demos, JOINTS, chain.lower, chain.upper)


def test_sim_cost_is_the_scripted_cost_of_the_measured_motion_plus_torques(setup):
    from cdmp_ros.sim.rollout_cost import SimRolloutCost
    chain, prim = setup
    dt = 0.01
    scripted = ScriptedCost(chain, CostConfig(), prim.goal_y_, dt)
    tr = prim.rollout(dt=dt)
    with SimRolloutCost(scripted, torque_weight=1e-3, joint_names=JOINTS) as sim:
        r = sim(tr)
        q, tau = sim.last_q, sim.last_torques
    assert r.shape == (tr.Y.shape[0],) and np.all(np.isfinite(r))
    assert np.abs(q - tr.Y).max() < 0.02        # computed torque tracks the reference
    assert np.abs(tau).max() > 1.0              # gravity alone needs torque
    expected = scripted.per_step(q) + 1e-3 * np.sum(tau ** 2, axis=1) * dt
    np.testing.assert_allclose(r, expected, rtol=1e-12)
    assert abs(r.sum() - scripted.per_step(tr.Y).sum()) < 0.2 * r.sum() + 1.0


def test_improving_against_the_sim_lowers_its_cost(setup):
    from cdmp_ros.sim.rollout_cost import SimRolloutCost
    chain, prim = setup
    cfg = ImproveConfig(updates=4, rollouts_per_update=4, cost='sim')
    scripted = ScriptedCost(chain, CostConfig(), prim.goal_y_, cfg.dt)
    with SimRolloutCost(scripted, joint_names=JOINTS) as sim:
        res = Improver(prim, cfg, sim, chain.lower, chain.upper).run()
    assert res.rollouts == 16 and res.rollouts_outside_limits == 0
    assert res.cost_after < res.cost_before


def test_sim_cost_needs_the_panda_joints(setup):
    from cdmp_ros.sim.rollout_cost import SimRolloutCost
    chain, prim = setup
    with pytest.raises(ValidationError, match='the sim cost needs the Panda joints'):
        SimRolloutCost(ScriptedCost(chain, CostConfig(), prim.goal_y_, 0.01),
                       joint_names=[f'j{i}' for i in range(7)])
