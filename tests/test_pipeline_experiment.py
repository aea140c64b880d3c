"""glossrt experiment --which pipeline (issue 25's evidence), the report's pipeline section and
the ``pipeline`` benchmark case, on tiny images."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest

from glossrt.errors import GlossrtError
from glossrt.experiments import pipeline as ep

TINY = (32, 24)
COARSE = {"bspvt_resolution": 8}  # coarse visibility maps: BSPVT's trees build in a second
#: the grid test's scenes: a moving occluder (BSPVT's lights fall back with motion) and the
#: interaction scene; the whole grid (every scene) is what `glossrt experiment --which
#: pipeline` runs
GRID_SCENES = ("glossy-cornell", "polygon-light")


@pytest.fixture(scope="module")
def results():
    return ep.evaluate(size=TINY, spp=8, frames=2, scenes=GRID_SCENES, choices=COARSE)


def test_every_pair_has_a_row_or_a_reason(results, tmp_path):
    for scene in GRID_SCENES:
        for motion in (True, False):
            for label in ep.PRESETS + (ep.FLOOR, ep.REFERENCE):
                row = results.row(scene, label, motion)
                assert row is not None, (scene, label, motion)
                if row.get("skipped"):
                    assert len(row["skipped"]) > 20  # the pipeline's stated reason
                else:
                    assert all(np.isfinite(row[k]) for k in ("rmse", "flip", "temporal"))
    # glossy-cornell's sphere moves (with motion) and is no mesh, and its light is mounted
    # under the ceiling: okuno-iwasaki falls back (the ratio estimator for the light, the path
    # tracer for the sphere) and is measured like every preset; polygon-light runs BSPVT
    for scene in GRID_SCENES:
        for motion in (True, False):
            assert not results.row(scene, "okuno-iwasaki", motion).get("skipped")
    for label in ep.VARIANTS:
        assert results.row(ep.INTERACTION_SCENE, label, True) is not None
    assert len(results.interactions()) == len(ep.VARIANTS)
    md = results.markdown()
    for scene in GRID_SCENES:
        for label in ep.PRESETS:
            assert f"| {scene} | {label}" in md
    data = json.loads(json.dumps(results.as_dict(), default=float))
    assert len(data["rows"]) == len(results.rows)
    assert results.montage(tmp_path / "m.png", "polygon-light").stat().st_size > 1000


def test_reference_is_zero_and_the_floor_is_not(results):
    for scene in GRID_SCENES:
        for motion in (True, False):
            ref = results.row(scene, ep.REFERENCE, motion)
            assert ref["rmse"] == 0 and ref["flip"] == 0 and ref["temporal"] == 0
            floor = results.row(scene, ep.FLOOR, motion)
            assert floor["rmse"] > 0 and floor["flip"] > 0 and floor["temporal"] > 0


def test_flicker_against_numpy():
    rng = np.random.default_rng(3)
    frames = [rng.uniform(0, 1, (4, 5, 3)) for _ in range(3)]
    refs = [rng.uniform(0, 1, (4, 5, 3)) for _ in range(3)]
    w = np.array([0.2126, 0.7152, 0.0722])
    d = [f @ w - r @ w for f, r in zip(frames, refs, strict=True)]
    want = np.mean([np.mean(np.abs(d[1] - d[0])), np.mean(np.abs(d[2] - d[1]))])
    assert ep.flicker(frames, refs) == pytest.approx(want, rel=1e-6)
    # a constant reference: flicker is Schied et al.'s temporal error of the sequence
    from glossrt import metrics

    assert ep.flicker(frames, [refs[0]] * 3) == pytest.approx(metrics.temporal_error(frames))


def test_experiment_cli_writes_table_and_json(tmp_path, monkeypatch):
    calls = {}
    real = ep.evaluate

    def small(**kw):  # the CLI's run, restricted to one scene and two presets
        calls.update(kw)
        calls["res"] = real(**{**kw, "scenes": ("polygon-light",),
                               "presets": ("schied2017", "full"), "choices": COARSE,
                               "static": False})
        return calls["res"]

    monkeypatch.setattr(ep, "evaluate", small)
    args = SimpleNamespace(spp=4, frames=2)
    assert ep.run_experiment(tmp_path, TINY, args) == 0
    md = (tmp_path / "pipeline.md").read_text()
    assert "| polygon-light | full (ltc+bspvt)" in md and "1 spp input" in md
    data = json.loads((tmp_path / "pipeline.json").read_text())
    assert {r["label"] for r in data["rows"]} >= {"schied2017", "full", ep.FLOOR}
    assert (tmp_path / "pipeline_polygon-light.png").is_file()
    assert calls["spp"] == 4 and calls["frames"] == 2
    # with 2 frames only frame 1 is scored: the rows against NumPy on the kept images
    res = calls["res"]
    imgs = res.images["polygon-light"]
    for label in (ep.FLOOR, "full"):
        want = float(np.sqrt(np.mean((imgs[label].astype(np.float64)
                                      - imgs[ep.REFERENCE]) ** 2)))
        assert res.row("polygon-light", label, True)["rmse"] == pytest.approx(want, rel=1e-5)
        assert want > 0


@pytest.mark.parametrize("kw, match", [
    ({"frames": 1}, "frames must be >= 2"),
    ({"spp": 0}, "spp must be >= 1"),
    ({"presets": ("nope",)}, "unknown preset"),
    ({"presets": ("reference",)}, "unknown preset"),
    ({"scenes": ("no-such-scene",)}, "unknown scene"),
])
def test_bad_arguments_refused(kw, match):
    with pytest.raises(GlossrtError, match=match):
        ep.evaluate(size=TINY, **{"spp": 4, "frames": 2, **kw})


def test_demo_section_renders(tmp_path):
    from glossrt.report import DemoContext, Report

    class _F:  # the section reads only the demo's frame width
        width, height = 32, 24

    ctx = DemoContext(out_dir=tmp_path, scene="glossy-cornell", frames=[_F()])
    rep = Report(tmp_path, "t")
    ep.section_pipeline(ctx, rep)
    page = rep.write()
    html = page.read_text()
    assert "Frame pipeline" in html and "schied2017" in html
    assert list((tmp_path / "img").glob("pipeline_montage*.png"))


def test_bench_case_keys():
    from glossrt import bench
    from glossrt.report.registry import BENCHMARKS, BenchContext, registered_benchmarks

    assert "pipeline" in registered_benchmarks()
    quick = {"pipeline_choices": COARSE, "pipeline_shrink": 10, "pipeline_memory": False}
    bench.check_args(names=["pipeline"], options=quick)
    ctx = BenchContext(size=TINY, warmup=1, repeats=1, min_sample=0.0, extra=quick)
    out = BENCHMARKS["pipeline"](ctx)
    # the cases side by side, at 1/10 of their sizes
    assert set(out["cases"]) == {"full/polygon-light@32x18", "full/polygon-light@64x36",
                                 "schied2017/glossy-cornell@32x18"}
    assert out["shrink"] == 10 and out["memory"] == {}
    for c in out["cases"].values():
        for k in ("frame_ms", "fps", "fps_untimed", "timing_cost_ms", "stage_ms_alone",
                  "sum_alone_ms", "stage_ms_in_frame",
                  "stage_host_ms_in_frame", "ratio_frame_vs_sum", "target_ratio",
                  "target_fps", "direct", "size"):
            assert k in c, k
        assert set(c["stage_ms_alone"]) >= {"gbuffer", "direct", "indirect", "composite",
                                            "taa"}
        assert set(c["stage_ms_in_frame"]) == set(c["stage_ms_alone"])
        assert c["frame_ms"] > 0 and c["sum_alone_ms"] > 0
        assert c["fps"] == pytest.approx(1000 / c["frame_ms"])
        assert c["target_fps"] is None  # (the targets are for the sizes)
        assert c["recordings_added"] == 0  # the timed frames replayed
    md = ep.timing_markdown(out)
    assert "| full / polygon-light (static copy) | 64x36 |" in md


def test_memory_probe_in_a_fresh_process():
    m = ep.memory_in_subprocess("schied2017", "glossy-cornell", (32, 18), warmup=2, frames=1)
    assert m["size"] == [32, 18] and m["frames"] == 1
    # Dr.Jit's peak holds at least the frame's own channels (float32, ~25 of them)
    assert m["jit_peak_mb"] > 25 * 32 * 18 * 4 / 2**20
    if m["rss_peak_mb"] is not None:  # Linux
        assert m["rss_peak_mb"] >= m["rss_before_mb"] > m["jit_peak_mb"]
    md = ep.timing_markdown({"cases": {}, "memory": {"x": m}})
    assert "| schied2017 / glossy-cornell (static copy) | 32x18 |" in md


@pytest.mark.parametrize("options, match", [
    (["pipeline_shrink=3"], "pipeline_shrink must be one of 1, 2, 5, 10"),
    (["pipeline_memory=maybe"], "pipeline_memory must be true or false"),
    (["pipeline_colour=1"], "unknown case option"),
    (["pipeline_choices={\"directt\": 1}"], "directt"),
    (["pipeline_shrink"], "KEY=VALUE"),
])
def test_bench_case_options_refused_before_any_work(options, match, capsys):
    from glossrt import bench
    from glossrt.cli import main

    with pytest.raises(GlossrtError, match=match):
        bench.parse_case_options(options)
    argv = ["bench", "--only", "pipeline"]
    for o in options:
        argv += ["--case-option", o]
    assert main(argv) != 0
    assert "bench pipeline ..." not in capsys.readouterr().err


def test_paper_scale_references_the_last_frames_of_its_three_scenes(tmp_path, monkeypatch):
    """``--scale paper`` (issue 28, SVGF's Table 1 / figs. 10-12): its three scenes, the last
    PAPER_REF_FRAMES frames referenced (and kept under OUT/references), TAA and the other
    reconstructions inside the pipeline on every scene; RMSE and SSIM checked against NumPy
    and scikit-image on the kept images."""
    from glossrt.render import blocks

    asked: list[tuple[str, list[int]]] = []
    real_refs, real_eval = blocks.references, ep.evaluate

    def refs(rend, job, frames, spp, cluster=None, desc="", cache=None):
        asked.append((job["scene"], job["max_depth"], list(frames), cache))
        return real_refs(rend, job, frames, spp, cluster, desc=desc, cache=cache)

    def small(**kw):  # the paper's run on tiny images, one preset and one variant
        calls.update(kw)
        calls["res"] = real_eval(**{**kw, "presets": ("schied2017",), "choices": COARSE,
                                    "variants": {"schied2017, taa off": ("schied2017",
                                                                         {"taa": False})}})
        return calls["res"]

    calls: dict = {}
    monkeypatch.setattr(blocks, "references", refs)
    monkeypatch.setattr(ep, "evaluate", small)
    args = SimpleNamespace(spp=4, frames=5, scale="paper", explicit={"size", "spp", "frames"})
    assert ep.run_experiment(tmp_path, TINY, args) == 0
    assert calls["scenes"] == ep.PAPER_SCENES and calls["static"] is False
    assert calls["variants"] == ep.PAPER_VARIANTS and calls["ref_frames"] == ep.PAPER_REF_FRAMES
    # every scene: one request for frames 2, 3, 4 (the last three of five), direct-only
    # scene at Mitsuba's max_depth 2, kept in OUT/references
    assert [(s, d, f) for s, d, f, _ in asked] == [
        ("glossy-cornell", None, [2, 3, 4]), ("polygon-light", 2, [2, 3, 4]),
        ("light-shapes", None, [2, 3, 4])]
    assert all(c == tmp_path / "references" for *_, c in asked)
    assert len(list((tmp_path / "references").rglob("*.exr"))) == 9
    md = (tmp_path / "pipeline.md").read_text()
    assert "| SSIM |" in md and "RMSE static" not in md and "last 3 of 5 frames" in md
    assert "| polygon-light@direct | schied2017, taa off (pathtraced)" in md
    assert (tmp_path / "pipeline_polygon-light-direct-only.png").is_file()
    res = calls["res"]
    assert res.first == 2 and res.referenced() == [2, 3, 4]
    for scene in ep.PAPER_SCENES:
        assert set(res.images[scene]) >= {ep.FLOOR, ep.REFERENCE, "schied2017"}
        row = res.row(scene, "schied2017", True)
        assert 0 < row["rmse"] and 0 < row["ssim"] < 1 and row["temporal"] > 0
        assert res.row(scene, ep.REFERENCE, True)["ssim"] == 1.0
        assert res.row(scene, "schied2017, taa off", True)["rmse"] > 0
    # a rerun reads the kept references back: no reference is rendered again
    monkeypatch.setattr(blocks.Renderer, "render_reference",
                        lambda *a, **k: pytest.fail("reference rendered again"))
    assert ep.run_experiment(tmp_path, TINY, args) == 0


def test_sparse_scores_against_numpy_and_skimage():
    """The paper-scale scoring: frames without a reference (None) are skipped; RMSE and SSIM
    are means over the scored frames (NumPy, scikit-image), the temporal error starts at the
    first referenced frame."""
    from skimage.metrics import structural_similarity

    rng = np.random.default_rng(5)
    colours = [rng.uniform(0, 1, (16, 20, 3)) for _ in range(5)]
    refs = [None, None] + [np.clip(c + rng.normal(0, 0.1, c.shape), 0, 1)
                           for c in colours[2:]]
    got = ep._score(colours, refs, 2)
    want_rmse = np.mean([np.sqrt(np.mean((colours[t] - refs[t]) ** 2)) for t in (2, 3, 4)])
    assert got["rmse"] == pytest.approx(want_rmse, rel=1e-6)
    def srgb(x):  # the sRGB transfer function (IEC 61966-2-1)
        return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)

    want_ssim = np.mean([structural_similarity(srgb(colours[t]), srgb(refs[t]),
                                               channel_axis=2, data_range=1.0)
                         for t in (2, 3, 4)])
    assert got["ssim"] == pytest.approx(want_ssim, rel=1e-4)
    assert got["temporal"] == pytest.approx(ep.flicker(colours[2:], refs[2:]))


def test_direct_only_reference_is_mitsubas_direct_integrator():
    """``NAME@direct`` renders direct light only: its reference matches Mitsuba's own
    ``direct`` integrator on the same frame (an independent estimator: light and BSDF
    sampling with MIS), and is darker than the full-depth reference.

    Compared away from the visible light: glossrt's references trace pixel centres, Mitsuba
    box-filters each pixel, which differs at the light's silhouette (12% of the image mean
    at 48x36, all of it there). Elsewhere on glossy-cornell the two agree within 0.1% at 256
    spp (two seeds), and the full-depth reference is 30% brighter. (On polygon-light the gap
    off the light is 1.6% at 48x36, 0.9% at 96x72, 0.3% at 192x144: edges of its glossy
    highlights, shrinking with the pixel size, not a shading difference.)"""
    from scipy.ndimage import maximum_filter

    from glossrt import render
    from glossrt import scenes as scn

    name, depth = ep.scene_case("glossy-cornell" + ep.DIRECT_ONLY)
    assert (name, depth) == ("glossy-cornell", 2)
    assert ep.scene_case("light-shapes") == ("light-shapes", None)
    setup = scn.load(name, size=(48, 36), frames=3)
    direct = render.Renderer(setup, max_depth=depth)
    ours = direct.render_reference(2, spp=256).numpy("color").astype(np.float64)
    mitsuba = np.array(direct.render_mitsuba(2, spp=256, integrator="direct"))[..., :3]
    far = maximum_filter(np.maximum(ours.max(-1), mitsuba.max(-1)), size=3) < 1.0
    assert far.mean() > 0.9
    assert ours[far].mean() == pytest.approx(mitsuba[far].mean(), rel=0.01)
    full = render.Renderer(setup).render_reference(2, spp=64).numpy("color")
    assert full[far].mean() > 1.2 * ours[far].mean()


@pytest.mark.parametrize("kw, match", [
    ({"ref_frames": 1, "frames": 4}, "at least 2 and fewer than --frames"),
    ({"ref_frames": 4, "frames": 4}, "at least 2 and fewer than --frames"),
    ({"scenes": ("nope" + ep.DIRECT_ONLY,)}, "unknown scene"),
])
def test_paper_arguments_refused(kw, match):
    with pytest.raises(GlossrtError, match=match):
        ep.evaluate(size=TINY, **{"spp": 4, "frames": 2, **kw})


def test_taa_check_scores_both_references(tmp_path, monkeypatch):
    """``glossrt experiment --which taa`` (issue 28): the pipelines with and without TAA and
    the 1 spp input, each scored against glossrt's pixel-centre references and Mitsuba's
    box-filtered ``path`` integrator; each reference against the other (the same RMSE both
    ways). The box references are Mitsuba's render of the same posed frame at the same
    depth, checked on the kept EXR against fresh pixel-centre references, away from the
    visible lights (where the pixel filter changes most): the means agree within 1.5%
    (measured 0.04-0.2%; polygon-light at full depth is 4.8% brighter, its frame 0 4.4%
    dimmer), and 3x3-averaged pixels (less noise) differ less from the same frame than
    from frame 0 (measured about half). Kept references are read back: a rerun renders
    none and scores the same."""
    from scipy.ndimage import maximum_filter, uniform_filter

    from glossrt import scenes as scn
    from glossrt.frame import Frame
    from glossrt.render import Renderer

    res = ep.taa_check(size=(48, 27), spp=64, frames=4, ref_frames=2, cache=tmp_path)
    centre, box = ep.TAA_REFERENCES
    for scene in ep.TAA_SCENES:
        for label in (ep.FLOOR, *ep.TAA_RUNS):
            for ref in ep.TAA_REFERENCES:
                s = res.scores[(scene, label, ref)]
                assert s["rmse"] > 0 and 0 < s["ssim"] < 1 and s["temporal"] > 0
        a = res.scores[(scene, f"{centre} reference", box)]
        b = res.scores[(scene, f"{box} reference", centre)]
        assert a["rmse"] == pytest.approx(b["rmse"], rel=1e-6) and a["rmse"] > 0
        assert (scene, f"{centre} reference", centre) not in res.scores
        assert list(res.images[scene]) == [ep.FLOOR, *ep.TAA_RUNS, f"{centre} reference",
                                           f"{box} reference"]
        stem = f"mitsuba-path-{ep._file_name(scene)}-48x27-64spp-"
        assert sorted(p.name for p in tmp_path.glob(stem + "*.exr")) == [
            stem + "0002.exr", stem + "0003.exr"]
        name, depth = ep.scene_case(scene)
        rend = Renderer(scn.load(name, size=(48, 27), frames=4), max_depth=depth)
        theirs = Frame.load(tmp_path / (stem + "0003.exr")).numpy("color").astype(np.float64)
        same, first = (rend.render_reference(i, 64).numpy("color").astype(np.float64)
                       for i in (3, 0))
        far = maximum_filter(np.maximum(same.max(-1), theirs.max(-1)), size=3) < 1.0
        assert far.mean() > 0.8
        assert theirs[far].mean() == pytest.approx(same[far].mean(), rel=0.015)
        gap_same, gap_first = (np.abs(uniform_filter(theirs - x, size=(3, 3, 1)))[far].mean()
                               for x in (same, first))
        assert gap_same < 0.7 * gap_first
    monkeypatch.setattr(Renderer, "render_reference",
                        lambda *a, **k: pytest.fail("reference rendered again"))
    monkeypatch.setattr(Renderer, "render_mitsuba",
                        lambda *a, **k: pytest.fail("box reference rendered again"))
    again = ep.taa_check(size=(48, 27), spp=64, frames=4, ref_frames=2, cache=tmp_path)
    assert again.scores.keys() == res.scores.keys()
    for k, v in res.scores.items():
        assert again.scores[k]["rmse"] == pytest.approx(v["rmse"], rel=1e-6)


def test_taa_experiment_command(tmp_path, monkeypatch):
    """``--which taa --scale paper`` takes 1280x720, 12 frames (the last 3 referenced) and
    1024 spp where the option was not given, keeps the references in OUT/references, and
    writes taa.md / taa.json."""
    seen: dict = {}

    def spy(**kw):
        seen.update(kw)
        res = ep.TaaResults(kw["size"], kw["spp"], kw["frames"], kw["ref_frames"])
        res.scores[("glossy-cornell", ep.FLOOR, ep.TAA_REFERENCES[1])] = {
            "rmse": 0.5, "ssim": 0.25, "flip": 0.125, "temporal": 0.0625}
        return res

    monkeypatch.setattr(ep, "taa_check", spy)
    args = SimpleNamespace(scale="paper", explicit=set(), spp=1, frames=30)
    assert ep.run_taa(tmp_path, (1, 1), args) == 0
    assert (seen["size"], seen["spp"], seen["frames"], seen["ref_frames"]) == (
        ep.PAPER_SIZE, ep.TAA_PAPER_SPP, ep.PAPER_FRAMES, ep.PAPER_REF_FRAMES)
    assert seen["cache"] == tmp_path / "references"
    md = (tmp_path / "taa.md").read_text()
    assert "| glossy-cornell | 1 spp input | - | 0.5000 | - | 0.250 | - | 0.0625 |" in md
    assert json.loads((tmp_path / "taa.json").read_text())["scores"][0]["rmse"] == 0.5
    quick = SimpleNamespace(scale="quick", explicit={"spp"}, spp=4, frames=6)
    ep.run_taa(tmp_path, (32, 18), quick)
    assert (seen["size"], seen["spp"], seen["frames"], seen["ref_frames"]) == (
        (32, 18), 4, 6, 3)


def test_taa_montage(tmp_path):
    """The taa run's picture: every pipeline and both references of a scene's last frame,
    and each one's distance to the box-filtered reference."""
    rng = np.random.default_rng(2)
    res = ep.TaaResults((20, 12), 4, 4, 2)
    labels = [ep.FLOOR, *ep.TAA_RUNS, *(f"{r} reference" for r in ep.TAA_REFERENCES)]
    res.images["glossy-cornell"] = {k: rng.uniform(0, 1, (12, 20, 3)) for k in labels}
    path = res.montage(tmp_path / "taa.png", "glossy-cornell")
    assert path.stat().st_size > 10_000
