"""Benchmark of the batched kinematics and the obstacle coupling (issue 4, core half).

Targets: forward kinematics + Jacobians of 3 points of the Panda for 1,500 configurations
<= 2 ms and for one configuration <= 30 us; one coupled CDMP step of the Panda with 3 sphere
obstacles (end effector + 2 link points: kinematics, closest points, fields, Eq. 7 + Eq. 12,
map to the exogenous space, stepper.update) median <= 60 us; closest point of one link
segment to a box <= 50 us. The coupled-step rows run the CDMP along its trajectory (the
configuration changes every step), 1,000 steps per restart.

Run: .venv/bin/python benchmarks/bench_kinematics.py
"""
import argparse
import os
import platform
import time

import numpy as np
import pybullet_data

from cdmp_ros.core.coupling.potential_fields import RepellerField
from cdmp_ros.core.kinematics import PointOfInterest, panda_chain
from cdmp_ros.core.kinematics.closest import Box, Sphere, point_box, segment_box_scalar
from cdmp_ros.core.coupling.obstacle import ObstacleCoupling

POINTS = (PointOfInterest('ee'), PointOfInterest('panda_link3', (0.0, 0.0, -0.1)),
          PointOfInterest('panda_link5', (0.0, 0.1, -0.1)))


CPU = {}


def timed(fn, reps, number=1):
    """Per-call wall-clock latency samples [us] of ``fn()``; the mean CPU time of this thread
    per call [us] goes to ``CPU[id(samples)]`` (the machine is shared: wall time includes
    preemption by other processes, thread CPU time does not)."""
    pc = time.perf_counter_ns
    samples = np.empty(reps)
    c0 = time.thread_time_ns()
    for i in range(reps):
        t0 = pc()
        for _ in range(number):
            fn()
        samples[i] = (pc() - t0) / number
    cpu = (time.thread_time_ns() - c0) / (reps * number) / 1e3
    samples /= 1e3
    CPU[id(samples)] = cpu
    return samples


def coupling_setup(chain, rng, q=(0.2, -0.4, 0.1, -2.0, 0.1, 1.8, 0.7)):
    """Panda, 3 spheres placed so that the end-effector and both link terms are active."""
    coupling = ObstacleCoupling(chain, ['panda_link3', 'panda_link5'],
                                RepellerField(gain=0.02, influence_distance=0.3,
                                              min_distance=0.01))
    q = np.array(q, dtype=float)
    ends = [PointOfInterest(s[0], s[2]) for s in coupling.segments]
    X = chain.forward(q, [PointOfInterest('ee')] + ends)
    obstacles = [Sphere(tuple(x + [0.08, 0.05, 0.0]), 0.05) for x in X]
    return coupling, q, obstacles


def bench_coupled_step(chain, coupling, obstacles, reps):
    from cdmp_ros.core.dmp.dmp import CDMP
    T = np.linspace(0.0, 1.0, 501)
    s = 10 * T ** 3 - 15 * T ** 4 + 6 * T ** 5
    start = np.array([0.2, -0.4, 0.1, -2.0, 0.1, 1.8, 0.7])
    goal = start + np.array([0.4, 0.3, -0.2, 0.4, 0.2, -0.3, 0.1])
    prim = CDMP(chain.lower, chain.upper).fit(T, start + np.outer(s, goal - start))
    stepper = prim.stepper(0.001)
    inp, update, out = stepper.input, stepper.update, stepper.output
    set_joint_coupling = stepper.set_joint_coupling
    joint_acceleration = coupling.joint_acceleration
    update(inp)

    def step():
        set_joint_coupling(joint_acceleration(out.y, out.yd, obstacles))
        update(inp)

    stepper.reset()
    alone = timed(lambda: update(inp), 1000)
    samples, cpu = [], []
    for _ in range(max(1, reps // 1000)):
        stepper.reset()
        update(inp)
        samples.append(timed(step, 1000))
        cpu.append(CPU[id(samples[-1])])
    out = np.concatenate(samples)
    CPU[id(out)] = float(np.mean(cpu))
    return out, alone


def bench_streamer_tick(chain, reps):
    """In-process streamer tick (``ReferenceStreamer.advance(1)``: coupling, the stepper's
    exogenous map, stepper, guard) on a 2 s Panda CDMP
    at 1 kHz with 3 spheres placed so that the end effector and both links are within reach;
    restarted every 1,000 ticks. No ROS: the node adds publishing and the executor."""
    from cdmp_ros.core.dmp.dmp import CDMP
    from cdmp_ros.core.primitive_io import dumps_primitive
    from cdmp_ros.core.streaming.primitives import prepare_primitive
    from cdmp_ros.core.streaming.streamer import ReferenceStreamer, StreamerConfig
    names = tuple(f'panda_joint{i}' for i in range(1, 8))
    y0 = np.array([0.0, -0.5, 0.0, -2.0, 0.0, 1.5, 0.7])
    y1 = np.array([0.8, 0.2, 0.3, -1.2, 0.2, 2.0, 0.3])
    T = np.linspace(0.0, 2.0, 401)
    s = T / 2.0
    s = 10 * s ** 3 - 15 * s ** 4 + 6 * s ** 5
    text = dumps_primitive(CDMP(chain.lower, chain.upper, joint_names=names).fit(
        T, y0 + s[:, None] * (y1 - y0)))
    coupling = ObstacleCoupling(chain, ['panda_link3', 'panda_link5'],
                                RepellerField(gain=0.02, influence_distance=0.3,
                                              min_distance=0.01))
    ends = [PointOfInterest(seg[0], seg[2]) for seg in coupling.segments]
    X = chain.forward(0.5 * (y0 + y1), [PointOfInterest('ee')] + ends)
    obstacles = [Sphere(tuple(x + [0.08, 0.05, 0.0]), 0.05) for x in X]
    cfg = StreamerConfig(joint_states_timeout=0.0)
    samples = []
    cpu = []
    for _ in range(max(1, reps // 1000)):
        rs = ReferenceStreamer(chain.lower, chain.upper, cfg, coupling=coupling)
        rs.obstacles = obstacles
        rs.activate(prepare_primitive(text, names, cfg.dt, chain.lower, chain.upper), 0.0)
        clock = [0.0]

        def tick():
            clock[0] += 0.001
            rs.advance(1, clock[0])
        samples.append(timed(tick, 1000))
        cpu.append(CPU[id(samples[-1])])
        assert rs.min_distance < 0.3
    out = np.concatenate(samples)
    CPU[id(out)] = float(np.mean(cpu))
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--reps', type=int, default=5000, help='repetitions of single calls')
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    chain = panda_chain(pybullet_data.getDataPath() + '/franka_panda/panda.urdf')
    Q = rng.uniform(chain.lower, chain.upper, (1500, 7))
    q = Q[0].copy()
    kernel = chain.fast_kernel(POINTS)
    ql = q.tolist()
    coupling, qc, obstacles = coupling_setup(chain, rng)
    qcl = qc.tolist()
    qd = [0.1] * 7
    dq = coupling.joint_acceleration(qcl, qd, obstacles)
    assert any(dq) and len(coupling.last_distances) == 3
    for fn in (lambda: chain.forward_and_jacobian(Q, POINTS),
               lambda: chain.forward_and_jacobian(q, POINTS)):
        timed(fn, 20)   # warm-up
    rows = [
        ('FK + Jacobians, 3 points, batch of 1,500 (us)',
         timed(lambda: chain.forward_and_jacobian(Q, POINTS), max(50, args.reps // 25)),
         '<= 2000'),
        ('FK + Jacobians, 3 points, 1 configuration, numpy arrays out (us)',
         timed(lambda: chain.forward_and_jacobian(q, POINTS), args.reps), '<= 30'),
        ('FK + Jacobians, 3 points, 1 configuration, kernel on lists (us)',
         timed(lambda: kernel(ql), args.reps), ''),
        ('joint coupling, 3 spheres, EE + 2 links, all active (us)',
         timed(lambda: coupling.joint_acceleration(qcl, qd, obstacles), args.reps), ''),
    ]
    # panda_joint4 at limit usage 0.94: the limit-aware Eq. 12 is evaluated
    near, qn, obstacles_n = coupling_setup(chain, rng, (0.2, -0.4, 0.1, -3.0472, 0.1, 1.8, 0.7))
    qnl = qn.tolist()
    usage = abs(qn[3] - 0.5 * (chain.lower[3] + chain.upper[3])) / (
        0.5 * (chain.upper[3] - chain.lower[3]))
    assert usage > near.config.limit_onset and any(near.joint_acceleration(qnl, qd, obstacles_n))
    rows.append(('joint coupling, same, panda_joint4 at limit usage 0.94 (limit-aware Eq. 12) '
                 '(us)', timed(lambda: near.joint_acceleration(qnl, qd, obstacles_n), args.reps),
                 ''))
    coupled, alone = bench_coupled_step(chain, coupling, obstacles, args.reps)
    rows.append(('coupled CDMP step: coupling + exogenous map + stepper.update (us)', coupled,
                 'median <= 60'))
    rows.append(('(reference) stepper.update alone, same CDMP (us)', alone, ''))
    # boxes: a board next to the link3 segment (closest point on the segment's interior)
    ends = chain.forward(qc, [PointOfInterest(s[0], s[i]) for s in coupling.segments[:1]
                              for i in (1, 2)])
    mid = (ends[0] + ends[1]) / 2
    box = Box.from_center(mid + [0.0, 0.12, 0.0], (0.4, 0.05, 0.4))
    al, bl = ends[0].tolist(), ends[1].tolist()

    def closest_box():
        """The coupling's path: the segment parameter, then the point's distance and normal."""
        t = segment_box_scalar(al, bl, box.lower, box.upper)
        return point_box([al[k] + t * (bl[k] - al[k]) for k in range(3)], box.lower, box.upper)
    assert closest_box()[0] > 0.0
    rows.append(('closest point link segment - box, 1 segment, plain floats (us)',
                 timed(closest_box, args.reps), '<= 50'))
    mixed = obstacles[:2] + [box]
    coupling.joint_acceleration(qcl, qd, mixed)
    assert any(coupling.joint_acceleration(qcl, qd, mixed))
    rows.append(('joint coupling, 2 spheres + 1 box, EE + 2 links (us)',
                 timed(lambda: coupling.joint_acceleration(qcl, qd, mixed), args.reps), ''))
    far = [Sphere((3.0, 3.0, 3.0), 0.1), Sphere((-3.0, 3.0, 3.0), 0.1),
           Box((3.0, 3.0, 3.0), (3.5, 3.5, 3.5))]
    assert not any(coupling.joint_acceleration(qcl, qd, far))
    rows.append(('joint coupling, 3 obstacles, none within reach (us)',
                 timed(lambda: coupling.joint_acceleration(qcl, qd, far), args.reps), ''))
    rows.append(('streamer tick in-process, coupling on, 3 spheres (us)',
                 bench_streamer_tick(chain, args.reps), ''))
    load = os.getloadavg()[0]
    print(f'Python {platform.python_version()}, numpy {np.__version__}, '
          f'load average {load:.2f}\n')
    print('| measurement | wall median | wall p99 | thread CPU mean | target |')
    print('|---|---|---|---|---|')
    for name, samples, target in rows:
        print(f'| {name} | {np.median(samples):.3g} | {np.percentile(samples, 99):.3g} '
              f'| {CPU[id(samples)]:.3g} | {target} |')


if __name__ == '__main__':
    main()
