"""The streamer's tick schedule (cdmp_ros.core.streaming.schedule), with a fake clock: slots on
the grid, late ticks and their catch-up, the catch-up limit, early (woken) ticks, stamps exactly
on the grid, the clock offset and its re-anchoring. No process, no ROS."""
import pytest

from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.streaming.schedule import ClockOffset, TickSchedule, clock_offset_ns

RATE = 1000.0
T0 = 100.0
OFFSET_NS = 1_700_000_000_000_000_000 - round(T0 * 1e9)  # ROS time = steady + offset


def at(slot: float) -> float:
    """The fake steady clock, ``slot`` periods after t0."""
    return T0 + slot / RATE


def make() -> TickSchedule:
    return TickSchedule(RATE, T0, OFFSET_NS)


def test_on_time_ticks_integrate_one_slot_each_stamped_on_the_grid():
    s = make()
    assert s.deadline() == pytest.approx(at(1))
    stamps = []
    for j in range(1, 6):
        late = s.woke(at(j + 0.2), woken=False)
        assert late == pytest.approx(0.2 / RATE)
        first, steps, skipped = s.advance(at(j + 0.2), max_catch_up=5)
        assert (first, steps, skipped) == (j, 1, 0)
        stamps.append(s.stamp_ns(first))
        assert s.deadline() == pytest.approx(at(j + 1))
    assert stamps == [1_700_000_000_000_000_000 + j * 1_000_000 for j in range(1, 6)]
    assert s.counts == {'missed_ticks': 0, 'late_ticks': 0, 'early_ticks': 0}


def test_a_late_tick_catches_up_every_slot_it_missed():
    s = make()
    s.advance(at(1.5), max_catch_up=5)
    late = s.woke(at(4.5), woken=False)       # the deadline was slot 2: 2.5 periods late
    assert late == pytest.approx(2.5 / RATE)
    assert s.counts['late_ticks'] == 1
    assert s.advance(at(4.5), max_catch_up=5) == (2, 3, 0)   # slots 2, 3, 4, each once
    assert s.k == 4 and s.counts['missed_ticks'] == 0
    s.woke(at(5.9), woken=False)              # 0.9 periods late: on time
    assert s.counts['late_ticks'] == 1
    assert s.advance(at(5.9), max_catch_up=5) == (5, 1, 0)


def test_the_catch_up_limit_skips_the_oldest_slots_and_counts_them_missed():
    s = make()
    s.advance(at(1.5), max_catch_up=3)
    first, steps, skipped = s.advance(at(11.5), max_catch_up=3)  # slots 2..11 began: 10
    assert (first, steps, skipped) == (9, 3, 7)         # the newest 3: 9, 10, 11; 2..8 skipped
    assert s.counts['missed_ticks'] == 7
    assert s.stamp_ns(first + steps - 1) == s.stamp_ns(0) + 11 * 1_000_000
    assert s.advance(at(12.5), max_catch_up=3) == (12, 1, 0)   # and on from there


def test_an_early_wake_up_publishes_the_next_slot_once_then_waits_for_the_schedule():
    s = make()
    s.advance(at(1.1), max_catch_up=5)       # slot 1
    assert not s.is_ahead(at(1.4))
    late = s.woke(at(1.4), woken=True)        # an obstacle message, before slot 2's deadline
    assert late == pytest.approx(-0.6 / RATE)
    assert s.counts['early_ticks'] == 1
    assert s.advance(at(1.4), max_catch_up=5) == (2, 1, 0)   # slot 2 now, with its own stamp
    assert s.is_ahead(at(1.6))                # a second wake-up in slot 1 must wait
    assert s.deadline() == pytest.approx(at(3))
    assert not s.is_ahead(at(2.1))
    s.woke(at(3.05), woken=False)
    assert s.advance(at(3.05), max_catch_up=5) == (3, 1, 0)  # slot 2 is not published twice
    woken_late = s.woke(at(4.2), woken=True)  # woken after the deadline: not early
    assert woken_late > 0 and s.counts['early_ticks'] == 1
    assert s.counts['late_ticks'] == 0


def test_stamps_stay_exactly_on_the_grid_at_a_rate_without_an_integer_period():
    s = TickSchedule(300.0, 0.0, 0)
    assert s.stamp_ns(3) == 10_000_000
    assert s.stamp_ns(300 * 3600 * 24) == 24 * 3600 * 1_000_000_000  # a day: no drift
    assert s.stamp_ns(1) == 3_333_333 and s.stamp_ns(2) == 6_666_667


def test_a_clock_step_re_anchors_the_stamps_a_small_drift_does_not():
    s = make()
    base = s.stamp_ns(10)
    assert not s.anchor(ClockOffset(OFFSET_NS + 500_000, 100))   # 0.5 ms: the grid stays
    assert s.stamp_ns(10) == base
    assert s.anchor(ClockOffset(OFFSET_NS + 2_000_000, 100))     # 2 ms step: re-anchored
    assert s.stamp_ns(10) == base + 2_000_000
    assert s.anchor(ClockOffset(OFFSET_NS - 3_600_000_000_000, 100))  # a step back of an hour
    assert s.stamp_ns(10) == base - 3_600_000_000_000


def test_a_reading_preempted_under_load_does_not_move_the_grid():
    """All readings of a measurement bracketed a 1.7 ms preemption: the offset is off by
    1.3 ms but its uncertainty says so; the grid stays (it moved stamps off the grid, and
    backwards, in the CI soak)."""
    s = make()
    base = s.stamp_ns(10)
    assert not s.anchor(ClockOffset(OFFSET_NS + 1_334_879, 850_000))
    assert s.stamp_ns(10) == base
    assert s.anchor(ClockOffset(OFFSET_NS + 1_334_879, 300_000))   # a tight one: a real step
    assert s.stamp_ns(10) == base + 1_334_879
    # the grid's own measurement was loose: a tight one within its bound does not move it
    s = TickSchedule(RATE, T0, OFFSET_NS + 1_269_194, 1_300_000)
    base = s.stamp_ns(10)
    assert not s.anchor(ClockOffset(OFFSET_NS, 20))
    assert s.stamp_ns(10) == base


def test_clock_offset_takes_the_tightest_reading_and_bounds_its_error():
    steady = iter([0, 100, 1000, 1010, 2000, 2500])   # the pair 1000..1010 is the tightest
    other = iter([5_000_050, 5_001_005, 5_002_100])
    off = clock_offset_ns(lambda: next(other), lambda: next(steady), readings=3)
    assert off == (5_001_005 - 1005, 5)
    # every bracket preempted: the bound is half the tightest
    steady = iter([0, 2_000_000, 3_000_000, 4_600_000])
    other = iter([1_900_000 + 7, 4_500_000 + 7])
    off = clock_offset_ns(lambda: next(other), lambda: next(steady), readings=2)
    assert off.uncertainty_ns == 800_000
    assert abs(off.offset_ns - 7) <= off.uncertainty_ns


def test_a_non_positive_rate_is_refused():
    with pytest.raises(ValidationError, match='rate'):
        TickSchedule(0.0, T0)
