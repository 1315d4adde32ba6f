"""Demonstrations for the learner: validation and joint mapping, topic segmentation, and the
fit of DMP / CDMP / ProMP from demonstrations of different lengths (cdmp_ros.core.learning)."""
import os

import numpy as np
import pytest

from cdmp_ros.core.demonstrations import DemonstrationSegmenter, map_demonstration
from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.learning import LearnerConfig, PrompLearnConfig, fit_primitive
from conftest import REPO_ROOT

JOINTS = tuple(f'panda_joint{i}' for i in range(1, 8))
LOWER = np.array([-2.9671, -1.8326, -2.9671, -3.1416, -2.9671, -0.0873, -2.9671])
UPPER = np.array([2.9671, 1.8326, 2.9671, 0.0, 2.9671, 3.8223, 2.9671])


@pytest.fixture(scope='module')
def bag_demos():
    from cdmp_ros.bag import read_demonstrations
    return [(T, Y) for T, Y, _ in read_demonstrations(os.path.join(REPO_ROOT, 'bags',
                                                                   'panda_reach'))]


# -- map_demonstration ---------------------------------------------------------------------------
def test_columns_are_mapped_by_name_and_extra_joints_ignored(bag_demos):
    T, Y = bag_demos[0]
    perm = [3, 6, 0, 2, 5, 1, 4]
    names = [JOINTS[i] for i in perm] + ['panda_finger_joint1']
    Yp = np.hstack([Y[:, perm], np.full((T.size, 1), 0.04)])
    T2, Y2 = map_demonstration('d', T + 7.0, Yp, names, JOINTS, LOWER, UPPER)
    assert np.array_equal(Y2, Y)
    assert T2[0] == 0.0 and np.allclose(T2, T)


@pytest.mark.parametrize('case, text', [
    ('duplicate', "d: duplicate joint name 'panda_joint1'"),
    ('missing', "d: missing joints ['panda_joint7']"),
    ('nan', 'd: positions: expected finite values, got nan at index (5, 2)'),
    ('short', 'd: expected at least 10 samples, got 4'),
    ('non_monotonic', 'd: non-monotonic time at sample 3'),
    ('outside', "d: position of 'panda_joint4' (sample 2): 0.3 is outside the limits"),
    ('shape', 'd: positions: expected shape (20, 7), got (19, 7)'),
])
def test_bad_recorded_demonstrations_are_rejected_naming_the_problem(case, text):
    T = np.arange(20) * 0.01
    Y = np.tile(np.array([0.0, 0.0, 0.0, -1.0, 0.0, 1.0, 0.0]), (20, 1))
    names = list(JOINTS)
    if case == 'duplicate':
        names[6] = 'panda_joint1'
    elif case == 'missing':
        names, Y = names[:6], Y[:, :6]
    elif case == 'nan':
        Y[5, 2] = np.nan
    elif case == 'short':
        T, Y = T[:4], Y[:4]
    elif case == 'non_monotonic':
        T[3] = T[2]
    elif case == 'outside':
        Y[2, 3] = 0.3  # upper limit 0.0, tolerance 0.05
    elif case == 'shape':
        Y = Y[:19]
    with pytest.raises(ValidationError) as e:
        map_demonstration('d', T, Y, names, JOINTS, LOWER, UPPER, min_samples=10)
    assert text in str(e.value)


def test_small_excursions_within_the_tolerance_are_kept():
    T = np.arange(20) * 0.01
    Y = np.tile(np.array([0.0, 0.0, 0.0, 0.04, 0.0, 1.0, 0.0]), (20, 1))
    _, Y2 = map_demonstration('d', T, Y, JOINTS, JOINTS, LOWER, UPPER, limit_tolerance=0.05)
    assert Y2[0, 3] == 0.04


# -- segmentation --------------------------------------------------------------------------------
def _seg(**kw):
    args = dict(gap=0.5, min_samples=5, max_samples=1000, limit_tolerance=0.05)
    args.update(kw)
    return DemonstrationSegmenter(JOINTS, LOWER, UPPER, **args)


Q = np.array([0.0, -0.5, 0.0, -2.0, 0.0, 1.5, 0.7])


def test_a_stamp_gap_closes_the_demonstration_and_starts_the_next():
    s = _seg()
    for k in range(10):
        assert s.add(100.0 + 0.01 * k, Q + 0.01 * k, now=k * 0.01) == []
    ev = s.add(100.09 + 0.6, Q, now=0.1)  # 0.6 s after the last stamp > gap
    assert len(ev) == 1 and ev[0].demo is not None and 'stamp gap of 0.600 s' in ev[0].message
    T, Y = ev[0].demo
    assert np.allclose(T, np.arange(10) * 0.01) and np.allclose(Y[-1], Q + 0.09)
    assert s.n_pending == 1 and s.n_completed == 1


def test_silence_for_the_gap_closes_the_demonstration():
    s = _seg()
    for k in range(6):
        s.add(5.0 + 0.01 * k, Q, now=10.0 + 0.01 * k)
    assert s.poll(10.05 + 0.5) == []           # exactly the gap: not yet
    ev = s.poll(10.05 + 0.51)
    assert len(ev) == 1 and ev[0].demo[0].size == 6 and 'no sample for 0.510 s' in ev[0].message
    assert s.poll(20.0) == [] and s.n_pending == 0


def test_end_marker_closes_and_short_demonstrations_are_discarded():
    s = _seg(min_samples=5)
    for k in range(4):
        s.add(0.01 * k, Q, now=0.0)
    ev = s.end('end marker')
    assert ev[0].demo is None
    assert ev[0].message == ('demonstration discarded (end marker): 4 samples, expected at '
                             'least min_samples=5')
    assert s.end() == [] and s.n_completed == 0


def test_max_samples_closes_the_demonstration():
    s = _seg(max_samples=8)
    events = []
    for k in range(12):
        events += s.add(0.01 * k, Q, now=0.0)
    assert len(events) == 1 and events[0].demo[0].size == 8 and s.n_pending == 4


def test_bad_samples_are_rejected_and_the_demonstration_goes_on():
    s = _seg()
    s.add(1.0, Q, now=0.0)
    s.add(1.01, Q, now=0.0)
    with pytest.raises(ValidationError, match='non-monotonic time, -0.005000 s'):
        s.add(1.005, Q, now=0.0)
    with pytest.raises(ValidationError, match='non-monotonic time'):
        s.add(1.01, Q, now=0.0)  # repeated stamp
    bad = Q.copy()
    bad[5] = 4.5
    with pytest.raises(ValidationError, match="position of 'panda_joint6': 4.5 is outside"):
        s.add(1.02, bad, now=0.0)
    with pytest.raises(ValidationError, match='expected finite values'):
        s.add(1.02, np.full(7, np.inf), now=0.0)
    with pytest.raises(ValidationError, match=r'expected shape \(7\), got \(6,\)'):
        s.add(1.02, Q[:6], now=0.0)
    assert s.n_pending == 2
    for k in range(3):
        s.add(1.02 + 0.01 * k, Q, now=0.0)
    assert s.end()[0].demo[0].size == 5


# -- fitting -------------------------------------------------------------------------------------
def _varied(bag_demos):
    """The bag demonstrations with different lengths and durations (resampled)."""
    out = []
    for i, (T, Y) in enumerate(bag_demos):
        n = 101 + 60 * i
        Tn = np.linspace(0.0, 2.0 + 0.25 * i, n)
        src = np.linspace(0.0, Tn[-1], T.size)
        out.append((Tn, np.stack([np.interp(Tn, src, Y[:, d]) for d in range(7)], axis=1)))
    return out


@pytest.mark.parametrize('kind', ['cdmp', 'dmp'])
def test_dmp_fit_from_demonstrations_of_different_lengths(bag_demos, kind):
    demos = _varied(bag_demos)
    prim = fit_primitive(kind, demos, JOINTS, LOWER, UPPER)
    assert prim.kind == kind and prim.joint_names == list(JOINTS)
    goals = np.array([Y[-1] for _, Y in demos])
    assert np.allclose(prim.goal_y_, goals.mean(axis=0), atol=1e-12)
    assert prim.tau_ == pytest.approx(np.mean([T[-1] for T, _ in demos]), abs=1e-12)
    assert prim.metadata['n_demonstrations'] == 5
    assert prim.metadata['fit_rms_error'] < 0.1
    Y = prim.rollout(dt=0.005).Y
    assert np.abs(Y[-1] - goals.mean(axis=0)).max() < 0.02
    # the mean demonstration (phase-aligned) is followed within the demos' spread
    s = np.linspace(0, 1, 50)
    mean_demo = np.mean([np.stack([np.interp(s, T / T[-1], Yd[:, d]) for d in range(7)], 1)
                         for T, Yd in demos], axis=0)
    Yr = np.stack([np.interp(s, np.linspace(0, 1, Y.shape[0]), Y[:, d]) for d in range(7)], 1)
    assert np.abs(Yr - mean_demo).max() < 0.1


def test_promp_fit_from_demonstrations_of_different_lengths(bag_demos):
    demos = _varied(bag_demos)
    prim = fit_primitive('promp', demos, JOINTS, LOWER, UPPER, promp_config=PrompLearnConfig(
        n_basis=10, n_iter=30))
    assert prim.kind == 'promp' and prim.n_basis == 10
    s = np.linspace(0, 1, 50)
    per_demo = np.array([np.stack([np.interp(s, T / T[-1], Y[:, d]) for d in range(7)], 1)
                         for T, Y in demos])
    assert np.abs(prim.mean(s) - per_demo.mean(axis=0)).max() < 0.02
    sd = np.sqrt(np.diagonal(prim.cov(s), axis1=1, axis2=2))
    assert np.all(sd[-1] > 0.3 * per_demo[:, -1].std(axis=0))  # the goal spread is learnt
    assert prim.metadata['limits']['upper'] == UPPER.tolist()


def test_fit_refuses_bad_requests(bag_demos):
    with pytest.raises(ValidationError, match='kind: expected one of'):
        fit_primitive('spline', bag_demos, JOINTS, LOWER, UPPER)
    with pytest.raises(ValidationError, match='at least one demonstration'):
        fit_primitive('cdmp', [], JOINTS, LOWER, UPPER)
    with pytest.raises(ValidationError, match=r'demos\[1\].Y: expected shape \(201, 7\)'):
        fit_primitive('cdmp', [bag_demos[0], (bag_demos[1][0], bag_demos[1][1][:, :6])],
                      JOINTS, LOWER, UPPER)


@pytest.mark.parametrize('kw, text', [
    (dict(kind='spline'), "kind: expected one of ['cdmp', 'dmp', 'promp'], got 'spline'"),
    (dict(demonstration_gap=-1.0), 'demonstration_gap: expected a value in'),
    (dict(min_samples=50, max_samples=20), 'max_samples: expected >= min_samples (50)'),
    (dict(demonstration_bags=('',)), 'demonstration_bags: expected a list of paths'),
    (dict(joint_names=('a', 'a')), 'joint_names: expected unique non-empty names'),
    (dict(min_samples=2.5), 'min_samples: expected int'),
    (dict(demonstration_topic='/'), 'demonstration_topic: expected a topic name'),
    (dict(fit_on_start=1), 'fit_on_start: expected a bool'),
])
def test_learner_config_is_validated(kw, text):
    with pytest.raises(ValidationError) as e:
        LearnerConfig(**kw)
    assert text in str(e.value)


def test_promp_learn_config_is_validated():
    with pytest.raises(ValidationError, match='n_basis: expected a value in'):
        PrompLearnConfig(n_basis=1)
    assert PrompLearnConfig(n_basis=2).n_basis == 2
