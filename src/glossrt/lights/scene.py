"""The polygon lights of a scene: every Mitsuba ``area`` emitter on a ``rectangle`` or on a
small planar convex mesh, as world-space polygons at a given frame.

Conventions (checked against Mitsuba 3.9 by ``tests/test_polygon_light_scene.py``):

* Mitsuba's ``rectangle`` is the square [-1, 1]^2 in the plane z = 0 of its ``to_world``
  with normal +z (``flip_normals`` turns it to -z); a mesh's normal is its vertex normals'
  (or, without them, its faces' counter-clockwise winding).
* An ``area`` emitter emits on the side its shape's normal points to, and only there:
  seen from behind it is black, whatever the BSDF (a ``twosided`` BSDF does not make the
  emission two-sided; Mitsuba has no two-sided area emitter). So every light here has
  ``two_sided=False``, and its vertices run counter-clockwise seen from the emitting side:
  ``cross(v1 - v0, v2 - v0)`` points to where the light goes.
* A rectangle's texture coordinates are ``uv = ((x + 1) / 2, (y + 1) / 2)`` of its local
  point (x, y); a bitmap radiance texture is looked up at ``to_uv @ (u, v, 1)`` with ``u``
  across the image's width (columns, left to right) and ``v`` down its rows (row 0 at
  v = 0), the convention of ``mi.Texture2f.eval`` -- so ``PolygonLight.texture`` is the
  bitmap's array as stored and ``PolygonLight.uv`` the (transformed) corners' coordinates.
  Bilinear lookups with clamping reproduce Mitsuba's bitmap exactly when the bitmap is
  loaded with ``filter_type="bilinear"`` (the default) and ``wrap_mode="clamp"``; with
  Mitsuba's default ``wrap_mode="repeat"`` they differ within half a texel of the border.

Other emitters (``constant``, ``envmap``, ``point``, ``spot``, ...) are not polygon lights and
are left out; an area emitter on any other shape (sphere, disk, a non-planar or non-convex
mesh, a planar convex mesh whose outline has more than 8 corners) raises
:class:`GlossrtError` naming the shape and the reason (the pipeline path-traces such lights
instead: :mod:`glossrt.pipeline.plan`).
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import numpy as np

from ..backend import mi
from ..errors import GlossrtError
from ..scenes import _registry_id, render_shapes, stable_emitters, to_matrix

#: most corners a polygon light may have (what the LTC / MC shaders take)
MAX_VERTICES = 8
#: relative tolerances: distance of a mesh vertex from the light's plane, and mismatch
#: between a mesh's area and its convex outline's, as fractions of the light's size / area
PLANE_TOL = 1e-5
AREA_TOL = 1e-4
#: a mesh light whose vertices spread across their line by less than this fraction of their
#: spread along it is collinear (zero area; Mitsuba stores vertices in float32, ~6e-8)
COLLINEAR_TOL = 1e-6

#: rectangle corners in its local frame, counter-clockwise about +z, and their uv
_RECT_LOCAL = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])
_RECT_UV = (_RECT_LOCAL + 1.0) / 2.0


@dataclass
class PolygonLight:
    """A one-sided planar polygon light in world space.

    ``vertices`` (K, 3) float64, 3 <= K <= 8, convex, counter-clockwise seen from the
    emitting side; ``radiance`` (3,) linear RGB, the emitted radiance (multiplied by the
    texture where there is one: 1 for bitmap-textured Mitsuba lights); ``two_sided``
    whether the back emits too (never, for Mitsuba area emitters); ``texture`` (H, W, 3)
    float32 or None and ``uv`` (K, 2) float64 its coordinates at the vertices (see the
    module's conventions; affine over the polygon); ``id`` the shape's id (or the
    emitter's), ``mesh_id`` the shape's 1-based index in the G-buffer's ``mesh_id``
    channel (0 when unknown), ``shape`` the Mitsuba plugin (``rectangle`` or ``mesh``)."""

    vertices: np.ndarray
    radiance: np.ndarray
    two_sided: bool = False
    texture: np.ndarray | None = None
    uv: np.ndarray | None = None
    id: str = ""
    mesh_id: int = 0
    shape: str = ""

    def __post_init__(self):
        self.vertices = np.asarray(self.vertices, dtype=np.float64)
        self.radiance = np.broadcast_to(np.asarray(self.radiance, dtype=np.float64).ravel(),
                                        (3,)).copy()
        if self.vertices.ndim != 2 or self.vertices.shape[1] != 3 or not (
                3 <= len(self.vertices) <= MAX_VERTICES):
            raise GlossrtError(f"polygon light {self.id!r} needs 3 to {MAX_VERTICES} vertices "
                               f"(K, 3), got shape {self.vertices.shape}")
        if self.texture is not None:
            tex = np.asarray(self.texture, dtype=np.float32)
            if tex.ndim == 2:
                tex = tex[..., None]
            if tex.shape[-1] == 1:
                tex = np.repeat(tex, 3, axis=-1)
            self.texture = np.ascontiguousarray(tex[..., :3])
            if self.uv is None:
                raise GlossrtError(f"polygon light {self.id!r}: a texture needs uv per vertex")
            self.uv = np.asarray(self.uv, dtype=np.float64).reshape(len(self.vertices), 2)

    @property
    def normal(self) -> np.ndarray:
        """Unit normal of the emitting side (Newell's method over the vertices)."""
        return _newell(self.vertices) / np.linalg.norm(_newell(self.vertices))

    @property
    def area(self) -> float:
        return 0.5 * float(np.linalg.norm(_newell(self.vertices)))

    @property
    def centroid(self) -> np.ndarray:
        """Area centroid of the polygon."""
        v = self.vertices
        tri_c = (v[0] + v[1:-1] + v[2:]) / 3.0
        tri_a = np.linalg.norm(np.cross(v[1:-1] - v[0], v[2:] - v[0]), axis=1)
        return (tri_c * tri_a[:, None]).sum(0) / tri_a.sum()


def _newell(v: np.ndarray) -> np.ndarray:
    """Twice the vector area of a closed polygon (points to where it winds
    counter-clockwise)."""
    return np.cross(v, np.roll(v, -1, axis=0)).sum(axis=0)


def _shape_name(shape) -> str:
    return shape.id() or f"<unnamed {shape.class_name()}>"


def _emitting_normals(shape, count: int = 1) -> np.ndarray:
    """(count, 3) normals of the emitting side at points Mitsuba samples on the shape."""
    u = (np.arange(count) + 0.5) / count
    sample = mi.Point2f(mi.Float(u), mi.Float(np.mod(u * 7.31, 1.0)))
    ps = shape.sample_position(0.0, sample)
    return np.array(ps.n, dtype=np.float64).reshape(3, -1).T


def _rectangle_polygon(shape) -> tuple[np.ndarray, np.ndarray]:
    m = to_matrix(mi.traverse(shape)["to_world"])
    local = np.c_[_RECT_LOCAL, np.zeros(4), np.ones(4)]
    verts = (local @ m.T)[:, :3]
    return verts, _RECT_UV.copy()


def _mesh_polygon(shape, textured: bool,
                  what: str = "") -> tuple[np.ndarray, np.ndarray | None]:
    """Convex outline of a planar triangle mesh (world space, Mitsuba stores it so), with
    the texture coordinates of its corners when ``textured``."""
    from scipy.spatial import ConvexHull, QhullError

    name = _shape_name(shape)
    params = mi.traverse(shape)
    pos = np.array(params["vertex_positions"], dtype=np.float64).reshape(-1, 3)
    faces = np.array(params["faces"], dtype=np.int64).reshape(-1, 3)
    used = np.unique(faces)
    pts = pos[used]
    _check_finite_vertices(what or f"mesh {name!r}", pts)
    size = float(np.linalg.norm(pts.max(0) - pts.min(0)))
    if not size > 0.0:
        raise GlossrtError(f"area light on mesh {name!r}: the mesh has no extent")
    centre = pts.mean(0)
    _, sing, vt = np.linalg.svd(pts - centre, full_matrices=False)
    if len(sing) < 2 or not sing[1] > COLLINEAR_TOL * sing[0]:
        raise GlossrtError(
            f"area light on mesh {name!r} has zero area: its {len(pts)} vertices are "
            "collinear (they lie on one line)")
    plane_n = vt[2]
    off = float(np.max(np.abs((pts - centre) @ plane_n)))
    if off > PLANE_TOL * size:
        raise GlossrtError(
            f"area light on mesh {name!r} is not a polygon light: its {len(faces)} triangles "
            f"are not coplanar (a vertex lies {off:.3g} off their best-fit plane, "
            f"{off / size:.2%} of the mesh's size)")
    fn = np.cross(pos[faces[:, 1]] - pos[faces[:, 0]], pos[faces[:, 2]] - pos[faces[:, 0]])
    tri_area = 0.5 * np.linalg.norm(fn, axis=1)
    side = fn @ plane_n
    real = tri_area > 1e-12 * size * size
    if not np.any(real):
        raise GlossrtError(
            f"area light on mesh {name!r} has zero area: each of its {len(faces)} triangles "
            "has collinear or repeated corners")
    if np.any(side[real] > 0) and np.any(side[real] < 0):
        raise GlossrtError(
            f"area light on mesh {name!r} is not a polygon light: its triangles are wound "
            "both ways (some face the other side)")
    normals = _emitting_normals(shape, 16)
    dots = normals @ plane_n
    if not (np.all(dots > 0.5) or np.all(dots < -0.5)):
        raise GlossrtError(
            f"area light on mesh {name!r} is not a polygon light: its normals do not all "
            "point to the same side of its plane")
    emit_n = plane_n if dots[0] > 0 else -plane_n
    # 2D frame (t1, t2, emit_n) right-handed: counter-clockwise in 2D = about emit_n
    t1 = vt[0] - (vt[0] @ emit_n) * emit_n
    t1 /= np.linalg.norm(t1)
    t2 = np.cross(emit_n, t1)
    p2 = np.c_[(pts - centre) @ t1, (pts - centre) @ t2]
    try:
        hull = ConvexHull(p2)
    except QhullError:
        raise GlossrtError(f"area light on mesh {name!r}: the mesh has zero area") from None
    ring = list(hull.vertices)  # counter-clockwise in 2D
    # drop corners where the outline goes straight on
    def straight(k: int) -> bool:
        a, b, c = p2[ring[k - 1]], p2[ring[k]], p2[ring[(k + 1) % len(ring)]]
        e1, e2 = b - a, c - b
        return abs(e1[0] * e2[1] - e1[1] * e2[0]) <= 1e-9 * size * size
    k = 0
    while k < len(ring) and len(ring) > 3:
        if straight(k):
            ring.pop(k)
        else:
            k += 1
    hull_area = float(hull.volume)  # the area, in 2D
    mesh_area = float(tri_area.sum())
    if abs(mesh_area - hull_area) > AREA_TOL * hull_area:
        raise GlossrtError(
            f"area light on mesh {name!r} is not a polygon light: its outline is not convex "
            f"or its triangles overlap (area {mesh_area:.6g} against {hull_area:.6g} for its "
            "convex hull)")
    if len(ring) > MAX_VERTICES:
        raise GlossrtError(
            f"area light on mesh {name!r} is not a polygon light: its convex outline has "
            f"{len(ring)} corners (at most {MAX_VERTICES})")
    verts = pts[ring]
    if not textured:
        return verts, None
    tc = params["vertex_texcoords"] if "vertex_texcoords" in params.keys() else None
    tc = np.array(tc, dtype=np.float64).reshape(-1, 2) if tc is not None else np.zeros((0, 2))
    if len(tc) != len(pos):
        raise GlossrtError(
            f"area light on mesh {name!r}: its radiance is a texture but the mesh has no "
            "texture coordinates")
    tc = tc[used]
    # texture coordinates must be an affine function of the position on the plane
    a = np.c_[p2, np.ones(len(p2))]
    coef, *_ = np.linalg.lstsq(a, tc, rcond=None)
    err = float(np.max(np.abs(a @ coef - tc), initial=0.0))
    if err > 1e-4 * max(1.0, float(np.max(np.abs(tc)))):
        raise GlossrtError(
            f"area light on mesh {name!r}: its texture coordinates are not an affine map of "
            f"the plane (off by up to {err:.3g}), so one uv per corner cannot describe them")
    return verts, tc[ring]


def _check_finite_vertices(what: str, verts: np.ndarray) -> None:
    """GlossrtError unless every vertex of the light on ``what`` is finite (a NaN or Inf in
    its transform or its vertex positions)."""
    bad = ~np.all(np.isfinite(verts), axis=-1)
    if np.any(bad):
        raise GlossrtError(
            f"area light on {what}: {int(bad.sum())} of its {len(verts)} vertices are not "
            f"finite (e.g. {np.asarray(verts)[np.argmax(bad)].tolist()}): a NaN or Inf in its "
            "transform (to_world) or vertex positions")


def _check_radiance(what: str, radiance: np.ndarray, texture: np.ndarray | None) -> None:
    """GlossrtError unless the radiance (and a bitmap texture's texels) are finite and >= 0."""
    r = np.asarray(radiance, dtype=np.float64)
    if not (np.all(np.isfinite(r)) and np.all(r >= 0)):
        raise GlossrtError(f"{what} has radiance {r.tolist()}: it must be finite and >= 0")
    if texture is not None:
        t = np.asarray(texture)
        bad = ~np.isfinite(t) | (t < 0)
        if np.any(bad):
            raise GlossrtError(
                f"{what} has a radiance texture with {int(bad.sum())} bad values (e.g. "
                f"{float(t[bad].ravel()[0])}): they must be finite and >= 0")


def _radiance(emitter, shape) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """(RGB radiance, texture or None, 3x3 to_uv or None) of an area emitter."""
    params = mi.traverse(emitter)
    keys = [k for k in params.keys() if k.startswith("radiance.")]
    if "radiance.data" in keys:
        tex = np.array(params["radiance.data"], dtype=np.float32)
        to_uv = (to_matrix3(params["radiance.to_uv"]) if "radiance.to_uv" in keys
                 else np.eye(3))
        return np.ones(3), tex, to_uv
    if keys and keys != ["radiance.value"]:
        raise GlossrtError(
            f"area light on {_shape_name(shape)!r}: its radiance texture "
            f"({', '.join(keys)}) is not supported (use a constant or a bitmap)")
    # constant radiance, whatever its spectrum type: what Mitsuba emits along the normal
    ps = shape.sample_position(0.0, mi.Point2f(0.5, 0.5))
    si = mi.SurfaceInteraction3f(ps, dr.zeros(mi.Color0f))
    si.wi = mi.Vector3f(0.0, 0.0, 1.0)
    value = np.array(emitter.eval(si), dtype=np.float64).ravel()
    return np.broadcast_to(value, (3,)).copy() if value.size == 1 else value[:3], None, None


def to_matrix3(t) -> np.ndarray:
    """3x3 float64 matrix of a Mitsuba 2D affine transform (``ScalarAffineTransform3f``)."""
    m = np.array(t.matrix, dtype=np.float64)
    if m.ndim == 3:
        m = m[..., 0]
    return m.reshape(3, 3)


def polygon_light(emitter, mesh_id: int = 0, where: str = "") -> PolygonLight:
    """The :class:`PolygonLight` of one Mitsuba area emitter, in its current pose.

    :class:`GlossrtError` for a shape that is not a polygon, non-finite vertices (a NaN or Inf
    transform), zero area, or radiance (or texture values) that are not finite and >= 0;
    ``where`` (e.g. "emitter 2 of scene 'x'") is named in those two messages."""
    shape = emitter.get_shape()
    if shape is None:
        raise GlossrtError(f"emitter {emitter.id() or emitter.class_name()!r} is not an area "
                           "light (it has no shape)")
    name = _shape_name(shape)
    radiance, texture, to_uv = _radiance(emitter, shape)
    cls = shape.class_name()
    what = f"shape {name!r}" + (f" ({where})" if where else "")
    if cls == "Rectangle":
        verts, uv = _rectangle_polygon(shape)
        _check_finite_vertices(what, verts)
        kind = "rectangle"
    elif isinstance(shape, mi.Mesh):
        verts, uv = _mesh_polygon(shape, texture is not None, what)  # checks its vertices
        kind = "mesh"
    else:
        raise GlossrtError(
            f"area light on shape {name!r} ({cls}) is not a polygon light: only rectangles "
            "and planar convex meshes are")
    n = _newell(verts)
    if not np.linalg.norm(n) > 0.0:
        raise GlossrtError(f"area light on shape {name!r} has zero area")
    _check_radiance(f"area light on {what}", radiance, texture)
    emit_n = _emitting_normals(shape, 1)[0]
    if float(n @ emit_n) < 0.0:  # e.g. flip_normals, or a mirroring to_world
        verts = verts[::-1].copy()
        uv = uv[::-1].copy() if uv is not None else None
    if texture is not None:
        uv = np.c_[uv, np.ones(len(uv))] @ to_uv.T
        uv = uv[:, :2] / uv[:, 2:3]
    else:
        uv = None
    return PolygonLight(vertices=verts, radiance=radiance, two_sided=False, texture=texture,
                        uv=uv, id=shape.id() or emitter.id(), mesh_id=mesh_id, shape=kind)


def polygon_lights(setup, frame: int | None = None, skip: bool = False) -> list[PolygonLight]:
    """Every area light of ``setup`` (a :class:`glossrt.scenes.SceneSetup`, posed for
    ``frame`` first when given; or a bare ``mi.Scene``) as a :class:`PolygonLight`, in the
    scene's stable emitter order (:func:`glossrt.scenes.stable_emitters`). Non-area emitters
    are left out; an area emitter that is not a polygon raises :class:`GlossrtError`, or with
    ``skip`` is left out too (the path tracer renders it: :mod:`glossrt.pipeline.plan`)."""
    if frame is not None and hasattr(setup, "set_frame"):
        setup.set_frame(int(frame))
    scene = getattr(setup, "scene", setup)
    label = getattr(setup, "source", None) or getattr(setup, "name", None) or scene.id()
    rank = {_registry_id(mi.ShapePtr, s): i + 1 for i, s in enumerate(render_shapes(scene))}
    lights = []
    for k, e in enumerate(stable_emitters(scene)):
        shape = e.get_shape()
        if shape is None:
            continue
        where = f"emitter {k}" + (f" of scene {label!r}" if label else "")
        try:
            lights.append(polygon_light(e, rank.get(_registry_id(mi.ShapePtr, shape), 0),
                                        where))
        except GlossrtError:
            if not skip:
                raise
    return lights
