"""Player node: its schedule (bag time / rate, on a fake clock), and as a real process topic
selection, remapping, /clock, loop, refusal of corrupted / truncated / huge-length bags, and
replay determinism (record -> play -> re-record gives identical payloads and order).  No wall
clock figure is asserted: benchmarks/bench_bag_timing.py prints the timing fidelity."""
import os
import signal
import struct

import numpy as np
import pytest

from bag_ros_util import Peer, recoverable_count
from conftest import wait_for
from node_harness import WAIT_S, assert_clean_stop, start_node, stop_process
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


def test_messages_are_due_at_their_bag_time_divided_by_the_rate(tmp_path, monkeypatch):
    """The playback schedule without the wall clock: the player's clock is a fake one that only
    its own waits advance, so every message (and its /clock tick just before it) must be
    published at exactly t0 + (log_time - first log_time) / rate; a late wake-up delays that
    message only (the schedule keeps to the bag, it does not drift).  The figures of the real
    timing are printed by benchmarks/bench_bag_timing.py."""
    from types import SimpleNamespace
    from cdmp_ros.bag.cdr import encode_clock
    from cdmp_ros.ros import bag_bridge
    bag = str(tmp_path / 'sched')
    t0 = _bag(bag, n=20, dt_ns=50_000_000)
    now = [100.0]

    class Stop:
        def wait(self, seconds):
            now[0] += seconds + (0.01 if len(sent) == 2 * 5 else 0.0)  # message 5: 10 ms late
            return False

        def is_set(self):
            return False

    sent = []

    class Pub:
        def __init__(self, name):
            self.name = name

        def publish(self, data):
            sent.append((self.name, now[0], data))

    monkeypatch.setattr(bag_bridge, 'time', SimpleNamespace(monotonic=lambda: now[0]))
    player = SimpleNamespace(reader=BagReader(bag), pubs={'/a': Pub('/a')}, rate=2.0,
                             clock_pub=Pub('/clock'), _stop=Stop(), published=0)
    bag_bridge.PlayerNode._play_once(player)
    assert player.published == 20
    assert [name for name, _, _ in sent] == ['/clock', '/a'] * 20
    clocks, msgs = sent[0::2], sent[1::2]
    assert [decode_string(d) for _, _, d in msgs] == [f'/a:{i:03d}' for i in range(20)]
    assert [d for _, _, d in clocks] == [encode_clock(t0 + i * 50_000_000) for i in range(20)]
    due = [100.0 + i * 0.025 + (0.01 if i == 5 else 0.0) for i in range(20)]
    np.testing.assert_allclose([t for _, t, _ in msgs], due, rtol=0, atol=1e-9)
    np.testing.assert_allclose([t for _, t, _ in clocks], due, rtol=0, atol=1e-9)


def test_plays_the_selected_topic_remapped_in_order_with_clock(tmp_path, peer):
    """A real player process: only the selected topic is played, under its remapped name, in
    bag order, looping; /clock carries the bag time of each message, from the first one on
    (the player waits for a subscriber on /clock too)."""
    from rosgraph_msgs.msg import Clock
    from std_msgs.msg import String
    bag = str(tmp_path / 'timed')
    t0 = _bag(bag, topics=('/a', '/b'))
    got_c = peer.collect(String, '/c')
    got_b = peer.collect(String, '/b')
    got_clock = peer.collect(Clock, '/clock', raw=False)
    log = str(tmp_path / 'play.log')
    play = start_node('player', {'bag': bag, 'rate': 2.0, 'topics': ['/a'], 'clock': True,
                                 'loop': True, 'wait_subscribers': WAIT_S},
                      remaps=['/a:=/c'], log_path=log)
    try:
        assert wait_for(lambda: len(got_c) >= 40 and len(got_clock) >= 21, WAIT_S), (
            len(got_c), len(got_clock), open(log).read())
        assert_clean_stop(stop_process(play), open(log).read(), 'player')
    finally:
        stop_process(play, signal.SIGKILL)
    texts = [decode_string(m) for _, m in got_c]
    assert texts[:40] == [f'/a:{i:03d}' for i in range(20)] * 2
    bag_times = [t0 + i * 50_000_000 for i in range(20)]
    stamps = [c.clock.sec * 10 ** 9 + c.clock.nanosec for _, c in got_clock]
    assert stamps == [bag_times[j % 20] for j in range(len(stamps))]
    # positive evidence that /b was left out: the player created no publisher for it
    assert 'playing ' + bag + ": ['/a'] at rate 2.0" in open(log).read()
    assert got_b == []


def test_loop_replays_in_order_until_stopped(tmp_path, peer):
    from std_msgs.msg import String
    bag = str(tmp_path / 'loop')
    _bag(bag, n=5, dt_ns=10_000_000)
    got = peer.collect(String, '/a')
    play = start_node('player', {'bag': bag, 'loop': True, 'wait_subscribers': WAIT_S},
                      log_path=str(tmp_path / 'play.log'),
                      extra=['--params-file', os.path.join(ROOT, 'config', 'bag.yaml')])
    try:
        assert wait_for(lambda: len(got) >= 16, WAIT_S), len(got)
        assert_clean_stop(stop_process(play), (tmp_path / 'play.log').read_text(), 'player')
    finally:
        stop_process(play, signal.SIGKILL)
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
    play = start_node('player', {'bag': bag}, log_path=log)
    try:
        play.wait(timeout=60)
    finally:
        stop_process(play, signal.SIGKILL)
    assert play.returncode == 2
    text = open(log).read()
    assert any(w in text for w in ('CRC', 'truncated', 'declares', 'corrupted', 'recover')), text
    # positive evidence that nothing was published: the bag was refused before the player
    # created any publisher (it logs 'playing ...' once it has them)
    assert 'playing' not in text and 'published' not in text, text
    assert got == []


def test_replay_determinism_record_play_rerecord(tmp_path, peer):
    """Demo bag -> play -> record -> play -> record: identical payloads and order."""
    src = os.path.join(ROOT, 'bags', 'panda_reach', 'demo_00')
    generations = [src]
    for gen in range(2):
        out = str(tmp_path / f'gen{gen}')
        rec_log = tmp_path / f'rec{gen}.log'
        rec = start_node('recorder', {'output': out, 'topics': ['/demonstration']},
                         log_path=str(rec_log))
        play = None
        try:
            # the recorder runs (it subscribes when the player's publisher appears), then the
            # player starts once it subscribed: a reliable writer then delivers every message
            assert wait_for(lambda: 'recording to' in rec_log.read_text(), WAIT_S)
            play = start_node('player', {'bag': generations[-1], 'rate': 4.0,
                                         'wait_subscribers': WAIT_S},
                              log_path=str(tmp_path / f'play{gen}.log'))
            assert play.wait(timeout=60) == 0
            # every message is on disk before the recorder is stopped
            probe = str(tmp_path / f'probe{gen}')
            assert wait_for(lambda: recoverable_count(out, probe) >= 201, WAIT_S, period=0.1)
            assert_clean_stop(stop_process(rec), rec_log.read_text(), 'recorder')
        finally:
            if play is not None:
                stop_process(play, signal.SIGKILL)
            stop_process(rec, signal.SIGKILL)
        generations.append(out)
    payloads = [[m.data for m in BagReader(g).messages()] for g in generations]
    assert len(payloads[0]) == 201
    # JointState CDR from our encoder is 4-byte aligned, so DDS adds no padding
    assert payloads[1] == payloads[0]
    assert payloads[2] == payloads[0]
