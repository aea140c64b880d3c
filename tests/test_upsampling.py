"""glossrt.denoise.upsampling: joint bilateral and spatio-temporal upsampling, adaptive
re-sampling (Tokuyoshi 2015, secs. 5.3-5.4; Kopf 2007; Herzog 2010), and the renderer's
sub-pixel jitter and multi-sample pixel subsets they use.

* the Dr.Jit upsampler against a plain NumPy re-implementation of the documented formula on
  tiny random frames (normal and lobe weights, with and without jitter);
* the jitter convention: a low-resolution frame rendered with ``jitter_sequence(f, k)`` has
  its samples exactly on full-resolution pixel centres;
* bookkeeping and errors; a roughness step kept by the lobe weight and blurred by the normal
  weight; adaptive re-sampling picks exactly the low-weight pixels and reduces their error;
  spatio-temporal upsampling of a static 1 spp sequence converges towards the reference.

Run with ``pytest -s`` to see the measured numbers.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from glossrt import backend

backend.ensure()
import mitsuba as mi  # noqa: E402, F401

from glossrt.denoise import upsampling as up  # noqa: E402
from glossrt.errors import FrameError, GlossrtError  # noqa: E402
from glossrt.frame import RADIANCE, Frame  # noqa: E402
from test_bilateral import (  # noqa: E402
    CAM_POS,
    _camera,
    beck,
    np_lobe,
    np_lobe_weight,
    random_frame,
    step_frame,
)


def np_upsample(frame, low, weight, channels, radius=2, sigma_s=1.0, sigma_n2=0.01,
                beta=20.0, kappa=100.0, approx=True, sigma_z2=0.01):
    """The module docstring's formula, float64, one full-resolution pixel at a time."""
    F = {k: frame.numpy(k).astype(np.float64) for k in frame.names}
    L = {k: low.numpy(k).astype(np.float64) for k in low.names}
    f = frame.width // low.width
    jx, jy = low.meta.get("jitter", (0.0, 0.0))
    hit = F["mesh_id"][..., 0] > 0
    lhit = L["mesh_id"][..., 0] > 0
    out = sum(F[c] for c in RADIANCE if c not in channels)
    for c in channels:
        aname = "albedo_specular" if c.endswith("specular") else "albedo_diffuse"
        la, fa = L[aname], F[aname]
        sig = np.where(la > 1e-3, L[c] / np.maximum(la, 1e-3), L[c])
        res = F[c].copy()
        for y in range(frame.height):
            for x in range(frame.width):
                if not hit[y, x]:
                    continue
                u, v = (x + 0.5) / f - 0.5 - jx, (y + 0.5) / f - 0.5 - jy
                ni, zi = F["normal"][y, x], F["depth"][y, x, 0]
                wo = CAM_POS - F["position"][y, x]
                li = np_lobe(ni, wo / np.linalg.norm(wo), F["roughness"][y, x, 0],
                             beck(F, y, x))
                num, den = np.zeros(3), 0.0
                for qy in range(math.floor(v) - radius + 1, math.floor(v) + radius + 1):
                    for qx in range(math.floor(u) - radius + 1, math.floor(u) + radius + 1):
                        if not (0 <= qx < low.width and 0 <= qy < low.height):
                            continue
                        sp = math.exp(-((qx - u) ** 2 + (qy - v) ** 2) / (2 * sigma_s**2))
                        wt = 0.0
                        if lhit[qy, qx]:
                            zj = L["depth"][qy, qx, 0]
                            wt = sp * math.exp(-(((zi - zj) / zi) ** 2) / (2 * sigma_z2))
                            nj = L["normal"][qy, qx]
                            if weight == "lobe" and c.endswith("specular"):
                                wj = CAM_POS - L["position"][qy, qx]
                                lj = np_lobe(nj, wj / np.linalg.norm(wj),
                                             L["roughness"][qy, qx, 0], beck(L, qy, qx))
                                wt *= np_lobe_weight(*li, *lj, beta, kappa, approx)
                            else:
                                wt *= math.exp(-np.sum((ni - nj) ** 2) / (2 * sigma_n2))
                        wt += 1e-6 * sp  # the documented spatial fallback floor
                        num += wt * sig[qy, qx]
                        den += wt
                illum = num / den
                res[y, x] = np.where(fa[y, x] > 1e-3, illum * fa[y, x], illum)
        out = out + res
    return out


def _with_meta(frame, **meta):
    return Frame(channels={k: frame.numpy(k) for k in frame.names}, camera=frame.camera,
                 meta={**frame.meta, **meta})


@pytest.mark.parametrize("weight,jitter", [("normal", None), ("lobe", None),
                                           ("lobe", (0.25, -0.25))])
def test_matches_numpy_reference(weight, jitter):
    full = random_frame(8, 6, seed=3, background=((0, 0), (5, 2)))
    low = random_frame(4, 3, seed=4, background=((3, 0),), jitter=jitter or (0.0, 0.0))
    channels = ("indirect_diffuse", "indirect_specular")
    got = np.array(up.upsample(full, low, weight=weight, channels=channels))
    want = np_upsample(full, low, weight, channels)
    np.testing.assert_allclose(got, want, rtol=2e-4, atol=2e-5)


def test_constant_illumination_is_remodulated_by_the_full_albedo():
    full = random_frame(8, 6, seed=5, background=())
    low = random_frame(4, 3, seed=6, background=())
    ch = {k: low.numpy(k) for k in low.names}
    ch["indirect_diffuse"] = 0.7 * ch["albedo_diffuse"]  # illumination 0.7 everywhere
    low = Frame(channels=ch, camera=low.camera)
    got = np.array(up.upsample(full, low, channels=("indirect_diffuse",)))
    rest = sum(full.numpy(c) for c in RADIANCE if c != "indirect_diffuse")
    np.testing.assert_allclose(got - rest, 0.7 * full.numpy("albedo_diffuse"), rtol=1e-4,
                               atol=1e-6)


def test_roughness_step_is_kept_by_the_lobe_weight_only():
    full = step_frame(24, 16)
    ch = {k: full.numpy(k)[::2, ::2] for k in full.names}  # the same plane at 1/2
    low = Frame(channels=ch, camera=_camera(12, 8))
    inp = full.numpy("indirect_specular")[..., 0]
    step = inp[0, 0] - inp[0, -1]
    cols = [10, 11, 12, 13]
    errs = {}
    for weight in ("normal", "lobe"):
        out = np.array(up.upsample(full, low, weight=weight,
                                   channels=("indirect_specular",)))[..., 0]
        errs[weight] = np.max(np.abs(out[:, cols] - inp[:, cols])) / step
    print(f"\nupsampled roughness step: max error next to it (fraction of the step): {errs}")
    assert errs["lobe"] < 0.01
    assert errs["normal"] > 0.1


def test_bad_inputs_name_the_problem():
    full = random_frame(8, 6)
    with pytest.raises(FrameError, match="integer multiple"):
        up.upsample(full, random_frame(3, 3, background=()))
    for bad in ("fancy", "screen"):
        with pytest.raises(GlossrtError, match="unknown weight"):
            up.upsample(full, random_frame(4, 3, background=()), weight=bad)
    with pytest.raises(GlossrtError, match="emission"):
        up.upsample(full, random_frame(4, 3, background=()), channels=("emission",))
    low = random_frame(4, 3, background=())
    del low.channels["normal"]
    with pytest.raises(FrameError, match="normal"):
        up.upsample(full, low)
    with pytest.raises(FrameError, match="jitter"):
        up.upsample(full, _with_meta(random_frame(4, 3, background=()), jitter="left"))


def test_jitter_sequence_visits_every_full_pixel_centre():
    for f in (1, 2, 4):
        js = {up.jitter_sequence(f, k) for k in range(f * f)}
        assert len(js) == f * f
        assert all(-0.5 <= a < 0.5 and -0.5 <= b < 0.5 for a, b in js)
        assert up.jitter_sequence(f, f * f) == up.jitter_sequence(f, 0)


# -- with the renderer -------------------------------------------------------------------------


@pytest.fixture(scope="module")
def cornell():
    from glossrt import render, scenes

    return {f: render.Renderer(scenes.load("glossy-cornell", size=(48 // f, 36 // f)))
            for f in (1, 2)}


@pytest.mark.slow
def test_jittered_low_samples_land_on_full_pixel_centres(cornell):
    full = cornell[1].render(3).numpy("position")
    for k in range(4):
        jx, jy = up.jitter_sequence(2, k)
        low = cornell[2].render(3, jitter=(jx, jy))
        assert low.meta["jitter"] == [jx, jy]
        i, j = k % 2, k // 2  # the full pixel (2qx + i, 2qy + j) of low pixel q
        np.testing.assert_allclose(low.numpy("position"), full[j::2, i::2], atol=2e-4)


def test_render_rejects_a_jitter_outside_the_pixel(cornell):
    with pytest.raises(GlossrtError, match="jitter"):
        cornell[2].render(0, jitter=(0.5, 0.0))


@pytest.mark.slow
def test_render_pixels_with_many_samples(cornell):
    """Means of 1024 samples over every 7th pixel agree with the reference's (independent
    samples: deterministic seeds, measured 0.1% / 1.7% apart); the G-buffer is unchanged."""
    r = cornell[1]
    idx = np.arange(0, 48 * 36, 7)
    ref = r.render_reference(1, spp=1024)
    got = r.render_pixels(1, idx, spp=1024)
    for c, tol in (("direct_diffuse", 0.02), ("indirect_diffuse", 0.06)):
        want = ref.numpy(c).reshape(-1, 3)[idx]
        assert abs(got[c].mean() / want.mean() - 1) < tol, c
    assert not np.array_equal(got["indirect_diffuse"],
                              ref.numpy("indirect_diffuse").reshape(-1, 3)[idx])
    np.testing.assert_array_equal(got["normal"], ref.numpy("normal").reshape(-1, 3)[idx])


@pytest.fixture(scope="module")
def roughness_up():
    """roughness-map at 64x48 from a converged 1/4-resolution render."""
    from glossrt import render, scenes

    full_r = render.Renderer(scenes.load("roughness-map", size=(64, 48)))
    low_r = render.Renderer(scenes.load("roughness-map", size=(16, 12)))
    full = full_r.render(0)
    ref = full_r.render_reference(0, spp=128)
    low = low_r.render_reference(0, spp=128)
    return full_r, full, ref, low


@pytest.mark.slow
def test_adaptive_resample_fixes_the_low_weight_pixels(roughness_up):
    full_r, full, ref, low = roughness_up
    img, wts = up.upsample(full, low, weight="lobe", return_weights=True)
    wts = np.array(wts)
    out, mask = up.adaptive_resample(full_r, 0, full, img, wts, threshold=0.05, spp=512)
    np.testing.assert_array_equal(mask, wts.min(-1) < 0.05)
    n = int(mask.sum())
    assert 0 < n < mask.size // 4
    # the error of the upsampled (indirect) part: the rest is the same 1 spp direct light
    ind = ("indirect_diffuse", "indirect_specular")
    rest = sum(full.numpy(c) for c in RADIANCE if c not in ind)
    tgt = sum(ref.numpy(c) for c in ind)
    before = np.mean((np.array(img) - rest - tgt)[mask] ** 2)
    after = np.mean((np.array(out) - rest - tgt)[mask] ** 2)
    # the noise floor: a second, independent 128 spp reference against the first
    other = full_r.render_reference(0, spp=128, seed=7)
    floor = np.mean((sum(other.numpy(c) for c in ind) - tgt)[mask] ** 2)
    print(f"\nadaptive re-sampling (1/4, lobe): {n} of {mask.size} pixels, their MSE "
          f"{before:.4g} -> {after:.4g} (two 128 spp references: {floor:.4g})")
    # re-rendered with 512 spp against a 128 spp reference: var_512 + var_128 is about 0.6 of
    # the floor (2 var_128); what is left of the upsampling error must be below the floor
    assert after < floor
    assert before > 1.5 * after
    np.testing.assert_array_equal(np.array(out)[~mask], np.array(img)[~mask])


@pytest.mark.slow
def test_spatio_temporal_upsampling_converges_on_a_static_view(cornell):
    """1 spp low-resolution frames of a still view (frame 0 each time, new seeds): the
    temporal upsampler averages them, the spatial one cannot. Errors of the upsampled
    (indirect) part against a 256 spp reference."""
    full_r, low_r = cornell[1], cornell[2]
    ind = ("indirect_diffuse", "indirect_specular")
    ref = full_r.render_reference(0, spp=256)
    tgt = sum(ref.numpy(c) for c in ind)
    st = up.SpatioTemporalUpsampler(weight="lobe")
    errs, spatial = [], []
    for k in range(16):
        full = full_r.render(0, seed=k)
        assert np.abs(full.numpy("motion")).max() < 1e-4  # frame 0: nothing moves
        rest = sum(full.numpy(c) for c in RADIANCE if c not in ind)
        low = low_r.render(0, seed=100 + k, jitter=up.jitter_sequence(2, k))
        out = np.array(st(full, low))
        errs.append(np.mean((out - rest - tgt) ** 2))
        sp = np.array(up.upsample(full, low, weight="lobe"))
        spatial.append(np.mean((sp - rest - tgt) ** 2))
    # 1 spp fireflies make single frames erratic: compare means (settled frames 8-15 vs all)
    print(f"\nupsampled MSE by frame, spatio-temporal: {np.round(errs, 5)}; spatial only: "
          f"{np.round(spatial, 5)}")
    assert np.mean(errs[8:]) < 0.5 * np.mean(spatial)
    assert np.mean(errs[8:]) < 0.5 * np.mean(errs[:4])
    st.reset()
    again = np.array(st(full, low))
    np.testing.assert_allclose(again, np.array(up.upsample(full, low, weight="lobe")),
                               rtol=1e-5, atol=1e-6)


@pytest.mark.slow
def test_upsampling_experiments_run_small():
    from glossrt.experiments import upsampling as ue

    res = ue.upsampling(size=(32, 24), ref_spp=16, low_spp=16)
    assert [(r["factor"], r["weight"]) for r in res.rows] == [
        (2, "normal"), (2, "lobe"), (4, "normal"), (4, "lobe")]
    for r in res.rows:
        assert np.isfinite(r["mse"]) and r["mse"] > 0 and r["ms"] > 0
        assert r["mse_adaptive"] <= r["mse"] * 1.5
    assert res.markdown().count("\n") == len(res.rows) + 1
    st = ue.spatio_temporal(size=(32, 24), frames=4, ref_spp=16, ref_frames=(1, 3))
    assert set(st.mse) == {(w, m) for w in ("normal", "lobe")
                           for m in ("spatial", "spatio-temporal")}
    assert all(len(v) == 2 and all(np.isfinite(v)) for v in st.mse.values())
    with pytest.raises(ValueError, match="multiple"):
        ue.upsampling(size=(30, 24), factors=(4,))


def test_pixel_view_directions_are_the_reversed_primary_rays(cornell):
    # the lobes' view directions from the camera model against normalize(camera - position)
    # of the renderer's own primary hits (Mitsuba's rays), with and without jitter
    from glossrt.denoise.common import Grid, pixel_view_directions

    def both(fr):
        p = fr.numpy("position").reshape(-1, 3).astype(np.float64)
        want = fr.camera.position - p
        want /= np.linalg.norm(want, axis=1, keepdims=True)
        got = np.array(pixel_view_directions(fr, Grid(fr.width, fr.height))).T
        hit = fr.numpy("mesh_id").ravel() > 0
        assert hit.mean() > 0.9
        return np.linalg.norm(got - want, axis=1)[hit]

    assert both(cornell[1].render(3)).max() < 2e-6
    low = cornell[2].render(3, jitter=(0.25, -0.4))
    assert both(low).max() < 2e-6
    # the jitter is read from meta: without it the directions are off by ~a third of a pixel
    assert both(_with_meta(low, jitter=[0.0, 0.0])).min() > 1e-4
