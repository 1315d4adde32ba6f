"""The player's waits (issue 31, item 6): before playing, for a subscriber on every topic it
plays and on /clock, at most ``wait_subscribers`` s (``cdmp bag play --wait-subscribers S``),
then it plays anyway naming the topics without one (log and diagnostics); after the last
message, for the acknowledgements of the reliable subscribers, at most ``ack_timeout`` s.

The decisions (what is still awaited, until when, what the state says) are ROS-free functions
tested on a fake clock; the behaviour is tested with real player processes. Every wait is on a
condition (a log line, a message count, the process end); no duration is asserted.
"""
import signal
import subprocess
import sys

import pytest

from bag_ros_util import Peer
from conftest import ros_env, wait_for
from node_harness import NodeHarness, WAIT_S, assert_clean_stop, start_node, stop_process
from cdmp_ros.bag import BagReader, BagWriter
from cdmp_ros.bag.cdr import decode_string, encode_string

T0_NS = 1_000_000_000_000


@pytest.fixture
def peer():
    p = Peer('player_wait_peer')
    yield p
    p.close()


def _bag(path, n=20, dt_ns=50_000_000, topics=('/a',)):
    with BagWriter(path) as w:
        for t in topics:
            w.add_topic(t, 'std_msgs/msg/String')
        for i in range(n):
            for t in topics:
                w.write(t, encode_string(f'{t}:{i:03d}'), T0_NS + i * dt_ns)
    return [T0_NS + i * dt_ns for i in range(n)]


def _lines(path):
    return open(path).read().splitlines()


def _logged(path, text):
    """True when a log line of the player ends with ``text`` (rcutils: '[LEVEL] [t] [player]:
    text')."""
    return any(line.endswith(text) for line in _lines(path))


# -- the decisions, without ROS ----------------------------------------------------------------
class FakeTime:
    """A clock that only the waits advance, and a stop event on it."""

    def __init__(self, stop_at=None):
        self.now = 0.0
        self.waits = []
        self.stop_at = stop_at

    def __call__(self):
        return self.now

    def wait(self, seconds):
        self.waits.append(seconds)
        self.now += seconds
        return self.is_set()

    def is_set(self):
        return self.stop_at is not None and self.now >= self.stop_at


def test_without_subscriber_names_every_topic_without_one_once():
    from cdmp_ros.ros.bag_bridge import without_subscriber
    assert without_subscriber([('/a', 1), ('/clock', 0), ('/b', 0)]) == ['/b', '/clock']
    # two bag topics remapped to one name: awaited while one of their publishers has none
    assert without_subscriber([('/c', 1), ('/c', 0)]) == ['/c']
    assert without_subscriber([('/a', 2), ('/clock', 1)]) == []


def test_poll_until_done_returns_when_nothing_is_pending_and_reports_each_change():
    from cdmp_ros.ros.bag_bridge import poll_until_done
    clock = FakeTime()
    answers = iter([['/clock', '/a'], ['/a', '/clock'], ['/clock'], []])
    changes = []
    left = poll_until_done(lambda: next(answers), 10.0, clock, changes.append, period=0.01,
                           clock=clock)
    assert left == []
    assert changes == [['/clock'], []]  # the first list is no change; sorted lists compared
    assert clock.waits == [0.01] * 3


def test_poll_until_done_gives_up_at_the_deadline_with_what_is_pending():
    from cdmp_ros.ros.bag_bridge import poll_until_done
    clock = FakeTime()
    calls = []
    left = poll_until_done(lambda: calls.append(clock.now) or {'/clock', '/a'}, 0.05, clock,
                           period=0.02, clock=clock)
    assert left == ['/a', '/clock']
    assert clock.waits == pytest.approx([0.02, 0.02, 0.01])  # never past the deadline
    assert clock.now == pytest.approx(0.05) and len(calls) == 4


def test_poll_until_done_checks_once_with_timeout_0_and_stops_on_request():
    from cdmp_ros.ros.bag_bridge import poll_until_done
    clock = FakeTime()
    assert poll_until_done(lambda: ['/a'], 0.0, clock, clock=clock) == ['/a']
    assert clock.waits == []
    stopping = FakeTime(stop_at=0.03)
    assert poll_until_done(lambda: ['/a'], 10.0, stopping, period=0.01,
                           clock=stopping) == ['/a']
    assert stopping.now == pytest.approx(0.03)


def test_player_state_names_the_topics_without_subscriber_or_acknowledgement():
    from cdmp_ros.ros.bag_bridge import player_state
    assert player_state([], None, False) == (True, 'playing')
    assert player_state([], [], True) == (True, 'finished')
    assert player_state(['/a', '/clock'], None, False) == (
        False, 'playing; played without subscriber on /a, /clock')
    assert player_state(['/clock'], ['/a'], True) == (
        False, 'finished; played without subscriber on /clock; not acknowledged on /a')


# -- real player processes ---------------------------------------------------------------------

@pytest.mark.ros
def test_waits_for_a_late_clock_subscriber_then_plays_from_the_first_message(tmp_path, peer):
    """The subscriptions are created only once the player waits; /a first: the player then
    still waits for /clock (it publishes nothing), and once /clock has its subscriber both
    receive the whole bag, /clock from the first message's bag time on."""
    from rosgraph_msgs.msg import Clock
    from std_msgs.msg import String
    bag = str(tmp_path / 'late')
    bag_times = _bag(bag, n=20)
    log = str(tmp_path / 'play.log')
    play = start_node('player', {'bag': bag, 'clock': True, 'rate': 4.0,
                                 'wait_subscribers': WAIT_S}, log_path=log)
    try:
        assert wait_for(lambda: _logged(log, f'waiting up to {WAIT_S:g} s for a subscriber '
                                        'on /a, /clock'), WAIT_S), open(log).read()
        got_a = peer.collect(String, '/a')
        assert wait_for(lambda: _logged(log, 'still waiting for a subscriber on /clock'),
                        WAIT_S), open(log).read()
        assert got_a == [] and play.poll() is None  # nothing played without /clock's reader
        got_clock = peer.collect(Clock, '/clock', raw=False)
        assert play.wait(timeout=120) == 0, open(log).read()
        assert wait_for(lambda: len(got_a) >= 20 and len(got_clock) >= 20, WAIT_S), (
            len(got_a), len(got_clock), open(log).read())
    finally:
        stop_process(play, signal.SIGKILL)
    text = open(log).read()
    assert _logged(log, 'every topic has a subscriber'), text
    assert 'no subscriber' not in text, text
    assert [decode_string(m) for _, m in got_a] == [f'/a:{i:03d}' for i in range(20)]
    assert [c.clock.sec * 10 ** 9 + c.clock.nanosec for _, c in got_clock] == bag_times


@pytest.mark.ros
def test_a_reliable_subscriber_has_every_message_when_the_player_exits(tmp_path, peer):
    """Large messages (1 MB) played as fast as the player can (rate 1000): the player has
    published the last one long before the subscriber has them all (measured: without the
    acknowledgement wait, ``ack_timeout: 0``, it received 0-28 of 80), yet it ends only once
    the reliable subscriber acknowledged everything: the subscriber has the bag's count for
    the topic, in order."""
    from std_msgs.msg import String
    bag = str(tmp_path / 'acked')
    n, pad = 80, 'x' * 1_000_000
    with BagWriter(bag) as w:
        w.add_topic('/a', 'std_msgs/msg/String')
        for i in range(n):
            w.write('/a', encode_string(f'{i:03d}{pad}'), T0_NS + i * 1_000_000)
    expected = [decode_string(m.data)[:3] for m in BagReader(bag).messages(['/a'])]
    assert len(expected) == n
    got = peer.collect(String, '/a')
    log = str(tmp_path / 'play.log')
    play = start_node('player', {'bag': bag, 'rate': 1000.0, 'wait_subscribers': WAIT_S,
                                 'ack_timeout': WAIT_S}, log_path=log)
    try:
        assert play.wait(timeout=120) == 0, open(log).read()
    finally:
        stop_process(play, signal.SIGKILL)
    text = open(log).read()
    assert _logged(log, 'every reliable subscriber acknowledged every message on /a'), text
    # acknowledged = in the subscription's queue: the callbacks may still be draining it
    assert wait_for(lambda: len(got) >= n, WAIT_S), (len(got), text)
    assert [decode_string(m)[:3] for _, m in got] == expected
    assert f'[player] published {n} messages' in text


@pytest.mark.ros
def test_wait_subscribers_0_plays_at_once(tmp_path):
    """``cdmp bag play --wait-subscribers 0`` with nobody listening: no wait, every message
    published, no warning."""
    bag = str(tmp_path / 'at_once')
    _bag(bag, n=20, dt_ns=1_000_000)
    cmd = [sys.executable, '-m', 'cdmp_ros.cli.main', 'bag', 'play', bag, '--clock',
           '--wait-subscribers', '0']
    done = subprocess.run(cmd, env=ros_env(), capture_output=True, text=True, timeout=120)
    out = done.stdout + done.stderr
    assert done.returncode == 0, out
    assert '[player] published 20 messages' in out, out
    assert 'waiting up to' not in out and 'no subscriber' not in out, out


@pytest.mark.ros
def test_the_timeout_names_the_topics_without_subscriber_and_plays_anyway(tmp_path):
    """Nobody subscribes to /a or /clock: after ``wait_subscribers`` the player says which
    topics had no subscriber, in the log and on diagnostics (WARN), and plays anyway."""
    h = NodeHarness('player_wait_diag', spin_period=0.02)  # /diagnostics
    bag = str(tmp_path / 'nobody')
    _bag(bag, n=20)
    log = str(tmp_path / 'play.log')
    play = start_node('player', {'bag': bag, 'clock': True, 'loop': True,
                                 'wait_subscribers': 0.5}, log_path=log)
    try:
        assert wait_for(lambda: _logged(log, 'no subscriber on /a, /clock after 0.5 s; '
                                        'playing anyway'), WAIT_S), open(log).read()
        assert h.wait_diag('played without subscriber on /a, /clock', since=0.0,
                           name='player: state'), h.diag_messages[-5:]
        with h.lock:
            state = [d for d in h.diag_messages if d.name == 'player: state'
                     and 'without subscriber' in d.message][-1]
        assert state.level == 1, state  # WARN
        assert state.values['no_subscriber'] == '/a, /clock', state
        assert state.values['waited_for'] == '/a, /clock', state
        assert wait_for(lambda: int(h.last_state()[1].get('published', 0)) > 0, WAIT_S)
        assert_clean_stop(stop_process(play), open(log).read(), 'player')
    finally:
        stop_process(play, signal.SIGKILL)
        h.close()


@pytest.mark.ros
def test_the_old_wait_parameters_are_refused_with_a_warning(tmp_path):
    """``wait_for_subscribers`` / ``wait_timeout`` (before issue 31) are ignored, not silently:
    the warning names the replacement."""
    bag = str(tmp_path / 'old')
    _bag(bag, n=3, dt_ns=1_000_000)
    log = str(tmp_path / 'play.log')
    play = start_node('player', {'bag': bag, 'wait_for_subscribers': 1, 'wait_timeout': 5.0,
                                 'wait_subscribers': 0.0}, log_path=log)
    try:
        assert play.wait(timeout=120) == 0, open(log).read()
    finally:
        stop_process(play, signal.SIGKILL)
    text = open(log).read()
    assert 'parameter wait_for_subscribers is no longer used (ignored): the player now takes ' \
        'wait_subscribers (seconds)' in text, text
    assert 'parameter wait_timeout is no longer used (ignored): the player now takes ' \
        'wait_subscribers and ack_timeout' in text, text
