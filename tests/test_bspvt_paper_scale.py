"""Okuno & Iwasaki's Table 1 at the paper's size (issue 28), checked at tiny sizes.

* the built-ins ``teapot-17k`` and ``teapot-100k`` have the vertex counts of their
  tessellation formulas (teapot ``32 n^2 + 4 n + 2``, floor ``(m + 1)^2``, sphere
  ``2 k (k - 1) + 2``), about 17K and past 100K;
* the epsilon sweep: epsilon 0 reconstructs the exact visibility maps (no texel
  misclassified), leaves never grow and the error never shrinks as epsilon grows, and each
  tree misclassifies at most ``epsilon`` texels per leaf (the leaf rule ``e(P) <= epsilon``);
* the sample build and its extrapolation against a full build of the same small mesh (an
  independent path: one visibility pass and one tree build over all vertices): exact when the
  sample is every chunk, close for a random half; the cluster model's arithmetic by hand;
* ``paper_table1`` end to end on the tiny mesh (full row and extrapolated row of the same
  scene agree);
* ``glossrt experiment --scale``: a bad value is one error line before anything is written;
  ``--scale paper`` runs the paper-scale path of ``--which bspvt``.
"""

from __future__ import annotations

import argparse

import numpy as np
import pytest

from glossrt import backend

backend.ensure()

from glossrt import scenes  # noqa: E402
from glossrt.cli import main  # noqa: E402
from glossrt.experiments import bspvt as ex  # noqa: E402
from glossrt.lights.bspvt import build_scene_trees, scene_vertices  # noqa: E402
from glossrt.scenes.library import PAPER_SIZE_DENSITIES, polygon_light_scene  # noqa: E402

TINY = "test-bspvt-paper-tiny"
RES = 8


@pytest.fixture(scope="module")
def tiny():
    """A tiny polygon-light (177 vertices) registered as a built-in, so that chunk items can
    load it by name (in this process: no cluster)."""
    scenes.builtin(TINY, "tiny polygon-light for tests")(
        lambda: polygon_light_scene(0.25, teapot_n=2, floor_n=4, sphere_n=3))
    yield TINY
    scenes.BUILTIN.pop(TINY, None)


@pytest.fixture(scope="module")
def tiny_full(tiny):
    return build_scene_trees(tiny, RES, 0.0, progress=False)


def _formula(t: int, f: int, s: int) -> int:
    return (32 * t * t + 4 * t + 2) + (f + 1) ** 2 + (2 * s * (s - 1) + 2)


@pytest.mark.parametrize("name, lo, hi", [("teapot-17k", 16_500, 17_500),
                                          ("teapot-100k", 100_000, 110_000)])
def test_paper_size_scenes_have_their_vertex_counts(name, lo, hi):
    n = len(scene_vertices(scenes.load(name, size=(16, 12)).scene)[0])
    assert n == _formula(*PAPER_SIZE_DENSITIES[name])
    assert lo <= n <= hi


def test_epsilon_sweep_trades_leaves_for_error(tiny):
    eps = (0, 1, 2, 4, 8, 32)
    rows = ex.epsilon_sweep(tiny, 30, eps, resolution=RES, seed=2)
    assert [r["epsilon"] for r in rows] == [float(e) for e in eps]
    assert rows[0]["misclassified"] == 0.0 and rows[0]["mean_abs_error"] == 0.0
    leaves = [r["leaves_per_vertex"] for r in rows]
    mis = [r["misclassified"] for r in rows]
    assert all(a >= b for a, b in zip(leaves, leaves[1:], strict=False))
    assert all(a <= b for a, b in zip(mis, mis[1:], strict=False))
    assert leaves[-1] < leaves[0] and mis[-1] > 0.0
    texels = 6 * RES * RES
    for r in rows:  # at most epsilon misclassified texels per leaf
        assert r["misclassified"] * texels <= r["epsilon"] * r["leaves_per_vertex"] + 1e-9
    md = ex.epsilon_sweep_markdown(rows, tiny, RES, 2)
    assert sum(ln.startswith("| ") for ln in md.splitlines()) == len(rows) + 1


def test_epsilon_sweep_refuses_bad_epsilons(tiny):
    from glossrt.errors import GlossrtError

    with pytest.raises(GlossrtError, match="epsilons"):
        ex.epsilon_sweep(tiny, 4, (0, -1), resolution=RES)


def test_sample_extrapolation_matches_the_full_build(tiny, tiny_full):
    st = tiny_full.stats()
    whole = ex.sample_build(tiny, 10 ** 6, RES, chunk_vertices=16)
    assert whole["vertices_sampled"] == st["vertices"] == whole["vertices_total"]
    ext = ex.extrapolate_build(whole)
    assert ext["leaves"] == pytest.approx(st["leaves"], abs=1e-6)
    assert ext["data_mb"] == pytest.approx(st["data_mb"], rel=1e-12)
    half = ex.sample_build(tiny, 90, RES, chunk_vertices=10, seed=3)
    assert 80 <= half["vertices_sampled"] < st["vertices"]
    ext = ex.extrapolate_build(half)
    assert ext["leaves_per_vertex"] == pytest.approx(st["leaves_per_vertex"], rel=0.15)
    assert ext["data_mb"] == pytest.approx(st["data_mb"], rel=0.15)


def test_cluster_model_arithmetic():
    s = {"vertices_total": 1000, "seconds_per_vertex": 0.05,
         "max_item_seconds_per_vertex": 0.08, "leaves_per_vertex": 40.0,
         "bytes_per_vertex": 1000.0}
    one = ex.extrapolate_build(s, 1)
    assert one["build_s"] == pytest.approx(50.0)
    assert one["data_mb"] == pytest.approx(1.0) and one["leaves"] == pytest.approx(40_000)
    many = ex.extrapolate_build(s, 10, chunk_vertices=100)
    assert many["build_s"] == pytest.approx(50.0 / 10 + ex.CLUSTER_START_S + 0.08 * 100)


def test_paper_table1_end_to_end_on_a_tiny_mesh(tiny, tiny_full):
    rows = ex.paper_table1(resolution=RES, sample_vertices=90, shade_size=(32, 24),
                           scenes=(tiny, tiny))
    full, est = rows
    assert not full["extrapolated"] and est["extrapolated"]
    assert full["vertices"] == est["vertices"] == tiny_full.vertex_count
    assert full["leaves_per_vertex"] == pytest.approx(tiny_full.stats()["leaves_per_vertex"])
    assert est["leaves_per_vertex"] == pytest.approx(full["leaves_per_vertex"], rel=0.2)
    assert full["shade_ms"] > 0 and est["shade_ms"] is None
    md = ex.paper_table1_markdown(rows, RES, (32, 24))
    assert "not measured" in md and "extrapolated" in md and "105.8" in md


def test_cli_scale_refuses_bad_values_in_one_line(tmp_path, capsys):
    out = tmp_path / "o"
    assert main(["experiment", "--out", str(out), "--which", "bspvt", "--scale", "huge"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("glossrt: error:") and err.count("\n") == 1
    assert "--scale" in err and "huge" in err and "paper" in err
    assert not out.exists()


def test_scale_paper_takes_the_paper_path(tmp_path, monkeypatch):
    seen = []
    monkeypatch.setattr(ex, "run_paper_scale", lambda out, args: seen.append(out) or 0)
    args = argparse.Namespace(scale="paper", resolution=RES, cluster=None)
    assert ex.run_experiment(tmp_path, (16, 12), args) == 0
    assert seen == [tmp_path]
    assert np.isfinite(ex.CLUSTER_START_S)
