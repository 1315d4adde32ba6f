"""The recorder/player (bag) tests' own part: a reader of a child's output, the in-process
peer (:class:`Peer`, a :class:`node_harness.NodeHarness` without diagnostics) and the count of
what a recorder already has safe on disk. Node processes: :func:`node_harness.start_node`,
:func:`node_harness.stop_process`.
"""
import threading

from node_harness import WAIT_S, NodeHarness


class Lines:
    """The lines of a child's text stream, read by a background thread as they come."""

    def __init__(self, stream):
        self.lines = []
        self._thread = threading.Thread(target=self._read, args=(stream,), daemon=True)
        self._thread.start()

    def _read(self, stream):
        for line in iter(stream.readline, ''):
            self.lines.append(line)

    def seen(self, *needles):
        """True when every needle occurs in some line read so far."""
        return all(any(n in x for x in list(self.lines)) for n in needles)

    def text(self, timeout=WAIT_S):
        """Everything read; waits (bounded) for the end of the stream first."""
        self._thread.join(timeout)
        return ''.join(self.lines)


class Peer(NodeHarness):
    """An rclpy context + node in this process, spun by a background thread every 20 ms
    (publishers: :meth:`NodeHarness.publisher`, subscriptions: :meth:`NodeHarness.collect`)."""

    def __init__(self, name='test_peer', domain_id=None):
        super().__init__(name, domain_id, diagnostics=None, spin_period=0.02)


def recoverable_count(bag, probe_dir):
    """Messages already safe on disk in the bag a recorder is still writing: what
    ``recover_bag`` would keep now, rebuilt into ``probe_dir`` (the bag itself is untouched).

    The recorder only appends, so the count never decreases; 0 while there is no file yet.
    """
    import shutil
    from cdmp_ros.bag import BagError, recover_bag
    shutil.rmtree(probe_dir, ignore_errors=True)
    try:
        return recover_bag(bag, output=probe_dir).message_count
    except (BagError, OSError):
        return 0
