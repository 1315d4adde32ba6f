"""rosbag2 ``metadata.yaml`` (format version 9, as rosbag2 Jazzy writes it) and QoS profiles.

A QoS profile is a plain dict in the version-9 layout::

    {'history': 'keep_last', 'depth': 10, 'reliability': 'reliable',
     'durability': 'volatile', 'deadline': {'sec': 9223372036, 'nsec': 854775807}, ...}

The ``ros`` layer converts rclpy profiles to and from this form (cdmp_ros/ros/qos.py).
"""
import os
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional

import yaml

from cdmp_ros.bag.errors import BagError, BagFormatError

METADATA_FILE = 'metadata.yaml'
METADATA_VERSION = 9
ROS_DISTRO = 'jazzy'
#: rmw's "infinite" duration as rosbag2 serializes it.
INFINITE = {'sec': 9223372036, 'nsec': 854775807}


def qos_dict(history: str = 'keep_last', depth: int = 10, reliability: str = 'reliable',
             durability: str = 'volatile', liveliness: str = 'automatic') -> Dict[str, Any]:
    """One offered QoS profile in the rosbag2 version-9 layout (infinite deadline/lifespan)."""
    return {'history': history, 'depth': int(depth), 'reliability': reliability,
            'durability': durability, 'deadline': dict(INFINITE), 'lifespan': dict(INFINITE),
            'liveliness': liveliness, 'liveliness_lease_duration': dict(INFINITE),
            'avoid_ros_namespace_conventions': False}


def dump_qos(profiles: List[Dict[str, Any]]) -> str:
    """YAML text of a list of QoS profiles (as stored in MCAP channel metadata)."""
    if not profiles:
        return ''
    return yaml.safe_dump(list(profiles), default_flow_style=False, sort_keys=False).strip()


def parse_qos(value: Any) -> List[Dict[str, Any]]:
    """QoS profiles from metadata (a list, or YAML text as in version <= 8 and MCAP)."""
    if not value:
        return []
    if isinstance(value, str):
        try:
            value = yaml.safe_load(value)
        except yaml.YAMLError as exc:
            raise BagFormatError(f'offered_qos_profiles: not YAML ({exc})') from None
    if not isinstance(value, list):
        raise BagFormatError(f'offered_qos_profiles: expected a list, got {type(value).__name__}')
    return value


@dataclass
class TopicInfo:
    """One topic of a bag: name, type, message count, QoS, type hash."""

    name: str
    type: str
    message_count: int = 0
    serialization_format: str = 'cdr'
    offered_qos_profiles: List[Dict[str, Any]] = field(default_factory=list)
    type_description_hash: str = ''


@dataclass
class BagMetadata:
    """Content of ``metadata.yaml`` (``rosbag2_bagfile_information``)."""

    relative_file_paths: List[str]
    topics: List[TopicInfo]
    starting_time_ns: int = 0
    duration_ns: int = 0
    message_count: int = 0
    storage_identifier: str = 'mcap'
    version: int = METADATA_VERSION
    custom_data: Optional[Dict[str, str]] = None
    ros_distro: str = ROS_DISTRO

    def to_dict(self) -> Dict[str, Any]:
        """The ``rosbag2_bagfile_information`` mapping."""
        topics = []
        for t in self.topics:
            tm = {'name': t.name, 'type': t.type,
                  'serialization_format': t.serialization_format,
                  'offered_qos_profiles': list(t.offered_qos_profiles),
                  'type_description_hash': t.type_description_hash}
            topics.append({'topic_metadata': tm, 'message_count': int(t.message_count)})
        files = [{'path': p, 'starting_time': {'nanoseconds_since_epoch': self.starting_time_ns},
                  'duration': {'nanoseconds': self.duration_ns},
                  'message_count': self.message_count} for p in self.relative_file_paths]
        return {
            'version': self.version,
            'storage_identifier': self.storage_identifier,
            'duration': {'nanoseconds': int(self.duration_ns)},
            'starting_time': {'nanoseconds_since_epoch': int(self.starting_time_ns)},
            'message_count': int(self.message_count),
            'topics_with_message_count': topics,
            'compression_format': '',
            'compression_mode': '',
            'relative_file_paths': list(self.relative_file_paths),
            'files': files,
            'custom_data': self.custom_data,
            'ros_distro': self.ros_distro,
        }

    def to_yaml(self) -> str:
        return yaml.safe_dump({'rosbag2_bagfile_information': self.to_dict()},
                              default_flow_style=False, sort_keys=False)

    def write(self, bag_dir: str) -> str:
        """Write ``metadata.yaml`` atomically (temp file + rename); return its path."""
        path = os.path.join(bag_dir, METADATA_FILE)
        tmp = path + '.tmp'
        with open(tmp, 'w', encoding='utf-8') as f:
            f.write(self.to_yaml())
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
        return path


def read_metadata(bag_dir: str) -> BagMetadata:
    """Parse ``<bag_dir>/metadata.yaml``.

    Raises
    ------
    BagError
        If the file is missing (e.g. a crashed recording: use ``cdmp bag recover``).
    BagFormatError
        If it is not rosbag2 metadata.
    """
    path = os.path.join(bag_dir, METADATA_FILE)
    if not os.path.isfile(path):
        raise BagError(f'{bag_dir}: no {METADATA_FILE} (not a rosbag2 bag directory, or a '
                       'crashed recording: run "cdmp bag recover" on it)')
    try:
        with open(path, encoding='utf-8') as f:
            doc = yaml.safe_load(f)
        info = doc['rosbag2_bagfile_information']
        topics = []
        for entry in info.get('topics_with_message_count') or []:
            tm = entry['topic_metadata']
            topics.append(TopicInfo(
                name=tm['name'], type=tm['type'], message_count=int(entry['message_count']),
                serialization_format=tm.get('serialization_format', 'cdr'),
                offered_qos_profiles=parse_qos(tm.get('offered_qos_profiles')),
                type_description_hash=tm.get('type_description_hash', '') or ''))
        return BagMetadata(
            relative_file_paths=list(info['relative_file_paths']), topics=topics,
            starting_time_ns=int(info['starting_time']['nanoseconds_since_epoch']),
            duration_ns=int(info['duration']['nanoseconds']),
            message_count=int(info['message_count']),
            storage_identifier=info['storage_identifier'], version=int(info['version']),
            custom_data=info.get('custom_data'), ros_distro=info.get('ros_distro', ''))
    except (KeyError, TypeError, ValueError, yaml.YAMLError) as exc:
        raise BagFormatError(f'{path}: not rosbag2 metadata ({type(exc).__name__}: {exc})'
                             ) from None
