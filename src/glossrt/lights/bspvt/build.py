"""Binary space partitioning visibility trees (BSPVT): precomputation.

Okuno & Iwasaki, "Interactive Rendering of Shadows for Polygonal Light using a Binary Space
Partitioning Visibility Tree" (sec. 3.2, eq. 3, Algorithm 1, Table 1). Every vertex of the
static geometry stores its visibility ``V`` (1: a ray in that direction escapes the occluders,
0: it is blocked) in a cube map, and every cube face's map is clustered by straight lines into
a binary tree whose leaves hold the mean visibility of their texels (the paper's ``v_i`` of
eq. 2). Shading (eq. 2: split the projected light polygon by the lines, weight each piece's
LTC integral by its leaf's mean visibility) lives elsewhere; this module builds and stores the
trees.

**Cube conventions**: :mod:`glossrt.lights.cubemap` (shared with the shading code and the
light maps of the highlights): texel ``(i, j)`` of face ``f`` is stored at
``vis[vertex, f, j, i]``.

**Tree format** (:class:`BSPVT`, flat arrays for all vertices together): ``lines`` float32
``(N, 3)`` holds ``(a, b, c)``, ``a^2 + b^2 = 1``, signed distance ``d(s, t) = a s + b t + c``;
``children`` int32 ``(N, 2)`` = [left ``{d < 0}``, right ``{d >= 0}``] where an entry ``>= 0``
is a node and an entry ``< 0`` is the leaf ``~entry``; ``leaf_value`` float32 ``(L,)``;
``roots`` int32 ``(V, 6)`` in the same encoding (a uniform face is a single leaf). Nodes and
leaves of one vertex are contiguous, faces in order, each face breadth first, so a child's
index is always larger than its parent's (the loader checks it: no cycles).

**Visibility** (:func:`visibility_cubemaps`): one ray per texel centre from ``p + offset n``
(``n`` the vertex normal), started a further ``mint`` along the ray, tested against the scene
without its emitting shapes (:func:`occluders`: the polygon light moves, and an area light
must not shadow itself). Directions below the tangent plane are traced like the others (they
mostly hit the vertex's own surface and read 0); shading clips the light at the horizon
anyway, and keeping them makes a face's map independent of the normal except through the
offset, with fewer mixed faces than a forced 0 along a tilted horizon would give.

**Trees** (:func:`build_trees`, Okuno & Iwasaki Algorithm 1). A cluster ``P`` (a set of texels
of one face) has the error ``e(P) = min(sum V, sum (1 - V))`` -- eq. 3 for a line that leaves
all of ``P`` on one side, with the better constant. A cluster with ``e <= epsilon`` (in
texels) is a leaf storing its mean ``V``; otherwise the line ``l`` minimising eq. 3,
``E(P, l) = sum_p (H0(d(p)) - V(p))^2`` over the texel centres ``p`` of ``P`` (``H0(x) = 1`` for
``x >= 0``), among lines that leave both sides non-empty, splits it. Two searches:

* ``"batched"`` (glossrt's): for each of ``A`` line-normal angles, the texel centres are sorted
  by their projection on the normal once per face resolution; each cluster keeps its texels in
  that order for every angle (children inherit it by a stable partition, as kd-tree builders
  keep presorted lists), so prefix sums of ``V`` give eq. 3 for *every* offset (the line goes
  half-way between consecutive projections) and both orientations at once, from the
  per-cluster minimum and maximum of ``2 O_k - k`` (``O_k`` the ones among the first ``k``
  texels): exact over offsets for each angle. The angles are ``pi m / A`` moved to the middle
  of the interval between the two critical angles around them (where two texel centres
  project equally; within ~1/R^2 rad), so no two centres project closer than ``TIE_TOL``
  texels and every line keeps half of that from every texel centre: float32 storage cannot
  flip a texel to the other side. ``angles="exact"`` takes one angle in *every* such interval:
  then the search is exact over all lines (``O(R^2)`` angles, 4912 at R = 64: for small ``R``
  and the tests). Work is vectorised over all clusters of many faces at once, level by level:
  without a leaf budget the tree does not depend on the order in which clusters with
  ``e > epsilon`` are split (a cluster's split depends on the cluster alone), so the
  level-synchronous build gives Algorithm 1's tree. The array work (the orders, prefix sums,
  per-cluster minima and maxima, texel sides, partition) runs in NumPy threads
  (``engine="numpy"``) or in Dr.Jit (``engine="drjit"``: the current variant's device, with
  global prefix sums and scatter-reductions; the same trees bit for bit).
* ``"nelder-mead"`` (the paper's): SciPy's Nelder-Mead over ``(angle, offset)`` of eq. 3
  (piecewise constant, so the simplex stops wherever it gets stuck -- as in the paper), from
  the best of 16 angles of the exact-offset search and from the cluster's two principal
  axes; clusters are popped from a priority queue by error (Algorithm 1 literally). Slow
  (Python per cluster): for comparisons on a few vertices.

Rules beyond the paper (it does not say): a split must reduce eq. 3 below ``e(P)``; when no
line does (an isolated texel inside a region of the other value cannot be cut off by one
line, nor can the texels along a straight cluster edge), ``stalled="split"`` (default) splits
the cluster anyway by the line that minimises the children's summed error and, among those,
cuts off the largest pure part (fewest texels left in impure children; searched over every
``FALLBACK_STRIDE``-th angle), so that with ``epsilon = 0`` every leaf ends up pure (exact
reconstruction at the texel centres); ``stalled="leaf"`` makes it a leaf (the literal rule,
inexact). On the teapot at R = 64 the fallback halves the leaves compared with a balanced
split (48 against 107 leaves per vertex). Depth is capped (``max_depth``, default 32; a capped leaf
may keep ``e > epsilon``; :meth:`BSPVT.stats` counts leaves with ``e > epsilon``).
``max_leaves`` (per face) stops splitting a face when it has that many leaves, popping
clusters by decreasing error (ties: shallower, then left before right) as Algorithm 1's
priority queue does; since a child's error never exceeds its parent's, the splits made are the
``max_leaves - 1`` largest-error splits of the unbounded tree, which is how the batched build
applies it.

Invariants: every leaf has ``e <= epsilon`` (unless it hit the depth cap, or stalled with
``stalled="leaf"``); then a leaf's texels deviate from its stored mean by
``sum |mean - V| = 2 n1 n0 / n <= 2 epsilon`` (``n1``/``n0`` its ones/zeros), and thresholding
the mean at 1/2 misclassifies ``e <= epsilon`` of them; with ``epsilon = 0`` the tree
reproduces the map exactly at the texel centres.

Table 1 of the paper (17K-vertex teapot: 2.7 min, 23.1 MB, 105.8 leaves per vertex at R = 64)
is reported by :meth:`BSPVT.stats`.
"""

from __future__ import annotations

import heapq
import json
import math
import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import NamedTuple

import drjit as dr
import numpy as np

from ...backend import mi
from ...errors import GlossrtError
from ...fileio import replacing
from ...jit import owned
from ...progress import Progress
from ..cubemap import (  # noqa: F401 - the cube conventions, shared with the light maps
    DEFAULT_RESOLUTION,
    _check_resolution,
    _face_axes,
    _texel_index,
    cube_coords,
    cube_dir,
    cube_directions,
    texel_centres,
)

__all__ = [
    "BSPVT",
    "DEFAULT_OFFSET",
    "FORMAT_VERSION",
    "Split",
    "best_split",
    "build_trees",
    "cube_coords",
    "cube_dir",
    "cube_directions",
    "occluders",
    "scene_vertices",
    "texel_centres",
    "visibility_cubemaps",
]

#: on-disk format version of :meth:`BSPVT.save`
FORMAT_VERSION = 1
#: default ray origin offset along the normal, relative to the occluders' bounding-box
#: diagonal. 1e-4 of the diagonal (0.85 mm for the 8.5 m occluders of ``polygon-light``) is
#: about 10^3 times float32's relative precision (6e-8; Embree's hit-distance error is a few
#: ulps of the coordinates) and 1/70 of the teapot's median triangle edge (5.7 cm at
#: ``teapot_n = 8``; 1/13 of its shortest 5 %): rays leave the vertex's own triangles cleanly
#: (with offset 0 the tests see a flat floor shadow itself), while contact shadows are lost
#: only within that distance. (glossrt's Monte Carlo shadow rays use the same 1e-4 scale.)
DEFAULT_OFFSET = 1e-4
#: ``mint`` (start distance along the ray) as a fraction of the offset
MINT_FRACTION = 1e-2
#: smallest gap (texel widths) between two texel centres' projections the search angles must
#: keep (lines lie half-way: >= TIE_TOL / 2 from every texel centre)
TIE_TOL = 1e-3
#: default number of line-normal angles of the batched search
DEFAULT_ANGLES = 64
#: the stalled-cluster fallback searches every FALLBACK_STRIDE-th angle
FALLBACK_STRIDE = 2
#: default depth cap
DEFAULT_MAX_DEPTH = 32
#: rays per ``ray_test`` batch (bounds memory: ~40 bytes of ray state each)
CHUNK_RAYS = 1 << 22
#: texels x angles per batched level step and thread (bounds memory: ~22 bytes each, ~90 MB)
CHUNK_WORK = 1 << 22
#: texels x angles per step of the Dr.Jit engine on the CPU (~20 bytes each, ~340 MB) and on
#: a GPU (~5 GB: fewer chunks, so fewer of the ~30 kernel launches per level and chunk;
#: chosen without a GPU to measure on)
CHUNK_WORK_DRJIT = 1 << 24
CHUNK_WORK_DRJIT_CUDA = 1 << 28
#: most worker threads of the batched build by default
MAX_THREADS = 8
#: array engines of the batched build
ENGINES = ("numpy", "drjit")

_NO_CUT = np.int64(1) << 62


# -- scene -----------------------------------------------------------------------------------

def occluders(scene: mi.Scene) -> mi.Scene:
    """The scene's shapes without the emitting ones (area lights), as a new scene for shadow
    rays. Meshes are copied (positions and faces); other shapes (analytic spheres, instances
    with the shape groups they place, ...) are shared with ``scene`` (their ids are kept:
    Mitsuba renames objects put in a scene dict). The new scene does not follow later edits
    of ``scene`` (moving objects): visibility is precomputed for the static geometry."""
    from ...scenes import children, stable_shapes

    shapes = {}
    if any(s.class_name() == "Instance" for s in scene.shapes()):
        # an instance refers to its shape group by key: the groups go along under theirs
        for key, group in children(scene).items():
            if isinstance(group, mi.Shape) and group.class_name().startswith("ShapeGroup"):
                shapes[key] = group
    for i, s in enumerate(stable_shapes(scene)):
        if s.is_emitter():
            continue
        if isinstance(s, mi.Mesh):
            m = mi.Mesh(f"occluder_{i}", s.vertex_count(), s.face_count())
            params = mi.traverse(m)
            params["vertex_positions"] = type(s.vertex_positions_buffer())(
                s.vertex_positions_buffer())
            params["faces"] = type(s.faces_buffer())(s.faces_buffer())
            params.update()
            shapes[f"occluder_{i}"] = m
        else:
            shapes[f"occluder_{i}"] = s
    ids = {k: s.id() for k, s in shapes.items()}
    try:
        return mi.load_dict({"type": "scene", **shapes})
    finally:
        for k, s in shapes.items():
            s.set_id(ids[k])


def _mesh_normals(mesh, pos: np.ndarray) -> np.ndarray:
    if mesh.has_vertex_normals():
        nrm = np.array(mesh.vertex_normals_buffer(), dtype=np.float64).reshape(-1, 3)
    else:
        faces = np.array(mesh.faces_buffer(), dtype=np.int64).reshape(-1, 3)
        fn = np.cross(pos[faces[:, 1]] - pos[faces[:, 0]], pos[faces[:, 2]] - pos[faces[:, 0]])
        nrm = np.zeros_like(pos)
        for c in range(3):  # area-weighted face normals summed at each corner
            np.add.at(nrm, faces[:, c], fn)
    length = np.linalg.norm(nrm, axis=1, keepdims=True)
    return np.where(length > 0, nrm / np.where(length > 0, length, 1.0), 0.0)


def scene_vertices(scene: mi.Scene) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(positions (V, 3), normals (V, 3), offsets (S,))`` (float64, float64, int64) of the
    vertices of the scene's non-emitting ``mi.Mesh`` shapes, shapes in glossrt's stable order
    (:func:`glossrt.scenes.stable_shapes`, emitters and non-meshes skipped); ``offsets[i]`` is
    the index of the ``i``-th such mesh's first vertex. Analytic shapes (Mitsuba's
    ``sphere``, ``cylinder``, ...) have no vertices and contribute none, though they still
    occlude. Normals are the mesh's vertex normals (``vertex_normals_buffer``) or, for meshes
    without them, area-weighted averages of the adjacent face normals (zero for a vertex on
    no face), unit length, in world space like the positions."""
    from ...scenes import stable_shapes

    pos, nrm, offsets, total = [], [], [], 0
    for s in stable_shapes(scene):
        if s.is_emitter() or not isinstance(s, mi.Mesh):
            continue
        p = np.array(s.vertex_positions_buffer(), dtype=np.float64).reshape(-1, 3)
        offsets.append(total)
        total += len(p)
        pos.append(p)
        nrm.append(_mesh_normals(s, p))
    if not pos:
        return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, np.int64)
    return np.concatenate(pos), np.concatenate(nrm), np.asarray(offsets, np.int64)


def _check_points(name: str, a, n: int | None = None) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        raise GlossrtError(f"{name} must have shape (V, 3), got {a.shape}")
    if n is not None and len(a) != n:
        raise GlossrtError(f"{name} has {len(a)} rows, expected {n}")
    if not np.all(np.isfinite(a)):
        raise GlossrtError(f"{name} contain NaN or Inf")
    return a


def _scene_diagonal(scene: mi.Scene) -> float:
    b = scene.bbox()
    lo = np.array([float(b.min[i]) for i in range(3)])
    hi = np.array([float(b.max[i]) for i in range(3)])
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) and np.all(hi >= lo)):
        return 1.0  # empty scene: nothing to hit, any offset will do
    return float(np.linalg.norm(hi - lo))


def visibility_cubemaps(scene: mi.Scene, positions, normals,
                        resolution: int = DEFAULT_RESOLUTION, offset: float | None = None,
                        progress: bool = True, mint: float | None = None,
                        chunk_rays: int = CHUNK_RAYS) -> np.ndarray:
    """Per-vertex visibility cube maps, ``uint8 (V, 6, R, R)`` indexed ``[vertex, face, j, i]``
    (1: the ray towards the texel centre escapes, 0: blocked).

    ``scene``: the occluders; a scene with emitting shapes is first reduced by
    :func:`occluders`. Rays start at ``p + offset n + mint d`` (``d`` the unit texel
    direction); ``offset`` defaults to :data:`DEFAULT_OFFSET` times the occluders'
    bounding-box diagonal, ``mint`` to :data:`MINT_FRACTION` of the offset. Directions below
    the tangent plane are traced too (see the module docstring). Rays are tested with
    ``scene.ray_test`` in batches of about ``chunk_rays`` (whole vertices per batch)."""
    r = _check_resolution(resolution)
    pos = _check_points("positions", positions)
    nrm = _check_points("normals", normals, len(pos))
    if any(s.is_emitter() for s in scene.shapes()):
        scene = occluders(scene)
    diag = _scene_diagonal(scene)
    offset = DEFAULT_OFFSET * diag if offset is None else float(offset)
    mint = MINT_FRACTION * offset if mint is None else float(mint)
    if not (math.isfinite(offset) and offset >= 0 and math.isfinite(mint) and mint >= 0):
        raise GlossrtError(f"offset and mint must be finite and >= 0, got {offset}, {mint}")
    texels = 6 * r * r
    out = np.zeros((len(pos), 6, r, r), np.uint8)
    if len(pos) == 0:
        return out
    dirs = cube_directions(r).reshape(-1, 3)
    table = mi.Vector3f(*[mi.Float(dirs[:, c].astype(np.float32)) for c in range(3)])
    off, mt = dr.opaque(mi.Float, offset), dr.opaque(mi.Float, mint)
    per = max(1, int(chunk_rays) // texels)
    with Progress(len(pos), f"visibility {r}x{r}", enabled=progress) as bar:
        for v0 in range(0, len(pos), per):
            v1 = min(len(pos), v0 + per)
            p = mi.Point3f(*[mi.Float(pos[v0:v1, c].astype(np.float32)) for c in range(3)])
            n = mi.Vector3f(*[mi.Float(nrm[v0:v1, c].astype(np.float32)) for c in range(3)])
            idx = dr.arange(mi.UInt32, (v1 - v0) * texels)
            vid = idx // texels
            d = dr.gather(mi.Vector3f, table, idx - vid * texels)
            o = dr.gather(mi.Point3f, p, vid) + dr.gather(mi.Vector3f, n, vid) * off + d * mt
            hit = scene.ray_test(mi.Ray3f(o, d))
            out[v0:v1] = (~np.array(hit, dtype=bool)).reshape(v1 - v0, 6, r, r)
            bar.update(v1)
    return out


# -- the tree --------------------------------------------------------------------------------

def _bad(msg: str) -> GlossrtError:
    return GlossrtError(f"invalid BSPVT: {msg}")


@dataclass
class BSPVT:
    """Per-vertex, per-face visibility trees in flat arrays (format in the module docstring).

    ``info`` holds build details (method, angles, build seconds, ...) for :meth:`stats`;
    ``source`` the file the trees were loaded from (not saved)."""

    lines: np.ndarray
    children: np.ndarray
    leaf_value: np.ndarray
    roots: np.ndarray
    resolution: int
    epsilon: float
    positions: np.ndarray
    normals: np.ndarray
    info: dict = field(default_factory=dict)
    #: the file :meth:`load` read the trees from ("" for trees built in memory); for messages
    source: str = field(default="", compare=False, repr=False)

    def __post_init__(self) -> None:
        self.lines = np.ascontiguousarray(self.lines, np.float32).reshape(-1, 3)
        self.children = np.ascontiguousarray(self.children, np.int32).reshape(-1, 2)
        self.leaf_value = np.ascontiguousarray(self.leaf_value, np.float32).reshape(-1)
        self.roots = np.ascontiguousarray(self.roots, np.int32)
        self.positions = np.ascontiguousarray(self.positions, np.float32)
        self.normals = np.ascontiguousarray(self.normals, np.float32)
        self.resolution = int(self.resolution)
        self.epsilon = float(self.epsilon)
        self.info = dict(self.info)
        self.validate()

    # -- checks ------------------------------------------------------------------------------
    def validate(self) -> None:
        """Raise :class:`GlossrtError` unless the arrays form valid trees: shapes, finite unit
        lines, child/root indices in range, children after their parents (acyclic), every
        node and leaf referenced exactly once, leaf values in [0, 1]."""
        n, leaves = len(self.lines), len(self.leaf_value)
        if self.roots.ndim != 2 or self.roots.shape[1] != 6:
            raise _bad(f"roots must have shape (V, 6), got {self.roots.shape}")
        nv = len(self.roots)
        for name in ("positions", "normals"):
            a = getattr(self, name)
            if a.shape != (nv, 3):
                raise _bad(f"{name} must have shape ({nv}, 3), got {a.shape}")
            if not np.all(np.isfinite(a)):
                raise _bad(f"{name} contain NaN or Inf")
        if len(self.children) != n:
            raise _bad(f"{n} lines but {len(self.children)} children rows")
        if not (1 <= self.resolution <= 1024):
            raise _bad(f"resolution {self.resolution} out of range")
        if not (math.isfinite(self.epsilon) and self.epsilon >= 0):
            raise _bad(f"epsilon must be finite and >= 0, got {self.epsilon}")
        if not np.all(np.isfinite(self.lines)):
            raise _bad("lines contain NaN or Inf")
        if n and np.max(np.abs(self.lines[:, 0] ** 2 + self.lines[:, 1] ** 2 - 1.0)) > 1e-4:
            raise _bad("line normals (a, b) are not unit length")
        if not np.all((self.leaf_value >= 0) & (self.leaf_value <= 1)):
            raise _bad("leaf values outside [0, 1] (or NaN)")
        refs = np.concatenate([self.roots.ravel(), self.children.ravel()])
        node_ref, leaf_ref = refs[refs >= 0], ~refs[refs < 0]
        if np.any(node_ref >= n) or np.any(leaf_ref >= leaves):
            raise _bad("child or root index out of range")
        parent = np.repeat(np.arange(n), 2)[self.children.ravel() >= 0]
        if np.any(self.children.ravel()[self.children.ravel() >= 0] <= parent):
            raise _bad("a child node does not come after its parent (cycle?)")
        if (np.bincount(node_ref, minlength=n).max(initial=1) > 1
                or np.bincount(leaf_ref, minlength=leaves).min(initial=1) != 1
                or np.bincount(leaf_ref, minlength=leaves).max(initial=1) != 1):
            raise _bad("every node and leaf must be referenced exactly once")
        if n and np.bincount(node_ref, minlength=n).min() != 1:
            raise _bad("unreferenced nodes")

    # -- queries -----------------------------------------------------------------------------
    @property
    def vertex_count(self) -> int:
        return len(self.roots)

    def _walk(self, entry: np.ndarray, s: np.ndarray, t: np.ndarray) -> np.ndarray:
        """Leaf indices reached from tree entries ``entry`` (root encodings) at ``(s, t)``."""
        entry = entry.astype(np.int64).copy()
        lines = self.lines.astype(np.float64)
        for _ in range(len(self.lines) + 1):
            inner = np.nonzero(entry >= 0)[0]
            if len(inner) == 0:
                break
            node = entry[inner]
            ln = lines[node]
            d = ln[:, 0] * s[inner] + ln[:, 1] * t[inner] + ln[:, 2]
            entry[inner] = self.children[node, (d >= 0).astype(np.int64)]
        return ~entry

    def _check_vertex(self, vertex) -> int:
        v = int(vertex)
        if v != vertex or not (0 <= v < self.vertex_count):
            raise GlossrtError(f"vertex index {vertex} out of range 0..{self.vertex_count - 1}")
        return v

    def evaluate(self, vertex: int, dirs) -> np.ndarray:
        """The tree's piecewise-constant visibility (float32, shape ``dirs.shape[:-1]``) of
        vertex ``vertex`` for world directions ``dirs`` (..., 3)."""
        v = self._check_vertex(vertex)
        face, s, t = cube_coords(dirs)
        shape = face.shape
        leaf = self._walk(self.roots[v][face.ravel()], s.ravel(), t.ravel())
        return self.leaf_value[leaf].reshape(shape)

    def leaf_map(self, vertex: int) -> np.ndarray:
        """``(6, R, R)`` int64: the leaf each texel centre of vertex ``vertex`` falls in."""
        v = self._check_vertex(vertex)
        r = self.resolution
        c = texel_centres(r)
        face = np.repeat(np.arange(6), r * r)
        s = np.tile(c, 6 * r)
        t = np.tile(np.repeat(c, r), 6)
        return self._walk(self.roots[v][face], s, t).reshape(6, r, r)

    def reconstruct(self, vertex: int) -> np.ndarray:
        """``(6, R, R)`` float32: the leaf values at the texel centres of vertex ``vertex``."""
        return self.leaf_value[self.leaf_map(vertex)]

    def stats(self) -> dict:
        """Table 1 of the paper: vertices, build seconds, data size (the tree arrays: lines,
        children, leaf values, roots; bytes and MB), leaves and nodes per vertex (mean), plus
        resolution, epsilon, node and leaf totals and leaves with ``e > epsilon``."""
        nv = max(self.vertex_count, 1)
        size = sum(a.nbytes for a in (self.lines, self.children, self.leaf_value, self.roots))
        return {
            "vertices": self.vertex_count,
            "build_seconds": self.info.get("build_seconds"),
            "data_bytes": int(size),
            "data_mb": size / 1e6,
            "leaves_per_vertex": len(self.leaf_value) / nv,
            "nodes_per_vertex": len(self.lines) / nv,
            "nodes": len(self.lines),
            "leaves": len(self.leaf_value),
            "resolution": self.resolution,
            "epsilon": self.epsilon,
            "method": self.info.get("method"),
            "leaves_over_epsilon": self.info.get("leaves_over_epsilon"),
            "max_depth": self.info.get("depth"),
        }

    # -- files -------------------------------------------------------------------------------
    def save(self, path: str) -> None:
        """Write a compressed ``.npz`` (format version :data:`FORMAT_VERSION`) atomically: into
        a temporary file in the same folder, then renamed over ``path`` (an interrupted save
        leaves ``path`` as it was; the temporary file is removed)."""
        with replacing(path) as tmp, open(tmp, "wb") as f:
            np.savez_compressed(
                f, version=np.int32(FORMAT_VERSION), lines=self.lines,
                children=self.children, leaf_value=self.leaf_value, roots=self.roots,
                resolution=np.int32(self.resolution), epsilon=np.float64(self.epsilon),
                positions=self.positions, normals=self.normals,
                info=np.array(json.dumps(self.info)))
            f.flush()
            os.fsync(f.fileno())

    @classmethod
    def load(cls, path: str) -> BSPVT:
        """Read a file written by :meth:`save`; :class:`GlossrtError` (one line naming the
        file) if it is missing, unreadable, not a tree file, of another version or not valid
        trees."""
        path = os.fspath(path)
        not_trees = f"{path}: not a BSPVT tree file written by `glossrt bspvt build`"
        try:
            with open(path, "rb") as f:
                head = f.read(8)
        except FileNotFoundError:
            raise GlossrtError(f"BSPVT file not found: {path}") from None
        except IsADirectoryError:
            raise GlossrtError(f"{not_trees} (it is a directory)") from None
        except OSError as e:
            raise GlossrtError(f"{path}: cannot read the BSPVT file ({e.strerror or e})") \
                from None
        if not head.startswith(b"PK"):  # .npz files are zip archives
            what = ("an OpenEXR image" if head.startswith(b"\x76\x2f\x31\x01")
                    else "a single NumPy array (.npy)" if head.startswith(b"\x93NUMPY")
                    else "empty" if not head else "not an .npz archive")
            raise GlossrtError(f"{not_trees} (it is {what})")
        try:
            with np.load(path, allow_pickle=False) as z:
                data = {k: z[k] for k in z.files}
        except ValueError as e:
            if "pickle" in str(e):
                raise GlossrtError(f"{not_trees} (it holds pickled Python objects)") from None
            raise GlossrtError(f"{not_trees} (unreadable .npz: {_one_line(e)})") from None
        except Exception as e:
            raise GlossrtError(f"{not_trees} (unreadable .npz: {_one_line(e)})") from None
        need = ("version", "lines", "children", "leaf_value", "roots", "resolution", "epsilon",
                "positions", "normals")
        missing = [k for k in need if k not in data]
        if missing:
            raise GlossrtError(f"{not_trees} (missing {', '.join(missing)})")
        if data["version"].shape != () or int(data["version"]) != FORMAT_VERSION:
            raise GlossrtError(f"{path}: BSPVT format version {data['version']}, "
                               f"expected {FORMAT_VERSION}")
        expect = {"lines": np.float32, "children": np.int32, "leaf_value": np.float32,
                  "roots": np.int32, "positions": np.float32, "normals": np.float32}
        for k, dt in expect.items():
            if data[k].dtype != dt:
                raise GlossrtError(f"{path}: {k} has dtype {data[k].dtype}, expected "
                                   f"{np.dtype(dt)}")
        try:
            info = json.loads(str(data["info"])) if "info" in data else {}
        except ValueError:
            raise GlossrtError(f"{path}: unreadable info field") from None
        try:
            return cls(lines=data["lines"], children=data["children"],
                       leaf_value=data["leaf_value"], roots=data["roots"],
                       resolution=int(data["resolution"]), epsilon=float(data["epsilon"]),
                       positions=data["positions"], normals=data["normals"], info=info,
                       source=path)
        except GlossrtError as e:
            raise GlossrtError(f"{path}: {e}") from None
        except (ValueError, TypeError) as e:
            raise GlossrtError(f"{path}: invalid BSPVT arrays ({e})") from None


def _one_line(e: BaseException) -> str:
    text = " ".join(str(e).split())
    return text or type(e).__name__


# -- batched split search --------------------------------------------------------------------

def _critical_angles(r: int) -> np.ndarray:
    """Sorted angles in [0, pi) of line normals perpendicular to the difference of two texel
    centres of an ``r`` x ``r`` face: where the projection order of the centres changes."""
    di, dj = np.meshgrid(np.arange(-(r - 1), r), np.arange(0, r), indexing="ij")
    keep = ((dj > 0) | ((dj == 0) & (di > 0))) & (np.gcd(di, dj) == 1)
    return np.sort(np.mod(np.arctan2(dj[keep], di[keep]) + 0.5 * np.pi, np.pi))


class _Angles:
    """Line-normal angles of the batched search for ``r`` x ``r`` faces, with the texel
    centres' projections (texel units) and their order per angle (shared by all clusters).

    Every angle lies in the middle of an interval between consecutive critical angles
    (:func:`_critical_angles`): ``"exact"`` takes all of them (every partition of texel
    centres by a line is realised at one of them), ``A`` (an integer) snaps ``pi m / A`` to
    the middle of its interval (within ~1/R^2 rad of it). No two centres then project closer
    than :data:`TIE_TOL` texels (checked), so no ties need handling and every line put
    half-way between two projections keeps that margin."""

    _cache: dict = {}

    def __init__(self, r: int, angles):
        crit = _critical_angles(r)
        if len(crit) == 0:
            mids = np.zeros(1)
        else:
            mids = np.mod(0.5 * (crit + np.append(crit[1:], crit[0] + np.pi)), np.pi)
        if isinstance(angles, str):
            if angles != "exact":
                raise GlossrtError(f"angles must be a positive integer or 'exact', got {angles!r}")
            theta = mids
        else:
            try:
                a = int(angles)
            except (TypeError, ValueError):
                a = 0
            if a != angles or a < 1:
                raise GlossrtError(f"angles must be a positive integer or 'exact', got {angles!r}")
            idx = np.searchsorted(crit, np.pi * np.arange(a) / a, side="right") - 1
            theta = np.unique(mids[np.mod(idx, len(mids))])
        self.r, self.theta = r, theta
        self.cos, self.sin = np.cos(theta), np.sin(theta)
        tau = np.arange(r * r)
        self.proj = self.cos[:, None] * (tau % r)[None, :] + self.sin[:, None] * (tau // r)[None]
        self.perm = np.argsort(self.proj, axis=1, kind="stable").astype(np.int32)
        if r > 1:
            gap = np.diff(np.take_along_axis(self.proj, self.perm, 1), axis=1).min()
            if gap < TIE_TOL:
                raise GlossrtError(f"resolution {r} is too fine for the batched BSPVT search "
                                   f"(texel projections {gap:.1e} texels apart)")

    @classmethod
    def get(cls, r: int, angles) -> _Angles:
        key = (r, angles)
        if key not in cls._cache:
            if len(cls._cache) > 8:
                cls._cache.clear()
            cls._cache[key] = cls(r, angles)
        return cls._cache[key]

    def line(self, a: np.ndarray, lo: np.ndarray, hi: np.ndarray, flip: np.ndarray) -> np.ndarray:
        """Lines ``(G, 3)`` float64 in ``(s, t)`` for angle indices ``a`` cutting half-way
        between the projections of texels ``lo`` and ``hi`` (indices ``j R + i``; ``lo``
        projects lower), with the higher projections on the right (``d >= 0``) side, or on
        the left where ``flip``."""
        r = self.r
        ca, sa = self.cos[a], self.sin[a]
        cut = 0.5 * (self.proj[a, lo] + self.proj[a, hi])
        # ca i + sa j - cut with i = (r (s + 1) - 1) / 2, divided by r / 2
        c = (ca + sa) * (r - 1.0) / r - 2.0 * cut / r
        ln = np.stack([ca, sa, c], -1)
        return np.where(flip[:, None], -ln, ln)


def _segment_ids(length: np.ndarray) -> np.ndarray:
    return np.repeat(np.arange(len(length), dtype=np.int64), length)


def _ranges(start: np.ndarray, length: np.ndarray) -> np.ndarray:
    """Concatenation of ``arange(start[g], start[g] + length[g])``."""
    total = int(length.sum())
    if total == 0:
        return np.zeros(0, np.int64)
    excl = np.cumsum(length) - length
    return np.repeat(start - excl, length) + np.arange(total)


class _Work:
    """Buffers reused from level to level of a chunk (fresh large arrays cost page faults:
    a new array made NumPy's in-place-able steps several times slower here)."""

    def __init__(self):
        self.bufs: dict[str, np.ndarray] = {}

    def get(self, name: str, shape: tuple, dtype) -> np.ndarray:
        size = int(np.prod(shape))
        b = self.bufs.get(name)
        if b is None or b.size < size or b.dtype != dtype:
            b = self.bufs[name] = np.empty(max(size, 1), dtype)
        return b[:size].reshape(shape)


def _scan(vals2: np.ndarray, order: np.ndarray, start: np.ndarray, work: _Work | None = None):
    """Prefix sums of every angle's order: ``y = 2 C - p`` (``C`` the ones up to and
    including column ``p``) and ``off`` (A, G) such that ``x = y + off[segment] = 2 O_k - k``
    with ``O_k`` the ones among a segment's first ``k`` texels. ``vals2`` = 2 V (int32)."""
    work = work or _Work()
    y = work.get("y", order.shape, np.int32)
    np.take(vals2, order, out=y, mode="clip")
    first = y[:, start]  # (a copy) 2 V of each segment's first texel
    np.cumsum(y, axis=1, out=y)
    before = y[:, start] - first  # 2 x the ones before each segment
    y -= np.arange(order.shape[1], dtype=np.int32)
    return y, (start - 1)[None, :] - before


def _best_splits(vals2, order, start, length, ones, nontrivial: bool = False,
                 work: _Work | None = None):
    """Eq. 3 minimised over the angles and offsets, per segment (cluster) of ``order``.

    With the segment's first ``k`` texels (in an angle's order) on the low side of a line,
    Okuno & Iwasaki's eq. 3 is ``E+ = O_k + (Z - (k - O_k)) = x + Z`` when the high side is
    the right one (``H0 = 1``) and ``E- = (k - O_k) + (O - O_k) = O - x`` when it is the left
    one, ``x = 2 O_k - k``, ``O``/``Z`` the segment's ones/zeros: both orientations and all
    offsets follow from the per-segment minimum and maximum of ``x``. (``k = n``, everything
    on one side, gives ``O`` and ``Z``, never less than ``e(P)``, so it needs no masking:
    a split is only made when it brings eq. 3 below ``e(P)``.)

    Returns ``(E, angle, column, flip)``: the minimum, its angle index, the segment's last
    column (in that angle's order) on the low side, and whether the low side is the right
    one. ``nontrivial``: exclude ``k = n`` (for :func:`best_split`, which wants the minimum
    even when it is not below ``e(P)``; every segment must then have two texels or more)."""
    y, off = _scan(vals2, order, start, work)
    g = np.arange(len(start))
    zeros_tot = (length - ones)[None, :]
    y_lo, y_hi = y, y
    if nontrivial:
        last = start + length - 1
        y_lo, y_hi = y.copy(), y.copy()
        y_lo[:, last], y_hi[:, last] = np.iinfo(np.int32).max, np.iinfo(np.int32).min
    e_plus = np.minimum.reduceat(y_lo, start, axis=1) + off + zeros_tot  # (A, G)
    e_minus = ones[None, :] - (np.maximum.reduceat(y_hi, start, axis=1) + off)
    a_p, a_m = np.argmin(e_plus, 0), np.argmin(e_minus, 0)
    vp, vm = e_plus[a_p, g], e_minus[a_m, g]
    flip = vm < vp
    a = np.where(flip, a_m, a_p)
    e = np.where(flip, vm, vp)
    # the first column of the chosen angle where x reaches its extreme
    target = np.where(flip, ones - vm, vp - zeros_tot[0]) - off[a, g]
    seg = _segment_ids(length)
    cols = np.arange(order.shape[1])
    hit = y[a[seg], cols] == target[seg]
    if nontrivial:
        hit[start + length - 1] = False
    col = np.minimum.reduceat(np.where(hit, cols, order.shape[1]), start)
    return e, a, col, flip


def _fallback_splits(vals2, order, start, length, ones):
    """For stalled clusters: the cut minimising the children's summed error ``e(P_L) +
    e(P_R)``, then the number of texels in impure children (cut off the largest pure part).
    Returns ``(key, angle, column)``, key :data:`_NO_CUT` where no cut leaves both sides
    non-empty."""
    v = np.take(vals2, order, mode="clip")
    o = np.cumsum(v, axis=1)
    o -= np.repeat(o[:, start] - v[:, start], length, axis=1)
    o >>= 1  # ones among the segment's first k texels
    k = (np.arange(order.shape[1]) + 1 - np.repeat(start, length)).astype(np.int32)
    n = np.repeat(length, length).astype(np.int32)
    ones_s = np.repeat(ones, length).astype(np.int32)
    z_l = k - o
    e_l = np.minimum(o, z_l)
    e_r = np.minimum(ones_s - o, (n - ones_s) - z_l)
    key = e_l + e_r
    key *= 2 * int(length.max()) + 1
    key += (e_l > 0) * k
    key += (e_r > 0) * (n - k)
    key[:, start + length - 1] = np.iinfo(np.int32).max
    best = np.minimum.reduceat(key, start, axis=1)
    a = np.argmin(best, 0)
    val = best[a, np.arange(len(start))].astype(np.int64)
    val[val == np.iinfo(np.int32).max] = _NO_CUT
    seg = _segment_ids(length)
    cols = np.arange(order.shape[1])
    col = np.minimum.reduceat(np.where(key[a[seg], cols] == val[seg], cols, len(cols)), start)
    return val, a, col


class Split(NamedTuple):
    """A cluster's best split: ``line`` (a, b, c) float64 and its eq.-3 error in texels
    (``None`` and -1 when no line leaves both sides non-empty)."""

    line: np.ndarray | None
    error: int


def _check_map(vmap) -> tuple[np.ndarray, int]:
    m = np.asarray(vmap)
    if m.ndim != 2 or m.shape[0] != m.shape[1] or m.shape[0] < 1:
        raise GlossrtError(f"a visibility map must have shape (R, R), got {m.shape}")
    return _binary(m, "visibility map").reshape(-1), m.shape[0]


def _binary(a: np.ndarray, name: str) -> np.ndarray:
    if a.dtype == bool:
        return a.astype(np.uint8)
    if not np.issubdtype(a.dtype, np.number):
        raise GlossrtError(f"{name} must be numeric, got dtype {a.dtype}")
    if np.issubdtype(a.dtype, np.floating) and not np.all(np.isfinite(a)):
        raise GlossrtError(f"{name} contains NaN or Inf")
    if not np.all((a == 0) | (a == 1)):
        raise GlossrtError(f"{name} must hold only 0 (blocked) and 1 (visible)")
    return a.astype(np.uint8)


def best_split(vmap, mask=None, method: str = "batched", angles=DEFAULT_ANGLES) -> Split:
    """The line minimising eq. 3 (Okuno & Iwasaki) over the texels of the ``(R, R)`` map
    ``vmap`` (``[j, i]``, 0/1) selected by ``mask`` (default: all), among lines leaving both
    sides non-empty, with the search of :func:`build_trees` (``method``, ``angles``)."""
    vals, r = _check_map(vmap)
    sel = np.ones(r * r, bool) if mask is None else np.asarray(mask, bool).reshape(-1)
    if sel.shape != (r * r,):
        raise GlossrtError(f"mask must have shape ({r}, {r})")
    if method == "nelder-mead":
        tau = np.nonzero(sel)[0]
        c = texel_centres(r)
        line, err = _nm_line(c[tau % r], c[tau // r], vals[tau].astype(np.int64), r)
        return Split(line, err)
    if method != "batched":
        raise GlossrtError(f"unknown split method {method!r} (batched or nelder-mead)")
    ang = _Angles.get(r, angles)
    order, start, length, ones = _cluster_lists(ang, sel, vals)
    if length[0] < 2:
        return Split(None, -1)
    e, a, col, flip = _best_splits(2 * vals.astype(np.int32), order, start, length, ones,
                                   nontrivial=True)
    line = ang.line(a, order[a, col], order[a, col + 1], flip)
    return Split(line[0], int(e[0]))


def _cluster_lists(ang: _Angles, sel: np.ndarray, vals: np.ndarray):
    """One cluster (texels ``sel`` of one face) as a single segment of presorted lists."""
    keep = sel[ang.perm]
    n = int(sel.sum())
    order = ang.perm[keep].reshape(len(ang.theta), n).astype(np.intp)
    return order, np.zeros(1, np.int64), np.array([n], np.int64), np.array([int(vals[sel].sum())])


def _fallback_line(sel: np.ndarray, vals: np.ndarray, r: int) -> np.ndarray | None:
    """The stalled-cluster split of the batched build (:func:`_fallback_splits`)."""
    ang = _Angles.get(r, DEFAULT_ANGLES)
    order, start, length, ones = _cluster_lists(ang, sel, vals)
    key, a, col = _fallback_splits(2 * vals.astype(np.int32), order, start, length, ones)
    if key[0] >= _NO_CUT:
        return None
    return ang.line(a, order[a, col], order[a, col + 1], np.zeros(1, bool))[0]


# -- Nelder-Mead split search (the paper's) --------------------------------------------------

def _eq3(s, t, v, line) -> int:
    """Okuno & Iwasaki, eq. 3: sum_p (H0(d(p)) - V(p))^2 for binary V."""
    d = line[0] * s + line[1] * t + line[2]
    return int(np.count_nonzero((d >= 0) != (v > 0)))


def _snap(s, t, line) -> np.ndarray | None:
    """The same partition with the line half-way between the nearest texels of each side
    (None when a side is empty or the gap is below the tie tolerance)."""
    p = line[0] * s + line[1] * t
    right = p + line[2] >= 0
    if right.all() or not right.any():
        return None
    lo, hi = p[~right].max(), p[right].min()
    if hi - lo < 0:  # cannot happen for a straight line
        return None
    return np.array([line[0], line[1], -0.5 * (lo + hi)])


def _nm_line(s, t, v, r: int):
    """Nelder-Mead over (angle, offset) of eq. 3 from a few starts (the best of 16 angles of
    the exact-offset search, and the two principal axes through the centroid)."""
    from scipy.optimize import minimize

    n = len(s)
    if n < 2:
        return None, -1
    starts = []
    for th in np.pi * np.arange(16) / 16:  # coarse exact-offset scan for a start
        p = np.cos(th) * s + np.sin(th) * t
        o = np.argsort(p, kind="stable")
        cs = np.cumsum(v[o])
        k = np.arange(1, n + 1)
        e = np.minimum(2 * cs - k + (n - v.sum()), v.sum() - (2 * cs - k))[:-1]
        if len(e):
            j = int(np.argmin(e))
            flip = (v.sum() - (2 * cs[j] - j - 1)) < (2 * cs[j] - j - 1 + (n - v.sum()))
            sign = -1.0 if flip else 1.0
            starts.append((e[j], th + (np.pi if flip else 0.0),
                           -sign * 0.5 * (p[o[j]] + p[o[min(j + 1, n - 1)]])))
    starts.sort(key=lambda z: z[0])
    x0s = [np.array(starts[0][1:])] if starts else []
    xy = np.stack([s, t], 1)
    cov = np.cov(xy.T) if n > 2 else np.eye(2)
    _, vecs = np.linalg.eigh(np.atleast_2d(cov))
    centre = xy.mean(0)
    for vec in vecs.T:
        th = math.atan2(vec[1], vec[0])
        x0s.append(np.array([th, -(math.cos(th) * centre[0] + math.sin(th) * centre[1])]))

    def obj(x):
        return _eq3(s, t, v, (math.cos(x[0]), math.sin(x[0]), x[1]))

    best_line, best_e = None, 4 * r * r + 1
    step = 2.0 / r
    for x0 in x0s:
        simplex = np.array([x0, x0 + [np.pi / 16, 0.0], x0 + [0.0, 2 * step]])
        res = minimize(obj, x0, method="Nelder-Mead",
                       options={"initial_simplex": simplex, "xatol": 1e-4, "fatol": 0.5,
                                "maxiter": 400})
        line = _snap(s, t, np.array([math.cos(res.x[0]), math.sin(res.x[0]), res.x[1]]))
        if line is None:
            continue
        e = _eq3(s, t, v, line.astype(np.float32).astype(np.float64))
        if e < best_e:
            best_line, best_e = line, e
    return best_line, (best_e if best_line is not None else -1)


# -- tree building ---------------------------------------------------------------------------

class _Clusters:
    """Growing table of the clusters of a build (each becomes a node or a leaf)."""

    KEYS = ("id", "map", "code", "n", "ones", "parent", "side")

    def __init__(self, first_id: int = 0):
        self.parts: list[dict] = []
        self.count = first_id

    def add(self, map_id, code, n, ones, parent, side) -> np.ndarray:
        ids = np.arange(self.count, self.count + len(map_id), dtype=np.int64)
        self.count += len(map_id)
        vals = (ids, map_id, code, n, ones, parent, side)
        self.parts.append({k: np.asarray(v, np.int64) for k, v in zip(self.KEYS, vals,
                                                                       strict=True)})
        return ids

    def table(self) -> dict:
        return {k: np.concatenate([p[k] for p in self.parts]) if self.parts
                else np.zeros(0, np.int64) for k in self.KEYS}


def _err(n, ones):
    return np.minimum(ones, n - ones)


class _NpOps:
    """The batched build's array work on one chunk in NumPy (:func:`_build_chunk` keeps the
    per-cluster bookkeeping): every angle's texel order (``order`` (A, N), the clusters'
    texels as contiguous segments in every row), Okuno & Iwasaki's eq. 3 over it, the texels'
    sides of the chosen lines and the stable partition into the children's segments."""

    def __init__(self, vals2: np.ndarray, ang: _Angles, m: int):
        r2 = ang.r * ang.r
        self.vals2, self.ang, self.work, self.spare = vals2, ang, _Work(), "order1"
        self.order = self.work.get("order0", (len(ang.theta), m * r2), np.intp)
        np.add(ang.perm[:, None, :], (np.arange(m, dtype=np.intp) * r2)[None, :, None],
               out=self.order.reshape(len(ang.theta), m, r2))

    def best_splits(self, start, length, ones):
        return _best_splits(self.vals2, self.order, start, length, ones, work=self.work)

    def fallback(self, start, length, ones, sub, rows, cols):
        """:func:`_fallback_splits` of the stalled segments ``sub`` over the angles
        ``rows`` (their columns ``cols``): ``(key, row index, block column)``."""
        return _fallback_splits(self.vals2, self.order[rows[:, None], cols[None, :]],
                                np.cumsum(length[sub]) - length[sub], length[sub], ones[sub])

    def pairs(self, a: np.ndarray, col: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The texels at columns ``col`` and ``col + 1`` of rows ``a``."""
        return self.order[a, col], self.order[a, col + 1]

    def sides(self, length, seg_line: np.ndarray, split: np.ndarray):
        """Per segment ``(right, ones on the right)``: the texels on the right (``d >= 0``) of
        the segment's float32 line evaluated in float64, as ``BSPVT.leaf_map`` does
        (segments where ``split`` is False: none)."""
        r, r2 = self.ang.r, self.ang.r * self.ang.r
        cs = texel_centres(r)
        self.seg = seg = _segment_ids(length)
        start = np.cumsum(length) - length
        tex0 = self.order[0]
        tau = tex0 % r2
        ln = seg_line[seg]
        right0 = (ln[:, 0] * cs[tau % r] + ln[:, 1] * cs[tau // r] + ln[:, 2] >= 0)
        right0 &= split[seg]
        self.side_tex = np.zeros(len(self.vals2), bool)
        self.side_tex[tex0] = right0
        return (np.add.reduceat(right0, start).astype(np.int64),
                np.add.reduceat(right0 & (self.vals2[tex0] > 0), start).astype(np.int64))

    def partition(self, keep: np.ndarray, n_new: list) -> None:
        """Stable partition of every angle's order (kd-tree style presorted lists): the kept
        left children, then the kept right children, each in its parent's order (``keep``
        (G, 2) per segment and side, ``n_new`` their texel totals)."""
        order, seg, w = self.order, self.seg, self.work
        right = w.get("right", order.shape, bool)
        np.take(self.side_tex, order, out=right, mode="clip")
        sel = w.get("sel", order.shape, bool)
        new = w.get(self.spare, (order.shape[0], n_new[0] + n_new[1]), np.intp)
        np.greater(keep[seg, 0][None, :], right, out=sel)  # kept left children
        for i in range(order.shape[0]):
            np.compress(sel[i], order[i], out=new[i, :n_new[0]])
        np.logical_and(right, keep[seg, 1][None, :], out=sel)  # kept right children
        for i in range(order.shape[0]):
            np.compress(sel[i], order[i], out=new[i, n_new[0]:])
        self.spare = "order0" if self.spare == "order1" else "order1"
        self.order = new


class _DrOps:
    """:class:`_NpOps` in Dr.Jit (LLVM on the CPU, CUDA on the GPU; the same trees, see
    tests/test_bspvt_build.py): the orders of all angles in one flat ``UInt32`` array (row
    ``a`` at ``a N``), segment sums from global prefix sums (differences are exact in 32-bit
    integers), per-segment minima / maxima / counts by ``dr.scatter_reduce`` and the
    partition by prefix counts and one scatter. Only per-cluster values (the best split, the
    stalled clusters' fallback, the children's counts) come back to the host each level."""

    def __init__(self, vals2: np.ndarray, ang: _Angles, m: int):
        r2 = ang.r * ang.r
        self.ang, self.a_count, self.n = ang, len(ang.theta), m * r2
        self.vals2 = owned(mi.Int32, vals2.astype(np.int32))
        perm = owned(mi.UInt32, ang.perm.astype(np.uint32).ravel())
        e = dr.arange(mi.UInt32, self.a_count * self.n)
        a = e // self.n
        t = e - a * self.n
        self.order = dr.gather(mi.UInt32, perm, a * r2 + t % r2) + (t // r2) * r2
        self.cs = owned(mi.Float64, texel_centres(ang.r))
        self._length = None
        dr.eval(self.order)

    def _segments(self, length: np.ndarray) -> None:
        """Each column's segment and each segment's first column, uploaded once per level
        (``length`` is the same object for a level's calls)."""
        if length is self._length:
            return
        self._length = length
        self.start = owned(mi.UInt32, np.cumsum(length) - length)
        # segment ids from a 1 at each segment's start but the first (no N-long upload)
        marks = dr.zeros(mi.UInt32, self.n)
        if len(length) > 1:
            g = dr.arange(mi.UInt32, 1, len(length))
            dr.scatter(marks, mi.UInt32(1), dr.gather(mi.UInt32, self.start, g))
        self.seg = dr.cumsum(marks)
        dr.eval(self.seg)

    def _before(self, first: mi.UInt32) -> mi.Int32:
        """The sum of ``2 V`` along the row before element ``first`` (a segment's first
        column: ``a N + start``), from this level's inclusive prefix sums."""
        return dr.gather(mi.Int32, self._incl, first) - dr.gather(mi.Int32, self._v, first)

    def best_splits(self, start, length, ones):
        """:func:`_best_splits` (without ``nontrivial``) on the device."""
        self._segments(length)
        a_count, g_count = self.a_count, len(start)
        # sizes change every level: opaque, or every level would compile new kernels
        n, gn = dr.opaque(mi.UInt32, self.n), dr.opaque(mi.UInt32, g_count)
        e = dr.arange(mi.UInt32, a_count * self.n)
        a = e // n
        col = e - a * n
        g = dr.gather(mi.UInt32, self.seg, col)
        s = dr.gather(mi.UInt32, self.start, g)
        v = dr.gather(mi.Int32, self.vals2, self.order)
        incl = dr.cumsum(v)
        dr.eval(v, incl)
        self._v, self._incl = v, incl  # also for fallback()
        # x = 2 O_k - k over each segment's first k = col - start + 1 texels (_best_splits)
        x = incl - self._before(a * n + s) - mi.Int32(col - s + 1)
        cell = a * gn + g
        lo = dr.full(mi.Int32, np.iinfo(np.int32).max, a_count * g_count)
        hi = dr.full(mi.Int32, np.iinfo(np.int32).min, a_count * g_count)
        # LLVM: long segments (the first levels: thousands of texels per cell) contend for
        # the same cells: per-thread copies of the targets (27 -> 9.5 s for 200 vertices);
        # short ones (deep levels, many cells: copies would cost more) plain atomics. CUDA:
        # Dr.Jit's default (warp-local pre-reduction)
        if dr.backend_v(lo) != dr.JitBackend.LLVM:
            mode = dr.ReduceMode.Auto
        elif self.n < 32 * g_count:
            mode = dr.ReduceMode.Direct
        else:
            mode = dr.ReduceMode.Expand
        dr.scatter_reduce(dr.ReduceOp.Min, lo, x, cell, mode=mode)
        dr.scatter_reduce(dr.ReduceOp.Max, hi, x, cell, mode=mode)
        # eq. 3's minimum over the angles per segment, on the device (only per-segment values
        # come back): keys e A + angle, so the minimum takes the first angle on ties as
        # np.argmin does (e >= 0: misclassified texels)
        og = owned(mi.Int32, np.stack([ones, length - ones], -1))  # (ones, zeros) per segment
        cells = dr.arange(mi.UInt32, a_count * g_count)
        ca = cells // gn
        cg = cells - ca * gn
        o_g, z_g = dr.gather(mi.Int32, og, cg * 2), dr.gather(mi.Int32, og, cg * 2 + 1)
        best = []
        for e_a in (lo + z_g, o_g - hi):  # E+ (high side right), E- (high side left)
            key = dr.zeros(mi.Int32, g_count) + np.iinfo(np.int32).max
            dr.scatter_reduce(dr.ReduceOp.Min, key, e_a * a_count + mi.Int32(ca), cg)
            best.append((key // a_count, key % a_count))
        (vp, a_p), (vm, a_m) = best
        flip = vm < vp
        best_a = dr.select(flip, a_m, a_p)
        best_e = dr.select(flip, vm, vp)
        gi = dr.arange(mi.UInt32, g_count)
        o_s, z_s = dr.gather(mi.Int32, og, gi * 2), dr.gather(mi.Int32, og, gi * 2 + 1)
        # the first column of the chosen angle where x reaches its extreme
        target = dr.select(flip, o_s - vm, vp - z_s)
        dr.eval(best_a, target)
        c = dr.arange(mi.UInt32, self.n)
        gc = dr.gather(mi.UInt32, self.seg, c)
        ac = mi.UInt32(dr.gather(mi.Int32, best_a, gc))
        sc = dr.gather(mi.UInt32, self.start, gc)
        ec = ac * n + c
        xc = dr.gather(mi.Int32, incl, ec) - self._before(ac * n + sc) - mi.Int32(c - sc + 1)
        hit = xc == dr.gather(mi.Int32, target, gc)
        first = dr.zeros(mi.UInt32, g_count) + n  # "no hit" (n: opaque)
        dr.scatter_reduce(dr.ReduceOp.Min, first, c, gc, hit)
        res = np.array(dr.ravel(mi.Vector4i(best_e, best_a, mi.Int32(first),
                                            mi.Int32(flip))), np.int64).reshape(g_count, 4)
        best_e, best_a, first, flip = res[:, 0], res[:, 1], res[:, 2], res[:, 3] != 0
        return best_e, best_a, first, flip

    def fallback(self, start, length, ones, sub, rows, cols):
        """:func:`_fallback_splits` on the device, from this level's prefix sums of
        :meth:`best_splits` (the same rows, so the same segment-relative sums): only the
        per-segment results come back."""
        s_count, r_count, c_count = len(sub), len(rows), len(cols)
        seg_b = _segment_ids(length[sub])
        per_col = owned(mi.UInt32, np.stack([cols, seg_b], -1))  # (global column, segment)
        per_seg = owned(mi.Int32, np.stack([start[sub], length[sub], ones[sub]], -1))
        row_a = owned(mi.UInt32, rows)
        n, cn, sn = (dr.opaque(mi.UInt32, x) for x in (self.n, c_count, s_count))
        e = dr.arange(mi.UInt32, r_count * c_count)
        r = e // cn
        j = e - r * cn
        col = dr.gather(mi.UInt32, per_col, j * 2)
        sb = dr.gather(mi.UInt32, per_col, j * 2 + 1)
        gs = mi.UInt32(dr.gather(mi.Int32, per_seg, sb * 3))
        ln = dr.gather(mi.Int32, per_seg, sb * 3 + 1)
        on = dr.gather(mi.Int32, per_seg, sb * 3 + 2)
        row = dr.gather(mi.UInt32, row_a, r) * n
        # ones among the segment's first k texels (inclusive), from the sums of 2 V
        o = (dr.gather(mi.Int32, self._incl, row + col) - self._before(row + gs)) >> 1
        k = mi.Int32(col - gs) + 1
        z_l = k - o
        e_l = dr.minimum(o, z_l)
        e_r = dr.minimum(on - o, (ln - on) - z_l)
        # as _fallback_splits: the summed error first, then the texels in impure children
        key = (e_l + e_r) * (2 * int(length[sub].max()) + 1) + dr.select(e_l > 0, k, 0) + \
            dr.select(e_r > 0, ln - k, 0)
        big = np.iinfo(np.int32).max
        key = dr.select(k == ln, big, key)  # everything on one side: no cut
        cell = r * sn + sb
        best = dr.zeros(mi.Int32, r_count * s_count) + big
        dr.scatter_reduce(dr.ReduceOp.Min, best, key, cell)
        cells = dr.arange(mi.UInt32, r_count * s_count)
        c_r = cells // sn
        c_s = cells - c_r * sn
        val = dr.zeros(mi.Int32, s_count) + big
        dr.scatter_reduce(dr.ReduceOp.Min, val, best, c_s)
        # the first angle (row) reaching it, then the first column of that row
        first_r = dr.zeros(mi.UInt32, s_count) + r_count
        dr.scatter_reduce(dr.ReduceOp.Min, first_r, c_r, c_s,
                          best == dr.gather(mi.Int32, val, c_s))
        fcol = dr.zeros(mi.UInt32, s_count) + cn
        dr.scatter_reduce(dr.ReduceOp.Min, fcol, j, sb,
                          (r == dr.gather(mi.UInt32, first_r, sb))
                          & (key == dr.gather(mi.Int32, val, sb)))
        res = np.array(dr.ravel(mi.Vector3i(val, mi.Int32(first_r), mi.Int32(fcol))),
                       np.int64).reshape(s_count, 3)
        key_out = np.where(res[:, 0] == big, _NO_CUT, res[:, 0])
        return key_out, res[:, 1], res[:, 2]

    def pairs(self, a: np.ndarray, col: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        idx = owned(mi.UInt32, np.stack([a * self.n + col, a * self.n + col + 1], -1))
        got = np.array(dr.gather(mi.UInt32, self.order, idx), np.int64).reshape(-1, 2)
        return got[:, 0], got[:, 1]

    def sides(self, length, seg_line: np.ndarray, split: np.ndarray):
        r, r2 = self.ang.r, self.ang.r * self.ang.r
        g_count = len(length)
        self._segments(length)
        cs = self.cs
        c = dr.arange(mi.UInt32, self.n)
        gc = dr.gather(mi.UInt32, self.seg, c)
        tex0 = dr.gather(mi.UInt32, self.order, c)
        tau = tex0 % r2
        # (a, b, c, split) per segment in one upload
        lines = owned(mi.Float64, np.concatenate([seg_line, split[:, None]], 1))
        ln = [dr.gather(mi.Float64, lines, gc * 4 + k) for k in range(4)]
        # float64, as NumPy and BSPVT.leaf_map evaluate the stored float32 line (no FMA
        # contraction matters: every texel centre is >= TIE_TOL texels from every line)
        right0 = (ln[0] * dr.gather(mi.Float64, cs, tau % r)
                  + ln[1] * dr.gather(mi.Float64, cs, tau // r) + ln[2] >= 0.0)
        right0 &= ln[3] != 0.0
        self.side_tex = dr.zeros(mi.UInt32, dr.width(self.vals2))
        dr.scatter(self.side_tex, mi.UInt32(right0), tex0)
        n_r = dr.zeros(mi.UInt32, g_count)
        ones_r = dr.zeros(mi.UInt32, g_count)
        dr.scatter_reduce(dr.ReduceOp.Add, n_r, mi.UInt32(right0), gc)
        lit = right0 & (dr.gather(mi.Int32, self.vals2, tex0) > 0)
        dr.scatter_reduce(dr.ReduceOp.Add, ones_r, mi.UInt32(lit), gc)
        dr.eval(self.side_tex, n_r, ones_r)
        return np.array(n_r, np.int64), np.array(ones_r, np.int64)

    def partition(self, keep: np.ndarray, n_new: list) -> None:
        a_count = self.a_count
        n_out = n_new[0] + n_new[1]
        n, n_o, n_l = (dr.opaque(mi.UInt32, x) for x in (self.n, n_out, n_new[0]))
        e = dr.arange(mi.UInt32, a_count * self.n)
        a = e // n
        col = e - a * n
        g = dr.gather(mi.UInt32, self.seg, col)
        right = dr.gather(mi.UInt32, self.side_tex, self.order) != 0
        k2 = owned(mi.UInt32, keep)  # (left, right) per segment
        keep_l = dr.gather(mi.UInt32, k2, g * 2) != 0
        keep_r = dr.gather(mi.UInt32, k2, g * 2 + 1) != 0
        sel_l, sel_r = keep_l & ~right, keep_r & right
        # rank within the row: exclusive prefix counts minus the count at the row's start
        pl = dr.prefix_sum(mi.UInt32(sel_l))
        pr = dr.prefix_sum(mi.UInt32(sel_r))
        dr.eval(pl, pr)
        row = a * n
        pos = dr.select(sel_l, pl - dr.gather(mi.UInt32, pl, row),
                        n_l + pr - dr.gather(mi.UInt32, pr, row))
        new = dr.zeros(mi.UInt32, a_count * n_out)
        dr.scatter(new, self.order, a * n_o + pos, sel_l | sel_r)
        dr.eval(new)
        self.order, self.n = new, n_out


def _build_chunk(vals, ang: _Angles, map_ids, root_ones, eps: float, max_depth: int,
                 stalled: str, engine: str = "numpy") -> tuple[dict, np.ndarray, np.ndarray, int]:
    """The batched build of a chunk of faces (``vals`` (M, R^2) 0/1, global face indices
    ``map_ids``), all clusters of a level at once, the array work by ``engine``
    (:class:`_NpOps` or :class:`_DrOps`). Returns the new clusters (ids local to the chunk:
    0..M-1 are the faces' roots, the rest follow), the ids and lines of the split clusters,
    and the number of stalled splits."""
    r2 = ang.r * ang.r
    m = len(map_ids)
    a_count = len(ang.theta)
    vals2 = (2 * vals).astype(np.int32).reshape(-1)
    ops = (_NpOps if engine == "numpy" else _DrOps)(vals2, ang, m)
    clusters = _Clusters(first_id=m)
    split_ids, split_lines, stalled_splits = [], [], 0
    start = np.arange(m, dtype=np.int64) * r2
    length = np.full(m, r2, np.int64)
    seg_id = np.arange(m, dtype=np.int64)
    seg_ones = np.asarray(root_ones, np.int64)
    seg_code = np.ones(m, np.int64)
    seg_map = np.asarray(map_ids, np.int64)
    depth = 0
    while len(start):
        e_best, a, col, flip = ops.best_splits(start, length, seg_ones)
        do = e_best < _err(length, seg_ones)  # the split reduces eq. 3
        if stalled == "split" and not do.all():
            sub = np.nonzero(~do)[0]
            cols = _ranges(start[sub], length[sub])
            rows = np.arange(0, a_count, FALLBACK_STRIDE)
            key, fa, fcol = ops.fallback(start, length, seg_ones, sub, rows, cols)
            fa = rows[fa]
            ok = key < _NO_CUT
            a[sub[ok]] = fa[ok]
            col[sub[ok]] = cols[fcol[ok]]
            flip[sub[ok]] = False
            do[sub[ok]] = True
            stalled_splits += int(ok.sum())
        g = np.nonzero(do)[0]
        if len(g) == 0:
            break
        lo, hi = (t % r2 for t in ops.pairs(a[g], col[g]))
        line = ang.line(a[g], lo, hi, flip[g]).astype(np.float32)
        split_ids.append(seg_id[g])
        split_lines.append(line)
        # the side of every texel of the split clusters by the stored (float32) line, as
        # BSPVT.leaf_map evaluates it
        seg_line = np.zeros((len(start), 3))
        seg_line[g] = line
        n_r, ones_r = ops.sides(length, seg_line, do)
        n_l, ones_l = length - n_r, seg_ones - ones_r
        depth += 1
        ch_n = np.stack([n_l[g], n_r[g]], 1)
        ch_ones = np.stack([ones_l[g], ones_r[g]], 1)
        if not np.all(ch_n > 0):  # pragma: no cover - the projection margin rules it out
            raise AssertionError("a BSPVT split left one side empty")
        ch_code = 2 * seg_code[g][:, None] + np.arange(2)
        ids = clusters.add(np.repeat(seg_map[g], 2), ch_code.ravel(), ch_n.ravel(),
                           ch_ones.ravel(), np.repeat(seg_id[g], 2), np.tile([0, 1], len(g)))
        keep = np.zeros((len(start), 2), bool)
        keep[g] = (_err(ch_n, ch_ones) > eps) & (depth < max_depth)
        if not keep.any():
            break
        ops.partition(keep, [int(n_l[keep[:, 0]].sum()), int(n_r[keep[:, 1]].sum())])
        kept = [np.nonzero(keep[:, 0])[0], np.nonzero(keep[:, 1])[0]]
        length = np.concatenate([n_l[kept[0]], n_r[kept[1]]])
        start = np.cumsum(length) - length
        seg_ones = np.concatenate([ones_l[kept[0]], ones_r[kept[1]]])
        per = np.zeros((len(keep), 2), np.int64)
        per[g] = ids.reshape(-1, 2)
        seg_id = np.concatenate([per[kept[0], 0], per[kept[1], 1]])
        per[g] = ch_code
        seg_code = np.concatenate([per[kept[0], 0], per[kept[1], 1]])
        seg_map = np.concatenate([seg_map[kept[0]], seg_map[kept[1]]])
    ids = np.concatenate(split_ids) if split_ids else np.zeros(0, np.int64)
    lines = np.concatenate(split_lines) if split_lines else np.zeros((0, 3), np.float32)
    return clusters.table(), ids, lines, stalled_splits


def _assemble(table: dict, split_id: np.ndarray, split_line: np.ndarray, n_maps: int,
              max_leaves: int | None) -> tuple:
    """Flat arrays (lines, children, leaf_value, roots) from the cluster table."""
    c = len(table["id"])
    assert np.array_equal(table["id"], np.arange(c))
    is_split = np.zeros(c, bool)
    is_split[split_id] = True
    line_of = np.zeros((c, 3), np.float32)
    line_of[split_id] = split_line
    child = np.full((c, 2), -1, np.int64)
    nonroot = table["parent"] >= 0
    child[table["parent"][nonroot], table["side"][nonroot]] = table["id"][nonroot]
    e = _err(table["n"], table["ones"])
    if max_leaves is not None:
        # Algorithm 1's priority queue with a leaf budget: pop by decreasing error (ties:
        # smaller code = shallower, then left); a child's error never exceeds its parent's,
        # so the popped splits are the (max_leaves - 1) first splits in that order per face
        cand = np.nonzero(is_split)[0]
        o = np.lexsort((table["code"][cand], -e[cand], table["map"][cand]))
        cand = cand[o]
        mp = table["map"][cand]
        first = np.searchsorted(mp, mp, side="left")
        rank = np.arange(len(cand)) - first
        chosen = np.zeros(c, bool)
        chosen[cand[rank < max_leaves - 1]] = True
        is_split &= chosen
    kept = ~nonroot.copy()
    kept[nonroot] = is_split[table["parent"][nonroot]]
    inner = kept & is_split
    leaf = kept & ~is_split
    ni = np.nonzero(inner)[0]
    ni = ni[np.lexsort((table["code"][ni], table["map"][ni]))]
    li = np.nonzero(leaf)[0]
    li = li[np.lexsort((table["code"][li], table["map"][li]))]
    enc = np.zeros(c, np.int64)
    enc[ni] = np.arange(len(ni))
    enc[li] = ~np.arange(len(li))
    lines = line_of[ni]
    children = enc[child[ni]].astype(np.int32)
    leaf_value = (table["ones"][li] / table["n"][li]).astype(np.float32)
    root_of = np.zeros(n_maps, np.int64)
    root_of[table["map"][~nonroot]] = table["id"][~nonroot]
    roots = enc[root_of].astype(np.int32)
    return lines, children, leaf_value, roots, e[li], table["code"][li]


def _check_vis(vis) -> np.ndarray:
    a = np.asarray(vis)
    if a.ndim != 4 or a.shape[1] != 6 or a.shape[2] != a.shape[3] or a.shape[2] < 1:
        raise GlossrtError(f"visibility cube maps must have shape (V, 6, R, R), got {a.shape}")
    _check_resolution(a.shape[2])
    return _binary(a, "visibility cube maps")


def _check_build_args(epsilon, method: str, stalled: str, max_leaves, max_depth) -> float:
    """:func:`build_trees`' settings checked (one clear error each); returns ``epsilon`` as a
    float."""
    eps = float(epsilon)
    if not (math.isfinite(eps) and eps >= 0):
        raise GlossrtError(f"epsilon must be finite and >= 0, got {epsilon}")
    if method not in ("batched", "nelder-mead"):
        raise GlossrtError(f"unknown method {method!r} (batched or nelder-mead)")
    if stalled not in ("split", "leaf"):
        raise GlossrtError(f"stalled must be 'split' or 'leaf', got {stalled!r}")
    if max_leaves is not None and (int(max_leaves) != max_leaves or max_leaves < 1):
        raise GlossrtError(f"max_leaves must be a positive integer, got {max_leaves}")
    if int(max_depth) != max_depth or not (0 <= max_depth <= 60):
        raise GlossrtError(f"max_depth must be an integer in 0..60, got {max_depth}")
    return eps


def _build_batched(maps: np.ndarray, ones: np.ndarray, active: np.ndarray,
                   root_ids: np.ndarray, clusters: _Clusters, splits: dict, stats: dict,
                   r: int, angles, eps: float, max_depth: int, stalled: str, engine: str,
                   chunk_work: int | None, threads: int | None, progress: bool) -> None:
    """:func:`build_trees`' ``"batched"`` search: the ``active`` faces' maps in chunks of
    about ``chunk_work`` texels x angles (:func:`_build_chunk`, side by side on ``threads``
    NumPy threads), their clusters added to ``clusters`` and their splits to ``splits`` with
    global cluster ids, ``stats["stalled_splits"]`` counted."""
    ang = _Angles.get(r, angles)
    if chunk_work is None:
        chunk_work = CHUNK_WORK if engine == "numpy" else (
            CHUNK_WORK_DRJIT_CUDA if mi.variant().startswith("cuda") else CHUNK_WORK_DRJIT)
    per = max(1, int(chunk_work) // (len(ang.theta) * r * r))
    chunks = [active[i:i + per] for i in range(0, len(active), per)]
    if threads is None:
        threads = min(os.cpu_count() or 1, MAX_THREADS) if engine == "numpy" else 1
    if int(threads) != threads or threads < 1:
        raise GlossrtError(f"threads must be a positive integer, got {threads}")
    workers = max(1, min(int(threads), len(chunks)))

    def run(chunk):
        return _build_chunk(maps[chunk], ang, chunk, ones[chunk], eps, max_depth, stalled,
                            engine)

    with Progress(len(active), f"BSPVT build {r}x{r}", enabled=progress) as bar, \
            ThreadPoolExecutor(workers) as pool:
        done = 0
        # NumPy releases the GIL in its array loops: chunks can run side by side
        results = pool.map(run, chunks) if workers > 1 else map(run, chunks)
        for chunk, (tab, sid, sline, st) in zip(chunks, results, strict=True):
            # chunk-local ids: 0..M-1 the faces' roots, M.. the new clusters in order
            m, base = len(chunk), clusters.count

            def glob(i, m=m, base=base, roots=root_ids[chunk]):
                return np.where(i < m, roots[np.minimum(i, m - 1)], base + i - m)

            if len(tab["id"]):
                clusters.add(tab["map"], tab["code"], tab["n"], tab["ones"],
                             glob(tab["parent"]), tab["side"])
            splits["id"].append(glob(sid))
            splits["line"].append(sline)
            stats["stalled_splits"] += st
            done += len(chunk)
            bar.update(done)


def build_trees(vis, epsilon: float = 0.0, method: str = "batched", angles=DEFAULT_ANGLES,
                max_leaves: int | None = None, max_depth: int = DEFAULT_MAX_DEPTH,
                stalled: str = "split", positions=None, normals=None,
                progress: bool = True, chunk_work: int | None = None,
                threads: int | None = None, engine: str = "numpy") -> BSPVT:
    """BSPVTs of visibility cube maps ``vis`` ``(V, 6, R, R)`` (0/1, ``[vertex, face, j, i]``)
    by Okuno & Iwasaki's Algorithm 1 (see the module docstring).

    ``epsilon``: leaf threshold on a cluster's error ``e`` (texels); ``method``:
    ``"batched"`` (exact over offsets for ``angles`` equally spaced angles, or ``"exact"``)
    or ``"nelder-mead"`` (the paper's; slow); ``max_leaves``: optional leaf budget per face
    (priority queue by error); ``max_depth``: depth cap; ``stalled``: ``"split"`` or
    ``"leaf"``, what to do with a cluster no line improves; ``positions``/``normals``
    ``(V, 3)`` are stored with the trees (zeros if not given); ``chunk_work`` bounds the
    batched build's memory (texels x angles per step, per thread; default
    :data:`CHUNK_WORK`; the Dr.Jit engine :data:`CHUNK_WORK_DRJIT`, on CUDA
    :data:`CHUNK_WORK_DRJIT_CUDA`); ``threads``: worker
    threads of the NumPy engine (default: one per CPU core, at most :data:`MAX_THREADS`;
    NumPy releases the GIL in its array loops: 1.5-1.9x with 2 threads on 2 cores).
    ``engine``: the batched build's array work in ``"numpy"`` or ``"drjit"`` (the current
    Mitsuba variant: LLVM on the CPU, CUDA on a GPU; one chunk at a time, Dr.Jit uses every
    core itself); both give the same trees."""
    t0 = time.perf_counter()
    v = _check_vis(vis)
    nv, r = v.shape[0], v.shape[2]
    r2 = r * r
    eps = _check_build_args(epsilon, method, stalled, max_leaves, max_depth)
    pos = np.zeros((nv, 3)) if positions is None else _check_points("positions", positions, nv)
    nrm = np.zeros((nv, 3)) if normals is None else _check_points("normals", normals, nv)

    maps = v.reshape(nv * 6, r2)
    ones = maps.sum(1, dtype=np.int64)
    clusters = _Clusters()
    root_ids = clusters.add(np.arange(nv * 6), np.ones(nv * 6), np.full(nv * 6, r2), ones,
                            np.full(nv * 6, -1), np.zeros(nv * 6))
    active = np.nonzero((_err(r2, ones) > eps) & (max_depth > 0))[0]
    splits = {"id": [], "line": []}
    stats = {"stalled_splits": 0}
    if engine not in ENGINES:
        raise GlossrtError(f"unknown engine {engine!r}; choose one of {ENGINES}")
    if method == "batched":
        _build_batched(maps, ones, active, root_ids, clusters, splits, stats, r, angles, eps,
                       max_depth, stalled, engine, chunk_work, threads, progress)
        budget = max_leaves
    else:
        with Progress(len(active), "BSPVT build (Nelder-Mead)", enabled=progress) as bar:
            for i, mp in enumerate(active):
                _nm_face(maps[mp], int(mp), int(root_ids[mp]), int(ones[mp]), r, clusters,
                         splits, eps, max_depth, stalled, max_leaves, stats)
                bar.update(i + 1)
        budget = None
    table = clusters.table()
    split_id = (np.concatenate(splits["id"]) if splits["id"] else np.zeros(0, np.int64))
    split_line = (np.concatenate(splits["line"]) if splits["line"]
                  else np.zeros((0, 3), np.float32))
    lines, children, leaf_value, roots, leaf_e, leaf_code = _assemble(
        table, split_id, split_line, nv * 6, budget)
    info = {
        "method": method,
        "angles": (angles if isinstance(angles, str) else int(angles))
        if method == "batched" else None,
        "max_leaves": None if max_leaves is None else int(max_leaves),
        "max_depth": int(max_depth), "stalled": stalled,
        "engine": engine if method == "batched" else None,
        "build_seconds": time.perf_counter() - t0,
        "leaves_over_epsilon": int(np.count_nonzero(leaf_e > eps)),
        "depth": int(leaf_code.max()).bit_length() - 1 if len(leaf_code) else 0,
        "stalled_splits": stats["stalled_splits"],
    }
    return BSPVT(lines=lines, children=children, leaf_value=leaf_value,
                 roots=roots.reshape(nv, 6), resolution=r, epsilon=eps, positions=pos,
                 normals=nrm, info=info)


def _nm_face(vals, map_id: int, root_id: int, root_ones: int, r: int, clusters: _Clusters,
             splits: dict, eps: float, max_depth: int, stalled: str, max_leaves, stats) -> None:
    """Algorithm 1 for one face with Nelder-Mead lines: a priority queue of clusters by
    error (ties: smaller code, i.e. shallower, then left)."""
    c = texel_centres(r)
    tau_all = np.arange(r * r)
    s_all, t_all = c[tau_all % r], c[tau_all // r]
    vals = vals.astype(np.int64)
    members = {root_id: tau_all}
    heap = [(-min(root_ones, r * r - root_ones), 1, root_id)]
    leaves = 1
    while heap:
        neg_e, code, cid = heapq.heappop(heap)
        if -neg_e <= eps or (max_leaves is not None and leaves >= max_leaves):
            break
        if code >= 1 << max_depth:
            continue
        tau = members.pop(cid)
        s, t, v = s_all[tau], t_all[tau], vals[tau]
        line, err = _nm_line(s, t, v, r)
        if line is None or err >= -neg_e:  # no reduction of eq. 3
            if stalled == "leaf":
                continue
            sel = np.zeros(r * r, bool)
            sel[tau] = True
            line = _fallback_line(sel, vals.astype(np.uint8), r)
            if line is None:
                continue
            stats["stalled_splits"] += 1
        line32 = line.astype(np.float32)
        ln = line32.astype(np.float64)
        right = ln[0] * s + ln[1] * t + ln[2] >= 0
        if right.all() or not right.any():
            continue
        splits["id"].append(np.array([cid]))
        splits["line"].append(line32[None])
        parts = [tau[~right], tau[right]]
        ids = clusters.add([map_id, map_id], [2 * code, 2 * code + 1],
                           [len(p) for p in parts], [int(vals[p].sum()) for p in parts],
                           [cid, cid], [0, 1])
        leaves += 1
        for side, (cid2, p) in enumerate(zip(ids, parts, strict=True)):
            o = int(vals[p].sum())
            members[int(cid2)] = p
            heapq.heappush(heap, (-min(o, len(p) - o), 2 * code + side, int(cid2)))


# -- chunked builds (issue 27: work items for a cluster) -------------------------------------
#
# A face's tree depends on that face's map alone (module docstring: every split is a function
# of its cluster, the leaf budget is per face) and the flat arrays store vertices one after
# the other, each vertex's nodes and leaves contiguous. So the build of vertices ``[a, b)``
# run on their own gives exactly the rows of the whole build, with node and leaf indices
# shifted by the nodes and leaves of the vertices before ``a``: :func:`build_vertex_chunk`
# computes one such item from plain data (a scene by name or XML path, the vertex range, the
# settings) in any process, and :func:`merge_vertex_chunks` concatenates the items' arrays
# (byte-identical to :func:`build_trees` of all vertices, whatever the chunking).

#: vertices per work item of a chunked build (:func:`plan_vertex_chunks`): about 8 s of work
#: at R = 64 on one core and ~0.5 MB of result, so a task's overhead (tens of ms) is noise
CHUNK_VERTICES = 256
#: :func:`build_trees` settings a work item carries (plain data)
CHUNK_SETTINGS = ("angles", "max_leaves", "max_depth", "stalled", "engine", "threads",
                  "chunk_work")
_CHUNK_ARRAYS = ("lines", "children", "leaf_value", "roots", "positions", "normals")
#: per-process cache of loaded scenes for work items: {key: (occluders, positions, normals)}
_ITEM_SCENES: dict = {}


def plan_vertex_chunks(n_vertices: int,
                       chunk_vertices: int = CHUNK_VERTICES) -> list[tuple[int, int]]:
    """Vertex ranges ``[(a, b), ...]`` of at most ``chunk_vertices`` covering ``0..n_vertices``
    in order."""
    n, k = int(n_vertices), int(chunk_vertices)
    if k != chunk_vertices or k < 1:
        raise GlossrtError(f"chunk_vertices must be a positive integer, got {chunk_vertices}")
    return [(a, min(n, a + k)) for a in range(0, n, k)]


def scene_ref(scene) -> str:
    """A scene reference a work item can carry: a built-in name as it is, an XML file's path
    made absolute (a worker may run in another folder)."""
    if not isinstance(scene, (str, os.PathLike)):
        raise GlossrtError("a chunked BSPVT build needs the scene by built-in name or XML path "
                           "(each work item loads it itself), not a loaded scene")
    s = os.fspath(scene)
    return os.path.abspath(s) if os.path.isfile(s) else s


def ship_scene(items: list[dict], cluster=None) -> list[dict]:
    """``items`` (:func:`vertex_chunk_items`) as the workers of the open ``cluster`` get them:
    an XML scene packed with the files it references (:func:`glossrt.scenefiles.bundle`),
    its bytes put once into the cluster's object store (:func:`glossrt.cluster.share`), so
    that nodes without the driver's folders load the same scene. Without a cluster, or for a
    built-in scene, ``items`` as they are."""
    from ... import cluster as _cluster

    if not items:
        return items
    shipped = _cluster.ship_scene(items[0]["scene"], cluster)
    return items if shipped is items[0]["scene"] else [dict(it, scene=shipped) for it in items]


def _scene_name(ref) -> str:
    return ref["xml"] if isinstance(ref, dict) else str(ref)


def _item_scene(ref) -> tuple:
    """``(occluders, positions, normals)`` of scene ``ref`` (:func:`glossrt.scenes.load`; a
    shipped bundle from :func:`ship_scene` is unpacked first,
    :func:`glossrt.scenefiles.materialise`), cached per process (a worker that gets several
    items loads the scene once). The key has the variant and, for a file, its modification
    time (for a bundle, its digest)."""
    from ...scenes import load

    if isinstance(ref, dict):
        key = ("bundle", ref.get("digest"), mi.variant())
    else:
        key = (ref, mi.variant(), os.stat(ref).st_mtime_ns if os.path.isfile(ref) else None)
    if key not in _ITEM_SCENES:
        if isinstance(ref, dict):
            from ...cluster import local_scene

            ref = local_scene(ref)
        scene = load(ref).scene
        pos, nrm, _ = scene_vertices(scene)
        _ITEM_SCENES.clear()  # one scene at a time: a worker serves one build
        _ITEM_SCENES[key] = (occluders(scene), pos, nrm)
    return _ITEM_SCENES[key]


def vertex_chunk_items(scene, n_vertices: int, resolution: int, epsilon: float,
                       method: str, chunk_vertices: int = CHUNK_VERTICES,
                       **settings) -> list[dict]:
    """The work items (plain dicts: strings, numbers) of a chunked build of ``scene`` (name
    or XML path) with ``n_vertices`` vertices; ``settings``: :data:`CHUNK_SETTINGS`. The
    settings are checked here, before any work."""
    ref = scene_ref(scene)
    _check_resolution(resolution)
    unknown = sorted(set(settings) - set(CHUNK_SETTINGS))
    if unknown:
        raise GlossrtError(f"unknown BSPVT build settings {unknown}; chunked builds take "
                           f"{list(CHUNK_SETTINGS)}")
    eps = _check_build_args(epsilon, method, settings.get("stalled", "split"),
                            settings.get("max_leaves"),
                            settings.get("max_depth", DEFAULT_MAX_DEPTH))
    if settings.get("engine", "numpy") not in ENGINES:
        raise GlossrtError(f"unknown engine {settings['engine']!r}; choose one of {ENGINES}")
    return [{"scene": ref, "start": a, "stop": b, "resolution": int(resolution),
             "epsilon": eps, "method": method, **settings}
            for a, b in plan_vertex_chunks(n_vertices, chunk_vertices)]


def build_vertex_chunk(item: dict) -> dict:
    """One work item of a chunked build, computed from plain data in any process: the
    visibility cube maps (:func:`visibility_cubemaps`, against :func:`occluders`) of
    vertices ``item["start"]:item["stop"]`` of ``item["scene"]`` and their trees
    (:func:`build_trees`). Returns plain data: the trees' arrays (vertex-local indices),
    ``start``/``stop`` and ``info`` (numbers: seconds, counts)."""
    t0 = time.perf_counter()
    occ, pos, nrm = _item_scene(item["scene"])
    a, b = int(item["start"]), int(item["stop"])
    if not (0 <= a < b <= len(pos)):
        raise GlossrtError(f"vertex range {a}..{b} outside scene "
                           f"{_scene_name(item['scene'])!r} "
                           f"({len(pos)} vertices)")
    settings = {k: item[k] for k in CHUNK_SETTINGS if k in item}
    if settings.get("threads") is None and item.get("engine", "numpy") == "numpy":
        # as many NumPy threads as Dr.Jit has: on a cluster worker, the CPUs the task got
        # (glossrt.cluster sets Dr.Jit's thread count so)
        settings["threads"] = max(1, min(int(dr.thread_count()), MAX_THREADS))
    vis = visibility_cubemaps(occ, pos[a:b], nrm[a:b], item["resolution"], progress=False)
    t1 = time.perf_counter()
    trees = build_trees(vis, item["epsilon"], item["method"], positions=pos[a:b],
                        normals=nrm[a:b], progress=False, **settings)
    out = {k: getattr(trees, k) for k in _CHUNK_ARRAYS}
    info = {k: trees.info[k] for k in ("leaves_over_epsilon", "depth", "stalled_splits")}
    info.update(visibility_seconds=t1 - t0, tree_seconds=time.perf_counter() - t1)
    return {"start": a, "stop": b, "resolution": trees.resolution, "epsilon": trees.epsilon,
            "info": info, **out}


def merge_vertex_chunks(results: list[dict], n_vertices: int | None = None,
                        info: dict | None = None) -> BSPVT:
    """The trees of all vertices from :func:`build_vertex_chunk` results in any order: sorted
    by vertex range (which must tile ``0..n_vertices`` without gaps or overlaps), arrays
    concatenated with node indices shifted by the nodes before each chunk and leaf
    encodings ``~k`` by the leaves before it. ``info`` is stored with the trees, plus the
    summed counts and seconds of the items."""
    res = sorted(results, key=lambda c: int(c["start"]))
    if not res:
        raise GlossrtError("no BSPVT chunks to merge")
    end = 0
    for c in res:
        if int(c["start"]) != end or int(c["stop"]) <= end:
            raise GlossrtError(f"BSPVT chunks do not tile the vertices: chunk "
                               f"{c['start']}..{c['stop']} after vertex {end}")
        if (c["resolution"], c["epsilon"]) != (res[0]["resolution"], res[0]["epsilon"]):
            raise GlossrtError("BSPVT chunks of different resolutions or epsilons")
        end = int(c["stop"])
    if n_vertices is not None and end != n_vertices:
        raise GlossrtError(f"BSPVT chunks cover {end} vertices, expected {n_vertices}")
    nodes = np.cumsum([0] + [len(c["lines"]) for c in res])
    leaves = np.cumsum([0] + [len(c["leaf_value"]) for c in res])

    def shifted(a, k):  # node n -> n + nodes[k]; leaf ~l -> ~(l + leaves[k])
        a = np.asarray(a, np.int64)
        return np.where(a >= 0, a + nodes[k], a - leaves[k]).astype(np.int32)

    if leaves[-1] >= 2 ** 31 or nodes[-1] >= 2 ** 31:
        raise GlossrtError("BSPVT too large for int32 indices")
    merged = dict(info or {})
    for key in ("leaves_over_epsilon", "stalled_splits"):
        merged[key] = int(sum(c["info"][key] for c in res))
    merged["depth"] = int(max(c["info"]["depth"] for c in res))
    for key in ("visibility_seconds", "tree_seconds"):
        merged[f"chunk_{key}"] = float(sum(c["info"][key] for c in res))
    merged["chunks"] = len(res)
    return BSPVT(lines=np.concatenate([c["lines"] for c in res]),
                 children=np.concatenate([shifted(c["children"], k) for k, c in enumerate(res)]),
                 leaf_value=np.concatenate([c["leaf_value"] for c in res]),
                 roots=np.concatenate([shifted(c["roots"], k) for k, c in enumerate(res)]),
                 resolution=res[0]["resolution"], epsilon=res[0]["epsilon"],
                 positions=np.concatenate([c["positions"] for c in res]),
                 normals=np.concatenate([c["normals"] for c in res]), info=merged)
