"""Headless TinyRenderer snapshots written as PNG."""
import matplotlib.image
import numpy as np
import pytest

from cdmp_ros.core.errors import ValidationError
from cdmp_ros.sim import CameraConfig, panda_spec, render, snapshot, World


def test_snapshot_writes_a_non_blank_png(tmp_path):
    cam = CameraConfig(width=160, height=120)
    with World() as world:
        empty = render(world, cam)
        world.add_robot(panda_spec())
        world.obstacles.add_sphere('ball', (0.4, 0.2, 0.5), 0.08)
        path = tmp_path / 'sub' / 'snap.png'
        img = snapshot(world, str(path), cam)
    assert path.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'
    back = matplotlib.image.imread(str(path))
    assert back.shape[:2] == (120, 160)
    np.testing.assert_allclose(back[..., :3], img / 255.0, atol=1 / 255 + 1e-6)
    assert img.shape == (120, 160, 3) and img.dtype == np.uint8
    # the robot and the ball are visible: many pixels differ from the empty scene
    changed = np.any(np.abs(img.astype(int) - empty.astype(int)) > 20, axis=2)
    assert changed.mean() > 0.02, changed.mean()
    assert img.std() > 5.0


def test_camera_config_validates():
    with pytest.raises(ValidationError, match='width'):
        CameraConfig(width=3)
    with pytest.raises(ValidationError, match='far'):
        CameraConfig(near=1.0, far=0.5)
