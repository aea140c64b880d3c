"""Measured comparisons behind docs/RESULTS.md and the report (``glossrt experiment``).

``denoisers``: every denoiser on an animated 1 spp sequence against converged references
(RMSE, SSIM, FLIP, wall time per frame), and the temporal error of each on a static
sequence (Schied 2017, sec. 5.4 / fig. 10).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from . import metrics
from .timing import steady_median, timed_eval

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
    from . import backend

    if method == "optix" and not backend.is_gpu():
        return "needs a CUDA GPU (cuda_ad_rgb)"
    if method == "oidn":
        try:
            from .denoise.oidn import oidn_available

            if not oidn_available():
                return "pyoidn not usable"
        except ImportError as e:
            return f"pyoidn not importable: {e}"
    return None


def _run_sequence(method: str, frames: list) -> tuple[list, list[float]]:
    from . import denoise

    d = denoise.make(method)
    outs, secs = [], []
    for f in frames:
        img, t = timed_eval(d, f)
        secs.append(t)
        outs.append(img)
    return outs, secs


def denoisers(size=(160, 120), frames: int = 20, ref_every: int = 10, ref_spp: int = 512,
              static_frames: int = 40, methods=DEFAULT_METHODS, scene: str = "glossy-cornell",
              progress=None, sequence=None, references=None) -> DenoiserResults:
    """Run the comparison; ``sequence``/``references`` may be passed in (e.g. by the demo)."""
    from . import render, scenes

    res = DenoiserResults(size=tuple(size), frames=frames, ref_spp=ref_spp,
                          methods=list(methods))
    if sequence is None:
        setup = scenes.load(scene, size=size, frames=frames)
        r = render.Renderer(setup)
        sequence = [r.render(i) for i in range(frames)]
        references = [r.render_reference(i, ref_spp) for i in range(0, frames, ref_every)]
    refs = {f.index: f for f in references}
    rs = render.Renderer(scenes.load_static(scene, size=size))
    static = [rs.render(i) for i in range(static_frames)]
    for k, m in enumerate(methods):
        why = _available(m)
        if why:
            res.skipped[m] = why
            continue
        outs, secs = _run_sequence(m, sequence)
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
        souts, _ = _run_sequence(m, static)
        res.temporal[m] = [metrics.temporal_error(souts[i - 1:i + 1])
                           for i in range(1, len(souts))]
        if progress:
            progress(k + 1)
    res.images["1 spp"] = sequence[max(refs)]["color"]
    res.images["reference"] = refs[max(refs)]["color"]
    return res
