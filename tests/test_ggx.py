"""Tests of the GGX lobe and the pre-integrated specular albedo table (glossrt.brdf.ggx).

Statistical tests compare against Monte Carlo estimates with a tolerance of 4 standard errors
(computed from the samples) plus the table's interpolation allowance, which is itself checked
against direct quadrature in ``test_interpolation_error_within_documented_bounds``. All random
numbers come from fixed seeds, so the tests are deterministic.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from glossrt.brdf import ggx  # (conftest.py selected the Mitsuba variant)

F64 = dr.float64_array_t(mi.Float)


@pytest.fixture(scope="module")
def table() -> ggx.SpecularAlbedoTable:
    return ggx.SpecularAlbedoTable.load()


def interp_bound(mu: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """Allowed |lookup - exact| for A and B: measured maxima (see the module docstring of
    glossrt.brdf.ggx) rounded up. The worst region is near-mirrors at grazing angles, where
    E jumps between the mirror limit (row alpha = 0) and the rough grazing limit."""
    b = np.full(np.shape(mu), 0.15)
    b = np.where(mu >= 0.001, 2e-2, b)
    b = np.where(mu >= 0.005, 6e-3, b)
    b = np.where(alpha >= 0.01, np.minimum(b, 2e-3), b)
    b = np.where(mu >= 0.05, np.minimum(b, 1.5e-3), b)
    return b


def _rgb(c: mi.Color3f) -> np.ndarray:
    return np.stack([c.x.numpy(), c.y.numpy(), c.z.numpy()], axis=-1).astype(np.float64)


def _block_mean_se(values: mi.Float, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-block mean and standard error of the mean (blocks of n consecutive lanes)."""
    v = F64(values)
    s1 = dr.block_sum(v, n).numpy() / n
    s2 = dr.block_sum(v * v, n).numpy() / n
    return s1, np.sqrt(np.maximum(s2 - s1 * s1, 0.0) / (n - 1))


def _mitsuba_albedo(bsdf: mi.BSDF, mus: list[float], n: int, ctx: mi.BSDFContext, seed: int):
    """Mean and standard error of Mitsuba's ``bsdf.sample`` weight (= f cos / pdf), i.e. the
    directional albedo, for wo at each cosine in ``mus`` (local frame, phi = 0)."""
    m_count = len(mus)
    idx = dr.arange(mi.UInt32, m_count * n)
    mu = dr.gather(mi.Float, mi.Float(mus), idx // n)
    si = dr.zeros(mi.SurfaceInteraction3f, m_count * n)
    si.wi = mi.Vector3f(dr.sqrt(1.0 - mu * mu), 0.0, mu)
    si.sh_frame = mi.Frame3f(mi.Vector3f(0.0, 0.0, 1.0))
    rng = mi.PCG32(m_count * n, initstate=seed, initseq=dr.arange(mi.UInt64, m_count * n))
    s1 = rng.next_float32()
    s2 = mi.Point2f(rng.next_float32(), rng.next_float32())
    _, weight = bsdf.sample(ctx, si, s1, s2)
    return _block_mean_se(weight.x, n)


# ----------------------------------------------------------------------------------------------
# The microfacet functions themselves
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("alpha", [1e-3, 0.01, 0.1, 0.5, 1.0])
def test_D_ggx_projected_area_is_one(alpha: float) -> None:
    """integral of D(h) cos(theta_h) dh over the hemisphere = 1 (Walter et al. 2007, eq. 4).

    With q = sin^2(theta_h): dh = dphi dcos, 2 cos dcos = -dq, so the integral is
    pi * integral_0^1 D(sqrt(1 - q)) dq, computed with Gauss-Legendre on panels graded
    geometrically towards q = 0 where D peaks (width ~alpha^2)."""
    edges = np.concatenate([[0.0], np.logspace(-14, 0, 71)])
    x, w = np.polynomial.legendre.leggauss(16)
    lo, hi = edges[:-1, None], edges[1:, None]
    q = (0.5 * (hi - lo) * x + 0.5 * (hi + lo)).ravel()
    wq = (0.5 * (hi - lo) * w).ravel()
    d64 = ggx.D_ggx(dr.sqrt(1.0 - F64(q)), alpha).numpy()
    assert abs(np.pi * np.dot(wq, d64) - 1.0) < 1e-6
    # Single precision (as in the renderer): cos^2 near 1 loses digits, hence the looser check.
    d32 = ggx.D_ggx(mi.Float(np.sqrt(1.0 - q)), alpha).numpy()
    assert abs(np.pi * np.dot(wq, d32) - 1.0) < (2e-3 if alpha < 0.01 else 2e-4)


def test_D_and_G1_match_mitsuba_microfacet_distribution() -> None:
    """Pointwise equality with Mitsuba's MicrofacetDistribution(GGX) eval / smith_g1."""
    rng = np.random.default_rng(11)
    n = 4096
    for alpha in (0.01, 0.13, 0.6, 1.0):
        distr = mi.MicrofacetDistribution(mi.MicrofacetType.GGX, alpha)
        h = mi.warp.square_to_uniform_hemisphere(mi.Point2f(rng.random(n), rng.random(n)))
        v = mi.warp.square_to_uniform_hemisphere(mi.Point2f(rng.random(n), rng.random(n)))
        front = dr.dot(v, h) > 0  # Mitsuba's orientation check, done by callers here
        d_ref = distr.eval(h).numpy()
        d = ggx.D_ggx(h.z, alpha).numpy()
        assert np.allclose(d, d_ref, rtol=2e-4, atol=1e-6 * d_ref.max())
        g_ref = distr.smith_g1(v, h).numpy()
        g = dr.select(front, ggx.G1_smith(v.z, alpha), 0.0).numpy()
        assert np.allclose(g, g_ref, rtol=1e-5, atol=1e-6)


def test_pointwise_matches_mitsuba_roughconductor_eval() -> None:
    """Mitsuba's roughconductor with eta = 0, k = 1 evaluates F D G1(wo) G1(wi) / (4 cos_o)
    (the cosine-weighted BRDF) with F = 1: the separable Smith G and a perfect mirror Fresnel.
    (fresnel_conductor with eta = 0 + 1i: a^2 + b^2 = 1 + sin^2, a = 0, so r_s = r_p = 1.)"""
    rng = np.random.default_rng(12)
    n = 4096
    for alpha in (0.05, 0.2, 0.5):
        bsdf = mi.load_dict(
            {"type": "roughconductor", "distribution": "ggx", "alpha": alpha, "eta": 0.0, "k": 1.0}
        )
        wo = mi.warp.square_to_uniform_hemisphere(mi.Point2f(rng.random(n), rng.random(n)))
        wi = mi.warp.square_to_uniform_hemisphere(mi.Point2f(rng.random(n), rng.random(n)))
        si = dr.zeros(mi.SurfaceInteraction3f, n)
        si.wi = wo
        si.sh_frame = mi.Frame3f(mi.Vector3f(0.0, 0.0, 1.0))
        ref = bsdf.eval(mi.BSDFContext(), si, wi).x.numpy()
        h = dr.normalize(wo + wi)
        val = (
            ggx.fresnel_schlick(dr.dot(wo, h), 1.0)
            * ggx.D_ggx(h.z, alpha)
            * ggx.G1_smith(wo.z, alpha)
            * ggx.G1_smith(wi.z, alpha)
            / (4.0 * wo.z)
        ).numpy()
        assert np.allclose(val, ref, rtol=5e-4, atol=1e-5 * ref.max())


def test_fresnel_schlick_rgb() -> None:
    f0 = mi.Color3f(0.04, 0.5, 1.0)
    assert np.allclose(_rgb(ggx.fresnel_schlick(mi.Float(1.0), f0)), [[0.04, 0.5, 1.0]])
    assert np.allclose(_rgb(ggx.fresnel_schlick(mi.Float(0.0), f0)), [[1.0, 1.0, 1.0]])
    out = _rgb(ggx.fresnel_schlick(mi.Float(0.5), f0))
    assert np.allclose(out, 0.03125 + (1 - 0.03125) * np.array([[0.04, 0.5, 1.0]]))


# ----------------------------------------------------------------------------------------------
# The table
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("k, distribution", [(0, "ggx"), (1, "beckmann")])
def test_shipped_table_layout(table: ggx.SpecularAlbedoTable, k: int, distribution: str) -> None:
    """The loaded tables are the shipped files, GGX first, then Beckmann."""
    with np.load(ggx.default_table_path(distribution)) as f:
        data = f["table"]
        mu, alpha = ggx.grid_nodes(data.shape[1], data.shape[0])
        assert data.dtype == np.float32
        assert np.allclose(f["mu"], mu) and np.allclose(f["alpha"], alpha)
        assert int(f["samples"]) == ggx.DEFAULT_SAMPLES
    assert (table.n_alpha, table.n_mu) == data.shape[:2] == (ggx.DEFAULT_N_ALPHA, ggx.DEFAULT_N_MU)
    assert table.n_d == 2
    assert np.array_equal(table.numpy()[k], data)
    assert np.all(np.isfinite(data)) and np.all(data >= 0.0) and np.all(data.sum(-1) <= 1.0 + 1e-6)
    assert ggx.SpecularAlbedoTable.load() is table  # cached


@pytest.mark.parametrize("k, distribution", [(0, "ggx"), (1, "beckmann")])
def test_regenerated_cells_reproduce_shipped_table(table: ggx.SpecularAlbedoTable, k: int,
                                                   distribution: str) -> None:
    """A 5 x 5 grid shares every 16th node of the 65 x 65 one; same Hammersley set, so the
    values agree to float32 rounding."""
    small = ggx.generate_albedo_table(n_mu=5, n_alpha=5, samples=ggx.DEFAULT_SAMPLES,
                                      distribution=distribution)
    shipped = table.numpy()[k]
    step_a = (table.n_alpha - 1) // 4
    step_m = (table.n_mu - 1) // 4
    assert np.abs(shipped[::step_a, ::step_m] - small).max() < 1e-6


def test_alpha_to_zero_limit(table: ggx.SpecularAlbedoTable) -> None:
    """alpha -> 0: a mirror with Schlick's Fresnel, A = 1 - (1 - mu)^5, B = (1 - mu)^5."""
    # At the nodes (mu = (i / 64)^2) the row alpha = 0 is exact ...
    mu = np.linspace(0.0, 1.0, table.n_mu) ** 2
    w5 = (1.0 - mu) ** 5
    ab = table.lookup_ab(mi.Float(mu), mi.Float(0.0))
    assert np.abs(ab.x.numpy() - (1.0 - w5)).max() < 1e-6
    assert np.abs(ab.y.numpy() - w5).max() < 1e-6
    # ... and between them it is interpolated (in sqrt(mu)) within the documented bound.
    mu = np.linspace(0.0, 1.0, 1001)
    w5 = (1.0 - mu) ** 5
    ab = table.lookup_ab(mi.Float(mu), mi.Float(0.0))
    err = np.maximum(np.abs(ab.x.numpy() - (1.0 - w5)), np.abs(ab.y.numpy() - w5))
    assert np.all(err <= interp_bound(mu, np.zeros_like(mu))), err.max()
    assert err.max() < 1e-3
    # The integral at Mitsuba's smallest roughness tends to the same limit away from grazing.
    m = mu[mu >= 0.05]
    a, b = ggx.albedo_ab(m, np.full_like(m, ggx.ALPHA_MIN), samples=1 << 12)
    assert np.abs(a - (1.0 - (1.0 - m) ** 5)).max() < 1e-4
    assert np.abs(b - (1.0 - m) ** 5).max() < 1e-4
    # ... and so do lookups just above alpha = 0.
    ab = table.lookup_ab(mi.Float(m), mi.Float(1e-4))
    assert np.abs(ab.x.numpy() + ab.y.numpy() - 1.0).max() < 1e-4


def test_interpolation_error_within_documented_bounds(table: ggx.SpecularAlbedoTable) -> None:
    """Lookups at random off-grid points vs. direct quadrature at those points (2^14 samples,
    quadrature error < 5e-5); extra points near the grazing / near-mirror corner."""
    rng = np.random.default_rng(21)
    n = 1200
    s = np.concatenate([rng.random(n), rng.uniform(0.0, 0.3, n // 2), rng.uniform(0, 0.1, 200)])
    r = np.concatenate([rng.random(n), rng.uniform(0.0, 0.3, n // 2), rng.uniform(0, 0.1, 200)])
    mu, alpha = s * s, r * r
    a, b = ggx.albedo_ab(mu, alpha, samples=1 << 14)
    ab = table.lookup_ab(mi.Float(mu), mi.Float(alpha))
    err = np.maximum(np.abs(ab.x.numpy() - a), np.abs(ab.y.numpy() - b))
    assert np.all(err <= interp_bound(mu, alpha) + 5e-5), err.max()


@pytest.mark.slow
def test_table_matches_independent_uniform_mc(table: ggx.SpecularAlbedoTable) -> None:
    """(a) E(mu, alpha, F0) for random off-grid inputs and RGB F0 against plain Monte Carlo with
    uniform hemisphere sampling of wi (pdf 1/(2 pi)) of F D G1(wo) G1(wi) / (4 cos_o)."""
    rng = np.random.default_rng(31)
    pts, n = 8, 1 << 21
    mu = rng.uniform(0.1, 1.0, pts)
    alpha = rng.uniform(0.35, 1.0, pts) ** 2  # uniform sampling is hopeless for sharp lobes
    f0 = rng.uniform(0.0, 1.0, (pts, 3))

    idx = dr.arange(mi.UInt32, pts * n)
    cell = idx // n
    m = dr.gather(mi.Float, mi.Float(mu), cell)
    a = dr.gather(mi.Float, mi.Float(alpha), cell)
    f0_lane = dr.gather(mi.Color3f, mi.Color3f(f0.T), cell)
    pcg = mi.PCG32(pts * n, initstate=7, initseq=dr.arange(mi.UInt64, pts * n))
    wi = mi.warp.square_to_uniform_hemisphere(mi.Point2f(pcg.next_float32(), pcg.next_float32()))
    wo = mi.Vector3f(dr.sqrt(1.0 - m * m), 0.0, m)
    h = dr.normalize(wo + wi)
    dgg = ggx.D_ggx(h.z, a) * ggx.G1_smith(wo.z, a) * ggx.G1_smith(wi.z, a) / (4.0 * wo.z)
    val = ggx.fresnel_schlick(dr.dot(wo, h), f0_lane) * dgg * (2.0 * dr.pi)
    stats = [_block_mean_se(val[k], n) for k in range(3)]
    mean = np.stack([s[0] for s in stats], -1)
    se = np.stack([s[1] for s in stats], -1)

    got = _rgb(table.lookup(mi.Float(mu), mi.Float(alpha), mi.Color3f(f0.T)))
    # E = F0 A + B with F0 in [0, 1]: the error is at most |dA| + |dB| <= 2 * bound.
    tol = 4.0 * se + 2.0 * interp_bound(mu, alpha)[:, None]
    assert np.all(np.abs(got - mean) <= tol), (np.abs(got - mean), tol)
    assert se.max() < 2e-3  # the test has teeth


@pytest.mark.parametrize("distribution", ["ggx", "beckmann"])
@pytest.mark.parametrize("alpha", [0.05, 0.2, 0.5])
def test_table_matches_mitsuba_roughconductor(table: ggx.SpecularAlbedoTable, alpha: float,
                                              distribution: str) -> None:
    """(b) A + B (F0 = 1) equals the albedo of Mitsuba's roughconductor with a perfect mirror
    Fresnel (eta = 0, k = 1), estimated from bsdf.sample weights (visible-normal sampling),
    for each distribution (the Beckmann lanes read the Beckmann table)."""
    bsdf = mi.load_dict({"type": "roughconductor", "distribution": distribution,
                         "alpha": alpha, "eta": 0.0, "k": 1.0})
    mus = [0.07, 0.23, 0.5, 0.81, 0.97]
    mean, se = _mitsuba_albedo(bsdf, mus, 1 << 18, mi.BSDFContext(), seed=3)
    beck = mi.Bool(distribution == "beckmann")
    got = table.lookup(mi.Float(mus), mi.Float(alpha), mi.Color3f(1.0), beck).x.numpy()
    tol = 4.0 * se + 2.0 * interp_bound(np.array(mus), alpha) + 1e-4  # 1e-4: float32 sums
    assert np.all(np.abs(got - mean) <= tol), (got - mean, tol)
    assert se.max() < 1e-3


@pytest.mark.parametrize("alpha", [0.05, 0.3])
def test_glossy_lobe_of_mitsuba_roughplastic(table: ggx.SpecularAlbedoTable, alpha: float) -> None:
    """(b') roughplastic's glossy lobe alone (ctx.type_mask = GlossyReflection) with
    eta = 1.5, F0 = ((eta - 1) / (eta + 1))^2 = 0.04.

    Mitsuba weights this lobe with the exact dielectric Fresnel term, not Schlick's, so
    E_table - E_mitsuba = integral (F_schlick - F_exact) D G / (4 cos_o) dwi, bounded by
    max_c |F_schlick(c) - F_exact(c)| * (A + B) (~0.036 * E(F0=1) for eta = 1.5): the table is
    checked against that bound. The exact-Fresnel integral by the same quadrature must then
    match Mitsuba to within Monte Carlo error, which shows the Fresnel model is the only
    difference."""
    eta = 1.5
    f0 = ((eta - 1.0) / (eta + 1.0)) ** 2
    bsdf = mi.load_dict(
        {
            "type": "roughplastic",
            "distribution": "ggx",
            "alpha": alpha,
            "int_ior": eta,
            "ext_ior": 1.0,
        }
    )
    ctx = mi.BSDFContext()
    ctx.type_mask = mi.BSDFFlags.GlossyReflection
    mus = [0.07, 0.23, 0.5, 0.81, 0.97]
    mean, se = _mitsuba_albedo(bsdf, mus, 1 << 18, ctx, seed=5)

    c = dr.linspace(mi.Float, 0.0, 1.0, 20001)
    df_max = dr.max(dr.abs(ggx.fresnel_schlick(c, f0) - mi.fresnel(c, eta)[0]))[0]
    mu_np = np.array(mus)
    ab = table.lookup_ab(mi.Float(mus), mi.Float(alpha))
    e1 = ab.x.numpy() + ab.y.numpy()
    got = f0 * ab.x.numpy() + ab.y.numpy()
    tol = df_max * e1 + 4.0 * se + 2.0 * interp_bound(mu_np, alpha) + 1e-4
    assert np.all(np.abs(got - mean) <= tol), (got - mean, tol)

    (exact,) = ggx.vndf_quadrature(
        mus, [alpha] * len(mus), lambda cos: [mi.fresnel(mi.Float(cos), eta)[0]], 1 << 14
    )
    assert np.all(np.abs(exact - mean) <= 4.0 * se + 1e-4), (exact - mean, se)


def test_lookup_clamps_inputs(table: ggx.SpecularAlbedoTable) -> None:
    ab = table.lookup_ab(mi.Float([-0.5, float("nan"), 2.0, 0.5]), mi.Float([0.3, 0.3, 5.0, -1]))
    ref = table.lookup_ab(mi.Float([0.0, 0.0, 1.0, 0.5]), mi.Float([0.3, 0.3, 1.0, 0.0]))
    assert np.array_equal(ab.x.numpy(), ref.x.numpy())
    assert np.array_equal(ab.y.numpy(), ref.y.numpy())
    assert np.all(np.isfinite(ab.x.numpy()))


def test_lookup_in_frozen_function_and_symbolic_loop(table: ggx.SpecularAlbedoTable) -> None:
    """The table is a PyTree (DRJIT_STRUCT): usable as a dr.freeze argument and in loops."""

    @dr.freeze
    def frozen(t: ggx.SpecularAlbedoTable, mu: mi.Float, alpha: mi.Float) -> mi.Color3f:
        return t.lookup(mu, alpha, mi.Color3f(0.9, 0.5, 0.04))

    # Inputs made by Dr.Jit (arrays mapped from NumPy may differ in alignment between calls,
    # which makes dr.freeze re-trace).
    for k, n in enumerate((1000, 1537, 4096)):
        rng = mi.PCG32(n, initstate=k, initseq=dr.arange(mi.UInt64, n))
        mu, alpha = rng.next_float32(), rng.next_float32() * 1.2
        got = _rgb(frozen(table, mu, alpha))
        ref = _rgb(table.lookup(mu, alpha, mi.Color3f(0.9, 0.5, 0.04)))
        assert np.allclose(got, ref, atol=1e-7)
    assert frozen.n_recordings == 1

    mu = mi.Float(np.random.default_rng(41).random(257))

    def body(i: mi.UInt32, acc: mi.Float) -> tuple[mi.UInt32, mi.Float]:
        ab = table.lookup_ab(mu, mi.Float(i) * 0.25)
        return i + 1, acc + ab.x + ab.y

    _, acc = dr.while_loop(
        (mi.UInt32(0), dr.zeros(mi.Float, 257)), lambda i, acc: i < 4, body, mode="symbolic"
    )
    ref = sum(
        table.lookup_ab(mu, mi.Float(0.25 * k)).x + table.lookup_ab(mu, mi.Float(0.25 * k)).y
        for k in range(4)
    )
    assert np.allclose(acc.numpy(), ref.numpy(), atol=1e-6)
