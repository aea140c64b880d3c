"""``glossrt demo``: render a built-in sequence and its references, write an HTML report.

The report is assembled from registered sections (:func:`glossrt.report.register_section`);
the foundation's sections are below, later techniques register their own.
"""

from __future__ import annotations

import time
from pathlib import Path

import drjit as dr
import numpy as np

from . import backend
from .errors import GlossrtError
from .report import DemoContext, Report, build_report, register_section


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


def _section_size(ctx: DemoContext, base: tuple[int, int], step: int,
                  floor: tuple[int, int]) -> tuple[float, tuple[int, int]]:
    """A paper section's image size: ``base`` scaled like the demo against its default 160
    pixels of width (smaller in the tests' small demos), rounded down to multiples of
    ``step``, at least ``floor``. Returns ``(scale, (w, h))``."""
    scale = min(1.0, ctx.frames[0].width / 160)
    return scale, tuple(max(lo, int(b * scale) // step * step)
                        for b, lo in zip(base, floor, strict=True))


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


@register_section("denoisers", order=40)
def section_denoisers(ctx: DemoContext, report: Report) -> None:
    from .experiments import DenoiserResults, denoisers

    res: DenoiserResults = ctx.extra.get("denoisers") or denoisers(
        size=(ctx.frames[0].width, ctx.frames[0].height), sequence=ctx.frames,
        references=ctx.references, static_frames=30)
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
        from .report.figures import new_figure

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


def _markdown_table(section, md: str, caption: str = "") -> None:
    """Show a Markdown table (as the experiments write them for docs/RESULTS.md)."""
    lines = [ln for ln in md.strip().splitlines() if ln.startswith("|")]
    cells = [[c.strip() for c in ln.strip("|").split("|")] for ln in lines]
    section.table(cells[0], cells[2:], caption=caption)


@register_section("lobes", order=50)
def section_lobes(ctx: DemoContext, report: Report) -> None:
    from . import lobe_experiments as le
    from . import upsampling_experiments as ue
    from .report.figures import plot_fig3

    t0 = time.perf_counter()
    # 96x72 at 256 spp for the demo's 160x120; smaller when the demo itself is (tests)
    _, size = _section_size(ctx, (96, 72), 4, (16, 12))
    spp = min(256, int(ctx.references[0].meta.get("spp", 256))) if ctx.references else 256
    s = report.section(
        "Specular-lobe-aware filtering and upsampling",
        "Tokuyoshi 2015: cross-bilateral filtering of the demodulated indirect light with the "
        "normal-aware weight, glossrt's sharpness-adapted screen kernel (the fig. 4(c) "
        "baseline) and the lobe-aware weight (beta 20, kappa 100, sigma_n^2 0.01; screen "
        f"kernel sigma_s 2 px, radius 6), at {size[0]}x{size[1]} against {spp} spp "
        "references; MSE of the indirect specular component. See docs/RESULTS.md for the "
        "full discussion; nothing is tuned to match the paper.")
    s.saved_figure("fig3.png", plot_fig3, "fig. 3 analogue: the lobe weight vs the angle "
                   "between lobe axes, exact (eq. 6) and approximate (eq. 7)")
    f4 = le.fig4(size=size, ref_spp=spp)
    _markdown_table(s, f4.markdown(), "fig. 4 analogue: roughness-map, indirect specular")
    s.images_row([(k, v) for k, v in f4.images.items()], name="fig4")
    f5 = le.fig5(size=size, ref_spp=spp)
    _markdown_table(s, f5.markdown(), "fig. 5 analogue: glossy-spheres, one parameter set")
    s.images_row([(k, v) for k, v in f5.images.items()], name="fig5")
    f6 = le.fig6(size=size, ref_spp=spp)
    _markdown_table(s, f6.markdown(), "fig. 6 analogue: optima per sphere")
    s.saved_figure("fig6.png", lambda p: f6.plot(str(p)), "fig. 6 analogue: MSE vs beta "
                   "(lobe) and vs 1/sigma_n^2 (normal), one line per Phong exponent")
    up = ue.upsampling(size=size, ref_spp=spp, low_spp=spp)
    _markdown_table(s, up.markdown(), "joint bilateral upsampling of converged 1/2 and 1/4 "
                    "resolution indirect light (roughness-map); adaptive re-sampling where the "
                    f"normalised weight sum < {up.threshold}")
    s.images_row([(k, v) for k, v in up.images.items()], name="upsampling")
    st = ue.spatio_temporal(size=size, frames=8, ref_spp=spp, ref_frames=(3, 7))
    _markdown_table(s, st.markdown(), "spatial vs spatio-temporal upsampling (1/2, jittered "
                    "1 spp low-resolution frames, animated glossy-cornell), indirect light MSE")
    ctx.timings["specular-lobe section (figs. 3-6, upsampling)"] = time.perf_counter() - t0


@register_section("ltc", order=60)
def section_ltc(ctx: DemoContext, report: Report) -> None:
    from . import ltc_experiments as le

    t0 = time.perf_counter()
    _, size = _section_size(ctx, (96, 72), 4, (16, 12))
    spp = min(512, int(ctx.references[0].meta.get("spp", 256)) * 2) if ctx.references else 512
    res = le.images(alphas=le.ALPHAS, size=size, ref_spp=spp, max_spp=64, textured=True)
    s = report.section(
        "Polygon lights: LTC",
        "Heitz et al. 2016 with glossrt's own GGX LTC fit: direct light of polygon-light "
        f"(teapot, sphere, glossy floor, one quad light) at {size[0]}x{size[1]}, LTC against an "
        f"unshadowed Monte Carlo reference of the same BRDF ({spp} spp), per GGX alpha and with "
        "the textured light (prefiltered texture); the Monte Carlo column gives the samples per "
        "pixel that reach LTC's RMSE (up to 64) and their time, measured in the same run. See "
        "docs/RESULTS.md for a larger run.")
    s.table(le.LTCImageResults.COLUMNS, res.table())
    for k, label in enumerate(res.labels):
        ltc = res.images[f"{label}: LTC"]
        ref = res.images[f"{label}: Monte Carlo {spp} spp"]
        s.images_row([(f"{label}: LTC", ltc), (f"{label}: Monte Carlo", ref)], name=f"ltc_{k}")
        s.error_map(f"ltc_error_{k}", ltc, ref, caption=f"{label}: relative error of "
                    "LTC against Monte Carlo (fig. 8 lower row analogue)")
    ctx.timings["LTC section"] = time.perf_counter() - t0


@register_section("bspvt", order=70)
def section_bspvt(ctx: DemoContext, report: Report) -> None:
    from . import bspvt_experiments as be

    t0 = time.perf_counter()
    scale, size = _section_size(ctx, (96, 72), 4, (16, 12))
    spp = min(512, int(ctx.references[0].meta.get("spp", 256)) * 2) if ctx.references else 512
    res = max(8, int(16 * scale))
    small = scale < 1.0  # (tests run the demo tiny)
    out = be.images(alphas=(0.1,) if small else (0.1, 1.0), frames=(0,) if small else (0, 24),
                    size=size, resolution=res, ref_spp=spp)
    s = report.section(
        "Polygon-light shadows: BSPVT",
        "Okuno & Iwasaki's binary space partitioning visibility trees on polygon-light "
        f"({size[0]}x{size[1]}, {res}x{res} cube maps per vertex, the moving light at frames "
        f"{', '.join(str(r['frame']) for r in out.rows[:2])}): mean absolute error against a "
        f"shadowed Monte Carlo reference ({spp} spp) of "
        "BSPVT per vertex (the paper's mode) and per pixel, the ratio estimator (Heitz, Hill & "
        "McGuire 2018, 4 spp, cross-bilateral denoised) and LTC without shadows, with the time "
        "per frame; the error split as in the paper's fig. 8 into LTC's (unshadowed LTC vs "
        "unshadowed Monte Carlo) and the visibility's. See docs/RESULTS.md for 64x64 maps.")
    _markdown_table(s, out.markdown(), "mean absolute error (ms per frame)")
    _markdown_table(s, out.direct_markdown(),
                    "against Mitsuba's own direct integrator (mean absolute error)")
    for k, im in out.images.items():
        s.images_row([(f"{k}: Monte Carlo", im["reference"]),
                      ("BSPVT per pixel", im["bspvt-pixel"]),
                      ("ratio estimator", im["ratio"]),
                      ("LTC, no shadows", im["ltc (no shadows)"])],
                     name=f"bspvt_{k.replace(' ', '_').replace(',', '')}")
        s.error_map(f"bspvt_err_{k.replace(' ', '_').replace(',', '')}", im["bspvt-pixel"],
                    im["reference"], caption=f"{k}: relative error of BSPVT per pixel")
    ctx.timings["BSPVT section"] = time.perf_counter() - t0


@register_section("highlights", order=75)
def section_highlights(ctx: DemoContext, report: Report) -> None:
    from . import highlight_experiments as he

    t0 = time.perf_counter()
    scale, size = _section_size(ctx, (160, 90), 2, (32, 18))
    ref = 256 if scale >= 1 else 32
    conv = he.convergence(size=size, ref_samples=ref, counts=(4, 16) if scale >= 1 else (4,))
    s = report.section(
        "Light-shape highlights",
        "Kimura & Tokoi 2004 on light-shapes: the lights rendered into a cube map per object, "
        "sampled with microfacet normals (the paper's ellipsoidal distribution: normal texture "
        "with embedded random numbers, per-pixel hash, 13-point regular pattern; and GGX "
        "visible normals with filtered importance sampling), against the converged reference "
        f"of the same model ({ref} samples), RMSE per sphere roughness. See docs/RESULTS.md.")
    _markdown_table(s, conv.markdown(), "RMSE against the same model's reference")
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


@register_section("specaa", order=80)
def section_specaa(ctx: DemoContext, report: Report) -> None:
    from . import specaa_experiments as se

    t0 = time.perf_counter()
    scale, size = _section_size(ctx, (160, 90), 2, (32, 18))
    spp = 256 if scale >= 1 else 16
    frames = 6 if scale >= 1 else 2
    res = se.evaluate(size=size, spp=spp, frames=frames, temporal_spp=min(spp, 64))
    s = report.section(
        "Specular antialiasing",
        "NDF filtering (Kaplanyan et al. 2016, as evaluated by Tokuyoshi) on normal-mapped: "
        "the half-vector filter and its bounding box, the deferred average-normal filter and "
        "its isotropic reductions, and projected-space filtering (Tokuyoshi & Kaplanyan 2021), "
        f"against the unfiltered shading averaged over {spp} sub-pixel positions; temporal "
        f"error over {frames} frames of the slow camera motion (the reference's own change "
        "is the floor). See docs/RESULTS.md.")
    _markdown_table(s, res.markdown(), "error against the supersampled reference")
    keys = list(res.images)
    for i in range(0, len(keys), 4):
        s.images_row([(k, res.images[k]) for k in keys[i:i + 4]], name=f"specaa_{i}")
    ref = res.images[keys[-1]]
    for k in ("none", "avgnormal-eig"):
        if k in res.images:
            s.error_map(f"specaa_err_{k}", res.images[k], ref,
                        caption=f"relative error of {k} against the supersampled reference")
    ctx.timings["specaa section"] = time.perf_counter() - t0


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
             scene: str = "glossy-cornell", log=print) -> Path:
    """Render, measure and report; returns the path of ``index.html``. Bad arguments
    (:func:`check_demo_args`) and scenes fail before anything is written."""
    from . import render, scenes
    from .frame import frame_filename
    from .progress import Progress

    check_demo_args(size, frames, ref_every, ref_spp, mitsuba_spp)
    out = Path(out)
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
    with Progress(frames, "1 spp frames") as p:
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
    with Progress(len(idx) * ref_spp, f"references ({ref_spp} spp)") as p:
        for k, i in enumerate(idx):
            ref = r.render_reference(i, ref_spp, progress=lambda d, n, k=k: p.update(k * n + d))
            ref.save(out / "references" / frame_filename(i))
            refs.append(ref)
    timings[f"references, {ref_spp} spp, per frame"] = (time.perf_counter() - t0) / len(idx)

    t0 = time.perf_counter()
    mit = r.render_mitsuba(0, mitsuba_spp)
    dr.eval(mit)  # Dr.Jit is lazy: time the rendering, not the tracing
    dr.sync_thread()
    timings[f"Mitsuba path, {mitsuba_spp} spp"] = time.perf_counter() - t0

    ctx = DemoContext(out_dir=out, scene=scene, frames=seq, references=refs, timings=timings,
                      extra={"mitsuba": (mit, mitsuba_spp)})
    return build_report(ctx, "glossrt demo")
