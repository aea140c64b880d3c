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
* ``direct`` -> ``direct``: the analytic direct light (0 with ``direct=pathtraced``);
* ``indirect`` -> ``indirect``: the denoised path-traced light beyond emission (indirect
  light, plus the direct light of every light the direct stage leaves to the path tracer);
* ``composite`` -> ``composite`` = ``emission + direct + indirect``;
* ``taa`` -> ``color`` (``composite`` reprojected and blended; ``composite`` when off).
"""

from __future__ import annotations

import hashlib

import drjit as dr
import numpy as np

from ..backend import mi
from ..errors import GlossrtError
from ..frame import Frame
from ..images import merge
from ..jit import no_gc, opaque

RADIANCE_PT = ("direct_diffuse", "direct_specular", "indirect_diffuse", "indirect_specular")
GUIDES = ("albedo_diffuse", "albedo_specular", "normal", "position", "depth", "roughness",
          "distribution", "mesh_id", "motion")


def _zeros(h: int, w: int, c: int = 3) -> mi.TensorXf:
    return dr.zeros(mi.TensorXf, (h, w, c))


def _tensor(img) -> mi.TensorXf:
    if isinstance(img, mi.TensorXf):
        return img
    return mi.TensorXf(np.ascontiguousarray(np.asarray(img, np.float32)))


class Stage:
    """A pipeline stage: ``name``, the ``inputs`` it reads from the context and the
    ``outputs`` it returns from :meth:`run`."""

    name = ""
    inputs: tuple[str, ...] = ()
    outputs: tuple[str, ...] = ()

    def run(self, index: int, ctx: dict) -> dict:
        raise NotImplementedError

    def reset(self) -> None:
        """Drop what the stage keeps between frames (histories, accumulations)."""

    def frozen(self) -> list:
        """The ``dr.freeze`` functions this stage owns (to count their recordings)."""
        return []


# -- gbuffer -------------------------------------------------------------------------------


class GBufferStage(Stage):
    """G-buffer plus 1 spp path tracing (:class:`glossrt.render.Renderer`), or with
    ``accumulate`` the running mean of converged estimates (``spp`` per frame) while the
    scene holds still. ``exclude``: emitter indices the analytic direct stage shades
    (removed from the path tracer at the primary hit only)."""

    name = "gbuffer"
    outputs = ("frame",)

    def __init__(self, setup, opts: dict, exclude: tuple[int, ...] = ()):
        from .. import render

        self.renderer = render.Renderer(setup, max_depth=opts["max_depth"], seed=opts["seed"],
                                        primary_exclude=tuple(exclude))
        self.setup = setup
        self.exclude = tuple(exclude)
        self.accumulate = bool(opts["accumulate"])
        self.spp = int(opts["spp"])
        self.seed = int(opts["seed"])
        self.reset()

    def reset(self) -> None:
        self._sum: dict | None = None
        self._n = 0
        self._pose = None
        self._passes = 0

    def frozen(self) -> list:
        return [self.renderer._trace_frozen]

    def run(self, index: int, ctx: dict) -> dict:
        if not self.accumulate:
            return {"frame": self.renderer.render(index)}
        pose = index if self.setup.animated else 0
        if pose != self._pose:
            self.reset()
            self._pose = pose
        f = self.renderer.render_reference(index, self.spp,
                                           seed=self.seed + 7919 * self._passes)
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
    (frozen per pipeline: the scene is an argument, the lights opaque)."""

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


#: BSPVT trees, built on first use, keyed by the scene's geometry (vertex positions of its
#: non-emitting meshes, the analytic occluders' boxes) and the resolution
_TREES: dict = {}
_TREES_MAX = 4


def geometry_key(scene, resolution: int) -> str:
    """A digest of what BSPVT's visibility depends on: the non-emitting meshes' vertices and
    the analytic occluders' bounds."""
    from ..lights.bspvt.scene import occluder_bounds, scene_meshes

    h = hashlib.sha1(str(resolution).encode())
    for m in scene_meshes(scene):
        h.update(np.asarray(m.vertex_positions_buffer(), np.float32).tobytes())
    h.update(repr(occluder_bounds(scene)).encode())
    return h.hexdigest()


def scene_trees(scene, resolution: int, progress: bool = True):
    """BSPVT trees of ``scene`` (cached per geometry; built with a progress bar on a miss)."""
    from ..lights.bspvt import build_scene_trees

    key = geometry_key(scene, resolution)
    if key not in _TREES:
        if len(_TREES) >= _TREES_MAX:
            _TREES.pop(next(iter(_TREES)))
        _TREES[key] = build_scene_trees(scene, resolution, progress=progress)
    return _TREES[key]


class DirectStage(Stage):
    """The direct light of the scene's lights (module docstring): ``pathtraced`` (0 here:
    the 1 spp estimate stays in the path-traced layers and is denoised with the rest), ``ltc``
    (Heitz et al. 2016, unshadowed), ``ltc+bspvt`` (Okuno & Iwasaki, eq. 2), ``ltc+ratio``
    (Heitz, Hill & McGuire 2018) or ``highlights`` (Kimura & Tokoi for the specular part,
    LTC for the diffuse part). Point and directional lights: analytic with shadow rays
    whenever the mode is not ``pathtraced``."""

    name = "direct"
    inputs = ("frame",)
    outputs = ("direct",)

    def __init__(self, setup, opts: dict, mode: str, progress: bool = True):
        self.setup = setup
        self.mode = mode
        self.opts = opts
        self.points = PointLights(setup) if mode != "pathtraced" else None
        self.trees = None
        if mode == "ltc+bspvt":
            self.trees = scene_trees(setup.scene, int(opts["bspvt_resolution"]), progress)
        self.highlights = None
        if mode == "highlights":
            from ..lights.highlights import HighlightRenderer

            self.highlights = HighlightRenderer(samples=int(opts["highlight_samples"]),
                                                sampling="hash", cull=False, frozen=True)
        self._textures: dict = {}

    def frozen(self) -> list:
        return [self.points._fn] if self.points is not None else []

    def run(self, index: int, ctx: dict) -> dict:
        gb: Frame = ctx["frame"]
        h, w = gb.height, gb.width
        if self.mode == "pathtraced":
            return {"direct": _zeros(h, w)}
        from ..lights.analytic import analytic_lights
        from ..lights.scene import polygon_lights
        from ..lights.shading import fresnel_image

        polys = polygon_lights(self.setup, index)
        points = analytic_lights(self.setup, index)
        f0 = fresnel_image(self.setup, gb)
        if self.mode == "ltc":
            out = self._ltc(gb, polys, f0)
        elif self.mode == "ltc+bspvt":
            from ..lights.bspvt import shade_bspvt

            out = _tensor(shade_bspvt(self.setup.scene, gb, self.trees, polys,
                                      self.opts["bspvt_mode"], f0=f0, textures=self._textures,
                                      frozen=True))
        elif self.mode == "ltc+ratio":
            from ..lights.ratio import render_ratio

            out = _tensor(render_ratio(gb, polys, self.setup.scene, spp=self.opts["ratio_spp"],
                                       f0=f0, seed=index).image)
        else:  # highlights: Kimura & Tokoi's specular + LTC's diffuse
            out = self._ltc_diffuse(gb, polys, f0) + self._highlights(gb, index, polys, f0)
        if points:
            out = out + self.points(gb, points, f0)
        return {"direct": out}

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
        spec = self._ltc(Frame(channels=ch, camera=gb.camera, prev_camera=gb.prev_camera,
                               index=gb.index, meta=gb.meta), polys, f0)
        return dr.maximum(total - spec, 0.0)

    def _highlights(self, gb: Frame, index: int, polys: list, f0) -> mi.TensorXf:
        maps = self.highlights.maps(self.setup, index, polys)
        return self.highlights.shade_tensor(gb, maps, f0, index)


# -- indirect ---------------------------------------------------------------------------------


class IndirectStage(Stage):
    """The path-traced light beyond emission, denoised: ``svgf`` (Schied et al. 2017),
    ``svgf-lobe`` (SVGF with Tokuyoshi 2015's specular-lobe weights), ``atrous`` (Dammertz
    et al. 2010, frozen), ``oidn`` or ``none`` (the raw estimate). The denoiser sees the
    frame with its emission set to 0 (the composite adds the noise-free primary-hit
    emission), so its output is exactly this layer."""

    name = "indirect"
    inputs = ("frame",)
    outputs = ("indirect",)

    def __init__(self, method: str):
        from ..denoise import SVGF

        self.method = method
        self.denoiser = None
        if method == "svgf":
            self.denoiser = SVGF()
        elif method == "svgf-lobe":
            self.denoiser = SVGF(weights="lobe")
        elif method == "atrous":
            self.denoiser = SVGF(temporal=False, spatial="dammertz")

    def reset(self) -> None:
        if self.denoiser is not None:
            self.denoiser.reset()

    def frozen(self) -> list:
        d = self.denoiser
        return [d._accumulate, d._reconstruct] if d is not None else []

    def run(self, index: int, ctx: dict) -> dict:
        gb: Frame = ctx["frame"]
        h, w = gb.height, gb.width
        raw = gb[RADIANCE_PT[0]] + gb[RADIANCE_PT[1]] + gb[RADIANCE_PT[2]] + gb[RADIANCE_PT[3]]
        if self.method == "none":
            return {"indirect": raw}
        ch = {k: gb[k] for k in RADIANCE_PT + GUIDES if k in gb}
        ch["emission"] = _zeros(h, w)
        ch["color"] = raw
        f = Frame(channels=ch, camera=gb.camera, prev_camera=gb.prev_camera, index=gb.index,
                  meta=gb.meta)
        if self.method == "oidn":
            from ..denoise.oidn import oidn_denoise

            return {"indirect": _tensor(oidn_denoise(f, quality="fast"))}
        return {"indirect": self.denoiser(f)}


# -- composite, taa ---------------------------------------------------------------------------


class CompositeStage(Stage):
    """``composite = emission + direct + indirect`` (the primary-hit emission is noise free:
    pixel-centre primary rays)."""

    name = "composite"
    inputs = ("frame", "direct", "indirect")
    outputs = ("composite",)

    def run(self, index: int, ctx: dict) -> dict:
        return {"composite": ctx["frame"]["emission"] + ctx["direct"] + ctx["indirect"]}


class TAAStage(Stage):
    """Temporal antialiasing (Karis 2014, :func:`glossrt.denoise.taa`) of the composite;
    off: ``color`` is the composite."""

    name = "taa"
    inputs = ("frame", "composite")
    outputs = ("color",)

    def __init__(self, enabled: bool, alpha: float):
        self.enabled = bool(enabled)
        self.alpha = float(alpha)
        self.reset()

    def reset(self) -> None:
        self.history = None

    def run(self, index: int, ctx: dict) -> dict:
        img = ctx["composite"]
        if not self.enabled:
            return {"color": img}
        from ..denoise import taa

        out = taa(img, self.history, ctx["frame"]["motion"], self.alpha)
        self.history = out
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
           "Stage", "TAAStage", "display", "scene_trees"]
