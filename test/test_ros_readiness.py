"""Readiness (issue 31 item 4): every node says when it is ready, on its log and on
``/diagnostics``, and ``cdmp bringup --wait-ready`` waits for the whole graph or stops it."""
import os
import signal
import subprocess
import sys

import pytest
import yaml

from bag_ros_util import Lines
from conftest import module_domain, ros_env, wait_for
from node_harness import WAIT_S, assert_bringup_stopped
from cdmp_ros.cli.cmd_bringup import NOT_READY_EXIT_CODE
from cdmp_ros.core.readiness import READY_LINE

pytestmark = pytest.mark.ros


def _bringup(tmp_path, nodes, *args):
    p = tmp_path / 'graph.yaml'
    p.write_text(yaml.safe_dump({'stop_timeout': WAIT_S, 'nodes': nodes}))
    proc = subprocess.Popen([sys.executable, '-m', 'cdmp_ros.cli.main', 'bringup', str(p),
                             *args], env=ros_env(), stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, start_new_session=True)
    return proc, Lines(proc.stdout)


def _stop(proc, out):
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGINT)
    try:
        proc.wait(timeout=2 * WAIT_S)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    return out.text()


def test_a_full_graph_becomes_ready_and_bringup_says_so(tmp_path):
    """sim, streamer, adapter and learner from config/*.yaml: each logs its ready line once
    its peers are matched (and, streamer and adapter, the learner's primitive arrived), then
    bringup prints that the graph is ready and keeps it running."""
    nodes = [{'name': n, 'executable': n, 'params_file': f'{n}.yaml'}
             for n in ('sim', 'learner', 'adapter', 'streamer')]
    proc, out = _bringup(tmp_path, nodes, '--wait-ready', str(6 * WAIT_S))
    try:
        assert wait_for(lambda: out.seen('bringup: graph ready') or proc.poll() is not None,
                        8 * WAIT_S), out.text(0)
        assert proc.poll() is None, out.text(0)  # ready, and the graph runs on
    finally:
        text = _stop(proc, out)
    assert_bringup_stopped(proc.returncode, text)
    for name in ('sim', 'learner', 'adapter', 'streamer'):
        lines = [x for x in text.splitlines() if x.startswith(f'[{name}') and READY_LINE.search(x)]
        assert len(lines) == 1, (name, text)
    ready_line = next(x for x in text.splitlines() if 'bringup: graph ready' in x)
    assert all(f'{n} ' in ready_line for n in ('sim', 'learner', 'adapter', 'streamer'))


def test_a_graph_that_cannot_become_ready_is_stopped_with_the_nodes_named(tmp_path):
    """A streamer alone never receives a primitive nor finds a consumer: --wait-ready gives
    up, names it, stops the graph cleanly and exits with its own code."""
    nodes = [{'name': 'streamer', 'executable': 'streamer', 'params_file': 'streamer.yaml'}]
    proc, out = _bringup(tmp_path, nodes, '--wait-ready', '3')
    try:
        proc.wait(timeout=4 * WAIT_S)
    finally:
        text = _stop(proc, out)
    assert_bringup_stopped(proc.returncode, text, NOT_READY_EXIT_CODE)
    assert 'bringup: not ready within 3 s: streamer' in text
    assert READY_LINE.search(text) is None


def test_the_streamer_reports_what_it_waits_for_on_diagnostics():
    """The same verdict on /diagnostics: ready false with the missing conditions named, then
    ready true once a primitive arrived and the references have a consumer (the test)."""
    from std_msgs.msg import String
    from cdmp_ros.core.primitive_io import dumps_primitive
    from streamer_harness import Harness, reach_cdmp, start_streamer

    domain = module_domain(41)
    proc = start_streamer(domain, ['diagnostics_period:=0.2'])
    h = Harness(domain)
    try:
        assert h.wait(lambda: h.last_state()[1].get('ready') == 'false'), h.last_state()
        waiting = h.last_state()[1]['waiting_for']
        assert 'primitive (a primitive received and in force)' in waiting, waiting
        assert h.last_state()[1]['ready_after_s'] == 'never'
        h.publish('primitive', String(data=dumps_primitive(reach_cdmp(duration=1.5))))
        assert h.wait(lambda: h.last_state()[1].get('ready') == 'true'), h.last_state()
        values = h.last_state()[1]
        assert values['waiting_for'] == 'nothing'
        assert float(values['ready_after_s']) > 0.0
    finally:
        h.close()
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=WAIT_S)
