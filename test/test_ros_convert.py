"""cdmp_ros.ros.convert / params / diagnostics on message objects (no DDS traffic)."""
import math

import numpy as np
import pytest
from sensor_msgs.msg import JointState
from visualization_msgs.msg import Marker

from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.kinematics.closest import Box, OrientedBox, Sphere
from cdmp_ros.ros.convert import (JointStateMapper, JointStateWriter, ObstacleSet, check_stamp,
                                  stamp_to_ns)
from node_harness import PANDA_JOINTS

Q = np.arange(7) * 0.1 - 0.3


def js(names=PANDA_JOINTS, position=Q, velocity=()):
    m = JointState()
    m.name = list(names)
    m.position = [float(v) for v in position]
    m.velocity = [float(v) for v in velocity]
    return m


# -- JointState ---------------------------------------------------------------------------------
def test_joint_state_in_order_and_shuffled():
    mapper = JointStateMapper(PANDA_JOINTS)
    q, qd = mapper.to_arrays(js())
    np.testing.assert_array_equal(q, Q)
    assert qd is None
    perm = [4, 0, 6, 2, 1, 5, 3]
    q, qd = mapper.to_arrays(js([PANDA_JOINTS[i] for i in perm], Q[perm], Q[perm] * 2))
    np.testing.assert_array_equal(q, Q)
    np.testing.assert_array_equal(qd, 2 * Q)


def test_extra_joints_ignored_only_when_allowed():
    names = list(PANDA_JOINTS) + ['panda_finger_joint1']
    msg = js(names, list(Q) + [0.04])
    np.testing.assert_array_equal(JointStateMapper(PANDA_JOINTS, allow_extra=True)
                                  .to_arrays(msg)[0], Q)
    with pytest.raises(ValidationError,
                       match=r'goal\.name: unknown joints \[.panda_finger_joint1.\]'):
        JointStateMapper(PANDA_JOINTS).to_arrays(msg, 'goal')


@pytest.mark.parametrize('msg,text', [
    (js(PANDA_JOINTS[:6], Q[:6]), r"missing joints \['panda_joint7'\]"),
    (js(list(PANDA_JOINTS[:6]) + ['panda_joint1'], Q), "duplicate joint name 'panda_joint1'"),
    (js(position=Q[:4]), r'joint_states\.position: expected 7 values \(one per name\), got 4'),
    (js(velocity=[0.0] * 3), r'joint_states\.velocity: expected 0 or 7 values, got 3'),
    (js(position=[0, 0, math.nan, 0, 0, 0, 0]),
     r"position of 'panda_joint3': expected a finite value, got nan"),
    (js(velocity=[0, 0, 0, 0, 0, math.inf, 0]),
     r"velocity of 'panda_joint6': expected a finite value, got inf"),
    (js(names=[]), r'missing joints'),
])
def test_bad_joint_states_name_the_field(msg, text):
    with pytest.raises(ValidationError, match=text):
        JointStateMapper(PANDA_JOINTS).to_arrays(msg)


def test_need_velocity():
    with pytest.raises(ValidationError, match='velocity: expected 7 values, got none'):
        JointStateMapper(PANDA_JOINTS).to_arrays(js(), need_velocity=True)


def test_writer_reuses_the_message_and_its_arrays():
    w = JointStateWriter(JointState(), PANDA_JOINTS, 'panda_link0')
    pos = w.msg.position
    msg = w.fill(1_500_000_123, Q, 2 * Q)
    assert msg is w.msg and msg.position is pos
    assert list(msg.position) == Q.tolist() and list(msg.velocity) == (2 * Q).tolist()
    assert stamp_to_ns(msg.header.stamp) == 1_500_000_123 and msg.name == list(PANDA_JOINTS)


def test_stamps():
    now = 10_000 * 10 ** 9
    m = JointState()
    check_stamp('s', m.header.stamp, now, 5.0, 1.0)  # zero = unstamped, accepted
    with pytest.raises(ValidationError, match='s: expected a stamp, got zero'):
        check_stamp('s', m.header.stamp, now, 5.0, 1.0, accept_zero=False)
    m.header.stamp.sec = 10_002
    with pytest.raises(ValidationError, match=r's: stamp 2\.000 s in the future'):
        check_stamp('s', m.header.stamp, now, 5.0, 1.0)
    m.header.stamp.sec = 9_990
    with pytest.raises(ValidationError, match=r's: stamp 10\.000 s in the past'):
        check_stamp('s', m.header.stamp, now, 5.0, 1.0)
    m.header.stamp.sec = 9_996
    check_stamp('s', m.header.stamp, now, 5.0, 1.0)


# -- MarkerArray --------------------------------------------------------------------------------
def marker(ns='a', id=0, type=Marker.SPHERE, action=Marker.ADD, xyz=(0.5, 0.0, 0.3),
           scale=(0.1, 0.1, 0.1), frame='panda_link0', quat=(0.0, 0.0, 0.0, 1.0), life=0.0):
    m = Marker(ns=ns, id=id, type=type, action=action)
    m.header.frame_id = frame
    m.pose.position.x, m.pose.position.y, m.pose.position.z = xyz
    o = m.pose.orientation
    o.x, o.y, o.z, o.w = quat
    m.scale.x, m.scale.y, m.scale.z = scale
    m.lifetime.sec = int(life)
    m.lifetime.nanosec = int(round((life - int(life)) * 1e9))
    return m


def test_sphere_and_cube_become_obstacles():
    s = ObstacleSet()
    assert s.apply([marker(), marker(id=1, type=Marker.CUBE, scale=(0.2, 0.4, 0.1)),
                    marker(ns='b', frame='')]) == []
    items = dict(zip(s.snapshot.keys, s.snapshot.items))
    assert items[('a', 0)] == Sphere((0.5, 0.0, 0.3), 0.05)
    box = items[('a', 1)]
    assert isinstance(box, Box)
    np.testing.assert_allclose(box.lower, (0.4, -0.2, 0.25))
    np.testing.assert_allclose(box.upper, (0.6, 0.2, 0.35))
    assert len(s) == 3


def test_rotated_cube_is_an_oriented_box():
    s = ObstacleSet()
    c = math.cos(math.pi / 8)
    q = (0.0, 0.0, math.sin(math.pi / 8), c)  # 45 deg about z
    assert s.apply([marker(type=Marker.CUBE, scale=(0.2, 0.4, 0.1), quat=q,
                           xyz=(0.5, 0.1, 0.3))]) == []
    box = s.snapshot.items[0]
    assert isinstance(box, OrientedBox)
    np.testing.assert_allclose(box.center, (0.5, 0.1, 0.3), atol=1e-12)
    np.testing.assert_allclose(box.size, (0.2, 0.4, 0.1), atol=1e-12)
    r = math.sqrt(0.5)
    np.testing.assert_allclose(box.rotation, [[r, -r, 0], [r, r, 0], [0, 0, 1]], atol=1e-12)
    # the same rotation as the library's own quaternion constructor
    ref = OrientedBox.from_quaternion((0.5, 0.1, 0.3), (0.2, 0.4, 0.1), q)
    np.testing.assert_allclose(box.rotation, ref.rotation, atol=1e-12)
    # unrotated: still the axis-aligned Box (boards of Eq. 30-31 need it)
    s.apply([marker(id=1, type=Marker.CUBE, scale=(0.2, 0.4, 0.1))])
    assert isinstance(s.snapshot.items[1], Box)


def test_modify_delete_and_deleteall_per_ns_id():
    s = ObstacleSet()
    s.apply([marker(id=0), marker(id=1), marker(ns='b', id=0)])
    s.apply([marker(id=0, xyz=(0.1, 0.2, 0.3))])  # MODIFY == ADD with the same key
    assert dict(zip(s.snapshot.keys, s.snapshot.items))[('a', 0)].center == (0.1, 0.2, 0.3)
    assert len(s) == 3
    assert s.apply([marker(id=1, action=Marker.DELETE)]) == [] and len(s) == 2
    errs = s.apply([marker(id=1, action=Marker.DELETE)])
    assert 'DELETE of unknown obstacle' in str(errs[0])
    s.apply([marker(ns='b', action=Marker.DELETEALL)])  # only namespace b
    assert s.snapshot.keys == (('a', 0),)
    s.apply([marker(ns='b', id=5), marker(ns='', action=Marker.DELETEALL)])  # everything
    assert len(s) == 0 and s.snapshot.items == ()


@pytest.mark.parametrize('kw,text', [
    (dict(scale=(-0.1, 0.1, 0.1)), r'markers\[0\]\.scale\.x: expected a finite positive size'),
    (dict(scale=(0.0, 0.1, 0.1)), r'scale\.x: expected a finite positive size \[m\], got 0\.0'),
    (dict(scale=(math.nan, 0.1, 0.1)), r'scale\.x: expected a finite positive size'),
    (dict(scale=(50.0, 0.1, 0.1)), r'scale\.x: expected at most 10\.0 m, got 50\.0'),
    (dict(type=Marker.CUBE, scale=(0.1, 0.1, -1)), r'scale\.z: expected a finite positive'),
    (dict(xyz=(math.inf, 0, 0)), r'pose\.position\.x: expected a finite value, got inf'),
    (dict(xyz=(1e4, 0, 0)), r'expected within 100\.0 m of the base'),
    (dict(type=Marker.CYLINDER), r'type: expected SPHERE \(2\) or CUBE \(1\), got 3 \(CYLINDER\)'),
    (dict(type=42), r'got 42 \(unknown\)'),
    (dict(action=1), r'action: expected ADD/MODIFY \(0\), DELETE \(2\) or DELETEALL \(3\), got 1'),
    (dict(frame='world'), r"frame_id: expected the robot base frame 'panda_link0'"),
    (dict(type=Marker.CUBE, quat=(0, 0, 0, 0)), r'orientation: expected a unit quaternion'),
    (dict(type=Marker.CUBE, quat=(math.nan, 0, 0, 1)), r'orientation\.x: expected a finite'),
])
def test_bad_markers_are_rejected_with_reasons(kw, text):
    s = ObstacleSet()
    errs = s.apply([marker(**kw), marker(ns='ok')])
    assert len(errs) == 1 and len(s) == 1  # the valid marker still applies
    assert isinstance(errs[0], ValidationError)
    import re
    assert re.search(text, str(errs[0])), str(errs[0])


def test_obstacle_limit_and_lifetime():
    s = ObstacleSet(max_obstacles=2)
    errs = s.apply([marker(id=i) for i in range(3)])
    assert len(s) == 2 and 'obstacle limit reached (2)' in str(errs[0])
    assert s.apply([marker(id=0, xyz=(0.0, 0.0, 1.0))]) == []  # modifying is still possible
    s = ObstacleSet()
    s.apply([marker(id=0, life=0.5), marker(id=1)], now=10.0)
    assert not s.expire(10.4) and len(s) == 2
    assert s.expire(10.5) and s.snapshot.keys == (('a', 1),)


# -- params and diagnostics (in-process node, no traffic) ---------------------------------------
@pytest.fixture
def node():
    import rclpy
    ctx = rclpy.Context()
    from conftest import module_domain
    rclpy.init(context=ctx, domain_id=module_domain(1))
    n = rclpy.create_node('params_test', context=ctx)
    yield n
    n.destroy_node()
    rclpy.try_shutdown(context=ctx)


def test_parameters_mirror_the_config_with_descriptors(node):
    from rcl_interfaces.msg import ParameterType
    from rclpy.parameter import Parameter
    from cdmp_ros.core.coupling.potential_fields import RepellerField
    from cdmp_ros.core.streaming.streamer import StreamerConfig
    from cdmp_ros.ros.params import ConfigParameters
    changes = []
    p = ConfigParameters(node, [('', StreamerConfig), ('repeller', RepellerField)],
                         on_change=changes.append)
    assert p[''] == StreamerConfig() and p['repeller'] == RepellerField()
    d = node.describe_parameter('rate')
    assert d.read_only and 'Range [1.0, 2000.0]' in d.description
    assert d.floating_point_range[0].to_value == 2000.0
    d = node.describe_parameter('max_catch_up')
    assert d.type == ParameterType.PARAMETER_INTEGER and d.integer_range[0].from_value == 1
    d = node.describe_parameter('repeller.gain')
    assert 'gain' in d.description and 'm^3/s^2' in d.description  # from the field
    assert node.describe_parameter('joint_names').type == \
        ParameterType.PARAMETER_STRING_ARRAY
    d = node.describe_parameter('tcp_offset')
    assert d.type == ParameterType.PARAMETER_DOUBLE_ARRAY and 'fingertips' in d.description
    r = node.set_parameters([Parameter('tcp_offset', value=[0.0, 0.0, 0.2])])[0]
    assert r.successful and p[''].tcp_offset == (0.0, 0.0, 0.2)
    r = node.set_parameters([Parameter('tcp_offset', value=[0.0, 0.1])])[0]
    assert not r.successful and 'tcp_offset' in r.reason
    r = node.set_parameters([Parameter('box_field_kind', value='wall')])[0]
    assert not r.successful and 'box_field_kind' in r.reason
    r = node.set_parameters([Parameter('stop_time', value=-1.0)])[0]
    assert not r.successful and 'stop_time' in r.reason
    r = node.set_parameters([Parameter('repeller.gain', value=-1.0)])[0]
    assert not r.successful and 'RepellerField.gain' in r.reason
    r = node.set_parameters([Parameter('stop_time', value=2)])[0]
    assert r.successful and p[''].stop_time == 2.0 and changes[-1][''].stop_time == 2.0
    r = node.set_parameters([Parameter('stop_time', value='slow')])[0]
    assert not r.successful and 'stop_time' in r.reason


def test_empty_string_arrays_are_declared_with_a_value(tmp_path):
    """A tuple-of-str field is a STRING_ARRAY parameter that has a value, ``[]`` included (as
    ``ros2 param get`` and the get_parameters service see it): by default, from an untyped
    empty list in a parameter file and from ``-p name:=[]``; a list given stays; read-only
    fields stay read-only, writable ones writable."""
    import dataclasses
    import rclpy
    from rcl_interfaces.msg import ParameterType
    from rclpy.parameter import Parameter
    from cdmp_ros.core.config_fields import param
    from cdmp_ros.core.streaming.config import StreamerConfig
    from cdmp_ros.ros.params import ConfigParameters
    from conftest import module_domain

    @dataclasses.dataclass(frozen=True)
    class Writable:
        names: tuple = param((), 'Names, writable.')

    path = tmp_path / 'arrays.yaml'
    path.write_text('/**:\n  ros__parameters:\n    coupling_links: []\n')
    default_links = list(StreamerConfig().coupling_links)
    assert default_links and StreamerConfig().controller_joints == ()
    runs = [([], {'controller_joints': [], 'coupling_capsule_links': [],
                  'coupling_links': default_links, 'w.names': []}),
            (['--params-file', str(path), '-p', 'controller_joints:=[]',
              '-p', 'coupling_capsule_links:=[panda_link4]', '-p', 'w.names:=[]'],
             {'controller_joints': [], 'coupling_capsule_links': ['panda_link4'],
              'coupling_links': [], 'w.names': []})]
    for args, expected in runs:
        ctx = rclpy.Context()
        rclpy.init(context=ctx, domain_id=module_domain(1), args=['--ros-args', *args])
        try:
            node = rclpy.create_node('params_arrays', context=ctx)
            p = ConfigParameters(node, [('', StreamerConfig), ('w', Writable)])
            for name, value in expected.items():
                got = node.get_parameter(name)
                assert got.type_ == Parameter.Type.STRING_ARRAY and list(got.value) == value, (
                    args, name, got.type_, got.value)
                # what the get_parameters service answers (ros2 param get)
                msg = got.get_parameter_value()
                assert msg.type == ParameterType.PARAMETER_STRING_ARRAY, (args, name)
                assert list(msg.string_array_value) == value, (args, name)
                d = node.describe_parameter(name)
                assert d.type == ParameterType.PARAMETER_STRING_ARRAY, (args, name)
                assert d.read_only == (name != 'w.names'), (args, name)
                prefix, _, field = name.rpartition('.')
                assert getattr(p[prefix], field) == tuple(value), (args, name)
            r = node.set_parameters([Parameter('controller_joints', value=['panda_joint1'])])[0]
            assert not r.successful and 'read-only' in r.reason
            r = node.set_parameters([Parameter('w.names', value=['a', 'b'])])[0]
            assert r.successful and p['w'].names == ('a', 'b')
            node.destroy_node()
        finally:
            rclpy.try_shutdown(context=ctx)


def test_every_node_parameter_has_its_descriptor_in_code():
    """Every parameter of every node takes its description from the field metadata (no
    docstring is parsed): a field without one is refused at declaration."""
    import dataclasses
    from cdmp_ros.core.adaptation.config import AdaptRequestConfig, AdapterConfig
    from cdmp_ros.core.coupling.obstacle import CouplingConfig
    from cdmp_ros.core.coupling.potential_fields import BoardField, ConstantField, RepellerField
    from cdmp_ros.core.coupling.obstacle import DampingConfig
    from cdmp_ros.core.dmp.dmp import DmpConfig
    from cdmp_ros.core.dmp.improve import CostConfig, ImproveConfig
    from cdmp_ros.core.learning import LearnerConfig, PrompLearnConfig
    from cdmp_ros.core.streaming.config import StreamerConfig
    from cdmp_ros.ros.params import descriptor_for, parameter_fields
    from cdmp_ros.sim.node_config import SimConfig
    classes = (StreamerConfig, CouplingConfig, DampingConfig, RepellerField, ConstantField,
               BoardField, AdapterConfig, AdaptRequestConfig, SimConfig, LearnerConfig, DmpConfig,
               PrompLearnConfig, ImproveConfig, CostConfig)
    for cls in classes:
        for f, kind, _ in parameter_fields(cls):
            d = descriptor_for(cls, f, kind, f.name)
            assert d.description.startswith(f.metadata['description']), (cls, f.name)
    assert 'm/s^2' in descriptor_for(ConstantField, *parameter_fields(ConstantField)[0][:2],
                                     'box_field.magnitude').description

    @dataclasses.dataclass(frozen=True)
    class Undocumented:
        """Attributes
        ----------
        gain : float
            Described only here.
        """
        gain: float = 1.0

    (f, kind, _), = parameter_fields(Undocumented)
    with pytest.raises(ValidationError, match='Undocumented.gain: a parameter field needs a '
                                              'description'):
        descriptor_for(Undocumented, f, kind, 'gain')


def test_diagnostics_reporter_summarises_rejections_and_timings(node):
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
    from cdmp_ros.ros.diagnostics import OK, DiagnosticsReporter
    sent = []

    class Pub:
        def publish(self, m):
            sent.append(m)

    r = DiagnosticsReporter(node, Pub(), 'streamer', window=100)
    r.set_state(OK, 'running', state='running')
    for i in range(5):
        r.reject('goal', f'bad {i}')
    for v in range(1, 201):
        r.timing('tick', v * 1e-5)
    stamp = node.get_clock().now().to_msg()
    assert r.publish_if_due(stamp) and not r.publish_if_due(stamp)
    arr = sent[-1]
    assert isinstance(arr, DiagnosticArray)
    st = {s.name: s for s in arr.status}
    assert st['streamer: state'].level == DiagnosticStatus.WARN  # recent rejection
    assert 'rejected input on goal' in st['streamer: state'].message
    kv = {k.key: k.value for k in st['streamer: input goal'].values}
    assert kv == {'rejected_total': '5', 'rejected_since_last_report': '5',
                  'last_reason': 'bad 4'}
    tk = {k.key: k.value for k in st['streamer: timing'].values}
    assert tk['tick_count'] == '200' and float(tk['tick_max_ms']) == pytest.approx(2.0)
    assert float(tk['tick_mean_ms']) == pytest.approx(1.505)  # the last 100 samples
    assert float(tk['tick_p99_ms']) == pytest.approx(1.99)
    r.publish(stamp)
    st = {s.name: s for s in sent[-1].status}
    assert st['streamer: state'].level == DiagnosticStatus.OK
    assert st['streamer: input goal'].message == 'ok'


def test_diagnostics_status_names_start_with_the_fully_qualified_node_name(node):
    """Every node shares /diagnostics: the status-name prefix is the node's fully qualified name
    without the leading slash (the node name in the root namespace), ``__ns`` and ``__node``
    remaps included."""
    import rclpy
    from cdmp_ros.core.topics import DIAGNOSTICS_TOPIC
    from cdmp_ros.ros.diagnostics import OK, DiagnosticsReporter
    from conftest import module_domain
    assert DIAGNOSTICS_TOPIC == '/diagnostics'  # absolute (design.md, Topics)

    class Pub:
        def publish(self, m):
            pass

    assert DiagnosticsReporter(node, Pub()).name == 'params_test'
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=module_domain(1),
               args=['--ros-args', '-r', '__ns:=/left/arm', '-r', '__node:=streamer2'])
    try:
        n = rclpy.create_node('streamer', context=ctx)
        r = DiagnosticsReporter(n, Pub())
        r.set_state(OK, 'running')
        r.reject('goal', 'bad')
        r.timing('tick', 1e-4)
        arr = r.build(n.get_clock().now().to_msg())
        assert [s.name for s in arr.status] == ['left/arm/streamer2: state',
                                                'left/arm/streamer2: input goal',
                                                'left/arm/streamer2: timing']
        assert {s.hardware_id for s in arr.status} == {'/left/arm/streamer2'}
        n.destroy_node()
    finally:
        rclpy.try_shutdown(context=ctx)


#: What config/streamer.yaml sets beyond the code's defaults: the coupling of the Panda's whole
#: arm (capsules fitted to the collision geometry of links 3-7 and the hand, the fingers'
#: capsule on panda_link7's axis) with the gains and damping it was tuned with. The code's
#: defaults stay those of the core classes, which the paper reproductions use.
SHIPPED_COUPLING = {
    'coupling_capsule_links': ('panda_link3', 'panda_link4', 'panda_link5', 'panda_link6',
                               'panda_link7', 'panda_hand'),
    'coupling_links': ('panda_link7',), 'coupling.link_radius': 0.06, 'damping.epsilon': 0.1,
    'repeller.gain': 0.03, 'repeller.influence_distance': 0.25}


def test_config_file_mirrors_every_parameter_with_its_default():
    """config/streamer.yaml lists every parameter of the streamer, each at its default but
    for the shipped coupling (:data:`SHIPPED_COUPLING`)."""
    from cdmp_ros.core.coupling.obstacle import DampingConfig
    from cdmp_ros.core.coupling.potential_fields import BoardField, ConstantField, RepellerField
    from cdmp_ros.core.coupling.obstacle import CouplingConfig
    from cdmp_ros.core.streaming.streamer import StreamerConfig
    from node_harness import config_file_parameters, parameter_defaults
    sections = [('', StreamerConfig), ('coupling', CouplingConfig), ('damping', DampingConfig),
                ('repeller', RepellerField), ('box_field', ConstantField),
                ('board_field', BoardField)]
    defaults = parameter_defaults(sections)
    assert set(SHIPPED_COUPLING) <= set(defaults)
    assert all(defaults[k] != v for k, v in SHIPPED_COUPLING.items())
    assert config_file_parameters('streamer') == {**defaults, **SHIPPED_COUPLING}
