"""The nodes' robot model loader (issue 31, item 7), no ROS graph: :func:`load_chain` builds the
chain of any URDF from its root link to ``tip_link`` with the tool centre point ``tcp_offset``
(the Panda's defaults give exactly :func:`panda_chain`), ``urdf_path`` may name a file of a
package (``package://``), and the planar 4-link arm's URDF is one checked-in file shared by the
sim and the nodes."""
import os
import shutil

import numpy as np
import pytest

from cdmp_ros.core.adaptation.config import AdapterConfig
from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.kinematics import (PANDA_EE_OFFSET, PANDA_JOINTS, PANDA_TIP_LINK,
                                      PointOfInterest, panda_chain, planar_chain)
from cdmp_ros.core.learning import LearnerConfig
from cdmp_ros.core.streaming.config import StreamerConfig
from cdmp_ros.ros.robot_model import (REJECTED, USED, RobotModelSelector, default_urdf_path,
                                      limits_source, load_chain, resolve_urdf_path)

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PLANAR4 = 'package://cdmp_ros/urdf/planar4.urdf'
PLANAR4_FILE = os.path.join(ROOT, 'urdf', 'planar4.urdf')
PLANAR4_JOINTS = ('joint1', 'joint2', 'joint3', 'joint4')
CONFIGS = (StreamerConfig, AdapterConfig, LearnerConfig)


def planar4(**kwargs):
    return load_chain(PLANAR4, PLANAR4_JOINTS, 'ee', (0.0, 0.0, 0.0), **kwargs)


# -- the URDF file ---------------------------------------------------------------------------
def test_the_checked_in_planar4_urdf_is_the_generated_one():
    """urdf/planar4.urdf is planar_arm_urdf() as it is: the two cannot drift apart."""
    from cdmp_ros.sim.robot_specs import PLANAR4_URDF, planar_arm_urdf
    assert PLANAR4_URDF == 'urdf/planar4.urdf'
    with open(PLANAR4_FILE) as f:
        assert f.read() == planar_arm_urdf()


def test_the_sim_and_the_nodes_load_the_same_planar4_file():
    from cdmp_ros.sim.robot_specs import planar4_spec
    spec = planar4_spec()
    assert os.path.samefile(spec.urdf_path, PLANAR4_FILE)
    assert os.path.samefile(resolve_urdf_path(PLANAR4), PLANAR4_FILE)
    assert spec.joint_names == PLANAR4_JOINTS and spec.ee_link == 'ee'
    assert spec.ee_offset == (0.0, 0.0, 0.0)


# -- the planar chain --------------------------------------------------------------------------
def test_the_planar4_chain_from_the_urdf_is_the_analytic_planar_arm(rng):
    """FK of the end effector and of every joint, and the end effector's Jacobian, at random
    configurations inside the limits: the URDF chain, planar_chain([1, 1, 1, 1]) and the
    closed form sum_i (cos theta_i, sin theta_i), theta_i = q_1 + ... + q_i."""
    chain = planar4()
    ref = planar_chain([1.0, 1.0, 1.0, 1.0])
    assert tuple(chain.joint_names) == PLANAR4_JOINTS
    np.testing.assert_array_equal(chain.lower, [-2.8] * 4)
    np.testing.assert_array_equal(chain.upper, [2.8] * 4)
    np.testing.assert_array_equal(chain.velocity_limits, [2.0] * 4)
    Q = rng.uniform(-2.8, 2.8, size=(200, 4))
    theta = np.cumsum(Q, axis=1)
    closed = np.stack([np.cos(theta).sum(axis=1), np.sin(theta).sum(axis=1),
                       np.zeros(len(Q))], axis=1)
    ee = chain.forward(Q, [PointOfInterest('ee')])[:, 0]
    np.testing.assert_allclose(ee, closed, rtol=0.0, atol=1e-12)
    np.testing.assert_allclose(ee, ref.forward(Q, [PointOfInterest('ee')])[:, 0], rtol=0.0,
                               atol=1e-12)
    # the joint origins: link i of the URDF starts where link i of planar_chain starts
    for i in range(1, 5):
        ours = chain.forward(Q, [PointOfInterest(f'link{i}')])[:, 0]
        np.testing.assert_allclose(ours, ref.forward(Q, [PointOfInterest(f'link{i}')])[:, 0],
                                   rtol=0.0, atol=1e-12)
    for q in Q[:20]:
        _, J = chain.forward_and_jacobian(q, [PointOfInterest('ee')])
        _, J_ref = ref.forward_and_jacobian(q, [PointOfInterest('ee')])
        np.testing.assert_allclose(np.asarray(J)[0], np.asarray(J_ref)[0], rtol=0.0,
                                   atol=1e-12)


def test_the_tcp_offset_is_the_end_effector_point(rng):
    chain = load_chain(PLANAR4, PLANAR4_JOINTS, 'ee', (0.5, 0.0, 0.0))
    q = rng.uniform(-2.8, 2.8, size=4)
    x = chain.forward(q, [PointOfInterest('ee')])[0]
    np.testing.assert_allclose(x, planar_chain([1.0, 1.0, 1.0, 1.5]).forward(
        q, [PointOfInterest('ee')])[0], rtol=0.0, atol=1e-12)
    # tip_link link4 with the tcp at the end of the link: the same point
    chain = load_chain(PLANAR4, PLANAR4_JOINTS, 'link4', (1.0, 0.0, 0.0))
    np.testing.assert_allclose(chain.forward(q, [PointOfInterest('ee')])[0], planar_chain(
        [1.0] * 4).forward(q, [PointOfInterest('ee')])[0], rtol=0.0, atol=1e-12)


# -- the Panda: unchanged ----------------------------------------------------------------------
def test_the_panda_defaults_give_exactly_panda_chain(rng):
    """Every node's defaults (joint_names, tip_link, tcp_offset, urdf_path '') load the chain
    panda_chain builds, bit for bit: the Panda's results do not change."""
    for cls in CONFIGS:
        cfg = cls()
        assert (cfg.joint_names, cfg.tip_link, cfg.tcp_offset, cfg.urdf_path) == (
            PANDA_JOINTS, PANDA_TIP_LINK, PANDA_EE_OFFSET, ''), cls.__name__
    ours = load_chain('', PANDA_JOINTS)
    ref = panda_chain(default_urdf_path())
    assert PANDA_TIP_LINK == 'panda_hand' and PANDA_EE_OFFSET == (0.0, 0.0, 0.105)
    for name in ('B', 'base_transform', 'ee_offset', 'lower', 'upper', 'velocity_limits'):
        assert np.array_equal(getattr(ours, name), getattr(ref, name)), name
    assert ours.attachments.keys() == ref.attachments.keys()
    assert ours.ee_link == ref.ee_link == 'panda_hand'
    Q = rng.uniform(ref.lower, ref.upper, size=(50, 7))
    points = [PointOfInterest('ee'), PointOfInterest('panda_link4')]
    assert np.array_equal(ours.forward(Q, points), ref.forward(Q, points))


# -- refusals naming the parameter -------------------------------------------------------------
def test_a_wrong_tip_link_is_refused_naming_it():
    with pytest.raises(ValidationError, match=r'^tip_link: expected one of the links of '
                                              r"'planar_arm'.*got 'panda_hand'"):
        load_chain(PLANAR4, PLANAR4_JOINTS)   # the Panda's tip link on the planar arm
    with pytest.raises(ValidationError, match=r"^tip_link: no movable joint between 'base' and "
                                              r"'base'"):
        load_chain(PLANAR4, PLANAR4_JOINTS, 'base', (0.0, 0.0, 0.0))
    with pytest.raises(ValidationError, match=r'^tip_link: expected one of the links of '
                                              r"'panda'.*got 'ee'"):
        load_chain('', PANDA_JOINTS, 'ee')


def test_joint_names_other_than_the_chains_are_refused_naming_them():
    with pytest.raises(ValidationError, match=r'^joint_names: expected the movable joints of '
                                              r".*planar4\.urdf' from 'base' to "
                                              r"tip_link 'ee' \['joint1', 'joint2', 'joint3', "
                                              r"'joint4'\], got \['panda_joint1'"):
        load_chain(PLANAR4, PANDA_JOINTS, 'ee', (0.0, 0.0, 0.0))
    with pytest.raises(ValidationError, match='^joint_names:'):   # a shorter chain
        load_chain(PLANAR4, PLANAR4_JOINTS, 'link3', (0.0, 0.0, 0.0))
    with pytest.raises(ValidationError, match='^joint_names:'):   # another order
        load_chain(PLANAR4, ('joint2', 'joint1', 'joint3', 'joint4'), 'ee', (0.0, 0.0, 0.0))


@pytest.mark.parametrize('cls', CONFIGS, ids=lambda c: c.__name__)
def test_bad_tip_link_and_tcp_offset_values_are_refused_naming_them(cls):
    for bad in ('', '  ', 3):
        with pytest.raises(ValidationError, match='^tip_link: expected a (link name|string)'):
            cls(tip_link=bad)
    for bad in ((0.0, 0.0), (0.0, 0.0, float('nan')), (0.0, 0.0, 11.0), 'abc'):
        with pytest.raises(ValidationError, match='^tcp_offset: expected 3 finite'):
            cls(tcp_offset=bad)
    assert cls(tcp_offset=[0, 1, 2]).tcp_offset == (0.0, 1.0, 2.0)


def test_both_parameters_are_declared_with_descriptors():
    from cdmp_ros.ros.params import FloatTuple, descriptor_for, parameter_fields
    for cls in CONFIGS:
        fields = {f.name: (f, kind) for f, kind, _ in parameter_fields(cls)}
        assert fields['tip_link'][1] is str and fields['tcp_offset'][1] is FloatTuple
        desc = {name: descriptor_for(cls, *fields[name], name)
                for name in ('tip_link', 'tcp_offset', 'urdf_path')}
        assert 'joint_names' in desc['tip_link'].description and desc['tip_link'].read_only
        assert 'frame of tip_link' in desc['tcp_offset'].description
        assert 'package://' in desc['urdf_path'].description


def test_an_unreadable_model_is_refused_naming_its_parameter():
    with pytest.raises(ValidationError, match='^urdf_path: cannot load a robot'):
        load_chain(os.devnull + '.missing', PANDA_JOINTS)
    with pytest.raises(ValidationError, match='^robot_description: cannot load a robot'):
        load_chain('', PANDA_JOINTS, robot_description='<robot')


# -- package:// names ---------------------------------------------------------------------------
def test_urdf_path_names_a_file_of_a_package(tmp_path, monkeypatch):
    assert resolve_urdf_path('') == default_urdf_path()
    assert resolve_urdf_path('/some/file.urdf') == '/some/file.urdf'
    # not in the ament index (a source tree): this package's files beside the package
    monkeypatch.setenv('AMENT_PREFIX_PATH', str(tmp_path / 'empty'))
    assert resolve_urdf_path(PLANAR4) == PLANAR4_FILE
    assert limits_source(PLANAR4) == PLANAR4_FILE
    monkeypatch.delenv('AMENT_PREFIX_PATH')
    assert resolve_urdf_path(PLANAR4) == PLANAR4_FILE
    # installed (colcon): the share directory the ament index names wins
    prefix = tmp_path / 'install'
    (prefix / 'share' / 'ament_index' / 'resource_index' / 'packages').mkdir(parents=True)
    (prefix / 'share' / 'ament_index' / 'resource_index' / 'packages' / 'cdmp_ros').touch()
    (prefix / 'share' / 'cdmp_ros' / 'urdf').mkdir(parents=True)
    installed = prefix / 'share' / 'cdmp_ros' / 'urdf' / 'planar4.urdf'
    shutil.copy(PLANAR4_FILE, installed)
    monkeypatch.setenv('AMENT_PREFIX_PATH', str(prefix))
    assert resolve_urdf_path(PLANAR4) == str(installed)
    assert tuple(planar4().joint_names) == PLANAR4_JOINTS
    with pytest.raises(ValidationError, match=r"^urdf_path: 'package://cdmp_ros/urdf/x.urdf': "
                                              r'no file .*share/cdmp_ros/urdf/x.urdf'):
        resolve_urdf_path('package://cdmp_ros/urdf/x.urdf')
    for bad in ('package://', 'package://cdmp_ros', 'package://cdmp_ros/'):
        with pytest.raises(ValidationError, match='^urdf_path: expected package://'):
            resolve_urdf_path(bad)
    with pytest.raises(ValidationError, match="^urdf_path: .*package 'no_such_pkg' not found"):
        resolve_urdf_path('package://no_such_pkg/robot.urdf')
    monkeypatch.setenv('AMENT_PREFIX_PATH', str(tmp_path / 'empty'))
    with pytest.raises(ValidationError, match="^urdf_path: 'package://cdmp_ros/urdf/x.urdf': "
                                              "data file 'urdf/x.urdf' not found"):
        resolve_urdf_path('package://cdmp_ros/urdf/x.urdf')


# -- the selector with another robot -----------------------------------------------------------
def test_the_selector_loads_the_planar_arm_and_rejects_a_panda_description():
    sel = RobotModelSelector(PLANAR4, PLANAR4_JOINTS, timeout=1.0, tip_link='ee',
                             tcp_offset=(0.0, 0.0, 0.0))
    model, note, warn = sel.start(open(default_urdf_path()).read())   # a Panda on the topic
    assert model.source == PLANAR4_FILE and tuple(model.chain.joint_names) == PLANAR4_JOINTS
    assert warn and f'using urdf_path {PLANAR4_FILE}' in note
    v = sel.verdict
    assert v.status == REJECTED and v.category == 'joint_names'
    assert v.message.startswith('robot_description: not a robot of the configured joint_names '
                                "and tip_link: tip_link: expected one of the links of 'panda'")
    # the planar arm's own description on the topic is the model in use
    sel = RobotModelSelector(PLANAR4, PLANAR4_JOINTS, timeout=1.0, tip_link='ee',
                             tcp_offset=(0.0, 0.0, 0.0))
    model, _, warn = sel.start(open(PLANAR4_FILE).read())
    assert sel.verdict.status == USED and not warn
    np.testing.assert_array_equal(model.chain.upper, [2.8] * 4)


def test_meshes_of_a_robot_description_are_found_as_ros_finds_them(tmp_path, monkeypatch):
    """load_collision_capsules of a robot_description (text): its relative mesh names are found
    beside the node's urdf_path file when not in the working directory, and
    package://<package>/<path> names in the share directory of an AMENT_PREFIX_PATH prefix;
    the capsules equal those of the file itself. A mesh found nowhere is named with every
    place looked at."""
    from cdmp_ros.ros.robot_model import load_collision_capsules, mesh_dirs
    path = default_urdf_path()
    links = ['panda_link4', 'panda_hand']
    want = load_collision_capsules(path, links)
    text = open(path).read()
    monkeypatch.chdir(tmp_path)                       # no meshes here
    assert load_collision_capsules(path, links, text) == want
    dirs = mesh_dirs(path, 'robot_description', True)
    assert dirs[:2] == [str(tmp_path), os.path.dirname(path)]
    # package://franka/meshes/... in <prefix>/share/franka/meshes/...
    share = tmp_path / 'prefix' / 'share' / 'franka'
    share.mkdir(parents=True)
    os.symlink(os.path.join(os.path.dirname(path), 'meshes'), share / 'meshes')
    monkeypatch.setenv('AMENT_PREFIX_PATH', str(tmp_path / 'prefix'))
    pkg = text.replace('filename="package://meshes/', 'filename="package://franka/meshes/')
    assert 'package://franka/meshes/collision/link4.obj' in pkg
    other = tmp_path / 'elsewhere.urdf'
    other.write_text('<robot name="x"/>')
    assert load_collision_capsules(str(other), links, pkg) == want
    gone = text.replace('filename="package://meshes/collision/link4.obj"',
                        'filename="package://nowhere/link4.obj"')
    with pytest.raises(ValidationError, match=r"coupling_capsule_links: .*'package://nowhere/"
                                              r"link4.obj' not found \(looked for .*prefix"):
        load_collision_capsules(str(other), links, gone)
