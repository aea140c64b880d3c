"""glossrt.lights.bspvt.shade: shadowed LTC shading with per-vertex visibility trees
(Okuno & Iwasaki, eq. 2).

Trees are built by hand / by a tiny random NumPy builder here (random lines through random
points of the face square, random leaf values). Checked against independent computations:

* all-visible trees (one leaf, or many leaves all of value 1: the pieces must partition the
  light) == ``ltc._integrals`` of the whole light, diffuse and specular, one- and two-sided,
  random polygons (3 to 8 vertices) straddling cube faces and crossing the horizon;
* all-invisible trees give exactly 0 and integrate nothing;
* half-plane trees and random multi-level trees == a brute-force NumPy reference: adaptive
  quadrature over the light's area (visibility looked up per point by walking the tree in
  NumPy, clamped cosine and ``ltc_fit.ltc_eval`` times the area-to-solid-angle Jacobian), which
  returns its own error bound (cells where the visibility changes, refined 7 times);
* edge cases (horizon, behind, 3 faces, face boundary, degenerate lights), per-vertex and
  per-pixel wrappers against ``polygon.clamped_cosine_integral`` / ``ltc.polygon_integral``,
  textured lights against ``ltc._texture_lookup``, and bad input.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from glossrt import backend

backend.ensure()

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

from glossrt.errors import GlossrtError  # noqa: E402
from glossrt.jit import owned  # noqa: E402
from glossrt.lights.bspvt import shade as bs  # noqa: E402
from glossrt.lights.ltc.fit import ltc_eval  # noqa: E402
from glossrt.lights.ltc.shade import (  # noqa: E402
    PrefilteredTexture,
    _integrals,
    _local,
    _table,
    _texture_lookup,
    ltc_frame,
    polygon_integral,
)
from glossrt.lights.ltc.table import minv_matrix  # noqa: E402
from glossrt.lights.polygon import clamped_cosine_integral, shading_frame, to_local  # noqa: E402

#: float32 agreement of a sum of pieces with the whole-light integral: each cosine_integral
#: is accurate to ~32 eps ~ 1.9e-6 absolute (polygon.py), the pieces' interior edges cancel
#: only to rounding (~16 eps per radian of cut / 2 pi, a few radians here); measured <= 1e-6.
ATOL_F32 = 5e-6


# --------------------------------------------------------------------------------------------
# trees by hand, a random builder, and a NumPy walker


def make_trees(per_vertex: list, positions=None, normals=None) -> SimpleNamespace:
    """Flat BSPVT arrays from nested face trees: a face tree is a leaf value (float) or
    ``((a, b, c), left, right)``; ``per_vertex`` lists 6 face trees per vertex."""
    lines, children, leaves, roots = [], [], [], []

    def add(node):
        if not isinstance(node, tuple):
            leaves.append(float(node))
            return -len(leaves)  # ~(index)
        line, left, right = node
        i = len(lines)
        lines.append(line)
        children.append([0, 0])
        children[i][0] = add(left)
        children[i][1] = add(right)
        return i

    for faces in per_vertex:
        roots.append([add(f) for f in faces])
    nv = len(per_vertex)
    pos = np.zeros((nv, 3)) if positions is None else positions
    nrm = np.tile([0.0, 0.0, 1.0], (nv, 1)) if normals is None else normals
    return SimpleNamespace(lines=np.array(lines, np.float32).reshape(-1, 3),
                           children=np.array(children, np.int32).reshape(-1, 2),
                           leaf_value=np.array(leaves, np.float32),
                           roots=np.array(roots, np.int32).reshape(nv, 6),
                           positions=np.asarray(pos, np.float32),
                           normals=np.asarray(nrm, np.float32), resolution=64, epsilon=0.0)


def random_face_tree(rng, n_leaves: int, values=(0.0, 1.0, None)):
    """Split random leaves by random lines through random points of [-1, 1]^2 until there
    are ``n_leaves`` leaves; leaf values drawn from ``values`` (None: uniform in [0, 1])."""
    def value():
        v = values[rng.integers(len(values))]
        return float(rng.uniform()) if v is None else v

    root = [value()]
    open_leaves = [root]
    while len(open_leaves) < n_leaves:
        node = open_leaves.pop(int(rng.integers(len(open_leaves))))
        th = rng.uniform(0, 2 * math.pi)
        a, b = math.cos(th), math.sin(th)
        c = -(a * rng.uniform(-1, 1) + b * rng.uniform(-1, 1))
        left, right = [value()], [value()]
        node[:] = [(a, b, c), left, right]
        open_leaves += [left, right]

    def conv(node):
        return node[0] if len(node) == 1 else (node[0], conv(node[1]), conv(node[2]))

    return conv(root)


def with_values(tr: SimpleNamespace, value: float) -> SimpleNamespace:
    out = SimpleNamespace(**vars(tr))
    out.leaf_value = np.full_like(tr.leaf_value, value)
    return out


def cube_face(d: np.ndarray):
    """(face, s, t) of world directions (..., 3), BSPVT conventions (ties: lowest face)."""
    ad = np.abs(d)
    f = np.full(d.shape[:-1], -1)
    for ff in range(6):
        k, sg = ff // 2, 1 - 2 * (ff % 2)
        u, v = (k + 1) % 3, (k + 2) % 3
        f[(sg * d[..., k] >= np.maximum(ad[..., u], ad[..., v])) & (f < 0)] = ff
    k, sg = f // 2, 1 - 2 * (f % 2)

    def comp(axis):
        return np.take_along_axis(d, axis[..., None], -1)[..., 0]

    w = sg * comp(k)
    return f, comp((k + 1) % 3) / w, comp((k + 2) % 3) / w


def tree_visibility(tr, vertex: int, d: np.ndarray) -> np.ndarray:
    """The tree's piecewise-constant visibility for world directions ``d`` (NumPy walk)."""
    f, s, t = cube_face(d)
    code = tr.roots[vertex, f].astype(np.int64)
    while np.any(code >= 0):
        inner = code >= 0
        c = code[inner]
        ln = tr.lines[c].astype(np.float64)
        dist = ln[:, 0] * s[inner] + ln[:, 1] * t[inner] + ln[:, 2]
        code[inner] = tr.children[c, (dist >= 0).astype(np.int64)]
    return tr.leaf_value[~code].astype(np.float64)


def ltc_frame_np(n, wo):
    """Rows ``(T1, T2, n)`` of ``ltc.ltc_frame`` (view along the normal: Mitsuba's
    ``coordinate_system``, which is ``polygon.shading_frame``)."""
    t1 = wo - n * np.dot(n, wo)
    if np.linalg.norm(t1) < 1e-6:
        t1 = shading_frame(n)[0]
    t1 = t1 / np.linalg.norm(t1)
    return np.stack([t1, np.cross(n, t1), n])


def reference(tr, vertex, p, n, wo, coeffs, light, two_sided, m=32, levels=7):
    """Brute force ``(i_d, i_s, bound_d, bound_s)``: ``int_A V(w) g(w) |cos_l| / r^2 dA`` over
    the light's area (fan triangles, each an m x m lattice of triangles, edge-midpoint rule:
    exact for quadratics), ``g`` = clamped cosine / pi (diffuse) or the LTC density
    ``ltc_eval(M^-1 R, w)`` (specular), ``V`` by walking the tree (:func:`tree_visibility`).
    Cells whose 6 samples (corners, edge midpoints) see different visibilities are split in 4,
    ``levels`` times; the bound is sum over the still-mixed cells of area x max integrand x
    (max V - min V), which covers their error as long as no leaf region hides inside a cell
    without touching a sample."""
    light = np.asarray(light, np.float64)
    minv = minv_matrix(np.asarray(coeffs, np.float64)) @ ltc_frame_np(n, wo)
    nl = np.cross(light[1] - light[0], light[2] - light[0])
    nl = nl / np.linalg.norm(nl)
    if not two_sided and np.dot(nl, p - light[0]) <= 0:
        return 0.0, 0.0, 0.0, 0.0
    i, j = np.meshgrid(np.arange(m), np.arange(m), indexing="ij")
    up, down = i + j < m, i + j < m - 1
    cells = []
    for k in range(1, len(light) - 1):
        a, e1, e2 = light[0], (light[k] - light[0]) / m, (light[k + 1] - light[0]) / m

        def pt(ii, jj, a=a, e1=e1, e2=e2):
            return a + ii[..., None] * e1 + jj[..., None] * e2

        iu, ju, idn, jdn = i[up], j[up], i[down], j[down]
        cells.append(np.stack([pt(iu, ju), pt(iu + 1, ju), pt(iu, ju + 1)], 1))
        cells.append(np.stack([pt(idn + 1, jdn), pt(idn + 1, jdn + 1), pt(idn, jdn + 1)], 1))
    cells = np.concatenate(cells)
    total, bound = np.zeros(2), np.zeros(2)
    for lev in range(levels + 1):
        a, b, c = cells[:, 0], cells[:, 1], cells[:, 2]
        pts = np.stack([a, b, c, (a + b) / 2, (b + c) / 2, (c + a) / 2], 1)
        r = pts - p
        dist = np.linalg.norm(r, axis=-1)
        w = r / dist[..., None]
        jac = np.abs(r @ nl) / dist**3
        g = np.stack([np.maximum(w @ n, 0) / math.pi * jac, ltc_eval(minv, w) * jac])
        v = tree_visibility(tr, vertex, w)
        area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=-1)
        mixed = v.max(1) > v.min(1)
        take = ~mixed | (lev == levels)
        total += np.sum(area[take] * np.mean((v * g)[:, take, 3:], -1), -1)
        if lev == levels:
            bound += np.sum(area[mixed] * g[:, mixed].max(-1) * (v.max(1) - v.min(1))[mixed],
                            -1)
            break
        f = cells[mixed]
        a, b, c = f[:, 0], f[:, 1], f[:, 2]
        ab, bc, ca = (a + b) / 2, (b + c) / 2, (c + a) / 2
        cells = np.concatenate([np.stack(x, 1) for x in
                                ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))])
    return total[0], total[1], bound[0], bound[1]


# --------------------------------------------------------------------------------------------
# queries


def vec(a, t=mi.Vector3f):
    """Rows as a Dr.Jit vector in Dr.Jit-owned memory (NumPy-backed arrays change alignment
    between calls, which recompiles kernels on the CPU)."""
    return bs._dr_vec(t, np.atleast_2d(np.asarray(a, np.float64)))


def unit(x):
    x = np.asarray(x, np.float64)
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


class Queries:
    """Shading points with normals, views above the horizon and LTC coefficients."""

    def __init__(self, p, n, wo, alpha, tree=None):
        self.p, self.n, self.wo = (np.atleast_2d(np.asarray(x, np.float64)) for x in (p, n, wo))
        self.n, self.wo = unit(self.n), unit(self.wo)
        self.alpha = np.broadcast_to(np.asarray(alpha, np.float64), (len(self.p),)).copy()
        self.tree = np.zeros(len(self.p), np.int64) if tree is None else np.asarray(tree)
        cos_o = np.clip(np.sum(self.n * self.wo, 1), 0, 1)
        self.coeffs, self.norm, self.fres = _table().lookup_np(self.alpha, cos_o)

    def dr(self):
        return (owned(mi.UInt32, self.tree), vec(self.p, mi.Point3f), vec(self.n),
                vec(self.wo), vec(self.coeffs, mi.Vector4f))

    @staticmethod
    def random(rng, q: int, spread: float = 0.3, trees: int = 1) -> Queries:
        n = unit(rng.normal(size=(q, 3)))
        wo = unit(rng.normal(size=(q, 3)))
        wo = np.where((np.sum(wo * n, 1) < 0.05)[:, None], unit(wo + 1.5 * n), wo)
        return Queries(rng.normal(size=(q, 3)) * spread, n, wo, rng.uniform(0.25, 1.0, q),
                       rng.integers(0, trees, q))


def integrals(trees, qs: Queries, light, two_sided, stats=None, texture=None,
              traversal="kernel"):
    i_d, i_s = bs.visible_integrals(trees, *qs.dr(), np.asarray(light, np.float64), two_sided,
                                    texture=texture, stats=stats, traversal=traversal)
    return np.array(i_d, np.float64), np.array(i_s, np.float64)


def unshadowed(qs: Queries, light, two_sided):
    """``ltc._integrals`` of the whole light (the LTC shading without visibility)."""
    _, p, n, wo, coeffs = qs.dr()
    t1, t2 = ltc_frame(n, wo)
    world = [mi.Point3f(*(float(c) for c in v)) for v in np.asarray(light, np.float64)]
    i_d, i_s = _integrals(_local(world, p, t1, t2, n), coeffs, two_sided)
    return np.array(i_d, np.float64), np.array(i_s, np.float64)


def random_light(rng, k: int, centre=None, dist=(0.8, 2.5), size=(0.3, 1.5)):
    """A random planar convex k-gon (random winding), tilted to its direction."""
    c = unit(rng.normal(size=3)) * rng.uniform(*dist) if centre is None else np.asarray(centre)
    e1, e2 = unit(rng.normal(size=3)), rng.normal(size=3)
    e2 = unit(e2 - e1 * (e2 @ e1))
    ang = np.sort(rng.uniform(0, 2 * math.pi, k))
    ang = ang if rng.uniform() < 0.5 else ang[::-1]
    return c + rng.uniform(*size) * (np.cos(ang)[:, None] * e1 + np.sin(ang)[:, None] * e2)


def check_against_reference(tr, qs: Queries, light, two_sided, label=""):
    """Each query vs the brute-force reference, within its bound + float32 noise; returns
    the worst error / allowed ratio."""
    i_d, i_s = integrals(tr, qs, light, two_sided)
    worst = 0.0
    for j in range(len(qs.p)):
        r_d, r_s, b_d, b_s = reference(tr, int(qs.tree[j]), qs.p[j], qs.n[j], qs.wo[j],
                                       qs.coeffs[j], light, two_sided)
        for got, want, bound in ((i_d[j], r_d, b_d), (i_s[j], r_s, b_s)):
            allowed = bound + ATOL_F32 + 1e-5 * abs(want)
            assert abs(got - want) <= allowed, (label, j, got, want, bound)
            worst = max(worst, abs(got - want) / allowed)
    return worst


# --------------------------------------------------------------------------------------------
# tests


def test_all_visible_equals_unshadowed():
    """One-leaf trees and random 60-leaf-per-face trees with every leaf 1 (the pieces must
    partition the light), random convex 3- to 8-gons around the point (straddling faces,
    crossing horizons, both windings), one- and two-sided: == ltc._integrals."""
    rng = np.random.default_rng(1)
    many = make_trees([[random_face_tree(rng, 60, (1.0,)) for _ in range(6)]
                       for _ in range(3)])
    one = make_trees([[1.0] * 6])
    worst, nonzero, pieces = 0.0, 0, []
    for k in (3, 4, 5, 8):
        light = random_light(rng, k)
        qs = Queries.random(rng, 96, spread=0.3, trees=3)
        for two in (False, True):
            want_d, want_s = unshadowed(qs, light, two)
            st = {}
            got = integrals(many, qs, light, two, stats=st)
            pieces.append(st["pieces"] / max(st["live"], 1))
            got1 = integrals(one, Queries(qs.p, qs.n, qs.wo, qs.alpha), light, two)
            for g_d, g_s in (got, got1):
                np.testing.assert_allclose(g_d, want_d, rtol=0, atol=ATOL_F32)
                np.testing.assert_allclose(g_s, want_s, rtol=0, atol=ATOL_F32)
                assert np.all(g_d[want_d == 0] == 0) and np.all(g_s[want_s == 0] == 0)
                worst = max(worst, np.abs(g_d - want_d).max(), np.abs(g_s - want_s).max())
            nonzero += int(np.sum(want_d > 0))
    print(f"\nall-visible vs ltc._integrals: max abs difference {worst:.2e}, {nonzero} lit "
          f"queries, {np.mean(pieces):.1f} pieces per lit query")
    assert nonzero > 200


def test_all_invisible_is_zero():
    rng = np.random.default_rng(2)
    tr = make_trees([[random_face_tree(rng, 20, (0.0,)) for _ in range(6)]])
    qs = Queries.random(rng, 64)
    light = random_light(rng, 4, centre=[0.2, 0.1, 1.5])
    st = {}
    i_d, i_s = integrals(tr, qs, light, True, stats=st)
    assert np.all(i_d == 0) and np.all(i_s == 0)
    assert st["pieces"] == 0 and st["live"] > 0  # leaves of value 0 are dropped unintegrated


@pytest.mark.slow
def test_half_plane_and_random_trees_match_brute_force():
    """A single line per face (half-plane visibility) and random multi-level trees with leaf
    values in {0, 1, uniform}: == the brute-force reference within its error bound + float32
    noise (ATOL_F32 + 1e-5 relative)."""
    rng = np.random.default_rng(3)
    half = make_trees([[((0.6, 0.8, 0.1), 0.0, 1.0)] * 6,
                       [((-0.8, 0.6, -0.3), 1.0, 0.25)] * 6])
    rand = make_trees([[random_face_tree(rng, 14) for _ in range(6)] for _ in range(2)])
    worst = 0.0
    for tr, label in ((half, "half-plane"), (rand, "random")):
        for k, two in ((4, True), (3, False), (6, True)):
            light = random_light(rng, k, dist=(1.2, 2.0), size=(0.6, 1.2))
            qs = Queries.random(rng, 4, spread=0.2, trees=2)
            worst = max(worst, check_against_reference(tr, qs, light, two, label))
    print(f"\nvs brute force: worst |error| / allowed {worst:.3f}")


def test_edge_cases():
    rng = np.random.default_rng(4)
    # per-face constant visibility, distinct per face: tests the face assignment too
    face_vals = [0.9, 0.15, 0.7, 0.35, 0.55, 0.05]
    faces = make_trees([face_vals])
    split = make_trees([[((1.0, 0.0, 0.2), 1.0, 0.3)] * 6])
    o = np.zeros(3)

    # light crossing the horizon (one- and two-sided), against the reference
    n_up = [0, 0, 1.0]
    horizon = np.array([[-0.8, 1.0, -0.6], [0.8, 1.0, -0.6], [0.8, 1.2, 0.9], [-0.8, 1.2, 0.9]])
    qs = Queries([o], [n_up], unit([0.2, -0.5, 1.0]), 0.4)
    for two in (True, False):
        assert unshadowed(qs, horizon, two)[0][0] > 0  # front-facing: lit either way
        check_against_reference(split, qs, horizon, two, "horizon")

    # light behind the surface, and the back of a one-sided light: exactly 0
    below = horizon - [0, 0, 2.0]
    st = {}
    assert np.all(np.concatenate(integrals(faces, qs, below, True, stats=st)) == 0)
    assert st["live"] == 0
    assert np.all(np.concatenate(integrals(faces, qs, horizon[::-1], False)) == 0)

    # straddling 3 faces (+X, +Y, +Z) around the direction (1, 1, 1)
    c = np.full(3, 1.5)
    e1, e2 = unit([1.0, -1.0, 0.0]), unit([1.0, 1.0, -2.0])
    tri = c + np.array([np.cos(a) * e1 + np.sin(a) * e2 for a in (0.3, 2.4, 4.4)])
    seen = {int(f) for f in cube_face(unit(tri[None] - o))[0].ravel()}
    qs3 = Queries([o], [unit(c)], unit([1.0, 0.5, 0.8]), 0.5)
    assert seen == {0, 2, 4}
    check_against_reference(faces, qs3, tri, True, "three faces")

    # exactly on a face boundary: an edge in the plane x = z, the light on the +X side
    on_edge = np.array([[1.0, -0.5, 1.0], [1.0, 0.5, 1.0], [2.0, 0.5, 0.5], [2.0, -0.5, 0.5]])
    qs_b = Queries([o], [unit([1.0, 0.0, 1.0])], [unit([1.0, 0.2, 1.0])], 0.5)
    for two in (True,):
        want_d, want_s = unshadowed(qs_b, on_edge, two)
        got_d, got_s = integrals(faces, qs_b, on_edge, two)
        np.testing.assert_allclose([got_d[0], got_s[0]],
                                   [face_vals[0] * want_d[0], face_vals[0] * want_s[0]],
                                   atol=ATOL_F32)
    # symmetric about the +X / +Z boundary, normal on it: half the light on each face
    sym = np.array([[1.0, -0.5, 1.0], [1.3, -0.5, 0.7], [1.3, 0.5, 0.7], [1.0, 0.5, 1.0],
                    [0.7, 0.5, 1.3], [0.7, -0.5, 1.3]])
    qs_s = Queries([o], [unit([1.0, 0.0, 1.0])], [unit([1.0, 0.0, 1.0])], 0.5)
    want_d, _ = unshadowed(qs_s, sym, True)
    got_d, _ = integrals(faces, qs_s, sym, True)
    np.testing.assert_allclose(got_d, (face_vals[0] + face_vals[4]) / 2 * want_d, atol=ATOL_F32)
    check_against_reference(faces, qs_s, sym, True, "symmetric boundary")

    # degenerate lights: zero area, repeated vertices, plane through the point, tiny
    qs_r = Queries.random(rng, 32)
    quad = np.array([[-0.5, -0.5, 1.5], [0.5, -0.5, 1.5], [0.5, 0.5, 1.5], [-0.5, 0.5, 1.5]])
    tr = make_trees([[random_face_tree(rng, 20, (1.0,)) for _ in range(6)]])
    cases = {
        "collinear": np.array([[0, 0, 1.0], [1, 1, 2.0], [2, 2, 3.0], [3, 3, 4.0]]),
        "repeated": np.array([quad[0], quad[1], quad[1], quad[2], quad[3], quad[3]]),
        "point": np.array([[0.3, 0.2, 1.0]] * 4),
        "through p": np.array([[-1, -1, 0.0], [1, -1, 0.0], [1, 1, 0.0]]),
        "tiny": quad * 1e-5 + [0.0, 0.0, 1.5],
    }
    for name, light in cases.items():
        for two in (True, False):
            want_d, want_s = unshadowed(qs_r, light, two)
            got_d, got_s = integrals(tr, qs_r, light, two)
            assert np.all(np.isfinite(got_d)) and np.all(np.isfinite(got_s)), name
            np.testing.assert_allclose(got_d, want_d, atol=ATOL_F32, err_msg=name)
            np.testing.assert_allclose(got_s, want_s, atol=ATOL_F32, err_msg=name)
    # the plane of the light through the shading point: exactly 0
    flat = Queries(np.zeros((1, 3)), [n_up], [unit([0.3, 0, 1])], 0.5)
    assert np.all(np.concatenate(integrals(tr, flat, cases["through p"], True)) == 0)


def test_pieces_with_many_vertices():
    """A regular octagon light on the +Z face whose 8 corners are cut off one by one: the
    central piece has 16 vertices (integrated as a fan of 3 sub-polygons). All leaves 1 ==
    the whole light; centre 1, corners 0.5 == the brute-force reference."""
    ang = np.arange(8) * math.pi / 4
    octagon = np.stack([0.9 * np.cos(ang), 0.9 * np.sin(ang), np.full(8, 1.5)], -1)
    # in (s, t) = (x, y) / 1.5 the corners lie at 0.6, the edges' midpoints at 0.554
    central = 1.0
    for th in ang[::-1]:
        central = ((math.cos(th), math.sin(th), -0.58), central, 0.5)
    tr = make_trees([[0.0, 0.0, 0.0, 0.0, central, 0.0]])
    qs = Queries([[0.0, 0.0, 0.0]], [unit([0.1, 0.2, 1.0])], [unit([0.5, 0.1, 1.0])], 0.5)
    for two in (True, False):
        light = octagon if two else octagon[::-1]  # counter-clockwise seen from below
        want_d, want_s = unshadowed(qs, light, two)
        got_d, got_s = integrals(with_values(tr, 1.0), qs, light, two)
        np.testing.assert_allclose([got_d[0], got_s[0]], [want_d[0], want_s[0]], atol=ATOL_F32)
        assert want_d[0] > 0.1
        check_against_reference(tr, qs, light, two, "16-gon")


def test_traversals_agree(monkeypatch):
    """The one-kernel depth-first traversal (default), the per-level wavefront and the fused
    traversal (splits and integration in one loop, no host synchronisation) split the same
    items into the same pieces: equal ``items`` and ``pieces`` counts and integrals equal
    to float32 summation order (the pieces are summed in another order), on deep random trees
    (60 leaves per face, values in {0, 1, uniform}) and random lights straddling faces,
    including lanes redone with KMAX slots (a 7-gon clipped to a face has up to 11 vertices).
    With the output capacity forced to 1 piece and the root items cut into chunks of 100, the
    traversal reruns with the exact capacity and gives the same result."""
    rng = np.random.default_rng(9)
    tr = bs.DeviceTrees.of(make_trees([[random_face_tree(rng, 60) for _ in range(6)]
                                       for _ in range(3)]))
    assert tr.depth >= 8
    passes = []  # (slots, lanes) of each traversal pass: the KMAX pass must run too
    first_pass = bs._traverse_pass

    def counting(dev, items, k, cap):
        passes.append((k, dr.width(items.n)))
        return first_pass(dev, items, k, cap)

    monkeypatch.setattr(bs, "_traverse_pass", counting)
    runs = []
    for k, two in ((4, False), (7, True)):
        light = random_light(rng, k, dist=(0.8, 1.2), size=(1.0, 1.5))
        qs = Queries.random(rng, 200, spread=0.3, trees=3)
        got = {}
        for traversal in bs.TRAVERSALS:
            st = {}
            got[traversal] = integrals(tr, qs, light, two, stats=st, traversal=traversal)
            got[traversal + " stats"] = st
        w, kn, fu = got["wavefront stats"], got["kernel stats"], got["fused stats"]
        assert (kn["items"], kn["pieces"]) == (w["items"], w["pieces"])
        assert (fu["items"], fu["pieces"], fu["live"]) == (w["items"], w["pieces"], w["live"])
        # deep, busy traversals: several splits and more than one leaf piece per lit query
        assert w["items"] > 5 * w["live"] and w["pieces"] > 1.5 * w["live"]
        assert w["levels"] >= 5
        for other in ("kernel", "fused"):
            for a, b in zip(got[other], got["wavefront"], strict=True):
                np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-7)
        runs.append((qs, light, two, got["kernel"]))
    assert any(k == bs.KMAX for k, _ in passes)  # lanes with pieces of more than 8 vertices
    monkeypatch.setattr(bs, "_capacity", lambda n: 1)
    monkeypatch.setattr(bs, "_TRAVERSE_CHUNK", 100)  # root items in chunks of 100
    before = len(passes)
    for qs, light, two, want in runs:
        for a, b in zip(integrals(tr, qs, light, two), want, strict=True):
            np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-7)
    chunked = [w for k, w in passes[before:] if k == bs._K_FIRST]
    assert len(chunked) > len(runs) and max(chunked) <= 100
    with pytest.raises(GlossrtError, match="traversal"):
        integrals(tr, qs, light, True, traversal="breadth")


def _light(vertices, radiance=(1.0, 0.8, 0.6), two_sided=False, texture=None, uv=None):
    return SimpleNamespace(vertices=np.asarray(vertices, np.float64),
                           radiance=np.asarray(radiance, np.float64), two_sided=two_sided,
                           texture=texture, uv=uv)


QUAD_DOWN = np.array([[-0.6, -0.5, 1.6], [-0.6, 0.7, 1.8], [0.7, 0.7, 1.8], [0.7, -0.5, 1.6]])


def test_shade_vertices_against_unshadowed_formulas():
    """All-visible trees: diffuse = L albedo clamped_cosine_integral, specular = L (F0 (norm -
    fres) + fres) i_s with i_s = ltc.polygon_integral / norm (NumPy routes); a tree of constant
    visibility 0.4 scales both by 0.4; views below the tangent plane give 0."""
    rng = np.random.default_rng(5)
    nv = 40
    pos = rng.normal(size=(nv, 3)) * 0.3
    nrm = unit(rng.normal(size=(nv, 3)) * 0.5 + [0, 0, 1])
    wo = unit(rng.normal(size=(nv, 3)) * 0.6 + nrm)
    wo[0] = -nrm[0]  # below: black
    alpha = rng.uniform(0.2, 1.0, nv)
    albedo, f0 = rng.uniform(0, 1, (nv, 3)), rng.uniform(0, 1, (nv, 3))
    tr = make_trees([[random_face_tree(rng, 8, (1.0,)) for _ in range(6)] for _ in range(nv)],
                    pos, nrm)
    lights = [_light(QUAD_DOWN), _light(QUAD_DOWN[:3] + [0.3, 0.2, 0.4], (0.5, 1.0, 2.0), True)]
    dev = bs.DeviceTrees.of(tr)
    diff, spec = bs.shade_vertices(dev, lights, wo, alpha, albedo, f0)
    want_d = np.zeros((nv, 3))
    want_s = np.zeros((nv, 3))
    cos_o = np.sum(nrm * wo, 1)
    _, norm, fres = _table().lookup_np(alpha, np.clip(cos_o, 0, 1))
    for lt in lights:
        i_d = clamped_cosine_integral(to_local(lt.vertices[None], pos, nrm),
                                      two_sided=lt.two_sided)
        i_s = polygon_integral(lt.vertices[None] - pos[:, None], nrm, wo, alpha,
                               two_sided=lt.two_sided) / norm
        want_d += lt.radiance * albedo * i_d[:, None]
        want_s += lt.radiance * (f0 * (norm - fres)[:, None] + fres[:, None]) * i_s[:, None]
    want_d[cos_o <= 0] = want_s[cos_o <= 0] = 0
    np.testing.assert_allclose(diff, want_d, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(spec, want_s, rtol=1e-4, atol=1e-5)
    assert np.all(diff[0] == 0) and want_d[1:].max() > 0.05
    d4, s4 = bs.shade_vertices(with_values(tr, 0.4), lights, wo, alpha, albedo, f0)
    np.testing.assert_allclose(d4, 0.4 * diff, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(s4, 0.4 * spec, rtol=1e-5, atol=1e-7)


@pytest.mark.slow
def test_deep_chain_tree():
    """A chain of 21 vertical lines on the +Z face, each with a lit leaf on its left and the
    rest of the chain on its right: the fused traversal holds 21 leaf pieces on its stack at
    once (its deepest use; the stack is sized from the tree depth). All traversals == the
    brute-force reference."""
    depth = 21
    node = 0.5
    for i in reversed(range(depth)):
        c = -0.75 + 1.5 * i / (depth - 1)
        node = ((1.0, 0.0, -c), 0.3 if i % 2 else 0.9, node)
    tr = make_trees([[0.0, 0.0, 0.0, 0.0, node, 0.0]])
    assert bs.DeviceTrees.of(tr).depth == depth
    light = np.array([[-1.2, -1.2, 1.5], [1.2, -1.2, 1.5], [1.2, 1.2, 1.5], [-1.2, 1.2, 1.5]])
    qs = Queries([[0.0, 0.0, 0.0]], [unit([0.1, 0.2, 1.0])], [unit([0.3, 0.1, 1.0])], 0.5)
    got = {}
    for traversal in bs.TRAVERSALS:
        st = {}
        got[traversal] = integrals(tr, qs, light, True, stats=st, traversal=traversal)
        assert st["pieces"] == depth + 1
    for traversal in ("kernel", "fused"):
        np.testing.assert_allclose(got[traversal], got["wavefront"], rtol=1e-5, atol=1e-7)
    check_against_reference(tr, qs, light, True, "chain")


def test_frozen_shading_replays_the_traced_result():
    """``frozen=True`` (the fused traversal recorded by dr.freeze) == the traced kernel
    traversal for three views and a moved light, per vertex and per pixel, with one recording
    per call signature (new views and light positions replay)."""
    rng = np.random.default_rng(10)
    nv = 30
    pos = rng.normal(size=(nv, 3)) * 0.3
    nrm = unit(rng.normal(size=(nv, 3)) * 0.5 + [0, 0, 1])
    alpha = rng.uniform(0.2, 1.0, nv)
    albedo, f0 = rng.uniform(0, 1, (nv, 3)), rng.uniform(0, 1, (nv, 3))
    dev = bs.DeviceTrees.of(make_trees([[random_face_tree(rng, 24) for _ in range(6)]
                                        for _ in range(nv)], pos, nrm))
    before = bs._shade_frozen.n_recordings
    for step in range(3):
        wo = unit(rng.normal(size=(nv, 3)) * 0.6 + nrm)
        lights = [_light(QUAD_DOWN + [0.1 * step, 0.0, 0.0]),
                  _light(QUAD_DOWN[:3] + [0.3, 0.2, 0.4], (0.5, 1.0, 2.0), True)]
        want = bs.shade_vertices(dev, lights, wo, alpha, albedo, f0)
        got = bs.shade_vertices(dev, lights, wo, alpha, albedo, f0, frozen=True)
        for g, w in zip(got, want, strict=True):
            np.testing.assert_allclose(g, w, rtol=1e-5, atol=1e-6)
        assert want[0].max() > 0.05
    assert bs._shade_frozen.n_recordings - before == 1
    tri = rng.integers(0, nv, (nv, 3))
    bary = rng.dirichlet([1, 1, 1], nv)
    pix = [bs.shade_pixels(dev, lights, pos, nrm, wo, alpha, albedo, f0, tri, bary,
                           frozen=fz) for fz in (False, True)]
    for g, w in zip(pix[1], pix[0], strict=True):
        np.testing.assert_allclose(g, w, rtol=1e-5, atol=1e-6)


def test_shade_pixels_blends_the_three_trees():
    """Three identical vertex trees == the single-tree result; three different trees == the
    barycentric blend of the single-tree results (shade_points with one tree each)."""
    rng = np.random.default_rng(6)
    face = [random_face_tree(rng, 12) for _ in range(6)]
    other = [[random_face_tree(rng, 12) for _ in range(6)] for _ in range(2)]
    tr = bs.DeviceTrees.of(make_trees([face, face, face, *other]))
    npx = 50
    p = rng.normal(size=(npx, 3)) * 0.2
    n = unit(rng.normal(size=(npx, 3)) * 0.3 + [0, 0, 1])
    wo = unit(rng.normal(size=(npx, 3)) * 0.5 + n)
    alpha, albedo, f0 = rng.uniform(0.2, 1, npx), rng.uniform(0, 1, (npx, 3)), \
        rng.uniform(0, 1, (npx, 3))
    bary = rng.dirichlet([1, 1, 1], npx)
    lights = [_light(QUAD_DOWN)]

    def single(vertex):
        sp = bs._points(p, n, wo, alpha, albedo, f0, npx)
        d, s = bs.shade_points(tr, lights, sp, [owned(mi.UInt32, np.full(npx, vertex))])
        return bs._np_color(d), bs._np_color(s)

    same = np.tile([0, 1, 2], (npx, 1))
    d, s = bs.shade_pixels(tr, lights, p, n, wo, alpha, albedo, f0, same, bary)
    d0, s0 = single(0)
    np.testing.assert_allclose(d, d0, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(s, s0, rtol=1e-5, atol=1e-7)
    assert d0.max() > 0.01
    mixed = np.tile([0, 3, 4], (npx, 1))
    d, s = bs.shade_pixels(tr, lights, p, n, wo, alpha, albedo, f0, mixed, bary)
    parts = [single(v) for v in (0, 3, 4)]
    want_d = sum(bary[:, j, None] * parts[j][0] for j in range(3))
    want_s = sum(bary[:, j, None] * parts[j][1] for j in range(3))
    np.testing.assert_allclose(d, want_d, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(s, want_s, rtol=1e-5, atol=1e-7)
    hit = np.arange(npx) % 2 == 0
    d, s = bs.shade_pixels(tr, lights, p, n, wo, alpha, albedo, f0, mixed, bary, hit=hit)
    assert np.all(d[~hit] == 0) and np.all(s[~hit] == 0)


def test_textured_lights():
    """A constant texture scales the untextured result; one piece (all-visible tree, light
    within one face) == ltc._texture_lookup times the integral; with shadows each piece's
    colour is a texture value, so col / i lies within the texture's range."""
    rng = np.random.default_rng(7)
    uv = np.array([[0, 0], [0, 1], [1, 1], [1, 0.0]])
    smooth = np.stack(np.meshgrid(np.linspace(0.2, 1, 16), np.linspace(1, 0.3, 16)), -1)
    img = np.concatenate([smooth, 0.5 * np.ones((16, 16, 1))], -1).astype(np.float32)
    qs = Queries.random(rng, 24, spread=0.2)
    qs.n = unit(qs.n * 0.3 + [0, 0, 1])
    qs = Queries(qs.p, qs.n, unit(qs.n + 0.4 * rng.normal(size=(24, 3))), qs.alpha)
    one = make_trees([[1.0] * 6])
    shadow = make_trees([[random_face_tree(rng, 16) for _ in range(6)]])
    const = PrefilteredTexture(np.full((8, 8, 3), [0.2, 0.5, 0.9], np.float32))
    light = _light(QUAD_DOWN, uv=uv)
    for tr in (one, shadow):
        i_d, i_s = integrals(tr, qs, QUAD_DOWN, False)
        c_d, c_s = integrals(tr, qs, QUAD_DOWN, False, texture=(light, const))
        np.testing.assert_allclose(c_d, i_d[None] * [[0.2], [0.5], [0.9]], rtol=1e-5,
                                   atol=1e-8)
        np.testing.assert_allclose(c_s, i_s[None] * [[0.2], [0.5], [0.9]], rtol=1e-5,
                                   atol=1e-8)
    tex = PrefilteredTexture(img)
    c_d, c_s = integrals(one, qs, QUAD_DOWN, False, texture=(light, tex))
    _, p, n, wo, coeffs = qs.dr()
    t1, t2 = ltc_frame(n, wo)
    local = _local([mi.Point3f(*(float(c) for c in v)) for v in QUAD_DOWN], p, t1, t2, n)
    i_d, i_s = _integrals(local, coeffs, False)
    want_d = np.array(_texture_lookup(light, tex, local, None) * i_d)
    want_s = np.array(_texture_lookup(light, tex, local, coeffs) * i_s)
    assert cube_face(unit(QUAD_DOWN - qs.p[:, None]))[0].max() == 4  # one face: one piece
    np.testing.assert_allclose(c_d, want_d, rtol=1e-4, atol=1e-7)
    np.testing.assert_allclose(c_s, want_s, rtol=1e-4, atol=1e-7)
    i_d, i_s = integrals(shadow, qs, QUAD_DOWN, False)
    c_d, c_s = integrals(shadow, qs, QUAD_DOWN, False, texture=(light, tex))
    lo, hi = img.reshape(-1, 3).min(0), img.reshape(-1, 3).max(0)
    for c, i in ((c_d, i_d), (c_s, i_s)):
        lit = i > 1e-4
        ratio = c[:, lit] / i[lit]
        assert np.all(ratio >= lo[:, None] - 1e-3) and np.all(ratio <= hi[:, None] + 1e-3)
        assert lit.sum() > 10
    with pytest.raises(GlossrtError, match="textured"):
        integrals(shadow, qs, QUAD_DOWN, False, texture=(light, tex), traversal="fused")
    # shade_points: a textured light is traced anew when frozen, and walked by the kernel
    # traversal under traversal="fused": the same colours as the default
    sp = bs._points(qs.p, qs.n, qs.wo, qs.alpha, np.ones((len(qs.p), 3)), None, len(qs.p))
    tex_light = _light(QUAD_DOWN, texture=img, uv=light.uv)
    shaded = [bs._np_color(bs.shade_points(shadow, [tex_light], sp, [qs.dr()[0]], **kw)[0])
              for kw in ({}, {"frozen": True}, {"traversal": "fused"})]
    for other in shaded[1:]:
        # equal to float32 rounding, not bit for bit: the kernel traversal appends pieces
        # (dr.scatter_inc) and sums them per query (dr.scatter_reduce) in the order the CPU
        # threads reach them, which changes with the load (seen 1e-7 apart under pytest-xdist)
        np.testing.assert_allclose(other, shaded[0], rtol=1e-6, atol=1e-9)
    assert shaded[0].max() > 0


def test_errors():
    rng = np.random.default_rng(8)
    good = make_trees([[random_face_tree(rng, 4) for _ in range(6)]])
    qs = Queries.random(rng, 4)
    dev = bs.DeviceTrees.of(good)
    assert bs.DeviceTrees.of(dev) is dev
    # the upload is cached on the trees with its arrays; new arrays upload anew
    assert bs.DeviceTrees.of(good) is dev
    again = SimpleNamespace(**vars(good))
    again.leaf_value = good.leaf_value * 0.5
    assert bs.DeviceTrees.of(again) is not dev
    np.testing.assert_allclose(np.array(bs.DeviceTrees.of(again).leaf_value),
                               0.5 * np.array(dev.leaf_value))

    def broken(**kw):
        out = SimpleNamespace(**vars(good))
        for k, v in kw.items():
            setattr(out, k, v)
        return out

    bad = {
        "shape": broken(lines=good.lines[:, :2]),
        "NaN": broken(lines=good.lines * np.nan),
        "out of range": broken(roots=np.full((1, 6), 1000, np.int32)),
        r"\[0, 1\]": broken(leaf_value=good.leaf_value + 2),
        "integers": broken(children=good.children.astype(np.float32)),
        "cycle": broken(children=np.where(good.children >= 0, 0, good.children)),
        "attribute": SimpleNamespace(lines=good.lines),
    }
    for msg, tr in bad.items():
        with pytest.raises(GlossrtError, match=msg):
            bs.DeviceTrees.of(tr)
    with pytest.raises(GlossrtError, match="3 to 8"):
        integrals(dev, qs, QUAD_DOWN[:2], True)
    with pytest.raises(GlossrtError, match="NaN"):
        integrals(dev, qs, QUAD_DOWN * np.nan, True)
    with pytest.raises(GlossrtError, match="out of range"):
        integrals(dev, Queries(qs.p, qs.n, qs.wo, qs.alpha, tree=[0, 0, 0, 5]), QUAD_DOWN, True)
    with pytest.raises(GlossrtError, match="NaN"):
        integrals(dev, Queries(qs.p * np.nan, qs.n, qs.wo, qs.alpha), QUAD_DOWN, True)
    # the frozen path checks its inputs too (one synchronisation for all tree indices)
    sp = bs._points(qs.p, qs.n, qs.wo, qs.alpha, np.ones((4, 3)), None, 4)
    sp.p = mi.Point3f(sp.p.x * np.nan, sp.p.y, sp.p.z)
    ok_idx, half = owned(mi.UInt32, [0, 0, 0, 0]), [mi.Float(0.5)] * 2
    with pytest.raises(GlossrtError, match="NaN"):
        bs.shade_points(dev, [_light(QUAD_DOWN)], sp, [ok_idx, ok_idx], half, frozen=True)
    sp = bs._points(qs.p, qs.n, qs.wo, qs.alpha, np.ones((4, 3)), None, 4)
    with pytest.raises(GlossrtError, match="out of range"):
        bs.shade_points(dev, [_light(QUAD_DOWN)], sp, [ok_idx, owned(mi.UInt32, [0, 0, 0, 9])],
                        half, frozen=True)
    with pytest.raises(GlossrtError, match="shape"):
        bs.shade_vertices(dev, [_light(QUAD_DOWN)], np.zeros((2, 3)), 0.5, np.zeros((1, 3)))
    with pytest.raises(GlossrtError, match="out of range"):
        bs.shade_pixels(dev, [_light(QUAD_DOWN)], qs.p, qs.n, qs.wo, qs.alpha,
                        np.zeros((4, 3)), None, np.full((4, 3), 3), np.full((4, 3), 1 / 3))
    with pytest.raises(GlossrtError, match="uv"):
        integrals(dev, qs, QUAD_DOWN, True,
                  texture=(_light(QUAD_DOWN), PrefilteredTexture(np.ones((4, 4, 3)))))
    empty = bs.shade_pixels(dev, [_light(QUAD_DOWN)], *[np.zeros((0, 3))] * 3, np.zeros(0),
                            np.zeros((0, 3)), None, np.zeros((0, 3), int), np.zeros((0, 3)))
    assert empty[0].shape == empty[1].shape == (0, 3)
    # a depth-2 traversal on 1 lane works (scalar-width arrays)
    i_d, _ = integrals(dev, Queries(qs.p[:1], qs.n[:1], qs.wo[:1], 0.5), QUAD_DOWN, True)
    assert np.isfinite(i_d).all()
