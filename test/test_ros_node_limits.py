"""The joint limits of the robot that runs, in the adapter, the learner and the sim (issue 14,
item 3), as processes: each is given a ``robot_description`` whose ``panda_joint1`` range
(+-2.5) is tighter than pybullet_data's Panda (+-2.9671) and than the primitive's or the
parameters' limits, and reports ``limits_source: robot_description`` and every differing bound
(``limit_mismatch``) on diagnostics.

- adapter: a ProMP whose limits are the pybullet URDF's, narrowed on panda_joint2; a goal
  beyond the robot's panda_joint1 limit. The adapted ProMP carries the tighter limits of the
  two and its mean (and the bulk of its samples) stays inside them.
- learner: ``limits.lower/upper`` wider than the robot on panda_joint1, narrower on
  panda_joint2: the fitted CDMP, and a ProMP fitted after ``kind:=promp``, have the tighter
  of the two as their file's ``limits``.
- sim: a reference beyond the robot's panda_joint1 limit is clipped into it (reported) and the
  arm settles there, not at the requested position.
"""
import json

import numpy as np
import pytest
import yaml

from conftest import module_domain, wait_for
from node_harness import LOWER, UPPER, running

pytestmark = pytest.mark.ros
DOMAIN = module_domain(33)
STARTUP = 60.0  # s; interpreter + rclpy start-up on a loaded 2-core machine
ROBOT_J1 = 2.5  # the robot_description's panda_joint1 limit [rad]


def robot_description():
    """pybullet_data's Panda URDF with panda_joint1 limited to +-ROBOT_J1."""
    from cdmp_ros.ros.robot_model import default_urdf_path
    with open(default_urdf_path()) as f:
        text = f.read()
    old = 'lower="-2.9671" upper="2.9671"'
    assert text.count(old) >= 1  # panda_joint1 is the first joint of the file
    return text.replace(old, f'lower="-{ROBOT_J1}" upper="{ROBOT_J1}"', 1)


def params_file(tmp_path, node=None):
    """A parameter file giving ``robot_description`` to every node (or to ``node``)."""
    path = tmp_path / 'robot_description.yaml'
    key = '/**' if node is None else f'/**/{node}'
    path.write_text(yaml.safe_dump({key: {'ros__parameters': {
        'robot_description': robot_description()}}}))
    return str(path)


def robot_limits():
    lo, hi = LOWER.copy(), UPPER.copy()
    lo[0], hi[0] = -ROBOT_J1, ROBOT_J1
    return lo, hi


def _list(v):
    return '[' + ', '.join(f'{x:.4f}' for x in v) + ']'


def test_adapter_adapts_within_the_tighter_limits(tmp_path):
    from std_msgs.msg import String
    from adapter_harness import Harness, Q_GOAL, Q_START, reach_promp, start_adapter
    from cdmp_ros.core.primitive_io import dumps_primitive, primitive_from_dict
    log = tmp_path / 'adapter.log'
    proc = start_adapter(DOMAIN, ['diagnostics_period:=0.2'], log_path=str(log),
                         params_file=params_file(tmp_path))
    h = Harness(DOMAIN)

    def state():
        st = h.states_since(0.0)
        return st[-1][2] if st else {}
    with running(proc, h, log, state, STARTUP, 'adapter'):
        assert state()['limits_source'] == 'robot_description'
        assert state()['limit_mismatch'] == 'none'
        # the ProMP's limits: pybullet's URDF (wider than the robot on panda_joint1),
        # narrowed on panda_joint2
        p_lo, p_hi = LOWER.copy(), UPPER.copy()
        p_lo[1], p_hi[1] = -0.8, 0.4
        d = json.loads(dumps_primitive(reach_promp()))
        d['limits'] = {'lower': p_lo.tolist(), 'upper': p_hi.tolist()}
        text = json.dumps(d)
        h.publish('primitive', String(data=text))
        assert h.wait(lambda: state().get('limit_mismatch', 'none') != 'none', STARTUP), (
            h.states_since(0.0)[-3:], log.read_text())
        mismatch = state()['limit_mismatch']
        assert 'panda_joint1 lower: primitive -2.9671, robot -2.5 -> -2.5 (robot)' in mismatch
        assert 'panda_joint1 upper: primitive 2.9671, robot 2.5 -> 2.5 (robot)' in mismatch
        assert 'panda_joint2 lower: primitive -0.8, robot -1.8326 -> -0.8 (primitive)' in mismatch
        assert 'panda_joint2 upper: primitive 0.4, robot 1.8326 -> 0.4 (primitive)' in mismatch
        assert len(mismatch.split('; ')) == 4, mismatch
        # a goal beyond the robot's panda_joint1 limit (inside the primitive's)
        n0 = h.n_adapted()
        goal = Q_GOAL.copy()
        goal[0] = 2.8
        h.robot_q = Q_START
        h.publish('goal', h.joint_state(goal))
        out = h.wait_adapted(n0, STARTUP, trigger='goal', source=text)
        assert out is not None, (h.states_since(0.0)[-3:], log.read_text())
        assert out['metadata']['adapter']['outcome'] == 'converged'
        tight_lo, tight_hi = np.maximum(robot_limits()[0], p_lo), np.minimum(robot_limits()[1],
                                                                             p_hi)
        assert out['limits']['lower'] == pytest.approx(tight_lo.tolist(), abs=1e-12)
        assert out['limits']['upper'] == pytest.approx(tight_hi.tolist(), abs=1e-12)
        adapted = primitive_from_dict(out)
        s = np.linspace(0.0, 1.0, 101)
        mean = adapted.mean(s)
        assert np.all(mean >= tight_lo) and np.all(mean <= tight_hi), (mean.min(0), mean.max(0))
        assert mean[-1, 0] > 2.3  # the goal pulled towards the robot's limit, not beyond it
        Y = adapted.sample_trajectories(s, 200, np.random.default_rng(0))
        inside = np.all((Y >= tight_lo) & (Y <= tight_hi), axis=(1, 2)).mean()
        assert inside >= 0.9, inside
        # the mismatch is in the log too
        assert wait_for(lambda: 'the primitive limits differ from the robot' in log.read_text(),
                        10.0), log.read_text()


def test_learner_fits_within_the_tighter_limits(tmp_path):
    from learner_harness import LearnerHarness, start_learner
    log = tmp_path / 'learner.log'
    lo, hi = LOWER.copy(), UPPER.copy()
    lo[0], hi[0] = -3.0, 3.0       # wider than the robot
    lo[1], hi[1] = -1.0, 0.6       # narrower (the bag demonstrations span [-0.79, 0.34])
    proc = start_learner(DOMAIN, ['diagnostics_period:=0.2', f'limits.lower:={_list(lo)}',
                                  f'limits.upper:={_list(hi)}'],
                         log_path=str(log), params_file=params_file(tmp_path, 'learner'))
    h = LearnerHarness(DOMAIN)
    with running(proc, h, log, lambda: h.n_primitives() > 0, STARTUP, 'learner'):
        d = h.last_primitive()
        tight_lo, tight_hi = np.maximum(robot_limits()[0], lo), np.minimum(robot_limits()[1], hi)
        assert d['kind'] == 'cdmp'
        assert d['limits']['lower'] == pytest.approx(tight_lo.tolist(), abs=1e-12)
        assert d['limits']['upper'] == pytest.approx(tight_hi.tolist(), abs=1e-12)
        assert h.wait(lambda: 'limit_mismatch' in h.last_state()[1], STARTUP)
        kv = h.last_state()[1]
        assert kv['limits_source'] == 'robot_description'
        mismatch = kv['limit_mismatch']
        assert 'panda_joint1 upper: primitive 3, robot 2.5 -> 2.5 (robot)' in mismatch
        assert 'panda_joint2 lower: primitive -1, robot -1.8326 -> -1 (primitive)' in mismatch
        assert len(mismatch.split('; ')) == 4, mismatch
        assert 'limits.lower/upper differ from the robot' in log.read_text()
        # a ProMP fitted by the learner carries the same limits in its file
        assert h.set_parameter('kind', 'promp').successful
        n0 = h.n_primitives()
        assert h.call('refit').success
        assert h.wait(lambda: h.n_primitives() > n0, STARTUP)
        d = h.last_primitive()
        assert d['kind'] == 'promp'
        assert d['limits']['lower'] == pytest.approx(tight_lo.tolist(), abs=1e-12)
        assert d['limits']['upper'] == pytest.approx(tight_hi.tolist(), abs=1e-12)


def test_sim_holds_the_robot_description_limits(tmp_path):
    from sim_harness import PANDA_HOME, SimHarness, start_sim
    from conftest import last_reason
    log = tmp_path / 'sim.log'
    proc = start_sim(DOMAIN, ['diagnostics_period:=0.2', 'reference_timeout:=0.0'],
                     log_path=str(log), params_file=params_file(tmp_path, 'sim'))
    h = SimHarness(DOMAIN)
    with running(proc, h, log, lambda: h.last_state()[0] is not None, STARTUP, 'sim'):
        kv = h.last_state()[1]
        assert kv['limits_source'] == 'robot_description'
        assert kv['limit_mismatch'] == ('panda_joint1 lower: pybullet -2.9671, robot -2.5 -> '
                                        '-2.5; panda_joint1 upper: pybullet 2.9671, robot 2.5 '
                                        '-> 2.5')
        q = PANDA_HOME.copy()
        q[0] = 2.8  # inside pybullet's model, beyond the robot's limit
        h.publish('joint_reference', h.reference(q))
        assert h.wait(lambda: "'panda_joint1' is outside the limits [-2.5, 2.5]"
                      in (last_reason(h, 'joint_reference') or ''), STARTUP), (
            h.last_state(), log.read_text())
        # the arm settles at the clipped reference, the robot's limit (a step of 2.5 rad
        # overshoots on the way: the pybullet motors are not limit-aware)

        def settled():
            q = h.q()
            return q is not None and abs(q[0] - ROBOT_J1) < 0.005
        assert h.wait(settled, STARTUP), h.q()
        t = h.states_since(0.0)[-1][0]
        assert h.wait(lambda: len(h.states_since(t)) > 50, STARTUP)
        Q = np.array([s[3] for s in h.states_since(t)])
        assert np.abs(Q[:, 0] - ROBOT_J1).max() < 0.01, (Q[:, 0].min(), Q[:, 0].max())
