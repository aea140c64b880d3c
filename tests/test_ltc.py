"""glossrt.lights.ltc: LTC polygon-light shading with glossrt's own fit.

* ``polygon_integral`` against a float64 NumPy quadrature of the same BRDF (GGX,
  height-correlated Smith, F = 1) over the light's area, for random quads and triangles,
  views and roughnesses: median and 99th-percentile relative error (printed);
* ``shade_frame``: the diffuse term is exact (Lambert's edge formula); the whole shading agrees
  with the Monte Carlo reference of the same BRDF (glossrt.lights.mc) on a glossy plane;
  a constant texture changes nothing; errors on bad lights.

Run with ``pytest -s`` to see the numbers.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from glossrt import backend

backend.ensure()

from glossrt.errors import GlossrtError  # noqa: E402
from glossrt.experiments.ltc import random_polygons  # noqa: E402
from glossrt.lights.ltc import PrefilteredTexture, polygon_integral, shade_frame  # noqa: E402
from glossrt.lights.mc import render_mc  # noqa: E402
from glossrt.lights.quadrature import polygon_quadrature  # noqa: E402
from test_lights_mc import QUAD_DOWN, Light, lambert, plane_frame  # noqa: E402


@pytest.mark.slow
def test_polygon_integral_against_quadrature():
    """600 random one-sided quads and triangles (views up to 87 degrees, alpha ~0.1-1):
    relative error statistics are printed (docs/RESULTS.md). Asserted: the rigorous bound of
    a fitted density. LTC and normalised lobe are both densities, so for any polygon the
    masses differ by at most the total variation, half the fit's L1 error ``err_l1`` (stored
    per cell); bilinear interpolation between cells gets the largest ``err_l1`` of the 4
    surrounding cells, x 1.3 for its estimation error, + 0.01 for interpolation."""
    from glossrt.lights.ltc.table import LTCTable, default_table_path

    rng = np.random.default_rng(5)
    cases = random_polygons(rng, 600)
    # 256 x 256 midpoints: near, sharp lobes need it (96 x 96 was 11% off on some)
    want = np.array([polygon_quadrature(v, wo, n, a, m=256) for v, wo, n, a in cases])
    by_k = {}
    for i, (v, *_r) in enumerate(cases):
        by_k.setdefault(len(v), []).append(i)
    got = np.zeros(len(cases))
    for idx in by_k.values():
        got[idx] = polygon_integral(np.array([cases[i][0] for i in idx]),
                                    np.array([cases[i][2] for i in idx]),
                                    np.array([cases[i][1] for i in idx]),
                                    np.array([cases[i][3] for i in idx]), two_sided=False)
    assert np.all(np.isfinite(got))
    sig = want > 1e-3 * want.max()
    rel = np.abs(got[sig] / want[sig] - 1)
    med, p90, p99 = np.percentile(rel, [50, 90, 99])
    tab = LTCTable.load()
    with np.load(default_table_path()) as f:
        err_l1 = f["err_l1"]
    n = err_l1.shape[0] - 1
    mass, bound = [], []
    for (_v, wo, _n, a), g, w in zip(cases, got, want, strict=True):
        norm = float(tab.lookup_np(a, wo[2])[1])
        j0 = min(int(math.sqrt(min(a, 1.0)) * n), n - 1)
        i0 = min(int(math.sqrt(1 - wo[2]) * n), n - 1)
        mass.append(abs(g - w) / norm)
        bound.append(0.65 * err_l1[j0:j0 + 2, i0:i0 + 2].max() + 0.01)
    mass, bound = np.array(mass), np.array(bound)
    print(f"\nLTC polygon_integral vs quadrature, {sig.sum()} polygons: relative error median "
          f"{med:.4f}, 90th percentile {p90:.4f}, 99th percentile {p99:.4f}; mass error "
          f"|LTC - exact| / norm median {np.median(mass):.2e}, 99th percentile "
          f"{np.percentile(mass, 99):.3f}, max {mass.max():.3f}; worst mass / bound "
          f"{(mass / bound).max():.2f}")
    assert np.all(mass <= bound)


def test_polygon_integral_batching_and_errors():
    quad = np.array([[-1, -1, 2], [1, -1, 2], [1, 1, 2], [-1, 1, 2.0]])
    one = polygon_integral(quad, [0, 0, 1.0], [0, 0, 1.0], 0.3)
    many = polygon_integral(np.stack([quad] * 3), [0, 0, 1.0], [0, 0, 1.0], [0.3, 0.3, 0.3])
    assert many.shape == (3,) and np.allclose(many, one)
    assert polygon_integral(-quad, [0, 0, 1.0], [0, 0, 1.0], 0.3) == 0.0  # below the horizon
    with pytest.raises(GlossrtError, match="vertices"):
        polygon_integral(quad[:2], [0, 0, 1.0], [0, 0, 1.0], 0.3)
    with pytest.raises(GlossrtError, match="NaN"):
        polygon_integral(quad * np.nan, [0, 0, 1.0], [0, 0, 1.0], 0.3)


def test_diffuse_shading_is_exact():
    f = plane_frame()
    img = shade_frame(f, [Light(QUAD_DOWN, (2.0, 2.0, 2.0))])  # F0 = 0: diffuse + Schlick
    # with F0 = 0 the specular part is the Fresnel moment term; compare the diffuse part alone
    f_spec = plane_frame(albedo=0.0)
    spec = shade_frame(f_spec, [Light(QUAD_DOWN, (2.0, 2.0, 2.0))])
    pos = f.numpy("position")
    want = np.array([[0.5 * 2.0 * lambert(QUAD_DOWN - pos[y, x]) for x in range(8)]
                     for y in range(6)])
    np.testing.assert_allclose((img - spec)[..., 0], want, rtol=2e-4)


@pytest.mark.parametrize("alpha", [0.1, 0.25, 0.5, 1.0])
def test_shading_against_monte_carlo(alpha):
    f = plane_frame(w=8, h=6, alpha=alpha)
    f0 = np.full((6, 8, 3), 0.5, np.float32)
    lights = [Light(QUAD_DOWN, (1.0, 1.0, 1.0))]
    ltc = shade_frame(f, lights, f0=f0)
    ref = render_mc(f, lights, spp=8192, f0=f0)
    rel = np.abs(ltc / ref - 1)
    print(f"\nLTC vs MC (8192 spp), plane, alpha {alpha}: relative error median "
          f"{np.median(rel):.4f}, max {rel.max():.4f}")
    assert np.median(rel) < 0.05
    assert rel.max() < 0.25


def test_constant_texture_changes_nothing():
    f = plane_frame(w=6, h=4, alpha=0.3)
    f0 = np.full((4, 6, 3), 0.5, np.float32)
    plain = shade_frame(f, [Light(QUAD_DOWN, (2.0, 1.0, 0.5))], f0=f0)
    tex = np.full((16, 16, 3), 0.5, np.float32)
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1.0]])
    textured = shade_frame(f, [Light(QUAD_DOWN, (4.0, 2.0, 1.0), texture=tex, uv=uv)], f0=f0)
    np.testing.assert_allclose(textured, plain, rtol=1e-4, atol=1e-7)


def test_prefiltered_texture_levels():
    img = np.zeros((32, 32, 3), np.float32)
    img[:, :16] = 1.0  # left half white
    t = PrefilteredTexture(img)
    import mitsuba as mi

    uv = mi.Point2f([0.1, 0.9, 0.5], [0.5, 0.5, 0.5])
    sharp = np.array(t.eval(uv, mi.Float(0.0)))
    wide = np.array(t.eval(uv, mi.Float(10.0)))
    assert sharp[0, 0] > 0.99 and sharp[0, 1] < 0.01
    # very wide filter: the average over the light, 0.5, everywhere
    np.testing.assert_allclose(wide[0], 0.5, atol=0.05)
    with pytest.raises(GlossrtError, match="NaN"):
        PrefilteredTexture(img * np.nan)


@pytest.mark.slow
def test_frozen_shading_replays_the_moving_light():
    """``frozen=True`` (dr.freeze) gives the traced result bit for bit on every frame of the
    moving light and the moving G-buffer, recording once (new light positions are inputs, not
    baked constants)."""
    from glossrt import render, scenes
    from glossrt.lights.ltc import shade as ltc
    from glossrt.lights.scene import polygon_lights
    from glossrt.lights.shading import f0_image

    setup = scenes.load("polygon-light", size=(32, 24), frames=3)
    r = render.Renderer(setup)
    before = ltc._shade_frozen.n_recordings
    for i in range(3):
        gb = r.render(i)
        lights = polygon_lights(setup, i)
        f0 = f0_image(setup, gb)
        traced = shade_frame(gb, lights, f0=f0)
        frozen = shade_frame(gb, lights, f0=f0, frozen=True)
        assert traced.max() > 0.1
        np.testing.assert_array_equal(frozen, traced)
    assert ltc._shade_frozen.n_recordings - before <= 1


@pytest.mark.slow
def test_textured_light_is_finite_on_its_own_pixels():
    """Pixels on the textured light itself (shading point on the light's plane) get 0 from
    it, not NaN (the texture lookup has no direction there)."""
    from glossrt import render, scenes
    from glossrt.lights.scene import polygon_lights
    from glossrt.lights.shading import f0_image

    setup = scenes.load("polygon-light-textured", size=(32, 24))
    gb = render.Renderer(setup).render(0)
    img = shade_frame(gb, polygon_lights(setup, 0), f0=f0_image(setup, gb))
    assert np.all(np.isfinite(img)) and img.max() > 0.1


def test_prefiltered_levels_equal_scipys_gaussian_filter():
    # the strided separable filter against scipy.ndimage.gaussian_filter at full resolution,
    # subsampled (the independent computation the levels were first built with)
    from scipy.ndimage import gaussian_filter

    from glossrt.lights.ltc.shade import strided_gaussian

    rng = np.random.default_rng(4)
    img = rng.uniform(0, 1, (23, 37)).astype(np.float64)
    for sigma in (2.0, 4.0, 16.0, 64.0):
        step = int(sigma)
        want = gaussian_filter(img, sigma, mode="constant")[::step, ::step]
        got = strided_gaussian(23, sigma, step) @ img @ strided_gaussian(37, sigma, step).T
        np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("distribution", ["ggx", "beckmann"])
def test_accuracy_groups_by_lobe_share_and_view(distribution):
    """The accuracy experiment reports per roughness, per share of the lobe a polygon catches
    and per view angle; the share and view groups partition the cases, and every group's
    mass error stays within half the worst fit error L1 of its distribution's table (0.5 x
    1.01 for Beckmann's grazing column)."""
    from glossrt.experiments.ltc import SHARES, VIEWS, accuracy, accuracy_markdown

    acc = accuracy(80, m=96, distribution=distribution)
    assert sum(v["cases"] for v in acc["share"].values()) == 80
    assert sum(v["cases"] for v in acc["view"].values()) == 80
    assert len(acc["share"]) == len(SHARES) and len(acc["view"]) == len(VIEWS)
    assert all(v["mass_max"] <= 0.51 for v in acc["share"].values() if v["cases"])
    md = accuracy_markdown(acc)
    assert "share of the lobe" in md and "view angle" in md
