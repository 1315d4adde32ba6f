"""The generator of the tick's obstacle coupling (paper 000, Eq. 7 and 12): one straight-line
Python module per chain and configuration.

:func:`compile_coupling` writes, once per chain, set of points and options, the whole
evaluation of :class:`~cdmp_ros.core.coupling.obstacle.ObstacleCoupling` for one configuration
on plain floats, as a module (:func:`cdmp_ros.core.generated.load_generated`: checked in for
the product's default configurations, else written into the kernel cache):

1. forward kinematics of the end effector and of the segment end points (the frame recursion of
   :mod:`cdmp_ros.core.kinematics.codegen`, constants folded); with velocity-dependent fields
   also their velocities ``J qd`` (with an end-effector task only, the end effector's);
2. a call ``gate(x, obstacles[, xd])`` (closest points and potential fields:
   :class:`~cdmp_ros.core.coupling.obstacle.ClosestPointGate`) that returns None when no field
   is active (then, without velocities, no Jacobian is computed at all) or the end-effector
   acceleration and, per link, the closest point ``p`` (world) and its acceleration;
3. the end-effector Jacobian and, per active link, the Jacobian ``J_o`` of the point ``p``
   rigidly attached to the link (columns ``z_j x (p - o_j)`` of the joints that move it only:
   the others are zero and are folded away); rows outside the chain's task axes are zero
   (planar chains: the plane's two rows, exactly the 2-row pseudo-inverses);
4. Eq. (7) and Eq. (12) with damped inverses (the undamped case inline, else
   :func:`inverse_h3`):
   with ``H = h(J J^T)``, ``K = J J_o^T``, ``W = H^-1 K``, the Gram matrix of
   ``J_o (I - J^+ J) = J_o - W^T J`` is ``J_o J_o^T - K^T W - W^T K + W^T (J J^T) W`` and
   ``(J_o N)^+ dx = J_o^T w - J^T (W w)`` with ``w = h(Gram)^-1 dx``;
5. near a joint limit (a joint's usage above ``limit_onset``, the comparison and the weights
   written inline), Eq. (12) in its limit-aware form ``D (J_o D (I - (J D)^+ J D))^+ dx`` with
   ``D^2 = diag(s)``: the same link block on the weighted Gram matrices ``J S J^T``,
   ``J S J_o^T``, ``J_o S J_o^T`` (``S = diag(s)``), its result ``S (J_o^T u - J^T W u)``
   accumulated apart from Eq. (7).

The damped pseudo-inverse (selective damping of small singular values)::

    M^+ = sum_i sigma_i / (sigma_i^2 + lambda_i^2) v_i u_i^T,
    lambda_i^2 = lambda_max^2 (1 - (sigma_i / epsilon)^2)   if sigma_i < epsilon, else 0

is ``M^+ = M^T h(A)^-1`` with ``A = M M^T`` and ``h(mu) = mu + lambda^2(mu)``, evaluated in
closed form (eigenvalues by the trigonometric formula, the projector on the damped eigenvalues
by Sylvester's formula). The limit weights (Chan and Dubey, IEEE T-RA 11(2), 1995)::

    u_i = (q_i - q_o,i) / y_delta_i,   rho_i = clip((|u_i| - u_on) / (u_lock - u_on), 0, 1),
    s_i = (1 - rho_i)^2 (1 + 2 rho_i)

test/coupling_oracle.py holds the numpy reference (SVD pseudo-inverses, batched) that the
tests compare every generated kernel with.
"""
import math
from typing import Callable, List, Optional, Sequence, Tuple

from cdmp_ros.core.generated import load_generated
from cdmp_ros.core.kinematics.codegen import (_Emitter, emit_frames, emit_jacobian, emit_point,
                                              literal, prune)

GENERATOR = 'cdmp_ros.core.coupling.kernel.compile_coupling'
#: What a generated coupling module imports besides math.
IMPORTS = ('from cdmp_ros.core.coupling.kernel import inverse_h3',)

_TWO_PI_3 = 2.0 * math.pi / 3.0


def inverse_h3(a00, a01, a02, a11, a12, a22, eps2, lam2):
    """``(h(A)^-1, damped)``: the inverse of the damped Gram matrix (module docstring) as a
    row-major 9-tuple, for a symmetric positive semi-definite 3x3 ``A``, and whether any
    eigenvalue was damped. The generated kernels inline the undamped case and call this one
    otherwise.

    Undamped (the plain inverse) when the cheap bound ``mu_min >= 4 det(A) / tr(A)^2`` already
    clears ``eps2``; otherwise ``h(A) = x A + y I + z P`` in closed form, with the eigenvalues
    of the trigonometric formula and ``P`` the projector of the isolated eigenvalue
    (Sylvester: ``P = (A - a I)(A - b I) / ((mu_g - a)(mu_g - b))``)."""
    c00 = a11 * a22 - a12 * a12
    c01 = a02 * a12 - a01 * a22
    c02 = a01 * a12 - a02 * a11
    det = a00 * c00 + a01 * c01 + a02 * c02
    tr = a00 + a11 + a22
    damped = False
    if not (det > 0.0 and 4.0 * det >= eps2 * tr * tr):
        q = tr / 3.0
        b00, b11, b22 = a00 - q, a11 - q, a22 - q
        p2 = b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * (a01 * a01 + a02 * a02 + a12 * a12)
        if p2 <= 1e-300:
            mu0 = mu1 = mu2 = q
        else:
            p = math.sqrt(p2 / 6.0)
            r = (b00 * (b11 * b22 - a12 * a12) - a01 * (a01 * b22 - a12 * a02)
                 + a02 * (a01 * a12 - b11 * a02)) / (2.0 * p * p * p)
            phi = math.acos(-1.0 if r < -1.0 else (1.0 if r > 1.0 else r)) / 3.0
            mu2 = q + 2.0 * p * math.cos(phi)
            mu0 = q + 2.0 * p * math.cos(phi + _TWO_PI_3)
            mu1 = 3.0 * q - mu0 - mu2
        if mu0 < eps2:
            damped = True
            if mu2 < eps2:
                x, y, z = 1.0 - lam2 / eps2, lam2, 0.0
                ea = eb = den = 1.0
            elif mu1 < eps2:
                x, y, z = 1.0 - lam2 / eps2, lam2, lam2 * (mu2 / eps2 - 1.0)
                ea, eb, den = mu0, mu1, (mu2 - mu0) * (mu2 - mu1)
            else:
                x, y, z = 1.0, 0.0, lam2 * (1.0 - mu0 / eps2)
                ea, eb, den = mu1, mu2, (mu0 - mu1) * (mu0 - mu2)
            if z:
                z /= den
                ab, sab = ea * eb, ea + eb
                p00 = a00 * a00 + a01 * a01 + a02 * a02 - sab * a00 + ab
                p11 = a01 * a01 + a11 * a11 + a12 * a12 - sab * a11 + ab
                p22 = a02 * a02 + a12 * a12 + a22 * a22 - sab * a22 + ab
                p01 = a00 * a01 + a01 * a11 + a02 * a12 - sab * a01
                p02 = a00 * a02 + a01 * a12 + a02 * a22 - sab * a02
                p12 = a01 * a02 + a11 * a12 + a12 * a22 - sab * a12
            else:
                p00 = p11 = p22 = p01 = p02 = p12 = 0.0
            a00, a11, a22 = x * a00 + y + z * p00, x * a11 + y + z * p11, x * a22 + y + z * p22
            a01, a02, a12 = x * a01 + z * p01, x * a02 + z * p02, x * a12 + z * p12
            c00 = a11 * a22 - a12 * a12
            c01 = a02 * a12 - a01 * a22
            c02 = a01 * a12 - a02 * a11
            det = a00 * c00 + a01 * c01 + a02 * c02
    inv = 1.0 / det
    c00 *= inv
    c01 *= inv
    c02 *= inv
    c11 = (a00 * a22 - a02 * a02) * inv
    c12 = (a01 * a02 - a00 * a12) * inv
    c22 = (a00 * a11 - a01 * a01) * inv
    return (c00, c01, c02, c01, c11, c12, c02, c12, c22), damped


_LINK_TEMPLATE = '''\
# W = H^-1 K
w00 = h00 * {k00} + h01 * {k10} + h02 * {k20}
w01 = h00 * {k01} + h01 * {k11} + h02 * {k21}
w02 = h00 * {k02} + h01 * {k12} + h02 * {k22}
w10 = h01 * {k00} + h11 * {k10} + h12 * {k20}
w11 = h01 * {k01} + h11 * {k11} + h12 * {k21}
w12 = h01 * {k02} + h11 * {k12} + h12 * {k22}
w20 = h02 * {k00} + h12 * {k10} + h22 * {k20}
w21 = h02 * {k01} + h12 * {k11} + h22 * {k21}
w22 = h02 * {k02} + h12 * {k12} + h22 * {k22}
m00 = {k00} * w00 + {k10} * w10 + {k20} * w20
m01 = {k00} * w01 + {k10} * w11 + {k20} * w21
m02 = {k00} * w02 + {k10} * w12 + {k20} * w22
m11 = {k01} * w01 + {k11} * w11 + {k21} * w21
m12 = {k01} * w02 + {k11} * w12 + {k21} * w22
m22 = {k02} * w02 + {k12} * w12 + {k22} * w22
s00 = {g00} - m00
s01 = {g01} - m01
s02 = {g02} - m02
s11 = {g11} - m11
s12 = {g12} - m12
s22 = {g22} - m22
if damped:
    y00 = a00 * w00 + a01 * w10 + a02 * w20
    y01 = a00 * w01 + a01 * w11 + a02 * w21
    y02 = a00 * w02 + a01 * w12 + a02 * w22
    y10 = a01 * w00 + a11 * w10 + a12 * w20
    y11 = a01 * w01 + a11 * w11 + a12 * w21
    y12 = a01 * w02 + a11 * w12 + a12 * w22
    y20 = a02 * w00 + a12 * w10 + a22 * w20
    y21 = a02 * w01 + a12 * w11 + a22 * w21
    y22 = a02 * w02 + a12 * w12 + a22 * w22
    s00 += w00 * y00 + w10 * y10 + w20 * y20 - m00
    s11 += w01 * y01 + w11 * y11 + w21 * y21 - m11
    s22 += w02 * y02 + w12 * y12 + w22 * y22 - m22
    s01 += (w00 * y01 + w10 * y11 + w20 * y21
            - (w00 * {k01} + w10 * {k11} + w20 * {k21}))
    s02 += (w00 * y02 + w10 * y12 + w20 * y22
            - (w00 * {k02} + w10 * {k12} + w20 * {k22}))
    s12 += (w01 * y02 + w11 * y12 + w21 * y22
            - (w01 * {k02} + w11 * {k12} + w21 * {k22}))
{inverse_s}
u0 = g00 * {d0} + g01 * {d1} + g02 * {d2}
u1 = g01 * {d0} + g11 * {d1} + g12 * {d2}
u2 = g02 * {d0} + g12 * {d1} + g22 * {d2}
{c}0 -= w00 * u0 + w01 * u1 + w02 * u2
{c}1 -= w10 * u0 + w11 * u1 + w12 * u2
{c}2 -= w20 * u0 + w21 * u1 + w22 * u2
'''

# inverse_h3 with its undamped branch inlined (the same operations)
_INVERSE_TEMPLATE = '''\
i00 = {a}11 * {a}22 - {a}12 * {a}12
i01 = {a}02 * {a}12 - {a}01 * {a}22
i02 = {a}01 * {a}12 - {a}02 * {a}11
det = {a}00 * i00 + {a}01 * i01 + {a}02 * i02
tr = {a}00 + {a}11 + {a}22
if det > 0.0 and 4.0 * det >= eps2 * tr * tr:
    inv = 1.0 / det
    {h}00 = i00 * inv
    {h}01 = i01 * inv
    {h}02 = i02 * inv
    {h}11 = ({a}00 * {a}22 - {a}02 * {a}02) * inv
    {h}12 = ({a}01 * {a}02 - {a}00 * {a}12) * inv
    {h}22 = ({a}00 * {a}11 - {a}01 * {a}01) * inv
    {damped} = False
else:
    ({h}00, {h}01, {h}02, _, {h}11, {h}12, _, _, {h}22), {damped} = inverse_h3(
        {a}00, {a}01, {a}02, {a}11, {a}12, {a}22, eps2, lam2)'''

_EE_INVERSE = _INVERSE_TEMPLATE.format(a='a', h='h', damped='damped')
_EE_APPLY = '''\
c0 = h00 * {e0} + h01 * {e1} + h02 * {e2}
c1 = h01 * {e0} + h11 * {e1} + h12 * {e2}
c2 = h02 * {e0} + h12 * {e1} + h22 * {e2}'''


def _indented(text: str, indent: str) -> List[str]:
    return [indent + line for line in text.splitlines()]


def _dot(em: _Emitter, u: Sequence, v: Sequence) -> str:
    """Emit ``u . v`` and return its source text (a name or a constant)."""
    return literal(em.sum([(1.0, a, b) for a, b in zip(u, v)]))


def _task_rows(cols, axes: Sequence[int]) -> list:
    """The 3 rows of the Jacobian with columns ``cols``; rows outside ``axes`` are zero."""
    return [[col[r] if r in axes else 0.0 for col in cols] for r in range(3)]


def _emit_links(em: _Emitter, Rs, ps, prismatic, segments, SJ, J, sn, c: str, indent: str,
                axes: Sequence[int]) -> int:
    """Emit the link blocks of Eq. (12), one ``if l{i}:`` block per segment.

    ``SJ``: the rows of ``J S`` (``J`` itself when unweighted), ``sn``: the ``s_i`` (names or
    the constant 1.0; None when unweighted), ``c``: prefix of the accumulators of
    ``-J^T W u``. ``acc{k}`` accumulate ``J_o^T u`` (initialised here); returns their
    number."""
    n = len(prismatic)
    n_acc = min(max((k for k, _, _ in segments), default=0), n)
    if n_acc:
        em.lines.append(f'{indent}{" = ".join(f"acc{k}" for k in range(n_acc))} = 0.0')
    top = em.cache
    inner = indent + '    '
    for i, (k, _, _) in enumerate(segments):
        em.lines.append(f'{indent}if l{i}:')
        em.indent = inner
        em.cache = dict(top)                  # names of this block stay in this block
        p = [f'p{i}_{r}' for r in range(3)]
        ocols = emit_jacobian(em, Rs, ps, prismatic, k, p)[:min(k, n)]
        Jo = _task_rows(ocols, axes)
        SJo = Jo if sn is None else [[em.sum([(1.0, sn[j], v)]) for j, v in enumerate(row)]
                                     for row in Jo]
        fmt = {f'd{r}': f'd{i}_{r}' if r in axes else '0.0' for r in range(3)}
        fmt['c'] = c
        for r in range(3):
            for t in range(3):
                fmt[f'k{r}{t}'] = _dot(em, SJ[r][:len(ocols)], Jo[t])
        for r in range(3):
            for t in range(r, 3):
                fmt[f'g{r}{t}'] = _dot(em, SJo[r], Jo[t])
        fmt['inverse_s'] = _INVERSE_TEMPLATE.format(a='s', h='g', damped='_')
        em.lines += _indented(_LINK_TEMPLATE.format(**fmt), inner)
        for j in range(len(ocols)):
            term = em.sum([(1.0, f'u{r}', Jo[r][j]) for r in range(3)])
            if not isinstance(term, float):
                em.lines.append(f'{inner}acc{j} += {term}')
        em.indent = indent
    em.cache = top
    return n_acc


def _joint_terms(prefix: str, J, c: int, n_acc: int) -> list:
    """Terms of joint c of ``J^T {prefix}`` (+ ``acc{c}``, the ``J_o^T u`` sums, for
    ``c < n_acc``)."""
    terms = [(1.0, f'{prefix}{r}', J[r][c]) for r in range(3)]
    if c < n_acc:
        terms.append((1.0, f'acc{c}', 1.0))
    return terms


def _limit_weights(lower: Sequence[float], upper: Sequence[float], onset: float,
                   lock: float) -> Tuple[List[str], List[str], List]:
    """The inline limit-aware weights (module docstring): ``(outside, lines, sn)`` with
    ``outside`` the comparisons that start the weighting, ``lines`` the computation of the
    weights ``sw<k>`` and ``sn`` per joint the name ``sw<k>`` or the constant 1.0 (a joint
    without finite limits)."""
    outside, lines, sn = [], [], []
    inv_width = 1.0 / (float(lock) - float(onset))
    for k, (lo, hi) in enumerate(zip(lower, upper)):
        lo, hi = float(lo), float(hi)
        if not (math.isfinite(lo) and math.isfinite(hi)):
            sn.append(1.0)
            continue
        centre, delta = 0.5 * (lo + hi), 0.5 * (hi - lo)
        outside += [f'q{k} < {centre - onset * delta!r}', f'q{k} > {centre + onset * delta!r}']
        lines += [f'rho = (abs(q{k} - {centre!r}) * {1.0 / delta!r} - {float(onset)!r})'
                  f' * {inv_width!r}',
                  'w = 1.0 - rho',
                  f'sw{k} = 1.0 if rho <= 0.0 else (0.0 if rho >= 1.0 else '
                  'w * w * (1.0 + 2.0 * rho))']
        sn.append(f'sw{k}')
    return outside, lines, sn


def compile_coupling(B, base, prismatic, ee: Tuple[int, Sequence[float]],
                     segments: Sequence[Tuple[int, Sequence[float], Sequence[float]]],
                     axes: Sequence[int] = (0, 1, 2),
                     limits: Optional[Tuple[Sequence[float], Sequence[float], float, float]]
                     = None, velocity=False, title: str = 'Obstacle coupling',
                     description: str = '') -> Callable:
    """Generate ``coupled(q, qd, gate, obstacles, eps2, lam2) -> list of n_dofs floats or
    None`` as a module (module docstring).

    Parameters
    ----------
    B, base, prismatic
        The chain's internal frames (as :func:`cdmp_ros.core.kinematics.codegen.compile_kernel`).
    ee : (frame, coords)
        Internal frame and coordinates of the end-effector point.
    segments : sequence of (frame, start, end)
        Internal frame of each link segment and its end points in that frame.
    axes : sequence of int
        The chain's task axes (``Chain.task_axes``); the other Jacobian rows are zero.
    limits : (lower, upper, onset, lock), optional
        Joint limits and the limit usages where the limit-aware weighting of Eq. (12) starts
        and where it no longer moves a joint; None: Eq. (12) as is.
    velocity : {False, 'ee', 'all'}
        ``'all'`` (fields that depend on the velocity): ``gate`` also receives the velocities
        ``xd`` of every point (same layout as ``x``) computed from ``qd``; ``'ee'`` (an
        end-effector task only): ``xd`` holds the end effector's velocity alone (3 values).
    title, description : str
        The generated module's first line and its description of the configuration.

    Returns
    -------
    coupled : callable
        ``coupled(q, qd, gate, obstacles, eps2, lam2)`` with ``q`` (and, with ``velocity``,
        ``qd``) lists of n_dofs floats. ``gate(x, obstacles[, xd])`` receives the world
        positions ``x`` (list of 3 + 6 n_links floats: end effector, then start and end of
        every segment) and returns None (no active field: ``coupled`` returns None) or the
        flat tuple ``(e0, e1, e2, l_0, p_00, p_01, p_02, d_00, d_01, d_02, l_1, ...)``: the
        end-effector acceleration ``e``, and per link a flag ``l_i`` (field active), the
        closest point ``p_i`` on the link (world) and its acceleration ``d_i``. ``eps2`` and
        ``lam2`` are ``epsilon^2`` and ``lambda_max^2`` of the damping. The result is
        ``J^+ e + sum_i (J_o,i (I - J^+ J))^+ d_i`` (Eq. 7 + Eq. 12, paper 000), in the
        limit-aware form near a limit. ``coupled.source`` is the generated source,
        ``coupled.path`` the module's file.
    """
    n = len(prismatic)
    axes = tuple(int(a) for a in axes)
    em = _Emitter()
    qn = [f'q{k}' for k in range(n)]
    em.lines.append(f'    {", ".join(qn)}, = q')
    Rs, ps = emit_frames(em, B, base, prismatic, qn)
    x_ee = emit_point(em, Rs, ps, ee[0], ee[1])
    points = [(ee[0], x_ee)]
    for k, start, end in segments:
        points += [(k, emit_point(em, Rs, ps, k, start)), (k, emit_point(em, Rs, ps, k, end))]
    xs = [v for _, x in points for v in x]
    gate_args = '[' + ', '.join(literal(v) for v in xs) + '], obstacles'
    if velocity:                      # xd = J qd of the points, for the fields or ee_task
        qdn = [f'qd{k}' for k in range(n)]
        em.lines.append(f'    {", ".join(qdn)}, = qd')
        xds = []
        for k, x in (points if velocity == 'all' else points[:1]):
            cols = emit_jacobian(em, Rs, ps, prismatic, k, x)
            xds += [em.sum([(1.0, col[r], qdn[j]) for j, col in enumerate(cols)])
                    for r in range(3)]
        gate_args += ', [' + ', '.join(literal(v) for v in xds) + ']'
    em.lines.append(f'    r = gate({gate_args})')
    em.lines.append('    if r is None:')
    em.lines.append('        return None')
    names = ['e0', 'e1', 'e2']
    for i in range(len(segments)):
        names += [f'l{i}'] + [f'p{i}_{c}' for c in range(3)] + [f'd{i}_{c}' for c in range(3)]
    em.lines.append(f'    {", ".join(names)}, = r')
    # Eq. (7), paper 000: J^+ e with J^+ = J^T h(J J^T)^-1
    J = _task_rows(emit_jacobian(em, Rs, ps, prismatic, ee[0], x_ee), axes)
    for i in range(3):
        for j in range(i, 3):
            em.lines.append(f'    a{i}{j} = {_dot(em, J[i], J[j])}')
    em.lines += _indented(_EE_INVERSE, '    ')
    e = {f'e{r}': f'e{r}' if r in axes else '0.0' for r in range(3)}
    em.lines += _indented(_EE_APPLY.format(**e), '    ')
    # limit-aware Eq. (12): S = diag(s), J S J^T rebinds a, h, damped (Eq. 7 is in c0..c2)
    outside, weights, sn = (_limit_weights(*limits) if limits is not None and segments
                            else ([], [], []))
    if outside:
        top = em.cache
        em.lines.append(f'    near_limit = {" or ".join(outside)}')
        em.lines.append('    if near_limit:')
        em.lines += _indented('\n'.join(weights), '        ')
        em.indent = '        '
        em.cache = dict(top)
        SJ = [[em.sum([(1.0, sn[c], J[i][c])]) for c in range(n)] for i in range(3)]
        for i in range(3):
            for j in range(i, 3):
                em.lines.append(f'        a{i}{j} = {_dot(em, SJ[i], J[j])}')
        em.lines += _indented(_EE_INVERSE, '        ')
        em.lines.append('        b0 = b1 = b2 = 0.0')
        n_acc_w = _emit_links(em, Rs, ps, prismatic, segments, SJ, J, sn, 'b', '        ',
                              axes)
        out = [literal(em.sum(_joint_terms('c', J, c, 0)
                              + [(1.0, sn[c], em.sum(_joint_terms('b', J, c, n_acc_w)))]))
               for c in range(n)]
        em.lines.append(f'        return [{", ".join(out)}]')
        em.indent = '    '
        em.cache = top
    # Eq. (12), paper 000, per active link
    n_acc = _emit_links(em, Rs, ps, prismatic, segments, J, J, None, 'c', '    ', axes)
    out = [literal(em.sum(_joint_terms('c', J, c, n_acc))) for c in range(n)]
    body = '\n'.join(prune(em.lines + [f'    return [{", ".join(out)}]']))
    source = f'def coupled(q, qd, gate, obstacles, eps2, lam2):\n{body}\n'
    return load_generated(source, 'coupled', title, description, GENERATOR, IMPORTS)
