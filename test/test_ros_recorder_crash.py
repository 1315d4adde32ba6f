"""SIGKILL of the recorder at random times: `recover_bag` yields a gap-free prefix of what was
published and the data lost is within the declared bound (LOSS_BOUND_S = 0.25 s)."""
import os
import signal
import time

import numpy as np
import pytest

from bag_ros_util import Peer, start_node, stop, wait_for
from cdmp_ros.bag import LOSS_BOUND_S, BagError, BagReader, recover_bag
from cdmp_ros.bag.cdr import decode_string, encode_string

pytestmark = pytest.mark.ros


@pytest.fixture
def peer():
    p = Peer('crash_peer')
    yield p
    p.close()


def test_sigkill_at_random_times_loses_at_most_the_bound(tmp_path, peer):
    from std_msgs.msg import String
    rng = np.random.default_rng(2026)
    for trial, kill_after in enumerate(rng.uniform(0.4, 1.4, size=3)):
        bag = str(tmp_path / f'crash{trial}')
        # one topic per trial: a killed recorder stays matched until its DDS lease expires
        pub = peer.publisher(String, f'/crash{trial}')
        rec = start_node('recorder', {'output': bag, 'topics': [f'/crash{trial}']},
                         log_path=str(tmp_path / f'rec{trial}.log'))
        try:
            assert wait_for(lambda: pub.get_subscription_count() >= 1, 20)
            time.sleep(0.3)
            mcap = os.path.join(bag, f'crash{trial}_0.mcap')
            base = os.path.getsize(mcap)
            start = None
            i = 0
            kill_ns = None
            deadline = time.monotonic() + 15
            while time.monotonic() < deadline:
                pub.publish(encode_string(f'{trial}:{i}'))
                i += 1
                # the clock starts when the first chunk reached the file (on a loaded machine
                # the recorder's reader may match the publisher a little late)
                if start is None and os.path.getsize(mcap) > base:
                    start = time.monotonic()
                if start is not None:
                    elapsed = time.monotonic() - start
                    if kill_ns is None and elapsed >= kill_after:
                        kill_ns = time.time_ns()
                        rec.send_signal(signal.SIGKILL)
                    if elapsed >= kill_after + 0.3:
                        break
                time.sleep(0.001)
        finally:
            stop(rec, signal.SIGKILL)
        assert kill_ns is not None
        assert not os.path.exists(os.path.join(bag, 'metadata.yaml'))
        with pytest.raises(BagError):
            BagReader(bag)
        report = recover_bag(bag)
        got = [decode_string(m.data) for m in BagReader(bag).messages()]
        assert got, f'trial {trial}: nothing recovered after {kill_after:.2f} s'
        idx = [int(s.split(':')[1]) for s in got]
        assert idx == list(range(idx[0], idx[0] + len(idx))), 'recovered data has gaps'
        assert not report.sequence_gaps
        lost_s = (kill_ns - report.last_log_time_ns) / 1e9
        print(f'trial {trial}: kill after {kill_after:.2f} s, lost {lost_s:.3f} s')
        assert lost_s <= LOSS_BOUND_S, (
            f'trial {trial}: lost {lost_s:.3f} s of data (bound {LOSS_BOUND_S} s)\n'
            + report.summary())
