"""Highlights that show the light's shape on rough surfaces (Kimura & Tokoi 2004; issue 7):
the scene's polygon lights rendered into a light environment map seen from a probe point per
object, sampled per pixel with microfacet normals drawn from a roughness distribution, each
sample reflecting the view into the map.

For a pixel with normal ``n``, view ``v`` (towards the eye) and ``N`` microfacet normals
``h_k`` (Kimura & Tokoi, secs. 4-5)::

    L_o = sum_k w_k  F(v . h_k) G(n, h_k, v, l_k) L_env(l_k),   l_k = 2 (v . h_k) h_k - v

* ``distribution="ellipsoidal"`` (the paper): ``h_k`` from the ellipsoidal distribution
  ``D_s(delta; R_r)`` with ``theta`` uniform on ``[0, pi)`` (:mod:`glossrt.brdf.ellipsoidal`;
  ``R_r`` from the pixel's alpha by matching the median microfacet angle of its own
  distribution, GGX or Beckmann: :func:`glossrt.brdf.ellipsoidal.median_alpha`), ``w_k = 1/N``
  for random samples (the microfacet-normal texture with embedded random numbers, secs. 5.1,
  5.3, or a per-pixel hash generator) or the 13-point regular pattern's ``D_s`` weights
  (sec. 7.2); ``G = min(1, G_m, G_s)`` (sec. 4.2);
* ``distribution="ggx"`` (beyond the paper; the name predates Beckmann support): the pixel's
  own microfacet lobe, GGX visible-normal sampling (Heitz 2018) or Beckmann ``D cos`` (the
  Frame's ``distribution`` channel), with filtered importance sampling (Colbert & Krivanek
  2007): each sample reads the pre-filtered level of the map chosen from its pdf; ``w_k =
  f cos / pdf / N`` with the shared BRDF (Mitsuba's separable Smith term).

``F`` is the pixel's Fresnel term (Schlick's with ``F0``, or Mitsuba's exact one with
:func:`glossrt.lights.shading.fresnel_image`; glossrt's addition: the paper's highlights are
the reflected light alone, i.e. ``F = 1``). ``L_env`` holds the lights only
(the paper's light environment map), so the method gives the specular reflection of the
lights; diffuse light is not part of it. Bounding-sphere culling (sec. 6) skips pixels whose
mirror direction, cast from the probe the pixel's map was rendered from (the map's lookups
see the lights from there, not from the pixel), misses every light's sphere enlarged by the
lobe's spread and by the map's texel footprint (:func:`texel_margin`). Smooth BSDFs (alpha
0: a ``conductor``, ``dielectric``; up to Mitsuba's clamp :data:`ALPHA_SMOOTH`) take the
distribution's limit: every microfacet normal is ``n``, the mirror reflection of the map.
"""

from __future__ import annotations

import math

import drjit as dr
import numpy as np

from ...backend import mi
from ...brdf import microfacet as mf
from ...brdf.ggx import ALPHA_MIN
from ...errors import GlossrtError
from ...images import check_frame, merge, split
from ...jit import opaque
from ..shading import (
    NEEDS,
    ShadingPoints,
    f0_tensor,
    light_vertices,
    refuse_anisotropic,
    shading_channels,
)


def shade_plain(frame, lights: list, f0: np.ndarray | None = None) -> np.ndarray:
    """The paper's baseline "plain shading" (sec. 7.1): every light as a point light at its
    centroid with intensity ``radiance x area x cos`` (a small Lambertian emitter), GGX
    specular (the shared BRDF of :mod:`glossrt.lights.shading`) and Schlick F; no light
    shape, no environment map. Specular only, like the highlight methods. (H, W, 3)."""
    from ..scene import PolygonLight
    from ..shading import brdf_cos

    sp = ShadingPoints.of(frame, f0)
    total = dr.zeros(mi.Color3f, frame.width * frame.height)
    for lt in lights:
        if not isinstance(lt, PolygonLight):
            lt = PolygonLight(light_vertices(lt), lt.radiance, bool(getattr(lt, "two_sided",
                                                                               False)))
        c = mi.Point3f(*opaque(np.asarray(lt.centroid, float)))
        ln = mi.Vector3f(*opaque(np.asarray(lt.normal, float)))
        le = mi.Color3f(*opaque(np.asarray(lt.radiance, float).ravel()[:3]))
        area = dr.opaque(mi.Float, float(lt.area))
        d = c - sp.p
        dist2 = dr.squared_norm(d)
        wi = d * dr.rsqrt(dr.maximum(dist2, 1e-12))
        cos_l = -dr.dot(ln, wi)
        if getattr(lt, "two_sided", False):
            cos_l = dr.abs(cos_l)
        _, spec = brdf_cos(sp, wi)
        total += dr.select(cos_l > 0, spec * le * (area * cos_l / dr.maximum(dist2, 1e-12)),
                           0.0)
    out = merge([total[0], total[1], total[2]], frame.height, frame.width)
    return np.array(out, dtype=np.float32).reshape(frame.height, frame.width, 3)


DISTRIBUTIONS = ("ellipsoidal", "ggx")
SAMPLINGS = ("texture", "hash", "regular")


def _groups(alpha: np.ndarray, hit: np.ndarray,
            beckmann: np.ndarray) -> list[tuple[float, bool, np.ndarray]]:
    """Pixels grouped by material roughness and distribution (the paper's normal texture,
    regular pattern and bounding-sphere enlargement are per material): (alpha, Beckmann?,
    flat pixel indices)."""
    out = []
    for b in (False, True):
        sel = hit & (beckmann == b)
        out += [(float(a), b, np.flatnonzero(sel & (alpha == a))) for a in np.unique(alpha[sel])]
    return out


#: Alphas up to this are smooth (a ``conductor`` or ``dielectric`` has alpha 0, where
#: ``R_r`` would be infinite; Mitsuba clamps every microfacet alpha to it, and so does
#: :class:`~glossrt.lights.shading.ShadingPoints`): the ellipsoidal estimator takes their
#: limit ``R_r -> infinity``, in which every microfacet normal is ``n`` -- mirror reflection,
#: ``h = n`` for every sample (``D_s``'s tails fall only like ``1 / (R_r delta)``, so a large
#: finite ratio would still scatter a few samples by milliradians). Traced and frozen paths.
ALPHA_SMOOTH = ALPHA_MIN


def _is_smooth(alpha: float) -> bool:
    return alpha <= ALPHA_SMOOTH


def _ratio(alpha: float, beckmann: bool) -> float:
    """The ellipsoidal ratio whose median microfacet angle is the material's (GGX or
    Beckmann; :func:`glossrt.brdf.ellipsoidal.ratio_from_alpha`), at least that of median
    alpha 1e-6 (smooth alphas, :data:`ALPHA_SMOOTH`, sample the mirror's normal instead;
    their ratio serves the culling's spread)."""
    from ...brdf import ellipsoidal as el

    a = float(el.median_alpha(alpha, "beckmann" if beckmann else "ggx"))
    return float(el.ratio_from_alpha(min(max(a, 1e-6), el.ALPHA_MAX)))


def _estimate(sp: ShadingPoints, env, pix_x, pix_y, pix_idx, alpha: float, samples: int,
              distribution: str, sampling: str, frame_index: int, texture=None,
              level0: int = 128, offset=0, fis_samples: int | None = None,
              beckmann: bool = False) -> mi.Color3f:
    """The module docstring's estimator for one material (scalar ``alpha``); hash samples
    use sample indices ``offset + k`` (``offset`` an opaque ``mi.UInt32`` for references
    summed over batches, so one kernel serves every batch); ``fis_samples``: the sample
    count that sets GGX's filtered-importance-sampling level (default ``samples``)."""
    from ...brdf import ellipsoidal as el

    n, v = sp.n, sp.wo
    total = dr.zeros(mi.Color3f, dr.width(n))
    if distribution == "ellipsoidal":
        # a scalar alpha: one material (``beckmann`` its distribution); per lane: sp's
        scalar = isinstance(alpha, float)
        ratio = _ratio(alpha, beckmann) if scalar else _ratio_dr(alpha, sp.beckmann)
        # smooth lanes (ALPHA_SMOOTH): the limit R_r -> infinity, every normal is n
        smooth = None if scalar else _smooth_dr(alpha)
        if scalar and _is_smooth(alpha):
            hs = [(n, 1.0)]
        elif sampling == "regular":
            hs = el.regular_normals(n, ratio)
        elif sampling == "texture":
            hs = [(h, 1.0 / samples) for h in texture.sample_normals(n, pix_x, pix_y, samples,
                                                                       frame_index)]
        else:
            hs = []
            for k in range(samples):
                u, vv = el.hash_uniforms(pix_idx, offset + k, frame_index)
                # Kimura & Tokoi, sec. 5.1: delta(U) by the inverse CDF, theta = pi V
                hs.append((el.microfacet_normal(n, el.ellipsoidal_sample(u, ratio),
                                                dr.pi * vv), 1.0 / samples))
        for h, w in hs:
            if smooth is not None:
                h = dr.select(smooth, n, h)
            l = el.reflect(v, h)  # noqa: E741
            g = el.geometric_attenuation(n, h, v, l)
            f = sp.fresnel_at(dr.dot(v, h))
            total += f * (g * w) * env(l, 0.0)
        return total
    # the pixel's microfacet lobe (GGX: visible normals, Heitz 2018; Beckmann: D cos, Walter
    # et al. 2007) + filtered importance sampling (Colbert & Krivanek 2007)
    from .envmap import fis_lod

    frame = mi.Frame3f(n)
    vl = frame.to_local(v)
    a = max(alpha, ALPHA_MIN) if isinstance(alpha, float) else dr.maximum(alpha, ALPHA_MIN)
    for k in range(samples):
        u1, u2 = el.hash_uniforms(pix_idx, offset + k, frame_index)
        hx, hy, hz = mf.sample_h(vl.x, vl.y, vl.z, a, u1, u2, sp.beckmann)
        hl = mi.Vector3f(hx, hy, hz)
        ll = 2.0 * dr.dot(vl, hl) * hl - vl
        ok = (ll.z > 0) & (vl.z > 0)
        vh = dr.maximum(dr.dot(vl, hl), 1e-8)
        # pdf of l: p_h(h) / (4 v.h)
        s2 = hx * hx + hy * hy  # the exact sin^2 of h (a near-mirror's D needs it)
        pdf = mf.pdf_h(vl.z, vh, hz, a, sp.beckmann, s2) / (4.0 * vh)
        lod = fis_lod(pdf, fis_samples or samples, level0)
        # weight f cos / pdf with the shared BRDF (Mitsuba's D and separable Smith term)
        fc = mf.specular_cos(vl.z, ll.z, hz, a, sp.beckmann, s2)
        f = sp.fresnel_at(vh)
        w = dr.select(ok & (pdf > 0), fc / dr.maximum(pdf, 1e-30), 0.0) / samples
        total += f * w * env(frame.to_world(ll), lod)
    return total


def _ratio_dr(alpha: mi.Float, beckmann=False) -> mi.Float:
    """Per lane :func:`glossrt.brdf.ellipsoidal.ratio_from_alpha` (its closed form
    ``R = sqrt(1 + alpha^2) / alpha - 1`` of the median-matched GGX alpha, ``alpha sqrt(ln 2)``
    on Beckmann lanes, clamped to ``(0, ALPHA_MAX]``, so R >= 1; smooth lanes take the
    mirror's normals instead, :data:`ALPHA_SMOOTH`)."""
    from ...brdf.ellipsoidal import ALPHA_MAX, BECKMANN_MEDIAN

    alpha = mf.by_distribution(beckmann, lambda: alpha * BECKMANN_MEDIAN, lambda: alpha)
    a = dr.clip(alpha, 1e-6, ALPHA_MAX)
    return dr.maximum(dr.sqrt(1.0 + a * a) / a - 1.0, 1.0)


def _smooth_dr(alpha: mi.Float) -> mi.Bool:
    """Per lane :func:`_is_smooth`."""
    return alpha <= ALPHA_SMOOTH


def _fast_kernel(ch: dict, cam: list, data, base, has, tables, n_ids: int, n_levels: int,
                 frame_index, samples: int, distribution: str, level0: int,
                 size: tuple[int, int]) -> mi.TensorXf:
    """The frozen path's body (:class:`HighlightRenderer` with ``frozen=True``): every pixel
    at once, per-lane roughness (ratio by its closed form), hash samples, no culling."""
    from .envmap import _lookup_dr

    h, w = size  # explicit: part of dr.freeze's key (see ltc._shade_kernel)
    sp = ShadingPoints.at_camera(ch, cam)
    ids = mi.UInt32(split(ch["mesh_id"])[0])
    inside = ids < n_ids
    idx = dr.select(inside, ids, 0)
    active = sp.hit & inside & (dr.gather(mi.UInt32, has, idx, inside) > 0)
    b = dr.gather(mi.UInt32, base, idx, active)

    def env(d, lod):
        return _lookup_dr(data, b, active, tables, n_levels, d, lod)

    pix = dr.arange(mi.UInt32, h * w)
    col = _estimate(sp, env, pix % w, pix // w, pix, sp.alpha, samples, distribution, "hash",
                    frame_index, None, level0)
    col = dr.select(sp.hit, col, 0.0)
    return merge([col[0], col[1], col[2]], h, w)


def _grid_kernel(ch: dict, cam: list, data, grid, tables, n_ids: int, n_levels: int,
                 texel_count: int, axes: tuple, frame_index, samples: int, distribution: str,
                 level0: int, size: tuple[int, int]) -> mi.TensorXf:
    """:func:`_fast_kernel` reading :class:`~glossrt.lights.highlights.envmap.ProbeGridMaps`:
    each sample's ``L_env(l_k)`` (Kimura & Tokoi, sec. 5.2: the environment map read in the
    mirror direction of the view about the microfacet normal) blended over the probes around
    the pixel's surface point."""
    from .envmap import grid_lookup

    h, w = size
    sp = ShadingPoints.at_camera(ch, cam)
    ids = mi.UInt32(split(ch["mesh_id"])[0])
    ids = dr.select(sp.hit, ids, mi.UInt32(n_ids))
    p = sp.p

    def env(d, lod):
        return grid_lookup(data, grid, tables, n_levels, texel_count, n_ids, axes, ids, p, d,
                           lod)

    pix = dr.arange(mi.UInt32, h * w)
    col = _estimate(sp, env, pix % w, pix // w, pix, sp.alpha, samples, distribution, "hash",
                    frame_index, None, level0)
    col = dr.select(sp.hit, col, 0.0)
    return merge([col[0], col[1], col[2]], h, w)


def spread_angle(alpha: float, distribution: str, q: float = 0.99,
                 beckmann: bool = False) -> float:
    """The angle (radians) from the normal within which a fraction ``q`` of the microfacet
    normals lie, for the bounding-sphere enlargement (Kimura & Tokoi, sec. 6): ellipsoidal
    ``|delta|`` quantile (``D_s`` is symmetric: ``delta(1/2 + q/2)``), else the material's
    ``theta_h`` quantile of the projected NDF: GGX ``P(tan^2 theta < x) = x / (alpha^2 + x)``,
    Beckmann (``beckmann``) ``1 - exp(-x / alpha^2)``."""
    from ...brdf import ellipsoidal as el

    if distribution == "ellipsoidal":
        return float(el.ellipsoidal_sample(0.5 + 0.5 * q, _ratio(alpha, beckmann)))
    a = max(alpha, ALPHA_MIN)
    if beckmann:
        return float(np.arctan(a * np.sqrt(-np.log(1.0 - q))))
    return float(np.arctan(a * np.sqrt(q / (1.0 - q))))


def _probe_table(maps) -> tuple[np.ndarray, np.ndarray]:
    """``(probes (n_ids, 3), known (n_ids,))``: the point each mesh id's cube map was
    rendered from (:attr:`glossrt.lights.highlights.envmap.LightCubeMap.probe`), where known."""
    n = int(maps._n_ids)
    probes, known = np.zeros((n, 3)), np.zeros(n, bool)
    for i, m in maps.maps.items():
        if m.probe is not None:
            probes[i], known[i] = m.probe, True
    return probes, known


def texel_margin(maps) -> float:
    """Angle (radians) by which a light's image in the level-0 maps reaches past the light
    itself: a texel is lit when any of its sub-samples sees the light (half a texel diagonal
    from its centre) and bilinear lookups reach a texel centre up to one diagonal away; a
    texel of a ``res``-texel face side spans at most ``2 / res`` radians (at the face's
    centre), its diagonal ``2 sqrt(2) / res``. The culling cone is enlarged by two diagonals
    (1.5 needed), so it drops no pixel the map lights."""
    return 2.0 * 2.0 * math.sqrt(2.0) / float(maps.resolutions[0])


class HighlightRenderer:
    """Light-shape highlights of G-buffers (module docstring); keeps the per-material normal
    textures between frames. ``samples`` per pixel (4, the paper's), ``distribution``
    ``"ellipsoidal"`` | ``"ggx"``, ``sampling`` ``"texture"`` (normal texture with embedded
    random numbers) | ``"hash"`` (per-pixel hash generator) | ``"regular"`` (13 points, the
    ellipsoidal distribution only), ``cull`` the bounding-sphere test, ``resolution`` of the
    light cube maps (the paper: 256). ``frozen=True``: every pixel in one ``dr.freeze``d
    kernel (recorded once, replayed for later frames: the GPU path; per-pixel roughness,
    hash samples, no culling), same estimator as the traced path up to float rounding of the
    per-pixel ratio."""

    def __init__(self, samples: int = 4, distribution: str = "ellipsoidal",
                 sampling: str = "texture", cull: bool = True, resolution: int = 128,
                 supersample: int = 2, texture_size: int = 64, frozen: bool = False) -> None:
        if distribution not in DISTRIBUTIONS:
            raise GlossrtError(f"unknown distribution {distribution!r}; choose one of "
                               f"{DISTRIBUTIONS}")
        if sampling not in SAMPLINGS:
            raise GlossrtError(f"unknown sampling {sampling!r}; choose one of {SAMPLINGS}")
        if distribution == "ggx" and sampling != "hash":
            sampling = "hash"  # GGX + FIS draws its own uniforms from the hash generator
        if int(samples) < 1:
            raise GlossrtError(f"samples must be >= 1, got {samples}")
        self.samples, self.distribution, self.sampling = int(samples), distribution, sampling
        self.cull, self.resolution, self.supersample = bool(cull), resolution, supersample
        self.texture_size = texture_size
        if frozen and (sampling != "hash" or cull):
            raise GlossrtError("frozen=True is the real-time path: per-pixel hash samples "
                               "(sampling='hash', or distribution='ggx') and no culling "
                               "(cull=False)")
        self.frozen = bool(frozen)
        # this renderer's own recordings (counted by the pipeline: DirectStage.frozen)
        self._frozen = dr.freeze(_fast_kernel, warn_after=16) if frozen else None
        self._frozen_grid = dr.freeze(_grid_kernel, warn_after=16) if frozen else None
        self._textures: dict = {}
        self.last_stats: dict = {}

    def reset(self) -> None:
        self._textures.clear()

    def maps(self, setup, frame_index: int, lights: list | None = None):
        """The light cube maps of ``setup`` at ``frame_index`` (probe per object)."""
        from ..scene import polygon_lights
        from .envmap import CubeMapSet, probe_points

        lights = polygon_lights(setup, frame_index) if lights is None else lights
        return CubeMapSet.render(lights, probe_points(setup), self.resolution,
                                 supersample=self.supersample)

    def grid_maps(self, setup, frame_index: int, lights: list | None = None,
                  probes: int | None = None, grids=None):
        """Light cube maps at a grid of probes per object (:func:`glossrt.lights.highlights.
        envmap.probe_grids`, ``probes`` along the largest object's longest side; 1: the
        paper's one map per object), for :meth:`shade_tensor`. The ellipsoidal estimator
        reads level 0 only: one level, rendered on the device; GGX's filtered importance
        sampling gets the full chain. ``grids``: precomputed probe grids."""
        from ..scene import polygon_lights
        from .envmap import DEFAULT_PROBES, ProbeGridMaps, probe_grids

        lights = polygon_lights(setup, frame_index) if lights is None else lights
        if grids is None:
            grids = probe_grids(setup, DEFAULT_PROBES if probes is None else probes)
        levels = 1 if self.distribution == "ellipsoidal" else None
        return ProbeGridMaps(lights, grids, self.resolution, levels, self.supersample)

    def _texture(self, ratio: float):
        from ...brdf.ellipsoidal import NormalTexture

        key = round(ratio, 9)
        if key not in self._textures:
            self._textures[key] = NormalTexture(ratio, self.texture_size, self.texture_size)
        return self._textures[key]

    def shade_tensor(self, frame, maps, f0: np.ndarray | None = None,
                     frame_index: int = 0) -> mi.TensorXf:
        """The frozen path's image as an (H, W, 3) ``mi.TensorXf`` left on the device (the
        real-time use; ``frozen=True`` renderers only)."""
        from ...jit import no_gc

        if not self.frozen:
            raise GlossrtError("shade_tensor is the frozen path: HighlightRenderer(frozen=True)")
        check_frame(frame, NEEDS)
        refuse_anisotropic(frame, "the light-shape highlights")
        if frame.camera is None:
            raise GlossrtError(f"{frame.where}: highlights need the camera")
        ch = shading_channels(frame)
        ch["f0"] = f0_tensor(frame, f0)
        if hasattr(maps, "axes"):  # ProbeGridMaps: several probes per object
            with no_gc():
                out = self._frozen_grid(
                    ch, opaque(frame.camera.position), maps.data, maps._grid, maps._tables,
                    maps._n_ids, maps.n_levels, maps.texel_count, maps.axes,
                    dr.opaque(mi.UInt32, int(frame_index)), self.samples, self.distribution,
                    int(maps.resolutions[0]), (frame.height, frame.width))
                dr.eval(out)
            return out
        with no_gc():
            out = self._frozen(ch, opaque(frame.camera.position), maps.data, maps._base,
                               maps._has, maps._tables, maps._n_ids, maps.n_levels,
                               dr.opaque(mi.UInt32, int(frame_index)), self.samples,
                               self.distribution, int(maps.resolutions[0]),
                               (frame.height, frame.width))
            dr.eval(out)
        return out

    def __call__(self, frame, lights: list, maps, f0: np.ndarray | None = None,
                 frame_index: int = 0, offset=0, fis_samples: int | None = None) -> np.ndarray:
        """Specular reflection (H, W, 3) of the ``lights`` in ``frame``'s G-buffer through the
        light cube ``maps`` (:meth:`maps`); ``f0`` per pixel (default 0: then only ``F``'s
        Fresnel term lights it; pass :func:`glossrt.lights.shading.fresnel_image` for the
        exact terms or :func:`~glossrt.lights.shading.f0_image` for Schlick's)."""
        from ...brdf import ellipsoidal as el
        from .envmap import cull_mask, light_spheres, lobe_spread

        check_frame(frame, NEEDS)
        refuse_anisotropic(frame, "the light-shape highlights")
        h, w = frame.height, frame.width
        if self.frozen and offset == 0 and fis_samples is None:
            out = self.shade_tensor(frame, maps, f0, frame_index)
            self.last_stats = {"pixels": int(np.count_nonzero(
                frame.numpy("mesh_id") > 0)), "shaded": None}
            return np.array(out, dtype=np.float32).reshape(h, w, 3)
        sp = ShadingPoints.of(frame, f0)
        alpha = frame.numpy("roughness")[..., 0].ravel()
        hit = np.array(sp.hit)
        beck = np.broadcast_to(np.array(sp.beckmann), hit.shape)
        mesh_id = mi.UInt32(split(frame["mesh_id"])[0])
        centres, radii = light_spheres(lights)
        if self.cull and len(lights):
            probes, known = _probe_table(maps)
            ids_np = np.asarray(mesh_id, dtype=np.int64)
            margin = texel_margin(maps)
        total = dr.zeros(mi.Color3f, w * h)
        stats = {"pixels": int(hit.sum()), "shaded": 0}
        for a, b, idx_np in _groups(alpha, hit, beck):
            idx = mi.UInt32(idx_np.astype(np.uint32))
            sub = sp.take(idx)
            if self.cull and len(lights):
                spread = lobe_spread(spread_angle(a, self.distribution, beckmann=b)) + margin
                # from the probe each pixel's map was rendered from (its lookups see the
                # lights from there), not from the shading point; a map without a known
                # probe: no culling
                pid = np.minimum(ids_np[idx_np], len(known) - 1)
                origin = mi.Point3f(*(mi.Float(c) for c in probes[pid].T.astype(np.float32)))
                keep = cull_mask(origin, el.reflect(sub.wo, sub.n), centres, radii, spread)
                keep |= mi.Bool(~known[pid] & (ids_np[idx_np] < len(known)))
                sel = dr.compress(keep)
                if dr.width(sel) == 0:
                    continue
                idx = dr.gather(mi.UInt32, idx, sel)
                sub = sub.take(sel)
            stats["shaded"] += dr.width(idx)
            ids = dr.gather(mi.UInt32, mesh_id, idx)

            def env(d, lod, ids=ids):
                return maps.lookup(ids, d, lod)

            tex = None
            if (self.distribution == "ellipsoidal" and self.sampling == "texture"
                    and not _is_smooth(a)):
                tex = self._texture(_ratio(a, b))
            col = _estimate(sub, env, idx % w, idx // w, idx, a, self.samples,
                            self.distribution, self.sampling, frame_index, tex,
                            int(maps.resolutions[0]), offset, fis_samples, b)
            dr.scatter(total, col, idx)
        self.last_stats = stats
        out = merge([total[0], total[1], total[2]], h, w)
        return np.array(out, dtype=np.float32).reshape(h, w, 3)


def reference(frame, lights: list, maps, f0: np.ndarray | None = None,
              distribution: str = "ellipsoidal", samples: int = 1024, batch: int = 16,
              frame_index: int = 0, fis: bool = False,
              progress=None) -> np.ndarray:
    """The converged reference of the same reflection model: ``samples`` hash-sampled
    microfacet normals per pixel, no culling, summed over batches of ``batch`` (one kernel for
    all batches). GGX: unfiltered (level 0) unless ``fis``."""
    hr = HighlightRenderer(batch, distribution, "hash", cull=False)
    acc = None
    n_batches = max(1, -(-int(samples) // int(batch)))
    for b in range(n_batches):
        img = hr(frame, lights, maps, f0, frame_index,
                 offset=dr.opaque(mi.UInt32, b * batch),
                 fis_samples=None if fis else 1 << 30)
        acc = img if acc is None else acc + img
        if progress is not None:
            progress(b + 1, n_batches)
    return acc / n_batches


def shade_highlights(setup, frame, frame_index: int = 0, lights: list | None = None,
                     f0: np.ndarray | None = None, **options) -> np.ndarray:
    """One-call form: light cube maps of ``setup`` at ``frame_index`` and the highlights of
    ``frame`` (options of :class:`HighlightRenderer`)."""
    from ..scene import polygon_lights
    from ..shading import fresnel_image

    lights = polygon_lights(setup, frame_index) if lights is None else lights
    hr = HighlightRenderer(**options)
    maps = hr.maps(setup, frame_index, lights)
    return hr(frame, lights, maps, fresnel_image(setup, frame) if f0 is None else f0,
              frame_index)
