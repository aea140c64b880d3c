"""glossrt.lights.highlights: Kimura & Tokoi's light-shape highlights (issue 7).

* the estimator converges to an independent quadrature of the same reflection model
  (``E[F G L_env(reflect(v, h))]`` over ``D_s(delta) / pi`` on ``(delta, theta)``) at chosen
  pixels;
* its error falls like 1/sqrt(N) with the sample count, for the texture and hash generators;
  the regular 13-point pattern beats 4 random samples;
* culling changes nothing that matters (the culled pixels' contributions are ~0);
* GGX with visible-normal sampling converges to the GGX BRDF lit by a small far light, i.e.
  to the plain point-light shading of the same BRDF; FIS trades noise for blur;
* the CLI runs each variant; bad options are clear errors."""

from __future__ import annotations

import numpy as np
import pytest

from glossrt import backend

backend.ensure()

from glossrt.brdf import ellipsoidal as el  # noqa: E402
from glossrt.errors import GlossrtError  # noqa: E402
from glossrt.lights.highlights import HighlightRenderer, reference, shade_plain  # noqa: E402
from glossrt.lights.highlights.envmap import CubeMapSet  # noqa: E402
from test_lights_mc import CAM, Light, plane_frame  # noqa: E402


def far_quad(dist=20.0, half=1.0, radiance=(5.0, 4.0, 3.0), turn=0.0):
    """A quad in the plane's mirror direction of the camera seen from the origin (turned by
    ``turn`` degrees about the y axis), facing it."""
    r = np.array([-CAM[0], -CAM[1], CAM[2]])
    r /= np.linalg.norm(r)
    c_, s_ = np.cos(np.radians(turn)), np.sin(np.radians(turn))
    r = np.array([c_ * r[0] + s_ * r[2], r[1], -s_ * r[0] + c_ * r[2]])
    c = r * dist
    n = -r
    t1 = np.cross(n, [0.0, 0.0, 1.0])
    t1 /= np.linalg.norm(t1)
    t2 = np.cross(n, t1)
    v = np.array([c - half * t1 - half * t2, c + half * t1 - half * t2,
                  c + half * t1 + half * t2, c - half * t1 + half * t2])
    if np.cross(v[1] - v[0], v[2] - v[0]) @ n < 0:
        v = v[::-1].copy()
    return Light(v, radiance)


def setup_plane(alpha=0.2, w=12, h=9, res=64, turn=0.0, spread=1.0, half=1.0):
    f = plane_frame(w, h, alpha=alpha)
    if spread != 1.0:  # a wider plane: mirror directions spread over a wider cone
        f["position"] = f.numpy("position") * spread
    lights = [far_quad(turn=turn, half=half)]
    maps = CubeMapSet.render(lights, {1: np.zeros(3)}, res)
    f0 = np.full((h, w, 3), 0.05, np.float32)
    return f, lights, maps, f0


def quadrature(frame, maps, f0, alpha, pix, n_delta=1500, n_theta=360):
    """Independent: midpoint quadrature over (delta, theta) of D_s(delta)/pi F G L_env."""
    ratio = float(el.ratio_from_alpha(alpha))
    p = frame.numpy("position").reshape(-1, 3)[pix]
    v = CAM - p
    v /= np.linalg.norm(v)
    n = np.array([0.0, 0.0, 1.0])
    d = (np.arange(n_delta) + 0.5) / n_delta * np.pi - np.pi / 2
    t = (np.arange(n_theta) + 0.5) / n_theta * np.pi
    dd, tt = np.meshgrid(d, t, indexing="ij")
    h = np.stack([np.sin(dd) * np.cos(tt), np.sin(dd) * np.sin(tt), np.cos(dd)], -1)
    vh = h @ v
    lvec = 2 * vh[..., None] * h - v
    g = el.geometric_attenuation(n, h, v, lvec)
    fres = f0[0, 0, 0] + (1 - f0[0, 0, 0]) * np.clip(1 - vh, 0, 1) ** 5
    m = maps.maps[1]
    env = m.lookup_np(lvec.reshape(-1, 3)).reshape(*lvec.shape[:2], 3)
    wgt = el.ellipsoidal_pdf(dd, ratio) / np.pi * (np.pi / n_delta) * (np.pi / n_theta)
    return ((wgt * fres * g)[..., None] * env).sum((0, 1))


@pytest.mark.slow
def test_estimator_matches_quadrature():
    alpha = 0.2
    f, lights, maps, f0 = setup_plane(alpha)
    ref = reference(f, lights, maps, f0, samples=4096, batch=32).reshape(-1, 3)
    ref2 = reference(f, lights, maps, f0, samples=4096, batch=32,
                     frame_index=1).reshape(-1, 3)
    for pix in (0, 40, 77, 107):
        want = quadrature(f, maps, f0, alpha, pix)
        sigma = np.abs(ref[pix] - ref2[pix]).max() / np.sqrt(2) + 1e-6
        print(pix, want, ref[pix], sigma)
        assert want.max() > 1e-3
        np.testing.assert_allclose(ref[pix], want, atol=5 * sigma + 0.01 * want.max())


def test_error_falls_with_samples_and_regular_beats_random():
    f, lights, maps, f0 = setup_plane(0.15, 24, 18)
    ref = reference(f, lights, maps, f0, samples=1024, batch=32)

    def err(**kw):
        img = HighlightRenderer(cull=False, **kw)(f, lights, maps, f0)
        return float(np.sqrt(np.mean((img - ref) ** 2)))

    for sampling in ("texture", "hash"):
        e4, e64 = err(samples=4, sampling=sampling), err(samples=64, sampling=sampling)
        print(sampling, e4, e64)
        assert 2.5 < e4 / e64 < 6.0  # 1/sqrt(N): 4
    assert err(sampling="regular") < err(samples=4, sampling="hash")


def test_culling_drops_only_dark_pixels():
    """alpha 0.01: 99% of the ellipsoidal normals within 23 degrees, so pixels whose mirror
    direction is more than ~49 degrees from the light are culled (a 4 m wide plane seen from
    2 m: mirror directions over +-45 degrees, the light turned 35 degrees to one side)."""
    f, lights, maps, f0 = setup_plane(0.01, 24, 18, turn=35.0, spread=4.0)
    on = HighlightRenderer(samples=16, sampling="hash", cull=True)
    off = HighlightRenderer(samples=16, sampling="hash", cull=False)
    a, b = on(f, lights, maps, f0), off(f, lights, maps, f0)
    print(on.last_stats, a.sum(), b.sum())
    assert 0 < on.last_stats["shaded"] < on.last_stats["pixels"]
    assert b.sum() > 0
    assert np.abs(a - b).sum() <= 0.02 * b.sum()


@pytest.mark.slow
def test_ggx_converges_to_the_brdf_lit_by_a_small_light():
    """A 4 x 4 quad at distance 20 (11 degrees) on alpha 0.3 GGX: the GGX reference of the
    environment (unfiltered) agrees with the point-light shading of the same BRDF: in the
    mean (bias, measured 1-3% from the map's discretisation, the probe's parallax and the
    point-light approximation) and per pixel within the reference's own noise (a sample hits
    the light with probability ~ its solid angle over the lobe's: measured ~10%)."""
    f, lights, maps, f0 = setup_plane(0.3, 12, 9, res=128, half=2.0)
    ref = reference(f, lights, maps, f0, distribution="ggx", samples=2048, batch=32)
    plain = shade_plain(f, lights, f0)
    bias = ref.mean() / plain.mean() - 1
    rel = np.abs(ref - plain).mean() / plain.mean()
    print("ggx vs point light: bias", bias, "mean abs", rel)
    assert abs(bias) < 0.05
    assert rel < 0.2
    e = [np.sqrt(np.mean((HighlightRenderer(samples=s, distribution="ggx", cull=False)(
        f, lights, maps, f0) - ref) ** 2)) for s in (4, 64)]
    assert e[1] < e[0]


def test_bad_options():
    with pytest.raises(GlossrtError, match="distribution"):
        HighlightRenderer(distribution="phong")
    with pytest.raises(GlossrtError, match="sampling"):
        HighlightRenderer(sampling="sobol")
    with pytest.raises(GlossrtError, match="samples"):
        HighlightRenderer(samples=0)


@pytest.mark.slow
def test_cli_highlight(tmp_path):
    from glossrt.cli import main

    for extra in (["--samples", "4"], ["--distribution", "ggx"], ["--sampling", "regular"]):
        out = tmp_path / "_".join(extra)
        assert main(["light", "light-shapes", "--method", "highlight", *extra, "--size",
                     "32x18", "--out", str(out)]) == 0
        assert (out / "frame_0000.exr").exists()


@pytest.mark.slow
def test_frozen_path_matches_the_traced_one():
    """``frozen=True`` (one dr.freeze'd kernel, per-pixel roughness) gives the traced
    estimator's result (hash samples, no culling) on every frame of a moving camera, and
    records once per distribution."""
    from glossrt import render, scenes
    from glossrt.lights.highlights import render as H
    from glossrt.lights.scene import polygon_lights
    from glossrt.lights.shading import f0_image

    setup = scenes.load("light-shapes", size=(40, 24), frames=3, orbit=20.0)
    r = render.Renderer(setup)
    for dist in ("ellipsoidal", "ggx"):
        traced = H.HighlightRenderer(4, dist, "hash", cull=False)
        frozen = H.HighlightRenderer(4, dist, "hash", cull=False, frozen=True)
        before = frozen._frozen.n_recordings
        for i in range(3):
            gb = r.render(i)
            lights = polygon_lights(setup, i)
            f0 = f0_image(setup, gb)
            maps = traced.maps(setup, i, lights)
            a = traced(gb, lights, maps, f0, i)
            b = frozen(gb, lights, maps, f0, i)
            assert a.max() > 0.05
            np.testing.assert_allclose(b, a, rtol=1e-4, atol=1e-5)
        assert frozen._frozen.n_recordings - before <= 1
    with pytest.raises(GlossrtError, match="frozen"):
        H.HighlightRenderer(sampling="texture", frozen=True)


def test_smooth_surface_reflects_the_light_map_like_a_mirror():
    """alpha = 0 (a smooth conductor or a mirror: the G-buffer's roughness of Mitsuba's
    ``conductor``) used to raise from ``ratio_from_alpha``; it is the mirror limit of D_s:
    every microfacet normal is n, so each pixel shows ``F(v.n) L_env(reflect(v, n))`` (G = 1
    there: ``2 (n.h)(n.v) / (v.h) = 2``). Reference: that product in NumPy, with the map's
    NumPy lookup, for every sampling, the culled path and the frozen one."""
    f, lights, maps, f0 = setup_plane(0.0, 24, 18, half=3.0)
    p = f.numpy("position").reshape(-1, 3).astype(np.float64)
    v = CAM - p
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    r = 2.0 * v[:, 2:3] * np.array([0.0, 0.0, 1.0]) - v  # mirror direction about n = +z
    fres = 0.05 + 0.95 * (1.0 - v[:, 2]) ** 5
    want = (fres[:, None] * maps.maps[1].lookup_np(r)).reshape(18, 24, 3)
    lit = want.max(-1) > 0.1
    print("lit pixels", lit.sum())
    assert 20 < lit.sum() < lit.size - 20  # a highlight with edges
    for kw in ({"sampling": "texture"}, {"sampling": "hash"}, {"sampling": "regular"},
               {"sampling": "hash", "cull": False, "frozen": True}):
        got = HighlightRenderer(**kw)(f, lights, maps, f0)
        print(kw, np.abs(got - want).max())
        np.testing.assert_allclose(got, want, rtol=2e-3, atol=2e-3)


def test_culling_keeps_the_highlight_of_a_near_light():
    """Culling tests the mirror ray from the probe the map was rendered from (the map's
    lookups see the lights from there), enlarged by the map's texel footprint; it used to
    test it from the shading point, which drops the highlights of lights near the object:
    here a small quad 0.4 from the probe (the plane's centre) in the mirror direction of a
    corner pixel 2.3 away, whose ray from the pixel passes 1.47 away from the light. The
    independent check: the map's NumPy lookup in that pixel's mirror direction sees the
    light; culled and unculled images agree (alpha 0: exactly; alpha 0.05: the highlight
    kept, the rest within the quantile's 1%)."""
    f = plane_frame(24, 18, alpha=0.0)
    f["position"] = f.numpy("position") * 4.0  # x in [-2, 2], y in [-1.2, 1.2]
    p = f.numpy("position").reshape(-1, 3).astype(np.float64)
    corner = 0  # pixel (0, 0), at (-2, -1.2, 0)
    v = CAM - p[corner]
    v /= np.linalg.norm(v)
    r = np.array([-v[0], -v[1], v[2]])
    c = 0.4 * r
    t1 = np.cross(r, [0.0, 0.0, 1.0])
    t1 /= np.linalg.norm(t1)
    t2 = np.cross(r, t1)
    h = 0.06
    quad = np.array([c - h * t1 - h * t2, c + h * t1 - h * t2, c + h * t1 + h * t2,
                     c - h * t1 + h * t2])
    if np.cross(quad[1] - quad[0], quad[2] - quad[0]) @ r > 0:  # emit towards the probe
        quad = quad[::-1].copy()
    lights = [Light(quad, (5.0, 4.0, 3.0))]
    maps = CubeMapSet.render(lights, {1: np.zeros(3)}, 64)
    assert maps.maps[1].lookup_np(r[None])[0].max() > 1.0  # the map sees it from the probe
    # from the pixel, the mirror ray misses the light by far
    off = np.linalg.norm(np.cross(c - p[corner], r))
    assert off > 1.4
    f0 = np.full((18, 24, 3), 0.05, np.float32)
    for alpha in (0.0, 0.05):
        f["roughness"] = np.full((18, 24, 1), alpha, np.float32)
        on = HighlightRenderer(samples=16, sampling="hash", cull=True)
        off_ = HighlightRenderer(samples=16, sampling="hash", cull=False)
        a, b = on(f, lights, maps, f0), off_(f, lights, maps, f0)
        print(alpha, on.last_stats, a.reshape(-1, 3)[corner], b.reshape(-1, 3)[corner],
              a.sum(), b.sum())
        assert b.reshape(-1, 3)[corner].max() > 0.05
        np.testing.assert_allclose(a.reshape(-1, 3)[corner], b.reshape(-1, 3)[corner])
        if alpha == 0.0:
            assert on.last_stats["shaded"] < on.last_stats["pixels"] / 4  # it still culls
            np.testing.assert_array_equal(a, b)
        else:
            assert np.abs(a - b).sum() <= 0.02 * b.sum()
