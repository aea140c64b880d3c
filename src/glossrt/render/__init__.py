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
from ..jit import no_gc
from ..scenes import SceneSetup, _registry_id, emitter_kind, stable_emitters, stable_shapes
from . import integrator as _integrator  # noqa: F401  (registers "glossrt" per variant)
from .motion import MotionInputs
from .pathtracer import (
    RADIANCE_OUT,
    RR_DEPTH,
    UNBOUNDED_DEPTH,
    EmitterTable,
    ShapeTable,
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
           max_depth, jitter, normal_maps, primary, roughness=None, lobe_key=None):
    # ``normal_maps`` (= shapes.any_normal_map, which gbuffer() reads) is only a key of the
    # frozen function: a Python attribute of the ShapeTable is not part of dr.freeze's key.
    # ``primary``: None (one recording) or the primary-hit EmitterTable (another one; a new
    # exclusion set of the same scene replays it with the new table's values)
    # ``roughness``: None (one recording) or the per-pixel alpha of the primary hit's rough
    # lobes (another one, replayed with each frame's values); ``lobe_key``
    # (= shapes.lobe_key, which PrimaryLobe reads) is only a key, like ``normal_maps``
    out = trace_pixels(scene, sensor, shapes, emitters, table, motion_inputs, pixel, seed, width,
                       height, max_depth, jitter, primary, roughness)
    return {k: _flat(v) for k, v in out.items()}


def _new_frozen_trace():
    """A frozen :func:`_trace` of its own for each :class:`Renderer`. A module-wide one
    replayed a recording made with *another* scene object of the same layout (an equal
    ``dr.freeze`` key): wrong G-buffers and, now and then, a segfault once the first scene
    had been freed (measured 2026-11-23: a second ``coarse_polygon_light`` scene rendered
    frozen differed from its traced render; the crash of test_shadows that
    scripts/run-tests.sh reran). A Renderer keeps one scene, so its recordings only ever
    replay with that scene."""
    return dr.freeze(_trace, warn_after=64)


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
    (at most), a set used before replays its recording."""

    def __init__(self, setup: SceneSetup, max_depth: int | None = None, seed: int = 0,
                 frozen: bool = True, primary_exclude: Collection[int] = ()):
        self.setup = setup
        if max_depth is not None:
            md, self.max_depth_from = max_depth, "argument"
        elif setup.max_depth is not None:
            md, self.max_depth_from = setup.max_depth, setup.max_depth_from or "scene"
        else:
            md, self.max_depth_from = DEFAULT_MAX_DEPTH, "glossrt's default"
        try:
            self.max_depth = resolve_max_depth(int(md))
        except ValueError as e:
            raise GlossrtError(str(e)) from None
        self.seed = seed
        self.frozen = frozen
        self._trace_frozen = _new_frozen_trace()  # recordings never shared across scenes
        self.shapes = ShapeTable(setup.scene)
        #: emitters in a load-independent order for next-event estimation (reproducible noise)
        self.emitters = EmitterTable(setup.scene)
        self._primary: EmitterTable | None = None
        self._primary_tables: dict[tuple[int, ...], EmitterTable] = {}
        self._exclude: tuple[int, ...] = ()
        # ids of the emitters in stable_emitters order (the numbering primary_exclude uses),
        # ordered once: stable_emitters digests every non-area emitter's parameters
        self._emitter_ids = tuple(e.id() for e in stable_emitters(setup.scene))
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
        if exclude and exclude not in self._primary_tables:
            self._primary_tables[exclude] = EmitterTable(self.setup.scene, exclude)
        # a table kept per set: going back to an earlier set replays its recording (a new
        # table of equal values was measured to record once more, dr.freeze in drjit 1.5)
        self._primary = self._primary_tables[exclude] if exclude else None
        self._exclude = exclude

    # -- low level ---------------------------------------------------------------------
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
              max_depth: int | None = None) -> dict:
        """Poses ``frame`` and returns every channel (interleaved flat arrays) for the pixel
        indices ``pixel`` with per-lane (or one opaque) seed; primary rays pass through
        pixel centre + ``jitter`` (pixels, within ``[-jitter_limit, jitter_limit)``).
        ``roughness``: the primary hit's per-pixel alpha (see :meth:`render`), an opaque
        input of the frozen trace; ``max_depth``: this call's path depth (default the
        renderer's; 1: G-buffer and emission only)."""
        roughness = self._roughness(roughness)
        md = self.max_depth if max_depth is None else resolve_max_depth(int(max_depth))
        self.setup.set_frame(frame)
        frozen = self.frozen if frozen is None else frozen
        fn = self._trace_frozen if frozen else _trace
        jx, jy = _check_jitter(jitter, jitter_limit)
        # None: primary rays through the pixel centres, which then also give the motion
        # (a jittered frame traces one more ray per pixel, through its centre, for it)
        offset = (None if (jx, jy) == (0.0, 0.0)
                  else mi.Point2f(dr.opaque(mi.Float, jx), dr.opaque(mi.Float, jy)))
        with no_gc():
            out = fn(self.setup.scene, self.setup.sensor, self.shapes, self.emitters, self.table,
                     self._motion_inputs(frame), pixel, seed, self.width, self.height,
                     md, offset, self.shapes.any_normal_map, self._primary, roughness,
                     self.shapes.lobe_key if roughness is not None else None)
            dr.eval(out)
        return out

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
            return {k: np.array(v).reshape(idx.size, -1) for k, v in out.items()}
        base = frame_seed(frame, self.seed if seed is None else seed, PIXELS_SALT)
        lanes = np.repeat(idx, spp).astype(np.uint32)  # pixel-major
        sample = dr.arange(mi.UInt32, lanes.size) % spp
        seeds = mi.sample_tea_32(sample, dr.opaque(mi.UInt32, base), 4)[0]
        out = self.trace(frame, mi.UInt32(lanes), seeds, frozen=False)
        out.pop("nonfinite")
        res = {}
        for k, v in out.items():
            a = np.array(v).reshape(idx.size, spp, -1)
            res[k] = a.mean(axis=1) if k in RADIANCE_OUT or k == "color" else a[:, 0]
        return res

    # -- frames --------------------------------------------------------------------------
    def render(self, frame: int, seed: int | None = None,
               jitter: tuple[float, float] = (0.0, 0.0), jitter_limit: float = 0.5,
               roughness=None) -> Frame:
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
        ``"override"``."""
        w, h = self.width, self.height
        t0 = time.perf_counter()
        s = frame_seed(frame, self.seed if seed is None else seed)
        out = self.trace(frame, dr.arange(mi.UInt32, w * h), dr.opaque(mi.UInt32, s),
                         jitter=jitter, jitter_limit=jitter_limit, roughness=roughness)
        bad = int(out.pop("nonfinite")[0])
        channels = {k: mi.TensorXf(v, (h, w, COMPONENTS.get(k, 3))) for k, v in out.items()}
        f = self._frame(frame, channels, 1, bad, time.perf_counter() - t0)
        if tuple(jitter) != (0.0, 0.0):
            f.meta["jitter"] = [float(jitter[0]), float(jitter[1])]
        if roughness is not None:
            f.meta["primary_roughness"] = "override"
        return f

    def render_gbuffer(self, frame: int) -> Frame:
        """The G-buffer of frame ``frame`` alone (path depth 1: every G-buffer channel and
        the motion vectors exactly as :meth:`render` gives them, the emission seen by the
        camera, no other light): a cheap first pass whose G-buffer a per-pixel roughness
        (specular antialiasing) is computed from before :meth:`render` traces the light
        with it. Frozen like :meth:`render` (its own recording)."""
        w, h = self.width, self.height
        t0 = time.perf_counter()
        s = frame_seed(frame, self.seed)
        out = self.trace(frame, dr.arange(mi.UInt32, w * h), dr.opaque(mi.UInt32, s),
                         max_depth=1)
        bad = int(out.pop("nonfinite")[0])
        channels = {k: mi.TensorXf(v, (h, w, COMPONENTS.get(k, 3))) for k, v in out.items()}
        f = self._frame(frame, channels, 1, bad, time.perf_counter() - t0)
        f.meta["max_depth"] = 1
        return f

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
        done = 0
        t0 = time.perf_counter()
        while done < spp:
            kk = min(k, spp - done)
            lane = dr.arange(mi.UInt32, n_pix * kk)
            sample = lane % kk + done
            seeds = mi.sample_tea_32(sample, dr.opaque(mi.UInt32, base), 4)[0]
            out = self.trace(frame, lane // kk, seeds, frozen=False, roughness=roughness)
            bad += int(out["nonfinite"][0])
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
        f = self._frame(frame, channels, spp, bad, time.perf_counter() - t0, reference=True)
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
        integrator = mi.load_dict({"type": "path", "max_depth": md} if integrator == "path"
                                  else {"type": "direct"})
        img = mi.render(self.setup.scene, sensor=self.setup.sensor, integrator=integrator,
                        spp=spp, seed=frame_seed(frame, seed, 0xA11A5))
        return mi.TensorXf(img)

    def _frame(self, frame: int, channels: dict, spp: int, bad: int, seconds: float,
               reference: bool = False) -> Frame:
        cam = self.setup.camera(frame)
        prev = self._prev_camera(frame)
        meta = {
            "scene": self.setup.name,
            "spp": spp,
            "seed": self.seed,
            "max_depth": self.mitsuba_max_depth,
            "max_depth_from": self.max_depth_from,
            "rr_depth": RR_DEPTH,
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
        return Frame(channels=channels, camera=cam, prev_camera=prev, index=frame, meta=meta)
