"""Crash safety of the bag files: truncated, footer-less and corrupted files, huge declared
lengths, and `recover_bag` giving a gap-free prefix with a report of what was lost."""
import os
import resource
import shutil
import struct

import numpy as np
import pytest

from cdmp_ros.bag import (BagCrcError, BagError, BagFormatError, BagReader, BagTruncatedError,
                          BagWriter, recover_bag)
from cdmp_ros.bag.cdr import encode_joint_state
from cdmp_ros.bag.scan import OP_CHUNK, ScanState, scan


def _make(tmp_path, n=600, flush_every=50, name='rec'):
    bag = str(tmp_path / name)
    msgs = []
    with BagWriter(bag, flush_period=0) as w:
        w.add_topic('/js', 'sensor_msgs/JointState')
        for i in range(n):
            data = encode_joint_state(i, ['a', 'b'], [np.sin(i), np.cos(i)])
            w.write('/js', data, 10_000 + i * 1000)
            msgs.append(data)
            if (i + 1) % flush_every == 0:
                w.flush()
    return bag, os.path.join(bag, name + '_0.mcap'), msgs


def _chunk_offsets(path):
    """Start offsets of the chunk records, walking the data section."""
    raw = open(path, 'rb').read()
    pos, out = 8, []
    while pos < len(raw) - 8:
        op = raw[pos]
        length = struct.unpack_from('<Q', raw, pos + 1)[0]
        if op == OP_CHUNK:
            out.append(pos)
        if op == 0x0F:  # data end
            break
        pos += 9 + length
    return out, pos


def _crash(path, size):
    """Simulate a crashed writer: cut the file and drop metadata.yaml."""
    with open(path, 'r+b') as f:
        f.truncate(size)
    meta = os.path.join(os.path.dirname(path), 'metadata.yaml')
    if os.path.exists(meta):
        os.remove(meta)


def test_footerless_file_is_refused_then_fully_recovered(tmp_path):
    bag, path, msgs = _make(tmp_path)
    _, data_end = _chunk_offsets(path)
    _crash(path, data_end)  # every chunk intact, no data end, no summary, no footer
    with pytest.raises(BagError, match='recover'):
        BagReader(bag)
    with pytest.raises(BagTruncatedError, match='recover'):
        list(BagReader(path).messages())
    report = recover_bag(bag)
    assert report.recovered == {'/js': 600} and not report.sequence_gaps
    assert report.bytes_discarded == 0 and report.error is not None
    assert [m.data for m in BagReader(bag).messages()] == msgs
    assert BagReader(bag).verify()['/js'].message_count == 600
    assert os.path.exists(path + '.crashed')


@pytest.mark.parametrize('seed', range(6))
def test_truncation_at_random_offsets_recovers_a_gap_free_prefix(tmp_path, seed):
    bag, path, msgs = _make(tmp_path)
    size = os.path.getsize(path)
    chunks, data_end = _chunk_offsets(path)
    raw = open(path, 'rb').read()
    chunk_ends = [c + 9 + struct.unpack_from('<Q', raw, c + 1)[0] for c in chunks]
    cut = int(np.random.default_rng(seed).integers(200, size - 1))
    _crash(path, cut)
    with pytest.raises(BagFormatError):
        list(BagReader(path).messages())
    out = str(tmp_path / 'fixed')
    report = recover_bag(bag, output=out)
    got = [m.data for m in BagReader(out).messages()]
    assert got == msgs[:len(got)]  # a prefix, in order, byte-identical
    assert [m.sequence for m in BagReader(out).messages()] == list(range(1, len(got) + 1))
    assert not report.sequence_gaps
    assert report.message_count == len(got)
    # whole chunks of 50 survive: at most the chunk being cut is lost (or nothing if the cut
    # fell in the summary section)
    assert len(got) % 50 == 0
    if cut < data_end:
        complete = sum(1 for c, end in zip(chunks, chunk_ends) if end <= cut)
        assert len(got) == 50 * complete
        assert report.bytes_discarded > 0
    else:
        assert len(got) == len(msgs)
    if report.lost_chunk_range_ns is not None:
        a, b = report.lost_chunk_range_ns
        assert a == 10_000 + len(got) * 1000 and b == a + 49 * 1000
    assert 'recovered' in report.summary()


def test_cut_inside_each_chunk_loses_exactly_that_chunk(tmp_path):
    bag, path, msgs = _make(tmp_path, n=200)
    chunks, _ = _chunk_offsets(path)
    for k, off in enumerate(chunks):
        work = tmp_path / f'w{k}'
        shutil.copytree(bag, work)
        p = str(work / 'rec_0.mcap')
        _crash(p, off + 40)
        report = recover_bag(str(work), output=str(tmp_path / f'o{k}'))
        assert report.message_count == 50 * k
        assert report.lost_chunk_range_ns == (10_000 + 50 * k * 1000,
                                              10_000 + (50 * k + 49) * 1000)


def test_corrupted_chunk_is_refused_and_nothing_from_it_is_yielded(tmp_path):
    bag, path, msgs = _make(tmp_path)
    chunks, _ = _chunk_offsets(path)
    raw = bytearray(open(path, 'rb').read())
    raw[chunks[3] + 100] ^= 0xFF  # inside the 4th chunk's compressed data
    open(path, 'wb').write(bytes(raw))
    got = []
    with pytest.raises((BagCrcError, BagFormatError)):
        for m in BagReader(bag).messages():
            got.append(m.data)
    assert got == msgs[:150]
    with pytest.raises((BagCrcError, BagFormatError)):
        BagReader(bag).verify()
    report = recover_bag(bag, output=str(tmp_path / 'o'))
    assert report.message_count == 150


def test_flipped_byte_in_uncompressed_chunk_fails_its_crc(tmp_path):
    bag = str(tmp_path / 'u')
    with BagWriter(bag, compression='none') as w:
        w.add_topic('/js', 'sensor_msgs/JointState')
        for i in range(20):
            w.write('/js', encode_joint_state(i, ['a'], [float(i)]), i)
    path = os.path.join(bag, 'u_0.mcap')
    chunks, _ = _chunk_offsets(path)
    raw = bytearray(open(path, 'rb').read())
    raw[chunks[0] + 300] ^= 0x01  # a payload byte: only the CRC can tell
    open(path, 'wb').write(bytes(raw))
    with pytest.raises(BagCrcError, match='CRC'):
        list(BagReader(bag).messages())


def test_summary_corruption_detected(tmp_path):
    bag, path, _ = _make(tmp_path, n=100)
    raw = bytearray(open(path, 'rb').read())
    raw[-30] ^= 0xFF  # inside the summary offsets / footer area
    open(path, 'wb').write(bytes(raw))
    with pytest.raises(BagFormatError):
        BagReader(bag).verify()


def _max_rss_mb():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


@pytest.mark.parametrize('length', [2 ** 63 - 1, 2 ** 40, 10 ** 9])
def test_huge_declared_record_length_fails_fast_without_memory(tmp_path, length):
    bag, path, _ = _make(tmp_path, n=100)
    chunks, _ = _chunk_offsets(path)
    raw = bytearray(open(path, 'rb').read())
    struct.pack_into('<Q', raw, chunks[1] + 1, length)
    open(path, 'wb').write(bytes(raw))
    before = _max_rss_mb()
    got = []
    with pytest.raises(BagTruncatedError, match='declares'):
        for m in BagReader(bag).messages():
            got.append(m)
    assert len(got) == 50
    assert _max_rss_mb() - before < 50


def test_huge_declared_uncompressed_size_is_refused(tmp_path):
    bag, path, _ = _make(tmp_path, n=100)
    chunks, _ = _chunk_offsets(path)
    raw = bytearray(open(path, 'rb').read())
    struct.pack_into('<Q', raw, chunks[0] + 9 + 16, 2 ** 50)
    open(path, 'wb').write(bytes(raw))
    with pytest.raises(BagFormatError, match='uncompressed bytes'):
        list(BagReader(bag).messages())


def test_not_mcap_and_empty_files(tmp_path):
    p = tmp_path / 'x.mcap'
    p.write_bytes(b'hello world, not an mcap file at all')
    with pytest.raises(BagFormatError, match='magic'):
        list(scan(str(p)))
    with pytest.raises(BagFormatError):
        recover_bag(str(p))
    p.write_bytes(b'')
    with pytest.raises(BagTruncatedError):
        list(scan(str(p)))


def test_recovery_of_complete_bag_loses_nothing(tmp_path):
    bag, path, msgs = _make(tmp_path, n=120)
    report = recover_bag(bag, output=str(tmp_path / 'copy'))
    assert report.error is None and report.message_count == 120
    assert 'nothing lost' in report.summary()
    st = ScanState()
    assert len([r for r in scan(str(tmp_path / 'copy' / 'copy_0.mcap'), st)]) == 122
    assert st.footer_seen
