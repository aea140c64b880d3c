"""Shadowed polygon-light shading of Frames (issue 6): the glue between scenes, G-buffers and
the BSPVT pieces (:mod:`glossrt.lights.bspvt.build` builds the trees,
:mod:`glossrt.lights.bspvt.shade` integrates the visible pieces) and the ratio-estimator peer
(:mod:`glossrt.lights.ratio`). :func:`match_scene` holds every check that trees fit the scene
as it is now; :func:`shade_bspvt` runs it once per frame.

* :func:`build_scene_trees`: visibility cube maps of every mesh vertex of a scene (emitters
  removed) and their trees, with the build statistics of the paper's Table 1;
* :func:`pixel_triangles`: for each pixel of a G-buffer, the triangle it sees (three global
  vertex indices, in the numbering of :func:`glossrt.lights.bspvt.build.scene_vertices`) and its
  barycentric coordinates, by tracing a ray from the camera to the pixel's ``position``;
* :func:`shade_bspvt`: direct light with BSPVT shadows of a Frame, per vertex (Okuno &
  Iwasaki's mode: vertices shaded with their own view and material, colours interpolated
  across triangles) or per pixel (their future work: each pixel evaluates its triangle's
  three vertex trees with its own G-buffer data and blends by barycentrics).
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import drjit as dr
import numpy as np

from ...backend import mi
from ...errors import FrameError, GlossrtError
from ...images import check_frame, merge, split
from ...jit import opaque, owned
from ..shading import (
    MATERIAL_ROW,
    NEEDS,
    ShadingPoints,
    _take,
    material_rows_at,
    mesh_material_tables,
    points_with_materials,
    refuse_anisotropic,
)
from . import build, shade

MODES = ("vertex", "pixel")


def scene_meshes(scene: mi.Scene) -> list:
    """The non-emitting ``mi.Mesh`` shapes in the order of
    :func:`glossrt.lights.bspvt.build.scene_vertices` (whose ``offsets`` number their vertices)."""
    from ...scenes import stable_shapes

    return _meshes_of(stable_shapes(scene))


def _meshes_of(shapes: list) -> list:
    """:func:`scene_meshes` of shapes already in ``stable_shapes`` order."""
    return [s for s in shapes if isinstance(s, mi.Mesh) and not s.is_emitter()]


def build_scene_trees(scene, resolution: int = 64, epsilon: float = 0.0,
                      method: str = "batched", progress: bool = True, *, cluster=None,
                      chunk_vertices: int | None = None, **kwargs):
    """Okuno & Iwasaki's precomputation for ``scene``: visibility cube maps at every vertex
    of its non-emitting meshes against its non-emitting shapes
    (:func:`glossrt.lights.bspvt.build.visibility_cubemaps` on
    :func:`glossrt.lights.bspvt.build.occluders`), then the trees
    (:func:`glossrt.lights.bspvt.build.build_trees`, ``kwargs`` passed on). The returned trees'
    ``info`` adds the visibility and total seconds (``stats()`` has the tree build's).

    ``scene``: a loaded ``mi.Scene``, or a built-in name or XML path. With ``cluster`` (a
    :func:`glossrt.cluster.map_items` spec) or ``chunk_vertices``, the build runs as work
    items of ``chunk_vertices`` vertices each
    (:func:`glossrt.lights.bspvt.build.build_vertex_chunk`, default
    :data:`glossrt.lights.bspvt.build.CHUNK_VERTICES`) that load the scene themselves (so
    ``scene`` must be a name or path), on the cluster's workers or one after the other in
    this process, merged into the same arrays as the one-process build."""
    import time

    from ...scenes import load

    chunked = cluster is not None or chunk_vertices is not None
    ref = build.scene_ref(scene) if chunked else None
    if isinstance(scene, (str, os.PathLike)):
        scene = load(os.fspath(scene)).scene
    pos, nrm, _ = build.scene_vertices(scene)
    if len(pos) == 0:
        raise GlossrtError("the scene has no mesh vertices to precompute visibility at "
                           "(BSPVT needs triangle meshes; analytic shapes only occlude)")
    t0 = time.perf_counter()
    if chunked:
        trees = _build_chunked(ref, pos, resolution, epsilon, method, progress, cluster,
                               build.CHUNK_VERTICES if chunk_vertices is None
                               else chunk_vertices, kwargs)
        t1 = t0 + trees.info.get("chunk_visibility_seconds", 0.0)  # summed over the items
    else:
        vis = build.visibility_cubemaps(build.occluders(scene), pos, nrm, resolution,
                                        progress=progress)
        t1 = time.perf_counter()
        trees = build.build_trees(vis, epsilon, method, positions=pos, normals=nrm,
                                  progress=progress, **kwargs)
    t2 = time.perf_counter()
    trees.info.update({"visibility_seconds": t1 - t0, "tree_seconds": t2 - t1,
                       "total_seconds": t2 - t0,
                       # the analytic occluders' placement (meshes: ``positions``), so that
                       # shading can refuse trees whose occluders have moved since
                       "occluder_bounds": occluder_bounds(scene)})
    return trees


def _build_chunked(ref: str, pos: np.ndarray, resolution: int, epsilon: float, method: str,
                   progress: bool, cluster, chunk_vertices: int, settings: dict):
    """:func:`build_scene_trees` by vertex chunks (issue 27), through
    :func:`glossrt.cluster.map_items` (in this process without a cluster); the merged
    trees' positions are checked against this process's scene (a worker that loaded another
    file is refused)."""
    import time

    from ...cluster import connect

    t0 = time.perf_counter()
    items = build.vertex_chunk_items(ref, len(pos), resolution, epsilon, method,
                                     chunk_vertices, **settings)
    with connect("none" if cluster is None else cluster) as c:
        # an XML scene travels with the items (no shared folder needed on the nodes)
        results = _map_items(build.build_vertex_chunk, build.ship_scene(items, c), c,
                             progress, f"BSPVT build {resolution}x{resolution}")
    info = {"method": method, "angles": settings.get("angles", build.DEFAULT_ANGLES)
            if method == "batched" else None,
            "max_leaves": settings.get("max_leaves"),
            "max_depth": int(settings.get("max_depth", build.DEFAULT_MAX_DEPTH)),
            "stalled": settings.get("stalled", "split"),
            "engine": settings.get("engine", "numpy") if method == "batched" else None,
            "chunk_vertices": int(chunk_vertices)}
    trees = build.merge_vertex_chunks(results, len(pos), info)
    if not np.array_equal(trees.positions, pos.astype(np.float32)):
        raise GlossrtError(f"the workers' scene {ref!r} has other vertex positions than this "
                           "process's (a different file or glossrt version on the cluster?)")
    trees.info["build_seconds"] = time.perf_counter() - t0
    return trees


def _map_items(fn, items: list, cluster, progress: bool, desc: str) -> list:
    """``fn`` over ``items`` through :func:`glossrt.cluster.map_items` (progress weights:
    vertices per item; one GPU per task on CUDA variants); ``cluster=None`` runs them in this
    process in order (the environment's ``GLOSSRT_CLUSTER`` is the command line's business)."""
    from ...cluster import map_items

    return map_items(fn, items, cluster="none" if cluster is None else cluster, desc=desc,
                     weights=[it["stop"] - it["start"] for it in items], progress=progress)


def vertex_beckmann(scene: mi.Scene) -> np.ndarray:
    """Per vertex (numbering of :func:`scene_vertices`): whether its mesh's rough lobe has
    Beckmann's distribution (V,) bool (:func:`glossrt.render.materials.describe_bsdf`)."""
    from ...render.materials import describe_bsdf

    return np.concatenate([np.full(m.vertex_count(), describe_bsdf(m.bsdf()).beckmann)
                           for m in scene_meshes(scene)] or [np.zeros(0, bool)])


def vertex_materials(scene: mi.Scene) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per vertex (numbering of :func:`scene_vertices`): GGX alpha (V,), diffuse albedo and
    F0 (V, 3) of each mesh's BSDF: alpha and F0 as the G-buffer and
    :func:`glossrt.lights.shading.f0_image` take them
    (:func:`glossrt.render.materials.describe_bsdf`), the albedo as the renderer's
    ``albedo_diffuse`` (``eval_diffuse_reflectance`` at the vertex's texture coordinates)."""
    from ...brdf.ggx import ALPHA_MIN
    from ...render.materials import describe_bsdf

    alpha, albedo, f0 = [], [], []
    for m in scene_meshes(scene):
        d = describe_bsdf(m.bsdf())
        k = m.vertex_count()
        alpha.append(np.full(k, max(float(d.alpha), ALPHA_MIN)))
        f0.append(np.tile(np.asarray(d.f0, np.float64).ravel()[:3], (k, 1)))
        si = dr.zeros(mi.SurfaceInteraction3f, k)
        if m.has_vertex_texcoords():
            uv = np.array(m.vertex_texcoords_buffer(), np.float32).reshape(-1, 2)
            si.uv = mi.Point2f(uv[:, 0], uv[:, 1])
        si.wi = mi.Vector3f(0, 0, 1)
        si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
        if not d.has_diffuse:  # (conductors: no diffuse lobe; their "reflectance" is not one)
            albedo.append(np.zeros((k, 3)))
            continue
        rho = m.bsdf().eval_diffuse_reflectance(si)
        albedo.append(np.stack([np.broadcast_to(np.asarray(rho[c], np.float64), (k,))
                                for c in range(3)], -1))  # (a constant texture: width 1)
    return np.concatenate(alpha), np.concatenate(albedo), np.concatenate(f0)


@dataclass
class PixelTriangles:
    """Per pixel (flattened, row-major): ``vertices`` (N, 3) int64 global vertex indices of the
    triangle seen, ``bary`` (N, 3) float32 barycentric weights of those vertices, ``valid``
    (N,) bool (False on background and on shapes without per-vertex data)."""

    vertices: np.ndarray
    bary: np.ndarray
    valid: np.ndarray


def pixel_triangles(scene: mi.Scene, frame, meshes: list, offsets: np.ndarray) -> PixelTriangles:
    """The triangle each pixel of ``frame`` sees and its barycentrics, for the ``meshes``
    (``mi.Mesh`` objects of ``scene``) whose vertices are numbered from ``offsets[i]`` on.

    A ray from the camera position to the G-buffer's ``position`` (stopping just short of it
    would miss it: it runs 1% past) finds the same surface point; Mitsuba's ``prim_uv``
    ``(b1, b2)`` weights the triangle's vertices ``(1 - b1 - b2, b1, b2)``."""
    verts, bary, valid = _pixel_triangles(scene, frame, meshes, offsets)
    dr.eval(verts, bary, valid)
    return PixelTriangles(np.stack([np.array(v).astype(np.int64) for v in verts], -1),
                          np.stack([np.array(b, np.float32) for b in bary], -1),
                          np.array(valid, bool))


def _pixel_triangles(scene: mi.Scene, frame, meshes: list, offsets) -> tuple:
    """:func:`pixel_triangles` on the device: (three ``mi.UInt32`` vertex indices, three
    ``mi.Float`` barycentrics, ``mi.Bool`` valid); 0 where not valid."""
    check_frame(frame, ("position", "mesh_id"))
    if frame.camera is None:
        raise FrameError(f"{frame.where}: per-vertex shading needs the camera")
    from ...scenes import _registry_id

    p = mi.Point3f(*split(frame["position"]))
    hit = split(frame["mesh_id"])[0] > 0
    o = mi.Point3f(*opaque(frame.camera.position))
    # missed rays carry undefined (possibly non-finite) prim_uv: _triangles zeroes them
    return _triangles(scene, p, hit, o, _Geometry(
        [m.faces_buffer() for m in meshes],
        [_registry_id(mi.ShapePtr, m) for m in meshes],
        [m.face_count() for m in meshes], [int(off) for off in offsets]))


def _shade_pixel_mode(frame, dev, lights: list, triangles: tuple, f0, textures,
                      traversal: str, frozen: bool) -> mi.TensorXf:
    """Per-pixel mode on the device: each pixel evaluates its triangle's three vertex trees
    with its own G-buffer point, normal, view and material
    (:func:`glossrt.lights.bspvt.shade.shade_points`, barycentric weights); pixels without a
    triangle (background, lights, analytic shapes) are not traversed and get 0."""
    verts, bary, valid = triangles
    sp = ShadingPoints.of(frame, f0)
    hit = sp.hit & valid
    up = mi.Vector3f(0.0, 0.0, 1.0)  # placeholders where nothing is shaded (finite inputs)
    sp = ShadingPoints(dr.select(hit, sp.p, mi.Point3f(0.0)),
                       dr.select(hit, dr.normalize(sp.n), up), dr.select(hit, sp.wo, up),
                       sp.alpha, sp.albedo, sp.f0, hit, sp.beckmann, sp.fresnel)
    if frozen:  # every pixel a lane (a fixed size: the recording replays frame after frame)
        d, s = shade.shade_points(dev, lights, sp, verts, bary, textures=textures,
                                        traversal=traversal, frozen=True)
        out = d + s
    else:  # only the shaded pixels (compacted): fewer lanes for the whole-light integrals
        idx = dr.compress(hit)
        out = dr.zeros(mi.Color3f, dr.width(hit))
        if dr.width(idx):
            d, s = shade.shade_points(
                dev, lights, _take(sp, idx), [dr.gather(mi.UInt32, v, idx) for v in verts],
                [dr.gather(mi.Float, b, idx) for b in bary], textures=textures,
                traversal=traversal)
            dr.scatter(out, d + s, idx)
    return merge([out[0], out[1], out[2]], frame.height, frame.width)


def _vertex_material_rows(scene: mi.Scene, dev, camera) -> np.ndarray:
    """Per tree vertex: its mesh's :func:`glossrt.lights.shading.material_rows_at` row at
    the vertex's view towards ``camera`` (V, 16)."""
    meshes = scene_meshes(scene)
    rows, scales = mesh_material_tables(meshes)
    ids = np.concatenate([np.full(m.vertex_count(), k) for k, m in enumerate(meshes)])
    pos = np.stack([np.asarray(dev.positions[c]) for c in range(3)], -1)
    nrm = np.stack([np.asarray(dev.normals[c]) for c in range(3)], -1)
    return material_rows_at(rows, scales, ids, pos, nrm, camera)


def _shade_vertex_mode(scene: mi.Scene, frame, dev, lights: list, triangles: tuple,
                       textures, traversal: str, frozen: bool,
                       materials: bool = False) -> mi.TensorXf:
    """Per-vertex mode on the device: every tree vertex shaded at its own position and normal
    towards the camera (:func:`glossrt.lights.bspvt.shade.shade_points`), then blended per
    pixel by the barycentrics of the triangle it sees."""
    verts, bary, valid = triangles
    nv = dev.n_vertices
    cam = mi.Point3f(*opaque(frame.camera.position))
    to_cam = cam - dev.positions
    wo = to_cam / dr.maximum(dr.norm(to_cam), 1e-12)
    alpha, albedo, vf0 = vertex_materials(scene)
    beckmann = shade._beckmann_lanes(vertex_beckmann(scene), nv)
    # as shade_vertices: views at or below a vertex's tangent plane shade it black
    hit = dr.dot(dev.normals, wo) > 0
    if materials:
        # the exact Fresnel terms and coated diffuse lobes (as fresnel_image per pixel)
        sp = points_with_materials(dev.positions, dev.normals, wo, owned(mi.Float, alpha),
                                   shade._dr_vec(mi.Color3f, albedo), hit, beckmann,
                                   _vertex_material_rows(scene, dev, frame.camera.position))
    else:
        sp = ShadingPoints(dev.positions, dev.normals, wo, owned(mi.Float, alpha),
                           shade._dr_vec(mi.Color3f, albedo),
                           shade._dr_vec(mi.Color3f, vf0), hit, beckmann)
    d, s = shade.shade_points(dev, lights, sp, [dr.arange(mi.UInt32, nv)],
                                    textures=textures, traversal=traversal, frozen=frozen)
    col = d + s
    out = dr.zeros(mi.Color3f, dr.width(valid))
    for v, b in zip(verts, bary, strict=True):
        out += b * dr.gather(mi.Color3f, col, v, valid)
    out = dr.select(valid, out, 0.0)
    return merge([out[0], out[1], out[2]], frame.height, frame.width)


def shade_bspvt(scene: mi.Scene, frame, trees, lights: list, mode: str = "vertex",
                f0: np.ndarray | None = None, textures: dict | None = None,
                traversal: str = "kernel", frozen: bool = False) -> np.ndarray:
    """Direct light (H, W, 3) of ``frame`` from the polygon ``lights`` with BSPVT shadows
    (Okuno & Iwasaki, eq. 2 per vertex tree; see the module docstring for ``mode``).

    ``trees`` must have been built for ``scene``'s vertices (:func:`build_scene_trees`);
    ``f0`` is the per-pixel F0 (H, W, 3) or, for Mitsuba's exact Fresnel terms and coated
    diffuse lobes, :func:`glossrt.lights.shading.fresnel_image` (H, W, 16); the ``vertex``
    mode takes materials per mesh (:func:`vertex_materials`), with the exact terms at each
    vertex's view when ``f0`` is a :func:`~glossrt.lights.shading.fresnel_image`, Schlick's
    and the raw diffuse reflectance otherwise; ``traversal``: how the trees are walked
    (:data:`glossrt.lights.bspvt.shade.TRAVERSALS`, same result); ``frozen``: replay recorded
    kernels (:func:`glossrt.lights.bspvt.shade.shade_points`). Pixels on shapes without
    trees (the lights themselves, analytic shapes) and background pixels get 0. Trees of
    another scene, or of this one before an occluder moved, raise :class:`GlossrtError`
    (:func:`match_scene`, once per call: the vertices once per trees and scene pose, the
    analytic occluders' boxes every call)."""

    if mode not in MODES:
        raise GlossrtError(f"unknown BSPVT mode {mode!r}; choose one of {MODES}")
    meshes, offsets = match_scene(scene, trees)
    check_frame(frame, NEEDS)
    refuse_anisotropic(frame, "BSPVT shading")
    dev = shade.DeviceTrees.of(trees)
    # (vertex indices, barycentrics, valid) of the triangle each pixel sees
    tri = _pixel_triangles(scene, frame, meshes, offsets[:-1])
    if mode == "vertex":
        exact = f0 is not None and np.asarray(f0).shape[-1] == MATERIAL_ROW
        img = _shade_vertex_mode(scene, frame, dev, lights, tri, textures, traversal, frozen,
                                 exact)
    else:
        img = _shade_pixel_mode(frame, dev, lights, tri, f0, textures, traversal, frozen)
    return np.array(img, np.float32).reshape(frame.height, frame.width, 3)


# -- the trees against the scene -----------------------------------------------------------

#: :func:`check_trees_match` tolerances: stored vertex positions against the scene's, as a
#: fraction of the scene's bounding-box diagonal (float32 storage rounds the coordinates to
#: ~6e-8 of their size), and stored unit normals against the scene's (absolute)
MATCH_POSITION_TOL = 1e-4
MATCH_NORMAL_TOL = 1e-3


def occluder_bounds(scene: mi.Scene) -> list[dict]:
    """Id and bounding box (``min``, ``max``) of each non-emitting shape that is not a mesh
    (analytic spheres, ...), in :func:`glossrt.scenes.stable_shapes` order: what the trees'
    ``info["occluder_bounds"]`` records at build time. Meshes are compared vertex by vertex
    instead (the trees' ``positions``)."""
    from ...scenes import stable_shapes

    return _bounds_of(stable_shapes(scene))


def _bounds_of(shapes: list) -> list[dict]:
    """:func:`occluder_bounds` of shapes already in ``stable_shapes`` order."""
    out = []
    for s in shapes:
        if s.is_emitter() or isinstance(s, mi.Mesh):
            continue
        b = s.bbox()
        out.append({"shape": s.id(), "min": [float(b.min[i]) for i in range(3)],
                    "max": [float(b.max[i]) for i in range(3)]})
    return out


def _count_mismatch(trees, stored: int, scene: int) -> GlossrtError:
    return GlossrtError(f"{_trees_name(trees)} hold {stored} vertices but the scene's meshes "
                        f"have {scene}: built for another scene?")


def _trees_name(trees) -> str:
    source = getattr(trees, "source", "")
    return f"the BSPVT trees in {source}" if source else "the BSPVT trees"


def check_trees_match(scene: mi.Scene, trees) -> None:
    """Raise :class:`GlossrtError` unless ``trees`` were built for ``scene``'s geometry as it
    is now. Okuno & Iwasaki precompute visibility for static occluders, so trees of another
    scene, or of this one before an occluder moved, shade wrong shadows.

    * Mesh vertices (:func:`glossrt.lights.bspvt.build.scene_vertices`): the same count, positions
      within :data:`MATCH_POSITION_TOL` of the scene's bounding-box diagonal, normals within
      :data:`MATCH_NORMAL_TOL`. Trees that store no geometry (all-zero positions and
      normals) are not compared. A pass is remembered on ``trees`` with the scene's identity
      and its mesh vertex buffers (Dr.Jit variable indices, which change when a mesh is
      edited through ``mi.traverse``), so shading frame after frame reads the vertices once
      and an edited mesh is compared anew.
    * The other occluders (analytic shapes), when the trees recorded them
      (``info["occluder_bounds"]``, :func:`occluder_bounds`; files written before this
      record skip it): the same shapes with bounding boxes within the same tolerance,
      compared on every call (a few ``bbox()`` calls).

    The message names the trees' file (``trees.source``) and the largest mismatch."""
    from ...scenes import stable_shapes

    shapes = stable_shapes(scene)  # once per call: both checks below read it
    _check_match(scene, trees, shapes, _meshes_of(shapes))


def match_scene(scene: mi.Scene, trees) -> tuple[list, np.ndarray]:
    """Every check that ``trees`` fit ``scene`` as it is now, in one place: what
    :func:`shade_bspvt` runs once per frame before any work. The vertex count of the scene's
    non-emitting meshes must be the trees' (else "built for another scene?"), then
    :func:`check_trees_match`. The scene's shapes are listed once for both. Returns the meshes
    (:func:`scene_meshes`) and their vertex offsets (``len(meshes) + 1`` entries, the last
    one the vertex count), which number the trees' vertices for shading."""
    from ...scenes import stable_shapes

    shapes = stable_shapes(scene)
    meshes = _meshes_of(shapes)
    offsets = np.cumsum([0] + [m.vertex_count() for m in meshes])
    if int(offsets[-1]) != int(trees.vertex_count):
        raise _count_mismatch(trees, trees.vertex_count, int(offsets[-1]))
    _check_match(scene, trees, shapes, meshes)
    return meshes, offsets


def _check_match(scene: mi.Scene, trees, shapes: list, meshes: list) -> None:
    """:func:`check_trees_match` given the scene's ``shapes`` (``stable_shapes`` order) and
    its non-emitting ``meshes`` among them."""
    pos_t, nrm_t = getattr(trees, "positions", None), getattr(trees, "normals", None)
    if pos_t is None or nrm_t is None:
        return
    stored = (getattr(trees, "info", None) or {}).get("occluder_bounds")
    if stored is not None:
        _compare_occluders(scene, trees, stored, _bounds_of(shapes))
    key = (id(scene), tuple(m.vertex_positions_buffer().index for m in meshes))
    cached = getattr(trees, "_glossrt_scene_match", None)
    if cached is not None and cached[0] == key and cached[1] is pos_t and cached[2] is nrm_t:
        return
    tp = np.asarray(pos_t, np.float64).reshape(-1, 3)
    tn = np.asarray(nrm_t, np.float64).reshape(-1, 3)
    if np.any(tp) or np.any(tn):
        _compare_geometry(scene, trees, tp, tn)
    try:  # the scene by identity only: the cache does not keep it alive
        trees._glossrt_scene_match = (key, pos_t, nrm_t)
    except AttributeError:  # objects without a __dict__: checked every time
        pass


def _compare_occluders(scene: mi.Scene, trees, stored: list, now: list) -> None:
    """:func:`check_trees_match`'s comparison of the analytic occluders recorded at build
    time (``stored``, :func:`occluder_bounds`) with the scene's (``now``)."""
    name = _trees_name(trees)
    fix = ("BSPVT visibility is precomputed for static occluders: rebuild the trees for this "
           "pose (glossrt bspvt build), or shade a scene whose occluders move with LTC "
           "(no shadows) or Monte Carlo")
    if [o.get("shape") for o in stored] != [o["shape"] for o in now]:
        raise GlossrtError(
            f"{name} were built with the analytic occluders "
            f"{[o.get('shape') for o in stored]} but the scene has "
            f"{[o['shape'] for o in now]}: built for another scene?")
    tol = MATCH_POSITION_TOL * build._scene_diagonal(scene)
    for o, n in zip(stored, now, strict=True):
        try:
            a = np.array([o["min"], o["max"]], np.float64)
        except (KeyError, TypeError, ValueError):
            raise GlossrtError(f"{name}: unreadable occluder_bounds entry {o!r}") from None
        b = np.array([n["min"], n["max"]], np.float64)
        if a.shape != (2, 3) or not np.all(np.abs(a - b) <= tol):
            raise GlossrtError(
                f"{name} were built with shape {n['shape']!r} inside "
                f"{np.round(a, 4).tolist()} but it is now inside {np.round(b, 4).tolist()}: "
                f"it has moved or changed since; {fix}")


def _compare_geometry(scene: mi.Scene, trees, tp: np.ndarray, tn: np.ndarray) -> None:
    """:func:`check_trees_match`'s comparison of stored positions ``tp`` and normals ``tn``
    with the scene's."""
    sp, sn, _ = build.scene_vertices(scene)
    name = _trees_name(trees)
    if sp.shape != tp.shape or sn.shape != tn.shape:
        raise _count_mismatch(trees, len(tp), len(sp))
    diag = build._scene_diagonal(scene)
    edit = "belong to another scene (or to this scene before an edit)"
    with np.errstate(invalid="ignore"):
        dp = np.linalg.norm(tp - sp, axis=1)
        dn = np.linalg.norm(tn - sn, axis=1)
    dp = np.where(np.isfinite(dp), dp, np.inf)
    dn = np.where(np.isfinite(dn), dn, np.inf)
    if len(dp) and dp.max() > MATCH_POSITION_TOL * diag:
        i = int(np.argmax(dp))
        raise GlossrtError(
            f"{name} {edit}: vertex {i} is stored at {np.round(tp[i], 6).tolist()} but the "
            f"scene has it at {np.round(sp[i], 6).tolist()} ({dp[i]:.3g} apart, "
            f"{dp[i] / diag:.2g} of the scene's size; {int((dp > MATCH_POSITION_TOL * diag).sum())}"
            f" of {len(dp)} vertices differ); rebuild them with `glossrt bspvt build`")
    if len(dn) and dn.max() > MATCH_NORMAL_TOL:
        i = int(np.argmax(dn))
        raise GlossrtError(
            f"{name} {edit}: vertex {i}'s stored normal {np.round(tn[i], 4).tolist()} differs "
            f"from the scene's {np.round(sn[i], 4).tolist()} by {dn[i]:.3g} "
            f"({int((dn > MATCH_NORMAL_TOL).sum())} of {len(dn)} normals differ); rebuild "
            "them with `glossrt bspvt build`")


# -- the real-time path: one frozen function per shader -------------------------------------


@dataclass
class MaterialTable:
    """:func:`glossrt.lights.shading.fresnel_image`'s material rows on the device: per mesh id
    (0 = background, then :func:`glossrt.scenes.render_shapes` order) the Fresnel row
    (``rows``, ``n x ROW`` flat) and the diffuse-scale table (``scales``, ``n x
    DIFFUSE_SCALE_NODES x 3`` flat); ``count`` the number of ids (an opaque scalar).
    :func:`material_columns` evaluates them per lane inside frozen functions."""

    rows: mi.Float
    scales: mi.Float
    count: mi.UInt32

    @staticmethod
    def of(scene: mi.Scene) -> MaterialTable:
        from ...brdf.fresnel import ROW
        from ...render.materials import DIFFUSE_SCALE_NODES
        from ...scenes import render_shapes

        rows, scales = mesh_material_tables(render_shapes(scene))
        rows = np.concatenate([np.zeros((1, ROW)), rows])
        scales = np.concatenate([np.ones((1, DIFFUSE_SCALE_NODES, 3)), scales])
        return MaterialTable(owned(mi.Float, rows), owned(mi.Float, scales),
                             dr.opaque(mi.UInt32, len(rows)))


def material_columns(table: MaterialTable, ids: mi.UInt32, p: mi.Point3f, n: mi.Vector3f,
                     cam: mi.Point3f) -> list:
    """The :data:`MATERIAL_ROW` columns of :func:`glossrt.lights.shading.material_rows_at` per
    lane, on the device: the Fresnel row of material ``ids`` (clamped to the table) and its
    diffuse scale at the lane's view cosine towards ``cam`` (``p``, ``n`` unnormalised as
    the G-buffer holds them), linear in ``sqrt(cos_o)`` between the table's nodes: the same
    float32 operations as the NumPy version, no host synchronisation."""
    from ...brdf.fresnel import ROW
    from ...render.materials import DIFFUSE_SCALE_NODES as NODES

    ids = dr.minimum(ids, table.count - 1)
    cols = [dr.gather(mi.Float, table.rows, ids * ROW + c) for c in range(ROW)]
    v = cam - p
    d = dr.dot(v, n)
    cos_o = dr.clip(d / dr.maximum(dr.sqrt(dr.dot(v, v)), 1e-12), 0.0, 1.0)
    x = dr.sqrt(cos_o) * float(NODES - 1)
    i0 = dr.minimum(mi.UInt32(x), NODES - 2)
    t = x - mi.Float(i0)
    base = (ids * NODES + i0) * 3
    for c in range(3):
        a = dr.gather(mi.Float, table.scales, base + c)
        b = dr.gather(mi.Float, table.scales, base + 3 + c)
        cols.append((1.0 - t) * a + t * b)
    return cols


def _material_kernel(ch: dict, cam: list, table: MaterialTable, size: tuple[int, int]):
    h, w = size
    p = mi.Point3f(*split(ch["position"]))
    n = mi.Vector3f(*split(ch["normal"]))
    ids = mi.UInt32(dr.maximum(split(ch["mesh_id"])[0], 0.0))
    return merge(material_columns(table, ids, p, n, mi.Point3f(*cam)), h, w)


class MaterialImage:
    """:func:`glossrt.lights.shading.fresnel_image` of a scene's frames on the device (one
    frozen kernel, no read-back): an (H, W, 16) ``mi.TensorXf`` every shading function takes
    as its ``f0``. The scene's materials are read once (:class:`MaterialTable`); call
    :meth:`refresh` after editing a BSDF."""

    def __init__(self, scene: mi.Scene):
        self.scene = scene
        self.table = MaterialTable.of(scene)
        self._fn = dr.freeze(_material_kernel, warn_after=16)

    def refresh(self) -> None:
        self.table = MaterialTable.of(self.scene)

    def __call__(self, frame) -> mi.TensorXf:
        from ...jit import no_gc

        check_frame(frame, ("position", "normal", "mesh_id"))
        if frame.camera is None:
            raise FrameError(f"{frame.where}: the material image needs the camera")
        ch = {k: frame[k] for k in ("position", "normal", "mesh_id")}
        with no_gc():
            return self._fn(ch, opaque(frame.camera.position), self.table,
                            (frame.height, frame.width))


@dataclass
class _Geometry:
    """What :func:`_triangles` reads of the scene's meshes (frozen-function inputs): per
    mesh its faces buffer, registry id, face count and first vertex (opaque scalars, so
    that a recording replays only with this scene's values)."""

    faces: list
    shape_ids: list
    face_counts: list
    offsets: list


@dataclass
class _VertexData:
    """Per tree vertex (frozen-function inputs): GGX / Beckmann alpha, diffuse reflectance,
    Schlick F0, Beckmann lanes, and the material id (:class:`MaterialTable`) of its mesh."""

    alpha: mi.Float
    albedo: mi.Color3f
    f0: mi.Color3f
    beckmann: mi.Bool
    ids: mi.UInt32


def _triangles(scene, p: mi.Point3f, hit: mi.Bool, o: mi.Point3f, geo: _Geometry) -> tuple:
    """:func:`_pixel_triangles`' device part: the triangle each lane's ray from ``o`` to
    ``p`` hits, its three global vertex indices, barycentrics and validity."""
    d = p - o
    dist = dr.norm(d)
    ray = mi.Ray3f(o, d / dr.maximum(dist, 1e-12))
    ray.maxt = dist * 1.01 + 1e-4
    pi = scene.ray_intersect_preliminary(ray, active=hit)
    shape_id = dr.reinterpret_array(mi.UInt32, pi.shape)
    width = dr.width(hit)
    verts = [dr.zeros(mi.UInt32, width) for _ in range(3)]
    valid = dr.zeros(mi.Bool, width)
    for faces, sid, count, off in zip(geo.faces, geo.shape_ids, geo.face_counts, geo.offsets,
                                      strict=True):
        sel = hit & (shape_id == sid) & (pi.prim_index < count)
        for j in range(3):
            v = dr.gather(mi.UInt32, faces, pi.prim_index * 3 + j, sel) + off
            verts[j] = dr.select(sel, v, verts[j])
        valid |= sel
    b1 = dr.select(valid, pi.prim_uv.x, 0.0)
    b2 = dr.select(valid, pi.prim_uv.y, 0.0)
    return verts, [dr.select(valid, 1.0 - b1 - b2, 0.0), b1, b2], valid


def _frozen_bspvt_kernel(ch: dict, cam: list, scene, geo: _Geometry, vdata: _VertexData,
                         table: MaterialTable, dev, lights: list, ltc_table, static: tuple):
    """The whole ``ltc+bspvt`` direct light of a frame (what :class:`FrozenShader` records):
    the triangle each pixel sees, then per vertex (Okuno & Iwasaki's mode) or per pixel the
    fused traversal (:func:`glossrt.lights.bspvt.shade._shade_core`), as :func:`shade_bspvt`
    with ``frozen=True`` computes it. ``static``: (mode, exact materials, (H, W), vertex
    count, two-sidedness per light), part of the recording's key."""
    mode, exact, (h, w), nv, two = static
    cam_p = mi.Point3f(*cam)
    p = mi.Point3f(*split(ch["position"]))
    hit = split(ch["mesh_id"])[0] > 0
    verts, bary, valid = _triangles(scene, p, hit, cam_p, geo)
    dl = [(world, le, tw, None, None) for (world, le), tw in zip(lights, two, strict=True)]
    if mode == "vertex":
        to_cam = cam_p - dev.positions
        wo = to_cam / dr.maximum(dr.norm(to_cam), 1e-12)
        vhit = dr.dot(dev.normals, wo) > 0
        if exact:
            cols = material_columns(table, vdata.ids, dev.positions, dev.normals, cam_p)
            from ..shading import FresnelLanes

            fres, f0, scale = FresnelLanes.of_columns(cols)
            sp = ShadingPoints(dev.positions, dev.normals, wo, vdata.alpha,
                               vdata.albedo * scale, f0, vhit, vdata.beckmann, fres)
        else:
            sp = ShadingPoints(dev.positions, dev.normals, wo, vdata.alpha, vdata.albedo,
                               vdata.f0, vhit, vdata.beckmann)
        d, s = shade._shade_core(dev, dl, sp, [dr.arange(mi.UInt32, nv)], [mi.Float(1.0)],
                                 ltc_table, nv, "fused", direct=True)
        col = d + s
        out = dr.zeros(mi.Color3f, h * w)
        for v, b in zip(verts, bary, strict=True):
            out += b * dr.gather(mi.Color3f, col, v, valid)
        out = dr.select(valid, out, 0.0)
    else:
        sp = ShadingPoints.at_camera(ch, cam)
        # lanes without a triangle or with non-finite G-buffer data are not traversed
        ok = sp.hit & valid & dr.all(dr.isfinite(sp.p)) & dr.all(dr.isfinite(sp.n))
        up = mi.Vector3f(0.0, 0.0, 1.0)
        sp = ShadingPoints(dr.select(ok, sp.p, mi.Point3f(0.0)),
                           dr.select(ok, dr.normalize(sp.n), up), dr.select(ok, sp.wo, up),
                           sp.alpha, sp.albedo, sp.f0, ok, sp.beckmann, sp.fresnel)
        d, s = shade._shade_core(dev, dl, sp, verts, bary, ltc_table, h * w, "fused",
                                 direct=True)
        out = d + s
    return merge([out[0], out[1], out[2]], h, w)


class FrozenShader:
    """:func:`shade_bspvt` for the real-time path (the pipeline's ``ltc+bspvt`` direct
    stage): the whole frame's shading (triangle lookup, per-vertex materials, the fused tree
    traversal, the barycentric blend) is one frozen function of this shader, recorded once
    per image size, light count and mode and replayed afterwards: no Python tracing, no host
    synchronisation, the result left on the device. New camera, light and G-buffer values
    replay (opaque inputs). The scene's per-vertex materials and mesh tables are read once
    and again whenever :func:`match_scene`'s check sees edited meshes. Textured lights (the
    fused traversal takes none) go through :func:`shade_bspvt` traced anew.

    ``f0``: the frame's material image (:class:`MaterialImage`, or a
    :func:`glossrt.lights.shading.fresnel_image` / F0 tensor); ``exact`` materials at the
    vertices when it has :data:`MATERIAL_ROW` columns, as :func:`shade_bspvt`. ``f0`` may
    also be the :class:`MaterialImage` itself, called only where the pixels' materials are
    read: ``vertex`` mode's fused kernel reads the vertices' materials from the scene's table
    and never the pixels', so it then shades with the exact materials and no material image
    at all (the pipeline's direct stage: 128 MiB less at 1920x1080, docs/PERFORMANCE.md),
    the same values as with one."""

    def __init__(self, scene: mi.Scene, trees, mode: str = "vertex",
                 materials: MaterialTable | None = None):
        if mode not in MODES:
            raise GlossrtError(f"unknown BSPVT mode {mode!r}; choose one of {MODES}")
        self.scene, self.trees, self.mode = scene, trees, mode
        self._table = materials
        self._fn = dr.freeze(_frozen_bspvt_kernel, warn_after=16)
        self._key = None
        self._geo = self._vdata = None

    def _prepare(self, meshes: list, offsets: np.ndarray) -> None:
        from ...scenes import _registry_id, stable_shapes

        key = (id(self.scene), tuple(m.vertex_positions_buffer().index for m in meshes))
        if key == self._key:
            return
        self._geo = _Geometry(
            [m.faces_buffer() for m in meshes],
            [dr.opaque(mi.UInt32, _registry_id(mi.ShapePtr, m)) for m in meshes],
            [dr.opaque(mi.UInt32, m.face_count()) for m in meshes],
            [dr.opaque(mi.UInt32, int(o)) for o in offsets[:-1]])
        alpha, albedo, vf0 = vertex_materials(self.scene)
        nv = int(offsets[-1])
        shapes = stable_shapes(self.scene)
        # each vertex's material id: its mesh's mesh_id (stable_shapes position + 1)
        rid = {_registry_id(mi.ShapePtr, s): k for k, s in enumerate(shapes)}
        ids = np.concatenate([np.full(m.vertex_count(), rid[_registry_id(mi.ShapePtr, m)] + 1)
                              for m in meshes])
        beck = vertex_beckmann(self.scene)
        self._vdata = _VertexData(owned(mi.Float, alpha), shade._dr_vec(mi.Color3f, albedo),
                                  shade._dr_vec(mi.Color3f, vf0),
                                  owned(mi.UInt32, beck[:nv]) != 0, owned(mi.UInt32, ids))
        if self._table is None or self._key is not None:
            self._table = MaterialTable.of(self.scene)
        self._key = key

    def frozen(self) -> list:
        return [self._fn]

    def __call__(self, frame, lights: list, f0=None, textures: dict | None = None
                 ) -> mi.TensorXf:
        from ...jit import no_gc
        from ..ltc.shade import _device_lights, _table, prefiltered
        from ..shading import f0_tensor, shading_channels

        meshes, offsets = match_scene(self.scene, self.trees)
        check_frame(frame, NEEDS)
        refuse_anisotropic(frame, "BSPVT shading")
        if frame.camera is None:
            raise FrameError(f"{frame.where}: BSPVT shading needs the camera")
        cache = {} if textures is None else textures
        lazy = isinstance(f0, MaterialImage)
        if not lights or any(prefiltered(lt, cache) is not None for lt in lights):
            if lazy:
                f0 = f0(frame)
            img = shade_bspvt(self.scene, frame, self.trees, lights, self.mode, f0=f0,
                              textures=cache, frozen=True)
            return mi.TensorXf(img)
        self._prepare(meshes, offsets)
        dev = shade.DeviceTrees.of(self.trees)
        ch = shading_channels(frame)
        if lazy and self.mode == "vertex":
            exact = True  # (the kernel reads the vertices' exact materials from the table)
        else:
            ch["f0"] = f0_tensor(frame, f0(frame) if lazy else f0)
            exact = ch["f0"].shape[-1] == MATERIAL_ROW
        dl, two = _device_lights(lights)
        static = (self.mode, exact, (frame.height, frame.width), dev.n_vertices, two)
        with no_gc():
            return self._fn(ch, opaque(frame.camera.position), self.scene, self._geo,
                            self._vdata, self._table, dev, dl, _table(), static)
