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
* :class:`StageClock`: per-stage times of a run of stages (the frame pipeline's), by default
  the kernel time of each stage from Dr.Jit's kernel history, no stage synchronised.

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


#: the stage clocks' modes (:class:`StageClock`)
STAGE_TIMINGS = ("kernels", "sync", "none")
#: width (elements) of the marker :class:`StageClock` puts in Dr.Jit's kernel history between
#: stages: a prime, so that no W x H image (W, H > 1) or channel array has it
MARKER_WIDTH = 4099


def check_stage_timing(mode) -> None:
    """Refuse a mode that is not one of :data:`STAGE_TIMINGS` (one GlossrtError line)."""
    if mode not in STAGE_TIMINGS:
        from .errors import GlossrtError

        raise GlossrtError(f"timing must be one of {', '.join(STAGE_TIMINGS)}, got {mode!r}")


class StageClock:
    """Per-stage times of stages run one after the other (the frame pipeline's).

    ``mode`` (:data:`STAGE_TIMINGS`):

    * ``"kernels"`` (the real-time path): no stage is synchronised. While the stages run,
      Dr.Jit's kernel history is on (``dr.JitFlag.KernelHistory``); between two stages the
      clock writes a marker, a ``MARKER_WIDTH``-element memset (an asynchronous launch of a
      few microseconds), so that :meth:`finish` can attribute every history entry to the
      stage that launched it by launch order. A stage's time is the sum of the
      ``execution_time`` of its entries: JIT kernels, frozen-function replays (measured on
      Dr.Jit 1.5: a replay lists each of its kernels with its own execution time and
      ``recording_mode`` ``Replayed``), memsets, copies and reductions. On the LLVM backend
      a launch's time is its span on the thread pool, and launches run one after the other,
      so the stages' times add up to the device's busy time. Python's own time is not in
      it: ``stage_host_ms`` has the wall time of each stage's call (launches and Python
      tracing, plus any wait the stage makes itself, e.g. reading a count back).
      :meth:`finish` reads the history, which waits for the launched kernels: the run ends
      evaluated, as a frame that is shown must. The history is read and cleared: a caller
      that keeps its own history on loses what it had gathered before :meth:`start`.
      Measured on Dr.Jit 1.5: the history flag is part of a frozen function's key, so a
      function replayed with it off records once more the first time it runs with it on
      (and keeps both recordings); reading the history costs about 10 microseconds per
      entry (the entries' IR is copied into Python), 2-4 ms for a pipeline frame of a few
      hundred entries on the CPU backend. ``read=False`` (the pipeline's frames between
      two read ones, ``Pipeline.timing_every``): the history is on while the stages run
      (the same recordings replay as in a read frame) and cleared unread at :meth:`finish`,
      which then waits for nothing and returns ``stage_host_ms`` alone.
    * ``"sync"``: the device synchronised after each stage (``dr.sync_thread``), its wall
      time; a synchronisation the real-time path does not make.
    * ``"none"``: no per-stage time.

    :meth:`finish` returns the frame header's fields: ``stage_ms`` (every mode; empty for
    ``none``) and, for ``kernels``, ``stage_host_ms``, ``stage_kernels`` (per stage
    ``launched``: its JIT kernels, ``replayed``: those replayed by a frozen function) and
    ``kernel_ms`` (every entry of the run, markers excluded)."""

    def __init__(self, mode: str, index_type=None, read: bool = True):
        check_stage_timing(mode)
        self.mode = mode
        #: ``kernels`` only: read the history at :meth:`finish` (False: the history is on
        #: while the stages run, as in a read frame, so that frozen functions replay the same
        #: recording, but no marker is written and the history is cleared unread; only
        #: ``stage_host_ms`` is returned)
        self.read = bool(read)
        self.index_type = index_type  # the backend's UInt32 (the marker's type)
        self.names: list[str] = []
        self.host: list[float] = []
        #: stage -> milliseconds computed outside Dr.Jit (:meth:`stage_done`)
        self.external: dict[str, float] = {}
        self._was_on = False
        self._t = 0.0

    def _mark(self) -> None:
        import drjit as dr

        if self.index_type is None:
            from .backend import mi

            self.index_type = mi.UInt32
        dr.opaque(self.index_type, 1, MARKER_WIDTH)  # a memset, launched and not waited for

    def start(self) -> None:
        import drjit as dr

        self._t = time.perf_counter()
        if self.mode == "kernels":
            self._was_on = bool(dr.flag(dr.JitFlag.KernelHistory))
            if not self._was_on:
                dr.kernel_history_clear()
                dr.set_flag(dr.JitFlag.KernelHistory, True)
            if self.read:
                self._mark()

    def stage_done(self, name: str, external_ms: float = 0.0) -> None:
        """After stage ``name`` launched its work (its outputs ``dr.eval``'d).
        ``external_ms``: what the stage computed outside Dr.Jit (Intel Open Image Denoise on
        the host), which no kernel history sees: ``kernels`` adds it to the stage's
        ``stage_ms`` and lists it in ``stage_external_ms`` (``sync`` already has it in its
        wall time)."""
        import drjit as dr

        if self.mode == "none":
            return
        if self.mode == "sync":
            dr.sync_thread()
        elif self.read:
            self._mark()
        t = time.perf_counter()
        self.names.append(name)
        self.host.append(1000.0 * (t - self._t))
        if external_ms:
            self.external[name] = self.external.get(name, 0.0) + float(external_ms)
        self._t = t

    def finish(self) -> dict:
        """The per-stage fields (class docstring); waits for the launched work."""
        import drjit as dr

        if self.mode == "none":
            return {"stage_ms": {}}
        if self.mode == "sync":
            return {"stage_ms": dict(zip(self.names, self.host, strict=True))}
        if not self.read:  # nothing waited for, nothing copied into Python
            if not self._was_on:
                dr.kernel_history_clear()
                dr.set_flag(dr.JitFlag.KernelHistory, False)
            return {"stage_host_ms": dict(zip(self.names, self.host, strict=True))}
        try:
            history = dr.kernel_history()
        finally:
            if not self._was_on:
                dr.set_flag(dr.JitFlag.KernelHistory, False)
        out = attribute(history, self.names, self.host)
        if self.external:
            out["stage_external_ms"] = dict(self.external)
            if out.get("stage_ms") is not None:
                for name, ms in self.external.items():
                    out["stage_ms"][name] += ms
        return out


def _is_marker(entry: dict) -> bool:
    import drjit as dr

    return entry.get("type") == dr.KernelType.Memset and entry.get("size") == MARKER_WIDTH


def attribute(history: list[dict], names: list[str], host_ms: list[float]) -> dict:
    """:class:`StageClock`'s fields from a kernel ``history`` (``dr.kernel_history()``) in
    which stage ``names[k]``'s entries lie between the ``k``-th and ``k+1``-th markers.
    Entries before the first marker are not the stages' (left out). If the markers are not
    exactly one more than the stages (another memset of the marker's width), the per-stage
    fields are None: nothing is attributed by guess."""
    import drjit as dr

    marks = [i for i, e in enumerate(history) if _is_marker(e)]
    total = sum(float(e["execution_time"]) for i, e in enumerate(history)
                if i >= (marks[0] if marks else 0) and not _is_marker(e))
    out: dict = {"stage_host_ms": dict(zip(names, host_ms, strict=True)), "kernel_ms": total}
    if len(marks) != len(names) + 1:
        out.update(stage_ms=None, stage_kernels=None)
        return out
    ms, kernels = {}, {}
    for k, name in enumerate(names):
        entries = history[marks[k] + 1:marks[k + 1]]
        ms[name] = sum(float(e["execution_time"]) for e in entries)
        jit = [e for e in entries if e.get("type") == dr.KernelType.JIT]
        kernels[name] = {"launched": len(jit), "replayed": sum(
            1 for e in jit if e.get("recording_mode") == dr.KernelRecordingMode.Replayed)}
    out.update(stage_ms=ms, stage_kernels=kernels)
    return out
