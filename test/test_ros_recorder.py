"""Recorder node as a real process: clean-stop exactness (SIGINT and SIGTERM; take thread and
executor callbacks), recording of all discovered topics, QoS and type hash in the bag."""
import os

import numpy as np
import pytest

from bag_ros_util import Peer
from node_harness import assert_clean_stop, start_node, stop_process, wait_acked, wait_matched
from cdmp_ros.bag import BagReader
from cdmp_ros.bag.metadata import read_metadata
from conftest import module_domain

pytestmark = pytest.mark.ros
# own domain: "every discovered topic" must not see a topic of another module's processes
DOMAIN = module_domain(9)


@pytest.fixture
def peer():
    p = Peer(domain_id=DOMAIN)
    yield p
    p.close()


@pytest.mark.parametrize('sig_name, take_period, rt', [('SIGINT', 0.005, 0), ('SIGTERM', 0.0, 0),
                                                       ('SIGINT', 0.005, 10)])
def test_clean_stop_records_exactly_what_was_published(tmp_path, peer, sig_name, take_period,
                                                       rt):
    import signal
    from std_msgs.msg import String
    from cdmp_ros.bag.cdr import encode_string
    bag = str(tmp_path / 'rec')
    rec = start_node('recorder', {'output': bag, 'topics': ['/exact'],
                                  'take_period': take_period, 'realtime_priority': rt},
                     log_path=str(tmp_path / 'rec.log'), domain_id=DOMAIN)
    try:
        pub = peer.publisher(String, '/exact')  # depth 1000 >= 500: nothing is replaced
        assert wait_matched(pub), 'recorder never matched'
        rng = np.random.default_rng(3)
        # DDS pads a serialized payload to a multiple of 4 bytes; choose lengths that need no
        # padding so that 'byte-identical' is exact (CDR string: 4 + 4 + len + NUL bytes)
        texts = [f'{i:04d}' + 'x' * int(4 * rng.integers(0, 80) + 3) for i in range(500)]
        sent = [encode_string(t) for t in texts]
        assert all(len(d) % 4 == 0 for d in sent)
        for data in sent:
            pub.publish(data)
        # every message is in the recorder's queue; the clean stop must take and write them
        assert wait_acked(pub), 'the recorder never acknowledged every message'
        assert_clean_stop(stop_process(rec, getattr(signal, sig_name)),
                          (tmp_path / 'rec.log').read_text(), 'recorder')
    finally:
        stop_process(rec, signal.SIGKILL)
    if rt:  # granted (root / CAP_SYS_NICE / rtprio limit) or refused with a warning
        log = (tmp_path / 'rec.log').read_text()
        assert 'under SCHED_FIFO priority 10' in log or 'SCHED_FIFO' in log and 'refused' in log
    msgs = list(BagReader(bag).messages())
    assert [m.data for m in msgs] == sent  # N = N, byte-identical, in order
    assert [m.sequence for m in msgs] == list(range(1, 501))
    meta = read_metadata(bag)
    assert meta.message_count == 500
    (topic,) = meta.topics
    assert topic.type == 'std_msgs/msg/String'
    assert topic.type_description_hash.startswith('RIHS01_')
    assert topic.offered_qos_profiles[0]['reliability'] == 'reliable'
    assert topic.offered_qos_profiles[0]['durability'] == 'volatile'


def test_records_all_discovered_topics_but_not_rosout(tmp_path, peer):
    from sensor_msgs.msg import JointState
    from std_msgs.msg import String
    bag = str(tmp_path / 'all')
    params_file = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
                               'config', 'bag.yaml')
    rec = start_node('recorder', {'output': bag, 'discovery_period': 0.1},
                     log_path=str(tmp_path / 'rec.log'), extra=['--params-file', params_file],
                     domain_id=DOMAIN)
    try:
        pa = peer.publisher(String, '/topic_a')
        pb = peer.publisher(JointState, '/topic_b')
        assert wait_matched(pa) and wait_matched(pb), 'the recorder never subscribed to both'
        for i in range(10):
            pa.publish(String(data=str(i)))
            pb.publish(JointState(name=['q'], position=[float(i)]))
        assert wait_acked(pa) and wait_acked(pb)
        assert_clean_stop(stop_process(rec), (tmp_path / 'rec.log').read_text(), 'recorder')
    finally:
        stop_process(rec, 9)
    counts = {t.name: (t.type, t.message_count) for t in read_metadata(bag).topics}
    assert counts == {'/topic_a': ('std_msgs/msg/String', 10),
                      '/topic_b': ('sensor_msgs/msg/JointState', 10)}
    assert os.path.getsize(os.path.join(bag, 'all_0.mcap')) > 0
