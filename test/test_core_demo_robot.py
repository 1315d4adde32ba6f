"""The robot of a demo (core.demo_robot) and the two-arm figures of the demo's summary
(cli.demo_promp), each against an independent computation: the sim's model of the dual cell
(pybullet_data's Panda twice, the second turned by pi, dual_panda_chains), one arm at a time,
and closed forms of a distribution without spread."""
import numpy as np
import pybullet_data
import pytest

from cdmp_ros.core.demo_robot import DemoRobot, between_hands
from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.kinematics import PointOfInterest, dual_panda_chains
from cdmp_ros.core.kinematics.capsules import ArmCapsules

PANDA = f'{pybullet_data.getDataPath()}/franka_panda/panda.urdf'
EE = [PointOfInterest('ee')]
LINKS = [f'panda_link{i}' for i in range(1, 8)] + ['panda_hand']


@pytest.fixture(scope='module')
def dual():
    return DemoRobot('dual_panda')


@pytest.fixture(scope='module')
def cell():
    return dual_panda_chains(PANDA)


def _random_q(robot, rng, n):
    lo, hi = robot.model.lower, robot.model.upper
    return lo + (hi - lo) * rng.random((n, robot.n_dofs))


def test_the_dual_robot_is_the_sims_cell(dual, cell):
    """Joints left then right (the sim's joint_states order); each hand where the sim's
    model of that arm puts it, at 20 random configurations."""
    assert dual.joint_names == [f'{s}panda_joint{i}' for s in ('left_', 'right_')
                                for i in range(1, 8)]
    assert dual.n_arms == 2 and dual.frame == 'world'
    Q = _random_q(dual, np.random.default_rng(0), 20)
    H = dual.hands(Q)
    assert H.shape == (20, 2, 3)
    for arm, chain in enumerate(cell):
        ref = chain.forward(Q[:, 7 * arm:7 * arm + 7], EE)[:, 0]
        np.testing.assert_allclose(H[:, arm], ref, atol=1e-9)
    np.testing.assert_allclose(dual.hands(Q[3]), H[3])
    np.testing.assert_allclose(between_hands(H[3]), 0.5 * (H[3, 0] + H[3, 1]))


def test_clearance_is_the_nearer_arm(dual, cell):
    """A sphere's clearance to the robot is the least of each arm's (capsules fitted to the
    stock Panda meshes of each arm of the sim's cell)."""
    rng = np.random.default_rng(1)
    arms = [ArmCapsules.from_urdf(c, PANDA, LINKS, 0.06) for c in cell]
    for q in _random_q(dual, rng, 10):
        center = rng.uniform([0.2, -0.5, 0.0], [0.9, 0.5, 0.8])
        each = [a.sphere_clearance(q[7 * k:7 * k + 7], center, 0.04) for k, a in enumerate(arms)]
        assert dual.clearance(q, center, 0.04) == pytest.approx(min(each), abs=1e-6)


def test_the_panda_is_the_nodes_default_robot():
    """The Panda of the demo is the nodes' robot with their defaults (``urdf_path`` '', the
    URDF read by the generic chain builder, ``tcp_offset`` of config/streamer.yaml)."""
    import yaml
    from conftest import REPO_ROOT
    from cdmp_ros.core.kinematics import PANDA_JOINTS
    from cdmp_ros.ros.robot_model import default_urdf_path, load_chain
    with open(f'{REPO_ROOT}/config/streamer.yaml') as f:
        tcp = yaml.safe_load(f)['/**']['ros__parameters']['tcp_offset']
    from cdmp_ros.sim.robot_specs import PANDA_URDF
    assert PANDA_URDF == default_urdf_path()  # what cdmp demo passes, what the nodes load
    robot = DemoRobot('panda', default_urdf_path())
    chain = load_chain('', PANDA_JOINTS, 'panda_hand', tcp)
    q = _random_q(robot, np.random.default_rng(2), 5)
    np.testing.assert_allclose(robot.hands(q)[:, 0], chain.forward(q, EE)[:, 0], atol=1e-9)
    assert robot.frame == 'panda_link0' and robot.n_arms == 1


def test_bad_input_is_refused_naming_it(dual):
    with pytest.raises(ValidationError, match='robot: expected one of'):
        DemoRobot('ur5')
    with pytest.raises(ValidationError, match='give panda_urdf'):
        DemoRobot('panda')
    with pytest.raises(ValidationError, match='14 joints'):
        dual.hands(np.zeros(7))
    with pytest.raises(ValidationError, match=r'avoid_links\[0\]'):
        dual.split(['panda_link4'], 'avoid_links')


def _fixed(promp_dims, Y, names):
    """A ProMP whose every sample is (nearly) the trajectory of weights Y (no spread)."""
    from cdmp_ros.core.promp.promp import ProMP, RbfBasis
    basis = RbfBasis(tuple(np.linspace(0.0, 1.0, 5)), 0.2)
    w = np.repeat(np.asarray(Y, dtype=float)[:, None], 5, axis=1).ravel()  # constant paths
    return ProMP(promp_dims, basis, w, 1e-16 * np.eye(w.size), np.full(promp_dims, 1e-8),
                 1.0, list(names))


def test_arm_distances_and_violation_against_each_pair(dual, cell):
    """arm_distances: the least distance between a point of one arm (hand, link4) and one of
    the other, computed pair by pair with the sim's chains; arm_violation of a distribution
    without spread is 1 or 0 as its one trajectory is inside the clearance or not."""
    from cdmp_ros.cli.demo_promp import arm_distances, arm_violation, demo_points
    rng = np.random.default_rng(3)
    links = ['left_panda_link4', 'right_panda_link4']
    origins = demo_points(dual, links, geometry=False)
    Q = _random_q(dual, rng, 6)
    got = arm_distances(dual, Q, origins)
    pts = [EE, [PointOfInterest('panda_link4')]]
    for q, d in zip(Q, got):
        A = np.concatenate([cell[0].forward(q[:7], p) for p in pts])
        B = np.concatenate([cell[1].forward(q[7:], p) for p in pts])
        assert d == pytest.approx(np.linalg.norm(A[:, None] - B[None], axis=-1).min(), abs=1e-9)
    q = Q[0]
    prior = _fixed(14, q, dual.joint_names)
    dist = float(arm_distances(dual, q, origins))
    for clearance, expect in ((dist + 0.01, 1.0), (max(dist - 0.01, 1e-3), 0.0)):
        v = arm_violation(prior, dual, origins, clearance, rng, n_samples=50, n_phases=5)
        assert v['trajectory'] == expect and v['per_step_max'] == expect
        assert v['min_arm_distance_mean_path_m'] == pytest.approx(dist, abs=1e-6)


def test_arm_distances_between_the_links_balls(dual, cell):
    """With the links' geometry (the adapter's link_geometry), arm_distances is the least
    distance between the surfaces of the balls covering panda_link4's capsule and the hands,
    computed pair by pair from the capsule the URDF gives (both arms have the same)."""
    from cdmp_ros.cli.demo_promp import arm_distances, demo_points
    from cdmp_ros.core.kinematics.capsules import collision_capsules
    links = ['left_panda_link4', 'right_panda_link4']
    points = demo_points(dual, links)
    cap = collision_capsules(dual.urdf, ['left_panda_link4'])[0]
    balls = cap.covering_balls()
    assert [p.name for p in points] == (['left_panda_hand_tcp'] + [f'left_panda_link4_{i}'
                                        for i in range(len(balls))] + ['right_panda_hand_tcp']
                                        + [f'right_panda_link4_{i}' for i in range(len(balls))])
    pts = [PointOfInterest('ee')] + [PointOfInterest('panda_link4', c) for c, _ in balls]
    pad = np.array([0.0] + [r for _, r in balls])
    Q = _random_q(dual, np.random.default_rng(5), 4)
    for q, d in zip(Q, arm_distances(dual, Q, points)):
        A, B = cell[0].forward(q[:7], pts), cell[1].forward(q[7:], pts)
        pair = np.linalg.norm(A[:, None] - B[None], axis=-1) - pad[:, None] - pad[None, :]
        assert d == pytest.approx(pair.min(), abs=1e-9)


def test_the_band_of_each_arm(dual, cell):
    """ee_band(arm=k): the mean path of arm k's hand (its own joints of the robot's ProMP)."""
    from cdmp_ros.core.adaptation.requests import ee_band
    rng = np.random.default_rng(4)
    q = _random_q(dual, rng, 1)[0]
    prior = _fixed(14, q, dual.joint_names)
    s = np.linspace(0.0, 1.0, 4)
    for arm, chain in enumerate(cell):
        X, r = ee_band(prior, dual.model, s, arm=arm)
        np.testing.assert_allclose(X, np.repeat(chain.forward(q[7 * arm:7 * arm + 7], EE),
                                                4, axis=0), atol=1e-6)
        assert np.all(r < 1e-5)
