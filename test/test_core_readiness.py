"""Readiness of a node (cdmp_ros.core.readiness): conditions, transitions, diagnostics values."""
import math

import pytest
from hypothesis import given, strategies as st

from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.readiness import Readiness

CONDITIONS = {'joint_states': 'a publisher on joint_states',
              'primitive': 'a primitive received'}


def test_not_ready_until_every_condition_holds():
    r = Readiness(CONDITIONS, started=10.0)
    assert not r.ready and math.isnan(r.ready_after)
    assert r.values() == {'ready': 'false', 'ready_after_s': 'never',
                          'waiting_for': 'joint_states (a publisher on joint_states), '
                                         'primitive (a primitive received)'}
    assert r.update(10.5, joint_states=True) is None  # still waiting: no transition
    assert r.missing() == ('primitive',)
    assert r.update(12.25, primitive=True) == 'ready 2.25 s after start'
    assert r.ready and r.ready_after == 2.25
    assert r.values() == {'ready': 'true', 'waiting_for': 'nothing', 'ready_after_s': '2.250'}
    assert r.update(13.0, primitive=True, joint_states=True) is None  # no change, no message


def test_losing_a_condition_is_one_transition_and_the_first_time_is_kept():
    r = Readiness(CONDITIONS, started=0.0)
    r.update(1.0, joint_states=True, primitive=True)
    msg = r.update(2.0, joint_states=False)
    assert msg == 'not ready: waiting for joint_states (a publisher on joint_states)'
    assert not r.ready and r.values()['ready'] == 'false'
    assert r.update(3.0, joint_states=False) is None
    assert r.update(4.0, joint_states=True) == 'ready again'
    assert r.ready_after == 1.0  # the first time, not the last


def test_bad_conditions_and_updates_are_named():
    with pytest.raises(ValidationError, match='at least one condition'):
        Readiness({}, 0.0)
    with pytest.raises(ValidationError, match='finite'):
        Readiness(CONDITIONS, math.nan)
    with pytest.raises(ValidationError, match='description'):
        Readiness({'x': 3}, 0.0)
    r = Readiness(CONDITIONS, 0.0)
    with pytest.raises(ValidationError, match="unknown condition 'goal'.*joint_states"):
        r.update(1.0, goal=True)


@given(st.lists(st.tuples(st.sampled_from(sorted(CONDITIONS)), st.booleans()), max_size=40))
def test_the_verdict_is_the_conjunction_and_messages_mark_every_change(updates):
    """Against a direct recomputation: ready iff every condition's last state is true; a
    message exactly when the verdict flips."""
    r = Readiness(CONDITIONS, 0.0)
    state = {k: False for k in CONDITIONS}
    verdict = False
    for i, (name, ok) in enumerate(updates):
        state[name] = ok
        msg = r.update(float(i), **{name: ok})
        expected = all(state.values())
        assert r.ready == expected
        assert (msg is not None) == (expected != verdict)
        verdict = expected
        assert set(r.missing()) == {k for k, v in state.items() if not v}


def test_the_ready_line_is_found_in_a_log_line():
    from cdmp_ros.core.readiness import READY_LINE
    r = Readiness(CONDITIONS, 0.0)
    msg = r.update(0.84, joint_states=True, primitive=True)
    line = f'[INFO] [1764331234.123456789] [arm.streamer]: {msg}\n'
    m = READY_LINE.search(line)
    assert m is not None and float(m.group(1)) == 0.84
    assert READY_LINE.search('[INFO] [1.0] [streamer]: not ready: waiting for primitive') is None
    assert READY_LINE.search('ready again') is None
