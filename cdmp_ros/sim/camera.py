"""Headless camera snapshots of a world (pybullet's TinyRenderer, no GPU or display needed)."""
from dataclasses import dataclass
import os
from typing import Optional

import numpy as np
from numpy.typing import NDArray
import pybullet

from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.validation import as_array, check_positive


@dataclass(frozen=True)
class CameraConfig:
    """An orbit camera looking at ``target``.

    Attributes
    ----------
    width, height : int
        Image size [px].
    target : tuple of float
        Point looked at, world frame [m].
    distance : float
        Camera distance from ``target`` [m].
    yaw, pitch : float
        Orbit angles [deg] (pybullet convention: pitch < 0 looks down).
    fov : float
        Vertical field of view [deg].
    near, far : float
        Clipping planes [m].
    eye : tuple of float or None
        Camera position [m]; if given, it replaces ``distance``, ``yaw`` and ``pitch`` (the
        camera looks from ``eye`` at ``target``, z up).
    """

    width: int = 640
    height: int = 480
    target: tuple = (0.3, 0.0, 0.4)
    distance: float = 1.8
    yaw: float = 50.0
    pitch: float = -30.0
    fov: float = 60.0
    near: float = 0.01
    far: float = 20.0
    eye: Optional[tuple] = None

    def __post_init__(self):
        for name in ('width', 'height'):
            v = getattr(self, name)
            if int(v) != v or not 8 <= v <= 4096:
                raise ValidationError(f'{name}: expected an integer in [8, 4096], got {v!r}')
        object.__setattr__(self, 'target', tuple(
            float(v) for v in as_array('target', self.target, (3,))))
        check_positive('distance', self.distance)
        if not 1.0 <= self.fov <= 170.0:
            raise ValidationError(f'fov: expected a value in [1, 170] deg, got {self.fov!r}')
        check_positive('near', self.near)
        if not self.far > self.near:
            raise ValidationError(f'far: expected > near ({self.near}), got {self.far!r}')
        if self.eye is not None:
            eye = as_array('eye', self.eye, (3,))
            if np.linalg.norm(eye - self.target) < 1e-6:
                raise ValidationError(f'eye: expected a point other than target, got {self.eye}')
            object.__setattr__(self, 'eye', tuple(float(v) for v in eye))


def render(world, config: CameraConfig = CameraConfig()) -> NDArray[np.uint8]:
    """Render the world; returns the RGB image ``(height, width, 3)`` uint8."""
    cid = world.client_id
    if config.eye is not None:
        view = pybullet.computeViewMatrix(list(config.eye), list(config.target), [0.0, 0.0, 1.0],
                                          physicsClientId=cid)
    else:
        view = pybullet.computeViewMatrixFromYawPitchRoll(
            list(config.target), config.distance, config.yaw, config.pitch, 0.0, 2,
            physicsClientId=cid)
    proj = pybullet.computeProjectionMatrixFOV(config.fov, config.width / config.height,
                                               config.near, config.far, physicsClientId=cid)
    _, _, rgba, _, _ = pybullet.getCameraImage(
        int(config.width), int(config.height), view, proj,
        renderer=pybullet.ER_TINY_RENDERER, physicsClientId=cid)
    img = np.reshape(np.asarray(rgba, dtype=np.uint8), (config.height, config.width, 4))
    return np.ascontiguousarray(img[..., :3])


def snapshot(world, path: str, config: CameraConfig = CameraConfig()) -> NDArray[np.uint8]:
    """Render the world and write it as a PNG file at ``path``; returns the RGB image."""
    import matplotlib.image
    img = render(world, config)
    directory = os.path.dirname(os.path.abspath(path))
    os.makedirs(directory, exist_ok=True)
    matplotlib.image.imsave(path, img, format='png')
    return img
