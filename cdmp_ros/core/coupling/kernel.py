"""Generated single-configuration obstacle coupling (paper 000, Eq. 7 and Eq. 12).

:func:`compile_coupling` generates, once per chain and set of link segments, one straight-line
Python function that evaluates the whole coupling of :class:`~cdmp_ros.core.coupling.obstacle.
ObstacleCoupling` for one configuration on plain floats:

1. forward kinematics of the end effector and of the segment end points (the frame recursion of
   :mod:`cdmp_ros.core.kinematics.codegen`, constants folded);
2. a call ``gate(x, obstacles)`` (closest points and potential fields:
   :class:`~cdmp_ros.core.coupling.obstacle.ClosestPointGate`, the one closest-point routine of
   the coupling) that returns None when no field is active (then no Jacobian is computed at all) or
   the end-effector acceleration and, per link, the closest point ``p`` (world) and its
   acceleration;
3. the end-effector Jacobian and, per active link, the Jacobian ``J_o`` of the point ``p``
   rigidly attached to the link (columns ``z_j x (p - o_j)`` of the joints that move it only:
   the others are zero and are folded away);
4. Eq. (7) and Eq. (12) with the damped inverses of :func:`cdmp_ros.core.coupling.terms.
   _inverse_h3`, exactly as :func:`cdmp_ros.core.coupling.terms.coupling_3d` (same formulas, with
   every 3-vector and 3x3 matrix held in local variables, and the dot products unrolled);
5. near a joint limit (``limit(q)`` returns the inverse weights ``s``, module docstring of
   :mod:`cdmp_ros.core.coupling.terms`), Eq. (12) in its limit-aware form
   ``D (J_o D (I - (J D)^+ J D))^+ dx`` with ``D^2 = diag(s)``: the same link block on the
   weighted Gram matrices ``J S J^T``, ``J S J_o^T``, ``J_o S J_o^T`` (``S = diag(s)``), its
   result ``S (J_o^T u - J^T W u)`` accumulated apart from Eq. (7).

The arithmetic is that of the reference paths up to the order of floating-point summation
(test/test_core_coupling.py compares it with the batched numpy reference and with
:func:`~cdmp_ros.core.coupling.terms.coupling_3d`). The generated source is kept in
``coupled.source``.
"""
import math
from typing import Callable, List, Optional, Sequence, Tuple

from cdmp_ros.core.coupling.terms import _inverse_h3
from cdmp_ros.core.kinematics.codegen import (_Emitter, build, emit_frames, emit_jacobian,
                                              emit_point, literal, prune)

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

# _inverse_h3 with its undamped branch inlined (the same operations)
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

_EE_TEMPLATE = _INVERSE_TEMPLATE.format(a='a', h='h', damped='damped') + '''
c0 = h00 * e0 + h01 * e1 + h02 * e2
c1 = h01 * e0 + h11 * e1 + h12 * e2
c2 = h02 * e0 + h12 * e1 + h22 * e2
'''


def _indented(text: str, indent: str) -> List[str]:
    return [indent + line for line in text.splitlines()]


def _dot(em: _Emitter, u: Sequence, v: Sequence) -> str:
    """Emit ``u . v`` and return its source text (a name or a constant)."""
    return literal(em.sum([(1.0, a, b) for a, b in zip(u, v)]))


def _emit_links(em: _Emitter, Rs, ps, prismatic, segments, SJ, J, sn: Optional[List[str]],
                c: str, indent: str) -> int:
    """Emit the link blocks of Eq. (12), one ``if l{i}:`` block per segment.

    ``SJ``: the rows of ``J S`` (``J`` itself when unweighted), ``sn``: the names of the
    ``s_i`` (None when unweighted), ``c``: prefix of the accumulators of ``-J^T W u``.
    ``acc{k}`` accumulate ``J_o^T u`` (initialised here); returns their number."""
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
        Jo = [[col[r] for col in ocols] for r in range(3)]
        SJo = Jo if sn is None else [[em.sum([(1.0, sn[j], v)]) for j, v in enumerate(row)]
                                     for row in Jo]
        fmt = {f'd{r}': f'd{i}_{r}' for r in range(3)}
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


def compile_coupling(B, base, prismatic, ee: Tuple[int, Sequence[float]],
                     segments: Sequence[Tuple[int, Sequence[float], Sequence[float]]],
                     limit_bounds: Optional[Sequence[Tuple[float, float]]] = None
                     ) -> Callable:
    """Generate ``coupled(q, gate, obstacles, eps2, lam2, limit=None) -> list of n_dofs floats
    or None``.

    Parameters
    ----------
    B, base, prismatic
        The chain's internal frames (as :func:`cdmp_ros.core.kinematics.codegen.compile_kernel`).
    ee : (frame, coords)
        Internal frame and coordinates of the end-effector point.
    segments : sequence of (frame, start, end)
        Internal frame of each link segment and its end points in that frame.
    limit_bounds : sequence of n_dofs (low, high), optional
        ``LimitScale.bounds`` of the ``limit`` that will be passed: ``limit(q)`` is then only
        called when some ``q_i`` is outside its bounds (the comparison is generated inline).

    Returns
    -------
    coupled : callable
        ``coupled(q, gate, obstacles, eps2, lam2)``. ``gate(x, obstacles)`` receives the
        world positions ``x`` (list of 3 + 6 n_links floats: end effector, then start and end
        of every segment) and returns None (no active field: ``coupled`` returns None) or the
        flat tuple ``(e0, e1, e2, l_0, p_00, p_01, p_02, d_00, d_01, d_02, l_1, ...)``: the
        end-effector acceleration ``e``, and per link a flag ``l_i`` (field active), the
        closest point ``p_i`` on the link (world) and its acceleration ``d_i``. ``eps2`` and
        ``lam2`` are ``epsilon^2`` and ``lambda_max^2`` of the damping. The result is
        ``J^+ e + sum_i (J_o,i (I - J^+ J))^+ d_i`` (Eq. 7 + Eq. 12, paper 000). ``limit``
        (a :class:`~cdmp_ros.core.coupling.terms.LimitScale`), called with ``q`` once a field is
        active, returns None (Eq. 12 as is) or the inverse weights ``s`` of the limit-aware
        Eq. (12), ``sum_i D (J_o,i D (I - (J D)^+ J D))^+ d_i`` with ``D^2 = diag(s)``.
    """
    n = len(prismatic)
    em = _Emitter()
    qn = [f'q{k}' for k in range(n)]
    em.lines.append(f'    {", ".join(qn)}, = q')
    Rs, ps = emit_frames(em, B, base, prismatic, qn)
    x_ee = emit_point(em, Rs, ps, ee[0], ee[1])
    xs = list(x_ee)
    for k, start, end in segments:
        xs += emit_point(em, Rs, ps, k, start)
        xs += emit_point(em, Rs, ps, k, end)
    em.lines.append(f'    r = gate([{", ".join(literal(v) for v in xs)}], obstacles)')
    em.lines.append('    if r is None:')
    em.lines.append('        return None')
    names = ['e0', 'e1', 'e2']
    for i in range(len(segments)):
        names += [f'l{i}'] + [f'p{i}_{c}' for c in range(3)] + [f'd{i}_{c}' for c in range(3)]
    em.lines.append(f'    {", ".join(names)}, = r')
    # Eq. (7), paper 000: J^+ e with J^+ = J^T h(J J^T)^-1
    cols = emit_jacobian(em, Rs, ps, prismatic, ee[0], x_ee)
    J = [[col[i] for col in cols] for i in range(3)]
    A = {}
    for i in range(3):
        for j in range(i, 3):
            A[f'a{i}{j}'] = _dot(em, J[i], J[j])
    em.lines += [f'    a{key[1:]} = {val}' for key, val in A.items()]
    em.lines += _indented(_EE_TEMPLATE, '    ')
    # limit-aware Eq. (12): S = diag(s), J S J^T rebinds a, h, damped (Eq. 7 is in c0..c2)
    top = em.cache
    outside = ' or '.join(
        part for k, (lo_k, hi_k) in enumerate(limit_bounds or ())
        for part in ((f'q{k} < {lo_k!r}' if math.isfinite(lo_k) else ''),
                     (f'q{k} > {hi_k!r}' if math.isfinite(hi_k) else '')) if part)
    if limit_bounds is None:
        em.lines.append('    s = limit(q) if limit is not None else None')
    elif outside:
        em.lines.append(f'    s = limit(q) if limit is not None and ({outside}) else None')
    else:
        em.lines.append('    s = None')
    em.lines.append('    if s is not None:')
    em.indent = '        '
    em.cache = dict(top)
    sn = [f'sw{c}' for c in range(n)]
    em.lines.append(f'        {", ".join(sn)}, = s')
    SJ = [[em.sum([(1.0, sn[c], J[i][c])]) for c in range(n)] for i in range(3)]
    for i in range(3):
        for j in range(i, 3):
            em.lines.append(f'        a{i}{j} = {_dot(em, SJ[i], J[j])}')
    em.lines += _indented(_EE_TEMPLATE.split('\nc0 = ')[0], '        ')
    em.lines.append('        b0 = b1 = b2 = 0.0')
    n_acc_w = _emit_links(em, Rs, ps, prismatic, segments, SJ, J, sn, 'b', '        ')
    out = [literal(em.sum(_joint_terms('c', J, c, 0)
                          + [(1.0, sn[c], em.sum(_joint_terms('b', J, c, n_acc_w)))]))
           for c in range(n)]
    em.lines.append(f'        return [{", ".join(out)}]')
    em.indent = '    '
    em.cache = top
    # Eq. (12), paper 000, per active link
    n_acc = _emit_links(em, Rs, ps, prismatic, segments, J, J, None, 'c', '    ')
    out = [literal(em.sum(_joint_terms('c', J, c, n_acc))) for c in range(n)]
    body = '\n'.join(prune(em.lines + [f'    return [{", ".join(out)}]']))
    source = f'def coupled(q, gate, obstacles, eps2, lam2, limit=None):\n{body}\n'
    return build(source, 'coupled', {'cos': math.cos, 'sin': math.sin,
                                     'inverse_h3': _inverse_h3})
