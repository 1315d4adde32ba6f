"""Sample demonstration bags: deterministic, within the Panda limits, smooth, and readable as
(T, Y, joint_names) for the learner."""
import os

import numpy as np
import pytest

from cdmp_ros.bag import BagError, BagWriter, read_demonstrations
from cdmp_ros.bag.cdr import encode_joint_state
from cdmp_ros.bag.demos import (PANDA_JOINTS, PANDA_Y_MAX, PANDA_Y_MIN, PLANAR4_JOINTS,
                                PLANAR4_START, min_jerk, noisy_reach, planar4_reach_set,
                                write_set)
from cdmp_ros.core.errors import ValidationError
from conftest import load_script

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
BAGS = os.path.join(ROOT, 'bags')


def _load_script():
    return load_script('make_demo_bags')


def _messages(bag):
    from cdmp_ros.bag.cdr import decode_joint_state
    from cdmp_ros.bag.reader import BagReader
    out = []
    for m in BagReader(bag).messages():
        assert m.type == 'sensor_msgs/msg/JointState', m.type
        js = decode_joint_state(m.data)
        out.append(((m.topic, m.log_time, m.publish_time, m.sequence, js.stamp_ns, js.frame_id,
                     js.name), np.concatenate([js.position, js.velocity, js.effort])))
    return out


def assert_same_bags(written, root):
    """Bags written under ``root`` equal the committed ones of the same relative path."""
    for bag in written:
        rel = os.path.relpath(bag, root)
        assert sorted(os.listdir(bag)) == sorted(os.listdir(os.path.join(BAGS, rel))), rel
        ours, committed = _messages(bag), _messages(os.path.join(BAGS, rel))
        assert len(ours) == len(committed) > 0, rel
        for (k1, v1), (k2, v2) in zip(ours, committed):
            assert k1 == k2, rel
            np.testing.assert_allclose(v1, v2, rtol=0.0, atol=1e-12, err_msg=rel)


def test_committed_bags_are_reproduced_by_the_script(tmp_path):
    """The script regenerates the committed bags: the same files, metadata, topics, times and
    names; floats to 1e-12 (numpy's vectorised sin/exp may differ in the last bit between
    CPUs, so the bytes may not be identical on every machine)."""
    written = _load_script().make(str(tmp_path))
    assert len(written) == 11
    assert_same_bags(written, str(tmp_path))


def test_planar4_set_is_reproduced_and_inside_the_limits(tmp_path):
    """bags/planar4_reach (the learner's demonstrations for robot planar4) is
    ``write_set(planar4_reach_set(default_rng(8)))`` (scripts/make_demo_bags.py,
    bags/README.md); 3 reaches of the 4 planar joints from the sim's initial pose, at least
    0.5 rad inside the +-2.8 rad limits of urdf/planar4.urdf."""
    assert _load_script().SETS['planar4_reach'] == (planar4_reach_set, 8)
    written = write_set(str(tmp_path / 'planar4_reach'),
                        planar4_reach_set(np.random.default_rng(8)))
    assert len(written) == 3
    assert_same_bags(written, str(tmp_path))
    demos = read_demonstrations(os.path.join(BAGS, 'planar4_reach'))
    assert len(demos) == 3
    for T, Y, names in demos:
        assert names == PLANAR4_JOINTS
        assert T.shape == (201,) and Y.shape == (201, 4)
        np.testing.assert_allclose(Y[0], PLANAR4_START, atol=1e-12)
        assert np.all(np.abs(Y) <= 2.8 - 0.5)


def test_bags_are_small():
    total = sum(os.path.getsize(os.path.join(d, f)) for d, _, fs in os.walk(BAGS) for f in fs)
    assert total < 600 * 1024


def test_panda_reach_set():
    demos = read_demonstrations(os.path.join(BAGS, 'panda_reach'))
    assert len(demos) == 5
    for T, Y, names in demos:
        assert names == PANDA_JOINTS
        assert T.shape == (201,) and Y.shape == (201, 7)
        np.testing.assert_allclose(T, np.arange(201) / 100.0, atol=1e-9)
        assert np.all(Y >= PANDA_Y_MIN + 0.5) and np.all(Y <= PANDA_Y_MAX - 0.5)
    # noisy: demonstrations differ, but not by much
    ends = np.array([Y[-1] for _, Y, _ in demos])
    assert np.all(ends.std(axis=0) > 0.005) and np.all(ends.std(axis=0) < 0.2)
    starts = np.array([Y[0] for _, Y, _ in demos])
    np.testing.assert_allclose(starts, np.tile(starts[0], (5, 1)), atol=1e-12)


def test_dual_arm_set():
    demos = read_demonstrations(os.path.join(BAGS, 'dual_panda'))
    assert len(demos) == 3
    for T, Y, names in demos:
        assert Y.shape == (201, 14)
        assert names == [f'left_{j}' for j in PANDA_JOINTS] + [f'right_{j}' for j in PANDA_JOINTS]
        lim_lo = np.tile(PANDA_Y_MIN, 2) + 0.5
        lim_hi = np.tile(PANDA_Y_MAX, 2) - 0.5
        assert np.all(Y >= lim_lo) and np.all(Y <= lim_hi)


def test_recorded_velocity_is_the_derivative_of_position():
    """Velocity in the bags vs central finite differences of the recorded positions."""
    from cdmp_ros.bag.cdr import decode_joint_state
    from cdmp_ros.bag import BagReader
    msgs = [decode_joint_state(m.data) for m in
            BagReader(os.path.join(BAGS, 'panda_reach', 'demo_02')).messages()]
    Y = np.array([m.position for m in msgs])
    Yd = np.array([m.velocity for m in msgs])
    fd = (Y[2:] - Y[:-2]) / 0.02
    np.testing.assert_allclose(Yd[1:-1], fd, atol=2e-3)
    np.testing.assert_allclose(Yd[0], 0, atol=1e-12)
    np.testing.assert_allclose(Yd[-1], 0, atol=1e-12)


def test_min_jerk_and_noisy_reach_boundary_conditions(rng):
    tau = np.linspace(0, 1, 101)
    s, ds = min_jerk(tau)
    assert s[0] == 0 and s[-1] == 1 and ds[0] == 0 and ds[-1] == 0
    np.testing.assert_allclose(np.gradient(s, tau)[5:-5], ds[5:-5], atol=2e-3)
    start = np.zeros(3)
    T, Y, Yd = noisy_reach(start, np.ones(3), rng, goal_noise=0.0)
    np.testing.assert_allclose(Y[0], 0, atol=1e-15)
    np.testing.assert_allclose(Y[-1], 1, atol=1e-12)


def test_one_bag_with_several_demonstrations_split_on_stamp_reset(tmp_path):
    bag = str(tmp_path / 'topic_demos')
    with BagWriter(bag) as w:
        w.add_topic('/demonstration', 'sensor_msgs/msg/JointState')
        t = 0
        for d, n in enumerate((5, 7, 3)):
            for k in range(n):
                t += 1
                w.write('/demonstration',
                        encode_joint_state(10 ** 9 + k * 10 ** 7, ['q1', 'q2'], [d, k]), t)
    demos = read_demonstrations(bag)
    assert [Y.shape for _, Y, _ in demos] == [(5, 2), (7, 2), (3, 2)]
    np.testing.assert_allclose(demos[1][0], np.arange(7) * 0.01)
    np.testing.assert_array_equal(demos[2][1][:, 0], 2)


def test_reader_errors(tmp_path):
    with pytest.raises(BagError, match='not a bag'):
        read_demonstrations(str(tmp_path / 'missing'))
    (tmp_path / 'empty').mkdir()
    with pytest.raises(BagError, match='no bag'):
        read_demonstrations(str(tmp_path / 'empty'))
    bag = str(tmp_path / 'bad')
    with BagWriter(bag) as w:
        w.add_topic('demonstration', 'sensor_msgs/msg/JointState')
        w.write('demonstration', encode_joint_state(1, ['a', 'b'], [1.0, 2.0]), 1)
        w.write('demonstration', encode_joint_state(2, ['a'], [1.0]), 2)
    with pytest.raises(ValidationError, match='expected joints'):
        read_demonstrations(bag)
    with pytest.raises(BagError, match='no message on topic'):
        read_demonstrations(bag, topic='other')
