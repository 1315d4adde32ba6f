"""Obstacles of a world: spheres and boxes (boards) added, moved and removed at run time.

Each obstacle is a static pybullet body, addressed by a unique name. A *colliding* obstacle is a
physical body the robot bumps into; a non-colliding one (``collide=False``) is a ghost that
only the distance and contact queries see (so a link may pass through it, as in the reaching
experiment of paper 000, IV-B, where the penetration depth is the reported figure).

Distances come from pybullet's closest-point query (``getClosestPoints``) between every link of
a robot and every obstacle: positive = separation, negative = penetration depth [m].
"""
from dataclasses import dataclass
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np
from numpy.typing import NDArray
import pybullet

from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.validation import as_array, check_positive, lookup


@dataclass(frozen=True)
class ObstacleInfo:
    """One obstacle: ``shape`` ``'sphere'`` (``size`` = (radius,)) or ``'box'`` (``size`` =
    half extents (3,)); pose in the world frame; pybullet ``body_id``."""

    name: str
    shape: str
    size: Tuple[float, ...]
    position: Tuple[float, float, float]
    orientation: Tuple[float, float, float, float]
    collide: bool
    body_id: int


@dataclass(frozen=True)
class LinkDistance:
    """Closest points between one robot link and one obstacle.

    ``distance`` [m] is negative when they overlap; ``normal`` (3,) is the unit vector from
    the obstacle towards the link (pybullet's contact normal on the obstacle).
    """

    link: str
    obstacle: str
    distance: float
    point_on_link: NDArray[np.float64]
    point_on_obstacle: NDArray[np.float64]
    normal: NDArray[np.float64]


@dataclass(frozen=True)
class DistanceReport:
    """Link-obstacle distances of one robot.

    Attributes
    ----------
    link_names : tuple of str
    obstacle_names : tuple of str
    distance : (n_links, n_obstacles) ndarray
        Minimum distance per pair [m]; ``inf`` where beyond the query's ``max_distance``.
    pairs : dict of (link, obstacle) to LinkDistance
        Closest points of every pair within ``max_distance``.
    """

    link_names: Tuple[str, ...]
    obstacle_names: Tuple[str, ...]
    distance: NDArray[np.float64]
    pairs: Dict[Tuple[str, str], LinkDistance]

    @property
    def minimum(self) -> Optional[LinkDistance]:
        """The closest pair overall (None without obstacles within range)."""
        if not self.pairs:
            return None
        return min(self.pairs.values(), key=lambda p: p.distance)


@dataclass(frozen=True)
class Contact:
    """A link touching or penetrating an obstacle: ``depth`` = -distance >= 0 [m];
    ``normal_force`` [N] from the last physics step (0 for non-colliding obstacles)."""

    link: str
    obstacle: str
    depth: float
    position: NDArray[np.float64]
    normal: NDArray[np.float64]
    normal_force: float


_DEFAULT_RGBA = (0.85, 0.25, 0.2, 0.6)


class Obstacles:
    """The obstacle set of a :class:`cdmp_ros.sim.world.World` (``world.obstacles``)."""

    def __init__(self, world):
        self._world = world
        self._items: Dict[str, ObstacleInfo] = {}

    # -- container ------------------------------------------------------------------------
    @property
    def names(self) -> Tuple[str, ...]:
        """Obstacle names in insertion order."""
        return tuple(self._items)

    def __len__(self) -> int:
        return len(self._items)

    def __contains__(self, name: str) -> bool:
        return name in self._items

    def get(self, name: str) -> ObstacleInfo:
        """The obstacle called ``name``."""
        return lookup('name', self._items, name)

    # -- add / move / remove --------------------------------------------------------------
    def add_sphere(self, name: str, position: Sequence[float], radius: float,
                   collide: bool = True, rgba: Sequence[float] = _DEFAULT_RGBA,
                   replace: bool = False) -> ObstacleInfo:
        """Add a sphere of ``radius`` [m] centred at ``position`` (3,) [m]."""
        r = check_positive('radius', radius)
        cid = self._world.client_id
        col = pybullet.createCollisionShape(pybullet.GEOM_SPHERE, radius=r, physicsClientId=cid)
        vis = pybullet.createVisualShape(pybullet.GEOM_SPHERE, radius=r, rgbaColor=list(rgba),
                                         physicsClientId=cid)
        return self._add(name, 'sphere', (r,), col, vis, position, (0.0, 0.0, 0.0, 1.0),
                         collide, replace)

    def add_box(self, name: str, position: Sequence[float], half_extents: Sequence[float],
                orientation: Sequence[float] = (0.0, 0.0, 0.0, 1.0), collide: bool = True,
                rgba: Sequence[float] = _DEFAULT_RGBA, replace: bool = False) -> ObstacleInfo:
        """Add a box (e.g. a board) with ``half_extents`` (3,) [m] at ``position`` (3,),
        ``orientation`` a quaternion (x, y, z, w)."""
        he = as_array('half_extents', half_extents, (3,))
        if np.any(he <= 0):
            raise ValidationError(f'half_extents: expected positive values, got {he.tolist()}')
        cid = self._world.client_id
        col = pybullet.createCollisionShape(pybullet.GEOM_BOX, halfExtents=he.tolist(),
                                            physicsClientId=cid)
        vis = pybullet.createVisualShape(pybullet.GEOM_BOX, halfExtents=he.tolist(),
                                         rgbaColor=list(rgba), physicsClientId=cid)
        return self._add(name, 'box', tuple(float(v) for v in he), col, vis, position,
                         orientation, collide, replace)

    def _add(self, name, shape, size, col, vis, position, orientation, collide, replace):
        name = str(name)
        if name in self._items:
            if not replace:
                raise ValidationError(f'name: expected a new obstacle name, got {name!r} '
                                      '(pass replace=True to replace it)')
            self.remove(name)
        pos, orn = self._pose(position, orientation)
        cid = self._world.client_id
        body = pybullet.createMultiBody(baseMass=0.0, baseCollisionShapeIndex=col,
                                        baseVisualShapeIndex=vis, basePosition=pos,
                                        baseOrientation=orn, physicsClientId=cid)
        if not collide:  # ghost: invisible to the physics, still seen by getClosestPoints
            pybullet.setCollisionFilterGroupMask(body, -1, 0, 0, physicsClientId=cid)
        info = ObstacleInfo(name, shape, size, tuple(pos), tuple(orn), bool(collide), body)
        self._items[name] = info
        return info

    @staticmethod
    def _pose(position, orientation):
        pos = as_array('position', position, (3,))
        orn = as_array('orientation', orientation, (4,))
        norm = float(np.linalg.norm(orn))
        if not norm > 0:
            raise ValidationError(f'orientation: expected a non-zero quaternion, got {orn}')
        return [float(v) for v in pos], [float(v) for v in orn / norm]

    def move(self, name: str, position: Sequence[float],
             orientation: Optional[Sequence[float]] = None) -> ObstacleInfo:
        """Move an obstacle to ``position`` (and ``orientation`` if given)."""
        info = self.get(name)
        pos, orn = self._pose(position, info.orientation if orientation is None
                              else orientation)
        pybullet.resetBasePositionAndOrientation(info.body_id, pos, orn,
                                                 physicsClientId=self._world.client_id)
        info = ObstacleInfo(info.name, info.shape, info.size, tuple(pos), tuple(orn),
                            info.collide, info.body_id)
        self._items[name] = info
        return info

    def remove(self, name: str) -> None:
        """Remove an obstacle."""
        info = self.get(name)
        pybullet.removeBody(info.body_id, physicsClientId=self._world.client_id)
        del self._items[name]

    def clear(self) -> None:
        """Remove every obstacle."""
        for name in list(self._items):
            self.remove(name)

    # -- queries --------------------------------------------------------------------------
    def distances(self, robot, max_distance: float = 1.0,
                  obstacles: Optional[Sequence[str]] = None) -> DistanceReport:
        """Minimum distance between every link of ``robot`` and every obstacle.

        Parameters
        ----------
        robot : Robot
        max_distance : float
            Pairs farther apart than this [m] are not computed (reported as ``inf``).
        obstacles : sequence of str, optional
            Restrict the query to these obstacles (default all).
        """
        check_positive('max_distance', max_distance, allow_zero=True)
        names = self.names if obstacles is None else tuple(obstacles)
        infos = [self.get(n) for n in names]
        cid = self._world.client_id
        links = robot.link_names
        dist = np.full((len(links), len(infos)), np.inf)
        pairs: Dict[Tuple[str, str], LinkDistance] = {}
        for k, info in enumerate(infos):
            points = pybullet.getClosestPoints(robot.body_id, info.body_id, float(max_distance),
                                               physicsClientId=cid)
            for pt in points:
                i = pt[3] + 1  # link index -1 (base) -> row 0
                d = pt[8]
                if d < dist[i, k]:
                    dist[i, k] = d
                    pairs[(links[i], info.name)] = LinkDistance(
                        links[i], info.name, float(d), np.array(pt[5]), np.array(pt[6]),
                        np.array(pt[7]))
        return DistanceReport(links, names, dist, pairs)

    def min_distance(self, robot, max_distance: float = 1.0) -> float:
        """Smallest link-obstacle distance of ``robot`` [m] (``inf`` if none within range)."""
        best = self.distances(robot, max_distance).minimum
        return np.inf if best is None else best.distance

    def contacts(self, robot, threshold: float = 0.0) -> List[Contact]:
        """Links touching or penetrating an obstacle (distance <= ``threshold`` [m]).

        Geometric (closest points), so ghost obstacles report penetrations too;
        ``normal_force`` sums the contact forces of the last step for colliding ones.
        """
        report = self.distances(robot, max(threshold, 0.0))
        cid = self._world.client_id
        out = []
        for (link, obstacle), p in report.pairs.items():
            if p.distance > threshold:
                continue
            info = self._items[obstacle]
            force = 0.0
            if info.collide:
                force = sum(c[9] for c in pybullet.getContactPoints(
                    robot.body_id, info.body_id, robot.link_index(link), -1,
                    physicsClientId=cid))
            out.append(Contact(link, obstacle, float(-p.distance), p.point_on_link,
                               p.normal, float(force)))
        return sorted(out, key=lambda c: -c.depth)
