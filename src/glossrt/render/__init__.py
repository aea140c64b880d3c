"""Render Frames: G-buffer + separated 1 spp light, converged references, motion vectors.

>>> from glossrt import scenes, render
>>> setup = scenes.load("glossy-cornell", size=(64, 48))      # doctest: +SKIP
>>> r = render.Renderer(setup)                                # doctest: +SKIP
>>> frame = r.render(0)                    # 1 spp, every channel  # doctest: +SKIP
>>> ref = r.render_reference(0, spp=256)   # same channels, converged  # doctest: +SKIP

NaN/Inf policy: a radiance sample that is not finite is replaced by 0 before it is written
or accumulated; how many were replaced is stored in ``frame.meta["nonfinite_samples"]``
and reported by the CLI, never written silently.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Collection

import drjit as dr
import numpy as np

from ..backend import mi
from ..brdf.ggx import SpecularAlbedoTable
from ..errors import GlossrtError
from ..frame import Frame
from ..images import TILE_PIXELS, tile_rows, tile_starts
from ..jit import no_gc
from ..scenes import SceneSetup, _registry_id, emitter_kind, stable_emitters, stable_shapes
from . import integrator as _integrator  # noqa: F401  (registers "glossrt" per variant)
from .motion import MotionInputs
from .pathtracer import (
    ANISOTROPY_OUT,
    RADIANCE_OUT,
    RR_DEPTH,
    UNBOUNDED_DEPTH,
    EmitterTable,
    ShapeTable,
    pixel_channels,
    resolve_max_depth,
    trace_pixels,
)

GBUFFER_OUT = ("albedo_diffuse", "albedo_specular", "normal", "position", "depth", "roughness",
               "roughness_uv", "tangent", "distribution", "mesh_id", "motion")
COMPONENTS = {"depth": 1, "roughness": 1, "roughness_uv": 2, "distribution": 1, "mesh_id": 1,
              "motion": 2}
REFERENCE_SALT = 0x5EED
#: seeds of multi-sample pixel subsets (:meth:`Renderer.render_pixels` with spp > 1)
PIXELS_SALT = 0xADA9
#: path depth of scenes that set none (built-in scenes say 3 themselves; XML files without an
#: integrator get Mitsuba's default, -1)
DEFAULT_MAX_DEPTH = 3
#: lanes per launch when rendering references (pixels x samples)
MAX_LANES = 1 << 21
# pixels per row tile of a frozen full frame (:meth:`Renderer.render`): images.TILE_PIXELS,
# rounded down to whole rows; larger frames replay one recording per row tile (see "row
# tiles" below): 320x180 and 640x360 run untiled, 1920x1080 in 8 tiles of 136 rows
#: radiance channels of the frame (besides ``emission``), by the path's part
DIRECT_OUT = ("direct_diffuse", "direct_specular")
INDIRECT_OUT = ("indirect_diffuse", "indirect_specular")


def _flat(value):
    """Interleaved flat array of a per-lane value (Float stays as it is)."""
    if isinstance(value, (mi.Float, mi.UInt32)):
        return value
    return dr.ravel(value)


def frame_seed(frame: int, seed: int = 0, salt: int = 0) -> int:
    """Deterministic 32-bit seed of a frame (different frames, seeds and salts decorrelate)."""
    x = (frame * 0x9E3779B1 + seed * 0x85EBCA77 + salt * 0xC2B2AE3D) & 0xFFFFFFFF
    x ^= x >> 16
    x = (x * 0x7FEB352D) & 0xFFFFFFFF
    x ^= x >> 15
    return x


def _trace(scene, sensor, shapes, emitters, table, motion_inputs, pixel, seed, width, height,
           max_depth, jitter, normal_maps, primary, roughness=None, lobe_key=None, skip=(),
           rr_depth=RR_DEPTH, material_key=None, primary_only=False):
    # ``normal_maps`` (= shapes.any_normal_map, which gbuffer() reads) is only a key of the
    # frozen function: a Python attribute of the ShapeTable is not part of dr.freeze's key.
    # ``primary``: None (one recording) or the primary-hit EmitterTable (another one; a new
    # exclusion set of the same scene replays it with the new table's values)
    # ``roughness``: None (one recording) or the per-pixel alpha of the primary hit's rough
    # lobes (another one, replayed with each frame's values); ``lobe_key``
    # (= shapes.lobe_key, which PrimaryLobe reads) is only a key, like ``normal_maps``
    # ``skip``: radiance channels not written (a key too); ``rr_depth`` a key;
    # ``material_key`` (= shapes.material_key: sampled albedos, inseparable lobes, null
    # surfaces, which shade() and gbuffer() trace only where the scene has them) a key
    out = trace_pixels(scene, sensor, shapes, emitters, table, motion_inputs, pixel, seed, width,
                       height, max_depth, jitter, primary, roughness, skip, rr_depth,
                       primary_only)
    return {k: _flat(v) for k, v in out.items()}


# -- row tiles of a frozen full frame -------------------------------------------------------
#
# A frozen replay (dr.freeze, Dr.Jit 1.5) keeps every intermediate buffer of the recorded
# function until the call returns: the whole frame's path-tracing state and, for the
# interleaved outputs (:func:`_flat`), a second copy of every channel. Frames of more than
# :attr:`Renderer.tile_pixels` pixels therefore replay one recording per row tile of
# ``rows x W`` pixels (the tile's first pixel an opaque input), whose channels are then
# copied into full-size interleaved buffers outside the frozen call (new each frame: a
# frozen function that scatters into an input buffer copies the whole buffer first,
# measured with drjit 1.5: a 64 MiB buffer held 128 MiB over three such calls). The last
# tile is moved up to end at the last row (overlapping the one before: the same pixels get
# the same values, each pixel's random numbers depending on its index and the frame's seed
# only), so every tile has one shape and one recording; its non-finite count only counts
# the rows no earlier tile wrote. The pattern of glossrt.denoise.upsampling's row tiles.


def _trace_tile(scene, sensor, shapes, emitters, table, motion_inputs, offset, count_from,
                rows, seed, width, height, max_depth, jitter, normal_maps, primary,
                roughness, lobe_key, skip, rr_depth=RR_DEPTH, material_key=None,
                primary_only=False):
    # one row tile of a frame (the pixels offset .. offset + rows * width - 1; ``offset`` and
    # ``count_from`` opaque, the rest as :func:`_trace`'s keys): its channels (interleaved
    # flat arrays of the tile), its non-finite count and its count of fallback pixels
    n = rows * width
    pixel = offset + dr.arange(mi.UInt32, n)
    out, bad, fallback = pixel_channels(scene, sensor, shapes, emitters, table, motion_inputs,
                                        pixel, seed, width, height, max_depth, jitter, primary,
                                        roughness, skip, rr_depth, primary_only)
    new = pixel >= count_from  # (the last tile's rows written before are not counted again)
    bad = dr.select(new, bad, 0)
    fallback = dr.select(new, fallback, 0)
    out = {k: _flat(v) for k, v in out.items()}
    dr.eval(out, bad, fallback)
    return out, dr.sum(bad), dr.sum(fallback)


def _new_frozen_trace():
    """A frozen :func:`_trace` of its own for each :class:`Renderer`. A module-wide one
    replayed a recording made with *another* scene object of the same layout (an equal
    ``dr.freeze`` key): wrong G-buffers and, now and then, a segfault once the first scene
    had been freed (measured 2026-11-23: a second ``coarse_polygon_light`` scene rendered
    frozen differed from its traced render; the crash of test_shadows that
    scripts/run-tests.sh reran). A Renderer keeps one scene, so its recordings only ever
    replay with that scene."""
    return dr.freeze(_trace, warn_after=64)


def _new_frozen_tile():
    """A frozen :func:`_trace_tile` of its own for each :class:`Renderer` (as
    :func:`_new_frozen_trace`). It records twice, on the first frame's first two tiles
    (measured, drjit 1.5: ``auto_opaque`` keeps the first call's literal inputs in its key
    and records again making those that changed opaque; with ``auto_opaque=False`` the
    renderer's literals were made opaque in place, which made this renderer and the others
    on the same scene record again on the next frame), then replays."""
    return dr.freeze(_trace_tile, warn_after=64)


def _warm_emitters(scene: mi.Scene) -> None:
    """Sample every emitter once, outside any frozen recording: Mitsuba builds a textured
    emitter's sampling table lazily on first use, and doing that inside ``dr.freeze``'s
    recording aborts the first frame ("frozen function included a virtual function call")."""
    it = dr.zeros(mi.Interaction3f, 1)
    for e in scene.emitters():
        ds, w = e.sample_direction(it, mi.Point2f(0.5, 0.5), True)
        dr.eval(ds, w)


def emitter_index(setup: SceneSetup) -> list[tuple[int, str, str, int | None]]:
    """The emitters of ``setup`` as the renderer numbers them (``Renderer(primary_exclude=)``
    takes these indices): ``(index, emitter id, kind, shape index)`` per emitter, in
    :func:`glossrt.scenes.stable_emitters` order; ``kind`` its plugin (``"area"``,
    ``"point"``, ``"directional"``, ``"envmap"``, ``"constant"``); ``shape index`` the
    1-based index of an area light's shape in :func:`glossrt.scenes.stable_shapes` (what the
    ``mesh_id`` channel and :attr:`glossrt.lights.scene.PolygonLight.mesh_id` hold), None for
    other emitters."""
    scene = setup.scene
    rank = {_registry_id(mi.ShapePtr, s): i + 1 for i, s in enumerate(stable_shapes(scene))}
    out = []
    for k, e in enumerate(stable_emitters(scene)):
        shape = e.get_shape()
        out.append((k, e.id(), emitter_kind(e),
                    rank.get(_registry_id(mi.ShapePtr, shape)) if shape is not None else None))
    return out


def _check_exclude(exclude, n: int) -> tuple[int, ...]:
    """``primary_exclude`` as sorted unique emitter indices, or one clear error."""
    if isinstance(exclude, (str, bytes)) or not isinstance(exclude, Collection):
        raise GlossrtError("primary_exclude must be a collection of emitter indices "
                           f"(see render.emitter_index), got {exclude!r}")
    out = set()
    for i in exclude:
        if isinstance(i, (bool, np.bool_)) or not isinstance(i, (int, np.integer)):
            raise GlossrtError(f"primary_exclude: emitter indices must be integers, got {i!r}")
        if not 0 <= int(i) < n:
            raise GlossrtError(f"primary_exclude: emitter index {int(i)} is out of range: the "
                               f"scene has {n} emitter(s) (indices 0..{n - 1}, see "
                               "render.emitter_index)")
        out.add(int(i))
    return tuple(sorted(out))


def _check_shapes(mesh_ids, n: int) -> tuple[int, ...] | None:
    """``exclude_on`` as sorted unique 1-based mesh ids (None stays None), or one clear
    error."""
    if mesh_ids is None:
        return None
    if isinstance(mesh_ids, (str, bytes)) or not isinstance(mesh_ids, Collection):
        raise GlossrtError("exclude_on must be a collection of mesh ids (1-based, as the "
                           f"mesh_id channel), or None; got {mesh_ids!r}")
    out = set()
    for i in mesh_ids:
        if isinstance(i, (bool, np.bool_)) or not isinstance(i, (int, np.integer)) \
                or not 1 <= int(i) <= n:
            raise GlossrtError(f"exclude_on: {i!r} is not a mesh id of the scene (1..{n})")
        out.add(int(i))
    return tuple(sorted(out))


def _check_jitter(jitter, limit: float = 0.5) -> tuple[float, float]:
    try:
        jx, jy = (float(v) for v in jitter)
    except (TypeError, ValueError):
        raise GlossrtError(f"jitter must be (x, y) in pixels, got {jitter!r}") from None
    if not (-limit <= jx < limit and -limit <= jy < limit):
        raise GlossrtError(f"jitter must lie in [-{limit}, {limit}) pixels, got {(jx, jy)}")
    return jx, jy


class Renderer:
    """glossrt's 1 spp G-buffer path tracer for one :class:`SceneSetup`.

    ``max_depth`` follows Mitsuba (3 = primary hit plus one extra scattering event; -1 = no
    limit, Russian roulette from depth 5). Without the argument: the scene's own (an XML
    file's integrator, ``<include>``d files included; Mitsuba's default -1 for a file without
    an integrator; 3 for the built-in scenes), else :data:`DEFAULT_MAX_DEPTH`. Frames record
    it in ``meta["max_depth"]`` (Mitsuba's convention), where it came from in
    ``meta["max_depth_from"]`` and the Russian-roulette depth in ``meta["rr_depth"]``.
    ``frozen=True`` records the per-frame kernels with ``dr.freeze`` and replays them on
    later frames of the same size (Python tracing otherwise costs ~0.35 s per frame).

    ``primary_exclude``: indices of emitters (:func:`emitter_index`) whose light an analytic
    stage computes instead: at the primary hit (path vertex 0) only, next-event estimation
    samples the other emitters (Mitsuba's selection probabilities renormalised over them,
    and the MIS pdf of BSDF-sampled hits uses the same ones) and a BSDF-sampled ray from
    there that hits an excluded emitter brings nothing, so ``direct_*`` lacks their light.
    Their emission seen by the camera (``emission``) and their light at every deeper vertex
    (``indirect_*``) stay; with the same seed ``indirect_*`` is the unexcluded render's.
    Frames record the indices in ``meta["primary_exclude"]`` and the emitters' ids in
    ``meta["primary_exclude_ids"]`` (only when some are excluded). Settable between frames
    (:attr:`primary_exclude`): a set not used before records the frozen trace once more
    (at most), a set used before replays its recording.

    ``exclude_on``: the shapes (1-based mesh ids, as the ``mesh_id`` channel numbers them)
    at whose primary hits the exclusion applies; a primary hit on any other shape samples
    every emitter (its direct light path-traced in full, as the analytic stage leaves such
    pixels). None (default): every shape. Frames count the primary hits elsewhere in
    ``meta["fallback_pixels"]`` (with an exclusion). Settable between frames, as
    :attr:`primary_exclude` (:meth:`set_exclusion` sets both): a pair not used before
    records the frozen trace once more, a pair used before replays its recording.

    ``rr_depth``: the depth Russian roulette starts at (default: the scene integrator's
    ``rr_depth``, else Mitsuba's 5). ``primary_only``: trace the primary hit's light alone
    (its emission, next-event estimation and the emitter hit of its BSDF sample, within
    ``max_depth``; ``indirect_*`` are 0), the full-resolution half of the pipeline's
    reduced-resolution indirect light. Unlike ``max_depth=2`` it leaves the path depth the
    scene's, which the surfaces a primary ray passes through count against (as
    Mitsuba's). A scene whose integrator glossrt does not render
    (:attr:`glossrt.scenes.SceneSetup.integrator_error`) is refused here unless
    ``max_depth`` is given."""

    def __init__(self, setup: SceneSetup, max_depth: int | None = None, seed: int = 0,
                 frozen: bool = True, primary_exclude: Collection[int] = (),
                 tile_pixels: int = TILE_PIXELS, exclude_on: Collection[int] | None = None,
                 rr_depth: int | None = None, primary_only: bool = False):
        if isinstance(tile_pixels, bool) or not isinstance(tile_pixels, (int, np.integer)) \
                or tile_pixels < 1:
            raise GlossrtError(f"tile_pixels must be a positive integer, got {tile_pixels!r}")
        #: frozen frames of more pixels than this run in row tiles (:data:`TILE_PIXELS`)
        self.tile_pixels = int(tile_pixels)
        self.setup = setup
        if max_depth is not None:
            md, self.max_depth_from = max_depth, "argument"
        elif getattr(setup, "integrator_error", None):
            raise GlossrtError(setup.integrator_error)
        elif setup.max_depth is not None:
            md, self.max_depth_from = setup.max_depth, setup.max_depth_from or "scene"
        else:
            md, self.max_depth_from = DEFAULT_MAX_DEPTH, "glossrt's default"
        self.max_depth = resolve_max_depth(md)
        rr = rr_depth if rr_depth is not None else getattr(setup, "rr_depth", None)
        rr = RR_DEPTH if rr is None else rr
        if isinstance(rr, bool) or not isinstance(rr, (int, np.integer)) or rr < 1:
            raise GlossrtError(f"rr_depth must be an integer >= 1 (as Mitsuba's), got {rr!r}")
        #: the depth Russian roulette starts at (Mitsuba's ``rr_depth``)
        self.rr_depth = int(rr)
        #: whether frames hold the primary hit's light alone (see the class)
        self.primary_only = bool(primary_only)
        self.seed = seed
        self.frozen = frozen
        self._trace_frozen = _new_frozen_trace()  # recordings never shared across scenes
        self._tile_frozen = _new_frozen_tile()
        self.shapes = ShapeTable(setup.scene)
        #: emitters in a load-independent order for next-event estimation (reproducible noise)
        self.emitters = EmitterTable(setup.scene)
        self._primary: EmitterTable | None = None
        self._primary_tables: dict[tuple, EmitterTable] = {}
        self._exclude: tuple[int, ...] = ()
        self._exclude_on: tuple[int, ...] | None = None
        # ids of the emitters in stable_emitters order (the numbering primary_exclude uses),
        # ordered once: stable_emitters digests every non-area emitter's parameters
        self._emitter_ids = tuple(e.id() for e in stable_emitters(setup.scene))
        self._exclude_on = _check_shapes(exclude_on, len(setup.shapes))
        self.primary_exclude = primary_exclude
        _warm_emitters(setup.scene)
        self.table = SpecularAlbedoTable.load()
        self.width, self.height = setup.size
        self.n_meshes = len(setup.shapes)
        #: the pose motion vectors point back to (:class:`glossrt.scenes.Pose`, e.g. the
        #: previous frame a real-time pipeline rendered); None: the animation's frame - 1
        self.previous_pose = None

    @property
    def primary_exclude(self) -> tuple[int, ...]:
        """Emitter indices left out of ``direct_*`` at the primary hit (see the class)."""
        return self._exclude

    @primary_exclude.setter
    def primary_exclude(self, exclude: Collection[int]) -> None:
        exclude = _check_exclude(exclude, len(self._emitter_ids))
        self._set_primary(exclude, self._exclude_on)

    @property
    def exclude_on(self) -> tuple[int, ...] | None:
        """Mesh ids of the shapes where :attr:`primary_exclude` applies (None: all)."""
        return self._exclude_on

    @exclude_on.setter
    def exclude_on(self, mesh_ids: Collection[int] | None) -> None:
        self._set_primary(self._exclude, _check_shapes(mesh_ids, len(self.setup.shapes)))

    def set_exclusion(self, primary_exclude: Collection[int],
                      exclude_on: Collection[int] | None = None) -> None:
        """:attr:`primary_exclude` and :attr:`exclude_on` together (checked first; one
        primary table for the pair)."""
        exclude = _check_exclude(primary_exclude, len(self._emitter_ids))
        self._set_primary(exclude, _check_shapes(exclude_on, len(self.setup.shapes)))

    def _set_primary(self, exclude: tuple[int, ...], on: tuple[int, ...] | None) -> None:
        if on is not None and len(on) == len(self.setup.shapes):
            on = None  # every shape: the same as no restriction
        key = (exclude, on)
        if exclude and key not in self._primary_tables:
            shapes = None if on is None else [self.setup.shapes[i - 1] for i in on]
            self._primary_tables[key] = EmitterTable(self.setup.scene, exclude, shapes)
        # a table kept per set: going back to an earlier set replays its recording (a new
        # table of equal values was measured to record once more, dr.freeze in drjit 1.5)
        self._primary = self._primary_tables[key] if exclude else None
        self._exclude = exclude
        self._exclude_on = on

    # -- low level ---------------------------------------------------------------------
    def frozen_functions(self) -> list:
        """The ``dr.freeze`` function this renderer's frames replay (the whole-frame trace,
        or the row tiles' one above :attr:`tile_pixels` pixels), to count its recordings."""
        if self.width * self.height > self.tile_pixels:
            return [self._tile_frozen]
        return [self._trace_frozen]

    def zero_channels(self, max_depth: int | None = None) -> tuple[str, ...]:
        """The radiance channels that are 0 by construction in a frame of path depth
        ``max_depth`` (Mitsuba's convention; default the renderer's) with the current
        :attr:`primary_exclude`: ``indirect_*`` at depth 2 or less (the path ends after
        the primary vertex's next-event estimation and BSDF-sampled emitter hit:
        :func:`~glossrt.render.pathtracer.shade` adds nothing to them), ``direct_*`` at
        depth 1 (no light sampled) or when every emitter is excluded at the primary hit.
        :meth:`render` writes no buffer for them: its frame holds one zero constant
        (``dr.zeros``, no memory until it is read out) per such channel."""
        md = self.max_depth if max_depth is None else resolve_max_depth(max_depth)
        out = []
        every = self._emitter_ids and len(self._exclude) == len(self._emitter_ids)
        if md <= 1 or (every and self._exclude_on is None):
            out += DIRECT_OUT
        if md <= 2 or self.primary_only:
            out += INDIRECT_OUT
        return tuple(out)

    @property
    def mitsuba_max_depth(self) -> int:
        """``max_depth`` in Mitsuba's convention (-1: no limit)."""
        return -1 if self.max_depth == UNBOUNDED_DEPTH else self.max_depth

    def _prev_camera(self, frame: int):
        """The camera motion vectors point back to: :attr:`previous_pose`'s when set, else
        the animation's at ``frame - 1`` (``frame`` itself for frame 0)."""
        from ..frame import Camera

        p = self.previous_pose
        if p is not None:
            return Camera(to_world=p.camera, fov=p.fov, resolution=self.setup.size)
        return self.setup.camera(frame - 1 if frame > 0 else frame)

    def _motion_inputs(self, frame: int) -> MotionInputs:
        p = self.previous_pose
        cur = self.setup.object_transforms(frame)
        if p is not None:
            prev_objs = p.objects
        else:
            prev_objs = self.setup.object_transforms(frame - 1 if frame > 0 else frame)
        for m in prev_objs:  # a shape moved then but at rest now
            cur.setdefault(m, np.eye(4))
        return MotionInputs(self._prev_camera(frame), cur, prev_objs, self.n_meshes)

    def _roughness(self, roughness) -> mi.Float | None:
        """``roughness`` as a flat per-pixel ``mi.Float`` (evaluated), or one clear error."""
        if roughness is None:
            return None
        n = self.width * self.height
        if isinstance(roughness, mi.TensorXf):
            if tuple(roughness.shape) not in ((self.height, self.width, 1),
                                              (self.height, self.width)):
                raise GlossrtError(f"roughness must be {self.height}x{self.width}(x1) (one "
                                   f"alpha per pixel), got shape {tuple(roughness.shape)}")
            flat = mi.Float(roughness.array)
        elif isinstance(roughness, mi.Float):
            flat = roughness
        else:
            a = np.asarray(roughness, np.float32)
            if a.size != n or a.ndim not in (2, 3) or a.shape[:2] != (self.height, self.width):
                raise GlossrtError(f"roughness must be {self.height}x{self.width}(x1) (one "
                                   f"alpha per pixel), got shape {a.shape}")
            flat = mi.Float(a.ravel())
        if dr.width(flat) != n:
            raise GlossrtError(f"roughness must hold one alpha per pixel ({n}), got "
                               f"{dr.width(flat)}")
        dr.eval(flat)
        return flat

    def trace(self, frame: int, pixel: mi.UInt32, seed: mi.UInt32,
              frozen: bool | None = None, jitter: tuple[float, float] = (0.0, 0.0),
              jitter_limit: float = 0.5, roughness=None,
              max_depth: int | None = None, skip: tuple[str, ...] = ()) -> dict:
        """Poses ``frame`` and returns every channel (interleaved flat arrays) for the pixel
        indices ``pixel`` with per-lane (or one opaque) seed; primary rays pass through
        pixel centre + ``jitter`` (pixels, within ``[-jitter_limit, jitter_limit)``).
        ``roughness``: the primary hit's per-pixel alpha (see :meth:`render`), an opaque
        input of the frozen trace; ``max_depth``: this call's path depth (default the
        renderer's; 1: G-buffer and emission only); ``skip``: radiance channels left
        out (a key of the frozen trace)."""
        roughness = self._roughness(roughness)
        md = self.max_depth if max_depth is None else resolve_max_depth(max_depth)
        self.setup.set_frame(frame)
        frozen = self.frozen if frozen is None else frozen
        fn = self._trace_frozen if frozen else _trace
        jx, jy = _check_jitter(jitter, jitter_limit)
        # None: primary rays through the pixel centres, which then also give the motion
        # (a jittered frame traces one more ray per pixel, through its centre, for it)
        offset = (None if (jx, jy) == (0.0, 0.0)
                  else mi.Point2f(dr.opaque(mi.Float, jx), dr.opaque(mi.Float, jy)))
        args = (self.setup.scene, self.setup.sensor, self.shapes, self.emitters, self.table,
                self._motion_inputs(frame), pixel, seed, self.width, self.height,
                md, offset, self.shapes.any_normal_map, self._primary, roughness,
                self.shapes.lobe_key if roughness is not None else None, tuple(skip),
                self.rr_depth, self.shapes.material_key, self.primary_only)
        with no_gc():
            try:
                out = fn(*args)
            except RuntimeError as e:
                if fn is _trace or not self._unfreezable(e):
                    raise
                out = _trace(*args)
            dr.eval(out)
        return out

    def _unfreezable(self, e: RuntimeError) -> bool:
        """Whether ``e`` is Dr.Jit refusing to record the frame's kernels with ``dr.freeze``
        (a plugin whose virtual calls read objects the scene does not hand to Dr.Jit's
        traversal: Mitsuba's ``polarizer`` in an RGB variant). Then this renderer traces
        every frame anew from now on (:attr:`frozen` False; about 0.35 s of Python tracing a
        frame on a CPU), with a one-line warning, rather than refusing the scene."""
        if "frozen function" not in str(e) and "record()" not in str(e):
            return False
        if self.frozen:
            import warnings

            warnings.warn(f"{self.setup.name}: Dr.Jit cannot freeze this scene's kernels "
                          f"({str(e).splitlines()[0][:160]}); every frame is traced anew "
                          "(slower)", stacklevel=4)
        self.frozen = False
        return True

    def render_pixels(self, frame: int, pixels, seed: int | None = None,
                      spp: int = 1) -> dict[str, np.ndarray]:
        """Channels for a subset of pixels (indices y*W + x) of ``frame``: name -> (N, C)
        NumPy arrays. With ``spp=1`` they equal those pixels' values in :meth:`render`; with
        ``spp > 1`` the radiance is the mean of ``spp`` independent samples (seeds of their
        own, independent of :meth:`render_reference`'s) and the G-buffer is unchanged."""
        idx = np.asarray(pixels, dtype=np.int64).ravel()
        if idx.size and (idx.min() < 0 or idx.max() >= self.width * self.height):
            raise GlossrtError(f"pixel indices must lie in [0, {self.width * self.height})")
        if spp < 1:
            raise GlossrtError(f"spp must be >= 1, got {spp}")
        if idx.size == 0:
            idx = np.zeros(0, np.int64)
        s = frame_seed(frame, self.seed if seed is None else seed)
        if spp == 1:
            out = self.trace(frame, mi.UInt32(idx.astype(np.uint32)), dr.opaque(mi.UInt32, s),
                             frozen=False)
            out.pop("nonfinite")
            out.pop("fallback")
            return {k: np.array(v).reshape(idx.size, -1) for k, v in out.items()}
        base = frame_seed(frame, self.seed if seed is None else seed, PIXELS_SALT)
        # launches of at most MAX_LANES lanes (pixel-major), whatever the pixels and spp:
        # each lane's sample depends on its pixel and sample index only
        step = max(1, MAX_LANES // spp)
        parts: dict[str, list[np.ndarray]] = {}
        for start in range(0, max(idx.size, 1), step):
            chunk = idx[start:start + step]
            lanes = np.repeat(chunk, spp).astype(np.uint32)
            sample = dr.arange(mi.UInt32, lanes.size) % spp
            seeds = mi.sample_tea_32(sample, dr.opaque(mi.UInt32, base), 4)[0]
            out = self.trace(frame, mi.UInt32(lanes), seeds, frozen=False)
            out.pop("nonfinite")
            out.pop("fallback")
            for k, v in out.items():
                a = np.array(v).reshape(chunk.size, spp, -1)
                parts.setdefault(k, []).append(
                    a.mean(axis=1) if k in RADIANCE_OUT or k == "color" else a[:, 0])
        return {k: np.concatenate(v) for k, v in parts.items()}

    # -- frames --------------------------------------------------------------------------
    def render(self, frame: int, seed: int | None = None,
               jitter: tuple[float, float] = (0.0, 0.0), jitter_limit: float = 0.5,
               roughness=None, omit: Collection[str] = ()) -> Frame:
        """The 1 spp Frame ``frame`` (G-buffer, separated radiance, motion vectors).
        ``jitter``: sub-pixel offset (x, y) of every primary ray from its pixel centre, in
        pixels within [-0.5, 0.5) (e.g. for spatio-temporal upsampling); recorded in
        ``meta["jitter"]``. ``jitter_limit`` widens that range (a Gaussian pixel filter's
        samples reach into the neighbouring pixels: :func:`glossrt.specaa.reference`).

        ``roughness``: a microfacet alpha per pixel (``(H, W)`` or ``(H, W, 1)``: a
        ``mi.TensorXf``, a flat ``mi.Float`` or a NumPy array) that the primary hit's rough
        lobes take instead of the material's (rough conductors and rough plastics' specular
        lobe, also inside ``twosided`` and ``normalmap``;
        :class:`glossrt.render.pathtracer.PrimaryLobe`): next-event estimation, BSDF
        sampling and the MIS pdfs at path vertex 0; deeper vertices, other BSDFs and pixels
        with a negative alpha keep the material's. For specular antialiasing (the filtered
        roughness of :mod:`glossrt.specaa`), so environment maps and path-traced light see
        it. An opaque input: frames with new values replay the frozen trace. The G-buffer's
        ``roughness`` stays the material's; ``meta["primary_roughness"]`` says
        ``"override"``.

        ``omit``: radiance channels (of ``emission``, ``direct_*``, ``indirect_*``,
        ``color``) or anisotropy channels (``tangent``, ``roughness_uv``:
        :data:`~glossrt.render.pathtracer.ANISOTROPY_OUT`) the caller does not read: not
        written, and absent from the frame
        (``meta["omitted"]`` lists them). Channels that are 0 by construction
        (:meth:`zero_channels`) are not written either; the frame holds a zero constant for
        each. Frozen frames of more than :attr:`tile_pixels` pixels are traced in row tiles
        (the same values)."""
        t0 = time.perf_counter()
        channels, bad, fallback = self._trace_frame(
            frame, self.seed if seed is None else seed, jitter, jitter_limit, roughness, None,
            omit)
        f = self._frame(frame, channels, 1, bad, time.perf_counter() - t0, fallback=fallback)
        if omit:
            f.meta["omitted"] = sorted(set(omit))
        if tuple(jitter) != (0.0, 0.0):
            f.meta["jitter"] = [float(jitter[0]), float(jitter[1])]
        if roughness is not None:
            f.meta["primary_roughness"] = "override"
        if self.primary_only:
            f.meta["primary_only"] = True
        return f

    def render_gbuffer(self, frame: int, omit: Collection[str] = (),
                       jitter: tuple[float, float] = (0.0, 0.0)) -> Frame:
        """The G-buffer of frame ``frame`` alone (path depth 1: every G-buffer channel and
        the motion vectors exactly as :meth:`render` gives them, the emission seen by the
        camera, no other light): a cheap first pass whose G-buffer a per-pixel roughness
        (specular antialiasing) is computed from before :meth:`render` traces the light
        with it. Frozen like :meth:`render` (its own recording). Its ``direct_*`` and
        ``indirect_*`` are zero constants (:meth:`zero_channels`); ``omit`` as
        :meth:`render`'s; ``jitter`` as :meth:`render`'s (the same rays as a jittered light
        pass)."""
        t0 = time.perf_counter()
        channels, bad, fallback = self._trace_frame(frame, self.seed, jitter, 0.5, None, 1,
                                                    omit)
        f = self._frame(frame, channels, 1, bad, time.perf_counter() - t0, fallback=fallback)
        f.meta["max_depth"] = 1
        if omit:
            f.meta["omitted"] = sorted(set(omit))
        return f

    def _trace_frame(self, frame: int, seed: int, jitter, jitter_limit, roughness,
                     max_depth: int | None, omit: Collection[str]) -> tuple[dict, int, int]:
        """The whole frame's channels (``(H, W, C)`` tensors), its non-finite count and its
        count of fallback pixels (:func:`glossrt.render.pathtracer.trace_pixels`):
        :meth:`trace` of every pixel, or its row tiles (frozen, more than
        :attr:`tile_pixels` pixels); the zero channels as constants, ``omit`` left out."""
        if isinstance(omit, (str, bytes)) or not isinstance(omit, Collection):
            raise GlossrtError(f"omit must be a collection of channel names, got {omit!r}")
        names = RADIANCE_OUT + ("color",)
        for k in omit:
            if k not in names + ANISOTROPY_OUT:
                raise GlossrtError(f"omit: {k!r} is not a radiance channel or an anisotropy "
                                   f"channel; choose from "
                                   f"{', '.join(names + ANISOTROPY_OUT)}")
        w, h = self.width, self.height
        zero = tuple(k for k in self.zero_channels(max_depth) if k not in omit)
        skip = tuple(k for k in names + ANISOTROPY_OUT if k in zero or k in omit)
        s = frame_seed(frame, seed)
        tiles = None
        if self.frozen and w * h > self.tile_pixels:
            try:
                tiles = self._trace_tiles(frame, s, jitter, jitter_limit, roughness, max_depth,
                                          skip)
            except RuntimeError as e:  # (traced anew from now on: _unfreezable)
                if not self._unfreezable(e):
                    raise
        if tiles is None:
            out = self.trace(frame, dr.arange(mi.UInt32, w * h), dr.opaque(mi.UInt32, s),
                             jitter=jitter, jitter_limit=jitter_limit, roughness=roughness,
                             max_depth=max_depth, skip=skip)
            bad = int(out.pop("nonfinite")[0])
            fallback = int(out.pop("fallback")[0])
        else:
            out, bad, fallback = tiles
        channels = {k: mi.TensorXf(v, (h, w, COMPONENTS.get(k, 3))) for k, v in out.items()}
        for k in zero:
            channels[k] = dr.zeros(mi.TensorXf, (h, w, 3))
        # the schema's order (readers list the channels as a frame holds them)
        order = {k: i for i, k in enumerate(GBUFFER_OUT[:-1] + names + ("motion",))}
        channels = dict(sorted(channels.items(), key=lambda kv: order.get(kv[0], len(order))))
        return channels, bad, fallback

    def _trace_tiles(self, frame: int, s: int, jitter, jitter_limit, roughness,
                     max_depth: int | None, skip: tuple[str, ...]) -> tuple[dict, int, int]:
        """The frozen frame in row tiles (see "row tiles of a frozen full frame"): flat
        interleaved channels, the non-finite count and the fallback pixels' count."""
        roughness = self._roughness(roughness)
        md = self.max_depth if max_depth is None else resolve_max_depth(max_depth)
        self.setup.set_frame(frame)
        jx, jy = _check_jitter(jitter, jitter_limit)
        offset = (None if (jx, jy) == (0.0, 0.0)
                  else mi.Point2f(dr.opaque(mi.Float, jx), dr.opaque(mi.Float, jy)))
        w, h = self.width, self.height
        rows = tile_rows(w, h, self.tile_pixels)
        names = [k for k in GBUFFER_OUT + RADIANCE_OUT + ("color",) if k not in skip]
        buffers = {k: dr.empty(mi.Float, w * h * COMPONENTS.get(k, 3)) for k in names}
        dr.eval(buffers)
        seed = dr.opaque(mi.UInt32, s)
        motion_inputs = self._motion_inputs(frame)
        bad, fallback = [], []
        done = 0  # rows written by the tiles so far
        with no_gc():
            for r in tile_starts(h, rows):
                tile, count, fb = self._tile_frozen(
                    self.setup.scene, self.setup.sensor, self.shapes, self.emitters,
                    self.table, motion_inputs, dr.opaque(mi.UInt32, r * w),
                    dr.opaque(mi.UInt32, done * w), rows, seed, w, h, md, offset,
                    self.shapes.any_normal_map, self._primary, roughness,
                    self.shapes.lobe_key if roughness is not None else None, skip,
                    self.rr_depth, self.shapes.material_key, self.primary_only)
                bad.append(count)
                fallback.append(fb)
                start = dr.opaque(mi.UInt32, r * w)  # (one copy kernel per width, any tile)
                for k, v in tile.items():
                    c = COMPONENTS.get(k, 3)
                    dr.scatter(buffers[k], v, start * c + dr.arange(mi.UInt32, rows * w * c))
                dr.eval(buffers)
                del tile
                done = r + rows
            total = sum(bad[1:], bad[0])
            fb_total = sum(fallback[1:], fallback[0])
            dr.eval(total, fb_total)
        return buffers, int(total[0]), int(fb_total[0])

    def render_reference(self, frame: int, spp: int, seed: int | None = None,
                         progress: Callable[[int, int], None] | None = None,
                         roughness=None) -> Frame:
        """A converged Frame: ``spp`` independent 1 spp estimates per pixel averaged, with the
        same pixel-centre primary hits (so it differs from :meth:`render` only by noise).
        ``roughness``: the primary hit's per-pixel alpha, as :meth:`render`'s."""
        roughness = self._roughness(roughness)
        if spp < 1:
            raise GlossrtError(f"spp must be >= 1, got {spp}")
        w, h = self.width, self.height
        n_pix = w * h
        k = max(1, min(spp, MAX_LANES // max(n_pix, 1)))
        base = frame_seed(frame, self.seed if seed is None else seed, REFERENCE_SALT)
        sums: dict[str, mi.Float] = {}
        gbuf: dict[str, mi.TensorXf] = {}
        bad = 0
        fallback = None
        done = 0
        t0 = time.perf_counter()
        while done < spp:
            kk = min(k, spp - done)
            lane = dr.arange(mi.UInt32, n_pix * kk)
            sample = lane % kk + done
            seeds = mi.sample_tea_32(sample, dr.opaque(mi.UInt32, base), 4)[0]
            out = self.trace(frame, lane // kk, seeds, frozen=False, roughness=roughness)
            bad += int(out["nonfinite"][0])
            if fallback is None:  # (each pixel's primary hit is the same in every sample)
                fallback = int(out["fallback"][0]) // kk
            for name in RADIANCE_OUT:
                # lanes are pixel-major: pixel p owns lanes p*kk .. p*kk+kk-1
                v = dr.unravel(mi.Color3f, out[name])
                part = dr.ravel(mi.Color3f(*(dr.block_sum(v[c], kk) for c in range(3))))
                sums[name] = sums[name] + part if name in sums else part
                dr.eval(sums[name])
            if not gbuf:
                for name in GBUFFER_OUT:
                    c = COMPONENTS.get(name, 3)
                    first = dr.arange(mi.UInt32, n_pix) * kk
                    idx = dr.repeat(first * c, c) + dr.tile(dr.arange(mi.UInt32, c), n_pix)
                    gbuf[name] = mi.TensorXf(dr.gather(mi.Float, out[name], idx), (h, w, c))
            done += kk
            if progress is not None:
                progress(done, spp)
        channels = {k_: mi.TensorXf(v / spp, (h, w, 3)) for k_, v in sums.items()}
        channels["color"] = mi.TensorXf(sum(sums[n] for n in RADIANCE_OUT) / spp, (h, w, 3))
        channels.update(gbuf)
        f = self._frame(frame, channels, spp, bad, time.perf_counter() - t0, reference=True,
                        fallback=fallback)
        if roughness is not None:
            f.meta["primary_roughness"] = "override"
        return f

    def render_mitsuba(self, frame: int, spp: int, seed: int = 0,
                       integrator: str = "path") -> mi.TensorXf:
        """Mitsuba's own ``path`` integrator (anti-aliased, box filter) on the same scene,
        camera and ``max_depth``, or its ``direct`` integrator (``integrator="direct"``:
        emission plus one bounce of light, shadowed, the ground truth of direct lighting):
        RGB image (H, W, 3)."""
        if integrator not in ("path", "direct"):
            raise GlossrtError(f"render_mitsuba: integrator must be 'path' or 'direct', "
                               f"got {integrator!r}")
        self.setup.set_frame(frame)
        md = self.mitsuba_max_depth
        integrator = mi.load_dict({"type": "path", "max_depth": md, "rr_depth": self.rr_depth}
                                  if integrator == "path" else {"type": "direct"})
        img = mi.render(self.setup.scene, sensor=self.setup.sensor, integrator=integrator,
                        spp=spp, seed=frame_seed(frame, seed, 0xA11A5))
        return mi.TensorXf(img)

    def _frame(self, frame: int, channels: dict, spp: int, bad: int, seconds: float,
               reference: bool = False, fallback: int | None = None) -> Frame:
        cam = self.setup.camera(frame)
        prev = self._prev_camera(frame)
        meta = {
            "scene": self.setup.name,
            "spp": spp,
            "seed": self.seed,
            "max_depth": self.mitsuba_max_depth,
            "max_depth_from": self.max_depth_from,
            "rr_depth": self.rr_depth,
            "reference": reference,
            "nonfinite_samples": int(bad),
            "render_seconds": seconds,
            "variant": mi.variant(),
        }
        if self.shapes.any_anisotropic:
            meta["anisotropic"] = True
        if self._exclude:
            meta["primary_exclude"] = list(self._exclude)
            meta["primary_exclude_ids"] = [self._emitter_ids[i] for i in self._exclude]
            if self._exclude_on is not None:
                meta["exclude_on"] = list(self._exclude_on)
            if fallback is not None:
                meta["fallback_pixels"] = int(fallback)
        return Frame(channels=channels, camera=cam, prev_camera=prev, index=frame, meta=meta)
