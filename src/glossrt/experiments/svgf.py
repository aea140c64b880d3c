"""The denoiser comparison behind docs/RESULTS.md, the report's "Denoisers" section, the
``denoisers`` benchmark and ``glossrt experiment --which denoisers`` (Schied et al. 2017).

``denoisers``: every denoiser on an animated 1 spp sequence against converged references
(RMSE, SSIM, FLIP, wall time per frame), and the temporal error of each on a static
sequence (Schied 2017, sec. 5.4 / fig. 10).
"""

from __future__ import annotations

import json
import statistics
from dataclasses import dataclass, field

import numpy as np

from .. import metrics
from ..report import DemoContext, Report, register_section
from ..report.registry import (
    BenchContext,
    benchmark,
    experiment_cluster,
    register_experiment,
)
from ..timing import paired_ratio, round_robin, steady_median, timed_eval

DEFAULT_METHODS = ("svgf", "svgf-lobe", "svgf-spatial-variance", "atrous", "atrous-temporal",
                   "oidn")


@dataclass
class DenoiserResults:
    size: tuple[int, int]
    frames: int
    ref_spp: int
    methods: list[str]
    quality: dict[str, dict[str, float]] = field(default_factory=dict)  # method -> means
    per_frame: dict[str, list[dict]] = field(default_factory=dict)
    seconds: dict[str, float] = field(default_factory=dict)  # median per frame
    temporal: dict[str, list[float]] = field(default_factory=dict)  # per frame, static seq
    images: dict[str, object] = field(default_factory=dict)  # method -> last referenced image
    skipped: dict[str, str] = field(default_factory=dict)

    def table(self) -> list[list]:
        rows = []
        for m in self.methods:
            if m in self.skipped:
                rows.append([m, None, None, None, None, None])
                continue
            q = self.quality[m]
            te = self.temporal.get(m)
            rows.append([m, q["rmse"], q["ssim"], q["flip"], 1000 * self.seconds[m],
                         float(np.mean(te[len(te) // 2:])) if te else None])
        return rows

    COLUMNS = ["method", "RMSE", "SSIM", "FLIP", "ms / frame", "temporal error (static)"]

    def markdown(self) -> str:
        lines = ["| " + " | ".join(self.COLUMNS) + " |", "|" + "---|" * len(self.COLUMNS)]
        for row in self.table():
            cells = [row[0]] + ["-" if v is None else f"{v:.4g}" for v in row[1:]]
            lines.append("| " + " | ".join(cells) + " |")
        return "\n".join(lines)


def _available(method: str) -> str | None:
    """Why a method cannot run here (None if it can)."""
    from .. import backend

    if method == "optix" and not backend.is_gpu():
        return "needs a CUDA GPU (cuda_ad_rgb)"
    if method == "oidn":
        try:
            from ..denoise.oidn import oidn_available

            if not oidn_available():
                return "pyoidn not usable"
        except ImportError as e:
            return f"pyoidn not importable: {e}"
    return None


def _run_sequence(method: str, frames: list, tick=None) -> tuple[list, list[float]]:
    """``method``'s output and seconds per frame of ``frames``; ``tick()`` after each."""
    from .. import denoise

    d = denoise.make(method)
    outs, secs = [], []
    for f in frames:
        img, t = timed_eval(d, f)
        secs.append(t)
        outs.append(img)
        if tick is not None:
            tick()
    return outs, secs


def denoisers(size=(160, 120), frames: int = 20, ref_every: int = 10, ref_spp: int = 512,
              static_frames: int = 40, methods=DEFAULT_METHODS, scene: str = "glossy-cornell",
              progress=None, sequence=None, references=None,
              cluster=None, cache=None) -> DenoiserResults:
    """Run the comparison; ``sequence``/``references`` may be passed in (e.g. by the demo).
    ``cluster``: where the references are rendered (:func:`glossrt.render.blocks.references`:
    None, in this process as before; else as sample blocks on that cluster); ``cache``: a
    folder that keeps each finished reference frame for a rerun (the experiment command's
    ``--out``/references). ``progress(done, total)``: after each denoised frame (the
    sequence's and the static sequence's, every method; a method that cannot run here counts
    as done)."""
    from .. import render, scenes
    from ..render import blocks

    res = DenoiserResults(size=tuple(size), frames=frames, ref_spp=ref_spp,
                          methods=list(methods))
    if sequence is None:
        setup = scenes.load(scene, size=size, frames=frames)
        r = render.Renderer(setup)
        sequence = [r.render(i) for i in range(frames)]
        references = blocks.references(
            r, blocks.reference_job(scene, size, frames=frames), range(0, frames, ref_every),
            ref_spp, cluster, desc=f"references {scene} {ref_spp} spp", cache=cache)
    refs = {f.index: f for f in references}
    rs = render.Renderer(scenes.load_static(scene, size=size))
    static = [rs.render(i) for i in range(static_frames)]
    per_method = len(sequence) + static_frames
    total, done = len(methods) * per_method, 0

    def tick():
        nonlocal done
        done += 1
        if progress:
            progress(done, total)

    for k, m in enumerate(methods):
        why = _available(m)
        if why:
            res.skipped[m] = why
            done = (k + 1) * per_method
            continue
        outs, secs = _run_sequence(m, sequence, tick)
        res.seconds[m] = steady_median(secs)
        rows = []
        for f, img in zip(sequence, outs, strict=True):
            if f.index in refs:
                ref = refs[f.index]["color"]
                rows.append({"frame": f.index, "rmse": metrics.rmse(img, ref),
                             "ssim": metrics.ssim(img, ref), "flip": metrics.flip(img, ref)})
                res.images[m] = img
        res.per_frame[m] = rows
        res.quality[m] = {key: float(np.mean([r[key] for r in rows]))
                          for key in ("rmse", "ssim", "flip")}
        souts, _ = _run_sequence(m, static, tick)
        res.temporal[m] = [metrics.temporal_error(souts[i - 1:i + 1])
                           for i in range(1, len(souts))]
    res.images["1 spp"] = sequence[max(refs)]["color"]
    res.images["reference"] = refs[max(refs)]["color"]
    return res


@register_section("denoisers", order=40)
def section_denoisers(ctx: DemoContext, report: Report) -> None:
    res: DenoiserResults | None = ctx.extra.get("denoisers")
    if res is None:
        ctx.say(f"a static 30-frame sequence, then each of {', '.join(DEFAULT_METHODS)} on "
                f"the demo's {len(ctx.frames)} frames and on the static ones ...")
        with ctx.bar("denoised frames") as p:
            res = denoisers(size=(ctx.frames[0].width, ctx.frames[0].height),
                            sequence=ctx.frames, references=ctx.references, static_frames=30,
                            progress=p)
    s = report.section(
        "Denoisers",
        "Every denoiser on the same 1 spp sequence, against the converged references "
        "(mean over the referenced frames), with its median wall time per frame after the "
        "first (frozen kernels replay) and its temporal error on a static 30-frame sequence "
        "(mean absolute luminance difference of consecutive frames, second half; Schied "
        "2017, fig. 10). SVGF: Schied et al. 2017 with 4 signals (direct/indirect x "
        "diffuse/specular); svgf-lobe: the same with Tokuyoshi 2015's specular-lobe weight "
        "in place of w_n for the specular signals; atrous: Dammertz et al. 2010 per frame; "
        "atrous-temporal: the same "
        "after SVGF's temporal accumulation; oidn: Intel Open Image Denoise per frame.",
    )
    s.table(DenoiserResults.COLUMNS, res.table())
    for m, why in res.skipped.items():
        s.paragraph(f"{m}: not run here ({why}).")
    s.images_row([(k, v) for k, v in res.images.items()], name="denoised")
    if res.temporal:
        from ..report.figures import new_figure

        fig = new_figure((6, 3.2))
        ax = fig.add_subplot()
        for m, te in res.temporal.items():
            ax.semilogy(range(1, len(te) + 1), te, label=m)
        ax.set_xlabel("frame")
        ax.set_ylabel("temporal error")
        ax.set_title("static sequence")
        ax.legend(fontsize=7)
        fig.tight_layout()
        s.figure("temporal_error", fig, caption="temporal error per frame (static camera)")


@benchmark("denoisers", order=20)
def bench_denoisers(ctx: BenchContext) -> dict:
    """Steady-state time per frame of each denoiser on a static glossy-cornell sequence (4
    frames cycling after 8 warm-up frames, so the temporal filters' history is full), the
    methods called in turn (:func:`round_robin`); ratios against OIDN and against plain
    a-trous as medians of per-repeat ratios."""
    import drjit as dr

    from .. import denoise, render, scenes

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


@register_experiment("denoisers", "Schied 2017 comparison", order=10)
def run_experiment(out, size, args) -> int:
    """``glossrt experiment --which denoisers``: the comparison at ``size`` with the command's
    --frames, --ref-every, --spp and --static-frames; writes denoisers.md / .json and a
    report page."""
    res = denoisers(size=size, frames=args.frames, ref_every=args.ref_every,
                    ref_spp=args.spp, static_frames=args.static_frames,
                    cluster=experiment_cluster(args), cache=out / "references")
    md = res.markdown()
    (out / "denoisers.md").write_text(md + "\n")
    (out / "denoisers.json").write_text(json.dumps({
        "size": list(res.size), "frames": res.frames, "ref_spp": res.ref_spp,
        "quality": res.quality, "per_frame": res.per_frame, "seconds": res.seconds,
        "temporal": res.temporal, "skipped": res.skipped}, indent=2))
    rep = Report(out, "glossrt denoiser comparison")
    s = rep.section("Denoisers", f"glossy-cornell {size[0]}x{size[1]}, {args.frames} frames, "
                                 f"references {args.spp} spp every {args.ref_every} frames")
    s.table(DenoiserResults.COLUMNS, res.table())
    s.images_row(list(res.images.items()), name="denoised")
    rep.write()
    print(md)
    return 0
