"""The viewer's error meter: the live colour against the accumulated reference.

RMSE is computed on every frame in the render loop (a few NumPy passes). FLIP
(:func:`glossrt.metrics.flip`, NVIDIA's ``flip-evaluator``) runs in one helper process
instead: its C++ holds Python's lock for the whole evaluation and spreads it over OpenMP
threads, and on the 2-core VM beside Dr.Jit's busy thread pool that made one 32x18 FLIP take
0.43 s instead of 4 ms and a 320x180 one about a second. Held in the render loop, that lock
stalled viser's websocket thread and delayed Ctrl-C / SIGTERM past the viewer's 2 s promise.
The helper evaluates with one OpenMP thread; its value lags the live frame by one evaluation
and is reported with the reference's sample count it was measured against.
"""

from __future__ import annotations

import io
import os
import select
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

#: at most one FLIP evaluation is started per this many seconds (one core of the helper
#: otherwise runs flat out while the view stands still)
MIN_INTERVAL_S = 0.5


def _helper_main() -> None:
    """The helper process: read (image, reference) pairs as ``.npy`` from stdin, answer each
    with one line, FLIP's mean or ``error: ...``; end at end of input."""
    from ..metrics import flip

    class _Pipe:  # read() only: NumPy's reader then never asks a pipe for its position
        read = sys.stdin.buffer.read

    inp, out = _Pipe(), sys.stdout
    while True:
        try:
            img = np.lib.format.read_array(inp)
            ref = np.lib.format.read_array(inp)
        except (EOFError, ValueError, OSError):  # the viewer closed the pipe or ended
            return
        try:
            line = repr(flip(img, ref))
        except Exception as e:  # noqa: BLE001 - reported to the viewer's panel
            line = f"error: {type(e).__name__}: {e}".replace("\n", " ")
        out.write(line + "\n")
        out.flush()


class ErrorMeter:
    """RMSE now, FLIP from a helper process (started on first use; :meth:`close` ends it).

    >>> m = ErrorMeter()                                    # doctest: +SKIP
    >>> m.measure(color, reference, spp=64)                 # doctest: +SKIP
    {'rmse': 0.012}                    # FLIP is being evaluated
    >>> m.measure(color, reference, spp=68)                 # doctest: +SKIP
    {'rmse': 0.011, 'flip': 0.043, 'flip_spp': 64}

    The helper is a plain ``python -c`` child fed through a pipe, not ``multiprocessing``:
    a spawned ``multiprocessing`` child re-imports the parent's ``__main__``, which re-ran
    a user's unguarded viewer script in the helper.
    """

    def __init__(self) -> None:
        self._proc: subprocess.Popen | None = None
        self._job: tuple[int, int] | None = None  # (generation, spp) of the running one
        self._generation = 0
        self._started = -np.inf
        self._flip: tuple[float, int] | None = None
        #: why FLIP is unavailable (its helper failed), or None
        self.error: str | None = None

    def reset(self) -> None:
        """Forget the last FLIP value: the reference it was measured against is gone. A job
        still running finishes in the helper and its value is dropped."""
        self._generation += 1
        self._flip = None

    def measure(self, color: np.ndarray, reference: np.ndarray, spp: int) -> dict[str, Any]:
        """``rmse`` of ``color`` against ``reference``; ``flip`` and ``flip_spp`` (the
        reference's samples it was measured against) once a FLIP evaluation has finished
        since the last :meth:`reset`. Starts a new FLIP evaluation when the helper is idle."""
        from ..metrics import rmse

        out: dict[str, Any] = {"rmse": rmse(color, reference)}
        self._collect(0.0)
        if self._job is None and self.error is None and \
                time.monotonic() - self._started >= MIN_INTERVAL_S:
            self._submit(color, reference, spp)
        if self._flip is not None:
            out["flip"], out["flip_spp"] = self._flip
        return out

    def wait(self, timeout: float = 60.0) -> bool:
        """Block until the running FLIP evaluation (if any) is collected (for tests)."""
        self._collect(timeout)
        return self._job is None

    def close(self) -> None:
        """End the helper process now (a running evaluation is abandoned)."""
        p, self._proc, self._job = self._proc, None, None
        if p is not None:
            p.kill()
            p.wait()
            for f in (p.stdin, p.stdout):
                f.close()

    def _submit(self, color: np.ndarray, reference: np.ndarray, spp: int) -> None:
        if self._proc is None:
            import glossrt

            env = dict(os.environ, OMP_NUM_THREADS="1")  # OpenMP reads it when FLIP loads
            root = str(Path(glossrt.__file__).resolve().parent.parent)
            env["PYTHONPATH"] = os.pathsep.join(
                [root] + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
            self._proc = subprocess.Popen(
                [sys.executable, "-c",
                 "from glossrt.view.meter import _helper_main; _helper_main()"],
                stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=env)
        try:
            for a in (color, reference):  # .npy, written whole (no file position needed)
                buf = io.BytesIO()
                np.lib.format.write_array(buf, np.ascontiguousarray(a, np.float32))
                self._proc.stdin.write(buf.getbuffer())
            self._proc.stdin.flush()
        except OSError as e:  # the helper died
            self._failed(f"FLIP helper ended ({e})")
            return
        self._job = (self._generation, int(spp))
        self._started = time.monotonic()

    def _collect(self, timeout: float) -> None:
        if self._job is None:
            return
        fd = self._proc.stdout
        if not select.select([fd], [], [], timeout)[0]:
            return
        line = fd.readline().decode().strip()
        generation, spp = self._job
        self._job = None
        if not line or line.startswith("error:"):
            self._failed(f"FLIP {line or 'helper ended'}")
        elif generation == self._generation:
            self._flip = (float(line), spp)

    def _failed(self, why: str) -> None:
        self.error = why
        self.close()


__all__ = ["ErrorMeter", "MIN_INTERVAL_S"]
