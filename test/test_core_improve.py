"""PI2 improvement of a learned (C)DMP (cdmp_ros.core.dmp.improve): the scripted cost against
independent computations, the improvement itself, reproducibility, and the guarantee that every
exploratory CDMP rollout stays inside the limits (a plain DMP with the same noise leaves them)."""
import os
import threading

import numpy as np
import pytest

from cdmp_ros.core.dmp.dmp import limit_usage
from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.dmp.improve import CostConfig, ImproveConfig, Improver, ScriptedCost
from cdmp_ros.core.learning import fit_primitive
from conftest import REPO_ROOT

JOINTS = tuple(f'panda_joint{i}' for i in range(1, 8))


@pytest.fixture(scope='module')
def chain():
    import pybullet_data
    from cdmp_ros.core.kinematics import panda_chain
    return panda_chain(os.path.join(pybullet_data.getDataPath(), 'franka_panda', 'panda.urdf'))


@pytest.fixture(scope='module')
def demos():
    from cdmp_ros.bag import read_demonstrations
    return [(T, Y) for T, Y, _ in read_demonstrations(os.path.join(REPO_ROOT, 'bags',
                                                                   'panda_reach'))]


@pytest.fixture(scope='module')
def narrow(demos):
    """The demonstrated range +- 0.1 rad: limits that exploration noise reaches."""
    Ys = np.vstack([Y for _, Y in demos])
    return Ys.min(0) - 0.1, Ys.max(0) + 0.1


# -- the scripted cost ---------------------------------------------------------------------------
def test_jerk_term_matches_the_closed_form_of_a_cubic(chain):
    dt = 0.01
    t = np.arange(101) * dt
    a = np.array([0.3, -0.2, 0.1, 0.05, 0.0, 0.4, -0.1])
    Y = np.array([0.0, -0.5, 0.0, -2.0, 0.0, 1.5, 0.7]) + np.outer(t ** 3, a)  # jerk = 6 a
    cfg = CostConfig(jerk_weight=2.0, obstacle_weight=0.0)
    terms = ScriptedCost(chain, cfg, Y[-1], dt).terms(Y)
    assert np.all(terms['jerk'][:3] == 0.0)
    np.testing.assert_allclose(terms['jerk'][3:], 2.0 * 36.0 * (a @ a) * dt, rtol=1e-6)
    assert terms['goal'] == 0.0 and np.all(terms['obstacle'] == 0.0)


def test_goal_term_and_terminal_placement(chain):
    dt = 0.01
    Y = np.tile(np.array([0.0, -0.5, 0.0, -2.0, 0.0, 1.5, 0.7]), (50, 1))
    goal = Y[-1] + np.array([0.1, 0.0, -0.2, 0.0, 0.0, 0.0, 0.05])
    cost = ScriptedCost(chain, CostConfig(goal_weight=7.0, obstacle_weight=0.0), goal, dt)
    r = cost.per_step(Y)
    assert r[-1] == pytest.approx(7.0 * (0.01 + 0.04 + 0.0025), rel=1e-12)
    assert np.all(r[:-1] == 0.0)


def test_obstacle_term_uses_the_end_effector_position_of_pybullet():
    """Independent forward kinematics: pybullet's tool centre point of the same URDF."""
    import pybullet
    import pybullet_data
    from cdmp_ros.core.kinematics import PANDA_EE_OFFSET, panda_chain
    urdf = os.path.join(pybullet_data.getDataPath(), 'franka_panda', 'panda.urdf')
    chain = panda_chain(urdf)
    q = np.array([0.3, -0.4, 0.2, -2.0, 0.1, 1.7, 0.6])
    cid = pybullet.connect(pybullet.DIRECT)
    try:
        body = pybullet.loadURDF(urdf, useFixedBase=True, physicsClientId=cid)
        names = {pybullet.getJointInfo(body, j, physicsClientId=cid)[1].decode(): j
                 for j in range(pybullet.getNumJoints(body, physicsClientId=cid))}
        for n, v in zip(JOINTS, q):
            pybullet.resetJointState(body, names[n], v, physicsClientId=cid)
        hand = next(j for j in range(pybullet.getNumJoints(body, physicsClientId=cid))
                    if pybullet.getJointInfo(body, j, physicsClientId=cid)[12] == b'panda_hand')
        st = pybullet.getLinkState(body, hand, computeForwardKinematics=True,
                                   physicsClientId=cid)
        R = np.array(pybullet.getMatrixFromQuaternion(st[5])).reshape(3, 3)
        tcp = np.array(st[4]) + R @ np.array(PANDA_EE_OFFSET)
    finally:
        pybullet.disconnect(cid)
    centre = tcp + np.array([0.03, 0.0, 0.0])  # 3 cm from the tool centre point
    cfg = CostConfig(obstacle_weight=5.0, obstacle_x=centre[0], obstacle_y=centre[1],
                     obstacle_z=centre[2], obstacle_radius=0.02, obstacle_clearance=0.04,
                     jerk_weight=0.0, goal_weight=0.0)
    terms = ScriptedCost(chain, cfg, q, 0.01).terms(np.tile(q, (3, 1)))
    # violation = radius + clearance - distance = 0.06 - 0.03; pybullet's link states carry
    # about 1e-8 m of rounding, hence the tolerances
    np.testing.assert_allclose(terms['obstacle'], 5.0 * 0.03 ** 2 * 0.01, rtol=1e-4)
    assert terms['min_distance'] == pytest.approx(0.01, abs=1e-6)


# -- improvement --------------------------------------------------------------------------------
def test_pi2_lowers_the_cost_and_is_reproducible(chain, demos):
    prim = fit_primitive('cdmp', demos, JOINTS, chain.lower, chain.upper)
    w0 = prim.weights_.copy()
    cfg = ImproveConfig(updates=10)
    cost = ScriptedCost(chain, CostConfig(), prim.goal_y_, cfg.dt)
    reports = []
    res = Improver(prim, cfg, cost, chain.lower, chain.upper).run(reports.append)
    assert np.array_equal(prim.weights_, w0)  # the input primitive is left untouched
    assert [r.update for r in reports] == list(range(1, 11))
    assert res.updates == 10 and res.rollouts == 50 and res.rollouts_outside_limits == 0
    assert res.cost_after < 0.3 * res.cost_before
    tr = res.primitive.rollout(dt=cfg.dt)
    terms = cost.terms(tr.Y)
    assert terms['min_distance'] > 0.0  # the path was bent around the obstacle
    assert terms['goal'] < 0.01          # and still reaches the goal
    assert res.primitive.metadata['pi2']['cost_after'] == res.cost_after
    again = Improver(prim, cfg, cost, chain.lower, chain.upper).run()
    assert np.array_equal(again.primitive.weights_, res.primitive.weights_)
    other = Improver(prim, ImproveConfig(updates=10, seed=1), cost, chain.lower,
                     chain.upper).run()
    assert not np.array_equal(other.primitive.weights_, res.primitive.weights_)


@pytest.mark.parametrize('std', [100.0, 1000.0])
def test_every_exploratory_cdmp_rollout_stays_inside_the_limits(chain, demos, narrow, std):
    lo, hi = narrow
    seen = []

    def recording_cost(traj):
        seen.append(limit_usage(traj.Y, lo, hi))
        return np.zeros(traj.Y.shape[0]) + float(np.sum(traj.Y[-1] ** 2))

    def run(kind):
        seen.clear()
        prim = fit_primitive(kind, demos, JOINTS, lo, hi)
        cfg = ImproveConfig(updates=6, rollouts_per_update=8, shape_std=std, goal_std=0.2)
        res = Improver(prim, cfg, recording_cost, lo, hi).run()
        return res, list(seen)

    res, usage = run('cdmp')
    assert len(usage) == 6 * 8 + 2  # every rollout (and the two evaluations) was checked
    assert max(usage) < 1.0 and res.rollouts_outside_limits == 0
    assert max(usage) > 0.95  # the noise did push towards the limits
    assert res.max_limit_usage == pytest.approx(max(usage[1:-1]))
    res_dmp, usage_dmp = run('dmp')  # the same exploration on a plain DMP leaves them
    assert res_dmp.rollouts_outside_limits > 0 and max(usage_dmp) > 1.0


def test_stop_event_ends_early_and_promp_is_refused(chain, demos):
    prim = fit_primitive('cdmp', demos, JOINTS, chain.lower, chain.upper)
    cfg = ImproveConfig(updates=50)
    stop = threading.Event()
    cost = ScriptedCost(chain, CostConfig(), prim.goal_y_, cfg.dt)
    imp = Improver(prim, cfg, cost, chain.lower, chain.upper)
    res = imp.run(lambda rep: stop.set() if rep.update == 3 else None, stop)
    assert res.stopped and res.updates == 3
    from cdmp_ros.core.promp.promp import ProMP, RbfBasis
    promp = ProMP(7, RbfBasis.uniform(5), joint_names=JOINTS)
    with pytest.raises(ValidationError, match='PI2 improves dmp and cdmp primitives, got '
                                              "'promp'"):
        Improver(promp, cfg, cost, chain.lower, chain.upper)


def test_a_bad_cost_function_is_reported(chain, demos):
    prim = fit_primitive('cdmp', demos, JOINTS, chain.lower, chain.upper)
    imp = Improver(prim, ImproveConfig(updates=1), lambda tr: np.full(3, np.nan),
                   chain.lower, chain.upper)
    with pytest.raises(ValidationError, match='cost: expected 201 finite per-step costs'):
        imp.run()


@pytest.mark.parametrize('kw, text', [
    (dict(rollouts_per_update=1), 'rollouts_per_update: expected a value in [2, 10000]'),
    (dict(cost='mujoco'), "cost: expected one of ['scripted', 'sim'], got 'mujoco'"),
    (dict(noise_decay=0.0), 'noise_decay: expected a value in'),
    (dict(dt=1.0), 'dt: expected a value in'),
    (dict(updates=2.5), 'updates: expected int'),
])
def test_improve_config_is_validated(kw, text):
    with pytest.raises(ValidationError) as e:
        ImproveConfig(**kw)
    assert text in str(e.value)
