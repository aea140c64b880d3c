"""Shading with specular antialiasing (:mod:`glossrt.specaa`): point, directional and
polygon lights on a G-buffer, each pixel's lobe widened by the filtered roughness of
:mod:`glossrt.specaa.filters` (covariance GGX or Beckmann for point / directional lights, LTC
with the isotropic reduction for polygon lights; no shadows).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import drjit as dr
import numpy as np

from ..backend import mi
from ..brdf import covariance_ggx as cggx
from ..brdf import microfacet as mf
from ..errors import FrameError
from ..images import check_frame, merge
from ..jit import no_gc, opaque
from ..lights import analytic
from ..lights.ltc import shade as _ltc
from ..lights.shading import (
    NEEDS,
    ShadingPoints,
    f0_tensor,
    shading_channels,
)
from .filters import (
    Method,
    _Quad,
    _quad,
    filtered_roughness,
    isotropic_alpha,
    material_matrix,
    parse_method,
)


def _specular(wo: mi.Vector3f, wi: mi.Vector3f, a: tuple, sp: ShadingPoints,
              masking: str, am: tuple | None = None) -> mi.Color3f:
    """The pixel's lobe (local directions) with the roughness matrix ``a``: covariance GGX
    (Tokuyoshi, appendix A.1) or, on Beckmann pixels, the Beckmann NDF with that matrix
    (Kaplanyan et al. 2016's own case, where ``A = alpha^2 I + 2 Sigma`` is exact in slope
    space), with Mitsuba's separable Smith term and the pixel's Fresnel term;
    ``masking="material"``: ``G1 G1`` of the material's own roughness instead (its
    anisotropic matrix ``am`` when given; :data:`glossrt.specaa.MASKING`)."""
    h = dr.normalize(wo + wi)
    fr = sp.fresnel_at(dr.dot(wo, h))
    if masking == "filtered":
        return fr * cggx.brdf_separable_dr(wo, wi, a[0], a[1], a[2], sp.beckmann)
    beck = sp.beckmann
    # D of the filtered A (Tokuyoshi, eq. A.1-3 / Beckmann), G1 G1 of the material's roughness
    d = cggx.D_lobe_dr(h, a[0], a[1], a[2], beck)
    if am is not None:
        g = cggx.G1_lobe_dr(wo, *am, beck) * cggx.G1_lobe_dr(wi, *am, beck)
    else:
        g = mf.G1(wo.z, sp.alpha, beck) * mf.G1(wi.z, sp.alpha, beck)
    val = d * g / (4.0 * dr.maximum(wo.z * wi.z, 1e-30))
    ok = (wo.z > 0.0) & (wi.z > 0.0)
    return fr * dr.select(ok, val, 0.0)


def _shade_lanes(q: _Quad, method: Method, lights: list, polygons: list, two_sided: tuple,
                 table, textures: Sequence = ()) -> mi.Color3f:
    sp = q.sp
    total = dr.zeros(mi.Color3f, dr.width(sp.p))
    frame = mi.Frame3f(q.t, q.b, sp.n)
    wo_l = frame.to_local(sp.wo)
    am = material_matrix(q) if method.masking == "material" else None
    shared = None if method.per_light else filtered_roughness(q, method)
    for light in lights:
        wi, e = analytic.incident(light, sp.p)
        a = shared if shared is not None else filtered_roughness(q, method, light, "analytic")
        wi_l = frame.to_local(wi)
        cos_i = wi_l.z
        ok = sp.hit & (cos_i > 0) & (wo_l.z > 0)
        spec = _specular(wo_l, wi_l, a, sp, method.masking, am) * cos_i
        diff = sp.albedo * (cos_i / dr.pi)
        total += dr.select(ok, e * (spec + diff), 0.0)
    if polygons:
        if shared is not None:
            sp_f = replace(sp, alpha=isotropic_alpha(*shared))
            total += _ltc._shade(sp_f, table, polygons, two_sided, textures)
        else:
            for k, (world, le) in enumerate(polygons):
                centroid = sum(world[1:], world[0]) / len(world)
                a = filtered_roughness(q, method, centroid, "polygon")
                sp_f = replace(sp, alpha=isotropic_alpha(*a))
                total += _ltc._shade(sp_f, table, [(world, le)], two_sided[k:k + 1],
                                     textures[k:k + 1])
    return dr.select(sp.hit, total, 0.0)


def _kernel(ch: dict, cam: list, method: Method, lights: list, polygons: list,
            two_sided: tuple, table, size: tuple[int, int], textures: Sequence = ()
            ) -> mi.TensorXf:
    # the image size is an explicit (key) argument: dr.freeze may replay a recording made
    # for another size, and sizes read off the input tensors are baked into the recording
    h, w = size
    sp = ShadingPoints.at_camera(ch, cam)
    q = _quad(ch, sp, mi.Point3f(*cam), size, method.per_light, method.source != "none")
    c = _shade_lanes(q, method, lights, polygons, two_sided, table, textures)
    return merge([c[0], c[1], c[2]], h, w)


_kernel_frozen = dr.freeze(_kernel, warn_after=32)


def shade_tensor(frame, lights: Sequence = (), polygons: Sequence = (), method: str = "none",
                 f0: np.ndarray | None = None, kappa: float | None = None,
                 frozen: bool = False, textures: dict | None = None,
                 masking: str = "filtered") -> mi.TensorXf:
    """:func:`shade` as an (H, W, 3) ``mi.TensorXf`` left on the device. ``frozen=True``
    records the kernels once with ``dr.freeze`` and replays them for later frames of the same
    size, method and light set (the real-time path); with a textured polygon light the
    kernels are traced anew (as :func:`glossrt.lights.ltc.shade.shade_tensor`). ``textures``: a
    cache {id(texture): prefiltered} reused across frames."""
    check_frame(frame, NEEDS)
    if frame.camera is None:
        raise FrameError(f"{frame.where}: specular antialiasing needs the camera")
    m = parse_method(method, kappa, masking)
    dev = analytic.device_lights(list(lights))
    polys, two = _ltc._device_lights(list(polygons))
    ch = shading_channels(frame)
    ch["f0"] = f0_tensor(frame, f0)
    size = (frame.height, frame.width)
    cam = opaque(frame.camera.position)
    with no_gc():
        if any(getattr(lt, "texture", None) is not None for lt in polygons):
            cache = {} if textures is None else textures
            tex = [_ltc.prefiltered(lt, cache) for lt in polygons]
            out = _kernel(ch, cam, m, dev, polys, two, _ltc._table(), size, tex)
        else:
            fn = _kernel_frozen if frozen else _kernel
            out = fn(ch, cam, m, dev, polys, two, _ltc._table(), size)
        dr.eval(out)
    return out


def shade(frame, lights: Sequence = (), polygons: Sequence = (), method: str = "none",
          f0: np.ndarray | None = None, kappa: float | None = None,
          frozen: bool = False, textures: dict | None = None,
          masking: str = "filtered") -> np.ndarray:
    """Direct light (H, W, 3) of ``frame``'s G-buffer with specular antialiasing ``method``.

    ``lights``: point / directional lights (:func:`glossrt.lights.analytic.analytic_lights`);
    ``polygons``: polygon lights (:func:`glossrt.lights.scene.polygon_lights`; textured ones
    prefiltered as in :mod:`glossrt.lights.ltc`), shaded by LTC with the filtered roughness;
    ``f0`` (H, W, 3) per-pixel Fresnel F0 (:func:`glossrt.lights.shading.f0_image`, default
    0); ``kappa``: clamp of the added
    roughness (:mod:`glossrt.specaa`). Diffuse (Lambert, ``albedo_diffuse``) plus GGX or Beckmann
    specular (the ``distribution`` channel),
    unshadowed. The frame needs position, normal, roughness, albedo_diffuse, mesh_id and
    its camera. ``textures``: see :func:`shade_tensor`; ``masking``:
    :data:`glossrt.specaa.MASKING`."""
    out = shade_tensor(frame, lights, polygons, method, f0, kappa, frozen, textures, masking)
    return np.array(out, dtype=np.float32).reshape(frame.height, frame.width, 3)
