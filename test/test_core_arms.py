"""A robot of several arms (core/kinematics/arms.py) as the nodes load it (tip_links): limits in
the node's joint order, one obstacle coupling per arm, the braking distance of the arm that
needs most, and the adapter's constraints per arm, each checked against the single arm."""
import dataclasses

import numpy as np
import pytest

from conftest import REPO_ROOT

from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.kinematics import PANDA_JOINTS, PointOfInterest, Sphere
from cdmp_ros.core.kinematics.arms import Arms, arms_of, split_by_arm
from cdmp_ros.ros.robot_model import load_chain

URDF = f'{REPO_ROOT}/urdf/dual_panda.urdf'
TIPS = ('left_panda_hand', 'right_panda_hand')
LEFT = [f'left_{j}' for j in PANDA_JOINTS]
RIGHT = [f'right_{j}' for j in PANDA_JOINTS]


@pytest.fixture(scope='module')
def arms():
    return load_chain(URDF, LEFT + RIGHT, TIPS)


@pytest.fixture(scope='module')
def single():
    return [load_chain(URDF, names, tip) for names, tip in ((LEFT, TIPS[0]), (RIGHT, TIPS[1]))]


def test_the_limits_follow_the_nodes_joint_order(single):
    names = RIGHT[::-1] + LEFT[3:] + LEFT[:3]
    model = load_chain(URDF, names, TIPS)
    assert isinstance(model, Arms) and model.joint_names == names
    for arm, idx in arms_of(model):
        assert [names[i] for i in idx] == arm.joint_names
        ref = single[0] if arm.joint_names == LEFT else single[1]
        np.testing.assert_array_equal(model.lower[idx], ref.lower)
        np.testing.assert_array_equal(model.upper[idx], ref.upper)
        np.testing.assert_array_equal(model.velocity_limits[idx], ref.velocity_limits)
    assert model.arm_of('right_panda_link4') == 1 and model.arm_of('left_panda_hand') == 0


@pytest.mark.parametrize('names, tips, match', [
    (LEFT + RIGHT[:-1], TIPS, r"joint_names: .*missing \['right_panda_joint7'\]"),
    (LEFT + RIGHT + ['extra'], TIPS, r"joint_names: .*not of an arm \['extra'\]"),
    (LEFT + RIGHT, ('left_panda_hand', 'nowhere'), r'tip_links\[1\]: .*nowhere'),
    (LEFT + RIGHT, ('left_panda_hand', 'left_panda_hand'), r'tip_links\[1\]: .*twice'),
    (LEFT + RIGHT, ('left_panda_hand', 'left_panda_link4'), r'belong to more than one arm'),
])
def test_a_bad_robot_of_arms_is_refused_naming_the_parameter(names, tips, match):
    with pytest.raises(ValidationError, match=match):
        load_chain(URDF, names, tips)


def test_links_are_split_by_arm(arms):
    assert split_by_arm(arms, ['right_panda_link3', 'left_panda_hand', 'left_panda_link4'],
                        'links') == [['left_panda_hand', 'left_panda_link4'],
                                     ['right_panda_link3']]
    with pytest.raises(ValidationError, match=r"links\[1\]: 'panda_link4' is not a link"):
        split_by_arm(arms, ['left_panda_link4', 'panda_link4'], 'links')


def _streamer_configs(**changes):
    from cdmp_ros.core.streaming.streamer import PARAMETER_SECTIONS
    configs = {name: cls() for name, cls in PARAMETER_SECTIONS}
    robot = dict(joint_names=tuple(LEFT + RIGHT), tip_links=TIPS,
                 coupling_links=('left_panda_link7', 'right_panda_link7'))
    configs[''] = dataclasses.replace(configs[''], **{**robot, **changes})
    return configs


def test_each_arm_couples_as_it_would_alone(arms, single):
    """The coupling of the arms, at random states beside spheres near both arms, is each
    arm's own coupling (the same links and capsules) on its joints."""
    from cdmp_ros.core.kinematics.capsules import collision_capsules
    from cdmp_ros.core.streaming.streamer import coupling_of
    cap_links = ['left_panda_link5', 'right_panda_link5', 'right_panda_hand']
    capsules = collision_capsules(URDF, cap_links)
    both = coupling_of(arms, _streamer_configs(), capsules)
    alone = [coupling_of(single[0], _streamer_configs(joint_names=tuple(LEFT), tip_links=(),
                                                      tip_link=TIPS[0],
                                                      coupling_links=('left_panda_link7',)),
                         capsules[:1]),
             coupling_of(single[1], _streamer_configs(joint_names=tuple(RIGHT), tip_links=(),
                                                      tip_link=TIPS[1],
                                                      coupling_links=('right_panda_link7',)),
                         capsules[1:])]
    rng = np.random.default_rng(0)
    moved = 0
    for _ in range(20):
        q = rng.uniform(arms.lower, arms.upper)
        qd = rng.normal(0.0, 0.3, 14)
        # spheres 10-20 cm from each hand
        hands = [a.forward(q[i], [PointOfInterest('ee')])[0] for a, i in arms_of(arms)]
        obstacles = [Sphere(h + rng.uniform(-0.2, 0.2, 3), 0.05) for h in hands]
        got = np.array(both.joint_acceleration(q.tolist(), qd.tolist(), obstacles))
        for (arm, idx), c in zip(arms_of(arms), alone):
            want = c.joint_acceleration(q[idx].tolist(), qd[idx].tolist(), obstacles)
            np.testing.assert_allclose(got[idx], want, rtol=0, atol=1e-12)
        moved += bool(np.any(got != 0.0))
        assert len(both.last_distances) == len(alone[0].last_distances) + len(
            alone[1].last_distances)
    assert moved >= 5, moved   # the spheres were near enough to act


def test_the_braking_distance_is_the_larger_arms(arms):
    from types import SimpleNamespace

    from cdmp_ros.core.coupling.braking import primitive_braking_distance
    T = np.linspace(0.0, 2.0, 101)[:, None]
    mid = 0.5 * (arms.lower + arms.upper)
    amp = np.r_[np.full(7, 0.1), np.full(7, 0.4)]      # the right arm moves faster
    traj = SimpleNamespace(Y=mid + amp * np.sin(np.pi * T), Yd=amp * np.pi * np.cos(np.pi * T))

    def motion(idx):
        return SimpleNamespace(rollout=lambda dt: SimpleNamespace(Y=traj.Y[:, idx],
                                                                  Yd=traj.Yd[:, idx]))
    A, J = np.full(14, 10.0), np.full(14, 5000.0)
    both = primitive_braking_distance(motion(np.arange(14)), arms, A, J)
    each = [primitive_braking_distance(motion(idx), arm, A[idx], J[idx])
            for arm, idx in arms_of(arms)]
    assert both == max(each) and each[1] > each[0] > 0.0


@pytest.fixture(scope='module')
def dual_prior():
    from cdmp_ros.experiments.exp_dual_arm import learn_prior, load_demonstrations
    return learn_prior(load_demonstrations())


def test_the_adapters_constraints_are_per_arm(arms, single, dual_prior):
    """A sphere on the left hand's mean path: its constraints act on the left arm's tool
    centre point and avoid_links of either arm, each point over its own arm's joints, at the
    positions the single arm computes."""
    from cdmp_ros.core.adaptation.config import AdaptRequestConfig
    from cdmp_ros.core.adaptation.requests import AdaptRequest, build_problem
    grid = np.linspace(0.0, 1.0, 21)
    mean = dual_prior.mean(grid)
    hand = single[0].forward(mean[:, :7], [PointOfInterest('ee')])[10, 0]
    cfg = AdaptRequestConfig(avoid_links=('right_panda_link4', 'left_panda_link4'), n_steps=21,
                             influence_distance=5.0)    # every point, the far arm's too
    built = build_problem(AdaptRequest(dual_prior, (Sphere(hand, 0.05),)), arms, cfg)
    near = build_problem(AdaptRequest(dual_prior, (Sphere(hand, 0.05),)), arms,
                         dataclasses.replace(cfg, influence_distance=0.3))
    assert 'obstacle_0_left_panda_hand_tcp' in {c.name for c in near.constraints}
    assert len(near.constraints) < len(built.constraints)   # the points that stay far: none
    obstacle = {c.name: c for c in built.constraints if c.name.startswith('obstacle_0_')}
    assert sorted(obstacle) == sorted(['obstacle_0_left_panda_hand_tcp',
                                       'obstacle_0_left_panda_link4',
                                       'obstacle_0_right_panda_hand_tcp',
                                       'obstacle_0_right_panda_link4'])
    for name, c in obstacle.items():
        left = name.startswith('obstacle_0_left')
        assert c.point.dofs == tuple(range(0, 7) if left else range(7, 14))
        ref = single[0 if left else 1]
        link = 'ee' if name.endswith('_tcp') else name[len('obstacle_0_'):]
        np.testing.assert_allclose(c.point.forward(mean[:, list(c.point.dofs)]),
                                   ref.forward(mean[:, list(c.point.dofs)],
                                               [PointOfInterest(link)])[:, 0], atol=1e-12)
    limits = [c for c in built.constraints if c.name.startswith('limit_')]
    assert [c.name for c in limits] == [f'limit_{j}' for j in LEFT + RIGHT]


def test_a_sphere_at_the_left_hand_is_avoided_by_the_left_arm(arms, single, dual_prior):
    """The adaptation of the two-arm ProMP converges, passes its sampled verification, and
    moves the left hand's mean path out of the sphere (with its margin)."""
    from cdmp_ros.core.adaptation.config import AdaptRequestConfig
    from cdmp_ros.core.adaptation.requests import AdaptRequest, run_request
    grid = np.linspace(0.0, 1.0, 41)
    hand = single[0].forward(dual_prior.mean(grid)[:, :7], [PointOfInterest('ee')])[20, 0]
    cfg = AdaptRequestConfig(n_steps=41, avoid_links=('left_panda_link4', 'left_panda_hand',
                                                      'right_panda_link4', 'right_panda_hand'))
    sphere = Sphere(hand + [0.0, 0.0, 0.03], 0.05)
    res = run_request(AdaptRequest(dual_prior, (sphere,)), arms, cfg)
    assert res.outcome == 'converged', res.report.status
    assert res.report.verification is not None and res.report.verification.holds
    X = single[0].forward(res.adapted.mean(grid)[:, :7], [PointOfInterest('ee')])[:, 0]
    assert np.linalg.norm(X - sphere.center, axis=1).min() > sphere.radius + cfg.obstacle_margin


def test_the_robot_model_selector_loads_and_compares_arms():
    from cdmp_ros.ros.robot_model import SAME, RobotModelSelector
    text = open(URDF).read()
    sel = RobotModelSelector(URDF, LEFT + RIGHT, capsule_links=['left_panda_hand',
                                                                'right_panda_link5'],
                             tip_link=TIPS)
    model, _, _ = sel.start()
    assert isinstance(model.chain, Arms) and [c.link for c in model.capsules] == [
        'left_panda_hand', 'right_panda_link5']
    assert sel.offer(text).status == SAME
    moved = text.replace('<origin xyz="1.13 0 0"', '<origin xyz="1.2 0 0"', 1)
    assert moved != text
    verdict = sel.offer(moved)
    assert verdict.status != SAME and 'right_panda_joint1' in verdict.message, verdict


@pytest.mark.parametrize('tips, match', [
    (('left_panda_hand',), r'tip_links: expected two or more links'),
    (('left_panda_hand', 'left_panda_hand'), r'tip_links: expected unique non-empty names'),
    (('left_panda_hand', ''), r'tip_links: expected unique non-empty names'),
])
def test_the_node_configs_refuse_bad_tip_links(tips, match):
    from cdmp_ros.core.adaptation.config import AdapterConfig
    from cdmp_ros.core.learning import LearnerConfig
    from cdmp_ros.core.streaming.config import StreamerConfig
    for cls in (StreamerConfig, AdapterConfig, LearnerConfig):
        with pytest.raises(ValidationError, match=match):
            cls(tip_links=tips)
    assert StreamerConfig(tip_links=TIPS, joint_names=tuple(LEFT + RIGHT)).tip_links == TIPS


def test_arm_clearance_keeps_the_arms_apart(arms, single, dual_prior):
    """adaptation.arm_clearance: Eq. 22 between every point of one arm and every point of the
    other; the demonstrations' hand-over brings the hands within 10 cm, the adapted
    distribution keeps them 15 cm apart (its mean at every step; the sampled verification
    holds at alpha)."""
    from cdmp_ros.core.adaptation.config import AdaptRequestConfig
    from cdmp_ros.core.adaptation.requests import AdaptRequest, build_problem, run_request
    cfg = AdaptRequestConfig(n_steps=41, arm_clearance=0.15,
                             avoid_links=('left_panda_link4', 'right_panda_link4'))
    req = AdaptRequest(dual_prior, ())
    pairs = [c for c in build_problem(req, arms, cfg).constraints if c.name.startswith('arms_')]
    assert sorted(c.name for c in pairs) == sorted(
        f'arms_{a}_{b}' for a in ('left_panda_hand_tcp', 'left_panda_link4')
        for b in ('right_panda_hand_tcp', 'right_panda_link4'))
    grid = np.linspace(0.0, 1.0, 41)

    def hands(promp):
        m = promp.mean(grid)
        return np.linalg.norm(
            single[0].forward(m[:, :7], [PointOfInterest('ee')])[:, 0]
            - single[1].forward(m[:, 7:], [PointOfInterest('ee')])[:, 0], axis=1)
    assert hands(dual_prior).min() < 0.1
    res = run_request(req, arms, cfg)
    assert res.outcome == 'converged', res.report.status
    assert res.report.verification is not None and res.report.verification.holds
    assert hands(res.adapted).min() > 0.15
    off = build_problem(req, arms, dataclasses.replace(cfg, arm_clearance=0.0))
    assert not [c for c in off.constraints if c.name.startswith('arms_')]
