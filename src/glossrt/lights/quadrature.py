"""Float64 NumPy ground truth for polygon-light integrals: the microfacet lobe (GGX or
Beckmann with Mitsuba's separable Smith term, Fresnel = 1) times the clamped cosine integrated
over a polygon's *area* with the midpoint rule (independent of the LTC fit, of the edge-integral
code and of :mod:`glossrt.brdf.microfacet`; used by the tests and the accuracy experiment)."""

from __future__ import annotations

import math

import numpy as np


def _g1(c, alpha: float, distribution: str) -> np.ndarray:
    """Smith's G1 for ``c = n.v`` (> 0): GGX ``2 / (1 + sqrt(1 + alpha^2 tan^2))`` (Walter et
    al. 2007, eq. 34); Beckmann by the rational approximation Mitsuba uses (eq. 27)."""
    c = np.clip(np.asarray(c, np.float64), 1e-300, 1.0)
    t = np.sqrt(np.maximum(1 - c * c, 0.0)) / c
    if distribution == "beckmann":
        with np.errstate(divide="ignore"):
            a = 1.0 / (alpha * t)
        r = (3.535 * a + 2.181 * a * a) / (1 + 2.276 * a + 2.577 * a * a)
        return np.where(a >= 1.6, 1.0, r)
    return 2.0 * c / (c + np.sqrt(c * c + (alpha * alpha) * (1.0 - c * c)))


def microfacet_cos(wi: np.ndarray, wo: np.ndarray, n: np.ndarray, alpha: float,
                   distribution: str = "ggx") -> np.ndarray:
    """``rho(wo, wi) cos_i = D(h) G1(wo) G1(wi) / (4 cos_o)`` (Walter et al. 2007, eqs. 20, 23;
    ``D`` GGX eq. 33 or Beckmann eq. 25), float64, batched over ``wi``'s leading axes; 0 below
    either horizon."""
    cos_i = np.sum(wi * n, -1)
    cos_o = float(np.dot(wo, n))
    h = wi + wo
    h = h / np.linalg.norm(h, axis=-1, keepdims=True)
    ch = np.sum(h * n, -1)
    a2 = alpha * alpha
    if distribution == "beckmann":
        c2 = np.maximum(ch**2, 1e-300)
        d = np.where(ch > 0, np.exp(-(1 - c2) / (c2 * a2)) / (math.pi * a2 * c2 * c2), 0.0)
    else:
        d = a2 / (math.pi * ((1 - ch**2) + ch**2 * a2) ** 2)
    g = _g1(cos_o, alpha, distribution) * _g1(cos_i, alpha, distribution)
    ok = (cos_i > 0) & (cos_o > 0)
    return np.where(ok, d * g / (4 * max(cos_o, 1e-300)), 0.0)


def polygon_quadrature(verts: np.ndarray, wo: np.ndarray, n: np.ndarray, alpha: float,
                       m: int = 96, one_sided: bool = True, distribution: str = "ggx") -> float:
    """``int_P rho cos dw`` for a triangle ``(v0, v1, v2)`` or a parallelogram ``(v0, v1, v2,
    v3)`` given relative to the shading point, as ``int_A rho cos |cos_l| / d^2 dA`` on an
    ``m x m`` midpoint grid. ``one_sided``: only if the polygon's right-hand normal faces the
    point (counter-clockwise seen from it); ``distribution`` ``"ggx"`` or ``"beckmann"``."""
    v = np.asarray(verts, np.float64)
    a, e1 = v[0], v[1] - v[0]
    e2 = v[3] - v[0] if len(v) == 4 else v[2] - v[0]
    cr = np.cross(v[1] - v[0], v[2] - v[0])
    if one_sided and np.dot(cr, -v[0]) <= 0:
        return 0.0
    s = (np.arange(m) + 0.5) / m
    su, sv = np.meshgrid(s, s)
    keep = np.ones_like(su, bool) if len(v) == 4 else (su + sv < 1)
    y = a + su[..., None] * e1 + sv[..., None] * e2
    c = np.cross(e1, e2)
    nl = c / np.linalg.norm(c)
    d2 = np.sum(y * y, -1)
    wi = y / np.sqrt(d2)[..., None]
    f = microfacet_cos(wi, wo, n, alpha, distribution)
    return float(np.sum(np.where(keep, f * np.abs(wi @ nl) / d2, 0.0))
                 * np.linalg.norm(c) / m**2)
