"""Read rosbag2 bag directories (or a bare ``.mcap`` file) strictly.

:class:`BagReader` never yields a message from a chunk whose CRC failed, and :meth:`verify`
checks a whole bag (every chunk, data-section and summary CRC, footer) before anything is
used, which is what the player does before it publishes.  Messages come in file order, which
for rosbag2 / cdmp_ros / rosbags writers is the order of reception.
"""
import os
from dataclasses import dataclass
from typing import Dict, Iterable, Iterator, List, Optional

from cdmp_ros.bag.errors import BagError, BagFormatError
from cdmp_ros.bag.metadata import (METADATA_FILE, BagMetadata, TopicInfo, parse_qos, read_metadata)
from cdmp_ros.bag.scan import MAX_CHUNK_BYTES, ChannelRec, MessageRec, ScanState, scan


@dataclass(frozen=True)
class BagMessage:
    """One recorded message: topic, type, times (ns) and the serialized CDR bytes."""

    topic: str
    type: str
    log_time: int
    publish_time: int
    sequence: int
    data: bytes


class BagReader:
    """Strict reader of a rosbag2 bag directory with MCAP storage, or of one ``.mcap`` file.

    Parameters
    ----------
    path : str
        Bag directory (with ``metadata.yaml``) or an ``.mcap`` file.
    max_chunk_bytes : int
        Refuse chunks declaring a larger uncompressed size (memory bound).

    Raises
    ------
    BagError
        If the path is neither.
    """

    def __init__(self, path: str, max_chunk_bytes: int = MAX_CHUNK_BYTES):
        self.path = path
        self.max_chunk_bytes = max_chunk_bytes
        self.metadata: Optional[BagMetadata] = None
        if os.path.isdir(path):
            if not os.path.isfile(os.path.join(path, METADATA_FILE)):
                mcaps = sorted(f for f in os.listdir(path) if f.endswith('.mcap'))
                hint = (f' ({", ".join(mcaps)} without metadata: a crashed recording? run '
                        f'"cdmp bag recover {path}")') if mcaps else ''
                raise BagError(f'{path}: no {METADATA_FILE}{hint}')
            self.metadata = read_metadata(path)
            if self.metadata.storage_identifier != 'mcap':
                raise BagError(f'{path}: storage {self.metadata.storage_identifier!r} is not '
                               'supported (only mcap)')
            self.files = [os.path.join(path, f) for f in self.metadata.relative_file_paths]
            for f in self.files:
                if not os.path.isfile(f):
                    raise BagError(f'{path}: storage file {f} listed in {METADATA_FILE} is '
                                   'missing')
        elif os.path.isfile(path):
            self.files = [path]
        else:
            raise BagError(f'path: {path} is neither a bag directory nor an .mcap file')

    def _scan(self, state: ScanState) -> Iterator:
        for f in self.files:
            st = ScanState()
            for rec in scan(f, st, require_footer=True, max_chunk_bytes=self.max_chunk_bytes):
                yield st, rec
            if st.profile not in ('ros2', ''):
                raise BagFormatError(f'{f}: MCAP profile {st.profile!r} is not ros2')
            state.chunks += st.chunks

    def messages(self, topics: Optional[Iterable[str]] = None) -> Iterator[BagMessage]:
        """Yield the messages (all topics, or those named) in file order.

        Raises
        ------
        BagFormatError, BagTruncatedError, BagCrcError
            At the first invalid byte; nothing from a bad chunk is yielded.
        """
        wanted = set(topics) if topics is not None else None
        schemas_of: Dict[int, str] = {}
        for st, rec in self._scan(ScanState()):
            if isinstance(rec, MessageRec):
                ch = st.channels[rec.channel_id]
                if wanted is not None and ch.topic not in wanted:
                    continue
                if ch.message_encoding != 'cdr':
                    raise BagFormatError(f'{self.path}: topic {ch.topic} has message encoding '
                                         f'{ch.message_encoding!r}, expected cdr')
                yield BagMessage(ch.topic, schemas_of.get(ch.id) or _type(st, ch),
                                 rec.log_time, rec.publish_time, rec.sequence, rec.data)
            elif isinstance(rec, ChannelRec):
                schemas_of[rec.id] = _type(st, rec)

    def verify(self) -> Dict[str, TopicInfo]:
        """Read the whole bag, checking every CRC and the footer; return per-topic info.

        Counts are those actually read; if ``metadata.yaml`` disagrees a
        :class:`BagFormatError` is raised.
        """
        state = ScanState()
        found: Dict[str, TopicInfo] = {}
        for st, rec in self._scan(state):
            if isinstance(rec, ChannelRec):
                if rec.topic not in found:
                    found[rec.topic] = TopicInfo(
                        name=rec.topic, type=_type(st, rec),
                        serialization_format=rec.message_encoding,
                        offered_qos_profiles=parse_qos(rec.metadata.get(
                            'offered_qos_profiles', '')),
                        type_description_hash=rec.metadata.get('topic_type_hash', ''))
            elif isinstance(rec, MessageRec):
                found[st.channels[rec.channel_id].topic].message_count += 1
        if self.metadata is not None:
            declared = {t.name: t.message_count for t in self.metadata.topics}
            actual = {k: v.message_count for k, v in found.items()}
            for name, n in declared.items():
                if actual.get(name, 0) != n:
                    raise BagFormatError(f'{self.path}: {METADATA_FILE} declares {n} messages '
                                         f'on {name}, the storage holds {actual.get(name, 0)}')
        return found

    def topics(self) -> List[TopicInfo]:
        """Topics from ``metadata.yaml``, or from a verifying scan for a bare ``.mcap``."""
        if self.metadata is not None:
            return list(self.metadata.topics)
        return list(self.verify().values())


def _type(st: ScanState, ch: ChannelRec) -> str:
    schema = st.schemas.get(ch.schema_id)
    if schema is None:
        raise BagFormatError(f'channel {ch.topic}: no schema (cannot tell its type)')
    return schema.name


def bag_info(path: str) -> Dict:
    """Verified summary of a bag: topics, types, counts, start, duration (for ``cdmp bag info``).

    Raises
    ------
    BagError
        If the bag is missing, truncated or corrupted.
    """
    reader = BagReader(path)
    topics = reader.verify()
    t0 = t1 = None
    n = 0
    for m in reader.messages():
        t0 = m.log_time if t0 is None else min(t0, m.log_time)
        t1 = m.log_time if t1 is None else max(t1, m.log_time)
        n += 1
    return {'path': path, 'files': [os.path.basename(f) for f in reader.files],
            'message_count': n, 'starting_time_ns': t0 or 0,
            'duration_ns': (t1 - t0) if t0 is not None else 0,
            'topics': [{'name': t.name, 'type': t.type, 'count': t.message_count,
                        'serialization_format': t.serialization_format}
                       for t in topics.values()]}
