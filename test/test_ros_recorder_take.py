"""The recorder's receive path (cdmp_ros/ros/recorder_take.py): the take thread drains raw
subscriptions into a bag exactly and in order, closes chunks when idle, and the Fast DDS profile
is loaded only when the user chose none and never opens a non-loopback or multicast locator."""
import os
import xml.etree.ElementTree as ET

import pytest

from bag_ros_util import Peer
from conftest import wait_for
from node_harness import WAIT_S, wait_matched
from cdmp_ros.bag import BagReader, BagWriter
from cdmp_ros.bag.cdr import decode_string, encode_string
from cdmp_ros.ros.recorder_take import (PROFILE_OVERRIDE, TakeThread, ThreadTakenGroup,
                                        apply_dds_profile, find_profile, set_fifo)

NS = '{http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles}'


@pytest.mark.ros
def test_take_thread_records_exactly_in_order_and_flushes_when_idle(tmp_path):
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from std_msgs.msg import String
    peer = Peer('take_peer')
    bag = str(tmp_path / 'take')
    writer = BagWriter(bag, flush_period=0.05)
    writer.add_topic('/take', 'std_msgs/msg/String')
    qos = QoSProfile(depth=5000, reliability=ReliabilityPolicy.RELIABLE)
    taker = TakeThread(writer, period=0.005)
    try:
        sub = peer.node.create_subscription(String, '/take', lambda m: None, qos,
                                            callback_group=ThreadTakenGroup(), raw=True)
        # publisher and subscription queues (5000) hold all 2000: none is ever replaced
        pub = peer.publisher(String, '/take', depth=5000)
        assert wait_matched(pub)
        taker.add('/take', sub)
        taker.start()
        size0 = os.path.getsize(writer.path)
        for i in range(2000):
            pub.publish(encode_string(f'm{i}'))
        # the last chunk reaches the file with no new message arriving (flush_if_due of the
        # idle take thread)
        assert wait_for(lambda: writer.message_count == 2000, WAIT_S), writer.message_count
        assert wait_for(lambda: writer._chunk_started is None, WAIT_S)
        assert os.path.getsize(writer.path) > size0
        taker.stop()
        assert taker.drain() == 0 and taker.error is None
    finally:
        taker.stop()
        writer.close()
        peer.close()
    got = [decode_string(m.data) for m in BagReader(bag).messages()]
    assert got == [f'm{i}' for i in range(2000)]  # the executor never took any of them


def test_take_thread_rejects_a_bad_period(tmp_path):
    with BagWriter(str(tmp_path / 'b')) as w:
        with pytest.raises(ValueError, match='period'):
            TakeThread(w, period=0.0)


def test_set_fifo_reports_refusals_and_never_raises():
    msg = set_fifo([2 ** 22 + 12345], 10)  # above pid_max: no such thread
    assert 'SCHED_FIFO refused' in msg and str(2 ** 22 + 12345) in msg
    assert set_fifo([], 10) == ''


def test_dds_profile_is_loaded_only_when_no_profile_is_set():
    path = find_profile()
    assert path and os.path.isfile(path)
    env = {}
    assert apply_dds_profile(env) == path
    assert env == {'FASTRTPS_DEFAULT_PROFILES_FILE': path}
    user = {'FASTRTPS_DEFAULT_PROFILES_FILE': '/mine.xml'}
    assert apply_dds_profile(user) is None and user == {'FASTRTPS_DEFAULT_PROFILES_FILE':
                                                        '/mine.xml'}
    assert apply_dds_profile({'FASTDDS_DEFAULT_PROFILES_FILE': '/x.xml'}) is None
    assert apply_dds_profile({'RMW_IMPLEMENTATION': 'rmw_cyclonedds_cpp'}) is None
    off = {PROFILE_OVERRIDE: ''}
    assert apply_dds_profile(off) is None and 'FASTRTPS_DEFAULT_PROFILES_FILE' not in off
    other = {PROFILE_OVERRIDE: '/other.xml'}
    assert apply_dds_profile(other) == '/other.xml'


def test_dds_profile_keeps_the_network_rule():
    """Loopback-only UDP, no multicast anywhere, builtin transports (all interfaces) off."""
    root = ET.parse(find_profile()).getroot()
    text = ET.tostring(root, encoding='unicode').lower()
    assert 'multicast' not in text
    udp = [t for t in root.iter(f'{NS}transport_descriptor')
           if t.find(f'{NS}type').text == 'UDPv4']
    assert udp
    for t in udp:
        assert [a.text for a in t.iter(f'{NS}address')] == ['127.0.0.1']
    types = {t.find(f'{NS}type').text for t in root.iter(f'{NS}transport_descriptor')}
    assert types == {'UDPv4', 'SHM'}
    (builtin,) = root.iter(f'{NS}useBuiltinTransports')
    assert builtin.text == 'false'
    for tag in ('initialPeersList', 'metatrafficUnicastLocatorList', 'defaultUnicastLocatorList',
                'discovery_config'):
        assert not list(root.iter(f'{NS}{tag}')), tag  # discovery stays the environment's
