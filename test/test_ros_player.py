"""Player node as a real process: timing and rate, topic selection, remapping, /clock, loop,
refusal of corrupted / truncated / huge-length bags, and replay determinism
(record -> play -> re-record gives identical payloads and order)."""
import os
import signal
import struct
import time

import numpy as np
import pytest

from bag_ros_util import Peer, start_node, stop, wait_for
from cdmp_ros.bag import BagReader, BagWriter
from cdmp_ros.bag.cdr import decode_string, encode_string

pytestmark = pytest.mark.ros
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.fixture
def peer():
    p = Peer('player_peer')
    yield p
    p.close()


def _bag(path, n=20, dt_ns=50_000_000, topics=('/a',)):
    t0 = 1_000_000_000_000
    with BagWriter(path) as w:
        for t in topics:
            w.add_topic(t, 'std_msgs/msg/String')
        for i in range(n):
            for t in topics:
                w.write(t, encode_string(f'{t}:{i:03d}'), t0 + i * dt_ns)
    return t0


def test_original_timing_at_rate_two_with_remap_selection_and_clock(tmp_path, peer):
    from rosgraph_msgs.msg import Clock
    from std_msgs.msg import String
    bag = str(tmp_path / 'timed')
    t0 = _bag(bag, topics=('/a', '/b'))
    got_c = peer.collect(String, '/c')
    got_b = peer.collect(String, '/b')
    got_clock = peer.collect(Clock, '/clock', raw=False)
    play = start_node('player', {'bag': bag, 'rate': 2.0, 'topics': ['/a'], 'clock': True,
                                 'wait_for_subscribers': 1, 'start_delay': 0.3},
                      remaps=['/a:=/c'], log_path=str(tmp_path / 'play.log'))
    try:
        play.wait(timeout=30)
    finally:
        stop(play, signal.SIGKILL)
    assert play.returncode == 0, open(tmp_path / 'play.log').read()
    assert wait_for(lambda: len(got_c) == 20, 5)
    assert [decode_string(m) for _, m in got_c] == [f'/a:{i:03d}' for i in range(20)]
    assert got_b == []  # not selected
    gaps = np.diff([t for t, _ in got_c])
    # 50 ms apart in the bag, played at rate 2 -> 25 ms apart
    assert abs(np.median(gaps) - 0.025) < 0.006, gaps
    assert abs((got_c[-1][0] - got_c[0][0]) - 19 * 0.025) < 0.08
    stamps = [c.clock.sec * 10 ** 9 + c.clock.nanosec for _, c in got_clock]
    assert stamps[:20] == [t0 + i * 50_000_000 for i in range(20)]


def test_loop_replays_in_order_until_stopped(tmp_path, peer):
    from std_msgs.msg import String
    bag = str(tmp_path / 'loop')
    _bag(bag, n=5, dt_ns=10_000_000)
    got = peer.collect(String, '/a')
    play = start_node('player', {'bag': bag, 'loop': True, 'wait_for_subscribers': 1,
                                 'start_delay': 0.3}, log_path=str(tmp_path / 'play.log'),
                      extra=['--params-file', os.path.join(ROOT, 'config', 'bag.yaml')])
    try:
        assert wait_for(lambda: len(got) >= 16, 20), len(got)
        assert stop(play) == 0
    finally:
        stop(play, signal.SIGKILL)
    texts = [decode_string(m) for _, m in got]
    assert texts[:15] == [f'/a:{i:03d}' for i in range(5)] * 3


def _corrupt(bag, how):
    path = os.path.join(bag, os.path.basename(bag) + '_0.mcap')
    raw = bytearray(open(path, 'rb').read())
    if how == 'flip':
        raw[len(raw) // 3] ^= 0xFF
    elif how == 'truncate':
        raw = raw[:len(raw) * 2 // 3]
    elif how == 'huge_length':
        struct.pack_into('<Q', raw, 8 + 1, 2 ** 62)  # the header record's length
    open(path, 'wb').write(bytes(raw))


@pytest.mark.parametrize('how', ['flip', 'truncate', 'huge_length'])
def test_refuses_bad_bag_and_publishes_nothing(tmp_path, peer, how):
    from std_msgs.msg import String
    bag = str(tmp_path / 'bad')
    _bag(bag, n=200)
    _corrupt(bag, how)
    got = peer.collect(String, '/a')
    log = str(tmp_path / 'play.log')
    t = time.monotonic()
    play = start_node('player', {'bag': bag}, log_path=log)
    try:
        play.wait(timeout=20)
    finally:
        stop(play, signal.SIGKILL)
    assert time.monotonic() - t < 20
    assert play.returncode == 2
    text = open(log).read()
    assert any(w in text for w in ('CRC', 'truncated', 'declares', 'corrupted', 'recover')), text
    time.sleep(0.2)
    assert got == []


def test_replay_determinism_record_play_rerecord(tmp_path, peer):
    """Demo bag -> play -> record -> play -> record: identical payloads and order."""
    src = os.path.join(ROOT, 'bags', 'panda_reach', 'demo_00')
    generations = [src]
    for gen in range(2):
        out = str(tmp_path / f'gen{gen}')
        rec = start_node('recorder', {'output': out, 'topics': ['/demonstration']},
                         log_path=str(tmp_path / f'rec{gen}.log'))
        play = start_node('player', {'bag': generations[-1], 'rate': 4.0,
                                     'wait_for_subscribers': 1, 'start_delay': 0.3},
                          log_path=str(tmp_path / f'play{gen}.log'))
        try:
            assert play.wait(timeout=30) == 0
            time.sleep(0.5)
            assert stop(rec) == 0
        finally:
            stop(play, signal.SIGKILL)
            stop(rec, signal.SIGKILL)
        generations.append(out)
    payloads = [[m.data for m in BagReader(g).messages()] for g in generations]
    assert len(payloads[0]) == 201
    # JointState CDR from our encoder is 4-byte aligned, so DDS adds no padding
    assert payloads[1] == payloads[0]
    assert payloads[2] == payloads[0]
    times = [m.log_time for m in BagReader(generations[1]).messages()]
    span = (times[-1] - times[0]) / 1e9
    assert abs(span - 2.0 / 4.0) < 0.1, span
