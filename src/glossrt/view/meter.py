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

import os
import time
from typing import Any

import numpy as np

#: at most one FLIP evaluation is started per this many seconds (one core of the helper
#: otherwise runs flat out while the view stands still)
MIN_INTERVAL_S = 0.5


def _helper_init() -> None:
    """Run in the helper before ``flip_evaluator`` loads: OpenMP reads this at load time."""
    os.environ["OMP_NUM_THREADS"] = "1"


class ErrorMeter:
    """RMSE now, FLIP from a helper process (started on first use; :meth:`close` ends it).

    >>> m = ErrorMeter()                                    # doctest: +SKIP
    >>> m.measure(color, reference, spp=64)                 # doctest: +SKIP
    {'rmse': 0.012}                    # FLIP is being evaluated
    >>> m.measure(color, reference, spp=68)                 # doctest: +SKIP
    {'rmse': 0.011, 'flip': 0.043, 'flip_spp': 64}
    """

    def __init__(self) -> None:
        self._pool = None
        self._job = None  # (AsyncResult, generation, spp)
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
        self._collect()
        if self._job is None and self.error is None and \
                time.monotonic() - self._started >= MIN_INTERVAL_S:
            self._submit(color, reference, spp)
        if self._flip is not None:
            out["flip"], out["flip_spp"] = self._flip
        return out

    def wait(self, timeout: float = 60.0) -> bool:
        """Block until the running FLIP evaluation (if any) is collected (for tests)."""
        if self._job is not None:
            self._job[0].wait(timeout)
        self._collect()
        return self._job is None

    def close(self) -> None:
        """End the helper process now (a running evaluation is abandoned)."""
        if self._pool is not None:
            self._pool.terminate()
            self._pool = None
        self._job = None

    def _submit(self, color: np.ndarray, reference: np.ndarray, spp: int) -> None:
        from ..metrics import flip

        if self._pool is None:
            import multiprocessing

            # spawn: a fork would copy Dr.Jit's and viser's threads' state mid-flight
            self._pool = multiprocessing.get_context("spawn").Pool(1, _helper_init)
        job = self._pool.apply_async(flip, (np.array(color, np.float32),
                                            np.array(reference, np.float32)))
        self._job = (job, self._generation, int(spp))
        self._started = time.monotonic()

    def _collect(self) -> None:
        if self._job is None or not self._job[0].ready():
            return
        job, generation, spp = self._job
        self._job = None
        try:
            value = float(job.get(0))
        except Exception as e:  # noqa: BLE001 - shown in the panel instead of FLIP
            self.error = f"FLIP failed: {type(e).__name__}: {e}"
            return
        if generation == self._generation:
            self._flip = (value, spp)


__all__ = ["ErrorMeter", "MIN_INTERVAL_S"]
