"""Float64 NumPy ground truth for polygon-light integrals: the GGX lobe (height-correlated
Smith, Fresnel = 1) times the clamped cosine integrated over a polygon's *area* with the
midpoint rule (independent of the LTC fit and of the edge-integral code; used by the tests and
the accuracy experiment)."""

from __future__ import annotations

import math

import numpy as np


def ggx_cos(wi: np.ndarray, wo: np.ndarray, n: np.ndarray, alpha: float) -> np.ndarray:
    """``rho(wo, wi) cos_i = D(h) G2 / (4 cos_o)`` (Walter et al. 2007, eq. 20; Heitz 2014,
    eq. 99 for G2), float64, batched over ``wi``'s leading axes; 0 below either horizon."""
    cos_i = np.sum(wi * n, -1)
    cos_o = float(np.dot(wo, n))
    h = wi + wo
    h = h / np.linalg.norm(h, axis=-1, keepdims=True)
    ch = np.sum(h * n, -1)
    a2 = alpha * alpha
    d = a2 / (math.pi * ((1 - ch**2) + ch**2 * a2) ** 2)

    def lam(c):
        c2 = np.maximum(np.asarray(c) ** 2, 1e-300)
        return 0.5 * (np.sqrt(1 + a2 * (1 - c2) / c2) - 1)

    g2 = 1 / (1 + lam(cos_o) + lam(cos_i))
    ok = (cos_i > 0) & (cos_o > 0)
    return np.where(ok, d * g2 / (4 * max(cos_o, 1e-300)), 0.0)


def polygon_quadrature(verts: np.ndarray, wo: np.ndarray, n: np.ndarray, alpha: float,
                       m: int = 96, one_sided: bool = True) -> float:
    """``int_P rho cos dw`` for a triangle ``(v0, v1, v2)`` or a parallelogram ``(v0, v1, v2,
    v3)`` given relative to the shading point, as ``int_A rho cos |cos_l| / d^2 dA`` on an
    ``m x m`` midpoint grid. ``one_sided``: only if the polygon's right-hand normal faces the
    point (counter-clockwise seen from it)."""
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
    f = ggx_cos(wi, wo, n, alpha)
    return float(np.sum(np.where(keep, f * np.abs(wi @ nl) / d2, 0.0))
                 * np.linalg.norm(c) / m**2)
