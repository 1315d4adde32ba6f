"""The obstacle -> joint_reference path of docs/architecture.md, measured.

``scripts/obstacle_path.py`` traces (``sys.setprofile``) an in-process streamer node from the
moment its ``obstacles`` subscription callback receives a serialized MarkerArray until it
publishes the first ``joint_reference`` computed with that obstacle: the files of cdmp_ros
whose code runs on that path. docs/architecture.md lists them in the section headed
**An obstacle message, to the next joint reference**; the two must agree.
"""
import os
import re

import pytest

from conftest import REPO_ROOT, load_script, module_domain

SCRIPT = os.path.join(REPO_ROOT, 'scripts', 'obstacle_path.py')
ARCHITECTURE = os.path.join(REPO_ROOT, 'docs', 'architecture.md')
HEADING = '**An obstacle message, to the next joint reference**'


def _load_script():
    return load_script('obstacle_path')


@pytest.fixture(scope='module')
def traced():
    """One measurement for the module (a node in its own context on a private domain)."""
    return _load_script().measure(domain_id=module_domain(71))


@pytest.fixture(scope='module')
def threaded():
    """The same with the tick thread, as a node process runs by default."""
    return _load_script().measure(domain_id=module_domain(71), tick_thread=True)


def documented_path(text: str) -> set:
    """Every backticked path starting with ``cdmp_ros/`` in the paragraphs from the one that
    starts with :data:`HEADING` up to the next paragraph that starts with ``**``."""
    paragraphs = [p.strip() for p in re.split(r'\n\s*\n', text)]
    starts = [i for i, p in enumerate(paragraphs) if p.startswith(HEADING)]
    assert len(starts) == 1, f'{len(starts)} paragraphs start with {HEADING}'
    section = [paragraphs[starts[0]]]
    for p in paragraphs[starts[0] + 1:]:
        if p.startswith('**'):
            break
        section.append(p)
    return set(re.findall(r'`(cdmp_ros/[^`\s]+)`', '\n\n'.join(section)))


def test_the_documented_section_is_parsed():
    text = ('intro\n\n' + HEADING + ' (x):\n\n1. `cdmp_ros/a.py`: `ros/b.py` and `c`;\n'
            '2. `cdmp_ros/core/d.py`\n\nmore `cdmp_ros/e.py`\n\n**Next**: `cdmp_ros/f.py`\n')
    assert documented_path(text) == {'cdmp_ros/a.py', 'cdmp_ros/core/d.py', 'cdmp_ros/e.py'}


def test_the_obstacle_reaches_the_first_reference_through_the_streamer_and_stepper(traced):
    # the obstacle was accepted and acted on the first reference published after it
    assert traced.rejected == 0
    assert traced.published >= 1 and traced.coupled >= 1, traced
    assert traced.latency_taken, traced
    assert any(abs(a) > 0.0 for a in traced.coupling_joint), traced
    assert traced.acted
    files = traced.files
    assert files, 'no cdmp_ros code traced'
    assert 'cdmp_ros/ros/streamer_node.py' in files, sorted(files)
    assert 'cdmp_ros/core/dmp/stepper.py' in files, sorted(files)
    assert {'StreamerNode._on_obstacles', 'StreamerNode._tick',
            'StreamerNode._publish_step'} <= files['cdmp_ros/ros/streamer_node.py']
    for path in files:
        assert os.path.isfile(os.path.join(REPO_ROOT, path)), path


def test_with_the_tick_thread_the_path_adds_only_the_wake_up(traced, threaded):
    """As a node process runs by default (tick thread, ``obstacle_wakeup``): the same files,
    the obstacle waking the tick thread, and the obstacle acting on the first reference."""
    assert threaded.acted, threaded
    assert set(traced.files) <= set(threaded.files), sorted(set(traced.files)
                                                            - set(threaded.files))
    assert 'DeadlineSleeper.wake' in threaded.files['cdmp_ros/common/realtime.py']


#: Runs on the path only when the tick that takes the obstacle woke at its deadline rather than
#: by the obstacle's wake-up (it times the lateness of the wake-up): a race of the two threads.
DEADLINE_ONLY = {'cdmp_ros/ros/diagnostics.py'}


def test_docs_architecture_lists_exactly_the_files_of_the_obstacle_path(threaded):
    """The files of a node process (tick thread) are the documented ones."""
    with open(ARCHITECTURE) as f:
        documented = documented_path(f.read())
    measured = set(threaded.files)
    assert DEADLINE_ONLY <= documented
    assert measured <= documented and documented - measured <= DEADLINE_ONLY, (
        f'measured {len(measured)} files; documented but not on the path: '
        f'{sorted(documented - measured)}; on the path but not documented: '
        f'{sorted(measured - documented)}')
