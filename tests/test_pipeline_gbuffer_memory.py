"""Issue 25, memory of the G-buffer stage: no buffer for channels that are 0 by construction
or that the pipeline never reads, and the full-resolution pass traced in row tiles (a frozen
replay keeps every intermediate until it returns), with the same values as the untiled pass
and no new recording across frames and poses."""

import drjit as dr
import numpy as np
import pytest

from glossrt import pipeline, render, scenes
from glossrt.errors import GlossrtError
from glossrt.render.pathtracer import RADIANCE_OUT

# (polygon-light is isotropic: its pipeline frames leave the anisotropy channels out)
SCHEMA = tuple(k for k in render.GBUFFER_OUT + RADIANCE_OUT + ("color",)
               if k not in render.pathtracer.ANISOTROPY_OUT)
COARSE = {"bspvt_resolution": 8}


def _literal(t) -> bool:
    return t.array.state == dr.VarState.Literal


@pytest.mark.slow
def test_zero_channels_are_zero_in_a_full_trace_and_hold_no_buffer():
    """The channels :meth:`Renderer.zero_channels` declares 0 (``indirect_*`` at path depth
    2, ``direct_*`` with every emitter excluded at the primary hit; both at depth 1) are 0
    in the path tracer's full output (``render_pixels``: the unfrozen trace of every
    channel, no channel skipped), and the frame holds them as zero constants (no buffer)."""
    setup = scenes.load("polygon-light", size=(24, 18))
    n = len(render.emitter_index(setup))
    r = render.Renderer(setup, max_depth=2, primary_exclude=tuple(range(n)))
    assert set(r.zero_channels()) == {"direct_diffuse", "direct_specular",
                                      "indirect_diffuse", "indirect_specular"}
    full = r.render_pixels(1, np.arange(24 * 18))
    f = r.render(1)
    assert f.names == render.Renderer(setup).render(1).names  # the schema, in its order
    for k in r.zero_channels():
        assert np.all(full[k] == 0.0), k
        assert _literal(f[k]), k
        assert np.all(f.numpy(k) == 0.0)
    for k in ("emission", "color", "normal"):
        assert not _literal(f[k])
        np.testing.assert_array_equal(f.numpy(k).reshape(-1, f[k].shape[2]), full[k])
    # depth 2, nothing excluded: only indirect_*; the direct light is there
    r2 = render.Renderer(setup, max_depth=2)
    assert r2.zero_channels() == ("indirect_diffuse", "indirect_specular")
    full2 = r2.render_pixels(1, np.arange(24 * 18))
    assert np.all(full2["indirect_diffuse"] == 0) and np.all(full2["indirect_specular"] == 0)
    assert full2["direct_diffuse"].max() > 0
    # depth 1 (the G-buffer pass)
    g = r2.render_gbuffer(1)
    for k in RADIANCE_OUT[1:]:
        assert _literal(g[k]) and np.all(g.numpy(k) == 0)
    assert render.Renderer(setup).zero_channels() == ()


@pytest.mark.slow
def test_omit_leaves_channels_out_and_refuses_unknown_names():
    setup = scenes.load("polygon-light", size=(16, 12))
    r = render.Renderer(setup)
    f = r.render(0, omit=("color",))
    ref = render.Renderer(setup).render(0)
    assert "color" not in f.names and f.meta["omitted"] == ["color"]
    for k in f.names:
        np.testing.assert_array_equal(f.numpy(k), ref.numpy(k))
    with pytest.raises(GlossrtError, match="not a radiance channel"):
        r.render(0, omit=("normal",))
    with pytest.raises(GlossrtError, match="omit"):
        r.render(0, omit="color")
    with pytest.raises(GlossrtError, match="tile_pixels"):
        render.Renderer(setup, tile_pixels=0)


def test_tile_rows_and_starts():
    assert render.tile_rows(1920, 1080) == (1 << 18) // 1920
    assert render.tile_rows(640, 360) == 360  # untiled
    starts = render.tile_starts(30, 7)
    assert starts == [0, 7, 14, 21, 23]  # the last tile ends on the last row


@pytest.mark.slow
@pytest.mark.parametrize("case", ["plain", "jitter+roughness+exclude"])
def test_tiled_frame_equals_the_untiled_and_the_traced_one(case):
    """7-row tiles of a 40x30 frame (the last one overlapping the one before) against the
    untiled frozen frame and the frame traced without dr.freeze: every channel bit for bit,
    the same non-finite count, frame after frame; the tile function records on the first
    frame only."""
    setup = scenes.load("polygon-light", size=(40, 30))
    kw, call = {}, {}
    if case != "plain":
        kw = {"primary_exclude": (0,), "max_depth": 4}
        rng = np.random.default_rng(3)
        call = {"jitter": (0.25, -0.375),
                "roughness": rng.uniform(0.05, 0.6, (30, 40)).astype(np.float32)}
    tiled = render.Renderer(setup, tile_pixels=7 * 40, **kw)
    whole = render.Renderer(setup, **kw)
    traced = render.Renderer(setup, frozen=False, **kw)
    for i in range(4):
        ft, fw, fu = (r.render(i, **call) for r in (tiled, whole, traced))
        assert ft.names == fw.names == fu.names
        for k in ft.names:
            a = ft.numpy(k)
            np.testing.assert_array_equal(a, fw.numpy(k), err_msg=k)
            np.testing.assert_array_equal(a, fu.numpy(k), err_msg=k)
        assert ft.meta["nonfinite_samples"] == fw.meta["nonfinite_samples"]
        if i == 0:
            rec = tiled._tile_frozen.n_recordings
            assert rec >= 1
    assert tiled._tile_frozen.n_recordings == rec
    assert tiled._trace_frozen.n_recordings == 0  # never the untiled trace
    assert whole._tile_frozen.n_recordings == 0


@pytest.mark.slow
def test_tiles_count_every_nonfinite_sample_once():
    """An infinite sky makes every background sample non-finite (replaced by 0 and counted):
    the overlapping last tile must not count its shared rows twice (the count of the frame
    traced without dr.freeze, untiled)."""
    from glossrt.backend import mi
    from glossrt.scenes import SceneSetup

    inf = float("inf")
    scene = mi.load_dict({
        "type": "scene",
        "sensor": {
            "type": "perspective", "fov": 40.0,
            "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 4], target=[0, 0, 0],
                                                       up=[0, 1, 0]),
            "film": {"type": "hdrfilm", "width": 20, "height": 15},
        },
        "ball": {"type": "sphere", "radius": 0.5, "bsdf": {"type": "diffuse"}},
        "sky": {"type": "constant", "radiance": {"type": "rgb", "value": [inf, inf, inf]}},
    })
    setup = SceneSetup("inf-sky", scene)
    a = render.Renderer(setup, tile_pixels=4 * 20).render(0)  # tiles 0, 4, 8, 11 (overlap)
    b = render.Renderer(setup, frozen=False).render(0)
    assert b.meta["nonfinite_samples"] > 0
    assert a.meta["nonfinite_samples"] == b.meta["nonfinite_samples"]
    for k in a.names:
        np.testing.assert_array_equal(a.numpy(k), b.numpy(k), err_msg=k)


def _pipe(tile_pixels: int | None, size=(64, 36)):
    pipe = pipeline.Pipeline(scenes.load_static("polygon-light", size=size), preset="full",
                             progress=False, **COARSE)
    if tile_pixels is not None:
        gb = pipe.stages["gbuffer"]
        gb.renderer.tile_pixels = tile_pixels
        gb.low.tile_pixels = tile_pixels
    return pipe


@pytest.mark.slow
def test_full_pipeline_tiled_equals_untiled_and_keeps_the_schema():
    """``full`` (indirect at 1/2 resolution, every polygon light analytic) with 5-row tiles
    in both G-buffer renderers against the untiled pipeline: every layer and channel equal
    over frames (histories: SVGF, the upsampler, TAA) and a camera move, no recording after
    the warm-up. The frame keeps every schema channel; the G-buffer stage's own frame holds
    no buffer for the zero channels and no ``color``."""
    def frames(pipe, counts=None):
        out = []
        for i in range(7):
            if i == 5:
                pipe.set_camera(position=(0.4, 2.2, 6.5), target=(0.0, 0.2, 0.0))
            f = pipe.render(i)
            out.append((f.names, {k: f.numpy(k) for k in f.names}, dict(f.meta)))
            if i == 2 and counts is not None:
                counts.extend(int(fn.n_recordings) for fn in pipe.frozen())
        return out

    # one pipeline at a time: two pipelines rendering in turn were seen to record once more
    # now and then (the untiled trace too), through state their frozen functions share
    tiled = _pipe(5 * 64)
    assert tiled.direct_mode == "ltc+bspvt"
    steady: list[int] = []
    got = frames(tiled, steady)
    assert [int(fn.n_recordings) for fn in tiled.frozen()] == steady
    want = frames(_pipe(None))
    for i, ((names, ch, meta), (names_w, ch_w, _)) in enumerate(zip(got, want, strict=True)):
        assert set(SCHEMA) <= set(names) and names == names_w
        assert "omitted" not in meta
        for k in names:
            np.testing.assert_array_equal(ch[k], ch_w[k], err_msg=f"{i} {k}")
    gb = tiled.stages["gbuffer"]
    assert gb.renderer._tile_frozen in tiled.frozen()
    assert gb.renderer._tile_frozen.n_recordings >= 1
    assert gb.low._tile_frozen.n_recordings >= 1
    out = gb.run(7, {})
    f, low = out["frame"], out["frame_low"]
    assert "color" not in f.names and "color" not in low.names
    for k in ("indirect_diffuse", "indirect_specular", "direct_diffuse", "direct_specular"):
        assert _literal(f[k]), k
    for k in ("direct_diffuse", "direct_specular"):
        assert _literal(low[k]), k
    assert not _literal(low["indirect_diffuse"])
