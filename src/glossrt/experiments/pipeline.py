"""Measurements behind docs/RESULTS.md for the frame pipeline that composes the five papers
(:mod:`glossrt.pipeline`, issue 25): the report section ``pipeline``, the benchmark case
``pipeline`` and ``glossrt experiment --which pipeline``.

For every preset of :data:`PRESETS` on every scene of :data:`SCENES` (a pair the pipeline
refuses is kept as a row with the pipeline's own reason), against the converged reference
(:meth:`glossrt.render.Renderer.render_reference` at ``spp``, the same frame indices):

* **with motion**: frames ``0 .. F-1`` of the scene's animation, one reference per frame;
  **without motion**: the same number of frames of a static copy
  (:func:`glossrt.scenes.load_static`), one reference for all of them;
* RMSE and FLIP (:mod:`glossrt.metrics`), averaged over the frames ``F // 2 .. F-1`` (the
  temporal filters' history is built in the first half);
* temporal error: the part of the sequence's frame-to-frame luminance change the reference
  does not have, ``mean_t mean_pixels |(L_t - L_{t-1}) - (R_t - R_{t-1})|`` over the same
  frames (:func:`glossrt.metrics.flicker`). Without motion the reference is one image, so
  this is Schied et al. 2017's temporal error (:func:`glossrt.metrics.temporal_error`,
  sec. 5.4) of the sequence itself;
* per-stage milliseconds: the median of each frame's ``meta["pipeline"]["stage_ms"]`` (the
  kernel time of each stage, stages not synchronised: :class:`glossrt.timing.StageClock`)
  over the frames after the first two (the first records the frozen kernels), on the static
  copy;
* the floor to beat: the raw 1 spp input, the path tracer's ``color`` (no light removed), and
  the reference scored against itself (0 by construction: a check of the metric path).

Composition interactions (:data:`VARIANTS`, on :data:`INTERACTION_SCENE`): ``full`` with one
choice changed (SVGF's normal weights instead of Tokuyoshi 2015's lobe weights, BSPVT per
pixel instead of per vertex, TAA off); the notes state, with numbers, where adding one
paper's technique makes the composed result worse.

The benchmark case (:func:`bench_pipeline`) measures issue 25's speed figures in one run:
the steady-state frame rate of ``full`` and ``schied2017`` at the issue's sizes with
per-stage kernel milliseconds (:func:`timing`: the composed frame against the sum of its
stages run alone, called in turn, :func:`glossrt.timing.round_robin`), and the peak memory
of a steady-state frame at 640x360 and 1920x1080 (:func:`memory`, each in a fresh process).
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import GlossrtError
from ..metrics import flicker
from ..report import DemoContext, Report, register_section
from ..report.registry import (
    BenchContext,
    benchmark,
    experiment_cluster,
    experiment_scale,
    finish_experiment,
    markdown_table,
    paper_value,
    register_experiment,
    section_size,
)

PRESETS = ("schied2017", "okuno-iwasaki", "kimura-tokoi", "tokuyoshi2015", "full")
SCENES = ("glossy-cornell", "polygon-light", "light-shapes", "normal-mapped", "roughness-map")
FLOOR = "1 spp input"
REFERENCE = "reference"
#: ``full`` with one choice changed: where one paper's technique meets another's
VARIANTS: dict[str, tuple[str, dict]] = {
    "full, indirect=svgf": ("full", {"indirect": "svgf"}),
    "full, bspvt_mode=pixel": ("full", {"bspvt_mode": "pixel"}),
    "full, taa off": ("full", {"taa": False}),
}
INTERACTION_SCENE = "polygon-light"
#: a scene name with this suffix: the scene rendered with direct light only (Mitsuba's
#: ``max_depth`` 2 for the pipeline, the 1 spp input and the references alike), as the
#: SVGF paper's fig. 11
DIRECT_ONLY = "@direct"
#: ``--scale paper`` (issue 28; Schied et al. 2017, Table 1 and figs. 10-12): the sizes and
#: scenes of the paper's evaluation as far as glossrt has them. The animated glossy scene; a
#: direct-lighting-only scene (fig. 11: polygon-light at max_depth 2); a many-lights scene
#: (fig. 12: light-shapes, 18 polygon lights). glossrt's choices, where the paper gives
#: none: 12 frames of each animation, the last :data:`PAPER_REF_FRAMES` of them referenced
#: and scored (the filters' history builds over the first 9), no static runs (the temporal
#: error is measured against the references' own change over the scored frames)
PAPER_SIZE = (1280, 720)
PAPER_SCENES = ("glossy-cornell", "polygon-light" + DIRECT_ONLY, "light-shapes")
PAPER_FRAMES = 12
PAPER_REF_FRAMES = 3
PAPER_REF_SPP = 4096
#: at paper scale, on every scene: SVGF (inside ``schied2017``, with its TAA) against the
#: other reconstructions in the same pipeline, and without TAA
PAPER_VARIANTS: dict[str, tuple[str, dict]] = {
    "schied2017, indirect=atrous": ("schied2017", {"indirect": "atrous"}),
    "schied2017, indirect=oidn": ("schied2017", {"indirect": "oidn"}),
    "schied2017, taa off": ("schied2017", {"taa": False}),
}
#: the benchmark's frame-rate cases: (preset, scene, size, issue 25's fps target on a 2-core
#: CPU)
BENCH_CASES = (("full", "polygon-light", (320, 180), 20.0),
               ("full", "polygon-light", (640, 360), 8.0),
               ("schied2017", "glossy-cornell", (320, 180), 30.0))
TARGET_RATIO = 1.10  # the composed frame against the sum of its stages run alone
#: the benchmark's memory cases (preset, scene, size, options; ``outputs`` is the
#: pipeline's, :attr:`glossrt.pipeline.Pipeline.outputs`); issue 25: at most 600 MB at
#: 1920x1080. The 1920x1080 frame as shipped (every channel and layer returned), with
#: ``release_memory``, and with it returning the composed colour alone (what a viewer or an
#: engine keeps of a frame)
MEMORY_CASES = (("full", "polygon-light", (640, 360), {}),
                ("full", "polygon-light", (1920, 1080), {}),
                ("full", "polygon-light", (1920, 1080), {"release_memory": True}),
                ("full", "polygon-light", (1920, 1080),
                 {"release_memory": True, "outputs": ["color"]}))
MEMORY_TARGET_MB = 600.0
#: ``pipeline_shrink`` values: every size of the cases stays even (1/2-resolution indirect)
SHRINKS = (1, 2, 5, 10)
#: the benchmark case's options (``glossrt bench --case-option KEY=VALUE``)
BENCH_OPTIONS = {
    "pipeline_shrink": "divide every size of the pipeline case by 2, 5 or 10 (a quick run); "
                       "1 (default): the issue's sizes",
    "pipeline_memory": "true (default) or false: measure the memory cases (each in a fresh "
                       "process)",
    "pipeline_choices": "pipeline options for every case, a JSON object "
                        "(e.g. {\"bspvt_resolution\": 16})",
}



@dataclass
class PipelineResults:
    size: tuple[int, int]
    spp: int
    frames: int
    scenes: tuple[str, ...]
    presets: tuple[str, ...]
    #: one dict per (scene, row label, motion): metrics, or ``skipped`` with the reason
    rows: list[dict] = field(default_factory=list)
    #: scene -> label -> last frame of the motion sequence (colour); ``layers``: full's layers
    images: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)
    layers: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)
    seconds: float = 0.0
    #: None: every frame referenced, the second half scored; N: only the last N frames
    #: referenced and scored
    ref_frames: int | None = None
    #: the composition rows (label -> preset, changed choices) measured
    variants: dict[str, tuple[str, dict]] = field(default_factory=lambda: dict(VARIANTS))

    @property
    def first(self) -> int:
        """The first frame scored (the temporal filters' history builds before it)."""
        if self.ref_frames:
            return self.frames - self.ref_frames
        return max(1, self.frames // 2)

    def referenced(self) -> list[int]:
        """The frames of the motion sequences that get a reference."""
        return list(range(self.first if self.ref_frames else 0, self.frames))

    def row(self, scene: str, label: str, motion: bool) -> dict | None:
        return next((r for r in self.rows if r["scene"] == scene and r["label"] == label
                     and r["motion"] == motion), None)

    def labels(self, scene: str) -> list[str]:
        out: list[str] = []
        for r in self.rows:
            if r["scene"] == scene and r["label"] not in out:
                out.append(r["label"])
        return out

    def markdown(self) -> str:
        static = any(not r["motion"] for r in self.rows)
        lines = ["| scene | pipeline (direct) | RMSE | x floor | SSIM | FLIP | temporal | " +
                 ("RMSE static | FLIP static | temporal static | " if static else "") +
                 f"ms / frame: stages{' (static)' if static else ''} |",
                 "|---|---|---|---|---|---|---|" + ("---|---|---|" if static else "") + "---|"]
        for scene in self.scenes:
            for label in self.labels(scene):
                mo, st = self.row(scene, label, True), self.row(scene, label, False)
                floor = self.row(scene, FLOOR, True)
                direct = next((r.get("direct") for r in (mo, st) if r and r.get("direct")),
                              None)
                name = f"{label} ({direct})" if direct else label
                cells = [scene, name]
                for r in (mo, st) if static else (mo,):
                    if r is None or r.get("skipped"):
                        cells += ["-"] * (5 if r is mo else 3)
                        continue
                    cells.append(f"{r['rmse']:.4f}")
                    if r is mo:
                        ratio = (r["rmse"] / floor["rmse"] if floor and floor["rmse"] > 0
                                 else float("nan"))
                        cells += [f"{ratio:.2f}", f"{r['ssim']:.3f}"]
                    cells += [f"{r['flip']:.4f}", f"{r['temporal']:.4f}"]
                ms = (st or {}).get("stage_ms") or (mo or {}).get("stage_ms")
                cells.append(" + ".join(f"{k} {v:.1f}" for k, v in ms.items())
                             + f" = {sum(ms.values()):.1f}" if ms else "-")
                lines.append("| " + " | ".join(cells) + " |")
        return "\n".join(lines)

    def skips(self) -> list[str]:
        return [f"{r['label']} on {r['scene']} ({'with' if r['motion'] else 'without'} "
                f"motion): {r['skipped']}" for r in self.rows if r.get("skipped")]

    def interactions(self) -> list[str]:
        """One sentence per composition row measured (:attr:`variants`): the change of RMSE,
        FLIP and temporal error from its preset (with and without motion) when the one choice
        differs."""
        out = []
        for scene in self.scenes:
            for label, (preset, choices) in self.variants.items():
                parts = []
                for motion in (True, False):
                    v, base = self.row(scene, label, motion), self.row(scene, preset, motion)
                    if not v or not base or v.get("skipped") or base.get("skipped"):
                        continue
                    d = {k: v[k] - base[k] for k in ("rmse", "flip", "temporal")}
                    parts.append(f"{'with' if motion else 'without'} motion: RMSE "
                                 f"{base['rmse']:.4f} -> {v['rmse']:.4f} ({d['rmse']:+.4f}), "
                                 f"FLIP {base['flip']:.4f} -> {v['flip']:.4f} "
                                 f"({d['flip']:+.4f}), temporal {base['temporal']:.4f} -> "
                                 f"{v['temporal']:.4f} ({d['temporal']:+.4f})")
                if parts:
                    change = ", ".join(f"{k}={c}" for k, c in choices.items())
                    out.append(f"{scene}, {preset} -> {change}: " + "; ".join(parts))
        return out

    def as_dict(self) -> dict:
        return {"size": list(self.size), "spp": self.spp, "frames": self.frames,
                "scored_frames": [self.first, self.frames - 1], "scenes": list(self.scenes),
                "presets": list(self.presets), "rows": self.rows,
                "ref_frames": self.ref_frames,
                "interactions": self.interactions(), "seconds": self.seconds}

    def montage(self, path: str | Path, scene: str) -> Path:
        """One scene: the 1 spp input, every preset's composed frame and the reference (last
        frame with motion), the error ``|x - reference|`` under each, and ``full``'s stage
        layers in the last row."""
        from ..report.figures import Panel, montage
        from ..report.page import tonemap

        imgs = self.images[scene]
        ref = imgs[REFERENCE]
        keys = [k for k in imgs if k != REFERENCE] + [REFERENCE]
        layers = self.layers.get(scene, {})
        cols = max(len(keys), len(layers), 1)
        scale = max(float(np.percentile(np.abs(ref), 99.5)), 1e-6)
        grid: list[list[Panel | None]] = [
            [Panel(tonemap(imgs[k]), k, fontsize=7) for k in keys],
            [Panel(np.abs(imgs[k] - ref).mean(axis=-1), f"|{k} - ref|", "magma", 0,
                   0.25 * scale, fontsize=6) for k in keys]]
        if layers:
            grid.append([Panel(tonemap(v), f"full: {k}", fontsize=7) for k, v in layers.items()])
        h, w = ref.shape[:2]
        return montage(path, grid, (2.2 * cols, len(grid) * 2.2 * h / w + 0.5), dpi=100)


def _sequence(setup, preset: str, choices: dict, frames: int) -> dict:
    """Render ``frames`` frames through a Pipeline: colours, stage times, last frame's layers
    (``skipped``: the pipeline's refusal)."""
    from ..pipeline import LAYERS, Pipeline

    try:
        # every frame reads its own stage times (the default reads every 8th frame)
        pipe = Pipeline(setup, preset=preset, progress=False, timing_every=1, **choices)
    except GlossrtError as e:
        return {"skipped": str(e)}
    colours, ms = [], []
    frame = None
    for i in range(frames):
        frame = pipe.render(i)
        colours.append(frame.numpy("color"))
        ms.append(frame.meta["pipeline"]["stage_ms"])
    steady = ms[2:] or ms[1:] or ms
    stage_ms = {k: float(statistics.median(m[k] for m in steady)) for k in ms[0]}
    layers = {k: frame.numpy(k) for k in LAYERS if k in frame.names}
    return {"colours": colours, "stage_ms": stage_ms, "layers": layers,
            "direct": pipe.direct_mode}


def _score(colours, refs, first: int) -> dict:
    """RMSE, SSIM and FLIP averaged over frames ``first ..``; the temporal error from frame
    ``first - 1`` on, or from ``first`` where that frame has no reference (``refs[t]``
    None: not referenced)."""
    from .. import metrics

    scored = range(first, len(colours))
    t0 = first - 1 if refs[first - 1] is not None else first
    return {"rmse": float(np.mean([metrics.rmse(colours[t], refs[t]) for t in scored])),
            "ssim": float(np.mean([metrics.ssim(colours[t], refs[t]) for t in scored])),
            "flip": float(np.mean([metrics.flip(colours[t], refs[t]) for t in scored])),
            "temporal": flicker(colours[t0:], refs[t0:])}


def scene_case(scene: str) -> tuple[str, int | None]:
    """``(built-in name, max_depth)`` of an experiment scene: ``NAME`` as it is (None: the
    renderer's default depth), ``NAME@direct`` (:data:`DIRECT_ONLY`) direct light only."""
    if scene.endswith(DIRECT_ONLY):
        return scene[: -len(DIRECT_ONLY)], 2
    return scene, None


def check_args(size, spp: int, frames: int, scenes=SCENES, presets=PRESETS,
               ref_frames: int | None = None) -> None:
    """Refuse bad arguments before any work."""
    from ..pipeline import PRESETS as KNOWN
    from ..scenes import BUILTIN, library  # noqa: F401  (library registers the built-ins)

    if frames < 2:
        raise GlossrtError(f"pipeline experiment: --frames must be >= 2 (temporal error), "
                           f"got {frames}")
    if spp < 1:
        raise GlossrtError(f"pipeline experiment: --spp must be >= 1, got {spp}")
    if len(size) != 2 or min(size) < 8:
        raise GlossrtError(f"pipeline experiment: size must be at least 8x8, got {size}")
    bad = [p for p in presets if p not in KNOWN or p == "reference"]
    if bad:
        raise GlossrtError(f"pipeline experiment: unknown preset(s) {bad}; choose from "
                           f"{', '.join(p for p in KNOWN if p != 'reference')}")
    bad = [s for s in scenes if scene_case(s)[0] not in BUILTIN]
    if bad:
        raise GlossrtError(f"pipeline experiment: unknown scene(s) {bad}")
    if ref_frames is not None and not 2 <= ref_frames < frames:
        raise GlossrtError(f"pipeline experiment: the referenced frames must be at least 2 "
                           f"and fewer than --frames ({frames}), got {ref_frames}")


def evaluate(size=(96, 72), spp: int = 256, frames: int = 6, scenes=SCENES, presets=PRESETS,
             variants: bool | dict = True, static: bool = True, choices: dict | None = None,
             progress: Callable[[str], None] | None = None, cluster=None,
             ref_frames: int | None = None, cache=None) -> PipelineResults:
    """Every preset on every scene against the converged reference (module docstring).
    ``scenes``: built-in names, ``NAME@direct`` for direct light only (:func:`scene_case`).
    ``choices``: pipeline options applied to every run (e.g. a coarse ``bspvt_resolution``
    in tests); ``variants``: True: also the :data:`VARIANTS` rows on
    :data:`INTERACTION_SCENE`; a dict of the same form: those rows on every scene;
    ``static``: also the runs without motion. ``ref_frames``: reference and score only the
    last ``ref_frames`` frames of each motion sequence (None: every frame referenced, the
    second half scored). ``cluster``, ``cache``: where the references are rendered and kept
    (:func:`glossrt.render.blocks.references`; None: in this process, not kept)."""

    scenes, presets = tuple(scenes), tuple(presets)
    check_args(size, spp, frames, scenes, presets, ref_frames)
    say = progress or (lambda _m: None)
    choices = dict(choices or {})
    t0 = time.perf_counter()
    table = variants if isinstance(variants, dict) else VARIANTS
    res = PipelineResults(tuple(size), spp, frames, scenes, presets, ref_frames=ref_frames,
                          variants=dict(table) if variants else {})
    for scene in scenes:
        depth = scene_case(scene)[1]
        depth_choice = {} if depth is None else {"max_depth": depth}
        runs = [(p, p, {}) for p in presets]
        if variants and (isinstance(variants, dict) or scene == INTERACTION_SCENE):
            runs += [(label, p, c) for label, (p, c) in table.items()]
        for motion in ((True, False) if static else (True,)):
            say(f"{scene} ({'with' if motion else 'without'} motion): references, {spp} spp")
            wanted = res.referenced() if motion else [0]
            setup, rend, got = _references(scene, size, frames, wanted, spp, cluster, cache,
                                           static=not motion)
            if motion:
                refs = [None] * frames
                for i, f in zip(wanted, got, strict=True):
                    refs[i] = f.numpy("color")
            else:
                refs = [got[0].numpy("color")] * frames
            raw = [rend.render(i).numpy("color") for i in range(frames)]
            base = {"scene": scene, "motion": motion}
            res.rows.append({**base, "label": FLOOR, **_score(raw, refs, res.first)})
            res.rows.append({**base, "label": REFERENCE, **_score(refs, refs, res.first)})
            if motion:
                res.images[scene] = {FLOOR: raw[-1]}
            for label, preset, extra in runs:
                say(f"{scene} ({'with' if motion else 'without'} motion): {label}")
                seq = _sequence(setup, preset, {**choices, **depth_choice, **extra}, frames)
                if "skipped" in seq:
                    res.rows.append({**base, "label": label, "skipped": seq["skipped"]})
                    continue
                res.rows.append({**base, "label": label, "direct": seq["direct"],
                                 "stage_ms": seq["stage_ms"],
                                 **_score(seq["colours"], refs, res.first)})
                if motion and label in presets:
                    res.images[scene][label] = seq["colours"][-1]
                    if label == "full":
                        res.layers[scene] = seq["layers"]
            if motion:
                res.images[scene][REFERENCE] = refs[-1]
    res.seconds = time.perf_counter() - t0
    return res


# -- TAA against pixel-centre and box-filtered references (issue 28) -------------------------

#: ``glossrt experiment --which taa``: the scenes where TAA in the measured pipeline cost
#: accuracy at 1280x720 (docs/RESULTS.md), and the two pipelines compared
TAA_SCENES = ("glossy-cornell", "polygon-light" + DIRECT_ONLY)
TAA_RUNS: dict[str, tuple[str, dict]] = {
    "schied2017 (SVGF + TAA)": ("schied2017", {}),
    "schied2017, TAA with jitter": ("schied2017", {"taa_jitter": True}),
    "schied2017, taa off": ("schied2017", {"taa": False}),
}
#: the two references: glossrt's (every sample through the pixel centre) and Mitsuba's own
#: ``path`` integrator through the scene's film, whose box pixel filter averages the whole
#: pixel (the antialiased image TAA converges to)
TAA_REFERENCES = ("pixel centre", "box filter")
#: ``--scale paper``: the paper-scale pipeline run's size and frames; 1024 spp (glossrt's
#: choice: at 4096 spp the pipeline table's RMSE moved by at most 4.1%)
TAA_PAPER_SPP = 1024


@dataclass
class TaaResults:
    size: tuple[int, int]
    spp: int
    frames: int
    ref_frames: int
    #: (scene, label, reference) -> RMSE / SSIM / FLIP / temporal; the labels include the 1
    #: spp input (:data:`FLOOR`) and each reference (``"pixel centre reference"``, scored
    #: against the box filter, and the other way round)
    scores: dict[tuple[str, str, str], dict] = field(default_factory=dict)
    #: scene -> label -> the last frame (colour; both references included)
    images: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)
    seconds: float = 0.0

    def montage(self, path: str | Path, scene: str) -> Path:
        """One scene's last frame: every pipeline and both references, and under each its
        distance to the box-filtered reference ``|x - box|``."""
        from ..report.figures import Panel, montage
        from ..report.page import tonemap

        imgs = self.images[scene]
        ref = imgs[f"{TAA_REFERENCES[1]} reference"]
        scale = max(float(np.percentile(np.abs(ref), 99.5)), 1e-6)
        grid: list[list[Panel | None]] = [
            [Panel(tonemap(v), k, fontsize=7) for k, v in imgs.items()],
            [Panel(np.abs(v - ref).mean(axis=-1), f"|{k} - box|", "magma", 0, 0.25 * scale,
                   fontsize=6) for k, v in imgs.items()]]
        h, w = ref.shape[:2]
        return montage(path, grid, (2.6 * len(imgs), 2 * 2.6 * h / w + 0.5), dpi=100)

    def markdown(self) -> str:
        cols = ["scene", "pipeline"] + [f"{m} ({r})" for m in ("RMSE", "SSIM", "temporal")
                                         for r in ("centre", "box")]
        lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
        keys = list(dict.fromkeys((sc, lb) for sc, lb, _ in self.scores))
        for scene, label in keys:
            cells = [scene, label]
            for m, fmt in (("rmse", ".4f"), ("ssim", ".3f"), ("temporal", ".4f")):
                for ref in TAA_REFERENCES:
                    v = self.scores.get((scene, label, ref))
                    cells.append("-" if v is None else format(v[m], fmt))
            lines.append("| " + " | ".join(cells) + " |")
        return "\n".join(lines)

    def as_dict(self) -> dict:
        return {"size": list(self.size), "spp": self.spp, "frames": self.frames,
                "ref_frames": self.ref_frames, "seconds": self.seconds,
                "scores": [{"scene": sc, "label": lb, "reference": rf, **v}
                           for (sc, lb, rf), v in self.scores.items()]}


def box_references(renderer, scene: str, frames, spp: int, cache=None) -> list[np.ndarray]:
    """Mitsuba's ``path`` integrator at ``frames`` (:meth:`glossrt.render.Renderer.
    render_mitsuba`: the scene's box pixel filter, ``renderer``'s ``max_depth``), colour
    (H, W, 3); with ``cache``, each frame is kept there as an EXR and read back by a later
    call for the same scene, size, sample count and frame."""
    from ..frame import Frame
    from ..render.blocks import cached_frames

    paths = None if cache is None else {
        int(i): Path(cache) / (f"mitsuba-path-{_file_name(scene)}-{renderer.width}x"
                               f"{renderer.height}-{spp}spp-{int(i):04d}.exr") for i in frames}

    def make(todo):
        for i in todo:
            yield Frame(channels={"color": np.array(renderer.render_mitsuba(i, spp))}, index=i,
                        meta={"scene": scene, "spp": spp, "reference": "mitsuba-path"})

    return [f.numpy("color") for f in cached_frames(frames, paths, make)]


def taa_check(size=(96, 72), spp: int = 256, frames: int = 6, ref_frames: int = 3,
              scenes=TAA_SCENES, cluster=None, cache=None,
              progress: Callable[[str], None] | None = None) -> TaaResults:
    """Is TAA's cost in the measured pipeline an artefact of pixel-centre references?
    Each pipeline of :data:`TAA_RUNS` (and the 1 spp input) over ``frames`` frames of each
    scene's animation, scored (:func:`_score`) over the last ``ref_frames`` frames against
    both references of :data:`TAA_REFERENCES` at ``spp`` samples: glossrt's
    (:func:`glossrt.render.blocks.references`, on ``cluster``) and Mitsuba's box-filtered
    (:func:`box_references`), both kept in ``cache``. Each reference is also scored
    against the other (how much of the image the pixel filter changes)."""
    scenes = tuple(scenes)
    check_args(size, spp, frames, scenes, ("schied2017",), ref_frames)
    say = progress or (lambda _m: None)
    t0 = time.perf_counter()
    res = TaaResults(tuple(size), spp, frames, ref_frames)
    first = frames - ref_frames
    wanted = list(range(first, frames))
    for scene in scenes:
        depth = scene_case(scene)[1]
        choices = {} if depth is None else {"max_depth": depth}
        say(f"{scene}: pixel-centre references, {spp} spp")
        setup, rend, got = _references(scene, size, frames, wanted, spp, cluster, cache)
        say(f"{scene}: box-filtered references (Mitsuba path), {spp} spp")
        refs = {TAA_REFERENCES[0]: [f.numpy("color") for f in got],
                TAA_REFERENCES[1]: box_references(rend, scene, wanted, spp, cache)}
        refs = {k: [None] * first + v for k, v in refs.items()}
        runs = {FLOOR: [rend.render(i).numpy("color") for i in range(frames)]}
        for label, (preset, extra) in TAA_RUNS.items():
            say(f"{scene}: {label}")
            seq = _sequence(setup, preset, {**choices, **extra}, frames)
            if "skipped" in seq:
                raise GlossrtError(f"taa check: {label} refused on {scene}: {seq['skipped']}")
            runs[label] = seq["colours"]
        for ref in TAA_REFERENCES:  # each reference against the other
            runs[f"{ref} reference"] = refs[ref]
        res.images[scene] = {label: colours[-1] for label, colours in runs.items()}
        for label, colours in runs.items():
            for ref in TAA_REFERENCES:
                if label == f"{ref} reference":
                    continue
                res.scores[(scene, label, ref)] = _score(colours, refs[ref], first)
    res.seconds = time.perf_counter() - t0
    return res


def _references(scene: str, size, frames: int, wanted, spp: int, cluster, cache,
                static: bool = False):
    """``(setup, renderer, reference frames)`` of an experiment scene (:func:`scene_case`):
    its animation of ``frames`` frames (``static``: the still copy), the references of
    ``wanted`` at ``spp`` samples (:func:`glossrt.render.blocks.references`, on ``cluster``,
    kept in ``cache``)."""
    from .. import render
    from .. import scenes as scn
    from ..render import blocks

    name, depth = scene_case(scene)
    setup = (scn.load_static(name, size=size) if static
             else scn.load(name, size=size, frames=frames))
    rend = render.Renderer(setup, max_depth=depth)
    job = (blocks.reference_job(name, size, static=True, max_depth=depth) if static
           else blocks.reference_job(name, size, frames=frames, max_depth=depth))
    got = blocks.references(rend, job, wanted, spp, cluster, cache=cache,
                            desc=f"references {scene} {spp} spp")
    return setup, rend, got


def _notes(res: PipelineResults) -> str:
    lines = [f"Scored frames {res.first}..{res.frames - 1} of {res.frames}; `x floor`: RMSE "
             f"with motion over the raw 1 spp input's; temporal: flicker against the "
             f"reference's own change (without motion: the sequence's temporal error)."]
    if res.skips():
        lines.append("Skipped (the pipeline refuses): " + "; ".join(res.skips()) + ".")
    if res.interactions():
        lines.append("Composition (one choice of a preset changed; a positive change is worse): "
                     + " | ".join(res.interactions()) + ".")
    return "\n\n".join(lines)


# -- timing (benchmark case) -----------------------------------------------------------------


def _evaluated(out: dict) -> None:
    import drjit as dr

    vals = []
    for v in out.values():
        vals += [v[k] for k in v.names] if hasattr(v, "names") else [v]
    dr.eval(vals)


def timing(preset: str, scene: str, size=(320, 180), warmup: int = 3, repeats: int = 9,
           min_sample: float = 0.0, choices: dict | None = None) -> dict:
    """Steady state of ``preset`` on the static copy of ``scene`` (frames differ only in
    noise, so the temporal histories stay full): the composed frame (``Pipeline.render``,
    its stages not synchronised, with per-stage timing: ``fps``; the same frame without
    per-stage timing: ``fps_untimed``, and ``timing_cost_ms`` the median per-repeat
    difference) and each stage run alone on the inputs a composed frame gave it
    (``stage.run`` with the stage's declared inputs, evaluated and synchronised), called
    in turn (:func:`glossrt.timing.round_robin`); the ratio of the timed frame to the sum of
    the stages alone is the median of per-repeat ratios. ``stage_ms_in_frame``: the median over
    the timed frames of each stage's kernel milliseconds inside the composed frame (Dr.Jit's
    kernel history, :class:`glossrt.timing.StageClock`), ``stage_host_ms_in_frame`` the
    Python time of each stage's call there."""
    import drjit as dr

    from .. import scenes as scn
    from ..pipeline import Pipeline
    from ..timing import round_robin

    pipe = Pipeline(scn.load_static(scene, size=size), preset=preset, progress=False,
                    **(choices or {}))
    metas = [pipe.render(i).meta["pipeline"] for i in range(8)]  # records, fills histories
    ctxs = []
    for i in range(8, 12):  # four frames of inputs for the stages alone
        ctx: dict = {}
        for stage in pipe.stages.values():
            out = stage.run(i, dict(ctx))  # (a stage may take an input out of its context)
            _evaluated(out)
            ctx.update(out)
        ctxs.append((i, ctx))
    dr.sync_thread()
    recordings = pipe.recordings()
    counter = {"frame": 12}

    def frame():
        counter["frame"] += 1
        pipe.timing = "kernels"
        meta = pipe.render(counter["frame"]).meta["pipeline"]
        # stage times only from frames that read the kernel history themselves (the
        # others repeat the last reading: Pipeline timing_every)
        if meta.get("stage_ms_frame", counter["frame"]) == counter["frame"]:
            metas.append(meta)

    def untimed():  # the same frame without per-stage timing: what the timing costs
        counter["frame"] += 1
        pipe.timing = "none"
        pipe.render(counter["frame"])

    cases: dict[str, Callable[[], object]] = {"frame": frame, "frame_untimed": untimed}
    for name, stage in pipe.stages.items():
        turn = {"k": 0}

        def alone(stage=stage, turn=turn):
            turn["k"] += 1
            i, ctx = ctxs[turn["k"] % len(ctxs)]
            _evaluated(stage.run(i, {k: ctx[k] for k in stage.inputs}))

        cases[name] = alone
    first = len(metas)
    times = round_robin(cases, warmup, repeats, min_sample)
    stages = [n for n in cases if not n.startswith("frame")]
    sums = [sum(times[n][r] for n in stages) for r in range(repeats)]
    frame_s = statistics.median(times["frame"])
    steady = [m for m in metas[first:] if m.get("stage_ms")] or metas[8:]

    def med(key: str) -> dict:
        return {n: float(statistics.median(m[key][n] for m in steady))
                for n in steady[0].get(key) or {}}

    return {
        "preset": preset, "scene": f"{scene} (static copy)", "size": list(size),
        "direct": pipe.direct_mode,
        "frame_ms": 1000 * frame_s, "fps": 1.0 / frame_s,
        "fps_untimed": 1.0 / statistics.median(times["frame_untimed"]),
        "timing_cost_ms": 1000 * statistics.median(
            a - b for a, b in zip(times["frame"], times["frame_untimed"], strict=True)),
        "stage_ms_alone": {n: 1000 * statistics.median(times[n]) for n in stages},
        "sum_alone_ms": 1000 * statistics.median(sums),
        "stage_ms_in_frame": med("stage_ms"),
        "stage_host_ms_in_frame": med("stage_host_ms"),
        "kernel_ms_in_frame": float(statistics.median(m.get("kernel_ms", 0.0)
                                                      for m in steady)),
        "stage_timing": "kernels (Dr.Jit kernel history, stages not synchronised)",
        "ratio_frame_vs_sum": statistics.median(a / b for a, b in zip(times["frame"], sums,
                                                                       strict=True)),
        "target_ratio": TARGET_RATIO,
        "recordings_added": pipe.recordings() - recordings,
        "repeats": repeats,
    }


def memory(preset: str, scene: str, size, warmup: int = 3, frames: int = 3,
           choices: dict | None = None) -> dict:
    """Peak memory of ``frames`` steady-state frames of ``preset`` on the static copy of
    ``scene`` after ``warmup`` frames (which record the kernels and fill the histories).
    ``choices``: pipeline options, and ``outputs`` (:attr:`glossrt.pipeline.Pipeline.
    outputs`).
    Run it in a fresh process (:func:`memory_in_subprocess`): earlier work's caches would
    count. Two measures:

    * ``jit_peak_mb``: Dr.Jit's allocator watermark (``dr.detail.malloc_watermark``) over
      the steady frames, its cache of freed blocks emptied and its statistics cleared
      first: the most memory Dr.Jit held at once (on a GPU: device memory), i.e. every live
      array (the scene's geometry and textures, BSPVT trees, the temporal histories, the
      frame's channels) plus the frame's transient buffers; not what lives outside Dr.Jit's
      allocator (the ray-tracing BVH, compiled kernels, Python). Allocations are rounded
      up by the allocator (measured: a 100 MB array takes 128 MB). ``jit_peak_mb_per_stage``:
      the same watermark within each stage (everything live when it starts, plus its own
      buffers; the allocator's cache emptied at its start), over two more frames.
    * ``rss_peak_mb`` (Linux): the process's peak resident set over the steady frames
      (``VmHWM`` after resetting it through ``/proc/self/clear_refs``): everything, Python,
      the libraries and LLVM included, on the CPU backend the Dr.Jit arrays too;
      ``rss_before_mb`` the resident set when the steady frames start.
    """
    import drjit as dr

    from .. import scenes as scn
    from ..backend import is_gpu
    from ..pipeline import Pipeline

    choices = dict(choices or {})
    outputs = choices.pop("outputs", None)
    pipe = Pipeline(scn.load_static(scene, size=size), preset=preset, progress=False,
                    outputs=outputs, **choices)
    for i in range(warmup):
        pipe.render(i)
    dr.sync_thread()
    backend = dr.JitBackend.CUDA if is_gpu() else dr.JitBackend.LLVM
    dr.flush_malloc_cache()
    dr.detail.malloc_clear_statistics()
    rss_before = _reset_peak_rss()
    t0 = time.perf_counter()
    for i in range(warmup, warmup + frames):
        pipe.render(i)
    dr.sync_thread()
    seconds = (time.perf_counter() - t0) / max(frames, 1)
    peak = _peak_rss()
    jit_peak = dr.detail.malloc_watermark(backend) / 2**20
    # where it peaks: the watermark within each stage (its outputs evaluated inside; the
    # device synchronised and the allocator's cache emptied first), over two more frames
    stage_peak = dict.fromkeys(pipe.stages, 0.0)
    for name, stage in pipe.stages.items():
        def run(index, ctx, run=stage.run, name=name):
            dr.sync_thread()
            dr.flush_malloc_cache()  # (freed blocks kept for reuse count as held)
            dr.detail.malloc_clear_statistics()
            out = run(index, ctx)
            _evaluated(out)
            stage_peak[name] = max(stage_peak[name],
                                   dr.detail.malloc_watermark(backend) / 2**20)
            return out

        stage.run = run
    for i in range(warmup + frames, warmup + frames + 2):
        pipe.render(i)
    return {
        "preset": preset, "scene": f"{scene} (static copy)", "size": list(size),
        "direct": pipe.direct_mode, "frames": frames, "frame_s": seconds,
        "jit_peak_mb": jit_peak, "jit_peak_mb_per_stage": stage_peak,
        "rss_peak_mb": peak, "rss_before_mb": rss_before,
        "target_mb": MEMORY_TARGET_MB if tuple(size) == (1920, 1080) else None,
    }


def _status_mb(field: str) -> float | None:
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith(field + ":"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        return None
    return None


def _reset_peak_rss() -> float | None:
    """Reset the process's peak resident set to its current size (Linux ``clear_refs``);
    returns the current size in MB (None where unsupported)."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
    except OSError:
        return None
    return _status_mb("VmRSS")


def _peak_rss() -> float | None:
    return _status_mb("VmHWM")


def memory_in_subprocess(preset: str, scene: str, size, warmup: int = 3, frames: int = 3,
                         choices: dict | None = None, timeout: float = 3600.0) -> dict:
    """:func:`memory` in a fresh Python process on the same device as this one."""
    import json
    import os
    import subprocess
    import sys

    from ..backend import is_gpu

    args = json.dumps({"preset": preset, "scene": scene, "size": list(size),
                       "warmup": warmup, "frames": frames, "choices": choices or {}})
    code = ("import json, sys; from glossrt.experiments.pipeline import memory; "
            "a = json.loads(sys.argv[1]); "
            "print('MEMORY ' + json.dumps(memory(a['preset'], a['scene'], tuple(a['size']), "
            "a['warmup'], a['frames'], a['choices'])))")
    env = dict(os.environ, GLOSSRT_DEVICE="gpu" if is_gpu() else "cpu")
    r = subprocess.run([sys.executable, "-c", code, args], env=env, capture_output=True,
                       text=True, timeout=timeout)
    for line in r.stdout.splitlines():
        if line.startswith("MEMORY "):
            return json.loads(line[len("MEMORY "):])
    tail = " | ".join(ln for ln in r.stderr.strip().splitlines()[-3:])
    raise GlossrtError(f"pipeline memory probe ({preset} on {scene}, {size[0]}x{size[1]}) "
                       f"failed with exit status {r.returncode}: {tail}")


def timing_markdown(t: dict) -> str:
    lines = ["| preset / scene | size | direct | frame ms | fps | fps, no per-stage timing | "
             "target fps (2-core CPU) | stages in the frame, kernel ms (not synchronised) | "
             "stages alone (ms) | sum alone | frame / sum (target <= 1.10) |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for c in t["cases"].values():
        alone = ", ".join(f"{k} {v:.2f}" for k, v in c["stage_ms_alone"].items())
        inside = ", ".join(f"{k} {v:.2f}" for k, v in c["stage_ms_in_frame"].items())
        w, h = c["size"]
        target = f"{c['target_fps']:.0f}" if c.get("target_fps") else "-"
        lines.append(f"| {c['preset']} / {c['scene']} | {w}x{h} | {c['direct']} | "
                     f"{c['frame_ms']:.2f} | {c['fps']:.1f} | {c['fps_untimed']:.1f} | "
                     f"{target} | {inside} | {alone} | "
                     f"{c['sum_alone_ms']:.2f} | {c['ratio_frame_vs_sum']:.3f} |")
    if t.get("memory"):
        lines += ["", "| preset / scene | size | options | Dr.Jit peak (MiB) | largest stage "
                  "(MiB) | process peak RSS (MB) | RSS before (MB) | frame (ms) | target (MB) |",
                  "|---|---|---|---|---|---|---|---|---|"]
        for m in t["memory"].values():
            w, h = m["size"]

            def mb(v):
                return "-" if v is None else f"{v:.0f}"

            stages = m.get("jit_peak_mb_per_stage") or {}
            top = max(stages, key=stages.get) if stages else None
            largest = f"{top} {stages[top]:.0f}" if top else "-"
            opts = ", ".join(f"{k}={v}" for k, v in (m.get("options") or {}).items()) or "-"
            lines.append(f"| {m['preset']} / {m['scene']} | {w}x{h} | {opts} | "
                         f"{mb(m['jit_peak_mb'])} | {largest} | "
                         f"{mb(m['rss_peak_mb'])} | {mb(m['rss_before_mb'])} | "
                         f"{1000 * m['frame_s']:.0f} | {mb(m['target_mb'])} |")
    return "\n".join(lines)


def _option(extra: dict, name: str, default):
    return extra.get(name, default) if extra else default


def check_bench_options(extra: dict) -> None:
    """Refuse, before any work, a ``pipeline_*`` option of the benchmark case that is
    unknown or has a bad value (:data:`BENCH_OPTIONS`)."""
    for k in extra:
        if k.startswith("pipeline_") and k not in BENCH_OPTIONS:
            raise GlossrtError(f"unknown bench option {k!r}; the pipeline case takes "
                               f"{', '.join(sorted(BENCH_OPTIONS))}")
    shrink = _option(extra, "pipeline_shrink", 1)
    if isinstance(shrink, bool) or shrink not in SHRINKS:
        raise GlossrtError(f"pipeline_shrink must be one of {', '.join(map(str, SHRINKS))} "
                           f"(every size stays even for the 1/2-resolution indirect light), "
                           f"got {shrink!r}")
    if not isinstance(_option(extra, "pipeline_memory", True), bool):
        raise GlossrtError("pipeline_memory must be true or false")
    choices = _option(extra, "pipeline_choices", None)
    if choices is not None:
        if not isinstance(choices, dict):
            raise GlossrtError("pipeline_choices must be an object of pipeline options, e.g. "
                               "{\"bspvt_resolution\": 16}")
        from ..pipeline import config

        config.check_names(choices)


@benchmark("pipeline", order=80)
def bench_pipeline(ctx: BenchContext) -> dict:
    """Issue 25's speed figures in one run, on the static copies of the scenes (their own
    sizes, not ``--size``):

    * frame rate (:func:`timing`): ``full`` on polygon-light at 320x180 and 640x360,
      ``schied2017`` on glossy-cornell at 320x180 (:data:`BENCH_CASES`, with the issue's
      2-core CPU targets), per-stage kernel milliseconds inside the composed frame (stages
      not synchronised), each stage alone, and the composed frame against the sum of its
      stages run alone (target <= 1.1);
    * memory (:func:`memory`, each case in a fresh process): the peak of a steady-state
      ``full`` frame on polygon-light at 640x360 and 1920x1080, the latter also with
      ``release_memory``, and with it returning ``color`` alone (``outputs``;
      :data:`MEMORY_CASES`; target: at most 600 MB at 1920x1080).

    Options (``glossrt bench --only pipeline --case-option KEY=VALUE``, or
    ``ctx.extra``): ``pipeline_shrink`` divides every size by 2, 5 or 10 for a quick run
    (10: 32x18, 64x36, 192x108); ``pipeline_memory=false`` leaves the memory cases out;
    ``pipeline_choices`` options for every pipeline (e.g. ``{"bspvt_resolution": 16}``).
    The full figure: ``glossrt bench --only pipeline --json pipeline.json`` on a quiet
    machine (the 1920x1080 memory case takes a few minutes on 2 CPU cores)."""
    extra = ctx.extra or {}
    check_bench_options(extra)
    shrink = int(_option(extra, "pipeline_shrink", 1))
    choices = _option(extra, "pipeline_choices", None)

    def scaled(size):
        return (size[0] // shrink, size[1] // shrink)

    cases = {}
    for preset, scene, size, fps in BENCH_CASES:
        t = timing(preset, scene, size=scaled(size), warmup=ctx.warmup, repeats=ctx.turns,
                   min_sample=ctx.min_sample, choices=choices)
        w, h = scaled(size)
        cases[f"{preset}/{scene}@{w}x{h}"] = {**t, "target_fps": fps if shrink == 1 else None}
    mem = {}
    if _option(extra, "pipeline_memory", True):
        for preset, scene, size, opts in MEMORY_CASES:
            w, h = scaled(size)
            m = memory_in_subprocess(preset, scene, (w, h), choices={**(choices or {}), **opts})
            m["options"] = opts
            if shrink != 1:
                m["target_mb"] = None
            tag = "".join(f" {k}={v}" for k, v in opts.items())
            mem[f"{preset}/{scene}@{w}x{h}{tag}"] = m
    return {"shrink": shrink, "cases": cases, "memory": mem, "repeats": ctx.turns}


# -- report section and experiment -------------------------------------------------------------


@register_section("pipeline", order=85)
def section_pipeline(ctx: DemoContext, report: Report) -> None:
    t0 = time.perf_counter()
    scale, size = section_size(ctx, (128, 96), 4, (32, 24))
    spp, frames = (64, 4) if scale >= 1 else (8, 3)
    presets = ("schied2017", "tokuyoshi2015", "full")
    scene = "glossy-cornell"
    res = evaluate(size=size, spp=spp, frames=frames, scenes=(scene,), presets=presets,
                   variants=False, static=False, progress=ctx.say)
    s = report.section(
        "Frame pipeline",
        f"glossrt.pipeline composes the papers into one real-time frame (issue 25): "
        f"{', '.join(presets)} on {scene} ({size[0]}x{size[1]}, {frames} frames of its "
        f"animation) against the converged reference ({spp} spp), with the raw 1 spp input "
        "as the floor to beat; stage times are per frame on this machine. See "
        "docs/RESULTS.md (`glossrt experiment --which pipeline`).")
    markdown_table(s, res.markdown(), "error against the converged reference")
    s.paragraph(_notes(res))
    s.saved_figure("pipeline_montage", lambda p: res.montage(p, scene),
                   caption="composed frames, |x - reference|, and full's stage layers")
    ctx.timings["pipeline section"] = time.perf_counter() - t0


@register_experiment("pipeline", "issue 25's frame pipeline: every preset on five scenes "
                     "against the converged reference, with and without motion, per-stage "
                     "ms, composition interactions (--size, --spp, --frames >= 2); --scale "
                     "paper: SVGF's Table 1 / figs. 10-12 at 1280x720 with TAA in the "
                     "pipeline, a-trous and OIDN in it, direct-only and many-lights scenes",
                     order=70)
def run_experiment(out, size, args) -> int:
    """Every preset against the converged reference (module docstring); writes pipeline.md,
    pipeline.json and one montage per scene (pipeline_SCENE.png). ``--scale paper``:
    :data:`PAPER_SCENES` at :data:`PAPER_SIZE` (or ``--size``), :data:`PAPER_FRAMES` frames
    (or ``--frames``), the last :data:`PAPER_REF_FRAMES` referenced at
    :data:`PAPER_REF_SPP` (or ``--spp``), :data:`PAPER_VARIANTS` on every scene, no static
    runs; the references are kept in ``OUT/references`` (a rerun reuses them)."""
    paper = experiment_scale(args) == "paper"
    size = tuple(paper_value(args, "size", size, PAPER_SIZE))
    spp = int(paper_value(args, "spp", args.spp, PAPER_REF_SPP))
    frames = int(paper_value(args, "frames", args.frames, PAPER_FRAMES))
    kw = (dict(scenes=PAPER_SCENES, variants=PAPER_VARIANTS, static=False,
               ref_frames=PAPER_REF_FRAMES, cache=out / "references") if paper else {})
    res = evaluate(  # (evaluate checks the arguments before any work)
        size=size, spp=spp, frames=frames, progress=lambda m: print(m, flush=True),
        cluster=experiment_cluster(args), **kw)
    for scene in res.scenes:
        res.montage(out / f"pipeline_{_file_name(scene)}.png", scene)
    w, h = size
    scored = (f"the last {res.ref_frames} of {frames} frames referenced" if paper
              else f"{frames} frames")
    md = (f"## every preset against the converged reference ({w}x{h}, reference {spp} "
          f"spp, {scored})\n\n{res.markdown()}\n\n{_notes(res)}")
    return finish_experiment(out, "pipeline", md,
                             f"pipeline_{_file_name(res.scenes[0])}.png", res.as_dict())


def _file_name(scene: str) -> str:
    return scene.replace(DIRECT_ONLY, "-direct-only")


@register_experiment("taa", "is TAA's cost in the measured pipeline an artefact of the "
                     "references? schied2017 with TAA, with TAA and its jitter, without "
                     "TAA (and the 1 spp input) against pixel-centre references and "
                     "Mitsuba's box-filtered path "
                     "integrator (--size, --spp, --frames); --scale paper: 1280x720, 12 "
                     "frames, the last 3 referenced at 1024 spp", order=71)
def run_taa(out, size, args) -> int:
    """:func:`taa_check` on :data:`TAA_SCENES`; ``--scale paper``: :data:`PAPER_SIZE`,
    :data:`PAPER_FRAMES`, :data:`PAPER_REF_FRAMES` and :data:`TAA_PAPER_SPP` where the
    option was not given. The references are kept in ``OUT/references``. Writes taa.md /
    taa.json."""
    paper = experiment_scale(args) == "paper"
    size = tuple(paper_value(args, "size", size, PAPER_SIZE))
    spp = int(paper_value(args, "spp", args.spp, TAA_PAPER_SPP))
    frames = int(paper_value(args, "frames", args.frames, PAPER_FRAMES))
    ref_frames = PAPER_REF_FRAMES if paper else max(2, min(PAPER_REF_FRAMES, frames // 2))
    res = taa_check(size=size, spp=spp, frames=frames, ref_frames=ref_frames,
                    cluster=experiment_cluster(args), cache=out / "references",
                    progress=lambda m: print(m, flush=True))
    for scene in res.images:
        res.montage(out / f"taa_{_file_name(scene)}.png", scene)
    w, h = size
    md = (f"## TAA against pixel-centre and box-filtered references ({w}x{h}, {frames} "
          f"frames, the last {ref_frames} referenced at {spp} spp, {res.seconds:.0f} s)\n\n"
          f"{res.markdown()}")
    shown = next(iter(res.images), TAA_SCENES[0])
    return finish_experiment(out, "taa", md, f"taa_{_file_name(shown)}.png", res.as_dict())
