"""The MarkerArray CDR decoder against rclpy's own deserialisation (the oracle), in both byte
orders, and on truncated, forged and corrupted bytes."""
import random
import struct

import pytest
from hypothesis import given, settings, strategies as st

from markers import MARKER_CASES, bad_marker, marker

pytest.importorskip('rclpy')
from geometry_msgs.msg import Point  # noqa: E402
from rclpy.serialization import deserialize_message, serialize_message  # noqa: E402
from std_msgs.msg import ColorRGBA  # noqa: E402
from visualization_msgs.msg import Marker, MarkerArray, UVCoordinate  # noqa: E402

from cdmp_ros.ros.convert import ObstacleSet  # noqa: E402
from cdmp_ros.ros.input_gate import deserialize, read_raw  # noqa: E402
from cdmp_ros.bag.cdr import (MIN_MARKER_BYTES, UnsupportedEncoding, WireMarkerArray,  # noqa
                              decode_marker_array)
from cdmp_ros.bag.errors import BagFormatError as CdrError  # noqa: E402

FIELDS = ('ns', 'id', 'type', 'action', 'frame_locked')


def same(wire, msg):
    """Every field a record carries equals the rclpy message's."""
    assert len(wire.markers) == len(msg.markers)
    for w, m in zip(wire.markers, msg.markers):
        for f in FIELDS:
            assert getattr(w, f) == getattr(m, f), f
        assert w.header.frame_id == m.header.frame_id
        assert tuple(w.header.stamp) == (m.header.stamp.sec, m.header.stamp.nanosec)
        assert tuple(w.lifetime) == (m.lifetime.sec, m.lifetime.nanosec)
        p, q = m.pose.position, m.pose.orientation
        assert tuple(w.pose.position) == (p.x, p.y, p.z)
        assert tuple(w.pose.orientation) == (q.x, q.y, q.z, q.w)
        assert tuple(w.scale) == (m.scale.x, m.scale.y, m.scale.z)
        assert tuple(w.color) == (m.color.r, m.color.g, m.color.b, m.color.a)


text = st.text(st.characters(blacklist_categories=('Cs',), blacklist_characters='\x00'),
               max_size=12)
f64 = st.floats(allow_nan=False, width=64)
f32 = st.floats(allow_nan=False, width=32)
i32 = st.integers(-2**31, 2**31 - 1)


@st.composite
def markers(draw):
    m = Marker(ns=draw(text), id=draw(i32), type=draw(st.integers(0, 12)),
               action=draw(st.sampled_from([0, 2, 3])), frame_locked=draw(st.booleans()))
    m.header.frame_id = draw(text)
    m.header.stamp.sec, m.header.stamp.nanosec = draw(i32), draw(st.integers(0, 999_999_999))
    m.lifetime.sec, m.lifetime.nanosec = draw(i32), draw(st.integers(0, 999_999_999))
    p, q, s = m.pose.position, m.pose.orientation, m.scale
    p.x, p.y, p.z, q.x, q.y, q.z, q.w, s.x, s.y, s.z = (draw(f64) for _ in range(10))
    m.color.r, m.color.g, m.color.b, m.color.a = (draw(f32) for _ in range(4))
    # the variable-length fields, each empty or not: every alignment case after them
    m.points = [Point(x=draw(f64)) for _ in range(draw(st.integers(0, 3)))]
    m.colors = [ColorRGBA(r=draw(f32)) for _ in range(draw(st.integers(0, 2)))]
    m.texture_resource = draw(text)
    m.texture.header.frame_id, m.texture.format = draw(text), draw(text)
    m.texture.data = draw(st.binary(max_size=7))
    m.uv_coordinates = [UVCoordinate(u=draw(f32)) for _ in range(draw(st.integers(0, 2)))]
    m.text, m.mesh_resource, m.mesh_file.filename = draw(text), draw(text), draw(text)
    m.mesh_file.data = draw(st.binary(max_size=5))
    m.mesh_use_embedded_materials = draw(st.booleans())
    return m


@settings(max_examples=150, deadline=None)
@given(st.lists(markers(), max_size=4))
def test_decoder_reads_what_rclpy_reads(ms):
    raw = serialize_message(MarkerArray(markers=ms))
    same(decode_marker_array(raw), deserialize_message(raw, MarkerArray))


def big_endian(m):
    """``m`` (a Marker without variable-length content but its strings) serialized as
    big-endian CDR by a writer of this test, whose little-endian output rclpy reads back as
    ``m`` first (byte for byte it differs in the padding, which Fast-CDR leaves unset)."""
    def write(order):
        out = bytearray(b'\x00\x00\x00\x00' if order == '>' else b'\x00\x01\x00\x00')

        def pad(n):
            out.extend(b'\x00' * (-(len(out) - 4) % n))

        def put(fmt, *v):
            pad(struct.calcsize(fmt.lstrip('0123456789')[0]))
            out.extend(struct.pack(order + fmt, *v))

        def string(s):
            b = s.encode() + b'\x00'
            put('I', len(b))
            out.extend(b)

        put('I', 1)
        put('iI', m.header.stamp.sec, m.header.stamp.nanosec)
        string(m.header.frame_id)
        string(m.ns)
        put('3i', m.id, m.type, m.action)
        p, q, s = m.pose.position, m.pose.orientation, m.scale
        put('10d', p.x, p.y, p.z, q.x, q.y, q.z, q.w, s.x, s.y, s.z)
        put('4f', m.color.r, m.color.g, m.color.b, m.color.a)
        put('iI', m.lifetime.sec, m.lifetime.nanosec)
        out.append(int(m.frame_locked))
        put('I', 0)
        put('I', 0)
        string('')
        put('iI', 0, 0)
        for _ in range(2):
            string('')
        put('I', 0)
        put('I', 0)
        for _ in range(3):
            string('')
        put('I', 0)
        out.append(0)
        return bytes(out)

    assert deserialize_message(write('<'), MarkerArray) == MarkerArray(markers=[m])
    return write('>')


def test_big_endian_cdr():
    m = marker(ns='obs', id=-7, kind='cube', position=(0.5, -0.25, 1e-3), size=0.3)
    m.header.stamp.sec, m.header.stamp.nanosec = 12, 345
    m.color.r, m.frame_locked = 0.5, True
    same(decode_marker_array(big_endian(m)), MarkerArray(markers=[m]))


def test_every_truncation_is_an_error_naming_a_field():
    ms = [marker(ns='a', id=1), marker(ns='b', id=2, kind='cube', text='x')]
    ms[1].points = [Point(x=1.0)]
    raw = serialize_message(MarkerArray(markers=ms))
    assert len(decode_marker_array(raw).markers) == 2
    for n in range(len(raw)):
        with pytest.raises(CdrError, match=r'markers|bytes'):
            decode_marker_array(raw[:n])


def test_forged_counts_are_rejected_before_any_work():
    raw = bytearray(serialize_message(MarkerArray(markers=[marker()])))
    forged = bytes(raw[:4]) + struct.pack('<I', 2**32 - 1) + bytes(raw[8:])
    with pytest.raises(CdrError, match='markers cannot fit'):
        decode_marker_array(forged)
    # a points sequence of 2**32 - 1 elements: its count is the uint32 before the (aligned)
    # first point
    m = marker(points=[Point(x=1.2345)])
    raw = serialize_message(MarkerArray(markers=[m]))
    first = raw.index(struct.pack('<d', 1.2345))
    at = first - 4 if struct.unpack_from('<I', raw, first - 4)[0] == 1 else first - 8
    assert struct.unpack_from('<I', raw, at)[0] == 1
    forged = raw[:at] + struct.pack('<I', 2**32 - 1) + raw[at + 4:]
    with pytest.raises(CdrError, match=r'markers\[0\]\.points: 4294967295 elements'):
        decode_marker_array(forged)


def test_minimum_marker_size_is_a_lower_bound():
    raw = serialize_message(MarkerArray(markers=[Marker()]))
    assert MIN_MARKER_BYTES <= len(raw) - 8


def test_corrupted_bytes_decode_or_raise_a_cdr_error():
    ms = [marker(ns='n', id=i, text='t' * i) for i in range(3)]
    raw = serialize_message(MarkerArray(markers=ms))
    rng = random.Random(5)
    for _ in range(2000):
        b = bytearray(raw)
        for _ in range(rng.randint(1, 4)):
            b[rng.randrange(4, len(b))] = rng.randrange(256)
        try:
            out = decode_marker_array(bytes(b))
        except CdrError:
            continue
        assert isinstance(out, WireMarkerArray) and len(out.markers) <= len(b) // 100


def test_invalid_utf8_names_the_field():
    m = marker(ns='ab')
    raw = serialize_message(MarkerArray(markers=[m]))
    at = raw.index(b'ab\x00')
    bad = raw[:at] + b'\xff\xfe' + raw[at + 2:]
    with pytest.raises(CdrError, match=r'markers\[0\]\.ns: not valid UTF-8'):
        decode_marker_array(bad)
    msg, reason, category = read_raw(MarkerArray, 'obstacles', bad)
    assert msg is None and category == 'malformed'
    assert reason.startswith('obstacles: cannot be deserialized (markers[0].ns: not valid')


def test_other_encapsulations_fall_back_to_rclpy():
    with pytest.raises(UnsupportedEncoding):
        decode_marker_array(b'\x00\x07\x00\x00' + bytes(8))
    raw = serialize_message(MarkerArray(markers=[marker()]))
    assert isinstance(deserialize(raw, MarkerArray), WireMarkerArray)
    assert type(deserialize(b'\x00\x07\x00\x00' + bytes(8), MarkerArray)) is MarkerArray


@pytest.mark.parametrize('case', sorted(MARKER_CASES))
def test_obstacle_set_gives_the_same_verdict_on_records_and_messages(case):
    bad, _ = bad_marker(case)
    good = marker(ns='ok', id=1)
    msgs = [good, bad]
    wire = decode_marker_array(serialize_message(MarkerArray(markers=msgs))).markers
    a, b = ObstacleSet(), ObstacleSet()
    ea, eb = a.apply(msgs, 1.0), b.apply(wire, 1.0)
    assert [str(e) for e in ea] == [str(e) for e in eb]
    assert a.snapshot == b.snapshot and len(a) == len(b) >= 1
