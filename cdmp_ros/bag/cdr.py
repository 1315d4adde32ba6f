"""Plain-CDR (XCDR1) codecs for the messages this package reads or writes without rclpy.

- ``sensor_msgs/msg/JointState``, ``std_msgs/msg/String``, ``rosgraph_msgs/msg/Clock`` and
  ``diagnostic_msgs/msg/DiagnosticArray`` for the bag layer (demo bags, the learner's reader,
  the player's clock, tests); everything else travels there as opaque serialized bytes;
- :func:`decode_marker_array`: ``visualization_msgs/msg/MarkerArray`` as records, for the
  nodes' ``obstacles`` subscriptions (rclpy's conversion builds a dozen nested Python objects
  per marker: 46 us for one sphere when warm, about 0.4 ms when the code path has not run for
  a while, which is every obstacle event; this decoder takes 10 / 106 us,
  ``benchmarks/bench_marker_decode.py``);
- :func:`cdr_first_count` and :func:`cdr_joint_state_names`: the element counts the input gate
  checks before any deserialisation.

Layout follows the OMG CDR rules used by rmw_fastrtps: a 4-byte encapsulation header
(``00 01 00 00`` little endian, which is what is written; ``00 00 00 00`` big endian is read
too), then fields aligned to their size relative to the end of that header; a sequence is a
uint32 count followed by its elements, aligned only when it is not empty. Every length read is
checked against the bytes left before it is used, so a forged count costs nothing. Any other
encapsulation (XCDR2, parameter lists) raises :class:`UnsupportedEncoding`.
"""
import struct
from dataclasses import dataclass
from typing import List, NamedTuple, Optional, Tuple

import numpy as np
from numpy.typing import NDArray

from cdmp_ros.bag.errors import BagFormatError

_ENCAPSULATION = b'\x00\x01\x00\x00'


class UnsupportedEncoding(BagFormatError):
    """An encapsulation other than plain CDR (for example XCDR2)."""


class _Layout:
    """The ``struct`` formats of one byte order."""

    def __init__(self, order: str):
        self.u32 = struct.Struct(order + 'I')
        self.i32 = struct.Struct(order + 'i')
        self.stamp = struct.Struct(order + 'iI')
        self.ids = struct.Struct(order + '3i')
        self.pose_scale = struct.Struct(order + '10d')
        self.color_life = struct.Struct(order + '4fiI?')   # 25 bytes, packed
        self.f64 = np.dtype(order + 'f8')


#: Layouts by the second byte of the encapsulation header (0 big endian, 1 little endian).
_LAYOUTS = {0: _Layout('>'), 1: _Layout('<')}


class _Out:
    def __init__(self) -> None:
        self.buf = bytearray(_ENCAPSULATION)

    def align(self, n: int) -> None:
        pad = (-(len(self.buf) - 4)) % n
        if pad:
            self.buf += b'\x00' * pad

    def u32(self, v: int) -> None:
        self.align(4)
        self.buf += struct.pack('<I', v)

    def i32(self, v: int) -> None:
        self.align(4)
        self.buf += struct.pack('<i', v)

    def string(self, s: str) -> None:
        raw = s.encode('utf-8')
        self.u32(len(raw) + 1)
        self.buf += raw + b'\x00'

    def f64_seq(self, a: NDArray[np.float64]) -> None:
        self.u32(len(a))
        if len(a):
            self.align(8)
            self.buf += np.ascontiguousarray(a, dtype='<f8').tobytes()


class _In:
    def __init__(self, data: bytes, what: str) -> None:
        self.data = data
        self.what = what
        if len(data) < 4:
            raise BagFormatError(f'{what}: {len(data)} bytes, shorter than the CDR header')
        if data[0] != 0 or data[1] > 1:
            raise UnsupportedEncoding(f'{what}: expected plain CDR encapsulation 00 00 or 00 01, '
                                      f'got {bytes(data[:2]).hex() or "nothing"}')
        self.lay = _LAYOUTS[data[1]]
        self.end = len(data)
        self.pos = 4

    def need(self, n: int, field: str = '') -> None:
        if n < 0 or self.pos + n > self.end:
            raise BagFormatError(f'{self.what}{field}: CDR data ends at byte {self.end}, '
                                 f'needed {n} more bytes at {self.pos}')

    def align(self, n: int) -> None:
        self.pos += (-(self.pos - 4)) & (n - 1)

    def fixed(self, st: struct.Struct, align: int, field: str = '') -> tuple:
        """The fields of ``st`` (packed) at the position aligned to ``align``."""
        self.align(align)
        self.need(st.size, field)
        v = st.unpack_from(self.data, self.pos)
        self.pos += st.size
        return v

    def u32(self, field: str = '') -> int:
        return self.fixed(self.lay.u32, 4, field)[0]

    def i32(self, field: str = '') -> int:
        return self.fixed(self.lay.i32, 4, field)[0]

    def string(self, field: str = '') -> str:
        n = self.u32(field)
        self.need(n, field)
        raw = bytes(self.data[self.pos:self.pos + n])
        self.pos += n
        if n == 0 or raw[-1] != 0:
            raise BagFormatError(f'{self.what}{field}: CDR string is not NUL-terminated')
        try:
            return raw[:-1].decode('utf-8')
        except UnicodeDecodeError as exc:
            raise BagFormatError(f'{self.what}{field}: not valid UTF-8 ({exc.reason} at byte '
                                 f'{self.pos - n + exc.start})') from None

    def skip_sequence(self, size: int, align: int, field: str = '') -> None:
        """Step over a sequence of ``size``-byte elements aligned to ``align``."""
        n = self.u32(field)
        if n:
            self.align(align)
            if n > (self.end - self.pos) // size:
                raise BagFormatError(f'{self.what}{field}: {n} elements of {size} bytes at byte '
                                     f'{self.pos} run past the end ({self.end} bytes)')
            self.pos += n * size

    def f64_seq(self) -> NDArray[np.float64]:
        n = self.u32()
        if n == 0:
            return np.zeros(0)
        self.align(8)
        self.need(8 * n)
        a = np.frombuffer(self.data, dtype=self.lay.f64, count=n,
                          offset=self.pos).astype(np.float64)
        self.pos += 8 * n
        return a


@dataclass(frozen=True)
class JointStateData:
    """Fields of a ``sensor_msgs/msg/JointState`` as numpy arrays.

    Attributes
    ----------
    stamp_ns : int
        ``header.stamp`` in nanoseconds.
    frame_id : str
    name : tuple of str, length n_dims
    position, velocity, effort : ndarray, shape (n_dims,) or (0,)
    """

    stamp_ns: int
    frame_id: str
    name: Tuple[str, ...]
    position: NDArray[np.float64]
    velocity: NDArray[np.float64]
    effort: NDArray[np.float64]


def encode_joint_state(stamp_ns: int, name: List[str], position, velocity=(), effort=(),
                       frame_id: str = '') -> bytes:
    """Serialize a JointState to CDR bytes (byte-identical to rclpy's serialize_message)."""
    out = _Out()
    sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
    out.i32(sec)
    out.u32(nsec)
    out.string(frame_id)
    out.u32(len(name))
    for n in name:
        out.string(n)
    for seq in (position, velocity, effort):
        out.f64_seq(np.asarray(seq, dtype=np.float64).reshape(-1))
    return bytes(out.buf)


def decode_joint_state(data: bytes) -> JointStateData:
    """Deserialize CDR bytes of a JointState.

    Raises
    ------
    BagFormatError
        If the bytes are not a well-formed JointState.
    """
    inp = _In(data, 'sensor_msgs/msg/JointState')
    sec = inp.i32()
    nsec = inp.u32()
    frame_id = inp.string()
    n = inp.u32()
    inp.need(4 * n)  # each name needs at least its length word: bounds a bogus count
    names = tuple(inp.string() for _ in range(n))
    position = inp.f64_seq()
    velocity = inp.f64_seq()
    effort = inp.f64_seq()
    return JointStateData(sec * 1_000_000_000 + nsec, frame_id, names, position, velocity,
                          effort)


def encode_string(text: str) -> bytes:
    """Serialize a ``std_msgs/msg/String`` to CDR bytes."""
    out = _Out()
    out.string(text)
    return bytes(out.buf)


def decode_string(data: bytes) -> str:
    """Deserialize CDR bytes of a ``std_msgs/msg/String``."""
    return _In(data, 'std_msgs/msg/String').string()


def encode_clock(stamp_ns: int) -> bytes:
    """Serialize a ``rosgraph_msgs/msg/Clock`` to CDR bytes."""
    out = _Out()
    sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
    out.i32(sec)
    out.u32(nsec)
    return bytes(out.buf)


def decode_diagnostic_array(data: bytes) -> List[dict]:
    """Deserialize CDR bytes of a ``diagnostic_msgs/msg/DiagnosticArray``.

    Returns
    -------
    list of dict
        One per status: ``level`` (int), ``name``, ``message``, ``hardware_id`` and
        ``values`` (a dict of the key/value pairs).
    """
    inp = _In(data, 'diagnostic_msgs/msg/DiagnosticArray')
    inp.i32()
    inp.u32()
    inp.string()
    n = inp.u32()
    inp.need(n)  # each status needs at least its level byte: bounds a bogus count
    out = []
    for _ in range(n):
        inp.need(1)
        level = inp.data[inp.pos]
        inp.pos += 1
        name, message, hardware_id = inp.string(), inp.string(), inp.string()
        k = inp.u32()
        inp.need(8 * k)  # two length words per pair at least
        values = {}
        for _ in range(k):
            key = inp.string()
            values[key] = inp.string()
        out.append({'level': int(level), 'name': name, 'message': message,
                    'hardware_id': hardware_id, 'values': values})
    return out


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
    off = 16 + n_frame
    return _peek_u32(data, off + ((-(off - 4)) & 3))


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
    message; ``lifetime`` is a ``builtin_interfaces/Duration``, here a :class:`Time`); its
    variable-length fields (points, colors, texture, uv_coordinates, text, mesh) are checked
    and skipped."""
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


#: Smallest serialized marker, padding left out: stamp, frame_id and ns (empty), id / type /
#: action, pose and scale, color / lifetime / frame_locked, the two sequences and the texture
#: resource, the texture (stamp, frame_id, format, data), uv_coordinates, text, mesh_resource,
#: mesh_file (filename, data), mesh_use_embedded_materials.
MIN_MARKER_BYTES = (8 + 4 + 4) + 12 + 80 + 25 + (4 + 4 + 4) + (8 + 4 + 4 + 4) + 4 + 4 + 4 \
    + (4 + 4) + 1


def _marker(inp: _In) -> WireMarker:
    lay = inp.lay
    sec, nsec = inp.fixed(lay.stamp, 4, '.header.stamp')
    frame = inp.string('.header.frame_id')
    ns = inp.string('.ns')
    mid, mtype, action = inp.fixed(lay.ids, 4, '.id')
    v = inp.fixed(lay.pose_scale, 8, '.pose')
    r, g, b, a, life_s, life_ns, locked = inp.fixed(lay.color_life, 4, '.color')
    inp.skip_sequence(24, 8, '.points')
    inp.skip_sequence(16, 4, '.colors')
    inp.string('.texture_resource')
    inp.fixed(lay.stamp, 4, '.texture.header.stamp')
    inp.string('.texture.header.frame_id')
    inp.string('.texture.format')
    inp.skip_sequence(1, 1, '.texture.data')
    inp.skip_sequence(8, 4, '.uv_coordinates')
    inp.string('.text')
    inp.string('.mesh_resource')
    inp.string('.mesh_file.filename')
    inp.skip_sequence(1, 1, '.mesh_file.data')
    inp.need(1, '.mesh_use_embedded_materials')
    inp.pos += 1
    return WireMarker(Header(Time(sec, nsec), frame), ns, mid, mtype, action,
                      Pose(Vector3(v[0], v[1], v[2]), Quaternion(v[3], v[4], v[5], v[6])),
                      Vector3(v[7], v[8], v[9]), ColorRGBA(r, g, b, a), Time(life_s, life_ns),
                      locked)


def decode_marker_array(data: bytes, name: str = 'markers') -> WireMarkerArray:
    """The markers of a serialized ``visualization_msgs/MarkerArray``.

    Raises
    ------
    UnsupportedEncoding
        For an encapsulation other than plain CDR.
    BagFormatError
        For malformed bytes, naming the field (e.g. ``markers[2].ns``).
    """
    inp = _In(data, name)
    n = inp.u32()
    if n > (inp.end - inp.pos) // MIN_MARKER_BYTES:
        raise BagFormatError(f'{name}: {n} markers cannot fit in the {inp.end - inp.pos} bytes '
                             'left')
    out = []
    for i in range(n):
        inp.what = f'{name}[{i}]'
        out.append(_marker(inp))
    return WireMarkerArray(out)
