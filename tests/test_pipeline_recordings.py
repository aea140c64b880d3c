"""The frame pipeline's steady state replays recorded kernels, and its per-stage times come
without synchronising the stages (issue 25, "Speed").

* ``Pipeline.recordings`` counts every frozen function a frame replays, the polygon lights'
  shading kernels included; after the warm-up frames, more frames, a camera move and a light
  move (``set_transform``) add no recording (``full`` and ``schied2017``).
* SVGF's second frozen stage replays one recording whatever the number of pixels with a
  young history (none, one, every pixel, some): Dr.Jit 1.5 records a frozen function again
  when an input's width becomes 1 or equal to another input's, or when it is a literal. The
  padded lane list gives the same spatial variance as computing it at every pixel.
* ``StageClock``: Dr.Jit's kernel history attributed to stages by launch order (counts of
  real launches, frozen replays marked as such), and a pipeline frame in the default mode
  calls no ``dr.sync_thread``.
"""

from __future__ import annotations

import drjit as dr
import numpy as np
import pytest

from glossrt import backend

backend.ensure()
import mitsuba as mi  # noqa: E402

from glossrt import pipeline, scenes, timing  # noqa: E402
from glossrt.denoise import SVGF  # noqa: E402
from glossrt.denoise.common import Grid, gbuffer  # noqa: E402
from glossrt.denoise.svgf import spatial_variance_multi, young_lanes  # noqa: E402
from glossrt.frame import Camera, Frame  # noqa: E402

SIZE = (64, 36)
COARSE = {"bspvt_resolution": 8}  # BSPVT's trees build in a second


# -- the pipeline: no recording after the warm-up ------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize(("preset", "scene"), [("full", "polygon-light"),
                                               ("schied2017", "glossy-cornell")])
def test_steady_frames_and_moves_add_no_recording(preset, scene):
    pipe = pipeline.Pipeline(scenes.load_static(scene, size=SIZE), preset=preset,
                             progress=False, **COARSE)
    k = 0
    for k in range(3):  # warm-up: the frozen functions record (empty histories, then full)
        pipe.render(k)
    steady = pipe.recordings()
    assert steady >= len(pipe.frozen()) > 0
    for k in range(3, 10):
        pipe.render(k)
    pipe.set_camera(position=(0.15, 0.6, 3.6) if scene == "glossy-cornell" else (0.4, 2.2, 6.5),
                    target=(0.0, 0.2, 0.0))
    for k in range(10, 13):
        pipe.render(k)
    pipe.set_transform("light", scenes.translation((0.12, -0.05, 0.08)))
    for k in range(13, 17):
        f = pipe.render(k)
    per_function = {getattr(fn, "__name__", repr(fn)): int(fn.n_recordings)
                    for fn in pipe.frozen()}
    print(f"\n[{preset}] recordings after warm-up {steady}, at the end {pipe.recordings()}: "
          f"{per_function}; direct={pipe.direct_mode}")
    assert pipe.recordings() == steady
    assert f.meta["pipeline"]["explicit_pose"]["shapes"] == ["light"]
    if preset == "full":  # the polygon light's shading kernels are counted (BSPVT here:
        # the whole frame's shading, one frozen function of the stage's shader)
        assert pipe.direct_mode == "ltc+bspvt"
        fn = pipe.stages["direct"].bspvt._fn
        assert fn in pipe.frozen()
        assert fn.n_recordings >= 1


@pytest.mark.parametrize("direct", ["ltc", "highlights"])
def test_recordings_count_the_polygon_light_kernels(direct):
    from glossrt.lights.ltc import shade as ltc_shade

    pipe = pipeline.Pipeline(scenes.load_static("polygon-light", size=(16, 12)),
                             direct=direct, indirect="none", taa=False, progress=False)
    fns = pipe.frozen()
    assert ltc_shade._shade_frozen in fns
    assert len({id(f) for f in fns}) == len(fns)  # each function once
    assert pipe.recordings() == sum(int(f.n_recordings) for f in fns)


# -- SVGF: one recording whatever the young-history count -----------------------------------------

H, W = 12, 16


def _plane(rad: np.ndarray, mesh: np.ndarray, index: int) -> Frame:
    """A plane facing the camera, hit at every pixel (depth 2, mesh ``mesh``), radiance
    ``rad`` in direct_diffuse only, diffuse albedo 1, no motion."""
    h, w = mesh.shape
    zeros = np.zeros((h, w, 3), np.float32)
    normal = zeros.copy()
    normal[..., 2] = 1.0
    ch = {"direct_diffuse": np.repeat(rad[..., None], 3, 2).astype(np.float32),
          "albedo_diffuse": np.ones((h, w, 3), np.float32), "albedo_specular": zeros,
          "normal": normal, "depth": np.full((h, w, 1), 2.0, np.float32),
          "mesh_id": mesh[..., None].astype(np.float32),
          "motion": np.zeros((h, w, 2), np.float32)}
    for name in ("emission", "direct_specular", "indirect_diffuse", "indirect_specular"):
        ch[name] = zeros
    cam = Camera(to_world=np.eye(4), fov=40.0, resolution=(w, h))
    return Frame(channels=ch, camera=cam, prev_camera=cam, index=index)


def _meshes() -> list[np.ndarray]:
    """Per frame the mesh ids, so that the pixels with a history under 4 frames (SVGF's
    young pixels) are: every pixel (frames 0-2), none (3), exactly one (4-6: one pixel
    shows another mesh from frame 4 on; back at 8, where the 3x3 fallback finds its
    neighbours' history), none (7-9), a block (10-12), none (13)."""
    one = np.ones((H, W))
    pixel = one.copy()
    pixel[5, 7] = 2
    block = one.copy()
    block[2:6, 3:9] = 2
    return [one] * 4 + [pixel] * 4 + [one] * 2 + [block] * 4


def test_svgf_replays_one_recording_whatever_the_young_count():
    rng = np.random.default_rng(3)
    frozen, plain = SVGF(frozen=True), SVGF(frozen=False)
    young = []
    for i, mesh in enumerate(_meshes()):
        f = _plane(rng.exponential(1.0, (H, W)), mesh, i)
        a, b = np.array(frozen(f)), np.array(plain(f))
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6, err_msg=f"frame {i}")
        young.append(int(np.count_nonzero(np.array(plain.history.length) < 4)))
    assert young == [H * W] * 3 + [0, 1, 1, 1, 0, 0, 0, 24, 24, 24, 0], young
    counts = [f.n_recordings for f in frozen.frozen_functions()]
    assert counts == [1] * (2 + frozen.params.levels - 1), counts


@pytest.mark.parametrize("case", ["none", "one", "all", "some"])
def test_young_lanes_give_the_spatial_variance_of_every_pixel(case):
    """The padded lane list (no young pixel: two dummy lanes; one: that pixel twice; all:
    one more) against the 7x7 estimate computed at every pixel, at the young pixels."""
    rng = np.random.default_rng(5)
    n = H * W
    mask = {"none": np.zeros(n, bool), "one": np.arange(n) == 37, "all": np.ones(n, bool),
            "some": rng.random(n) < 0.3}[case]
    depth = 2.0 + 0.3 * rng.random((H, W, 1))
    f = _plane(np.ones((H, W)), np.ones((H, W)), 0)
    f["depth"] = mi.TensorXf(depth.astype(np.float32))
    grid = Grid(W, H)
    gb = gbuffer(f, grid)
    moments = [[mi.Float(rng.random(n).astype(np.float32)),
                mi.Float(rng.random(n).astype(np.float32) + 1.0)] for _ in range(2)]
    lanes = young_lanes(mi.Bool(mask), n)
    assert 2 <= dr.width(lanes) != n
    got = spatial_variance_multi(grid, gb, moments, lanes=lanes)
    want = spatial_variance_multi(grid, gb, moments)
    for g, w in zip(got, want, strict=True):
        np.testing.assert_allclose(np.array(g)[mask], np.array(w)[mask], rtol=1e-6, atol=1e-7)
    assert young_lanes(mi.Bool([True, False]), 2) is None  # (tiny images: every pixel)


# -- per-stage times from the kernel history ------------------------------------------------------


def test_attribute_splits_the_history_at_the_markers():
    jit, memset = dr.KernelType.JIT, dr.KernelType.Memset
    replayed, inactive = dr.KernelRecordingMode.Replayed, dr.KernelRecordingMode.Inactive

    def e(kind, ms, size=100, mode=inactive):
        return {"type": kind, "execution_time": ms, "size": size, "recording_mode": mode}

    mark = e(memset, 0.5, timing.MARKER_WIDTH)
    hist = [e(jit, 9.0), mark, e(jit, 1.0, mode=replayed), e(memset, 0.25), e(jit, 2.0),
            mark, mark, e(jit, 4.0, mode=replayed), mark]
    out = timing.attribute(hist, ["a", "b", "c"], [1.0, 2.0, 3.0])
    assert out["stage_ms"] == {"a": 3.25, "b": 0.0, "c": 4.0}
    assert out["stage_kernels"] == {"a": {"launched": 2, "replayed": 1},
                                    "b": {"launched": 0, "replayed": 0},
                                    "c": {"launched": 1, "replayed": 1}}
    assert out["kernel_ms"] == 7.25  # from the first marker on, markers left out
    assert out["stage_host_ms"] == {"a": 1.0, "b": 2.0, "c": 3.0}
    # a stray memset of the marker's width: nothing attributed by guess
    bad = timing.attribute(hist + [mark], ["a", "b", "c"], [1.0, 2.0, 3.0])
    assert bad["stage_ms"] is None and bad["stage_kernels"] is None


def test_stage_clock_attributes_real_launches():
    """Two stages: the first launches two kernels, the second calls a frozen function of one
    kernel; the clock counts them per stage (the first run records the frozen function, the
    second replays it) and leaves the history flag as it was. Measured on Dr.Jit 1.5: the
    kernel-history flag is part of a frozen function's key, so a function replayed with the
    flag off records once more under it."""

    def one(x):
        return x * 3.0 + 1.0

    fn = dr.freeze(one)
    x = dr.arange(mi.Float, 1000) + dr.opaque(mi.Float, 0.5)
    dr.eval(x)
    dr.eval(fn(x))
    assert fn.n_recordings == 1

    def run():
        clock = timing.StageClock("kernels")
        clock.start()
        a = dr.sin(x)
        dr.eval(a)
        b = dr.cos(a) + x
        dr.eval(b)
        clock.stage_done("two")
        c = fn(b)
        dr.eval(c)
        clock.stage_done("frozen")
        return clock.finish(), b, c

    assert not dr.flag(dr.JitFlag.KernelHistory)
    first, _, _ = run()
    assert fn.n_recordings == 2  # (the flag's own recording)
    out, b, c = run()
    assert fn.n_recordings == 2
    assert not dr.flag(dr.JitFlag.KernelHistory)
    assert first["stage_kernels"]["frozen"] == {"launched": 1, "replayed": 0}
    assert out["stage_kernels"] == {"two": {"launched": 2, "replayed": 0},
                                    "frozen": {"launched": 1, "replayed": 1}}
    assert all(v >= 0 for v in out["stage_ms"].values())
    assert sum(out["stage_ms"].values()) == pytest.approx(out["kernel_ms"])
    np.testing.assert_allclose(np.array(c), np.array(one(b)))


def test_pipeline_frame_synchronises_no_stage(monkeypatch):
    pipe = pipeline.Pipeline(scenes.load_static("glossy-cornell", size=(32, 18)),
                             preset="schied2017", progress=False, timing_every=1)
    for k in range(3):
        pipe.render(k)
    calls = []
    real = dr.sync_thread
    monkeypatch.setattr(dr, "sync_thread", lambda: (calls.append(1), real())[1])
    f = pipe.render(3)
    assert calls == []
    meta = f.meta["pipeline"]
    assert meta["timing"] == "kernels"
    names = set(pipe.stages)
    assert set(meta["stage_ms"]) == set(meta["stage_host_ms"]) == names
    assert all(np.isfinite(v) and v >= 0 for v in meta["stage_ms"].values())
    assert sum(meta["stage_ms"].values()) <= meta["kernel_ms"] + 1e-9
    # the steady state replays: the path tracer's and SVGF's kernels are frozen replays
    kernels = meta["stage_kernels"]
    for name in ("gbuffer", "indirect"):
        assert kernels[name]["replayed"] >= 1, kernels
    pipe.timing = "sync"  # the old way: each stage synchronised for its wall time
    f = pipe.render(4)
    assert len(calls) == len(names)
    assert set(f.meta["pipeline"]["stage_ms"]) == names
    assert "stage_kernels" not in f.meta["pipeline"]
    pipe.timing = "none"
    assert pipe.render(5).meta["pipeline"]["stage_ms"] == {}
    with pytest.raises(pipeline.GlossrtError, match="timing must be one of kernels, sync"):
        pipeline.Pipeline("glossy-cornell", size=(8, 8), timing="fast")
