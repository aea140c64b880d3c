"""The command line's input checks (issue 23): every documented command parses, options where
users put them, help that lists the choices, and bad input refused in one line before any
work, with nothing overwritten, half-written or left behind as an empty folder."""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from glossrt.cli import build_parser, main

ROOT = Path(__file__).resolve().parents[1]


# -- documented commands parse ------------------------------------------------------------------

def _readme_commands() -> list[str]:
    """Every ``glossrt ...`` command of README.md's ``sh`` blocks: ``\\`` continuations
    joined, comments dropped, each ``[optional part]`` both left out and put in."""
    blocks = re.findall(r"```sh\n(.*?)```", (ROOT / "README.md").read_text(), re.S)
    assert blocks
    lines, cur = [], ""
    for raw in "\n".join(blocks).splitlines():
        line = raw.split("#", 1)[0].rstrip()
        if line.endswith(" &"):  # (the shell runs it in the background)
            line = line[:-2].rstrip()
        if cur:
            cur += " " + line.strip()
        elif line.startswith("glossrt "):
            cur = line
        else:
            continue
        if cur.endswith("\\"):
            cur = cur[:-1].rstrip()
            continue
        lines.append(cur)
        cur = ""
    assert not cur, f"README: a continued command runs off its block: {cur!r}"
    out = []
    for line in lines:
        variants = [line]
        while any("[" in v for v in variants):
            nxt = []
            for v in variants:
                m = re.search(r"\s*\[([^\]]*)\]", v)
                if m is None:
                    nxt.append(v)
                    continue
                nxt += [v[:m.start()] + v[m.end():], v[:m.start()] + " " + m.group(1)
                        + v[m.end():]]
            variants = nxt
        out += variants
    return out


def _cli_examples() -> list[str]:
    """The examples in ``glossrt --help`` and in every command's help."""
    ap = build_parser()
    text = ap.format_help()
    sub = next(a for a in ap._actions if a.choices and "render" in a.choices)
    for p in sub.choices.values():
        text += "\n" + (p.epilog or "")
    out, cur = [], ""
    for raw in text.splitlines():
        line = raw.strip()
        if not (cur or line.startswith("glossrt ")):
            continue
        cur = (cur + " " + line) if cur else line
        if cur.endswith("\\"):
            cur = cur[:-1].rstrip()
            continue
        out.append(cur)
        cur = ""
    return out


def test_readme_lists_commands():
    cmds = _readme_commands()
    # every command of the CLI appears in the README's shell section
    for name in ("info", "render", "light", "ltc-fit", "bspvt", "denoise", "compare",
                 "experiment", "demo", "bench"):
        assert any(c.split()[1] == name for c in cmds), name
    assert any("--published ltc.js" in c for c in cmds)  # the optional part is tried too
    assert not any("[" in c or "#" in c for c in cmds)


@pytest.mark.parametrize("source", ["README.md", "--help"])
def test_documented_commands_parse(source, capsys):
    """Parse only (no work): argparse exits on a missing or unknown option."""
    cmds = _readme_commands() if source == "README.md" else _cli_examples()
    assert len(cmds) >= 5
    bad = []
    for cmd in cmds:
        argv = shlex.split(cmd)[1:]
        try:
            args = build_parser().parse_args(argv)
        except SystemExit:
            bad.append(f"{cmd}: {capsys.readouterr().err.strip().splitlines()[-1]}")
            continue
        assert callable(args.fn)
    assert not bad, "\n".join(bad)


# -- --device after the command, help ----------------------------------------------------------

def test_device_is_accepted_after_the_command(tmp_path, capsys):
    ap = build_parser()
    assert ap.parse_args(["render", "x", "--out", "o", "--device", "cpu"]).device == "cpu"
    assert ap.parse_args(["--device", "cpu", "render", "x", "--out", "o"]).device == "cpu"
    assert ap.parse_args(["render", "x", "--out", "o"]).device is None
    # after the command it wins (it is the later one)
    assert ap.parse_args(["--device", "gpu", "bench", "--device", "cpu"]).device == "cpu"
    for cmd in (["info"], ["bench"], ["demo", "--out", "o"], ["compare", "a", "b"]):
        assert ap.parse_args([*cmd, "--device", "auto"]).device == "auto"
    out = tmp_path / "o"
    assert main(["render", "glossy-cornell", "--size", "8x6", "--device", "cpu",
                 "--out", str(out)]) == 0
    assert (out / "frame_0000.exr").is_file()


def _help(argv, capsys) -> str:
    with pytest.raises(SystemExit):
        main([*argv, "--help"])
    return capsys.readouterr().out


def test_help_lists_every_choice(capsys):
    from glossrt.scenes import BUILTIN, library  # noqa: F401  (registers the scenes)

    text = _help(["render"], capsys)
    assert len(BUILTIN) >= 8
    for name in BUILTIN:
        assert re.search(rf"^\s+{re.escape(name)}\s", text, re.M), name
    text = " ".join(_help(["experiment"], capsys).split())
    ap = build_parser()
    sub = next(a for a in ap._actions if a.choices and "experiment" in a.choices)
    which = next(a for a in sub.choices["experiment"]._actions if a.dest == "which")
    assert "specaa" in which.choices
    for choice in which.choices:  # each explained, not only named in the usage line
        assert f"{choice}:" in text, choice


# -- nothing overwritten ------------------------------------------------------------------------

SCENE = """<scene version="3.0.0">
  <sensor type="perspective"><film type="hdrfilm"><integer name="width" value="8"/>
  <integer name="height" value="6"/></film></sensor>
  <shape type="sphere"><bsdf type="diffuse"/></shape>
  <emitter type="constant"/>
</scene>
"""


def test_no_command_writes_over_its_input(tmp_path, capsys):
    xml = tmp_path / "scene.xml"
    xml.write_text(SCENE)
    frame = tmp_path / "frame_0000.exr"
    frame.write_bytes(b"precious")  # e.g. a texture the scene names, where a frame would go
    with_texture = tmp_path / "textured.xml"
    with_texture.write_text(SCENE.replace(
        '<bsdf type="diffuse"/>', '<bsdf type="diffuse"><texture type="bitmap" name="reflectance">'
        '<string name="filename" value="frame_0000.exr"/></texture></bsdf>'))
    alias = tmp_path / "alias.npz"
    alias.symlink_to(xml)
    for argv, words in [
        (["bspvt", "build", str(xml), "--out", str(xml)], ["scene.xml", "refusing"]),
        (["bspvt", "build", str(xml), "--out", str(alias)], ["alias.npz", "refusing"]),
        (["render", str(with_texture), "--out", str(tmp_path)], ["frame_0000.exr", "input"]),
        (["light", str(with_texture), "--out", str(tmp_path)], ["frame_0000.exr", "input"]),
        (["demo", "--scene", str(with_texture), "--out", str(tmp_path)],
         ["frame_0000.exr", "output folder"]),
    ]:
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert err.startswith("glossrt: error:") and err.count("\n") == 1, err
        for w in words:
            assert w in err, (argv, err)
    assert xml.read_text() == SCENE
    assert frame.read_bytes() == b"precious"


def test_experiment_refuses_published_table_in_its_output(tmp_path, capsys):
    out = tmp_path / "res"
    out.mkdir()
    (out / "ltc.md").write_text("var g_ltc = [];")
    assert main(["experiment", "--which", "ltc", "--out", str(out), "--published",
                 str(out / "ltc.md")]) == 2
    assert "lies in the output folder" in capsys.readouterr().err
    assert (out / "ltc.md").read_text() == "var g_ltc = [];"


# -- outputs checked before the work ------------------------------------------------------------

def _unwritable_folder(tmp_path) -> Path:
    """A folder no file can be created in, also for root: /proc (a pseudo file system)."""
    probe = Path("/proc/glossrt-probe")
    try:
        probe.write_text("x")
    except OSError:
        return Path("/proc")
    probe.unlink()  # pragma: no cover
    pytest.skip("/proc is writable here")


@pytest.fixture(scope="module")
def tiny_sequence(tmp_path_factory):
    seq = tmp_path_factory.mktemp("seq") / "in"
    assert main(["render", "glossy-cornell", "--out", str(seq), "--frames", "2",
                 "--size", "8x6"]) == 0
    return seq


def test_outputs_are_checked_before_the_work(tiny_sequence, tmp_path, capsys, monkeypatch):
    """An output whose folder cannot be written is refused before the work (which it would
    lose): the work functions must not even be called."""
    from glossrt import bench, compare
    from glossrt.lights.bspvt import scene as shadows
    from glossrt.lights.ltc import fit as ltc_fit

    def never(*a, **kw):
        raise AssertionError("the work ran")

    monkeypatch.setattr(compare, "compare_dirs", never)
    monkeypatch.setattr(bench, "run", never)
    monkeypatch.setattr(shadows, "build_scene_trees", never)
    monkeypatch.setattr(ltc_fit, "main", never)
    bad = _unwritable_folder(tmp_path)
    for argv in (["compare", str(tiny_sequence), str(tiny_sequence), "--json",
                  str(bad / "m.json")],
                 ["bench", "--json", str(bad / "b.json")],
                 ["bspvt", "build", "polygon-light", "--out", str(bad / "t.npz")],
                 ["ltc-fit", "--out", str(bad / "t.npz")]):
        t0 = time.perf_counter()
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert err.startswith("glossrt: error:") and err.count("\n") == 1, err
        assert str(bad) in err and "cannot write" in err, err
        assert time.perf_counter() - t0 < 30


# -- demo --------------------------------------------------------------------------------------

@pytest.mark.parametrize("argv, words", [
    (["--frames", "0"], ["--frames", ">= 2"]),
    (["--frames", "1"], ["--frames", ">= 2"]),
    (["--spp", "0"], ["--spp", ">= 1"]),
    (["--scene", "no-such-scene"], ["no-such-scene"]),
    (["--size", "0x4"], ["size"]),
])
def test_demo_refuses_bad_arguments_before_any_work(tmp_path, capsys, argv, words):
    out = tmp_path / "demo"
    t0 = time.perf_counter()
    assert main(["demo", "--out", str(out), "--size", "16x12", *argv]) == 2
    assert time.perf_counter() - t0 < 15  # before rendering anything
    err = capsys.readouterr().err
    assert err.startswith("glossrt: error:") and err.count("\n") == 1, err
    for w in words:
        assert w in err
    assert not out.exists()


def test_demo_api_refuses_too_few_frames(tmp_path):
    from glossrt.demo import run_demo
    from glossrt.errors import GlossrtError

    with pytest.raises(GlossrtError, match="frames"):
        run_demo(tmp_path / "d", size=(16, 12), frames=1, progress=False)
    assert not (tmp_path / "d").exists()


# -- denoise reports bad radiance ---------------------------------------------------------------

def test_denoise_reports_nonfinite_and_negative_radiance(tmp_path, capsys):
    from glossrt.frame import Frame

    src, out = tmp_path / "in", tmp_path / "out"
    assert main(["render", "glossy-cornell", "--out", str(src), "--frames", "2",
                 "--size", "16x12"]) == 0
    capsys.readouterr()
    f = Frame.load(src / "frame_0001.exr")
    color = f.numpy("color").copy()
    color[2, 3, 0] = np.nan
    color[4, 5, :] = np.inf
    color[6, 7, 1] = -0.5
    color[6, 8, 2] = -1.0
    import mitsuba as mi

    f["color"] = mi.TensorXf(color)
    f.save(src / "frame_0001.exr")
    # independent count of what was put in: 1 NaN + 3 Inf components, 2 negative ones
    assert main(["denoise", str(src), "--method", "atrous", "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert "4 non-finite" in err and "2 negative" in err, err
    meta1 = Frame.load(out / "frame_0001.exr").meta
    assert meta1["input_nonfinite"] == {"color": 4}
    assert meta1["input_negative"] == {"color": 2}
    meta0 = Frame.load(out / "frame_0000.exr").meta
    assert "input_nonfinite" not in meta0 and "input_negative" not in meta0


# -- clear messages, no silent clamping ---------------------------------------------------------

def test_negative_size_names_the_size(tmp_path, capsys):
    assert main(["render", "glossy-cornell", "--size", "-64x48", "--out",
                 str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("glossrt: error:") and "-64x48" in err and "positive" in err
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("kind", ["loop", "dangling"])
@pytest.mark.parametrize("cmd", ["render", "json"])
def test_broken_link_as_output_is_named(tmp_path, capsys, kind, cmd, tiny_sequence):
    link = tmp_path / "o"
    link.symlink_to(link if kind == "loop" else tmp_path / "missing" / "x")
    argv = (["render", "glossy-cornell", "--size", "8x6", "--out", str(link)] if cmd == "render"
            else ["compare", str(tiny_sequence), str(tiny_sequence), "--json", str(link)])
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("glossrt: error:") and err.count("\n") == 1
    assert ("symbolic link loop" if kind == "loop" else "missing target") in err, err
    assert os.path.islink(link) and not (tmp_path / "missing").exists()


@pytest.mark.parametrize("seed", ["-1", str(2**32), str(2**40)])
@pytest.mark.parametrize("cmd", ["render", "light"])
def test_out_of_range_seed_is_refused(tmp_path, capsys, seed, cmd):
    scene = "glossy-cornell" if cmd == "render" else "polygon-light"
    assert main([cmd, scene, "--size", "8x6", "--seed", seed, "--out",
                 str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "--seed" in err and seed in err and str(2**32 - 1) in err
    assert not (tmp_path / "o").exists()


def test_largest_seed_is_recorded_as_given(tmp_path):
    from glossrt.frame import Frame

    assert main(["render", "glossy-cornell", "--size", "8x6", "--seed", str(2**32 - 1),
                 "--out", str(tmp_path / "o")]) == 0
    assert Frame.load(tmp_path / "o" / "frame_0000.exr").meta["seed"] == 2**32 - 1


@pytest.mark.parametrize("argv, word", [(["--repeats", "0"], "--repeats"),
                                        (["--repeats", "-2"], "--repeats"),
                                        (["--warmup", "-1"], "--warmup")])
def test_bench_refuses_bad_repeats(tmp_path, capsys, monkeypatch, argv, word):
    from glossrt import bench

    monkeypatch.setitem(bench.BENCHMARKS, "never", lambda ctx: pytest.fail("the work ran"))
    js = tmp_path / "j" / "b.json"
    assert main(["bench", "--only", "never", "--json", str(js), *argv]) == 2
    err = capsys.readouterr().err
    assert err.startswith("glossrt: error:") and word in err and ">= " in err
    assert not (tmp_path / "j").exists()


# -- no empty folders after a failure ----------------------------------------------------------

def test_failed_runs_leave_no_new_folder(tmp_path, capsys):
    xml = tmp_path / "s.xml"
    xml.write_text('<scene version="3.0.0"><sensor type="perspective"><film type="hdrfilm">'
                   '</film></sensor><shape type="sphere"><bsdf type="diffuse"/>'
                   '</shape><emitter type="point"><point name="position" x="0" y="0" z="-3"/>'
                   '</emitter></scene>')
    new = tmp_path / "a" / "b"
    assert main(["light", str(xml), "--out", str(new), "--size", "8x6"]) == 2
    assert "no polygon lights" in capsys.readouterr().err
    assert not (tmp_path / "a").exists()
    # a folder that was there before stays, with what it held
    old = tmp_path / "old"
    old.mkdir()
    (old / "keep.txt").write_text("mine")
    assert main(["light", str(xml), "--out", str(old), "--size", "8x6"]) == 2
    assert sorted(os.listdir(old)) == ["keep.txt"]


# -- memory ------------------------------------------------------------------------------------

def test_huge_size_is_refused_by_its_memory_estimate(tmp_path, capsys):
    from glossrt.cli import _available_memory, memory_estimate

    avail = _available_memory()
    assert avail is not None and avail > 0
    need = memory_estimate((16384, 16384))
    if need <= avail:  # pragma: no cover - a machine with more than ~540 GB free
        pytest.skip(f"{avail / 1e9:.0f} GB available: 16384x16384 fits")
    for argv in (["render", "glossy-cornell"], ["light", "polygon-light"], ["demo"],
                 ["experiment"]):
        t0 = time.perf_counter()
        assert main([*argv, "--size", "16384x16384", "--out", str(tmp_path / "o")]) == 2
        assert time.perf_counter() - t0 < 15
        err = capsys.readouterr().err
        assert err.startswith("glossrt: error:") and err.count("\n") == 1
        assert "16384x16384" in err and "GB" in err and "available" in err
        # the estimate in the message: at least the 3 float32 colour channels per pixel of
        # one frame, the smallest imaginable render
        gb = float(re.search(r"about ([\d.]+) GB", err).group(1))
        assert gb * 1e9 >= 16384 * 16384 * 12
        assert not (tmp_path / "o").exists()


@pytest.mark.slow
def test_memory_estimate_covers_a_measured_render(tmp_path):
    """Peak resident memory of a real render (a fresh process) against the estimate: the
    estimate must cover it and not be more than 3x above it. The peak is the process' own
    VmHWM (/proc/self/status), which starts afresh at exec; getrusage's ru_maxrss does not (on
    Linux it keeps the forking pytest worker's peak, 2.3 GB late in a full run)."""
    from glossrt.cli import memory_estimate

    w, h = 512, 384
    code = ("from glossrt.cli import main; "
            f"rc = main(['render', 'glossy-cornell', '--size', '{w}x{h}', '--frames', '2', "
            f"'--reference', '--spp', '4', '--out', {str(tmp_path / 'o')!r}]); "
            "hwm = [ln.split()[1] for ln in open('/proc/self/status') "
            "if ln.startswith('VmHWM:')][0]; "
            "print('RSS', rc, hwm)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=600)
    line = [ln for ln in out.stdout.splitlines() if ln.startswith("RSS")]
    assert line, out.stderr[-2000:]
    _, rc, kib = line[0].split()
    assert rc == "0"
    peak = int(kib) * 1024  # VmHWM in kB
    est = memory_estimate((w, h))
    assert peak <= est <= 3 * peak, (peak, est)


def test_demo_output_subfolder_in_the_way(tmp_path, capsys):
    out = tmp_path / "demo"
    out.mkdir()
    (out / "frames").write_text("a file where the frames folder goes")
    t0 = time.perf_counter()
    assert main(["demo", "--out", str(out), "--size", "16x12", "--frames", "2"]) == 2
    assert time.perf_counter() - t0 < 30
    err = capsys.readouterr().err
    assert err.startswith("glossrt: error:") and err.count("\n") == 1 and "frames" in err
    assert os.listdir(out) == ["frames"]


def test_failed_light_keeps_finished_frames_only(tmp_path, capsys, monkeypatch):
    """A run failing part-way keeps the frames it finished (each written whole) and removes
    only the folders it created that stayed empty."""
    from glossrt.lights import scene as light_scene

    real, calls = light_scene.polygon_lights, []

    def second_fails(setup, i, skip=False):
        calls.append(i)
        return real(setup, i, skip=skip) if i == 0 else []

    monkeypatch.setattr(light_scene, "polygon_lights", second_fails)
    out = tmp_path / "new" / "o"
    assert main(["light", "polygon-light", "--size", "8x6", "--frames", "2",
                 "--out", str(out)]) == 2
    assert "no polygon lights" in capsys.readouterr().err
    assert sorted(os.listdir(out)) == ["frame_0000.exr", "frame_0000.png"]
