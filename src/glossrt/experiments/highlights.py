"""Measurements behind docs/RESULTS.md for light-shape highlights (Kimura & Tokoi; issue 7).

* :func:`convergence`: on ``light-shapes``, RMSE against the converged reference of the same
  reflection model (many hash-sampled normals, no culling) per sphere roughness, for the
  ellipsoidal distribution with the normal texture and the hash generator at 1-64 samples,
  the 13-point regular pattern, and GGX visible-normal sampling with filtered importance
  sampling (against the GGX reference);
* :func:`convergence` also scores the converged references and the paper's 4-sample method
  against Mitsuba's own ``direct`` integrator on the same scene with the spheres' diffuse
  reflectance set to 0 (their specular reflection of the lights alone: the yardstick of the
  BRDF and of the light map's probe approximation), per sphere;
* :func:`timing`: the paper's Table 1 as ratios measured side by side in one run: plain
  shading (point lights, no shape), regular sampling, random sampling (4), each with and
  without bounding-sphere culling.

The paper's report section (``highlights``), benchmark case (``highlights``) and ``glossrt
experiment --which highlights`` are registered here.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..report import DemoContext, Report, register_section
from ..report.registry import (
    BenchContext,
    benchmark,
    finish_experiment,
    markdown_table,
    register_experiment,
    section_size,
)
from ..timing import paired_ratio, round_robin

SAMPLE_COUNTS = (1, 4, 16, 64)


def _frame(size, frame_index: int = 0):
    from .. import render, scenes
    from ..lights.scene import polygon_lights
    from ..lights.shading import fresnel_image

    setup = scenes.load("light-shapes", size=size)
    gb = render.Renderer(setup).render(frame_index)
    return setup, gb, polygon_lights(setup, frame_index), fresnel_image(setup, gb)


@dataclass
class Convergence:
    size: tuple[int, int]
    ref_samples: int
    alphas: list[float]
    rows: list[dict] = field(default_factory=list)
    images: dict[str, np.ndarray] = field(default_factory=dict)
    direct_rows: list[dict] = field(default_factory=list)

    def direct_markdown(self) -> str:
        """Mean absolute error over the mean against Mitsuba's ``direct`` (specular only)."""
        head = "| method | " + " | ".join(f"alpha {a:g}" for a in self.alphas) + " |"
        lines = [head, "|" + "---|" * (len(self.alphas) + 1)]
        for r in self.direct_rows:
            lines.append(f"| {r['method']} | " + " | ".join(f"{v:.3f}" for v in r["rel"])
                         + " |")
        return "\n".join(lines)

    def markdown(self) -> str:
        head = "| method | samples | " + " | ".join(f"alpha {a:g}" for a in self.alphas) + \
            " | all |"
        lines = [head, "|" + "---|" * (len(self.alphas) + 3)]
        for r in self.rows:
            lines.append(f"| {r['method']} | {r['samples']} | "
                         + " | ".join(f"{v:.4f}" for v in r["rmse"]) + f" | {r['all']:.4f} |")
        return "\n".join(lines)

    def montage(self, path: str | Path) -> Path:
        """Every image tone-mapped, one per row, titled with its key."""
        from ..report.figures import Panel, montage
        from ..report.page import tonemap

        keys = list(self.images)
        w, h = self.size
        grid = [[Panel(tonemap(self.images[k]), k)] for k in keys]
        return montage(path, grid, (8, len(keys) * 8 * h / w + 0.3), dpi=100)


def convergence(size=(320, 180), ref_samples: int = 2048, counts=SAMPLE_COUNTS,
                progress: Callable[[str], None] | None = None) -> Convergence:
    """RMSE per roughness and overall (module docstring)."""
    from ..lights.highlights import HighlightRenderer, reference, shade_plain

    say = progress or (lambda _m: None)
    setup, gb, lights, f0 = _frame(size)
    hr = HighlightRenderer()
    maps = hr.maps(setup, 0, lights)
    rough = gb.numpy("roughness")[..., 0]
    hit = gb.numpy("mesh_id")[..., 0] > 0
    from ..scenes.library import LIGHT_SHAPES_ALPHAS

    alphas = list(LIGHT_SHAPES_ALPHAS)
    masks = [hit & np.isclose(rough, a, rtol=1e-4) for a in alphas]
    refs = {}
    for dist in ("ellipsoidal", "ggx"):
        say(f"reference ({ref_samples} samples): {dist}")
        refs[dist] = reference(gb, lights, maps, f0, dist, ref_samples)
    res = Convergence(tuple(size), ref_samples, alphas)

    def add(method, samples, img, ref):
        err = [float(np.sqrt(np.mean((img - ref)[m] ** 2))) for m in masks]
        res.rows.append({"method": method, "samples": samples, "rmse": err,
                         "all": float(np.sqrt(np.mean((img - ref)[hit] ** 2)))})

    res.images["plain shading (point lights)"] = shade_plain(gb, lights, f0)
    for n in counts:
        say(f"{n} samples")
        for sampling in ("texture", "hash"):
            img = HighlightRenderer(n, "ellipsoidal", sampling)(gb, lights, maps, f0)
            add(f"ellipsoidal, {sampling}", n, img, refs["ellipsoidal"])
            if n == 4 and sampling == "texture":
                res.images["ellipsoidal, normal texture, 4 samples (the paper)"] = img
        img = HighlightRenderer(n, "ggx", "hash")(gb, lights, maps, f0)
        add("GGX VNDF + FIS", n, img, refs["ggx"])
        if n == 4:
            res.images["GGX visible normals + FIS, 4 samples"] = img
    img = HighlightRenderer(13, "ellipsoidal", "regular")(gb, lights, maps, f0)
    add("ellipsoidal, regular", 13, img, refs["ellipsoidal"])
    res.images["ellipsoidal, 13-point regular"] = img
    res.images[f"ellipsoidal reference ({ref_samples})"] = refs["ellipsoidal"]
    res.images[f"GGX reference ({ref_samples})"] = refs["ggx"]
    say(f"Mitsuba's direct integrator ({ref_samples} spp), spheres' diffuse reflectance 0")
    direct = _specular_direct(size, ref_samples)
    paper = res.images["ellipsoidal, normal texture, 4 samples (the paper)"] \
        if "ellipsoidal, normal texture, 4 samples (the paper)" in res.images else None
    for method, img in (("GGX reference (the pixel's own lobe)", refs["ggx"]),
                        ("ellipsoidal reference", refs["ellipsoidal"]),
                        ("ellipsoidal, normal texture, 4 (the paper)", paper)):
        if img is not None:
            res.direct_rows.append({"method": method, "rel": [
                float(np.mean(np.abs(img - direct)[m]) / max(np.mean(direct[m]), 1e-12))
                for m in masks]})
    return res


def _specular_direct(size, spp: int) -> np.ndarray:
    """Mitsuba's ``direct`` integrator on ``light-shapes`` with the spheres' diffuse
    reflectance 0: the spheres show their specular reflection of the lights alone (what the
    highlight methods compute), frame 0."""
    from .. import render
    from ..scenes import from_spec
    from ..scenes.library import light_shapes

    spec = light_shapes()
    for key, shape in spec.scene_dict.items():
        if key.startswith("sphere"):
            shape["bsdf"]["diffuse_reflectance"] = {"type": "rgb", "value": [0.0, 0.0, 0.0]}
    r = render.Renderer(from_spec("light-shapes-specular", spec, size=size))
    return np.array(r.render_mitsuba(0, spp, integrator="direct"))


def timing(size=(640, 360), repeats: int = 5) -> dict:
    """Table 1 as ratios to plain shading, interleaved (module docstring); the light maps are
    rendered once (their cost, per frame for moving lights, is reported apart)."""
    import drjit as dr

    from ..lights.highlights import HighlightRenderer, shade_plain

    setup, gb, lights, f0 = _frame(size)
    hr = HighlightRenderer()
    t0 = time.perf_counter()
    maps = hr.maps(setup, 0, lights)
    dr.sync_thread()
    maps_s = time.perf_counter() - t0
    cases = {"plain": lambda: shade_plain(gb, lights, f0)}
    for cull in (False, True):
        tag = "culling" if cull else "no culling"
        for name, kw in (("regular 13", {"samples": 13, "sampling": "regular"}),
                         ("random 4 (texture)", {"samples": 4, "sampling": "texture"}),
                         ("random 4 (hash)", {"samples": 4, "sampling": "hash"}),
                         ("GGX FIS 4", {"samples": 4, "distribution": "ggx"})):
            r = HighlightRenderer(cull=cull, **kw)
            cases[f"{name}, {tag}"] = (lambda r=r: r(gb, lights, maps, f0))
    times = round_robin(cases, 1, repeats)  # warm-up: compile
    med = {k: statistics.median(v) for k, v in times.items()}
    return {"size": list(size), "seconds": med, "maps_seconds": maps_s,
            "ratio_to_plain": {k: paired_ratio(v, times["plain"]) for k, v in times.items()}}


def timing_markdown(t: dict) -> str:
    lines = ["| method | ms / frame | x plain |", "|---|---|---|"]
    for k, v in t["seconds"].items():
        lines.append(f"| {k} | {1000 * v:.1f} | {t['ratio_to_plain'][k]:.2f} |")
    lines.append(f"\n(light cube maps, 6 x 128^2 per object, rendered once: "
                 f"{1000 * t['maps_seconds']:.0f} ms)")
    return "\n".join(lines)


@register_section("highlights", order=75)
def section_highlights(ctx: DemoContext, report: Report) -> None:
    t0 = time.perf_counter()
    scale, size = section_size(ctx, (160, 90), 2, (32, 18))
    ref = 256 if scale >= 1 else 32
    conv = convergence(size=size, ref_samples=ref, counts=(4, 16) if scale >= 1 else (4,),
                       progress=ctx.say)
    s = report.section(
        "Light-shape highlights",
        "Kimura & Tokoi 2004 on light-shapes: the lights rendered into a cube map per object, "
        "sampled with microfacet normals (the paper's ellipsoidal distribution: normal texture "
        "with embedded random numbers, per-pixel hash, 13-point regular pattern; and GGX "
        "visible normals with filtered importance sampling), against the converged reference "
        f"of the same model ({ref} samples), RMSE per sphere roughness. See docs/RESULTS.md.")
    markdown_table(s, conv.markdown(), "RMSE against the same model's reference")
    keys = list(conv.images)
    for i in range(0, len(keys), 3):
        s.images_row([(k, conv.images[k]) for k in keys[i:i + 3]], name=f"highlights_{i}")
    ref_e = conv.images[f"ellipsoidal reference ({ref})"]
    ref_g = conv.images[f"GGX reference ({ref})"]
    s.error_map("highlights_err_paper", conv.images[
        "ellipsoidal, normal texture, 4 samples (the paper)"], ref_e,
        caption="relative error of the paper's method (4 samples) against its reference")
    s.error_map("highlights_err_ggx", conv.images["GGX visible normals + FIS, 4 samples"],
                ref_g, caption="relative error of GGX + FIS (4 samples) against GGX's reference")
    ctx.timings["highlights section"] = time.perf_counter() - t0


@benchmark("highlights", order=60)
def bench_highlights(ctx: BenchContext) -> dict:
    """Kimura & Tokoi's light-shape highlights on ``light-shapes`` at the bench size, the
    light cube maps rendered once: the paper's ellipsoidal sampling and GGX visible normals
    with filtered importance sampling, 4 samples, traced (hash samples, no culling) and
    frozen (the real-time path, result left on the device), beside plain point-light
    shading, called in turn. GPU target (issue 7): 1920x1080, 4 samples, at most 1 ms."""
    import drjit as dr

    from ..lights.highlights import HighlightRenderer, shade_plain

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


@register_experiment("highlights", "Kimura & Tokoi convergence and Table 1 (--size, --spp = "
                     "reference samples)", order=50)
def run_experiment(out, size, args) -> int:
    """Kimura & Tokoi measurements (RESULTS.md): RMSE vs samples per roughness, Table 1."""
    spp = args.spp
    conv = convergence(size=size, ref_samples=spp, progress=print)
    conv.montage(out / "highlights.png")
    t = timing(size=size)
    md = (f"## RMSE against the same model's reference ({size[0]}x{size[1]}, {spp} samples)"
          f"\n\n{conv.markdown()}\n\n## against Mitsuba's direct integrator ({spp} spp, "
          f"the spheres' specular reflection alone; mean absolute error over the mean)\n\n"
          f"{conv.direct_markdown()}\n\n## Table 1 (ratios to plain shading)\n\n"
          f"{timing_markdown(t)}")
    return finish_experiment(out, "highlights", md, "highlights.png",
                             {"rows": conv.rows, "direct": conv.direct_rows, "timing": t})
