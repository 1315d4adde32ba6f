"""Locate the package's data files (msg_schemas/, config/) in a source tree or an install.

Search order: the source tree beside the package (editable installs, tests), then
``<prefix>/share/cdmp_ros`` for the interpreter prefix and every ``AMENT_PREFIX_PATH`` entry
(colcon and pip installs).
"""
import functools
import json
import os
import sys
from typing import List

from cdmp_ros.core.errors import CdmpError

_PKG_DIR = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def share_dirs() -> List[str]:
    """Candidate directories holding msg_schemas/ and config/, best first."""
    dirs = [os.path.dirname(_PKG_DIR)]
    prefixes = [sys.prefix] + [p for p in os.environ.get('AMENT_PREFIX_PATH', '').split(
        os.pathsep) if p]
    dirs += [os.path.join(p, 'share', 'cdmp_ros') for p in prefixes]
    return dirs


def data_path(*parts: str) -> str:
    """Absolute path of a data file, e.g. ``data_path('msg_schemas', 'x.json')``."""
    for base in share_dirs():
        candidate = os.path.join(base, *parts)
        if os.path.exists(candidate):
            return candidate
    raise CdmpError(f'data file {os.path.join(*parts)!r} not found in {share_dirs()}')


def schema_path(name: str) -> str:
    """Absolute path of ``msg_schemas/<name>``."""
    return data_path('msg_schemas', name)


@functools.lru_cache(maxsize=None)
def load_schema(name: str) -> dict:
    """The JSON Schema ``msg_schemas/<name>``, read once (the same dict on every call: the
    validators are cached by its identity)."""
    with open(schema_path(name)) as f:
        return json.load(f)
