"""Joint-space obstacle coupling of a chain: kinematics + closest points + fields + Eq. 7/12.

:class:`ObstacleCoupling` is built once per chain (it compiles the single-configuration
kinematics kernel of the end effector and of the chosen link segments) and evaluated every
tick on plain floats::

    coupling = ObstacleCoupling(chain, links=['panda_link3', 'panda_link5'])
    dq_dd = coupling.joint_acceleration(q, qd, [Sphere((0.4, 0.1, 0.5), 0.05)])
    stepper.set_joint_coupling(dq_dd)          # the exogenous map, capped near saturation

End effector (paper 000, Eq. 7): the field of every obstacle at the tool centre point (the
chain's end-effector point, or ``tcp_offset`` from the tip link: the Panda's fingertips by
default, so the hand itself avoids obstacles), summed.
Links (Eq. 12): for each chosen link segment, the most dangerous point (smallest signed distance
over the obstacles, :mod:`cdmp_ros.core.kinematics.closest`) with that obstacle's field, and
the Jacobian ``J_o`` of that point. Spheres use ``sphere_field``, boxes ``box_field``. Near a
joint limit (usage above ``CouplingConfig.limit_onset``) the link terms are the joint-limit
weighted form of Eq. (12) (:mod:`cdmp_ros.core.coupling.terms`)::

    dq_dd_l = D (J_o D (I - (J D)^+ J D))^+ dx_dd_l,   D = diag(sqrt(s_i)),
    s_i = (1 - rho_i)^2 (1 + 2 rho_i),   rho_i = clip((|u_i| - u_on) / (u_lock - u_on), 0, 1)

with ``u_i`` the limit usage of joint i, ``u_on``/``u_lock`` = ``limit_onset``/``limit_lock``
(``D = I`` below the onset: Eq. 12 unchanged).

With three task rows and velocity-independent fields the whole evaluation runs in one
generated function (:mod:`cdmp_ros.core.coupling.kernel`; no Jacobian at all when no field is
active); otherwise :meth:`ObstacleCoupling.joint_acceleration_generic` (kernel of both segment
ends, ``J_o = (1 - t) J_a + t J_b``, exact because point Jacobians of one rigid link are affine
in the point). It implements :class:`cdmp_ros.core.coupling.contract.Coupling`; the stepper
(:meth:`cdmp_ros.core.dmp.stepper.DmpStepper.set_joint_coupling`) maps the result into its
exogenous coupling term, capped near saturation.
"""
import math
from dataclasses import dataclass, field
from typing import List, Optional, Sequence, Union

import numpy as np

from cdmp_ros.core.coupling.terms import DampingConfig, LimitScale, coupling_3d, scalar_coupling
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


@dataclass(frozen=True)
class CouplingConfig:
    """Configuration of :class:`ObstacleCoupling`.

    Attributes
    ----------
    damping : DampingConfig
        Pseudo-inverse damping (:mod:`cdmp_ros.core.coupling.terms`).
    link_radius : float
        Radius [m] of the capsules modelling the links (distances are to the capsule surface).
    end_effector : bool
        Apply the fields to the end-effector point (Eq. 7). The link terms always act in the
        null space of the end-effector task.
    limit_aware : bool
        Weight the link terms (Eq. 12) away from joints near their limits (weighted least
        norm, module docstring of :mod:`cdmp_ros.core.coupling.terms`); False: Eq. (12) as is.
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
    """

    def __init__(self, chain: Chain, links: Sequence = (),
                 sphere_field: Field = RepellerField(), box_field: Field = ConstantField(),
                 config: CouplingConfig = CouplingConfig(),
                 tcp_offset: Optional[Sequence[float]] = None):
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
        self._kernel = chain.fast_kernel(self.points)
        frames, coords = chain.resolve(self.points)
        # joints that move each segment: J_o columns beyond are zero and are cut off
        self._n_moving = [int(frames[1 + 2 * i]) for i in range(len(self.segments))]
        self._axes = chain.task_axes
        fields = (sphere_field, box_field)
        self._needs_velocity = any(getattr(f, 'damping', 0.0) for f in fields)
        self.last_distances: List[float] = []
        self._eps2 = config.damping.epsilon ** 2
        self._lam2 = config.damping.lambda_max ** 2
        # Generated path (coupling_kernel): 3 task rows and velocity-independent fields; the
        # generic path below handles the rest and serves as its reference in the tests.
        # limit-aware Eq. (12): None when off (or no link)
        self._limit = (LimitScale(chain.lower, chain.upper, config.limit_onset,
                                  config.limit_lock)
                       if self.segments and config.limit_aware else None)
        self._gate = ClosestPointGate(self.radii, sphere_field, box_field, config)
        self._coupled = None
        if self._axes == (0, 1, 2) and not self._needs_velocity:
            self._coupled = compile_coupling(
                chain.B, chain.base_transform, chain.prismatic,
                (int(frames[0]), coords[0]),
                [(int(frames[1 + 2 * i]), coords[1 + 2 * i], coords[2 + 2 * i])
                 for i in range(len(self.segments))],
                self._limit.bounds if self._limit is not None else None)

    @staticmethod
    def _velocity(rows, qd):
        if qd is None:
            return (0.0, 0.0, 0.0)
        return tuple(sum(a * b for a, b in zip(row, qd)) for row in rows)

    def joint_acceleration(self, q: Sequence[float], qd: Optional[Sequence[float]],
                           obstacles: Sequence[Union[Sphere, Box]]) -> List[float]:
        """Total joint acceleration coupling ``J^+ dx_e + sum_l (J_o,l N)^+ dx_l`` (near a
        joint limit the link terms in their limit-aware form, module docstring).

        Parameters
        ----------
        q, qd : sequence of float (n_dofs)
            Joint positions and velocities (``qd`` feeds velocity-dependent fields; None
            means at rest).
        obstacles : sequence of Sphere or Box

        Returns
        -------
        list of float (n_dofs)
            Joint acceleration change [rad/s^2]. ``self.last_distances`` then holds the
            signed distance of the end effector and of every chosen link to its nearest
            obstacle.
        """
        coupled = self._coupled
        if coupled is not None:
            gate = self._gate
            dq = coupled(q.tolist() if isinstance(q, np.ndarray) else q, gate, obstacles,
                         self._eps2, self._lam2, self._limit)
            self.last_distances = gate.distances
            return [0.0] * self.chain.n_dofs if dq is None else dq
        return self.joint_acceleration_generic(q, qd, obstacles)

    def joint_acceleration_generic(self, q: Sequence[float], qd: Optional[Sequence[float]],
                                   obstacles: Sequence[Union[Sphere, Box]]) -> List[float]:
        """:meth:`joint_acceleration` without the generated kernel (any task axes, fields
        that depend on the velocity): kernel of both segment ends, the same closest points and
        fields (:class:`ClosestPointGate`), ``J_o`` interpolated, and
        :func:`~cdmp_ros.core.coupling.terms.coupling_3d` / ``scalar_coupling``."""
        n = self.chain.n_dofs
        ql = q.tolist() if isinstance(q, np.ndarray) else list(q)
        qdl = (qd.tolist() if isinstance(qd, np.ndarray) else list(qd)) if qd is not None \
            else None
        x, jac = self._kernel(ql)
        rows_e = [jac[0:n], jac[n:2 * n], jac[2 * n:3 * n]]
        stride = 3 * n

        def link_jacobian(i, t):
            """``J_o`` of the point at ``t`` on segment i (the columns that move it)."""
            k = self._n_moving[i]
            base_a = (1 + 2 * i) * stride
            s = 1.0 - t
            lerp = [s * u + t * v for u, v in zip(jac[base_a:base_a + stride],
                                                  jac[base_a + stride:base_a + 2 * stride])]
            return [lerp[0:k], lerp[n:n + k], lerp[2 * n:2 * n + k]]

        def velocity(i, t):
            """Velocity of the end effector (i = -1) or of the point at t on segment i."""
            return self._velocity(rows_e if i < 0 else link_jacobian(i, t), qdl)

        gate = self._gate
        r = gate(x, obstacles, velocity if self._needs_velocity and qdl is not None else None)
        self.last_distances = gate.distances
        if r is None:
            return [0.0] * n
        dx_e = list(r[0:3])
        links = []
        for i in range(len(self.segments)):
            j = 3 + 7 * i
            if r[j]:
                links.append((link_jacobian(i, gate.link_t[i]), r[j + 4:j + 7]))
        scale = self._limit(ql) if self._limit is not None and links else None
        if self._axes == (0, 1, 2):
            return coupling_3d(rows_e, dx_e, links, self.config.damping, scale)
        ax = self._axes
        rows = [rows_e[a] for a in ax]
        links = [([list(J_o[a]) + [0.0] * (n - len(J_o[a])) for a in ax], [dx[a] for a in ax])
                 for J_o, dx in links]
        return scalar_coupling(rows, [dx_e[a] for a in ax], links, self.config.damping, scale)


class ClosestPointGate:
    """The closest points and potential fields of :class:`ObstacleCoupling` (the ``gate`` of
    :func:`~cdmp_ros.core.coupling.kernel.compile_coupling`, and the geometry of
    :meth:`ObstacleCoupling.joint_acceleration_generic`): the one closest-point routine of the
    coupling. Spheres inline, boxes by :func:`~cdmp_ros.core.kinematics.boxes.point_box` /
    :func:`~cdmp_ros.core.kinematics.boxes.segment_box_scalar`, oriented boxes by
    :meth:`~cdmp_ros.core.kinematics.closest.OrientedBox.point` / ``segment``.

    ``gate(x, obstacles, velocity=None)`` returns None when no field is active, else
    ``[e0, e1, e2] + [active, p (3), dx (3)] * n_links``; ``distances`` then holds the signed
    distance of the end effector and of every link to its nearest obstacle, ``link_t`` the
    segment parameter of every link's closest point. ``velocity(i, t)``, if given, returns the
    velocity of the end effector (``i = -1``) or of the point at ``t`` on segment ``i`` for
    velocity-dependent fields (zero otherwise). A
    :class:`~cdmp_ros.core.coupling.potential_fields.RepellerField` without damping on spheres
    is inlined (the arithmetic of its ``acceleration``); other fields are called.
    """

    def __init__(self, radii: Sequence[float], sphere_field, box_field, config):
        n_links = len(radii)
        self.n_links = n_links
        self.sphere_field = sphere_field
        self.box_field = box_field
        self.radii = tuple(float(r) for r in radii)
        self.end_effector = config.end_effector
        self.ee_radius = config.end_effector_radius
        self.distances: List[float] = []
        self.link_t: List[float] = [0.0] * n_links
        self.repeller = None
        if type(sphere_field) is RepellerField and not sphere_field.damping:
            self.repeller = (sphere_field.gain, sphere_field.influence_distance,
                             sphere_field.min_distance, 1.0 / sphere_field.influence_distance)

    def __call__(self, x: List[float], obstacles, velocity=None) -> Optional[list]:
        """``x``: end effector, then start and end of every segment (world)."""
        radii = self.radii
        sphere_field, box_field = self.sphere_field, self.box_field
        rep = self.repeller
        if rep is not None:
            gain, d0, d_floor, inv_d0 = rep
        use_ee = self.end_effector
        ee_radius = self.ee_radius
        e0, e1, e2 = ee = x[0], x[1], x[2]
        xd_e = ZERO if velocity is None or not use_ee else velocity(-1, 0.0)
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
                    n0, n1, n2 = v0 / r, v1 / r, v2 / r
                else:
                    d, n0, n1, n2 = -obs.radius - ee_radius, 0.0, 0.0, 1.0
                if d < dmin:
                    dmin = d
                if not use_ee:
                    continue
                if rep is not None:                 # RepellerField.acceleration, inlined
                    if d < d0:
                        dd = d if d > d_floor else d_floor
                        g = gain * (1.0 / dd - inv_d0) / (dd * dd)
                        ax += g * n0
                        ay += g * n1
                        az += g * n2
                    continue
                a = sphere_field.acceleration(ee, xd_e, obs, d, (n0, n1, n2))
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
                a = box_field.acceleration(ee, xd_e, obs, d, normal)
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
                t = self.link_t[i] = bt
                p0, p1, p2 = a0 + t * u0, a1 + t * u1, a2 + t * u2
                xd = ZERO if velocity is None else velocity(i, t)
                if br is None:                                  # box: bv is the normal
                    a = box_field.acceleration((p0, p1, p2), xd, best, best_d, bv)
                else:
                    r = br
                    if r > 1e-12:
                        n0, n1, n2 = bv[0] / r, bv[1] / r, bv[2] / r
                    else:
                        n0, n1, n2 = 0.0, 0.0, 1.0
                    if rep is not None:                 # RepellerField.acceleration, inlined
                        if best_d < d0:
                            dd = best_d if best_d > d_floor else d_floor
                            g = gain * (1.0 / dd - inv_d0) / (dd * dd)
                            a = (g * n0, g * n1, g * n2)
                        else:
                            a = ZERO
                    else:
                        a = sphere_field.acceleration((p0, p1, p2), xd, best, best_d,
                                                      (n0, n1, n2))
                if a[0] or a[1] or a[2]:
                    out += (True, p0, p1, p2, a[0], a[1], a[2])
                    active = True
                    continue
            out += (False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        self.distances = dists
        return out if active else None
