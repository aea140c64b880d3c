"""The temporal antialiasing pass (Karis 2014 style) that can follow SVGF."""

import mitsuba as mi
import numpy as np
import pytest

from glossrt.denoise import taa
from glossrt.errors import GlossrtError


def _t(a):
    return mi.TensorXf(np.ascontiguousarray(a, dtype=np.float32))


def test_first_frame_passes_through():
    img = np.random.default_rng(0).random((6, 8, 3))
    out = np.array(taa(_t(img), None, _t(np.zeros((6, 8, 2)))))
    np.testing.assert_array_equal(out, img.astype(np.float32))


def test_static_blend_is_an_ema_within_the_neighbourhood_clamp():
    rng = np.random.default_rng(1)
    cur = 0.5 + 0.1 * rng.random((6, 8, 3))
    hist = cur + 0.01  # inside the 3x3 min/max almost everywhere
    out = np.array(taa(_t(cur), _t(hist), _t(np.zeros((6, 8, 2))), alpha=0.1))
    lo = np.full_like(cur, np.inf)
    hi = np.full_like(cur, -np.inf)
    pad = np.pad(cur, ((1, 1), (1, 1), (0, 0)), mode="edge")
    for dy in range(3):
        for dx in range(3):
            lo = np.minimum(lo, pad[dy:dy + 6, dx:dx + 8])
            hi = np.maximum(hi, pad[dy:dy + 6, dx:dx + 8])
    want = 0.9 * np.clip(hist, lo, hi) + 0.1 * cur
    np.testing.assert_allclose(out, want, rtol=1e-5, atol=1e-6)


def test_history_is_reprojected_with_motion():
    """Content moving right by 2 px: the history is fetched 2 px to the left (motion -2)."""
    h, w = 4, 12
    base = np.tile(np.linspace(0, 1, w)[None, :, None], (h, 1, 3))
    prev = base
    cur = np.roll(base, 2, axis=1)  # what was at x - 2 is now at x
    motion = np.zeros((h, w, 2))
    motion[..., 0] = -2.0
    out = np.array(taa(_t(cur), _t(prev), _t(motion), alpha=0.1))
    # interior columns: the reprojected history equals the current value, so no change
    np.testing.assert_allclose(out[:, 3:-1], cur[:, 3:-1], atol=1e-6)
    # with zero motion the history would lag and differ
    still = np.array(taa(_t(cur), _t(prev), _t(np.zeros((h, w, 2))), alpha=0.1))
    assert np.abs(still[:, 3:-1] - cur[:, 3:-1]).max() > 1e-3


def test_non_finite_input_stays_where_it_is():
    """NaN/Inf in the image or the history count as 0 (they used to spread over the 3x3
    clamp and stay in the history); NaN/Inf motion drops that pixel's history (the integer
    conversion of a NaN position is backend-dependent)."""
    rng = np.random.default_rng(3)
    h, w = 6, 8
    cur = 0.5 + 0.1 * rng.random((h, w, 3))
    hist = cur + 0.01
    zero = np.zeros((h, w, 2))
    clean = np.array(taa(_t(cur), _t(hist), _t(zero)))
    bad_cur, bad_hist = cur.copy(), hist.copy()
    bad_cur[2, 3] = [np.nan, np.inf, -np.inf]
    bad_hist[4, 5] = np.nan
    for c, hs, pixel in ((bad_cur, hist, (2, 3)), (cur, bad_hist, (4, 5))):
        out = np.array(taa(_t(c), _t(hs), _t(zero)))
        assert np.isfinite(out).all()
        zeroed = [np.where(np.isfinite(a), a, 0.0) for a in (c, hs)]
        np.testing.assert_array_equal(out, np.array(taa(*(_t(a) for a in zeroed), _t(zero))))
        far = np.ones((h, w), bool)
        far[pixel[0] - 1:pixel[0] + 2, pixel[1] - 1:pixel[1] + 2] = False
        np.testing.assert_array_equal(out[far], clean[far])  # nothing spread past the clamp
    first = np.array(taa(_t(bad_cur), None, _t(zero)))
    assert np.isfinite(first).all() and (first[2, 3] == 0).all()
    motion = zero.copy()
    motion[1, 1] = [np.nan, 0.0]
    motion[1, 2] = [np.inf, -np.inf]
    out = np.array(taa(_t(cur), _t(hist), _t(motion)))
    np.testing.assert_array_equal(out[1, 1:3], cur[1, 1:3].astype(np.float32))  # no history
    np.testing.assert_array_equal(np.delete(out[1], [1, 2], 0), np.delete(clean[1], [1, 2], 0))


def _moving_square(k, h=12, w=16, size=4, speed=2):
    """Frame k of a noise-free scene: a bright emitter square (mesh id 2, radiance 12) moving
    ``speed`` pixels right per frame over a dark floor (mesh id 1, radiance 0.1, motion 0);
    the square's motion points back to where its pixels were."""
    img = np.full((h, w, 3), 0.1)
    ids = np.ones((h, w, 1))
    motion = np.zeros((h, w, 2))
    x0, y0 = 2 + speed * k, 4
    img[y0:y0 + size, x0:x0 + size] = 12.0
    ids[y0:y0 + size, x0:x0 + size] = 2
    motion[y0:y0 + size, x0:x0 + size, 0] = -speed
    return img, ids, motion


def test_mesh_ids_drop_the_trail_of_a_moving_emitter():
    """The scene is noise-free, so every frame is its own exact reference. With the mesh ids
    (Schied 2017 sec. 4.1's consistency test on each bilinear tap) TAA returns it exactly;
    with the neighbourhood clamp alone the floor behind the square keeps a trail of the
    emitter (its 3x3 neighbourhood still holds the square's edge)."""
    hist = {True: None, False: None}
    prev_ids = None
    for k in range(4):
        img, ids, motion = _moving_square(k)
        for with_ids in (True, False):
            kw = {"mesh_id": _t(ids), "prev_mesh_id": _t(prev_ids if prev_ids is not None
                                                         else ids)} if with_ids else {}
            hist[with_ids] = taa(_t(img), hist[with_ids], _t(motion), alpha=0.1, **kw)
        prev_ids = ids
    exact = np.abs(np.array(hist[True]) - img).max()
    trail = np.abs(np.array(hist[False]) - img).max()
    assert exact < 1e-5, exact
    assert trail > 5.0, trail  # the emitter's 12 kept (clamped to the edge's max) on the floor


def test_mesh_ids_must_come_in_pairs():
    import pytest

    from glossrt.errors import GlossrtError

    img, ids, motion = _moving_square(0)
    with pytest.raises(GlossrtError, match="both"):
        taa(_t(img), _t(img), _t(motion), mesh_id=_t(ids))


def _radical_inverse_digits(k: int, base: int) -> float:
    """Independent of glossrt's loop: k's digits in ``base`` as a string, mirrored after the
    radix point."""
    digits = np.base_repr(k, base)[::-1]
    return sum(int(d, base) * base ** -(i + 1) for i, d in enumerate(digits))


def test_taa_jitter_is_halton_2_3():
    """Karis 2014's jitter: points 1..8 of the Halton (2, 3) sequence, centred on the pixel
    and cycled; one point per 1/8 column and per 1/9 row band (stratified), never the
    pixel centre itself."""
    from glossrt.denoise import taa_jitter
    from glossrt.denoise.svgf import TAA_JITTER_COUNT

    assert TAA_JITTER_COUNT == 8
    pts = [taa_jitter(i) for i in range(8)]
    for i, (x, y) in enumerate(pts):
        assert x == pytest.approx(_radical_inverse_digits(i + 1, 2) - 0.5, abs=1e-15)
        assert y == pytest.approx(_radical_inverse_digits(i + 1, 3) - 0.5, abs=1e-15)
        assert -0.5 <= x < 0.5 and -0.5 <= y < 0.5 and (x, y) != (0.0, 0.0)
    assert sorted(int((x + 0.5) * 8) for x, _ in pts) == list(range(8))
    assert len({int((y + 0.5) * 9 + 1e-9) for _, y in pts}) == 8  # (thirds: not exact)
    assert [taa_jitter(i + 8) for i in range(8)] == pts
    with pytest.raises(GlossrtError, match="count"):
        taa_jitter(0, count=0)


@pytest.mark.slow
def test_jittered_taa_resolves_edges_towards_the_box_filtered_image():
    """The pipeline's TAA with its sub-pixel jitter (``taa_jitter``) converges, on geometric
    edges, towards the pixel-area (box-filtered) image, which Mitsuba's own ``direct``
    integrator renders through the scene's box pixel filter: polygon-light's visible light
    against the black sky, noise-free shading (LTC, no indirect light), 16 frames (two
    jitter cycles).
    Measured at 48x27 on the light's edge pixels away from the image border: RMSE 1.33
    with jitter, 4.53 without TAA, the same without jitter (TAA without jitter sees one
    point per pixel: nothing to resolve). With a consistency test on the pixel's own
    surface only, jittered TAA dropped its history there: 5.97."""
    from glossrt import scenes as scn
    from glossrt.pipeline import Pipeline
    from glossrt.render import Renderer

    setup = scn.load_static("polygon-light", size=(48, 27))
    r = Renderer(setup, max_depth=2)
    box = np.array(r.render_mitsuba(0, 256, integrator="direct"))[..., :3]
    centre = r.render_reference(0, 16).numpy("color")
    edge = np.abs(box - centre).max(-1) > 1.0  # where the pixel filter matters: the edge
    edge[[0, -1], :] = False
    edge[:, [0, -1]] = False  # (at the border the 3x3 clamp is one-sided)
    assert edge.sum() >= 10
    err = {}
    for name, opts in (("off", {"taa": False}), ("no jitter", {"taa": True, "taa_jitter": False}),
                       ("jitter", {"taa": True, "taa_jitter": True})):
        p = Pipeline(setup, direct="ltc", indirect="none", max_depth=2, progress=False, **opts)
        for i in range(16):
            f = p.render(i)
        err[name] = float(np.sqrt(np.mean((f.numpy("color") - box)[edge] ** 2)))
        assert (f.meta.get("jitter") is not None) == (name == "jitter")
    assert err["jitter"] < 0.5 * err["off"], err
    assert err["no jitter"] == pytest.approx(err["off"], rel=0.01), err


@pytest.mark.slow
def test_taa_under_motion_without_jitter_beats_the_raw_input():
    """schied2017 on the animated polygon-light (camera and light move), 64x48, frames 3..5
    against 64 spp references: TAA without jitter keeps the consistency test on the pixel's
    own surface. Accepting its 3x3 neighbours' surfaces as well (meant for jittered frames)
    made the frames 5.5x worse than the raw 1 spp input (RMSE 0.74 against 0.13; measured
    0.076 with the test on the pixel's own surface, 0.054 without TAA)."""
    from glossrt import scenes as scn
    from glossrt.pipeline import Pipeline
    from glossrt.render import Renderer

    size = (64, 48)
    r = Renderer(scn.load("polygon-light", size=size))
    refs = {i: r.render_reference(i, 64).numpy("color") for i in (3, 4, 5)}
    floor = np.mean([np.sqrt(np.mean((r.render(i).numpy("color") - refs[i]) ** 2))
                     for i in refs])
    err = {}
    for taa_on in (True, False):
        p = Pipeline(scn.load("polygon-light", size=size), preset="schied2017", taa=taa_on,
                     progress=False)
        e = []
        for i in range(6):
            f = p.render(i)
            if i in refs:
                e.append(np.sqrt(np.mean((f.numpy("color") - refs[i]) ** 2)))
        err[taa_on] = float(np.mean(e))
    assert err[True] < 0.8 * floor, (err, floor)
    assert err[True] < 2.0 * err[False], err
