"""Turn a crashed recording (no footer, no summary, perhaps a cut chunk) into a readable bag.

The crashed ``.mcap`` is scanned from the start with the strict scanner; every record up to
the first one that is cut or fails its CRC is kept (whole chunks only: a chunk is used only if
its CRC matches), everything after is discarded and reported.  The messages kept are
rewritten into a fresh, indexed ``.mcap`` with :class:`~cdmp_ros.bag.writer.BagWriter` (same
topics, schemas, QoS metadata, times and sequence numbers) and ``metadata.yaml`` is written.
The original file is kept beside it as ``<name>.mcap.crashed`` unless ``keep_original`` is
False.
"""
import os
import shutil
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Tuple

import yaml
from cdmp_ros.bag.errors import BagError, BagFormatError
from cdmp_ros.bag.mcap_writer import McapStreamWriter
from cdmp_ros.bag.metadata import BagMetadata, TopicInfo, parse_qos
from cdmp_ros.bag.scan import ChannelRec, MessageRec, SchemaRec, ScanState, scan
from cdmp_ros.bag.writer import LIBRARY, mcap_file_name


@dataclass
class RecoveryReport:
    """What ``recover_bag`` kept and lost.

    Attributes
    ----------
    recovered : dict topic -> int
        Messages kept per topic.
    sequence_gaps : dict topic -> list of (after, before)
        Jumps in the per-topic sequence numbers among the kept messages (cdmp_ros writers
        number messages 1, 2, ...; empty for a gap-free prefix).
    bytes_discarded : int
        Bytes of the crashed file after the last valid record.
    last_log_time_ns : int or None
        Receive time of the last message kept.
    lost_chunk_range_ns : (int, int) or None
        Declared time range of the chunk that was cut or corrupted, when its header was
        readable: the data in it is lost.
    error : str or None
        Why the scan stopped (None if the file was complete).
    """

    bag_dir: str
    recovered: Dict[str, int] = field(default_factory=dict)
    sequence_gaps: Dict[str, List[Tuple[int, int]]] = field(default_factory=dict)
    bytes_discarded: int = 0
    last_log_time_ns: Optional[int] = None
    lost_chunk_range_ns: Optional[Tuple[int, int]] = None
    error: Optional[str] = None

    @property
    def message_count(self) -> int:
        return sum(self.recovered.values())

    def summary(self) -> str:
        """Human-readable report."""
        lines = [f'recovered {self.message_count} messages into {self.bag_dir}']
        for topic, n in sorted(self.recovered.items()):
            gaps = self.sequence_gaps.get(topic)
            lines.append(f'  {topic}: {n}' + (f' (sequence gaps: {gaps})' if gaps else ''))
        if self.error is None:
            lines.append('the file was complete: nothing lost')
        else:
            lines.append(f'stopped at: {self.error}')
            lines.append(f'discarded {self.bytes_discarded} trailing bytes')
            if self.last_log_time_ns is not None:
                lines.append(f'last recovered message at {self.last_log_time_ns} ns')
            if self.lost_chunk_range_ns is not None:
                a, b = self.lost_chunk_range_ns
                lines.append(f'lost: the cut chunk held messages from {a} to {b} ns '
                             f'({(b - a) / 1e9:.3f} s of data)')
            else:
                lines.append('lost: anything received after the last recovered message that '
                             'was not yet written')
        return '\n'.join(lines)


def _find_mcap(bag_dir: str) -> str:
    if os.path.isfile(bag_dir) and bag_dir.endswith('.mcap'):
        return bag_dir
    if not os.path.isdir(bag_dir):
        raise BagError(f'bag: {bag_dir} is neither a bag directory nor an .mcap file')
    mcaps = sorted(f for f in os.listdir(bag_dir) if f.endswith('.mcap'))
    if len(mcaps) != 1:
        raise BagError(f'bag: expected exactly one .mcap file in {bag_dir}, found {mcaps}')
    return os.path.join(bag_dir, mcaps[0])


def recover_bag(bag: str, output: Optional[str] = None,
                keep_original: bool = True) -> RecoveryReport:
    """Rebuild a readable bag from a crashed or truncated recording.

    Parameters
    ----------
    bag : str
        Bag directory holding one ``.mcap`` (or the ``.mcap`` file itself).
    output : str, optional
        Write the recovered bag directory here instead of repairing ``bag`` in place.
    keep_original : bool
        In-place repair keeps the crashed file as ``<file>.crashed``.

    Returns
    -------
    RecoveryReport

    Raises
    ------
    BagError
        If there is no ``.mcap`` or it is not MCAP at all (bad magic).
    """
    src = _find_mcap(bag)
    out_dir = output if output is not None else (bag if os.path.isdir(bag) else
                                                 os.path.dirname(src))
    os.makedirs(out_dir, exist_ok=True)
    out_name = mcap_file_name(out_dir)
    out_path = os.path.join(out_dir, out_name)
    tmp = out_path + '.recovering'
    state = ScanState()
    schemas: Dict[int, SchemaRec] = {}
    topics: Dict[int, TopicInfo] = {}
    report = RecoveryReport(bag_dir=out_dir)
    last_seq: Dict[int, int] = {}
    t_min = t_max = None
    with open(tmp, 'wb') as f:
        w = McapStreamWriter(f, profile='ros2', library=LIBRARY + ' (recovered)')
        sid_map: Dict[int, int] = {}
        cid_map: Dict[int, int] = {}
        try:
            for rec in scan(src, state, require_footer=True):
                if isinstance(rec, MessageRec):
                    w.add_message(cid_map[rec.channel_id], rec.sequence, rec.log_time,
                                  rec.publish_time, rec.data)
                    t = topics[rec.channel_id]
                    t.message_count += 1
                    prev = last_seq.get(rec.channel_id)
                    if prev is not None and rec.sequence not in (0, prev + 1):
                        report.sequence_gaps.setdefault(t.name, []).append((prev, rec.sequence))
                    last_seq[rec.channel_id] = rec.sequence
                    t_min = rec.log_time if t_min is None else min(t_min, rec.log_time)
                    t_max = rec.log_time if t_max is None else max(t_max, rec.log_time)
                elif isinstance(rec, SchemaRec):
                    schemas[rec.id] = rec
                    sid_map[rec.id] = len(sid_map) + 1
                    w.add_schema(sid_map[rec.id], rec.name, rec.encoding, rec.data)
                elif isinstance(rec, ChannelRec):
                    cid_map[rec.id] = len(cid_map) + 1
                    w.add_channel(cid_map[rec.id], sid_map.get(rec.schema_id, 0), rec.topic,
                                  rec.message_encoding, rec.metadata)
                    schema = schemas.get(rec.schema_id)
                    topics[rec.id] = TopicInfo(
                        name=rec.topic, type=schema.name if schema else '',
                        serialization_format=rec.message_encoding,
                        offered_qos_profiles=parse_qos(
                            rec.metadata.get('offered_qos_profiles', '')),
                        type_description_hash=rec.metadata.get('topic_type_hash', ''))
        except BagFormatError as exc:
            if state.good_offset == 0:
                f.close()
                os.remove(tmp)
                raise
            report.error = str(exc)
            report.bytes_discarded = state.file_size - state.good_offset
            report.lost_chunk_range_ns = state.bad_chunk_range
        count = sum(t.message_count for t in topics.values())
        meta = BagMetadata(relative_file_paths=[out_name], topics=list(topics.values()),
                           starting_time_ns=t_min or 0,
                           duration_ns=(t_max - t_min) if t_min is not None else 0,
                           message_count=count)
        w.add_metadata('rosbag2', {'serialized_metadata': yaml.safe_dump(
            meta.to_dict(), default_flow_style=False, sort_keys=False)})
        w.finish()
        f.flush()
        os.fsync(f.fileno())
    if os.path.dirname(os.path.abspath(src)) == os.path.abspath(out_dir):
        if keep_original:
            shutil.move(src, src + '.crashed')
        elif os.path.abspath(src) != os.path.abspath(out_path):
            os.remove(src)
    os.replace(tmp, out_path)
    meta.write(out_dir)
    report.recovered = {t.name: t.message_count for t in topics.values()}
    report.last_log_time_ns = t_max
    return report
