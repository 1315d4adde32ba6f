"""The one ``prctl(2)`` call of the package (Linux; standard library only, so every layer may
use it): the streamer's timer slack (:mod:`cdmp_ros.common.realtime`) and the parent-death
signal of a graph's nodes (:mod:`cdmp_ros.cli.cmd_bringup`)."""
import ctypes
import ctypes.util

#: prctl option that sends the calling process a signal when its parent dies (linux/prctl.h).
PR_SET_PDEATHSIG = 1
#: prctl option number of PR_SET_TIMERSLACK (linux/prctl.h).
PR_SET_TIMERSLACK = 29

_libc = None


def load() -> bool:
    """Load the C library now (idempotent); True if it has ``prctl``.

    Call it in a parent before forking: a ``preexec_fn`` runs in the child of a possibly
    multi-threaded parent, where loading a library (``find_library`` even starts
    ``ldconfig``) may deadlock; after this the child only makes the call."""
    global _libc
    if _libc is None:
        try:
            _libc = ctypes.CDLL('libc.so.6', use_errno=True)
        except OSError:
            try:
                _libc = ctypes.CDLL(ctypes.util.find_library('c') or 'libc.so.6',
                                    use_errno=True)
            except OSError:
                _libc = False
    return bool(_libc) and hasattr(_libc, 'prctl')


def prctl(option: int, arg: int) -> bool:
    """``prctl(option, arg, 0, 0, 0)`` for the calling thread/process; False when prctl is
    unavailable (not Linux) or refuses. Never raises."""
    try:
        if not load():
            return False
        return _libc.prctl(option, ctypes.c_ulong(arg), 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False
