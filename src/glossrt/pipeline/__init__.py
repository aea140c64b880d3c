"""One real-time frame pipeline that composes the five papers (issue 25, first slice).

>>> from glossrt.pipeline import Pipeline                        # doctest: +SKIP
>>> pipe = Pipeline("polygon-light", preset="full", size=(320, 180))  # doctest: +SKIP
>>> frame = pipe.render(0)          # Frame: color + every stage's layer  # doctest: +SKIP
>>> pipe.configure(direct="ltc+ratio")   # re-records the changed stage once  # doctest: +SKIP
>>> rgb8 = pipe.display(frame)      # (H, W, 3) uint8 for viewers     # doctest: +SKIP

Stages (:mod:`glossrt.pipeline.stages`, each with declared input and output channels):
``gbuffer`` -> ``direct`` -> ``indirect`` -> ``composite`` -> ``taa`` (-> ``display``).
No double counting, nothing lost: the lights an analytic ``direct`` stage shades (the
polygon lights, and the point and directional lights) are removed from the path tracer at
the primary hit only (:class:`glossrt.render.Renderer`'s ``primary_exclude``); they still
light every deeper bounce. Presets and options: :mod:`glossrt.pipeline.config`.

Every refusal (unknown option, BSPVT with a moving occluder, highlights or LTC modes in a
scene without polygon lights, anisotropic materials under analytic shading, OIDN missing)
is one :class:`~glossrt.errors.GlossrtError` raised by the constructor or
:meth:`Pipeline.configure` before any rendering.
"""

from __future__ import annotations

import time
from typing import Any

import drjit as dr

from ..errors import GlossrtError
from ..frame import Frame
from . import config
from .config import OPTIONS, PRESETS, load_toml, parse, resolve
from .stages import (
    CompositeStage,
    DirectStage,
    GBufferStage,
    IndirectStage,
    Stage,
    TAAStage,
    display,
)

STAGES = ("gbuffer", "direct", "indirect", "composite", "taa", "display")
#: the channels a pipeline frame adds to the G-buffer's (docs/FORMATS.md)
LAYERS = ("direct", "indirect", "composite", "color")
POLYGON_MODES = ("ltc", "ltc+bspvt", "ltc+ratio", "highlights")


def _setup_of(scene_or_setup, size):
    from ..scenes import SceneSetup, load

    if isinstance(scene_or_setup, SceneSetup):
        if size is not None and tuple(size) != tuple(scene_or_setup.size):
            raise GlossrtError("Pipeline: size is given, but the SceneSetup has its own "
                               f"({scene_or_setup.size[0]}x{scene_or_setup.size[1]})")
        return scene_or_setup
    return load(scene_or_setup, size=size)


def moving_occluders(setup) -> list[str]:
    """Ids of the shapes that move in ``setup``'s animation and are not lights."""
    moving = []
    for sid in setup.object_paths:
        shape = next((s for s in setup.shapes if s.id() == sid), None)
        if shape is not None and not shape.is_emitter():
            moving.append(sid)
    return moving


class Pipeline:
    """A real-time frame pipeline for one scene (module docstring).

    ``setup_or_scene``: a :class:`glossrt.scenes.SceneSetup`, or anything
    :func:`glossrt.scenes.load` takes (built-in name, XML path, scene dict, ``mi.Scene``);
    ``preset``: a name of :data:`PRESETS` or a ``.toml`` file; ``choices``: options of
    :data:`OPTIONS` overriding the preset. ``progress``: progress bars (BSPVT's trees)."""

    def __init__(self, setup_or_scene, preset: str = "schied2017", size=None,
                 progress: bool = True, **choices: Any):
        if preset not in PRESETS:
            preset, file_choices = parse(preset)
            choices = {**file_choices, **choices}
        self.opts = resolve(preset, **choices)  # names and values, before the scene loads
        self.setup = _setup_of(setup_or_scene, size)
        self.progress = progress
        self.stages: dict[str, Stage] = {}
        self._gbuffer: GBufferStage | None = None
        self.frames = 0
        self._apply(self.opts)

    # -- configuration ---------------------------------------------------------------------
    @property
    def preset(self) -> str:
        return self.opts["preset"]

    @property
    def choices(self) -> dict[str, Any]:
        return {k: v for k, v in self.opts.items() if k != "preset"}

    def _resolve_direct(self, opts: dict) -> str:
        mode = opts["direct"]
        if mode != "auto":
            return mode
        return "ltc+ratio" if moving_occluders(self.setup) else "ltc+bspvt"

    def _check(self, opts: dict, direct: str) -> tuple[list, list]:
        """Every refusal of ``opts`` for this scene, before any work. Returns the polygon and
        point/directional lights at frame 0."""
        from ..lights.analytic import analytic_lights
        from ..lights.scene import polygon_lights

        name = self.setup.name
        polys = polygon_lights(self.setup, 0) if direct != "pathtraced" else []
        points = analytic_lights(self.setup, 0) if direct != "pathtraced" else []
        if direct in POLYGON_MODES and not polys and (direct != "ltc" or not points):
            raise GlossrtError(f"direct={direct}: scene {name!r} has no polygon (area) "
                               "lights; use direct=pathtraced")
        if direct == "ltc+bspvt":
            moving = moving_occluders(self.setup)
            if moving:
                raise GlossrtError(f"direct=ltc+bspvt: object {moving[0]!r} of scene "
                                   f"{name!r} moves, which invalidates BSPVT's precomputed "
                                   "visibility; use direct=ltc+ratio")
            from ..lights.bspvt.scene import scene_meshes

            if not scene_meshes(self.setup.scene):
                raise GlossrtError(f"direct=ltc+bspvt: scene {name!r} has no triangle "
                                   "meshes to precompute visibility at; use direct=ltc+ratio")
        if direct != "pathtraced":
            from ..render.pathtracer import ShapeTable

            if ShapeTable(self.setup.scene).any_anisotropic:
                raise GlossrtError(f"direct={direct}: scene {name!r} has anisotropic "
                                   "materials, which the analytic shading does not handle; "
                                   "use direct=pathtraced")
        if opts["indirect"] == "oidn":
            from ..denoise.oidn import oidn_available

            if not oidn_available():
                raise GlossrtError("indirect=oidn: Intel Open Image Denoise (pyoidn) is not "
                                   "installed; choose svgf, svgf-lobe, atrous or none")
        return polys, points

    def _exclude(self, direct: str, polys: list, points: list) -> tuple[int, ...]:
        """Emitter indices of the lights the analytic direct stage shades."""
        if direct == "pathtraced":
            return ()
        from ..render import emitter_index

        shapes = {p.mesh_id for p in polys}
        out = []
        for index, _eid, kind, shape in emitter_index(self.setup):
            if (kind == "area" and shape in shapes) or kind in ("point", "directional"):
                out.append(index)
        return tuple(out)

    def _apply(self, opts: dict) -> None:
        old = getattr(self, "_applied", None)
        direct = self._resolve_direct(opts)
        polys, points = self._check(opts, direct)
        exclude = self._exclude(direct, polys, points)

        def same(*keys: str) -> bool:
            return old is not None and all(old[k] == opts[k] for k in keys)

        if not same("max_depth", "seed", "accumulate", "spp") or self._gbuffer is None:
            self._gbuffer = GBufferStage(self.setup, opts, exclude)
        elif self._gbuffer.exclude != exclude:
            # the frozen trace records once more (render.Renderer.primary_exclude)
            self._gbuffer.renderer.primary_exclude = exclude
            self._gbuffer.exclude = exclude
            self._gbuffer.reset()
        stages: dict[str, Stage] = {"gbuffer": self._gbuffer}
        prev = self.stages
        if (old is not None and old.get("_direct") == direct
                and same("bspvt_mode", "bspvt_resolution", "ratio_spp", "highlight_samples")):
            stages["direct"] = prev["direct"]
        else:
            stages["direct"] = DirectStage(self.setup, opts, direct, self.progress)
        if old is not None and same("indirect") and old.get("_direct") == direct:
            stages["indirect"] = prev["indirect"]
        else:
            stages["indirect"] = IndirectStage(opts["indirect"])
        stages["composite"] = prev.get("composite") or CompositeStage()
        if old is not None and same("taa", "taa_alpha"):
            stages["taa"] = prev["taa"]
        else:
            stages["taa"] = TAAStage(opts["taa"], opts["taa_alpha"])
        self.stages = stages
        self.opts = dict(opts)
        self._applied = dict(opts, _direct=direct)
        self.direct_mode = direct
        self.point_lights = ("analytic, one shadow ray each" if direct != "pathtraced"
                             else "path-traced")

    def configure(self, **choices: Any) -> None:
        """Change options between frames (checked first; nothing changes on a refusal). Only
        the stages whose options changed are rebuilt: their frozen kernels record once on
        the next frame; the others keep replaying theirs."""
        config.check_names(choices)
        opts = resolve(self.opts["preset"], **{**self.choices, **choices})
        self._apply(opts)

    def reset(self) -> None:
        """Drop every history (denoiser, TAA, accumulation): the next frame starts anew."""
        for stage in self.stages.values():
            stage.reset()

    # -- frames --------------------------------------------------------------------------
    def recordings(self) -> int:
        """Recordings made so far by the current stages' frozen functions."""
        return sum(int(f.n_recordings) for s in self.stages.values() for f in s.frozen())

    def render(self, index: int) -> Frame:
        """Frame ``index`` of the scene's animation: the G-buffer's channels (1 spp, with the
        analytic lights removed at the primary hit), each stage's layer (:data:`LAYERS`) and
        the composed ``color``; ``meta["pipeline"]`` holds the choices and per-stage
        milliseconds (each stage synchronised for its timing)."""
        ctx: dict[str, Any] = {}
        ms: dict[str, float] = {}
        t_all = time.perf_counter()
        for name, stage in self.stages.items():
            t0 = time.perf_counter()
            out = stage.run(index, ctx)
            if set(out) != set(stage.outputs):
                raise GlossrtError(f"pipeline stage {name} returned {sorted(out)}, declared "
                                   f"{list(stage.outputs)}")
            ctx.update(out)
            dr.eval([v for k, v in out.items() if k != "frame"])
            dr.sync_thread()
            ms[name] = 1000.0 * (time.perf_counter() - t0)
        gb: Frame = ctx["frame"]
        channels = {k: gb[k] for k in gb.names if k != "color"}
        for layer in LAYERS:
            channels[layer] = ctx[layer]
        meta = dict(gb.meta)
        meta["pipeline"] = {
            "preset": self.preset,
            "choices": self.choices,
            "direct": self.direct_mode,
            "point_lights": self.point_lights,
            "primary_exclude": list(self._gbuffer.exclude),
            "stages": {n: {"inputs": list(s.inputs), "outputs": list(s.outputs)}
                       for n, s in self.stages.items()},
            "layers": list(LAYERS),
            "stage_ms": ms,
            "frame_ms": 1000.0 * (time.perf_counter() - t_all),
        }
        note = config.PRESET_NOTES.get(self.preset)
        if note:
            meta["pipeline"]["note"] = note
        self.frames += 1
        return Frame(channels=channels, camera=gb.camera, prev_camera=gb.prev_camera,
                     index=index, meta=meta)

    def display(self, frame: Frame) -> Any:
        """The frame's ``color`` as 8-bit sRGB (H, W, 3) ``uint8`` (exposure and tonemap
        from the options)."""
        return display(frame.numpy("color"), self.opts["exposure"], self.opts["tonemap"])


__all__ = ["LAYERS", "OPTIONS", "PRESETS", "STAGES", "Pipeline", "display", "load_toml",
           "moving_occluders", "parse", "resolve"]
