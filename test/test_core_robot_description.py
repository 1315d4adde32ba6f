"""Which robot model a node runs with (issue 31, item 7): :class:`RobotModelSelector` of
cdmp_ros/ros/robot_model.py, no ROS. The ``robot_description`` parameter, else the
``robot_description`` topic (waited for ``robot_description_timeout`` s at start-up), else
``urdf_path``; a description arriving later is compared with the model in use and reported,
never swapped in; one that is not a URDF of the configured joints is rejected, naming why.
"""
import os

import numpy as np
import pytest

from cdmp_ros.core.errors import CdmpError, ValidationError
from cdmp_ros.core.kinematics.builders import PANDA_JOINTS
from cdmp_ros.ros.robot_model import (DIFFERS, REJECTED, ROBOT_DESCRIPTION,
                                      ROBOT_DESCRIPTION_TOPIC, SAME, USED, RobotModelSelector,
                                      default_urdf_path)

FILE = default_urdf_path()
PANDA = open(FILE).read()
V1 = 'velocity="2.1750"'  # panda_joint1's velocity limit, the first in the file
assert PANDA.index(V1) < PANDA.index('name="panda_joint2"')


def tightened(velocity='1.5', text=PANDA):
    """The Panda URDF with panda_joint1's velocity limit set to ``velocity`` [rad/s]."""
    return text.replace(V1, f'velocity="{velocity}"', 1)


def absolute_meshes(text=PANDA):
    """Mesh names that resolve from any working directory (``file://``)."""
    return text.replace('package://meshes/', f'file://{os.path.dirname(FILE)}/meshes/')


def test_the_topic_is_waited_for_only_without_the_parameter_and_with_a_timeout():
    assert RobotModelSelector('', PANDA_JOINTS).wait_s == 0.0                    # the default
    assert RobotModelSelector('', PANDA_JOINTS, timeout=2.5).wait_s == 2.5
    assert RobotModelSelector('', PANDA_JOINTS, PANDA, timeout=2.5).wait_s == 0.0
    assert RobotModelSelector('', PANDA_JOINTS, '  \n', timeout=2.5).wait_s == 2.5  # blank


def test_the_parameter_wins_over_the_topic_and_urdf_path():
    sel = RobotModelSelector('/nonexistent.urdf', PANDA_JOINTS, tightened('1.2'), timeout=5.0)
    model, note, warn = sel.start(tightened('1.5'))   # a message offered anyway: ignored
    assert model.source == ROBOT_DESCRIPTION and model.text == tightened('1.2')
    assert model.chain.velocity_limits[0] == 1.2
    assert (note, warn) == ('', False)
    assert sel.topic_state == 'none received'


def test_a_description_received_at_start_up_is_used():
    sel = RobotModelSelector('/nonexistent.urdf', PANDA_JOINTS, timeout=5.0)
    model, note, warn = sel.start(tightened())
    assert model.source == ROBOT_DESCRIPTION_TOPIC == 'robot_description topic'
    assert model.chain.velocity_limits[0] == 1.5
    assert list(model.chain.joint_names) == list(PANDA_JOINTS)
    assert 'robot_description topic' in note and not warn
    assert sel.verdict.status == USED and sel.topic_state == 'in use'
    # its re-delivery (latched, or republished unchanged) is the model in use
    v = sel.offer(tightened())
    assert v.status == USED and v.repeat and not v.warn


def test_without_a_description_urdf_path_is_used_and_logged():
    sel = RobotModelSelector('', PANDA_JOINTS, timeout=2.0)
    model, note, warn = sel.start(None)
    assert model.source == FILE and model.text is None
    assert warn and 'no robot_description message within robot_description_timeout = 2 s' in note
    assert FILE in note
    # timeout 0: nothing waited for, nothing to say
    model, note, warn = RobotModelSelector('', PANDA_JOINTS).start(None)
    assert model.source == FILE and (note, warn) == ('', False)


# (text, reason category, words of the reason)
BAD = [('garbage', 'malformed', 'not a valid URDF: malformed XML'),
       ('', 'malformed', 'not a valid URDF: malformed XML'),
       ('<robot name="x"><link name="a"/><link name="a"/></robot>', 'malformed',
        "link 'a' defined twice"),
       ('<launch/>', 'malformed', 'root element expected <robot>'),
       (PANDA.replace('panda_joint1', 'j1'), 'joint_names',
        'not a robot of the configured joint_names and tip_link: joint_names: expected the '
        "movable joints of 'robot_description' from 'panda_link0' to tip_link "
        "'panda_hand' ['j1', 'panda_joint2'"),
       ('<robot name="ur"><link name="base"/></robot>', 'joint_names',
        "tip_link: expected one of the links of 'ur'")]


@pytest.mark.parametrize('text,category,words', BAD)
def test_a_bad_description_at_start_up_is_rejected_and_urdf_path_used(text, category, words):
    sel = RobotModelSelector('', PANDA_JOINTS, timeout=2.0)
    model, note, warn = sel.start(text)
    assert model.source == FILE
    v = sel.verdict
    assert v.status == REJECTED and v.category == category and v.warn
    assert v.message.startswith('robot_description: ') and words in v.message, v.message
    assert warn and words in note and f'using urdf_path {FILE}' in note
    assert sel.topic_state == 'rejected: ' + v.message[len('robot_description: '):]


def test_joints_other_than_the_configured_ones_are_rejected():
    joints = list(PANDA_JOINTS)
    joints[0], joints[1] = joints[1], joints[0]
    # the parameter or the file: the node does not start (as before)
    with pytest.raises(ValidationError, match='joint_names'):
        RobotModelSelector('', joints).start(None)
    # the file is fine for the Panda joints; the topic's description of them is not for
    # another order of joint_names
    sel = RobotModelSelector('', PANDA_JOINTS, timeout=1.0)
    sel.start(None)
    sel.joint_names = joints
    v = sel.offer(PANDA)
    assert v.status == REJECTED and v.category == 'joint_names'
    assert v.message.startswith('robot_description: not a robot of the configured joint_names')
    assert f"tip_link 'panda_hand' {list(PANDA_JOINTS)}, got {joints}" in v.message


def test_a_file_that_cannot_be_loaded_still_stops_the_start():
    sel = RobotModelSelector('/nonexistent.urdf', PANDA_JOINTS, timeout=1.0)
    with pytest.raises(ValidationError, match='urdf_path'):
        sel.start(None)
    with pytest.raises(ValidationError, match='urdf_path'):  # a rejected message: the file
        RobotModelSelector('/nonexistent.urdf', PANDA_JOINTS, timeout=1.0).start('garbage')
    with pytest.raises(ValidationError, match='robot_description'):
        RobotModelSelector('', PANDA_JOINTS, '<robot name="x"><link name="a"/></robot>').start()


def test_a_later_description_is_compared_and_reported_never_swapped_in():
    sel = RobotModelSelector('', PANDA_JOINTS)           # the default: no wait
    model, _, _ = sel.start()
    chain = model.chain
    v = sel.offer(PANDA)                                  # the same robot as the file
    assert v.status == SAME and not v.warn and v.message == f'matches the model in use ({FILE})'
    v = sel.offer(tightened())
    assert v.status == DIFFERS and v.warn and not v.repeat
    assert v.message == (f'differs from the model in use ({FILE}): panda_joint1 velocity '
                         '2.175 -> 1.5; a restart of the node with robot_description_timeout '
                         '> 0 applies it')
    assert sel.model is model and model.chain is chain   # kept
    assert np.all(chain.velocity_limits[:4] == 2.175)
    v = sel.offer(tightened())                            # a repeat: judged once
    assert v.status == DIFFERS and v.repeat
    v = sel.offer('garbage')
    assert v.status == REJECTED and v.warn and v.category == 'malformed'
    assert sel.model is model
    v = sel.offer(PANDA)                                  # back to the model in use
    assert v.status == SAME and not v.warn and sel.topic_state.startswith('matches')


def test_the_report_of_a_different_description_says_how_to_apply_it():
    other = tightened('1.2')
    # the model came from the topic: a restart applies the new one
    sel = RobotModelSelector('', PANDA_JOINTS, timeout=3.0)
    sel.start(tightened())
    v = sel.offer(other)
    assert v.status == DIFFERS and v.warn
    assert v.message == ('differs from the model in use (the robot_description topic at '
                         'start-up): panda_joint1 velocity 1.5 -> 1.2; a restart of the node '
                         'applies it')
    # waited, nothing came in time, then it came
    sel = RobotModelSelector('', PANDA_JOINTS, timeout=3.0)
    sel.start(None)
    v = sel.offer(other)
    assert 'it came after robot_description_timeout = 3 s: a restart of the node applies it' \
        in v.message and v.warn
    # the parameter takes precedence: reported, no warning
    sel = RobotModelSelector('', PANDA_JOINTS, tightened())
    sel.start()
    v = sel.offer(other)
    assert v.status == DIFFERS and not v.warn
    assert v.message.startswith('differs from the model in use (the robot_description '
                                'parameter, which takes precedence): panda_joint1 velocity')
    assert not sel.offer('garbage').warn
    assert sel.offer(tightened()).status == SAME    # the parameter's own text


def test_kinematics_and_limits_are_compared_other_elements_are_not():
    sel = RobotModelSelector('', PANDA_JOINTS)
    sel.start()
    moved = PANDA.replace('xyz="0 -0.316 0"', 'xyz="0 -0.320 0"', 1)   # panda_joint3's origin
    assert moved != PANDA
    v = sel.offer(moved)
    assert v.status == DIFFERS and 'origin or axis of panda_joint3' in v.message, v.message
    narrowed = PANDA.replace('lower="-2.9671" upper="2.9671"', 'lower="-2.5" upper="2.9671"', 1)
    v = sel.offer(narrowed)
    assert 'panda_joint1 lower -2.9671 -> -2.5' in v.message and 'upper' not in v.message
    heavier = PANDA.replace('<mass value="2.9"/>', '<mass value="3.9"/>', 1)
    assert heavier != PANDA
    assert sel.offer(heavier).status == SAME    # inertia: not used by the nodes


def test_collision_capsules_are_part_of_the_model(tmp_path, monkeypatch):
    """The streamer's coupling_capsule_links: loaded with the model from the same source; a
    description whose meshes are found nowhere (working directory, beside urdf_path, share
    directories) is rejected; the stock one's package://meshes/... are found beside the
    Panda file of urdf_path ''."""
    monkeypatch.chdir(tmp_path)
    links = ('panda_hand',)
    sel = RobotModelSelector('', PANDA_JOINTS, timeout=1.0, capsule_links=links)
    model, _, _ = sel.start(PANDA)
    assert model.source == ROBOT_DESCRIPTION_TOPIC and model.capsules[0].link == 'panda_hand'
    lost = PANDA.replace('package://meshes/collision/hand.obj', 'package://nowhere/hand.obj')
    assert lost != PANDA
    sel = RobotModelSelector('', PANDA_JOINTS, timeout=1.0, capsule_links=links)
    model, note, warn = sel.start(lost)
    assert model.source == FILE and len(model.capsules) == 1
    v = sel.verdict
    assert v.status == REJECTED and 'robot_description: coupling_capsule_links' in v.message
    assert 'not found' in v.message and warn
    v = sel.offer(absolute_meshes())               # found: the same capsule as the file's
    assert v.status == SAME, v.message
    sel = RobotModelSelector('', PANDA_JOINTS, timeout=1.0, capsule_links=links)
    model, _, _ = sel.start(absolute_meshes())
    assert model.source == ROBOT_DESCRIPTION_TOPIC and model.capsules[0].link == 'panda_hand'
    scaled = absolute_meshes().replace('<mesh filename="file://', '<mesh scale="2 2 2" '
                                       'filename="file://')
    v = sel.offer(scaled)
    assert v.status == DIFFERS and 'collision capsule of panda_hand' in v.message, v.message


def test_offer_before_start_is_a_programming_error():
    with pytest.raises(CdmpError, match='before start'):
        RobotModelSelector('', PANDA_JOINTS).offer(PANDA)
