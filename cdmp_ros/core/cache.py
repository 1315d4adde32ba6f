"""The package's cache directories: files computed once per input and reused by every process.

Four kinds use it: generated kernels (``kernels``, :mod:`cdmp_ros.core.generated`; code is
imported from them), fitted link capsules (``capsules``,
:mod:`cdmp_ros.core.kinematics.capsules`; checked on reading), generated URDFs (``urdf``,
:mod:`cdmp_ros.sim.robot_specs`) and ``cdmp bringup``'s parameter files (``parameters``). A
kind's directory is, in this order: its own environment variable if the kind has one
(``$CDMP_ROS_KERNEL_CACHE``), ``$CDMP_ROS_CACHE/<kind>``, ``$XDG_CACHE_HOME/cdmp_ros/<kind>``,
``~/.cache/cdmp_ros/<kind>``; :func:`fallback_dir` when that is not usable
(:func:`locations`). Only directories of this user that no one else may write are used
(:func:`private_dir`); files are written atomically (:func:`write_atomic`), so concurrent
processes never see half a file.
"""
import os
import stat
import tempfile
from typing import List, Optional, Sequence, Tuple

from cdmp_ros.core.errors import ValidationError

#: Root of every kind's directory when set (the tests set it to a directory of their session).
CACHE_ENV = 'CDMP_ROS_CACHE'


def _absolute(path: str) -> str:
    return os.path.abspath(os.path.expanduser(path))


def cache_dir(kind: str, env: Optional[str] = None) -> str:
    """The directory of ``kind`` (module docstring); ``env``: the kind's own variable."""
    own = os.environ.get(env) if env else None
    if own:
        return _absolute(own)
    root = os.environ.get(CACHE_ENV)
    if root:
        return os.path.join(_absolute(root), kind)
    base = os.environ.get('XDG_CACHE_HOME') or os.path.join(os.path.expanduser('~'), '.cache')
    return os.path.join(_absolute(base), 'cdmp_ros', kind)


def fallback_dir(kind: str) -> str:
    """The temporary directory of ``kind`` when :func:`cache_dir` is not usable."""
    return os.path.join(tempfile.gettempdir(), f'cdmp_ros_{kind}_{os.getuid()}')


def locations(kind: str, env: Optional[str] = None) -> Tuple[str, str]:
    """Where files of ``kind`` are looked for and written, in order."""
    return cache_dir(kind, env), fallback_dir(kind)


def _problem(st: os.stat_result) -> Optional[str]:
    if (not stat.S_ISDIR(st.st_mode) or st.st_uid != os.getuid()
            or st.st_mode & (stat.S_IWGRP | stat.S_IWOTH)):
        return f'not a directory of uid {os.getuid()} closed to others'
    return None


def private_dir(directory: str) -> Optional[str]:
    """Create ``directory`` (mode 0700) if needed; what is wrong with it, or None when it is a
    directory of this user that no one else may write."""
    os.makedirs(directory, mode=0o700, exist_ok=True)
    return _problem(os.lstat(directory))


def write_atomic(directory: str, filename: str, text: str) -> str:
    """``text`` as ``directory/filename`` (kept if already identical; written atomically), in
    a directory :func:`private_dir` accepted."""
    path = os.path.join(directory, filename)
    try:
        if stat.S_ISREG(os.lstat(path).st_mode):
            with open(path, encoding='utf-8') as f:
                if f.read(len(text) + 1) == text:
                    return path
    except (OSError, UnicodeDecodeError):
        pass
    fd, tmp = tempfile.mkstemp(prefix='.' + filename, dir=directory)
    try:
        with os.fdopen(fd, 'w', encoding='utf-8') as f:
            f.write(text)
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
    return path


def store(filename: str, text: str,
          directories: Sequence[str]) -> Tuple[Optional[str], List[str]]:
    """``text`` written as ``filename`` into the first usable of ``directories``: its path
    (None if none was usable) and what was wrong with the ones passed over."""
    errors = []
    for directory in directories:
        try:
            problem = private_dir(directory)
            if problem is None:
                return write_atomic(directory, filename, text), errors
            errors.append(f'{directory}: {problem}')
        except OSError as exc:
            errors.append(f'{directory}: {exc}')
    return None, errors


def store_or_raise(filename: str, text: str, directories: Sequence[str], what: str) -> str:
    """:func:`store`, raising a ValidationError that names ``what`` and every directory's
    problem when none was usable."""
    path, errors = store(filename, text, directories)
    if path is None:
        raise ValidationError(f'cannot write {what} ({filename}): {"; ".join(errors)}')
    return path


def read(filename: str, directories: Sequence[str], max_bytes: int) -> Optional[str]:
    """The text of ``filename`` in the first of ``directories`` that exists, is private (as
    :func:`private_dir` requires; nothing is created) and holds it as a regular file of at
    most ``max_bytes``; None if none does."""
    for directory in directories:
        try:
            if _problem(os.lstat(directory)) is not None:
                continue
            path = os.path.join(directory, filename)
            st = os.lstat(path)
            if not stat.S_ISREG(st.st_mode) or st.st_size > max_bytes:
                continue
            with open(path, encoding='utf-8') as f:
                text = f.read(max_bytes + 1)
            if len(text) <= max_bytes:
                return text
        except (OSError, UnicodeDecodeError):
            continue
    return None
