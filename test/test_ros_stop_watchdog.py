"""The stop watchdog of every node (cdmp_ros.ros.node_main): a node whose stop hangs after
SIGINT writes the stack of every thread and exits on its own, within STOP_LIMIT of each part
of the stop that has no bound of its own.

Each case runs a small node process through ``run_node`` (real rclpy, localhost, a private
domain) and makes one part of its stop hang forever: the middleware teardown
(``destroy_node``, also blocked in C with the GIL held, in the node's code or inside rclpy's),
or the main loop (a ``done()`` that never returns). The test waits for the node's ``ready``
line, sends SIGINT and waits (bounded) for the exit. No duration is asserted: what is checked
is the exit code, the message and the stack of the place that hung.
A last case checks the order of the teardown that removed the hang of the sim and the streamer:
the node is destroyed only after its EventsExecutor shut down.
"""
import signal
import subprocess
import sys
import threading

import pytest

from conftest import module_domain, ros_env, wait_for
from cdmp_ros.common.node_signals import EXIT_BACKSTOP, teardown_hang
from cdmp_ros.ros.node_main import EXIT_STUCK

pytestmark = pytest.mark.ros
DOMAIN = module_domain(13)
TIMEOUT = 60.0   # s; bounds a failing wait only

NODE = '''
import sys
import threading

from cdmp_ros.ros.node_main import catch_stop_signals, make_executor, run_node
catch_stop_signals()
from rclpy.node import Node

HANG = sys.argv[1]


def hang_forever():
    threading.Event().wait()


def hang_holding_the_gil():
    """Block in C with the GIL held (a PyDLL call keeps it): lock a plain pthread mutex
    twice, as a teardown call waiting for a mutex that another thread keeps."""
    import ctypes
    libc = ctypes.PyDLL(None)
    mutex = ctypes.create_string_buffer(64)     # zeroed: PTHREAD_MUTEX_INITIALIZER (glibc)
    libc.pthread_mutex_lock(mutex)
    libc.pthread_mutex_lock(mutex)


def block_rclpys_node_handle(node):
    """The hang of Fast DDS 2.14's participant deletion (issue 31 item 3): rclpy's own
    destroy_node blocks in C in its node handle's last call, holding the GIL. The handle's
    destroy_when_not_in_use becomes a C call that never returns, and the node's destroy_node
    rclpy's own (no frame of this file on the main thread's stack)."""
    import ctypes
    import functools
    libc = ctypes.PyDLL(None)
    mutex = ctypes.create_string_buffer(64)
    libc.pthread_mutex_lock(mutex)
    handle = node._Node__node

    class Handle:
        destroy_when_not_in_use = functools.partial(libc.pthread_mutex_lock, mutex)

        def __getattr__(self, name):
            return getattr(handle, name)

        def __enter__(self):
            return handle.__enter__()

        def __exit__(self, *exc):
            return handle.__exit__(*exc)

    node._Node__node = Handle()
    node.destroy_node = functools.partial(Node.destroy_node, node)


class Stuck(Node):
    def __init__(self):
        super().__init__('stop_watchdog_case')

    def done(self):
        print('ready', flush=True)
        if HANG == 'loop':
            hang_forever()
        return False

    def close(self):
        print('closed', flush=True)
        if HANG == 'rclpy':
            block_rclpys_node_handle(self)

    def destroy_node(self):
        if HANG == 'order':     # the executor must have let go of every entity by now
            print(f'destroyed after the executor shut down: {SHUT_DOWN[0]}', flush=True)
        if HANG == 'teardown':
            hang_forever()
        if HANG == 'gil':
            hang_holding_the_gil()
        return super().destroy_node()


SHUT_DOWN = [False]


class Recording:
    """The EventsExecutor (a pybind11 class) with its shutdown recorded."""
    def __init__(self, executor):
        self._executor = executor

    def __getattr__(self, name):
        return getattr(self._executor, name)

    def shutdown(self, *args):
        result = self._executor.shutdown(*args)
        SHUT_DOWN[0] = True
        return result


EXECUTOR = Recording(make_executor()) if HANG == 'order' else None   # as the sim's main()
sys.exit(run_node(Stuck, ['--ros-args'], executor=EXECUTOR))
'''


def _run(case):
    """Start the node with ``case`` ('teardown', 'loop' or 'none') hanging, SIGINT it once it
    is in its loop; returns (exit code, output). The output is read by a thread (a line the
    middleware prints before ``ready`` is kept, not taken for it)."""
    lines = []
    proc = subprocess.Popen([sys.executable, '-c', NODE, case], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, env=ros_env(DOMAIN))
    reader = threading.Thread(target=lambda: lines.extend(iter(proc.stdout.readline, '')),
                              daemon=True)
    reader.start()
    try:
        assert wait_for(lambda: 'ready\n' in lines or proc.poll() is not None, TIMEOUT)
        assert proc.poll() is None, ''.join(lines)
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=TIMEOUT)
        reader.join(timeout=TIMEOUT)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    return proc.returncode, ''.join(lines)


def test_a_hanging_middleware_teardown_ends_after_close_with_the_stacks():
    code, text = _run('teardown')
    assert code == 0, text
    assert 'closed' in text
    assert ('the node has not exited 4 s after the stop signal (its close() had returned: '
            'the middleware teardown hangs)' in text), text
    assert 'in hang_forever' in text and 'in destroy_node' in text, text


def test_a_teardown_blocked_in_c_holding_the_gil_ends_by_the_backstop():
    """The sim's hung stop: the Python watchdog cannot run without the GIL; faulthandler's C
    thread ends the process with the stacks."""
    code, text = _run('gil')
    assert code == EXIT_BACKSTOP, text
    assert 'closed' in text
    assert 'Timeout (' in text, text
    assert 'in hang_holding_the_gil' in text and 'in destroy_node' in text, text
    assert not teardown_hang(code, text), text   # the node's own code: not excused


def test_a_hang_inside_rclpys_teardown_is_told_apart_from_the_nodes_own():
    """What the fixtures and cdmp bringup excuse: the backstop's exit with the main thread
    inside rclpy's destroy_node, after close(). The same exit from the node's own teardown
    code (the case above) is not excused."""
    code, text = _run('rclpy')
    assert code == EXIT_BACKSTOP and 'closed' in text, text
    assert 'rclpy/node.py' in text and 'in destroy_node' in text, text
    assert teardown_hang(code, text), text


def test_a_main_loop_that_never_ends_exits_stuck_with_the_stacks():
    code, text = _run('loop')
    assert code == EXIT_STUCK, text
    assert 'closed' not in text
    assert 'its main loop did not end, close() never started' in text, text
    assert 'in hang_forever' in text and 'in done' in text, text


def test_a_node_that_stops_normally_is_not_touched():
    """The same node without a hang: exit code 0, no watchdog message."""
    code, text = _run('none')
    assert code == 0 and 'closed' in text, text
    assert '[node_main]' not in text, text


def test_the_node_is_destroyed_after_its_events_executor_shut_down():
    """The hung stops of the sim and the streamer: the EventsExecutor holds the entities of
    its nodes until its shutdown, so a node destroyed before it had its DDS entities deleted
    inside that shutdown. run_node destroys the node after the executor's shutdown."""
    code, text = _run('order')
    assert code == 0 and 'closed' in text, text
    assert 'destroyed after the executor shut down: True' in text, text
    assert '[node_main]' not in text, text
