"""Compatibility both ways with the `rosbags` library and `mcap-ros2-support`.

Messages of every recorded type are built with the real ROS message classes, serialized by
rclpy, written by our BagWriter and read back by both libraries: field values must be
identical.  Bags written by both libraries are read by our BagReader with identical messages.
"""
import array
import dataclasses
import os
from pathlib import Path

import numpy as np
import pytest

from cdmp_ros.bag import BagReader, BagWriter
from cdmp_ros.bag.metadata import read_metadata


def _plain(obj):
    """Nested plain-Python value of a message from rclpy, rosbags or mcap_ros2."""
    if hasattr(obj, 'get_fields_and_field_types'):  # rclpy; its 'byte' fields are bytes
        return {k: (getattr(obj, k)[0] if t == 'octet' else _plain(getattr(obj, k)))
                for k, t in obj.get_fields_and_field_types().items()}
    if hasattr(obj, '__dataclass_fields__'):  # rosbags
        return {f.name: _plain(getattr(obj, f.name)) for f in dataclasses.fields(obj)
                if f.name != '__msgtype__' and not f.name.isupper()}  # no constants
    if hasattr(obj, '__slots__') and type(obj).__module__ != 'builtins':  # mcap_ros2
        return {k: _plain(getattr(obj, k)) for k in obj.__slots__}
    if isinstance(obj, (bytes, bytearray)):
        return list(obj)
    if isinstance(obj, (list, tuple, array.array, np.ndarray)):
        return [_plain(x) for x in obj]
    if isinstance(obj, (np.floating, float)):
        return float(obj)
    if isinstance(obj, (np.integer, int)) and not isinstance(obj, bool):
        return int(obj)
    return obj


def _samples():
    """(topic, type, [rclpy messages]) for every recorded type, with non-trivial content."""
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
    from geometry_msgs.msg import PointStamped, PoseStamped
    from rosgraph_msgs.msg import Clock
    from sensor_msgs.msg import JointState
    from std_msgs.msg import String
    from visualization_msgs.msg import Marker, MarkerArray

    js = JointState(name=['j1', 'j2'], position=[0.5, -0.25], velocity=[1.0, 2.0])
    js.header.stamp.sec, js.header.frame_id = 3, 'base'
    pose = PoseStamped()
    pose.header.frame_id = 'world'
    pose.pose.position.x, pose.pose.orientation.w = 1.5, 1.0
    pt = PointStamped()
    pt.point.x, pt.point.y, pt.point.z = 0.3, -0.2, 0.9
    m = Marker(ns='obstacles', id=4, type=Marker.SPHERE, action=Marker.ADD)
    m.scale.x = m.scale.y = m.scale.z = 0.2
    m.color.r, m.color.a = 1.0, 0.5
    m.pose.position.z = 0.4
    m2 = Marker(ns='walls', id=1, type=Marker.CUBE, text='board')
    m2.points = [pose.pose.position, pose.pose.position]
    diag = DiagnosticArray(status=[DiagnosticStatus(
        level=DiagnosticStatus.WARN, name='adapter', message='slow solve',
        hardware_id='cpu', values=[KeyValue(key='solve_ms', value='12.5')])])
    clock = Clock()
    clock.clock.sec, clock.clock.nanosec = 10, 500
    return [('/joint_states', 'sensor_msgs/msg/JointState', [js, JointState(name=['x'])]),
            ('/ee_pose', 'geometry_msgs/msg/PoseStamped', [pose]),
            ('/goal_point', 'geometry_msgs/msg/PointStamped', [pt]),
            ('/obstacles', 'visualization_msgs/msg/MarkerArray',
             [MarkerArray(markers=[m, m2]), MarkerArray()]),
            ('/constraints', 'std_msgs/msg/String', [String(data='{"constraints": []}')]),
            ('/diagnostics', 'diagnostic_msgs/msg/DiagnosticArray', [diag]),
            ('/clock', 'rosgraph_msgs/msg/Clock', [clock])]


def _message_class(type_name):
    import importlib
    pkg, ns, name = type_name.split('/')
    return getattr(importlib.import_module(f'{pkg}.{ns}'), name)


@pytest.fixture(scope='module')
def our_bag(tmp_path_factory):
    """Payloads are encoded by mcap_ros2 from the field values and checked against rclpy.

    (rmw_fastrtps' own buffers may carry uninitialised trailing padding, which rosbags'
    strict size check rejects; the container, not the payload, is under test here.)
    """
    from mcap_ros2._dynamic import serialize_dynamic
    from rclpy.serialization import deserialize_message
    from cdmp_ros.bag.schemas import schema_text
    bag = str(tmp_path_factory.mktemp('compat') / 'ours')
    expected = []
    t = 1_000_000
    with BagWriter(bag) as w:
        for topic, type_name, msgs in _samples():
            w.add_topic(topic, type_name)
            encode = serialize_dynamic(type_name, schema_text(type_name))[type_name]
            for msg in msgs:
                t += 1000
                data = encode(_plain(msg))
                assert deserialize_message(data, _message_class(type_name)) == msg
                w.write(topic, data, t)
                expected.append((topic, type_name, t, _plain(msg)))
    return bag, expected


def test_rosbags_reads_our_bag(our_bag):
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore
    bag, expected = our_bag
    store = get_typestore(Stores.ROS2_JAZZY)
    with Reader(Path(bag)) as reader:
        assert reader.message_count == len(expected)
        got = [(c.topic, c.msgtype, t, _plain(store.deserialize_cdr(raw, c.msgtype)))
               for c, t, raw in reader.messages()]
        hashes = {c.topic: c.digest for c in reader.connections}
    assert got == expected
    assert hashes['/joint_states'].startswith('RIHS01_')


def test_rosbags_parses_our_schemas(our_bag):
    """rosbags' own message-definition parser accepts our stored ros2msg texts."""
    from rosbags.typesys import get_types_from_msg
    from cdmp_ros.bag.schemas import schema_text
    for _, type_name, _ in _samples():
        types = get_types_from_msg(schema_text(type_name), type_name)
        assert type_name in types


def test_mcap_ros2_reads_our_bag(our_bag):
    from mcap_ros2.reader import read_ros2_messages
    bag, expected = our_bag
    path = os.path.join(bag, 'ours_0.mcap')
    got = [(m.channel.topic, m.schema.name, m.log_time_ns, _plain(m.ros_msg))
           for m in read_ros2_messages(path)]
    assert got == expected


def test_our_reader_reads_rosbags_bag(tmp_path):
    from rclpy.serialization import deserialize_message
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness
    from rosbags.interfaces import QosReliability, QosTime
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore
    store = get_typestore(Stores.ROS2_JAZZY)
    JointState = store.types['sensor_msgs/msg/JointState']
    Header = store.types['std_msgs/msg/Header']
    Time = store.types['builtin_interfaces/msg/Time']
    String = store.types['std_msgs/msg/String']
    inf = QosTime(sec=9223372036, nsec=854775807)
    qos = Qos(QosHistory.KEEP_LAST, 7, QosReliability.RELIABLE, QosDurability.TRANSIENT_LOCAL,
              inf, inf, QosLiveliness.AUTOMATIC, inf, False)
    bag = tmp_path / 'rb'
    sent = []
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        cj = w.add_connection('/joint_states', JointState.__msgtype__, typestore=store,
                              offered_qos_profiles=[qos])
        cs = w.add_connection('/chatter', String.__msgtype__, typestore=store)
        for i in range(30):
            msg = JointState(header=Header(stamp=Time(sec=i, nanosec=7), frame_id='b'),
                             name=['a', 'b'], position=np.array([i, -i], dtype=float),
                             velocity=np.array([], dtype=float), effort=np.array([0.5, 1.5]))
            raw = bytes(store.serialize_cdr(msg, JointState.__msgtype__))
            w.write(cj, 100 + i, raw)
            sent.append(('/joint_states', 100 + i, _plain(msg)))
            if i % 3 == 0:
                s = String(data=f'n{i}')
                w.write(cs, 100 + i, bytes(store.serialize_cdr(s, String.__msgtype__)))
                sent.append(('/chatter', 100 + i, _plain(s)))
    reader = BagReader(str(bag))
    topics = reader.verify()
    assert topics['/joint_states'].message_count == 30
    assert read_metadata(str(bag)).topics[0].offered_qos_profiles[0]['depth'] == 7
    got = [(m.topic, m.log_time, _plain(deserialize_message(m.data, _message_class(m.type))))
           for m in reader.messages()]
    assert got == sent


def test_our_reader_reads_mcap_ros2_file(tmp_path):
    from mcap_ros2.writer import Writer
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import JointState
    from cdmp_ros.bag.schemas import schema_text
    path = str(tmp_path / 'x.mcap')
    sent = []
    with open(path, 'wb') as f:
        w = Writer(f)
        schema = w.register_msgdef('sensor_msgs/msg/JointState',
                                   schema_text('sensor_msgs/msg/JointState'))
        for i in range(20):
            msg = {'header': {'stamp': {'sec': i, 'nanosec': 0}, 'frame_id': 'f'},
                   'name': ['q'], 'position': [0.1 * i], 'velocity': [], 'effort': []}
            w.write_message('/js', schema, msg, log_time=i * 10, publish_time=i * 10)
            sent.append((i * 10, [0.1 * i]))
        w.finish()
    got = [(m.log_time, list(deserialize_message(m.data, JointState).position))
           for m in BagReader(path).messages()]
    assert got == sent


def test_diagnostic_arrays_decode_as_rclpy_serialises_them():
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
    from rclpy.serialization import serialize_message
    from cdmp_ros.bag.cdr import decode_diagnostic_array
    from cdmp_ros.bag.errors import BagFormatError
    m = DiagnosticArray()
    m.header.stamp.sec, m.header.frame_id = 5, 'base'
    m.status = [DiagnosticStatus(level=b'\x01', name='streamer: inputs', message='ok ü',
                                 hardware_id='hw', values=[KeyValue(key='a', value='1'),
                                                           KeyValue(key='bb', value='')]),
                DiagnosticStatus(level=b'\x02', name='y')]
    data = serialize_message(m)
    assert decode_diagnostic_array(data) == [
        {'level': 1, 'name': 'streamer: inputs', 'message': 'ok ü', 'hardware_id': 'hw',
         'values': {'a': '1', 'bb': ''}},
        {'level': 2, 'name': 'y', 'message': '', 'hardware_id': '', 'values': {}}]
    with pytest.raises(BagFormatError, match='DiagnosticArray: CDR data ends'):
        decode_diagnostic_array(data[:-3])
