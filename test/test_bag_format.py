"""Bag layer: schemas, CDR codecs, writer/reader round trip, metadata.yaml (rosbag2 v9)."""
import os
import sys

import numpy as np
import pytest
import yaml

from cdmp_ros.bag import BagError, BagReader, BagWriter, bag_info
from cdmp_ros.bag.cdr import (decode_joint_state, decode_string, encode_clock, encode_joint_state,
                              encode_string)
from cdmp_ros.bag.metadata import read_metadata
from cdmp_ros.bag.scan import ScanState, scan
from cdmp_ros.bag.schemas import normalize_type, schema_text, type_hash
from conftest import load_script

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
gen = load_script('gen_msg_schemas')
SHARE = os.path.join(sys.prefix, 'share')


@pytest.mark.parametrize('type_name', gen.RECORDED_TYPES)
def test_committed_schema_matches_installed_messages(type_name):
    """msg_schemas/msg holds exactly what the generator builds from the installed .msg files."""
    assert schema_text(type_name) == gen.full_text(SHARE, type_name)
    assert type_hash(type_name) == gen.type_hash(SHARE, type_name)


def test_schema_layout_is_rosbag2s():
    text = schema_text('sensor_msgs/JointState')
    with open(os.path.join(SHARE, 'sensor_msgs', 'msg', 'JointState.msg')) as f:
        top = f.read()
    assert text.startswith(top)
    rest = text[len(top):]
    # dependency blocks: "\n" + 80 '=' + "\nMSG: <type>\n" + verbatim file text
    blocks = rest.split('\n' + '=' * 80 + '\nMSG: ')
    assert blocks[0] == ''
    deps = [b.split('\n', 1)[0] for b in blocks[1:]]
    assert deps == ['std_msgs/Header', 'builtin_interfaces/Time']
    with open(os.path.join(SHARE, 'std_msgs', 'msg', 'Header.msg')) as f:
        assert blocks[1].split('\n', 1)[1] == f.read()


def test_normalize_type_and_unknown_schema():
    assert normalize_type('std_msgs/String') == 'std_msgs/msg/String'
    assert normalize_type('std_msgs/msg/String') == 'std_msgs/msg/String'
    with pytest.raises(BagError, match='type_name'):
        normalize_type('String')
    with pytest.raises(BagError, match='no ros2msg schema'):
        schema_text('nonexistent_msgs/msg/Foo')
    # types outside msg_schemas/msg are built from the installed .msg files
    assert schema_text('geometry_msgs/msg/Twist').count('MSG: geometry_msgs/Vector3') == 1


@pytest.mark.parametrize('vel,eff', [([0.5, -1.0, 2.0], []), ([], []), ([], [1.0, 2.0, 3.0]),
                                     ([1.0, 2.0, 3.0], [4.0, 5.0, 6.0])])
def test_joint_state_cdr_interoperates_with_rclpy(vel, eff):
    """Our JointState codec and rclpy's serializer read each other's bytes.

    (Byte equality is not expected: rmw leaves alignment padding uninitialised.)
    """
    from rclpy.serialization import deserialize_message, serialize_message
    from sensor_msgs.msg import JointState
    msg = JointState()
    msg.header.stamp.sec, msg.header.stamp.nanosec = 12, 345
    msg.header.frame_id = 'base'
    msg.name = ['a', 'bb', 'ccc']
    msg.position = [0.1, 0.2, 0.3]
    msg.velocity = vel
    msg.effort = eff
    ours = encode_joint_state(12 * 10 ** 9 + 345, ['a', 'bb', 'ccc'], [0.1, 0.2, 0.3], vel, eff,
                              frame_id='base')
    assert deserialize_message(ours, JointState) == msg
    for data in (ours, serialize_message(msg)):
        js = decode_joint_state(data)
        assert js.stamp_ns == 12 * 10 ** 9 + 345 and js.frame_id == 'base'
        assert js.name == ('a', 'bb', 'ccc')
        np.testing.assert_array_equal(js.position, [0.1, 0.2, 0.3])
        np.testing.assert_array_equal(js.velocity, vel)
        np.testing.assert_array_equal(js.effort, eff)


def test_string_and_clock_cdr_interoperate_with_rclpy():
    from rclpy.serialization import deserialize_message, serialize_message
    from rosgraph_msgs.msg import Clock
    from std_msgs.msg import String
    assert deserialize_message(encode_string('héllo'), String).data == 'héllo'
    assert decode_string(serialize_message(String(data='héllo'))) == 'héllo'
    c = deserialize_message(encode_clock(7 * 10 ** 9 + 9), Clock)
    assert (c.clock.sec, c.clock.nanosec) == (7, 9)


def test_cdr_decoder_rejects_garbage():
    from cdmp_ros.bag import BagFormatError
    good = encode_joint_state(1, ['a'], [1.0])
    with pytest.raises(BagFormatError):
        decode_joint_state(good[:-3])
    with pytest.raises(BagFormatError):
        decode_joint_state(b'\x00\x01\x00\x00' + b'\xff' * 16)
    with pytest.raises(BagFormatError, match='encapsulation'):
        decode_joint_state(b'\x01\x00' + good[2:])


def _write_sample(bag_dir, n=50, **kw):
    with BagWriter(bag_dir, **kw) as w:
        w.add_topic('/joint_states', 'sensor_msgs/JointState')
        w.add_topic('chatter', 'std_msgs/msg/String')
        sent = []
        for i in range(n):
            data = encode_joint_state(i, ['j1', 'j2'], [i * 0.1, -i * 0.1])
            w.write('/joint_states', data, 1000 + 10 * i)
            sent.append(('/joint_states', 1000 + 10 * i, data))
            if i % 10 == 0:
                data = encode_string(f'msg {i}')
                w.write('chatter', data, 1000 + 10 * i + 1, publish_time_ns=999)
                sent.append(('chatter', 1000 + 10 * i + 1, data))
            if i % 17 == 0:
                w.flush()
    return sent


@pytest.mark.parametrize('compression', ['zstd', 'lz4', 'none'])
def test_round_trip_exact(tmp_path, compression):
    bag = str(tmp_path / 'bag')
    sent = _write_sample(bag, compression=compression)
    got = [(m.topic, m.log_time, m.data) for m in BagReader(bag).messages()]
    assert got == sent
    seqs = [m.sequence for m in BagReader(bag).messages(['chatter'])]
    assert seqs == [1, 2, 3, 4, 5]
    assert [m.publish_time for m in BagReader(bag).messages(['chatter'])] == [999] * 5


def test_metadata_yaml_is_rosbag2_v9(tmp_path):
    bag = str(tmp_path / 'rec')
    _write_sample(bag)
    assert sorted(os.listdir(bag)) == ['metadata.yaml', 'rec_0.mcap']
    with open(os.path.join(bag, 'metadata.yaml')) as f:
        info = yaml.safe_load(f)['rosbag2_bagfile_information']
    assert info['version'] == 9 and info['storage_identifier'] == 'mcap'
    assert info['relative_file_paths'] == ['rec_0.mcap']
    assert info['message_count'] == 55
    assert info['starting_time']['nanoseconds_since_epoch'] == 1000
    assert info['duration']['nanoseconds'] == 490
    topics = {t['topic_metadata']['name']: t for t in info['topics_with_message_count']}
    js = topics['/joint_states']
    assert js['message_count'] == 50
    assert js['topic_metadata']['type'] == 'sensor_msgs/msg/JointState'
    assert js['topic_metadata']['serialization_format'] == 'cdr'
    assert js['topic_metadata']['type_description_hash'] == type_hash('sensor_msgs/JointState')
    qos = js['topic_metadata']['offered_qos_profiles'][0]
    assert qos['reliability'] == 'reliable' and qos['history'] == 'keep_last'
    meta = read_metadata(bag)
    assert meta.message_count == 55 and meta.topics[1].name == 'chatter'


def test_mcap_records_profile_schema_encoding_and_crcs(tmp_path):
    bag = str(tmp_path / 'b')
    _write_sample(bag)
    state = ScanState()
    recs = list(scan(os.path.join(bag, 'b_0.mcap'), state))
    assert state.profile == 'ros2' and state.footer_seen
    assert state.chunks >= 3  # explicit flushes closed chunks
    assert {s.encoding for s in state.schemas.values()} == {'ros2msg'}
    assert {c.message_encoding for c in state.channels.values()} == {'cdr'}
    assert 'rosbag2' in state.metadata
    assert len(recs) == 2 + 2 + 55
    # every chunk carries a CRC: flip one byte of compressed data -> CRC or zstd error
    from mcap.reader import make_reader
    with open(os.path.join(bag, 'b_0.mcap'), 'rb') as f:
        summary = make_reader(f).get_summary()
    assert all(ci.chunk_length > 0 for ci in summary.chunk_indexes)
    import struct
    import zlib
    with open(os.path.join(bag, 'b_0.mcap'), 'rb') as f:
        raw = f.read()
    ci = summary.chunk_indexes[0]
    body = raw[ci.chunk_start_offset + 9:]
    crc = struct.unpack_from('<I', body, 24)[0]
    assert crc != 0
    import zstandard
    clen_pos = 28 + 4 + 4
    data = body[clen_pos + 8:clen_pos + 8 + struct.unpack_from('<Q', body, clen_pos)[0]]
    assert zlib.crc32(zstandard.ZstdDecompressor().decompress(
        data, max_output_size=struct.unpack_from('<Q', body, 16)[0])) == crc


def test_writer_errors(tmp_path):
    bag = str(tmp_path / 'b')
    w = BagWriter(bag)
    with pytest.raises(BagError, match='not registered'):
        w.write('/nope', b'', 1)
    w.add_topic('/a', 'std_msgs/String')
    assert w.add_topic('/a', 'std_msgs/msg/String') == w.add_topic('/a', 'std_msgs/String')
    with pytest.raises(BagError, match='already recorded'):
        w.add_topic('/a', 'sensor_msgs/JointState')
    w.close()
    with pytest.raises(BagError, match='closed'):
        w.add_topic('/b', 'std_msgs/String')
    with pytest.raises(BagError, match='not empty'):
        BagWriter(bag)
    with pytest.raises(BagError, match='compression'):
        BagWriter(str(tmp_path / 'c'), compression='gzip')


def test_bag_info_and_missing_bag(tmp_path):
    bag = str(tmp_path / 'b')
    _write_sample(bag)
    info = bag_info(bag)
    assert info['message_count'] == 55 and info['duration_ns'] == 490
    counts = [(t['name'], t['count']) for t in info['topics']]
    assert counts == [('/joint_states', 50), ('chatter', 5)]
    with pytest.raises(BagError, match='neither'):
        BagReader(str(tmp_path / 'missing'))
    os.remove(os.path.join(bag, 'metadata.yaml'))
    with pytest.raises(BagError, match='recover'):
        BagReader(bag)
    # a bare .mcap file is readable on its own
    assert len(list(BagReader(os.path.join(bag, 'b_0.mcap')).messages())) == 55


def test_metadata_count_mismatch_is_reported(tmp_path):
    from cdmp_ros.bag import BagFormatError
    bag = str(tmp_path / 'b')
    _write_sample(bag)
    path = os.path.join(bag, 'metadata.yaml')
    text = open(path).read().replace('message_count: 50', 'message_count: 51')
    open(path, 'w').write(text)
    with pytest.raises(BagFormatError, match='declares 51'):
        BagReader(bag).verify()


def test_mcap_library_reads_our_files_with_indexes_and_crcs(tmp_path):
    """The reference `mcap` reader: summary statistics, chunk/message indexes, CRCs."""
    from mcap.reader import make_reader
    from mcap.stream_reader import StreamReader
    bag = str(tmp_path / 'm')
    sent = _write_sample(bag)
    path = os.path.join(bag, 'm_0.mcap')
    with open(path, 'rb') as f:
        reader = make_reader(f, validate_crcs=True)
        summary = reader.get_summary()
        stats = summary.statistics
        assert stats.message_count == 55 and stats.chunk_count == len(summary.chunk_indexes)
        assert stats.message_start_time == 1000 and stats.message_end_time == 1490
        assert sorted(stats.channel_message_counts.values()) == [5, 50]
        assert {c.topic for c in summary.channels.values()} == {'/joint_states', 'chatter'}
        got = [(c.topic, m.log_time, m.data) for _, c, m in reader.iter_messages(
            log_time_order=False)]
        assert sorted(got) == sorted(sent)
        only = [m.data for _, _, m in reader.iter_messages(topics=['chatter'])]
        assert only == [d for t, _, d in sent if t == 'chatter']
        assert reader.get_header().profile == 'ros2'
        assert 'rosbag2' in [m.name for m in reader.iter_metadata()]
    with open(path, 'rb') as f:  # streaming with data-section and chunk CRC validation
        n = sum(1 for r in StreamReader(f, validate_crcs=True).records
                if type(r).__name__ == 'Message')
    assert n == 55


def _write_from_two_threads(bag: str) -> int:
    """Messages and chunk flushes from one thread while another registers 60 topics (what the
    recorder does: its take thread writes, its executor thread's discovery adds topics), with
    the interpreter switching threads every microsecond so that the two interleave."""
    import threading
    w = BagWriter(bag, chunk_size=4096, flush_period=0)
    w.add_topic('/joint_states', 'sensor_msgs/msg/JointState')
    data = encode_joint_state(1, ['a', 'b'], [0.1, 0.2], [0.0, 0.0])
    start = threading.Barrier(2)

    def add_topics():
        start.wait()
        for i in range(60):
            w.add_topic(f'/late_{i}', 'std_msgs/msg/String')

    adder = threading.Thread(target=add_topics)
    old = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)
    try:
        adder.start()
        start.wait()
        n = 0
        while adder.is_alive() or n < 2000:
            w.write('/joint_states', data, 1000 + n)
            n += 1
            if n % 7 == 0:
                w.flush()
        adder.join()
    finally:
        sys.setswitchinterval(old)
    w.close()
    return n


def test_topics_registered_while_another_thread_writes_keep_the_file_valid(tmp_path):
    """CI once read a demo bag whose data-section CRC did not match: the recorder's discovery
    wrote Channel records while its take thread wrote chunks.  The writer's lock serialises
    them; every CRC, the footer and the message count must hold."""
    from mcap.stream_reader import StreamReader
    for k in range(3):
        bag = str(tmp_path / f'b{k}')
        n = _write_from_two_threads(bag)
        infos = BagReader(bag).verify()
        assert infos['/joint_states'].message_count == n
        assert len(infos) == 61
        with open(os.path.join(bag, f'b{k}_0.mcap'), 'rb') as f:
            assert sum(1 for r in StreamReader(f, validate_crcs=True).records
                       if type(r).__name__ == 'Message') == n
