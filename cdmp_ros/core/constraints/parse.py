"""Constraint sets as files and messages (msg_schemas/constraints.schema.json).

:func:`parse_constraint_set` validates a JSON constraint set against the schema and against the
ProMP and robot it is meant for, and builds the constraint objects and optimiser settings.
Malformed sets raise :class:`ConstraintSetError` naming the constraint and the field.
"""
import json
from typing import Any, List, Optional, Sequence, Tuple

import jsonschema
import numpy as np

from cdmp_ros.core.constraints.hyperplane import Hyperplane, NonConvexCorner
from cdmp_ros.core.constraints.limits import JointLimit
from cdmp_ros.core.constraints.points import ChainPoint, DofPoint, Point
from cdmp_ros.core.constraints.smoothness import SmoothnessConstraint
from cdmp_ros.core.constraints.spheres import (MutualAvoidance, Repeller, UnboundWaypoint,
                                               Waypoint)
from cdmp_ros.core.errors import ConstraintSetError, ValidationError
from cdmp_ros.core.resources import schema_path

_SCHEMA = None


def constraints_schema() -> dict:
    """The JSON Schema of constraint sets (loaded once)."""
    global _SCHEMA
    if _SCHEMA is None:
        with open(schema_path('constraints.schema.json')) as f:
            _SCHEMA = json.load(f)
    return _SCHEMA


def _where(path) -> str:
    out = 'constraint_set'
    for p in path:
        out += f'[{p}]' if isinstance(p, int) else f'.{p}'
    return out


def validate_constraint_set(doc: Any) -> None:
    """Schema validation; raises ConstraintSetError naming the first offending field."""
    if not isinstance(doc, dict):
        raise ConstraintSetError(f'constraint_set: expected a JSON object, got '
                                 f'{type(doc).__name__}')
    validator = jsonschema.Draft202012Validator(constraints_schema())
    errors = sorted(validator.iter_errors(doc),
                    key=lambda e: (-len(e.absolute_path), e.message))
    if errors:
        e = errors[0]
        name = ''
        path = list(e.absolute_path)
        if len(path) >= 2 and path[0] == 'constraints' and isinstance(path[1], int):
            c = doc['constraints'][path[1]]
            if isinstance(c, dict):
                name = f' ({c.get("name", c.get("type", "?"))})'
        raise ConstraintSetError(f'{_where(path)}{name}: {e.message}')


class RobotContext:
    """What the points of interest refer to.

    Parameters
    ----------
    n_dims : int
        ProMP dimensions.
    chains : sequence of (Chain, dofs), optional
        Kinematic chain of each robot and the ProMP dimensions of its joints.
    axes : tuple of int
        World coordinates of chain points (``(0, 1)`` for planar arms).
    """

    def __init__(self, n_dims: int, chains: Optional[Sequence[Tuple[Any, Sequence[int]]]] = None,
                 axes: Tuple[int, ...] = (0, 1, 2)):
        self.n_dims = int(n_dims)
        self.chains = [(c, tuple(int(d) for d in dofs)) for c, dofs in (chains or [])]
        self.axes = tuple(axes)
        self._cache = {}


def _point(spec: dict, ctx: RobotContext, where: str) -> Point:
    if 'joint' in spec:
        j = spec['joint']
        if j >= ctx.n_dims:
            raise ConstraintSetError(f'{where}.joint: expected an index < {ctx.n_dims}, got {j}')
        key = ('dims', (j,))
    elif 'dims' in spec:
        dims = tuple(spec['dims'])
        if max(dims) >= ctx.n_dims:
            raise ConstraintSetError(f'{where}.dims: expected indices < {ctx.n_dims}, '
                                     f'got {list(dims)}')
        key = ('dims', dims)
    else:
        r = spec.get('robot', 0)
        if r >= len(ctx.chains):
            raise ConstraintSetError(f'{where}.robot: expected one of {len(ctx.chains)} '
                                     f'robots with kinematics, got {r}')
        chain, dofs = ctx.chains[r]
        link = spec['link']
        if link != 'ee' and link not in chain.link_names:
            raise ConstraintSetError(f'{where}.link: expected "ee" or one of '
                                     f'{list(chain.link_names)}, got {link!r}')
        offset = tuple(spec.get('offset', (0.0, 0.0, 0.0)))
        key = ('link', r, link, offset)
    if key in ctx._cache:          # shared points share their moments in the optimiser
        return ctx._cache[key]
    if key[0] == 'dims':
        pt = DofPoint(key[1])
    else:
        from cdmp_ros.core.kinematics import PointOfInterest
        pt = ChainPoint(chain, PointOfInterest(link, offset), dofs, ctx.axes)
    ctx._cache[key] = pt
    return pt


def _vec(c: dict, field: str, n: int, where: str) -> np.ndarray:
    v = np.asarray(c[field], dtype=float)
    if v.shape != (n,):
        raise ConstraintSetError(f'{where}.{field}: expected {n} numbers (the point of '
                                 f'interest has {n} coordinates), got {v.size}')
    return v


def _bound(b):
    if b is None or isinstance(b, (int, float)):
        return b
    ts = np.asarray(b['times'], float)
    vs = np.asarray(b['values'], float)
    return lambda times: np.interp(times, ts, vs)


def parse_constraint_set(doc: Any, promp, ctx: Optional[RobotContext] = None
                         ) -> Tuple[List, dict]:
    """Build constraints and optimiser overrides from a constraint-set dict or JSON string.

    Returns
    -------
    constraints : list
    optimizer : dict
        Keyword overrides for :class:`cdmp_ros.core.adaptation.AdaptationConfig`.
    """
    if isinstance(doc, (str, bytes)):
        try:
            doc = json.loads(doc)
        except json.JSONDecodeError as exc:
            raise ConstraintSetError(f'constraint_set: not valid JSON ({exc})') from None
    validate_constraint_set(doc)
    ctx = ctx or RobotContext(promp.n_dims)
    if ctx.n_dims != promp.n_dims:
        raise ConstraintSetError(f'constraint_set: the robot has {ctx.n_dims} dimensions, '
                                 f'the primitive {promp.n_dims}')
    out = []
    for i, c in enumerate(doc['constraints']):
        kind = c['type']
        label = c.get('name', f'{kind}_{i + 1}')
        where = f'constraint_set.constraints[{i}] ({label})'
        common = {'alpha': c.get('alpha', 0.999), 'lambda0': c.get('lambda0'),
                  'eta': c.get('eta'), 'name': label}
        support = tuple(c.get('support', (0.0, 1.0)))
        if support[0] > support[1]:
            raise ConstraintSetError(f'{where}.support: expected t0 <= t1, got {list(support)}')
        try:
            if kind == 'joint_limit':
                j = c['joint']
                if j >= promp.n_dims:
                    raise ConstraintSetError(f'{where}.joint: expected an index < '
                                             f'{promp.n_dims}, got {j}')
                out.append(JointLimit(j, _bound(c.get('lower')), _bound(c.get('upper')),
                                      support, **common))
            elif kind == 'smoothness':
                w = c.get('joint_weights')
                if w is not None and len(w) != promp.n_dims:
                    raise ConstraintSetError(f'{where}.joint_weights: expected {promp.n_dims} '
                                             f'values, got {len(w)}')
                Phi = promp.smoothness_matrix(support if support[1] > support[0]
                                              else (0.0, 1.0), w)
                out.append(SmoothnessConstraint(Phi, c['bound'], **common))
            elif kind == 'mutual_avoidance':
                p1 = _point(c['point1'], ctx, f'{where}.point1')
                p2 = _point(c['point2'], ctx, f'{where}.point2')
                if p1.n_out != p2.n_out:
                    raise ConstraintSetError(f'{where}.point2: expected {p1.n_out} coordinates '
                                             f'like point1, got {p2.n_out}')
                out.append(MutualAvoidance(p1, p2, c['distance'], support, **common))
            else:
                pt = _point(c['point'], ctx, f'{where}.point')
                k = pt.n_out
                if kind == 'hyperplane':
                    out.append(Hyperplane(pt, _vec(c, 'normal', k, where),
                                          _vec(c, 'offset', k, where), support, **common))
                elif kind == 'corner':
                    out.append(NonConvexCorner(pt, _vec(c, 'normal1', k, where),
                                               _vec(c, 'offset1', k, where),
                                               _vec(c, 'normal2', k, where),
                                               _vec(c, 'offset2', k, where), support, **common))
                else:
                    cls = {'waypoint': Waypoint, 'repeller': Repeller,
                           'unbound_waypoint': UnboundWaypoint}[kind]
                    out.append(cls(pt, _vec(c, 'center', k, where), c['radius'], support,
                                   **common))
        except ConstraintSetError:
            raise
        except ValidationError as exc:
            raise ConstraintSetError(f'{where}: {exc}') from None
    opt = dict(doc.get('optimizer', {}))
    objective = opt.pop('objective', 'joint_kl')
    if 'smoothness_weights' in opt:
        if len(opt['smoothness_weights']) != promp.n_dims:
            raise ConstraintSetError(f'constraint_set.optimizer.smoothness_weights: expected '
                                     f'{promp.n_dims} values, got '
                                     f'{len(opt["smoothness_weights"])}')
        opt['smoothness_weights'] = tuple(opt['smoothness_weights'])
    if objective == 'marginal_kl':
        if len(ctx.chains) < 2:
            raise ConstraintSetError('constraint_set.optimizer.objective: marginal_kl needs '
                                     'two robots')
        M = promp.n_basis
        blocks = []
        for _, dofs in ctx.chains:
            blocks.append((min(dofs) * M, (max(dofs) + 1) * M))
        opt['kl_blocks'] = tuple(blocks)
    return out, opt
