"""Deterministic restart of the streamer (issue 13 item 5), as real processes over DDS.

A publisher (the test process) latches ``primitive`` P2 and an ``adapted_primitive`` that
adapts an older primitive P1; a streamer started afterwards receives both (in whatever order
DDS delivers them) and must stream P2, never the adaptation of P1. Then an adaptation of P2
is latched: the running streamer switches it in (its trigger stamp gives one
``adaptation_latency`` sample and the stamp of the first reference computed from it, which the
listener must have received), and a restarted streamer receiving P2 and that adaptation
streams the adaptation. Each primitive reaches a different goal, so the references show which
one is streamed. Every wait is on a condition with a generous timeout.
"""
import time

import numpy as np
import pytest

from conftest import module_domain
from cdmp_ros.core.primitive_io import dumps_primitive
from cdmp_ros.core.streaming.selection import Provenance, primitive_id
from node_harness import assert_clean_stop, stop_process
from streamer_harness import Harness, Q_GOAL, Q_START, reach_cdmp, start_streamer

pytestmark = pytest.mark.ros
DOMAIN = module_domain(35)
STARTUP = 60.0  # s; interpreter + rclpy start-up on a loaded 2-core machine
TIMEOUT = 30.0  # s; bounds a failing wait only
GOAL_P1_ADAPTED = np.array([-0.4, -0.1, -0.15, -1.5, -0.1, 1.0, -0.15])
GOAL_P2_ADAPTED = np.array([0.5, -0.3, 0.4, -1.8, 0.3, 1.2, 1.0])


def adapted_text(goal, source_text, generation, stamp_ns=0):
    prim = reach_cdmp(Q_START, goal, 1.5)
    prim.metadata = {'adapter': Provenance(primitive_id(source_text), generation, 'obstacles',
                                           stamp_ns).as_dict()}
    return dumps_primitive(prim)


def converges_to(h, proc, goal, since=0):
    """The references received after index ``since`` reach ``goal`` (and the node lives)."""
    def reached():
        refs = h.refs_since(max(since, h.n_refs() - 1))
        return proc.poll() is not None or (refs and np.abs(refs[-1][2] - goal).max() < 0.02)
    return h.wait(reached, STARTUP) and proc.poll() is None


def state_value(h, key, since):
    """Values of ``key`` on the streamer's state diagnostics received after ``since``."""
    with h.lock:
        return [d.values.get(key) for d in h.diag_messages
                if d.t >= since and d.name.endswith(': state') and key in d.values]


def test_restarted_streamer_streams_the_newest_adaptation_of_the_current_primitive(tmp_path):
    from std_msgs.msg import String
    p1 = dumps_primitive(reach_cdmp(Q_START, GOAL_P1_ADAPTED, 1.4))
    p2 = dumps_primitive(reach_cdmp(Q_START, Q_GOAL, 1.5))
    h = Harness(DOMAIN)
    procs = []
    try:
        # latched before the streamer exists: P2, and an adaptation of the older P1
        h.publish('primitive', String(data=p2))
        h.publish('adapted_primitive', String(data=adapted_text(GOAL_P1_ADAPTED, p1, 10)))
        log = tmp_path / 'streamer1.log'
        proc = start_streamer(DOMAIN, ['diagnostics_period:=0.2'], log_path=str(log),
                              params_file='config/streamer.yaml')
        procs.append((proc, log))
        t_start = time.monotonic()
        assert converges_to(h, proc, Q_GOAL), log.read_text()
        # P2 is streamed; the adaptation of P1 was never switched in
        assert h.wait(lambda: 'cdmp from primitive' in state_value(h, 'primitive', t_start),
                      TIMEOUT), log.read_text()
        assert all(v in ('none', None) for v in state_value(h, 'adapted_generation', t_start))
        assert not any('adapted_primitive' in v for v in state_value(h, 'primitive', t_start))
        assert 'switched in' not in ''.join(
            line for line in log.read_text().splitlines() if 'adapted_primitive' in line)

        # an adaptation of P2 (trigger stamped now) is switched in and followed
        n0 = h.n_refs()
        stamp = h.node.get_clock().now().nanoseconds
        adapted_p2 = adapted_text(GOAL_P2_ADAPTED, p2, 20, stamp)
        h.publish('adapted_primitive', String(data=adapted_p2))
        assert converges_to(h, proc, GOAL_P2_ADAPTED), log.read_text()
        t1 = time.monotonic()
        assert h.wait(lambda: '20' in state_value(h, 'adapted_generation', t1), TIMEOUT)
        kv = h.last_state()[1]
        assert kv['adaptation_latency_n'] == '1' and float(kv['adaptation_latency_ms_last']) > 0
        first = int(kv['adapted_reference_stamp_ns'])
        assert int(kv['adapted_trigger_stamp_ns']) == stamp
        # a reference the streamer published: on the 2 ms stamp grid (500 Hz, streamer.yaml)
        # of the stream this listener received, inside it (a keep-last-10 listener on a loaded
        # machine may miss that very message, so its presence is not required)
        stamps = [r[1] for r in h.refs_since(n0)]
        assert stamps[0] <= first <= stamps[-1], (first, stamps[0], stamps[-1])
        assert any((first - s) % 2_000_000 == 0 for s in stamps), first
        # a second adaptation answering the same obstacle message (the adapter's refinement of
        # a warm solve): switched in, not timed again
        h.publish('adapted_primitive', String(data=adapted_text(GOAL_P2_ADAPTED, p2, 21, stamp)))
        t1 = time.monotonic()
        assert h.wait(lambda: '21' in state_value(h, 'adapted_generation', t1), TIMEOUT)
        n1 = h.n_refs()        # references computed from it, then a report after them
        assert h.wait(lambda: h.n_refs() > n1 + 5, TIMEOUT)
        t2 = time.monotonic()
        assert h.wait(lambda: state_value(h, 'adaptation_latency_n', t2), TIMEOUT)
        kv = h.last_state()[1]
        assert kv['adapted_generation'] == '21'
        assert kv['adaptation_latency_n'] == '1' and int(kv['adapted_reference_stamp_ns']) == first
        assert_clean_stop(stop_process(proc), log.read_text(), 'streamer')

        # a restarted streamer gets P2 and its newest adaptation (latched): streams it
        h.robot_q = Q_START.copy()
        n2 = h.n_refs()
        log2 = tmp_path / 'streamer2.log'
        proc2 = start_streamer(DOMAIN, ['diagnostics_period:=0.2'], log_path=str(log2),
                               params_file='config/streamer.yaml')
        procs.append((proc2, log2))
        t2 = time.monotonic()
        assert h.wait(lambda: '21' in state_value(h, 'adapted_generation', t2)
                      or proc2.poll() is not None, STARTUP), log2.read_text()
        assert converges_to(h, proc2, GOAL_P2_ADAPTED, n2 + 1), log2.read_text()
        assert 'cdmp from adapted_primitive' in state_value(h, 'primitive', t2)
        # its trigger happened before this streamer started: not timed as a latency
        assert h.last_state()[1]['adaptation_latency_n'] == '0'
    finally:
        h.close()
        codes = [(stop_process(p), log) for p, log in procs]
    assert codes
    for code, log in codes:
        assert_clean_stop(code, log.read_text(), 'streamer')
    assert not h.violations, h.violations[:5]
