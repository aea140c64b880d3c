"""Benchmarks run by ``glossrt bench``: registered functions, warm-up, median of repeats.

Each benchmark returns a dict of measurements; ratios are always measured side by side in
the same run (machines are noisy). The device and versions are recorded with the results.
The generic case (``render-vs-mitsuba-path``) is below; each paper's case is registered by
its module in :mod:`glossrt.experiments` (:func:`glossrt.report.registry.benchmark`).
"""

from __future__ import annotations

import json
import platform
import statistics
from collections.abc import Callable

from . import backend, experiments
from .errors import GlossrtError
from .report.registry import BENCHMARKS, BenchContext, benchmark, registered_benchmarks
from .timing import MIN_SAMPLE, paired_ratio, round_robin

experiments.load_all()  # the papers' benchmark cases


@benchmark("render-vs-mitsuba-path", order=10)
def render_vs_mitsuba(ctx: BenchContext) -> dict:
    """glossrt's G-buffer + separated 1 spp frame (frozen) vs Mitsuba's own 1 spp ``path``
    integrator, same scene (glossy-cornell), size and max_depth, interleaved in one run."""
    import drjit as dr
    import mitsuba as mi

    from . import render, scenes

    setup = scenes.load("glossy-cornell", size=ctx.size)
    r = render.Renderer(setup, frozen=True)
    integrator = mi.load_dict({"type": "path", "max_depth": r.mitsuba_max_depth})
    counter = {"f": 0}

    def ours():
        counter["f"] += 1
        r.trace(0, dr.arange(mi.UInt32, ctx.size[0] * ctx.size[1]),
                dr.opaque(mi.UInt32, counter["f"]))

    def ours_frame():
        counter["f"] += 1
        r.render(counter["f"] % 60)

    def theirs():
        counter["f"] += 1
        img = mi.render(setup.scene, sensor=setup.sensor, integrator=integrator, spp=1,
                        seed=counter["f"])
        dr.eval(img)

    times = round_robin({"glossrt_kernels": ours, "glossrt_frame": ours_frame,
                         "mitsuba_path": theirs}, ctx.warmup, ctx.turns,
                       ctx.min_sample)
    med = {k: statistics.median(v) for k, v in times.items()}
    return {
        "scene": "glossy-cornell",
        "size": list(ctx.size),
        "max_depth": r.mitsuba_max_depth,
        "glossrt_trace_s": med["glossrt_kernels"],
        "glossrt_frame_s": med["glossrt_frame"],
        "mitsuba_path_1spp_s": med["mitsuba_path"],
        "ratio_trace_vs_path": paired_ratio(times["glossrt_kernels"], times["mitsuba_path"]),
        "ratio_frame_vs_path": paired_ratio(times["glossrt_frame"], times["mitsuba_path"]),
        "target_ratio": 1.5,
        "repeats": ctx.turns,
    }


def _echo(x):
    """A trivial work item (the cluster benchmark's per-task overhead)."""
    return x


#: options of the cluster case (``--case-option KEY=VALUE``)
CLUSTER_OPTIONS = {
    "cluster_spp": "samples per pixel of the reference timed with 1 and 2 workers (1024)",
    "cluster_bspvt_resolution": "BSPVT cube-map resolution of the timed build (16)",
    "cluster_workers": "worker counts compared, e.g. [1, 2] (default)",
}


@benchmark("cluster", order=90)
def cluster_scaling(ctx: BenchContext) -> dict:
    """Scale-out on Ray (issue 27): a local Ray cluster with 1, then 2 worker slots, each
    running (after a warm-up that loads the scene and compiles the kernels in every worker)
    a glossy-cornell reference of ``cluster_spp`` samples at the bench size as sample blocks
    (glossrt.render.blocks), and polygon-light's BSPVT build in 256-vertex chunks; plus the
    per-task overhead of 400 trivial items. Speed-up = time with 1 slot / time with 2."""
    import time

    from . import cluster, render, scenes
    from .lights.bspvt.scene import build_scene_trees
    from .render import blocks

    spp = int(ctx.extra.get("cluster_spp", 1024))
    res_b = int(ctx.extra.get("cluster_bspvt_resolution", 16))
    workers = [int(n) for n in ctx.extra.get("cluster_workers", [1, 2])]
    setup = scenes.load("glossy-cornell", size=ctx.size)
    r = render.Renderer(setup)
    job = blocks.reference_job("glossy-cornell", ctx.size)
    out: dict = {"scene": "glossy-cornell", "size": list(ctx.size), "spp": spp,
                 "bspvt_scene": "polygon-light", "bspvt_resolution": res_b, "runs": {}}
    images = {}
    for n in workers:
        t_start = time.perf_counter()
        with cluster.connect(f"local:{n}") as c:
            started = time.perf_counter() - t_start
            t0 = time.perf_counter()
            cluster.map_items(_echo, list(range(400)), cluster=c, progress=False)
            per_task = (time.perf_counter() - t0) / 400
            # warm-up: every worker loads the scene and compiles its kernels once
            list(blocks.reference_frames(r, job, [0], 16 * n, cluster=c, block_spp=1))
            t0 = time.perf_counter()
            f = next(blocks.reference_frames(r, job, [0], spp, cluster=c))
            t_ref = time.perf_counter() - t0
            images[n] = f.numpy("color")
            build_scene_trees("polygon-light", resolution=4, progress=False, cluster=c,
                              chunk_vertices=4096)  # warm-up
            t0 = time.perf_counter()
            build_scene_trees("polygon-light", resolution=res_b, progress=False, cluster=c,
                              chunk_vertices=256)
            t_bspvt = time.perf_counter() - t0
        out["runs"][str(n)] = {"start_s": started, "per_task_ms": 1000.0 * per_task,
                               "reference_s": t_ref, "bspvt_build_s": t_bspvt}
    import numpy as np

    if len(workers) >= 2:
        a, b = (out["runs"][str(n)] for n in workers[:2])
        out["speedup_reference"] = a["reference_s"] / b["reference_s"]
        out["speedup_bspvt"] = a["bspvt_build_s"] / b["bspvt_build_s"]
        out["bit_identical"] = bool(np.array_equal(images[workers[0]], images[workers[1]]))
    out["target_speedup"] = 1.7
    return out


def case_options() -> dict[str, str]:
    """Every option a benchmark case takes (``--case-option KEY=VALUE``): name -> help."""
    from .experiments import pipeline

    return {**pipeline.BENCH_OPTIONS, **CLUSTER_OPTIONS}


def parse_case_options(items: list[str] | None) -> dict:
    """``KEY=VALUE`` strings as a dict; a VALUE that reads as JSON (a number, true/false, an
    object) is that value, else the string. Unknown keys and bad values are refused (one
    GlossrtError line) before any benchmark runs."""
    import json

    out = {}
    for item in items or []:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise GlossrtError(f"bench: --case-option takes KEY=VALUE, got {item!r}")
        try:
            out[key] = json.loads(value)
        except ValueError:
            out[key] = value
    check_case_options(out)
    return out


def check_case_options(options: dict) -> None:
    known = case_options()
    unknown = sorted(k for k in options if k not in known)
    if unknown:
        raise GlossrtError(f"bench: unknown case option(s) {unknown}; available: "
                           + "; ".join(f"{k}: {v}" for k, v in known.items()))
    from .experiments import pipeline

    pipeline.check_bench_options(options)


def check_args(repeats: int = 9, warmup: int = 3, min_sample: float = MIN_SAMPLE,
               names: list[str] | None = None, options: dict | None = None) -> None:
    """Refuse, before any benchmark runs, repeats < 1, a negative warm-up or shortest sample,
    unknown benchmark names and unknown or bad case options."""
    unknown = [n for n in names or [] if n not in BENCHMARKS]
    if unknown:
        raise GlossrtError(f"unknown benchmark(s) {unknown}; available: {sorted(BENCHMARKS)}")
    check_case_options(options or {})
    if repeats < 1:
        raise GlossrtError(f"bench: --repeats must be >= 1, got {repeats}")
    if warmup < 0:
        raise GlossrtError(f"bench: --warmup must be >= 0, got {warmup}")
    if not min_sample >= 0:
        raise GlossrtError(f"bench: min_sample must be >= 0 seconds, got {min_sample}")


def run(names: list[str] | None = None, size: tuple[int, int] = (640, 360), warmup: int = 3,
        repeats: int = 9, log: Callable[[str], None] = print,
        min_sample: float = MIN_SAMPLE, options: dict | None = None) -> dict:
    """Run the named (default: all) benchmarks and return a JSON-able dict. ``options``:
    the cases' own options (:func:`case_options`)."""
    check_args(repeats=repeats, warmup=warmup, min_sample=min_sample, names=names,
               options=options)
    info = backend.info()
    ctx = BenchContext(size=size, warmup=warmup, repeats=repeats, min_sample=min_sample,
                       extra=dict(options or {}))
    if ctx.turns != repeats:
        log(f"bench: side-by-side ratios take {ctx.turns} repeats (asked for {repeats})")
    results = {}
    for name in names or registered_benchmarks():
        log(f"bench {name} ...")
        results[name] = BENCHMARKS[name](ctx)
        log("  " + json.dumps(results[name]))
    return {
        "device": info["device"],
        "variant": info["variant"],
        "versions": {k: info[k] for k in ("glossrt", "mitsuba", "drjit")},
        "machine": {"platform": platform.platform(), "processor": platform.processor()},
        "size": list(size),
        "min_sample_s": min_sample,
        "case_options": dict(options or {}),
        "results": results,
    }
