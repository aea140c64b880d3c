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

At the paper's scale (issue 28, ``glossrt experiment --which specaa --scale paper``,
:func:`run_paper` / :func:`evaluate_paper`): 1280x720, 60 frames of the camera path, every row
against Gaussian-filtered references (eq. 1's filter) at frame pairs every ``--ref-every``
frames, each reference in several seeds of its jittered sub-pixel strata: per method the mean
over the frames of RMSE with its standard deviation across the seeds, RMSE and HDR-FLIP
against the seeds' pooled reference, flicker over the referenced pairs (± across seeds), and
the RMSE-per-frame plot with a band per method.

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
from ..progress import Progress
from ..report import DemoContext, Report, register_section
from ..report.registry import (
    BenchContext,
    benchmark,
    experiment_scale,
    finish_experiment,
    markdown_table,
    paper_value,
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
        return _montage(self.images, path, crop)


def _montage(images: dict[str, np.ndarray], path: str | Path,
             crop: tuple[slice, slice] | None = None) -> Path:
    """:meth:`SpecAAResults.montage` of ``images`` (the last one is the reference)."""
    from ..report.figures import Panel, montage
    from ..report.page import tonemap

    keys = list(images)
    ref = images[keys[-1]]
    cols = 4
    rows = 2 * ((len(keys) + cols - 1) // cols)
    crop = crop or (slice(None), slice(None))
    h, w = ref[crop].shape[:2]
    grid: list[list[Panel | None]] = [[None] * cols for _ in range(rows)]
    scale = max(float(np.percentile(np.abs(ref[crop]), 99.5)), 1e-6)
    for i, k in enumerate(keys):
        r, c = 2 * (i // cols), i % cols
        grid[r][c] = Panel(tonemap(images[k][crop]), k, fontsize=8)
        err = np.abs(images[k][crop] - ref[crop]).mean(axis=-1)
        grid[r + 1][c] = Panel(err, f"|{k} - reference|", "magma", 0, 0.5 * scale, fontsize=7)
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
    show = progress is not None  # progress bars on stderr

    say(f"reference, frame 0 ({spp} sub-pixel samples, box filter)")
    with Progress(spp, "reference, box filter (sub-pixel samples)", enabled=show) as p:
        ref = specaa.reference(rend, 0, *lights_of(0), f0_of=materials, spp=spp, progress=p)
    say(f"reference, frame 0 ({spp} sub-pixel samples, Gaussian filter, variance 0.25)")
    with Progress(spp, "reference, Gaussian filter (sub-pixel samples)", enabled=show) as p:
        ref_g = specaa.reference(rend, 0, *lights_of(0), f0_of=materials, spp=spp,
                                 pixel_filter="gaussian", progress=p)
    # the reference against Mitsuba's own direct integrator (box pixel filter, 4x the spp)
    say(f"Mitsuba's direct integrator, frame 0 ({4 * spp} spp)")
    direct = np.array(rend.render_mitsuba(0, 4 * spp, integrator="direct"))
    seqs: dict[str, list] = {m: [] for m in methods}
    seqs["reference"] = []
    say(f"{frames} frames: every method, and a reference of {temporal_spp} sub-pixel "
        "samples for the temporal error")
    with Progress(frames * (len(methods) + 1), "frames x (methods + reference)",
                  enabled=show) as bar:
        for t in range(frames):
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
                bar.update(bar.done + 1)
            seqs["reference"].append(
                ref if t == 0 and temporal_spp == spp
                else specaa.reference(rend, t, lt, pl, f0_of=materials, spp=temporal_spp))
            bar.update(bar.done + 1)
    res.reference_temporal = metrics.temporal_error(seqs["reference"])
    ref_flat = float(ref[flat].mean()) if flat.any() else float("nan")
    say(f"scores of {len(methods)} methods (RMSE, FLIP, temporal error, flicker)")
    with Progress(len(methods), "scores", enabled=show) as bar:
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
            bar.update(bar.done + 1)
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
    res = evaluate(size=size, spp=spp, frames=frames, temporal_spp=min(spp, 64),
                   progress=ctx.say)
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
                     "at most 16); --scale paper: 1280x720, 60 frames, Gaussian references "
                     "of 16 samples x 4 seeds at frame pairs every --ref-every frames, error "
                     "bars across the seeds", order=60)
def run_experiment(out, size, args) -> int:
    """Tokuyoshi / Kaplanyan et al. measurements (RESULTS.md): every specular antialiasing
    method against the supersampled reference on normal-mapped (RMSE, FLIP, flat-region bias,
    temporal error under the slow camera motion) and the shading-time ratios.
    ``--scale paper``: :func:`run_paper`."""
    if experiment_scale(args) == "paper":
        return run_paper(out, size, args)
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


# -- paper scale (issue 28): 1280x720, a 60-frame camera path, error bars from seeds ------------

#: ``--scale paper`` defaults (glossrt's choices; the papers give no sequence): the image size,
#: frames of normal-mapped's camera path (:func:`glossrt.scenes.library.normal_mapped_path` is
#: defined for every frame: 60 frames turn the view 3.6 degrees and dolly 18 cm), Gaussian
#: reference sub-pixel samples per seed (:data:`PAPER_SPP`, a square), the seeds of the
#: references' jittered strata, and the stride of the referenced frame pairs (``--ref-every``)
PAPER_SIZE = (1280, 720)
PAPER_FRAMES = 60
PAPER_SPP = 16
PAPER_SEEDS = (0, 1, 2, 3)
PAPER_REF_EVERY = 10
#: frames whose HDR-FLIP is measured at paper scale (about 10-15 s per 1280x720 FLIP on the
#: 2-core machine: against the seeds' pooled reference, per method, on frame 0 only)
PAPER_FLIP_FRAMES = (0,)


def referenced_frames(frames: int, ref_every: int) -> list[int]:
    """The frames that get references: the pairs ``(k, k + 1)`` for ``k = 0, ref_every,
    2 ref_every...`` (``k + 1`` only when it is below ``frames``): flicker needs consecutive
    references; ``ref_every = 1``: every frame."""
    return sorted({f for k in range(0, frames, ref_every) for f in (k, k + 1) if f < frames})


def _std(values) -> float:
    """Sample standard deviation (``ddof = 1``) over the seeds; 0 for one seed."""
    v = np.asarray(values, dtype=np.float64)
    return float(v.std(ddof=1)) if v.size > 1 else 0.0


@dataclass
class SpecAAPaperResults:
    """:func:`evaluate_paper`'s measurements. ``rows``: per method ``rmse`` (mean over the
    referenced frames against each seed's Gaussian reference; ``rmse_seeds`` per seed,
    ``rmse_std`` their standard deviation), ``rmse_pooled`` (against the mean of the seeds'
    references), ``flip_pooled`` (mean over :data:`PAPER_FLIP_FRAMES`, pooled reference;
    with ``flip_per_seed`` also ``flip`` / ``flip_std`` / ``flip_seeds``), ``flicker`` /
    ``flicker_std`` / ``flicker_seeds`` (over the referenced consecutive pairs, against each
    seed's reference sequence), ``flicker_pooled``, ``temporal`` (the method's own
    frame-to-frame change over all frames). ``curves[method]``: per seed, RMSE per
    referenced frame (``ref_frames``)."""

    size: tuple[int, int]
    spp: int
    seeds: tuple[int, ...]
    frames: int
    ref_frames: list[int]
    flip_frames: list[int]
    rows: list[dict] = field(default_factory=list)
    curves: dict[str, list[list[float]]] = field(default_factory=dict)
    images: dict[str, np.ndarray] = field(default_factory=dict)
    reference_temporal: float = 0.0
    seconds: float = 0.0

    def markdown(self) -> str:
        s = len(self.seeds)
        per_seed_flip = bool(self.rows) and "flip" in self.rows[0]
        lines = [
            f"| method | RMSE, mean ± std over {s} seeds | RMSE (pooled reference) | "
            f"FLIP (pooled reference{', ± std over seeds' if per_seed_flip else ''}) | "
            f"flicker, mean ± std over {s} seeds | temporal error (reference "
            f"{self.reference_temporal:.4f}) |",
            "|---|---|---|---|---|---|"]
        for r in self.rows:
            flip = f"{r['flip_pooled']:.4f}"
            if per_seed_flip:
                flip += f" ({r['flip']:.4f} ± {r['flip_std']:.4f})"
            lines.append(
                f"| {r['method']} | {r['rmse']:.4f} ± {r['rmse_std']:.4f} | "
                f"{r['rmse_pooled']:.4f} | {flip} | {r['flicker']:.4f} ± "
                f"{r['flicker_std']:.4f} | {r['temporal']:.4f} |")
        return "\n".join(lines)

    def as_dict(self) -> dict:
        return {"size": list(self.size), "spp_per_seed": self.spp, "seeds": list(self.seeds),
                "frames": self.frames, "ref_frames": self.ref_frames,
                "flip_frames": self.flip_frames, "pixel_filter": "gaussian",
                "reference_temporal": self.reference_temporal, "rows": self.rows,
                "curves": {m: {"frames": self.ref_frames, "rmse_per_seed": c}
                           for m, c in self.curves.items()},
                "seconds": self.seconds}

    def plot(self, path: str | Path) -> Path:
        """RMSE against the Gaussian reference per referenced frame: per method the mean over
        the seeds, the band ± one standard deviation across them."""
        from ..report.figures import subplots

        fig, ax = subplots(1, 1, (9, 5))
        ax = ax[0, 0]
        x = np.asarray(self.ref_frames)
        colours = [f"C{i}" for i in range(10)]
        styles = ("-", "--", ":")
        for i, (m, c) in enumerate(self.curves.items()):
            a = np.asarray(c, dtype=np.float64)  # (seeds, frames)
            mean = a.mean(axis=0)
            sd = a.std(axis=0, ddof=1) if a.shape[0] > 1 else np.zeros_like(mean)
            col = colours[i % 10]
            ax.plot(x, mean, styles[(i // 10) % 3], color=col, marker=".", lw=1.2, label=m)
            ax.fill_between(x, mean - sd, mean + sd, color=col, alpha=0.12, lw=0)
        ax.set_xlabel("frame")
        ax.set_ylabel("RMSE against the Gaussian reference")
        w, h = self.size
        ax.set_title(f"normal-mapped {w}x{h}: RMSE per frame (mean ± std over "
                     f"{len(self.seeds)} seeds of {self.spp}-sample references)", fontsize=9)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, ncol=2, loc="center left", bbox_to_anchor=(1.0, 0.5))
        fig.tight_layout()
        path = Path(path)
        fig.savefig(path, dpi=110)
        return path


def evaluate_paper(size=PAPER_SIZE, spp: int = PAPER_SPP, frames: int = PAPER_FRAMES,
                   seeds=PAPER_SEEDS, ref_every: int = PAPER_REF_EVERY, methods=None,
                   flip_frames=PAPER_FLIP_FRAMES, flip_per_seed: bool = False,
                   scene: str = SCENE,
                   progress: Callable[[str], None] | None = None) -> SpecAAPaperResults:
    """Every method against Gaussian-filtered references (Tokuyoshi's eq. 1 pixel filter,
    variance 0.25 px^2) over ``frames`` frames of the camera path, with error bars from
    ``seeds``: each seed's reference of a referenced frame (:func:`referenced_frames`) averages
    the unfiltered shading over ``spp`` jittered strata of the filter
    (:func:`glossrt.specaa.subpixel_offsets` with that seed); the seeds change only those
    sub-pixel positions (the methods' one-sample G-buffers are at the pixel centres, with no
    random numbers), so the spread across seeds is the references' sampling error. The pooled
    reference is the mean of the seeds' references (``spp * len(seeds)`` samples). Methods'
    images are streamed frame by frame (nothing but the previous frame is kept)."""
    from .. import metrics, render, scenes, specaa
    from ..errors import GlossrtError
    from ..lights.analytic import analytic_lights
    from ..lights.scene import polygon_lights
    from ..lights.shading import fresnel_image

    seeds = tuple(int(s) for s in seeds)
    if frames < 2:
        raise GlossrtError(f"the paper-scale specaa run needs at least 2 frames, got {frames}")
    if ref_every < 1:
        raise GlossrtError(f"--ref-every must be >= 1, got {ref_every}")
    if not seeds:
        raise GlossrtError("the paper-scale specaa run needs at least one seed")
    specaa.subpixel_offsets(spp, "gaussian")  # a bad spp: one line, before any work
    methods = tuple(methods or (specaa.METHODS + EXTRA))
    for m in methods:
        specaa.parse_method(_variant(m)[0])
    say = progress or (lambda _m: None)
    t_start = time.perf_counter()
    setup = scenes.load(scene, size=size)
    rend = render.Renderer(setup)
    refd = referenced_frames(frames, ref_every)
    flip_at = [f for f in flip_frames if f in refd]
    res = SpecAAPaperResults(tuple(size), spp, seeds, frames, refd, flip_at)

    def f0_of(fr):  # Mitsuba's exact Fresnel terms (the one BRDF)
        return fresnel_image(setup, fr)

    rmse = {m: [[] for _ in seeds] for m in methods}
    rmse_pooled = {m: [] for m in methods}
    flip_pooled = {m: [] for m in methods}
    flip = {m: [[] for _ in seeds] for m in methods}
    flick = {m: [[] for _ in seeds] for m in methods}
    flick_pooled = {m: [] for m in methods}
    temporal = {m: 0.0 for m in methods}
    ref_temporal: list[float] = []
    prev: dict | None = None  # the previous frame: images, references, luminance
    for t in range(frames):
        lt, pl = analytic_lights(setup, t), polygon_lights(setup, t)
        g = rend.render(t)
        f0 = f0_of(g)
        imgs = {}
        for m in methods:
            meth, masking = _variant(m)
            imgs[m] = np.asarray(specaa.shade(g, lt, pl, meth, f0, frozen=True,
                                              masking=masking))
        lum = {m: metrics.luminance(imgs[m]) for m in methods}
        if prev is not None:
            for m in methods:
                temporal[m] += float(np.mean(np.abs(lum[m] - prev["lum"][m])))
        refs = None
        if t in refd:
            say(f"frame {t + 1}/{frames}: references ({len(seeds)} seeds x {spp} samples, "
                "Gaussian filter)")
            refs = [specaa.reference(rend, t, lt, pl, f0_of=f0_of, spp=spp,
                                     pixel_filter="gaussian", seed=s) for s in seeds]
            pooled = np.mean(refs, axis=0)
            paired = prev is not None and prev["refs"] is not None
            if paired:
                ref_temporal.append(float(np.mean(np.abs(
                    metrics.luminance(pooled) - metrics.luminance(prev["pooled"])))))
            for m in methods:
                rmse_pooled[m].append(metrics.rmse(imgs[m], pooled))
                for i, r in enumerate(refs):
                    rmse[m][i].append(metrics.rmse(imgs[m], r))
                if t in flip_at:
                    flip_pooled[m].append(metrics.flip(imgs[m], pooled))
                    if flip_per_seed:
                        for i, r in enumerate(refs):
                            flip[m][i].append(metrics.flip(imgs[m], r))
                if paired:  # the pair's term of glossrt.metrics.flicker
                    flick_pooled[m].append(flicker([prev["imgs"][m], imgs[m]],
                                                   [prev["pooled"], pooled]))
                    for i, r in enumerate(refs):
                        flick[m][i].append(flicker([prev["imgs"][m], imgs[m]],
                                                   [prev["refs"][i], r]))
            if t == 0:
                res.images = {m: imgs[m] for m in methods}
                res.images[f"Gaussian reference ({spp * len(seeds)} samples)"] = pooled
        else:
            say(f"frame {t + 1}/{frames}")
            pooled = None
        prev = {"imgs": imgs, "lum": lum, "refs": refs, "pooled": pooled}
    nan = float("nan")
    res.reference_temporal = float(np.mean(ref_temporal)) if ref_temporal else nan
    for m in methods:
        per_seed = [float(np.mean(v)) for v in rmse[m]]
        fl_seed = [float(np.mean(v)) if v else nan for v in flick[m]]
        row = {"method": m, "rmse": float(np.mean(per_seed)), "rmse_std": _std(per_seed),
               "rmse_seeds": per_seed, "rmse_pooled": float(np.mean(rmse_pooled[m])),
               "flip_pooled": float(np.mean(flip_pooled[m])) if flip_pooled[m] else nan,
               "flicker": float(np.mean(fl_seed)), "flicker_std": _std(fl_seed),
               "flicker_seeds": fl_seed,
               "flicker_pooled": float(np.mean(flick_pooled[m])) if flick_pooled[m] else nan,
               "temporal": temporal[m] / (frames - 1)}
        if flip_per_seed:
            fs = [float(np.mean(v)) if v else nan for v in flip[m]]
            row.update(flip=float(np.mean(fs)), flip_std=_std(fs), flip_seeds=fs)
        res.rows.append(row)
        res.curves[m] = [list(map(float, v)) for v in rmse[m]]
    res.seconds = time.perf_counter() - t_start
    return res


def run_paper(out, size, args) -> int:
    """``glossrt experiment --which specaa --scale paper``: :func:`evaluate_paper` at
    :data:`PAPER_SIZE` (or ``--size``), :data:`PAPER_FRAMES` frames (or ``--frames``, any
    number: no cap of 16 here), ``--spp`` Gaussian samples per seed (default
    :data:`PAPER_SPP`), seeds :data:`PAPER_SEEDS`, reference pairs every ``--ref-every``
    frames (CLI default 10 = :data:`PAPER_REF_EVERY`). Writes ``specaa-paper.md`` /
    ``.json``, the RMSE-per-frame plot ``specaa-paper-rmse.png`` and frame 0's montage
    ``specaa-paper.png``."""
    size = tuple(paper_value(args, "size", size, PAPER_SIZE))
    spp = int(paper_value(args, "spp", args.spp, PAPER_SPP))
    frames = int(paper_value(args, "frames", args.frames, PAPER_FRAMES))
    ref_every = int(getattr(args, "ref_every", PAPER_REF_EVERY))
    res = evaluate_paper(size=size, spp=spp, frames=frames, ref_every=ref_every,
                         progress=lambda m: print(m, flush=True))
    res.plot(out / "specaa-paper-rmse.png")
    _montage(res.images, out / "specaa-paper.png")
    w, h = size
    s = len(res.seeds)
    pairs = sum(1 for f in res.ref_frames if f - 1 in res.ref_frames)
    md = (f"## Specular antialiasing at paper scale (normal-mapped, {w}x{h}, {frames} frames "
          f"of the camera path)\n\n"
          f"Against references with Tokuyoshi's Gaussian pixel filter (eq. 1, variance "
          f"0.25 px^2), each the unfiltered shading averaged over {spp} jittered strata of "
          f"the filter; {s} seeds ({', '.join(map(str, res.seeds))}) of the strata's "
          f"positions (the only random numbers: the methods' images do not change with them); "
          f"± = sample standard deviation across the seeds of each seed's mean over the "
          f"frames. Pooled reference: the mean of the {s} seeds' references "
          f"({spp * s} samples). References at frames {res.ref_frames} (pairs every "
          f"{ref_every} frames); RMSE: mean over them; flicker: over their {pairs} "
          f"consecutive pairs; temporal error: "
          f"the method's own change over all {frames} frames; FLIP: frames "
          f"{res.flip_frames}.\n\n{res.markdown()}\n\n"
          f"Wall time {res.seconds:.0f} s.")
    return finish_experiment(out, "specaa-paper", md, "specaa-paper-rmse.png",
                             {**res.as_dict(), "ref_every": ref_every})
