"""Motion vectors (pixels, current -> previous) for camera motion and rigid object motion.

A hit point ``p`` on mesh ``m`` at frame t was at ``M_{t-1}(m) M_t(m)^-1 p`` in frame t-1
(``M`` the rigid transform that animates the mesh, identity for static ones); projecting
that point with the previous camera gives where the pixel's surface point was. The
convention (docs/FORMATS.md): the pixel centre (x+0.5, y+0.5) was at
(x+0.5+mx, y+0.5+my) in the previous frame.
"""

from __future__ import annotations

import drjit as dr
import numpy as np

from ..backend import VariantStruct, mi


class MotionInputs:
    """Per-frame inputs of :func:`motion`: relative object transforms (16 floats per mesh
    index, row-major) and the previous camera (world->camera matrix, focal scale, centre)."""

    DRJIT_STRUCT = VariantStruct(lambda: {"rel": mi.Float, "prev": mi.Float})

    def __init__(self, prev_camera, objs: dict[int, np.ndarray], objs_prev: dict[int, np.ndarray],
                 n_meshes: int):
        rel = np.tile(np.eye(4), (n_meshes + 1, 1, 1))
        for m, cur in objs.items():
            rel[m] = objs_prev.get(m, np.eye(4)) @ np.linalg.inv(cur)
        w, h = prev_camera.resolution
        w2c = np.linalg.inv(np.asarray(prev_camera.to_world, dtype=np.float64))
        prev = np.concatenate([w2c.ravel(), [prev_camera.focal_px, w / 2, h / 2]])
        # from Python lists: NumPy-backed inputs can make dr.freeze re-record (alignment)
        self.rel = mi.Float(rel.astype(np.float32).ravel().tolist())
        self.prev = mi.Float(prev.astype(np.float32).tolist())


def _row_dot(arr: mi.Float, base, p: mi.Vector3f, row: int) -> mi.Float:
    g = [dr.gather(mi.Float, arr, base + 4 * row + c) for c in range(4)]
    return g[0] * p.x + g[1] * p.y + g[2] * p.z + g[3]


def motion(position: mi.Vector3f, mesh: mi.UInt32, valid: mi.Bool, pixel_xy: mi.Point2f,
           inputs: MotionInputs) -> mi.Vector2f:
    """Motion vector of each lane: previous pixel position minus current pixel centre."""
    base = mesh * 16
    p_prev = mi.Vector3f(*(_row_dot(inputs.rel, base, position, r) for r in range(3)))
    zero = mi.UInt32(0)
    cam = mi.Vector3f(*(_row_dot(inputs.prev, zero, p_prev, r) for r in range(3)))
    focal = dr.gather(mi.Float, inputs.prev, zero + 16)
    cx = dr.gather(mi.Float, inputs.prev, zero + 17)
    cy = dr.gather(mi.Float, inputs.prev, zero + 18)
    # Mitsuba's perspective camera: camera-space +x points left in the image, +y up
    inv_z = dr.rcp(cam.z)
    px = cx - focal * cam.x * inv_z
    py = cy - focal * cam.y * inv_z
    ok = valid & (cam.z > 0)
    return mi.Vector2f(dr.select(ok, px - pixel_xy.x, 0.0), dr.select(ok, py - pixel_xy.y, 0.0))
