"""The streamer's tick schedule: slots on a fixed grid, deadlines, catch-up and stamps (no ROS).

Slot ``j`` begins at ``t0 + j * dt`` on the steady clock (``time.monotonic``); the reference
integrated for it is stamped ``stamp0 + j * dt`` on the ROS clock, where ``stamp0`` is ``t0``
read on the ROS clock (steady clock + a measured offset, :func:`clock_offset_ns`). So the
stamps are exactly on the grid whatever the jitter of the tick, and each slot is integrated
and published exactly once:

- the tick thread sleeps to :meth:`TickSchedule.deadline` (the beginning of the slot after
  the last one integrated) and reports the wake-up (:meth:`TickSchedule.woke`): a deadline
  wake-up more than one period late is a *late tick*; a wake-up before the deadline (an
  obstacle message woke the thread) is an *early tick*, which publishes the next slot at once
  with its own stamp, at most one period early (:meth:`TickSchedule.is_ahead` says when the
  thread is already one slot ahead and must wait);
- :meth:`TickSchedule.advance` integrates every slot that began since the last tick (a late
  tick catches up), at most ``max_catch_up`` of them: the oldest ones beyond that are skipped
  (not published) and counted as *missed ticks*; it returns how many, so that the output
  stage can still run through them (:meth:`ReferenceStreamer.advance`, ``skipped``) and the
  published positions stay consistent with the stamps across the gap;
- :meth:`TickSchedule.anchor` follows a step of the ROS clock (an NTP step, sim time) by
  re-anchoring ``stamp0`` when the grid is off by more than a tolerance plus the uncertainty of
  the new offset measurement; otherwise the grid stays exact (a reading preempted for a
  millisecond under load must not move the stamps off the grid, or backwards).

The schedule takes the time as an argument (no clock of its own), so a test drives it with any
fake clock.
"""
import time
from typing import Callable, Dict, NamedTuple, Tuple

from cdmp_ros.core.errors import ValidationError

#: Re-anchor the stamp grid when the ROS clock moved by more than this [ns] against it.
ANCHOR_TOLERANCE_NS = 1_000_000


class ClockOffset(NamedTuple):
    """A measured offset of a clock from the steady clock."""
    offset_ns: int       #: clock - steady clock [ns]
    uncertainty_ns: int  #: bound of the measurement error [ns] (half the tightest bracket)


def clock_offset_ns(now_ns: Callable[[], int],
                    steady_ns: Callable[[], int] = time.monotonic_ns,
                    readings: int = 5) -> ClockOffset:
    """Offset of a clock from the steady clock [ns], from the tightest of ``readings``
    back-to-back readings, with the bound of its error.

    Each reading brackets ``now_ns()`` between two steady readings ``a <= b``; the offset is
    ``now - (a + b) / 2``, off by at most ``(b - a) / 2`` (the reading happened inside the
    bracket). Under load a bracket can span a preemption of milliseconds: the bound says so.

    Parameters
    ----------
    now_ns : callable
        The clock whose offset is measured (e.g. the ROS clock), in ns.
    steady_ns : callable
        The steady clock, in ns.
    readings : int
        Brackets taken (at least 1).

    Returns
    -------
    ClockOffset
        ``(offset_ns, uncertainty_ns)``.
    """
    best = None
    for _ in range(max(1, readings)):
        a = steady_ns()
        t = now_ns()
        b = steady_ns()
        if best is None or b - a < best[0]:
            best = (b - a, t - (a + b) // 2)
    return ClockOffset(best[1], (best[0] + 1) // 2)


class TickSchedule:
    """Deadlines, catch-up and stamps of a fixed-rate tick (module docstring).

    Parameters
    ----------
    rate : float
        Ticks per second [Hz].
    t0 : float
        Beginning of slot 0 on the steady clock [s].
    clock_offset_ns : int
        ROS clock - steady clock [ns] (:func:`clock_offset_ns`, its ``offset_ns``).
    uncertainty_ns : int
        The bound of that measurement's error [ns] (its ``uncertainty_ns``).

    Attributes
    ----------
    dt : float
        Period [s].
    k : int
        The last slot integrated (0 before the first tick).
    counts : dict
        ``missed_ticks`` (slots skipped by the catch-up limit), ``late_ticks`` (deadline
        wake-ups more than one period late), ``early_ticks`` (wake-ups before the deadline).
    """

    def __init__(self, rate: float, t0: float, clock_offset_ns: int = 0,
                 uncertainty_ns: int = 0):
        if not rate > 0.0:
            raise ValidationError(f'rate: expected a positive number, got {rate!r}')
        self.dt = 1.0 / rate
        self._dt_ns = 1e9 / rate
        self.t0 = t0
        self.k = 0
        self.stamp0_ns = clock_offset_ns + round(t0 * 1e9)
        self._stamp0_uncertainty_ns = uncertainty_ns
        self.counts: Dict[str, int] = {'missed_ticks': 0, 'late_ticks': 0, 'early_ticks': 0}

    def deadline(self) -> float:
        """Beginning [s, steady clock] of the slot after the last one integrated."""
        return self.t0 + (self.k + 1) * self.dt

    def is_ahead(self, now: float) -> bool:
        """True when the last slot integrated has not begun yet at ``now`` (an early tick
        already published it): the tick must wait for the schedule."""
        return self.k > (now - self.t0) / self.dt

    def woke(self, now: float, woken: bool) -> float:
        """Count a wake-up of the tick thread at ``now``, before it ticks.

        Parameters
        ----------
        now : float
            Steady clock [s].
        woken : bool
            True when the thread was woken before its deadline (an obstacle message), False
            for a deadline wake-up.

        Returns
        -------
        float
            ``now - deadline()`` [s]: the lateness of a deadline wake-up (negative: early).
        """
        late = now - self.deadline()
        if not woken:
            if late > self.dt:  # the slot goes out after the next slot's deadline
                self.counts['late_ticks'] += 1
        elif late < 0.0:  # the next slot goes out now, stamped on the grid
            self.counts['early_ticks'] += 1
        return late

    def advance(self, now: float, max_catch_up: int) -> Tuple[int, int, int]:
        """The slots a tick at ``now`` integrates: every slot begun since the last tick (at
        least the next one), at most ``max_catch_up`` (the older ones are counted as missed).

        Returns
        -------
        first : int
            The first slot to integrate.
        steps : int
            How many consecutive slots to integrate (``first .. first + steps - 1``).
        skipped : int
            How many slots before ``first`` were skipped (``first - skipped .. first - 1``:
            never published).
        """
        k = int((now - self.t0) / self.dt)  # the slot that began most recently
        steps = k - self.k
        skipped = 0
        if steps < 1:  # an early tick, or the same slot again: the next slot
            steps, k = 1, self.k + 1
        if steps > max_catch_up:  # too late: skip the oldest slots
            skipped = steps - max_catch_up
            self.counts['missed_ticks'] += skipped
            steps = max_catch_up
        self.k = k
        return k - steps + 1, steps, skipped

    def stamp_ns(self, slot: int) -> int:
        """The ROS-clock stamp [ns] of ``slot``: exactly on the grid."""
        return self.stamp0_ns + round(slot * self._dt_ns)

    def anchor(self, offset: ClockOffset, tolerance_ns: int = ANCHOR_TOLERANCE_NS) -> bool:
        """Re-anchor the stamps when the ROS clock moved against the grid by more than
        ``tolerance_ns`` plus the uncertainties of the grid's measurement and of ``offset`` (a
        new :func:`clock_offset_ns`); returns True if it did."""
        stamp0 = offset.offset_ns + round(self.t0 * 1e9)
        if abs(stamp0 - self.stamp0_ns) > (tolerance_ns + offset.uncertainty_ns
                                           + self._stamp0_uncertainty_ns):
            self.stamp0_ns = stamp0
            self._stamp0_uncertainty_ns = offset.uncertainty_ns
            return True
        return False
