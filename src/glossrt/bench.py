"""Benchmarks run by ``glossrt bench``: registered functions, warm-up, median of repeats.

Each benchmark returns a dict of measurements; ratios are always measured side by side in
the same run (machines are noisy). The device and versions are recorded with the results.
"""

from __future__ import annotations

import functools
import json
import platform
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from . import backend
from .errors import GlossrtError
from .timing import MIN_SAMPLE, paired_ratio, round_robin

BENCHMARKS: dict[str, Callable[[BenchContext], dict]] = {}


@dataclass
class BenchContext:
    size: tuple[int, int] = (640, 360)
    warmup: int = 3
    repeats: int = 9
    #: shortest time of one sample (s): faster calls are repeated within it
    #: (see :func:`glossrt.timing.round_robin`)
    min_sample: float = MIN_SAMPLE
    extra: dict = field(default_factory=dict)

    @property
    def turns(self) -> int:
        """Repeats of a :func:`glossrt.timing.round_robin` (at least 3, so a median of ratios
        means something)."""
        return max(3, self.repeats)


def benchmark(name: str):
    """Register ``fn(ctx) -> dict`` as benchmark ``name``."""

    def deco(fn):
        BENCHMARKS[name] = fn
        return fn

    return deco


@benchmark("render-vs-mitsuba-path")
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


@benchmark("denoisers")
def denoisers(ctx: BenchContext) -> dict:
    """Steady-state time per frame of each denoiser on a static glossy-cornell sequence (4
    frames cycling after 8 warm-up frames, so the temporal filters' history is full), the
    methods called in turn (:func:`round_robin`); ratios against OIDN and against plain
    a-trous as medians of per-repeat ratios."""
    import drjit as dr

    from . import denoise, render, scenes
    from .experiments import _available

    # a static camera and scene: frames i and i + 1 differ only in their noise, so the
    # reprojection succeeds everywhere and the history stays full while the 4 frames cycle
    # (feeding one frame over and over with its motion vectors would disocclude most pixels
    # and time the spatial-variance fallback instead of the steady state)
    r = render.Renderer(scenes.load_static("glossy-cornell", size=ctx.size))
    frames = [r.render(i) for i in range(4)]
    configs = {
        "svgf": ("svgf", {}),
        "svgf-lobe": ("svgf-lobe", {}),
        "svgf-paper-2-signals": ("svgf", {"signals": "direct-indirect"}),
        "svgf-1-signal": ("svgf", {"signals": "single"}),
        "atrous": ("atrous", {}),
        "atrous-temporal": ("atrous-temporal", {}),
        "oidn": ("oidn", {}),
    }
    runners = {}
    for name, (method, params) in configs.items():
        if _available(method):
            continue
        d = denoise.make(method, **params)
        for i in range(8):
            dr.eval(d(frames[i % 4]))
        counter = {"i": 0}

        def step(d=d, counter=counter):
            counter["i"] += 1
            dr.eval(d(frames[counter["i"] % 4]))

        runners[name] = step
    times = round_robin(runners, 1, ctx.turns, ctx.min_sample)
    med = {k: statistics.median(v) for k, v in times.items()}
    out = {"scene": "glossy-cornell (static camera)", "size": list(ctx.size),
           "seconds": med, "repeats": ctx.turns, "samples": times}
    if "oidn" in times:
        out["oidn_over"] = {k: paired_ratio(times["oidn"], v) for k, v in times.items()}
    if "atrous" in times:
        out["cost_vs_atrous"] = {k: paired_ratio(v, times["atrous"]) for k, v in times.items()}
    return out


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


@benchmark("lobe-weights")
def lobe_weights(ctx: BenchContext) -> dict:
    """Cost of Tokuyoshi 2015's lobe weight over the normal weight at the same footprint,
    interleaved in one run on ``roughness-map``: the cross-bilateral filter (13x13 window) and
    joint bilateral upsampling from 1/2 and 1/4 resolution (4x4 samples), each for the
    specular channel alone (``spec``: the weight function is swapped) and for both indirect
    channels (``both``: the diffuse one keeps the normal weight, so lobe mode computes both
    weights); each traced anew per call and frozen (``frozen_on_frames``: kernels replayed,
    no Python tracing, the real-time path). Target: lobe / normal <= 1.15."""
    import drjit as dr

    from . import render, scenes
    from .denoise import bilateral, upsample

    w, h = ctx.size
    full = render.Renderer(scenes.load("roughness-map", size=(w, h))).render(0)
    lows = {f: render.Renderer(scenes.load("roughness-map", size=(w // f, h // f))).render(0)
            for f in (2, 4) if w % f == 0 and h % f == 0}
    sets = {"spec": ("indirect_specular",), "both": ("indirect_diffuse", "indirect_specular")}
    cases = {}
    for cname, ch in sets.items():
        for weight in ("normal", "lobe"):
            fns = {"bilateral": (lambda fr, wt=weight, ch=ch: bilateral(
                fr, weight=wt, channels=ch), (full,))}
            for f, low in lows.items():
                fns[f"upsample-1/{f}"] = (lambda fr, lo, wt=weight, ch=ch: upsample(
                    fr, lo, weight=wt, channels=ch), (full, low))
            for op, (fn, frames) in fns.items():
                cases[f"{op}-{cname}-traced-{weight}"] = (
                    lambda fn=fn, frames=frames: dr.eval(fn(*frames)))
                cases[f"{op}-{cname}-frozen-{weight}"] = frozen_on_frames(fn, *frames)
    times = round_robin(cases, 2, ctx.turns, ctx.min_sample)
    med = {k: statistics.median(v) for k, v in times.items()}
    ratios = {k.replace("-normal", ""): paired_ratio(times[k.replace("-normal", "-lobe")], v)
              for k, v in times.items() if k.endswith("-normal")}
    return {"scene": "roughness-map", "size": [w, h], "seconds": med,
            "ratio_lobe_vs_normal": ratios, "target_ratio": 1.15,
            "repeats": ctx.turns}


@benchmark("ltc")
def ltc(ctx: BenchContext) -> dict:
    """Deferred LTC shading of ``polygon-light``'s G-buffer by its quad light (Heitz et al.
    2016) at the bench size, the light moving between calls: traced anew and frozen
    (``dr.freeze``, the real-time path), with unshadowed Monte Carlo of the same BRDF at 1 spp
    for scale, interleaved in one run; the result stays on the device (no NumPy copy).
    GPU target (issue 5): frozen, 1920x1080, at most 0.5 ms."""
    import drjit as dr

    from . import render, scenes
    from .lights.ltc import shade_tensor
    from .lights.mc import render_mc
    from .lights.scene import polygon_lights
    from .lights.shading import fresnel_image

    w, h = ctx.size
    setup = scenes.load("polygon-light", size=(w, h), frames=4)
    r = render.Renderer(setup)
    inputs = []
    for i in range(4):
        gb = r.render(i)
        inputs.append((gb, polygon_lights(setup, i), fresnel_image(setup, gb)))
    state = {"k": 0}

    def step(frozen):
        gb, lights, f0 = inputs[state["k"] % 4]
        state["k"] += 1
        dr.eval(shade_tensor(gb, lights, f0=f0, frozen=frozen))

    gb0, lights0, f00 = inputs[0]
    cases = {"ltc-traced": lambda: step(False), "ltc-frozen": lambda: step(True),
             "mc-1spp": lambda: render_mc(gb0, lights0, 1, f0=f00)}
    times = round_robin(cases, 1, ctx.turns, ctx.min_sample)
    med = {k: statistics.median(v) for k, v in times.items()}
    return {"scene": "polygon-light", "size": [w, h], "lights": 1, "seconds": med,
            "frozen_vs_traced": paired_ratio(times["ltc-frozen"], times["ltc-traced"]),
            "gpu_target_s_at_1920x1080": 0.5e-3}


@benchmark("specaa")
def specaa(ctx: BenchContext) -> dict:
    """Deferred direct shading of ``normal-mapped``'s G-buffer (its point, directional and
    polygon lights; frozen kernels) with each specular antialiasing method, interleaved in
    one run; ratios to unfiltered shading. Target (issue 8): filtering adds at most 10%."""
    from . import specaa_experiments as se

    t = se.timing(size=ctx.size, repeats=ctx.turns, min_sample=ctx.min_sample)
    return {"scene": se.SCENE, **t, "target_ratio": 1.10}


@benchmark("highlights")
def highlights(ctx: BenchContext) -> dict:
    """Kimura & Tokoi's light-shape highlights on ``light-shapes`` at the bench size, the
    light cube maps rendered once: the paper's ellipsoidal sampling and GGX visible normals
    with filtered importance sampling, 4 samples, traced (hash samples, no culling) and
    frozen (the real-time path, result left on the device), beside plain point-light
    shading, called in turn. GPU target (issue 7): 1920x1080, 4 samples, at most 1 ms."""
    import drjit as dr

    from .highlight_experiments import _frame
    from .lights.highlights import HighlightRenderer, shade_plain

    setup, gb, lights, f0 = _frame(ctx.size)
    maps = HighlightRenderer().maps(setup, 0, lights)
    cases = {"plain": lambda: shade_plain(gb, lights, f0)}
    state = {"k": 0}
    for dist in ("ellipsoidal", "ggx"):
        traced = HighlightRenderer(samples=4, distribution=dist, sampling="hash", cull=False)
        frozen = HighlightRenderer(samples=4, distribution=dist, sampling="hash", cull=False,
                                   frozen=True)
        cases[f"{dist}-4-traced"] = lambda r=traced: r(gb, lights, maps, f0)

        def replay(r=frozen):
            state["k"] += 1  # a new frame index: new random numbers, same kernels
            dr.eval(r.shade_tensor(gb, maps, f0, state["k"]))

        cases[f"{dist}-4-frozen"] = replay
    times = round_robin(cases, 2, ctx.turns, ctx.min_sample)
    return {"scene": "light-shapes", "size": list(ctx.size),
            "seconds": {k: statistics.median(v) for k, v in times.items()},
            "ratio_to_plain": {k: paired_ratio(v, times["plain"]) for k, v in times.items()},
            "gpu_target_s_at_1920x1080": 1e-3}


@benchmark("bspvt")
def bspvt(ctx: BenchContext) -> dict:
    """Okuno & Iwasaki's BSPVT shadows on ``polygon-light`` (4965 vertices): precomputation
    (visibility rays and trees, 32x32 cube maps, 8x8 below 320 pixels wide: the 64x64
    default is in ``glossrt experiment --which bspvt``) per vertex, and shadowed shading of a
    frame at the bench size per vertex (the paper's mode) and per pixel, each with the
    one-kernel traversal (default), the per-level wavefront and frozen (the fused traversal
    replayed), with unshadowed LTC and the ratio estimator at 1 spp beside them, interleaved
    in one run; and the tree build alone with each array engine (NumPy, Dr.Jit) at 64x64 on
    512 vertices (``tree_engines``). GPU targets (issue 6): build 50x faster than the
    paper's 2.7 min for 17K vertices; per-vertex shading of 512x512 at 200 fps or more."""
    from . import render, scenes
    from .lights.bspvt import build_scene_trees, shade_bspvt
    from .lights.ltc import shade_frame
    from .lights.ratio import render_ratio
    from .lights.scene import polygon_lights
    from .lights.shading import fresnel_image

    w, h = ctx.size
    setup = scenes.load("polygon-light", size=(w, h))
    res = 32 if w >= 320 else 8  # tiny bench sizes (tests) build tiny maps
    t0 = time.perf_counter()
    trees = build_scene_trees(setup.scene, res, progress=False)
    build_s = time.perf_counter() - t0
    engines = _bspvt_engines(setup.scene, 64 if w >= 320 else 8, 512 if w >= 320 else 16)
    gb = render.Renderer(setup).render(0)
    lights = polygon_lights(setup, 0)
    f0 = fresnel_image(setup, gb)
    cases = {}
    for mode in ("vertex", "pixel"):
        for kind, kw in (("", {}), ("-wavefront", {"traversal": "wavefront"}),
                         ("-frozen", {"frozen": True})):
            cases[f"bspvt-{mode}{kind}"] = functools.partial(
                shade_bspvt, setup.scene, gb, trees, lights, mode,
                f0=f0 if mode == "pixel" else None, **kw)
    cases |= {"ltc": lambda: shade_frame(gb, lights, f0=f0),
              "ratio-1spp": lambda: render_ratio(gb, lights, setup.scene, spp=1, f0=f0)}
    times = round_robin(cases, 1, ctx.turns, ctx.min_sample)
    med = {k: statistics.median(v) for k, v in times.items()}
    st = trees.stats()
    return {"scene": "polygon-light", "size": [w, h], "vertices": st["vertices"],
            "resolution": res, "build_s": build_s,
            "build_ms_per_vertex": 1000 * build_s / st["vertices"],
            "visibility_s": trees.info["visibility_seconds"],
            "leaves_per_vertex": st["leaves_per_vertex"], "data_mb": st["data_mb"],
            "tree_engines": engines, "seconds": med}


def _bspvt_engines(scene, res: int, count: int) -> dict:
    """The tree build alone (visibility computed once) with each array engine on ``count``
    vertices spread over the scene at ``res`` x ``res`` maps: ms per vertex, the time
    extrapolated to the paper's 17K-vertex model (issue 6's GPU target: 2.7 min / 50 =
    3.24 s), and whether the engines' trees are identical."""
    import numpy as np

    from .lights.bspvt import build as bspvt

    pos, nrm, _ = bspvt.scene_vertices(scene)
    sel = np.linspace(0, len(pos) - 1, min(count, len(pos))).astype(int)
    vis = bspvt.visibility_cubemaps(bspvt.occluders(scene), pos[sel], nrm[sel], res,
                                    progress=False)
    out, built = {"resolution": res, "vertices": len(sel), "target_s_17k": 2.7 * 60 / 50}, {}
    for engine in bspvt.ENGINES:
        bspvt.build_trees(vis[:2], progress=False, engine=engine)  # compile / warm up
        t0 = time.perf_counter()
        built[engine] = bspvt.build_trees(vis, progress=False, engine=engine)
        dt = time.perf_counter() - t0
        out[engine] = {"seconds": dt, "ms_per_vertex": 1000 * dt / len(sel),
                       "extrapolated_17k_s": dt / len(sel) * 17000}
    a, b = built["numpy"], built["drjit"]
    out["identical"] = all(np.array_equal(getattr(a, k), getattr(b, k))
                           for k in ("lines", "children", "leaf_value", "roots"))
    return out


def check_args(repeats: int = 9, warmup: int = 3, min_sample: float = MIN_SAMPLE,
               names: list[str] | None = None) -> None:
    """Refuse, before any benchmark runs, repeats < 1, a negative warm-up or shortest sample,
    and unknown benchmark names."""
    unknown = [n for n in names or [] if n not in BENCHMARKS]
    if unknown:
        raise GlossrtError(f"unknown benchmark(s) {unknown}; available: {sorted(BENCHMARKS)}")
    if repeats < 1:
        raise GlossrtError(f"bench: --repeats must be >= 1, got {repeats}")
    if warmup < 0:
        raise GlossrtError(f"bench: --warmup must be >= 0, got {warmup}")
    if not min_sample >= 0:
        raise GlossrtError(f"bench: min_sample must be >= 0 seconds, got {min_sample}")


def run(names: list[str] | None = None, size: tuple[int, int] = (640, 360), warmup: int = 3,
        repeats: int = 9, log: Callable[[str], None] = print,
        min_sample: float = MIN_SAMPLE) -> dict:
    """Run the named (default: all) benchmarks and return a JSON-able dict."""
    check_args(repeats=repeats, warmup=warmup, min_sample=min_sample, names=names)
    info = backend.info()
    ctx = BenchContext(size=size, warmup=warmup, repeats=repeats, min_sample=min_sample)
    if ctx.turns != repeats:
        log(f"bench: side-by-side ratios take {ctx.turns} repeats (asked for {repeats})")
    results = {}
    for name in names or list(BENCHMARKS):
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
        "results": results,
    }
