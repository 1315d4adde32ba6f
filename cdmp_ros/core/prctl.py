"""The one ``prctl(2)`` call of the package (Linux; standard library only, so every layer may
use it): the streamer's timer slack (:mod:`cdmp_ros.ros.realtime`) and the parent-death signal
of a graph's nodes (:mod:`cdmp_ros.cli.cmd_bringup`)."""
import ctypes
import ctypes.util

#: prctl option that sends the calling process a signal when its parent dies (linux/prctl.h).
PR_SET_PDEATHSIG = 1
#: prctl option number of PR_SET_TIMERSLACK (linux/prctl.h).
PR_SET_TIMERSLACK = 29

_libc = None


def prctl(option: int, arg: int) -> bool:
    """``prctl(option, arg, 0, 0, 0)`` for the calling thread/process; False when prctl is
    unavailable (not Linux) or refuses. Never raises."""
    global _libc
    try:
        if _libc is None:
            _libc = ctypes.CDLL(ctypes.util.find_library('c') or 'libc.so.6', use_errno=True)
        return _libc.prctl(option, ctypes.c_ulong(arg), 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False
