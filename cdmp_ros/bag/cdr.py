"""Plain-CDR (XCDR1, little endian) codecs for the message types the bag layer builds itself.

Only ``sensor_msgs/msg/JointState`` and ``std_msgs/msg/String`` are needed without ROS (demo
bags, the learner's reader, tests); everything else travels as opaque serialized bytes.
Layout follows the OMG CDR rules used by rmw_fastrtps: a 4-byte encapsulation header
``00 01 00 00``, then fields aligned to their size relative to the end of that header; a
sequence is a uint32 count followed by its elements, aligned only when it is not empty.
"""
import struct
from dataclasses import dataclass
from typing import List, Tuple

import numpy as np
from numpy.typing import NDArray

from cdmp_ros.bag.errors import BagFormatError

_ENCAPSULATION = b'\x00\x01\x00\x00'


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
        self.data = memoryview(data)
        self.what = what
        if len(data) < 4 or bytes(self.data[:2]) not in (b'\x00\x01',):
            raise BagFormatError(f'{what}: expected little-endian CDR encapsulation 00 01, '
                                 f'got {bytes(self.data[:2]).hex() or "nothing"}')
        self.pos = 4

    def need(self, n: int) -> None:
        if n < 0 or self.pos + n > len(self.data):
            raise BagFormatError(f'{self.what}: CDR data ends at byte {len(self.data)}, '
                                 f'needed {n} more bytes at {self.pos}')

    def align(self, n: int) -> None:
        self.pos += (-(self.pos - 4)) % n

    def _int32(self, fmt: str) -> int:
        """The aligned 4-byte integer at the position (``fmt``: '<I' unsigned, '<i' signed)."""
        self.align(4)
        self.need(4)
        v = struct.unpack_from(fmt, self.data, self.pos)[0]
        self.pos += 4
        return v

    def u32(self) -> int:
        return self._int32('<I')

    def i32(self) -> int:
        return self._int32('<i')

    def string(self) -> str:
        n = self.u32()
        self.need(n)
        raw = bytes(self.data[self.pos:self.pos + n])
        self.pos += n
        if n == 0 or raw[-1] != 0:
            raise BagFormatError(f'{self.what}: CDR string is not NUL-terminated')
        return raw[:-1].decode('utf-8')

    def f64_seq(self) -> NDArray[np.float64]:
        n = self.u32()
        if n == 0:
            return np.zeros(0)
        self.align(8)
        self.need(8 * n)
        a = np.frombuffer(self.data, dtype='<f8', count=n, offset=self.pos).astype(np.float64)
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
