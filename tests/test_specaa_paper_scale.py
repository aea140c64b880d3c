"""``glossrt experiment --which specaa --scale paper`` (issue 28): Gaussian-filtered references
with seeded (jittered) strata, error bars across seeds, frames beyond the quick run's 16.

Independent checks: the seeded offsets against NumPy moments and the normal CDF
(``math.erf``); the experiment's per-frame RMSE against NumPy on :func:`glossrt.specaa.reference`
and :func:`glossrt.specaa.shade` called directly; flicker against NumPy's formula."""

from __future__ import annotations

import json
import math
from argparse import Namespace

import numpy as np
import pytest

from glossrt import specaa
from glossrt.errors import GlossrtError
from glossrt.experiments import specaa as se

TINY = (32, 18)


def test_seeded_offsets_jitter_each_stratum_and_sample_the_gaussian_filter():
    # no seed: the strata's centres, as before
    np.testing.assert_array_equal(specaa.subpixel_offsets(16, "gaussian", None),
                                  specaa.subpixel_offsets(16, "gaussian"))
    a, b = (specaa.subpixel_offsets(16, "gaussian", s) for s in (3, 4))
    np.testing.assert_array_equal(a, specaa.subpixel_offsets(16, "gaussian", 3))
    assert not np.allclose(a, b)
    # box: one position in each of the 4 x 4 strata of the pixel (row-major)
    box = specaa.subpixel_offsets(16, "box", 7)
    cells = np.floor((box + 0.5) * 4).astype(int)
    np.testing.assert_array_equal(cells[:, 0], np.tile(np.arange(4), 4))
    np.testing.assert_array_equal(cells[:, 1], np.repeat(np.arange(4), 4))
    # Gaussian (Tokuyoshi eq. 1, variance 0.25 px^2, truncated at 2 px): the normal CDF of
    # each coordinate falls in its stratum's probability interval, and over many seeds the
    # moments are the filter's (the 4-sigma truncation takes 0.1% of the variance)
    cdf = np.vectorize(lambda x: 0.5 * (1 + math.erf(x / (0.5 * math.sqrt(2)))))
    lo = cdf(-2.0)
    u = (cdf(a) - lo) / (1 - 2 * lo)
    ix, iy = np.tile(np.arange(4), 4), np.repeat(np.arange(4), 4)
    assert np.all((u[:, 0] >= ix / 4 - 1e-9) & (u[:, 0] < (ix + 1) / 4 + 1e-9))
    assert np.all((u[:, 1] >= iy / 4 - 1e-9) & (u[:, 1] < (iy + 1) / 4 + 1e-9))
    o = np.concatenate([specaa.subpixel_offsets(16, "gaussian", s) for s in range(400)])
    assert np.abs(o).max() < 2.0
    np.testing.assert_allclose(o.mean(axis=0), 0.0, atol=0.01)
    np.testing.assert_allclose(o.var(axis=0), 0.25 * 0.9989, rtol=0.02)


def test_error_bars_vanish_for_equal_seeds_and_not_otherwise():
    kw = dict(size=TINY, spp=4, frames=3, ref_every=1, methods=("none", "projected"))
    same = se.evaluate_paper(seeds=(5, 5), **kw)
    diff = se.evaluate_paper(seeds=(5, 6), **kw)
    for r in same.rows:
        assert r["rmse_std"] == 0.0 and r["flicker_std"] == 0.0
        assert r["rmse_seeds"][0] == r["rmse_seeds"][1]
        # the pooled reference of equal seeds is each seed's reference
        assert r["rmse_pooled"] == pytest.approx(r["rmse"], rel=1e-6)
    for r in diff.rows:
        assert r["rmse_std"] > 0.0 and r["flicker_std"] > 0.0
    # the seeds change the references only: the methods' own change is the same
    for a, b in zip(same.rows, diff.rows, strict=True):
        assert a["temporal"] == b["temporal"]


def test_paper_rows_against_numpy_on_the_library_reference():
    # RMSE and flicker of the experiment against NumPy on specaa.reference / specaa.shade
    from glossrt import render, scenes
    from glossrt.lights.analytic import analytic_lights
    from glossrt.lights.scene import polygon_lights
    from glossrt.lights.shading import fresnel_image

    res = se.evaluate_paper(size=TINY, spp=4, frames=2, seeds=(1, 2), ref_every=1,
                            methods=("none", "avgnormal-eig"), flip_per_seed=True)
    assert res.ref_frames == [0, 1]
    setup = scenes.load("normal-mapped", size=TINY)
    rend = render.Renderer(setup)

    def f0_of(fr):
        return fresnel_image(setup, fr)

    imgs, refs = {}, {}
    for t in (0, 1):
        lt, pl = analytic_lights(setup, t), polygon_lights(setup, t)
        g = rend.render(t)
        for m in ("none", "avgnormal-eig"):
            imgs[m, t] = np.asarray(specaa.shade(g, lt, pl, m, f0_of(g)), np.float64)
        for s in (1, 2):
            refs[s, t] = specaa.reference(rend, t, lt, pl, f0_of=f0_of, spp=4,
                                          pixel_filter="gaussian", seed=s).astype(np.float64)
    w = np.array([0.2126, 0.7152, 0.0722])
    for i, s in enumerate((1, 2)):
        for t in (0, 1):
            want = np.sqrt(np.mean((imgs["none", t] - refs[s, t]) ** 2))
            assert res.curves["none"][i][t] == pytest.approx(want, rel=1e-4)
        d = [(imgs["none", t] - refs[s, t]) @ w for t in (0, 1)]
        row = res.rows[0]
        assert row["flicker_seeds"][i] == pytest.approx(np.mean(np.abs(d[1] - d[0])),
                                                        rel=1e-4)
    rows = {r["method"]: r for r in res.rows}
    assert rows["avgnormal-eig"]["rmse"] < rows["none"]["rmse"]
    assert 0 < rows["none"]["flip_pooled"] <= 1 and len(rows["none"]["flip_seeds"]) == 2


def _args(**kw) -> Namespace:
    base = dict(scale="paper", size="32x18", spp=4, frames=4, ref_every=1,
                explicit={"size", "spp", "frames"}, cluster=None)
    base.update(kw)
    return Namespace(**base)


def test_paper_run_writes_table_json_and_plot(tmp_path, capsys):
    from glossrt.cli import main

    rc = main(["experiment", "--which", "specaa", "--scale", "paper", "--size", "32x18",
               "--spp", "4", "--frames", "4", "--ref-every", "1", "--out", str(tmp_path)])
    assert rc == 0
    md = (tmp_path / "specaa-paper.md").read_text()
    data = json.loads((tmp_path / "specaa-paper.json").read_text())
    assert (tmp_path / "specaa-paper-rmse.png").stat().st_size > 0
    assert (tmp_path / "specaa-paper.png").stat().st_size > 0
    assert data["size"] == [32, 18] and data["frames"] == 4 and data["spp_per_seed"] == 4
    assert data["seeds"] == list(se.PAPER_SEEDS) and data["pixel_filter"] == "gaussian"
    names = [r["method"] for r in data["rows"]]
    assert "projected" in names and f"avgnormal-eig:kappa={se.KAPPA}" in names
    assert names == list(specaa.METHODS + se.EXTRA)
    for r in data["rows"]:
        assert r["method"] in md and r["rmse_std"] > 0
        assert len(data["curves"][r["method"]]["rmse_per_seed"]) == len(se.PAPER_SEEDS)
    assert "± " in md


def test_paper_scale_accepts_more_than_16_frames(tmp_path, capsys):
    res = se.run_experiment(tmp_path, (32, 18), _args(frames=18, ref_every=16))
    assert res == 0
    data = json.loads((tmp_path / "specaa-paper.json").read_text())
    assert data["frames"] == 18
    assert data["ref_frames"] == [0, 1, 16, 17]


def test_paper_defaults_and_bad_input(tmp_path):
    assert se.referenced_frames(60, 10) == [0, 1, 10, 11, 20, 21, 30, 31, 40, 41, 50, 51]
    assert se.referenced_frames(5, 1) == [0, 1, 2, 3, 4]
    assert se.PAPER_SIZE == (1280, 720) and se.PAPER_FRAMES == 60
    with pytest.raises(GlossrtError, match="square"):
        se.run_experiment(tmp_path, (32, 18), _args(spp=5))
    with pytest.raises(GlossrtError, match="at least 2 frames"):
        se.run_experiment(tmp_path, (32, 18), _args(frames=1))
    assert list(tmp_path.iterdir()) == []
