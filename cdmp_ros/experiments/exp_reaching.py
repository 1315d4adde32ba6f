"""Paper 000, section IV-B: reaching with link obstacle avoidance through the null space.

Setup (Franka Panda in pybullet instead of the iCub, built by
:func:`cdmp_ros.sim.scenes.build_reaching_scene`): the end effector reaches a Cartesian goal;
a board is placed so that it overlaps the upper arm (``panda_link3``, the elbow housing) by
1.37 cm at the final configuration of the unmodified motion, as in the paper. A CDMP (and, for
the comparison, a DMP) is learned from the nominal path, a minimum-jerk motion in joint space
from the start to the inverse-kinematics goal, and streamed tick by tick at 1 kHz to the
simulated robot (computed torque, Eq. 2), faster than real time.

Coupling (paper 000, Eq. 12 and 7, applied in the exogenous space of Eq. 21): the link capsules
(elbow housing and forearm) get the constant field of IV-B, a constant acceleration away from
the board face while they are within the influence distance, mapped into the null space of the
end-effector task by ``(J_o (I - J^+ J))^+``; the end effector is held on the path of the
unmodified motion (its forward kinematics) by an Eq. 7 term, because the null-space motion is
exact only to first order. Both are expressed in the exogenous space (Eq. 29 solved for the
exogenous acceleration, times tau^2) and added to the CDMP's transformation system. The strong
field test multiplies the field by 100 and integrates CDMP and DMP with the same coupling.

Distances are pybullet's closest points between every robot link (collision meshes) and the
board along the measured motion; the paper's figure is the distance of the most dangerous
upper-arm point at the final configuration. Limit usage is ``max |q - centre| / half-range``
over joints and time (above 1: outside the limits).
"""
import os
import time

import numpy as np

from cdmp_ros.experiments.results import row, write_results

NAME = 'reaching'
HELP = 'paper 000 IV-B: reaching with link avoidance in the null space (CDMP vs DMP)'

# ee_error_cm: |(0.354, 0.083, 0.848) - (0.350, 0.091, 0.853)| m, the paper's final and
# requested end-effector positions
PAPER = {'without_cm': -1.37, 'with_cm': 1.03,
         'ee_error_cm': 100.0 * float(np.linalg.norm(
             np.subtract((0.354, 0.083, 0.848), (0.350, 0.091, 0.853))))}


def add_arguments(parser):
    parser.add_argument('--out', required=True, help='output directory')
    parser.add_argument('--duration', type=float, default=2.0,
                        help='movement duration tau [s] (default 2)')
    parser.add_argument('--settle', type=float, default=1.0,
                        help='time simulated after tau [s] (default 1)')
    parser.add_argument('--field', type=float, default=3.0,
                        help='constant field magnitude [m/s^2] (default 3)')
    parser.add_argument('--influence', type=float, default=0.10,
                        help='influence distance of the field [m] (default 0.10)')
    parser.add_argument('--strong-factor', type=float, default=100.0,
                        help='field multiplier of the strong-field test (default 100)')
    parser.add_argument('--hold-kp', type=float, default=1600.0,
                        help='end-effector hold stiffness [1/s^2] (0: Eq. 12 only; kd = '
                             '2 sqrt(kp))')
    parser.add_argument('--distance-every', type=int, default=10,
                        help='ticks between two distance evaluations (default 10 = 10 ms)')
    parser.add_argument('--no-figures', action='store_true',
                        help='skip the snapshots and the joint plot')


class Setup:
    """Scene, board obstacle, chain, primitives and the unmodified end-effector path."""

    def __init__(self, world, args):
        from cdmp_ros.core.dmp.dmp import CDMP, DMP
        from cdmp_ros.core.kinematics import panda_chain, PointOfInterest
        from cdmp_ros.experiments.reaching_coupling import board_obstacle
        from cdmp_ros.sim.control import ComputedTorqueController
        from cdmp_ros.sim.scenes import build_reaching_scene, nominal_path
        self.args = args
        self.world = world
        self.dt = world.config.time_step
        self.scene = build_reaching_scene(world)
        self.robot = self.scene.robot
        self.robot.set_controller(ComputedTorqueController())
        self.board = board_obstacle(self.scene.board)
        self.chain = panda_chain(self.robot.spec.urdf_path)
        T = np.linspace(0.0, args.duration, 201)
        Y = nominal_path(self.scene.q_start, self.scene.q_goal, len(T))
        self.cdmp = CDMP(self.robot.lower, self.robot.upper).fit(T, Y)
        self.dmp = DMP(7).fit(T, Y)
        self.n_steps = int(round((args.duration + args.settle) / self.dt))
        ref = self.cdmp.rollout(self.dt, duration=self.n_steps * self.dt)
        X, J = self.chain.forward_and_jacobian(ref.Y, [PointOfInterest('ee')])
        self.ee_ref = np.ascontiguousarray(X[:, 0])
        self.ee_ref_velocity = np.einsum('kij,kj->ki', J[:, 0], ref.Yd)

    def coupling(self, factor=1.0, hold=True):
        from cdmp_ros.experiments.reaching_coupling import (HoldGains, ReachingCoupling,
                                                            board_field)
        kp = self.args.hold_kp if hold else 0.0
        field = board_field(self.board, factor * self.args.field, self.args.influence)
        return ReachingCoupling(self.chain, field, hold=HoldGains(kp, 2.0 * np.sqrt(kp)),
                                ee_ref=self.ee_ref, ee_ref_velocity=self.ee_ref_velocity)

    def run(self, prim, coupling=None, physics=True):
        """Stream ``prim`` tick by tick (coupling from its own state, Eq. 21/13); with
        ``physics`` the robot tracks each reference for one 1 kHz step.

        Returns the reference ``Y`` and the measured ``Q`` (None without physics), each
        (n_steps + 1, 7).
        """
        stepper = prim.stepper(self.dt, start_y=self.scene.q_start)
        inp, out = stepper.input, stepper.output
        obstacles = (self.board,)
        n = self.n_steps
        Y = np.empty((n + 1, 7))
        Y[0] = out.y
        Q = None
        robot, world = self.robot, self.world
        if physics:
            Q = np.empty((n + 1, 7))
            robot.reset(self.scene.q_start)
            robot.set_reference(self.scene.q_start)
            Q[0] = robot.q
        for k in range(n):
            if coupling is not None:
                coupling.tick = k
                stepper.set_joint_coupling(coupling.joint_acceleration(out.y, out.yd, obstacles))
            stepper.update(inp)
            Y[k + 1] = out.y
            if physics:
                robot.set_reference(out.y, out.yd, out.ydd)
                world.step()
                Q[k + 1] = robot.q
        return Y, Q

    def distances(self, Q):
        """(min over time and links, final) board distance along ``Q`` [m]; the final value
        is the paper's link (the upper arm)."""
        every = max(1, int(self.args.distance_every))
        idx = np.unique(np.r_[np.arange(0, len(Q), every), len(Q) - 1])
        d = self.scene.board_distances(Q[idx])
        final = self.scene.board_distances(Q[-1:], links=[self.scene.config.link])[0]
        return float(d.min()), float(final)


def run(args):
    from cdmp_ros.core.dmp.dmp import limit_usage
    from cdmp_ros.sim import World, WorldConfig
    os.makedirs(args.out, exist_ok=True)
    t_start = time.perf_counter()
    with World(WorldConfig(time_step=1e-3)) as world:
        s = Setup(world, args)
        lo, hi = s.robot.lower, s.robot.upper
        sim_time = s.n_steps * s.dt

        def execute(coupling, picture):
            """The CDMP executed with the coupling made by ``coupling`` (None: without):
            reference, measured path, wall time, board distances (min, final), end-effector
            error; the final pose snapshot in ``picture``."""
            t0 = time.perf_counter()
            Y, Q = s.run(s.cdmp, coupling() if coupling is not None else None)
            wall = time.perf_counter() - t0
            d_min, d_final = s.distances(Q)
            ee = s.scene.ee_error(Q[-1])
            if not args.no_figures:
                s.robot.reset(Q[-1])
                snap(world, s, os.path.join(args.out, picture))
            return Y, Q, wall, d_min, d_final, ee

        # 1. unmodified CDMP, executed
        Y0, Q0, wall_free, d0_min, d0_final, ee0 = execute(None, 'before.png')
        # 2. with the coupling, executed
        Y1, Q1, wall_coupled, d1_min, d1_final, ee1 = execute(s.coupling, 'after.png')
        # 3. the same field without the end-effector hold (Eq. 12 only), reference only
        Y2, _ = s.run(s.cdmp, s.coupling(hold=False), physics=False)
        d2_min, _ = s.distances(Y2)
        ee2 = s.scene.ee_error(Y2[-1])
        # 4. strong field, CDMP vs DMP (references; the DMP's cannot be executed)
        Ys_c, _ = s.run(s.cdmp, s.coupling(args.strong_factor), physics=False)
        Ys_d, _ = s.run(s.dmp, s.coupling(args.strong_factor), physics=False)
        usage = {name: limit_usage(Y, lo, hi) for name, Y in
                 (('free', Q0), ('coupled', Q1), ('coupled_ref', Y1), ('cdmp', Ys_c),
                  ('dmp', Ys_d))}
        if not args.no_figures:
            plot_joints(s, {'without coupling': Q0, 'with coupling': Q1,
                            f'CDMP, field x{args.strong_factor:g}': Ys_c,
                            f'DMP, field x{args.strong_factor:g}': Ys_d},
                        os.path.join(args.out, 'joints.png'))
    rows = [
        row('link_distance_cm.without_coupling', 100 * d0_min, PAPER['without_cm'], 'cm'),
        row('link_distance_cm.with_coupling', 100 * d1_min, PAPER['with_cm'], 'cm'),
        row('link_distance_cm.final.without_coupling', 100 * d0_final, PAPER['without_cm'],
            'cm'),
        row('link_distance_cm.final.with_coupling', 100 * d1_final, PAPER['with_cm'], 'cm'),
        row('ee_error_cm', 100 * ee1, round(PAPER['ee_error_cm'], 2), 'cm'),
        row('ee_error_cm.without_coupling', 100 * ee0, None, 'cm'),
        row('link_term_only.link_distance_cm', 100 * d2_min, None, 'cm'),
        row('link_term_only.ee_error_cm', 100 * ee2, None, 'cm'),
        row('limit_usage.without_coupling', usage['free'], None, ''),
        row('limit_usage.with_coupling', usage['coupled'], None, ''),
        row('limit_usage.with_coupling_reference', usage['coupled_ref'], None, ''),
        row('strong_field.factor', float(args.strong_factor), None, 'x'),
        row('strong_field.cdmp_limit_usage', usage['cdmp'], None, ''),
        row('strong_field.dmp_limit_usage', usage['dmp'], None, ''),
        row('strong_field.cdmp_limit_margin_rad', limit_margin(Ys_c, lo, hi), None, 'rad'),
        row('strong_field.dmp_limit_margin_rad', limit_margin(Ys_d, lo, hi), None, 'rad'),
        row('strong_field.cdmp_inside_limits', bool(usage['cdmp'] < 1.0), True, ''),
        row('strong_field.dmp_inside_limits', bool(usage['dmp'] < 1.0), False, ''),
        row('field_magnitude_m_s2', float(args.field), None, 'm/s^2'),
        row('real_time_factor.with_coupling', sim_time / wall_coupled, None, 'x'),
        row('real_time_factor.without_coupling', sim_time / wall_free, None, 'x'),
    ]
    notes = [__doc__.split('\n\n', 1)[1].strip(),
             f'Movement duration tau = {args.duration:g} s, {args.settle:g} s settling, 1 kHz; '
             f'field {args.field:g} m/s^2 within {args.influence:g} m; end-effector hold '
             f'k_p = {args.hold_kp:g} 1/s^2. The distance rows are minima over the motion and '
             'all links (final.*: the upper arm at the end, the measurement of the paper). '
             'link_term_only.*: the same field without the end-effector hold (reference '
             f'trajectory, kinematic). Total wall time {time.perf_counter() - t_start:.1f} s.']
    if not args.no_figures:
        notes += ['![before](before.png) ![after](after.png)', '![joints](joints.png)']
    print(write_results(args.out, 'paper 000 IV-B reaching with link avoidance', rows, notes,
                        extra={'settings': {k: v for k, v in vars(args).items()
                                            if not k.startswith('_')}}))
    return 0


def limit_margin(Y, lower, upper):
    """Smallest distance to a joint limit over joints and time [rad] (< 0: outside)."""
    return float(np.min(np.minimum(Y - lower, upper - Y)))


def snap(world, setup, path):
    from cdmp_ros.sim import snapshot
    snapshot(world, path, setup.scene.camera)


def plot_joints(setup, runs, path):
    """Joint trajectories of every run with the limits (one panel per joint)."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    lo, hi = setup.robot.lower, setup.robot.upper
    fig, axes = plt.subplots(4, 2, figsize=(10, 10), sharex=True)
    axes = axes.ravel()
    for j in range(7):
        ax = axes[j]
        for name, Y in runs.items():
            ax.plot(np.arange(len(Y)) * setup.dt, Y[:, j], lw=1.2, label=name)
        for b in (lo[j], hi[j]):
            ax.axhline(b, color='k', ls='--', lw=0.8)
        ax.set_ylabel(f'joint {j + 1} [rad]')
    axes[7].axis('off')
    handles, labels = axes[0].get_legend_handles_labels()
    axes[7].legend(handles, labels, loc='center')
    for ax in axes[5:7]:
        ax.set_xlabel('t [s]')
        ax.tick_params(labelbottom=True)
    fig.suptitle('Panda joints (limits dashed)')
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
