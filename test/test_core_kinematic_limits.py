"""KinematicLimits and the joint_limits.yaml convention (cdmp_ros.core.joint_limits, issue 28):
parse_joint_limits, joint_limits_entries, merged, default_joint_limits, panda_limits, ratios,
describe. (merge_limits of primitive and robot position limits: test_core_joint_limits.py.)"""
import math

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.joint_limits import (IGNORED_KEYS, PANDA_DATASHEET, PLANAR_ACCELERATION,
                                        PLANAR_JERK, KinematicLimits, default_joint_limits,
                                        joint_limits_entries, panda_limits, parse_joint_limits)

NAMES = ('j1', 'j2', 'j3')
LO = np.array([-1.0, -2.0, 0.0])
HI = np.array([1.0, 2.0, 3.0])
INF = math.inf

#: The design doc's table (../shared/design.md, Joint limits): Franka's datasheet.
DOC_VELOCITY = (2.175, 2.175, 2.175, 2.175, 2.61, 2.61, 2.61)
DOC_ACCELERATION = (15.0, 7.5, 10.0, 12.5, 15.0, 20.0, 20.0)
DOC_JERK = (7500.0, 3750.0, 5000.0, 6250.0, 7500.0, 10000.0, 10000.0)


def parse(entries, lower=LO, upper=HI):
    return parse_joint_limits(NAMES, entries, lower, upper)


# -- parse_joint_limits: refusals -----------------------------------------------------------------
@pytest.mark.parametrize('order', ['velocity', 'acceleration', 'jerk'])
@pytest.mark.parametrize('value', [None, 0.0, 0, -1.0, float('nan'), float('inf'), '2.0', True,
                                   [1.0]], ids=repr)
def test_a_bad_max_value_is_refused_naming_the_parameter(order, value):
    entry = {f'has_{order}_limits': True}
    if value is not None:   # None: missing
        entry[f'max_{order}'] = value
    with pytest.raises(ValidationError, match=rf'joint_limits\.j2\.max_{order}\b'):
        parse({'j2': entry})


@pytest.mark.parametrize('key', ['has_position_limits', 'has_velocity_limits',
                                 'has_acceleration_limits', 'has_jerk_limits'])
@pytest.mark.parametrize('value', [1, 0, 'true', 'false', None, 1.0, [True]], ids=repr)
def test_a_flag_that_is_not_a_bool_is_refused_naming_the_parameter(key, value):
    with pytest.raises(ValidationError, match=rf'joint_limits\.j1\.{key}\b'):
        parse({'j1': {key: value, 'max_velocity': 1.0, 'min_position': -0.5,
                      'max_position': 0.5}})


@pytest.mark.parametrize('key,value', [('min_position', None), ('max_position', None),
                                       ('min_position', 'low'), ('max_position', float('nan')),
                                       ('max_position', float('inf')),
                                       ('min_position', -float('inf')), ('min_position', False)])
def test_a_bad_position_bound_is_refused_naming_the_parameter(key, value):
    entry = {'has_position_limits': True, 'min_position': -0.5, 'max_position': 0.5}
    if value is None:
        del entry[key]
    else:
        entry[key] = value
    with pytest.raises(ValidationError, match=rf'joint_limits\.j3\.{key}\b'):
        parse({'j3': entry})


@pytest.mark.parametrize('lo,hi', [(0.5, 0.5), (0.6, 0.4), (3.0, -3.0)])
def test_min_position_not_below_max_position_is_refused(lo, hi):
    with pytest.raises(ValidationError,
                       match=r'joint_limits\.j1\b.*min_position.*max_position'):
        parse({'j1': {'has_position_limits': True, 'min_position': lo, 'max_position': hi}})


def test_an_unknown_key_is_refused_naming_joint_and_key():
    with pytest.raises(ValidationError, match=r'joint_limits\.j2\b.*max_vel\b'):
        parse({'j2': {'has_velocity_limits': True, 'max_vel': 1.0}})
    with pytest.raises(ValidationError, match=r'joint_limits\.j1\b.*Max_Velocity'):
        parse({'j1': {'Max_Velocity': 1.0}})   # keys are case-sensitive


def test_an_unknown_joint_is_refused_naming_it():
    with pytest.raises(ValidationError, match=r'joint_limits\b.*elbow'):
        parse({'j1': {}, 'elbow': {'has_velocity_limits': True, 'max_velocity': 1.0}})


@pytest.mark.parametrize('entry', [[1.0], 'fast', 3.0, 0, '', [], False], ids=repr)
def test_an_entry_that_is_not_a_mapping_is_refused(entry):
    """BUG (kept failing for 0, '', [] and False): ``entries.get(name) or {}`` turns every
    falsy non-mapping entry into an empty one, so ``joint_limits: {j1: 0}`` is accepted
    silently (no limit), while ``[1.0]`` or ``'fast'`` are refused. (A missing entry, or None
    as YAML gives for ``j1:``, means no limit: next test.)"""
    with pytest.raises(ValidationError, match=r'joint_limits\.j1\b'):
        parse({'j1': entry})


def test_no_entry_or_an_empty_one_sets_no_limit():
    for entries in ({}, {'j1': None}, {'j1': {}, 'j3': {}}):
        lim = parse(entries)
        np.testing.assert_array_equal(lim.lower, LO)
        np.testing.assert_array_equal(lim.upper, HI)
        for order in ('velocity', 'acceleration', 'jerk'):
            assert np.all(np.isinf(getattr(lim, order)))
        assert lim.sources == ('joint_limits: nothing',)


# -- parse_joint_limits: what is read ---------------------------------------------------------
def test_limits_are_read_per_joint_and_order():
    lim = parse_joint_limits(NAMES, {
        'j1': {'has_velocity_limits': True, 'max_velocity': 2.0,
               'has_jerk_limits': True, 'max_jerk': 5000},      # an int counts
        'j3': {'has_acceleration_limits': True, 'max_acceleration': 7.5,
               'has_velocity_limits': False},
    }, LO, HI, source='params')
    np.testing.assert_array_equal(lim.velocity, [2.0, INF, INF])
    np.testing.assert_array_equal(lim.acceleration, [INF, INF, 7.5])
    np.testing.assert_array_equal(lim.jerk, [5000.0, INF, INF])
    assert lim.jerk.dtype == np.float64
    assert lim.joint_names == NAMES
    assert lim.sources == ('params: velocity, acceleration, jerk',)


def test_ignored_keys_are_accepted_and_change_nothing():
    values = {'has_deceleration_limits': True, 'max_deceleration': 3.0,
              'has_effort_limits': True, 'max_effort': 87.0, 'angle_wraparound': False,
              'has_soft_limits': True, 'k_position': 100.0, 'k_velocity': 1.5,
              'soft_lower_limit': -0.1, 'soft_upper_limit': 0.1}
    assert set(values) == set(IGNORED_KEYS)
    lim = parse({'j2': dict(values, has_velocity_limits=True, max_velocity=1.5)})
    np.testing.assert_array_equal(lim.velocity, [INF, 1.5, INF])
    np.testing.assert_array_equal(lim.acceleration, [INF] * 3)
    np.testing.assert_array_equal(lim.lower, LO)
    # whatever their values (they are not read)
    parse({'j1': {k: 'anything' for k in IGNORED_KEYS}})


@pytest.mark.parametrize('order', ['velocity', 'acceleration', 'jerk'])
@pytest.mark.parametrize('flag', [None, False])
def test_a_max_without_its_flag_true_is_ignored(order, flag):
    entry = {f'max_{order}': 1.0}
    if flag is not None:
        entry[f'has_{order}_limits'] = flag
    lim = parse({'j1': entry})
    assert np.all(np.isinf(getattr(lim, order)))
    # not even validated: only a limit in force is
    entry[f'max_{order}'] = 'not a number'
    assert np.all(np.isinf(getattr(parse({'j1': entry}), order)))
    assert parse({'j1': {'min_position': 0.5, 'max_position': 'x'}}).lower[0] == LO[0]


def test_position_limits_tighten_and_never_widen():
    lim = parse({
        'j1': {'has_position_limits': True, 'min_position': -5.0, 'max_position': 0.5},
        'j2': {'has_position_limits': True, 'min_position': -1.5, 'max_position': 9.0},
        'j3': {'has_position_limits': False, 'min_position': 1.0, 'max_position': 2.0},
    })
    np.testing.assert_array_equal(lim.lower, [-1.0, -1.5, 0.0])
    np.testing.assert_array_equal(lim.upper, [0.5, 2.0, 3.0])
    assert lim.sources == ('joint_limits: position',)
    # the caller's arrays are not modified
    np.testing.assert_array_equal(LO, [-1.0, -2.0, 0.0])
    # limits outside the URDF's range leave nothing: refused
    with pytest.raises(ValidationError):
        parse({'j1': {'has_position_limits': True, 'min_position': 2.0, 'max_position': 3.0}})


def test_numpy_bools_count_as_flags():
    lim = parse({'j1': {'has_velocity_limits': np.bool_(True), 'max_velocity': np.float64(1.0)}})
    assert lim.velocity[0] == 1.0


# -- KinematicLimits ------------------------------------------------------------------------------
def kl(names, lower, upper, velocity, acceleration, jerk, source='s'):
    return KinematicLimits(tuple(names), lower, upper, velocity, acceleration, jerk, (source,))


@pytest.mark.parametrize('order', ['velocity', 'acceleration', 'jerk'])
@pytest.mark.parametrize('bad', [[1.0, 1.0], [1.0, 0.0, 1.0], [1.0, -2.0, 1.0],
                                 [1.0, float('nan'), 1.0], [[1.0, 1.0, 1.0]]])
def test_kinematic_limits_refuse_bad_values_naming_the_order(order, bad):
    kw = dict(velocity=[1.0] * 3, acceleration=[1.0] * 3, jerk=[1.0] * 3)
    kw[order] = bad
    if np.asarray(bad).size == 3 and np.asarray(bad).ndim == 2:
        # a (1, 3) array is flattened: accepted
        lim = KinematicLimits(NAMES, LO, HI, **kw)
        assert getattr(lim, order).shape == (3,)
        return
    with pytest.raises(ValidationError, match=order):
        KinematicLimits(NAMES, LO, HI, **kw)


def test_kinematic_limits_refuse_bad_position_limits():
    with pytest.raises(ValidationError):
        KinematicLimits(NAMES, HI, LO, [1.0] * 3, [1.0] * 3, [1.0] * 3)
    with pytest.raises(ValidationError):
        KinematicLimits(NAMES, LO[:2], HI[:2], [1.0] * 3, [1.0] * 3, [1.0] * 3)


def test_merged_takes_the_tighter_per_joint_and_order_in_any_joint_order():
    a = kl(NAMES, LO, HI, [1.0, 2.0, INF], [10.0, INF, 5.0], [INF, INF, 100.0], 'urdf')
    perm = [2, 0, 1]
    b = kl([NAMES[i] for i in perm], [-0.5, -3.0, -1.0], [2.0, 0.5, 1.0],
           [3.0, 0.5, 1.0], [INF, 20.0, 2.0], [50.0, INF, INF], 'params')
    # b in a's order: j1 = b[1], j2 = b[2], j3 = b[0]
    m = a.merged(b)
    assert m.joint_names == NAMES
    np.testing.assert_array_equal(m.lower, [-1.0, -1.0, 0.0])
    np.testing.assert_array_equal(m.upper, [0.5, 1.0, 2.0])
    np.testing.assert_array_equal(m.velocity, [0.5, 1.0, 3.0])
    np.testing.assert_array_equal(m.acceleration, [10.0, 2.0, 5.0])
    np.testing.assert_array_equal(m.jerk, [INF, INF, 50.0])
    assert m.sources == ('urdf', 'params')
    # the other way round: the same limits in b's order
    n = b.merged(a)
    assert n.joint_names == b.joint_names and n.sources == ('params', 'urdf')
    for attr in ('lower', 'upper', 'velocity', 'acceleration', 'jerk'):
        np.testing.assert_array_equal(getattr(n, attr), getattr(m, attr)[perm])


def test_merged_refuses_other_joints_and_empty_intersections():
    a = kl(NAMES, LO, HI, [1.0] * 3, [1.0] * 3, [1.0] * 3)
    with pytest.raises(ValidationError, match='joint limits'):
        a.merged(kl(['j1', 'j2', 'elbow'], LO, HI, [1.0] * 3, [1.0] * 3, [1.0] * 3))
    with pytest.raises(ValidationError, match='joint limits'):
        a.merged(kl(['j1', 'j2'], LO[:2], HI[:2], [1.0] * 2, [1.0] * 2, [1.0] * 2))
    with pytest.raises(ValidationError):
        a.merged(kl(NAMES, LO + 5.0, HI + 5.0, [1.0] * 3, [1.0] * 3, [1.0] * 3))


POSITIVE = st.one_of(st.floats(1e-3, 1e5), st.just(INF))


@st.composite
def limit_pair(draw):
    n = draw(st.integers(1, 5))
    names = [f'q{i}' for i in range(n)]

    def one(order):
        lo = np.array(draw(st.lists(st.floats(-5.0, 0.0), min_size=n, max_size=n)))
        hi = np.array(draw(st.lists(st.floats(0.1, 5.0), min_size=n, max_size=n)))
        vals = [draw(st.lists(POSITIVE, min_size=n, max_size=n)) for _ in range(3)]
        return kl([names[i] for i in order], lo[order], hi[order], *(np.array(v)[order]
                                                                     for v in vals))
    perm = draw(st.permutations(list(range(n))))
    return one(list(range(n))), one(list(perm))


@settings(max_examples=100)
@given(limit_pair())
def test_merged_is_never_wider_than_either(pair):
    a, b = pair
    m = a.merged(b)
    idx = [b.joint_names.index(n) for n in a.joint_names]
    assert np.all(m.lower >= a.lower) and np.all(m.lower >= b.lower[idx])
    assert np.all(m.upper <= a.upper) and np.all(m.upper <= b.upper[idx])
    for order in ('velocity', 'acceleration', 'jerk'):
        x, y = getattr(a, order), getattr(b, order)[idx]
        assert np.all(getattr(m, order) <= x) and np.all(getattr(m, order) <= y)
        np.testing.assert_array_equal(getattr(m, order), np.minimum(x, y))  # and not tighter
    np.testing.assert_array_equal(m.lower, np.maximum(a.lower, b.lower[idx]))
    np.testing.assert_array_equal(m.upper, np.minimum(a.upper, b.upper[idx]))
    # merging again changes nothing
    mm = m.merged(b)
    for attr in ('lower', 'upper', 'velocity', 'acceleration', 'jerk'):
        np.testing.assert_array_equal(getattr(mm, attr), getattr(m, attr))


def test_unlimited_and_subset():
    u = KinematicLimits.unlimited(NAMES, LO, HI)
    assert u.sources == ('urdf: position',)
    assert np.all(np.isinf(u.velocity)) and np.all(np.isinf(u.jerk))
    v = KinematicLimits.unlimited(NAMES, LO, HI, [2.0, 0.0, float('nan')], source='file.urdf')
    np.testing.assert_array_equal(v.velocity, [2.0, INF, INF])   # 0 / NaN in a URDF: none
    assert v.sources == ('file.urdf: position, velocity',)
    s = v.subset(['j3', 'j1'])
    assert s.joint_names == ('j3', 'j1')
    np.testing.assert_array_equal(s.lower, [0.0, -1.0])
    np.testing.assert_array_equal(s.velocity, [INF, 2.0])
    with pytest.raises(ValidationError, match='joint limits'):
        v.subset(['j1', 'elbow'])


# -- joint_limits_entries -------------------------------------------------------------------------
@settings(max_examples=100)
@given(limit_pair(), st.booleans())
def test_entries_round_trip_through_parse(pair, position):
    lim = pair[0]
    entries = joint_limits_entries(lim, position=position)
    assert set(entries) == set(lim.joint_names)
    for name, e in entries.items():
        assert set(e) <= set(('has_position_limits', 'min_position', 'max_position',
                              'has_velocity_limits', 'max_velocity', 'has_acceleration_limits',
                              'max_acceleration', 'has_jerk_limits', 'max_jerk'))
        assert all(type(e[k]) is bool for k in e if k.startswith('has_'))
        assert all(type(e[k]) is float for k in e if not k.startswith('has_'))
    n = len(lim.joint_names)
    # with the positions in the entries, any wider position limits give them back
    lower, upper = (lim.lower - 1.0, lim.upper + 1.0) if position else (lim.lower, lim.upper)
    back = parse_joint_limits(lim.joint_names, entries, lower, upper)
    for attr in ('lower', 'upper', 'velocity', 'acceleration', 'jerk'):
        np.testing.assert_array_equal(getattr(back, attr), getattr(lim, attr))
    assert back.joint_names == lim.joint_names and len(back.lower) == n


def test_entries_leave_out_the_max_of_an_unlimited_order():
    lim = kl(['a'], [-1.0], [1.0], [INF], [3.0], [INF])
    assert joint_limits_entries(lim) == {'a': {
        'has_velocity_limits': False, 'has_acceleration_limits': True, 'max_acceleration': 3.0,
        'has_jerk_limits': False}}
    assert joint_limits_entries(lim, position=True)['a']['min_position'] == -1.0


# -- shipped values -------------------------------------------------------------------------------
def test_panda_limits_are_the_datasheet_table_of_the_design_doc():
    lim = panda_limits()
    assert lim.joint_names == tuple(f'panda_joint{i}' for i in range(1, 8))
    assert lim.velocity.tolist() == list(DOC_VELOCITY)
    assert lim.acceleration.tolist() == list(DOC_ACCELERATION)
    assert lim.jerk.tolist() == list(DOC_JERK)
    # position: Franka's datasheet q_min / q_max
    np.testing.assert_array_equal(lim.lower, PANDA_DATASHEET['lower'])
    np.testing.assert_array_equal(lim.upper, PANDA_DATASHEET['upper'])
    assert lim.upper[3] == -0.0698 and lim.lower[5] == -0.0175 and lim.upper[5] == 3.7525
    assert lim.sources == ('Franka datasheet',)
    left = panda_limits('left_panda_')
    assert left.joint_names[0] == 'left_panda_joint1'
    np.testing.assert_array_equal(left.jerk, lim.jerk)


@pytest.mark.parametrize('prefix', ['', 'left_', 'right_', 'arm2_'])
def test_default_joint_limits_give_the_datasheet_to_panda_joints(prefix):
    names = [f'{prefix}panda_joint{i}' for i in range(1, 8)]
    entries = default_joint_limits(names)
    assert list(entries) == names
    for i, name in enumerate(names):
        assert entries[name] == {
            'has_velocity_limits': True, 'max_velocity': DOC_VELOCITY[i],
            'has_acceleration_limits': True, 'max_acceleration': DOC_ACCELERATION[i],
            'has_jerk_limits': True, 'max_jerk': DOC_JERK[i]}
    lim = parse_joint_limits(names, entries, PANDA_DATASHEET['lower'], PANDA_DATASHEET['upper'])
    np.testing.assert_array_equal(lim.velocity, DOC_VELOCITY)
    np.testing.assert_array_equal(lim.acceleration, DOC_ACCELERATION)
    np.testing.assert_array_equal(lim.jerk, DOC_JERK)


def test_default_joint_limits_for_planar_and_unknown_joints():
    names = ['joint1', 'joint2', 'joint12', 'panda_joint8', 'panda_joint0', 'xpanda_joint1',
             'panda_joint', 'joint', 'jointA', 'left_joint1', 'panda_finger_joint1', 'elbow',
             'panda_joint7x']
    entries = default_joint_limits(names)
    planar = {'has_acceleration_limits': True, 'max_acceleration': PLANAR_ACCELERATION,
              'has_jerk_limits': True, 'max_jerk': PLANAR_JERK}
    assert entries == {'joint1': planar, 'joint2': planar, 'joint12': planar}
    assert (PLANAR_ACCELERATION, PLANAR_JERK) == (10.0, 5000.0)
    assert default_joint_limits([]) == {}


# -- ratios and describe ------------------------------------------------------------------------
def test_ratios_are_the_worst_ratio_per_order():
    lim = kl(NAMES, LO, HI, [1.0, 2.0, INF], [10.0, INF, 5.0], [100.0, 100.0, 100.0])
    r = lim.ratios([0.5, -3.0, 1e9], [-20.0, 1e9, 2.5], [0.0, 0.0, -50.0])
    assert r == (1.5, 2.0, 0.5)
    assert all(type(x) is float for x in r)
    # a batch (n_steps, n_dims): the worst over all steps
    V = np.array([[0.1, 0.1, 0.0], [0.0, -1.9, 0.0]])
    assert lim.ratios(V, np.zeros((2, 3)), np.zeros((2, 3))) == (0.95, 0.0, 0.0)
    # nothing to compare: 0
    assert lim.ratios(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3))) == (0.0, 0.0, 0.0)
    unl = KinematicLimits.unlimited(NAMES, LO, HI)
    assert unl.ratios([1e9] * 3, [1e9] * 3, [1e9] * 3) == (0.0, 0.0, 0.0)


def test_describe_lists_every_order_and_none_for_unlimited():
    lim = kl(['a', 'b'], [-1.0, -2.0], [1.0, 2.5], [1.0, INF], [10.0, 20.0], [INF, 1000.0])
    assert lim.describe() == ('position [-1..1, -2..2.5]; velocity [1, none]; '
                              'acceleration [10, 20]; jerk [none, 1000]')
    text = panda_limits().describe()
    assert 'velocity [2.175, 2.175, 2.175, 2.175, 2.61, 2.61, 2.61]' in text
    assert 'acceleration [15, 7.5, 10, 12.5, 15, 20, 20]' in text
    assert 'jerk [7500, 3750, 5000, 6250, 7500, 10000, 10000]' in text
    assert text.startswith('position [-2.897..2.897, -1.763..1.763, ')
