"""The pipeline's stages: small objects with declared input and output channels (the
render-graph idea of Falcor, kept small). A stage reads the channels it declares in
``inputs`` from the frame's context and returns exactly the channels it declares in
``outputs`` (``H x W x C`` ``mi.TensorXf``); :class:`glossrt.pipeline.Pipeline` chains them
and checks both. Each stage keeps its own frozen kernels (``dr.freeze``): replacing a stage
(``Pipeline.configure``) records its kernels once more and leaves the others' recordings
alone.

Layers (docs/FORMATS.md, "Pipeline frames"):

* ``gbuffer`` -> the renderer's G-buffer and separated 1 spp radiance (schema channels),
  with the lights of an analytic ``direct`` stage removed at the primary hit;
* ``specaa`` -> the frame with its ``roughness`` filtered (:class:`SpecAAStage`; the
  material's in ``roughness_material``);
* ``direct`` -> ``direct``: the analytic direct light (0 with ``direct=pathtraced``);
* ``indirect`` -> ``indirect``: the denoised path-traced light beyond emission (indirect
  light, plus the direct light of every light the direct stage leaves to the path tracer);
* ``composite`` -> ``composite`` = ``emission + direct + indirect``;
* ``taa`` -> ``color`` (``composite`` reprojected and blended; ``composite`` when off).
"""

from __future__ import annotations

import hashlib
import os
import warnings

import drjit as dr
import numpy as np

from ..backend import mi
from ..errors import GlossrtError
from ..frame import Frame
from ..images import merge
from ..jit import no_gc, opaque
from ..render import DIRECT_OUT, INDIRECT_OUT

RADIANCE_PT = DIRECT_OUT + INDIRECT_OUT  # the path tracer's radiance channels
GUIDES = ("albedo_diffuse", "albedo_specular", "normal", "position", "depth", "roughness",
          "distribution", "mesh_id", "motion")


def _zeros(h: int, w: int, c: int = 3) -> mi.TensorXf:
    return dr.zeros(mi.TensorXf, (h, w, c))


def _with_channels(f: Frame, channels: dict, meta: dict | None = None) -> Frame:
    """``f``'s camera, previous camera and index with other ``channels`` (and ``meta``)."""
    return Frame(channels=channels, camera=f.camera, prev_camera=f.prev_camera, index=f.index,
                 meta=f.meta if meta is None else meta)


def _taken(ctx: dict, name: str) -> Frame:
    """Frame ``name`` taken out of ``ctx`` as this stage's own copy (the same channel
    arrays in a new Frame): the stage may drop channels from it without touching the frame
    its caller holds, and once the caller's context lets go, what it drops is freed."""
    f = ctx.pop(name)
    return _with_channels(f, dict(f.channels))


def _tensor(img) -> mi.TensorXf:
    if isinstance(img, mi.TensorXf):
        return img
    return mi.TensorXf(np.ascontiguousarray(np.asarray(img, np.float32)))


class Stage:
    """A pipeline stage: ``name``, the ``inputs`` it reads from the context and the
    ``outputs`` it returns from :meth:`run`; :meth:`reads` narrows an input frame down to
    the channels the stage reads (the pipeline frees what no later stage reads and the
    caller did not ask for: ``Pipeline.outputs``)."""

    name = ""
    inputs: tuple[str, ...] = ()
    outputs: tuple[str, ...] = ()
    #: milliseconds of the last run's work outside Dr.Jit, which no kernel history sees
    #: (the pipeline adds it to the stage's time: ``timing.StageClock.stage_done``)
    external_ms = 0.0

    def reads(self) -> dict[str, tuple[str, ...] | None]:
        """Input -> the channels of it this stage reads (a frame's channel names), None:
        all of it. Default: every input whole. A stage must not read a channel it does not
        list (tests/test_pipeline_outputs.py renders every preset with the fewest outputs
        against every output)."""
        return dict.fromkeys(self.inputs)

    def run(self, index: int, ctx: dict) -> dict:
        raise NotImplementedError

    def reset(self) -> None:
        """Drop what the stage keeps between frames (histories, accumulations)."""

    def frozen(self) -> list:
        """The ``dr.freeze`` functions this stage owns (to count their recordings)."""
        return []


# -- gbuffer -------------------------------------------------------------------------------


def check_scale(size: tuple[int, int], scale: int) -> None:
    """Refuse an ``indirect_scale`` that does not divide the image size (issue 25), before
    any work: one GlossrtError line naming both."""
    w, h = size
    if w % scale or h % scale:
        raise GlossrtError(f"indirect_scale={scale} does not divide the image size {w}x{h}: "
                           f"choose a size whose width and height are multiples of {scale}, "
                           "or another scale (1, 2 or 4)")


class ScaledSetup:
    """``setup``'s scene seen by a sensor of the same pose, field of view and clip planes at
    ``1/scale`` the size (the reduced-resolution indirect light). Posing goes through the
    full setup (its ``set_frame``, and so its animation or explicit pose); the sensor then
    copies the full sensor's ``to_world``. Everything else is the full setup's."""

    def __init__(self, setup, scale: int):
        check_scale(setup.size, scale)
        self._full = setup
        self.scale = int(scale)
        w, h = setup.size
        self.size = (w // scale, h // scale)
        sp = setup.sensor_params
        keys = sp.keys()
        self.sensor = mi.load_dict({
            "type": "perspective", "fov": setup.fov, "fov_axis": "x",
            "near_clip": float(sp["near_clip"]) if "near_clip" in keys else 1e-2,
            "far_clip": float(sp["far_clip"]) if "far_clip" in keys else 1e4,
            "to_world": mi.ScalarTransform4f(setup.rest_camera),
            "film": {"type": "hdrfilm", "width": self.size[0], "height": self.size[1],
                     "rfilter": {"type": "box"}, "pixel_format": "rgb"}})
        self.sensor_params = mi.traverse(self.sensor)

    def __getattr__(self, name):
        return getattr(self._full, name)

    def set_frame(self, frame: int) -> None:
        self._full.set_frame(frame)
        full = self._full.sensor_params
        self.sensor_params["to_world"] = full["to_world"]
        self.sensor_params["x_fov"] = full["x_fov"]  # an explicit field of view too
        self.sensor_params.update()

    def camera(self, frame: int):
        import dataclasses

        cam = self._full.camera(frame)
        return None if cam is None else dataclasses.replace(cam, resolution=self.size)


#: what the G-buffer stage's frames leave out (:meth:`glossrt.render.Renderer.render`'s
#: ``omit``): the path tracer's ``color`` (the pipeline's ``color`` is the composed image;
#: the indirect stage sums the radiance channels it denoises itself)
OMIT = ("color",)
#: and the specaa stage's G-buffer pass (the filter reads the G-buffer alone; its
#: ``direct_*`` and ``indirect_*`` are zero constants, path depth 1)
GBUFFER_PASS_OMIT = ("emission", "color")


class GBufferStage(Stage):
    """G-buffer plus 1 spp path tracing (:class:`glossrt.render.Renderer`), or with
    ``accumulate`` the running mean of converged estimates (``spp`` per frame) while the
    scene holds still. ``exclude``: emitter indices the analytic direct stage shades
    (removed from the path tracer at the primary hit only), on the shapes ``exclude_on``
    (mesh ids; None: all; :class:`glossrt.pipeline.plan.DirectPlan`).

    ``indirect_scale`` 2 or 4 (issue 25; Tokuyoshi 2015's pipeline, sec. 3): the
    full-resolution renderer traces the G-buffer and the direct light only
    (``Renderer(primary_only=True)``: NEE and the BSDF-sampled emitter hit at the primary
    vertex, within the scene's path depth), and a second renderer
    traces the indirect light at ``1/scale`` the size (``frame_low``: its own low-resolution
    G-buffer, every emitter excluded at its primary hit so that it holds the indirect light
    alone, bit-identical to a full-depth render's). Its primary rays are jittered by
    :func:`glossrt.denoise.upsampling.jitter_sequence` (recorded in ``meta["jitter"]``,
    where the upsamplers put the samples), a cycle over the ``scale^2`` full-resolution
    pixel centres of a low-resolution pixel.

    Memory (issue 25): the frames hold no buffer for the channels that are 0 by
    construction (:meth:`glossrt.render.Renderer.zero_channels`: the full-resolution
    frame's ``indirect_*`` (its primary hit's light alone), ``direct_*`` when every emitter
    is excluded, as in the low-resolution frame; zero constants instead) nor for the path
    tracer's ``color`` (:data:`OMIT`); frames of more than ``Renderer.tile_pixels`` pixels
    are traced in row tiles.

    ``specaa`` (set by the pipeline: its :class:`SpecAAStage`): when that stage filters,
    the frame is traced in two passes so that the path tracer's primary hit sees the
    filtered roughness (issue 25): a G-buffer pass (:meth:`glossrt.render.Renderer.
    render_gbuffer`, path depth 1), the specaa stage's frozen filter on it
    (:meth:`SpecAAStage.filter`), then the light traced with that roughness at the primary
    hit (``Renderer.render(roughness=...)``, an opaque input of the frozen trace: no
    re-recording across frames or poses). The low-resolution indirect light reads it at the
    full-resolution pixel centre each low-resolution sample lands on (the jitter cycle), the
    accumulated reference (``accumulate``) traces with it too. The G-buffer of both passes
    is the same (pixel-centre primary rays), so the filtered roughness is the current
    frame's, not a reprojection of the previous one."""

    name = "gbuffer"
    outputs = ("frame",)

    def __init__(self, setup, opts: dict, exclude: tuple[int, ...] = (),
                 exclude_on: tuple[int, ...] | None = None):
        from .. import render

        self.scale = int(opts.get("indirect_scale", 1))
        self.low = None
        md = opts["max_depth"]
        if self.scale > 1:
            if opts["accumulate"]:
                raise GlossrtError("accumulate=true traces the converged reference at full "
                                   "resolution: use indirect_scale=1")
            low_setup = ScaledSetup(setup, self.scale)
            n = len(setup.scene.emitters())
            self.low = render.Renderer(low_setup, max_depth=md, seed=opts["seed"] + 1,
                                       primary_exclude=tuple(range(n)))
            md = self.low.mitsuba_max_depth  # (the scene's, or the option's)
            self.outputs = ("frame", "frame_low")
        # at scale 2 or 4 the full-resolution frame holds the primary hit's light alone
        # (the light of its next-event estimation and of its BSDF sample's emitter hit)
        self.renderer = render.Renderer(setup, max_depth=md, seed=opts["seed"],
                                        primary_exclude=tuple(exclude),
                                        exclude_on=exclude_on, primary_only=self.scale > 1)
        self.setup = setup
        self.exclude = tuple(exclude)
        self.exclude_on = exclude_on
        self.accumulate = bool(opts["accumulate"])
        self.spp = int(opts["spp"])
        self.seed = int(opts["seed"])
        self.specaa: SpecAAStage | None = None
        #: TAA's sub-pixel jitter of the full-resolution primary rays (set by the pipeline:
        #: ``taa`` and ``taa_jitter``; :func:`glossrt.denoise.taa_jitter`); not while
        #: accumulating the converged reference, which traces pixel centres
        self.jitter = False
        #: what the frames leave out: :data:`OMIT`, and on isotropic scenes the anisotropy
        #: channels (``tangent``, ``roughness_uv``: no stage reads them there; 48 MiB at
        #: 1920x1080)
        self._aniso_omit = (() if self.renderer.shapes.any_anisotropic
                            else render.pathtracer.ANISOTROPY_OUT)
        self.omit = OMIT + self._aniso_omit
        self.reset()

    def reset(self) -> None:
        self._sum: dict | None = None
        self._n = 0
        self._pose = None
        self._passes = 0

    def set_exclude(self, exclude: tuple[int, ...], exclude_on: tuple[int, ...] | None) -> None:
        """Another set of analytically shaded lights and the shapes they are shaded on (the
        renderer's ``primary_exclude`` and ``exclude_on``; a set not used before records
        the frozen trace once more)."""
        self.renderer.set_exclusion(exclude, exclude_on)
        self.exclude, self.exclude_on = tuple(exclude), exclude_on

    def frozen(self) -> list:
        low = self.low.frozen_functions() if self.low is not None else []
        return self.renderer.frozen_functions() + low

    def _filtered_roughness(self, index: int, jitter):
        """The specaa stage's filtered roughness of frame ``index`` from a G-buffer pass
        through the same rays as the light pass (None when no specaa stage filters)."""
        spec = self.specaa
        if spec is None or not spec.filters:
            return None
        return spec.filter(self.renderer.render_gbuffer(
            index, omit=GBUFFER_PASS_OMIT + self._aniso_omit, jitter=jitter))

    def _jitter(self, index: int) -> tuple[float, float]:
        if not self.jitter or self.accumulate:
            return (0.0, 0.0)
        from ..denoise import taa_jitter

        return taa_jitter(index)

    def run(self, index: int, ctx: dict) -> dict:
        jitter = self._jitter(index)
        alpha = self._filtered_roughness(index, jitter)
        if self.low is not None:
            from ..denoise.upsampling import jitter_sequence

            # the motion vectors' previous pose, when the pipeline sets one (explicit posing)
            self.low.previous_pose = getattr(self.renderer, "previous_pose", None)
            f = self.renderer.render(index, jitter=jitter, roughness=alpha, omit=self.omit)
            jit = jitter_sequence(self.scale, index)
            low_alpha = None
            if alpha is not None:  # the full-resolution pixel each low sample lands on
                k = index % (self.scale * self.scale)
                i, j = k % self.scale, k // self.scale
                low_alpha = alpha[j::self.scale, i::self.scale]
            low = self.low.render(index, jitter=jit, roughness=low_alpha, omit=self.omit)
            # the full frame's light: emission and direct from it, the indirect light from
            # the low-resolution frame (the indirect stage upsamples it)
            f.meta["max_depth"] = low.meta["max_depth"]
            f.meta["max_depth_from"] = low.meta["max_depth_from"]
            f.meta["indirect_scale"] = self.scale
            return {"frame": f, "frame_low": low}
        if not self.accumulate:
            return {"frame": self.renderer.render(index, jitter=jitter, roughness=alpha,
                                                  omit=self.omit)}
        pose = index if self.setup.animated else 0
        if pose != self._pose:
            self.reset()
            self._pose = pose
        f = self.renderer.render_reference(index, self.spp,
                                           seed=self.seed + 7919 * self._passes,
                                           roughness=alpha)
        self._passes += 1
        names = ("emission",) + RADIANCE_PT + ("color",)
        if self._sum is None:
            self._sum = {k: f[k] for k in names}
        else:
            self._sum = {k: self._sum[k] + f[k] for k in names}
        self._n += self.spp
        share = self.spp / self._n
        for k in names:  # the running mean: sum of the per-pass means x (spp / total)
            f[k] = self._sum[k] * share
        f.meta["spp"] = self._n
        return {"frame": f}


# -- specaa ----------------------------------------------------------------------------------


def _specaa_kernel(ch: dict, cam: list, method, size: tuple[int, int]) -> mi.TensorXf:
    """The filtered isotropic alpha per pixel (H, W, 1): :func:`glossrt.specaa.
    filtered_roughness` of ``method`` (Kaplanyan et al. 2016 / Tokuyoshi eq. 2:
    ``alpha'^2 = min(alpha^2 + K, 1)``), an anisotropic result reduced to
    ``sqrt(lambda_max(A))`` (:func:`glossrt.specaa.isotropic_alpha`); the material's
    roughness where no surface was hit."""
    from ..lights.shading import ShadingPoints
    from ..specaa.filters import _quad, filtered_roughness, isotropic_alpha

    h, w = size
    sp = ShadingPoints.at_camera(ch, cam)
    q = _quad(ch, sp, mi.Point3f(*cam), size, False)
    a = filtered_roughness(q, method)
    alpha = dr.select(sp.hit, isotropic_alpha(*a), sp.alpha)
    return mi.TensorXf(alpha, (h, w, 1))


class SpecAAStage(Stage):
    """Specular antialiasing of the G-buffer's roughness (:mod:`glossrt.specaa`, Kaplanyan
    et al. 2016 as evaluated by Tokuyoshi; ``projected``: Tokuyoshi & Kaplanyan 2021): the
    frame's ``roughness`` channel becomes the filtered isotropic alpha per pixel, which every
    later reader of the frame sees: the analytic ``direct`` stage (LTC, BSPVT, ratio,
    highlights, point and directional lights) and the lobe weights of ``svgf-lobe`` and of
    the lobe upsampling (at the full-resolution target pixels; a reduced-resolution
    ``frame_low`` keeps its material roughness channel). The material's roughness stays in
    ``roughness_material``.

    The path tracer's primary hit sees the filtered roughness too (environment maps,
    path-traced direct light, the first bounce of the indirect light): the ``gbuffer``
    stage runs this stage's :meth:`filter` on a G-buffer pass of the same frame and traces
    the light with it (:class:`GBufferStage`); rough conductors and rough plastics' specular
    lobe take it (:class:`glossrt.render.pathtracer.PrimaryLobe`), other BSDFs keep their
    own. :meth:`run` then reuses that roughness rather than filtering again.
    ``method="none"``: the frame passes through untouched (no ``roughness_material``).
    Frozen (``dr.freeze``) per pipeline."""

    name = "specaa"
    inputs = ("frame",)
    outputs = ("frame",)

    def __init__(self, method: str):
        from ..specaa import parse_method

        self.spec = method
        self.method = parse_method(method)
        self._fn = (dr.freeze(_specaa_kernel, warn_after=16)
                    if self.method.source != "none" else None)
        self._pending: mi.TensorXf | None = None

    @property
    def filters(self) -> bool:
        """Whether this stage filters the roughness (``method`` is not ``none``)."""
        return self._fn is not None

    def frozen(self) -> list:
        return [self._fn] if self._fn is not None else []

    def reset(self) -> None:
        self._pending = None

    def filter(self, gb: Frame) -> mi.TensorXf:
        """The filtered isotropic alpha (H, W, 1) of the G-buffer ``gb`` (frozen); the next
        :meth:`run` uses it for its frame (the same G-buffer, traced with it)."""
        from ..lights.shading import f0_tensor, shading_channels

        ch = shading_channels(gb)
        ch["f0"] = f0_tensor(gb, None)  # (the roughness does not depend on F0)
        with no_gc():
            alpha = self._fn(ch, opaque(gb.camera.position), self.method,
                             (gb.height, gb.width))
            dr.eval(alpha)
        self._pending = alpha
        return alpha

    def run(self, index: int, ctx: dict) -> dict:
        gb: Frame = ctx["frame"]
        if self._fn is None:
            return {"frame": gb}
        alpha = self._pending
        self._pending = None
        if alpha is None or gb.meta.get("primary_roughness") != "override":
            alpha = self.filter(gb)  # a frame traced without it (the stage used alone)
            self._pending = None
        channels = dict(gb.channels)
        channels["roughness_material"] = gb["roughness"]
        channels["roughness"] = alpha
        meta = dict(gb.meta)
        meta["specaa"] = self.spec
        return {"frame": _with_channels(gb, channels, meta)}


# -- direct -----------------------------------------------------------------------------------


def _points_kernel(ch: dict, cam: list, lights: list, scene, size: tuple[int, int]):
    """Point and directional lights with one shadow ray each: ``E f cos`` (Lambert + the
    pixel's microfacet lobe, :func:`glossrt.lights.shading.brdf_cos`; ``E = I / d^2`` or the
    irradiance, :func:`glossrt.lights.analytic.incident`) where the ray from the surface
    towards the light reaches it."""
    from ..lights.analytic import incident
    from ..lights.shading import ShadingPoints, brdf_cos

    h, w = size
    sp = ShadingPoints.at_camera(ch, cam)
    total = dr.zeros(mi.Color3f, h * w)
    eps = 1e-4 * (1.0 + dr.maximum(dr.abs(sp.p.x), dr.maximum(dr.abs(sp.p.y),
                                                                dr.abs(sp.p.z))))
    for light in lights:
        wi, e = incident(light, sp.p)
        d, s = brdf_cos(sp, wi)
        if light[0] == "point":
            maxt = dr.norm(light[1] - sp.p) * (1.0 - 1e-4) - eps
        else:
            maxt = dr.largest(mi.Float) + dr.zeros(mi.Float, h * w)
        side = dr.select(dr.dot(sp.n, wi) >= 0, 1.0, -1.0)
        o = sp.p + sp.n * (eps * side)
        ray = mi.Ray3f(o, wi)
        ray.maxt = dr.maximum(maxt, 0.0)
        active = sp.hit & (dr.squared_norm(wi) > 0)
        blocked = scene.ray_test(ray, active)
        total += dr.select(active & ~blocked, e * (d + s), 0.0)
    return merge([total[0], total[1], total[2]], h, w)


class PointLights:
    """The scene's point and directional lights shaded analytically, one shadow ray each
    (frozen per pipeline: the scene is an argument, the lights opaque). The lights are read
    from the posed scene every frame (:func:`glossrt.lights.analytic.analytic_lights`), so a
    point light moved by ``Pipeline.set_transform`` (its emitter's ``position`` parameter,
    which the path tracer reads too) is shaded where it is, with no re-recording."""

    def __init__(self, setup):
        self.setup = setup
        self._fn = dr.freeze(_points_kernel, warn_after=16)

    def __call__(self, gb: Frame, lights: list, f0) -> mi.TensorXf:
        from ..lights.analytic import device_lights
        from ..lights.shading import f0_tensor, shading_channels

        ch = shading_channels(gb)
        ch["f0"] = f0_tensor(gb, f0)
        with no_gc():
            out = self._fn(ch, opaque(gb.camera.position), device_lights(lights),
                           self.setup.scene, (gb.height, gb.width))
            dr.eval(out)
        return out


#: BSPVT trees, built on first use, keyed by the scene's geometry (vertex positions and
#: faces of its non-emitting meshes, the analytic occluders' boxes) and the resolution
_TREES: dict = {}
_TREES_MAX = 4
#: trees built by :func:`scene_trees` in this process (a cache hit, in memory or on disk,
#: builds none)
BUILDS = {"count": 0}
#: tree cache folders found unwritable in this process (each is warned about once)
_UNWRITABLE: set = set()


def default_bspvt_cache() -> str:
    """The user's cache folder for built BSPVT trees: ``$XDG_CACHE_HOME/glossrt/bspvt``, else
    (unset, empty or relative, as the XDG base directory specification says)
    ``~/.cache/glossrt/bspvt``. Read when a pipeline is made; created when the first trees
    are written."""
    base = os.environ.get("XDG_CACHE_HOME", "")
    if not os.path.isabs(base):
        base = os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "glossrt", "bspvt")


def bspvt_cache_dir(cache: bool | str | os.PathLike | None) -> str | None:
    """The folder ``Pipeline(bspvt_cache=...)`` keeps built trees in: ``True`` the user's
    cache folder (:func:`default_bspvt_cache`); ``False`` or ``None`` none (trees are kept in
    memory only); a path that folder (made when the first trees are written). A path that
    exists and is not a folder, or any other value, is one :class:`GlossrtError`."""
    if cache is True:
        return default_bspvt_cache()
    if cache is False or cache is None:
        return None
    if isinstance(cache, str | os.PathLike) and os.fspath(cache):
        folder = os.fspath(cache)
        if os.path.exists(folder) and not os.path.isdir(folder):
            raise GlossrtError(f"bspvt_cache: {folder} exists and is not a folder")
        return folder
    raise GlossrtError("bspvt_cache must be a folder, True (the user's cache folder) or False "
                       f"(no cache on disk), got {cache!r}")


def geometry_key(scene, resolution: int) -> str:
    """A digest of what BSPVT's visibility depends on: the non-emitting meshes' vertices and
    faces (their ids and order), the analytic occluders' bounds, and the resolution. Lights
    are not occluders (moving one keeps the trees); moving an occluder changes the key."""
    from ..lights.bspvt.scene import occluder_bounds, scene_meshes

    h = hashlib.sha1(f"bspvt-v1 {int(resolution)}".encode())
    for m in scene_meshes(scene):
        h.update(m.id().encode() + b"\0")
        h.update(np.asarray(m.vertex_positions_buffer(), np.float32).tobytes())
        h.update(np.asarray(m.faces_buffer(), np.uint32).tobytes())
    h.update(repr(occluder_bounds(scene)).encode())
    return h.hexdigest()


def _read_cached(scene, resolution: int, path: str):
    """The trees in cache file ``path`` if they fit ``scene`` at ``resolution``, else None
    (no file, or one damaged, of another format version, or stale: built anew)."""
    from ..lights.bspvt import BSPVT, match_scene

    if not os.path.isfile(path):
        return None
    try:
        trees = BSPVT.load(path)
        if int(trees.resolution) != int(resolution):
            return None
        match_scene(scene, trees)
    except GlossrtError:
        return None
    return trees


def _write_cached(trees, folder: str, path: str) -> None:
    """Keep ``trees`` in cache file ``path`` (made in ``folder`` if need be), written whole or
    not at all (:meth:`glossrt.lights.bspvt.BSPVT.save`: a temporary file renamed over
    ``path``, so a process reading it meanwhile sees the old file or the new one). A folder
    that cannot be made or written is warned about once per process; the trees stay in
    memory."""
    try:
        os.makedirs(folder, exist_ok=True)
        trees.save(path)
    except OSError as e:
        if folder not in _UNWRITABLE:
            _UNWRITABLE.add(folder)
            warnings.warn(f"BSPVT trees not cached on disk: cannot write to {folder} "
                          f"({e.strerror or e}); kept in memory for this process only "
                          "(--bspvt-cache DIR or bspvt_cache=DIR chooses another folder, "
                          "none turns the cache off)", stacklevel=2)
        return
    trees.source = path


def scene_trees(scene, resolution: int, progress: bool = True,
                cache_dir: str | os.PathLike | None = None):
    """BSPVT trees of ``scene`` as it is posed now: cached in memory per
    :func:`geometry_key`; with ``cache_dir`` also on disk (``bspvt-<key>.npz``, read back by
    later processes and checked against the scene: a damaged or stale file is built anew and
    replaced); built with a progress bar on a miss (:data:`BUILDS` counts the builds). A
    folder that cannot be written costs a warning, never the trees."""
    from ..lights.bspvt import build_scene_trees

    key = geometry_key(scene, resolution)
    if key in _TREES:
        return _TREES[key]
    folder = os.fspath(cache_dir) if cache_dir else None
    path = os.path.join(folder, f"bspvt-{key[:20]}.npz") if folder else None
    trees = _read_cached(scene, resolution, path) if path is not None else None
    if trees is None:
        trees = build_scene_trees(scene, resolution, progress=progress)
        BUILDS["count"] += 1
        if path is not None:
            _write_cached(trees, folder, path)
    if len(_TREES) >= _TREES_MAX:
        _TREES.pop(next(iter(_TREES)))
    _TREES[key] = trees
    return trees


def _mask_kernel(img: mi.TensorXf, mesh_id: mi.TensorXf, table: mi.Bool) -> mi.TensorXf:
    """``img`` (H, W, 3) where the pixel's mesh id is marked in ``table`` (per mesh id), 0
    elsewhere (a NaN there too)."""
    h, w = img.shape[0], img.shape[1]
    ids = mi.UInt32(mesh_id.array)
    keep = dr.gather(mi.Bool, table, ids)
    lane = dr.arange(mi.UInt32, h * w * 3)
    on = dr.gather(mi.Bool, keep, lane // 3)
    return mi.TensorXf(dr.select(on, img.array, 0.0), (h, w, 3))


class DirectStage(Stage):
    """The direct light of the scene's lights (module docstring): ``pathtraced`` (0 here:
    the 1 spp estimate stays in the path-traced layers and is denoised with the rest), ``ltc``
    (Heitz et al. 2016, unshadowed), ``ltc+bspvt`` (Okuno & Iwasaki, eq. 2), ``ltc+ratio``
    (Heitz, Hill & McGuire 2018) or ``highlights`` (Kimura & Tokoi for the specular part,
    LTC for the diffuse part). Point and directional lights: analytic with shadow rays
    whenever the mode is not ``pathtraced``.

    ``plan`` (:class:`glossrt.pipeline.plan.DirectPlan`) says which lights each method shades
    (under ``ltc+bspvt`` some polygon lights may take the ratio estimator) and on which
    surfaces: the image is 0 on every other pixel (the path tracer lights those with every
    emitter)."""

    name = "direct"
    inputs = ("frame",)
    outputs = ("direct",)

    def __init__(self, setup, opts: dict, mode: str, progress: bool = True, trees=None,
                 cache_dir=None, plan=None):
        from .plan import LightsAt
        from .plan import plan as make_plan

        self.setup = setup
        self.mode = mode
        self.opts = opts
        if plan is None:
            from ..render.pathtracer import ShapeTable

            plan = make_plan(setup, mode, ShapeTable(setup.scene))
        self.plan = plan
        self._lights = LightsAt(setup)  # the lights it shades, posed each frame
        analytic = mode != "pathtraced"
        self.points = PointLights(setup) if analytic and plan.points else None
        self.trees = None
        if mode == "ltc+bspvt" and plan.bspvt and plan.bspvt_shapes:  # prebuilt or cached
            self.trees = trees if trees is not None else scene_trees(
                setup.scene, int(opts["bspvt_resolution"]), progress, cache_dir)
        #: the frame's material image (fresnel_image) on the device, and BSPVT's frozen
        #: shading of the whole frame (lights.bspvt.scene.FrozenShader)
        self.materials = None
        self.bspvt = None
        if analytic:
            from ..lights.bspvt.scene import FrozenShader, MaterialImage

            self.materials = MaterialImage(setup.scene)
            if self.trees is not None:
                self.bspvt = FrozenShader(setup.scene, self.trees, opts["bspvt_mode"],
                                          materials=self.materials.table)
        self.highlights = None
        if mode == "highlights" and plan.polygons:
            from ..lights.highlights import HighlightRenderer

            self.highlights = HighlightRenderer(
                samples=int(opts["highlight_samples"]),
                distribution=opts.get("highlight_distribution", "ellipsoidal"),
                sampling="hash", cull=False, frozen=True)
        # the surfaces the analytic methods shade (mesh ids; 0 the background): a mask only
        # where some are left to the path tracer
        self._mask_table = None
        self._mask_fn = None
        self._trees_table = self._ratio_table = None
        if analytic and len(plan.shapes) < plan.n_shapes:
            self._mask_table = self._table(plan.shapes)
        if self.bspvt is not None and plan.bspvt_ratio:
            # the BSPVT lights' shading on the surfaces the trees cover, the ratio
            # estimator's on the others (plan.bspvt_ratio)
            self._trees_table = self._table(set(plan.shapes) - set(plan.bspvt_ratio))
            self._ratio_table = self._table(plan.bspvt_ratio)
        if self._mask_table is not None or self._trees_table is not None:
            self._mask_fn = dr.freeze(_mask_kernel, warn_after=16)
        #: the highlights' light maps and what they were built from (:meth:`_highlights`)
        self._maps = None
        self._maps_key = None
        #: light-map builds so far (a frame whose lights and objects hold still builds none)
        self.map_builds = 0
        self._textures: dict = {}
        #: one array per distinct light texture (digest of its texels): the ids that key
        #: ``_textures`` (:meth:`_stable_textures`)
        self._stable: dict = {}

    def _table(self, mesh_ids) -> mi.Bool:
        """A per-mesh-id mask (0: the background) marking ``mesh_ids``."""
        table = np.zeros(self.plan.n_shapes + 1, bool)
        table[list(mesh_ids)] = True
        out = mi.Bool(table)
        dr.make_opaque(out)
        return out

    def _masked(self, img: mi.TensorXf, gb: Frame, table: mi.Bool) -> mi.TensorXf:
        with no_gc():
            return self._mask_fn(img, gb["mesh_id"], table)

    @property
    def shades(self) -> bool:
        """Whether the stage shades anything (an analytic mode with some analytic light)."""
        return self.mode != "pathtraced" and bool(self.plan.polygons or self.plan.points)

    def reads(self) -> dict[str, tuple[str, ...] | None]:
        return {"frame": None} if self.shades else {}

    def frozen(self) -> list:
        out = [self.points._fn] if self.points is not None else []
        if self.materials is not None:
            out.append(self.materials._fn)
        if self.bspvt is not None:
            out += self.bspvt.frozen()
        # the polygon lights' shading kernels (module-wide frozen functions, shared with
        # every other user of LTC / BSPVT shading in the process)
        if self.mode in ("ltc", "highlights") and self.plan.polygons:
            from ..lights.ltc import shade as ltc_shade

            out.append(ltc_shade._shade_frozen)
        if self.highlights is not None:
            out += [self.highlights._frozen_grid]
        if self._mask_fn is not None:
            out.append(self._mask_fn)
        return out

    def run(self, index: int, ctx: dict) -> dict:
        gb: Frame = ctx["frame"]
        h, w = gb.height, gb.width
        if not self.shades:
            return {"direct": _zeros(h, w)}
        plan = self.plan
        if gb.meta.get("anisotropic"):
            # the isotropic methods refuse such frames; here the anisotropic shapes are not
            # among the plan's (their pixels are the path tracer's, masked out below)
            gb = _with_channels(gb, gb.channels,
                                {k: v for k, v in gb.meta.items() if k != "anisotropic"})
        ratio = plan.polygons if self.mode == "ltc+ratio" else \
            plan.ratio if self.mode == "ltc+bspvt" else ()
        # every light the frame shades, posed once
        lights = self._lights((*plan.points, *plan.polygons, *plan.bspvt, *ratio), index)

        def posed(indices):
            return [lights[k] for k in indices]

        points = posed(plan.points)
        # every pixel's material (lights.shading.fresnel_image, 16 floats a pixel), computed
        # on the device where it is read: BSPVT's vertex mode reads the vertices' instead
        # (FrozenShader takes the MaterialImage and calls it only when it needs it)
        f0 = (self.materials(gb) if self.mode != "ltc+bspvt" or points or plan.ratio
              or plan.bspvt_ratio else None)
        out = None
        if self.mode in ("ltc", "highlights") and plan.polygons:
            polys = self._stable_textures(posed(plan.polygons))
            if self.mode == "ltc":
                out = self._ltc(gb, polys, f0)
            else:  # highlights: Kimura & Tokoi's specular + LTC's diffuse
                out = (self._ltc_diffuse(gb, polys, f0)
                       + self._highlights(gb, index, polys, f0))
        if self.bspvt is not None and plan.bspvt:
            polys = self._stable_textures(posed(plan.bspvt))
            out = self.bspvt(gb, polys, self.materials if f0 is None else f0,
                             textures=self._textures)
            if self._trees_table is not None:  # the surfaces the trees do not cover
                out = (self._masked(out, gb, self._trees_table)
                       + self._masked(self._ratio(gb, polys, f0, index), gb, self._ratio_table))
        if ratio:
            polys = self._stable_textures(posed(ratio))
            img = self._ratio(gb, polys, f0, index)
            out = img if out is None else out + img
        if points:
            img = self.points(gb, points, f0)
            out = img if out is None else out + img
        if out is None:
            out = _zeros(h, w)
        if self._mask_table is not None:
            out = self._masked(out, gb, self._mask_table)
        return {"direct": out}

    def _ratio(self, gb: Frame, polys: list, f0, index: int) -> mi.TensorXf:
        """The ratio estimator's direct light of ``polys`` (Heitz, Hill & McGuire 2018)."""
        from ..lights.ratio import render_ratio

        return _tensor(render_ratio(gb, polys, self.setup.scene, spp=self.opts["ratio_spp"],
                                    f0=f0, seed=index, textures=self._textures).image)

    def _stable_textures(self, polys: list) -> list:
        """``polys`` with each light texture replaced by the array this stage already holds
        for the same texels. ``polygon_lights`` reads a new array every frame, and the
        prefiltered-texture cache (``self._textures``, :func:`glossrt.lights.ltc.shade.
        prefiltered`) is keyed by the array's id: without this every frame rebuilt each
        textured light's mip chain (0.1-0.7 s, and twice per light under ``ltc+ratio``), and
        a new array that reused a freed one's id could have been shaded with the other's."""
        for lt in polys:
            tex = getattr(lt, "texture", None)
            if tex is None:
                continue
            a = np.ascontiguousarray(tex)
            key = hashlib.sha1(a.tobytes()).hexdigest() + str(a.shape) + str(a.dtype)
            if key not in self._stable:
                if len(self._stable) >= 64:  # (both caches start over)
                    self._stable.clear()
                    self._textures.clear()
                self._stable[key] = a
            lt.texture = self._stable[key]
        return polys

    def _ltc(self, gb: Frame, polys: list, f0) -> mi.TensorXf:
        from ..lights.ltc import shade_tensor

        if not polys:
            return _zeros(gb.height, gb.width)
        return shade_tensor(gb, polys, f0=f0, textures=self._textures, frozen=True)

    def _ltc_diffuse(self, gb: Frame, polys: list, f0) -> mi.TensorXf:
        """LTC's diffuse part: the full shading minus the shading without diffuse albedo."""
        total = self._ltc(gb, polys, f0)
        ch = dict(gb.channels)
        ch["albedo_diffuse"] = _zeros(gb.height, gb.width)
        spec = self._ltc(_with_channels(gb, ch), polys, f0)
        return dr.maximum(total - spec, 0.0)

    def _highlights(self, gb: Frame, index: int, polys: list, f0) -> mi.TensorXf:
        """Kimura & Tokoi's highlights (sec. 5.2: the light environment map sampled in the
        view's mirror directions about microfacet normals drawn from D_s, sec. 4.1, weighted
        by G = min(1, G_m, G_s), sec. 4.2), through light maps at ``highlight_probes`` probes
        per object (:func:`glossrt.lights.highlights.envmap.probe_grids`; 1: the paper's one
        map per object, sec. 3). The maps are world-space (directions from a fixed probe, the
        lights only): they depend on the lights (vertices, radiance, texture) and on the
        probes (the objects' bounding boxes), not on the camera, so they are rebuilt only
        when those change (:func:`highlight_maps_key`). The shading replays one frozen
        kernel."""
        from ..lights.highlights.envmap import probe_grids

        grids = probe_grids(self.setup, int(self.opts["highlight_probes"]))
        key = highlight_maps_key(polys, grids, self.highlights.resolution,
                                 self.highlights.supersample)
        if key != self._maps_key:
            self._maps = self.highlights.grid_maps(self.setup, index, polys, grids=grids)
            self._maps_key = key
            self.map_builds += 1
        return self.highlights.shade_tensor(gb, self._maps, f0, index)


def highlight_maps_key(polys: list, grids: dict, resolution: int, supersample: int) -> str:
    """A digest of what the highlights' light maps depend on: every polygon light's vertices,
    radiance, sidedness, texture and uv, the probe points per object, the map resolution and
    supersampling. The camera is not in it (the maps are world-space)."""
    h = hashlib.sha1(f"highlights-v1 {int(resolution)} {int(supersample)}".encode())
    for lt in polys:
        h.update(np.asarray(lt.vertices, np.float64).tobytes())
        h.update(np.asarray(lt.radiance, np.float64).tobytes())
        h.update(b"2" if getattr(lt, "two_sided", False) else b"1")
        tex = getattr(lt, "texture", None)
        if tex is not None:
            h.update(np.ascontiguousarray(tex, np.float32).tobytes())
            h.update(np.asarray(lt.uv, np.float64).tobytes())
        h.update(b"|")
    for k in sorted(grids):
        h.update(f"{k}:".encode() + np.asarray(grids[k].points, np.float64).tobytes())
    return h.hexdigest()


# -- indirect ---------------------------------------------------------------------------------


def filter_params(opts: dict) -> dict:
    """The SVGF parameters the pipeline's options set (Schied et al. 2017: the colour
    average's ``alpha``, sec. 4.1; the edge-stopping ``sigma_z``, ``sigma_n``, ``sigma_l``,
    sec. 4.4, eqs. 3-5) and Tokuyoshi 2015's lobe weight parameters ``beta``, ``kappa``
    (sec. 4.2; read by ``svgf-lobe`` and the lobe-weighted upsamplers)."""
    from .config import DEFAULTS

    o = {**DEFAULTS, **opts}
    return {"alpha": float(o["svgf_alpha"]), "sigma_z": float(o["svgf_sigma_z"]),
            "sigma_n": float(o["svgf_sigma_n"]), "sigma_l": float(o["svgf_sigma_l"]),
            "beta": float(o["lobe_beta"]), "kappa": float(o["lobe_kappa"])}


def _denoiser(method: str, **params):
    """The frozen filter of ``method`` (None for ``none`` and ``oidn``)."""
    from ..denoise import SVGF

    if method == "svgf":
        return SVGF(**params)
    if method == "svgf-lobe":
        return SVGF(weights="lobe", **params)
    if method == "atrous":
        return SVGF(temporal=False, spatial="dammertz", **params)
    return None


#: the low-resolution frame's channels the upsamplers read besides the light
LOW_GUIDES = ("normal", "depth", "mesh_id", "roughness", "distribution")
INDIRECT_PT = INDIRECT_OUT
DIRECT_PT = DIRECT_OUT


class IndirectStage(Stage):
    """The path-traced light beyond emission, denoised: ``svgf`` (Schied et al. 2017),
    ``svgf-lobe`` (SVGF with Tokuyoshi 2015's specular-lobe weights), ``atrous`` (Dammertz
    et al. 2010, frozen), ``oidn`` or ``none`` (the raw estimate). The denoiser sees the
    frame with its emission set to 0 (the composite adds the noise-free primary-hit
    emission), so its output is exactly this layer.

    ``indirect_scale`` 2 or 4 (inputs ``frame`` and ``frame_low``, :class:`GBufferStage`):
    Tokuyoshi 2015's pipeline (sec. 3: filter or upsample the albedo-demodulated indirect
    light, remodulate, add the direct light). The low-resolution indirect light is denoised
    at its own resolution (the SVGF filters give their demodulated signals,
    ``output="illumination"``), then upsampled to the full G-buffer
    (:mod:`glossrt.denoise.upsampling`): ``joint-bilateral`` (Tokuyoshi eq. 1 with Kopf
    et al. 2007's spatial Gaussian on the low grid) or ``spatio-temporal`` (Herzog et al.
    2010, sec. 5.3 / fig. 7), with the ``normal`` weight (sec. 2.2) or the ``lobe`` weight
    (sec. 4.2) for the specular component, and remodulated by the full-resolution albedo.
    ``resample``: adaptive re-sampling (sec. 5.4, fig. 8): the pixels whose normalised weight
    sum (the denominator of eq. 1) is below ``resample_threshold`` are path-traced again at
    full resolution with ``resample_spp`` samples. The direct light the path tracer keeps
    at the primary hit (``direct=pathtraced``, or lights no analytic stage shades) is traced
    at full resolution and denoised there by a second filter of the same method."""

    name = "indirect"
    inputs = ("frame",)
    outputs = ("indirect",)
    #: hand Dr.Jit's cached blocks back after the low-resolution denoiser (the pipeline's
    #: option ``release_memory``)
    release_memory = False

    def __init__(self, method: str, opts: dict | None = None, setup=None,
                 direct_pt: bool = True):
        self.method = method
        opts = opts or {}
        self.scale = int(opts.get("indirect_scale", 1))
        self.last_resampled = 0
        #: what the host-side denoiser reports (``oidn_ms``: :attr:`external_ms`)
        self.timings: dict = {}
        fp = filter_params(opts)
        if self.scale == 1:
            self.denoiser = _denoiser(method, **fp)
            self.low_denoiser = self.direct_denoiser = self.upsampler = None
            return
        from ..denoise.upsampling import SpatioTemporalUpsampler, Upsampler

        self.inputs = ("frame", "frame_low")
        self.denoiser = None
        self.setup = setup
        self.opts = opts
        self.weight = opts["upsampling_weight"]
        self.mode = opts["upsampling"]
        self.resample = bool(opts["resample"])
        self._resampler = None
        self.low_denoiser = _denoiser(method, signals="indirect", output="illumination", **fp)
        # the primary hit's path-traced direct light: left to the path tracer for some lights
        # or some surfaces (pipeline.plan.DirectPlan.path_traced_direct)
        self.direct_pt = bool(direct_pt)
        self.direct_denoiser = (_denoiser(method, signals="direct", **fp) if self.direct_pt
                                else None)
        # frozen (the camera terms and the jitter opaque inputs): steady frames replay
        lobe = {"beta": fp["beta"], "kappa": fp["kappa"]}
        self.upsampler = (SpatioTemporalUpsampler(weight=self.weight, channels=INDIRECT_PT,
                                                  frozen=True, **lobe)
                          if self.mode == "spatio-temporal" else None)
        self.spatial = (Upsampler(weight=self.weight, channels=INDIRECT_PT, frozen=True,
                                  **lobe)
                        if self.upsampler is None or self.resample else None)

    @property
    def external_ms(self) -> float:
        """Milliseconds of the last run's work outside Dr.Jit (OIDN on the host), which the
        pipeline adds to the stage's kernel time."""
        return float(self.timings.get("oidn_ms", 0.0))

    def reads(self) -> dict[str, tuple[str, ...] | None]:
        """The guides (``position`` only for ``atrous``, whose edge-stopping reads it), the
        path-traced light it denoises: all of it at scale 1; at scale 2 or 4 the
        full-resolution direct light the path tracer keeps (if any) and the whole
        ``frame_low``'s guides and indirect light (this stage consumes it: :meth:`run`)."""
        guides = tuple(k for k in GUIDES if k != "position" or self.method == "atrous")
        if self.scale == 1:
            return {"frame": guides + RADIANCE_PT}
        return {"frame": guides + (DIRECT_PT if self.direct_pt else ()),
                "frame_low": guides + INDIRECT_PT}

    def reset(self) -> None:
        for d in (self.denoiser, self.low_denoiser, self.direct_denoiser, self.upsampler):
            if d is not None:
                d.reset()

    def frozen(self) -> list:
        out = []
        for d in (self.denoiser, self.low_denoiser, self.direct_denoiser):
            if d is not None:
                out += d.frozen_functions()
        if self.upsampler is not None:
            out += self.upsampler.frozen_functions()  # (its row tiles' functions too)
        spatial = getattr(self, "spatial", None)
        if spatial is not None and spatial.frozen:
            out.append(spatial._fn)
        return out

    @staticmethod
    def _input(gb: Frame, names: tuple[str, ...]) -> Frame:
        """``gb`` with emission 0 and only the radiance ``names`` (the others 0): the frame
        a denoiser of this layer sees."""
        h, w = gb.height, gb.width
        ch = {k: gb[k] for k in GUIDES if k in gb}
        for k in ("emission",) + RADIANCE_PT:
            ch[k] = gb[k] if k in names else _zeros(h, w)
        ch["color"] = sum((gb[k] for k in names[1:]), gb[names[0]])
        return _with_channels(gb, ch)

    def _denoise(self, f: Frame, denoiser) -> mi.TensorXf:
        if self.method == "none":
            return f["color"]
        if self.method == "oidn":
            from ..denoise.oidn import oidn_denoise

            return _tensor(oidn_denoise(f, quality="fast", timings=self.timings))
        return denoiser(f)

    def run(self, index: int, ctx: dict) -> dict:
        self.timings.clear()  # (this run's alone: external_ms)
        gb: Frame = ctx["frame"]
        if self.scale == 1:
            return {"indirect": self._denoise(self._input(gb, RADIANCE_PT), self.denoiser)}
        # the low frame is read by this stage alone: taken out of the context, and its
        # light dropped once denoised (_upsampled), so that it is not held through the
        # upsampling (frame_low is never one of the pipeline's outputs)
        img = self._upsampled(index, gb, _taken(ctx, "frame_low"))
        if self.direct_pt:
            img = img + self._denoise(self._input(gb, DIRECT_PT), self.direct_denoiser)
        return {"indirect": img}

    def _low_light(self, low: Frame) -> dict:
        """The low-resolution indirect light, denoised, as the upsamplers read it: per
        component, with the albedo that demodulates it (1 where it already is)."""
        h, w = low.height, low.width
        if self.low_denoiser is not None:
            chs = self.low_denoiser.planes(self._input(low, INDIRECT_PT))  # 6 planes
            if self.release_memory:  # (the filter's freed blocks, before the images below)
                dr.flush_malloc_cache()
            ones = dr.ones(mi.TensorXf, (h, w, 3))
            out = {c: merge(chs[3 * k:3 * k + 3], h, w) for k, c in enumerate(INDIRECT_PT)}
            out["albedo_diffuse"] = out["albedo_specular"] = ones
            return out
        out = {"albedo_diffuse": low["albedo_diffuse"],
               "albedo_specular": low["albedo_specular"]}
        for c in INDIRECT_PT:  # none: the raw estimate; oidn: each component alone
            out[c] = self._denoise(self._input(low, (c,)), None)
        return out

    def _upsampled(self, index: int, gb: Frame, low: Frame) -> mi.TensorXf:
        from ..denoise.upsampling import adaptive_resample

        h, w = gb.height, gb.width
        lch = {k: low[k] for k in LOW_GUIDES if k in low}
        lch.update(self._low_light(low))
        dr.eval(lch)
        for k in [k for k in low.names if k not in LOW_GUIDES]:  # (read: the light is in lch)
            del low.channels[k]
        if self.release_memory:
            dr.flush_malloc_cache()
        for k in ("emission",) + DIRECT_PT:
            lch[k] = _zeros(low.height, low.width)
        lo = _with_channels(low, lch)
        # the full frame as the upsamplers see it: its G-buffer, no light of its own (the
        # upsampled components are all this part of the layer)
        fch = {k: gb[k] for k in GUIDES if k in gb}
        for k in ("emission",) + RADIANCE_PT:
            fch[k] = _zeros(h, w)
        full = _with_channels(gb, fch)
        wts = None
        if self.upsampler is not None:
            img = self.upsampler(full, lo)
            if self.resample:
                _, wts = self.spatial(full, lo, return_weights=True)
        elif self.resample:
            img, wts = self.spatial(full, lo, return_weights=True)
        else:
            img = self.spatial(full, lo)
        if wts is not None:
            img, mask = adaptive_resample(self._resample_renderer(), index, full, img, wts,
                                          threshold=float(self.opts["resample_threshold"]),
                                          channels=INDIRECT_PT,
                                          spp=int(self.opts["resample_spp"]))
            self.last_resampled = int(mask.sum())
        return img

    def _resample_renderer(self):
        """A full-resolution, full-depth renderer for adaptive re-sampling (every emitter
        excluded at the primary hit: its ``indirect_*`` are the indirect light alone)."""
        if self._resampler is None:
            from .. import render

            n = len(self.setup.scene.emitters())
            self._resampler = render.Renderer(self.setup, max_depth=self.opts["max_depth"],
                                              seed=self.opts["seed"] + 2, frozen=False,
                                              primary_exclude=tuple(range(n)))
        return self._resampler


# -- composite, taa ---------------------------------------------------------------------------


class CompositeStage(Stage):
    """``composite = emission + direct + indirect`` (the primary-hit emission is noise free:
    pixel-centre primary rays)."""

    name = "composite"
    inputs = ("frame", "direct", "indirect")
    outputs = ("composite",)

    #: the context entry of ``emission + direct`` made early (:meth:`fold`)
    FOLDED = "emission+direct"

    def reads(self) -> dict[str, tuple[str, ...] | None]:
        return {"frame": ("emission",), "direct": None, "indirect": None,
                self.FOLDED: None}

    @classmethod
    def fold(cls, ctx: dict) -> None:
        """The composite's first sum, ``emission + direct``, made as soon as the direct
        layer exists, when neither is wanted on its own (``Pipeline.outputs``): the two
        full-size images are freed before the indirect stage, one kept (32 MiB less held
        through it at 1920x1080). The same values: :meth:`run` adds ``indirect`` to it, the
        order of the unfolded sum."""
        ctx[cls.FOLDED] = ctx["frame"]["emission"] + ctx.pop("direct")
        dr.eval(ctx[cls.FOLDED])
        del ctx["frame"].channels["emission"]

    def run(self, index: int, ctx: dict) -> dict:
        if self.FOLDED in ctx:
            return {"composite": ctx[self.FOLDED] + ctx["indirect"]}
        return {"composite": ctx["frame"]["emission"] + ctx["direct"] + ctx["indirect"]}


class TAAStage(Stage):
    """Temporal antialiasing (Karis 2014, :func:`glossrt.denoise.taa`) of the composite;
    off: ``color`` is the composite."""

    name = "taa"
    inputs = ("frame", "composite")
    outputs = ("color",)

    def __init__(self, enabled: bool, alpha: float, jitter: bool = False):
        self.enabled = bool(enabled)
        self.alpha = float(alpha)
        #: the frames are jittered (``taa_jitter``): the consistency test accepts the 3x3
        #: neighbours' surfaces too (:func:`glossrt.denoise.taa`'s ``neighbours``)
        self.jitter = bool(jitter)
        self.reset()

    def reads(self) -> dict[str, tuple[str, ...] | None]:
        if not self.enabled:
            return {"composite": None}
        return {"frame": ("mesh_id", "motion"), "composite": None}

    def reset(self) -> None:
        self.history = None
        self.history_ids = None

    def run(self, index: int, ctx: dict) -> dict:
        img = ctx["composite"]
        if not self.enabled:
            return {"color": img}
        from ..denoise import taa

        ids = ctx["frame"]["mesh_id"]
        # the previous frame's surfaces: a pixel that showed another one (a light that moved
        # away) drops its history instead of keeping the emitter's trail
        out = taa(img, self.history, ctx["frame"]["motion"], self.alpha, mesh_id=ids,
                  prev_mesh_id=self.history_ids if self.history is not None else ids,
                  neighbours=self.jitter)
        self.history, self.history_ids = out, ids
        return {"color": out}


# -- display ----------------------------------------------------------------------------------


def display(image, exposure: float = 0.0, tonemap: str = "filmic") -> np.ndarray:
    """8-bit sRGB (H, W, 3) ``uint8`` of a linear RGB image, for viewers: ``exposure`` in
    stops, then ``srgb`` (clamp + the sRGB transfer function) or ``filmic`` (Narkowicz's
    fit of the ACES curve, then sRGB). NaN shows as 0."""
    from ..metrics import srgb_encode

    if tonemap not in ("srgb", "filmic"):
        raise GlossrtError(f"unknown tonemap {tonemap!r}; choose srgb or filmic")
    x = np.asarray(image, np.float64)
    x = np.nan_to_num(x, nan=0.0, posinf=1e6, neginf=0.0)[..., :3] * 2.0 ** float(exposure)
    x = np.maximum(x, 0.0)
    if tonemap == "filmic":
        x = np.clip((x * (2.51 * x + 0.03)) / (x * (2.43 * x + 0.59) + 0.14), 0.0, 1.0)
    return np.round(srgb_encode(x) * 255.0).astype(np.uint8)


__all__ = ["CompositeStage", "DirectStage", "GBufferStage", "IndirectStage", "PointLights",
           "SpecAAStage", "Stage", "TAAStage", "bspvt_cache_dir", "default_bspvt_cache",
           "display", "geometry_key", "highlight_maps_key", "scene_trees"]
