"""Measurements behind docs/RESULTS.md for specular antialiasing (Tokuyoshi's evaluation of
Kaplanyan et al. 2016; issue 8), on the ``normal-mapped`` scene.

For each method of :data:`glossrt.specaa.METHODS` (and the rows of :data:`EXTRA`):

* error against two supersampled references (:func:`glossrt.specaa.reference`: the
  unfiltered shading averaged over ``spp`` stratified sub-pixel positions) in RMSE and
  HDR-FLIP, on frame 0 and over the whole image: the box pixel filter, and the Gaussian pixel
  filter of variance 0.25 px^2 that Tokuyoshi's eq. 1 assumes (``*_gauss``);
* the bias on a flat region (the ``floor_flat`` strip, no normal map, eroded by one pixel so
  its quads see no other mesh): the mean of ``image - reference`` relative to the reference's
  mean there (0 = unbiased; filtering that blurs highlights on a flat mirror shows here);
* temporal error under the scene's slow camera motion: :func:`glossrt.metrics.temporal_error`
  (mean absolute luminance change between consecutive frames) of each method's sequence and
  of a supersampled (box-filter) reference sequence (``temporal_spp``), which changes only
  because the
  view does; and the *flicker*, the part of a method's frame-to-frame change the reference
  does not have: ``mean_t mean_pixels |(L_t - L_{t-1}) - (R_t - R_{t-1})|`` (luminance ``L``
  of the method, ``R`` of the reference).

The report section (``specaa``), benchmark case (``specaa``) and ``glossrt experiment --which
specaa`` are registered here.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..metrics import flicker
from ..report import DemoContext, Report, register_section
from ..report.registry import (
    BenchContext,
    benchmark,
    finish_experiment,
    markdown_table,
    register_experiment,
    section_size,
)

SCENE = "normal-mapped"
FLAT_SHAPE = "floor_flat"
#: rows beyond the paper's methods: ``METHOD+material`` shades point / directional lights with
#: the Smith masking of the material's own alpha (:data:`glossrt.specaa.MASKING`);
#: ``METHOD:kappa=K`` clamps the added kernel's eigenvalues to ``K`` (Kaplanyan et al. 2016's
#: clamp, projected-space filtering's 0.18 on the paper's methods; ``projected:kappa=none``
#: is projected without its default clamp)
KAPPA = 0.18
EXTRA = ("avgnormal-eig+material", "projected+material", f"halfvector:kappa={KAPPA}",
         f"halfvector-bbox:kappa={KAPPA}", f"avgnormal:kappa={KAPPA}",
         f"avgnormal-eig:kappa={KAPPA}", "projected:kappa=none")


def _variant(label: str) -> tuple[str, str]:
    """``(method, masking)`` of a row label ``METHOD[:kappa=K][+material]``."""
    method, _, masking = label.partition("+")
    return method, masking or "filtered"


@dataclass
class SpecAAResults:
    size: tuple[int, int]
    spp: int
    temporal_spp: int
    frames: int
    rows: list[dict] = field(default_factory=list)
    images: dict[str, np.ndarray] = field(default_factory=dict)
    reference_temporal: float = 0.0
    seconds: float = 0.0
    #: the supersampled reference of frame 0 against Mitsuba's direct integrator: relative L1
    #: and the ratio of the means over the pixels that see a non-emitting surface
    reference_vs_direct: dict = field(default_factory=dict)

    def markdown(self) -> str:
        lines = [
            f"| method | RMSE | FLIP | RMSE (Gaussian) | FLIP (Gaussian) | mean bias | "
            f"flat-region bias | temporal error (reference {self.reference_temporal:.4f}) | "
            f"flicker |",
            "|---|---|---|---|---|---|---|---|---|"]
        for r in self.rows:
            lines.append(
                f"| {r['method']} | {r['rmse']:.4f} | {r['flip']:.4f} | "
                f"{r['rmse_gauss']:.4f} | {r['flip_gauss']:.4f} | "
                f"{100 * r['bias']:+.1f}% | {100 * r['flat_bias']:+.1f}% | "
                f"{r['temporal']:.4f} | {r['flicker']:.4f} |")
        return "\n".join(lines)

    def as_dict(self) -> dict:
        return {"size": list(self.size), "spp": self.spp, "temporal_spp": self.temporal_spp,
                "frames": self.frames, "reference_temporal": self.reference_temporal,
                "rows": self.rows, "seconds": self.seconds,
                "reference_vs_direct": self.reference_vs_direct}

    def montage(self, path: str | Path, crop: tuple[slice, slice] | None = None) -> Path:
        """The paper's figs. 1-3 side by side: every method and the reference (tone-mapped),
        with ``|image - reference|`` under each; ``crop`` (rows, cols) zooms in."""
        from ..report.figures import Panel, montage
        from ..report.page import tonemap

        keys = list(self.images)
        ref = self.images[keys[-1]]
        cols = 4
        rows = 2 * ((len(keys) + cols - 1) // cols)
        crop = crop or (slice(None), slice(None))
        h, w = ref[crop].shape[:2]
        grid: list[list[Panel | None]] = [[None] * cols for _ in range(rows)]
        scale = max(float(np.percentile(np.abs(ref[crop]), 99.5)), 1e-6)
        for i, k in enumerate(keys):
            r, c = 2 * (i // cols), i % cols
            grid[r][c] = Panel(tonemap(self.images[k][crop]), k, fontsize=8)
            err = np.abs(self.images[k][crop] - ref[crop]).mean(axis=-1)
            grid[r + 1][c] = Panel(err, f"|{k} - reference|", "magma", 0, 0.5 * scale,
                                   fontsize=7)
        return montage(path, grid, (3.2 * cols, rows * 3.2 * h / w + 0.4), dpi=100)


def _flat_mask(setup, frame) -> np.ndarray:
    """Pixels of the flat strip whose 3x3 neighbourhood is the strip too."""
    idx = setup.shape_index.get(FLAT_SHAPE)
    mid = frame.numpy("mesh_id")[..., 0]
    if idx is None:
        return np.zeros(mid.shape, bool)
    m = mid == idx
    e = m.copy()
    e[1:] &= m[:-1]
    e[:-1] &= m[1:]
    e[:, 1:] &= e[:, :-1].copy()
    e[:, :-1] &= e[:, 1:].copy()
    return e



def evaluate(size=(320, 180), spp: int = 256, frames: int = 8, temporal_spp: int = 64,
             methods=None, scene: str = SCENE,
             progress: Callable[[str], None] | None = None) -> SpecAAResults:
    """Every method against the supersampled reference (module docstring)."""
    from .. import metrics, render, scenes, specaa
    from ..lights.analytic import analytic_lights
    from ..lights.scene import polygon_lights
    from ..lights.shading import fresnel_image

    say = progress or (lambda _m: None)
    methods = tuple(methods or (specaa.METHODS + EXTRA))
    t_start = time.perf_counter()
    setup = scenes.load(scene, size=size)
    rend = render.Renderer(setup)

    def lights_of(i):
        return analytic_lights(setup, i), polygon_lights(setup, i)

    def materials(fr):  # Mitsuba's exact Fresnel terms (the one BRDF)
        return fresnel_image(setup, fr)

    res = SpecAAResults(tuple(size), spp, temporal_spp, frames)
    say(f"reference, frame 0 ({spp} sub-pixel samples, box filter)")
    ref = specaa.reference(rend, 0, *lights_of(0), f0_of=materials, spp=spp)
    say(f"reference, frame 0 ({spp} sub-pixel samples, Gaussian filter, variance 0.25)")
    ref_g = specaa.reference(rend, 0, *lights_of(0), f0_of=materials, spp=spp,
                             pixel_filter="gaussian")
    # the reference against Mitsuba's own direct integrator (box pixel filter, 4x the spp)
    say(f"Mitsuba's direct integrator, frame 0 ({4 * spp} spp)")
    direct = np.array(rend.render_mitsuba(0, 4 * spp, integrator="direct"))
    seqs: dict[str, list] = {m: [] for m in methods}
    seqs["reference"] = []
    for t in range(frames):
        say(f"frame {t + 1}/{frames}")
        lt, pl = lights_of(t)
        g = rend.render(t)
        f0_t = materials(g)
        if t == 0:
            flat = _flat_mask(setup, g)
            hit = g.numpy("mesh_id")[..., 0] > 0
            surf = hit & ~(g.numpy("emission").max(-1) > 0)
            res.reference_vs_direct = {
                "rel_l1": float(np.abs(ref - direct)[surf].sum() / np.abs(direct)[surf].sum()),
                "mean_ratio": float(ref[surf].mean() / max(direct[surf].mean(), 1e-12))}
        for m in methods:
            meth, masking = _variant(m)
            seqs[m].append(specaa.shade(g, lt, pl, meth, f0_t, frozen=True, masking=masking))
        seqs["reference"].append(
            ref if t == 0 and temporal_spp == spp
            else specaa.reference(rend, t, lt, pl, f0_of=materials, spp=temporal_spp))
    res.reference_temporal = metrics.temporal_error(seqs["reference"])
    ref_flat = float(ref[flat].mean()) if flat.any() else float("nan")
    for m in methods:
        img = seqs[m][0]
        d = (img - ref).mean(axis=-1)
        res.rows.append({
            "method": m,
            "rmse": metrics.rmse(img, ref),
            "rmse_surfaces": float(np.sqrt(np.mean((img - ref)[hit] ** 2))),
            "flip": metrics.flip(img, ref),
            "rmse_gauss": metrics.rmse(img, ref_g),
            "flip_gauss": metrics.flip(img, ref_g),
            "flat_bias": float(d[flat].mean() / max(ref_flat, 1e-9)) if flat.any()
            else float("nan"),
            "flat_pixels": int(flat.sum()),
            "temporal": metrics.temporal_error(seqs[m]),
            "flicker": flicker(seqs[m], seqs["reference"]),
            "bias": float((img - ref)[hit].mean() / max(float(ref[hit].mean()), 1e-9)),
        })
        res.images[m] = img
    res.images[f"Gaussian reference ({spp} spp)"] = ref_g
    res.images[f"reference ({spp} spp)"] = ref
    res.seconds = time.perf_counter() - t_start
    return res


def timing_markdown(t: dict) -> str:
    """:func:`timing`'s result as a markdown table."""
    rows = ["| method | ms / frame | x none |", "|---|---|---|"]
    rows += [f"| {k} | {1000 * v:.2f} | {t['ratio_to_none'][k]:.3f} |"
             for k, v in t["seconds"].items()]
    return "\n".join(rows)


def timing(size=(640, 360), repeats: int = 7, methods=None, scene: str = SCENE,
           min_sample: float | None = None) -> dict:
    """Shading time per method and its ratio to unfiltered shading (median of per-repeat
    ratios), the methods called in turn (frozen kernels, the real-time path; calls shorter
    than ``min_sample`` seconds, default :data:`glossrt.timing.MIN_SAMPLE`, timed in batches,
    :func:`glossrt.timing.round_robin`)."""
    import statistics

    from .. import render, scenes, specaa
    from ..lights.analytic import analytic_lights
    from ..lights.scene import polygon_lights
    from ..lights.shading import f0_image
    from ..timing import MIN_SAMPLE, paired_ratio, round_robin

    methods = tuple(methods or specaa.METHODS)
    setup = scenes.load(scene, size=size)
    gb = render.Renderer(setup).render(0)
    lights, polys = analytic_lights(setup, 0), polygon_lights(setup, 0)
    f0 = f0_image(setup, gb)
    cases = {m: (lambda m=m: specaa.shade_tensor(gb, lights, polys, m, f0, frozen=True))
             for m in methods}
    min_sample = MIN_SAMPLE if min_sample is None else min_sample
    times = round_robin(cases, 2, repeats, min_sample)  # warm-up: record + compile
    med = {k: statistics.median(v) for k, v in times.items()}
    return {"size": list(size), "seconds": med,
            "ratio_to_none": {k: paired_ratio(v, times["none"]) for k, v in times.items()}}


@register_section("specaa", order=80)
def section_specaa(ctx: DemoContext, report: Report) -> None:
    t0 = time.perf_counter()
    scale, size = section_size(ctx, (160, 90), 2, (32, 18))
    spp = 256 if scale >= 1 else 16
    frames = 6 if scale >= 1 else 2
    res = evaluate(size=size, spp=spp, frames=frames, temporal_spp=min(spp, 64))
    s = report.section(
        "Specular antialiasing",
        "NDF filtering (Kaplanyan et al. 2016, as evaluated by Tokuyoshi) on normal-mapped: "
        "the half-vector filter and its bounding box, the deferred average-normal filter and "
        "its isotropic reductions, and projected-space filtering (Tokuyoshi & Kaplanyan 2021), "
        f"against the unfiltered shading averaged over {spp} sub-pixel positions; temporal "
        f"error over {frames} frames of the slow camera motion (the reference's own change "
        "is the floor). See docs/RESULTS.md.")
    markdown_table(s, res.markdown(), "error against the supersampled reference")
    keys = list(res.images)
    for i in range(0, len(keys), 4):
        s.images_row([(k, res.images[k]) for k in keys[i:i + 4]], name=f"specaa_{i}")
    ref = res.images[keys[-1]]
    for k in ("none", "avgnormal-eig"):
        if k in res.images:
            s.error_map(f"specaa_err_{k}", res.images[k], ref,
                        caption=f"relative error of {k} against the supersampled reference")
    ctx.timings["specaa section"] = time.perf_counter() - t0


@benchmark("specaa", order=50)
def bench_specaa(ctx: BenchContext) -> dict:
    """Deferred direct shading of ``normal-mapped``'s G-buffer (its point, directional and
    polygon lights; frozen kernels) with each specular antialiasing method, interleaved in
    one run; ratios to unfiltered shading. Target (issue 8): filtering adds at most 10%."""
    t = timing(size=ctx.size, repeats=ctx.turns, min_sample=ctx.min_sample)
    return {"scene": SCENE, **t, "target_ratio": 1.10}


@register_experiment("specaa", "Kaplanyan et al. / Tokuyoshi specular antialiasing against "
                     "the supersampled reference and shading times (--size, --spp, --frames: "
                     "at most 16)", order=60)
def run_experiment(out, size, args) -> int:
    """Tokuyoshi / Kaplanyan et al. measurements (RESULTS.md): every specular antialiasing
    method against the supersampled reference on normal-mapped (RMSE, FLIP, flat-region bias,
    temporal error under the slow camera motion) and the shading-time ratios."""
    spp, frames = args.spp, args.frames
    # one converged reference per frame: flicker is measured against them
    res = evaluate(size=size, spp=spp, frames=min(frames, 16), temporal_spp=spp,
                   progress=lambda m: print(m, flush=True))
    res.montage(out / "specaa.png")
    w, h = size
    res.montage(out / "specaa_crop.png", crop=(slice(h // 3, h), slice(0, w // 2)))
    t = timing(size=size)
    vd = res.reference_vs_direct
    md = (f"## against the supersampled reference ({w}x{h}, {spp} spp; temporal: "
          f"{res.frames} frames, reference {spp} spp, box filter; the Gaussian columns: "
          f"against the reference with Tokuyoshi's Gaussian pixel filter, variance 0.25)"
          f"\n\n{res.markdown()}\n\n"
          f"The reference against Mitsuba's own direct integrator ({4 * spp} spp): relative "
          f"L1 {vd['rel_l1']:.3f}, ratio of the means {vd['mean_ratio']:.3f}.\n\n"
          f"## shading time (frozen, {w}x{h})\n\n{timing_markdown(t)}")
    return finish_experiment(out, "specaa", md, "specaa.png", {**res.as_dict(), "timing": t})
