"""Tests of the covariance-matrix GGX BRDF (glossrt.brdf.covariance_ggx, Tokuyoshi app. A.1).

References used here are independent of the module's formulas: hemisphere quadrature (for the
normalisations), the textbook anisotropic GGX written in spherical coordinates (Heitz 2014,
eqs. 85-86 with alpha_x, alpha_y), the isotropic Dr.Jit functions of glossrt.brdf.ggx, and a
chi-square test of the samplers against binned quadrature of the visible-normal density.
Random inputs come from fixed seeds, so the tests are deterministic.

Quadrature: the hemisphere is parametrised by (t, phi), with the polar angle
theta = atan(c(phi) tan t), c(phi)^2 = u^T A u (u = (cos phi, sin phi)) the roughness seen in
the azimuth phi, so that the GGX peak is spread evenly over t in [0, pi/2]. Gauss-Legendre in t,
midpoint (spectrally accurate for periodic integrands) in phi. The tolerances are set from the
measured convergence (error when halving the nodes), see each test.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
from scipy import stats

from glossrt.brdf import covariance_ggx as cg
from glossrt.brdf import ggx
from glossrt.errors import GlossrtError

F64 = dr.float64_array_t(mi.Float)
V64 = dr.float64_array_t(mi.Vector3f)


def random_spd(rng: np.random.Generator, n: int, amin: float = 0.05, amax: float = 1.0):
    """``n`` SPD matrices R diag(ax^2, ay^2) R^T with ax, ay log-uniform in [amin, amax]."""
    ax = np.exp(rng.uniform(np.log(amin), np.log(amax), n))
    ay = np.exp(rng.uniform(np.log(amin), np.log(amax), n))
    b = rng.uniform(0.0, np.pi, n)
    c, s = np.cos(b), np.sin(b)
    R = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)
    L = np.zeros((n, 2, 2))
    L[:, 0, 0] = ax * ax
    L[:, 1, 1] = ay * ay
    return R @ L @ np.swapaxes(R, -1, -2)


def random_dirs(rng: np.random.Generator, n: int, zmin: float = 0.0) -> np.ndarray:
    """Unit vectors uniform on the upper hemisphere with z > zmin."""
    z = rng.uniform(zmin, 1.0, n)
    phi = rng.uniform(0.0, 2.0 * np.pi, n)
    s = np.sqrt(1.0 - z * z)
    return np.stack([s * np.cos(phi), s * np.sin(phi), z], -1)


def hemisphere_rule(A: np.ndarray, n_t: int, n_phi: int, t0=0.0, t1=np.pi / 2, p0=0.0, p1=None):
    """Nodes ``m`` (n_t, n_phi, 3) and weights (solid angle) over t in [t0, t1], phi in
    [p0, p1] with the A-adapted mapping of the module docstring."""
    p1 = 2.0 * np.pi if p1 is None else p1
    xg, wg = np.polynomial.legendre.leggauss(n_t)
    t = 0.5 * (t1 - t0) * (xg + 1.0) + t0
    wt = 0.5 * (t1 - t0) * wg
    phi = p0 + (np.arange(n_phi) + 0.5) * (p1 - p0) / n_phi
    wp = (p1 - p0) / n_phi
    cp, sp = np.cos(phi), np.sin(phi)
    c = np.sqrt(A[0, 0] * cp * cp + 2 * A[0, 1] * cp * sp + A[1, 1] * sp * sp)  # (n_phi,)
    tt = np.tan(t)[:, None]
    theta = np.arctan(c[None, :] * tt)
    dtheta = c[None, :] * (1.0 + tt * tt) / (1.0 + (c[None, :] * tt) ** 2)
    st = np.sin(theta)
    m = np.stack([st * cp, st * sp, np.cos(theta)], -1)
    w = st * dtheta * wt[:, None] * wp
    return m, w


# ----------------------------------------------------------------------------------------------
# Normalisations (quadrature)
# ----------------------------------------------------------------------------------------------


def projected_ndf_integral(A: np.ndarray, n: int) -> float:
    m, w = hemisphere_rule(A, n, n)
    return float(np.sum(cg.D(m, A) * m[..., 2] * w))


def test_projected_ndf_integrates_to_one():
    # Measured max |I - 1| over these 12 matrices (anisotropy up to 20:1): 8.7e-4 at 48 x 48
    # nodes, 8.9e-8 at 96, 2e-13 at 192 (exponential convergence), so 1e-10 at 192 leaves
    # margin while any wrong constant (det instead of sqrt(det), A instead of A^-1) is O(1) off.
    A = random_spd(np.random.default_rng(1), 12)
    for a in A:
        assert abs(projected_ndf_integral(a, 192) - 1.0) < 1e-10, a


def test_visible_normals_normalised():
    # Heitz 2014, eq. 2: int G1(wo, m) max(0, wo.m) D(m) dm = wo.z. The kink of max(0, wo.m)
    # slows the quadrature's convergence: measured max error 9.4e-6 at 128 x 128 nodes,
    # 2.5e-7 at 256 x 256, 5.8e-8 at 512 x 512, so the tolerance is 2e-6 at 256. Using
    # sqrt(det A) A^-1 instead of A in Lambda misses by 9e-2 for the first case.
    rng = np.random.default_rng(2)
    A = random_spd(rng, 10)
    wo = random_dirs(rng, 10, zmin=0.05)
    for a, w in zip(A, wo, strict=True):
        m, q = hemisphere_rule(a, 256, 256)
        g1 = cg.G1(w, a, m)
        val = np.sum(g1 * np.maximum(m @ w, 0.0) * cg.D(m, a) * q)
        assert abs(val - w[2]) < 2e-6, (a, w, val)


def test_vndf_pdf_integrates_to_one():
    rng = np.random.default_rng(3)
    A = random_spd(rng, 3)
    wo = random_dirs(rng, 3, zmin=0.1)
    for a, w in zip(A, wo, strict=True):
        # Measured |error| <= 3e-7 (see test_visible_normals_normalised for the tolerance).
        m, q = hemisphere_rule(a, 256, 256)
        assert abs(np.sum(cg.vndf_pdf(w, m, a) * q) - 1.0) < 2e-6


# ----------------------------------------------------------------------------------------------
# Special cases and symmetries
# ----------------------------------------------------------------------------------------------


def test_isotropic_matches_ggx_module():
    rng = np.random.default_rng(4)
    n = 500
    alpha = np.exp(rng.uniform(np.log(0.01), 0.0, n))
    A = alpha[:, None, None] ** 2 * np.eye(2)
    m = random_dirs(rng, n)
    w = random_dirs(rng, n)
    d_ref = ggx.D_ggx(F64(m[:, 2]), F64(alpha)).numpy()
    np.testing.assert_allclose(cg.D(m, A), d_ref, rtol=1e-12, atol=0)
    g1_ref = ggx.G1_smith(F64(w[:, 2]), F64(alpha)).numpy()
    np.testing.assert_allclose(1.0 / (1.0 + cg.Lambda(w, A)), g1_ref, rtol=1e-12)
    np.testing.assert_allclose(cg.G1(w, A), g1_ref, rtol=1e-12)


def aniso_textbook(m: np.ndarray, ax: np.ndarray, ay: np.ndarray) -> tuple:
    """Anisotropic GGX in spherical coordinates (Heitz 2014, eqs. 85 and 86)."""
    theta = np.arccos(m[:, 2])
    phi = np.arctan2(m[:, 1], m[:, 0])
    tan2 = np.tan(theta) ** 2
    c2, s2 = np.cos(phi) ** 2, np.sin(phi) ** 2
    d = 1.0 / (np.pi * ax * ay * np.cos(theta) ** 4 * (1.0 + tan2 * (c2 / ax**2 + s2 / ay**2)) ** 2)
    a = 1.0 / (np.tan(theta) * np.sqrt(c2 * ax**2 + s2 * ay**2))
    lam = 0.5 * (-1.0 + np.sqrt(1.0 + 1.0 / (a * a)))
    return d, lam


def test_diagonal_matches_textbook_anisotropic():
    rng = np.random.default_rng(5)
    n = 500
    ax = np.exp(rng.uniform(np.log(0.02), 0.0, n))
    ay = np.exp(rng.uniform(np.log(0.02), 0.0, n))
    A = np.zeros((n, 2, 2))
    A[:, 0, 0], A[:, 1, 1] = ax * ax, ay * ay
    m = random_dirs(rng, n, zmin=0.01)
    d_ref, lam_ref = aniso_textbook(m, ax, ay)
    np.testing.assert_allclose(cg.D(m, A), d_ref, rtol=1e-10)
    np.testing.assert_allclose(cg.Lambda(m, A), lam_ref, rtol=1e-8, atol=1e-14)


def rot_z(beta: np.ndarray) -> np.ndarray:
    c, s = np.cos(beta), np.sin(beta)
    o, z = np.ones_like(beta), np.zeros_like(beta)
    return np.stack(
        [np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2
    )


def test_rotation_covariance():
    rng = np.random.default_rng(6)
    n = 300
    A = random_spd(rng, n)
    m = random_dirs(rng, n)
    R = rot_z(rng.uniform(0, 2 * np.pi, n))
    Rm = np.einsum("nij,nj->ni", R, m)
    R2 = R[:, :2, :2]
    RA = R2 @ A @ np.swapaxes(R2, -1, -2)
    RA = 0.5 * (RA + np.swapaxes(RA, -1, -2))  # exactly symmetric after rounding
    np.testing.assert_allclose(cg.D(Rm, RA), cg.D(m, A), rtol=1e-10)
    np.testing.assert_allclose(cg.Lambda(Rm, RA), cg.Lambda(m, A), rtol=1e-10, atol=1e-14)
    # A rotation of A alone does change D (the test can fail).
    assert np.max(np.abs(cg.D(m, RA) / cg.D(m, A) - 1.0)) > 0.1


def test_g2_and_brdf_composition():
    # G2 = 1 / (1 + Lambda(wo) + Lambda(wi)), and for diagonal A the BRDF equals
    # F D G2 / (4 zo zi) built from the textbook anisotropic D and Lambda.
    rng = np.random.default_rng(7)
    n = 400
    ax = np.exp(rng.uniform(np.log(0.05), 0.0, n))
    ay = np.exp(rng.uniform(np.log(0.05), 0.0, n))
    A = np.zeros((n, 2, 2))
    A[:, 0, 0], A[:, 1, 1] = ax * ax, ay * ay
    wo = random_dirs(rng, n, zmin=0.02)
    wi = random_dirs(rng, n, zmin=0.02)
    g2 = cg.G2(wo, wi, A)
    np.testing.assert_allclose(g2, 1.0 / (1.0 + cg.Lambda(wo, A) + cg.Lambda(wi, A)), rtol=1e-12)
    h = wo + wi
    h /= np.linalg.norm(h, axis=-1, keepdims=True)
    d, _ = aniso_textbook(h, ax, ay)
    _, lo = aniso_textbook(wo, ax, ay)
    _, li = aniso_textbook(wi, ax, ay)
    f0 = rng.uniform(0.02, 0.9, n)
    fr = f0 + (1 - f0) * (1 - np.sum(wo * h, -1)) ** 5
    ref = fr * d / (1 + lo + li) / (4 * wo[:, 2] * wi[:, 2])
    np.testing.assert_allclose(cg.brdf(wo, wi, A, f0), ref, rtol=1e-8)
    # Below the horizon: zero.
    below = wi * np.array([1, 1, -1])
    assert np.all(cg.brdf(wo, below, A, f0) == 0.0)
    assert np.all(cg.G2(wo, below, A) == 0.0)


def test_brdf_reciprocal():
    rng = np.random.default_rng(8)
    n = 1000
    A = random_spd(rng, n, amin=0.02)
    wo = random_dirs(rng, n)
    wi = random_dirs(rng, n)
    f0 = rng.uniform(0.0, 1.0, n)
    a, b = cg.brdf(wo, wi, A, f0), cg.brdf(wi, wo, A, f0)
    assert np.all(a > 0)
    np.testing.assert_allclose(a, b, rtol=1e-12)


def test_brdf_rgb_broadcast():
    rng = np.random.default_rng(9)
    A = random_spd(rng, 5)
    wo, wi = random_dirs(rng, 5), random_dirs(rng, 5)
    f0 = rng.uniform(0, 1, (5, 3))
    rgb = cg.brdf(wo[:, None, :], wi[:, None, :], A[:, None], f0)
    assert rgb.shape == (5, 3)
    for k in range(3):
        np.testing.assert_allclose(rgb[:, k], cg.brdf(wo, wi, A, f0[:, k]), rtol=1e-14)


# ----------------------------------------------------------------------------------------------
# Dr.Jit versions
# ----------------------------------------------------------------------------------------------


def test_drjit_matches_numpy():
    # float32 kernels (mi.Float) against the float64 NumPy code on the same (float32-rounded)
    # inputs, alpha >= 0.05. Measured max rel. errors: D 1e-5, G2 5e-7, brdf 6e-6; Lambda has
    # cancellation near the normal (-1/2 + 1/2 (1 + eps)), hence its atol 1e-6.
    rng = np.random.default_rng(10)
    n = 2000
    A = random_spd(rng, n)
    wo = random_dirs(rng, n, zmin=0.01)
    wi = random_dirs(rng, n, zmin=0.01)
    m = random_dirs(rng, n, zmin=0.01)
    f0 = rng.uniform(0, 1, (n, 3))

    def v3(a):
        return mi.Vector3f(*(mi.Float(a[:, k].astype(np.float32)) for k in range(3)))

    a11, a12, a22 = (mi.Float(A[:, i, j].astype(np.float32)) for i, j in ((0, 0), (0, 1), (1, 1)))
    # Evaluate the NumPy reference on the float32-rounded inputs.
    A32 = A.astype(np.float32).astype(np.float64)

    def r32(v):
        v = v.astype(np.float32).astype(np.float64)
        return v / np.linalg.norm(v, axis=-1, keepdims=True)

    wo_, wi_, m_ = r32(wo), r32(wi), r32(m)
    np.testing.assert_allclose(cg.D_dr(v3(m), a11, a12, a22).numpy(), cg.D(m_, A32), rtol=1e-4)
    np.testing.assert_allclose(
        cg.Lambda_dr(v3(wo), a11, a12, a22).numpy(), cg.Lambda(wo_, A32), rtol=1e-4, atol=1e-6
    )
    np.testing.assert_allclose(cg.G1_dr(v3(wo), a11, a12, a22).numpy(), cg.G1(wo_, A32), rtol=1e-4)
    np.testing.assert_allclose(
        cg.G2_dr(v3(wo), v3(wi), a11, a12, a22).numpy(), cg.G2(wo_, wi_, A32), rtol=1e-4
    )
    col = mi.Color3f(*(mi.Float(f0[:, k].astype(np.float32)) for k in range(3)))
    f = cg.brdf_dr(v3(wo), v3(wi), a11, a12, a22, col)
    got = np.stack([f.x.numpy(), f.y.numpy(), f.z.numpy()], -1)
    ref = cg.brdf(wo_[:, None], wi_[:, None], A32[:, None], f0.astype(np.float32))
    np.testing.assert_allclose(got, ref, rtol=2e-4)


def test_drjit_isotropic_matches_ggx_module():
    rng = np.random.default_rng(11)
    n = 500
    alpha = np.exp(rng.uniform(np.log(0.01), 0.0, n))
    m = random_dirs(rng, n)
    mv = V64(*(F64(m[:, k]) for k in range(3)))
    al = F64(alpha)
    a2 = al * al
    np.testing.assert_allclose(
        cg.D_dr(mv, a2, 0.0, a2).numpy(), ggx.D_ggx(mv.z, al).numpy(), rtol=1e-12
    )
    np.testing.assert_allclose(
        cg.G1_dr(mv, a2, 0.0, a2).numpy(), ggx.G1_smith(mv.z, al).numpy(), rtol=1e-12
    )


# ----------------------------------------------------------------------------------------------
# Samplers: chi-square against binned quadrature of the visible-normal density
# ----------------------------------------------------------------------------------------------

N_T, N_PHI = 12, 16  # bins in (t, phi), with the A-adapted t of hemisphere_rule


def bin_probabilities(wo: np.ndarray, A: np.ndarray) -> np.ndarray:
    # 24 x 24 Gauss/midpoint nodes per bin: the binned probabilities sum to 1 within 2e-7
    # (measured), far below the chi-square resolution ~1/sqrt(N p) per bin.
    p = np.empty((N_T, N_PHI))
    for i in range(N_T):
        for j in range(N_PHI):
            m, w = hemisphere_rule(
                A,
                24,
                24,
                i * np.pi / 2 / N_T,
                (i + 1) * np.pi / 2 / N_T,
                j * 2 * np.pi / N_PHI,
                (j + 1) * 2 * np.pi / N_PHI,
            )
            p[i, j] = np.sum(cg.vndf_pdf(wo, m, A) * w)
    return p


def bin_index(m: np.ndarray, A: np.ndarray) -> np.ndarray:
    phi = np.mod(np.arctan2(m[:, 1], m[:, 0]), 2 * np.pi)
    cp, sp = np.cos(phi), np.sin(phi)
    c = np.sqrt(A[0, 0] * cp * cp + 2 * A[0, 1] * cp * sp + A[1, 1] * sp * sp)
    theta = np.arccos(np.clip(m[:, 2], -1, 1))
    t = np.arctan(np.tan(theta) / c)
    i = np.minimum((t / (np.pi / 2) * N_T).astype(int), N_T - 1)
    j = np.minimum((phi / (2 * np.pi) * N_PHI).astype(int), N_PHI - 1)
    return i * N_PHI + j


def chi2_pvalue(m: np.ndarray, wo: np.ndarray, A: np.ndarray) -> float:
    p = bin_probabilities(wo, A).ravel()
    assert abs(p.sum() - 1.0) < 1e-4
    obs = np.bincount(bin_index(m, A), minlength=p.size).astype(float)
    exp = p * len(m)
    keep = exp >= 5.0  # pool sparse bins into one (standard chi-square practice)
    o = np.append(obs[keep], obs[~keep].sum())
    e = np.append(exp[keep], exp[~keep].sum())
    if e[-1] < 5.0:
        o[-2] += o[-1]
        e[-2] += e[-1]
        o, e = o[:-1], e[:-1]
    e *= o.sum() / e.sum()
    return float(stats.chisquare(o, e).pvalue)


CASES = [
    (np.array([[0.09, 0.06], [0.06, 0.16]]), (0.5, -0.3)),
    (np.array([[0.5, -0.1], [-0.1, 0.05]]), (-0.8, 0.4)),
    (np.array([[0.0144, 0.0], [0.0, 0.0144]]), (0.0, 0.0)),
]


def _dir(xy):
    x, y = xy
    return np.array([x, y, np.sqrt(1 - x * x - y * y)])


@pytest.mark.parametrize("case", range(len(CASES)))
def test_sample_vndf_chi_square(case):
    # 2e5 samples, 163-192 bins with >= 5 expected counts; p > 1e-3 (fixed seeds; measured
    # p = 0.51, 0.92, 0.12 for the NumPy sampler). The negative control (samples for 1.2 A
    # tested against the density for A, measured p = 0) must be rejected.
    A, xy = CASES[case]
    wo = _dir(xy)
    rng = np.random.default_rng(100 + case)
    n = 200_000
    u = rng.random((n, 2))
    m = cg.sample_vndf(wo, A, u)
    assert m.shape == (n, 3)
    np.testing.assert_allclose(np.linalg.norm(m, axis=-1), 1.0, atol=1e-12)
    assert chi2_pvalue(m, wo, A) > 1e-3
    wrong = cg.sample_vndf(wo, 1.2 * A, u)
    assert chi2_pvalue(wrong, wo, A) < 1e-6

    # Dr.Jit sampler (Heitz 2018 construction), float32.
    wv = mi.Vector3f(*(float(v) for v in wo))
    md = cg.sample_vndf_dr(
        wv, float(A[0, 0]), float(A[0, 1]), float(A[1, 1]), mi.Float(u[:, 0]), mi.Float(u[:, 1])
    )
    md = np.stack([md.x.numpy(), md.y.numpy(), md.z.numpy()], -1).astype(np.float64)
    assert chi2_pvalue(md, wo, A) > 1e-3


# ----------------------------------------------------------------------------------------------
# Errors
# ----------------------------------------------------------------------------------------------

GOOD_A = np.array([[0.1, 0.02], [0.02, 0.05]])
GOOD_M = np.array([0.0, 0.6, 0.8])


@pytest.mark.parametrize(
    "A, match",
    [
        (np.array([[0.1, 0.0], [0.0, -0.1]]), "positive-definite"),
        (np.array([[0.1, 0.2], [0.2, 0.1]]), "positive-definite"),
        (np.array([[0.0, 0.0], [0.0, 0.0]]), "positive-definite"),
        (np.array([[0.1, 0.02], [0.01, 0.05]]), "symmetric"),
        (np.array([[np.nan, 0.0], [0.0, 0.1]]), "NaN"),
        (np.array([[np.inf, 0.0], [0.0, 0.1]]), "NaN or Inf"),
        (np.eye(3), r"shape \(\.\.\., 2, 2\)"),
        (np.array([0.1, 0.1]), r"shape \(\.\.\., 2, 2\)"),
    ],
)
def test_bad_roughness(A, match):
    with pytest.raises(GlossrtError, match=match):
        cg.D(GOOD_M, A)
    with pytest.raises(GlossrtError, match=match):
        cg.Lambda(GOOD_M, A)
    with pytest.raises(GlossrtError, match=match):
        cg.brdf(GOOD_M, GOOD_M, A, 0.04)


def test_bad_vectors():
    with pytest.raises(GlossrtError, match=r"m must have shape \(\.\.\., 3\)"):
        cg.D(np.array([0.6, 0.8]), GOOD_A)
    with pytest.raises(GlossrtError, match="w contains NaN"):
        cg.Lambda(np.array([np.nan, 0.0, 1.0]), GOOD_A)
    with pytest.raises(GlossrtError, match="unit vectors"):
        cg.G1(np.array([0.0, 0.0, 2.0]), GOOD_A)
    with pytest.raises(GlossrtError, match="do not broadcast"):
        cg.D(np.tile(GOOD_M, (3, 1)), np.tile(GOOD_A, (4, 1, 1)))
    with pytest.raises(GlossrtError, match="f0 contains NaN"):
        cg.brdf(GOOD_M, GOOD_M, GOOD_A, np.nan)
    with pytest.raises(GlossrtError, match="wi must be a numeric array"):
        cg.brdf(GOOD_M, "abc", GOOD_A)
    with pytest.raises(GlossrtError, match=r"u must have shape \(\.\.\., 2\)"):
        cg.sample_vndf(GOOD_M, GOOD_A, np.zeros(3))


def test_batched_shapes():
    rng = np.random.default_rng(12)
    A = random_spd(rng, 6).reshape(2, 3, 2, 2)
    m = random_dirs(rng, 3)
    assert cg.D(m, A).shape == (2, 3)
    assert cg.Lambda(m[:, None, :], A[0]).shape == (3, 3)
    assert cg.G2(m, m, A[1]).shape == (3,)
