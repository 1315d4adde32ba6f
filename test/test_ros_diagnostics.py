"""``/diagnostics`` is absolute (design.md, Topics): a node started under a namespace publishes
its statuses on ``/diagnostics``, where diagnostic_aggregator and rqt_robot_monitor read them,
named after its fully qualified name (``arm/streamer: state``), and nothing on
``/arm/diagnostics``."""
import signal

import pytest

from cdmp_ros.core.topics import DIAGNOSTICS_TOPIC
from conftest import module_domain
from node_harness import NodeHarness, WAIT_S, assert_clean_stop, start_node, stop_process

pytestmark = pytest.mark.ros
DOMAIN = module_domain(53)


def test_a_node_in_a_namespace_reports_on_the_absolute_topic(tmp_path):
    h = NodeHarness('diagnostics_test', DOMAIN)  # subscribes DIAGNOSTICS_TOPIC
    log = tmp_path / 'streamer.log'
    proc = start_node('streamer', ['diagnostics_period:=0.2'], DOMAIN,
                      params_file='config/streamer.yaml', remaps=['__ns:=/arm'],
                      log_path=str(log))
    try:
        def names():
            with h.lock:
                return {d.name for d in h.diag_messages}
        assert h.wait(lambda: 'arm/streamer: state' in names() or proc.poll() is not None,
                      WAIT_S), (names(), log.read_text())
        assert 'arm/streamer: state' in names(), (names(), log.read_text())
        assert all(n.startswith('arm/streamer: ') for n in names()), names()
        # the node's publisher is on /diagnostics (its message came: discovery is done)
        assert h.node.count_publishers(DIAGNOSTICS_TOPIC) == 1
        assert h.node.count_publishers('/arm/diagnostics') == 0
        assert_clean_stop(stop_process(proc), log.read_text())
    finally:
        stop_process(proc, signal.SIGKILL)
        h.close()
