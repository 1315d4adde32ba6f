"""ROS messages read straight from their CDR bytes, without rclpy's message classes.

- :func:`cdr_first_count` and :func:`cdr_joint_state_names`: the element counts the input gate
  checks before any deserialisation;
- :func:`decode_marker_array`: a ``visualization_msgs/MarkerArray`` as records.

The obstacle subscriptions (streamer, adapter, sim) read these records instead of rclpy's
message classes: rclpy's conversion builds a dozen nested Python objects per marker (47 us for
one sphere when warm, about 0.4 ms when the code path has not run for a while, which is every
obstacle event), and this decoder reads the same fields with a few ``struct`` calls
(``benchmarks/bench_marker_decode.py``).

The records carry what an obstacle needs (header, ns, id, type, action, pose, scale, color,
lifetime, frame_locked) under the message's own field names; the variable-length fields
(points, colors, texture, uv_coordinates, text, mesh) are bounds-checked and skipped. Every
length is checked against the bytes left before it is used, so a forged count costs nothing.
Plain CDR (XCDR1) of either byte order is decoded here, which is what ROS 2's middlewares
publish; any other encapsulation raises :class:`UnsupportedEncoding` and the caller falls back
to rclpy.
"""
import struct
from typing import List, NamedTuple, Optional, Tuple


class CdrError(ValueError):
    """Malformed CDR bytes; the message names the field and the offset."""


class UnsupportedEncoding(CdrError):
    """An encapsulation other than plain CDR (for example XCDR2)."""


class Time(NamedTuple):
    sec: int
    nanosec: int


class Header(NamedTuple):
    stamp: Time
    frame_id: str


class Vector3(NamedTuple):
    x: float
    y: float
    z: float


class Quaternion(NamedTuple):
    x: float
    y: float
    z: float
    w: float


class Pose(NamedTuple):
    position: Vector3
    orientation: Quaternion


class ColorRGBA(NamedTuple):
    r: float
    g: float
    b: float
    a: float


class WireMarker(NamedTuple):
    """The fixed fields of a ``visualization_msgs/Marker`` (names and nesting as in the
    message; ``lifetime`` is a ``builtin_interfaces/Duration``, here a :class:`Time`)."""
    header: Header
    ns: str
    id: int
    type: int
    action: int
    pose: Pose
    scale: Vector3
    color: ColorRGBA
    lifetime: Time
    frame_locked: bool


class WireMarkerArray(NamedTuple):
    markers: List[WireMarker]


class _Layout:
    """The ``struct`` formats of one byte order."""

    def __init__(self, order: str):
        self.u32 = struct.Struct(order + 'I')
        self.stamp = struct.Struct(order + 'iI')
        self.ids = struct.Struct(order + '3i')
        self.pose_scale = struct.Struct(order + '10d')
        self.color_life = struct.Struct(order + '4fiI?')   # 25 bytes, packed


_LAYOUTS = {0: _Layout('>'), 1: _Layout('<')}
#: Smallest serialized marker, padding left out: stamp, frame_id and ns (empty), id / type /
#: action, pose and scale, color / lifetime / frame_locked, the two sequences and the texture
#: resource, the texture (stamp, frame_id, format, data), uv_coordinates, text, mesh_resource,
#: mesh_file (filename, data), mesh_use_embedded_materials.
MIN_MARKER_BYTES = (8 + 4 + 4) + 12 + 80 + 25 + (4 + 4 + 4) + (8 + 4 + 4 + 4) + 4 + 4 + 4 \
    + (4 + 4) + 1


def _align(pos: int, size: int) -> int:
    """``pos`` (absolute) aligned to ``size`` relative to the payload after the 4-byte
    encapsulation header."""
    return pos + (-(pos - 4) & (size - 1))


def _peek_u32(data: bytes, offset: int) -> Optional[int]:
    """The CDR uint32 at ``offset`` (absolute, after the 4-byte encapsulation header) in the
    byte order the header names, or None past the end."""
    if len(data) < offset + 4:
        return None
    return _LAYOUTS[data[1] & 1].u32.unpack_from(data, offset)[0]


def cdr_first_count(data: bytes) -> Optional[int]:
    """Length of the first field of a CDR message when it is a sequence or a string
    (``MarkerArray.markers``, ``String.data`` with its NUL): the uint32 after the
    encapsulation header."""
    return _peek_u32(data, 4)


def cdr_joint_state_names(data: bytes) -> Optional[int]:
    """Number of names of a CDR ``JointState``: after the stamp (8 bytes) and the
    ``frame_id`` string (length + characters), aligned to 4 bytes."""
    n_frame = _peek_u32(data, 12)
    if n_frame is None:
        return None
    return _peek_u32(data, _align(16 + n_frame, 4))


def _u32(data: bytes, pos: int, lay: _Layout, end: int, what: str) -> Tuple[int, int]:
    pos = _align(pos, 4)
    if pos + 4 > end:
        raise CdrError(f'{what}: length at byte {pos} is past the end ({end} bytes)')
    return lay.u32.unpack_from(data, pos)[0], pos + 4


def _string(data: bytes, pos: int, lay: _Layout, end: int, what: str) -> Tuple[str, int]:
    n, pos = _u32(data, pos, lay, end, what)
    if n > end - pos:
        raise CdrError(f'{what}: string of {n} bytes at byte {pos} runs past the end '
                       f'({end} bytes)')
    raw = data[pos:pos + n]
    if n and raw[-1] == 0:
        raw = raw[:-1]
    try:
        return raw.decode('utf-8'), pos + n
    except UnicodeDecodeError as exc:
        raise CdrError(f'{what}: not valid UTF-8 ({exc.reason} at byte {pos + exc.start})'
                       ) from None


def _skip_sequence(data: bytes, pos: int, lay: _Layout, end: int, what: str, size: int,
                   align: int) -> int:
    n, pos = _u32(data, pos, lay, end, what)
    if n:
        pos = _align(pos, align)
        if n > (end - pos) // size:
            raise CdrError(f'{what}: {n} elements of {size} bytes at byte {pos} run past the '
                           f'end ({end} bytes)')
        pos += n * size
    return pos


def _fixed(lay_struct: struct.Struct, data: bytes, pos: int, end: int, what: str):
    if pos + lay_struct.size > end:
        raise CdrError(f'{what}: {lay_struct.size} bytes at byte {pos} run past the end '
                       f'({end} bytes)')
    return lay_struct.unpack_from(data, pos)


def _marker(data: bytes, pos: int, lay: _Layout, end: int, name: str
            ) -> Tuple[WireMarker, int]:
    pos = _align(pos, 4)
    sec, nsec = _fixed(lay.stamp, data, pos, end, f'{name}.header.stamp')
    frame, pos = _string(data, pos + 8, lay, end, f'{name}.header.frame_id')
    ns, pos = _string(data, pos, lay, end, f'{name}.ns')
    pos = _align(pos, 4)
    mid, mtype, action = _fixed(lay.ids, data, pos, end, f'{name}.id')
    pos = _align(pos + 12, 8)
    v = _fixed(lay.pose_scale, data, pos, end, f'{name}.pose')
    pos += 80
    r, g, b, a, life_s, life_ns, locked = _fixed(lay.color_life, data, pos, end,
                                                 f'{name}.color')
    pos += 25
    pos = _skip_sequence(data, pos, lay, end, f'{name}.points', 24, 8)
    pos = _skip_sequence(data, pos, lay, end, f'{name}.colors', 16, 4)
    _, pos = _string(data, pos, lay, end, f'{name}.texture_resource')
    pos = _align(pos, 4)
    _fixed(lay.stamp, data, pos, end, f'{name}.texture.header.stamp')
    _, pos = _string(data, pos + 8, lay, end, f'{name}.texture.header.frame_id')
    _, pos = _string(data, pos, lay, end, f'{name}.texture.format')
    pos = _skip_sequence(data, pos, lay, end, f'{name}.texture.data', 1, 1)
    pos = _skip_sequence(data, pos, lay, end, f'{name}.uv_coordinates', 8, 4)
    _, pos = _string(data, pos, lay, end, f'{name}.text')
    _, pos = _string(data, pos, lay, end, f'{name}.mesh_resource')
    _, pos = _string(data, pos, lay, end, f'{name}.mesh_file.filename')
    pos = _skip_sequence(data, pos, lay, end, f'{name}.mesh_file.data', 1, 1)
    if pos + 1 > end:
        raise CdrError(f'{name}.mesh_use_embedded_materials: byte {pos} is past the end '
                       f'({end} bytes)')
    marker = WireMarker(Header(Time(sec, nsec), frame), ns, mid, mtype, action,
                        Pose(Vector3(v[0], v[1], v[2]), Quaternion(v[3], v[4], v[5], v[6])),
                        Vector3(v[7], v[8], v[9]), ColorRGBA(r, g, b, a),
                        Time(life_s, life_ns), locked)
    return marker, pos + 1


def decode_marker_array(data: bytes, name: str = 'markers') -> WireMarkerArray:
    """The markers of a serialized ``visualization_msgs/MarkerArray``.

    Raises :class:`UnsupportedEncoding` for an encapsulation other than plain CDR and
    :class:`CdrError` (naming the field, e.g. ``markers[2].ns``) for malformed bytes.
    """
    end = len(data)
    if end < 8:
        raise CdrError(f'{end} bytes: too short for a MarkerArray')
    if data[0] != 0 or data[1] > 1:
        raise UnsupportedEncoding(f'encapsulation 0x{data[0]:02x}{data[1]:02x} is not plain '
                                  'CDR')
    lay = _LAYOUTS[data[1]]
    n, pos = _u32(data, 4, lay, end, name)
    if n > (end - pos) // MIN_MARKER_BYTES:
        raise CdrError(f'{name}: {n} markers cannot fit in the {end - pos} bytes left')
    out = []
    for i in range(n):
        marker, pos = _marker(data, pos, lay, end, f'{name}[{i}]')
        out.append(marker)
    return WireMarkerArray(out)
