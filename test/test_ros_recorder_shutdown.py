"""cdmp_ros.ros.node_main, the shared Jazzy entry-point pattern: a node exits 0 on SIGINT and
SIGTERM and calls close() once, and a CdmpError while building the node gives exit code 2."""
import signal
import subprocess
import sys
import threading

import pytest

from conftest import ros_env

pytestmark = pytest.mark.ros

NODE = '''
import sys
from rclpy.node import Node
from cdmp_ros.core.errors import ValidationError
from cdmp_ros.ros.node_main import run_node

class Tiny(Node):
    def __init__(self):
        super().__init__('tiny')
        if sys.argv[1] == 'fail':
            raise ValidationError('parameter x: expected > 0, got -1')
        self.create_timer(0.05, self.tick)
        self.closed = 0

    def tick(self):
        print('tick', flush=True)

    def close(self):
        self.closed += 1
        print(f'closed {self.closed}', flush=True)

sys.exit(run_node(Tiny, []))
'''


@pytest.mark.parametrize('sig', [signal.SIGINT, signal.SIGTERM])
def test_signals_end_the_node_cleanly(sig):
    proc = subprocess.Popen([sys.executable, '-c', NODE, 'ok'], env=ros_env(),
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    watchdog = threading.Timer(60.0, proc.kill)  # a hang fails the test instead of blocking
    watchdog.start()
    try:
        assert proc.stdout.readline().strip() == 'tick'  # spinning
        proc.send_signal(sig)
        out, _ = proc.communicate(timeout=60)
    finally:
        watchdog.cancel()
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, out
    assert out.count('closed 1') == 1 and 'Traceback' not in out


def test_error_while_building_the_node_exits_2():
    proc = subprocess.run([sys.executable, '-c', NODE, 'fail'], env=ros_env(),
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    assert 'parameter x: expected > 0, got -1' in proc.stderr
