"""The tighter of a primitive's and the robot's limits (cdmp_ros.core.joint_limits) and where
it enters a streamed primitive (prepare_primitive), and the robot model's sources."""
import os

import numpy as np
import pytest

from cdmp_ros.core.dmp.dmp import CDMP
from cdmp_ros.core.errors import PrimitiveFileError, ValidationError
from cdmp_ros.core.joint_limits import describe_mismatches, merge_limits
from cdmp_ros.core.primitive_io import dumps_primitive
from cdmp_ros.core.streaming.primitives import prepare_primitive
from streamer_harness import (LOWER, PANDA_JOINTS, Q_GOAL, Q_START, TIGHT_LOWER, TIGHT_UPPER,
                              UPPER, VMAX, reach_demo, wide_narrow_cdmp)


def test_merge_takes_the_tighter_bound_per_joint_and_reports_both_values():
    lo, hi, mm = merge_limits(['a', 'b', 'c'], [-1.0, -2.0, -3.0], [1.0, 2.0, 3.0],
                              [-1.5, -1.0, -3.0], [0.5, 2.5, 3.0])
    np.testing.assert_array_equal(lo, [-1.0, -1.0, -3.0])
    np.testing.assert_array_equal(hi, [0.5, 2.0, 3.0])
    assert [(m.joint, m.bound, m.primitive, m.robot, m.used) for m in mm] == [
        ('a', 'lower', -1.5, -1.0, -1.0), ('a', 'upper', 0.5, 1.0, 0.5),
        ('b', 'lower', -1.0, -2.0, -1.0), ('b', 'upper', 2.5, 2.0, 2.0)]
    assert [m.wider for m in mm] == [True, False, False, True]
    text = describe_mismatches(mm)
    assert 'a lower: primitive -1.5, robot -1 -> -1 (robot)' in text
    assert 'b upper: primitive 2.5, robot 2 -> 2 (robot)' in text
    assert 'a upper: primitive 0.5, robot 1 -> 0.5 (primitive)' in text
    assert 'c ' not in text


def test_equal_limits_are_no_mismatch():
    lo, hi, mm = merge_limits(PANDA_JOINTS, LOWER, UPPER, LOWER.copy(), UPPER.copy())
    assert mm == [] and describe_mismatches(mm) == 'none'
    np.testing.assert_array_equal(lo, LOWER)


def test_disjoint_limits_are_refused():
    with pytest.raises(ValidationError, match='y_min'):
        merge_limits(['a'], [0.0], [1.0], [2.0], [3.0])


def test_a_cdmp_wider_than_the_robot_is_refitted_into_the_tighter_limits():
    prep = prepare_primitive(dumps_primitive(wide_narrow_cdmp()), PANDA_JOINTS, 0.002,
                             LOWER, UPPER, VMAX)
    tight_lo, tight_hi = TIGHT_LOWER, TIGHT_UPPER
    # the tanh transform (Eq. 19) has the tighter limits: every position is inside them
    np.testing.assert_array_equal(prep.prim.y_min, tight_lo)
    np.testing.assert_array_equal(prep.prim.y_max, tight_hi)
    assert {(m.joint, m.bound) for m in prep.limit_mismatches} == {
        ('panda_joint1', 'lower'), ('panda_joint1', 'upper'), ('panda_joint2', 'lower'),
        ('panda_joint2', 'upper')}
    assert any('panda_joint1 upper: primitive 3.5, robot 2.9671' in n for n in prep.notes)
    Y = prep.prim.rollout(dt=0.01).Y
    assert np.all(Y > tight_lo) and np.all(Y < tight_hi)
    assert prep.prim.goal_y_[0] < UPPER[0]


def test_a_primitive_without_limit_differences_is_unchanged():
    T, Y = reach_demo(Q_START, Q_GOAL, 2.0)
    prim = CDMP(LOWER, UPPER, joint_names=PANDA_JOINTS).fit(T, Y)
    prep = prepare_primitive(dumps_primitive(prim), PANDA_JOINTS, 0.002, LOWER, UPPER, VMAX)
    assert prep.limit_mismatches == []
    np.testing.assert_array_equal(prep.prim.weights_, prim.weights_)


def test_limits_without_a_common_range_reject_the_primitive():
    T, Y = reach_demo(Q_START, Q_GOAL, 2.0)
    prim = CDMP(LOWER, UPPER, joint_names=PANDA_JOINTS).fit(T, Y)
    robot_hi = UPPER.copy()
    robot_lo = LOWER.copy()
    robot_lo[3], robot_hi[3] = 0.5, 1.0  # the primitive's joint 4 range ends at 0.0
    with pytest.raises(PrimitiveFileError, match='limits'):
        prepare_primitive(dumps_primitive(prim), PANDA_JOINTS, 0.002, robot_lo, robot_hi)


def test_robot_description_takes_precedence_over_urdf_path():
    from cdmp_ros.ros.robot_model import default_urdf_path, limits_source, load_chain
    text = open(default_urdf_path()).read().replace(
        'lower="-2.9671" upper="2.9671"', 'lower="-2.5" upper="2.5"', 1)
    assert limits_source('', '') == default_urdf_path()
    assert limits_source('/x.urdf', '') == '/x.urdf'
    assert limits_source('/x.urdf', text) == 'robot_description'
    chain = load_chain('/nonexistent.urdf', PANDA_JOINTS, robot_description=text)
    assert chain.upper[0] == 2.5 and chain.lower[0] == -2.5
    with pytest.raises(ValidationError, match=r"tip_link: .*\(the robot of 'robot_description'\)"):
        load_chain('', PANDA_JOINTS, robot_description='<robot name="x"><link name="a"/></robot>')
    with pytest.raises(ValidationError, match='urdf_path'):
        load_chain(os.devnull + '.missing', PANDA_JOINTS)


def test_a_promp_file_carries_the_limits_it_was_fitted_within():
    """A ProMP's limits live in ``metadata['limits']`` (the learner's fit limits, the adapter's
    merged ones) and are written as the file's ``limits``: read back, reordered (with the
    weights) and written the same way by the adapter's promp_message."""
    import json
    from cdmp_ros.core.adaptation.requests import promp_message, reorder_promp
    from cdmp_ros.core.learning import fit_primitive
    from cdmp_ros.core.primitive_io import primitive_from_dict, primitive_to_dict
    lo, hi = TIGHT_LOWER, TIGHT_UPPER
    demos = [reach_demo(Q_START, Q_GOAL + 0.01 * k, 2.0, 101) for k in range(3)]
    prim = fit_primitive('promp', demos, PANDA_JOINTS, lo, hi)
    d = primitive_to_dict(prim)
    assert d['limits'] == {'lower': lo.tolist(), 'upper': hi.tolist()}
    msg, doc = json.loads(promp_message(prim)), json.loads(dumps_primitive(prim))
    assert (primitive_from_dict(msg).cov_w == primitive_from_dict(doc).cov_w).all()
    msg['promp']['cov_w'] = doc['promp']['cov_w']   # the compact covariance aside: the same
    del msg['promp']['cov_w_base64']
    assert msg == doc
    back = primitive_from_dict(d)
    assert primitive_to_dict(back)['limits'] == d['limits']
    rev = reorder_promp(back, PANDA_JOINTS[::-1])
    d_rev = primitive_to_dict(rev)
    assert d_rev['limits'] == {'lower': lo[::-1].tolist(), 'upper': hi[::-1].tolist()}
    assert d_rev['joint_names'] == list(PANDA_JOINTS[::-1])
    # the file's field wins over stale metadata
    d2 = dict(d, limits={'lower': LOWER.tolist(), 'upper': UPPER.tolist()})
    assert primitive_to_dict(primitive_from_dict(d2))['limits']['upper'] == UPPER.tolist()
