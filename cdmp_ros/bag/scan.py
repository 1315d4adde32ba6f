"""Strict, bounded MCAP scanner: the one place that parses ``.mcap`` bytes for reading.

Every record length is checked against the bytes that remain before anything is read, every
chunk's declared uncompressed size is capped (``max_chunk_bytes``) before decompression, and
every non-zero CRC (chunk, data section, summary) is verified.  A chunk's records are yielded
only after the whole chunk decompressed, matched its CRC and parsed, so a caller never sees
part of a bad chunk.  The file is memory-mapped: a huge declared length costs nothing.

:func:`scan` raises :class:`BagTruncatedError` where the file ends early (no footer, cut
record) and :class:`BagFormatError` / :class:`BagCrcError` on corrupted bytes; ``good_offset``
of the :class:`ScanState` tells the end of the last record that was fully validated, which
recovery uses.
"""
import mmap
import struct
import zlib
from dataclasses import dataclass, field
from typing import Dict, Iterator, Optional, Tuple, Union

from cdmp_ros.bag.errors import BagCrcError, BagFormatError, BagTruncatedError

MAGIC = b'\x89MCAP0\r\n'
OP_HEADER, OP_FOOTER, OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_CHUNK = 1, 2, 3, 4, 5, 6
OP_METADATA, OP_DATA_END = 0x0C, 0x0F
#: Default cap of one chunk's uncompressed size (our writer produces <= ~1 MiB chunks).
MAX_CHUNK_BYTES = 256 * 2 ** 20


@dataclass(frozen=True)
class SchemaRec:
    id: int
    name: str
    encoding: str
    data: bytes


@dataclass(frozen=True)
class ChannelRec:
    id: int
    schema_id: int
    topic: str
    message_encoding: str
    metadata: Dict[str, str]


@dataclass(frozen=True)
class MessageRec:
    channel_id: int
    sequence: int
    log_time: int
    publish_time: int
    data: bytes


@dataclass
class ScanState:
    """What a scan has validated so far (filled in while :func:`scan` runs)."""

    profile: str = ''
    library: str = ''
    good_offset: int = 0
    file_size: int = 0
    chunks: int = 0
    footer_seen: bool = False
    schemas: Dict[int, SchemaRec] = field(default_factory=dict)
    channels: Dict[int, ChannelRec] = field(default_factory=dict)
    metadata: Dict[str, Dict[str, str]] = field(default_factory=dict)
    #: Declared time range (start, end) of a chunk that could not be used, if readable.
    bad_chunk_range: Optional[Tuple[int, int]] = None


class _NoDataEnd(Exception):
    """The data section ended with the file (no DataEnd record)."""


class _Cursor:
    __slots__ = ('buf', 'pos', 'end', 'base', 'what')

    def __init__(self, buf, pos: int, end: int, base: int, what: str):
        self.buf, self.pos, self.end, self.base, self.what = buf, pos, end, base, what

    def fail(self, msg: str):
        raise BagFormatError(f'{self.what} at byte {self.base + self.pos}: {msg}',
                             self.base + self.pos)

    def take(self, n: int) -> bytes:
        if n < 0 or n > self.end - self.pos:
            self.fail(f'field of {n} bytes overruns its record ({self.end - self.pos} left)')
        b = bytes(self.buf[self.pos:self.pos + n])
        self.pos += n
        return b

    def uint(self, fmt: str, size: int) -> int:
        if size > self.end - self.pos:
            self.fail('record too short')
        v = struct.unpack_from(fmt, self.buf, self.pos)[0]
        self.pos += size
        return v

    def u16(self) -> int:
        return self.uint('<H', 2)

    def u32(self) -> int:
        return self.uint('<I', 4)

    def u64(self) -> int:
        return self.uint('<Q', 8)

    def string(self) -> str:
        raw = self.take(self.u32())
        try:
            return raw.decode('utf-8')
        except UnicodeDecodeError:
            self.fail('string is not UTF-8')

    def str_map(self) -> Dict[str, str]:
        n = self.u32()
        sub = _Cursor(self.buf, self.pos, self.pos + n, self.base, self.what)
        if n > self.end - self.pos:
            self.fail('map overruns its record')
        out = {}
        while sub.pos < sub.end:
            k = sub.string()
            out[k] = sub.string()
        self.pos += n
        return out


def _records(buf, start: int, end: int, base: int, what: str) -> Iterator[Tuple[int, int, int]]:
    """Yield (opcode, body_start, body_end) of the records in ``buf[start:end]``."""
    pos = start
    while pos < end:
        if end - pos < 9:
            raise BagTruncatedError(f'{what}: ends inside a record header at byte {base + pos}',
                                    base + pos)
        op = buf[pos]
        length = struct.unpack_from('<Q', buf, pos + 1)[0]
        if length > end - pos - 9:
            raise BagTruncatedError(
                f'{what}: record (opcode 0x{op:02x}) at byte {base + pos} declares {length} '
                f'bytes but only {end - pos - 9} remain', base + pos)
        yield op, pos + 9, pos + 9 + length
        pos += 9 + length


def _decompress(compression: str, data: bytes, size: int, where: str) -> bytes:
    if compression == '':
        out = data
    elif compression == 'zstd':
        import zstandard
        try:
            out = zstandard.ZstdDecompressor().decompress(data, max_output_size=size)
        except zstandard.ZstdError as exc:
            raise BagCrcError(f'{where}: zstd data is corrupted ({exc})') from None
    elif compression == 'lz4':
        import lz4.frame
        try:
            dec = lz4.frame.LZ4FrameDecompressor()
            out = dec.decompress(data, max_length=size + 1)
        except RuntimeError as exc:
            raise BagCrcError(f'{where}: lz4 data is corrupted ({exc})') from None
    else:
        raise BagFormatError(f'{where}: unsupported chunk compression {compression!r}')
    if len(out) != size:
        raise BagCrcError(f'{where}: decompressed to {len(out)} bytes, declared {size}')
    return out


def _parse_inner(op: int, cur: _Cursor, state: ScanState, out: list) -> None:
    if op == OP_SCHEMA:
        sid = cur.u16()
        name = cur.string()
        enc = cur.string()
        data = cur.take(cur.u32())
        out.append(SchemaRec(sid, name, enc, data))
    elif op == OP_CHANNEL:
        cid = cur.u16()
        sid = cur.u16()
        topic = cur.string()
        enc = cur.string()
        out.append(ChannelRec(cid, sid, topic, enc, cur.str_map()))
    elif op == OP_MESSAGE:
        cid = cur.u16()
        seq = cur.u32()
        log_time = cur.u64()
        pub_time = cur.u64()
        out.append(MessageRec(cid, seq, log_time, pub_time, cur.take(cur.end - cur.pos)))


def _check_refs(recs: list, state: ScanState, what: str) -> None:
    """Register schemas/channels and check every message names a known channel."""
    schemas = dict(state.schemas)
    channels = dict(state.channels)
    for r in recs:
        if isinstance(r, SchemaRec):
            schemas[r.id] = r
        elif isinstance(r, ChannelRec):
            if r.schema_id != 0 and r.schema_id not in schemas:
                raise BagFormatError(f'{what}: channel {r.id} ({r.topic}) uses unknown schema '
                                     f'{r.schema_id}')
            channels[r.id] = r
        elif r.channel_id not in channels:
            raise BagFormatError(f'{what}: message on unknown channel {r.channel_id}')
    state.schemas, state.channels = schemas, channels


def scan(path: str, state: Optional[ScanState] = None, require_footer: bool = True,
         max_chunk_bytes: int = MAX_CHUNK_BYTES
         ) -> Iterator[Union[SchemaRec, ChannelRec, MessageRec]]:
    """Yield the schema, channel and message records of an MCAP file in file order.

    Parameters
    ----------
    path : str
        The ``.mcap`` file.
    state : ScanState, optional
        Filled in while scanning (profile, channels, ``good_offset`` ...).
    require_footer : bool
        Raise :class:`BagTruncatedError` if the data section is not followed by DataEnd,
        Footer and the closing magic (a crashed recording).
    max_chunk_bytes : int
        Refuse chunks declaring a larger uncompressed size.

    Raises
    ------
    BagFormatError, BagTruncatedError, BagCrcError
    """
    state = state if state is not None else ScanState()
    with open(path, 'rb') as f:
        size = f.seek(0, 2)
        state.file_size = size
        if size < len(MAGIC):
            raise BagTruncatedError(f'{path}: {size} bytes, too short for an MCAP file', 0)
        buf = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
    try:
        yield from _scan(path, buf, size, state, require_footer, max_chunk_bytes)
    finally:
        buf.close()


def _scan(path, buf, size, state, require_footer, max_chunk_bytes):
    if buf[:8] != MAGIC:
        raise BagFormatError(f'{path}: not an MCAP file (bad magic {bytes(buf[:8])!r})', 0)
    state.good_offset = 8
    data_end_seen = False
    try:
        yield from _data_section(path, buf, size, state, max_chunk_bytes)
        data_end_seen = True
    except BagTruncatedError as exc:
        off = exc.offset if exc.offset is not None else size
        if off + 25 <= size and buf[off] == OP_CHUNK:  # a cut chunk: tell what it held
            state.bad_chunk_range = struct.unpack_from('<QQ', buf, off + 9)
        raise BagTruncatedError(f'{exc}: the file is truncated (crashed or interrupted '
                                'recording?); run "cdmp bag recover" on it', off) from None
    except _NoDataEnd:
        pass
    if not data_end_seen and require_footer:
        raise BagTruncatedError(
            f'{path}: file ends at byte {size} without data-end record and footer (crashed or '
            f'interrupted recording?); run "cdmp bag recover" on it', state.good_offset)


def _data_section(path, buf, size, state, max_chunk_bytes):
    """Scan the data section; return normally only after a valid DataEnd + summary."""
    for op, b0, b1 in _records(buf, 8, size, 0, path):
        cur = _Cursor(buf, b0, b1, 0, f'{path} record 0x{op:02x}')
        if op == OP_HEADER:
            state.profile = cur.string()
            state.library = cur.string()
        elif op in (OP_SCHEMA, OP_CHANNEL, OP_MESSAGE):
            recs: list = []
            _parse_inner(op, cur, state, recs)
            _check_refs(recs, state, path)
            state.good_offset = b1
            yield from recs
            continue
        elif op == OP_CHUNK:
            yield from _chunk(path, buf, b0, b1, cur, state, max_chunk_bytes)
        elif op == OP_METADATA:
            name = cur.string()
            state.metadata[name] = cur.str_map()
        elif op == OP_DATA_END:
            crc = cur.u32()
            if crc != 0:
                actual = zlib.crc32(buf[:b0 - 9])
                if actual != crc:
                    raise BagCrcError(f'{path}: data section CRC mismatch (stored 0x{crc:08x}, '
                                      f'computed 0x{actual:08x})', b0 - 9)
            state.good_offset = b1
            _check_summary(path, buf, b1, size, state)
            return
        elif op == OP_FOOTER:
            raise BagFormatError(f'{path}: footer before the data end record', b0 - 9)
        state.good_offset = b1
    raise _NoDataEnd()


def _chunk(path, buf, b0, b1, cur, state, max_chunk_bytes):
    start = cur.u64()
    end = cur.u64()
    state.bad_chunk_range = (start, end)
    usize = cur.u64()
    crc = cur.u32()
    compression = cur.string()
    clen = cur.u64()
    where = f'{path}: chunk at byte {b0 - 9}'
    if clen > cur.end - cur.pos:
        raise BagFormatError(f'{where} declares {clen} compressed bytes, record holds '
                             f'{cur.end - cur.pos}', b0 - 9)
    if usize > max_chunk_bytes:
        raise BagFormatError(f'{where} declares {usize} uncompressed bytes, more than the '
                             f'limit {max_chunk_bytes}', b0 - 9)
    data = _decompress(compression, bytes(buf[cur.pos:cur.pos + clen]), usize, where)
    if crc != 0:
        actual = zlib.crc32(data)
        if actual != crc:
            raise BagCrcError(f'{where}: CRC mismatch (stored 0x{crc:08x}, computed '
                              f'0x{actual:08x})', b0 - 9)
    recs: list = []
    try:
        for op, c0, c1 in _records(data, 0, len(data), 0, where):
            _parse_inner(op, _Cursor(data, c0, c1, 0, where), state, recs)
    except BagTruncatedError as exc:  # the CRC matched, so the writer produced this
        raise BagFormatError(f'{exc} (malformed chunk content)', b0 - 9) from None
    _check_refs(recs, state, where)
    state.bad_chunk_range = None
    state.chunks += 1
    state.good_offset = b1
    yield from recs


def _check_summary(path, buf, pos, size, state):
    """Check that the summary section is well framed, its CRC and the footer + magic."""
    for op, b0, b1 in _records(buf, pos, size - 8, 0, path):
        if op == OP_FOOTER:
            cur = _Cursor(buf, b0, b1, 0, f'{path} footer')
            s_start = cur.u64()
            cur.u64()
            crc = cur.u32()
            if b1 != size - 8:
                raise BagFormatError(f'{path}: bytes after the footer', b1)
            if buf[size - 8:size] != MAGIC:
                raise BagTruncatedError(f'{path}: missing closing magic', size - 8)
            if crc != 0 and s_start != 0:
                actual = zlib.crc32(buf[s_start:b1 - 4])
                if actual != crc:
                    raise BagCrcError(f'{path}: summary CRC mismatch', s_start)
            state.footer_seen = True
            state.good_offset = size
            return
    raise BagTruncatedError(f'{path}: no footer after the data section', pos)
