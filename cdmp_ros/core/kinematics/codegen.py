"""Single-configuration forward kinematics and Jacobians on plain Python floats.

For one 7-DoF configuration numpy's per-call overhead (about 1 us per ufunc) dominates the
arithmetic (../shared/design.md, Numerics notes). This module therefore generates, once per
chain and set of points, a straight-line Python function of the joint positions that performs
exactly the recursion of :meth:`Chain._frames` on scalar floats, with the constant transforms
folded in: products with constant 0 are dropped and products with constant +-1 become
(negated) copies. For the Panda, whose joint origins are rotations by +-pi/2 about x, this
turns each constant rotation into a renaming of columns. Every kernel is a module in a file
(:func:`cdmp_ros.core.generated.load_generated`); its source is kept in ``kernel.source``;
test/test_core_kinematics.py checks the kernels against the batched numpy path.
"""
import re
from collections import Counter
from typing import Callable, Dict, List, Sequence, Tuple, Union

from cdmp_ros.core.generated import load_generated

Value = Union[float, str]


class _Emitter:
    """Builds straight-line code; values are float constants or variable names.

    Identical expressions are emitted once (``cache``: expression -> name; a caller that
    opens a conditional block saves and restores it around the block)."""

    def __init__(self):
        self.lines: List[str] = []
        self.count = 0
        self.indent = '    '
        self.cache: Dict[str, str] = {}
        self.negated: Dict[str, str] = {}            # name of -v -> v

    def sum(self, terms: Sequence[Tuple[float, Value, Value]]) -> Value:
        """Emit ``sum(sign * a * b)``, folding constants; return a constant or a name."""
        const = 0.0
        parts = []
        for sign, a, b in terms:
            if isinstance(a, float) and isinstance(b, float):
                const += sign * a * b
                continue
            if isinstance(a, float):
                a, b = b, a
            if isinstance(b, float):
                if b == 0.0:
                    continue
                if b == 1.0 or b == -1.0:
                    parts.append((sign * b, a))
                    continue
                parts.append((sign, f'{a} * {b!r}'))
            else:
                parts.append((sign, f'{a} * {b}'))
        if not parts:
            return const
        if len(parts) == 1 and const == 0.0 and ' ' not in parts[0][1]:
            sign, name = parts[0]
            if sign == 1.0:
                return name
            if name in self.negated:                 # -(-v) = v
                return self.negated[name]
            neg = self.assign(f'-{name}')
            self.negated[neg] = name
            return neg
        expr = ''
        for sign, text in parts:
            if not expr:
                expr = text if sign > 0 else f'-{text}'
            else:
                expr += f' + {text}' if sign > 0 else f' - {text}'
        if const != 0.0:
            expr += f' + {const!r}'
        return self.assign(expr)

    def assign(self, expr: str) -> str:
        name = self.cache.get(expr)
        if name is None:
            name = self.cache[expr] = f'v{self.count}'
            self.count += 1
            self.lines.append(f'{self.indent}{name} = {expr}')
        return name


_ASSIGN = re.compile(r'^\s+(v\d+) = ')
_NAME = re.compile(r'\bv\d+\b')


def prune(lines: List[str]) -> List[str]:
    """Drop the generated assignments ``vN = ...`` whose value is never used."""
    while True:
        uses = Counter(_NAME.findall('\n'.join(lines)))
        keep = [line for line in lines
                if not ((m := _ASSIGN.match(line)) and uses[m.group(1)] == 1)]
        if len(keep) == len(lines):
            return lines
        lines = keep


def emit_frames(em: _Emitter, B, base, prismatic, qn: Sequence[str]):
    """Emit the frame recursion of :meth:`Chain._frames`; returns the rotations ``Rs`` and
    origins ``ps`` of internal frames 0..n_dofs (3x3 and 3 lists of values)."""
    R = [[float(base[i, j]) for j in range(3)] for i in range(3)]
    p = [float(base[i, 3]) for i in range(3)]
    Rs, ps = [R], [p]
    for k in range(len(prismatic)):
        b = B[k]
        p = [em.sum([(1.0, p[i], 1.0)] + [(1.0, R[i][m], float(b[m, 3])) for m in range(3)])
             for i in range(3)]
        M = [[em.sum([(1.0, R[i][m], float(b[m, j])) for m in range(3)]) for j in range(3)]
             for i in range(3)]
        if prismatic[k]:
            p = [em.sum([(1.0, p[i], 1.0), (1.0, M[i][2], qn[k])]) for i in range(3)]
            R = M
        else:
            c = em.assign(f'cos({qn[k]})')
            s = em.assign(f'sin({qn[k]})')
            R = [[em.sum([(1.0, M[i][0], c), (1.0, M[i][1], s)]),
                  em.sum([(1.0, M[i][1], c), (-1.0, M[i][0], s)]),
                  M[i][2]] for i in range(3)]
        Rs.append(R)
        ps.append(p)
    return Rs, ps


def emit_point(em: _Emitter, Rs, ps, k: int, coords) -> List[Value]:
    """Emit the world position of the point with coordinates ``coords`` in frame ``k``."""
    c = [float(v) for v in coords]
    return [em.sum([(1.0, ps[k][i], 1.0)] + [(1.0, Rs[k][i][m], c[m]) for m in range(3)])
            for i in range(3)]


def emit_jacobian(em: _Emitter, Rs, ps, prismatic, k: int, x: Sequence[Value]
                  ) -> List[Tuple[Value, Value, Value]]:
    """Emit the Jacobian columns (n_dofs 3-tuples) of the world point ``x`` rigidly attached
    to internal frame ``k``: ``z_j x (x - p_j)`` (revolute) or ``z_j`` (prismatic), zero for
    the joints at or after ``k``."""
    cols = []
    for j in range(len(prismatic)):
        if j >= k:
            cols.append((0.0, 0.0, 0.0))
            continue
        z = [Rs[j + 1][i][2] for i in range(3)]
        if prismatic[j]:
            cols.append(tuple(z))
            continue
        d = [em.sum([(1.0, x[i], 1.0), (-1.0, ps[j + 1][i], 1.0)]) for i in range(3)]
        cols.append((em.sum([(1.0, z[1], d[2]), (-1.0, z[2], d[1])]),
                     em.sum([(1.0, z[2], d[0]), (-1.0, z[0], d[2])]),
                     em.sum([(1.0, z[0], d[1]), (-1.0, z[1], d[0])])))
    return cols


def literal(v: Value) -> str:
    """Source text of a value (a float constant or a variable name)."""
    return repr(v) if isinstance(v, float) else v


def compile_kernel(B, base, prismatic, frames: Sequence[int], coords, description: str = ''
                   ) -> Callable[[Sequence[float]], Tuple[List[float], List[float]]]:
    """Generate the scalar kernel ``kernel(q) -> (x, jac)`` of a chain and a set of points.

    Parameters
    ----------
    B : ndarray (n_dofs, 4, 4)
        Constant transforms of the internal frames (see :mod:`.chain`).
    base : ndarray (4, 4)
        World pose of internal frame 0.
    prismatic : sequence of bool (n_dofs)
    frames : sequence of int (n_points)
        Internal frame of each point.
    coords : array-like (n_points, 3)
        Coordinates of each point in its internal frame.
    description : str
        The chain and points, for the header of the generated module
        (:func:`cdmp_ros.core.generated.load_generated`).

    Returns
    -------
    kernel : callable
        ``kernel(q)`` with ``q`` a sequence of n_dofs floats returns ``x``, a list of
        3 * n_points floats (row-major (n_points, 3)) and ``jac``, a list of
        n_points * 3 * n_dofs floats (row-major (n_points, 3, n_dofs)).
    """
    n = len(prismatic)
    em = _Emitter()
    qn = [f'q{k}' for k in range(n)]
    em.lines.append(f'    {", ".join(qn)}, = q')
    Rs, ps = emit_frames(em, B, base, prismatic, qn)
    xs, jac = [], []
    for k, c in zip(frames, coords):
        x = emit_point(em, Rs, ps, k, c)
        xs += x
        cols = emit_jacobian(em, Rs, ps, prismatic, k, x)
        for i in range(3):
            jac += [col[i] for col in cols]
    ret_x = ', '.join(literal(v) for v in xs)
    ret_j = ', '.join(literal(v) for v in jac)
    body = '\n'.join(prune(em.lines + [f'    return [{ret_x}], [{ret_j}]']))
    source = f'def kernel(q):\n{body}\n'
    return load_generated(source, 'kernel',
                          f'Kinematics kernel: positions and Jacobians of {len(frames)} points '
                          f'of a {n}-joint chain.', description,
                          'cdmp_ros.core.kinematics.codegen.compile_kernel')
