"""Kimura & Tokoi's ellipsoidal microfacet distribution and its samplers
(glossrt.brdf.ellipsoidal), checked against independent computations: the paper's formulas
retyped here, scipy quadrature, chi-square tests of samples, Mitsuba's GGX sampler, NumPy
re-implementations (PCG hash, Cook-Torrance G) and the paper's rotation matrix."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.integrate import quad
from scipy.stats import chisquare

from glossrt.brdf import ellipsoidal as ell
from glossrt.errors import GlossrtError

mi = ell.mi
dr = ell.dr

RATIOS = [1.0, 1.0 + 1e-9, 1.5, 4.0, 30.0, 1e4]


# ------------------------------------------------------------------------------ helpers


def ds_paper(d, r):
    """D_s as typeset in sec. 4.1 (R = 1: its limit cos(d) / 2)."""
    d = np.asarray(d, dtype=np.float64)
    if r == 1.0:
        return np.where(np.abs(d) <= np.pi / 2, np.cos(d) / 2.0, 0.0)
    k = math.sqrt(r * r - 1.0)
    c, s = np.cos(d), np.sin(d)
    return k / (2.0 * r * math.atan(k)) * c / (c * c / r + r * s * s)


def inv_paper(u, r):
    """delta(U) as typeset in sec. 5.1 (R = 1: asin(2U - 1))."""
    u = np.asarray(u, dtype=np.float64)
    if r == 1.0:
        return np.arcsin(2.0 * u - 1.0)
    k = math.sqrt(r * r - 1.0)
    return np.arcsin(np.clip(np.tan((2.0 * u - 1.0) * math.atan(k)) / k, -1.0, 1.0))


def folded_cdf(d, r):
    """P(|delta| < d) = atan(k sin d) / atan(k) (integral of 2 D_s; checked by quadrature in
    test_folded_cdf_helper)."""
    if r == 1.0:
        return np.sin(d)
    k = math.sqrt(r * r - 1.0)
    return np.arctan(k * np.sin(d)) / math.atan(k)


def breakpoints(r, lo=-np.pi / 2, hi=np.pi / 2):
    """Points that resolve the peak of D_s (width ~1/k) for scipy.quad."""
    k = math.sqrt(max(r * r - 1.0, 0.0))
    pts = {0.0}
    for c in (0.1, 1.0, 10.0, 100.0):
        if k > 0 and c / k < np.pi / 2:
            pts |= {c / k, -c / k}
    return sorted(p for p in pts if lo < p < hi) or None


def bin_probs(edges, r):
    return np.array([
        quad(lambda x: float(ds_paper(x, r)), a, b, points=breakpoints(r, a, b), limit=200)[0]
        for a, b in zip(edges[:-1], edges[1:], strict=True)
    ])


def chi2_vs_ds(deltas, r, bins=30):
    """p-value of binned signed angles against D_s(r): bins at the paper's quantiles, expected
    masses by quadrature of the paper's D_s."""
    edges = inv_paper(np.linspace(0.0, 1.0, bins + 1), r)
    edges[0], edges[-1] = -np.pi / 2, np.pi / 2
    p = bin_probs(edges, r)
    obs = np.histogram(deltas, bins=edges)[0]
    return chisquare(obs, p / p.sum() * len(deltas)).pvalue


def chi2_folded(abs_deltas, r, bins=20):
    obs = np.histogram(folded_cdf(abs_deltas, r), bins=np.linspace(0.0, 1.0, bins + 1))[0]
    return chisquare(obs).pvalue


def vec(a) -> mi.Vector3f:
    a = np.atleast_2d(np.asarray(a, dtype=np.float64))
    return mi.Vector3f(mi.Float(a[:, 0]), mi.Float(a[:, 1]), mi.Float(a[:, 2]))


def to_np(v) -> np.ndarray:
    return np.stack([np.asarray(v.x), np.asarray(v.y), np.asarray(v.z)], -1).astype(np.float64)


def random_dirs(rng, n, upper=True):
    v = rng.normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    if upper:
        v[:, 2] = np.abs(v[:, 2])
    return v


def angle_from_normal(h):
    """Polar angle of local normals (z = reference axis)."""
    return np.arctan2(np.hypot(h[..., 0], h[..., 1]), h[..., 2])


# ------------------------------------------------------------------------------ D_s


def test_folded_cdf_helper():
    for r in (1.0, 3.0, 1e4):
        for d in (1e-3, 0.1, 0.7, 1.5):
            ref = 2.0 * quad(lambda x, r=r: float(ds_paper(x, r)), 0.0, d,
                             points=breakpoints(r, 0.0, d), limit=200)[0]
            assert folded_cdf(d, r) == pytest.approx(ref, abs=1e-9)


def test_pdf_matches_paper_formula():
    d = np.linspace(-np.pi / 2, np.pi / 2, 401)
    for r in (1.0, 1.2, 4.0, 30.0, 1e4):
        np.testing.assert_allclose(ell.ellipsoidal_pdf(d, r), ds_paper(d, r),
                                   rtol=1e-12, atol=1e-13)
        got = ell.ellipsoidal_pdf(mi.Float(d), r).numpy()
        np.testing.assert_allclose(got, ds_paper(d, r), rtol=2e-5, atol=1e-6 * ds_paper(0, r))
    assert np.all(ell.ellipsoidal_pdf(np.array([-2.0, 1.6, 3.0]), 2.0) == 0.0)


def test_pdf_near_one_has_no_nan_and_is_continuous():
    d = np.linspace(-np.pi / 2, np.pi / 2, 101)
    ref = np.cos(d) / 2.0
    for r in (1.0, 1.0 + 1e-15, 1.0 + 1e-9, 1.0 + 1e-7, 1.0 + 1e-5):
        for got in (ell.ellipsoidal_pdf(d, r), ell.ellipsoidal_pdf(mi.Float(d), r).numpy(),
                    ell.ellipsoidal_cdf(d, r), ell.ellipsoidal_sample((d + 2) / 4, r),
                    ell.ellipsoidal_cdf(mi.Float(d), r).numpy(),
                    ell.ellipsoidal_sample(mi.Float((d + 2) / 4), r).numpy()):
            assert np.all(np.isfinite(got))
        # D_s(R) = cos/2 (1 + O(R - 1))
        np.testing.assert_allclose(ell.ellipsoidal_pdf(d, r), ref, atol=3 * (r - 1) + 1e-15)
    # the series branch (k < 1e-3) agrees with the closed forms evaluated in float64 where
    # they are still accurate (k = 5e-4 .. 1e-3: k / atan(k) to ~1e-16)
    for k in (5e-4, 0.999e-3):
        r = math.sqrt(1 + k * k)
        x = np.array([-1.2, -0.3, 0.01, 0.3, 1.2])
        np.testing.assert_allclose(ell.ellipsoidal_pdf(x, r), ds_paper(x, r), rtol=1e-12)
        atan_k = math.atan(k)
        np.testing.assert_allclose(ell.ellipsoidal_cdf(x, r),
                                   0.5 + np.arctan(k * np.sin(x)) / (2 * atan_k), atol=1e-13)
        u = np.array([0.0, 0.1, 0.5, 0.77, 1.0])
        np.testing.assert_allclose(ell.ellipsoidal_sample(u, r),
                                   np.arcsin(np.tan((2 * u - 1) * atan_k) / k), atol=1e-12)


@pytest.mark.parametrize("r", [1.0, 1.0 + 1e-12, 1.0001, 2.0, 10.0, 1e4])
def test_pdf_integrates_to_one(r):
    total = quad(lambda x: float(ell.ellipsoidal_pdf(x, r)), -np.pi / 2, np.pi / 2,
                 points=breakpoints(r), limit=400, epsabs=1e-12)[0]
    assert total == pytest.approx(1.0, abs=1e-9)
    # the Dr.Jit version (float32) on a fine composite grid in sin(delta)
    s = np.linspace(-1.0, 1.0, 2_000_001)
    d = np.arcsin(s)
    f = ell.ellipsoidal_pdf(mi.Float(d), r).numpy() / np.maximum(np.cos(d), 1e-300)
    if r < 1e3:  # (for 1e4 the float32 peak is narrower than the grid)
        assert np.trapezoid(f, s) == pytest.approx(1.0, abs=1e-4)


def test_cdf_is_the_integral_of_the_pdf():
    for r in (1.0, 1.7, 25.0, 1e4):
        for d in (-1.5, -0.3, -1e-3, 0.0, 2e-4, 0.05, 0.9, np.pi / 2):
            ref = quad(lambda x, r=r: float(ds_paper(x, r)), -np.pi / 2, d,
                       points=breakpoints(r, -np.pi / 2, d), limit=400)[0]
            assert float(ell.ellipsoidal_cdf(d, r)) == pytest.approx(ref, abs=1e-9)
            got = ell.ellipsoidal_cdf(mi.Float([d]), r).numpy()[0]
            assert got == pytest.approx(ref, abs=3e-6)
    assert float(ell.ellipsoidal_cdf(-2.0, 3.0)) == 0.0
    assert float(ell.ellipsoidal_cdf(2.0, 3.0)) == 1.0


def test_cdf_of_sample_is_identity():
    u = np.linspace(0.0, 1.0, 1001)
    for r in RATIOS:
        np.testing.assert_allclose(ell.ellipsoidal_cdf(ell.ellipsoidal_sample(u, r), r), u,
                                   atol=1e-12)
        np.testing.assert_allclose(ell.ellipsoidal_sample(u, r), inv_paper(u, r), atol=1e-9)
        x = ell.ellipsoidal_cdf(ell.ellipsoidal_sample(mi.Float(u), r), r).numpy()
        np.testing.assert_allclose(x, u, atol=1e-6)


@pytest.mark.parametrize("r", RATIOS)
def test_sampler_follows_ds_chi_square(r):
    rng = np.random.default_rng(12)
    u = rng.random(20000)
    d_dr = ell.ellipsoidal_sample(mi.Float(u), r).numpy()
    assert chi2_vs_ds(d_dr, r) > 0.01
    d_np = ell.ellipsoidal_sample(rng.random(20000), r)
    assert chi2_vs_ds(d_np, r) > 0.01


def test_wrong_sampler_fails_chi_square():
    rng = np.random.default_rng(13)
    u = rng.random(20000)
    # a mismatched ratio
    assert chi2_vs_ds(ell.ellipsoidal_sample(u, 2.0), 2.5) < 1e-6
    assert chi2_vs_ds(ell.ellipsoidal_sample(u, 30.0), 20.0) < 1e-6
    # sin(delta) from the Cauchy inverse without the asin (uniform-in-delta mistake)
    k = math.sqrt(4.0**2 - 1.0)
    wrong = np.tan((2 * u - 1) * math.atan(k)) / k * (np.pi / 2)
    assert chi2_vs_ds(wrong, 4.0) < 1e-6


# ------------------------------------------------------------------------------ GGX match


def test_ratio_from_alpha_round_trip_and_limits():
    alpha = np.geomspace(1e-4, ell.ALPHA_MAX, 50)
    r = ell.ratio_from_alpha(alpha)
    assert np.all(r >= 1.0) and np.all(np.diff(r) < 0)
    np.testing.assert_allclose(ell.alpha_from_ratio(r), alpha, rtol=1e-10)
    assert float(ell.ratio_from_alpha(ell.ALPHA_MAX)) == pytest.approx(1.0, abs=1e-12)
    assert float(ell.alpha_from_ratio(1.0)) == pytest.approx(1 / math.sqrt(3))
    np.testing.assert_array_equal(ell.ratio_from_alpha([0.7, 1.0, 5.0]), 1.0)
    assert ell.ratio_from_alpha(np.ones((2, 3)) * 0.1).shape == (2, 3)
    # the medians agree analytically: folded CDF of D_s at GGX's median atan(alpha) is 1/2
    for a in (1e-3, 0.05, 0.3, 0.5):
        assert folded_cdf(math.atan(a), float(ell.ratio_from_alpha(a))) == pytest.approx(0.5)


@pytest.mark.parametrize("alpha", [0.02, 0.15, 0.45])
def test_ratio_from_alpha_medians_agree_by_sampling(alpha):
    n = 40000
    rng = np.random.default_rng(int(alpha * 1000))
    # GGX normals sampled by Mitsuba from D(h) cos(theta_h) (not the visible normals)
    md = mi.MicrofacetDistribution(mi.MicrofacetType.GGX, alpha, False)
    u = rng.random((2, n))
    h, _ = md.sample(mi.Vector3f(0, 0, 1), mi.Point2f(mi.Float(u[0]), mi.Float(u[1])))
    theta_ggx = np.arccos(np.clip(np.asarray(h.z, np.float64), -1, 1))
    r = float(ell.ratio_from_alpha(alpha))
    d = np.abs(ell.ellipsoidal_sample(mi.Float(rng.random(n)), r).numpy())
    # the GGX sample median is atan(alpha) and splits the ellipsoidal samples in halves
    se = 0.5 / math.sqrt(n)
    assert np.mean(theta_ggx < math.atan(alpha)) == pytest.approx(0.5, abs=4 * se)
    assert np.mean(d < np.median(theta_ggx)) == pytest.approx(0.5, abs=6 * se)


# ------------------------------------------------------------------------------ normals, G


def test_microfacet_normal_unit_angle_and_right_handed():
    rng = np.random.default_rng(3)
    m = 2000
    n = random_dirs(rng, m, upper=False)
    delta = rng.uniform(-np.pi / 2, np.pi / 2, m)
    theta = rng.uniform(0, np.pi, m)
    h = to_np(ell.microfacet_normal(vec(n), mi.Float(delta), mi.Float(theta)))
    np.testing.assert_allclose(np.linalg.norm(h, axis=1), 1.0, atol=2e-6)
    cos = np.clip(np.sum(h * n, 1), -1, 1)
    np.testing.assert_allclose(np.arccos(cos), np.abs(delta), atol=2e-3)
    np.testing.assert_allclose(cos, np.cos(delta), atol=3e-6)
    # NumPy path (float64 in, same frame)
    np.testing.assert_allclose(ell.microfacet_normal(n, delta, theta), h, atol=3e-6)
    # the images of the local axes x (delta = pi/2, theta = 0), y (theta = pi/2), z (delta = 0)
    ex = to_np(ell.microfacet_normal(vec(n), mi.Float(np.full(m, np.pi / 2)), mi.Float(0.0)))
    ey = to_np(ell.microfacet_normal(vec(n), mi.Float(np.full(m, np.pi / 2)),
                                     mi.Float(np.pi / 2)))
    ez = to_np(ell.microfacet_normal(vec(n), mi.Float(np.zeros(m)), mi.Float(0.0)))
    np.testing.assert_allclose(ez, n, atol=1e-6)
    np.testing.assert_allclose(np.cross(ex, ey), n, atol=1e-5)  # right-handed: t x b = n
    np.testing.assert_allclose(np.sum(ex * ey, 1), 0.0, atol=1e-6)
    # n = +z: the local frame is the world frame
    hz = ell.microfacet_normal(np.array([0.0, 0.0, 1.0]), delta, theta)
    np.testing.assert_allclose(hz, ell.local_normal(delta, theta), atol=1e-7)
    np.testing.assert_allclose(
        ell.local_normal(delta, theta),
        np.stack([np.sin(delta) * np.cos(theta), np.sin(delta) * np.sin(theta), np.cos(delta)],
                 -1))
    # the sign of delta covers the other half plane: (delta, theta) ~ (-delta, theta + pi)
    h2 = ell.microfacet_normal(n, -delta, theta + np.pi)
    np.testing.assert_allclose(h2, h, atol=3e-6)


def test_paper_rotation_matrix_gives_the_same_angles():
    """Sec. 5.2's DirectX matrix (row vectors, reference axis x, texel (H_x, H_y, H_z) =
    (cos d, sin d cos t, sin d sin t)), with its tangent rows normalised, puts the normal at
    the same angle from n as glossrt's frame; its tangent rows have length sqrt(1 - n_x^2)."""
    rng = np.random.default_rng(4)
    for _ in range(20):
        n = random_dirs(rng, 1, upper=False)[0]
        nx, ny, nz = n
        rows = np.array([[nx, ny, nz], [0.0, nz, -ny], [ny**2 + nz**2, -nx * ny, -nx * nz]])
        np.testing.assert_allclose(np.linalg.norm(rows[1:], axis=1), math.sqrt(1 - nx * nx))
        rows[1:] /= np.linalg.norm(rows[1:], axis=1, keepdims=True)
        d, t = rng.uniform(-1.5, 1.5), rng.uniform(0, np.pi)
        texel = np.array([math.cos(d), math.sin(d) * math.cos(t), math.sin(d) * math.sin(t)])
        h_paper = texel @ rows
        h_ours = ell.microfacet_normal(n, d, t)
        assert np.dot(h_paper, n) == pytest.approx(np.dot(h_ours, n), abs=1e-9)
        assert np.linalg.norm(h_paper) == pytest.approx(1.0)


def test_reflect():
    rng = np.random.default_rng(5)
    v = random_dirs(rng, 500)
    h = random_dirs(rng, 500)
    l = ell.reflect(v, h)
    np.testing.assert_allclose(l, to_np(mi.reflect(vec(v), vec(h))), atol=2e-6)
    np.testing.assert_allclose(to_np(ell.reflect(vec(v), vec(h))), l, atol=2e-6)
    np.testing.assert_allclose(np.linalg.norm(l, axis=1), 1.0, atol=1e-12)
    hv = (v + l) / np.linalg.norm(v + l, axis=1, keepdims=True)
    ok = np.sum(v * h, 1) > 1e-3
    np.testing.assert_allclose(hv[ok], h[ok], atol=1e-9)


def g_cook_torrance(n, h, v, l):
    """Cook & Torrance 1982, eq. for G (Blinn 1977): min(1, 2 NH NV / VH, 2 NH NL / VH)."""
    nh, nv, nl, vh = (np.einsum("ij,ij->i", a, b) for a, b in ((n, h), (n, v), (n, l), (v, h)))
    g = np.minimum(1.0, np.minimum(2 * nh * nv / vh, 2 * nh * nl / vh))
    return np.where((nv > 0) & (nl > 0) & (nh > 0) & (vh > 0), g, 0.0)


def test_geometric_attenuation():
    rng = np.random.default_rng(6)
    m = 4000
    n = np.tile([0.0, 0.0, 1.0], (m, 1))
    v = random_dirs(rng, m)
    l = random_dirs(rng, m, upper=False)  # some below the horizon
    h = (v + l) / np.linalg.norm(v + l, axis=1, keepdims=True)
    g = ell.geometric_attenuation(n, h, v, l)
    g_dr = ell.geometric_attenuation(vec(n), vec(h), vec(v), vec(l)).numpy()
    ref = g_cook_torrance(n, h, v, l)
    np.testing.assert_allclose(g, ref, atol=1e-12)
    np.testing.assert_allclose(g_dr, ref, atol=2e-5)
    assert np.all((g >= 0) & (g <= 1))
    assert np.all(g[l[:, 2] <= 0] == 0)  # light below the horizon
    assert 0.05 < np.mean((g > 0) & (g < 1)) and np.any(g == 1.0)  # both regimes exercised
    np.testing.assert_allclose(ell.geometric_attenuation(n, h, l, v), g, atol=1e-12)
    # rotated frame: G only depends on dot products
    q = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    np.testing.assert_allclose(ell.geometric_attenuation(n @ q, h @ q, v @ q, l @ q), g,
                               atol=1e-9)
    # masking alone: grazing view, light along the normal
    nv = 0.1
    vv = np.array([[math.sqrt(1 - nv * nv), 0.0, nv]])
    ll = np.array([[0.0, 0.0, 1.0]])
    hh = (vv + ll) / np.linalg.norm(vv + ll)
    gm = 2 * hh[0, 2] * nv / np.dot(vv[0], hh[0])
    assert float(ell.geometric_attenuation(n[:1], hh, vv, ll)[0]) == pytest.approx(gm)


# ------------------------------------------------------------------------------ hash RNG


def pcg_np(x):
    x = np.asarray(x, dtype=np.uint64)
    m = np.uint64(0xFFFFFFFF)
    state = (x * np.uint64(747796405) + np.uint64(2891336453)) & m
    word = (((state >> ((state >> np.uint64(28)) + np.uint64(4))) ^ state)
            * np.uint64(277803737)) & m
    return ((word >> np.uint64(22)) ^ word) & m


def test_pcg_hash_matches_reference():
    x = np.array([0, 1, 2, 12345, 2**31, 2**32 - 1], dtype=np.uint64)
    got = ell.pcg_hash(mi.UInt32(x.astype(np.uint32))).numpy().astype(np.uint64)
    np.testing.assert_array_equal(got, pcg_np(x))


def test_hash_uniforms_uniform_and_decorrelated():
    n_pix, n_s = 16384, 4
    pix = np.repeat(np.arange(n_pix, dtype=np.uint32), n_s)
    smp = np.tile(np.arange(n_s, dtype=np.uint32), n_pix)
    u, v = ell.hash_uniforms(mi.UInt32(pix), mi.UInt32(smp), 7)
    u, v = u.numpy().astype(np.float64), v.numpy().astype(np.float64)
    # NumPy re-implementation of the documented construction
    h1 = pcg_np(pix.astype(np.uint64) + pcg_np(smp.astype(np.uint64) + pcg_np(7)) & 0xFFFFFFFF)
    np.testing.assert_array_equal(u, (h1 >> np.uint64(8)) / 2.0**24)
    assert np.all((u >= 0) & (u < 1) & (v >= 0) & (v < 1))
    for x in (u, v):
        assert chisquare(np.histogram(x, bins=64, range=(0, 1))[0]).pvalue > 0.01
    assert chisquare(np.histogram2d(u, v, bins=16, range=[[0, 1], [0, 1]])[0].ravel()).pvalue \
        > 0.01
    uu = u.reshape(n_pix, n_s)
    lim = 4.5 / math.sqrt(n_pix)
    assert abs(np.corrcoef(uu[:-1, 0], uu[1:, 0])[0, 1]) < lim  # neighbouring pixels
    assert abs(np.corrcoef(uu[:, 0], uu[:, 1])[0, 1]) < lim  # samples of one pixel
    assert abs(np.corrcoef(u, v)[0, 1]) < 4.5 / math.sqrt(u.size)
    u8, _ = ell.hash_uniforms(mi.UInt32(pix), mi.UInt32(smp), 8)  # next frame
    assert abs(np.corrcoef(u, u8.numpy())[0, 1]) < 4.5 / math.sqrt(u.size)
    assert chisquare(np.histogram2d(uu[:-1, 0], uu[1:, 0], bins=16,
                                    range=[[0, 1], [0, 1]])[0].ravel()).pvalue > 0.01


def test_hash_normals_follow_ds():
    rng = np.random.default_rng(8)
    m = 8192
    n = random_dirs(rng, 1, upper=False)[0]
    r = 6.0
    hs = ell.hash_normals(vec(np.tile(n, (m, 1))), mi.UInt32(np.arange(m)), r, count=2, frame=3)
    assert len(hs) == 2
    for h in hs:
        h = to_np(h)
        np.testing.assert_allclose(np.linalg.norm(h, axis=1), 1.0, atol=2e-6)
        d = np.arccos(np.clip(h @ n, -1, 1))
        assert chi2_folded(d, r) > 0.01
    assert chi2_folded(np.arccos(np.clip(to_np(hs[0]) @ n, -1, 1)), 3.0) < 1e-6


# ------------------------------------------------------------------------------ texture


@pytest.mark.parametrize("r", [1.0, 2.0, 4.0, 50.0])
def test_normal_texture_follows_ds(r):
    tex = ell.NormalTexture(r)
    h = tex.texels.reshape(-1, 3).astype(np.float64)
    np.testing.assert_allclose(np.linalg.norm(h, axis=1), 1.0, atol=1e-6)
    d = angle_from_normal(h)
    assert chi2_folded(d, r) > 0.01
    phi = np.mod(np.arctan2(h[:, 1], h[:, 0]), 2 * np.pi)
    keep = d > 1e-6
    assert chisquare(np.histogram(phi[keep], bins=24, range=(0, 2 * np.pi))[0]).pvalue > 0.01
    # a texture of another ratio is rejected
    assert chi2_folded(d, r * 1.5 + 0.5) < 1e-6


def test_normal_texture_texels_from_baked_numbers():
    tex = ell.NormalTexture(3.0, width=16, height=8, seed=2)
    assert tex.u.shape == tex.v.shape == (8, 16)
    assert np.all((tex.theta >= 0) & (tex.theta < np.pi))  # theta(V) = pi V, sec. 5.1
    d = inv_paper(tex.u, 3.0)
    t = np.pi * tex.v
    ref = np.stack([np.sin(d) * np.cos(t), np.sin(d) * np.sin(t), np.cos(d)], -1)
    np.testing.assert_allclose(tex.texels, ref, atol=1e-6)
    # stratified: one U (and one V) per interval [m / 128, (m + 1) / 128)
    for x in (tex.u, tex.v):
        np.testing.assert_array_equal(np.sort(np.floor(x.ravel() * 128)), np.arange(128))
    # seeded: reproducible
    np.testing.assert_array_equal(ell.NormalTexture(3.0, 16, 8, seed=2).texels, tex.texels)


def test_normal_texture_iid_like_paper():
    """Without stratification most seeds pass (1 in 100 fails at p < 0.01 by chance)."""
    fails = 0
    for seed in range(20):
        tex = ell.NormalTexture(3.0, seed=seed, stratify=False)
        fails += chi2_folded(angle_from_normal(tex.texels.reshape(-1, 3)), 3.0) < 0.01
    assert fails <= 3


@pytest.mark.parametrize("r", [1.0, 2.0, 4.0])
def test_quantized_texture_still_follows_ds(r):
    tex = ell.NormalTexture(r, quantize=True)
    assert tex.codes is not None and tex.codes.dtype == np.uint8 and tex.codes.shape == (64, 64, 4)
    np.testing.assert_array_equal(tex.codes[..., 3], 255)
    exact = ell.local_normal(tex.delta, tex.theta)
    np.testing.assert_allclose(tex.texels, exact, atol=1.0 / 255 + 1e-6)  # RGBA8, sec. 5.1
    h = tex.texels.reshape(-1, 3).astype(np.float64)
    h /= np.linalg.norm(h, axis=1, keepdims=True)
    assert chi2_folded(angle_from_normal(h), r) > 0.01


def test_quantized_texture_limit_for_smooth_surfaces():
    """The documented limit: 8-bit normals cannot resolve the narrow lobe of R_r = 20."""
    tex = ell.NormalTexture(20.0, quantize=True)
    h = tex.texels.reshape(-1, 3).astype(np.float64)
    assert chi2_folded(angle_from_normal(h), 20.0) < 1e-6


def test_texture_lookup_indexing():
    tex = ell.NormalTexture(3.0, width=64, height=32, seed=5)
    w, hgt = 64, 32
    ys, xs = np.mgrid[0:hgt, 0:w]
    px, py = mi.UInt32(xs.ravel() + 100), mi.UInt32(ys.ravel() + 7)  # any W x H block
    idx = [tex.texel_index(px, py, s, frame=2).numpy() for s in range(4)]
    for i in idx:  # each sample: a bijection pixel block -> texels
        assert np.array_equal(np.sort(i), np.arange(w * hgt))
    stack = np.stack(idx, 1)
    assert all(len(set(row)) == 4 for row in stack)  # the 4 samples of a pixel differ
    assert tex.distinct_samples >= 16
    # the documented pattern: R2 offsets per sample, PCG-hashed offset per frame
    g = 1.32471795724474602596
    hf = int(pcg_np(2))
    fx, fy = ((hf & 0xFFFF) * w) >> 16, ((hf >> 16) * hgt) >> 16
    for s in range(4):
        ox = math.floor(w * ((s / g) % 1.0))
        oy = math.floor(hgt * ((s / g**2) % 1.0))
        col = (xs.ravel() + 100 + ox + fx) % w
        row = (ys.ravel() + 7 + oy + fy) % hgt
        np.testing.assert_array_equal(idx[s], row * w + col)
    # a per-lane UInt32 sample index gives the same texels as the Python ints
    s_arr = mi.UInt32(np.full(w * hgt, 3))
    np.testing.assert_array_equal(tex.texel_index(px, py, s_arr, frame=2).numpy(), idx[3])
    # the frame moves the pattern
    assert not np.array_equal(tex.texel_index(px, py, 0, frame=3).numpy(), idx[0])
    # lookup returns the (normalised) texel
    h = to_np(tex.lookup(px, py, 1, frame=2))
    ref = tex.texels.reshape(-1, 3)[idx[1]]
    np.testing.assert_allclose(h, ref / np.linalg.norm(ref, axis=1, keepdims=True), atol=1e-6)
    # neighbouring pixels are decorrelated
    d = angle_from_normal(h).reshape(hgt, w)
    lim = 4.5 / math.sqrt(d.size)
    assert abs(np.corrcoef(d[:, :-1].ravel(), d[:, 1:].ravel())[0, 1]) < lim
    assert abs(np.corrcoef(d[:-1].ravel(), d[1:].ravel())[0, 1]) < lim
    d2 = angle_from_normal(to_np(tex.lookup(px, py, 2, frame=2))).ravel()
    assert abs(np.corrcoef(d.ravel(), d2)[0, 1]) < lim


def test_texture_sample_normals_world_space():
    rng = np.random.default_rng(9)
    tex = ell.NormalTexture(5.0)
    n = random_dirs(rng, 1, upper=False)[0]
    ys, xs = np.mgrid[0:64, 0:64]
    hs = tex.sample_normals(vec(np.tile(n, (4096, 1))), mi.UInt32(xs.ravel()),
                            mi.UInt32(ys.ravel()))
    assert len(hs) == ell.DEFAULT_RANDOM_SAMPLES == 4
    for h in hs:
        h = to_np(h)
        np.testing.assert_allclose(np.linalg.norm(h, axis=1), 1.0, atol=2e-6)
        assert chi2_folded(np.arccos(np.clip(h @ n, -1, 1)), 5.0) > 0.01


# ------------------------------------------------------------------------------ regular


def expectation(f, r):
    """E[f(h)] under D_s and uniform azimuth: scipy quad over |delta| (density 2 D_s), periodic
    trapezoid in the azimuth."""
    phi = (np.arange(256) + 0.5) * (2 * np.pi / 256)

    def g(d):
        h = np.stack([np.sin(d) * np.cos(phi), np.sin(d) * np.sin(phi),
                      np.full_like(phi, np.cos(d))], -1)
        return 2.0 * float(ds_paper(d, r)) * f(h).mean()

    return quad(g, 0.0, np.pi / 2, points=breakpoints(r, 0.0, np.pi / 2), limit=400,
                epsabs=1e-12, epsrel=1e-10)[0]


@pytest.mark.parametrize("r", [1.0, 3.0, 1e4])
def test_regular_samples_shape_weights_exactness(r):
    d, t, w = ell.regular_samples(r)
    assert d.shape == t.shape == w.shape == (ell.REGULAR_SAMPLE_COUNT,)
    assert w.sum() == pytest.approx(1.0, abs=1e-14) and np.all(w > 0)
    assert np.all(np.abs(d) <= np.pi / 2) and np.all((t >= 0) & (t < np.pi))
    assert d[0] == 0.0
    # layout: two rings of 6, azimuths k 60 deg and 30 + k 60 deg, at folded D_s quantiles
    # (6 -+ sqrt 6) / 10 with Radau weights (16 +- sqrt 6) / 36 per ring, 1/9 at the centre
    az = np.rad2deg(np.mod(t + np.where(d < 0, np.pi, 0.0), 2 * np.pi))
    np.testing.assert_allclose(np.sort(az[1:7]), np.arange(0, 360, 60), atol=1e-9)
    np.testing.assert_allclose(np.sort(az[7:]), np.arange(30, 360, 60), atol=1e-9)
    s6 = math.sqrt(6)
    for ring, (tq, wq) in enumerate((((6 - s6) / 10, (16 + s6) / 36),
                                     ((6 + s6) / 10, (16 - s6) / 36))):
        sl = slice(1 + 6 * ring, 7 + 6 * ring)
        np.testing.assert_allclose(folded_cdf(np.abs(d[sl]), r), tq, atol=1e-9)
        np.testing.assert_allclose(w[sl].sum(), wq, atol=1e-14)
    assert w[0] == pytest.approx(1 / 9, abs=1e-14)
    h = ell.local_normal(d, t)
    assert np.abs(np.sum(w[:, None] * h[:, :2], 0)).max() < 1e-14  # centred on the normal
    # exact for polynomials of degree <= 4 in the folded D_s mass t (uniform on [0, 1]) plus
    # azimuthal modes 1..5
    k = math.sqrt(max(r * r - 1, 0))
    sin_d = np.hypot(h[:, 0], h[:, 1])
    tt = sin_d if k == 0 else np.arctan(k * sin_d) / math.atan(k)
    phi = np.arctan2(h[:, 1], h[:, 0])
    poly = 1 - 2 * tt + 3 * tt**4 + tt * np.cos(5 * phi) + tt**2 * np.sin(3 * phi)
    assert np.sum(w * poly) == pytest.approx(1 - 1 + 3 / 5, abs=1e-12)
    assert np.sum(w * tt**5) != pytest.approx(1 / 6, abs=1e-4)  # degree 5: not exact


@pytest.mark.parametrize("r", [1.0, 2.0, 20.0, 1e4])
def test_regular_samples_beat_random(r):
    rng = np.random.default_rng(10)
    med = math.asin(1 / (r + 1))  # median microfacet angle
    fs = [lambda h: np.exp(2.0 * h @ np.array([0.6, 0.0, 0.8])),
          lambda h: (h @ np.array([0.6, 0.0, 0.8])) ** 3]
    for off, sc in ((0.0, 1.0), (1.0, 1.0), (3.0, 1.0), (1.0, 3.0)):  # lobe-sized features
        a = np.array([math.sin(off * med), 0.0, math.cos(off * med)])
        fs.append(lambda h, a=a, s=sc * med: np.exp((h @ a - 1.0) / (s * s)))
    d, t, w = ell.regular_samples(r)
    hr = ell.local_normal(d, t)
    u = rng.random((2000, 13))
    hs = ell.local_normal(ell.ellipsoidal_sample(u, r), np.pi * rng.random((2000, 13)))
    for f in fs:
        ref = expectation(f, r)
        err = abs(np.sum(w * f(hr)) - ref)
        rms = math.sqrt(np.mean((f(hs).mean(1) - ref) ** 2))
        assert err < 0.5 * rms, (r, err, rms)


def frame_np(n):
    """Independent tangent frame (s, t) of the unit normal n, right-handed (s x t = n): Gram-
    Schmidt from the world axis least aligned with n. It differs from glossrt's (Mitsuba's
    Duff et al.) frame by a rotation about n, so azimuths measured in it differ from glossrt's
    local ones by a constant angle per normal, with the same sense."""
    a = np.eye(3)[np.argmin(np.abs(n))]
    s = a - (a @ n) * n
    s /= np.linalg.norm(s)
    return s, np.cross(n, s)


def pattern_azimuth(delta, theta):
    """Azimuth in glossrt's local frame of local_normal(delta, theta): theta for delta >= 0,
    theta + pi for delta < 0 (sin(-d) (cos t, sin t) = sin d (cos(t + pi), sin(t + pi)))."""
    return np.where(np.asarray(delta) >= 0, theta, np.asarray(theta) + np.pi)


def wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


NORMALS = np.array([[0.36, 0.48, 0.8], [0, 0, 1.0], [0, 0, -1.0], [1.0, 0, 0], [0, -1.0, 0],
                    [-0.6, 0.0, -0.8], [0.0, 0.6, 0.8]])


def test_frame_tangents_orthonormal_right_handed():
    """The frame glossrt rotates local normals with (the images of the local x and y axes,
    to_world, NumPy and Dr.Jit): unit, orthogonal to each other and to n, s x t = n, and
    a rotation about n of the independent Gram-Schmidt frame (the 2 x 2 matrix between them
    has determinant +1, not -1: a mirrored frame would fail)."""
    rng = np.random.default_rng(21)
    ns = np.vstack([NORMALS / np.linalg.norm(NORMALS, axis=1, keepdims=True),
                    random_dirs(rng, 200, upper=False)])
    for dr_path in (False, True):
        if dr_path:
            s_ = to_np(ell.to_world(vec(ns), vec(np.tile([1.0, 0, 0], (len(ns), 1)))))
            t_ = to_np(ell.to_world(vec(ns), vec(np.tile([0, 1.0, 0], (len(ns), 1)))))
            tol = 2e-6
        else:
            s_ = ell.to_world(ns, np.tile([1.0, 0, 0], (len(ns), 1)))
            t_ = ell.to_world(ns, np.tile([0, 1.0, 0], (len(ns), 1)))
            tol = 1e-12
        np.testing.assert_allclose(np.linalg.norm(s_, axis=1), 1.0, atol=tol)
        np.testing.assert_allclose(np.linalg.norm(t_, axis=1), 1.0, atol=tol)
        for a, b in ((s_, t_), (s_, ns), (t_, ns)):
            np.testing.assert_allclose(np.sum(a * b, 1), 0.0, atol=tol)
        np.testing.assert_allclose(np.cross(s_, t_), ns, atol=2 * tol)
        for i, n in enumerate(ns):
            s, t = frame_np(n)
            m = np.array([[s_[i] @ s, s_[i] @ t], [t_[i] @ s, t_[i] @ t]])
            assert np.linalg.det(m) == pytest.approx(1.0, abs=10 * tol)


def test_regular_normals_world_space():
    """The 13 regular normals around n, measured in the independent frame: angle from n =
    |delta_i|, and azimuths = the pattern's (theta_i, or theta_i + pi for negative delta) plus
    one constant per normal (a rotation, same sense): the two rings of 6 at 60 degrees, the
    second turned by 30 (sec. 7.2 pattern, regular_samples' docstring)."""
    r = 7.0
    d, t, w = ell.regular_samples(r)
    ring = np.abs(d) > 0
    psi = pattern_azimuth(d, t)
    for n in NORMALS / np.linalg.norm(NORMALS, axis=1, keepdims=True):
        pairs = ell.regular_normals(vec(n[None]), r)
        assert len(pairs) == 13
        np.testing.assert_allclose([p[1] for p in pairs], w)
        h = np.vstack([to_np(p[0]) for p in pairs])
        np.testing.assert_allclose(np.linalg.norm(h, axis=1), 1.0, atol=2e-6)
        np.testing.assert_allclose(h @ n, np.cos(d), atol=2e-6)
        s, tt = frame_np(n)
        phi = np.arctan2(h @ tt, h @ s)
        off = wrap(phi[ring] - psi[ring])
        np.testing.assert_allclose(wrap(off - off[0]), 0.0, atol=2e-4)
        # the pattern itself, independently: per ring 6 azimuths 60 degrees apart, rings 30
        # degrees apart
        rings = [np.sort(wrap(phi[np.isclose(np.abs(d), x)] - off[0]) % (2 * np.pi))
                 for x in np.unique(np.abs(d[ring]))]
        for k, az in enumerate(rings):
            np.testing.assert_allclose(az, k * np.pi / 6 + np.arange(6) * np.pi / 3, atol=2e-4)


def test_hash_normals_distribution_in_an_independent_frame():
    """hash_normals measured in the independent frame of n: each sample's azimuth is
    pi v (+ pi for negative delta(u)) plus one constant per normal, from its own hash
    uniforms (u, v) (hash_uniforms; so the mapping is a rotation, same sense), the azimuths
    are uniform on [0, 2 pi) (chi-square), the angle from n follows D_s, and the two are
    independent (chi-square of the joint 6 x 5 histogram)."""
    m, r = 8192, 6.0
    for n in NORMALS[[0, 2, 3]] / np.linalg.norm(NORMALS[[0, 2, 3]], axis=1, keepdims=True):
        pix = mi.UInt32(np.arange(m))
        hs = ell.hash_normals(vec(np.tile(n, (m, 1))), pix, r, count=2, frame=5)
        s, tt = frame_np(n)
        for i, h in enumerate(hs):
            h = to_np(h)
            u, v = ell.hash_uniforms(pix, mi.UInt32(i), 5)
            delta = ell.ellipsoidal_sample(u.numpy().astype(np.float64), r)
            psi = pattern_azimuth(delta, np.pi * v.numpy().astype(np.float64))
            phi = np.arctan2(h @ tt, h @ s)
            big = np.abs(delta) > 0.05  # azimuth well defined in float32
            off = wrap(phi[big] - psi[big])
            np.testing.assert_allclose(wrap(off - off[0]), 0.0, atol=1e-4)
            assert chisquare(np.histogram(phi % (2 * np.pi), bins=24,
                                          range=(0, 2 * np.pi))[0]).pvalue > 1e-3
            ad = np.arccos(np.clip(h @ n, -1, 1))
            assert chi2_folded(ad, r) > 1e-3
            q = np.minimum((folded_cdf(ad, r) * 5).astype(int), 4)
            a = np.minimum((phi % (2 * np.pi) / (2 * np.pi) * 6).astype(int), 5)
            joint = np.histogram2d(a, q, bins=[6, 5], range=[[0, 6], [0, 5]])[0]
            expect = np.outer(joint.sum(1), joint.sum(0)) / joint.sum()
            assert chisquare(joint.ravel(), expect.ravel(), ddof=9).pvalue > 1e-3


# ------------------------------------------------------------------------------ errors


@pytest.mark.parametrize("call", [
    lambda: ell.ellipsoidal_pdf(0.1, 0.5),
    lambda: ell.ellipsoidal_pdf(0.1, float("nan")),
    lambda: ell.ellipsoidal_pdf(0.1, float("inf")),
    lambda: ell.ellipsoidal_pdf(float("nan"), 2.0),
    lambda: ell.ellipsoidal_pdf(np.zeros(3), np.ones(2) * 2),
    lambda: ell.ellipsoidal_pdf("x", 2.0),
    lambda: ell.ellipsoidal_cdf(0.1, 0.99),
    lambda: ell.ellipsoidal_sample(1.5, 2.0),
    lambda: ell.ellipsoidal_sample(-0.1, 2.0),
    lambda: ell.ellipsoidal_sample(mi.Float([0.5]), 0.0),
    lambda: ell.ellipsoidal_sample(mi.Float([0.5]), [2.0, 3.0]),
    lambda: ell.ratio_from_alpha(0.0),
    lambda: ell.ratio_from_alpha([0.1, float("nan")]),
    lambda: ell.alpha_from_ratio(0.5),
    lambda: ell.microfacet_normal(np.zeros((3, 2)), 0.1, 0.2),
    lambda: ell.geometric_attenuation(np.zeros(3), np.zeros(3), np.zeros(3), np.full(3, np.inf)),
    lambda: ell.NormalTexture(0.5),
    lambda: ell.NormalTexture(2.0, width=0),
    lambda: ell.NormalTexture(2.0, width=2.5),
    lambda: ell.regular_samples(float("nan")),
    lambda: ell.hash_uniforms(-1, 0),
    lambda: ell.hash_uniforms(np.array([0.5]), 0),
    lambda: ell.hash_normals(mi.Vector3f(0, 0, 1), 0, 2.0, count=0),
])
def test_bad_input_raises(call):
    with pytest.raises(GlossrtError):
        call()


def test_error_messages_name_the_problem():
    with pytest.raises(GlossrtError, match="ratio"):
        ell.ellipsoidal_pdf(0.0, 0.9)
    with pytest.raises(GlossrtError, match="NaN"):
        ell.ellipsoidal_sample([0.2, float("nan")], 2.0)
    with pytest.raises(GlossrtError, match=r"\[0, 1\]"):
        ell.ellipsoidal_sample(2.0, 2.0)


def test_numpy_frame_matches_mitsuba():
    rng = np.random.default_rng(11)
    n = random_dirs(rng, 1000, upper=False)
    n[:4] = [[1, 0, 0], [0, 1, -0.0], [0, 0, -1], [0, 0, 1]]
    f = mi.Frame3f(vec(n))
    for axis, local in ((f.s, [1, 0, 0]), (f.t, [0, 1, 0]), (f.n, [0, 0, 1])):
        got = ell.to_world(n, np.tile(local, (len(n), 1)))
        np.testing.assert_allclose(got, to_np(axis), atol=3e-7)
