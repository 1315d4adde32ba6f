"""Speed and separation monitoring (core/streaming/separation.py): the brake it assumes, checked
by integrating that brake; the admissible factor against its defining equation; the monitor's
cap; the stepper's speed cap against a nominal stepper on the warped grid; and, in the
streamer, a hand that stops before a sphere on its path when nothing else would keep it out."""
import math

import numpy as np
import pytest

from cdmp_ros.core.coupling.potential_fields import RepellerField
from cdmp_ros.core.dmp.dmp import CDMP
from cdmp_ros.core.joint_limits import shipped_limits
from cdmp_ros.core.kinematics import PointOfInterest, panda_chain
from cdmp_ros.core.kinematics.closest import Sphere
from cdmp_ros.core.primitive_io import dumps_primitive
from cdmp_ros.core.run_metrics import kinematic_report
from cdmp_ros.core.streaming.config import StreamerConfig
from cdmp_ros.core.streaming.primitives import prepare_primitive
from cdmp_ros.core.streaming.separation import (MIN_SPEED, SeparationMonitor,
                                                admissible_factor, brake_time)
from cdmp_ros.core.streaming.streamer import ReferenceStreamer, StreamFlags, streamer_coupling
from cdmp_ros.ros.robot_model import default_urdf_path


def test_brake_time_is_the_fastest_time_scaled_brake_within_the_limits():
    """Integrate the brake s(t) = 1 - t / T of joint velocities qd: every joint decelerates
    by |qd_j| / T, at most its A_j (equal for the limiting joint), and a point whose approach
    speed scales with s covers r T / 2 meanwhile."""
    qd = np.array([1.2, -0.4, 2.0, 0.0, -1.5])
    A = np.array([15.0, 7.5, 10.0, 12.5, 15.0])
    T = brake_time(qd, A)
    assert T == pytest.approx(np.max(np.abs(qd) / A))
    decel = np.abs(qd) / T
    assert np.all(decel <= A * (1 + 1e-12)) and np.isclose(np.max(decel / A), 1.0)
    r, n = 0.3, 100_000
    t = np.linspace(0.0, T, n + 1)
    covered = np.trapezoid(r * (1.0 - t / T), t)
    assert covered == pytest.approx(r * T / 2, rel=1e-9)
    assert brake_time([0.0, 0.0], [1.0, 1.0]) == 0.0
    assert brake_time([1.0, 5.0], [2.0, math.inf]) == 0.5   # no limit: not counted


@pytest.mark.parametrize('r, clearance, T, tr', [(0.2, 0.05, 0.1, 0.02), (1.5, 0.01, 0.2, 0.0),
                                                 (0.05, 0.3, 0.0, 0.02), (3.0, 0.2, 0.3, 0.1)])
def test_admissible_factor_solves_its_equation(r, clearance, T, tr):
    f = admissible_factor(r, clearance, T, tr)
    assert f >= 0.0
    # f r tr + f^2 r T / 2 = clearance: the brake from f times the speed ends at the margin
    assert f * r * tr + f * f * r * T / 2 == pytest.approx(clearance, rel=1e-12)
    # and any faster motion would not stop in time
    g = 1.01 * f
    assert g * r * tr + g * g * r * T / 2 > clearance


def test_admissible_factor_edges():
    assert admissible_factor(0.0, 0.1, 0.1, 0.02) == math.inf    # not approaching
    assert admissible_factor(-0.5, 0.1, 0.1, 0.02) == math.inf   # receding
    assert admissible_factor(0.5, 0.0, 0.1, 0.02) == 0.0         # at the margin
    assert admissible_factor(0.5, -0.01, 0.1, 0.02) == 0.0       # inside it
    assert admissible_factor(0.5, 0.1, 0.0, 0.0) == math.inf     # at rest, no reaction time


def test_the_monitor_caps_an_approach_it_could_not_stop_and_lifts_the_cap():
    A = [10.0, 10.0]
    mon = SeparationMonitor(margin=0.02, reaction_time=0.02, max_acceleration=A)
    obstacles = ('one set',)
    qd = [2.0, 0.5]       # T = 0.2 s
    dt = 0.002
    # first evaluation of a set: nothing measured, no cap
    assert mon.update([0.10, 0.5], obstacles, 0, dt, qd, 1.0) == 1.0
    # the first point approaches at 1 m/s: 1 * (0.02 + 0.1) = 0.12 m > 0.098 - 0.02
    cap = mon.update([0.098, 0.5], obstacles, 1, dt, qd, 1.0)
    f = admissible_factor(1.0, 0.098 - 0.02, 0.2, 0.02)
    assert cap == pytest.approx(f) and 0.0 < cap < 1.0 and mon.limiting == 0
    # at the capped speed the brake ends at the margin
    assert cap * 1.0 * 0.02 + cap ** 2 * 1.0 * 0.2 / 2 == pytest.approx(0.078)
    # measured at the capped speed kappa, the same approach per unit speed: the same cap
    again = mon.update([0.098 - cap * 0.002, 0.5], obstacles, 2, dt, [v * cap for v in qd],
                       cap)
    assert again == pytest.approx(admissible_factor(1.0, 0.098 - cap * 0.002 - 0.02, 0.2,
                                                    0.02), rel=1e-3)
    # a new obstacle set keeps the cap until its approach is measured
    other = ('another set',)
    assert mon.update([0.5, 0.5], other, 3, dt, qd, again) == again
    # receding: lifted
    assert mon.update([0.51, 0.5], other, 4, dt, qd, again) == 1.0 and mon.limiting == -1
    # inside the margin and approaching: the least speed
    mon.update([0.015, 0.5], other, 5, dt, qd, 1.0)
    assert mon.update([0.014, 0.5], other, 6, dt, qd, 1.0) == MIN_SPEED
    mon.reset()
    assert mon.cap == 1.0
    # a point without an obstacle (inf) or a non-finite distance is not looked at
    mon.update([math.inf, math.nan], other, 7, dt, qd, 1.0)
    assert mon.update([math.inf, math.nan], other, 8, dt, qd, 1.0) == 1.0


@pytest.fixture(scope='module')
def panda():
    chain = panda_chain(default_urdf_path())
    limits = shipped_limits(chain.joint_names, chain.lower, chain.upper,
                            chain.velocity_limits, 'urdf')
    T = np.linspace(0.0, 2.0, 401)
    s = T / 2
    s = 10 * s ** 3 - 15 * s ** 4 + 6 * s ** 5
    q0 = np.array([0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785])
    q1 = np.array([0.8, 0.2, -0.4, -1.6, 0.3, 1.9, 1.2])
    prim = CDMP(chain.lower, chain.upper, joint_names=chain.joint_names).fit(
        T, q0 + s[:, None] * (q1 - q0))
    mid = chain.forward((0.5 * (q0 + q1))[None], [PointOfInterest('ee')])[0, 0]
    return chain, limits, prim, mid


def test_the_speed_cap_keeps_the_path_and_scales_the_time(panda):
    """A stepper capped at 0.5 from the start runs the nominal stepper of half the step:
    the same positions, on twice the time, at half the velocity."""
    _, _, prim, _ = panda
    dt = 0.002
    capped = prim.stepper(dt)
    capped.set_speed_cap(0.5)
    capped.reset()
    nominal = prim.stepper(dt / 2)
    for _ in range(300):
        out_c, _ = capped.update(capped.input)
        out_n, _ = nominal.update(nominal.input)
        assert np.allclose(out_c.y, out_n.y, atol=1e-9, rtol=0)
        assert np.allclose(out_c.yd, 0.5 * np.asarray(out_n.yd), atol=1e-9, rtol=0)
    assert out_c.kappa == 0.5
    # lifted: kappa recovers at recovery_rate, the velocity continuous
    capped.set_speed_cap(1.0)
    yd0 = list(out_c.yd)
    out_c, _ = capped.update(capped.input)
    assert out_c.kappa == pytest.approx(0.5 + capped.recovery_rate * dt)
    assert np.max(np.abs(np.asarray(out_c.yd) - yd0)) < 0.01
    for bad in (float('nan'), 'x', None, -1.0, 7.0):
        capped.set_speed_cap(bad)
        assert 0.0 < capped.speed_cap <= 1.0


def _stream(panda, monitoring, gain, n=2000):
    chain, limits, prim, mid = panda
    cfg = StreamerConfig(joint_states_timeout=0.0, separation_monitoring=monitoring)
    coupling = streamer_coupling(chain, cfg, repeller=RepellerField(gain=gain))
    rs = ReferenceStreamer(chain.lower, chain.upper, cfg, coupling, limits=limits)
    prep = prepare_primitive(dumps_primitive(prim), chain.joint_names, cfg.dt, chain.lower,
                             chain.upper, limits.velocity)
    rs.activate(prep, 0.0)
    rs.obstacles = (Sphere(tuple(mid), 0.05),)   # on the hand's path
    dmin, flags, Q = math.inf, 0, []
    for k in range(n):
        flags |= rs.advance(1, k * cfg.dt)
        dmin = min(dmin, rs.min_distance)
        Q.append(list(rs.out_y))
    stamps = np.arange(n) * round(cfg.dt * 1e9)
    return dmin, flags, kinematic_report(stamps, np.array(Q), limits)


def test_the_monitor_stops_the_hand_before_a_sphere_on_its_path(panda):
    """No repeller (gain 0): the reach runs the fingertips 5 cm into a sphere on its path; with
    speed and separation monitoring they stop at the margin (2 cm, less the last tick's
    approach). What is published keeps every limit either way."""
    dmin_off, flags_off, rep_off = _stream(panda, False, 0.0)
    assert dmin_off < -0.04 and not flags_off & StreamFlags.SEPARATION
    dmin_on, flags_on, rep_on = _stream(panda, True, 0.0)
    assert 0.015 < dmin_on <= 0.02 + 1e-9
    assert flags_on & StreamFlags.SEPARATION
    for rep in (rep_off, rep_on):
        assert rep['ok'], rep


def test_the_monitor_leaves_an_avoided_sphere_alone(panda):
    """With the repeller the hand goes round the sphere slowly enough to stop: no cap, the
    stream is the one without the monitor."""
    on = _stream(panda, True, 0.01, n=1500)
    off = _stream(panda, False, 0.01, n=1500)
    assert not on[1] & StreamFlags.SEPARATION
    assert on[0] == off[0] > 0.05
