"""Upsampling measurements behind docs/RESULTS.md and the report (Tokuyoshi 2015, secs.
5.3-5.4; issue 4's "Upsampling (1/2 and 1/4): error and time, normal vs lobe weights").

``upsampling``: on ``roughness-map`` the indirect light of a converged low-resolution render
(1/2 and 1/4) is upsampled to the full-resolution G-buffer with normal and lobe weights (so
the error is the upsampling's own, not noise), against a converged full-resolution reference;
adaptive re-sampling re-renders the pixels whose normalised weight sum is below a threshold.
``spatio_temporal``: on the animated ``glossy-cornell`` sequence, 1 spp low-resolution frames
(jittered) upsampled per frame (spatial only) and with the spatio-temporal upsampler.
``fig7``: Tokuyoshi 2015 fig. 7 analogue: the same on ``normal-mapped`` with a
Toksvig-filtered normal map and roughness, spatial only vs glossrt's simplified history vs
Herzog 2010's confidence weighting.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import drjit as dr
import numpy as np

from ..errors import GlossrtError
from ..frame import RADIANCE
from ..report.registry import (
    experiment_cluster,
    experiment_scale,
    finish_experiment,
    paper_value,
    register_experiment,
)

INDIRECT = ("indirect_diffuse", "indirect_specular")


def _indirect(frame) -> np.ndarray:
    return sum(frame.numpy(c) for c in INDIRECT)


def _rest(frame) -> np.ndarray:
    return sum(frame.numpy(c) for c in RADIANCE if c not in INDIRECT)


@dataclass
class UpsamplingResults:
    size: tuple[int, int]
    ref_spp: int
    low_spp: int
    threshold: float
    #: one row per (factor, weight): mse (indirect), mse_specular, ms, resampled, mse_adaptive
    rows: list[dict] = field(default_factory=list)
    images: dict[str, np.ndarray] = field(default_factory=dict)

    COLUMNS = ["factor", "weights", "MSE indirect", "MSE indirect specular", "ms / upsample",
               "re-sampled pixels", "MSE after re-sampling"]

    def table(self) -> list[list]:
        return [[f"1/{r['factor']}", r["weight"], r["mse"], r["mse_specular"], r["ms"],
                 r["resampled"], r["mse_adaptive"]] for r in self.rows]

    def markdown(self) -> str:
        lines = ["| " + " | ".join(self.COLUMNS) + " |", "|" + "---|" * len(self.COLUMNS)]
        for row in self.table():
            cells = [str(v) if isinstance(v, str | int) else f"{v:.4g}" for v in row]
            lines.append("| " + " | ".join(cells) + " |")
        return "\n".join(lines)


def upsampling(size: tuple[int, int] = (192, 144), ref_spp: int = 256, low_spp: int = 256,
               factors: tuple[int, ...] = (2, 4), threshold: float = 0.05,
               resample_spp: int | None = None, scene: str = "roughness-map",
               progress: Callable[[str], None] | None = None,
               cluster=None) -> UpsamplingResults:
    """Error (MSE of the indirect light against a ``ref_spp`` reference) and wall time of
    joint bilateral upsampling from each factor, normal vs lobe weights, and adaptive
    re-sampling (``resample_spp`` samples per re-rendered pixel, default ``low_spp``).
    ``cluster``: where the references (full and low resolution) are rendered
    (:func:`glossrt.render.blocks.references`)."""
    from .. import render, scenes
    from ..denoise.upsampling import adaptive_resample, upsample
    from ..render import blocks

    w, h = size
    for f in factors:
        if w % f or h % f:
            raise GlossrtError(f"size {w}x{h} is not a multiple of the factor {f}")
    say = progress or (lambda _m: None)
    full_r = render.Renderer(scenes.load(scene, size=size))
    full = full_r.render(0)
    say(f"reference {w}x{h}, {ref_spp} spp")
    ref = blocks.references(full_r, blocks.reference_job(scene, size), [0], ref_spp,
                            cluster, desc=f"reference {scene} {ref_spp} spp")[0]
    tgt, rest = _indirect(ref), _rest(full)
    spec = ref.numpy("indirect_specular")
    res = UpsamplingResults(size, ref_spp, low_spp, threshold)
    res.images["reference (indirect)"] = tgt
    for f in factors:
        say(f"1/{f}: low-resolution reference {w // f}x{h // f}, {low_spp} spp")
        low_size = (w // f, h // f)
        low = blocks.references(render.Renderer(scenes.load(scene, size=low_size)),
                                blocks.reference_job(scene, low_size), [0], low_spp, cluster,
                                desc=f"reference {scene} 1/{f} {low_spp} spp")[0]
        for weight in ("normal", "lobe"):
            dr.eval(upsample(full, low, weight=weight))  # warm the kernel cache
            times = []
            for _ in range(3):
                t0 = time.perf_counter()
                img, wts = upsample(full, low, weight=weight, return_weights=True)
                dr.eval(img, wts)
                dr.sync_thread()
                times.append(time.perf_counter() - t0)
            img = np.array(img)
            ind = img - rest
            spec_only = np.array(upsample(full, low, weight=weight,
                                          channels=("indirect_specular",)))
            spec_err = spec_only - sum(full.numpy(c) for c in RADIANCE
                                       if c != "indirect_specular") - spec
            out, mask = adaptive_resample(full_r, 0, full, img, wts, threshold=threshold,
                                          spp=resample_spp or low_spp)
            res.rows.append({
                "factor": f, "weight": weight,
                "mse": float(np.mean((ind - tgt) ** 2)),
                "mse_specular": float(np.mean(spec_err ** 2)),
                "ms": 1000 * float(np.median(times)),
                "resampled": int(mask.sum()),
                "mse_adaptive": float(np.mean((np.array(out) - rest - tgt) ** 2)),
            })
            res.images[f"1/{f} {weight}"] = ind
            if weight == "lobe":
                res.images[f"1/{f} re-sampled pixels (lobe)"] = np.repeat(
                    mask[..., None].astype(np.float32), 3, -1)
    return res


@dataclass
class SpatioTemporalResults:
    size: tuple[int, int]
    factor: int
    frames: int
    ref_spp: int
    ref_frames: list[int]
    #: (weight, mode) -> MSE of the indirect light per referenced frame
    mse: dict[tuple[str, str], list[float]] = field(default_factory=dict)
    ms: dict[tuple[str, str], float] = field(default_factory=dict)

    def markdown(self) -> str:
        head = ["weights", "upsampling"] + [f"MSE frame {i}" for i in self.ref_frames] + [
            "ms / frame"]
        lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        for (weight, mode), errs in self.mse.items():
            cells = [weight, mode] + [f"{e:.4g}" for e in errs] + [
                f"{self.ms[(weight, mode)]:.3g}"]
            lines.append("| " + " | ".join(cells) + " |")
        return "\n".join(lines)


def _sequence(scene: str, size, factor: int, frames: int, ref_frames, ref_spp: int,
              cluster, say, cache=None) -> tuple[dict, list, object]:
    """The references' indirect light at ``ref_frames`` (rendered on ``cluster``, kept in
    ``cache``: :func:`glossrt.render.blocks.references`), each frame's full-resolution
    G-buffer and the 1/``factor`` resolution renderer (:func:`_lows` makes its 1 spp
    sequence)."""
    from .. import render, scenes
    from ..render import blocks

    w, h = size
    full_r = render.Renderer(scenes.load(scene, size=size))
    low_r = render.Renderer(scenes.load(scene, size=(w // factor, h // factor)))
    say(f"reference frames {list(ref_frames)}, {ref_spp} spp")
    refs = {f.index: _indirect(f) for f in blocks.references(
        full_r, blocks.reference_job(scene, size), ref_frames, ref_spp, cluster,
        desc=f"references {scene} {ref_spp} spp", cache=cache)}
    return refs, [full_r.render(i) for i in range(frames)], low_r


def _lows(low_r, factor: int, frames: int, seed: int | None = None) -> list:
    """The jittered 1 spp low-resolution sequence (``seed``: None for the renderer's own;
    distinct seeds give independent noise)."""
    from ..denoise.upsampling import jitter_sequence

    return [low_r.render(i, jitter=jitter_sequence(factor, i), seed=seed)
            for i in range(frames)]


def _upsample_sequence(seq: list, refs: dict, step) -> tuple[list[float], float, dict]:
    """``step(full, low)`` on every frame of ``seq``: the MSE of the indirect light at the
    referenced frames, the median ms per frame after the first, and the upsampled indirect
    light at the referenced frames (frame -> (H, W, 3))."""
    errs, times, outs = [], [], {}
    for i, (full, low) in enumerate(seq):
        t0 = time.perf_counter()
        img = step(full, low)
        dr.eval(img)
        dr.sync_thread()
        times.append(time.perf_counter() - t0)
        if i in refs:
            outs[i] = np.array(img) - _rest(full)
            errs.append(float(np.mean((outs[i] - refs[i]) ** 2)))
    return errs, 1000 * float(np.median(times[1:] or times)), outs


def spatio_temporal(size: tuple[int, int] = (192, 144), factor: int = 2, frames: int = 16,
                    ref_spp: int = 256, ref_frames: tuple[int, ...] = (7, 15),
                    scene: str = "glossy-cornell",
                    progress: Callable[[str], None] | None = None,
                    cluster=None) -> SpatioTemporalResults:
    """Spatial-only vs spatio-temporal upsampling of 1 spp, jittered low-resolution indirect
    light over an animated sequence (camera and object motion), MSE of the indirect light
    against references at ``ref_frames`` (rendered on ``cluster``:
    :func:`glossrt.render.blocks.references`)."""
    from ..denoise.upsampling import SpatioTemporalUpsampler, upsample

    say = progress or (lambda _m: None)
    refs, fulls, low_r = _sequence(scene, size, factor, frames, ref_frames, ref_spp, cluster,
                                   say)
    seq = list(zip(fulls, _lows(low_r, factor, frames), strict=True))
    res = SpatioTemporalResults(size, factor, frames, ref_spp, list(ref_frames))
    for weight in ("normal", "lobe"):
        st = SpatioTemporalUpsampler(weight=weight)
        for mode in ("spatial", "spatio-temporal"):
            st.reset()
            step = st if mode == "spatio-temporal" else (
                lambda full, low, weight=weight: upsample(full, low, weight=weight))
            res.mse[(weight, mode)], res.ms[(weight, mode)], _ = _upsample_sequence(
                seq, refs, step)
    return res


# -- Tokuyoshi 2015, fig. 7: spatio-temporal upsampling on a normal-mapped glossy scene ---------

#: the built-in scene of :func:`fig7`: ``normal-mapped`` with its normal maps replaced by a
#: Toksvig-filtered mip level and the matching per-texel roughness
#: (:func:`glossrt.scenes.library.normal_mapped_toksvig`)
FIG7_SCENE = "normal-mapped-toksvig"
#: the histories compared (SpatioTemporalUpsampler's ``history``), with their table names
FIG7_MODES = (("spatial", None), ("simplified history", "ema"),
              ("Herzog confidence", "herzog"))
#: what differs from the paper's fig. 7 scene (stated with the table)
FIG7_DIFFERENCES = (
    "Differences from the paper's fig. 7: glossrt's `normal-mapped` scene (GGX aluminium "
    "floor and sphere, procedural bumps and scratches, slow camera dolly) instead of the "
    "paper's voxel-cone-traced room with a horse; path-traced 1 spp indirect light at 1/2 "
    "resolution (jittered) instead of cone tracing; one fixed mip level of the normal map "
    "(Toksvig-filtered) for the whole image instead of per-pixel mip selection. The "
    "G-buffer's roughness channel (the lobe weight's input) is the per-texel Toksvig alpha "
    "Mitsuba renders (before 2026-12-02's fourth session it was each material's mean).")


@dataclass
class Fig7Results(SpatioTemporalResults):
    mip_level: int = 0
    #: independent 1 spp sequences (seeds); ``mse`` is the mean over them
    inputs: int = 1
    #: inputs >= 2: (weight, mode) -> per referenced frame, the error split into bias^2 and
    #: variance over the inputs (:class:`glossrt.experiments.lobes.ErrorSplit`)
    split: dict = field(default_factory=dict)

    def markdown(self) -> str:
        w, h = self.size
        head = (f"{w}x{h}, 1/{self.factor} resolution 1 spp jittered indirect light, "
                f"{self.frames} frames, references {self.ref_spp} spp, Toksvig mip level "
                f"{self.mip_level}"
                + (f", MSE the mean over {self.inputs} independent sequences (seeds "
                   f"{FIG7_SEED0}-{FIG7_SEED0 + self.inputs - 1})" if self.inputs > 1 else "")
                + ".\n\n")
        return head + super().markdown() + self._split_markdown() + "\n\n" + FIG7_DIFFERENCES

    def _split_markdown(self) -> str:
        if not self.split:
            return ""
        cols = ["weights", "upsampling"]
        for i in self.ref_frames:
            cols += [f"frame {i}: bias^2", "variance"]
        lines = ["", "", f"The same MSE split over the {self.inputs} sequences: variance = "
                 "the unbiased variance over them per pixel, bias^2 = (their mean - "
                 "reference)^2 - variance / K (it holds the reference's own noise).", "",
                 "| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
        for (weight, mode), per_frame in self.split.items():
            cells = [weight, mode]
            for e in per_frame:
                cells += [f"{e.bias2:.3g}", f"{e.variance:.3g}"]
            lines.append("| " + " | ".join(cells) + " |")
        return "\n".join(lines)

    def as_dict(self) -> dict:
        return {"size": list(self.size), "frames": self.frames, "ref_spp": self.ref_spp,
                "ref_frames": list(self.ref_frames), "inputs": self.inputs,
                "mse": {f"{w} / {m}": v for (w, m), v in self.mse.items()},
                "ms": {f"{w} / {m}": v for (w, m), v in self.ms.items()},
                "split": {f"{w} / {m}": [{"bias2": e.bias2, "variance": e.variance,
                                          "per_input": e.per_input} for e in v]
                          for (w, m), v in self.split.items()}}


#: the first seed of fig. 7's independent sequences when there are several (one sequence:
#: the renderer's own seed, as the quick run)
FIG7_SEED0 = 1


def fig7(size: tuple[int, int] = (160, 90), frames: int = 16, ref_spp: int = 256,
         ref_frames: tuple[int, ...] | None = None, factor: int = 2,
         progress: Callable[[str], None] | None = None, cluster=None,
         cache=None, inputs: int = 1) -> Fig7Results:
    """Tokuyoshi 2015 fig. 7 analogue (sec. 5.3): spatio-temporal upsampling of 1 spp
    jittered 1/``factor`` resolution indirect light on the normal-mapped glossy scene with
    Toksvig-filtered roughness (:data:`FIG7_SCENE`, :data:`FIG7_DIFFERENCES`): spatial only,
    glossrt's simplified history and Herzog 2010's confidence weighting, normal and lobe
    weights; MSE of the indirect light against ``ref_spp`` references at ``ref_frames``
    (default: the middle and the last frame), rendered on ``cluster`` and kept in ``cache``
    (:func:`glossrt.render.blocks.references`; a built-in scene, so workers load it by
    name). ``inputs`` >= 2: that many independent 1 spp sequences (seeds
    :data:`FIG7_SEED0` + k), the MSE their mean and split into bias^2 and variance
    (:attr:`Fig7Results.split`); the times are the first sequence's."""
    from ..denoise.upsampling import SpatioTemporalUpsampler, upsample
    from ..scenes.library import NORMAL_MAPPED_TOKSVIG_LEVEL
    from .lobes import BiasVariance

    w, h = size
    if frames < 1:
        raise GlossrtError(f"fig7: frames must be >= 1, got {frames}")
    if w % factor or h % factor:
        raise GlossrtError(f"fig7: size {w}x{h} is not a multiple of the factor {factor}")
    ref_frames = tuple(sorted({frames // 2, frames - 1})) if ref_frames is None \
        else tuple(ref_frames)
    if any(not 0 <= i < frames for i in ref_frames):
        raise GlossrtError(f"fig7: reference frames {list(ref_frames)} outside 0..{frames - 1}")
    if ref_spp < 1:
        raise GlossrtError(f"fig7: ref_spp must be >= 1, got {ref_spp}")
    if inputs < 1:
        raise GlossrtError(f"fig7: inputs must be >= 1, got {inputs}")
    say = progress or (lambda _m: None)
    refs, fulls, low_r = _sequence(FIG7_SCENE, size, factor, frames, ref_frames, ref_spp,
                                   cluster, say, cache)
    res = Fig7Results(size, factor, frames, ref_spp, list(ref_frames),
                      mip_level=NORMAL_MAPPED_TOKSVIG_LEVEL, inputs=inputs)
    seeds = [None] if inputs == 1 else [FIG7_SEED0 + k for k in range(inputs)]
    acc: dict = {}
    for k, seed in enumerate(seeds):
        if inputs > 1:
            say(f"independent sequence {k + 1} of {inputs} (seed {seed})")
        seq = list(zip(fulls, _lows(low_r, factor, frames, seed), strict=True))
        for weight in ("normal", "lobe"):
            for mode, history in FIG7_MODES:
                step = ((lambda full, low, weight=weight: upsample(full, low, weight=weight))
                        if history is None
                        else SpatioTemporalUpsampler(weight=weight, history=history))
                errs, ms, outs = _upsample_sequence(seq, refs, step)
                key = (weight, mode)
                res.mse[key] = [a + e / inputs for a, e in
                                zip(res.mse.get(key, [0.0] * len(errs)), errs, strict=True)]
                res.ms.setdefault(key, ms)
                if inputs > 1:
                    bv = acc.setdefault(key, {i: BiasVariance(refs[i], {"image": None})
                                              for i in ref_frames})
                    for i in ref_frames:
                        bv[i].add(outs[i])
    res.split = {key: [bv[i].split("image") for i in ref_frames] for key, bv in acc.items()}
    return res


#: ``glossrt experiment --which fig7 --scale paper``: the size of Tokuyoshi 2015's fig. 5
#: (the paper gives none for fig. 7), 16 frames (the jitter cycle of 2x2 four times), the
#: middle and last frame referenced at the SVGF paper's 4096 spp
FIG7_PAPER_SIZE = (640, 360)
FIG7_PAPER_FRAMES = 16
FIG7_PAPER_REF_SPP = 4096
#: independent 1 spp sequences at paper scale, for the bias / variance split (glossrt's
#: choice; the paper shows one)
FIG7_PAPER_INPUTS = 8


@register_experiment("fig7", "Tokuyoshi 2015 fig. 7 analogue: spatio-temporal upsampling "
                     "(simplified history vs Herzog 2010 confidence, normal and lobe "
                     "weights) on the Toksvig-filtered normal-mapped scene (--size, --spp, "
                     "--frames); --scale paper: 640x360, 16 frames, 4096 spp references",
                     order=25)
def run_fig7(out, size, args) -> int:
    """:func:`fig7` at ``size`` with ``--spp`` references and ``--frames`` frames; ``--scale
    paper``: :data:`FIG7_PAPER_SIZE`, :data:`FIG7_PAPER_FRAMES` and
    :data:`FIG7_PAPER_REF_SPP` where the option was not given, and
    :data:`FIG7_PAPER_INPUTS` independent sequences. Writes fig7.md / .json."""
    size = tuple(paper_value(args, "size", size, FIG7_PAPER_SIZE))
    frames = int(paper_value(args, "frames", args.frames, FIG7_PAPER_FRAMES))
    spp = int(paper_value(args, "spp", args.spp, FIG7_PAPER_REF_SPP))
    inputs = FIG7_PAPER_INPUTS if experiment_scale(args) == "paper" else 1
    t0 = time.perf_counter()
    res = fig7(size=size, frames=frames, ref_spp=spp, cluster=experiment_cluster(args),
               progress=lambda m: print(m, flush=True), cache=out / "references",
               inputs=inputs)
    seconds = time.perf_counter() - t0
    md = (f"## Tokuyoshi 2015 fig. 7 analogue ({seconds:.0f} s)\n\n{res.markdown()}")
    return finish_experiment(out, "fig7", md, "fig7.json",
                             {**res.as_dict(), "seconds": seconds})
