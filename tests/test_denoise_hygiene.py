"""Input hygiene of the screen-space denoisers (glossrt.denoise).

* NaN / Inf in a *guide* channel (normal, depth, position, roughness: whichever the filter
  reads) must not spread: such a pixel is treated exactly as a background pixel. The
  expectation is independent of the filters' internals: the output equals, everywhere, the
  output for the same frame with those pixels made background in the guides (docs/FORMATS.md:
  ``mesh_id = 0``, ``depth = +inf``, ``normal = position = 0``; roughness 0 as the renderer
  writes on background), and it is finite. Temporal filters: the next (clean) frame is finite
  and equals the one filtered after the background-patched frame (nothing entered the
  history). NaN / Inf motion vectors are a disocclusion.
* docs/FORMATS.md: consumers that reproject must refuse frames without a camera.

Frames are 32x24 (16x12 for the low-resolution side of the upsamplers).
"""

from __future__ import annotations

import numpy as np
import pytest

from glossrt import backend

backend.ensure()

from glossrt import denoise, render, scenes  # noqa: E402
from glossrt.denoise import SpatioTemporalUpsampler, bilateral, upsample  # noqa: E402
from glossrt.errors import FrameError  # noqa: E402
from glossrt.frame import Frame  # noqa: E402

SIZE, LOW = (32, 24), (16, 12)
PATCH = (slice(10, 13), slice(14, 17))  # rows, columns: a 3x3 patch of hit pixels
LOW_PATCH = (slice(5, 8), slice(7, 10))
#: guide channel -> its value on background (docs/FORMATS.md; roughness as rendered)
BACKGROUND = {"mesh_id": 0.0, "depth": np.inf, "normal": 0.0, "position": 0.0,
              "roughness": 0.0}
BAD = {"nan": np.nan, "inf": np.inf}
#: the guides each method reads
DENOISERS = {
    "svgf": ("normal", "depth"),
    "svgf-lobe": ("normal", "depth", "roughness"),
    "svgf-spatial-variance": ("normal", "depth"),
    "atrous": ("normal", "depth", "position"),
    "atrous-temporal": ("normal", "depth", "position"),
}
TEMPORAL = ("svgf", "svgf-lobe", "svgf-spatial-variance", "atrous-temporal")
TOL = dict(rtol=1e-6, atol=1e-7)


@pytest.fixture(scope="module")
def frames():
    full = render.Renderer(scenes.load("glossy-cornell", size=SIZE))
    low = render.Renderer(scenes.load("glossy-cornell", size=LOW))
    f = [full.render(k) for k in range(3)]
    lo = [low.render(0), low.render(1)]
    assert (f[0].numpy("mesh_id")[PATCH] > 0).all()
    assert (lo[0].numpy("mesh_id")[LOW_PATCH] > 0).all()
    return f, lo


def _copy(f, camera="same", source=None) -> Frame:
    return Frame(channels={k: f.numpy(k) for k in f.names},
                 camera=f.camera if camera == "same" else camera, prev_camera=f.prev_camera,
                 index=f.index, meta=dict(f.meta), source=source)


def _patched(f, channel, value, patch=PATCH) -> Frame:
    """``f`` with ``channel`` set to ``value`` on the patch."""
    g = _copy(f)
    a = g.numpy(channel)
    a[patch] = value
    g[channel] = a
    return g


def _background(f, patch=PATCH) -> Frame:
    """``f`` with the patch's pixels made background in every guide channel."""
    g = _copy(f)
    for name, v in BACKGROUND.items():
        a = g.numpy(name)
        a[patch] = v
        g[name] = a
    return g


def _check(got, want, what):
    got, want = np.array(got), np.array(want)
    bad = ~np.isfinite(got).all(axis=-1)
    assert not bad.any(), f"{what}: {bad.sum()} of {bad.size} pixels non-finite"
    np.testing.assert_allclose(got, want, **TOL, err_msg=what)


CASES = [(m, c, b) for m, chans in DENOISERS.items() for c in chans for b in BAD]


@pytest.mark.parametrize("method,channel,bad", CASES)
def test_nonfinite_guides_are_background(frames, method, channel, bad):
    (f0, f1, _), _ = frames
    d = denoise.make(method)
    got0 = d(_patched(f0, channel, BAD[bad]))
    got1 = d(f1)
    ref = denoise.make(method)
    want0 = ref(_background(f0))
    want1 = ref(f1)
    _check(got0, want0, f"{method}, {bad} {channel}")
    # temporal: nothing of the patch entered the history
    _check(got1, want1, f"{method}, the clean frame after a {bad} {channel} patch")


def _without_position(f) -> Frame:
    g = _copy(f)
    del g.channels["position"]
    return g


def test_lobe_weights_take_view_directions_from_the_camera(frames):
    # the lobes' view directions are the camera rays (common.pixel_view_directions): a frame
    # without a position channel is filtered exactly as one with it
    (f0, f1, _), (l0, l1) = frames
    for weight in ("lobe", "screen"):
        _check(bilateral(_without_position(f0), weight=weight), bilateral(f0, weight=weight),
               f"bilateral {weight} without position")
    _check(upsample(_without_position(f0), _without_position(l0), weight="lobe"),
           upsample(f0, l0, weight="lobe"), "upsample lobe without position")
    st, ref = SpatioTemporalUpsampler(weight="lobe"), SpatioTemporalUpsampler(weight="lobe")
    for f, lo in ((f0, l0), (f1, l1)):
        _check(st(_without_position(f), _without_position(lo)), ref(f, lo),
               "spatio-temporal upsampler without position")
    d, ref = denoise.make("svgf-lobe"), denoise.make("svgf-lobe")
    for f in (f0, f1):
        _check(d(_without_position(f)), ref(f), "svgf-lobe without position")


@pytest.mark.parametrize("method,bad", [(m, b) for m in TEMPORAL for b in BAD])
def test_nonfinite_motion_is_a_disocclusion(frames, method, bad):
    """NaN / Inf motion: the pixel has no history, as when its motion points far off the
    image (converting NaN to an integer pixel index is backend-dependent)."""
    (f0, f1, f2), _ = frames
    d, ref = denoise.make(method), denoise.make(method)
    d(f0), ref(f0)
    got = [d(_patched(f1, "motion", BAD[bad])), d(f2)]
    want = [ref(_patched(f1, "motion", 1e4)), ref(f2)]
    _check(got[0], want[0], f"{method}, {bad} motion")
    _check(got[1], want[1], f"{method}, the frame after {bad} motion")


BILATERAL = {
    "normal": ("normal", "depth"),
    "lobe": ("normal", "depth", "roughness"),
    "screen": ("normal", "depth", "roughness"),
}


@pytest.mark.parametrize("weight,channel,bad",
                         [(w, c, b) for w, chans in BILATERAL.items() for c in chans
                          for b in BAD])
def test_bilateral_nonfinite_guides_are_background(frames, weight, channel, bad):
    (f0, _, _), _ = frames
    got = bilateral(_patched(f0, channel, BAD[bad]), weight=weight)
    _check(got, bilateral(_background(f0), weight=weight), f"bilateral {weight}, {bad} "
           f"{channel}")


UPSAMPLE = [(w, side, c, b) for w, chans in (("normal", ("normal", "depth")),
                                              ("lobe", ("normal", "depth", "roughness")))
            for side in ("full", "low") for c in chans for b in BAD]


@pytest.mark.parametrize("weight,side,channel,bad", UPSAMPLE)
def test_upsample_nonfinite_guides_are_background(frames, weight, side, channel, bad):
    (f0, _, _), (l0, _) = frames
    if side == "full":
        bad_pair = (_patched(f0, channel, BAD[bad]), l0)
        ref_pair = (_background(f0), l0)
    else:
        bad_pair = (f0, _patched(l0, channel, BAD[bad], LOW_PATCH))
        ref_pair = (f0, _background(l0, LOW_PATCH))
    got, got_w = upsample(*bad_pair, weight=weight, return_weights=True)
    want, want_w = upsample(*ref_pair, weight=weight, return_weights=True)
    what = f"upsample {weight}, {bad} {channel} in the {side} frame"
    _check(got, want, what)
    _check(got_w, want_w, what + " (weights)")


@pytest.mark.parametrize("channel,bad", [(c, b) for c in ("normal", "depth", "roughness")
                                         for b in BAD])
def test_spatio_temporal_upsampler_nonfinite_guides(frames, channel, bad):
    (f0, f1, _), (l0, l1) = frames
    st, ref = SpatioTemporalUpsampler(weight="lobe"), SpatioTemporalUpsampler(weight="lobe")
    _check(st(_patched(f0, channel, BAD[bad]), _patched(l0, channel, BAD[bad], LOW_PATCH)),
           ref(_background(f0), _background(l0, LOW_PATCH)),
           f"spatio-temporal upsampler, {bad} {channel}")
    _check(st(f1, l1), ref(f1, l1), f"spatio-temporal upsampler, the frame after {bad} "
           f"{channel}")


@pytest.mark.parametrize("method", TEMPORAL)
def test_reprojecting_denoisers_refuse_frames_without_camera(frames, method):
    (f0, _, _), _ = frames
    g = _copy(f0, camera=None, source="in/frame_0007.exr")
    d = denoise.make(method)
    with pytest.raises(FrameError, match=r"frame_0007\.exr.*reproject.*camera"):
        d(g)
    # the refusal leaves the filter usable
    assert np.isfinite(np.array(d(f0))).all()


def test_spatio_temporal_upsampler_refuses_frames_without_camera(frames):
    (f0, _, _), (l0, _) = frames
    g = _copy(f0, camera=None, source="in/frame_0007.exr")
    with pytest.raises(FrameError, match=r"frame_0007\.exr.*reproject.*camera"):
        SpatioTemporalUpsampler()(g, l0)


def test_per_frame_filters_need_no_camera(frames):
    """Only the reprojecting filters refuse: the per-frame a-trous and the normal-weight
    bilateral / upsampling read no camera."""
    (f0, _, _), (l0, _) = frames
    g = _copy(f0, camera=None)
    lo = _copy(l0, camera=None)
    assert np.isfinite(np.array(denoise.make("atrous")(g))).all()
    assert np.isfinite(np.array(bilateral(g))).all()
    assert np.isfinite(np.array(upsample(g, lo))).all()


@pytest.mark.parametrize("bad", sorted(BAD))
def test_nonfinite_radiance_does_not_spread_in_bilateral_and_upsample(frames, bad):
    """NaN / Inf in a filtered radiance channel stays where it is: the bilateral filter and
    the upsampler zero such illumination before their taps read it, so every pixel outside
    the patch (bilateral) and every full-resolution pixel (upsampled from a patched low frame)
    is finite and equals the result with that radiance set to 0."""
    f, lo = frames
    for weight in ("normal", "lobe"):
        got = np.asarray(bilateral(_patched(f[0], "indirect_specular", BAD[bad]),
                                   weight=weight))
        want = np.asarray(bilateral(_patched(f[0], "indirect_specular", 0.0), weight=weight))
        outside = np.ones(got.shape[:2], bool)
        outside[PATCH] = False
        assert np.isfinite(got[outside]).all()
        np.testing.assert_allclose(got[outside], want[outside], **TOL)
        full = _copy(f[0])
        up = np.asarray(upsample(full, _patched(lo[0], "indirect_diffuse", BAD[bad], LOW_PATCH),
                                 weight=weight))
        up0 = np.asarray(upsample(full, _patched(lo[0], "indirect_diffuse", 0.0, LOW_PATCH),
                                  weight=weight))
        assert np.isfinite(up).all()
        np.testing.assert_allclose(up, up0, **TOL)
