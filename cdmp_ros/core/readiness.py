"""When a node is ready: the conditions it waits for, their state, and the transitions.

A node of the graph is *ready* when every one of its conditions holds at once: its essential
subscriptions and publications are matched by a peer, and (streamer, adapter) a primitive was
received. :class:`Readiness` keeps the conditions' states, says which are still missing, when the
node first became ready (seconds after it started) and whether the last update changed the
verdict, so that the node logs one line per transition and reports the same on
``/diagnostics`` (``ready``, ``waiting_for``, ``ready_after_s``). It holds no ROS object: the
node measures the conditions (publisher and subscription counts, a primitive in force) and
passes them to :meth:`Readiness.update`.
"""
import math
import re
from typing import Dict, Mapping, Optional, Tuple

from cdmp_ros.core.errors import ValidationError

#: The first "ready" message of a node (:meth:`Readiness.update`), as found in its log output
#: whatever the log format around it: group 1 is the seconds after start.
READY_LINE = re.compile(r'\bready (\d+\.\d+) s after start\b')


class Readiness:
    """The readiness of one node.

    Parameters
    ----------
    conditions : mapping of str to str
        Condition name -> what it means, for the messages (``{'joint_states': 'a publisher on
        joint_states'}``). At least one; names are unique by construction.
    started : float
        The node's start time [s] on the clock later passed to :meth:`update`.

    Attributes
    ----------
    ready : bool
        Every condition held at the last :meth:`update`.
    ready_after : float
        Seconds from ``started`` to the first update at which every condition held (``nan``
        before).
    """

    def __init__(self, conditions: Mapping[str, str], started: float):
        if not conditions:
            raise ValidationError('readiness: expected at least one condition')
        for name, text in conditions.items():
            if not isinstance(name, str) or not name or not isinstance(text, str):
                raise ValidationError(f'readiness: expected condition name -> description '
                                      f'strings, got {name!r}: {text!r}')
        if not math.isfinite(started):
            raise ValidationError(f'readiness: started: expected a finite time, got {started}')
        self.conditions: Dict[str, str] = dict(conditions)
        self.started = float(started)
        self._state: Dict[str, bool] = {name: False for name in self.conditions}
        self.ready = False
        self.ready_after = math.nan

    def update(self, now: float, **states: bool) -> Optional[str]:
        """Set the states of some conditions at ``now``; returns a one-line message when the
        verdict changed (ready, or not ready any more and why), else None.

        Raises
        ------
        ValidationError
            Naming a condition this node does not have.
        """
        for name, ok in states.items():
            if name not in self._state:
                raise ValidationError(f'readiness: unknown condition {name!r}; expected one of '
                                      f'{sorted(self._state)}')
            self._state[name] = bool(ok)
        ready = all(self._state.values())
        if ready == self.ready:
            return None
        self.ready = ready
        if ready:
            first = math.isnan(self.ready_after)
            if first:
                self.ready_after = max(0.0, now - self.started)
            return (f'ready {self.ready_after:.2f} s after start' if first
                    else 'ready again')
        return 'not ready: waiting for ' + self._missing_text()

    def missing(self) -> Tuple[str, ...]:
        """The conditions that did not hold at the last update, in declaration order."""
        return tuple(name for name, ok in self._state.items() if not ok)

    def _missing_text(self) -> str:
        return ', '.join(f'{name} ({self.conditions[name]})' for name in self.missing())

    def values(self) -> Dict[str, str]:
        """The diagnostics key/values: ``ready`` (true|false), ``waiting_for`` (the missing
        conditions with their meaning, or ``nothing``) and ``ready_after_s`` (``never`` before
        the first time)."""
        return {'ready': 'true' if self.ready else 'false',
                'waiting_for': self._missing_text() if self.missing() else 'nothing',
                'ready_after_s': ('never' if math.isnan(self.ready_after)
                                  else f'{self.ready_after:.3f}')}
