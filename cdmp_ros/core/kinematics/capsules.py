"""Capsules that enclose a link's collision geometry, read from the URDF (no pybullet, no ROS).

The obstacle coupling models a link as a capsule (a segment and a radius, distances to its
surface). Segments between consecutive joint origins with one radius for every link
(:meth:`~cdmp_ros.core.kinematics.chain.Chain.link_segments`) miss much of a real arm: the
Panda's forearm (``panda_link5``) runs up to 8 cm beside the elbow-wrist axis, and its hand is
21 cm wide. :func:`collision_capsules` fits one capsule to every ``<collision>`` element of a
link instead, in that link's frame, so that the capsule **encloses** the geometry: a distance
to the capsule is a lower bound of the distance to the link's collision shape (the one the
simulator and a real collision checker use).

Geometry read from ``<collision>``: ``<mesh filename scale>`` (Wavefront ``.obj`` vertices;
other formats are refused), ``<box size>``, ``<cylinder radius length>``, ``<sphere
radius>`` and ``<capsule radius length>`` (pybullet's extension: ``length`` between the centres
of its end caps), each placed by its ``<origin xyz rpy>``. A mesh's ``package://`` or relative
``filename`` is looked up under each of ``mesh_dirs`` in turn (default: the URDF's directory),
with and without its first path component (the package name: a ``share`` directory of an
install prefix resolves ``package://<package>/<path>`` as ROS does).

Fit (:func:`fit_capsule`): the geometry becomes balls (points with a radius: mesh and box
vertices with radius 0, sphere centres, cylinder rims sampled with the chord's sag as radius,
a capsule's two end centres with its radius).
For each candidate axis (the principal axis of the points and the three axes of the link
frame, then refined by Nelder-Mead on the volume) and radius ``R`` (a grid from the smallest
possible), the shortest segment whose capsule contains every ball is closed form: a ball at
axial coordinate ``t_i``, radial distance ``r_i`` and radius ``rho_i`` lies inside iff
``t_0 <= t_i + sqrt((R - rho_i)^2 - r_i^2)`` and ``t_1 >= t_i - sqrt((R - rho_i)^2 - r_i^2)``.
The capsule of least volume found wins (a local search: small, not proven minimal; what is
guaranteed is the enclosure). A capsule is convex, so enclosing a mesh's vertices encloses
the mesh.
"""
import hashlib
import json
import os
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from typing import List, Optional, Sequence, Tuple

import numpy as np
from numpy.typing import NDArray

from cdmp_ros.core import cache
from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.kinematics.chain import PointOfInterest
from cdmp_ros.core.kinematics.closest import segment_sphere
from cdmp_ros.core.kinematics.urdf import rpy_to_matrix

Vec3 = Tuple[float, float, float]
#: Points of a cylinder's rim per cap.
RIM_POINTS = 32
#: Radii tried per axis, from the least enclosing one to twice it.
RADIUS_STEPS = 120
#: Largest mesh file read [bytes]: a URDF is input, its cost is bounded before parsing.
MAX_MESH_BYTES = 50_000_000


#: Decimals [m] of the fitted capsules' ends (:func:`collision_capsules`), and the largest
#: distance that rounding moves a point of the axis.
ENDS_DECIMALS = 9
ENDS_ROUNDING = 1e-9

with open(__file__, 'rb') as _f:  # a fitted capsule is cached under this source's hash too
    _SOURCE_HASH = hashlib.sha256(_f.read()).digest()


@dataclass(frozen=True)
class Capsule:
    """A segment ``start``-``end`` in the frame of ``link`` and a ``radius`` [m]."""

    link: str
    start: Vec3
    end: Vec3
    radius: float

    def distance(self, points: NDArray) -> NDArray:
        """Distance [m] of ``points`` (..., 3), in the link frame, to the capsule's surface
        (negative inside)."""
        return segment_sphere(self.start, self.end, points, 0.0, self.radius)[1]

    def covering_balls(self) -> List[Tuple[Vec3, float]]:
        """Balls ``(centre, radius)`` in the link frame whose union contains the capsule:
        centres at ``k + 1`` evenly spaced points of the segment, both ends included, with
        ``k = ceil(L / (2 r))`` for a segment of length ``L``, each of radius
        ``sqrt(r^2 + (L / 2k)^2)`` (at most ``sqrt(2) r``).

        A point of the capsule lies within ``r`` of a point ``s`` of the segment: a point of an
        end cap within ``r`` of an end, which is a centre; a point of the cylinder at ``r`` or
        less across the axis from ``s``, which is at most ``L / 2k`` along the axis from the
        nearest centre. A ball therefore stands for the link wherever the link must keep clear:
        the adapter's obstacle constraints (:mod:`cdmp_ros.core.adaptation.requests`)."""
        a, b, r = np.asarray(self.start), np.asarray(self.end), float(self.radius)
        if not r > 0.0:
            raise ValidationError(f'capsule of {self.link!r}: balls cannot cover a radius of '
                                  f'{r!r}')
        length = float(np.linalg.norm(b - a))
        k = int(np.ceil(length / (2.0 * r)))
        if k == 0:
            return [(tuple(float(v) for v in a), r)]
        radius = float(np.hypot(r, length / (2.0 * k)))
        return [(tuple(float(v) for v in a + (b - a) * (i / k)), radius) for i in range(k + 1)]


def _enclose(X, rho, axis, c):
    """(volume, start, end, radius) of the least-volume capsule on the line ``c + t axis``
    (over the radius grid) that encloses the balls."""
    t = (X - c) @ axis
    r = np.linalg.norm(X - c - np.outer(t, axis), axis=1)
    r_min = float((r + rho).max())
    R = np.linspace(r_min, 2.0 * r_min + 1e-9, RADIUS_STEPS)[:, None]  # (K, 1)
    h = np.sqrt(np.maximum((R - rho) ** 2 - r * r, 0.0))             # (K, N)
    t1 = (t - h).max(axis=1)
    t0 = np.minimum((t + h).min(axis=1), t1)  # ball-shaped: any t in [t1, t0] encloses
    R = R[:, 0]
    volume = np.pi * R * R * (t1 - t0) + 4.0 / 3.0 * np.pi * R ** 3
    k = int(np.argmin(volume))
    return float(volume[k]), c + t0[k] * axis, c + t1[k] * axis, float(R[k])


def fit_capsule(centres: NDArray, radii: Optional[NDArray] = None
                ) -> Tuple[NDArray, NDArray, float]:
    """The least-volume capsule (over the candidate axes and radii of the module docstring)
    enclosing the balls ``centres`` (N, 3) with ``radii`` (N,) (default 0): ``(start, end,
    radius)``."""
    X = np.asarray(centres, dtype=np.float64)
    if X.ndim != 2 or X.shape[1] != 3 or len(X) == 0 or not np.isfinite(X).all():
        raise ValidationError(f'centres: expected finite points (N, 3), N >= 1, got shape '
                              f'{X.shape}')
    rho = np.zeros(len(X)) if radii is None else np.asarray(radii, dtype=np.float64)
    if rho.shape != (len(X),) or not np.isfinite(rho).all() or (rho < 0).any():
        raise ValidationError(f'radii: expected {len(X)} finite values >= 0')
    from scipy.optimize import minimize           # only here: not in every importer's start
    from scipy.spatial import ConvexHull, QhullError
    if len(X) > 4 and np.ptp(rho) == 0.0:
        # equal radii: only the convex hull's vertices can touch the surface
        try:
            X = X[ConvexHull(X).vertices]
            rho = rho[:len(X)]
        except QhullError:  # flat or degenerate: keep every point
            pass
    c0 = X.mean(axis=0)
    candidates = [np.eye(3)[k] for k in range(3)]
    if len(X) > 1:
        candidates.insert(0, np.linalg.svd(X - c0, full_matrices=False)[2][0])
    best = min((_enclose(X, rho, axis, c0) for axis in candidates), key=lambda b: b[0])
    if len(X) > 1:
        # refine the axis direction and where it passes (Nelder-Mead on the volume)
        axis0 = (best[2] - best[1]) / max(np.linalg.norm(best[2] - best[1]), 1e-12) \
            if np.linalg.norm(best[2] - best[1]) > 1e-9 else candidates[0]
        e1 = np.cross(axis0, [1.0, 0.0, 0.0] if abs(axis0[0]) < 0.9 else [0.0, 1.0, 0.0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(axis0, e1)
        scale = float(np.ptp(X, axis=0).max()) or 1.0

        def volume(z):
            axis = axis0 + z[0] * e1 + z[1] * e2
            return _enclose(X, rho, axis / np.linalg.norm(axis),
                            c0 + scale * (z[2] * e1 + z[3] * e2))[0]

        res = minimize(volume, np.zeros(4), method='Nelder-Mead',
                       options={'xatol': 1e-4, 'fatol': 1e-12, 'maxiter': 400})
        if res.fun < best[0]:
            z = res.x
            axis = axis0 + z[0] * e1 + z[1] * e2
            best = _enclose(X, rho, axis / np.linalg.norm(axis),
                            c0 + scale * (z[2] * e1 + z[3] * e2))
    return best[1], best[2], best[3]


def _mesh_file(filename: str, mesh_dirs: Sequence[str], where: str) -> str:
    if filename.startswith('file://'):
        candidates = [filename[len('file://'):]]
    else:
        rel = filename[len('package://'):] if filename.startswith('package://') else filename
        names = [rel] + ([rel.split('/', 1)[1]] if '/' in rel else [])
        candidates = [rel] if os.path.isabs(rel) else [os.path.join(d, n) for d in mesh_dirs
                                                       for n in names]
    for path in candidates:
        if os.path.isfile(path):
            return path
    raise ValidationError(f'{where}: mesh {filename!r} not found (looked for '
                          f'{", ".join(repr(p) for p in candidates)})')


def _obj_vertices(path: str, where: str) -> NDArray:
    if not path.lower().endswith('.obj'):
        raise ValidationError(f'{where}: mesh {path!r}: only Wavefront .obj meshes are read '
                              f'for collision capsules')
    try:
        size = os.path.getsize(path)
    except OSError as exc:
        raise ValidationError(f'{where}: cannot read mesh {path!r} ({exc})') from None
    if size > MAX_MESH_BYTES:
        raise ValidationError(f'{where}: mesh {path!r} is larger than {MAX_MESH_BYTES} bytes')
    vertices = []
    try:
        with open(path, encoding='utf-8', errors='replace') as f:
            for n, line in enumerate(f, 1):
                if line.startswith('v '):
                    try:
                        v = [float(x) for x in line.split()[1:4]]
                    except ValueError:
                        v = []
                    if len(v) != 3:
                        raise ValidationError(f'{where}: mesh {path!r} line {n}: bad vertex '
                                              f'{line.strip()[:80]!r}')
                    vertices.append(v)
    except OSError as exc:
        raise ValidationError(f'{where}: cannot read mesh {path!r} ({exc})') from None
    V = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    if V.shape[0] == 0 or V.shape[1:] != (3,) or not np.isfinite(V).all():
        raise ValidationError(f'{where}: mesh {path!r} has no usable vertices')
    return V


def _floats(el, attr: str, n: int, default, where: str) -> NDArray:
    """Attribute ``attr`` of ``el`` as ``n`` finite numbers; ``default`` None: required."""
    text = el.get(attr) if el is not None else None
    if text is None:
        if default is None:
            raise ValidationError(f'{where}: <{el.tag}> needs {attr}')
        return np.asarray(default, dtype=np.float64)
    try:
        v = np.asarray([float(x) for x in text.split()], dtype=np.float64)
    except ValueError:
        v = np.zeros(0)
    if v.shape != (n,) or not np.isfinite(v).all():
        raise ValidationError(f'{where}: {attr}: expected {n} numbers, got {text!r}')
    return v


def collision_balls(link_el, mesh_dirs, where: str) -> Tuple[NDArray, NDArray]:
    """The collision geometry of a ``<link>`` element as balls (centres (N, 3) in the link
    frame, radii (N,)): see the module docstring. ``mesh_dirs``: a directory or a sequence
    of them, where mesh files are looked up in turn."""
    mesh_dirs = [mesh_dirs] if isinstance(mesh_dirs, str) else list(mesh_dirs)
    centres, radii = [], []
    for k, col in enumerate(link_el.findall('collision')):
        at = f'{where} <collision> {k}'
        origin = col.find('origin')
        R = rpy_to_matrix(_floats(origin, 'rpy', 3, (0.0, 0.0, 0.0), at))
        p = _floats(origin, 'xyz', 3, (0.0, 0.0, 0.0), at)
        geom = col.find('geometry')
        shape = None if geom is None or len(geom) == 0 else geom[0]
        if shape is None:
            raise ValidationError(f'{at}: no <geometry>')
        if shape.tag == 'mesh':
            V = _obj_vertices(_mesh_file(shape.get('filename', ''), mesh_dirs, at), at)
            V = V * _floats(shape, 'scale', 3, (1.0, 1.0, 1.0), at)
            rho = np.zeros(len(V))
        elif shape.tag == 'box':
            half = 0.5 * _floats(shape, 'size', 3, None, at)
            V = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1)
                          for sz in (-1, 1)]) * half
            rho = np.zeros(8)
        elif shape.tag in ('sphere', 'cylinder', 'capsule'):
            r = _floats(shape, 'radius', 1, None, at)
            if r[0] < 0:
                raise ValidationError(f'{at}: <{shape.tag}> radius: expected >= 0, got {r[0]}')
            if shape.tag == 'sphere':
                V, rho = np.zeros((1, 3)), r.copy()
            elif shape.tag == 'capsule':  # the balls at the ends of its axis: exact
                half = 0.5 * _floats(shape, 'length', 1, None, at)[0]
                V, rho = np.array([[0.0, 0.0, -half], [0.0, 0.0, half]]), np.repeat(r, 2)
            else:
                half = 0.5 * _floats(shape, 'length', 1, None, at)[0]
                a = np.linspace(0.0, 2.0 * np.pi, RIM_POINTS, endpoint=False)
                rim = np.stack([r[0] * np.cos(a), r[0] * np.sin(a), np.zeros_like(a)], 1)
                V = np.vstack([rim + [0.0, 0.0, -half], rim + [0.0, 0.0, half]])
                rho = np.full(len(V), r[0] * (1.0 - np.cos(np.pi / RIM_POINTS)))
        else:
            raise ValidationError(f'{at}: unsupported geometry <{shape.tag}>')
        centres.append(V @ R.T + p)
        radii.append(rho)
    if not centres:
        raise ValidationError(f'{where}: no <collision> geometry')
    return np.vstack(centres), np.concatenate(radii)


def collision_capsules(path: str, links: Sequence[str], urdf_text: Optional[str] = None,
                       mesh_dirs: Optional[Sequence[str]] = None) -> List[Capsule]:
    """One enclosing capsule per link of ``links``, fitted to its URDF ``<collision>``
    geometry (module docstring), in the link's frame.

    Parameters
    ----------
    path : str
        The URDF file (read unless ``urdf_text`` is given; names it in messages).
    links : sequence of str
    urdf_text : str, optional
        The URDF XML itself (a ``robot_description``).
    mesh_dirs : sequence of str, optional
        Where mesh file names are looked up, in turn; default the directory of ``path``.

    Raises
    ------
    ValidationError
        Naming the link and what is wrong: unknown link, no collision geometry, a mesh not
        found or not ``.obj``, bad numbers.
    """
    if urdf_text is None:
        try:
            with open(path, encoding='utf-8') as f:
                urdf_text = f.read()
        except OSError as exc:
            raise ValidationError(f'urdf path: cannot read {path!r} ({exc})') from None
    try:
        root = ET.fromstring(urdf_text)
    except ET.ParseError as exc:
        raise ValidationError(f'{path}: malformed XML ({exc})') from None
    by_name = {el.get('name'): el for el in root.findall('link')}
    if mesh_dirs is None:
        mesh_dirs = [os.path.dirname(os.path.abspath(path))]
    out = []
    for i, link in enumerate(links):
        if link in links[:i]:
            raise ValidationError(f'links[{i}]: {link!r} is listed twice')
        if link not in by_name:
            raise ValidationError(f'links[{i}]: no link {link!r} in {path!r}')
        centres, radii = collision_balls(by_name[link], mesh_dirs, f'link {link!r}')
        out.append(Capsule(link, *link_capsule(centres, radii)))
    return out


def link_capsule(centres: NDArray, radii: NDArray) -> Tuple[Vec3, Vec3, float]:
    """``(start, end, radius)`` of the capsule :func:`collision_capsules` gives a link with
    these balls: :func:`fit_capsule`, its ends rounded to ENDS_DECIMALS (the fit's last bits
    follow the CPU's BLAS kernels, the generated coupling kernels, their source and its hash,
    must not), its radius grown by the rounding so that it still encloses the balls.

    A fit costs 0.1-0.3 s and its import of scipy.optimize 0.7 s, at every streamer start: the
    result is kept in the capsule cache (:mod:`cdmp_ros.core.cache`, kind ``capsules``), under
    the SHA-256 of the balls, of this module's source and of the numpy and scipy versions, and
    a capsule read back is used only if it encloses every ball (:func:`encloses`) and is of
    the balls' size (:func:`_plausible`); else it is fitted again."""
    X = np.ascontiguousarray(centres, dtype=np.float64)
    rho = np.ascontiguousarray(radii, dtype=np.float64)
    key = hashlib.sha256(_SOURCE_HASH + repr((X.shape, rho.shape, np.__version__,
                                              _scipy_version())).encode()
                         + X.tobytes() + rho.tobytes()).hexdigest()[:32]
    filename = f'capsule_{key}.json'
    dirs = cache.locations('capsules')
    text = cache.read(filename, dirs, max_bytes=1000)
    if text is not None:
        try:
            d = json.loads(text)
            a, b = tuple(map(float, d['start'])), tuple(map(float, d['end']))
            r = float(d['radius'])
            if (len(a) == 3 and len(b) == 3 and encloses(a, b, r, X, rho)
                    and _plausible(a, b, r, X, rho)):
                return a, b, r
        except (ValueError, KeyError, TypeError, OverflowError):
            pass
    a, b, r = fit_capsule(X, rho)
    a, b = (tuple(round(float(v), ENDS_DECIMALS) for v in e) for e in (a, b))
    r = float(r) + ENDS_ROUNDING
    cache.store(filename, json.dumps({'start': a, 'end': b, 'radius': r}), dirs)
    return a, b, r


def _scipy_version() -> str:
    from importlib.metadata import version  # not scipy itself: its import is what is saved
    return version('scipy')


def _plausible(start, end, radius: float, centres: NDArray, radii: NDArray) -> bool:
    """Whether a capsule is of the size a fit of these balls can have: a least-volume fit has
    a radius below 2.3 times the balls' extent ``e`` (the diagonal of their box plus twice the
    largest ball radius: a candidate of the fit has radius <= 2 e and length <= e, and the fit
    is no larger than its candidates), and its ends lie within 3 e + radius of the box."""
    e = float(np.linalg.norm(np.ptp(centres, axis=0)) + 2.0 * np.max(radii, initial=0.0))
    lo, hi = centres.min(axis=0), centres.max(axis=0)
    reach = 3.0 * e + radius
    ends = np.array([start, end])
    return bool(0.0 < radius <= 2.3 * e + 1e-9 and np.all(ends >= lo - reach)
                and np.all(ends <= hi + reach))


def encloses(start: Sequence[float], end: Sequence[float], radius: float, centres: NDArray,
             radii: NDArray) -> bool:
    """Whether the capsule (``start``, ``end``, ``radius``) contains every ball (``centres``
    (N, 3), ``radii`` (N,)); False for non-finite numbers."""
    if not (np.all(np.isfinite(start)) and np.all(np.isfinite(end)) and np.isfinite(radius)):
        return False
    return bool(np.all(Capsule('', tuple(start), tuple(end), float(radius)).distance(centres)
                       + radii <= 0.0))


class ArmCapsules:
    """Capsules fixed to the links of a chain, and how far a sphere is from them.

    ``tool``: an extra capsule of that radius [m] around the chain's last link segment (for the
    Panda: panda_link7's flange to the fingertips, which holds the fingers; they are not links of
    the chain). The demo driver places its dropped sphere and the kinematic-limits storm its
    spheres with :meth:`sphere_clearance`.
    """

    def __init__(self, chain, capsules: Sequence[Capsule], tool_radius: Optional[float] = None):
        caps = list(capsules)
        if tool_radius is not None:
            link, start, end = chain.link_segments()[-1]
            caps.append(Capsule(link, tuple(start), tuple(end), float(tool_radius)))
        self.chain = chain
        self.capsules = tuple(caps)
        self._ends = [PointOfInterest(c.link, c.start) for c in caps] + \
            [PointOfInterest(c.link, c.end) for c in caps]
        self.radii = np.array([c.radius for c in caps])

    @classmethod
    def from_urdf(cls, chain, path: str, links: Sequence[str],
                  tool_radius: Optional[float] = None) -> 'ArmCapsules':
        """:func:`collision_capsules` of ``links`` in the URDF ``path``, plus the tool's."""
        return cls(chain, collision_capsules(path, links), tool_radius)

    def sphere_clearance(self, q: NDArray, center, radius: float) -> float:
        """Least distance [m] between a sphere and the capsules at joint positions ``q``
        (negative: they overlap)."""
        n = len(self.radii)
        ends = self.chain.forward(np.asarray(q, dtype=np.float64), self._ends)
        _, d, _, _ = segment_sphere(ends[:n], ends[n:], center, radius, self.radii)
        return float(d.min())
