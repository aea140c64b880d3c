"""BSPVT precomputation (glossrt.lights.bspvt): cube conventions, visibility by ray tests
against analytic answers, trees against brute-force searches and NumPy re-implementations of
Okuno & Iwasaki's Algorithm 1 and eq. 3, and the file format."""

from __future__ import annotations

import heapq
import itertools
import math

import numpy as np
import pytest

from glossrt import backend

backend.ensure()
import mitsuba as mi  # noqa: E402

from glossrt.errors import GlossrtError  # noqa: E402
from glossrt.lights.bspvt import BSPVT  # noqa: E402
from glossrt.lights.bspvt import build as bspvt  # noqa: E402

T = mi.ScalarTransform4f


# -- helpers ------------------------------------------------------------------------------------

def centres_st(r):
    """(R, R) s and t of the texel centres, indexed [j, i]."""
    c = -1.0 + (2.0 * np.arange(r) + 1.0) / r
    return np.meshgrid(c, c, indexing="xy")


def eq3(vmap, sel, line):
    """Okuno & Iwasaki eq. 3 of a line over the selected texel centres (independent code)."""
    s, t = centres_st(vmap.shape[0])
    d = line[0] * s + line[1] * t + line[2]
    h0 = (d >= 0).astype(np.int64)
    return int(((h0 - vmap) ** 2)[sel].sum())


def synthetic_maps(rng, n, r):
    """0/1 maps (n, 6, r, r) with straight and curved boundaries (half-planes xor discs)."""
    s, t = centres_st(r)
    out = np.zeros((n, 6, r, r), np.uint8)
    for v in range(n):
        for f in range(6):
            th, off = rng.uniform(0, 2 * np.pi), rng.uniform(-1.2, 1.2)
            m = np.cos(th) * s + np.sin(th) * t + off >= 0
            cx, cy, rad = rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(0.1, 0.8)
            m ^= (s - cx) ** 2 + (t - cy) ** 2 < rad ** 2
            out[v, f] = m
    out[0, 0] = 1  # a uniform face
    return out


def mesh(name, v, f, nrm=None):
    props = mi.Properties("mesh")
    m = mi.Mesh(name, len(v), len(f), props, has_vertex_normals=nrm is not None)
    p = mi.traverse(m)
    p["vertex_positions"] = mi.Float(np.asarray(v, np.float32).ravel())
    p["faces"] = mi.UInt32(np.asarray(f, np.uint32).ravel())
    if nrm is not None:
        p["vertex_normals"] = mi.Float(np.asarray(nrm, np.float32).ravel())
    p.update()
    return m


def grid(n, half):
    """A square [-half, half]^2 at z = 0 as an n x n grid of quads (triangles, facing +z)."""
    x = np.linspace(-half, half, n + 1)
    xx, yy = np.meshgrid(x, x, indexing="xy")
    v = np.stack([xx.ravel(), yy.ravel(), np.zeros(xx.size)], -1)
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="xy")
    a = (j * (n + 1) + i).ravel()
    f = np.concatenate([np.stack([a, a + 1, a + n + 2], -1), np.stack([a, a + n + 2, a + n + 1],
                                                                        -1)])
    return v, f


def leaf_errors(tree, vis):
    """Per leaf: (texel count, ones) from the leaf map (bincount, independent of the build)."""
    n = np.zeros(len(tree.leaf_value), np.int64)
    o = np.zeros(len(tree.leaf_value), np.int64)
    for v in range(tree.vertex_count):
        lm = tree.leaf_map(v).ravel()
        n += np.bincount(lm, minlength=len(n))
        o += np.bincount(lm, weights=vis[v].ravel(), minlength=len(n)).astype(np.int64)
    return n, o


# -- cube conventions ---------------------------------------------------------------------------

def test_cube_round_trip_and_partition():
    rng = np.random.default_rng(1)
    d = rng.normal(size=(20000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    face, s, t = bspvt.cube_coords(d)
    assert np.all(np.abs(s) <= 1) and np.all(np.abs(t) <= 1)
    back = bspvt.cube_dir(face, s, t)
    assert np.allclose(back / np.linalg.norm(back, axis=1, keepdims=True), d, atol=1e-12)
    # every direction lies on exactly one face (the others' gnomonic coordinates leave
    # [-1, 1]^2 or their axis points away)
    on = np.zeros((len(d), 6), bool)
    for f in range(6):
        k, sg = f // 2, 1 - 2 * (f % 2)
        lead = sg * d[:, k]
        with np.errstate(divide="ignore", invalid="ignore"):
            su, tv = d[:, (k + 1) % 3] / lead, d[:, (k + 2) % 3] / lead
        on[:, f] = (lead > 0) & (np.abs(su) <= 1) & (np.abs(tv) <= 1)
    assert np.all(on.sum(1) == 1) and np.array_equal(np.argmax(on, 1), face)
    # the six faces share the sphere equally (Monte Carlo, 3 sigma)
    frac = np.bincount(face, minlength=6) / len(d)
    assert np.all(np.abs(frac - 1 / 6) < 3 * math.sqrt(1 / 6 * 5 / 6 / len(d)))
    # ties go to the lowest face; edges and corners
    f2, _, _ = bspvt.cube_coords(np.array([[1, 1, 0], [-1, 1, 1], [0, -1, -1], [1, -1, 1.0]]))
    assert f2.tolist() == [0, 1, 3, 0]


def test_texel_directions_map_back_to_their_texels():
    r = 8
    d = bspvt.cube_directions(r)
    assert d.shape == (6, r, r, 3) and np.allclose(np.linalg.norm(d, axis=-1), 1)
    face, s, t = bspvt.cube_coords(d)
    i, j = bspvt._texel_index(s, t, r)
    ff, jj, ii = np.meshgrid(np.arange(6), np.arange(r), np.arange(r), indexing="ij")
    assert np.array_equal(face, ff) and np.array_equal(i, ii) and np.array_equal(j, jj)
    c = bspvt.texel_centres(r)
    assert np.allclose(s, c[ii]) and np.allclose(t, c[jj])
    # +Z face: u = x, v = y; -Y face: u = z, v = x
    assert np.allclose(d[4, 0, r - 1] * (1 / d[4, 0, r - 1, 2]), [c[-1], c[0], 1])
    assert np.allclose(d[3, 2, 5] / -d[3, 2, 5, 1], [c[2], -1, c[5]])


def test_cube_bad_input():
    with pytest.raises(GlossrtError, match="NaN"):
        bspvt.cube_coords([[np.nan, 0, 1]])
    with pytest.raises(GlossrtError, match="zero"):
        bspvt.cube_coords([[0, 0, 0.0]])
    with pytest.raises(GlossrtError, match=r"\(\.\.\., 3\)"):
        bspvt.cube_coords(np.ones((4, 2)))
    with pytest.raises(GlossrtError):
        bspvt.cube_dir(6, 0.0, 0.0)
    with pytest.raises(GlossrtError):
        bspvt.cube_directions(0)


# -- visibility ---------------------------------------------------------------------------------

def occluder_scene(h, a, b):
    """A large floor grid (z = 0, facing +z) under a rectangle [-a, a] x [-b, b] at z = h, and
    an emitting rectangle (must not occlude) and an analytic sphere far away."""
    gv, gf = grid(8, 4.0)
    return mi.load_dict({
        "type": "scene",
        "floor": mesh("floor", gv, gf, np.tile([0, 0, 1.0], (len(gv), 1))),
        "roof": {"type": "rectangle", "to_world": T().translate([0, 0, h]).scale([a, b, 1])},
        "lamp": {"type": "rectangle", "to_world": T().translate([0, 0, 0.5 * h]).scale(0.3),
                 "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 1.0}}},
        "ball": {"type": "sphere", "center": [30, 30, 30], "radius": 0.5},
    })


def test_scene_vertices_and_occluders():
    scene = occluder_scene(1.0, 2.0, 1.0)
    pos, nrm, offs = bspvt.scene_vertices(scene)
    # stable order: floor (81 grid vertices), roof (Mitsuba's rectangle is a 4-vertex mesh);
    # the emitter and the analytic sphere contribute none
    assert offs.tolist() == [0, 81] and len(pos) == 85
    assert np.allclose(nrm[:81], [0, 0, 1]) and np.allclose(pos[81:, 2], 1.0)
    before = sorted(s.id() for s in scene.shapes())
    occ = bspvt.occluders(scene)
    # the emitter is gone, the analytic sphere stays (shared, id kept), meshes are copies;
    # the original scene's shapes keep their ids
    assert len(occ.shapes()) == 3 and "ball" in [s.id() for s in occ.shapes()]
    assert sorted(s.id() for s in scene.shapes()) == before
    ray = mi.Ray3f(mi.Point3f(0.1, 0.1, 0.25), mi.Vector3f(0, 0, 1))  # through the lamp
    assert bool(occ.ray_test(ray)[0]) and bool(scene.ray_test(mi.Ray3f(ray.o, ray.d))[0])
    occ_dirs = mi.Vector3f(1, 1, 1) / math.sqrt(3)
    far = mi.Ray3f(mi.Point3f(5, 5, 5), occ_dirs)  # towards the sphere at (30, 30, 30)
    assert bool(occ.ray_test(far)[0])


def test_faceted_normals_are_face_averages():
    # a tent: two slopes meeting at a ridge; no vertex normals in the mesh
    v = np.array([[-1, 0, 0], [0, 0, 1], [1, 0, 0], [-1, 1, 0], [0, 1, 1], [1, 1, 0.0]])
    f = np.array([[0, 1, 4], [0, 4, 3], [1, 2, 5], [1, 5, 4]])
    scene = mi.load_dict({"type": "scene", "tent": mesh("tent", v, f)})
    pos, nrm, offs = bspvt.scene_vertices(scene)
    assert np.allclose(pos, v) and offs.tolist() == [0]
    expect = np.zeros((6, 3))
    for tri in f:  # area-weighted face normals of the incident triangles
        n = np.cross(v[tri[1]] - v[tri[0]], v[tri[2]] - v[tri[0]])
        for k in tri:
            expect[k] += n
    expect /= np.linalg.norm(expect, axis=1, keepdims=True)
    assert np.allclose(nrm, expect)
    assert np.allclose(np.abs(nrm[0]), [1 / math.sqrt(2), 0, 1 / math.sqrt(2)])


def test_visibility_under_a_rectangle_is_analytic():
    h, a, b, r = 0.9, 1.7, 1.1, 16
    scene = occluder_scene(h, a, b)
    pos = np.array([[0.0, 0.0, 0.0], [0.5, -0.25, 0.0]])
    nrm = np.array([[0, 0, 1.0], [0, 0, 1.0]])
    vis = bspvt.visibility_cubemaps(scene, pos, nrm, r, progress=False)
    assert vis.shape == (2, 6, r, r) and vis.dtype == np.uint8
    d = bspvt.cube_directions(r)
    for k, p in enumerate(pos):
        with np.errstate(divide="ignore", invalid="ignore"):
            x = p[0] + h * d[..., 0] / d[..., 2]
            y = p[1] + h * d[..., 1] / d[..., 2]
        up = d[..., 2] > 0
        hits_roof = up & (np.abs(x) <= a) & (np.abs(y) <= b)
        expect = (up & ~hits_roof).astype(np.uint8)  # below the horizon: the floor
        # skip rays grazing the roof's edges (within 1e-3)
        edge = up & ((np.abs(np.abs(x) - a) < 1e-3) | (np.abs(np.abs(y) - b) < 1e-3))
        assert edge.sum() <= 8
        assert np.array_equal(vis[k][~edge], expect[~edge])
        assert hits_roof.sum() > 100 and (expect == 1).sum() > 100


def test_no_self_shadowing_on_a_flat_floor():
    gv, gf = grid(16, 2.0)
    scene = mi.load_dict({"type": "scene", "floor": mesh("floor", gv, gf)})
    pos, nrm, _ = bspvt.scene_vertices(scene)
    inner = np.nonzero((np.abs(pos[:, 0]) < 1.5) & (np.abs(pos[:, 1]) < 1.5))[0][::7]
    vis = bspvt.visibility_cubemaps(scene, pos[inner], nrm[inner], 16, progress=False)
    up = bspvt.cube_directions(16)[..., 2] > 0
    # every upper-hemisphere texel escapes, every lower one hits the floor
    assert np.array_equal(vis, np.broadcast_to(up, vis.shape).astype(np.uint8))


def test_visibility_bad_input():
    scene = occluder_scene(1.0, 1.0, 1.0)
    with pytest.raises(GlossrtError, match="positions"):
        bspvt.visibility_cubemaps(scene, np.zeros((3, 2)), np.zeros((3, 3)), 8)
    with pytest.raises(GlossrtError, match="NaN"):
        bspvt.visibility_cubemaps(scene, np.full((1, 3), np.nan), np.ones((1, 3)), 8)
    with pytest.raises(GlossrtError, match="normals"):
        bspvt.visibility_cubemaps(scene, np.zeros((2, 3)), np.ones((3, 3)), 8)
    with pytest.raises(GlossrtError, match="resolution"):
        bspvt.visibility_cubemaps(scene, np.zeros((1, 3)), np.ones((1, 3)), 0)


# -- the split search ---------------------------------------------------------------------------

def brute_force_best(vmap, sel):
    """min of eq. 3 over all lines leaving both sides of the selected texel centres non-empty:
    every such partition is realised by a line through two centres, nudged (rotated about
    their midpoint or shifted) by a tiny amount."""
    r = vmap.shape[0]
    s, t = centres_st(r)
    pts = np.stack([s[sel], t[sel]], 1)
    v = vmap[sel].astype(np.int64)
    best = None
    eps = 1e-7
    for p, q in itertools.combinations(range(len(pts)), 2):
        dvec = pts[q] - pts[p]
        nrm = np.array([-dvec[1], dvec[0]]) / np.linalg.norm(dvec)
        mid = 0.5 * (pts[p] + pts[q])
        base = (pts - mid) @ nrm
        along = (pts - mid) @ (dvec / np.linalg.norm(dvec))
        for d in (base + eps, base - eps, base + eps * along, base - eps * along):
            right = d >= 0
            if right.all() or not right.any():
                continue
            for h0 in (right, ~right):
                e = int(np.sum(h0.astype(np.int64) != v))
                best = e if best is None else min(best, e)
    return best


def test_batched_split_is_optimal_over_all_lines():
    rng = np.random.default_rng(7)
    r = 6
    for trial in range(12):
        if trial % 3 == 0:
            vmap = rng.integers(0, 2, (r, r))
        else:
            vmap = synthetic_maps(rng, 1, r)[0, 1 + trial % 5].astype(np.int64)
        sel = np.ones((r, r), bool) if trial % 2 == 0 else rng.random((r, r)) < 0.7
        if sel.sum() < 2:
            continue
        split = bspvt.best_split(vmap, sel, angles="exact")
        assert split.error == brute_force_best(vmap, sel)
        # the returned line really has that error, and leaves both sides non-empty
        assert eq3(vmap, sel, split.line.astype(np.float32)) == split.error
        s, t = centres_st(r)
        d = split.line[0] * s + split.line[1] * t + split.line[2]
        assert (d[sel] >= 0).any() and (d[sel] < 0).any()
        # 64 angles are never better than all lines
        assert bspvt.best_split(vmap, sel, angles=64).error >= split.error


def test_batched_split_is_exact_over_offsets_per_angle():
    """For each angle of the search the offset is optimal: compare with a NumPy scan of every
    cut between consecutive projections."""
    rng = np.random.default_rng(3)
    r = 12
    vmap = synthetic_maps(rng, 1, r)[0, 2].astype(np.int64)
    ang = bspvt._Angles(r, 8)
    s, t = centres_st(r)
    best = None
    for th in ang.theta:
        p = (np.cos(th) * s + np.sin(th) * t).ravel()
        for cut in 0.5 * (np.sort(p)[1:] + np.sort(p)[:-1]):
            for sg in (1, -1):
                e = int(np.sum(((sg * (p - cut)) >= 0) != vmap.ravel()))
                best = e if best is None else min(best, e)
    assert bspvt.best_split(vmap, angles=8).error == best


def test_nelder_mead_never_beats_the_exact_search():
    rng = np.random.default_rng(11)
    r = 8
    for trial in range(5):
        vmap = synthetic_maps(rng, 1, r)[0, 1 + trial].astype(np.int64)
        nm = bspvt.best_split(vmap, method="nelder-mead")
        exact = bspvt.best_split(vmap, angles="exact")
        assert nm.line is not None and nm.error >= exact.error
        assert eq3(vmap, np.ones((r, r), bool), nm.line.astype(np.float32)) == nm.error
    # a half-plane map: Nelder-Mead finds a perfect line
    s, t = centres_st(16)
    half = (0.6 * s - 0.8 * t + 0.13 >= 0).astype(np.int64)
    nm = bspvt.best_split(half, method="nelder-mead")
    assert nm.error == 0 and eq3(half, np.ones((16, 16), bool), nm.line) == 0


# -- trees --------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def maps16():
    return synthetic_maps(np.random.default_rng(5), 6, 16)


def test_epsilon_zero_reconstructs_exactly(maps16):
    tree = bspvt.build_trees(maps16, progress=False)
    assert tree.info["leaves_over_epsilon"] == 0
    for v in range(len(maps16)):
        assert np.array_equal(tree.reconstruct(v), maps16[v].astype(np.float32))
    # uniform faces are single leaves
    assert tree.roots[0, 0] < 0 and tree.leaf_value[~tree.roots[0, 0]] == 1.0
    # leaf values are the means of their texels
    n, o = leaf_errors(tree, maps16)
    assert np.all(n > 0) and np.allclose(tree.leaf_value, o / n)


def test_real_visibility_reconstructs_exactly():
    scene = occluder_scene(0.6, 0.8, 0.5)
    pos = np.array([[0.1, 0.2, 0.0], [1.0, 0.3, 0.0], [-0.7, -0.9, 0.0]])
    nrm = np.array([[0, 0, 1.0], [0.3, 0, 1.0], [0, -0.5, 1.0]])
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    vis = bspvt.visibility_cubemaps(scene, pos, nrm, 32, progress=False)
    tree = bspvt.build_trees(vis, positions=pos, normals=nrm, progress=False)
    for v in range(3):
        assert np.array_equal(tree.reconstruct(v), vis[v].astype(np.float32))
    assert np.allclose(tree.positions, pos) and np.allclose(tree.normals, nrm)


@pytest.mark.parametrize("eps", [1.0, 4.0, 12.5])
def test_epsilon_bounds_every_leaf(maps16, eps):
    tree = bspvt.build_trees(maps16, epsilon=eps, progress=False)
    n, o = leaf_errors(tree, maps16)
    e = np.minimum(o, n - o)
    # every leaf's error (its minority count) is at most epsilon; thresholding its mean
    # misclassifies e texels and the texels deviate from it by 2 n1 n0 / n <= 2 epsilon
    assert np.all(e <= eps) and tree.info["leaves_over_epsilon"] == 0
    assert np.all(2 * o * (n - o) / n <= 2 * eps + 1e-9)
    assert np.allclose(tree.leaf_value, o / n)
    # a coarser tolerance never needs more leaves
    assert len(tree.leaf_value) <= len(bspvt.build_trees(maps16, progress=False).leaf_value)


def test_stalled_leaf_rule_and_depth_cap(maps16):
    # an isolated texel inside a region of the other value: no single line reduces eq. 3
    vis = np.ones((1, 6, 16, 16), np.uint8)
    vis[0, 2, 7, 9] = 0
    exact = bspvt.build_trees(vis, progress=False)
    assert np.array_equal(exact.reconstruct(0), vis[0].astype(np.float32))
    literal = bspvt.build_trees(vis, stalled="leaf", progress=False)
    assert literal.roots[0, 2] < 0 and literal.info["leaves_over_epsilon"] == 1
    assert np.isclose(literal.leaf_value[~literal.roots[0, 2]], 255 / 256)
    capped = bspvt.build_trees(maps16, max_depth=2, progress=False)
    for v in range(len(maps16)):
        for f in range(6):
            assert len(np.unique(capped.leaf_map(v)[f])) <= 4
    assert capped.stats()["max_depth"] <= 2


def full_tree_clusters(tree, vis, v, f):
    """For one face of a tree: every node's texel set, by a NumPy walk (independent of the
    builder): dict code -> (mask, is_internal, (left code, right code))."""
    r = tree.resolution
    s, t = centres_st(r)
    out = {}

    def rec(entry, code, mask):
        if entry < 0:
            out[code] = (mask, False, None)
            return
        a, b, c = tree.lines[entry].astype(np.float64)
        right = a * s + b * t + c >= 0
        out[code] = (mask, True, (2 * code, 2 * code + 1))
        rec(tree.children[entry, 0], 2 * code, mask & ~right)
        rec(tree.children[entry, 1], 2 * code + 1, mask & right)

    rec(tree.roots[v, f], 1, np.ones((r, r), bool))
    return out


def test_max_leaves_is_the_priority_queue(maps16):
    full = bspvt.build_trees(maps16, progress=False)
    for budget in (1, 3, 7):
        cut = bspvt.build_trees(maps16, max_leaves=budget, progress=False)
        for v in range(len(maps16)):
            rec = cut.reconstruct(v)
            for f in range(6):
                cl = full_tree_clusters(full, maps16, v, f)
                vals = maps16[v, f]

                def err(code, cl=cl, vals=vals):
                    m = cl[code][0]
                    o = int(vals[m].sum())
                    return min(o, int(m.sum()) - o)

                # Algorithm 1 with a leaf budget: pop the largest error (ties: smaller code)
                heap, leaves, frontier = [(-err(1), 1)], 1, []
                while heap:
                    ne, code = heapq.heappop(heap)
                    if -ne <= 0 or leaves >= budget or not cl[code][1]:
                        frontier.append(code)
                        continue
                    leaves += 1
                    for ch in cl[code][2]:
                        heapq.heappush(heap, (-err(ch), ch))
                expect = np.zeros(vals.shape)
                for code in frontier:
                    m = cl[code][0]
                    expect[m] = vals[m].mean()
                assert len(frontier) <= budget
                assert np.allclose(rec[f], expect)


def test_nelder_mead_trees(maps16):
    vis = maps16[1:3]
    tree = bspvt.build_trees(vis, method="nelder-mead", progress=False)
    for v in range(2):
        assert np.array_equal(tree.reconstruct(v), vis[v].astype(np.float32))
    small = bspvt.build_trees(vis, method="nelder-mead", max_leaves=3, epsilon=2,
                              progress=False)
    for v in range(2):
        for f in range(6):
            assert len(np.unique(small.leaf_map(v)[f])) <= 3
    assert small.info["method"] == "nelder-mead"


def test_chunking_and_threads_do_not_change_the_tree(maps16):
    a = bspvt.build_trees(maps16, progress=False)
    b = bspvt.build_trees(maps16, chunk_work=3 * 64 * 256, threads=2, progress=False)
    for k in ("lines", "children", "leaf_value", "roots"):
        assert np.array_equal(getattr(a, k), getattr(b, k))


def test_drjit_engine_builds_the_same_trees(maps16):
    """The Dr.Jit engine (prefix sums, scatter-reductions and the partition on the device)
    gives the NumPy engine's trees bit for bit: exact reconstruction (epsilon 0, stalled
    clusters split by the fallback), and an error threshold with a leaf budget and a depth
    cap in chunks of eight faces."""
    stalled = []
    for kw in ({}, {"epsilon": 2.0, "max_leaves": 6, "max_depth": 5, "angles": 16}):
        a = bspvt.build_trees(maps16, progress=False, **kw)
        stalled.append(a.info["stalled_splits"])
        chunk = 8 * len(_angles(kw)) * 256 if kw else None  # 8 faces per chunk
        b = bspvt.build_trees(maps16, progress=False, engine="drjit", chunk_work=chunk, **kw)
        assert_same_trees(a, b)
        assert a.info["stalled_splits"] == b.info["stalled_splits"]
        assert b.info["engine"] == "drjit" and a.info["depth"] >= 4
    assert stalled[0] > 0  # the fallback split of stalled clusters ran on the device too
    # one face per chunk (chunks of a single cluster at the root)
    a = bspvt.build_trees(maps16[:2], progress=False, angles=16)
    b = bspvt.build_trees(maps16[:2], progress=False, angles=16, engine="drjit",
                          chunk_work=len(_angles({"angles": 16})) * 256)
    assert_same_trees(a, b)
    with pytest.raises(GlossrtError, match="engine"):
        bspvt.build_trees(maps16, engine="torch", progress=False)


def assert_same_trees(a, b):
    for k in ("lines", "children", "leaf_value", "roots"):
        assert np.array_equal(getattr(a, k), getattr(b, k)), k


def _angles(kw: dict):
    return bspvt._Angles.get(16, kw.get("angles", bspvt.DEFAULT_ANGLES)).theta


def test_evaluate_matches_reconstruct_and_directions(maps16):
    tree = bspvt.build_trees(maps16, epsilon=2, progress=False)
    d = bspvt.cube_directions(16) * 3.0  # any length
    for v in range(3):
        assert np.array_equal(tree.evaluate(v, d), tree.reconstruct(v))
    rng = np.random.default_rng(0)
    dirs = rng.normal(size=(500, 3))
    face, s, t = bspvt.cube_coords(dirs)
    i, j = bspvt._texel_index(s, t, 16)
    # every direction reads the leaf of some texel of its face (piecewise constant)
    vals = tree.evaluate(2, dirs)
    assert vals.shape == (500,) and set(np.unique(vals)) <= set(tree.leaf_value.tolist())
    with pytest.raises(GlossrtError, match="vertex"):
        tree.evaluate(len(maps16), dirs)


def test_stats_are_table_1(maps16):
    tree = bspvt.build_trees(maps16, progress=False)
    st = tree.stats()
    assert st["vertices"] == 6 and st["resolution"] == 16 and st["epsilon"] == 0
    assert st["data_bytes"] == 20 * len(tree.lines) + 4 * len(tree.leaf_value) + 24 * 6
    assert st["leaves_per_vertex"] == len(tree.leaf_value) / 6
    assert st["build_seconds"] > 0 and st["data_mb"] == st["data_bytes"] / 1e6


def test_build_bad_input(maps16):
    with pytest.raises(GlossrtError, match=r"\(V, 6, R, R\)"):
        bspvt.build_trees(np.zeros((2, 5, 8, 8)), progress=False)
    with pytest.raises(GlossrtError, match="NaN"):
        bspvt.build_trees(np.full((1, 6, 4, 4), np.nan), progress=False)
    with pytest.raises(GlossrtError, match="only 0"):
        bspvt.build_trees(np.full((1, 6, 4, 4), 2), progress=False)
    with pytest.raises(GlossrtError, match="epsilon"):
        bspvt.build_trees(maps16, epsilon=-1, progress=False)
    with pytest.raises(GlossrtError, match="method"):
        bspvt.build_trees(maps16, method="simplex", progress=False)
    with pytest.raises(GlossrtError, match="angles"):
        bspvt.build_trees(maps16, angles=0, progress=False)
    with pytest.raises(GlossrtError, match="positions"):
        bspvt.build_trees(maps16, positions=np.zeros((2, 3)), progress=False)


# -- files --------------------------------------------------------------------------------------

def test_save_load_round_trip(tmp_path, maps16):
    tree = bspvt.build_trees(maps16, epsilon=1, positions=np.arange(18.0).reshape(6, 3),
                             normals=np.tile([0, 1.0, 0], (6, 1)), progress=False)
    path = tmp_path / "trees.npz"
    tree.save(str(path))
    back = BSPVT.load(str(path))
    for k in ("lines", "children", "leaf_value", "roots", "positions", "normals"):
        assert np.array_equal(getattr(back, k), getattr(tree, k))
        assert getattr(back, k).dtype == getattr(tree, k).dtype
    assert back.resolution == 16 and back.epsilon == 1 and back.info == tree.info
    assert np.array_equal(back.reconstruct(3), tree.reconstruct(3))


def test_load_rejects_bad_files(tmp_path, maps16):
    tree = bspvt.build_trees(maps16[:2], progress=False)
    with pytest.raises(GlossrtError, match="not found"):
        BSPVT.load(str(tmp_path / "missing.npz"))
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"PK\x03\x04 this is not a zip file")
    with pytest.raises(GlossrtError, match="junk.npz"):
        BSPVT.load(str(junk))
    good = tmp_path / "good.npz"
    tree.save(str(good))
    data = dict(np.load(good))

    def write(name, **changes):
        p = tmp_path / name
        np.savez(p, **{**data, **changes})
        return str(p)

    with pytest.raises(GlossrtError, match="version"):
        BSPVT.load(write("v.npz", version=np.int32(99)))
    np.savez(tmp_path / "m.npz", **{k: v for k, v in data.items() if k != "lines"})
    with pytest.raises(GlossrtError, match="missing lines"):
        BSPVT.load(str(tmp_path / "m.npz"))
    bad_children = data["children"].copy()
    bad_children[0, 0] = len(data["lines"]) + 5
    with pytest.raises(GlossrtError, match="out of range"):
        BSPVT.load(write("c.npz", children=bad_children))
    cyc = data["children"].copy()
    if len(cyc) > 1:
        cyc[1, 0] = 0  # points back at the root of an earlier tree
        with pytest.raises(GlossrtError, match="after its parent|exactly once"):
            BSPVT.load(write("y.npz", children=cyc))
    nan_lines = data["lines"].copy()
    nan_lines[0, 2] = np.nan
    with pytest.raises(GlossrtError, match="NaN"):
        BSPVT.load(write("n.npz", lines=nan_lines))
    with pytest.raises(GlossrtError, match="dtype"):
        BSPVT.load(write("d.npz", roots=data["roots"].astype(np.int64)))
    with pytest.raises(GlossrtError, match="leaf values"):
        BSPVT.load(write("l.npz", leaf_value=data["leaf_value"] + 2))
