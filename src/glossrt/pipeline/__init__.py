"""One real-time frame pipeline that composes the five papers (issue 25, first slice).

>>> from glossrt.pipeline import Pipeline                        # doctest: +SKIP
>>> pipe = Pipeline("polygon-light", preset="full", size=(320, 180))  # doctest: +SKIP
>>> frame = pipe.render(0)          # Frame: color + every stage's layer  # doctest: +SKIP
>>> pipe.configure(direct="ltc+ratio")   # re-records the changed stage once  # doctest: +SKIP
>>> rgb8 = pipe.display(frame)      # (H, W, 3) uint8 for viewers     # doctest: +SKIP
>>> pipe.set_camera(position=(0, 1, 4), target=(0, 0.5, 0))  # explicit pose  # doctest: +SKIP
>>> pipe.set_transform("light", matrix)  # a polygon light, object or point light  # doctest: +SKIP
>>> frame = pipe.render(1)   # posed explicitly, the rest from the animation  # doctest: +SKIP
>>> pipe.outputs = ("color", "direct")  # keep only these; the rest freed early  # doctest: +SKIP

Posing: a frame is posed by its index (the scene's animation) or explicitly
(:meth:`Pipeline.set_camera`, :meth:`Pipeline.set_transform`, :meth:`Pipeline.clear_pose`):
explicit parts replace the animation's in every later frame. Motion vectors (and so the
denoiser's and TAA's reprojection) point back to the pose of the previous frame rendered,
whatever its index. A new pose replays the frozen kernels (camera, shapes and lights are
their inputs): it never re-records.

BSPVT trees (``direct=ltc+bspvt``) are built on first use with a progress bar and cached,
keyed by the occluders' geometry and the resolution (:func:`stages.scene_trees`), in memory
and on disk: by default in the user's cache folder (``$XDG_CACHE_HOME/glossrt/bspvt``, else
``~/.cache/glossrt/bspvt``), where later processes find them; ``bspvt_cache=DIR`` chooses
another folder, ``bspvt_cache=False`` none. ``bspvt=FILE`` uses prebuilt trees (``glossrt
bspvt build``), checked against the scene before any work whatever ``direct`` resolves to
(trees of another scene are refused, never ignored). Moving an occluder
invalidates them: under ``direct=ltc+bspvt`` the polygon lights take the ratio estimator and
the ``full`` preset (``direct=auto``) switches to ``ltc+ratio`` while an occluder is away from
its rest pose (and back when it returns: the trees are still cached).

Stages (:mod:`glossrt.pipeline.stages`, each with declared input and output channels):
``gbuffer`` -> ``specaa`` -> ``direct`` -> ``indirect`` -> ``composite`` -> ``taa``
(-> ``display``). ``specaa`` (option ``specaa=METHOD``, :mod:`glossrt.specaa`; default
``none``) replaces the frame's ``roughness`` by the filtered one (the material's kept in
``roughness_material``), which the analytic direct stage and the lobe weights read, and
which the path tracer's primary hit takes too (rough conductors and rough plastics' specular
lobe; the gbuffer stage traces a G-buffer pass first to filter it:
``meta["pipeline"]["specaa"]``).
No double counting, nothing lost: the lights an analytic ``direct`` stage shades (the
polygon lights, and the point and directional lights) are removed from the path tracer at
the primary hit only, and only on the surfaces the stage shades (:class:`glossrt.render.
Renderer`'s ``primary_exclude`` and ``exclude_on``; the stage's image is 0 elsewhere); they
still light every deeper bounce. Presets and options: :mod:`glossrt.pipeline.config`.

Memory: ``Pipeline(outputs=("color",))`` (the render graph's marked outputs, settable between
frames) returns only the channels asked for and frees every other one after the last stage
that reads it (:meth:`stages.Stage.reads`), with the same values; with ``release_memory``
that is what keeps ``full`` at 1920x1080 under 600 MB (docs/PERFORMANCE.md).

Every preset renders every scene the renderer renders: what a direct mode cannot shade (a
light that is not a polygon, point or directional light; a surface whose material it does not
represent; under BSPVT a light its visibility cannot see, or any while an occluder moves) falls
back to the ratio estimator or the path tracer (:mod:`glossrt.pipeline.plan`), and the frames'
``meta["pipeline"]`` says so. Every refusal (unknown option, a specaa method that is unknown
or filters per light, BSPVT trees of another scene, OIDN missing, a size the reduced
resolution does not divide) is one :class:`~glossrt.errors.GlossrtError` raised by the
constructor or :meth:`Pipeline.configure` before any rendering.
"""

from __future__ import annotations

import os
import time
from typing import Any

import drjit as dr
import numpy as np

from ..errors import GlossrtError
from ..frame import Frame
from ..timing import StageClock, check_stage_timing
from . import config
from .config import FILTER_OPTIONS, OPTIONS, PRESETS, load_toml, parse, resolve
from .plan import POLYGON_MODES, DirectPlan, moving_occluders, plan
from .stages import (
    CompositeStage,
    DirectStage,
    GBufferStage,
    IndirectStage,
    SpecAAStage,
    Stage,
    TAAStage,
    display,
)

STAGES = ("gbuffer", "specaa", "direct", "indirect", "composite", "taa", "display")
#: the channels a pipeline frame adds to the G-buffer's (docs/FORMATS.md)
LAYERS = ("direct", "indirect", "composite", "color")


def _setup_of(scene_or_setup, size):
    from ..scenes import SceneSetup, load

    if isinstance(scene_or_setup, SceneSetup):
        if size is not None and tuple(size) != tuple(scene_or_setup.size):
            raise GlossrtError("Pipeline: size is given, but the SceneSetup has its own "
                               f"({scene_or_setup.size[0]}x{scene_or_setup.size[1]})")
        return scene_or_setup
    return load(scene_or_setup, size=size)


def _matrix(m):
    """A 4x4 (or 3x4) NumPy matrix of ``m``: array-like or a Mitsuba transform."""
    from ..scenes import to_matrix

    return to_matrix(m) if hasattr(m, "matrix") else m


def check_outputs(names) -> tuple[str, ...] | None:
    """:attr:`Pipeline.outputs` checked: None, or the names (a string: one name) with
    ``color`` first and no repeats; an unknown name is one GlossrtError listing the
    channels a pipeline frame has."""
    from ..frame import CHANNELS

    if names is None:
        return None
    if isinstance(names, str):
        names = (names,)
    try:
        names = tuple(names)
    except TypeError:
        raise GlossrtError(f"outputs must be channel names or None, got {names!r}") from None
    known = tuple(k for k in CHANNELS if k != "color") + ("roughness_material",) + LAYERS
    bad = [k for k in names if k not in known]
    if bad:
        raise GlossrtError(f"unknown output channel(s) {', '.join(map(str, bad))}; a "
                           f"pipeline frame has {', '.join(known)}")
    return ("color",) + tuple(dict.fromkeys(k for k in names if k != "color"))


def _free(ctx: dict, keep: dict) -> None:
    """Drop from the frame's context what ``keep`` (:meth:`Pipeline._liveness`) does not
    hold: whole entries, and a frame's channels outside its set (``keep`` always holds
    ``frame``: the returned frame's cameras and meta)."""
    for name in list(ctx):
        if name not in keep:
            del ctx[name]
            continue
        chans = keep[name]
        if chans is not None and isinstance(ctx[name], Frame):
            f = ctx[name]
            for k in [k for k in f.names if k not in chans]:
                del f.channels[k]


def _nonfinite(t) -> int:
    """How many values of the tensor ``t`` are NaN or infinite."""
    return int(dr.count(~dr.isfinite(t.array))[0]) if dr.width(t.array) else 0


def check_index(index) -> int:
    """A frame index: an integer >= 0 (NumPy integers too), else one GlossrtError line."""
    if isinstance(index, bool) or not isinstance(index, int | np.integer) or index < 0:
        raise GlossrtError(f"frame index must be an integer >= 0, got {index!r}")
    return int(index)


def _check_every(n) -> None:
    if isinstance(n, bool) or not isinstance(n, int | np.integer) or n < 1:
        raise GlossrtError(f"timing_every must be an integer >= 1, got {n!r}")


class Pipeline:
    """A real-time frame pipeline for one scene (module docstring).

    ``setup_or_scene``: a :class:`glossrt.scenes.SceneSetup`, or anything
    :func:`glossrt.scenes.load` takes (built-in name, XML path, scene dict, ``mi.Scene``);
    ``preset``: a name of :data:`PRESETS` or a ``.toml`` file; ``choices``: options of
    :data:`OPTIONS` overriding the preset. ``progress``: progress bars (BSPVT's trees).
    ``bspvt``: a file of prebuilt BSPVT trees (``glossrt bspvt build``, or a
    :class:`glossrt.lights.bspvt.BSPVT`) for ``direct=ltc+bspvt`` (or ``auto``), checked against
    the scene before any work (trees of another scene are one GlossrtError, even where
    ``auto`` resolves to ``ltc+ratio`` and would not use them). ``bspvt_cache``: where
    built trees are kept on disk, keyed by the geometry and the resolution, and found again
    by later pipelines and processes: ``True`` (default) the user's cache folder
    (:func:`stages.default_bspvt_cache`: ``$XDG_CACHE_HOME/glossrt/bspvt``, else
    ``~/.cache/glossrt/bspvt``); a path: that folder; ``False`` (or ``None``): none, the
    trees are kept in memory only. The folder is made when the first trees are written; one
    that cannot be made or written is warned about once and the trees are kept in memory (the
    frames are the same); a damaged or stale file in it is built anew. :attr:`bspvt_cache` is
    the folder in use (None: none). ``timing``: how ``meta["pipeline"]
    ["stage_ms"]`` is measured (:data:`glossrt.timing.STAGE_TIMINGS`, :class:`glossrt.timing.
    StageClock`): ``"kernels"`` (default) the kernel time of each stage from Dr.Jit's kernel
    history, no stage synchronised; ``"sync"`` the wall time of each stage with the device
    synchronised after it; ``"none"``. Settable between frames (:attr:`timing`).
    ``timing_every`` (``kernels``; default 8): the history is read (which waits for the
    frame's kernels and copies a few hundred entries into Python, 2-4 ms on 2 CPU cores)
    every ``timing_every``-th frame and after the stages change; the frames between carry
    that frame's ``stage_ms``, ``stage_kernels`` and ``kernel_ms``, with its index in
    ``stage_ms_frame`` (``stage_host_ms`` is every frame's own). 1: every frame."""

    def __init__(self, setup_or_scene, preset: str = "schied2017", size=None,
                 progress: bool = True, bspvt=None,
                 bspvt_cache: bool | str | os.PathLike | None = True,
                 timing: str = "kernels", timing_every: int = 8, outputs=None,
                 **choices: Any):
        check_stage_timing(timing)
        self.outputs = outputs  # (checked: the setter)
        self.timing_every = timing_every
        _check_every(timing_every)
        if not (isinstance(preset, str) and preset in PRESETS):
            preset, file_choices = parse(preset)  # (None: the default preset)
            choices = {**file_choices, **choices}
        self.opts = resolve(preset, **choices)  # names and values, before the scene loads
        from .stages import bspvt_cache_dir

        #: the folder built BSPVT trees are kept in (None: in memory only)
        self.bspvt_cache: str | None = bspvt_cache_dir(bspvt_cache)
        trees = self._load_trees(bspvt, self.opts)  # a bad file fails before the scene loads
        self.setup = _setup_of(setup_or_scene, size)
        self.setup.prepare_to_move()  # moving a shape later never re-records (set_transform)
        self.progress = progress
        self.stages: dict[str, Stage] = {}
        self._gbuffer: GBufferStage | None = None
        self._shape_table = None
        self.frames = 0
        self._last_pose = None  # the pose of the previous frame rendered
        self.bspvt_trees = None
        self.timing = timing
        #: the per-stage kernel fields of the last frame whose history was read (``kernels``)
        self._kernel_times: dict | None = None
        self._timed = 0  # frames rendered with ``timing="kernels"``
        self.outputs = outputs  # (checked against the scene's channels, before any work)
        self._apply(self.opts, trees)

    # -- configuration ---------------------------------------------------------------------
    @property
    def outputs(self) -> tuple[str, ...] | None:
        """The channels the frames :meth:`render` returns hold (the render graph's marked
        outputs): None (default) every G-buffer channel and every layer (:data:`LAYERS`);
        else these names, ``color`` always among them. A channel that is neither asked for
        nor read by a later stage is freed as soon as the last stage that reads it has run
        (:meth:`glossrt.pipeline.stages.Stage.reads`), which lowers a frame's peak memory
        (docs/PERFORMANCE.md); the values are the same. Settable between frames (no
        re-recording). Names the scene's frames do not have (``tangent`` and
        ``roughness_uv`` in a scene without anisotropic materials) are refused."""
        return self._outputs

    @outputs.setter
    def outputs(self, names) -> None:
        from ..render.pathtracer import ANISOTROPY_OUT

        names = check_outputs(names)
        absent = ([k for k in names if k in ANISOTROPY_OUT]
                  if names and getattr(self, "setup", None) is not None
                  and not self.shape_table.any_anisotropic else [])
        if absent:
            raise GlossrtError(f"outputs {', '.join(absent)}: scene {self.setup.name!r} has "
                               "no anisotropic material, and its frames have no tangent or "
                               "roughness_uv channel")
        self._outputs = names

    def _liveness(self) -> list[dict[str, set | None]]:
        """Per stage, what the context must still hold after it: context entry -> the frame
        channels still read or asked for (None: all of it); entries absent are freed."""
        want = self._outputs
        final: dict[str, set | None] = {"frame": None if want is None else set(want)}
        for layer in LAYERS:
            if want is None or layer in want:
                final[layer] = None
        out = []
        need = final
        for stage in reversed(list(self.stages.values())):
            out.append(need)
            need = dict(need)
            for name, chans in stage.reads().items():
                if name in need and need[name] is None:
                    continue  # (all of it already)
                need[name] = None if chans is None else set(need.get(name) or ()) | set(chans)
        return out[::-1]

    @property
    def preset(self) -> str:
        return self.opts["preset"]

    @property
    def choices(self) -> dict[str, Any]:
        return {k: v for k, v in self.opts.items() if k != "preset"}

    @property
    def shape_table(self):
        """The scene's :class:`glossrt.render.pathtracer.ShapeTable` (its materials), built
        once."""
        if self._shape_table is None:
            from ..render.pathtracer import ShapeTable

            self._shape_table = ShapeTable(self.setup.scene)
        return self._shape_table

    def _max_depth(self, opts: dict) -> int | None:
        """The path depth the frames render (Mitsuba's convention), None where the
        renderer's default applies."""
        md = opts.get("max_depth")
        return md if md is not None else self.setup.max_depth

    def _resolve_direct(self, opts: dict) -> tuple[str, DirectPlan | None]:
        """``direct``, with ``auto`` (the ``full`` preset) resolved for the scene as it is
        posed: ``ltc+bspvt`` when BSPVT's trees can shade at least one polygon light on at
        least one surface, else ``ltc+ratio`` (an occluder away from its rest pose, no
        triangle meshes fine enough, every polygon light with geometry behind it;
        :mod:`glossrt.pipeline.plan`). At path depth 1 (the
        scene renders emission only) every mode is ``pathtraced``: there is no direct light
        to shade. Also returns the ``ltc+bspvt`` plan ``auto`` was resolved with, when it
        was (None otherwise): the frame's plan, not made twice."""
        mode = opts["direct"]
        if self._max_depth(opts) == 1:
            return "pathtraced", None  # (emission only: no direct light to shade)
        if mode != "auto":
            return mode, None
        if moving_occluders(self.setup):
            return "ltc+ratio", None
        from ..lights.bspvt.scene import scene_meshes

        if not scene_meshes(self.setup.scene):
            return "ltc+ratio", None
        trial = plan(self.setup, "ltc+bspvt", self.shape_table)
        if trial.bspvt and trial.bspvt_shapes:
            return "ltc+bspvt", trial
        return "ltc+ratio", None

    @staticmethod
    def _load_trees(bspvt, opts: dict):
        """The prebuilt trees of ``bspvt`` (a path or BSPVT trees; None: none), refused with
        a ``direct`` that never uses them."""
        if bspvt is None:
            return None
        if opts["direct"] not in ("ltc+bspvt", "auto"):
            what = os.fspath(bspvt) if isinstance(bspvt, (str, os.PathLike)) else "trees"
            raise GlossrtError(f"bspvt={what}: direct={opts['direct']} does not use BSPVT "
                               "trees; choose "
                               "direct=ltc+bspvt (presets okuno-iwasaki, full)")
        if isinstance(bspvt, (str, os.PathLike)):
            from ..lights.bspvt import BSPVT

            return BSPVT.load(os.fspath(bspvt))
        if not hasattr(bspvt, "vertex_count"):
            raise GlossrtError("bspvt must be a BSPVT tree file (glossrt bspvt build) or "
                               f"glossrt.lights.bspvt.BSPVT trees, got {type(bspvt).__name__}")
        return bspvt

    def _check(self, opts: dict, direct: str, trees=None,
               known: DirectPlan | None = None) -> DirectPlan:
        """Every refusal of ``opts`` for this scene, before any work (bad options and files,
        never a light, material or integrator the path tracer renders), and the
        :class:`~glossrt.pipeline.plan.DirectPlan` of ``direct`` at frame 0 (``known``: that
        plan, already made). ``trees``: prebuilt BSPVT trees (checked against the scene:
        :func:`glossrt.lights.bspvt.match_scene`)."""
        name = self.setup.name
        if opts["indirect_scale"] > 1:  # the reduced-resolution indirect light
            from .stages import check_scale

            check_scale(self.setup.size, opts["indirect_scale"])
            if opts["accumulate"]:
                raise GlossrtError("accumulate=true traces the converged reference at full "
                                   "resolution: use indirect_scale=1")
        trees_ok = True
        if direct == "ltc+bspvt":
            from ..lights.bspvt.scene import scene_meshes

            trees_ok = bool(scene_meshes(self.setup.scene))
        # prebuilt trees fit the scene whatever ``direct`` resolves to (``auto`` may resolve
        # to ltc+ratio and not use them: another scene's trees are still refused). Checked
        # once: a later plan, e.g. an occluder away from its rest pose, keeps the trees of
        # the rest pose
        if trees is not None and trees is not getattr(self, "_checked_trees", None):
            from ..lights.bspvt import match_scene

            try:
                match_scene(self.setup.scene, trees)
            except GlossrtError as e:
                raise GlossrtError(f"bspvt: scene {name!r}: {e}") from None
        if opts["indirect"] == "oidn":
            from ..denoise.oidn import oidn_available

            if not oidn_available():
                raise GlossrtError("indirect=oidn: Intel Open Image Denoise (pyoidn) is not "
                                   "installed; choose svgf, svgf-lobe, atrous or none")
        if known is not None:
            return known
        why = ("max_depth 1: the scene renders emission only" if self._max_depth(opts) == 1
               else "direct=pathtraced")
        return plan(self.setup, direct, self.shape_table, trees_ok, why=why)

    def _apply(self, opts: dict, trees=None) -> None:
        old = getattr(self, "_applied", None)
        direct, known = self._resolve_direct(opts)
        trees = self.bspvt_trees if trees is None else trees
        the_plan = self._check(opts, direct, trees, known)
        exclude, on = the_plan.exclude, the_plan.shapes
        self.bspvt_trees = trees
        if trees is not None:
            self._checked_trees = trees

        def same(*keys: str) -> bool:
            return old is not None and all(old[k] == opts[k] for k in keys)

        if (not same("max_depth", "seed", "accumulate", "spp", "indirect_scale")
                or self._gbuffer is None):
            self._gbuffer = GBufferStage(self.setup, opts, exclude, on)
        elif self._gbuffer.exclude != exclude or self._gbuffer.exclude_on != on:
            # the frozen trace records once more (render.Renderer.primary_exclude)
            self._gbuffer.set_exclude(exclude, on)
            self._gbuffer.reset()
        # TAA's sub-pixel jitter: an opaque input of the frozen trace (turning it on or off
        # records the trace once more, a new cycle point does not)
        self._gbuffer.jitter = bool(opts["taa"] and opts["taa_jitter"])
        stages: dict[str, Stage] = {"gbuffer": self._gbuffer}
        prev = self.stages
        stages["specaa"] = (prev["specaa"] if same("specaa") and "specaa" in prev
                            else SpecAAStage(opts["specaa"]))
        # the path tracer's primary hit takes the filtered roughness (GBufferStage)
        self._gbuffer.specaa = stages["specaa"]
        same_plan = old is not None and old.get("_plan") == the_plan.key()
        if (same_plan and old.get("_direct") == direct and old.get("_trees") is trees
                and same("bspvt_mode", "bspvt_resolution", "ratio_spp", "highlight_samples",
                         "highlight_probes", "highlight_distribution")):
            stages["direct"] = prev["direct"]
        else:
            stages["direct"] = DirectStage(self.setup, opts, direct, self.progress,
                                           trees=trees, cache_dir=self.bspvt_cache,
                                           plan=the_plan)
        if (same_plan and old.get("_direct") == direct
                and same("indirect", "indirect_scale", "upsampling", "upsampling_weight",
                         "resample", "resample_threshold", "resample_spp", "max_depth",
                         "seed", *FILTER_OPTIONS)):
            stages["indirect"] = prev["indirect"]
        else:
            stages["indirect"] = IndirectStage(opts["indirect"], opts, self.setup,
                                               the_plan.path_traced_direct)
        stages["composite"] = prev.get("composite") or CompositeStage()
        if old is not None and same("taa", "taa_alpha", "taa_jitter"):
            stages["taa"] = prev["taa"]
        else:
            stages["taa"] = TAAStage(opts["taa"], opts["taa_alpha"],
                                     jitter=bool(opts["taa"] and opts["taa_jitter"]))
        stages["indirect"].release_memory = bool(opts["release_memory"])
        self.stages = stages
        self.opts = dict(opts)
        self._applied = dict(opts, _direct=direct, _trees=trees, _plan=the_plan.key())
        self._moving = bool(moving_occluders(self.setup))
        self.direct_mode = direct
        #: which method shades which light, and the surfaces left to the path tracer
        #: (:class:`glossrt.pipeline.plan.DirectPlan`)
        self.plan = the_plan
        self.point_lights = ("analytic, one shadow ray each" if direct != "pathtraced"
                             else "path-traced")

    def configure(self, bspvt=None, **choices: Any) -> None:
        """Change options between frames (checked first; nothing changes on a refusal). Only
        the stages whose options changed are rebuilt: their frozen kernels record once on
        the next frame; the others keep replaying theirs. ``bspvt``: another file of prebuilt
        trees (as the constructor's)."""
        config.check_names(choices)
        opts = resolve(self.opts["preset"], **{**self.choices, **choices})
        self._apply(opts, self._load_trees(bspvt, opts))

    def reset(self) -> None:
        """Drop every history (denoiser, TAA, accumulation): the next frame starts anew."""
        for stage in self.stages.values():
            stage.reset()
        self._last_pose = None

    # -- posing ------------------------------------------------------------------------------
    def set_camera(self, camera=None, *, position=None, target=None, up=(0.0, 1.0, 0.0),
                   fov: float | None = None) -> None:
        """Pose the camera explicitly in every later frame (instead of the animation's):
        ``camera`` a :class:`glossrt.frame.Camera` (its ``to_world`` and ``fov``; its
        resolution must be the pipeline's) or a 4x4 ``to_world`` matrix (Mitsuba's
        convention, rigid); or ``position`` and ``target`` (and ``up``): Mitsuba's
        ``look_at``. ``fov``: the horizontal field of view in degrees (alone: only the field
        of view changes). Checked first: a GlossrtError changes nothing."""
        from ..frame import Camera
        from ..scenes import look_at

        to_world = None
        if camera is not None and position is not None:
            raise GlossrtError("set_camera: give a camera or position/target, not both")
        if isinstance(camera, Camera):
            if tuple(camera.resolution) != tuple(self.setup.size):
                raise GlossrtError(f"set_camera: the camera is {camera.resolution[0]}x"
                                   f"{camera.resolution[1]}, the pipeline renders "
                                   f"{self.setup.size[0]}x{self.setup.size[1]}")
            to_world, fov = camera.to_world, camera.fov if fov is None else fov
        elif camera is not None:
            to_world = _matrix(camera)
        elif position is not None or target is not None:
            if position is None or target is None:
                raise GlossrtError("set_camera: position and target go together")
            try:
                p, t, u = (np.asarray(v, np.float64).reshape(3) for v in (position, target, up))
            except ValueError:
                raise GlossrtError("set_camera: position, target and up must be 3-vectors") \
                    from None
            d = t - p
            if not (np.isfinite([p, t, u]).all() and np.linalg.norm(d) > 0
                    and np.linalg.norm(np.cross(d, u)) > 1e-9 * np.linalg.norm(d)):
                raise GlossrtError("set_camera: position and target must be finite and apart, "
                                   "and up must not be along the view direction")
            to_world = look_at(p.tolist(), t.tolist(), u.tolist())
        elif fov is None:
            raise GlossrtError("set_camera: give a camera, position and target, or fov "
                               "(clear_pose() goes back to the animation)")
        keep = self.setup.camera_override if to_world is None else to_world
        keep_fov = self.setup.fov_override if fov is None else fov
        self.setup.set_camera_override(keep, keep_fov)  # SceneError (a GlossrtError) first
        self._pose_changed()

    def set_transform(self, name: str, matrix) -> None:
        """Place shape ``name`` (an object, or a polygon light's shape) by the rigid
        ``matrix`` (4x4, on top of its rest pose, as the animation's paths) in every later
        frame; None: back to its animation. ``name`` may also be a point light's emitter id
        (the XML ``id``, the scene dict's key; :meth:`glossrt.scenes.SceneSetup.
        movable_lights`): its position becomes ``matrix`` applied to its rest position, for
        the analytic direct stage and for the path tracer's deeper bounces alike (the
        emitter's ``position`` parameter, an input of the frozen frame: no re-recording).
        Moving an occluder (a shape that is not a light) invalidates BSPVT's precomputed
        visibility: under ``direct=ltc+bspvt`` its polygon lights take the ratio estimator
        while it is away from its rest pose (``meta["pipeline"]["lights"]`` says so), and
        ``direct=auto`` (the ``full`` preset) switches to ``ltc+ratio`` (no trees are
        built); both switch back when it returns. Checked first: a GlossrtError changes
        nothing."""
        from ..scenes import check_rigid

        setup = self.setup
        lights = setup.movable_lights()
        if not isinstance(name, str) or (name not in setup.shape_index and name not in lights):
            raise GlossrtError(f"set_transform: scene {setup.name!r} has no shape {name!r} "
                               "(nor a point light of that id); the shapes that can move are "
                               f"{', '.join(sorted(setup.movable_shapes())) or 'none'}; the "
                               f"point lights {', '.join(lights) or 'none'}")
        m = None
        if matrix is not None:
            m = check_rigid(_matrix(matrix), f"set_transform({name!r})")
        if name not in setup.shape_index:  # a point light: never an occluder
            setup.set_light_override(name, m)
            self._pose_changed()
            return
        setup.set_object_override(name, m)
        self._pose_changed()

    def clear_pose(self) -> None:
        """Back to the animation: no explicit camera, field of view, shape transforms or
        point-light positions."""
        self.setup.clear_overrides()
        self._pose_changed()

    def _pose_changed(self) -> None:
        # an occluder leaving or reaching its rest pose: BSPVT's trees stop or start to hold
        # (auto: ltc+bspvt <-> ltc+ratio; ltc+bspvt: its lights' ratio fallback)
        if self.opts["direct"] not in ("auto", "ltc+bspvt"):
            return
        moving = bool(moving_occluders(self.setup))
        if moving != self._moving:
            self._apply(self.opts)

    # -- frames --------------------------------------------------------------------------
    def frozen(self) -> list:
        """Every ``dr.freeze`` function a frame of the current stages replays (each stage's
        :meth:`~glossrt.pipeline.stages.Stage.frozen`, each function once)."""
        out: dict[int, Any] = {}
        for stage in self.stages.values():
            for f in stage.frozen():
                out.setdefault(id(f), f)
        return list(out.values())

    def recordings(self) -> int:
        """Recordings made so far by the frozen functions a frame replays (:meth:`frozen`).
        The polygon lights' shading kernels (LTC, BSPVT) are module-wide frozen functions:
        their count includes recordings other pipelines made. A steady-state frame adds
        none: new poses (camera, lights, objects) and frames replay."""
        return sum(int(f.n_recordings) for f in self.frozen())

    def render(self, index: int) -> Frame:
        """Frame ``index`` of the scene's animation: the G-buffer's channels (1 spp, with the
        analytic lights removed at the primary hit), each stage's layer (:data:`LAYERS`) and
        the composed ``color``; ``meta["pipeline"]`` holds the choices and per-stage
        milliseconds (:attr:`timing`: by default the kernel time of each stage from Dr.Jit's
        kernel history, no stage synchronised, read every :attr:`timing_every`-th frame: the
        frames between carry the last read frame's, ``stage_ms_frame`` its index; a read frame
        ends evaluated).

        Memory: Dr.Jit's allocator keeps the blocks a stage frees for reuse, so a frame holds
        the sum of its stages' transient buffers, not their maximum. With the option
        ``release_memory`` the pipeline hands them back (``dr.flush_malloc_cache``) after
        each stage and after the low-resolution denoiser; with :attr:`outputs` it frees the
        channels no later stage reads as soon as their last reader has run. ``full`` at
        1920x1080 on the CPU peaks at 824 MiB as is, 627 MiB with ``release_memory`` and
        563 MiB with it and ``outputs=("color",)`` (docs/PERFORMANCE.md); the flush costs
        frame time (the next frame allocates its buffers anew), and on a GPU it may wait for
        the device (not measured)."""
        index = check_index(index)
        ctx: dict[str, Any] = {}
        check_stage_timing(self.timing)
        _check_every(self.timing_every)
        kernels = self.timing == "kernels"
        # the kernel history is read every ``timing_every``-th frame (and after a change of
        # the stages); in between it is on but cleared unread (timing.StageClock)
        names = tuple(self.stages)
        read = (not kernels or self._kernel_times is None
                or self._kernel_times.get("_stages") != names
                or self._timed % self.timing_every == 0)
        clock = StageClock(self.timing, read=read)
        release = bool(self.opts["release_memory"])
        t_all = time.perf_counter()
        pose = self.setup.pose(index)
        if self._last_pose is not None and not pose.same(self._last_pose):
            self._gbuffer.reset()  # (an accumulation starts anew; no history to drop else)
        # motion vectors point back to the previous frame rendered (None: index - 1)
        self._gbuffer.renderer.previous_pose = self._last_pose
        live = self._liveness()
        want = self._outputs
        fold = want is not None and "direct" not in want and "emission" not in want
        clock.start()
        try:
            for (name, stage), keep in zip(self.stages.items(), live, strict=True):
                out = stage.run(index, ctx)
                if set(out) != set(stage.outputs):
                    raise GlossrtError(f"pipeline stage {name} returned {sorted(out)}, "
                                       f"declared {list(stage.outputs)}")
                ctx.update(out)
                # a kernel boundary (no wait): the stage's own work is launched here
                dr.eval([v for k, v in out.items() if not k.startswith("frame")])
                del out  # (the context holds what is still read: _free)
                if fold and name == "direct":
                    CompositeStage.fold(ctx)
                _free(ctx, keep)
                clock.stage_done(name, stage.external_ms)
                if release:
                    dr.flush_malloc_cache()
        finally:
            times = clock.finish()  # waits for the frame's kernels (kernels read, sync)
        if kernels:
            self._timed += 1
            if read:
                self._kernel_times = {k: times.get(k) for k in
                                      ("stage_ms", "stage_kernels", "kernel_ms")}
                if "stage_external_ms" in times:  # (OIDN's host time, in stage_ms)
                    self._kernel_times["stage_external_ms"] = times["stage_external_ms"]
                self._kernel_times.update(_stages=names, stage_ms_frame=index)
            times.update({k: v for k, v in self._kernel_times.items() if k != "_stages"},
                         stage_ms_every=self.timing_every)
        gb: Frame = ctx["frame"]
        channels = {k: gb[k] for k in gb.names if k != "color"}
        for layer in LAYERS:
            if layer in ctx:
                channels[layer] = ctx[layer]
        meta = dict(gb.meta)
        meta.pop("omitted", None)  # (the G-buffer frame's: this frame has its own color)
        # the composed colour's non-finite values (a filter's arithmetic, not the trace's)
        # are replaced by 0 and counted with the trace's in the header's nonfinite_samples
        bad_color = _nonfinite(channels["color"])
        if bad_color:
            c = channels["color"]
            channels["color"] = dr.select(dr.isfinite(c), c, 0.0)
        meta["nonfinite_samples"] = int(meta.get("nonfinite_samples", 0)) + bad_color
        meta["pipeline"] = {
            "preset": self.preset,
            "choices": self.choices,
            "direct": self.direct_mode,
            "point_lights": self.point_lights,
            **self.plan.report(),
            "fallback_share": self._fallback_share(gb),
            "primary_exclude": list(self._gbuffer.exclude),
            "stages": {n: {"inputs": list(s.inputs), "outputs": list(s.outputs)}
                       for n, s in self.stages.items()},
            "layers": [k for k in LAYERS if k in channels],
            "outputs": "all" if self._outputs is None else list(self._outputs),
            "nonfinite_color": bad_color,
            "frame_ms": 1000.0 * (time.perf_counter() - t_all),
            "timing": self.timing,
            **times,
        }
        meta["pipeline"]["specaa"] = {
            "method": self.opts["specaa"],
            # the 1 spp path-traced layers' primary hit (render.pathtracer.PrimaryLobe)
            "path_tracer": ("material roughness" if self.opts["specaa"] == "none"
                            else "filtered roughness at the primary hit")}
        note = config.PRESET_NOTES.get(self.preset)
        if note:
            meta["pipeline"]["note"] = note
        trees = getattr(self.stages["direct"], "trees", None)
        if self.direct_mode == "ltc+bspvt" and trees is not None:
            meta["pipeline"]["bspvt"] = {
                "trees": getattr(trees, "source", "") or "built (cached by geometry)",
                "resolution": int(trees.resolution), "vertices": int(trees.vertex_count)}
        if self.setup.camera_override is not None or self.setup.fov_override is not None \
                or self.setup.object_overrides or self.setup.light_overrides:
            meta["pipeline"]["explicit_pose"] = {
                "camera": self.setup.camera_override is not None,
                "fov": self.setup.fov_override,
                "shapes": sorted(self.setup.object_overrides),
                "point_lights": sorted(self.setup.light_overrides)}
        self._last_pose = pose
        self.frames += 1
        return Frame(channels=channels, camera=gb.camera, prev_camera=gb.prev_camera,
                     index=index, meta=meta)

    @staticmethod
    def _fallback_share(gb: Frame) -> float:
        """The share of the frame's pixels whose direct light the path tracer computes for
        every light although the analytic stage shades some (their surface is one it does
        not represent: ``meta["pipeline"]["fallback_shapes"]``); 0 without analytic
        lights."""
        return float(gb.meta.get("fallback_pixels", 0)) / max(gb.width * gb.height, 1)

    def display(self, frame: Frame) -> Any:
        """The frame's ``color`` as 8-bit sRGB (H, W, 3) ``uint8`` (exposure and tonemap
        from the options)."""
        if not isinstance(frame, Frame) or "color" not in frame.names:
            raise GlossrtError("display: expects a Frame with a color channel (as render "
                               f"returns), got {type(frame).__name__}")
        return display(frame.numpy("color"), self.opts["exposure"], self.opts["tonemap"])


__all__ = ["LAYERS", "OPTIONS", "POLYGON_MODES", "PRESETS", "STAGES", "DirectPlan", "Pipeline",
           "check_outputs", "display", "load_toml", "moving_occluders", "parse", "resolve"]
