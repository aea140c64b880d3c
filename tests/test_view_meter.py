"""The viewer's error meter (glossrt.view.meter): RMSE now, FLIP from a helper process."""

from __future__ import annotations

import threading
import time

import numpy as np

from glossrt.metrics import flip, rmse
from glossrt.view.meter import ErrorMeter


def _pair(w, h, seed=0):
    rng = np.random.default_rng(seed)
    ref = rng.random((h, w, 3)).astype(np.float32) * 4.0
    return (ref * rng.uniform(0.7, 1.3, ref.shape)).astype(np.float32), ref


def test_rmse_now_flip_from_the_helper_with_its_spp():
    img, ref = _pair(48, 27)
    m = ErrorMeter()
    try:
        first = m.measure(img, ref, spp=16)
        assert first == {"rmse": rmse(img, ref)}  # FLIP is still being evaluated
        assert m.wait(120)
        out = m.measure(img * 2.0, ref, spp=20)  # a later frame: the value is the 16 spp one
        # independent of the helper: FLIP evaluated here, in this process
        assert out["flip"] == flip(img, ref) and out["flip_spp"] == 16
        assert out["rmse"] == rmse(img * 2.0, ref)
        assert m.error is None
    finally:
        m.close()


def test_reset_drops_the_value_measured_against_the_old_reference():
    img, ref = _pair(48, 27, seed=1)
    m = ErrorMeter()
    try:
        m.measure(img, ref, spp=8)
        m.reset()  # the reference moved while the helper evaluated
        assert m.wait(120)
        assert "flip" not in m.measure(img, ref, spp=4)
    finally:
        m.close()


def test_close_ends_the_helper_process():
    img, ref = _pair(16, 9)
    m = ErrorMeter()
    m.measure(img, ref, spp=1)
    proc = m._proc
    assert proc.poll() is None
    m.close()
    assert proc.wait(10) is not None and m._proc is None


def _longest_stall(work) -> tuple[float, float]:
    """Run ``work()`` while another thread ticks every 5 ms: (the longest gap between ticks,
    work's seconds)."""
    gaps = [0.0]
    done = threading.Event()

    def tick():
        last = time.perf_counter()
        while not done.is_set():
            time.sleep(0.005)
            now = time.perf_counter()
            gaps.append(now - last)
            last = now

    t = threading.Thread(target=tick)
    t.start()
    t0 = time.perf_counter()
    try:
        work()
    finally:
        seconds = time.perf_counter() - t0
        done.set()
        t.join()
    return max(gaps), seconds


def test_flip_never_holds_the_render_loop():
    """The point of the helper: flip-evaluator's C++ keeps Python's lock for the whole
    evaluation, so in-process it froze every other thread (viser's websocket, the signal
    handler) for its duration. Here a ticking thread must keep ticking while it runs."""
    img, ref = _pair(640, 360, seed=2)
    m = ErrorMeter()
    try:
        m.measure(img, ref, spp=1)  # starts the helper process and the evaluation
        stall, seconds = _longest_stall(lambda: m.wait(300))
        assert "flip" in m.measure(img, ref, spp=2)
    finally:
        m.close()
    # the contrast: the same FLIP in this process stalls the ticking thread throughout
    stall_here, seconds_here = _longest_stall(lambda: flip(img, ref))
    assert stall_here > 0.5 * seconds_here > 0.05, (stall_here, seconds_here)
    # Held, the thread would wait the whole evaluation. Free, its longest wait is the OS's
    # scheduling: under 0.25 s on an idle machine, and a small part of an evaluation that a
    # loaded machine (two test workers, stolen CPU time) stretches to seconds.
    assert seconds > 0.05 and stall < max(0.25, 0.1 * seconds), (stall, seconds)


def test_a_users_unguarded_script_runs_once(tmp_path):
    """The helper must not re-import the caller's ``__main__`` (a spawned multiprocessing
    child does, and so re-ran a viewer script without ``if __name__ == "__main__"``)."""
    import subprocess
    import sys

    log = tmp_path / "runs.txt"
    script = tmp_path / "user.py"
    script.write_text(
        "import numpy as np\n"
        "from glossrt.view.meter import ErrorMeter\n"
        f"open({str(log)!r}, 'a').write('ran\\n')\n"
        "m = ErrorMeter()\n"
        "a = np.ones((9, 16, 3), np.float32)\n"
        "m.measure(a, a * 1.1, spp=1)\n"
        "assert m.wait(120)\n"
        "print(m.measure(a, a, spp=2)['flip'])\n"
        "m.close()\n")
    p = subprocess.run([sys.executable, str(script)], capture_output=True, text=True,
                       timeout=300)
    assert p.returncode == 0, p.stderr
    assert 0.0 < float(p.stdout) < 1.0
    assert log.read_text() == "ran\n"


def test_a_helper_that_dies_is_reported_not_raised():
    m = ErrorMeter()
    try:
        a = np.ones((9, 16, 3), np.float32)
        m.measure(a, a * 1.1, spp=1)
        m._proc.kill()  # as an out-of-memory kill would
        assert m.wait(120)
        out = m.measure(a, a, spp=2)
        assert "flip" not in out and "helper ended" in m.error and m._proc is None
        assert "rmse" in out  # the panel keeps its RMSE
    finally:
        m.close()
