"""Primitive files: schema-valid, exact round trip, malformed input rejected naming the field."""
import json

import numpy as np
import pytest

from cdmp_ros.core.dmp.dmp import CDMP, DMP, DmpConfig
from cdmp_ros.core.errors import PrimitiveFileError
from cdmp_ros.core.primitive_io import (dumps_primitive, load_primitive, loads_primitive,
                                        primitive_to_dict, save_primitive)


@pytest.fixture
def cdmp():
    T = np.linspace(0, 1.3, 131)
    Y = np.stack([np.sin(T), T ** 2 - 0.5, 0.1 * T], axis=1)
    prim = CDMP([-1, -1, -1], [1.2, 1.5, 0.2], DmpConfig(n_weights_per_dim=12),
                joint_names=['a', 'b', 'c'])
    return prim.fit(T, Y)


@pytest.mark.parametrize('kind', ['dmp', 'cdmp'])
def test_round_trip_is_bit_exact(tmp_path, cdmp, kind):
    prim = cdmp if kind == 'cdmp' else DMP(3, DmpConfig(n_weights_per_dim=12)).fit(
        np.linspace(0, 1, 50), np.random.default_rng(1).normal(size=(50, 3)).cumsum(0))
    path = tmp_path / 'p.json'
    save_primitive(prim, path)
    back = load_primitive(path)
    assert back.kind == kind and back.joint_names == prim.joint_names
    a = prim.rollout(dt=0.001, goal_y=prim.goal_y_ + 0.1)
    b = back.rollout(dt=0.001, goal_y=prim.goal_y_ + 0.1)
    assert np.array_equal(a.Y, b.Y) and np.array_equal(a.Ydd, b.Ydd)
    sa, sb = prim.stepper(0.002), back.stepper(0.002)
    for _ in range(300):
        oa, _ = sa.update(sa.input)
        ob, _ = sb.update(sb.input)
        assert oa.y == ob.y
    assert loads_primitive(dumps_primitive(prim)).weights_.tobytes() == prim.weights_.tobytes()


def _broken(cdmp, mutate):
    d = json.loads(json.dumps(primitive_to_dict(cdmp)))
    mutate(d)
    return json.dumps(d)


@pytest.mark.parametrize('mutate, field', [
    (lambda d: d['dmp'].pop('weights'), 'weights'),
    (lambda d: d.__setitem__('kind', 'spline'), 'primitive.kind'),
    (lambda d: d['dmp']['weights'][1].append(0.0), 'primitive.dmp.weights'),
    (lambda d: d['dmp']['goal'].__setitem__(0, 'x'), r'primitive.dmp.goal\[0\]'),
    (lambda d: d['limits']['upper'].pop(), 'primitive.limits.upper'),
    (lambda d: d.pop('limits'), 'limits'),
    (lambda d: d.__setitem__('duration', -1.0), 'primitive.duration'),
    (lambda d: d.__setitem__('joint_names', ['a', 'b']), 'primitive.joint_names'),
    (lambda d: d['limits'].__setitem__('lower', [5.0, 5.0, 5.0]),
     r'primitive\.limits\.upper\[0\]: expected a value > primitive\.limits\.lower\[0\]'),
    (lambda d: d['basis']['widths'].__setitem__(0, -1.0), 'basis'),
    (lambda d: d.__setitem__('extra', 1), 'extra'),
])
def test_malformed_primitive_names_the_field(cdmp, mutate, field):
    with pytest.raises(PrimitiveFileError, match=field):
        loads_primitive(_broken(cdmp, mutate))


@pytest.mark.parametrize('text', ['', '{', '[]', 'null', '"x"', b'\xff\xfe'])
def test_not_json_or_not_object(text):
    with pytest.raises(PrimitiveFileError, match='primitive'):
        loads_primitive(text)


def test_missing_file_is_reported(tmp_path):
    with pytest.raises(PrimitiveFileError, match='nope.json'):
        load_primitive(tmp_path / 'nope.json')
