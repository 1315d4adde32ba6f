"""Joint-space obstacle coupling of a chain (paper 000, Eq. 7 and 12): configuration, the
closest points and fields, and the generated kernel that evaluates it every tick.

:class:`ObstacleCoupling` is built once per chain and configuration (it generates the
single-configuration kernel, :func:`cdmp_ros.core.coupling.kernel.compile_coupling`) and is
evaluated every tick on plain floats::

    coupling = ObstacleCoupling(chain, links=['panda_link3', 'panda_link5'])
    dq_dd = coupling.joint_acceleration(q, qd, [Sphere((0.4, 0.1, 0.5), 0.05)])
    stepper.set_joint_coupling(dq_dd)          # the exogenous map, capped near saturation

End effector (Eq. 7): the field of every obstacle at the tool centre point (the chain's
end-effector point, or ``tcp_offset`` from the tip link: the Panda's fingertips by default, so
the hand itself avoids obstacles), summed, plus an optional end-effector task (``ee_task``).
Links (Eq. 12): for each chosen link segment, the most dangerous point (smallest signed
distance over the obstacles) with that obstacle's field, and the Jacobian ``J_o`` of that
point, in the null space of the end-effector task; near a joint limit (usage above
``CouplingConfig.limit_onset``) in the joint-limit weighted form::

    dq_dd_l = D (J_o D (I - (J D)^+ J D))^+ dx_dd_l,   D = diag(sqrt(s_i))

(``D = I`` below the onset: Eq. 12 unchanged; the weights and the damped pseudo-inverses are
in the docstring of :mod:`cdmp_ros.core.coupling.kernel`). Spheres use ``sphere_field``, boxes
``box_field`` (:mod:`cdmp_ros.core.coupling.potential_fields`, the one implementation of each
field). The result implements :class:`cdmp_ros.core.coupling.contract.Coupling`; the stepper
(:meth:`cdmp_ros.core.dmp.stepper.DmpStepper.set_joint_coupling`) maps it into its exogenous
coupling term, capped near saturation.

Why the link terms are weighted: Eq. (12) can push a redundant joint into its limit; the CDMP
keeps it strictly inside, but the exogenous map divides the joint acceleration by
``y_delta (1 - tanh(xi)^2)``, so a push that keeps pointing at a limit grows as the joint
approaches it and holds the joint saturated. The weighted least-norm solution (Chan and Dubey,
IEEE T-RA 11(2), 1995) still leaves the end effector alone (``J D z = 0`` implies
``J (D z) = 0``) and no longer moves a joint from ``limit_lock`` on.
"""
import math
from dataclasses import dataclass, field
from typing import Callable, List, Optional, Sequence, Union

import numpy as np

from cdmp_ros.core.config_fields import param
from cdmp_ros.core.coupling.kernel import compile_coupling
from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.coupling.potential_fields import (ZERO, BoardField, ConstantField,
                                                     RepellerField)
from cdmp_ros.core.kinematics import Chain, PointOfInterest
from cdmp_ros.core.kinematics.capsules import Capsule
from cdmp_ros.core.kinematics.closest import (Box, OrientedBox, Sphere, point_box,
                                              segment_box_scalar)
from cdmp_ros.core.validation import as_array, check_positive

Field = Union[RepellerField, ConstantField, BoardField]
#: ``ee_task(x, xd) -> (ax, ay, az)``: an end-effector acceleration besides the obstacles'.
EndEffectorTask = Callable[[Sequence[float], Sequence[float]], Sequence[float]]


@dataclass(frozen=True)
class DampingConfig:
    """Damping of the pseudo-inverses (the damped pseudo-inverse of
    :mod:`cdmp_ros.core.coupling.kernel`).

    Attributes
    ----------
    epsilon : float
        Singular value [m/rad for position Jacobians] below which damping starts.
    lambda_max : float
        Damping at an exact singularity (same unit as ``epsilon``).
    """

    epsilon: float = param(
        0.02, 'Singular value [m/rad for position Jacobians] below which the damping of the '
        'pseudo-inverses starts.')
    lambda_max: float = param(
        0.05, 'Damping of the pseudo-inverses at an exact singularity (same unit as '
        'epsilon).')

    def __post_init__(self):
        check_positive('DampingConfig.epsilon', self.epsilon)
        check_positive('DampingConfig.lambda_max', self.lambda_max)


@dataclass(frozen=True)
class CouplingConfig:
    """Configuration of :class:`ObstacleCoupling`.

    Attributes
    ----------
    damping : DampingConfig
        Pseudo-inverse damping.
    link_radius : float
        Radius [m] of the capsules modelling the links (distances are to the capsule surface).
    end_effector : bool
        Apply the fields to the end-effector point (Eq. 7). The link terms always act in the
        null space of the end-effector task; an ``ee_task`` of the coupling acts either way.
    limit_aware : bool
        Weight the link terms (Eq. 12) away from joints near their limits (weighted least
        norm, module docstring); False: Eq. (12) as is.
    limit_onset : float
        Joint limit usage ``|q - q_o| / y_delta`` above which that weighting starts.
    limit_lock : float
        Limit usage from which the link terms no longer move that joint (its weight is
        infinite); ``0 < limit_onset < limit_lock <= 1``.
    """

    damping: DampingConfig = field(default_factory=DampingConfig)
    link_radius: float = param(
        0.0, 'Radius [m] of the capsules modelling the links (distances are to the capsule '
        'surface).')
    end_effector: bool = param(
        True, 'Apply the fields to the end-effector point (Eq. 7). The link terms always act in '
        'the null space of the end-effector task.')
    end_effector_radius: float = param(
        0.0, 'Radius [m] of a ball around the tool centre point that Eq. 7 keeps away from '
        'obstacles (distances are to its surface): with the centre inside the hand, a ball '
        'that encloses hand and fingers makes the primary task avoid with the whole tool.')
    limit_aware: bool = param(
        True, 'Weight the link terms (Eq. 12) away from joints near their limits (weighted '
        'least norm); false: Eq. (12) as is.')
    limit_onset: float = param(
        0.9, 'Joint limit usage |q - q_o| / y_delta above which the limit-aware weighting of '
        'the link terms starts; 0 < limit_onset < limit_lock <= 1.')
    limit_lock: float = param(
        0.95, 'Limit usage from which the link terms no longer move that joint (its weight is '
        'infinite); 0 < limit_onset < limit_lock <= 1.')

    def __post_init__(self):
        if not isinstance(self.damping, DampingConfig):
            raise ValidationError(f'CouplingConfig.damping: expected DampingConfig, got '
                                  f'{type(self.damping).__name__}')
        check_positive('CouplingConfig.link_radius', self.link_radius, allow_zero=True)
        check_positive('CouplingConfig.end_effector_radius', self.end_effector_radius,
                       allow_zero=True)
        onset = check_positive('CouplingConfig.limit_onset', self.limit_onset)
        lock = check_positive('CouplingConfig.limit_lock', self.limit_lock)
        if onset >= 1.0:
            raise ValidationError(f'CouplingConfig.limit_onset: expected a number in (0, 1), '
                                  f'got {self.limit_onset!r}')
        if not onset < lock <= 1.0:
            raise ValidationError(f'CouplingConfig.limit_lock: expected a number in '
                                  f'(limit_onset, 1] = ({onset!r}, 1], got {self.limit_lock!r}')


class ObstacleCoupling:
    """Joint acceleration coupling of a chain for a set of obstacles (module docstring).

    Parameters
    ----------
    chain : Chain
    links : sequence of str, (link, start, end) or Capsule
        Link segments that get a null-space avoidance term: link names (looked up in
        ``chain.link_segments()``), explicit segments (points in the link frame), both with
        radius ``config.link_radius``, or
        :class:`~cdmp_ros.core.kinematics.capsules.Capsule` s with their own radius (e.g.
        fitted to the link's collision geometry,
        :func:`~cdmp_ros.core.kinematics.capsules.collision_capsules`).
    sphere_field, box_field : field
        Potential fields of spheres and of boxes.
    config : CouplingConfig
    tcp_offset : sequence of 3 float, optional
        The tool centre point, on which the end-effector term (Eq. 7) acts: this offset [m]
        in the frame of the chain's tip link (``chain.ee_link``, the Panda's hand flange).
        None: the chain's own end-effector point (``PointOfInterest('ee')``; for
        :func:`~cdmp_ros.core.kinematics.builders.panda_chain` the fingertips,
        ``PANDA_EE_OFFSET``).
    ee_task : callable, optional
        ``ee_task(x, xd) -> (ax, ay, az)``: a Cartesian acceleration of the tool centre point
        (at position ``x`` and velocity ``xd``) added to the obstacles' in Eq. (7), e.g. a hold
        on a reference path. Evaluated every call, with the velocities (as velocity-dependent
        fields are).

    Attributes
    ----------
    kernel_description : str
        The configuration the generated kernel was written for (its module's header).
    """

    def __init__(self, chain: Chain, links: Sequence = (),
                 sphere_field: Field = RepellerField(), box_field: Field = ConstantField(),
                 config: CouplingConfig = CouplingConfig(),
                 tcp_offset: Optional[Sequence[float]] = None,
                 ee_task: Optional[EndEffectorTask] = None):
        self.chain = chain
        self.config = config
        self.sphere_field = sphere_field
        self.box_field = box_field
        by_name = {seg[0]: seg for seg in chain.link_segments()}
        self.segments = []
        radii = []
        for i, link in enumerate(links):
            if isinstance(link, str):
                if link not in by_name:
                    raise ValidationError(f'links[{i}]: expected one of {list(by_name)}, got '
                                          f'{link!r}')
                self.segments.append(by_name[link])
                radii.append(config.link_radius)
            elif isinstance(link, Capsule):
                if not (math.isfinite(link.radius) and link.radius >= 0.0):
                    raise ValidationError(f'links[{i}]: radius: expected a finite value >= 0, '
                                          f'got {link.radius!r}')
                self.segments.append((link.link, tuple(map(float, link.start)),
                                      tuple(map(float, link.end))))
                radii.append(float(link.radius))
            else:
                name, start, end = link
                self.segments.append((name, tuple(map(float, start)), tuple(map(float, end))))
                radii.append(config.link_radius)
        #: capsule radius [m] of every segment
        self.radii = tuple(radii)
        if tcp_offset is None:
            tcp = PointOfInterest('ee')
        else:
            tcp = PointOfInterest(chain.ee_link,
                                  tuple(as_array('tcp_offset', tcp_offset, (3,)).tolist()))
        points = [tcp]
        for name, start, end in self.segments:
            points += [PointOfInterest(name, start), PointOfInterest(name, end)]
        self.points = tuple(points)
        frames, coords = chain.resolve(self.points)
        # 'all': velocity-dependent fields (every point's velocity); 'ee': an end-effector
        # task only (the end effector's velocity)
        self._velocity = ('all' if any(getattr(f, 'damping', 0.0)
                                       for f in (sphere_field, box_field))
                          else 'ee' if ee_task is not None else False)
        self.last_distances: List[float] = []
        self._eps2 = config.damping.epsilon ** 2
        self._lam2 = config.damping.lambda_max ** 2
        self._zeros = [0.0] * chain.n_dofs
        self._gate = ClosestPointGate(self.radii, sphere_field, box_field, config, ee_task)
        limits = ((chain.lower.tolist(), chain.upper.tolist(), config.limit_onset,
                   config.limit_lock) if self.segments and config.limit_aware else None)
        self.kernel_description = self._describe(tcp, limits)
        self._coupled = compile_coupling(
            chain.B, chain.base_transform, chain.prismatic,
            (int(frames[0]), coords[0].tolist()),
            [(int(frames[1 + 2 * i]), coords[1 + 2 * i].tolist(), coords[2 + 2 * i].tolist())
             for i in range(len(self.segments))],
            axes=chain.task_axes, limits=limits, velocity=self._velocity,
            title=f'Obstacle coupling of {chain!r}.', description=self.kernel_description)

    def _describe(self, tcp: PointOfInterest, limits) -> str:
        """The configuration of the generated kernel, for its module's header."""
        chain = self.chain
        lines = [f'Configuration: the chain of joints {", ".join(chain.joint_names)} '
                 f'(links {chain.link_names[0]} -> {chain.ee_link}, task axes '
                 f'{chain.task_axes});',
                 f'Eq. (7) on the tool centre point {tcp.link} + {tuple(tcp.offset)};',
                 'Eq. (12) on the segments (link: start, end in the link frame [m]): '
                 + ('; '.join(f'{n}: {a}, {b}' for n, a, b in self.segments) or 'none') + ';']
        if limits is None:
            lines.append('the link terms not limit-aware;')
        else:
            lo, hi = (', '.join(f'{v:.6g}' for v in side) for side in limits[:2])
            lines.append(f'the limit-aware Eq. (12) from limit usage {limits[2]!r} to '
                         f'{limits[3]!r} of the limits [{lo}] .. [{hi}];')
        lines.append({'all': 'the fields depend on the velocity: the gate gets xd = J qd.',
                      'ee': 'an end-effector task: the gate gets its velocity J qd.'}.get(
                          self._velocity, 'fields independent of the velocity.'))
        return '\n'.join(lines)

    def joint_acceleration(self, q: Sequence[float], qd: Optional[Sequence[float]],
                           obstacles: Sequence[Union[Sphere, Box]]) -> List[float]:
        """Total joint acceleration coupling ``J^+ dx_e + sum_l (J_o,l N)^+ dx_l`` (near a
        joint limit the link terms in their limit-aware form, module docstring).

        Parameters
        ----------
        q, qd : sequence of float (n_dofs)
            Joint positions and velocities (``qd`` feeds velocity-dependent fields and the
            ``ee_task``; None means at rest).
        obstacles : sequence of Sphere, Box or OrientedBox

        Returns
        -------
        list of float (n_dofs)
            Joint acceleration change [rad/s^2]. ``self.last_distances`` then holds the
            signed distance of the end effector and of every chosen link to its nearest
            obstacle.
        """
        if isinstance(q, np.ndarray):
            q = q.tolist()
        if self._velocity:
            qd = self._zeros if qd is None else (qd.tolist() if isinstance(qd, np.ndarray)
                                                 else qd)
        gate = self._gate
        dq = self._coupled(q, qd, gate, obstacles, self._eps2, self._lam2)
        self.last_distances = gate.distances
        return [0.0] * self.chain.n_dofs if dq is None else dq


class ClosestPointGate:
    """The closest points and potential fields of :class:`ObstacleCoupling` (the ``gate`` of
    :func:`~cdmp_ros.core.coupling.kernel.compile_coupling`): the one closest-point routine of
    the coupling. Spheres inline, boxes by :func:`~cdmp_ros.core.kinematics.boxes.point_box`
    / :func:`~cdmp_ros.core.kinematics.boxes.segment_box_scalar`, oriented boxes by
    :meth:`~cdmp_ros.core.kinematics.closest.OrientedBox.point` / ``segment``; every field by
    its own ``acceleration``.

    ``gate(x, obstacles, xd=None)`` returns None when no field is active, else
    ``[e0, e1, e2] + [active, p (3), dx (3)] * n_links``; ``distances`` then holds the signed
    distance of the end effector and of every link to its nearest obstacle. ``x`` (and the
    velocities ``xd``, for velocity-dependent fields) list the end effector, then the start
    and end of every segment (world); ``xd`` of 3 values is the end effector's alone (an
    end-effector task); the velocity of a link's closest point is interpolated between its
    segment's ends (exact: point velocities of one rigid link are affine in the point).
    """

    def __init__(self, radii: Sequence[float], sphere_field, box_field, config,
                 ee_task: Optional[EndEffectorTask] = None):
        self.n_links = len(radii)
        self.sphere_field = sphere_field
        self.box_field = box_field
        self.radii = tuple(float(r) for r in radii)
        self.end_effector = config.end_effector
        self.ee_radius = config.end_effector_radius
        self.ee_task = ee_task
        self.distances: List[float] = []

    def __call__(self, x: List[float], obstacles, xd: Optional[List[float]] = None
                 ) -> Optional[list]:
        radii = self.radii
        sphere_acc = self.sphere_field.acceleration
        box_acc = self.box_field.acceleration
        use_ee = self.end_effector
        ee_radius = self.ee_radius
        e0, e1, e2 = ee = x[0], x[1], x[2]
        xd_e = ZERO if xd is None else (xd[0], xd[1], xd[2])
        ax = ay = az = 0.0
        dmin = math.inf
        sqrt = math.sqrt
        for obs in obstacles:
            if type(obs) is Sphere:
                c0, c1, c2 = obs.center
                v0, v1, v2 = e0 - c0, e1 - c1, e2 - c2
                r = sqrt(v0 * v0 + v1 * v1 + v2 * v2)
                if r > 1e-12:
                    d = r - obs.radius - ee_radius
                    normal = (v0 / r, v1 / r, v2 / r)
                else:
                    d, normal = -obs.radius - ee_radius, (0.0, 0.0, 1.0)
                if d < dmin:
                    dmin = d
                if not use_ee:
                    continue
                a = sphere_acc(ee, xd_e, obs, d, normal)
            else:
                if type(obs) is Box:
                    d, _, normal = point_box(ee, obs.lower, obs.upper)
                elif type(obs) is OrientedBox:
                    d, normal = obs.point(ee)
                else:
                    raise ValidationError(f'obstacles: expected Sphere, Box or OrientedBox, '
                                          f'got {type(obs).__name__}')
                d -= ee_radius
                if d < dmin:
                    dmin = d
                if not use_ee:
                    continue
                a = box_acc(ee, xd_e, obs, d, normal)
            ax += a[0]
            ay += a[1]
            az += a[2]
        if self.ee_task is not None:
            a = self.ee_task(ee, xd_e)
            ax += a[0]
            ay += a[1]
            az += a[2]
        dists = [dmin]
        out = [ax, ay, az]
        active = ax != 0.0 or ay != 0.0 or az != 0.0
        for i in range(self.n_links):
            j = 3 + 6 * i
            a0, a1, a2, b0, b1, b2 = x[j:j + 6]
            radius = radii[i]
            u0, u1, u2 = b0 - a0, b1 - a1, b2 - a2
            uu = u0 * u0 + u1 * u1 + u2 * u2
            best_d = math.inf
            best = None
            for obs in obstacles:
                if type(obs) is Sphere:
                    c0, c1, c2 = obs.center
                    if uu > 0.0:
                        t = ((c0 - a0) * u0 + (c1 - a1) * u1 + (c2 - a2) * u2) / uu
                        t = 0.0 if t < 0.0 else (1.0 if t > 1.0 else t)
                    else:
                        t = 0.0
                    v0, v1, v2 = a0 + t * u0 - c0, a1 + t * u1 - c1, a2 + t * u2 - c2
                    r = sqrt(v0 * v0 + v1 * v1 + v2 * v2)
                    d = r - obs.radius - radius
                    if d < best_d:
                        best_d, best, bt, bv, br = d, obs, t, (v0, v1, v2), r
                elif type(obs) is Box:
                    lo, hi = obs.lower, obs.upper
                    t = segment_box_scalar((a0, a1, a2), (b0, b1, b2), lo, hi)
                    d, _, normal = point_box((a0 + t * u0, a1 + t * u1, a2 + t * u2), lo, hi)
                    d -= radius
                    if d < best_d:
                        best_d, best, bt, bv, br = d, obs, t, normal, None
                else:                                           # OrientedBox
                    t = obs.segment((a0, a1, a2), (b0, b1, b2))
                    d, normal = obs.point((a0 + t * u0, a1 + t * u1, a2 + t * u2))
                    d -= radius
                    if d < best_d:
                        best_d, best, bt, bv, br = d, obs, t, normal, None
            dists.append(best_d)
            if best is not None:
                t = bt
                p = (a0 + t * u0, a1 + t * u1, a2 + t * u2)
                if xd is None or len(xd) == 3:                 # no link velocities
                    v = ZERO
                else:
                    s = 1.0 - t
                    v = (s * xd[j] + t * xd[j + 3], s * xd[j + 1] + t * xd[j + 4],
                         s * xd[j + 2] + t * xd[j + 5])
                if br is None:                                  # box: bv is the normal
                    a = box_acc(p, v, best, best_d, bv)
                else:
                    normal = ((bv[0] / br, bv[1] / br, bv[2] / br) if br > 1e-12
                              else (0.0, 0.0, 1.0))
                    a = sphere_acc(p, v, best, best_d, normal)
                if a[0] or a[1] or a[2]:
                    out += (True, p[0], p[1], p[2], a[0], a[1], a[2])
                    active = True
                    continue
            out += (False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        self.distances = dists
        return out if active else None
