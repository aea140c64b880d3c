"""The two microfacet distributions Mitsuba 3 renders, GGX and Beckmann, as the renderer
evaluates them (``include/mitsuba/render/microfacet.h``, ``MicrofacetDistribution``).

Mitsuba's ``roughconductor`` and ``roughplastic`` default to **Beckmann** when the scene sets no
``distribution``; glossrt reads the distribution of every BSDF
(:func:`glossrt.render.materials.describe_bsdf`) and records it per pixel in the Frame's
``distribution`` channel (:data:`GGX` = 0, :data:`BECKMANN` = 1; :data:`NO_LOBE` = 2 where no
GGX or Beckmann lobe describes the surface, e.g. smooth glass or a blend of unlike lobes;
docs/FORMATS.md).

Everything here is generic over the distribution: ``beckmann`` is a Python ``bool`` (one
distribution, traced once) or a per-lane Dr.Jit ``Bool`` (both evaluated, selected per lane).

* ``D``: GGX (Walter et al. 2007, eq. 33) or Beckmann (Walter et al. 2007, eq. 25), isotropic;
* ``G1``: Smith's masking term as Mitsuba computes it: GGX exactly (Walter et al. 2007,
  eq. 34), Beckmann by the rational approximation of Walter et al. 2007, eq. 27 (< 0.35 %
  from the exact erf form); the BRDF's shadowing-masking is the *separable* product
  ``G1(wo) G1(wi)`` (Walter et al. 2007, eq. 23), which Mitsuba renders;
* sampling: GGX visible normals (Heitz 2018, :func:`glossrt.brdf.ggx.sample_vndf`, the same
  distribution as Mitsuba's ``sample_visible``), Beckmann normals from ``D(h) cos(theta_h)``
  (Walter et al. 2007, eqs. 28-29: ``tan^2 theta_h = -alpha^2 ln(1 - u1)``), with
  :func:`pdf_h` the density of either.

The specular lobe with Fresnel 1 is ``f cos(theta_i) = D(h) G1(wo) G1(wi) / (4 cos_o)``
(Walter et al. 2007, eq. 20 times ``cos_i``): :func:`specular_cos`.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import drjit as dr

__all__ = ["GGX", "BECKMANN", "NO_LOBE", "NAMES", "code", "by_distribution", "D", "G1",
           "specular_cos",
           "sample_h", "pdf_h", "aniso_specular_cos", "sample_h_aniso", "pdf_h_aniso"]

#: ``distribution`` channel values
GGX = 0
BECKMANN = 1
#: the ``distribution`` channel where no GGX or Beckmann lobe describes the surface ("no
#: analytic lobe": smooth glass, ``principled``, a blend of unlike lobes, ...); shading code
#: that reads a distribution treats it as GGX, and the analytic direct-light methods do not
#: shade such pixels (the path tracer does)
NO_LOBE = 2
#: names as Mitsuba's ``distribution`` parameter spells them, by code
NAMES = ("ggx", "beckmann")


def code(name: str) -> int:
    """:data:`GGX` or :data:`BECKMANN` for Mitsuba's name of a distribution."""
    return NAMES.index(name.lower())


def by_distribution(beckmann: Any, fb: Callable[[], Any], fg: Callable[[], Any]) -> Any:
    """``fb()`` (Beckmann's value) where ``beckmann``, else ``fg()`` (GGX's): one branch for a
    Python bool (one distribution, traced once), a per-lane select of both for a Dr.Jit
    mask."""
    if isinstance(beckmann, bool):
        return fb() if beckmann else fg()
    return dr.select(beckmann, fb(), fg())


def D(cos_h: Any, alpha: Any, beckmann: Any = False, sin2_h: Any = None) -> Any:
    """Isotropic normal distribution ``D(h)`` for ``cos_h = n.h`` (0 for ``cos_h <= 0``),
    normalised so that ``integral D(h) cos(theta_h) dh = 1``. ``sin2_h``: ``1 - cos_h^2``
    computed from the tangential components (``|n x h|^2``): in float32 ``1 - cos^2``
    vanishes for angles below ~3e-4 rad, so near-mirror lobes (alpha ~1e-4, Mitsuba's smooth
    plugins) need it, or every direction within that angle reads the peak."""
    c2 = cos_h * cos_h
    s2 = (1.0 - c2) if sin2_h is None else sin2_h
    a2 = alpha * alpha

    def beck():
        # Walter et al. 2007, eq. 25: exp(-tan^2 / alpha^2) / (pi alpha^2 cos^4)
        c2s = dr.maximum(c2, 1e-30)
        return dr.exp(-s2 / (c2s * a2)) / (dr.pi * a2 * c2s * c2s)

    def ggx():
        # Walter et al. 2007, eq. 33, as c2 (a2 - 1) + 1 ordered against cancellation
        d = s2 + c2 * a2
        return a2 / (dr.pi * d * d)

    return dr.select(cos_h > 0.0, by_distribution(beckmann, beck, ggx), 0.0)


def G1(cos_theta: Any, alpha: Any, beckmann: Any = False) -> Any:
    """Smith's masking ``G1(v)`` for ``cos_theta = n.v`` as Mitsuba's ``smith_g1`` (0 for
    ``cos_theta <= 0``; callers check ``v.h > 0`` themselves, as for a reflection
    ``wi.h = wo.h``)."""
    c = dr.maximum(cos_theta, 0.0)
    s2 = dr.maximum(1.0 - c * c, 0.0)

    def beck():
        # Walter et al. 2007, eq. 27: a = 1 / (alpha tan theta), rational approximation
        a = c * dr.rsqrt(dr.maximum(alpha * alpha * s2, 1e-30))
        r = (3.535 * a + 2.181 * a * a) / (1.0 + 2.276 * a + 2.577 * a * a)
        return dr.select((a >= 1.6) | (s2 <= 0.0), 1.0, r)

    def ggx():
        # Walter et al. 2007, eq. 34 as 2c / (c + sqrt(c^2 + alpha^2 s^2)): finite at c = 0
        return 2.0 * c / (c + dr.sqrt(c * c + alpha * alpha * s2))

    return dr.select(c > 0.0, by_distribution(beckmann, beck, ggx), 0.0)


def specular_cos(cos_o: Any, cos_i: Any, cos_h: Any, alpha: Any, beckmann: Any = False,
                 sin2_h: Any = None) -> Any:
    """``f cos(theta_i)`` of the specular lobe with Fresnel 1 and Mitsuba's separable Smith
    term: ``D(h) G1(wo) G1(wi) / (4 cos_o)`` (Walter et al. 2007, eqs. 20 and 23); 0 when
    either direction is below the surface. (For a reflection ``wo.h = wi.h``, positive
    whenever both are above it.) ``sin2_h``: see :func:`D`."""
    g = G1(cos_o, alpha, beckmann) * G1(cos_i, alpha, beckmann)
    val = D(cos_h, alpha, beckmann, sin2_h) * g / (4.0 * dr.maximum(cos_o, 1e-8))
    return dr.select((cos_o > 0.0) & (cos_i > 0.0), val, 0.0)


def sample_h(wo_x: Any, wo_y: Any, wo_z: Any, alpha: Any, u1: Any, u2: Any,
             beckmann: Any = False) -> tuple[Any, Any, Any]:
    """A half vector (local frame, ``z`` = normal) for the view ``wo`` (``wo_z > 0``): GGX
    visible normals (Heitz 2018) or Beckmann ``D(h) cos(theta_h)`` (Walter et al. 2007,
    eqs. 28-29); :func:`pdf_h` is its density."""
    from .ggx import sample_vndf

    def beck():
        # Walter et al. 2007, eq. 28: tan^2 theta_h = -alpha^2 ln(1 - u1); eq. 29: phi
        t2 = -alpha * alpha * dr.log(dr.maximum(1.0 - u1, 1e-30))
        cz = dr.rsqrt(1.0 + t2)
        sz = dr.sqrt(dr.maximum(1.0 - cz * cz, 0.0))
        sp, cp = dr.sincos(2.0 * dr.pi * u2)
        return sz * cp, sz * sp, cz

    if isinstance(beckmann, bool):
        return beck() if beckmann else sample_vndf(wo_x, wo_y, wo_z, alpha, u1, u2)
    b = beck()
    g = sample_vndf(wo_x, wo_y, wo_z, alpha, u1, u2)
    return tuple(dr.select(beckmann, bb, gg) for bb, gg in zip(b, g, strict=True))


def pdf_h(wo_z: Any, wo_h: Any, h_z: Any, alpha: Any, beckmann: Any = False,
          sin2_h: Any = None) -> Any:
    """Density (per steradian of ``h``) of :func:`sample_h`: GGX visible normals
    ``G1(wo) max(0, wo.h) D(h) / cos_o`` (Heitz 2018), Beckmann ``D(h) cos(theta_h)``.
    ``sin2_h``: see :func:`D`."""
    d = D(h_z, alpha, beckmann, sin2_h)

    def beck():
        return d * dr.maximum(h_z, 0.0)

    def ggx():
        return G1(wo_z, alpha, False) * dr.maximum(wo_h, 0.0) * d / dr.maximum(wo_z, 1e-8)

    return by_distribution(beckmann, beck, ggx)


# ----------------------------------------------------------------------------------------------
# Anisotropic lobes (Mitsuba's alpha_u, alpha_v along its shading frame's s and t)
# ----------------------------------------------------------------------------------------------


def aniso_specular_cos(wo, wi, alpha_u, alpha_v, beckmann: Any = False) -> Any:
    """``f cos(theta_i)`` (Fresnel 1) of an anisotropic lobe, local directions in the frame
    ``(s, t, n)`` whose axes carry ``alpha_u`` and ``alpha_v`` (Mitsuba's): ``D(h) G1(wo)
    G1(wi) / (4 cos_o)`` with GGX's or Beckmann's ``D`` and Smith ``G1`` for the roughness
    matrix ``diag(alpha_u^2, alpha_v^2)`` (Walter et al. 2007; Heitz 2014, sec. 5:
    :mod:`glossrt.brdf.covariance_ggx`'s forms). Isotropic when ``alpha_u = alpha_v``."""
    from .covariance_ggx import D_lobe_dr, G1_lobe_dr

    a11, a22 = alpha_u * alpha_u, alpha_v * alpha_v
    h = wo + wi
    h = h * dr.rsqrt(dr.maximum(dr.squared_norm(h), 1e-30))
    val = (D_lobe_dr(h, a11, 0.0, a22, beckmann) * G1_lobe_dr(wo, a11, 0.0, a22, beckmann)
           * G1_lobe_dr(wi, a11, 0.0, a22, beckmann) / (4.0 * dr.maximum(wo.z, 1e-8)))
    return dr.select((wo.z > 0.0) & (wi.z > 0.0), val, 0.0)


def sample_h_aniso(wo, alpha_u, alpha_v, u1, u2, beckmann: Any = False):
    """A half vector (local frame) of an anisotropic lobe: GGX visible normals (Heitz 2018,
    stretched by ``(alpha_u, alpha_v)``) or Beckmann normals from ``D(h) cos(theta_h)``
    (Walter et al. 2007, eqs. 28-29 with the anisotropic phi of Ward 1992: ``tan phi =
    (alpha_v / alpha_u) tan(2 pi u2)``); :func:`pdf_h_aniso` is its density. Returns a
    3-vector of the type of ``wo``."""
    from .ggx import sample_vndf

    vt = type(wo)

    def ggx():
        # stretch the view by (alpha_u, alpha_v), sample the alpha = 1 hemisphere, unstretch
        gx, gy, gz = sample_vndf(wo.x * alpha_u, wo.y * alpha_v, wo.z, 1.0, u1, u2)
        return dr.normalize(vt(gx * alpha_u, gy * alpha_v, dr.maximum(gz, 0.0)))

    def beck():
        phi = dr.atan2(alpha_v * dr.sin(2.0 * dr.pi * u2), alpha_u * dr.cos(2.0 * dr.pi * u2))
        sp_, cp = dr.sincos(phi)
        inv_a2 = cp * cp / (alpha_u * alpha_u) + sp_ * sp_ / (alpha_v * alpha_v)
        t2 = -dr.log(dr.maximum(1.0 - u1, 1e-30)) / inv_a2
        cz = dr.rsqrt(1.0 + t2)
        sz = dr.sqrt(dr.maximum(1.0 - cz * cz, 0.0))
        return vt(sz * cp, sz * sp_, cz)

    return by_distribution(beckmann, beck, ggx)


def pdf_h_aniso(wo, h, alpha_u, alpha_v, beckmann: Any = False) -> Any:
    """Density (per steradian of ``h``) of :func:`sample_h_aniso`: GGX visible normals
    ``G1(wo) max(0, wo.h) D(h) / cos_o``, Beckmann ``D(h) cos(theta_h)``."""
    from .covariance_ggx import D_lobe_dr, G1_dr

    a11, a22 = alpha_u * alpha_u, alpha_v * alpha_v
    dh = D_lobe_dr(h, a11, 0.0, a22, beckmann)

    def beck():
        return dh * dr.maximum(h.z, 0.0)

    def ggx():
        return G1_dr(wo, a11, 0.0, a22) * dr.maximum(dr.dot(wo, h), 0.0) * dh / \
            dr.maximum(wo.z, 1e-8)

    return by_distribution(beckmann, beck, ggx)
