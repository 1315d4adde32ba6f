"""Shared fixtures. ROS processes started by tests obey the network rule: localhost-only
discovery and a private ROS_DOMAIN_ID (see ../shared/design.md, Environment facts)."""
import os
import random
import sys

import pytest
from hypothesis import settings

# Property tests draw the same examples on every run (a CI run never fails on a draw that the
# previous one did not make), keep no example database between runs, and have no per-example
# deadline (a loaded machine is slow, not wrong).
settings.register_profile('cdmp', derandomize=True, database=None, deadline=None)
settings.load_profile('cdmp')

REPO_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

# The network rule holds for everything this test session starts, including rclpy in-process.
os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
os.environ.setdefault('ROS_DOMAIN_ID', str(random.Random(os.getpid()).randint(100, 199)))
os.environ.setdefault('AMENT_PREFIX_PATH', sys.prefix)
os.environ.setdefault('MPLBACKEND', 'Agg')


def module_domain(offset: int) -> int:
    """A private domain id for one test module: the session's ``ROS_DOMAIN_ID`` plus ``offset``.

    Modules that keep processes running get their own offset so that a process left over from
    one module never talks to the next; sessions started with different ``ROS_DOMAIN_ID`` values
    (parallel checkouts, soak runs) never share a domain as long as their ids are 10 apart.
    """
    return (int(os.environ['ROS_DOMAIN_ID']) + int(offset)) % 233


def ros_env(domain_id=None) -> dict:
    """Environment for a ROS child process: localhost discovery, private domain id."""
    env = dict(os.environ)
    env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    env['ROS_DOMAIN_ID'] = str(domain_id if domain_id is not None else os.environ['ROS_DOMAIN_ID'])
    env['AMENT_PREFIX_PATH'] = sys.prefix
    env['PYTHONUNBUFFERED'] = '1'
    return env


@pytest.fixture
def repo_root():
    return REPO_ROOT


@pytest.fixture
def rng():
    import numpy as np
    return np.random.default_rng(12345)
