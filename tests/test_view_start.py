"""The viewer's start-up, in a file of its own (each test opens its own viewer; a process runs
one at a time): the server answers while the pipeline is still being constructed, with the
construction's progress in the panel; an error of the construction reaches the panel, the
API and the CLI in one line; refusals of the pipeline's checks still come before the server
starts; and a process that exits with a viewer mid-frame exits cleanly."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
import urllib.request

import pytest

from glossrt.errors import GlossrtError

SIZE = (32, 18)


def _gated_direct_stage(monkeypatch, gate: threading.Event, started: threading.Event,
                        fail: str | None = None):
    """Make the pipeline's construction report progress (4 of 10 steps), then wait for
    ``gate`` (and raise ``fail`` then, if given): a slow BSPVT build, under control."""
    import glossrt.pipeline as pl
    from glossrt.progress import Progress

    real = pl.DirectStage

    class Gated(real):
        def __init__(self, *args, **kwargs):
            with Progress(10, "fake trees") as bar:
                bar.update(4)
                started.set()
                assert gate.wait(120)
            if fail is not None:
                raise GlossrtError(fail)
            super().__init__(*args, **kwargs)

    monkeypatch.setattr(pl, "DirectStage", Gated)


def test_the_server_answers_while_the_pipeline_is_constructed(tmp_path, monkeypatch):
    import glossrt.view as gv

    gate, started = threading.Event(), threading.Event()
    _gated_direct_stage(monkeypatch, gate, started)
    v = gv.open("polygon-light", pipeline="schied2017", size=SIZE, port=0,
                captures=tmp_path / "c", verbose=False)
    try:
        assert v.pipe is None and v.preset == "schied2017"  # (still constructing)
        with urllib.request.urlopen(v.url, timeout=30) as r:
            assert r.status == 200 and b"<html" in r.read().lower()
        assert started.wait(60)
        # the construction's progress, in the panel's status line and bar
        assert v.wait(until=lambda: "fake trees 4/10" in v._status_md.content
                      and v._progress_bar.value == pytest.approx(40.0), timeout=30)
        assert v.progress == ("fake trees", 4, 10) and v._progress_bar.visible
        assert v.stats["frames"] == 0 and v.pipe is None
        gate.set()
        assert v.wait(1, timeout=240), v.message
        assert v.pipe is not None and v.last_image is not None
        assert not v._progress_bar.visible  # (hidden with the first image)
        assert v.error is None
    finally:
        gate.set()
        v.stop()


def test_an_error_of_the_construction_shows_in_one_line(tmp_path, monkeypatch):
    import glossrt.view as gv

    gate, started = threading.Event(), threading.Event()
    _gated_direct_stage(monkeypatch, gate, started, fail="fake trees: out of\nmemory")
    v = gv.open("polygon-light", pipeline="schied2017", size=SIZE, port=0,
                captures=tmp_path / "c", verbose=False)
    try:
        assert started.wait(60)
        gate.set()
        with pytest.raises(GlossrtError, match="fake trees: out of memory"):
            v.wait(1, timeout=120)
        assert v.error == "fake trees: out of memory"  # one line
        assert not v.running
        assert "fake trees: out of memory" in v._message_md.content
        assert "failed" in v._status_md.content
    finally:
        gate.set()
        v.stop()
    # the process' viewer is free again
    monkeypatch.undo()
    w = gv.open("polygon-light", pipeline="schied2017", size=SIZE, port=0,
                captures=tmp_path / "c", verbose=False)
    try:
        assert w.wait(1, timeout=240), w.message
    finally:
        w.stop()


@pytest.mark.parametrize("kw,msg", [
    ({"size": (48, 27), "indirect_scale": 2}, "does not divide"),
    ({"scene": "no-such-scene"}, "no-such-scene"),
    ({"pipeline": "okuno-iwasaki", "bspvt": "missing.bspvt.npz"}, "missing.bspvt.npz"),
])
def test_the_pipelines_refusals_come_before_the_server_starts(kw, msg, tmp_path):
    import glossrt.view as gv

    args = {"scene": "polygon-light", "pipeline": "schied2017", "size": SIZE, "port": 0,
            "captures": tmp_path / "c", "verbose": False, **kw}
    scene = args.pop("scene")
    with pytest.raises(GlossrtError, match=msg):
        gv.open(scene, **args)
    assert not (tmp_path / "c").exists()


#: ``python -c`` prefix of the CLI tests: the CLI with a pipeline construction that reports
#: progress, then sleeps (``slow``) or fails (``fail``)
_CLI = textwrap.dedent("""
    import sys, time
    import glossrt.pipeline as pl
    from glossrt.errors import GlossrtError
    from glossrt.progress import Progress
    mode = sys.argv[1]
    real = pl.DirectStage

    class Fake(real):
        def __init__(self, *args, **kwargs):
            with Progress(4, "fake trees") as bar:
                for i in range(4):
                    time.sleep(1.0 if mode == "slow" else 0.5)
                    bar.update(i + 1)
                    if mode == "fail" and i == 1:
                        raise GlossrtError("fake trees: out of memory")
            super().__init__(*args, **kwargs)

    pl.DirectStage = Fake
    from glossrt.cli import main
    raise SystemExit(main(sys.argv[2:]))
""")


def _cli(mode: str, tmp_path, *args: str) -> subprocess.Popen:
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    return subprocess.Popen(
        [sys.executable, "-c", _CLI, mode, "view", "polygon-light", "--size", "32x18",
         "--pipeline", "schied2017", "--port", "0", "--captures", str(tmp_path / "caps"),
         *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)


def test_cli_an_error_of_the_construction_exits_nonzero_in_one_line(tmp_path):
    p = _cli("fail", tmp_path)
    try:
        out, err = p.communicate(timeout=240)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == 2, (out, err)
    assert "glossrt view: http://" in out  # served first
    assert "Traceback" not in err, err
    lines = [line for line in err.splitlines() if "out of memory" in line]
    assert lines == ["glossrt: error: fake trees: out of memory"], err


def test_cli_ctrl_c_while_the_pipeline_is_built_prints_no_traceback(tmp_path):
    p = _cli("slow", tmp_path)
    try:
        line = p.stdout.readline()  # the URL, before the construction ends
        assert "glossrt view: http://" in line, (line, p.stderr.read() if p.poll() else "")
        t0 = time.monotonic()
        p.send_signal(signal.SIGINT)
        rc = p.wait(timeout=30)
        err = p.stderr.read()
        # (130: the signal came before serve() took Ctrl-C over)
        assert rc in (0, 130) and time.monotonic() - t0 < 2.0, (rc, err)
        assert "Traceback" not in err and "Exception" not in err, err
    finally:
        if p.poll() is None:
            p.kill()


#: a script that leaves its viewer mid-frame at exit: the frame records kernels (a Dr.Jit call
#: of the render loop's thread) when the interpreter finalizes; ``stop`` first with a short
#: timeout (returns while the frame goes on) or not at all
_EXIT_MID_FRAME = textwrap.dedent("""
    import sys, threading
    import glossrt.view
    v = glossrt.view.open("polygon-light", pipeline="schied2017", size=(32, 18), port=0,
                          verbose=False)
    assert v.wait(1, timeout=240)
    rendering, render = threading.Event(), v.pipe.render

    def traced(index):
        rendering.set()
        return render(index)

    v.pipe.render = traced
    v.configure(direct="ltc")  # the next frame records kernels
    assert rendering.wait(60)
    if sys.argv[1] == "stop":
        v.stop(timeout=0.2)
""")


@pytest.mark.parametrize("how", ["stop", "no-stop"])
def test_exit_with_the_render_loop_mid_frame_is_clean(tmp_path, how):
    """A Dr.Jit call still running in the render loop's thread while the interpreter
    finalized aborted the process ('terminate called without an active exception', or a
    crash) in about half the runs: the viewer's exit hook waits for the loop."""
    for _ in range(3):
        r = subprocess.run([sys.executable, "-c", _EXIT_MID_FRAME, how], capture_output=True,
                           text=True, cwd=tmp_path, timeout=240)
        assert r.returncode == 0 and "terminate called" not in r.stderr, (r.returncode,
                                                                           r.stderr[-2000:])
