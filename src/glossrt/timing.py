"""Wall-clock timing shared by the benchmarks, the experiments and the CLI (ground floor).

* :func:`round_robin` / :func:`paired_ratio`: cases called in turn, one call each per repeat,
  so a slow spell of the machine hits them alike; ratios as the median of per-repeat ratios.
  Calls shorter than ``min_sample`` (default :data:`MIN_SAMPLE`) are timed in back-to-back
  batches.
* :func:`timed_eval` / :func:`steady_median`: the time of one per-frame call with its result
  evaluated and the device synchronised, and the median per frame after the first (which
  compiles or records the kernels).
* :func:`frozen_on_frames`: a pure function of Frames under ``dr.freeze``, as the real-time
  path runs it (the benchmarks time it).

Dr.Jit is imported where a device is synchronised, never at import: importing this module
picks no backend.
"""

from __future__ import annotations

import math
import statistics
import time
from collections.abc import Callable, Sequence
from typing import Any

#: default shortest sample (s): calls of a few ms are timed in batches this long, because on a
#: shared machine a single short call moves by tens of percent from one sample to the next
MIN_SAMPLE = 0.05


def round_robin(cases: dict[str, Callable[[], object]], warmup: int,
                repeats: int, min_sample: float = 0.0) -> dict[str, list[float]]:
    """Wall times (s) per call of every case, called in turn: repeat i times each case once, so
    the i-th samples of all cases are taken within moments of each other and a slow spell of
    the machine hits them alike (ratios: :func:`paired_ratio`).

    ``min_sample > 0``: a case whose call (timed once after the warm-up) is shorter is called
    ``ceil(min_sample / t)`` times back to back per sample, and the sample is the batch's time
    divided by its count, as ``timeit`` does; one preempted call then moves a sample by a
    fraction of itself instead of doubling it."""
    import drjit as dr

    for fn in cases.values():
        for _ in range(warmup):
            fn()
    dr.sync_thread()
    batch = dict.fromkeys(cases, 1)
    if min_sample > 0:
        for name, fn in cases.items():
            batch[name] = max(1, math.ceil(min_sample / max(_timed(fn, 1), 1e-9)))
    times: dict[str, list[float]] = {k: [] for k in cases}
    for _ in range(repeats):
        for name, fn in cases.items():
            times[name].append(_timed(fn, batch[name]))
    return times


def _timed(fn: Callable[[], object], count: int) -> float:
    """Seconds per call of ``count`` calls of ``fn`` back to back (the device synchronised)."""
    import drjit as dr

    t0 = time.perf_counter()
    for _ in range(count):
        fn()
    dr.sync_thread()
    return (time.perf_counter() - t0) / count


def paired_ratio(num: list[float], den: list[float]) -> float:
    """Median over repeats of ``num[i] / den[i]`` (samples from :func:`round_robin`)."""
    return statistics.median(a / b for a, b in zip(num, den, strict=True))


def timed_eval(fn: Callable[..., Any], *args: Any) -> tuple[Any, float]:
    """``(fn(*args), seconds)``: the call's wall time with its result evaluated
    (``dr.eval``) and the device synchronised, so the time covers the kernels it launched."""
    import drjit as dr

    t0 = time.perf_counter()
    out = fn(*args)
    dr.eval(out)
    dr.sync_thread()
    return out, time.perf_counter() - t0


def steady_median(seconds: Sequence[float]) -> float:
    """The median of per-frame ``seconds`` after the first frame (the first compiles or
    records the kernels); the only frame's time if there is one."""
    return float(statistics.median(list(seconds[1:]) or list(seconds)))


class _Static:
    """A plain holder: ``dr.freeze`` does not traverse it (frame cameras and metadata that
    stay fixed while a frozen function replays)."""


def frozen_on_frames(fn: Callable, *frames) -> Callable[[], object]:
    """``fn(*frames)`` frozen (``dr.freeze``) with the frames' channels as its inputs, for
    timing a pure function of Frames as the real-time path would run it: each call returns
    the evaluated result, and Python tracing is gone after the first calls. The cameras and
    metadata are baked in (the frames here are fixed between calls)."""
    import drjit as dr

    from .frame import Frame
    from .jit import no_gc

    static = _Static()
    static.meta = [(f.camera, f.prev_camera, f.index, f.meta) for f in frames]

    def run(chans):
        return fn(*(Frame(c, camera=m[0], prev_camera=m[1], index=m[2], meta=m[3])
                    for c, m in zip(chans, static.meta, strict=True)))

    frozen = dr.freeze(run)
    chans = [dict(f.channels) for f in frames]

    def call():
        with no_gc():
            out = frozen(chans)
            dr.eval(out)
        return out

    return call
