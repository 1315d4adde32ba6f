"""QoS glue of the recorder/player: rclpy profiles <-> rosbag2 v9 dicts, adaptive choice."""
from rclpy.duration import Duration
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from cdmp_ros.bag.metadata import INFINITE, qos_dict
from cdmp_ros.ros.qos import (adapted_subscription_profile, dict_to_profile, playback_profile,
                              profile_to_dict)


def test_profile_round_trip_and_infinite_durations():
    q = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=7,
                   reliability=ReliabilityPolicy.BEST_EFFORT,
                   durability=DurabilityPolicy.TRANSIENT_LOCAL,
                   deadline=Duration(seconds=1, nanoseconds=5))
    d = profile_to_dict(q)
    assert d['history'] == 'keep_last' and d['depth'] == 7
    assert d['reliability'] == 'best_effort' and d['durability'] == 'transient_local'
    assert d['deadline'] == {'sec': 1, 'nsec': 5}
    assert d['lifespan'] == INFINITE and d['liveliness'] == 'system_default'
    back = dict_to_profile(d)
    assert (back.reliability, back.durability, back.depth) == (
        ReliabilityPolicy.BEST_EFFORT, DurabilityPolicy.TRANSIENT_LOCAL, 7)


def test_playback_profile_defaults_and_version8_integers():
    assert playback_profile([]).reliability == ReliabilityPolicy.RELIABLE
    p = playback_profile([qos_dict(depth=0)], depth=100)
    assert p.depth == 100 and p.history == HistoryPolicy.KEEP_LAST
    v8 = {'history': 1, 'depth': 5, 'reliability': 2, 'durability': 1}  # rosbag2 <= v8 ints
    p = dict_to_profile(v8)
    assert p.reliability == ReliabilityPolicy.BEST_EFFORT
    assert p.durability == DurabilityPolicy.TRANSIENT_LOCAL
    unknown = dict_to_profile({'history': 'unknown', 'reliability': 'bogus'})
    assert unknown.history == HistoryPolicy.KEEP_LAST
    assert unknown.reliability == ReliabilityPolicy.RELIABLE


def test_adapted_subscription_follows_every_publisher():
    rel = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
    be = QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT)
    q = adapted_subscription_profile([rel, rel], depth=50)
    assert q.reliability == ReliabilityPolicy.RELIABLE and q.depth == 50
    assert q.durability == DurabilityPolicy.TRANSIENT_LOCAL  # latched topics keep their last
    q = adapted_subscription_profile([rel, be])
    assert q.reliability == ReliabilityPolicy.BEST_EFFORT
    assert q.durability == DurabilityPolicy.VOLATILE
