"""The browser's camera and the pipeline's, both ways (issue 26).

viser reports a client's camera as a position, a look-at point, an up direction and a
*vertical* field of view in radians. glossrt's cameras are Mitsuba ``perspective`` sensors
with a *horizontal* field of view in degrees (``fov_axis = "x"``) and a ``to_world`` whose
columns are (left, up, forward, origin). For an image of ``W x H`` pixels both describe the
same pinhole when ``tan(fov_x / 2) = tan(fov_y / 2) * W / H`` (a pinhole's image plane at
distance 1 is ``2 tan(fov_x / 2)`` wide and ``2 tan(fov_y / 2)`` high, in the ratio of the
pixels, the pixels being square).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ViewerCamera:
    """A camera as viser states it: ``position``, ``look_at``, ``up`` (3-vectors, world
    space) and ``fov_y`` (vertical, radians)."""

    position: tuple[float, float, float]
    look_at: tuple[float, float, float]
    up: tuple[float, float, float]
    fov_y: float

    def close_to(self, other: ViewerCamera | None, tol: float = 1e-6) -> bool:
        """True when ``other`` is the same camera within ``tol`` (relative to the scale of
        the positions): an echo of a camera the viewer itself sent."""
        if other is None:
            return False

        def pose(c: ViewerCamera) -> tuple[np.ndarray, np.ndarray]:
            # what the rendered image depends on: position, view direction, up, fov (not how
            # far along the view axis the orbit point lies: clients move it)
            p = np.asarray(c.position, np.float64)
            d = np.asarray(c.look_at, np.float64) - p
            d /= max(float(np.linalg.norm(d)), 1e-300)
            u = np.asarray(c.up, np.float64)
            u /= max(float(np.linalg.norm(u)), 1e-300)
            return p, np.concatenate([d, u, [c.fov_y]])

        pa, ra = pose(self)
        pb, rb = pose(other)
        scale = max(1.0, float(np.abs(pa).max()))
        return bool(np.all(np.abs(pa - pb) <= tol * scale) and np.all(np.abs(ra - rb) <= tol))


def fov_x_degrees(fov_y: float, size: tuple[int, int]) -> float:
    """Horizontal field of view (degrees) of an image of ``size = (W, H)`` pixels whose
    vertical one is ``fov_y`` radians."""
    w, h = size
    return math.degrees(2.0 * math.atan(math.tan(0.5 * fov_y) * w / h))


def fov_y_radians(fov_x_deg: float, size: tuple[int, int]) -> float:
    """The inverse of :func:`fov_x_degrees`."""
    w, h = size
    return 2.0 * math.atan(math.tan(0.5 * math.radians(fov_x_deg)) * h / w)


def to_pipeline(cam: ViewerCamera, size: tuple[int, int]) -> dict:
    """Keyword arguments of :meth:`glossrt.pipeline.Pipeline.set_camera` for ``cam``
    (``position``, ``target``, ``up`` and the horizontal ``fov`` in degrees)."""
    return {"position": tuple(cam.position), "target": tuple(cam.look_at),
            "up": tuple(cam.up), "fov": fov_x_degrees(cam.fov_y, size)}


def from_pipeline(to_world, fov_x_deg: float, size: tuple[int, int],
                  pivot=None) -> ViewerCamera:
    """The viser camera of a Mitsuba ``to_world`` (4x4) and horizontal ``fov_x_deg``. The
    look-at point lies on the view axis at the distance of ``pivot`` (the point the camera
    orbits, projected onto the axis; 1 unit ahead when None or behind the camera)."""
    m = np.asarray(to_world, dtype=np.float64).reshape(4, 4)
    origin = m[:3, 3]
    up = m[:3, 1] / np.linalg.norm(m[:3, 1])
    forward = m[:3, 2] / np.linalg.norm(m[:3, 2])
    d = 1.0
    if pivot is not None:
        d = float(np.dot(np.asarray(pivot, np.float64) - origin, forward))
        if not math.isfinite(d) or d <= 1e-3:
            d = 1.0
    target = origin + d * forward
    return ViewerCamera(tuple(map(float, origin)), tuple(map(float, target)),
                        tuple(map(float, up)), fov_y_radians(fov_x_deg, size))


def quaternion_matrix(wxyz) -> np.ndarray:
    """3x3 rotation of a unit quaternion ``(w, x, y, z)`` (viser's convention)."""
    w, x, y, z = (float(v) for v in wxyz)
    n = math.sqrt(w * w + x * x + y * y + z * z)
    if n == 0.0:
        return np.eye(3)
    w, x, y, z = w / n, x / n, y / n, z / n
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def gizmo_matrix(position, wxyz, rest_centre) -> np.ndarray:
    """The rigid 4x4 that moves a light from its rest pose to a gizmo's pose: the gizmo
    starts at ``rest_centre`` unrotated; dragged to ``position`` and turned by ``wxyz`` it
    means ``T(position) R(wxyz) T(-rest_centre)`` (rotation about the light's centre)."""
    m = np.eye(4)
    r = quaternion_matrix(wxyz)
    c = np.asarray(rest_centre, np.float64)
    m[:3, :3] = r
    m[:3, 3] = np.asarray(position, np.float64) - r @ c
    return m
