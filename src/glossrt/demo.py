"""``glossrt demo``: render a built-in sequence and its references, write an HTML report.

The report is assembled from registered sections (:func:`glossrt.report.register_section`):
the generic ones (frames, noise, mitsuba, timings) are below; each paper's section is
registered by its module in :mod:`glossrt.experiments` (:func:`~glossrt.experiments.load_all`).
"""

from __future__ import annotations

import time
from pathlib import Path

import drjit as dr
import numpy as np

from . import backend, experiments
from .errors import GlossrtError
from .report import DemoContext, Report, build_report, register_section

experiments.load_all()  # the papers' report sections


def _vis_normal(n: np.ndarray) -> np.ndarray:
    return (0.5 + 0.5 * n) ** 2.2  # the report applies sRGB; undo it for a linear display


def _vis_scalar(x: np.ndarray, lo: float, hi: float) -> np.ndarray:
    x = np.where(np.isfinite(x), x, hi)
    v = np.clip((x - lo) / max(hi - lo, 1e-9), 0, 1) ** 2.2
    return np.repeat(v, 3, axis=-1)


def _vis_ids(ids: np.ndarray) -> np.ndarray:
    rng = np.random.default_rng(7)
    colours = rng.uniform(0.1, 1.0, size=(int(ids.max()) + 1, 3))
    colours[0] = 0
    return colours[ids[..., 0].astype(int)]


@register_section("frames", order=10)
def section_frames(ctx: DemoContext, report: Report) -> None:
    s = report.section(
        "Frames",
        f"Scene {ctx.scene}: {len(ctx.frames)} frames at 1 spp "
        f"({ctx.frames[0].width}x{ctx.frames[0].height}), camera and sphere moving. "
        "Radiance components add up to the colour; the G-buffer is noise-free.",
    )
    s.images_row([(f"frame {f.index}, 1 spp", f["color"]) for f in ctx.frames[:: max(
        1, len(ctx.frames) // 4)]], name="sequence")
    f = ctx.frames[0]
    s.images_row([(name, f[name]) for name in ("color", "emission", "direct_diffuse",
                                                "direct_specular", "indirect_diffuse",
                                                "indirect_specular")], name="components")
    depth = f.numpy("depth")
    finite = depth[np.isfinite(depth)]
    motion = np.linalg.norm(f.numpy("motion") if f.index > 0 else ctx.frames[1].numpy("motion"),
                            axis=-1, keepdims=True)
    s.images_row(
        [
            ("albedo_diffuse", f["albedo_diffuse"]),
            ("albedo_specular", f["albedo_specular"]),
            ("normal (0.5 + 0.5 n)", _vis_normal(f.numpy("normal"))),
            ("depth", _vis_scalar(depth, float(finite.min(initial=0)), float(finite.max(
                initial=1)))),
            ("roughness (alpha)", _vis_scalar(f.numpy("roughness"), 0, 1)),
            ("mesh_id", _vis_ids(f.numpy("mesh_id"))),
            ("|motion| (0..2 px), next frame", _vis_scalar(motion, 0, 2)),
        ],
        name="gbuffer",
    )


@register_section("noise", order=20)
def section_noise(ctx: DemoContext, report: Report) -> None:
    from . import metrics

    s = report.section(
        "1 spp against the converged reference",
        "The raw 1 spp input every reconstruction technique starts from, measured against "
        f"references of {ctx.references[0].meta.get('spp')} spp with the same pixel-centre "
        "primary hits. These are the numbers a denoiser has to beat.",
    )
    by_index = {f.index: f for f in ctx.frames}
    rows = []
    for ref in ctx.references:
        f = by_index[ref.index]
        img, r = f["color"], ref["color"]
        rows.append([ref.index, metrics.rmse(img, r), metrics.relmse(img, r),
                     metrics.ssim(img, r), metrics.flip(img, r)])
    s.table(["frame", "RMSE", "relMSE", "SSIM", "FLIP"], rows)
    te = metrics.temporal_error([f["color"] for f in ctx.frames])
    s.paragraph("Temporal error of the 1 spp sequence (mean absolute luminance difference of "
                f"consecutive frames): {te:.4g}")
    ref = ctx.references[0]
    f = by_index[ref.index]
    s.images_row([("1 spp", f["color"]), (f"reference, {ref.meta.get('spp')} spp", ref["color"])],
                 name="noise")
    s.error_map("noise_error", f["color"], ref["color"], caption="relative error of 1 spp")


@register_section("mitsuba", order=30)
def section_mitsuba(ctx: DemoContext, report: Report) -> None:
    from . import metrics

    mit = ctx.extra.get("mitsuba")
    if mit is None:
        return
    ref = ctx.references[0]
    img, spp = mit
    a, b = np.array(ref["color"]), np.array(img)
    s = report.section(
        "Agreement with Mitsuba's path integrator",
        "glossrt's converged reference (pixel centres) next to Mitsuba's own `path` integrator "
        f"({spp} spp, box-filtered, anti-aliased) with the same max_depth. Away from geometric "
        "edges and near-mirror reflections (where a pixel centre and a pixel's area see "
        "different things, e.g. the edge of the light in the gold sphere) they differ by Monte "
        "Carlo noise only; tests/test_render.py checks this statistically.",
    )
    s.images_row([("glossrt reference", ref["color"]), ("Mitsuba path", img)], name="mitsuba")
    s.error_map("mitsuba_error", ref["color"], img, caption="relative difference")
    s.table(["channel", "glossrt mean", "Mitsuba mean", "relative difference"],
            [[c, float(a[..., i].mean()), float(b[..., i].mean()),
              float(a[..., i].mean() / b[..., i].mean() - 1)] for i, c in enumerate("RGB")])
    s.paragraph(f"RMSE between the two: {metrics.rmse(ref['color'], img):.4g}")


@register_section("timings", order=90)
def section_timings(ctx: DemoContext, report: Report) -> None:
    info = backend.info()
    s = report.section("Timings", f"Device: {info['device']}, variant {info['variant']}, "
                                  f"Mitsuba {info['mitsuba']}, Dr.Jit {info['drjit']}.")
    s.table(["stage", "seconds"], [[k, v] for k, v in ctx.timings.items()])


#: the fewest 1 spp frames the report needs (the frames section shows frame 0's motion to
#: frame 1; per-frame timings are over the frames after the first)
MIN_FRAMES = 2


def check_demo_args(size: tuple[int, int], frames: int, ref_every: int = 4, ref_spp: int = 256,
                    mitsuba_spp: int = 256) -> None:
    """Refuse, before any work, arguments :func:`run_demo` cannot make a report of."""
    if frames < MIN_FRAMES:
        raise GlossrtError(f"demo: --frames must be >= {MIN_FRAMES} (the report shows the "
                           f"motion from one frame to the next), got {frames}")
    for name, v in (("--spp", ref_spp), ("ref_every", ref_every), ("mitsuba_spp", mitsuba_spp)):
        if v < 1:
            raise GlossrtError(f"demo: {name} must be >= 1, got {v}")
    if size[0] < 1 or size[1] < 1:
        raise GlossrtError(f"demo: the size must be positive, got {size[0]}x{size[1]}")


def run_demo(out: str | Path, size: tuple[int, int] = (160, 120), frames: int = 8,
             ref_every: int = 4, ref_spp: int = 256, mitsuba_spp: int = 256,
             scene: str = "glossy-cornell", progress: bool = True) -> Path:
    """Render, measure and report; returns the path of ``index.html``. Bad arguments
    (:func:`check_demo_args`) and scenes fail before anything is written. ``progress``: each
    step and report section says on stderr what it does and how far it is (a line when it
    starts, a :class:`~glossrt.progress.Progress` bar where it has many items)."""
    from . import render, scenes
    from .frame import frame_filename
    from .progress import Progress

    check_demo_args(size, frames, ref_every, ref_spp, mitsuba_spp)
    out = Path(out)
    ctx = DemoContext(out_dir=out, scene=scene, verbose=progress)
    setup = scenes.load(scene, size=size, frames=frames)
    for sub in ("frames", "references"):
        try:
            (out / sub).mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise GlossrtError(f"demo: cannot create the folder {str(out / sub)!r}: "
                               f"{e.strerror or e}") from None
    timings: dict[str, float] = {}
    r = render.Renderer(setup)

    t0 = time.perf_counter()
    seq = []
    with Progress(frames, "1 spp frames", enabled=progress) as p:
        for i in range(frames):
            t = time.perf_counter()
            f = r.render(i)
            if i > 0:
                timings.setdefault("1 spp frame (frozen replay), per frame", 0.0)
                timings["1 spp frame (frozen replay), per frame"] += (
                    time.perf_counter() - t) / (frames - 1)
            f.save(out / "frames" / frame_filename(i))
            seq.append(f)
            p.update(i + 1)
    timings["1 spp sequence incl. first-frame tracing and EXR writes"] = time.perf_counter() - t0

    refs = []
    t0 = time.perf_counter()
    idx = list(range(0, frames, ref_every))
    with Progress(len(idx) * ref_spp, f"references ({ref_spp} spp)", enabled=progress) as p:
        for k, i in enumerate(idx):
            ref = r.render_reference(i, ref_spp, progress=lambda d, n, k=k: p.update(k * n + d))
            ref.save(out / "references" / frame_filename(i))
            refs.append(ref)
    timings[f"references, {ref_spp} spp, per frame"] = (time.perf_counter() - t0) / len(idx)

    t0 = time.perf_counter()
    ctx.say(f"Mitsuba's path integrator, frame 0, {mitsuba_spp} spp ...")
    mit = r.render_mitsuba(0, mitsuba_spp)
    dr.eval(mit)  # Dr.Jit is lazy: time the rendering, not the tracing
    dr.sync_thread()
    timings[f"Mitsuba path, {mitsuba_spp} spp"] = time.perf_counter() - t0

    ctx.frames, ctx.references, ctx.timings = seq, refs, timings
    ctx.extra["mitsuba"] = (mit, mitsuba_spp)
    return build_report(ctx, "glossrt demo")
