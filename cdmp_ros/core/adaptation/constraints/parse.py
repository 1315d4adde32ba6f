"""Constraint sets as files and messages (msg_schemas/constraints.schema.json).

:func:`parse_constraint_set` validates a JSON constraint set against the schema and against the
ProMP and robot it is meant for, and builds the constraint objects and optimiser settings.
Malformed sets raise :class:`ConstraintSetError` naming the constraint and the field.
"""
import json
from typing import Any, List, Optional, Sequence, Tuple

import numpy as np

from cdmp_ros.core.adaptation.constraints.hyperplane import Hyperplane, NonConvexCorner
from cdmp_ros.core.adaptation.constraints.limits import JointLimit
from cdmp_ros.core.adaptation.constraints.points import ChainPoint, DofPoint, Point
from cdmp_ros.core.adaptation.constraints.smoothness import SmoothnessConstraint
from cdmp_ros.core.adaptation.constraints.spheres import (MutualAvoidance, Repeller,
                                                          UnboundWaypoint, Waypoint)
from cdmp_ros.core.errors import ConstraintSetError, ValidationError
from cdmp_ros.core.file_checks import check_document
from cdmp_ros.core.resources import load_schema


def constraints_schema() -> dict:
    """The JSON Schema of constraint sets (loaded once)."""
    return load_schema('constraints.schema.json')


def _label(doc: dict, path: list) -> str:
    """`` (name)`` of the constraint a path points into (empty outside the constraints)."""
    if len(path) >= 2 and path[0] == 'constraints' and isinstance(path[1], int):
        cons = doc.get('constraints')
        c = cons[path[1]] if isinstance(cons, list) and path[1] < len(cons) else None
        if isinstance(c, dict):
            return f' ({c.get("name", c.get("type", "?"))})'
    return ''


def _order(e) -> tuple:
    # the deepest error first: a oneOf / allOf failure is reported at the field inside it
    return (-len(e.absolute_path), e.message)


def validate_constraint_set(doc: Any) -> None:
    """Check a decoded constraint set; raise :class:`ConstraintSetError` naming the field.

    The one gate of every constraint-set loader (files, the constraints topic, ``cdmp
    adapt``): finite numbers and the schema's ranges
    (:func:`cdmp_ros.core.file_checks.check_document`), then what the schema cannot express
    and that does not depend on the ProMP: ordered supports, time-varying bounds with as many
    values as strictly increasing times, constant lower < upper, non-zero normals.
    Checks against the ProMP and the robot (indices, dimensions) are in
    :func:`parse_constraint_set`.
    """
    label = (lambda path: _label(doc, path)) if isinstance(doc, dict) else None
    check_document(doc, constraints_schema(), 'constraint_set', ConstraintSetError,
                   order=_order, label=label)
    for i, c in enumerate(doc['constraints']):
        tag = _label(doc, ['constraints', i])

        def fail(field: str, text: str):
            raise ConstraintSetError(f'constraint_set.constraints[{i}].{field}{tag}: {text}')

        support = c.get('support', (0.0, 1.0))
        if support[0] > support[1]:
            fail('support[1]', f'expected t1 >= constraint_set.constraints[{i}].support[0] = '
                 f'{support[0]!r}, got {support[1]!r}')
        for key in ('lower', 'upper'):
            b = c.get(key)
            if isinstance(b, dict):
                ts, vs = b['times'], b['values']
                if len(vs) != len(ts):
                    fail(f'{key}.values', f'expected {len(ts)} values (one per entry of '
                         f'constraint_set.constraints[{i}].{key}.times), got {len(vs)}')
                for k in range(1, len(ts)):
                    if not ts[k] > ts[k - 1]:
                        fail(f'{key}.times[{k}]', f'expected strictly increasing times (> '
                             f'{ts[k - 1]!r}), got {ts[k]!r}')
        lo, hi = c.get('lower'), c.get('upper')
        if isinstance(lo, (int, float)) and isinstance(hi, (int, float)) and not lo < hi:
            fail('upper', f'expected a value > lower = {lo!r}, got {hi!r}')
        for key in ('normal', 'normal1', 'normal2'):
            if key in c and not any(v != 0 for v in c[key]):
                fail(key, f'expected a non-zero vector, got {c[key]}')


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

    @classmethod
    def of_robot(cls, model) -> 'RobotContext':
        """The context of a node's robot model (a Chain, or an Arms: each arm a chain over
        its joints), the ProMP's dimensions in the model's joint order."""
        from cdmp_ros.core.kinematics.arms import arms_of
        return cls(model.n_dofs, [(c, idx.tolist()) for c, idx in arms_of(model)])


def _point(spec: dict, ctx: RobotContext, where: str, tag: str = '') -> Point:
    if 'joint' in spec:
        j = spec['joint']
        if j >= ctx.n_dims:
            raise ConstraintSetError(f'{where}.joint{tag}: expected an index < {ctx.n_dims}, '
                                     f'got {j}')
        key = ('dims', (j,))
    elif 'dims' in spec:
        dims = tuple(spec['dims'])
        if max(dims) >= ctx.n_dims:
            raise ConstraintSetError(f'{where}.dims{tag}: expected indices < {ctx.n_dims}, '
                                     f'got {list(dims)}')
        key = ('dims', dims)
    else:
        r = spec.get('robot', 0)
        if r >= len(ctx.chains):
            raise ConstraintSetError(f'{where}.robot{tag}: expected one of {len(ctx.chains)} '
                                     f'robots with kinematics, got {r}')
        chain, dofs = ctx.chains[r]
        link = spec['link']
        if link != 'ee' and link not in chain.link_names:
            raise ConstraintSetError(f'{where}.link{tag}: expected "ee" or one of '
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


def _vec(c: dict, field: str, n: int, where: str, tag: str = '',
         point_field: str = '') -> np.ndarray:
    v = np.asarray(c[field], dtype=float)
    if v.shape != (n,):
        raise ConstraintSetError(f'{where}.{field}{tag}: expected {n} numbers (the point of '
                                 f'interest {point_field} has {n} coordinates), got {v.size}')
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

    Parameters
    ----------
    doc : dict, str or bytes
        A constraint set (schema ``msg_schemas/constraints.schema.json``).
    promp : ProMP
        The primitive the constraints apply to (its ``n_dims`` and joint names).
    ctx : RobotContext, optional
        What link and end-effector points refer to (default: joints only, no chain).

    Returns
    -------
    constraints : list
    optimizer : dict
        Keyword overrides for :class:`cdmp_ros.core.adaptation.config.AdaptationConfig`
        (the set's ``optimizer`` settings and its ``guarantee``).
    """
    if isinstance(doc, (str, bytes)):
        try:
            doc = json.loads(doc)
        except (json.JSONDecodeError, UnicodeDecodeError, RecursionError) as exc:
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
        where = f'constraint_set.constraints[{i}]'
        tag = f' ({label})'
        common = {'alpha': c.get('alpha', 0.999), 'lambda0': c.get('lambda0'),
                  'eta': c.get('eta'), 'name': label}
        support = tuple(c.get('support', (0.0, 1.0)))
        try:
            if kind == 'joint_limit':
                j = c['joint']
                if j >= promp.n_dims:
                    raise ConstraintSetError(f'{where}.joint{tag}: expected an index < '
                                             f'{promp.n_dims}, got {j}')
                out.append(JointLimit(j, _bound(c.get('lower')), _bound(c.get('upper')),
                                      support, **common))
            elif kind == 'smoothness':
                w = c.get('joint_weights')
                if w is not None and len(w) != promp.n_dims:
                    raise ConstraintSetError(f'{where}.joint_weights{tag}: expected '
                                             f'{promp.n_dims} values, got {len(w)}')
                Phi = promp.smoothness_matrix(support if support[1] > support[0]
                                              else (0.0, 1.0), w)
                out.append(SmoothnessConstraint(Phi, c['bound'], **common))
            elif kind == 'mutual_avoidance':
                p1 = _point(c['point1'], ctx, f'{where}.point1', tag)
                p2 = _point(c['point2'], ctx, f'{where}.point2', tag)
                if p1.n_out != p2.n_out:
                    raise ConstraintSetError(f'{where}.point2{tag}: expected {p1.n_out} '
                                             f'coordinates like point1, got {p2.n_out}')
                out.append(MutualAvoidance(p1, p2, c['distance'], support, **common))
            else:
                pt = _point(c['point'], ctx, f'{where}.point', tag)
                k = pt.n_out

                point_field = f'{where}.point.' + next(
                    key for key in ('joint', 'dims', 'link') if key in c['point'])

                def vec(field):
                    return _vec(c, field, k, where, tag, point_field)
                if kind == 'hyperplane':
                    out.append(Hyperplane(pt, vec('normal'), vec('offset'), support, **common))
                elif kind == 'corner':
                    out.append(NonConvexCorner(pt, vec('normal1'), vec('offset1'),
                                               vec('normal2'), vec('offset2'), support,
                                               **common))
                else:
                    cls = {'waypoint': Waypoint, 'repeller': Repeller,
                           'unbound_waypoint': UnboundWaypoint}[kind]
                    out.append(cls(pt, vec('center'), c['radius'], support, **common))
        except ConstraintSetError:
            raise
        except ValidationError as exc:
            raise ConstraintSetError(f'{where}{tag}: {exc}') from None
    opt = dict(doc.get('optimizer', {}))
    if 'guarantee' in doc:            # per_step (default) or trajectory: AdaptationConfig
        opt['guarantee'] = doc['guarantee']
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
