"""The command line end to end on tiny images: render, compare, bench, demo, bad input."""

import json
import os

import numpy as np
import pytest

from glossrt.cli import main
from glossrt.frame import Frame, load_sequence


def test_info(capsys):
    assert main(["info"]) == 0
    out = capsys.readouterr().out
    assert "variant" in out and "libllvm" in out and "mitsuba" in out


def test_render_compare_roundtrip(tmp_path, capsys):
    out, ref = tmp_path / "out", tmp_path / "ref"
    assert main(["render", "glossy-cornell", "--out", str(out), "--frames", "3",
                 "--size", "32x24"]) == 0
    files = sorted(os.listdir(out))
    assert files == ["frame_0000.exr", "frame_0001.exr", "frame_0002.exr"]
    frames = load_sequence(out)
    assert frames[1].width == 32 and frames[1].height == 24
    assert frames[1].prev_camera is not None
    # the camera moves, so frame 1 has non-zero motion somewhere
    assert np.abs(frames[1].numpy("motion")).max() > 0.01
    assert main(["render", "glossy-cornell", "--out", str(ref), "--frames", "3", "--every", "2",
                 "--size", "32x24", "--reference", "--spp", "32"]) == 0
    assert sorted(os.listdir(ref)) == ["frame_0000.exr", "frame_0002.exr"]
    assert Frame.load(ref / "frame_0002.exr").meta["spp"] == 32
    capsys.readouterr()
    js = tmp_path / "m.json"
    assert main(["compare", str(out), str(ref), "--json", str(js)]) == 0
    table = capsys.readouterr().out
    assert "frame_0000.exr" in table and "frame_0002.exr" in table
    res = json.loads(js.read_text())
    assert len(res["frames"]) == 2 and res["mean"]["rmse"] > 0


def test_render_mitsuba_reference(tmp_path):
    out = tmp_path / "m"
    assert main(["render", "glossy-cornell", "--out", str(out), "--size", "24x16", "--mitsuba",
                 "--spp", "8"]) == 0
    f = Frame.load(out / "frame_0000.exr")
    assert tuple(f.names) == ("color",) and f.meta["reference"] == "mitsuba-path"


@pytest.mark.parametrize(
    "argv, words",
    [
        (["render", "no-such-scene", "--out", "{tmp}/o"], ["no-such-scene"]),
        (["render", "{tmp}/missing.xml", "--out", "{tmp}/o"], ["not found", "missing.xml"]),
        (["render", "glossy-cornell", "--out", "{tmp}/o", "--size", "0x10"], ["size"]),
        (["render", "glossy-cornell", "--out", "{tmp}/o", "--size", "abc"], ["size", "abc"]),
        (["render", "glossy-cornell", "--out", "{tmp}/file/sub"], ["not writable", "file"]),
        (["render", "glossy-cornell", "--out", "{tmp}/o", "--frames", "0"], ["frames"]),
        (["render", "glossy-cornell", "--out", "{tmp}/o", "--max-depth", "0"], ["max_depth"]),
        (["compare", "{tmp}/nope", "{tmp}"], ["not a folder", "nope"]),
        (["bench", "--only", "nope", "--size", "8x8"], ["unknown benchmark", "nope"]),
        (["render", "glossy-cornell", "--out", "{tmp}/o", "--every", "0"], ["--every"]),
        (["render", "glossy-cornell", "--out", "{tmp}/o", "--start", "-3"], ["--start"]),
        (["render", "glossy-cornell", "--out", "{tmp}/o", "--size", "99999x99999"],
         ["16384"]),
        (["render", "glossy-cornell", "--out", "{tmp}/o", "--orbit", "nan"], ["orbit"]),
        (["render", "{tmp}", "--out", "{tmp}/o"], ["is a folder"]),
        (["render", "glossy-cornell", "--out", "{tmp}/file"], ["exists and is not a folder"]),
        (["render", "glossy-cornell", "--out", ""], ["empty path"]),
        (["experiment", "--out", "{tmp}/o", "--spp", "0"], ["--spp"]),
        (["experiment", "--out", "{tmp}/o", "--frames", "0"], ["--frames"]),
        (["experiment", "--out", "{tmp}/o", "--ref-every", "0"], ["--ref-every"]),
        (["experiment", "--out", "{tmp}/o", "--which", "ltc", "--published", "{tmp}/x.js"],
         ["--published", "x.js"]),
        (["bspvt", "build", "polygon-light", "--out", "{tmp}"], ["is a folder"]),
        (["bspvt", "build", "polygon-light", "--out", ""], ["empty path"]),
        (["compare", "{tmp}", "{tmp}", "--json", "{tmp}"], ["is a folder"]),
        (["bench", "--only", "ltc", "--json", "{tmp}"], ["is a folder"]),
    ],
)
def test_bad_input_is_a_clear_error(tmp_path, capsys, argv, words):
    (tmp_path / "file").write_text("not a folder")
    argv = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("glossrt: error:")
    for w in words:
        assert w in err
    assert not (tmp_path / "o").exists() or not os.listdir(tmp_path / "o")
    assert (tmp_path / "file").read_text() == "not a folder"  # inputs are kept


def _digests(folder) -> dict:
    import hashlib

    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.iterdir()) if p.is_file()}


@pytest.fixture(scope="module")
def tiny_sequence(tmp_path_factory):
    seq = tmp_path_factory.mktemp("seq") / "in"
    assert main(["render", "glossy-cornell", "--out", str(seq), "--frames", "2",
                 "--size", "16x12"]) == 0
    return seq


def test_denoise_refuses_its_input_folder(tiny_sequence, capsys):
    before = _digests(tiny_sequence)
    for out in (str(tiny_sequence), str(tiny_sequence) + "/", ""):
        assert main(["denoise", str(tiny_sequence), "--method", "atrous", "--out", out]) == 2
    err = capsys.readouterr().err
    assert "is the input folder" in err and "empty path" in err
    assert _digests(tiny_sequence) == before


def test_failed_denoise_leaves_the_output_folder_as_it_was(tiny_sequence, tmp_path, capsys,
                                                            monkeypatch):
    """Frames are written to --out only when every frame is done: a denoiser failing on the
    second frame leaves the first run's frames (not a mix) and no temporary folder."""
    from glossrt import denoise
    from glossrt.errors import FrameError

    out = tmp_path / "out"
    assert main(["denoise", str(tiny_sequence), "--method", "atrous", "--out", str(out)]) == 0
    before = _digests(out)
    real = denoise.make

    def failing(method, **kw):
        d, calls = real(method, **kw), []

        def run(frame):
            calls.append(frame)
            if len(calls) == 2:
                raise FrameError(f"{frame.where}: bad frame")
            return d(frame)
        return run

    monkeypatch.setattr(denoise, "make", failing)
    assert main(["denoise", str(tiny_sequence), "--method", "atrous", "--out", str(out)]) == 2
    assert "bad frame" in capsys.readouterr().err
    assert _digests(out) == before
    assert sorted(os.listdir(out)) == sorted(before)  # no hidden leftovers


def test_render_warns_about_frames_of_an_earlier_run(tmp_path, capsys):
    out = tmp_path / "o"
    assert main(["render", "glossy-cornell", "--out", str(out), "--frames", "3",
                 "--size", "16x12"]) == 0
    assert "earlier run" not in capsys.readouterr().err
    assert main(["render", "glossy-cornell", "--out", str(out), "--frames", "2",
                 "--size", "16x12"]) == 0
    err = capsys.readouterr().err
    assert "1 frame(s) from an earlier run" in err and "frame_0002.exr" in err


def test_compare_json_never_overwrites_a_frame(tiny_sequence, tmp_path, capsys):
    before = _digests(tiny_sequence)
    target = tiny_sequence / "frame_0001.exr"
    assert main(["compare", str(tiny_sequence), str(tiny_sequence), "--json",
                 str(target)]) == 2
    assert "refusing to overwrite" in capsys.readouterr().err
    assert _digests(tiny_sequence) == before
    js = tmp_path / "new" / "m.json"  # a missing folder is created
    assert main(["compare", str(tiny_sequence), str(tiny_sequence), "--json", str(js)]) == 0
    assert json.loads(js.read_text())["mean"]["rmse"] == 0.0
    # the metrics written into a compared folder are not an input: a second run rewrites them
    inside = tiny_sequence / "metrics.json"
    try:
        for _ in range(2):
            assert main(["compare", str(tiny_sequence), str(tiny_sequence), "--json",
                         str(inside)]) == 0
            assert json.loads(inside.read_text())["mean"]["rmse"] == 0.0
    finally:
        inside.unlink(missing_ok=True)  # the folder is shared by this module's tests
    # ... while a link named like JSON that points at a frame is still refused
    link = tmp_path / "frame-link.json"
    link.symlink_to(target)
    assert main(["compare", str(tiny_sequence), str(tiny_sequence), "--json", str(link)]) == 2
    assert "refusing to overwrite" in capsys.readouterr().err
    assert _digests(tiny_sequence) == before


def test_unsupported_plugin_exit_code(tmp_path, capsys):
    """A plugin Mitsuba cannot load in the RGB variant: exit 2, one line naming it, nothing
    written."""
    xml = tmp_path / "s.xml"
    xml.write_text('<scene version="3.0.0"><shape type="sphere"><bsdf type="measured_polarized">'
                   '<string name="filename" value="x.pbsdf"/></bsdf></shape></scene>')
    assert main(["render", str(xml), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "measured_polarized" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "o").exists()


def test_bench_json(tmp_path, capsys):
    js = tmp_path / "b.json"
    # the pipeline case at 1/10 of the sizes, without its memory cases
    assert main(["bench", "--json", str(js), "--size", "32x24", "--repeats", "1",
                 "--warmup", "1", "--min-sample", "0",
                 "--case-option", "pipeline_shrink=10", "--case-option", "pipeline_memory=false",
                 "--case-option", 'pipeline_choices={"bspvt_resolution": 8}',
                 "--case-option", "cluster_spp=8", "--case-option", "cluster_bspvt_resolution=4",
                 "--case-option", "cluster_workers=[2]"]) == 0
    res = json.loads(js.read_text())
    c = res["results"]["cluster"]["runs"]["2"]
    assert c["per_task_ms"] > 0 and c["reference_s"] > 0 and c["bspvt_build_s"] > 0
    assert res["case_options"]["pipeline_shrink"] == 10
    assert "full/polygon-light@64x36" in res["results"]["pipeline"]["cases"]
    r = res["results"]["render-vs-mitsuba-path"]
    assert res["variant"] and res["device"]
    assert r["glossrt_frame_s"] > 0 and r["mitsuba_path_1spp_s"] > 0
    assert r["ratio_frame_vs_path"] > 0 and r["repeats"] >= 3
    d = res["results"]["denoisers"]
    # cost_vs_atrous: the median over repeats of each method's time over atrous' time in the
    # same repeat, recomputed here from the recorded samples, for every method that can run
    from glossrt.experiments.svgf import _available

    method = {"svgf-paper-2-signals": "svgf", "svgf-1-signal": "svgf"}
    ran = {m for m in ("svgf", "svgf-lobe", "svgf-paper-2-signals", "svgf-1-signal", "atrous",
                       "atrous-temporal", "oidn") if _available(method.get(m, m)) is None}
    assert set(d["seconds"]) == set(d["samples"]) == set(d["cost_vs_atrous"]) == ran
    base = np.asarray(d["samples"]["atrous"])
    assert len(base) == d["repeats"] >= 3
    for m, s in d["samples"].items():
        s = np.asarray(s)
        assert (s > 0).all()
        assert d["seconds"][m] == pytest.approx(np.median(s), rel=1e-12)
        assert d["cost_vs_atrous"][m] == pytest.approx(np.median(s / base), rel=1e-12)
    lw = res["results"]["lobe-weights"]["ratio_lobe_vs_normal"]
    assert {"bilateral-spec-traced", "bilateral-spec-frozen", "upsample-1/2-both-frozen"} <= set(lw)


def test_frozen_on_frames_replays_the_same_result():
    """The bench's frozen wrapper gives the traced result, on replay too (lobe weights read the
    camera, which the wrapper bakes in)."""
    import drjit as dr
    import numpy as np

    from glossrt import render, scenes
    from glossrt.denoise import bilateral, upsample
    from glossrt.timing import frozen_on_frames

    full = render.Renderer(scenes.load("roughness-map", size=(32, 24))).render(0)
    low = render.Renderer(scenes.load("roughness-map", size=(16, 12))).render(0)
    for fn, frames in ((lambda f: bilateral(f, weight="lobe"), (full,)),
                       (lambda f, lo: upsample(f, lo, weight="lobe"), (full, low))):
        want = np.asarray(fn(*frames))
        call = frozen_on_frames(fn, *frames)
        for _ in range(3):
            np.testing.assert_array_equal(np.asarray(call()), want)
        assert dr.width(call()) == want.size


def test_round_robin_pairs_samples():
    from glossrt.timing import paired_ratio, round_robin

    calls = []
    times = round_robin({"a": lambda: calls.append("a"), "b": lambda: calls.append("b")},
                        warmup=1, repeats=3)
    assert calls == ["a", "b"] + ["a", "b"] * 3  # warm-up, then strictly in turn
    assert len(times["a"]) == len(times["b"]) == 3
    # the median of per-repeat ratios, not the ratio of medians (2 here, 1.5 otherwise)
    assert paired_ratio([2.0, 4.0, 3.0], [1.0, 2.0, 3.0]) == 2.0


def test_steady_median_skips_the_first_frame():
    from glossrt.timing import steady_median

    assert steady_median([9.0, 1.0, 3.0, 2.0]) == 2.0  # the first (compiling) call dropped
    assert steady_median([9.0, 1.0, 3.0]) == 2.0  # even count: the mean of the middle two
    assert steady_median([4.0]) == 4.0


def test_round_robin_batches_short_calls():
    """With ``min_sample``, a call shorter than it is repeated back to back within a sample
    and the sample is the time per call; a long call stays single."""
    import time

    from glossrt.timing import round_robin

    calls = {"short": 0, "long": 0}

    def short():
        calls["short"] += 1
        time.sleep(0.002)

    def long():
        calls["long"] += 1
        time.sleep(0.03)

    times = round_robin({"short": short, "long": long}, warmup=1, repeats=3, min_sample=0.02)
    # warm-up 1 + calibration 1 + 3 samples of ceil(0.02 / ~0.002) <= 10 calls each
    assert 1 + 1 + 3 * 3 <= calls["short"] <= 1 + 1 + 3 * 10
    assert calls["long"] == 1 + 1 + 3
    assert all(0.0015 < t < 0.015 for t in times["short"])  # per call (a batch is >= 0.02)
    assert all(t >= 0.03 for t in times["long"])


@pytest.fixture(scope="module")
def small_demo(tmp_path_factory):
    """One small demo run: its folder, its report page and the lines it wrote on stderr."""
    import contextlib
    import io

    from glossrt.demo import run_demo

    out = tmp_path_factory.mktemp("demo") / "demo"
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        page = run_demo(out, size=(32, 24), frames=4, ref_every=2, ref_spp=16, mitsuba_spp=16)
    return out, page, err.getvalue().splitlines()


def test_demo_writes_report(small_demo):
    out, page, _ = small_demo
    html = page.read_text()
    assert page.name == "index.html"
    for heading in ("Frames", "converged reference", "Mitsuba", "Timings"):
        assert heading in html
    assert len(os.listdir(out / "frames")) == 4
    assert len(os.listdir(out / "references")) == 2
    for src in __import__("re").findall(r'src="([^"]+)"', html):
        assert (out / src).is_file()


def test_demo_says_what_it_does_on_stderr(small_demo):
    """Every step of the demo and every report section writes progress lines on stderr: a
    line when a section starts and when it ends, and the long sections (the papers') lines
    of their own steps or progress bars in between."""
    from glossrt.report import registered_sections

    _, _, lines = small_demo
    for start in ("1 spp frames: 4/4", "references (16 spp): 32/32",
                  "Mitsuba's path integrator"):
        assert any(ln.startswith(start) for ln in lines), (start, lines)
    names = [name for name, _, _ in registered_sections()]
    for k, name in enumerate(names):
        begin = lines.index(f"report section {k + 1}/{len(names)}: {name} ...")
        end = next(i for i, ln in enumerate(lines)
                   if i > begin and ln.startswith(f"{name}: done ("))
        steps = [ln for ln in lines[begin + 1:end] if ln.startswith(f"{name}: ")]
        if name in ("denoisers", "lobes", "ltc", "bspvt", "highlights", "specaa",
                    "pipeline"):
            assert steps, (name, lines[begin:end + 1])
    assert lines[-1] == "writing the report page ..."


def test_help_has_examples(capsys):
    with pytest.raises(SystemExit):
        main(["--help"])
    assert "examples:" in capsys.readouterr().out


@pytest.mark.parametrize("method", ["svgf", "atrous", "atrous-temporal", "oidn"])
def test_denoise_cli(tmp_path, method):
    src, out = tmp_path / "in", tmp_path / "out"
    assert main(["render", "glossy-cornell", "--out", str(src), "--frames", "3",
                 "--size", "32x24"]) == 0
    assert main(["denoise", str(src), "--method", method, "--out", str(out)]) == 0
    noisy, clean = load_sequence(src), load_sequence(out)
    assert [f.source.split("/")[-1] for f in clean] == [f.source.split("/")[-1] for f in noisy]
    for a, b in zip(noisy, clean, strict=True):
        assert b.meta["denoiser"] == method
        c = b.numpy("color")
        assert np.isfinite(c).all() and not np.array_equal(c, a.numpy("color"))
        np.testing.assert_array_equal(b.numpy("normal"), a.numpy("normal"))


def test_denoise_cli_reads_foreign_exrs(tmp_path, capsys):
    """A sequence written without glossrt (plain multi-layer EXRs named as in FORMATS.md,
    no glossrt header) is denoised by the per-frame filters; the reprojecting ones refuse it
    (no camera: FORMATS.md), naming the frame, and write nothing."""
    import mitsuba as mi

    from glossrt.frame import CHANNELS

    src, foreign, out = tmp_path / "in", tmp_path / "foreign", tmp_path / "out"
    assert main(["render", "glossy-cornell", "--out", str(src), "--frames", "2",
                 "--size", "24x16"]) == 0
    foreign.mkdir()
    for f in load_sequence(src):
        names, planes = [], []
        for name, comps in CHANNELS.items():
            a = f.numpy(name)
            for k, comp in enumerate(comps):
                names.append(f"{name}.{comp}")
                planes.append(a[..., k])
        bmp = mi.Bitmap(np.stack(planes, -1).astype(np.float32), channel_names=names)
        bmp.write(str(foreign / os.path.basename(f.source)))
    assert Frame.load(foreign / "frame_0001.exr").camera is None
    assert main(["denoise", str(foreign), "--method", "atrous", "--out", str(out)]) == 0
    assert len(os.listdir(out)) == 2
    capsys.readouterr()
    out2 = tmp_path / "out2"
    assert main(["denoise", str(foreign), "--method", "svgf", "--out", str(out2)]) == 2
    err = capsys.readouterr().err
    assert "frame_0000.exr" in err and "no camera" in err
    assert not out2.exists()  # the folder this failed run created is removed again


def test_denoise_cli_missing_channel(tmp_path, capsys):
    src = tmp_path / "in"
    assert main(["render", "glossy-cornell", "--out", str(src), "--size", "16x12",
                 "--mitsuba", "--spp", "2"]) == 0  # colour only
    assert main(["denoise", str(src), "--method", "svgf", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "frame_0000.exr" in err and "albedo" in err


def test_experiment_lobes(tmp_path, capsys):
    out = tmp_path / "lobes"
    assert main(["experiment", "--which", "lobes", "--out", str(out), "--size", "32x24",
                 "--spp", "8"]) == 0
    md = (out / "lobes.md").read_text()
    for title in ("fig. 4", "fig. 5", "fig. 6", "upsampling", "spatio-temporal"):
        assert title in md
    assert (out / "fig6.png").stat().st_size > 1000
    assert main(["experiment", "--which", "lobes", "--out", str(out), "--size", "30x24"]) == 2
    assert "multiple of 4" in capsys.readouterr().err


@pytest.mark.parametrize("method", ["ltc", "mc"])
def test_light_cli(tmp_path, method):
    out = tmp_path / method
    argv = ["light", "polygon-light", "--method", method, "--frames", "2", "--size", "24x18",
            "--out", str(out)] + (["--spp", "4"] if method == "mc" else [])
    assert main(argv) == 0
    from glossrt.frame import Frame

    f = Frame.load(out / "frame_0001.exr", require=("color", "normal"))
    c = f.numpy("color")
    assert np.all(np.isfinite(c)) and c.max() > 0
    assert (out / "frame_0001.png").stat().st_size > 100
    assert f.meta["method"] == method


def test_light_cli_scene_without_polygon_lights(tmp_path, capsys):
    xml = tmp_path / "s.xml"
    xml.write_text('<scene version="3.0.0"><sensor type="perspective"><film type="hdrfilm">'
                   '</film></sensor><shape type="sphere"><bsdf type="diffuse"/>'
                   '</shape><emitter type="point"><point name="position" x="0" y="0" z="-3"/>'
                   '</emitter></scene>')
    assert main(["light", str(xml), "--out", str(tmp_path / "o"), "--size", "8x6"]) == 2
    assert "no polygon lights" in capsys.readouterr().err
