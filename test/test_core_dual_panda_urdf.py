"""urdf/dual_panda.urdf, the nodes' model of the sim's dual_panda cell: up to date with its
generator, and each arm read from it is the sim's arm (pybullet_data's Panda at its base),
with the capsules fitted around the stock meshes."""
import numpy as np
import pytest

from conftest import REPO_ROOT, load_script

URDF = f'{REPO_ROOT}/urdf/dual_panda.urdf'


@pytest.fixture(scope='module')
def stock():
    from cdmp_ros.sim.robot_specs import panda_urdf_path
    return panda_urdf_path()


def test_the_file_is_what_its_generator_writes(capsys):
    assert load_script('gen_dual_panda_urdf').main(['--check']) == 0, capsys.readouterr().out


def test_the_check_fails_on_a_difference(tmp_path, monkeypatch, capsys):
    gen = load_script('gen_dual_panda_urdf')
    out = tmp_path / 'dual_panda.urdf'
    out.write_text(open(URDF).read().replace('right_panda_joint4', 'right_panda_jointX', 1))
    monkeypatch.setattr(gen, 'OUT', str(out))
    assert gen.main(['--check']) == 1
    assert 'right_panda_jointX' in capsys.readouterr().out


@pytest.mark.parametrize('side', [0, 1])
def test_each_arm_is_the_sims_arm_at_its_base(side, stock):
    from cdmp_ros.core.kinematics import PANDA_JOINTS, PointOfInterest, dual_panda_chains
    from cdmp_ros.core.kinematics.builders import PANDA_EE_OFFSET, chain_from_urdf
    ref = dual_panda_chains(stock)[side]
    prefix = ('left_', 'right_')[side]
    arm = chain_from_urdf(URDF, prefix + 'panda_hand', ee_offset=PANDA_EE_OFFSET,
                          joint_names=[prefix + j for j in PANDA_JOINTS])
    Q = np.random.default_rng(side).uniform(ref.lower, ref.upper, size=(50, 7))
    X = arm.forward(Q, [PointOfInterest('ee'), PointOfInterest(prefix + 'panda_link4',
                                                               (0.1, -0.02, 0.05))])
    X_ref = ref.forward(Q, [PointOfInterest('ee'), PointOfInterest('panda_link4',
                                                                   (0.1, -0.02, 0.05))])
    np.testing.assert_allclose(X, X_ref, atol=1e-12)
    for name in ('lower', 'upper', 'velocity_limits'):
        np.testing.assert_array_equal(getattr(arm, name), getattr(ref, name))


def test_the_capsules_are_those_of_the_stock_meshes(stock):
    from cdmp_ros.core.kinematics.capsules import collision_capsules
    links = ['panda_link0', 'panda_link3', 'panda_link5', 'panda_hand', 'panda_leftfinger']
    want = collision_capsules(stock, links)
    for prefix in ('left_', 'right_'):
        got = collision_capsules(URDF, [prefix + n for n in links])
        for a, b in zip(want, got):
            assert b.link == prefix + a.link
            # the same segment (either direction), the radius within the fit's rounding
            ends = np.array([a.start, a.end])
            assert min(np.abs(ends - [b.start, b.end]).max(),
                       np.abs(ends[::-1] - [b.start, b.end]).max()) < 1e-8, (a, b)
            assert b.radius == pytest.approx(a.radius, abs=3e-9)
