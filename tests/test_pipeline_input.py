"""The pipeline's input, as a user gives it (Python, TOML, the command line): every option has
a documented range checked before any work, a bad file or value is one GlossrtError line, and
the flags that do not apply to composed frames are refused instead of ignored."""

from __future__ import annotations

import math
from contextlib import nullcontext
from pathlib import Path

import numpy as np
import pytest

from glossrt.cli import main
from glossrt.errors import GlossrtError
from glossrt.frame import Frame
from glossrt.pipeline import Pipeline, config, load_toml, resolve

ROOT = Path(__file__).resolve().parents[1]
SIZE = (32, 24)


def _one_line(capsys, *words: str) -> str:
    err = capsys.readouterr().err
    assert err.startswith("glossrt: error:") and err.count("\n") == 1, err
    for w in words:
        assert w in err, (w, err)
    return err


# -- ranges ---------------------------------------------------------------------------------

@pytest.mark.parametrize("name", sorted(config.RANGES))
def test_every_numeric_option_is_refused_outside_its_range(name):
    lo, hi, open_below = config.RANGES[name]
    kind = config.OPTIONS[name]
    below = lo if open_below else (lo - 1 if kind is int else lo - 0.5 * max(abs(lo), 1))
    above = hi + 1 if kind is int else hi * 2 + 1
    for bad in (below, above, 1e39 if kind is float else 2**40):
        if name == "max_depth" and bad == -1:
            continue  # (Mitsuba's "no limit")
        with pytest.raises(GlossrtError, match=rf"{name} must lie in"):
            resolve("schied2017", **{name: bad})
    for good in (lo if not open_below else None, hi):
        if good is not None:
            resolve("schied2017", **{name: kind(good)})
    assert name in config.HELP
    assert config.range_text(name).endswith(f"{hi}]" if kind is int else f"{hi:g}]")


def test_every_option_has_help_and_a_default():
    assert set(config.HELP) == set(config.OPTIONS) == set(config.DEFAULTS)
    for name, kind in config.OPTIONS.items():
        if kind in (int, float):
            assert name in config.RANGES, name
            d = config.DEFAULTS[name]
            if d is not None:
                resolve("schied2017", **{name: d})  # the default lies in its range


@pytest.mark.parametrize("seed", [4294967296, -1])
def test_a_seed_beyond_32_bits_is_refused_in_toml_and_python(tmp_path, seed):
    toml = tmp_path / "p.toml"
    toml.write_text(f"preset = \"schied2017\"\nseed = {seed}\n")
    with pytest.raises(GlossrtError, match="seed must lie in"):
        load_toml(toml)
    with pytest.raises(GlossrtError, match="seed must lie in"):
        Pipeline("polygon-light", size=SIZE, seed=seed)
    resolve("schied2017", seed=2**32 - 1)


def test_huge_max_depth_is_one_line_everywhere(tmp_path, capsys):
    from glossrt import render, scenes

    with pytest.raises(GlossrtError, match="max_depth must lie in"):
        Pipeline("polygon-light", size=SIZE, max_depth=2**40)
    with pytest.raises(GlossrtError, match="max_depth must be in"):
        render.Renderer(scenes.load("glossy-cornell", size=SIZE), max_depth=2**40)
    toml = tmp_path / "p.toml"
    toml.write_text("max_depth = 100000000000\n")
    with pytest.raises(GlossrtError, match="max_depth must lie in"):
        load_toml(toml)
    for extra in ([], ["--pipeline", "schied2017"]):
        assert main(["render", "glossy-cornell", "--size", "8x6", "--max-depth",
                     "100000000000", "--out", str(tmp_path / "o"), *extra]) == 2
        _one_line(capsys, "max")
    assert not (tmp_path / "o").exists()
    resolve("schied2017", max_depth=-1)


def test_lobe_beta_beyond_its_range_is_refused_not_an_overflow():
    with pytest.raises(GlossrtError, match="lobe_beta must lie in"):
        Pipeline("polygon-light", preset="tokuyoshi2015", size=SIZE, lobe_beta=1024.0)


# The filters' float32 arithmetic at the ends of their ranges: every composed value finite,
# and the image not black (the default's mean within a factor of 3; a 1e39 sigma gave 0,
# a 1e39 kappa NaN in 2878 of 3072 pixels).
@pytest.mark.slow
@pytest.mark.parametrize("preset,names", [
    ("schied2017", ("svgf_sigma_z", "svgf_sigma_n", "svgf_sigma_l")),
    ("tokuyoshi2015", ("lobe_beta", "lobe_kappa")),
])
def test_filters_stay_finite_and_lit_at_the_ends_of_their_ranges(preset, names):
    pipe = Pipeline("polygon-light", preset=preset, size=(64, 48), progress=False)
    base = [pipe.render(i) for i in range(2)][-1]
    m0 = float(base.numpy("color").mean())
    assert m0 > 0
    for name in names:
        lo, hi, _ = config.RANGES[name]
        for value in (hi, max(lo, 1e-3) if name != "lobe_beta" else 0.5):
            pipe.configure(**{name: value})
            f = [pipe.render(i) for i in range(2)][-1]
            c = f.numpy("color")
            assert np.isfinite(c).all(), (name, value)
            assert f.meta["pipeline"]["nonfinite_color"] == 0, (name, value)
            assert m0 / 3 < c.mean() < 3 * m0, (name, value, c.mean(), m0)
        pipe.configure(**{name: config.DEFAULTS[name]})


def test_the_header_counts_the_composed_frames_nonfinite_values():
    pipe = Pipeline("polygon-light", size=SIZE, progress=False)
    clean = pipe.render(0)
    assert clean.meta["pipeline"]["nonfinite_color"] == 0
    taa = pipe.stages["taa"]
    run = taa.run

    def poisoned(index, ctx):  # a filter whose arithmetic overflowed on some pixels
        import drjit as dr

        out = run(index, ctx)
        c = np.array(out["color"])
        c[:3, :5] = np.nan
        c[5, 5, 1] = np.inf
        out["color"] = type(out["color"])(c)
        dr.eval(out["color"])
        return out

    taa.run = poisoned
    f = pipe.render(1)
    assert f.meta["pipeline"]["nonfinite_color"] == 3 * 5 * 3 + 1
    assert f.meta["nonfinite_samples"] >= 46
    assert np.isfinite(f.numpy("color")).all()


# -- the Python API ---------------------------------------------------------------------------

def test_python_api_refuses_bad_arguments_in_one_line():
    pipe = Pipeline("polygon-light", preset=None, size=SIZE, progress=False)  # the default
    assert pipe.preset == "schied2017"
    for bad in (1.5, float("nan"), "3", None, -1, True):
        with pytest.raises(GlossrtError, match="frame index"):
            pipe.render(bad)
    pipe.render(np.int64(0))
    for bad in (None, "frame", np.zeros((2, 2, 3))):
        with pytest.raises(GlossrtError, match="display"):
            pipe.display(bad)
    with pytest.raises(GlossrtError, match="preset"):
        Pipeline("polygon-light", preset=3, size=SIZE)
    with pytest.raises(GlossrtError, match="preset"):
        Pipeline("polygon-light", preset=["full"], size=SIZE)


def test_anisotropy_outputs_on_an_isotropic_scene_are_refused(tmp_path, capsys):
    with pytest.raises(GlossrtError, match="no anisotropic material"):
        Pipeline("polygon-light", size=SIZE, outputs=("tangent", "roughness_uv"))
    pipe = Pipeline("polygon-light", size=SIZE, progress=False)
    with pytest.raises(GlossrtError, match="no anisotropic material"):
        pipe.outputs = ("color", "tangent")
    assert main(["render", "polygon-light", "--size", "16x12", "--pipeline", "schied2017",
                 "--outputs", "tangent,roughness_uv", "--out", str(tmp_path / "o")]) == 2
    _one_line(capsys, "tangent")
    assert not (tmp_path / "o").exists()


# -- files and flags ------------------------------------------------------------------------------

def test_a_pipeline_file_that_is_a_folder_or_not_utf8_is_one_line(tmp_path, capsys):
    utf16 = tmp_path / "p16.toml"
    utf16.write_bytes('preset = "full"\n'.encode("utf-16"))
    binary = tmp_path / "bin.toml"
    binary.write_bytes(bytes(range(256)))
    for spec, word in ((tmp_path, "folder"), (utf16, "UTF-8"), (binary, "UTF-8")):
        assert main(["render", "polygon-light", "--size", "8x6", "--pipeline", str(spec),
                     "--out", str(tmp_path / "o")]) == 2
        _one_line(capsys, word)
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("flag", [["--resume"], ["--block-spp", "4"], ["--cluster", "local"]])
def test_flags_of_sample_blocks_are_refused_with_a_pipeline(tmp_path, capsys, flag):
    assert main(["render", "polygon-light", "--size", "8x6", "--pipeline", "schied2017",
                 *flag, "--out", str(tmp_path / "o")]) == 2
    _one_line(capsys, flag[0])
    assert not (tmp_path / "o").exists()


def test_set_overrides_the_preset_and_is_checked(tmp_path, capsys):
    out = tmp_path / "o"
    assert main(["render", "polygon-light", "--size", "16x12", "--pipeline", "schied2017",
                 "--set", "direct=ltc+ratio", "--set", "taa=false", "--set", "svgf_sigma_l=2",
                 "--set", 'tonemap="srgb"', "--out", str(out)]) == 0
    capsys.readouterr()
    choices = Frame.load(out / "frame_0000.exr").meta["pipeline"]["choices"]
    assert (choices["direct"], choices["taa"], choices["svgf_sigma_l"], choices["tonemap"]) \
        == ("ltc+ratio", False, 2.0, "srgb")
    for bad, word in ((["--set", "svgf_sigma_l=1e39"], "svgf_sigma_l"),
                      (["--set", "nonsense=1"], "nonsense"), (["--set", "taa"], "KEY=VALUE")):
        assert main(["render", "polygon-light", "--size", "16x12", "--pipeline", "schied2017",
                     *bad, "--out", str(tmp_path / "bad")]) == 2
        _one_line(capsys, word)
    assert main(["render", "polygon-light", "--size", "8x6", "--set", "taa=false",
                 "--out", str(tmp_path / "bad")]) == 2
    _one_line(capsys, "--set")
    assert not (tmp_path / "bad").exists()


def test_spp_sets_the_reference_presets_samples(tmp_path, capsys):
    out = tmp_path / "o"
    assert main(["render", "polygon-light", "--size", "16x12", "--pipeline", "reference",
                 "--spp", "8", "--out", str(out)]) == 0
    capsys.readouterr()
    f = Frame.load(out / "frame_0000.exr")
    assert f.meta["spp"] == 8 and f.meta["pipeline"]["choices"]["spp"] == 8
    assert main(["render", "polygon-light", "--size", "16x12", "--pipeline", "full",
                 "--spp", "8", "--out", str(tmp_path / "bad")]) == 2
    _one_line(capsys, "--spp", "accumulat")
    assert main(["render", "polygon-light", "--size", "16x12", "--pipeline", "reference",
                 "--spp", "5000", "--out", str(tmp_path / "bad")]) == 2
    _one_line(capsys, "spp must lie in")
    assert not (tmp_path / "bad").exists()


def test_presets_lists_every_preset_and_option_with_range_and_default(capsys):
    for argv in (["presets"], ["render", "x", "--out", "o", "--pipeline", "help"]):
        with pytest.raises(SystemExit) if argv[0] == "render" else nullcontext():
            assert main(argv) == 0
        text = capsys.readouterr().out
        for name in config.PRESETS:
            assert f"  {name}: " in text, name
        for name in config.OPTIONS:
            line = next(ln for ln in text.splitlines() if ln.startswith(f"  {name} = "))
            assert config.range_text(name) in line and "(default " in line, line
        assert "svgf_sigma_l = (0, 10000]  (default 4)" in text


@pytest.mark.slow
def test_the_example_pipeline_file_loads_and_renders(tmp_path):
    example = ROOT / "examples" / "pipeline.toml"
    preset, choices = load_toml(example)
    opts = resolve(preset, **choices)
    assert (opts["preset"], opts["direct"], opts["ratio_spp"], opts["seed"]) \
        == ("full", "ltc+ratio", 2, 7)
    assert main(["render", "polygon-light", "--size", "16x12", "--pipeline", str(example),
                 "--out", str(tmp_path / "o")]) == 0
    meta = Frame.load(tmp_path / "o" / "frame_0000.exr").meta
    assert meta["pipeline"]["choices"]["exposure"] == 0.5 and meta["pipeline"]["direct"] \
        == "ltc+ratio"
    assert not math.isnan(meta["pipeline"]["frame_ms"])
