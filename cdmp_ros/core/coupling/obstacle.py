"""Joint-space obstacle coupling of a chain: kinematics + closest points + fields + Eq. 7/12.

:class:`ObstacleCoupling` is built once per chain (it compiles the single-configuration
kinematics kernel of the end effector and of the chosen link segments) and evaluated every
tick on plain floats::

    coupling = ObstacleCoupling(chain, links=['panda_link3', 'panda_link5'])
    dq_dd = coupling.joint_acceleration(q, qd, [Sphere((0.4, 0.1, 0.5), 0.05)])
    stepper.input.coupling[:] = coupling.to_internal(dq_dd, out.xi, tau, transform)

End effector (paper 000, Eq. 7): the field of every obstacle at the end-effector point, summed.
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
in the point). :meth:`ObstacleCoupling.to_internal` maps the result to the stepper's exogenous
coupling term, capped near saturation.
"""
import math
from dataclasses import dataclass, field
from typing import List, Optional, Sequence, Union

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdmp_ros.core.coupling.terms import DampingConfig, LimitScale, coupling_3d, scalar_coupling
from cdmp_ros.core.coupling.kernel import ClosestPointGate, compile_coupling
from cdmp_ros.core.config_fields import param
from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.coupling.potential_fields import BoardField, ConstantField, RepellerField
from cdmp_ros.core.kinematics import Chain, PointOfInterest
from cdmp_ros.core.kinematics.closest import (Box, OrientedBox, Sphere, point_box,
                                              segment_box_scalar)
from cdmp_ros.core.validation import check_positive

Field = Union[RepellerField, ConstantField, BoardField]

#: Default floor of ``1 - tanh(xi)^2`` in :meth:`ObstacleCoupling.to_internal` (the cap of the
#: coupling term near saturation).
SATURATION_FLOOR = 1e-2


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
    links : sequence of str or (link, start, end)
        Link segments that get a null-space avoidance term: link names (looked up in
        ``chain.link_segments()``) or explicit segments (points in the link frame).
    sphere_field, box_field : field
        Potential fields of spheres and of boxes.
    config : CouplingConfig
    """

    def __init__(self, chain: Chain, links: Sequence = (),
                 sphere_field: Field = RepellerField(), box_field: Field = ConstantField(),
                 config: CouplingConfig = CouplingConfig()):
        self.chain = chain
        self.config = config
        self.sphere_field = sphere_field
        self.box_field = box_field
        by_name = {seg[0]: seg for seg in chain.link_segments()}
        self.segments = []
        for i, link in enumerate(links):
            if isinstance(link, str):
                if link not in by_name:
                    raise ValidationError(f'links[{i}]: expected one of {list(by_name)}, got '
                                          f'{link!r}')
                self.segments.append(by_name[link])
            else:
                name, start, end = link
                self.segments.append((name, tuple(map(float, start)), tuple(map(float, end))))
        points = [PointOfInterest('ee')]
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
        self._coupled = self._gate = None
        if self._axes == (0, 1, 2) and not self._needs_velocity:
            self._gate = ClosestPointGate(len(self.segments), sphere_field, box_field, config)
            self._coupled = compile_coupling(
                chain.B, chain.base_transform, chain.prismatic,
                (int(frames[0]), coords[0]),
                [(int(frames[1 + 2 * i]), coords[1 + 2 * i], coords[2 + 2 * i])
                 for i in range(len(self.segments))],
                self._limit.bounds if self._limit is not None else None)

    def _field(self, obstacle) -> Field:
        if isinstance(obstacle, Sphere):
            return self.sphere_field
        if isinstance(obstacle, (Box, OrientedBox)):
            return self.box_field
        raise ValidationError(f'obstacles: expected Sphere, Box or OrientedBox, got '
                              f'{type(obstacle).__name__}')

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
        that depend on the velocity): kernel of both segment ends, ``J_o`` interpolated, and
        :func:`~cdmp_ros.core.coupling.terms.coupling_3d` / ``scalar_coupling``."""
        n = self.chain.n_dofs
        ql = q.tolist() if isinstance(q, np.ndarray) else list(q)
        qdl = (qd.tolist() if isinstance(qd, np.ndarray) else list(qd)) if qd is not None \
            else None
        x, jac = self._kernel(ql)
        radius = self.config.link_radius
        rows_e = [jac[0:n], jac[n:2 * n], jac[2 * n:3 * n]]
        ee = x[0:3]
        dx_e = [0.0, 0.0, 0.0]
        xd_e = self._velocity(rows_e, qdl) if self._needs_velocity else (0.0, 0.0, 0.0)
        dists = [math.inf]
        sphere_field, box_field = self.sphere_field, self.box_field
        use_ee = self.config.end_effector
        e0, e1, e2 = ee
        for obs in obstacles:
            if type(obs) is Sphere:
                c = obs.center
                v0, v1, v2 = e0 - c[0], e1 - c[1], e2 - c[2]
                r = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
                if r > 1e-12:
                    d, normal = r - obs.radius, (v0 / r, v1 / r, v2 / r)
                else:
                    d, normal = -obs.radius, (0.0, 0.0, 1.0)
                f = sphere_field
            elif type(obs) is Box:
                d, _, normal = point_box(ee, obs.lower, obs.upper)
                f = box_field
            elif type(obs) is OrientedBox:
                d, normal = obs.point(ee)
                f = box_field
            else:
                self._field(obs)                                # raises ValidationError
            if d < dists[0]:
                dists[0] = d
            if use_ee:
                a = f.acceleration(ee, xd_e, obs, d, normal)
                dx_e[0] += a[0]
                dx_e[1] += a[1]
                dx_e[2] += a[2]
        links = []
        stride = 3 * n
        for i, k in enumerate(self._n_moving):
            a0, a1, a2 = x[3 + 6 * i:6 + 6 * i]
            u0, u1, u2 = x[6 + 6 * i] - a0, x[7 + 6 * i] - a1, x[8 + 6 * i] - a2
            uu = u0 * u0 + u1 * u1 + u2 * u2
            best_d, best = math.inf, None
            for obs in obstacles:
                if type(obs) is Sphere:
                    c0, c1, c2 = obs.center
                    t = ((c0 - a0) * u0 + (c1 - a1) * u1 + (c2 - a2) * u2) / uu \
                        if uu > 0.0 else 0.0
                    t = 0.0 if t < 0.0 else (1.0 if t > 1.0 else t)
                    v0, v1, v2 = a0 + t * u0 - c0, a1 + t * u1 - c1, a2 + t * u2 - c2
                    r = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
                    d = r - obs.radius - radius
                    if d < best_d:
                        normal = (v0 / r, v1 / r, v2 / r) if r > 1e-12 else (0.0, 0.0, 1.0)
                        best_d, best = d, (obs, t, normal, sphere_field)
                else:
                    b = (a0 + u0, a1 + u1, a2 + u2)
                    if type(obs) is Box:
                        lo, hi = obs.lower, obs.upper
                        t = segment_box_scalar((a0, a1, a2), b, lo, hi)
                        d, _, normal = point_box((a0 + t * u0, a1 + t * u1, a2 + t * u2), lo, hi)
                    else:                                       # OrientedBox
                        t = obs.segment((a0, a1, a2), b)
                        d, normal = obs.point((a0 + t * u0, a1 + t * u1, a2 + t * u2))
                    d -= radius
                    if d < best_d:
                        best_d, best = d, (obs, t, normal, box_field)
            dists.append(best_d)
            if best is None:
                continue
            obs, t, normal, f = best
            p = (a0 + t * u0, a1 + t * u1, a2 + t * u2)
            base_a = (1 + 2 * i) * stride
            s = 1.0 - t
            lerp = [s * u + t * v for u, v in zip(jac[base_a:base_a + stride],
                                                  jac[base_a + stride:base_a + 2 * stride])]
            J_o = [lerp[0:k], lerp[n:n + k], lerp[2 * n:2 * n + k]]
            xd = self._velocity(J_o, qdl) if self._needs_velocity else (0.0, 0.0, 0.0)
            a = f.acceleration(p, xd, obs, best_d, normal)
            if a[0] or a[1] or a[2]:
                links.append((J_o, a))
        self.last_distances = dists
        if not links and not any(dx_e):
            return [0.0] * n
        scale = self._limit(ql) if self._limit is not None and links else None
        if self._axes == (0, 1, 2):
            return coupling_3d(rows_e, dx_e, links, self.config.damping, scale)
        ax = self._axes
        rows = [rows_e[a] for a in ax]
        links = [([list(J_o[a]) + [0.0] * (n - len(J_o[a])) for a in ax], [dx[a] for a in ax])
                 for J_o, dx in links]
        return scalar_coupling(rows, [dx_e[a] for a in ax], links, self.config.damping, scale)

    @staticmethod
    def to_internal(dq_dd: Sequence[float], xi: Optional[Sequence[float]], tau: float,
                    y_delta: Optional[Sequence[float]] = None,
                    floor: float = SATURATION_FLOOR) -> List[float]:
        """The coupling term ``P`` of the stepper (``stepper.input.coupling``).

        CDMP (``y_delta`` given): Eq. (29) at fixed ``(xi, xid)`` gives
        ``dxi_dd = dq_dd / (y_delta (1 - tanh(xi)^2))`` and Eq. (21) takes
        ``P = tau^2 dxi_dd``; DMP (``y_delta`` None): ``P = tau^2 dq_dd``. Where
        ``1 - tanh(xi)^2 >= floor`` this is ``TanhTransform.joint_accel_to_exogenous`` on plain
        floats.

        Cap near saturation: ``1 - tanh(xi)^2`` is floored at ``floor``, so
        ``|P| <= tau^2 |dq_dd| / (y_delta floor)``. Without it the divisor falls to ~2e-9 at the
        saturation bound ``XI_SAT``: a coupling that turns away from a limit the state was
        pushed into asks for an exogenous acceleration so large that ``xi`` crosses the whole
        range in one tick (a jump from one joint limit to the other; test_core_coupling.py).
        With the floor the coupling only acts attenuated, by ``(1 - tanh(xi)^2) / floor``,
        within ``1 - sqrt(1 - floor)`` (0.5 % for the default) of the half-range from a limit.
        ``floor = 0`` gives the uncapped map (divisor floored at 1e-300).
        """
        tau2 = tau * tau
        if y_delta is None:
            return [tau2 * a for a in dq_dd]
        tanh = math.tanh
        out = []
        for a, x, yd in zip(dq_dd, xi, y_delta):
            t = tanh(x)
            s = 1.0 - t * t
            if s < floor:
                s = floor
            out.append(tau2 * a / max(yd * s, 1e-300))
        return out


def joint_coupling(chain: Chain, q: ArrayLike, qd: Optional[ArrayLike],
                   obstacles: Sequence[Union[Sphere, Box]], links: Sequence = (),
                   sphere_field: Field = RepellerField(), box_field: Field = ConstantField(),
                   config: CouplingConfig = CouplingConfig()) -> NDArray[np.float64]:
    """One-shot :meth:`ObstacleCoupling.joint_acceleration` (builds the coupling each call;
    keep an :class:`ObstacleCoupling` for repeated use)."""
    coupling = ObstacleCoupling(chain, links, sphere_field, box_field, config)
    return np.array(coupling.joint_acceleration(q, qd, obstacles))
