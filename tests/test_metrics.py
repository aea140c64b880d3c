"""Tests for glossrt.metrics and glossrt.compare (compare with a fake frame loader)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import mitsuba as mi
import numpy as np
import pytest

from glossrt import compare, metrics
from glossrt.errors import GlossrtError


def _rand(shape=(24, 32, 3), seed=0, lo=0.0, hi=1.0):
    return np.random.default_rng(seed).uniform(lo, hi, shape).astype(np.float32)


# -- rmse / relmse ---------------------------------------------------------------------------


def test_rmse_matches_hand_computation():
    x, r = _rand(seed=1), _rand(seed=2)
    d = x.astype(np.float64) - r
    expected = np.sqrt(np.sum(d * d) / d.size)
    assert metrics.rmse(x, r) == pytest.approx(expected, rel=1e-12)
    assert metrics.rmse(r, r) == 0.0
    # A constant offset c gives exactly c.
    assert metrics.rmse(r + 0.25, r) == pytest.approx(0.25, rel=1e-6)


def test_rmse_accepts_tensorxf():
    x, r = _rand(seed=3), _rand(seed=4)
    assert metrics.rmse(mi.TensorXf(x), mi.TensorXf(r)) == pytest.approx(
        metrics.rmse(x, r), rel=1e-12
    )


def test_relmse_known_values():
    r = _rand(seed=5, lo=0.1, hi=2.0)
    assert metrics.relmse(r, r) == 0.0
    # (2r - r)^2 / (r^2 + eps) = r^2 / (r^2 + eps), averaged.
    r64 = r.astype(np.float64)
    expected = np.mean(r64**2 / (r64**2 + 1e-2))
    assert metrics.relmse(2 * r, r) == pytest.approx(expected, rel=1e-9)
    # eps -> ~0 gives ~1 for doubling.
    assert metrics.relmse(2 * r, r, eps=1e-12) == pytest.approx(1.0, rel=1e-6)
    # Per-channel average: only channel 0 wrong -> a third of the full value.
    y = r.copy()
    y[..., 0] *= 2
    per_ch = np.mean(r64[..., 0] ** 2 / (r64[..., 0] ** 2 + 1e-2))
    assert metrics.relmse(y, r) == pytest.approx(per_ch / 3, rel=1e-9)


# -- ssim / flip -----------------------------------------------------------------------------


def test_ssim_identity_and_noise():
    r = _rand((32, 32, 3), seed=6, hi=0.8)
    assert metrics.ssim(r, r) == pytest.approx(1.0, abs=1e-12)
    rng = np.random.default_rng(7)
    small = metrics.ssim(r + rng.normal(0, 0.02, r.shape), r)
    big = metrics.ssim(r + rng.normal(0, 0.2, r.shape), r)
    assert 1.0 > small > big


def test_ssim_small_image_and_too_small():
    r = _rand((5, 6, 3), seed=8)
    assert metrics.ssim(r, r) == pytest.approx(1.0)
    with pytest.raises(GlossrtError, match="3x3"):
        metrics.ssim(_rand((2, 8, 3)), _rand((2, 8, 3)))


def test_flip_identity_and_noise():
    r = _rand((32, 32, 3), seed=9, hi=2.0)
    assert metrics.flip(r, r) == 0.0
    rng = np.random.default_rng(10)
    small = metrics.flip(np.abs(r + rng.normal(0, 0.05, r.shape)), r)
    big = metrics.flip(np.abs(r + rng.normal(0, 0.5, r.shape)), r)
    assert 0.0 < small < big <= 1.0


def test_flip_black_reference_does_not_abort():
    # FLIP itself exits the process for an all-black reference; metrics.flip must not.
    black = np.zeros((16, 16, 3), np.float32)
    assert metrics.flip(black, black) == 0.0
    assert metrics.flip(_rand((16, 16, 3), seed=11), black) > 0.1


# -- temporal error / luminance ---------------------------------------------------------------


def test_temporal_error_constant_and_alternating():
    a = _rand((8, 8, 3), seed=12)
    assert metrics.temporal_error([a, a, a, a]) == 0.0
    # Alternating grey levels 0.2 / 0.5: every step changes luminance by exactly 0.3.
    g1 = np.full((8, 8, 3), 0.2, np.float32)
    g2 = np.full((8, 8, 3), 0.5, np.float32)
    assert metrics.temporal_error([g1, g2, g1, g2, g1]) == pytest.approx(0.3, rel=1e-6)
    # One step only in the red channel: luminance weight 0.2126.
    b = a.copy()
    b[..., 0] += 1.0
    assert metrics.temporal_error([a, b]) == pytest.approx(0.2126, rel=1e-6)
    # Steps 0.3 then 0 -> mean 0.15.
    assert metrics.temporal_error([g1, g2, g2]) == pytest.approx(0.15, rel=1e-6)


def test_temporal_error_needs_two_frames_of_one_size():
    with pytest.raises(GlossrtError, match="at least 2"):
        metrics.temporal_error([_rand()])
    with pytest.raises(GlossrtError, match="size"):
        metrics.temporal_error([_rand((4, 4, 3)), _rand((4, 5, 3))])


def test_luminance_numpy_and_tensor():
    img = np.zeros((2, 3, 3), np.float32)
    img[..., 0], img[..., 1], img[..., 2] = 1.0, 2.0, 4.0
    expected = 0.2126 + 0.7152 * 2 + 0.0722 * 4
    lum = metrics.luminance(img)
    assert isinstance(lum, np.ndarray) and lum.shape == (2, 3)
    assert np.allclose(lum, expected)
    lt = metrics.luminance(mi.TensorXf(img))
    assert isinstance(lt, mi.TensorXf) and tuple(lt.shape) == (2, 3)
    assert np.allclose(lt.numpy(), expected, rtol=1e-6)


# -- input checks ------------------------------------------------------------------------------


@pytest.mark.parametrize("fn", [metrics.rmse, metrics.relmse, metrics.ssim, metrics.flip])
def test_size_mismatch_names_both_shapes(fn):
    with pytest.raises(GlossrtError) as e:
        fn(_rand((8, 8, 3)), _rand((8, 9, 3)))
    assert "(8, 8, 3)" in str(e.value) and "(8, 9, 3)" in str(e.value)


@pytest.mark.parametrize("fn", [metrics.rmse, metrics.relmse, metrics.ssim, metrics.flip])
def test_nonfinite_inputs_are_reported_with_count(fn):
    x, r = _rand((8, 8, 3), seed=1), _rand((8, 8, 3), seed=2)
    x[0, 0, 0] = np.nan
    x[1, 1, 1] = np.inf
    with pytest.raises(GlossrtError, match=r"2 NaN/Inf"):
        fn(x, r)
    r[2, 2, 2] = -np.inf
    with pytest.raises(GlossrtError, match=r"reference contains 1 NaN/Inf"):
        fn(_rand((8, 8, 3)), r)


def test_bad_dimensions():
    with pytest.raises(GlossrtError, match="shape"):
        metrics.rmse(np.zeros((2, 2, 2, 2)), np.zeros((2, 2, 2, 2)))


# -- compare_dirs / format_table (fake frame loader) -----------------------------------------


class FakeFrame:
    def __init__(self, path: Path, index: int, img: np.ndarray, channel: str = "color"):
        self.source, self.index, self.meta, self._img = path, index, {}, img
        self._channel = channel

    def numpy(self, name: str) -> np.ndarray:
        assert name == self._channel
        return self._img


def _fake_dirs(monkeypatch, tmp_path):
    out, ref = tmp_path / "out", tmp_path / "ref"
    base = _rand((16, 16, 3), seed=20)
    frames = {
        out: [FakeFrame(out / f"frame_{i:04d}.exr", i, base + 0.01 * i) for i in range(5)],
        ref: [FakeFrame(ref / f"frame_{i:04d}.exr", i, base) for i in (0, 2, 4)],
    }

    def load(directory, channel):
        assert channel == "color"
        return frames[Path(directory)]

    monkeypatch.setattr(compare, "_load_sequence", load)
    return out, ref, base, frames


def test_compare_dirs_matches_sparse_references(monkeypatch, tmp_path):
    out, ref, base, _ = _fake_dirs(monkeypatch, tmp_path)
    res = compare.compare_dirs(out, ref)
    assert [f["file"] for f in res["frames"]] == [
        "frame_0000.exr",
        "frame_0002.exr",
        "frame_0004.exr",
    ]
    assert res["unmatched"] == 2
    assert [f["rmse"] for f in res["frames"]] == pytest.approx([0.0, 0.02, 0.04], abs=1e-6)
    assert res["mean"]["rmse"] == pytest.approx(0.02, abs=1e-6)
    assert res["frames"][0]["ssim"] == pytest.approx(1.0) and res["frames"][0]["flip"] == 0.0
    # All 5 output frames step by 0.01 in every channel -> luminance step 0.01.
    assert res["temporal_error"] == pytest.approx(0.01, rel=1e-4)
    json.dumps(res)  # serialisable for --json
    table = compare.format_table(res)
    assert "frame_0002.exr" in table and "mean (3 frames)" in table
    assert "temporal error" in table and "rmse" in table.splitlines()[0]


def test_compare_dirs_metric_subset_and_errors(monkeypatch, tmp_path):
    out, ref, _, frames = _fake_dirs(monkeypatch, tmp_path)
    res = compare.compare_dirs(out, ref, metrics=("rmse",))
    assert set(res["mean"]) == {"rmse"} and "flip" not in res["frames"][0]
    with pytest.raises(GlossrtError, match="unknown metric"):
        compare.compare_dirs(out, ref, metrics=("psnr",))
    for f in frames[ref]:
        f.source = f.source.with_name("other_" + f.source.name)
    with pytest.raises(GlossrtError) as e:
        compare.compare_dirs(out, ref)
    assert str(out) in str(e.value) and str(ref) in str(e.value)


def test_compare_dirs_with_real_exr_frames(tmp_path):
    frame = pytest.importorskip("glossrt.frame")
    out, ref = tmp_path / "out", tmp_path / "ref"
    out.mkdir()
    ref.mkdir()
    base = _rand((16, 16, 3), seed=30)
    for i in range(4):
        f = frame.Frame(channels={"color": mi.TensorXf(base + 0.01 * i)}, index=i)
        f.save(out / frame.frame_filename(i))
    for i in (0, 2):
        f = frame.Frame(channels={"color": mi.TensorXf(base)}, index=i)
        f.save(ref / frame.frame_filename(i))
    res = compare.compare_dirs(out, ref, metrics=("rmse", "flip"))
    assert [r["file"] for r in res["frames"]] == ["frame_0000.exr", "frame_0002.exr"]
    assert [r["rmse"] for r in res["frames"]] == pytest.approx([0.0, 0.02], abs=1e-6)
    assert res["temporal_error"] == pytest.approx(0.01, rel=1e-4)
    assert res["unmatched"] == 2


def test_compare_dirs_depth_background(monkeypatch, tmp_path):
    """docs/FORMATS.md: depth is +inf on background. Background in both frames scores as
    equal (it made every depth comparison fail with "NaN/Inf"); background in one frame only
    is counted per frame and scored against 0; a NaN is still refused."""
    out, ref = tmp_path / "out", tmp_path / "ref"
    depth = 1.0 + _rand((8, 8, 1), seed=40)
    depth[:3] = np.inf  # background: the top three rows
    moved = depth + 0.5
    moved[3, :2] = np.inf  # two pixels more of background in the output
    frames = {d: [FakeFrame(d / f"frame_{i:04d}.exr", i, img, "depth")
                  for i, img in enumerate(imgs)]
              for d, imgs in ((out, (depth.copy(), moved)), (ref, (depth, depth)))}
    monkeypatch.setattr(compare, "_load_sequence", lambda d, channel: frames[Path(d)])
    res = compare.compare_dirs(out, ref, channel="depth", metrics=("rmse",))
    assert [r["background_mismatch"] for r in res["frames"]] == [0, 2]
    assert res["frames"][0]["rmse"] == 0.0
    # independent: the squared error of the 38 pixels hit in both (0.5 each) and of the two
    # pixels hit only in the reference (their depth against 0), over all 64 pixels
    diff = np.where(np.isinf(moved), 0.0, moved) - np.where(np.isinf(depth), 0.0, depth)
    assert np.count_nonzero(diff) == 40
    assert res["frames"][1]["rmse"] == pytest.approx(
        math.sqrt((38 * 0.25 + float(np.sum(depth[3, :2] ** 2))) / 64), rel=1e-6)
    assert res["temporal_error"] > 0 and math.isfinite(res["temporal_error"])
    assert "background_mismatch" in compare.format_table(res).splitlines()[0]
    moved[5, 5] = np.nan
    with pytest.raises(GlossrtError, match="frame_0001.exr.*NaN"):
        compare.compare_dirs(out, ref, channel="depth", metrics=("rmse",))
