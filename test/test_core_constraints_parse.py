"""Constraint sets (msg_schemas/constraints.schema.json): parsing, rejection of malformed sets
naming the constraint and the field, and `cdmp adapt`."""
import argparse
import json

import numpy as np
import pytest

from cdmp_ros.cli import cmd_adapt
from cdmp_ros.core.adaptation.constraints import (ChainPoint, Hyperplane, MutualAvoidance,
                                                  Repeller, SmoothnessConstraint)
from cdmp_ros.core.adaptation.constraints.parse import RobotContext, parse_constraint_set
from cdmp_ros.core.errors import ConstraintSetError
from cdmp_ros.core.kinematics import planar_chain
from cdmp_ros.core.primitive_io import load_primitive, save_primitive
from cdmp_ros.core.promp.promp import ProMP, RbfBasis


def _cart_promp(M=8):
    p = ProMP(2, RbfBasis.uniform(M), np.r_[np.linspace(-3, 3, M), np.zeros(M)],
              0.64 * np.eye(2 * M), joint_names=['x', 'y'])
    return p.condition([0, 1], [[-3, 0.5], [3, -0.5]], var=1e-3)


XY = {'dims': [0, 1]}


def test_parse_every_type_cartesian_and_planar():
    p = _cart_promp()
    doc = {'format_version': 1, 'constraints': [
        {'type': 'repeller', 'point': XY, 'center': [0, 0.3], 'radius': 0.5, 'name': 'ball'},
        {'type': 'waypoint', 'point': XY, 'center': [0, 1], 'radius': 0.2,
         'support': [0.4, 0.5]},
        {'type': 'unbound_waypoint', 'point': XY, 'center': [1, 1], 'radius': 0.2},
        {'type': 'hyperplane', 'point': XY, 'normal': [0, 1], 'offset': [0, 2]},
        {'type': 'corner', 'point': XY, 'normal1': [1, 0], 'offset1': [0, 0],
         'normal2': [0, 1], 'offset2': [0, 0], 'alpha': 0.99},
        {'type': 'joint_limit', 'joint': 1, 'lower': -2.0,
         'upper': {'times': [0, 1], 'values': [1.0, 2.0]}},
        {'type': 'smoothness', 'bound': 100.0, 'joint_weights': [1.0, 0.5]}],
        'optimizer': {'kappa': 0.01, 'n_steps': 31}}
    cons, opt = parse_constraint_set(json.dumps(doc), p)
    assert [c.kind for c in cons] == ['repeller', 'waypoint', 'unbound_waypoint', 'hyperplane',
                                      'corner', 'joint_limit', 'smoothness']
    assert cons[0].name == 'ball' and cons[0].point is cons[1].point   # shared point
    assert cons[4].alpha == 0.99
    assert np.allclose(cons[5].bounds(np.array([0.5]))[1], 1.5)
    assert isinstance(cons[6], SmoothnessConstraint)
    assert opt == {'kappa': 0.01, 'n_steps': 31}
    # planar 4-link arm: link points through the kinematics
    q = ProMP(4, RbfBasis.uniform(5))
    ctx = RobotContext(4, [(planar_chain([1.0] * 4), range(4))], axes=(0, 1))
    cons, _ = parse_constraint_set({'constraints': [
        {'type': 'repeller', 'point': {'link': 'ee'}, 'center': [2, 3], 'radius': 1.0},
        {'type': 'hyperplane', 'point': {'link': 'link4'}, 'normal': [1, 1],
         'offset': [0, 2]}]}, q, ctx)
    assert isinstance(cons[0].point, ChainPoint) and cons[0].point.n_out == 2
    assert isinstance(cons[1], Hyperplane) and isinstance(cons[0], Repeller)


def test_parse_mutual_avoidance_and_marginal_objective():
    q = ProMP(8, RbfBasis.uniform(4))
    ch = planar_chain([1.0] * 4)
    ctx = RobotContext(8, [(ch, range(4)), (ch, range(4, 8))], axes=(0, 1))
    cons, opt = parse_constraint_set({'constraints': [
        {'type': 'mutual_avoidance', 'point1': {'link': 'ee', 'robot': 0},
         'point2': {'link': 'ee', 'robot': 1}, 'distance': 0.4}],
        'optimizer': {'objective': 'marginal_kl'}}, q, ctx)
    assert isinstance(cons[0], MutualAvoidance)
    assert opt['kl_blocks'] == ((0, 16), (16, 32))


@pytest.mark.parametrize('constraint, field', [
    ({'type': 'repeller', 'point': XY, 'center': [0, 0]}, 'radius'),
    ({'type': 'repeller', 'point': XY, 'center': [0, 0], 'radius': -1}, 'radius'),
    ({'type': 'repeller', 'point': XY, 'center': [0, 0, 0], 'radius': 1}, 'center'),
    ({'type': 'hyperplane', 'point': XY, 'normal': [0, 1], 'offset': [0, 1],
      'alpha': 1.5}, 'alpha'),
    ({'type': 'hyperplane', 'point': {'dims': [0, 5]}, 'normal': [0, 1],
      'offset': [0, 1]}, 'dims'),
    ({'type': 'joint_limit', 'joint': 0}, 'joint_limit'),
    ({'type': 'joint_limit', 'joint': 7, 'upper': 1.0}, 'joint'),
    ({'type': 'waypoint', 'point': XY, 'center': [0, 0], 'radius': 1,
      'support': [0.8, 0.2]}, 'support'),
    ({'type': 'warp_drive', 'point': XY}, 'type'),
    ({'type': 'repeller', 'point': {'link': 'ee'}, 'center': [0, 0], 'radius': 1}, 'robot'),
    ({'type': 'repeller', 'point': XY, 'center': [0, 0], 'radius': 1, 'colour': 'red'},
     'colour'),
])
def test_malformed_sets_are_rejected_naming_constraint_and_field(constraint, field):
    p = _cart_promp()
    doc = {'constraints': [{'type': 'hyperplane', 'point': XY, 'normal': [0, 1],
                            'offset': [0, 3]}, dict(constraint, name='bad_one')]}
    with pytest.raises(ConstraintSetError) as exc:
        parse_constraint_set(doc, p)
    msg = str(exc.value)
    assert 'constraints[1]' in msg and 'bad_one' in msg, msg
    assert field in msg, msg


def test_cmd_adapt_writes_adapted_primitive_and_report(tmp_path, capsys):
    p = _cart_promp()
    save_primitive(p, tmp_path / 'p.json')
    with open(tmp_path / 'c.json', 'w') as f:
        json.dump({'constraints': [{'type': 'repeller', 'name': 'ball', 'point': XY,
                                    'center': [0.0, 0.2], 'radius': 0.5}],
                   'optimizer': {'n_steps': 31}}, f)
    args = argparse.Namespace(primitive=str(tmp_path / 'p.json'),
                              constraints=str(tmp_path / 'c.json'), robot='none',
                              out=str(tmp_path / 'a.json'), json=False)
    assert cmd_adapt.run(args) == 0
    out = capsys.readouterr().out
    assert 'ball [repeller]' in out and 'converged' in out
    assert 'sampled verification' in out and 'ball: per-step max' in out
    q = load_primitive(tmp_path / 'a.json')
    assert q.metadata['adaptation']['converged'] is True
    assert not np.allclose(q.mean_w, p.mean_w)
    # malformed constraint file: exit status 1 and the field named on stderr
    with open(tmp_path / 'bad.json', 'w') as f:
        json.dump({'constraints': [{'type': 'repeller', 'point': XY, 'radius': 0.5}]}, f)
    args.constraints = str(tmp_path / 'bad.json')
    assert cmd_adapt.run(args) == 1
    assert 'center' in capsys.readouterr().err
    # infeasible: exit status 2
    with open(tmp_path / 'inf.json', 'w') as f:
        json.dump({'constraints': [{'type': 'hyperplane', 'point': XY, 'normal': [-1, 0],
                                    'offset': [-2, 0], 'support': [0, 0]}],
                   'optimizer': {'max_outer': 2, 'max_inner': 30}}, f)
    args.constraints = str(tmp_path / 'inf.json')
    assert cmd_adapt.run(args) == 2


def test_guarantee_field_is_parsed_and_a_bad_value_is_named():
    p = _cart_promp()
    doc = {'constraints': [{'type': 'repeller', 'point': XY, 'center': [0, 0], 'radius': 0.5}]}
    assert 'guarantee' not in parse_constraint_set(doc, p)[1]     # default: per_step
    for mode in ('per_step', 'trajectory'):
        _, opt = parse_constraint_set(dict(doc, guarantee=mode), p)
        assert opt['guarantee'] == mode
    _, opt = parse_constraint_set(dict(doc, optimizer={'verification_samples': 500,
                                                       'max_refinements': 2}), p)
    assert opt == {'verification_samples': 500, 'max_refinements': 2}
    for bad, field in (({'guarantee': 'always'}, 'constraint_set.guarantee'),
                       ({'guarantee': 1}, 'constraint_set.guarantee'),
                       ({'optimizer': {'verification_samples': 0}},
                        'constraint_set.optimizer.verification_samples')):
        with pytest.raises(ConstraintSetError) as exc:
            parse_constraint_set(dict(doc, **bad), p)
        assert field in str(exc.value), str(exc.value)


def test_cmd_adapt_json_report_carries_the_verification(tmp_path, capsys):
    p = _cart_promp()
    save_primitive(p, tmp_path / 'p.json')
    with open(tmp_path / 'c.json', 'w') as f:
        json.dump({'constraints': [{'type': 'hyperplane', 'name': 'wall', 'point': XY,
                                    'normal': [0, 1], 'offset': [0, 0.5]}],
                   'guarantee': 'trajectory', 'optimizer': {'n_steps': 31}}, f)
    args = argparse.Namespace(primitive=str(tmp_path / 'p.json'),
                              constraints=str(tmp_path / 'c.json'), robot='none',
                              out=str(tmp_path / 'a.json'), json=True, seed=3)
    status = cmd_adapt.run(args)
    rep = json.loads(capsys.readouterr().out)
    assert status == (0 if rep['converged'] else 2)
    ver = rep['verification']
    assert ver['guarantee'] == 'trajectory' and ver['n_samples'] >= 20000
    assert 0.0 <= ver['trajectory_violation'] <= ver['trajectory_violation_upper95'] <= 1.0
    assert [c['name'] for c in ver['constraints']] == ['wall']
    assert set(ver['constraints'][0]) >= {'name', 'per_step_max', 'trajectory', 'upper95'}
    assert rep['converged'] == (ver['holds'] and rep['status'] == 'converged')
    q = load_primitive(tmp_path / 'a.json')
    assert q.metadata['adaptation']['verification'] == ver
