"""glossrt.lights.polygon (horizon clipping, Lambert's edge integral of the clamped cosine)
against independent float64 NumPy computations:

* Monte Carlo: cosine-distributed directions and a ray-polygon hit test (the direction lies
  in the polygon's cone: on the inner side of every edge plane). The number of hits of ``N``
  directions is Binomial(N, I) exactly, so each polygon gets an exact binomial p-value; the
  test fails if any is below 1e-3 / (2 x number of polygons) (one- and two-sided;
  Bonferroni: a correct
  implementation fails with probability < 1e-3; the seeds are fixed, so it is deterministic);
* Gauss quadrature of ``cos theta cos theta_l / (pi r^2)`` over the polygon's area (after a
  float64 Sutherland-Hodgman clip written here), for the accuracy numbers;
* closed forms: differential element to a parallel rectangle and to a perpendicular
  rectangle (J. R. Howell, "A Catalog of Radiation Heat Transfer Configuration Factors":
  differential planar element to a parallel / perpendicular finite rectangle), the
  small-source limit ``A cos cos' / (pi d^2)``.

Float32 error bounds come from an error analysis (:func:`robust_bound`), not from the
measurements; the measured numbers are printed with ``pytest -s`` and summarised in the module
docstring of glossrt.lights.polygon.
"""

from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
from scipy import stats

from glossrt.errors import GlossrtError
from glossrt.lights import polygon as P

EPS32 = 2.0**-24
ABS32 = 32 * EPS32  # absolute error cap of the robust form (see robust_bound)
K8 = 8

# ------------------------------------------------------------------------------ helpers


def _vec(a, vt=mi.Vector3f):
    a = np.atleast_2d(np.asarray(a, dtype=np.float64))
    ft = dr.value_t(vt)
    return vt(ft(a[:, 0]), ft(a[:, 1]), ft(a[:, 2]))


def _dr_poly(v, vt=mi.Vector3f):
    """(P, K, 3) array -> list of K Dr.Jit vectors."""
    v = np.asarray(v, dtype=np.float64)
    if v.ndim == 2:
        v = v[None]
    return [_vec(v[:, i], vt) for i in range(v.shape[1])]


def _np(x) -> np.ndarray:
    return np.asarray(x.numpy(), dtype=np.float64)


def _np3(v) -> np.ndarray:
    return np.stack([_np(v[i]) for i in range(3)], axis=-1)


def random_rotation(rng, n):
    q, r = np.linalg.qr(rng.normal(size=(n, 3, 3)))
    q = q * np.sign(np.diagonal(r, axis1=1, axis2=2))[:, None, :]
    det = np.linalg.det(q)
    q[:, :, 0] *= det[:, None]  # proper rotations
    return q


def random_polygons(rng, n, k_max=K8):
    """``n`` random convex polygons: ``k`` in 3..k_max vertices at sorted random angles on an
    ellipse (points on an ellipse are in convex position), random size, rotation, distance
    and direction (~60 % of centres above the horizon, many polygons straddle it), random
    winding. Slots ``k..k_max-1`` hold unrelated junk (they must be ignored through counts).
    Vertices are rounded to float32, so the references see the same input."""
    k = rng.integers(3, k_max + 1, n)
    ang = np.sort(rng.uniform(0.0, 2.0 * math.pi, (n, k_max)), axis=1)
    ang = np.where(np.arange(k_max) < k[:, None], ang, np.inf)
    ang = np.sort(ang, axis=1)
    size = 10.0 ** rng.uniform(-1.0, 1.0, n)
    ecc = rng.uniform(0.2, 1.0, n)
    ang = np.where(np.isfinite(ang), ang, 0.0)  # slots >= k: overwritten by junk below
    local = np.stack([np.cos(ang), ecc[:, None] * np.sin(ang), np.zeros_like(ang)], -1)
    local = local * size[:, None, None]
    rot = random_rotation(rng, n)
    d = size * 10.0 ** rng.uniform(math.log10(0.3), math.log10(40.0), n)
    u = rng.normal(size=(n, 3))
    u[:, 2] = np.abs(u[:, 2]) * np.where(rng.random(n) < 0.6, 1.0, -1.0)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v = np.einsum("nij,nkj->nki", rot, local) + (d[:, None] * u)[:, None, :]
    flip = rng.random(n) < 0.5
    idx = np.arange(k_max)[None, :]
    rev = np.where(idx < k[:, None], k[:, None] - 1 - idx, idx)
    v = np.where(flip[:, None, None], np.take_along_axis(v, rev[..., None], axis=1), v)
    junk = rng.normal(size=v.shape) * 1e3
    v = np.where(idx[..., None] < k[:, None, None], v, junk)
    return v.astype(np.float32).astype(np.float64), k


def used(v, k):
    return v[:k]


def newell(p):
    """Right-hand area vector (twice the area times the front normal), float64."""
    return sum(np.cross(p[i] - p[0], p[i + 1] - p[0]) for i in range(1, len(p) - 1))


def front_facing(p) -> bool:
    """The right-hand normal points towards the origin (the shading point)."""
    return float(newell(p) @ (-p[0])) > 0.0


def clip_np(p):
    """Sutherland & Hodgman 1974 against z >= 0, float64 (reference implementation)."""
    out = []
    for i in range(len(p)):
        a, b = p[i], p[(i + 1) % len(p)]
        if a[2] >= 0:
            out.append(a)
        if (a[2] >= 0) != (b[2] >= 0):
            t = a[2] / (a[2] - b[2])
            q = a + t * (b - a)
            q[2] = 0.0
            out.append(q)
    return np.array(out).reshape(-1, 3)


def mc_hits(polys, ks, n_dir, rng, chunk=100):
    """Hits of ``n_dir`` cosine-distributed directions per polygon (ray-polygon test: the
    direction is inside the polygon's cone, i.e. on the inner side of all edge planes)."""
    n = len(polys)
    hits = np.zeros(n, dtype=np.int64)
    kmax = polys.shape[1]
    for s in range(0, n, chunk):
        pp, kk = polys[s:s + chunk], ks[s:s + chunk]
        m = len(pp)
        nxt = np.where(np.arange(kmax)[None] + 1 < kk[:, None],
                       (np.arange(kmax)[None] + 1) % kmax, 0)
        pn = np.take_along_axis(pp, nxt[..., None], axis=1)
        edge_n = np.cross(pp, pn)
        edge_n = np.where((np.arange(kmax)[None] < kk[:, None])[..., None], edge_n, 0.0)
        g = np.array([used(pp[i], kk[i]).mean(0) for i in range(m)])
        sigma = np.sign(np.einsum("pc,pkc->p", g, edge_n))
        edge_n = edge_n * sigma[:, None, None]  # inward normals
        # cosine-distributed directions (Malley's method), float64
        u1 = rng.random((m, n_dir))
        phi = rng.random((m, n_dir)) * (2.0 * math.pi)
        r = np.sqrt(u1)
        w = np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(1.0 - u1)], -1)
        side = np.matmul(w, np.swapaxes(edge_n, 1, 2))  # (m, n_dir, K)
        hits[s:s + m] = np.count_nonzero(side.min(axis=-1) >= 0.0, axis=1)
    return hits


def arc_sum(p) -> float:
    """Sum of the edge angles of the horizon-clipped polygon (float64): the error scale of the
    edge sum, whose terms have size theta_i."""
    c = clip_np(p)
    total = 0.0
    for i in range(len(c)):
        a, b = c[i], c[(i + 1) % len(c)]
        total += math.atan2(np.linalg.norm(np.cross(a, b)), a @ b)
    return total


def robust_bound(p, value) -> float:
    """Error bound of the robust float32 edge sum: every term theta_i c_i / |c_i| carries a
    relative error below 16 eps (Dr.Jit's float32 atan2: up to 13.7 eps, measured over 3.5e6
    arguments; cross product, norm and division: a few eps more, partly cancelling), so
    |error| <= 16 eps (sum_i theta_i / (2 pi) + I). Since sum theta_i <= 2 pi (perimeter of a
    convex spherical polygon in a hemisphere) and I <= 1 this is at most ABS32 = 32 eps; relative
    to I it grows for small polygons and slivers (the terms cancel)."""
    return 16 * EPS32 * (arc_sum(p) / (2 * math.pi) + value)


def binom_pvalues(hits, n, p):
    p = np.clip(p, 0.0, 1.0)
    lo = stats.binom.cdf(hits, n, p)
    hi = stats.binom.sf(hits - 1, n, p)
    return np.minimum(1.0, 2.0 * np.minimum(lo, hi))


def _tri_rule(order):
    x, w = np.polynomial.legendre.leggauss(order)
    x, w = 0.5 * (x + 1.0), 0.5 * w
    s, t = np.meshgrid(x, x, indexing="ij")
    ws = np.outer(w, w) * s  # collapsed (Duffy) square -> triangle, Jacobian s
    return s.ravel(), t.ravel(), ws.ravel()


def area_integral(p, f, order):
    """Integral of ``f(x, n)`` over the convex polygon ``p`` (fan triangulation, collapsed
    Gauss-Legendre per triangle; ``n``: the triangle's unit normal). Per-triangle normals
    matter: vertices rounded to float32 are not exactly coplanar, and the edge formula
    integrates over the cone of the actual (slightly non-planar) edge loop."""
    s, t, w = _tri_rule(order)
    total = 0.0
    for i in range(1, len(p) - 1):
        a, b, c = p[0], p[i], p[i + 1]
        x = a + s[:, None] * (b - a) + (s * t)[:, None] * (c - b)
        nrm = np.cross(b - a, c - b)
        jac = np.linalg.norm(nrm)
        if jac == 0.0:
            continue
        total = total + jac * np.tensordot(w, f(x, nrm / jac), axes=(0, 0))
    return total


def quad_cosine(p, order):
    """(1/pi) int max(cos, 0) dw of polygon p (two-sided), by area quadrature of the clipped
    polygon: integrand z |n.x| / (pi |x|^4)."""
    c = clip_np(p)
    if len(c) < 3:
        return 0.0
    return float(area_integral(c, lambda x, n: x[:, 2] * np.abs(x @ n)
                               / (math.pi * np.sum(x * x, 1) ** 2), order))


def quad_form_factor(p, order):
    """+-(1/pi) int w dw of the unclipped polygon (+ front-facing), area quadrature."""
    v = area_integral(p, lambda x, n: x * (np.abs(x @ n) / (math.pi * np.sum(x * x, 1) ** 2))
                      [:, None], order)
    return v if front_facing(p) else -v


def parallel_rect(x0, x1, y0, y1, c):
    """Clamped-cosine integral of the rectangle [x0,x1] x [y0,y1] at height c > 0 parallel
    to the receiver: superposition of the corner form factor (Howell's catalogue, "differential
    planar element to a parallel rectangle, normal through a corner")
    F(X, Y) = 1/(2 pi) [X/sqrt(1+X^2) atan(Y/sqrt(1+X^2)) + Y/sqrt(1+Y^2) atan(X/sqrt(1+Y^2))]."""

    def g(x, y):
        X, Y = abs(x) / c, abs(y) / c
        f = (X / math.sqrt(1 + X * X) * math.atan(Y / math.sqrt(1 + X * X))
             + Y / math.sqrt(1 + Y * Y) * math.atan(X / math.sqrt(1 + Y * Y))) / (2 * math.pi)
        return math.copysign(1.0, x) * math.copysign(1.0, y) * f

    return g(x1, y1) - g(x0, y1) - g(x1, y0) + g(x0, y0)


def perpendicular_rect(a, b, c):
    """Rectangle in the plane x = c, y in [0, b], z in [0, a] (one edge on the receiver's
    plane): Howell's "differential element to a perpendicular rectangle", X = a/b, Y = c/b:
    F = 1/(2 pi) [atan(1/Y) - Y/sqrt(X^2+Y^2) atan(1/sqrt(X^2+Y^2))]."""
    X, Y = a / b, c / b
    r = math.hypot(X, Y)
    return (math.atan(1 / Y) - Y / r * math.atan(1 / r)) / (2 * math.pi)


def square(half, z, cx=0.0, cy=0.0, front=True):
    """Axis-aligned square at height z; front=True: counter-clockwise seen from below."""
    q = np.array([[-half, half, z], [half, half, z], [half, -half, z], [-half, -half, z]])
    q[:, 0] += cx
    q[:, 1] += cy
    return q if front else q[::-1].copy()


# ------------------------------------------------------------------------------ shared data


@pytest.fixture(scope="module")
def random_set():
    rng = np.random.default_rng(20260505)
    polys, ks = random_polygons(rng, 3000)
    verts = _dr_poly(polys)
    cnt = mi.UInt32(ks.astype(np.uint32))
    res = {
        "two": _np(P.cosine_integral(verts, cnt, two_sided=True)),
        "one": _np(P.cosine_integral(verts, cnt, two_sided=False)),
        "two_exact": _np(P.cosine_integral(verts, cnt, two_sided=True, robust=False)),
        "ff": _np3(P.form_factor_vector(verts, cnt)),
        "ff_exact": _np3(P.form_factor_vector(verts, cnt, robust=False)),
    }
    return polys, ks, res


@pytest.fixture(scope="module")
def quadrature(random_set):
    """Float64 area quadrature at two orders; keep the polygons where they agree to 1e-10."""
    polys, ks, _ = random_set
    sel = np.arange(0, len(polys), 2)  # every other polygon: half the cost, same statistics
    q16 = np.array([quad_cosine(used(polys[i], ks[i]), 16) for i in sel])
    q28 = np.array([quad_cosine(used(polys[i], ks[i]), 28) for i in sel])
    ok = np.abs(q16 - q28) <= 1e-10 * np.maximum(q28, 1e-3)
    return sel[ok], q28[ok], ok.mean()


# ------------------------------------------------------------------------------ clipping


@pytest.mark.slow
def test_clip_matches_reference_sutherland_hodgman(random_set):
    polys, ks, _ = random_set
    sel = slice(0, 600)
    out, cnt = P.clip_to_horizon(_dr_poly(polys[sel]), mi.UInt32(ks[sel].astype(np.uint32)))
    assert len(out) == K8 + 1
    got = np.stack([_np3(o) for o in out], axis=1)
    cnt = _np(cnt).astype(int)
    n_straddle = 0
    for i, (p, k) in enumerate(zip(polys[sel], ks[sel], strict=True)):
        ref = clip_np(used(p, k))
        assert cnt[i] == len(ref) <= k + 1
        scale = np.abs(used(p, k)).max()
        np.testing.assert_allclose(got[i, :cnt[i]], ref, atol=4 * EPS32 * scale, rtol=0)
        assert np.all(got[i, :cnt[i], 2] >= 0.0)
        # unused slots repeat the last vertex (all zero for an empty result)
        fill = got[i, cnt[i] - 1] if cnt[i] else np.zeros(3)
        assert np.all(got[i, cnt[i]:] == fill)
        n_straddle += 0 < np.sum(used(p, k)[:, 2] >= 0) < k
    assert n_straddle > 100  # the set exercises the crossing branch


def test_clip_special_cases():
    tri = np.array([[0, 0, 0.0], [1, 0, -1], [0, 1, -1]])  # touches the horizon in a vertex
    out, cnt = P.clip_to_horizon(_dr_poly(tri))
    assert _np(cnt)[0] == 3 and np.all(np.stack([_np3(o)[0] for o in out]) == 0.0)
    below = square(1.0, -0.5)
    out, cnt = P.clip_to_horizon(_dr_poly(below))
    assert _np(cnt)[0] == 0 and all(np.all(_np3(o) == 0.0) for o in out)
    above = square(1.0, 0.5)
    out, cnt = P.clip_to_horizon(_dr_poly(above))
    assert _np(cnt)[0] == 4
    np.testing.assert_array_equal(np.stack([_np3(o)[0] for o in out[:4]]), above)
    # a vertical quad straddling the horizon is cut into its upper half
    wall = np.array([[1, -1, -1.0], [1, 1, -1], [1, 1, 1], [1, -1, 1]])
    out, cnt = P.clip_to_horizon(_dr_poly(wall))
    got = np.stack([_np3(o)[0] for o in out])
    assert _np(cnt)[0] == 4
    np.testing.assert_array_equal(got[:4], [[1, 1, 0], [1, 1, 1], [1, -1, 1], [1, -1, 0]])
    # a triangle with one vertex above: a triangle; with two above: a quad (K + 1 = 4)
    tri = np.array([[0, 0, 1.0], [1, 0, -1], [0, 1, -1]])
    assert _np(P.clip_to_horizon(_dr_poly(tri))[1])[0] == 3
    assert _np(P.clip_to_horizon(_dr_poly(-tri))[1])[0] == 4
    # count < 3 gives an empty result
    assert _np(P.clip_to_horizon(_dr_poly(above), mi.UInt32([2]))[1])[0] == 0


# ------------------------------------------------------------------------------ Monte Carlo


@pytest.mark.slow
def test_random_polygons_vs_monte_carlo(random_set):
    """3000 random convex polygons (3 to 8 vertices, ~40 % straddling the horizon), 8192
    cosine-distributed directions each: exact binomial p-values of the hit counts under the
    computed integral, one-sided (hits on front-facing polygons only) and two-sided."""
    polys, ks, res = random_set
    n_dir = 8192
    hits = mc_hits(polys, ks, n_dir, np.random.default_rng(7))
    front = np.array([front_facing(used(p, k)) for p, k in zip(polys, ks, strict=True)])
    alpha = 1e-3 / (2 * len(polys))
    p_two = binom_pvalues(hits, n_dir, res["two"])
    p_one = binom_pvalues(np.where(front, hits, 0), n_dir, res["one"])
    # the aggregate: total hits against the sum of the integrals (z-score)
    mean = n_dir * res["two"].sum()
    z = (hits.sum() - mean) / math.sqrt(n_dir * np.sum(res["two"] * (1 - res["two"])))
    est = hits / n_dir
    nz = res["two"] > 0.02  # relative error vs MC where the MC is meaningful
    rel = np.abs(est[nz] / res["two"][nz] - 1)
    straddle = np.array([0 < np.sum(used(p, k)[:, 2] >= 0) < k
                         for p, k in zip(polys, ks, strict=True)])
    print(f"\nMC ({n_dir} dirs) vs cosine_integral on {len(polys)} polygons "
          f"({straddle.sum()} straddling, {np.sum(res['two'] == 0)} zero): min p-value "
          f"two-sided {p_two.min():.3g}, one-sided {p_one.min():.3g} (threshold {alpha:.2g}); "
          f"aggregate z = {z:.2f}; |MC/I - 1| (I > 0.02, n={nz.sum()}): median "
          f"{np.median(rel):.3g}, 99th pct {np.percentile(rel, 99):.3g} (MC noise)")
    assert straddle.sum() > 500 and np.sum(res["two"] > 0.05) > 250
    assert p_two.min() > alpha and p_one.min() > alpha
    assert abs(z) < 4.0
    # one-sided = two-sided on front-facing polygons, 0 on back-facing ones
    np.testing.assert_array_equal(res["one"], np.where(front, res["two"], 0.0))
    # the same statistic rejects the wrong recipe |F.z| of the unclipped polygon
    wrong = np.abs(res["ff"][:, 2])
    assert binom_pvalues(hits, n_dir, wrong).min() < 1e-12


# ------------------------------------------------------------------------------ accuracy


def test_atan2_accuracy_assumed_by_the_bound():
    """robust_bound assumes Dr.Jit's float32 atan2 is within 14 eps (relative) of the exact
    angle, for y >= 0 (|a x b|) and any x (a . b), over scales 1e-3..1e3 and tiny angles."""
    rng = np.random.default_rng(0)
    ang = np.concatenate([rng.uniform(0, math.pi, 600_000), 10 ** rng.uniform(-8, 0, 200_000),
                          math.pi - 10 ** rng.uniform(-6, 0, 200_000)])
    r = 10 ** rng.uniform(-3, 3, ang.size)
    y = (r * np.sin(ang)).astype(np.float32)
    x = (r * np.cos(ang)).astype(np.float32)
    got = _np(dr.atan2(mi.Float(y), mi.Float(x)))
    ref = np.arctan2(y.astype(np.float64), x.astype(np.float64))
    rel = np.abs(got / ref - 1) / EPS32
    print(f"\natan2 float32: max relative error {rel.max():.3g} eps")
    assert rel.max() < 14.0


@pytest.mark.slow
def test_accuracy_vs_quadrature(random_set, quadrature):
    """float32 results against float64 quadrature. Bounds from the error analysis: robust
    form, :func:`robust_bound` per polygon (<= 16 eps absolute); exact form, acos near 1 has an
    absolute error up to sqrt(2 eps) = 3.5e-4 per edge, so |error| <= K sqrt(2 eps) / (2 pi)
    ~ 5e-4 for K <= 9 clipped edges."""
    polys, ks, res = random_set
    sel, ref, frac = quadrature
    err_r = np.abs(res["two"][sel] - ref)
    err_e = np.abs(res["two_exact"][sel] - ref)
    bound = np.array([robust_bound(used(polys[i], ks[i]), r) for i, r in zip(sel, ref,
                                                                            strict=True)])
    big = ref > 1e-4
    rel_r = err_r[big] / ref[big]
    rel_e = err_e[big] / ref[big]
    diff = np.abs(res["two"] - res["two_exact"])
    print(f"\nvs quadrature ({len(sel)} polygons, {100 * frac:.1f} % of those tried; "
          f"{big.sum()} with I > 1e-4): robust rel. error median {np.median(rel_r):.3g}, "
          f"99th pct {np.percentile(rel_r, 99):.3g}, max {rel_r.max():.3g}, max abs "
          f"{err_r.max():.3g}; exact (acos) median {np.median(rel_e):.3g}, 99th pct "
          f"{np.percentile(rel_e, 99):.3g}, max {rel_e.max():.3g}, max abs {err_e.max():.3g}; "
          f"robust vs exact max |diff| {diff.max():.3g} over {len(diff)} polygons; robust error "
          f"/ bound: max {np.max(err_r[bound > 0] / bound[bound > 0]):.3g}")
    assert frac > 0.85 and big.sum() > 500
    assert np.all(err_r <= bound) and err_r.max() < ABS32  # bound = 0: exact 0 required
    assert err_e.max() < 5e-4 and diff.max() < 5e-4


def test_float64_lanes_match_quadrature(random_set, quadrature):
    """The same code on Float64 lanes (mi.Vector3d) agrees with the quadrature to ~1e-10:
    the formula, clipping and conventions are right independently of float32 rounding."""
    polys, ks, _ = random_set
    sel, ref, _ = quadrature
    sel, ref = sel[:300], ref[:300]
    verts = _dr_poly(polys[sel], mi.Vector3d)
    cnt = mi.UInt32(ks[sel].astype(np.uint32))
    for robust in (True, False):
        got = _np(P.cosine_integral(verts, cnt, robust=robust))
        assert np.max(np.abs(got - ref)) < 1e-10, robust


def test_form_factor_vector_vs_quadrature(random_set):
    """F of the unclipped polygon is +-(1/pi) int w dw (+ front-facing)."""
    polys, ks, res = random_set
    errs = []
    for i in range(0, 600, 3):
        p = used(polys[i], ks[i])
        r16, r28 = quad_form_factor(p, 16), quad_form_factor(p, 28)
        if np.max(np.abs(r16 - r28)) > 1e-10:
            continue
        errs.append(np.max(np.abs(res["ff"][i] - r28)))
        assert np.max(np.abs(res["ff_exact"][i] - r28)) < 5e-4
    errs = np.array(errs)
    print(f"\nform factor vector vs quadrature ({len(errs)} polygons): max abs error "
          f"{errs.max():.3g}")
    assert len(errs) > 150 and errs.max() < ABS32


# ------------------------------------------------------------------------------ closed forms


@pytest.mark.parametrize("half,c,cx,cy", [
    (1.0, 1.0, 0.0, 0.0), (0.3, 2.0, 0.5, -0.2), (5.0, 0.1, 1.0, 2.0),
    (1e3, 1.0, 0.0, 0.0), (1e4, 1.0, 10.0, 0.0), (1.0, 0.05, 0.99, 0.0)])
def test_parallel_rectangle_closed_form(half, c, cx, cy):
    q = square(half, c, cx, cy)
    want = parallel_rect(cx - half, cx + half, cy - half, cy + half, c)
    got = P.clamped_cosine_integral(q, two_sided=False)
    got_e = P.clamped_cosine_integral(q, two_sided=False, robust=False)
    assert abs(got - want) <= robust_bound(q, want) and abs(got_e - want) < 5e-4
    assert P.clamped_cosine_integral(q[::-1], two_sided=False) == 0.0
    if half >= 1e3:  # a huge light overhead covers nearly the whole hemisphere
        assert 1.0 - 2e-3 < got <= 1.0


@pytest.mark.parametrize("a,b,c", [(1.0, 1.0, 1.0), (2.0, 0.5, 0.3), (0.3, 2.0, 1.5),
                                   (50.0, 1.0, 0.01)])
def test_perpendicular_rectangle_straddling_horizon(a, b, c):
    """A wall x = c spanning z in [-a, a]: clipping leaves the closed-form rectangle."""
    wall = np.array([[c, 0, -a], [c, 0, a], [c, b, a], [c, b, -a]])  # front-facing
    assert front_facing(wall)
    want = perpendicular_rect(a, b, c)
    for poly, two_sided, w in ((wall, False, want), (wall, True, want),
                               (wall[::-1], True, want), (wall[::-1], False, 0.0)):
        got = P.clamped_cosine_integral(poly, two_sided=two_sided)
        assert abs(got - w) <= robust_bound(wall, want), (got, w)


@pytest.mark.parametrize("size,dist", [(1e-3, 1.0), (1.0, 1e3), (1e-2, 5.0)])
@pytest.mark.parametrize("tilt", [0.0, 0.7])
def test_small_and_distant_quads_float32(size, dist, tilt):
    """A small square of side s at distance d, direction at 50 degrees from the normal,
    tilted by ``tilt`` about its own edge: I = A cos(theta) cos(theta_l) / (pi d^2) with a
    relative correction O((s/d)^2) <= 1e-4 (checked against float64 quadrature). The robust
    float32 form keeps 1e-4 relative accuracy; the acos form does not."""
    th = math.radians(50.0)
    w = np.array([math.sin(th), 0.0, math.cos(th)])
    # a square facing the shading point, then tilted about its first in-plane axis
    e1 = np.array([0.0, 1.0, 0.0])
    e2 = np.cross(w, e1)
    e2 = math.cos(tilt) * e2 + math.sin(tilt) * w
    h = 0.5 * size
    c = dist * w
    q = np.array([c - h * e1 - h * e2, c + h * e1 - h * e2, c + h * e1 + h * e2,
                  c - h * e1 + h * e2])
    if not front_facing(q):
        q = q[::-1].copy()
    nl = newell(q) / np.linalg.norm(newell(q))
    small = size * size * w[2] * abs(nl @ w) / (math.pi * dist * dist)
    ref = quad_cosine(q, 12)
    assert abs(ref / small - 1) < 1e-4  # the small-source limit is this close
    got = float(P.clamped_cosine_integral(q, two_sided=False))
    got_e = float(P.clamped_cosine_integral(q, two_sided=False, robust=False))
    print(f"\nsquare {size:g} at {dist:g} (tilt {tilt}): I = {ref:.4g}; robust rel. error "
          f"{abs(got / ref - 1):.2g}, acos form {abs(got_e / ref - 1):.2g}")
    bound = robust_bound(q, ref)
    print(f"  robust error / bound {abs(got - ref) / bound:.2g}, bound / I {bound / ref:.2g}")
    assert abs(got - ref) <= bound
    assert abs(got_e - ref) < 5e-4  # the exact form only meets its absolute bound


# ------------------------------------------------------------------------------ winding


def test_winding_and_sides(random_set):
    polys, ks, res = random_set
    sel = np.arange(400)
    rev = polys[sel].copy()
    for j, i in enumerate(sel):
        rev[j, :ks[i]] = polys[i, :ks[i]][::-1]
    verts = _dr_poly(rev)
    cnt = mi.UInt32(ks[sel].astype(np.uint32))
    two = _np(P.cosine_integral(verts, cnt, two_sided=True))
    one = _np(P.cosine_integral(verts, cnt, two_sided=False))
    ff = _np3(P.form_factor_vector(verts, cnt))
    np.testing.assert_allclose(two, res["two"][sel], rtol=0, atol=2 * ABS32)
    np.testing.assert_allclose(ff, -res["ff"][sel], rtol=0, atol=2 * ABS32)
    # reversed: exactly the other side lights up
    np.testing.assert_array_equal(one > 0, (res["one"][sel] == 0) & (res["two"][sel] > 0))
    np.testing.assert_allclose(one + res["one"][sel], res["two"][sel], rtol=0, atol=2 * ABS32)
    # F points towards a front-facing polygon above the horizon
    q = square(1.0, 2.0)
    f = P.form_factor_vectors(q)
    assert f[2] > 0 and abs(f[0]) < 1e-7 and abs(f[1]) < 1e-7
    np.testing.assert_allclose(P.form_factor_vectors(q[::-1]), -f, rtol=1e-6)
    # per-lane two-sided flags
    v = _dr_poly(np.stack([q[::-1], q[::-1]]))
    got = _np(P.cosine_integral(v, two_sided=mi.Bool([True, False])))
    assert got[0] == pytest.approx(parallel_rect(-1, 1, -1, 1, 2.0), rel=1e-6) and got[1] == 0


# ------------------------------------------------------------------------------ degenerate


DEGENERATE_ZERO = {
    "collinear": np.array([[0, 0, 1.0], [1, 1, 2], [2, 2, 3]]),
    "all vertices equal": np.array([[0.3, 0.2, 1.0]] * 4),
    "two distinct vertices": np.array([[0, 0, 1.0], [1, 0, 1], [1, 0, 1], [0, 0, 1]]),
    "below the horizon": square(1.0, -0.5),
    "far below the horizon": square(10.0, -1e3),
    "in the tangent plane, around the point": square(1.0, 0.0),
    "in the tangent plane, beside the point": square(1.0, 0.0, cx=3.0),
    "plane through the point, point inside": np.array([[1, -1, 0.0], [1, 1, 0], [-1, 1, 2],
                                                        [-1, -1, 2]]) - [0, 0, 1],
    "plane through the point, point outside": np.array([[0, 1, 0.0], [0, 2, 0], [0, 2, 1],
                                                         [0, 1, 1]]),
    "vertex at the origin": np.array([[0, 0, 0.0], [1, 0, 1], [0, 1, 1]]),
    "vertex at the origin, below": np.array([[0, 0, 0.0], [1, 0, -1], [0, 1, -1]]),
    "touching the horizon in a vertex": np.array([[0, 0, 0.0], [1, 0, -1], [0, 1, -1]]) + [3, 0,
                                                                                           0],
    "edge on the horizon, rest below": np.array([[1, -1, 0.0], [1, 1, 0], [2, 1, -1],
                                                 [2, -1, -1]]),
}


def test_degenerate_polygons_give_zero():
    """Every case of DEGENERATE_ZERO, both windings, both edge terms, one- and two-sided:
    exactly 0, and a finite form factor vector (exactly 0 where the plane passes through the
    point or the area is zero). Evaluated as one batch (counts pad the triangles)."""
    names = list(DEGENERATE_ZERO)
    cases = [DEGENERATE_ZERO[k].astype(np.float64) for k in names]
    ks = np.array([len(c) for c in cases])
    fwd = np.stack([np.vstack([c, np.repeat(c[-1:], 4 - len(c), 0)]) for c in cases])
    rev = np.stack([np.vstack([c[::-1], np.repeat(c[:1], 4 - len(c), 0)]) for c in cases])
    for robust in (True, False):
        for two_sided in (True, False):
            for poly in (fwd, rev):
                got = P.clamped_cosine_integral(poly, two_sided=two_sided, robust=robust,
                                                count=ks)
                bad = [n for n, g in zip(names, got, strict=True) if g != 0.0]
                assert not bad, (bad, robust, two_sided)
        f = P.form_factor_vectors(fwd, robust=robust, count=ks)
        assert np.all(np.isfinite(f))
        for n, fi in zip(names, f, strict=True):
            if "below" not in n and "horizon" not in n:
                assert np.all(fi == 0.0), (n, fi)


def test_repeated_vertices_and_counts():
    q = square(1.0, 1.5, 0.3, -0.2)
    want = parallel_rect(-0.7, 1.3, -1.2, 0.8, 1.5)
    reps = [np.insert(q, 2, q[1], axis=0), np.vstack([q, q[-1:], q[-1:]]),
            np.vstack([q[:1], q])]
    for r in reps:
        for robust in (True, False):
            got = P.clamped_cosine_integral(r, two_sided=False, robust=robust)
            assert abs(got - want) <= (robust_bound(q, want) if robust else 5e-4), (r, robust)
    # per-lane counts (junk beyond them is ignored) == repeating the last vertex
    junk = np.vstack([q, [[1e3, -7, 3], [5, 5, -5], [np.pi, 1, 1]]])
    a = P.clamped_cosine_integral(np.stack([junk, junk]), count=[4, 4])
    b = P.clamped_cosine_integral(np.vstack([q, q[-1:], q[-1:], q[-1:]]))
    np.testing.assert_allclose(a, [b, b], rtol=1e-6)
    # Dr.Jit API: counts above K are clamped, below 3 give 0
    v = _dr_poly(np.stack([q] * 3))
    got = _np(P.cosine_integral(v, mi.UInt32([9, 2, 0])))
    assert abs(got[0] - want) <= robust_bound(q, want) and got[1] == 0 and got[2] == 0
    assert np.all(_np3(P.form_factor_vector(v, mi.UInt32([9, 2, 0])))[1:] == 0.0)


def test_near_plane_and_vertex_near_origin_are_not_zeroed():
    """The in-plane guard only catches rounding-level distances: a point 1e-4 below a large
    light, or a vertex 1e-4 from the origin, still gets the right value."""
    q = square(10.0, 1e-4)
    want = parallel_rect(-10, 10, -10, 10, 1e-4)
    assert abs(P.clamped_cosine_integral(q) - want) <= robust_bound(q, want)
    c = 1e-4  # a wall at distance 1e-4 with a corner 1e-4 from the point
    wall = np.array([[c, 0, 0], [c, 0, 1.0], [c, 1, 1], [c, 1, 0]])
    want = perpendicular_rect(1, 1, c)
    assert abs(P.clamped_cosine_integral(wall) - want) <= robust_bound(wall, want)


def test_in_plane_configurations_give_zero():
    """3000 random polygons moved so that the shading point lies in their plane (at a vertex,
    inside, or on an edge), built in float64 and rounded to float32: all exactly 0, with
    both edge terms, one- and two-sided; the form factor vector is 0 too."""
    rng = np.random.default_rng(5)
    polys, ks = random_polygons(rng, 3000, k_max=6)
    out = []
    for i, (p, k) in enumerate(zip(polys, ks, strict=True)):
        q = p[:k]
        j = rng.integers(k)
        if i % 3 == 0:
            o = q[j]
        elif i % 3 == 1:
            o = rng.dirichlet(np.ones(k)) @ q
        else:
            o = q[j] + rng.random() * (q[(j + 1) % k] - q[j])
        out.append(p - o)
    v = _dr_poly(np.array(out).astype(np.float32))
    cnt = mi.UInt32(ks.astype(np.uint32))
    for robust in (True, False):
        for two_sided in (True, False):
            got = _np(P.cosine_integral(v, cnt, two_sided=two_sided, robust=robust))
            assert np.all(got == 0.0), (robust, two_sided, np.sum(got != 0))
        assert np.all(_np3(P.form_factor_vector(v, cnt, robust=robust)) == 0.0)


def test_extreme_scales_are_finite_and_scale_invariant():
    rng = np.random.default_rng(3)
    polys, ks = random_polygons(rng, 64, k_max=5)
    base = P.clamped_cosine_integral(polys, count=ks)
    for s in (1e-30, 1e-12, 1e12, 1e30, 1e300):
        got = P.clamped_cosine_integral(polys * s, count=ks)
        assert np.all(np.isfinite(got))
        np.testing.assert_allclose(got, base, rtol=0, atol=2 * ABS32)
    # Dr.Jit API without the NumPy rescaling: float32 extremes
    for s in (1e-18, 1e18):
        v = _dr_poly(polys[:, :3] * s)
        got = _np(P.cosine_integral(v))
        ref = P.clamped_cosine_integral(polys[:, :3])
        np.testing.assert_allclose(got, ref, rtol=0, atol=2 * ABS32)


# ------------------------------------------------------------------------------ errors


def test_errors_name_the_problem():
    q = square(1.0, 1.0)
    with pytest.raises(GlossrtError, match="at least 3 vertices, got K = 2"):
        P.clamped_cosine_integral(q[:2])
    with pytest.raises(GlossrtError, match="at most 8 vertices, got K = 9"):
        P.clamped_cosine_integral(np.zeros((9, 3)) + [0, 0, 1])
    with pytest.raises(GlossrtError, match=r"shape \(\.\.\., K, 3\)"):
        P.clamped_cosine_integral(q[:, :2])
    with pytest.raises(GlossrtError, match="NaN or Inf.*batch index \\(1,\\)"):
        P.clamped_cosine_integral(np.stack([q, q * np.nan]))
    with pytest.raises(GlossrtError, match="NaN or Inf"):
        P.form_factor_vectors(np.where(q == 1.0, np.inf, q))
    with pytest.raises(GlossrtError, match="count of 2"):
        P.clamped_cosine_integral(q, count=2)
    with pytest.raises(GlossrtError, match="count 5 exceeds"):
        P.clamped_cosine_integral(q, count=5)
    with pytest.raises(GlossrtError, match="3 to 8 vertices, got 9"):
        P.cosine_integral(_dr_poly(np.zeros((9, 3))))
    with pytest.raises(GlossrtError, match="3 to 8 vertices, got 2"):
        P.clip_to_horizon(_dr_poly(q[:2]))
    with pytest.raises(GlossrtError, match="list of 3 to 8"):
        P.form_factor_vector(_vec(q[0]))
    with pytest.raises(GlossrtError, match="finite and non-zero"):
        P.to_local(q, [0, 0, 0], [0, 0, 0])
    assert P.clamped_cosine_integral(np.zeros((0, 2, 4, 3))).shape == (0, 2)


# ------------------------------------------------------------------------------ frames


def test_shading_frame_and_to_local():
    rng = np.random.default_rng(11)
    n = rng.normal(size=(200, 3))
    n[:3] = [[0, 0, 1.0], [0, 0, -1.0], [1.0, 0, 0]]
    n[3:6] *= [1, 1, 1e-9]  # nearly in the xy-plane
    fr = P.shading_frame(n)
    nn = n / np.linalg.norm(n, axis=1, keepdims=True)
    np.testing.assert_allclose(fr @ np.swapaxes(fr, 1, 2), np.broadcast_to(np.eye(3), fr.shape),
                               atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(fr), 1.0, atol=1e-12)  # right-handed
    np.testing.assert_allclose(fr[:, 2], nn, atol=1e-15)
    # the same tangent frame as Mitsuba's mi.Frame3f
    frame = mi.Frame3f(_vec(nn))
    np.testing.assert_allclose(_np3(frame.s), fr[:, 0], atol=2e-6)
    np.testing.assert_allclose(_np3(frame.t), fr[:, 1], atol=2e-6)
    # to_local: world polygon seen from shading points; the integral is a world quantity
    pos = rng.normal(size=(200, 3))
    quad = square(0.7, 0.0) + [0.2, -0.1, 2.5]  # one world polygon, broadcast
    loc = P.to_local(quad, pos, n)
    assert loc.shape == (200, 4, 3)
    np.testing.assert_allclose(loc[:, :, 2], np.einsum("nkc,nc->nk", quad[None] - pos[:, None],
                                                       nn), atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(loc, axis=-1),
                               np.linalg.norm(quad[None] - pos[:, None], axis=-1), rtol=1e-12)
    got = P.clamped_cosine_integral(loc)
    checked = 0
    for i in range(0, 200, 5):
        r16, r28 = quad_cosine(loc[i], 16), quad_cosine(loc[i], 28)
        if abs(r16 - r28) < 1e-10:  # quadrature converged (the point is not too close)
            assert abs(got[i] - r28) <= robust_bound(loc[i], r28), i
            checked += 1
    assert checked > 30
    # rotating the world (positions, normals, light together) changes nothing
    rot = random_rotation(rng, 1)[0]
    loc2 = P.to_local(quad @ rot.T, pos @ rot.T, n @ rot.T)
    np.testing.assert_allclose(P.clamped_cosine_integral(loc2), got, rtol=0, atol=2 * ABS32)


# ------------------------------------------------------------------- LTC polygon_integral


def _ltc_quadrature(quad, n_view, alpha, m=600):
    """norm * integral over the quad (z = const > 0 above the shading point at the origin,
    normal +z, view (sin t, 0, cos t)) of the LTC density ``D(w) = D_o(M^-1 w / |M^-1 w|)
    |det M^-1| / |M^-1 w|^3`` (Heitz et al. 2016, eq. 1), D_o = max(z, 0) / pi; midpoint rule
    on an m x m grid of the quad's area (dw = cos_l dA / r^2), float64. The LTC coefficients
    from the table's NumPy lookup."""
    from glossrt.lights.ltc.table import LTCTable, minv_matrix

    coeffs, norm, _ = LTCTable.load().lookup_np(alpha, n_view[2])
    minv = minv_matrix(coeffs)
    a, b, d = quad[0], quad[1], quad[3]
    s = (np.arange(m) + 0.5) / m
    su, sv = np.meshgrid(s, s)
    y = a + su[..., None] * (b - a) + sv[..., None] * (d - a)
    area = np.linalg.norm(np.cross(b - a, d - a))
    r2 = np.sum(y * y, -1)
    w = y / np.sqrt(r2)[..., None]
    cos_l = np.abs(w[..., 2])  # the quad's normal is +-z
    wo = w @ minv.T
    lo = np.linalg.norm(wo, axis=-1)
    dens = np.maximum(wo[..., 2] / lo, 0.0) / np.pi * abs(np.linalg.det(minv)) / lo**3
    return float(norm) * float(np.sum(dens * cos_l / r2) * area / (m * m)), coeffs, float(norm)


def test_ltc_polygon_integral_is_scale_invariant_near_the_plane():
    """Issue 23: ``polygon_integral`` returned 0 for a quad of half-size 1 at distance 2e-6
    from the shading point's plane (the same shape as a quad of half-size 5e5 at distance 1):
    float32 vertices put that plane within rounding of the shading point. It now works in
    float64: the integral is the same for the polygon and the distance scaled together, and
    near the plane it tends to the LTC's mass over the whole upper hemisphere. References:
    area quadrature of the LTC density for the quad at distance 2, and for the near-plane
    quads the closed form of that limit: with ``m`` the third row of ``M`` (``w.z > 0`` iff
    ``m . w_o > 0``), ``(1/pi) int_{z>0, m.w>0} cos = (1 + cos beta) / 2`` with ``cos beta = m_z /
    |m|`` (projected on the unit disk, the region is a half disk and a half ellipse of
    semi-axes 1 and cos beta)."""
    from glossrt.lights.ltc import polygon_integral
    from glossrt.lights.ltc.table import minv_matrix

    quad = np.array([[-1.0, -1.0, 2.0], [1.0, -1.0, 2.0], [1.0, 1.0, 2.0], [-1.0, 1.0, 2.0]])
    nrm = np.array([0.0, 0.0, 1.0])
    for t, alpha in ((0.3, 0.3), (1.0, 0.15), (0.0, 0.6)):
        wo = np.array([math.sin(t), 0.0, math.cos(t)])
        want, coeffs, norm = _ltc_quadrature(quad, wo, alpha)
        got = polygon_integral(quad, nrm, wo, alpha)
        print("quad at 2:", t, alpha, got, want)
        assert got == pytest.approx(want, rel=2e-4)
        for s in (5e5, 2e-6, 1e-30, 1e30):  # polygon and distance scaled together
            assert polygon_integral(quad * s, nrm, wo, alpha) == pytest.approx(got, rel=1e-12)
        m_row = np.linalg.inv(minv_matrix(coeffs))[2]
        limit = norm * (1.0 + m_row[2] / np.linalg.norm(m_row)) / 2.0
        near = quad.copy()
        near[:, 2] = 2e-6
        wide = quad * np.array([5e5, 5e5, 1.0])
        a, b = polygon_integral(near, nrm, wo, alpha), polygon_integral(wide, nrm, wo, alpha)
        print("near the plane:", a, b, "limit", limit)
        assert a == pytest.approx(limit, rel=1e-5)
        assert b == pytest.approx(a, rel=1e-6)  # the same shape (the edge terms: ~1e-7)


def test_ltc_polygon_integral_refuses_bad_input():
    """Negative alpha used to read the table's alpha-0 row (a mirror), and a non-planar
    polygon (which the scene loader refuses as a light) was integrated as if it were one:
    both are clear one-line errors now."""
    from glossrt.lights.ltc import polygon_integral

    quad = np.array([[-1.0, -1.0, 2.0], [1.0, -1.0, 2.0], [1.0, 1.0, 2.0], [-1.0, 1.0, 2.0]])
    nrm, wo = [0.0, 0.0, 1.0], [0.3, 0.0, 0.95]
    with pytest.raises(GlossrtError, match=r"alpha must be >= 0, got -0.3") as e:
        polygon_integral(quad, nrm, wo, -0.3)
    assert "\n" not in str(e.value)
    with pytest.raises(GlossrtError, match="alpha"):
        polygon_integral(np.stack([quad, quad]), nrm, wo, np.array([0.2, -1e-9]))
    bent = quad.copy()
    bent[2, 2] = 2.5
    with pytest.raises(GlossrtError, match=r"polygon 1 is not planar") as e:
        polygon_integral(np.stack([quad, bent]), nrm, wo, 0.3)
    assert "\n" not in str(e.value)
    # planar within the scene loader's tolerance (1e-5 of the size): accepted
    ok = quad.copy()
    ok[2, 2] += 1e-7
    assert polygon_integral(ok, nrm, wo, 0.3) == pytest.approx(
        polygon_integral(quad, nrm, wo, 0.3), rel=1e-5)
    assert polygon_integral(quad, nrm, wo, 0.0) > 0  # alpha 0 (a mirror's limit) is allowed
