"""Shadowed polygon-light shading with per-vertex binary space partitioning visibility trees
(BSPVT; H. Okuno and K. Iwasaki, "Interactive Rendering of Shadows for Polygonal Light using a
Binary Space Partitioning Visibility Tree"), in Dr.Jit (one lane per query; CPU LLVM and CUDA).

What is computed (Okuno & Iwasaki, sec. 3.1, eq. 2)::

    B(wo) = L int_P V(wi) f(wi, wo) cos dwi  ~=  L sum_i v_i int_{P_i} f(wi, wo) cos dwi

where the ``P_i`` are the pieces into which the lines of a vertex's visibility tree cut the
light polygon ``P`` (projected onto that vertex's visibility cube map), and ``v_i`` is the mean
visibility stored at the tree leaf the piece falls into. Each piece integral is evaluated with
linearly transformed cosines (Heitz, Dupuy, Hill, Neubelt 2016) exactly as
:func:`glossrt.lights.ltc.shade._integrals` does for a whole light: the clamped-cosine integral of
the piece (diffuse, ``i_d``) and of the piece transformed by the LTC's ``M^-1`` (specular, ``i_s``),
both with the horizon clipping and one- / two-sided handling of
:func:`glossrt.lights.polygon.cosine_integral`. With an all-visible tree the sums equal the
unshadowed ``_integrals`` of the whole light (the pieces partition it).

How (Okuno & Iwasaki, sec. 3.3 and fig. 5; step 2 depth-first in one kernel by default, as
a breadth-first wavefront, or fused with step 3 in one loop: ``visible_integrals(...,
traversal=)``, :data:`TRAVERSALS`):

1. Per query (shading point ``p``) and cube face ``f`` (world axes; conventions of
   :mod:`glossrt.lights.bspvt`: face ``f`` has axis ``k = f // 2``, sign ``sg``, in-face axes
   ``u = (k + 1) % 3``, ``v = (k + 2) % 3``), the light polygon relative to ``p`` is clipped in 3D
   against the face's frustum ``sg d_k >= |d_u|``, ``sg d_k >= |d_v|`` (four planes through the
   origin; Sutherland and Hodgman 1974) and projected gnomonically,
   ``(s, t) = (d_u, d_v) / (sg d_k)``: a plane through the origin maps to a straight line, so the
   projected piece is a convex polygon in the face's square ``[-1, 1]^2`` (at most ``K + 4``
   vertices).
2. Work items ``(query, face, node, 2D polygon)`` start at the face's root; each level, every
   item at an internal node is cut by the node's line ``a s + b t + c`` into its left
   (``d < 0``) and right (``d >= 0``) children (one half-plane Sutherland-Hodgman clip each);
   empty children are dropped, children at internal nodes form the next level (compacted with
   ``dr.compress``), children at leaves with mean visibility ``v > 0`` are integrated at once
   and leaves with ``v = 0`` are dropped without integration (fig. 5 (c), (d)). The kernel
   traversal does the same cuts per root item in a loop with a stack in local memory
   (``dr.alloc_local``) and appends the leaf pieces to one buffer (``dr.scatter_inc``). The
   fused traversal pushes leaf pieces onto that stack too and integrates them when popped:
   no array whose size depends on the data and no host synchronisation, so ``dr.freeze`` can
   record it (``shade_points(..., frozen=True)``, the real-time path).
3. A leaf piece is lifted back to directions ``dir(f, s, t) = sg e_k + s e_u + t e_v`` (a
   polygon on the plane ``sg d_k = 1``: the same solid angle and the same winding seen from
   ``p``), expressed in the shading frame and integrated; ``v i_d`` and ``v i_s`` are summed
   per query (``dr.scatter_reduce``).

Pieces carry at most :data:`KMAX` 2D vertices (a convex polygon cut by ``m`` lines has at most
``K + 4 + m`` vertices; in the tests pieces rarely exceed 8; a piece that would exceed
``KMAX`` keeps its first ``KMAX`` vertices, i.e. loses a corner: convex still, slightly
smaller). Pieces with more than 8 vertices (what ``cosine_integral`` takes) are integrated as
a fan of up to 3 sub-polygons sharing vertex 0 (the integrals add: the shared edges cancel and
every sub-polygon has the piece's winding).

Textured lights (Heitz et al. 2016, sec. 5.3, glossrt's form in :mod:`glossrt.lights.ltc`):
each piece's integral is weighted by the prefiltered texture looked up where the piece's
vector form factor (its mean direction, in the untransformed or ``M^-1`` space) meets the
*whole* light's plane, with the whole light's affine uv map and the filter width from that
distance and the whole light's area. (For a single piece covering the light this is exactly
:func:`glossrt.lights.ltc.shade._texture_lookup`.)

Two shading modes on top of :func:`visible_integrals`: :func:`shade_vertices` (the paper's
per-vertex shading, at each tree's own vertex position and normal) and :func:`shade_pixels`
(per pixel: the three vertex trees of the pixel's triangle evaluated with the pixel's own
position, normal, view and BRDF, blended by barycentrics; the paper's sec. 5 names
interpolating vertex trees for per-fragment shadows as future work). Both combine ``i_d``,
``i_s`` with albedo, ``F0``, the LTC norm and Fresnel moment as :func:`ltc.shade_frame` does.
"""

from __future__ import annotations

import types
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import drjit as dr
import numpy as np

from ...backend import mi
from ...errors import GlossrtError
from ...jit import no_gc, opaque, owned
from ..ltc.shade import (
    PrefilteredTexture,
    _apply_minv,
    _device_lights,
    _integrals,
    _local,
    _mask,
    _table,
    _tex_eval,
    _tex_plane,
    light_uv,
    ltc_frame,
    prefiltered,
)
from ..polygon import _edge_sum, cosine_integral
from ..shading import ShadingPoints, light_vertices

__all__ = ["KMAX", "TRAVERSALS", "DeviceTrees", "shade_pixels", "shade_points", "shade_vertices",
           "visible_integrals"]

#: How :func:`visible_integrals` walks the trees: ``"kernel"`` (one kernel, a depth-first
#: loop per item with its stack in local memory) or ``"wavefront"`` (breadth-first, a few
#: kernels and a host synchronisation per tree level).
TRAVERSALS = ("kernel", "wavefront", "fused")
#: Most 2D vertices a piece keeps (see the module docstring).
KMAX = 16
#: Vertex slot counts the wavefront rounds up to (each size compiles its own kernels).
_SLOT_SIZES = (4, 6, 8, 12, KMAX)
#: Vertices per ``cosine_integral`` call (``polygon.K_MAX``); larger pieces are fanned.
_KI = 8


# --------------------------------------------------------------------------------------------
# trees on the device


def _dr_vec(t: type, a: np.ndarray):
    """(N, C) NumPy rows as a Dr.Jit C-vector type ``t`` in Dr.Jit-owned memory."""
    return t(*(owned(mi.Float, a[:, c]) for c in range(a.shape[1])))


def _int_array(name: str, x: Any, ndim: int, width: int | None) -> np.ndarray:
    a = np.asarray(x)
    if not np.issubdtype(a.dtype, np.integer):
        raise GlossrtError(f"BSPVT {name} must be integers, got dtype {a.dtype}")
    if a.ndim != ndim or (width is not None and a.shape[-1] != width):
        want = "(N,)" if ndim == 1 else f"(N, {width})"
        raise GlossrtError(f"BSPVT {name} must have shape {want}, got {a.shape}")
    return a.astype(np.int64)


def _float_array(name: str, x: Any, shape_tail: tuple) -> np.ndarray:
    try:
        a = np.asarray(x, np.float64)
    except (TypeError, ValueError) as e:
        raise GlossrtError(f"BSPVT {name} must be numeric: {e}") from e
    if a.ndim != 1 + len(shape_tail) or a.shape[1:] != shape_tail:
        raise GlossrtError(f"BSPVT {name} must have shape (N, {', '.join(map(str, shape_tail))})"
                           f", got {a.shape}" if shape_tail else
                           f"BSPVT {name} must have shape (N,), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise GlossrtError(f"BSPVT {name} contain NaN or Inf")
    return a


def _tree_depth(children: np.ndarray, roots: np.ndarray) -> int:
    """Most internal nodes on a root-to-leaf path (levels of the wavefront); a GlossrtError
    when some node is reachable by more than ``N`` steps (a cycle)."""
    n = len(children)
    frontier = np.unique(roots[roots >= 0])
    depth = 0
    while frontier.size:
        depth += 1
        if depth > n:
            raise GlossrtError("BSPVT children contain a cycle (a node is its own descendant)")
        nxt = children[frontier].ravel()
        frontier = np.unique(nxt[nxt >= 0])
    return depth


_TREE_ATTRS = ("lines", "children", "leaf_value", "roots", "positions", "normals")


@dataclass
class DeviceTrees:
    """The flat tree arrays of all vertices, uploaded once (opaque Dr.Jit arrays).

    ``lines`` (3 N floats: ``a, b, c`` per node), ``children`` (2 N: left, right), ``leaf_value``
    (L), ``roots`` (6 V: per vertex and face), ``positions`` / ``normals`` (V lanes);
    ``n_vertices`` = V and ``depth`` = most internal nodes on a root-to-leaf path. Build it with
    :meth:`of` from any object with the attributes of :class:`glossrt.lights.bspvt.build.BSPVT`."""

    lines: mi.Float
    children: mi.Int32
    leaf_value: mi.Float
    roots: mi.Int32
    positions: mi.Point3f
    normals: mi.Vector3f
    n_vertices: int
    depth: int

    @classmethod
    def of(cls, trees: Any) -> DeviceTrees:
        """Validate and upload ``trees`` (``lines`` (N, 3), ``children`` (N, 2), ``leaf_value``
        (L,), ``roots`` (V, 6), ``positions`` and ``normals`` (V, 3)); a :class:`DeviceTrees`
        is returned as it is. Raises GlossrtError naming the problem: wrong shapes, NaN / Inf,
        child or root codes out of range, leaf values outside [0, 1], cycles.

        The upload (and its validation, ~7 ms for 5K vertices) is cached on ``trees`` with the
        arrays it was made from: treat a BSPVT's arrays as read-only (assign new arrays to
        change them; changes made in place are not seen)."""
        if isinstance(trees, DeviceTrees):
            return trees
        for attr in _TREE_ATTRS:
            if not hasattr(trees, attr):
                raise GlossrtError(f"BSPVT trees need the attribute {attr!r}")
        # the arrays themselves (held: no id reuse) and the variant (the device) key the cache
        arrays = (mi.variant(), *(getattr(trees, a) for a in _TREE_ATTRS))
        cached = getattr(trees, "_glossrt_device", None)
        if cached is not None and cached[0][0] == arrays[0] and all(
                a is b for a, b in zip(cached[0][1:], arrays[1:], strict=True)):
            return cached[1]
        dev = cls._upload(trees)
        try:  # kept with the arrays it was made from (replaced arrays upload anew)
            trees._glossrt_device = (arrays, dev)
        except AttributeError:  # objects without a __dict__
            pass
        return dev

    @classmethod
    def _upload(cls, trees: Any) -> DeviceTrees:
        lines = _float_array("lines", trees.lines, (3,))
        children = _int_array("children", trees.children, 2, 2)
        leaf = _float_array("leaf_value", trees.leaf_value, ())
        roots = _int_array("roots", trees.roots, 2, 6)
        pos = _float_array("positions", trees.positions, (3,))
        nrm = _float_array("normals", trees.normals, (3,))
        n, nl, nv = len(lines), len(leaf), len(roots)
        if len(children) != n:
            raise GlossrtError(f"BSPVT children ({len(children)}) and lines ({n}) differ in "
                               "length")
        if len(pos) != nv or len(nrm) != nv:
            raise GlossrtError(f"BSPVT positions / normals ({len(pos)}, {len(nrm)}) must have "
                               f"one row per vertex of roots ({nv})")
        if nl == 0 or nv == 0:
            raise GlossrtError(f"BSPVT has no {'leaves' if nl == 0 else 'vertices'}")
        if np.any((leaf < 0) | (leaf > 1)):
            raise GlossrtError("BSPVT leaf values (mean visibilities) must lie in [0, 1]")
        for name, codes in (("children", children), ("roots", roots)):
            bad = ((codes >= 0) & (codes >= n)) | ((codes < 0) & (~codes >= nl))
            if bad.any():
                raise GlossrtError(f"BSPVT {name} contain codes out of range ({int(bad.sum())}"
                                   f"; {n} nodes, {nl} leaves)")
        ab = np.hypot(lines[:, 0], lines[:, 1])
        if np.any(ab < 1e-6):
            raise GlossrtError("BSPVT lines need (a, b) != 0")
        depth = _tree_depth(children, roots)
        if n == 0:  # keep the gathers valid (never read)
            lines, children = np.zeros((1, 3)), np.full((1, 2), -1)
        nl_ = np.linalg.norm(nrm, axis=1)
        if np.any(nl_ < 1e-12):
            raise GlossrtError("BSPVT normals must be non-zero")
        nrm = nrm / nl_[:, None]
        return cls(owned(mi.Float, lines.ravel()), owned(mi.Int32, children.ravel()),
                   owned(mi.Float, leaf), owned(mi.Int32, roots.ravel()),
                   _dr_vec(mi.Point3f, pos), _dr_vec(mi.Vector3f, nrm), nv, depth)


# --------------------------------------------------------------------------------------------
# cube faces and clipping (branch-free per lane)


def _face_axes(f: mi.UInt32):
    k = f >> 1
    sg = dr.select((f & 1) == 0, mi.Float(1.0), mi.Float(-1.0))
    return k, sg


def _face_coords(f: mi.UInt32, d) -> tuple:
    """``(w, x, y) = (sg d_k, d_u, d_v)`` of face ``f`` (per lane)."""
    k, sg = _face_axes(f)
    w = sg * dr.select(k == 0, d.x, dr.select(k == 1, d.y, d.z))
    x = dr.select(k == 0, d.y, dr.select(k == 1, d.z, d.x))
    y = dr.select(k == 0, d.z, dr.select(k == 1, d.x, d.y))
    return w, x, y


def _lift(f: mi.UInt32, s: mi.Float, t: mi.Float) -> mi.Vector3f:
    """``dir(f, s, t) = sg e_k + s e_u + t e_v`` (unnormalised; BSPVT conventions)."""
    k, sg = _face_axes(f)
    return mi.Vector3f(dr.select(k == 0, sg, dr.select(k == 1, t, s)),
                       dr.select(k == 0, s, dr.select(k == 1, sg, t)),
                       dr.select(k == 0, t, dr.select(k == 1, s, sg)))


def _clip_emissions(comps: list, n: mi.UInt32, dist: list):
    """Sutherland and Hodgman's emissions, in order, for :func:`_clip` and
    :func:`_clip_into`: per edge ``a -> b`` of the polygon ``comps`` (``n`` slots used),
    ``(a, a inside)`` and ``(crossing, exactly one end inside)``; values are lists over the
    coordinates."""
    k = len(dist)
    for i in range(k):
        active = n > i
        if i + 1 < k:
            wrap = n > i + 1
            b = [dr.select(wrap, comp[i + 1], comp[0]) for comp in comps]
            db = dr.select(wrap, dist[i + 1], dist[0])
        else:
            b = [comp[0] for comp in comps]
            db = dist[0]
        a, da = [comp[i] for comp in comps], dist[i]
        a_in, b_in = da >= 0.0, db >= 0.0
        crosses = active & (a_in ^ b_in)
        t = da / dr.select(crosses, da - db, 1.0)
        yield a, active & a_in
        yield [ac + (bc - ac) * t for ac, bc in zip(a, b, strict=True)], crosses


def _clip(comps: list, n: mi.UInt32, dist: list, kout: int,
          raw: bool = False) -> tuple[list, mi.UInt32]:
    """Sutherland and Hodgman (1974): the convex polygon ``comps`` (a list over coordinates of
    lists over vertex slots; the first ``n`` slots used) clipped to ``{dist >= 0}`` (``dist``: a
    value per slot, affine in the coordinates). Returns the clipped polygon with ``kout``
    slots and its count (emissions beyond ``kout`` are dropped). Vertex order is kept, so the
    winding is too. Each edge ``a -> b`` emits ``a`` if ``d_a >= 0`` and, if exactly one end is
    inside, the crossing ``a + (b - a) d_a / (d_a - d_b)``; emitted values go to slot ``c``
    (the running count) through ``dr.select``."""
    width = dr.width(n)
    zero = dr.zeros(mi.Float, width)
    out = [[zero] * kout for _ in comps]
    c = dr.zeros(mi.UInt32, width)
    for j, (value, emit) in enumerate(_clip_emissions(comps, n, dist)):
        for s in range(min(j, kout - 1) + 1):
            hit = emit & (c == s)
            for ci in range(len(comps)):
                out[ci][s] = dr.select(hit, value[ci], out[ci][s])
        c = c + dr.select(emit, mi.UInt32(1), mi.UInt32(0))
    return out, (c if raw else dr.minimum(c, kout))


def _area2(s: list, t: list, n: mi.UInt32) -> mi.Float:
    """Twice the signed area of the 2D polygon (first ``n`` slots; shoelace formula)."""
    acc = dr.zeros(mi.Float, dr.width(n))
    k = len(s)
    for i in range(k):
        if i + 1 < k:
            wrap = n > i + 1
            sb, tb = dr.select(wrap, s[i + 1], s[0]), dr.select(wrap, t[i + 1], t[0])
        else:
            sb, tb = s[0], t[0]
        acc = acc + dr.select(n > i, s[i] * tb - sb * t[i], 0.0)
    return acc


def _root_items(dev: DeviceTrees, tree_index: mi.UInt32, rel: list, q: mi.UInt32,
                f: mi.UInt32) -> tuple[_Items, mi.Bool]:
    """Root work items of the lanes ``(q, f)`` (query, face): the light (``rel``: its vertices
    relative to each query) clipped to face ``f``'s frustum and projected (module docstring,
    step 1), at the root of tree ``tree_index[q]``; and whether the piece is a non-degenerate
    polygon."""
    ws, xs, ys = [], [], []
    for v in rel:
        w, x, y = _face_coords(f, dr.gather(mi.Vector3f, v, q))
        ws.append(w)
        xs.append(x)
        ys.append(y)
    comps, cnt = [ws, xs, ys], dr.full(mi.UInt32, len(rel), dr.width(q))
    for sx, sy in ((-1.0, 0.0), (1.0, 0.0), (0.0, -1.0), (0.0, 1.0)):
        # the face's frustum: w + sx x >= 0, w + sy y >= 0 (planes through the origin)
        dist = [w + sx * x + sy * y for w, x, y in zip(*comps, strict=True)]
        comps, cnt = _clip(comps, cnt, dist, len(dist) + 1)
    s_l, t_l = [], []
    for w, x, y in zip(*comps, strict=True):
        # gnomonic projection: (s, t) = (d_u, d_v) / (sg d_k); w > 0 inside the frustum
        inv = dr.select(w > 0.0, dr.rcp(w), 0.0)
        s_l.append(dr.clip(x * inv, -1.0, 1.0))
        t_l.append(dr.clip(y * inv, -1.0, 1.0))
    tree = dr.gather(mi.UInt32, tree_index, q)
    code = dr.gather(mi.Int32, dev.roots, tree * 6 + f)
    keep = (cnt >= 3) & (dr.abs(_area2(s_l, t_l, cnt)) > 0.0)
    return _Items(q, f, code, cnt, s_l, t_l), keep


# --------------------------------------------------------------------------------------------
# the wavefront


class _Items:
    """Work items: query ``q``, face ``f``, node code ``code`` (tree encoding), 2D polygon
    ``s``, ``t`` (lists of slots) with ``n`` vertices used."""

    __slots__ = ("code", "f", "n", "q", "s", "t")

    def __init__(self, q, f, code, n, s, t):
        self.q, self.f, self.code, self.n, self.s, self.t = q, f, code, n, s, t

    def fields(self) -> list:
        return [self.q, self.f, self.code, self.n, *self.s, *self.t]

    def take(self, idx: mi.UInt32) -> _Items:
        g = dr.gather
        return _Items(g(mi.UInt32, self.q, idx), g(mi.UInt32, self.f, idx),
                      g(mi.Int32, self.code, idx), g(mi.UInt32, self.n, idx),
                      [g(mi.Float, x, idx) for x in self.s], [g(mi.Float, x, idx) for x in self.t])

    def trim(self) -> _Items:
        """Keep as many vertex slots as the items use, rounded up to one of
        :data:`_SLOT_SIZES` (fewer slots: smaller kernels; few sizes: few kernels to compile).
        Extra slots are zero (ignored: every use reads the first ``n``)."""
        used = int(dr.max(self.n)[0])
        k = next(b for b in _SLOT_SIZES if b >= used)
        if k < len(self.s):
            self.s, self.t = self.s[:k], self.t[:k]
        elif k > len(self.s):
            pad = [dr.zeros(mi.Float, dr.width(self.n))] * (k - len(self.s))
            self.s, self.t = self.s + pad, self.t + pad
        return self


def _split(dev: DeviceTrees, items: _Items, idx: mi.UInt32, n_items) -> _Items:
    """The children ``idx`` of the items' nodes: lanes ``[0, N)`` are left children
    (``d < 0``), ``[N, 2N)`` right ones (``d >= 0``) of item ``idx mod N`` (Okuno & Iwasaki,
    sec. 3.2-3.3: the node's line splits the projected light)."""
    side = idx >= n_items
    par = dr.select(side, idx - n_items, idx)
    it = items.take(par)
    node = mi.UInt32(it.code)
    a = dr.gather(mi.Float, dev.lines, node * 3)
    b = dr.gather(mi.Float, dev.lines, node * 3 + 1)
    c = dr.gather(mi.Float, dev.lines, node * 3 + 2)
    sgn = dr.select(side, mi.Float(1.0), mi.Float(-1.0))
    dist = [sgn * (a * s + b * t + c) for s, t in zip(it.s, it.t, strict=True)]
    (s, t), n = _clip([it.s, it.t], it.n, dist, min(len(it.s) + 1, KMAX))
    child = dr.gather(mi.Int32, dev.children, node * 2 + mi.UInt32(side))
    return _Items(it.q, it.f, child, n, s, t)


def _cut(dev: DeviceTrees, node: mi.UInt32, side, s: list, t: list, n: mi.UInt32) -> tuple:
    """Node ``node``'s line ``a s + b t + c`` against the piece ``(s, t)`` (``n`` vertices) for
    its child on ``side`` (0 / False: left, ``d < 0``; 1 / True: right, ``d >= 0``; a Python
    int or a per-lane ``mi.Bool``): ``(dist, some, child, leaf, val)``, the vertices' signed
    distances towards that side, whether some vertex lies strictly on it (else the child's
    piece has zero area), the child's code, whether it is a leaf and its mean visibility
    (Okuno & Iwasaki, sec. 3.2-3.3)."""
    a = dr.gather(mi.Float, dev.lines, node * 3)
    b = dr.gather(mi.Float, dev.lines, node * 3 + 1)
    c = dr.gather(mi.Float, dev.lines, node * 3 + 2)
    if isinstance(side, int):
        sgn, off = (1.0 if side else -1.0), side
    else:
        sgn, off = dr.select(side, mi.Float(1.0), mi.Float(-1.0)), mi.UInt32(side)
    dist = [sgn * (a * sj + b * tj + c) for sj, tj in zip(s, t, strict=True)]
    some = dr.zeros(mi.Bool, dr.width(n))
    for j, d in enumerate(dist):
        some = some | ((n > j) & (d > 0.0))
    child = dr.gather(mi.Int32, dev.children, node * 2 + off)
    leaf = child < 0
    val = dr.gather(mi.Float, dev.leaf_value, mi.UInt32(~child), leaf)
    return dist, some, child, leaf, val


def _stack(entries: int, k: int, code, n, s: list, t: list) -> tuple:
    """A traversal's stack in local memory, ``(codes, counts, s, t)`` with ``k`` vertex slots
    per entry and at least ``entries`` entries (rounded up to a multiple of 8, so that trees
    of similar depth share the compiled kernel), its entry 0 the pieces ``(code, n, s, t)``
    (slots past ``len(s)`` zero, past ``k`` dropped)."""
    depth = -(-entries // 8) * 8
    codes = dr.alloc_local(mi.Int32, depth)
    counts = dr.alloc_local(mi.UInt32, depth)
    ls = dr.alloc_local(mi.Float, depth * k)
    lt = dr.alloc_local(mi.Float, depth * k)
    codes.write(code, 0)
    counts.write(n, 0)
    zero = dr.zeros(mi.Float, dr.width(n))
    for j in range(k):
        ls.write(s[j] if j < len(s) else zero, j)
        lt.write(t[j] if j < len(t) else zero, j)
    return codes, counts, ls, lt


def _pop(top: mi.UInt32, codes, counts, ls, lt, k: int) -> tuple:
    """Stack entry ``top`` of the local-memory stack: ``(code, count, s, t)`` (``k`` slots)."""
    base = top * k
    return (codes.read(top), counts.read(top), [ls.read(base + j) for j in range(k)],
            [lt.read(base + j) for j in range(k)])


def _children_masks(dev: DeviceTrees, items: _Items, n_items):
    """For the 2N children of the items: (non-empty at an internal node, non-empty at a leaf
    with mean visibility > 0). A child is non-empty when some parent vertex lies strictly on
    its side (otherwise it has zero area)."""
    width = 2 * dr.width(items.n)
    idx = dr.arange(mi.UInt32, width)
    side = idx >= n_items
    par = dr.select(side, idx - n_items, idx)
    code = dr.gather(mi.Int32, items.code, par)
    n = dr.gather(mi.UInt32, items.n, par)
    s = [dr.gather(mi.Float, x, par) for x in items.s]
    t = [dr.gather(mi.Float, x, par) for x in items.t]
    _, some, _, leaf, val = _cut(dev, mi.UInt32(code), side, s, t, n)
    # Okuno & Iwasaki, sec. 3.3 / fig. 5 (d): a leaf with mean visibility 0 is dropped
    return some & ~leaf, some & leaf & (val > 0.0)


@dataclass
class _Queries:
    """Per-query data the leaf integration gathers (evaluated arrays)."""

    t1: mi.Vector3f
    t2: mi.Vector3f
    n: mi.Vector3f
    coeffs: mi.Vector4f
    plane_d: tuple | None = None
    plane_s: tuple | None = None


def _gather_tuple(src: tuple, q: mi.UInt32) -> tuple:
    return tuple(dr.gather(type(x), x, q) for x in src)


def _accumulate(pieces: _Items, dev: DeviceTrees, qd: _Queries, acc: dict, two_sided,
                texture) -> None:
    """Integrate the (evaluated, trimmed) leaf pieces and add ``v i_d``, ``v i_s`` (colours
    with a texture) to the per-query accumulators (Okuno & Iwasaki, eq. 2: sum over pieces of
    mean visibility times the piece's LTC integral). Pieces with more than 8 vertices are
    fans of sub-polygons sharing vertex 0, ``[0..7]``, ``[0, 7..13]``, ``[0, 13..15]``: the
    first for every piece, the others on the compacted pieces that have them."""
    _accumulate_groups(pieces, [0], dev, qd, acc, two_sided, texture)
    k = len(pieces.s)
    more = [g for g in (1, 2) if _fan_start(g) + 1 < k]
    if more:
        idx = dr.compress(pieces.n > _KI)
        if dr.width(idx):
            _accumulate_groups(pieces.take(idx), more, dev, qd, acc, two_sided, texture)
    acc["pieces"] += dr.width(pieces.q)


def _fan_start(g: int) -> int:
    return 0 if g == 0 else _KI - 1 + (_KI - 2) * (g - 1)


def _piece_integrals(f: mi.UInt32, s: list, t: list, n: mi.UInt32, groups, frame: tuple,
                     coeffs: mi.Vector4f, two_sided) -> tuple:
    """The pieces ``(f, s, t, n)`` lifted to the shading ``frame`` ``(t1, t2, n)``: returns
    ``(local vertices, i_d, i_s)``, the integrals summed over the fan ``groups``
    (:func:`_fan_integrals`)."""
    local = _lift_local(f, s, t, frame)
    return (local, *_fan_integrals(local, n, groups, coeffs, two_sided))


def _lift_local(f: mi.UInt32, s: list, t: list, frame: tuple) -> list:
    """Piece vertices back to directions (a polygon on the face's plane ``sg d_k = 1``) in the
    shading frame ``(t1, t2, n)``."""
    t1, t2, nn = frame
    local = []
    for sj, tj in zip(s, t, strict=True):
        d = _lift(f, sj, tj)
        local.append(mi.Vector3f(dr.dot(d, t1), dr.dot(d, t2), dr.dot(d, nn)))
    return local


def _fan_integrals(local: list, n: mi.UInt32, groups, coeffs: mi.Vector4f,
                   two_sided) -> tuple:
    """``(i_d, i_s)`` of the pieces ``local`` (``n`` vertices used) summed over the fan
    ``groups`` (module docstring; Heitz et al. 2016 as ``ltc._integrals``: the identity and
    ``M^-1``-transformed piece)."""
    i_d = i_s = None
    for g in groups:
        start = _fan_start(g)
        if g == 0:
            verts, cnt = local[:_KI], n
        else:
            verts = [local[0]] + local[start:start + _KI - 1]
            rest = dr.maximum(mi.Int32(n) - start, 0)
            cnt = mi.UInt32(dr.select(rest >= 2, dr.minimum(rest, _KI - 1) + 1, 0))
        d_g = cosine_integral(verts, cnt, two_sided)
        s_g = cosine_integral(_apply_minv(coeffs, verts), cnt, two_sided)
        i_d = d_g if i_d is None else i_d + d_g
        i_s = s_g if i_s is None else i_s + s_g
    return i_d, i_s


def _accumulate_groups(pieces: _Items, groups: list, dev: DeviceTrees, qd: _Queries, acc: dict,
                       two_sided, texture) -> None:
    q = pieces.q
    val = dr.gather(mi.Float, dev.leaf_value, mi.UInt32(~pieces.code))
    t1 = dr.gather(mi.Vector3f, qd.t1, q)
    t2 = dr.gather(mi.Vector3f, qd.t2, q)
    nn = dr.gather(mi.Vector3f, qd.n, q)
    coeffs = dr.gather(mi.Vector4f, qd.coeffs, q)
    local, i_d, i_s = _piece_integrals(pieces.f, pieces.s, pieces.t, pieces.n, groups,
                                       (t1, t2, nn), coeffs, two_sided)
    if texture is None:
        w_d, w_s = val * i_d, val * i_s
    else:
        light_uv, tex = texture
        # the whole piece's vector form factor (Lambert / Arvo edge sum over all vertices)
        f_d = _edge_sum(local, pieces.n, True)
        f_s = _edge_sum(_apply_minv(coeffs, local), pieces.n, True)
        col_d = _tex_eval(light_uv, tex, _gather_tuple(qd.plane_d, q), f_d)
        col_s = _tex_eval(light_uv, tex, _gather_tuple(qd.plane_s, q), f_s)
        w_d, w_s = col_d * (val * i_d), col_s * (val * i_s)
    # Okuno & Iwasaki, eq. 2: B ~= L sum_i v_i int_{P_i} f cos
    dr.scatter_reduce(dr.ReduceOp.Add, acc["d"], w_d, q)
    dr.scatter_reduce(dr.ReduceOp.Add, acc["s"], w_s, q)


def _capacity(n_items: int) -> int:
    """Leaf pieces per side the traversal's output holds at first (the polygon-light scene
    gives about 2 per internal root item)."""
    return 4 * n_items + 64


#: Root items per kernel traversal: bounds its piece buffers (4 pieces per item and side at
#: first, 19 values each with 8 slots: ~600 bytes per item) and keeps slot indices in 32 bits.
_TRAVERSE_CHUNK = 1 << 20
#: Vertex slots of the traversal's first pass (pieces rarely have more; lanes whose pieces
#: would are redone with :data:`KMAX`).
_K_FIRST = 8


def _traverse(dev: DeviceTrees, items: _Items, stats: dict | None) -> list:
    """Depth-first traversal of the items' subtrees in one kernel per pass (one lane per
    item, a ``dr.while_loop`` with a stack in local memory; Okuno & Iwasaki, sec. 3.3 and
    fig. 5): the same splits as the wavefront (:func:`_split`, :func:`_children_masks`),
    without a host synchronisation per tree level.

    The first pass keeps :data:`_K_FIRST` vertex slots per piece (less work per split); a lane
    that would need more (a piece with more vertices) stops, its pieces are discarded and it
    is redone in a second pass with :data:`KMAX` slots (truncated there as the wavefront
    does). Returns the lists of leaf pieces (evaluated, in no particular order).
    ``stats``: ``items`` += the internal items split (as the wavefront counts them),
    ``levels`` = the most iterations of one lane."""
    width = dr.width(items.n)
    if width > _TRAVERSE_CHUNK:  # bounded output buffers (32-bit slot indices, memory)
        out = []
        for lo in range(0, width, _TRAVERSE_CHUNK):
            idx = dr.arange(mi.UInt32, lo, min(lo + _TRAVERSE_CHUNK, width))
            out += _traverse(dev, items.take(idx), stats)
        return out
    out = []
    lanes = None
    for k in (_K_FIRST, KMAX):
        sub = items if lanes is None else items.take(lanes)
        pieces, over, n_iter = _traverse_pass(dev, sub, k, _capacity(dr.width(sub.n)))
        lanes = dr.compress(over)
        if stats is not None:
            n_done = dr.select(over, 0, n_iter)
            stats["items"] += int(dr.sum(n_done)[0])
            stats["levels"] = max(stats["levels"], int(dr.max(n_done)[0]))
        if pieces is not None:
            lane, pieces = pieces
            if dr.width(lanes):  # drop the pieces of the lanes to redo
                keep = dr.compress(~dr.gather(mi.Bool, over, lane))
                pieces = pieces.take(keep) if dr.width(keep) else None
            if pieces is not None:
                out.append(pieces)
        if not dr.width(lanes):
            break
    return out


def _traverse_pass(dev: DeviceTrees, items: _Items, k: int, cap: int):
    """One pass of :func:`_traverse` with ``k`` vertex slots (:func:`_traverse_kernel`):
    returns ``((lane, pieces) or None, over, iterations)``. Reruns once with the exact
    capacity when more than ``cap`` pieces per side come out."""
    while True:
        out, counters, over, n_iter = _traverse_kernel(dev, items, k, cap)
        used = [int(x[0]) for x in counters]
        if max(used) <= cap:
            break
        cap = max(used)
    total = used[0] + used[1]
    if total == 0:
        return None, over, n_iter
    o_lane, o_code, o_n, o_s, o_t = out
    idx = dr.arange(mi.UInt32, total)
    idx = dr.select(idx < used[0], idx, idx - used[0] + cap)
    lane = dr.gather(mi.UInt32, o_lane, idx)
    pieces = _Items(dr.gather(mi.UInt32, items.q, lane), dr.gather(mi.UInt32, items.f, lane),
                    dr.gather(mi.Int32, o_code, idx), dr.gather(mi.UInt32, o_n, idx),
                    [dr.gather(mi.Float, o_s, idx * k + j) for j in range(k)],
                    [dr.gather(mi.Float, o_t, idx * k + j) for j in range(k)])
    return (lane, pieces), over, n_iter


def _traverse_kernel(dev: DeviceTrees, items: _Items, k: int, cap: int):
    """The traversal kernel with ``k`` vertex slots and room for ``cap`` pieces per side.
    Returns the evaluated output ``(lane, leaf code, count, s, t)`` (per slot; ``s``, ``t``
    flat, slot * k + j; unused vertex slots 0 as :func:`_clip` leaves them; left pieces in
    slots ``[0, cap)``, right ones in ``[cap, 2 cap)``), the two counters (pieces wanted per
    side, possibly more than ``cap``: those were not written), ``over`` (the lanes that
    needed more than ``k`` slots; never set when ``k == KMAX``, which truncates as the
    wavefront does) and each lane's iterations.

    Each iteration pops an internal node's piece and cuts it by the node's line into its
    left (``d < 0``) and right (``d >= 0``) children (:func:`_clip` in registers); a non-empty
    child at an internal node is written onto the stack, one at a leaf with mean visibility
    > 0 into the output (a slot from ``dr.scatter_inc`` on the side's counter: a counter
    bumped twice in one loop body would have to be evaluated inside it), empty children and
    leaves with visibility 0 are dropped. The stack holds at most ``depth + 1`` entries (one
    pending sibling per level)."""
    truncate = k >= KMAX
    width = dr.width(items.n)
    # at most depth + 1 entries: one pending sibling per level
    codes, counts, ls, lt = _stack(dev.depth + 2, k, items.code, items.n, items.s, items.t)
    size = 2 * cap
    o_lane, o_n = dr.zeros(mi.UInt32, size), dr.zeros(mi.UInt32, size)
    o_code = dr.zeros(mi.Int32, size)
    o_s, o_t = dr.zeros(mi.Float, size * k), dr.zeros(mi.Float, size * k)
    counters = (dr.zeros(mi.UInt32, 1), dr.zeros(mi.UInt32, 1))
    # scatter targets: evaluated before the loop
    dr.make_opaque(o_lane, o_n, o_code, o_s, o_t, counters)
    lane_id = dr.arange(mi.UInt32, width)
    cap_ = dr.opaque(mi.UInt32, cap)
    one, none = mi.UInt32(1), mi.UInt32(0)

    def cond(sp, n_iter, over, codes, counts, ls, lt):
        return sp > 0

    def body(sp, n_iter, over, codes, counts, ls, lt):
        top = sp - 1
        code, n, s, t = _pop(top, codes, counts, ls, lt, k)
        node = mi.UInt32(code)
        for side in (0, 1):
            dist, some, child, leaf, val = _cut(dev, node, side, s, t, n)
            push = some & ~leaf
            emit = some & leaf & (val > 0.0)
            slot = dr.scatter_inc(counters[side], mi.UInt32(0), emit)
            emit = emit & (slot < cap_)
            slot = slot + side * cap_
            # the child onto the stack at `top` (the popped entry, now in registers) or out
            (cs, ct), cnt = _clip([s, t], n, dist, k, raw=True)
            dst_l, dst_o = top * k, slot * k
            for j in range(k):
                ls.write(cs[j], dst_l + j, push)
                lt.write(ct[j], dst_l + j, push)
                dr.scatter(o_s, cs[j], dst_o + j, emit)
                dr.scatter(o_t, ct[j], dst_o + j, emit)
            if not truncate:
                over = over | ((push | emit) & (cnt > k))
            cnt = dr.minimum(cnt, k)
            codes.write(child, top, push)
            counts.write(cnt, top, push)
            dr.scatter(o_lane, lane_id, slot, emit)
            dr.scatter(o_code, child, slot, emit)
            dr.scatter(o_n, cnt, slot, emit)
            top = top + dr.select(push, one, none)
        return dr.select(over, 0, top), n_iter + 1, over, codes, counts, ls, lt

    over0 = items.n > k
    sp = dr.select(over0, 0, dr.ones(mi.UInt32, width))
    n_iter = dr.zeros(mi.UInt32, width)
    _, n_iter, over, *_ = dr.while_loop((sp, n_iter, over0, codes, counts, ls, lt), cond, body)
    out = (o_lane, o_code, o_n, o_s, o_t)
    dr.eval(out, counters, n_iter, over)
    return out, counters, over, n_iter


def _clip_into(s: list, t: list, n: mi.UInt32, dist: list, ls, lt, dst, mask) -> mi.UInt32:
    """:func:`_clip` of the polygon ``(s, t)`` (``n`` of its slots used) to ``{dist >= 0}``,
    written vertex by vertex into the local-memory buffers ``ls``, ``lt`` from index ``dst``
    on where ``mask`` holds (at most ``len(s)`` vertices: the rest dropped, as ``_clip``
    does). Returns the number of vertices the clip produced (before that cap)."""
    k = len(s)
    one, none = mi.UInt32(1), mi.UInt32(0)
    cnt = dr.zeros(mi.UInt32, dr.width(n))
    for (vs, vt), e in _clip_emissions([s, t], n, dist):
        w = mask & e & (cnt < k)
        ls.write(vs, dst + cnt, w)
        lt.write(vt, dst + cnt, w)
        cnt = cnt + dr.select(e, one, none)
    return cnt


def _fused_integrals(dev: DeviceTrees, tree_index: mi.UInt32, p: mi.Point3f, n: mi.Vector3f,
                     wo: mi.Vector3f, coeffs: mi.Vector4f, world: list, two_sided,
                     width: int, stats: dict | None = None,
                     active: mi.Bool | None = None) -> tuple[mi.Float, mi.Float]:
    """Shadowed integrals ``(i_d, i_s)`` with no data-dependent array size and no host
    synchronisation (what ``dr.freeze`` can record): one lane per query and cube face
    (``width`` queries, an explicit int), the root items of :func:`_root_items` for every
    lane, and one ``dr.while_loop`` that both splits and integrates (Okuno & Iwasaki, eq. 2
    and sec. 3.3). Each iteration pops a stack entry (local memory, :data:`KMAX` vertex slots
    per piece, truncated as the wavefront does): at an internal node it cuts the piece by the
    node's line and pushes the non-empty children that are internal or leaves of visibility
    > 0; at a leaf it integrates the piece (:func:`_piece_integrals`) into the lane's sums.
    The six faces' sums are added per query at the end. Same pieces as the other
    traversals; no textured lights."""
    t1, t2 = ltc_frame(n, wo)

    def whole():
        return _integrals(_local(world, p, t1, t2, n), coeffs, two_sided)

    # dr.if_stmt: packets without an active lane (background pixels) skip the work (LLVM)
    nothing = dr.zeros(mi.Float, width)
    whole_d, whole_s = whole() if active is None else dr.if_stmt(
        (), active, whole, lambda: (nothing, mi.Float(nothing)))
    live = (whole_d > 0.0) | (whole_s > 0.0)
    if active is not None:
        live &= active
    rel = [mi.Vector3f(v - p) for v in world]
    lanes = dr.arange(mi.UInt32, 6 * width)
    nq = dr.opaque(mi.UInt32, width)
    f = lanes // nq
    q = lanes - f * nq
    lane_live = dr.gather(mi.Bool, live, q)
    slots = len(world) + 4  # the light clipped by a face's four frustum planes
    code0, cnt0, keep, *st0 = _fused_roots(dev, tree_index, rel, q, f, lane_live, width, slots)
    keep &= lane_live
    leaf0 = code0 < 0
    val0 = dr.gather(mi.Float, dev.leaf_value, mi.UInt32(~code0), leaf0)
    start = keep & (~leaf0 | (val0 > 0.0))
    frame = (dr.gather(mi.Vector3f, t1, q), dr.gather(mi.Vector3f, t2, q),
             dr.gather(mi.Vector3f, n, q))
    lane_coeffs = dr.gather(mi.Vector4f, coeffs, q)
    acc_d, acc_s, n_split, n_piece = _fused_walk(dev, start, code0, cnt0, st0[:slots],
                                                 st0[slots:], f, frame, lane_coeffs,
                                                 two_sided, width)
    i_d = i_s = None
    for face in range(6):  # the six faces' sums per query
        idx = dr.arange(mi.UInt32, width) + face * nq
        d_f, s_f = dr.gather(mi.Float, acc_d, idx), dr.gather(mi.Float, acc_s, idx)
        i_d = d_f if i_d is None else i_d + d_f
        i_s = s_f if i_s is None else i_s + s_f
    if stats is not None:
        stats.update(levels=int(dr.max(n_split + n_piece)[0]),
                     items=int(dr.sum(n_split)[0]), pieces=int(dr.sum(n_piece)[0]),
                     live=int(dr.sum(mi.UInt32(live))[0]))
    # exact zeros where the whole light gives 0 (as ltc._integrals)
    return dr.select(whole_d > 0.0, i_d, 0.0), dr.select(whole_s > 0.0, i_s, 0.0)


def _fused_roots(dev: DeviceTrees, tree_index: mi.UInt32, rel: list, q: mi.UInt32,
                 f: mi.UInt32, lane_live: mi.Bool, width: int, slots: int) -> tuple:
    """:func:`_fused_integrals`' root items, one lane per query ``q`` and face ``f``:
    ``(code, n, keep, *s, *t)`` of :func:`_root_items` (``slots`` vertex slots each), zeros
    on lanes that are not ``lane_live`` (packets without a live lane skip the clipping)."""

    def clip_roots():
        roots, keep = _root_items(dev, tree_index, rel, q, f)
        return (roots.code, roots.n, keep, *roots.s, *roots.t)

    def no_roots():
        z = dr.zeros(mi.Float, 6 * width)
        return (dr.zeros(mi.Int32, 6 * width), dr.zeros(mi.UInt32, 6 * width),
                dr.zeros(mi.Bool, 6 * width), *[mi.Float(z) for _ in range(2 * slots)])

    return dr.if_stmt((), lane_live, clip_roots, no_roots)


def _fused_walk(dev: DeviceTrees, start: mi.Bool, code0: mi.Int32, cnt0: mi.UInt32, s0: list,
                t0: list, f: mi.UInt32, frame: tuple, lane_coeffs: mi.Vector4f, two_sided,
                width: int) -> tuple:
    """:func:`_fused_integrals`' loop: from each ``start`` lane's root piece (``code0``,
    ``cnt0`` vertices ``(s0, t0)``), pop, split and integrate until the lane's stack is
    empty. Returns per lane (query x face) ``(acc_d, acc_s, n_split, n_piece)``: the
    visibility-weighted integrals (evaluated) and the nodes split and leaf pieces integrated."""
    k = KMAX
    # internal nodes and leaf pieces waiting to be integrated: at most depth + 2 entries
    codes, counts, ls, lt = _stack(dev.depth + 3, k, code0, cnt0, s0, t0)
    one, none = mi.UInt32(1), mi.UInt32(0)

    def cond(sp, acc_d, acc_s, n_split, n_piece, codes, counts, ls, lt):
        return sp > 0

    def body(sp, acc_d, acc_s, n_split, n_piece, codes, counts, ls, lt):
        top = sp - 1
        code, cnt, s, t = _pop(top, codes, counts, ls, lt, k)
        at_leaf = code < 0
        inner = ~at_leaf

        # dr.if_stmt: the LLVM backend skips a branch no lane of a packet takes
        def integrate(acc_d, acc_s):
            # a leaf piece: v * its integrals (Okuno & Iwasaki, eq. 2); fans past 8 vertices
            val = dr.gather(mi.Float, dev.leaf_value, mi.UInt32(~code))
            local = _lift_local(f, s, t, frame)
            i_d, i_s = _fan_integrals(local, cnt, (0,), lane_coeffs, two_sided)
            i_d, i_s = dr.if_stmt(
                (i_d, i_s), cnt > _KI,
                lambda d, s_: tuple(x + y for x, y in zip(
                    (d, s_), _fan_integrals(local, cnt, (1, 2), lane_coeffs, two_sided),
                    strict=True)),
                lambda d, s_: (d, s_))
            return acc_d + val * i_d, acc_s + val * i_s

        acc_d, acc_s = dr.if_stmt((acc_d, acc_s), at_leaf, integrate, lambda d, s_: (d, s_))

        def split(top):
            # an internal node: its line cuts the piece into the children
            node = mi.UInt32(code)
            dst = top
            for side in (0, 1):
                dist, some, child, leaf, v = _cut(dev, node, side, s, t, cnt)
                push = some & (~leaf | (v > 0.0))
                # into slot `dst` (first the popped entry, now in registers)
                c_out = _clip_into(s, t, cnt, dist, ls, lt, dst * k, push)
                codes.write(child, dst, push)
                counts.write(dr.minimum(c_out, k), dst, push)
                dst = dst + dr.select(push, one, none)
            return (dst,)

        top = dr.if_stmt((top,), inner, split, lambda x: (x,))[0]
        n_split = n_split + dr.select(inner, one, none)
        n_piece = n_piece + dr.select(at_leaf, one, none)
        return top, acc_d, acc_s, n_split, n_piece, codes, counts, ls, lt

    sp = dr.select(start, one, none)
    acc = dr.zeros(mi.Float, 6 * width)
    ctr = dr.zeros(mi.UInt32, 6 * width)
    _, acc_d, acc_s, n_split, n_piece, *_ = dr.while_loop(
        (sp, acc, mi.Float(acc), ctr, mi.UInt32(ctr), codes, counts, ls, lt), cond, body)
    dr.eval(acc_d, acc_s)  # one loop kernel for both (the caller's gathers would run it twice)
    return acc_d, acc_s, n_split, n_piece


def _check_traversal(traversal: str) -> None:
    if traversal not in TRAVERSALS:
        raise GlossrtError(f"unknown BSPVT traversal {traversal!r}; choose one of {TRAVERSALS}")


def _light_array(vertices: Any) -> np.ndarray:
    return light_vertices(types.SimpleNamespace(vertices=vertices))


def _check_lanes(tree_index, dev: DeviceTrees, *vecs) -> None:
    """GlossrtError unless every tree index (one ``mi.UInt32`` or a list of them) is in
    range and every vector is finite: one host synchronisation."""
    ok = None
    for t in tree_index if isinstance(tree_index, list) else [tree_index]:
        ok_t = dr.all(t < dev.n_vertices)
        ok = ok_t if ok is None else ok & ok_t
    fin = dr.all(dr.all(dr.isfinite(mi.Vector3f(vecs[0]))))
    for v in vecs[1:]:
        fin = fin & dr.all(dr.all(dr.isfinite(v)))
    dr.eval(ok, fin)
    if not bool(ok[0]):
        raise GlossrtError(f"tree_index out of range (the trees have {dev.n_vertices} vertices)")
    if not bool(fin[0]):
        raise GlossrtError("shading points, normals, views or LTC coefficients contain NaN or "
                           "Inf")


def _texture_arg(texture: tuple | None, n_vertices: int) -> tuple | None:
    """:func:`visible_integrals`' ``texture`` ``(light, PrefilteredTexture)``, checked, as the
    ``(light_uv(light), texture)`` the pieces read; ``None`` for an untextured light."""
    if texture is None:
        return None
    light, tex = texture
    if not isinstance(tex, PrefilteredTexture):
        raise GlossrtError("texture must be (light, PrefilteredTexture)")
    uv = np.asarray(getattr(light, "uv", None), np.float64)
    if uv.shape != (n_vertices, 2) or not np.all(np.isfinite(uv)):
        raise GlossrtError(f"a textured light needs finite uv ({n_vertices}, 2), got "
                           f"{uv.shape}")
    return (light_uv(light), tex)


def _whole_light(world: list, p, n, wo, coeffs, two_sided, textured: bool) -> tuple:
    """Per query: the shading frame (:class:`_Queries`, with the light's texture planes when
    ``textured``), the light's vertices relative to ``p`` and the whole light's diffuse and
    specular integrals (for exact zeros and pruning), evaluated."""
    t1, t2 = ltc_frame(n, wo)
    local = _local(world, p, t1, t2, n)
    local_s = _apply_minv(coeffs, local)
    whole_d = cosine_integral(local, None, two_sided)
    whole_s = cosine_integral(local_s, None, two_sided)
    rel = [mi.Vector3f(v - p) for v in world]
    qd = _Queries(t1, t2, n, coeffs)
    if textured:
        qd.plane_d, qd.plane_s = _tex_plane(local), _tex_plane(local_s)
    dr.eval(qd.t1, qd.t2, qd.n, qd.coeffs, whole_d, whole_s, rel, qd.plane_d, qd.plane_s)
    return qd, rel, whole_d, whole_s


def _root_pass(dev: DeviceTrees, tree_index: mi.UInt32, rel: list, live: mi.UInt32,
               n_live: int, qd: _Queries, acc: dict, two_sided, tex_arg) -> _Items | None:
    """The root items of the ``live`` queries: query x face, the light clipped to each face's
    frustum and projected. Faces whose root is a leaf are integrated into ``acc`` at once;
    returns the items whose root is a node, to traverse (``None``: there are none)."""
    lanes = dr.arange(mi.UInt32, 6 * n_live)
    nq = dr.opaque(mi.UInt32, n_live)
    f = lanes // nq
    q = dr.gather(mi.UInt32, live, lanes - f * nq)
    roots, keep = _root_items(dev, tree_index, rel, q, f)
    code = roots.code
    leaf = code < 0
    val = dr.gather(mi.Float, dev.leaf_value, mi.UInt32(~code), leaf)
    keep_int, keep_leaf = keep & ~leaf, keep & leaf & (val > 0.0)
    dr.eval(roots.fields(), keep_int, keep_leaf)
    idx_l = dr.compress(keep_leaf)
    if dr.width(idx_l):
        _accumulate(roots.take(idx_l).trim(), dev, qd, acc, two_sided, tex_arg)
    idx_i = dr.compress(keep_int)
    return roots.take(idx_i) if dr.width(idx_i) else None


def _wavefront(dev: DeviceTrees, items: _Items, qd: _Queries, acc: dict, two_sided, tex_arg,
               st: dict) -> None:
    """The ``"wavefront"`` traversal: one tree level per pass, the pieces that reach a leaf
    integrated into ``acc``, the others split again (``st`` counts levels and items)."""
    while items is not None:
        dr.eval(items.fields())
        items = items.trim()
        st["levels"] += 1
        st["items"] += dr.width(items.n)
        if st["levels"] > dev.depth:
            raise GlossrtError("BSPVT traversal deeper than the trees (internal error)")
        n_items = dr.opaque(mi.UInt32, dr.width(items.n))
        keep_int, keep_leaf = _children_masks(dev, items, n_items)
        dr.eval(keep_int, keep_leaf)
        idx_l = dr.compress(keep_leaf)
        if dr.width(idx_l):
            pieces = _split(dev, items, idx_l, n_items)
            dr.eval(pieces.fields())
            _accumulate(pieces.trim(), dev, qd, acc, two_sided, tex_arg)
        idx_i = dr.compress(keep_int)
        items = _split(dev, items, idx_i, n_items) if dr.width(idx_i) else None


def visible_integrals(trees: Any, tree_index: mi.UInt32, p: mi.Point3f, n: mi.Vector3f,
                      wo: mi.Vector3f, coeffs: mi.Vector4f, light_vertices: np.ndarray,
                      two_sided: bool, texture: tuple | None = None,
                      stats: dict | None = None, traversal: str = "kernel",
                      active: mi.Bool | None = None) -> tuple:
    """Shadowed LTC integrals ``(i_d, i_s)`` of one polygon light, one lane per query
    (Okuno & Iwasaki, eq. 2; the algorithm in the module docstring).

    ``trees``: a :class:`DeviceTrees` or any object with the BSPVT attributes (uploaded once
    and cached on it, :meth:`DeviceTrees.of`); ``tree_index``: the vertex whose tree
    each query reads; ``p``, ``n``, ``wo``: shading point, unit normal, unit view (towards the
    viewer; the visibility is looked up for directions from ``p`` even where ``p`` is not the
    tree's vertex); ``coeffs``: the LTC ``M^-1`` coefficients of each query
    (``LTCTable.lookup``); ``light_vertices``: (K, 3) world, ``3 <= K <= 8``, convex, planar;
    ``two_sided``: as :func:`glossrt.lights.polygon.cosine_integral`.

    Returns ``(i_d, i_s)`` (``mi.Float``): the sums over leaf pieces of mean visibility times
    the clamped-cosine integral of the piece and of its ``M^-1`` transform. With an
    all-visible tree they equal ``ltc._integrals`` of the whole light (exactly 0 where that is:
    light below the horizon, behind a one-sided light, plane through ``p``). ``texture``:
    ``(light, PrefilteredTexture)`` for a textured light (``light.uv`` (K, 2)): then colours
    ``(col_d, col_s)`` (``mi.Color3f``), each piece weighted by the prefiltered texture (module
    docstring). ``stats``: a dict to receive ``levels`` (tree levels of the wavefront; the
    most loop iterations of one lane in the kernel and fused traversals), ``items`` (split
    work items), ``pieces`` (integrated leaf pieces) and ``live`` (queries the whole light
    reaches); all traversals split the same items into the same pieces. ``active``: optional
    per-lane mask; lanes where it is False are not traversed and get 0.

    ``traversal`` (:data:`TRAVERSALS`): ``"kernel"`` (default) walks every item's subtree in
    one kernel (:func:`_traverse`), then integrates the pieces: about ten kernels and four host
    synchronisations whatever the trees' depth. ``"wavefront"`` runs a few kernels and host
    synchronisations per tree level (compaction), plus Python tracing of ~1-2 ms per level
    whatever the number of lanes (the 640x360 bench frame: 15 levels, 41 ms against 15 ms for
    the kernel, same pieces). ``"fused"`` (:func:`_fused_integrals`) splits and integrates in
    one loop over every query and face, with no host synchronisation (what ``dr.freeze``
    records: :func:`shade_points` with ``frozen=True``); it takes no textured light. On the
    CPU, pass inputs in
    Dr.Jit-owned memory (not arrays built straight from NumPy, whose buffer alignment varies
    between calls and makes the LLVM backend compile new kernels; see ``glossrt.jit.owned``)."""
    dev = DeviceTrees.of(trees)
    lv = _light_array(light_vertices)
    tree_index = mi.UInt32(tree_index)
    p, n, wo, coeffs = mi.Point3f(p), mi.Vector3f(n), mi.Vector3f(wo), mi.Vector4f(coeffs)
    width = dr.width(tree_index)
    for name, x in (("p", p), ("n", n), ("wo", wo), ("coeffs", coeffs)):
        if dr.width(x) != width:
            raise GlossrtError(f"visible_integrals: {name} has {dr.width(x)} lanes, "
                               f"tree_index {width}")
    _check_traversal(traversal)
    if width == 0:
        empty = mi.Color3f() if texture is not None else mi.Float()
        return empty, type(empty)(empty)
    _check_lanes(tree_index, dev, p, n, wo, coeffs)
    # opaque: one- and two-sided lights share kernels (cosine_integral takes a per-lane mask)
    two_sided = dr.opaque(mi.Bool, bool(two_sided))
    tex_arg = _texture_arg(texture, len(lv))
    world = [mi.Point3f(*opaque(v)) for v in lv]
    if traversal == "fused":
        if tex_arg is not None:
            raise GlossrtError("the fused BSPVT traversal does not take textured lights")
        st = {} if stats is not None else None
        i_d, i_s = _fused_integrals(dev, tree_index, p, n, wo, coeffs, world, two_sided,
                                    width, st, active)
        dr.eval(i_d, i_s)
        if stats is not None:
            stats.update(st, queries=width)
        return i_d, i_s
    qd, rel, whole_d, whole_s = _whole_light(world, p, n, wo, coeffs, two_sided,
                                             tex_arg is not None)
    lit = (whole_d > 0.0) | (whole_s > 0.0)
    live = dr.compress(lit if active is None else lit & active)
    zero = mi.Color3f(0.0) if tex_arg is not None else mi.Float(0.0)
    acc = {"d": dr.zeros(type(zero), width), "s": dr.zeros(type(zero), width), "pieces": 0}
    st = {"levels": 0, "items": 0}
    n_live = dr.width(live)
    if n_live:
        items = _root_pass(dev, tree_index, rel, live, n_live, qd, acc, two_sided, tex_arg)
        if items is not None and traversal == "kernel":
            dr.eval(items.fields())
            for pieces in _traverse(dev, items, st if stats is not None else None):
                dr.eval(pieces.fields())
                _accumulate(pieces.trim(), dev, qd, acc, two_sided, tex_arg)
        elif items is not None:
            _wavefront(dev, items, qd, acc, two_sided, tex_arg, st)
    # exact zeros where the whole light gives 0 (as ltc._integrals)
    i_d = dr.select(whole_d > 0.0, acc["d"], zero)
    i_s = dr.select(whole_s > 0.0, acc["s"], zero)
    dr.eval(i_d, i_s)
    if stats is not None:
        stats.update(st, pieces=acc["pieces"], queries=width, live=n_live)
    return i_d, i_s


# --------------------------------------------------------------------------------------------
# shading


def _shade_core(dev: DeviceTrees, lights: list, sp: ShadingPoints, idx: list, w: list, table,
                width: int, traversal: str, direct: bool = False) -> tuple[mi.Color3f, mi.Color3f]:
    """:func:`shade_points` after validation. ``lights``: per light ``(world vertices (opaque
    Point3f), radiance (Color3f), two_sided, light vertices (K, 3), texture or None)``;
    ``direct``: call :func:`_fused_integrals` without :func:`visible_integrals`' checks (no
    host synchronisation: what :data:`_shade_frozen` records)."""
    cos_o = dr.clip(dr.dot(sp.n, sp.wo), 0.0, 1.0)
    coeffs, norm, fres = table.lookup(sp.alpha, cos_o, _mask(sp.beckmann))
    # as ltc.shade_frame: the fit's split sum, int f F cos per unit D integral
    spec_w = sp.spec_weight(norm, fres)
    m = len(idx)
    if m == 1:
        lane_q, tree = dr.arange(mi.UInt32, width), idx[0]
    else:
        lanes = dr.arange(mi.UInt32, m * width)
        nw = dr.opaque(mi.UInt32, width)
        j = lanes // nw
        lane_q = lanes - j * nw
        tree = dr.gather(mi.UInt32, idx[-1], lane_q)
        for jj in range(m - 2, -1, -1):
            tree = dr.select(j == jj, dr.gather(mi.UInt32, idx[jj], lane_q), tree)
    g = (lambda x: x) if m == 1 else (lambda x: dr.gather(type(x), x, lane_q))
    args = (tree, g(sp.p), g(sp.n), g(sp.wo), g(coeffs))
    active = g(sp.hit)  # lanes without a surface are not traversed
    total_d = dr.zeros(mi.Color3f, width)
    total_s = dr.zeros(mi.Color3f, width)
    for world, le, two_sided, lv, tex in lights:
        if direct:
            i_d, i_s = _fused_integrals(dev, *args, world, two_sided, m * width,
                                        active=active)
        else:
            # the fused traversal takes no textured light: those go through the kernel one
            trav = "kernel" if traversal == "fused" and tex is not None else traversal
            i_d, i_s = visible_integrals(dev, *args, lv, two_sided, texture=tex,
                                         traversal=trav, active=active)
        if m == 1:
            b_d, b_s = w[0] * i_d, w[0] * i_s
        else:
            b_d = b_s = None
            for jj in range(m):
                k = dr.arange(mi.UInt32, width) + jj * width
                d_j = w[jj] * dr.gather(type(i_d), i_d, k)
                s_j = w[jj] * dr.gather(type(i_s), i_s, k)
                b_d = d_j if b_d is None else b_d + d_j
                b_s = s_j if b_s is None else b_s + s_j
        total_d = total_d + le * (sp.albedo * b_d)
        total_s = total_s + le * (spec_w * b_s)
    return dr.select(sp.hit, total_d, 0.0), dr.select(sp.hit, total_s, 0.0)


def _shade_frozen_kernel(dev: DeviceTrees, lights: list, sp: ShadingPoints, idx: list,
                         w: list, table, width: int) -> tuple[mi.Color3f, mi.Color3f]:
    # ``width`` is an explicit argument, part of dr.freeze's key (sizes baked into a
    # recording); each light's two-sidedness (a Python bool) is too
    return _shade_core(dev, [(world, le, two, None, None) for world, le, two in lights], sp,
                       idx, w, table, width, "fused", direct=True)


#: :func:`shade_points` with ``frozen=True``: the fused traversal recorded once per tree set,
#: light count and lane count, replayed afterwards.
_shade_frozen = dr.freeze(_shade_frozen_kernel, warn_after=16)


def shade_points(trees: Any, lights: Sequence, sp: ShadingPoints,
                 tree_index: Sequence[mi.UInt32], weights: Sequence[mi.Float] | None = None,
                 textures: dict | None = None, traversal: str = "kernel",
                 frozen: bool = False) -> tuple[mi.Color3f, mi.Color3f]:
    """Shadowed direct light (diffuse, specular) at the shading points ``sp``, summed over the
    polygon ``lights`` (objects with ``vertices``, ``radiance``, ``two_sided``, optional
    ``texture`` and ``uv``; :class:`glossrt.lights.scene.PolygonLight`).

    Each lane reads the trees ``tree_index[j]`` (one ``mi.UInt32`` per lane each) and blends
    the shadowed integrals with ``weights[j]`` (default: one tree, weight 1). The BRDF is
    combined as in :func:`glossrt.lights.ltc.shade.shade_frame`: diffuse ``L albedo i_d``, specular
    ``L (F0 (norm - fres) + fres) i_s``; 0 where ``sp.hit`` is False. ``textures``: a cache
    {id(light texture): PrefilteredTexture} reused across calls; ``traversal``: as
    :func:`visible_integrals`.

    ``frozen=True``: the real-time path. The ``"fused"`` traversal (whatever ``traversal``
    says) is recorded once with ``dr.freeze`` and replayed for later calls with the same
    trees, number of lights and lanes (new views, materials and light positions replay;
    ~10 K traced operations and the other traversals' per-call host synchronisations are
    gone; one remains, the check of the tree indices and inputs). A call with a textured
    light is traced anew, all its lights (``traversal="fused"`` then walks textured lights
    with the kernel traversal)."""
    _check_traversal(traversal)
    dev = DeviceTrees.of(trees)
    width = dr.width(sp.p)
    idx = [mi.UInt32(t) for t in tree_index]
    if not idx:
        raise GlossrtError("shade_points needs at least one tree index per lane")
    w = [mi.Float(x) for x in weights] if weights is not None else [mi.Float(1.0)]
    if len(w) != len(idx):
        raise GlossrtError(f"{len(idx)} tree indices but {len(w)} weights")
    for t in idx:
        if dr.width(t) != width:
            raise GlossrtError(f"tree indices have {dr.width(t)} lanes, the points {width}")
    cache = {} if textures is None else textures
    dev_lights, two = _device_lights(lights)
    lv = [light_vertices(light) for light in lights]
    tex = [prefiltered(light, cache) for light in lights]
    if frozen and width and all(t is None for t in tex):
        _check_lanes(idx, dev, sp.p, sp.n, sp.wo)
        with no_gc():
            total_d, total_s = _shade_frozen(
                dev, [(world, le, tw) for (world, le), tw in zip(dev_lights, two, strict=True)],
                sp, idx, w, _table(), width)
    else:
        total_d, total_s = _shade_core(
            dev, [(world, le, tw, v, tx) for (world, le), tw, v, tx
                  in zip(dev_lights, two, lv, tex, strict=True)],
            sp, idx, w, _table(), width, traversal)
    dr.eval(total_d, total_s)
    return total_d, total_s


def _np_vec(name: str, x: Any, rows: int, cols: int | None = 3) -> np.ndarray:
    try:
        a = np.asarray(x, np.float64)
    except (TypeError, ValueError) as e:
        raise GlossrtError(f"{name} must be numeric: {e}") from e
    if cols is None and a.ndim == 0:
        a = np.full(rows, float(a))
    shape = (rows,) if cols is None else (rows, cols)
    if a.shape != shape:
        raise GlossrtError(f"{name} must have shape {shape}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise GlossrtError(f"{name} contains NaN or Inf")
    return a




def _points(p, n, wo, alpha, albedo, f0, rows: int, hit=None,
            beckmann=None) -> ShadingPoints:
    from ...brdf.ggx import ALPHA_MIN

    p = _np_vec("positions", p, rows)
    n = _np_vec("normals", n, rows)
    wo = _np_vec("view directions", wo, rows)
    alpha = _np_vec("alpha", alpha, rows, None)
    albedo = _np_vec("albedo", albedo, rows)
    f0 = np.zeros((rows, 3)) if f0 is None else _np_vec("f0", f0, rows)
    for name, v in (("normals", n), ("view directions", wo)):
        ln = np.linalg.norm(v, axis=1)
        if np.any(ln < 1e-12):
            raise GlossrtError(f"{name} must be non-zero")
    n = n / np.linalg.norm(n, axis=1, keepdims=True)
    wo = wo / np.linalg.norm(wo, axis=1, keepdims=True)
    ok = np.sum(n * wo, axis=1) > 0
    if hit is not None:
        h = np.asarray(hit, bool)
        if h.shape != (rows,):
            raise GlossrtError(f"hit must have shape ({rows},), got {h.shape}")
        ok &= h
    return ShadingPoints(_dr_vec(mi.Point3f, p), _dr_vec(mi.Vector3f, n),
                         _dr_vec(mi.Vector3f, wo),
                         owned(mi.Float, np.maximum(alpha, ALPHA_MIN)),
                         _dr_vec(mi.Color3f, albedo), _dr_vec(mi.Color3f, f0),
                         owned(mi.UInt32, ok) != 0, _beckmann_lanes(beckmann, rows))


def _beckmann_lanes(beckmann: Any, rows: int) -> mi.Bool | bool:
    """A ``ShadingPoints.beckmann`` from a bool or a (rows,) array (``None``: GGX)."""
    if beckmann is None or np.ndim(beckmann) == 0:
        return bool(beckmann)
    b = np.asarray(beckmann, bool)
    if b.shape != (rows,):
        raise GlossrtError(f"beckmann must have shape ({rows},), got {b.shape}")
    return owned(mi.UInt32, b) != 0


def _np_color(c: mi.Color3f) -> np.ndarray:
    return np.stack([np.asarray(c[i], np.float32) for i in range(3)], -1)


def shade_vertices(trees: Any, lights: Sequence, wo: Any, alpha: Any, albedo: Any,
                   f0: Any = None, textures: dict | None = None, traversal: str = "kernel",
                   frozen: bool = False, beckmann: Any = None) -> tuple[np.ndarray, np.ndarray]:
    """The paper's per-vertex shading (Okuno & Iwasaki, sec. 3.3): each vertex shaded at its
    own position and normal (``trees.positions``, ``trees.normals``) with its own tree.

    ``wo`` (V, 3) view directions (towards the viewer), ``alpha`` (V,) microfacet roughness
    (or a scalar), ``albedo`` and ``f0`` (V, 3); ``beckmann`` (V,) or a bool: Beckmann's
    distribution instead of GGX (default GGX); ``traversal`` and ``frozen`` as
    :func:`shade_points`.
    Returns (diffuse, specular), (V, 3) float32 each (:func:`shade_points`; 0 where the view
    is below the vertex's tangent plane)."""
    dev = DeviceTrees.of(trees)
    nv = dev.n_vertices
    pos = np.stack([np.asarray(dev.positions[c], np.float64) for c in range(3)], -1)
    nrm = np.stack([np.asarray(dev.normals[c], np.float64) for c in range(3)], -1)
    sp = _points(pos, nrm, wo, alpha, albedo, f0, nv, beckmann=beckmann)
    d, s = shade_points(dev, lights, sp, [dr.arange(mi.UInt32, nv)], textures=textures,
                        traversal=traversal, frozen=frozen)
    return _np_color(d), _np_color(s)


def shade_pixels(trees: Any, lights: Sequence, p: Any, n: Any, wo: Any, alpha: Any,
                 albedo: Any, f0: Any, triangles: Any, barycentrics: Any, hit: Any = None,
                 textures: dict | None = None, traversal: str = "kernel",
                 frozen: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel shading: each pixel evaluates the trees of its triangle's three vertices
    with its own position ``p``, normal ``n``, view ``wo``, ``alpha``, ``albedo`` and ``f0``
    (P, 3) / (P,) and blends the shadowed integrals by its ``barycentrics`` (P, 3);
    ``triangles`` (P, 3) are the vertex (tree) indices; ``hit`` (P,) optional mask;
    ``traversal`` and ``frozen`` as :func:`shade_points`. Returns (diffuse, specular), (P, 3)
    float32 each (:func:`shade_points`)."""
    dev = DeviceTrees.of(trees)
    tri = np.asarray(triangles)
    rows = tri.shape[0] if tri.ndim == 2 else -1
    if tri.ndim != 2 or tri.shape[1] != 3 or not np.issubdtype(tri.dtype, np.integer):
        raise GlossrtError(f"triangles must be (P, 3) integers, got {tri.shape} {tri.dtype}")
    if tri.size and (tri.min() < 0 or tri.max() >= dev.n_vertices):
        raise GlossrtError(f"triangle vertex indices out of range [0, {dev.n_vertices})")
    bary = _np_vec("barycentrics", barycentrics, rows)
    if rows == 0:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32)
    sp = _points(p, n, wo, alpha, albedo, f0, rows, hit)
    idx = [owned(mi.UInt32, tri[:, j]) for j in range(3)]
    wts = [owned(mi.Float, bary[:, j]) for j in range(3)]
    d, s = shade_points(dev, lights, sp, idx, wts, textures=textures, traversal=traversal,
                        frozen=frozen)
    return _np_color(d), _np_color(s)
