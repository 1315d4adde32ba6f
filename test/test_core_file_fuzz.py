"""Property test of the file loaders: every field of valid primitive files (dmp, cdmp, promp)
and constraint sets is mutated (missing, wrong type, NaN, +-inf, +-1e308, empty, negative, zero,
huge list), through the dict API and through JSON text (Python's json reads the non-standard
NaN / Infinity tokens). Each mutant is either refused with a CdmpError whose message names the
mutated field, or it loads and then behaves: a (C)DMP rollout and a stepper run towards a goal
far outside the limits, with huge and non-finite couplings, stay finite and (CDMP) strictly
inside the limits; a ProMP adapts to a constraint set with a small optimiser budget, or
refuses with a CdmpError, and what it returns is finite."""
import copy
import json
import math
import zlib

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from cdmp_ros.core.adaptation.guarantee import adapt
from cdmp_ros.core.adaptation.solver import AdaptationConfig
from cdmp_ros.core.adaptation.constraints.parse import parse_constraint_set
from cdmp_ros.core.dmp.dmp import CDMP, DMP, DmpConfig
from cdmp_ros.core.errors import CdmpError, ConstraintSetError, PrimitiveFileError
from cdmp_ros.core.file_checks import field_path
from cdmp_ros.core.primitive_io import loads_primitive, primitive_from_dict, primitive_to_dict
from cdmp_ros.core.promp.promp import ProMP, RbfBasis
from cdmp_ros.core.dmp.stepper import StepStatus

MUTATIONS = ('missing', 'string', 'nan', 'inf', '-inf', '1e308', '-1e308', 'empty_list',
             'empty_string', 'negative', 'zero', 'huge_list', 'object')
FUZZ = settings(max_examples=1200, deadline=None, derandomize=True, database=None,
                suppress_health_check=[HealthCheck.too_slow])
N_W = 4
DT = 0.01
TICKS = 300
COUPLINGS = (0.0, 1e9, -1e9, math.nan, math.inf, -math.inf, 1e300, -3.0)


def _dmp_file(kind):
    cfg = DmpConfig(n_weights_per_dim=N_W)
    rng = np.random.default_rng(3)
    if kind == 'cdmp':
        prim = CDMP([-1.0, -2.0], [1.0, 0.5], cfg, ['a', 'b'])
    else:
        prim = DMP(2, cfg, ['a', 'b'])
    prim.set_parameters(rng.normal(0.0, 50.0, (2, N_W)), [0.1, -0.5], [0.6, 0.2], 1.0)
    prim.velocity_limits = np.array([2.0, 3.0])
    prim.metadata = {'source': 'fuzz', 'fit': [1.0, 2.0]}
    return primitive_to_dict(prim)


def _promp():
    M = N_W
    p = ProMP(2, RbfBasis.uniform(M), np.r_[np.linspace(-3, 3, M), np.zeros(M)],
              0.64 * np.eye(2 * M), joint_names=['x', 'y'])
    return p.condition([0, 1], [[-3, 0.5], [3, -0.5]], var=1e-3)


def XY():  # one dict per constraint (a shared one would be mutated everywhere at once)
    return {'dims': [0, 1]}


CONSTRAINTS = {'format_version': 1, 'constraints': [
    {'type': 'repeller', 'point': XY(), 'center': [0, 0.3], 'radius': 0.5, 'name': 'ball',
     'lambda0': 20.0, 'eta': 1.0},
    {'type': 'waypoint', 'point': XY(), 'center': [0, 1], 'radius': 0.2, 'support': [0.4, 0.5]},
    {'type': 'unbound_waypoint', 'point': XY(), 'center': [1, 1], 'radius': 0.2},
    {'type': 'hyperplane', 'point': XY(), 'normal': [0, 1], 'offset': [0, 2]},
    {'type': 'corner', 'point': XY(), 'normal1': [1, 0], 'offset1': [0, 0],
     'normal2': [0, 1], 'offset2': [0, 0], 'alpha': 0.99},
    {'type': 'joint_limit', 'joint': 1, 'lower': -2.0,
     'upper': {'times': [0, 1], 'values': [1.0, 2.0]}},
    {'type': 'smoothness', 'bound': 100.0, 'joint_weights': [1.0, 0.5]}],
    'optimizer': {'kappa': 0.01, 'n_steps': 11, 'max_outer': 2, 'max_inner': 20,
                  'lambda0': 20.0, 'eta': 1.0, 'smoothness_weights': [1.0, 1.0]}}

PROMP = _promp()
FILES = {'dmp': _dmp_file('dmp'), 'cdmp': _dmp_file('cdmp'),
         'promp': primitive_to_dict(PROMP), 'constraints': CONSTRAINTS}


def _paths(doc, prefix=()):
    """Every node (leaf and container) below the root, as a path of keys / indices."""
    out = []
    items = doc.items() if isinstance(doc, dict) else enumerate(doc)
    for k, v in items:
        out.append(prefix + (k,))
        if isinstance(v, (dict, list)):
            out.extend(_paths(v, prefix + (k,)))
    return out


PATHS = {kind: _paths(doc) for kind, doc in FILES.items()}


def _mutate(doc, path, mutation):
    """A mutated deep copy and the paths of which the error must name one: the mutated
    field (for a removed or zeroed field, also the object or list that holds it)."""
    doc = copy.deepcopy(doc)
    parent = doc
    for k in path[:-1]:
        parent = parent[k]
    key = path[-1]
    old = parent[key]
    if mutation == 'missing':
        del parent[key]
        return doc, [path, path[:-1]]
    value = {'string': 'x', 'nan': math.nan, 'inf': math.inf, '-inf': -math.inf,
             '1e308': 1e308, '-1e308': -1e308, 'empty_list': [], 'empty_string': '',
             'zero': 0, 'huge_list': [0.5] * 20001, 'object': {'x': 1}}.get(mutation)
    if mutation == 'negative':
        value = -old if isinstance(old, (int, float)) and not isinstance(old, bool) else -1
    parent[key] = value
    # a zero can break a relation between the entries of its container (a non-zero normal)
    return doc, ([path, path[:-1]] if mutation == 'zero' else [path])


def _finite(*arrays):
    return all(np.all(np.isfinite(np.asarray(a, dtype=float))) for a in arrays)


def _check_refusal(exc, error_cls, root, named):
    assert isinstance(exc, error_cls), repr(exc)
    names = [field_path(root, p) for p in named]
    assert any(n in str(exc) for n in names), f'none of {names} named in: {exc}'


def _exercise_dmp(prim):
    """A rollout and a coupled stepper run towards a goal far outside the limits."""
    if prim.kind == 'cdmp':
        lo, hi = prim.y_min, prim.y_max
        far = np.where(np.arange(prim.n_dims) % 2 == 0, hi + 50 * (hi - lo), lo - 1e5)
    else:
        far = prim.start_y_ + 1e5
    try:
        tr = prim.rollout(dt=DT, goal_y=far)
        st = prim.stepper(DT, goal_y=far)
    except CdmpError:
        return 'refused'  # e.g. dt / tau unstable for the loaded constants: a clear refusal
    assert _finite(tr.Y, tr.Yd, tr.Ydd)
    ys = [tr.Y]
    inp = st.input
    for k in range(TICKS):
        c = COUPLINGS[k % len(COUPLINGS)]
        inp.coupling[:] = [c, -c][:prim.n_dims] + [c] * (prim.n_dims - 2)
        out, status = st.update(inp)
        assert isinstance(status, StepStatus)
        ys.append(np.array([out.y]))
        assert _finite(out.y, out.yd, out.ydd)
    if prim.kind == 'cdmp':
        Y = np.concatenate(ys)
        assert np.all(Y > prim.y_min) and np.all(Y < prim.y_max)
    return 'ok'


def _exercise_promp(promp, doc=CONSTRAINTS):
    try:
        constraints, overrides = parse_constraint_set(doc, promp)
        overrides.update(max_outer=min(overrides.get('max_outer', 2), 2),
                         max_inner=min(overrides.get('max_inner', 20), 20),
                         n_steps=min(overrides.get('n_steps', 11), 11))
        adapted, report = adapt(promp, constraints, AdaptationConfig(**overrides))
    except CdmpError:
        return 'refused'
    assert _finite(adapted.mean_w, adapted.cov_w, adapted.mean(np.linspace(0, 1, 11)))
    return 'ok'


def _load(kind, doc, via):
    if via == 'text':
        return loads_primitive(json.dumps(doc))  # json writes NaN / Infinity tokens
    return primitive_from_dict(doc)


@FUZZ
@given(kind=st.sampled_from(['dmp', 'cdmp', 'promp']), data=st.data(),
       mutation=st.sampled_from(MUTATIONS), via=st.sampled_from(['dict', 'text']))
def test_mutated_primitive_files_are_refused_naming_the_field_or_behave(
        kind, data, mutation, via):
    path = data.draw(st.sampled_from(PATHS[kind]), label='path')
    doc, named = _mutate(FILES[kind], path, mutation)
    try:
        prim = _load(kind, doc, via)
    except Exception as exc:  # noqa: B902 - any other class fails the check below
        _check_refusal(exc, PrimitiveFileError, 'primitive', named)
        return
    if kind == 'promp':
        _exercise_promp(prim)
    else:
        _exercise_dmp(prim)


@settings(FUZZ, max_examples=500)
@given(data=st.data(), mutation=st.sampled_from(MUTATIONS),
       via=st.sampled_from(['dict', 'text']))
def test_mutated_constraint_sets_are_refused_naming_the_field_or_adapt(data, mutation, via):
    path = data.draw(st.sampled_from(PATHS['constraints']), label='path')
    doc, named = _mutate(CONSTRAINTS, path, mutation)
    payload = json.dumps(doc) if via == 'text' else doc
    try:
        constraints, overrides = parse_constraint_set(payload, PROMP)
    except Exception as exc:  # noqa: B902 - any other class fails the check below
        _check_refusal(exc, ConstraintSetError, 'constraint_set', named)
        return
    _exercise_promp(PROMP, doc)


def test_the_valid_files_load_and_behave():
    for kind in ('dmp', 'cdmp'):
        for via in ('dict', 'text'):
            assert _exercise_dmp(_load(kind, FILES[kind], via)) == 'ok'
    assert _exercise_promp(_load('promp', FILES['promp'], 'text')) == 'ok'


def test_the_measured_overflow_is_refused_naming_duration():
    doc = copy.deepcopy(FILES['cdmp'])
    doc['duration'] = 1e308
    for via in ('dict', 'text'):
        try:
            _load('cdmp', doc, via)
        except PrimitiveFileError as exc:
            assert 'primitive.duration' in str(exc) and '300' in str(exc), str(exc)
        else:
            raise AssertionError('duration 1e308 was accepted')


def test_every_mutation_and_kind_is_reachable():
    # the fuzz draws from these lists: each has leaves and containers
    for kind, paths in PATHS.items():
        assert len(paths) > 20, kind
        assert any(isinstance(p[-1], int) for p in paths), kind


def test_the_schema_ranges_mirror_the_dataclass_and_parameter_ranges():
    """A value a node accepts as a parameter is one its files accept, and the reverse."""
    from dataclasses import fields

    from cdmp_ros.core.adaptation.config import RANGES
    from cdmp_ros.core.adaptation.config import AdaptRequestConfig
    from cdmp_ros.core.adaptation.constraints.parse import constraints_schema
    from cdmp_ros.core.primitive_io import primitive_schema
    dmp = primitive_schema()['properties']['dmp']['properties']
    phase = primitive_schema()['properties']['phase']['properties']
    basis = primitive_schema()['properties']['basis']['properties']
    schema = {'alpha_y': dmp['alpha_y'], 'beta_y': dmp['beta_y'], 'alpha_g': dmp['alpha_g'],
              'demo_margin': dmp['demo_margin'], 'alpha_s': phase['alpha_s'],
              'basis_width': basis['basis_width']}
    ranges = {f.name: f.metadata['range'] for f in fields(DmpConfig)}
    for name, prop in schema.items():
        assert (prop['minimum'], prop['maximum']) == ranges[name], name
    assert basis['centers']['maxItems'] == ranges['n_weights_per_dim'][1]
    opt = constraints_schema()['properties']['optimizer']['properties']
    adapter = {f.name: f.metadata.get('range') for f in fields(AdaptRequestConfig)}
    assert {'n_steps', 'max_outer', 'max_inner', 'lambda0'} <= set(adapter)
    for name, (lo, hi) in RANGES.items():
        assert (opt[name]['minimum'], opt[name]['maximum']) == (lo, hi), name
        if adapter.get(name) is not None:
            assert adapter[name] == (lo, hi), name


def _large_promp_dict():
    """A ProMP file whose arrays are long enough for check_document's compaction."""
    M = 40
    p = ProMP(2, RbfBasis.uniform(M), np.r_[np.linspace(-3, 3, M), np.zeros(M)],
              0.64 * np.eye(2 * M), joint_names=['x', 'y'])
    return primitive_to_dict(p)


@pytest.mark.parametrize('field', ['mean_w', 'cov_w', 'centers'])
@pytest.mark.parametrize('bad', ['string', True, None, 1e13, -1e13, [1.0], 'short', 'long'])
def test_compacted_arrays_are_refused_as_jsonschema_refuses_them(field, bad, monkeypatch):
    """check_document checks long numeric arrays itself (file_checks._compact); every bad
    element or size must still be refused, with the message of the uncompacted check."""
    from cdmp_ros.core import file_checks
    rng = np.random.default_rng(zlib.crc32(f'{field} {bad!r}'.encode()))
    d = _large_promp_dict()
    body = d['promp']
    target = {'mean_w': body['mean_w'], 'centers': body['basis']['centers'],
              'cov_w': body['cov_w'][int(rng.integers(len(body['cov_w'])))]}[field]
    assert len(target) >= file_checks._COMPACT_MIN
    if bad == 'short':
        del target[int(rng.integers(len(target))):]
    elif bad == 'long':
        target.extend([0.0] * 1000)
    else:
        target[int(rng.integers(len(target)))] = bad
    with pytest.raises(PrimitiveFileError) as fast:
        primitive_from_dict(copy.deepcopy(d))
    monkeypatch.setattr(file_checks, '_compact', lambda doc, schema, root: doc)
    with pytest.raises(PrimitiveFileError) as slow:
        primitive_from_dict(copy.deepcopy(d))
    assert str(fast.value) == str(slow.value)


def test_compaction_accepts_what_jsonschema_accepts_and_checks_less():
    from cdmp_ros.core import file_checks
    from cdmp_ros.core.primitive_io import primitive_schema
    d = _large_promp_dict()
    schema = primitive_schema()
    small = file_checks._compact(d, schema, schema)
    assert len(small['promp']['cov_w']) < len(d['promp']['cov_w'])
    assert len(small['promp']['mean_w']) < len(d['promp']['mean_w'])
    assert d['promp']['cov_w'][0] is not small['promp']['cov_w'][0]  # the input is untouched
    assert len(d['promp']['cov_w']) == 80
    primitive_from_dict(d)
