"""The shipped config/joint_limits/*.yaml files equal the nodes' built-in defaults and parse in
the joint_limits.yaml convention."""
import os

import numpy as np
import pytest
import yaml

from cdmp_ros.core.joint_limits import (PANDA_DATASHEET, default_joint_limits,
                                        parse_joint_limits)

CONFIG = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), 'config',
                      'joint_limits')
JOINTS = {'panda': [f'panda_joint{i}' for i in range(1, 8)],
          'dual_panda': [f'{s}_panda_joint{i}' for s in ('left', 'right') for i in range(1, 8)],
          'planar4': [f'joint{i}' for i in range(1, 5)]}


@pytest.mark.parametrize('robot', sorted(JOINTS))
def test_shipped_file_equals_the_built_in_defaults(robot):
    with open(os.path.join(CONFIG, f'{robot}.yaml')) as f:
        entries = yaml.safe_load(f)['/**']['ros__parameters']['joint_limits']
    names = JOINTS[robot]
    assert sorted(entries) == sorted(names)
    assert entries == default_joint_limits(names)
    n = len(names)
    lim = parse_joint_limits(names, entries, -np.ones(n), np.ones(n))
    assert np.all(np.isfinite(lim.acceleration)) and np.all(np.isfinite(lim.jerk))


def test_panda_file_is_the_datasheet():
    with open(os.path.join(CONFIG, 'panda.yaml')) as f:
        entries = yaml.safe_load(f)['/**']['ros__parameters']['joint_limits']
    for i, key in enumerate(JOINTS['panda']):
        e = entries[key]
        assert (e['max_velocity'], e['max_acceleration'], e['max_jerk']) == (
            PANDA_DATASHEET['velocity'][i], PANDA_DATASHEET['acceleration'][i],
            PANDA_DATASHEET['jerk'][i])
