"""`cdmp bag info|recover` (no ROS) and `cdmp bag record|play` driving the nodes."""
import os
import signal
import subprocess
import sys

import pytest

from cdmp_ros.bag import BagReader
from cdmp_ros.cli.main import main

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
DEMO = os.path.join(ROOT, 'bags', 'panda_reach', 'demo_00')


def test_info_prints_topics_types_counts_duration(capsys):
    assert main(['bag', 'info', DEMO]) == 0
    out = capsys.readouterr().out
    assert '/demonstration' in out and 'sensor_msgs/msg/JointState' in out
    assert '201 msgs' in out and 'Duration:     2.000 s' in out


def test_info_on_truncated_bag_fails_with_a_clear_error(tmp_path, capsys):
    import shutil
    bag = tmp_path / 'cut'
    shutil.copytree(DEMO, bag)
    path = bag / 'demo_00_0.mcap'
    path.write_bytes(path.read_bytes()[:5000])
    assert main(['bag', 'info', str(bag)]) == 2
    assert 'recover' in capsys.readouterr().err


@pytest.mark.parametrize('option', ['--wait-subscribers', '--ack-timeout'])
@pytest.mark.parametrize('value', ['-1', 'nan', '1e9'])
def test_play_refuses_a_wait_out_of_range(capsys, option, value):
    assert main(['bag', 'play', DEMO, option, value]) == 2
    assert option in capsys.readouterr().err


def test_play_help_documents_the_waits(capsys):
    with pytest.raises(SystemExit) as exit_:
        main(['bag', 'play', '--help'])
    assert exit_.value.code == 0
    text = ' '.join(capsys.readouterr().out.split())
    assert '--wait-subscribers S before playing, wait up to S seconds until every played ' \
        'topic (and /clock with --clock) has a subscriber' in text
    assert '0 = play at once' in text
    assert '--ack-timeout S after the last message, wait up to S seconds until every ' \
        'reliable subscriber acknowledged every message' in text


def test_recover_command_reports_loss(tmp_path, capsys):
    from cdmp_ros.bag import BagWriter
    from cdmp_ros.bag.cdr import encode_string
    bag = tmp_path / 'crashed'
    with BagWriter(str(bag), flush_period=0) as w:
        w.add_topic('/s', 'std_msgs/msg/String')
        for i in range(300):
            w.write('/s', encode_string(f'message {i}'), i)
            if i % 100 == 99:
                w.flush()
    os.remove(bag / 'metadata.yaml')
    path = bag / 'crashed_0.mcap'
    raw = path.read_bytes()
    path.write_bytes(raw[:int(len(raw) * 0.6)])
    assert main(['bag', 'recover', str(bag), '--no-backup']) == 0
    out = capsys.readouterr().out
    assert 'recovered' in out and 'discarded' in out and 'lost' in out
    assert not (bag / 'crashed_0.mcap.crashed').exists()
    n = len(list(BagReader(str(bag)).messages()))
    assert n in (100, 200) and f'recovered {n} messages' in out


@pytest.mark.ros
def test_record_and_play_commands(tmp_path):
    from bag_ros_util import Lines, recoverable_count
    from conftest import wait_for
    from node_harness import WAIT_S
    from conftest import ros_env
    out = str(tmp_path / 'via_cli')
    cdmp = [sys.executable, '-m', 'cdmp_ros.cli.main', 'bag']
    rec = subprocess.Popen(cdmp + ['record', '-o', out, '/replayed'], env=ros_env(),
                           stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    rec_lines = Lines(rec.stdout)
    try:
        # the recorder runs (it subscribes as soon as the player's publisher appears) ...
        assert wait_for(lambda: rec_lines.seen('recording to'), WAIT_S), rec_lines.text(0)
        # ... and the player starts once it subscribed: a reliable writer then delivers all
        play = subprocess.run(cdmp + ['play', DEMO, '--rate', '4', '--remap',
                                      '/demonstration:=/replayed', '--wait-subscribers',
                                      str(WAIT_S)],
                              env=ros_env(), capture_output=True, text=True, timeout=120)
        assert play.returncode == 0, play.stdout + play.stderr
        # every message is on disk before the recorder is stopped
        probe = str(tmp_path / 'probe')
        assert wait_for(lambda: recoverable_count(out, probe) >= 201, WAIT_S, period=0.1)
        rec.send_signal(signal.SIGINT)  # the CLI forwards it to the recorder node
        rec.wait(timeout=60)
        rec_out = rec_lines.text()
    finally:
        if rec.poll() is None:
            rec.kill()
            rec.wait()
    assert rec.returncode == 0, rec_out
    assert '201 messages' in rec_out
    got = [m.data for m in BagReader(out).messages()]
    assert got == [m.data for m in BagReader(DEMO).messages()]
