"""The signals between a graph launcher and its node processes, and what a node's exit says
(standard library only, so every layer may use it): :mod:`cdmp_ros.ros.node_main` handles them
in each node, :mod:`cdmp_ros.cli.cmd_bringup` sends them and reads the exits."""
import re
import signal

#: Signals that stop a node (exit code 0 after its ``close()``).
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)
#: Makes a node write the Python stack of every thread to its stderr (``cdmp bringup`` sends it
#: to a node that has not stopped within ``stop_timeout``, before SIGKILL).
DUMP_SIGNAL = signal.SIGUSR1
#: Exit code of a node ended by the stop watchdog's GIL-free backstop (faulthandler's
#: ``dump_traceback_later(exit=True)``, :mod:`cdmp_ros.ros.node_main`).
EXIT_BACKSTOP = 1
#: The rclpy calls with which ``run_node`` tears the middleware down once the node's
#: ``close()`` has returned (``executor.remove_node``, ``executor.shutdown``,
#: ``node.destroy_node``, ``rclpy.try_shutdown``).
TEARDOWN_CALLS = frozenset({'remove_node', 'shutdown', 'destroy_node', 'try_shutdown'})
#: faulthandler's header of a ``dump_traceback_later`` dump.
_BACKSTOP_HEADER = re.compile(r'^Timeout \(\d+:\d\d:\d\d(?:\.\d+)?\)!$', re.M)
_FRAME = re.compile(r'^\s+File "(?P<path>[^"]*)", line \d+ in (?P<func>\S+)\s*$')
_ENTRY = ('<module>', '_run_module_as_main')


def teardown_hang(code: int, output: str) -> bool:
    """Whether a node's exit was the stop backstop ending a hang inside rclpy's middleware
    teardown, after the node's ``close()`` had returned.

    Evidence required, from the node's exit code and its output (stdout and stderr): the code
    is :data:`EXIT_BACKSTOP`; the output holds faulthandler's ``Timeout (...)!`` dump; in the
    last such dump, the main thread (the stack that starts at the executable's ``<module>``)
    is inside rclpy only, in a call of :data:`TEARDOWN_CALLS` made by ``run_node``. Such a
    node did all of its own work, its close() included; what hung is below rclpy, holding the
    GIL (see :mod:`cdmp_ros.ros.node_main`). A hang in the node's own code, in ``close()``, in
    the spin loop, or a dump cut short is not one.
    """
    if code != EXIT_BACKSTOP:
        return False
    headers = list(_BACKSTOP_HEADER.finditer(output))
    if not headers:
        return False
    for block in re.split(r'\n[ \t]*\n', output[headers[-1].end():]):
        frames = [m.group('path', 'func') for m in map(_FRAME.match, block.splitlines()) if m]
        if not frames or frames[-1][1] not in _ENTRY:
            continue                                # not the main thread's stack
        for i, (path, func) in enumerate(frames):
            if func == 'run_node' and path.replace('\\', '/').endswith('/node_main.py'):
                below = frames[:i]
                return (bool(below) and below[-1][1] in TEARDOWN_CALLS and
                        all('/rclpy/' in p.replace('\\', '/') for p, _ in below))
        return False
    return False
