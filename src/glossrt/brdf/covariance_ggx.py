"""GGX with a 2x2 roughness (covariance) matrix: the BRDF of Tokuyoshi's appendix A.1.

Y. Tokuyoshi's evaluation of Kaplanyan, Hill, Patney, Lefohn 2016 ("Filtering Distributions of
Normals for Shading Antialiasing", HPG 2016), appendix A.1 (共分散行列ベースの GGX BRDF). The
appendix's four displayed equations are unnumbered; the code cites them in order as

* eq. A.1-1, the microfacet BRDF (Cook & Torrance 1982)::

      f(wi, wo) = G2(wi, wo, m) D(m) F(m.wo) / (4 |wi.n| |wo.n|),   m = normalize(wi + wo);

* eq. A.1-2, Smith's height-correlated masking-shadowing with ``G1(w) = 1 / (1 + Lambda(w))``::

      G2(wi, wo, m) = 1 / (1 + Lambda(wi) + Lambda(wo));

* eq. A.1-3, the NDF for a symmetric positive-definite roughness matrix ``A`` (shape
  invariance: the microsurface is the GGX one stretched along the eigenvectors of ``A``, with
  squared scales the eigenvalues of ``A``); in tangent space ``m = (x, y, z)``::

      D(m) = 1 / (pi sqrt(det A) ([x, y] A^-1 [x, y]^T + z^2)^2);

* eq. A.1-4, the Smith Lambda (stretch invariance); ``w = (x, y, z)``::

      Lambda(w) = -1/2 + sqrt([x, y] A [x, y]^T + z^2) / (2 |z|).

``A = alpha^2 I`` is isotropic GGX (:func:`glossrt.brdf.ggx.D_ggx`, :func:`~glossrt.brdf.ggx.
G1_smith`), ``A = diag(alpha_x^2, alpha_y^2)`` the anisotropic GGX of Heitz 2014, and a
rotation ``R`` of the tangent plane maps ``A`` to ``R A R^T``. ``A`` is the covariance of the
microfacet slopes scaled as in Kaplanyan et al. (``A = alpha^2 I`` has slope "variance"
``alpha^2``). As in the appendix, ``D`` is zero for ``z <= 0`` (Heitz 2014's ``chi+``) and the
BRDF is one-sided (zero unless ``wo.z > 0`` and ``wi.z > 0``); the Fresnel term is Schlick's
``F0 + (1 - F0)(1 - wo.m)^5`` (Schlick 1994). Unlike :mod:`glossrt.brdf.ggx` (Mitsuba's separable
``G1 G1``), ``G2`` here is the height-correlated form of eq. A.1-2.

Sampling (not in the paper): with the Cholesky factor ``A = L L^T`` the microsurface is the
``alpha = 1`` GGX surface whose tangent coordinates are mapped by ``L^-T``: directions map to the
``alpha = 1`` configuration as ``(x, y, z) -> (L^T [x, y], z)`` and microfacet normals back as
``(x, y, z) -> (L [x, y], z)`` (each followed by a normalisation). ``L = diag(alpha_x, alpha_y)``
gives the usual stretch of Heitz 2018. :func:`sample_vndf` samples the visible normals of the
``alpha = 1`` surface with spherical caps (Dupuy & Benyoub 2023), :func:`sample_vndf_dr` with
Heitz 2018's hemisphere construction (:func:`glossrt.brdf.ggx.sample_vndf` at ``alpha = 1``).
Both draw ``m`` with density ``D_wo(m) = G1(wo) max(0, wo.m) D(m) / wo.z`` (Heitz 2014, eq. 2
normalisation of visible normals).

Public API:

* NumPy (float64, batched over leading axes with broadcasting; ``m, w: (..., 3)`` unit vectors
  in the tangent frame, z = normal; ``A: (..., 2, 2)``): :func:`D`, :func:`Lambda`, :func:`G1`,
  :func:`G2`, :func:`brdf`, :func:`sample_vndf`, :func:`vndf_pdf`. Bad input (wrong shapes,
  NaN/Inf, non-unit vectors, ``A`` not symmetric positive-definite) raises
  :class:`glossrt.errors.GlossrtError`.
* Dr.Jit (per-pixel kernels, generic over the float type; ``A`` given by its entries ``a11,
  a12, a22``, Python floats or Dr.Jit floats; nothing is validated there): :func:`D_dr`,
  :func:`Lambda_dr`, :func:`G1_dr`, :func:`G2_dr`, :func:`brdf_dr`, :func:`sample_vndf_dr`.

References:
    Y. Tokuyoshi, evaluation of Kaplanyan et al. 2016 (Japanese), appendix A.1.
    A. Kaplanyan, S. Hill, A. Patney, A. Lefohn, "Filtering Distributions of Normals for
    Shading Antialiasing", HPG 2016.
    E. Heitz, "Understanding the Masking-Shadowing Function in Microfacet-Based BRDFs",
    JCGT 3(2), 2014.
    E. Heitz, "Sampling the GGX Distribution of Visible Normals", JCGT 7(4), 2018.
    J. Dupuy, A. Benyoub, "Sampling Visible GGX Normals with Spherical Caps", HPG 2023.
    C. Schlick, "An Inexpensive BRDF Model for Physically-based Rendering", CGF 13(3), 1994.
"""

from __future__ import annotations

from typing import Any, TypeVar

import drjit as dr
import numpy as np

from ..backend import mi
from ..errors import GlossrtError
from . import ggx
from .microfacet import by_distribution

__all__ = [
    "D",
    "Lambda",
    "G1",
    "G2",
    "brdf",
    "sample_vndf",
    "vndf_pdf",
    "D_dr",
    "Lambda_dr",
    "G1_dr",
    "G2_dr",
    "brdf_dr",
    "sample_vndf_dr",
    "D_beckmann_dr",
    "G1_beckmann_dr",
    "D_lobe_dr",
    "G1_lobe_dr",
    "brdf_separable_dr",
]

#: Allowed deviation of ``|v|`` from 1 for the unit-vector inputs of the NumPy functions.
UNIT_TOL = 1e-5
#: Allowed asymmetry ``|a12 - a21| / max|a|`` of a roughness matrix.
SYM_TOL = 1e-9

F = TypeVar("F")  # a Dr.Jit floating point array type (mi.Float, Float64, ...)


# ----------------------------------------------------------------------------------------------
# Input checks (NumPy API)
# ----------------------------------------------------------------------------------------------


def _vec3(name: str, v: Any) -> np.ndarray:
    try:
        a = np.asarray(v, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise GlossrtError(f"{name} must be a numeric array of shape (..., 3): {e}") from None
    if a.ndim < 1 or a.shape[-1] != 3:
        raise GlossrtError(f"{name} must have shape (..., 3), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise GlossrtError(f"{name} contains NaN or Inf")
    n = np.sqrt(np.sum(a * a, axis=-1))
    if a.size and np.max(np.abs(n - 1.0)) > UNIT_TOL:
        raise GlossrtError(
            f"{name} must hold unit vectors (max | |v| - 1 | = {np.max(np.abs(n - 1.0)):.3g})"
        )
    return a


def _roughness(A: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Validated entries ``(a11, a12, a22)`` of a batch of SPD 2x2 matrices."""
    try:
        a = np.asarray(A, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise GlossrtError(f"A must be a numeric array of shape (..., 2, 2): {e}") from None
    if a.ndim < 2 or a.shape[-2:] != (2, 2):
        raise GlossrtError(f"A must have shape (..., 2, 2), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise GlossrtError("A contains NaN or Inf")
    a11, a12, a21, a22 = a[..., 0, 0], a[..., 0, 1], a[..., 1, 0], a[..., 1, 1]
    scale = np.maximum(np.max(np.abs(a), axis=(-2, -1)), np.finfo(np.float64).tiny)
    if np.any(np.abs(a12 - a21) > SYM_TOL * scale):
        raise GlossrtError("A must be symmetric (A[..., 0, 1] != A[..., 1, 0])")
    sym = 0.5 * (a12 + a21)
    det = a11 * a22 - sym * sym
    if np.any(a11 <= 0.0) or np.any(det <= 0.0):
        raise GlossrtError(
            "A must be positive-definite (a11 > 0 and det A > 0); "
            f"min a11 = {np.min(a11):.3g}, min det = {np.min(det):.3g}"
        )
    return a11, sym, a22


def _batch(name: str, *shapes: tuple[int, ...]) -> tuple[int, ...]:
    try:
        return np.broadcast_shapes(*shapes)
    except ValueError:
        raise GlossrtError(f"{name}: batch shapes {shapes} do not broadcast") from None


# ----------------------------------------------------------------------------------------------
# NumPy implementation (float64)
# ----------------------------------------------------------------------------------------------


def _D(x, y, z, a11, a12, a22):
    det = a11 * a22 - a12 * a12
    # [x, y] A^-1 [x, y]^T with A^-1 = [[a22, -a12], [-a12, a11]] / det.
    q = (a22 * x * x - 2.0 * a12 * x * y + a11 * y * y) / det + z * z
    # Tokuyoshi, appendix A.1, eq. A.1-3 (zero below the horizon: chi+(m.n)).
    return np.where(z > 0.0, 1.0 / (np.pi * np.sqrt(det) * q * q), 0.0)


def _root(x, y, z, a11, a12, a22):
    """``sqrt([x, y] A [x, y]^T + z^2)``, the numerator of eq. A.1-4."""
    return np.sqrt(np.maximum(a11 * x * x + 2.0 * a12 * x * y + a22 * y * y + z * z, 0.0))


def _G1(x, y, z, a11, a12, a22):
    # 1 / (1 + Lambda) with Lambda of eq. A.1-4, written 2|z| / (|z| + root) (finite at z = 0);
    # zero for directions below the horizon.
    az = np.abs(z)
    den = az + _root(x, y, z, a11, a12, a22)
    with np.errstate(divide="ignore", invalid="ignore"):
        g = 2.0 * az / den
    return np.where((z > 0.0) & (den > 0.0), g, 0.0)


def _schlick(c, f0):
    m = 1.0 - np.clip(c, 0.0, 1.0)
    return f0 + (1.0 - f0) * (m * m) * (m * m) * m


def D(m: Any, A: Any) -> np.ndarray:
    """GGX normal distribution ``D(m; A)`` (Tokuyoshi, appendix A.1, eq. A.1-3).

    Args:
        m: microfacet normals, unit vectors of shape ``(..., 3)`` in the tangent frame
            (z = macro normal).
        A: symmetric positive-definite roughness matrices, shape ``(..., 2, 2)``.

    Returns:
        ``D`` with the broadcast batch shape; 0 for ``m.z <= 0``. Normalised so that
        ``integral D(m) m.z dm = 1`` over the hemisphere.
    """
    m = _vec3("m", m)
    a11, a12, a22 = _roughness(A)
    _batch("D(m, A)", m.shape[:-1], a11.shape)
    return _D(m[..., 0], m[..., 1], m[..., 2], a11, a12, a22)


def Lambda(w: Any, A: Any) -> np.ndarray:
    """Smith's ``Lambda(w; A)`` for GGX (Tokuyoshi, appendix A.1, eq. A.1-4).

    ``Lambda = -1/2 + sqrt([x, y] A [x, y]^T + z^2) / (2 |z|)`` for the unit direction ``w =
    (x, y, z)`` (shape ``(..., 3)``) and roughness ``A`` (``(..., 2, 2)``); ``+inf`` at
    ``z = 0``. Like the paper it depends on ``|z|`` only (symmetric under ``z -> -z``).
    """
    w = _vec3("w", w)
    a11, a12, a22 = _roughness(A)
    _batch("Lambda(w, A)", w.shape[:-1], a11.shape)
    x, y, z = w[..., 0], w[..., 1], w[..., 2]
    az = np.abs(z)
    root = _root(x, y, z, a11, a12, a22)
    with np.errstate(divide="ignore", invalid="ignore"):
        # Tokuyoshi, appendix A.1, eq. A.1-4.
        lam = -0.5 + root / (2.0 * az)
    return np.where(az > 0.0, lam, np.inf)


def G1(w: Any, A: Any, m: Any | None = None) -> np.ndarray:
    """Smith masking ``G1(w) = 1 / (1 + Lambda(w))`` (Tokuyoshi, appendix A.1, text of eq. A.1-2).

    Zero for ``w.z <= 0``. With microfacet normals ``m`` (``(..., 3)``) it is Heitz 2014's
    ``G1(w, m) = chi+(w.m) G1(w)``.
    """
    w = _vec3("w", w)
    a11, a12, a22 = _roughness(A)
    shapes = [w.shape[:-1], a11.shape]
    if m is not None:
        m = _vec3("m", m)
        shapes.append(m.shape[:-1])
    _batch("G1(w, A, m)", *shapes)
    g = _G1(w[..., 0], w[..., 1], w[..., 2], a11, a12, a22)
    if m is not None:
        g = np.where(np.sum(w * m, axis=-1) > 0.0, g, 0.0)
    return g


def G2(wo: Any, wi: Any, A: Any, m: Any | None = None) -> np.ndarray:
    """Height-correlated masking-shadowing ``1 / (1 + Lambda(wo) + Lambda(wi))``.

    Tokuyoshi, appendix A.1, eq. A.1-2. Zero unless ``wo.z > 0`` and ``wi.z > 0`` (reflection);
    with microfacet normals ``m`` also zero unless ``wo.m > 0`` and ``wi.m > 0``. Computed as
    ``2 zo zi / (zo r_i + zi r_o)`` with ``r`` the square roots of eq. A.1-4 (finite at grazing).
    """
    wo = _vec3("wo", wo)
    wi = _vec3("wi", wi)
    a11, a12, a22 = _roughness(A)
    shapes = [wo.shape[:-1], wi.shape[:-1], a11.shape]
    if m is not None:
        m = _vec3("m", m)
        shapes.append(m.shape[:-1])
    _batch("G2(wo, wi, A, m)", *shapes)
    return _G2(wo, wi, a11, a12, a22, m)


def _G2(wo, wi, a11, a12, a22, m=None):
    zo, zi = wo[..., 2], wi[..., 2]
    ro = _root(wo[..., 0], wo[..., 1], zo, a11, a12, a22)
    ri = _root(wi[..., 0], wi[..., 1], zi, a11, a12, a22)
    # 1 / (1 + Lambda_o + Lambda_i) = 1 / (ro / (2 zo) + ri / (2 zi)) (eq. A.1-2 with A.1-4).
    den = zo * ri + zi * ro
    ok = (zo > 0.0) & (zi > 0.0) & (den > 0.0)
    if m is not None:
        ok = ok & (np.sum(wo * m, axis=-1) > 0.0) & (np.sum(wi * m, axis=-1) > 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        g = 2.0 * zo * zi / den
    return np.where(ok, g, 0.0)


def brdf(wo: Any, wi: Any, A: Any, f0: Any = 1.0) -> np.ndarray:
    """The covariance-matrix GGX BRDF ``f(wo, wi)`` (Tokuyoshi, appendix A.1, eq. A.1-1).

    ``f = F(wo.m) D(m) G2(wo, wi) / (4 wo.z wi.z)`` with ``m = normalize(wo + wi)``, ``D`` of
    eq. A.1-3, ``G2`` of eq. A.1-2 and Schlick's Fresnel. Only ``f`` (no cosine factor). Zero
    unless both directions lie above the surface.

    Args:
        wo, wi: unit directions ``(..., 3)`` in the tangent frame.
        A: roughness matrices ``(..., 2, 2)``.
        f0: Schlick's normal-incidence reflectance, a float or an array broadcastable to the
            batch shape. For RGB, give ``f0`` shape ``(..., 3)`` and insert a channel axis in
            the others: ``brdf(wo[..., None, :], wi[..., None, :], A[..., None, :, :], f0)``.

    Returns:
        float64 array of the broadcast batch shape.
    """
    wo = _vec3("wo", wo)
    wi = _vec3("wi", wi)
    a11, a12, a22 = _roughness(A)
    f0 = np.asarray(f0, dtype=np.float64)
    if not np.all(np.isfinite(f0)):
        raise GlossrtError("f0 contains NaN or Inf")
    _batch("brdf(wo, wi, A, f0)", wo.shape[:-1], wi.shape[:-1], a11.shape, f0.shape)
    h = wo + wi
    hn = np.sqrt(np.sum(h * h, axis=-1))
    ok = (wo[..., 2] > 0.0) & (wi[..., 2] > 0.0) & (hn > 0.0)
    h = h / np.where(hn > 0.0, hn, 1.0)[..., None]
    d = _D(h[..., 0], h[..., 1], h[..., 2], a11, a12, a22)
    g = _G2(wo, wi, a11, a12, a22)
    fr = _schlick(np.sum(wo * h, axis=-1), f0)
    with np.errstate(divide="ignore", invalid="ignore"):
        # Tokuyoshi, appendix A.1, eq. A.1-1.
        f = fr * d * g / (4.0 * wo[..., 2] * wi[..., 2])
    return np.where(ok, f, 0.0)


def _cholesky(a11, a12, a22):
    l11 = np.sqrt(a11)
    l21 = a12 / l11
    l22 = np.sqrt(np.maximum(a22 - l21 * l21, 0.0))
    return l11, l21, l22


def sample_vndf(wo: Any, A: Any, u: Any) -> np.ndarray:
    """Sample microfacet normals from the visible-normal density ``D_wo(m)`` of ``wo``.

    ``D_wo(m) = G1(wo) max(0, wo.m) D(m) / wo.z`` (Heitz 2014), see :func:`vndf_pdf`. Maps
    ``wo`` to the ``alpha = 1`` configuration with ``L^T`` (``A = L L^T``), samples the visible
    hemisphere there with a spherical cap (Dupuy & Benyoub 2023) and maps the normal back with
    ``L`` (module docstring).

    Args:
        wo: unit view directions ``(..., 3)`` with ``wo.z > 0``.
        A: roughness matrices ``(..., 2, 2)``.
        u: uniform numbers in [0, 1), shape ``(..., 2)``.

    Returns:
        Unit normals ``(..., 3)`` (batch shape broadcast over the inputs).
    """
    wo = _vec3("wo", wo)
    a11, a12, a22 = _roughness(A)
    u = np.asarray(u, dtype=np.float64)
    if u.ndim < 1 or u.shape[-1] != 2:
        raise GlossrtError(f"u must have shape (..., 2), got {u.shape}")
    if not np.all(np.isfinite(u)):
        raise GlossrtError("u contains NaN or Inf")
    if np.any(wo[..., 2] <= 0.0):
        raise GlossrtError("sample_vndf needs wo.z > 0")
    _batch("sample_vndf(wo, A, u)", wo.shape[:-1], a11.shape, u.shape[:-1])
    l11, l21, l22 = _cholesky(a11, a12, a22)
    x, y, z = wo[..., 0], wo[..., 1], wo[..., 2]
    # Direction into the alpha = 1 configuration: (L^T [x, y], z).
    vx = l11 * x + l21 * y
    vy = l22 * y
    vz = z
    n = np.sqrt(vx * vx + vy * vy + vz * vz)
    vx, vy, vz = vx / n, vy / n, vz / n
    # Spherical cap sampling of the visible hemisphere (Dupuy & Benyoub 2023, listing 3).
    phi = 2.0 * np.pi * u[..., 0]
    cz = (1.0 - u[..., 1]) * (1.0 + vz) - vz
    st = np.sqrt(np.clip(1.0 - cz * cz, 0.0, 1.0))
    hx = st * np.cos(phi) + vx
    hy = st * np.sin(phi) + vy
    hz = cz + vz
    # Back to the A configuration: (L [hx, hy], hz).
    mx = l11 * hx
    my = l21 * hx + l22 * hy
    mz = np.maximum(hz, 0.0)
    n = np.sqrt(mx * mx + my * my + mz * mz)
    n = np.where(n > 0.0, n, 1.0)
    return np.stack(np.broadcast_arrays(mx / n, my / n, mz / n), axis=-1)


def vndf_pdf(wo: Any, m: Any, A: Any) -> np.ndarray:
    """Density per solid angle of :func:`sample_vndf`: ``G1(wo) max(0, wo.m) D(m) / wo.z``."""
    wo = _vec3("wo", wo)
    m = _vec3("m", m)
    a11, a12, a22 = _roughness(A)
    _batch("vndf_pdf(wo, m, A)", wo.shape[:-1], m.shape[:-1], a11.shape)
    g = _G1(wo[..., 0], wo[..., 1], wo[..., 2], a11, a12, a22)
    d = _D(m[..., 0], m[..., 1], m[..., 2], a11, a12, a22)
    c = np.maximum(np.sum(wo * m, axis=-1), 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        p = g * c * d / wo[..., 2]
    return np.where(wo[..., 2] > 0.0, p, 0.0)


# ----------------------------------------------------------------------------------------------
# Dr.Jit implementation (per-pixel kernels; generic over the float type, no validation)
# ----------------------------------------------------------------------------------------------


def _root_dr(w: Any, a11: Any, a12: Any, a22: Any) -> Any:
    x, y, z = w.x, w.y, w.z
    return dr.sqrt(dr.maximum(a11 * x * x + 2.0 * a12 * x * y + a22 * y * y + z * z, 0.0))


def D_dr(m: mi.Vector3f, a11: Any, a12: Any, a22: Any) -> Any:
    """Dr.Jit ``D(m; A)`` (Tokuyoshi, appendix A.1, eq. A.1-3) for ``A = [[a11, a12], [a12,
    a22]]`` (floats or Dr.Jit floats, SPD: not checked); 0 for ``m.z <= 0``. ``a11 = a22 =
    alpha^2``, ``a12 = 0`` gives :func:`glossrt.brdf.ggx.D_ggx`."""
    x, y, z = m.x, m.y, m.z
    det = a11 * a22 - a12 * a12
    q = (a22 * x * x - 2.0 * a12 * x * y + a11 * y * y) / det + z * z
    # Tokuyoshi, appendix A.1, eq. A.1-3.
    return dr.select(z > 0.0, dr.rcp(dr.pi * dr.sqrt(det) * q * q), 0.0)


def Lambda_dr(w: mi.Vector3f, a11: Any, a12: Any, a22: Any) -> Any:
    """Dr.Jit Smith ``Lambda(w; A)`` (Tokuyoshi, appendix A.1, eq. A.1-4); ``+inf`` at
    ``w.z = 0``."""
    # Tokuyoshi, appendix A.1, eq. A.1-4.
    return -0.5 + _root_dr(w, a11, a12, a22) / (2.0 * dr.abs(w.z))


def G1_dr(w: mi.Vector3f, a11: Any, a12: Any, a22: Any) -> Any:
    """Dr.Jit Smith masking ``1 / (1 + Lambda(w))`` (appendix A.1), as ``2 z / (z + root)``;
    0 for ``w.z <= 0``. Equals :func:`glossrt.brdf.ggx.G1_smith` for ``A = alpha^2 I``."""
    z = w.z
    den = z + _root_dr(w, a11, a12, a22)
    return dr.select((z > 0.0) & (den > 0.0), 2.0 * z / den, 0.0)


def G2_dr(wo: mi.Vector3f, wi: mi.Vector3f, a11: Any, a12: Any, a22: Any) -> Any:
    """Dr.Jit height-correlated ``G2 = 1 / (1 + Lambda(wo) + Lambda(wi))`` (Tokuyoshi,
    appendix A.1, eq. A.1-2); 0 unless ``wo.z > 0`` and ``wi.z > 0``."""
    zo, zi = wo.z, wi.z
    den = zo * _root_dr(wi, a11, a12, a22) + zi * _root_dr(wo, a11, a12, a22)
    # eq. A.1-2 with A.1-4: 1 / (ro / (2 zo) + ri / (2 zi)).
    return dr.select((zo > 0.0) & (zi > 0.0) & (den > 0.0), 2.0 * zo * zi / den, 0.0)


def brdf_dr(wo: mi.Vector3f, wi: mi.Vector3f, a11: Any, a12: Any, a22: Any, f0: Any) -> Any:
    """Dr.Jit covariance-matrix GGX BRDF (Tokuyoshi, appendix A.1, eq. A.1-1), ``f`` only.

    ``f0`` may be a float, a Dr.Jit float or ``mi.Color3f``; the result has the type of
    ``f0 * D``. Zero unless both directions lie above the surface.
    """
    h = wo + wi
    hn2 = dr.squared_norm(h)
    h = h * dr.rsqrt(dr.maximum(hn2, 1e-30))
    d = D_dr(h, a11, a12, a22)
    g = G2_dr(wo, wi, a11, a12, a22)
    fr = ggx.fresnel_schlick(dr.dot(wo, h), f0)
    ok = (wo.z > 0.0) & (wi.z > 0.0) & (hn2 > 0.0)
    # Tokuyoshi, appendix A.1, eq. A.1-1.
    val = d * g / (4.0 * wo.z * wi.z)
    return fr * dr.select(ok, val, 0.0)


def sample_vndf_dr(wo: mi.Vector3f, a11: Any, a12: Any, a22: Any, u1: Any, u2: Any) -> Any:
    """Dr.Jit sampler of the visible normals ``D_wo(m)`` for roughness ``A`` (``wo.z > 0``).

    Maps ``wo`` to the ``alpha = 1`` configuration with ``L^T`` (``A = L L^T``, Cholesky),
    samples there with :func:`glossrt.brdf.ggx.sample_vndf` (Heitz 2018) at ``alpha = 1`` and
    maps the normal back with ``L``. Returns a unit vector of the type of ``wo``.
    """
    l11 = dr.sqrt(a11)
    l21 = a12 / l11
    l22 = dr.sqrt(dr.maximum(a22 - l21 * l21, 0.0))
    vx = l11 * wo.x + l21 * wo.y
    vy = l22 * wo.y
    # ggx.sample_vndf normalises the view vector itself.
    nx, ny, nz = ggx.sample_vndf(vx, vy, wo.z, 1.0, u1, u2)
    m = type(wo)(l11 * nx, l21 * nx + l22 * ny, nz)
    return dr.normalize(m)


# ----------------------------------------------------------------------------------------------
# Beckmann with a roughness matrix (Kaplanyan et al. 2016's own distribution)
# ----------------------------------------------------------------------------------------------


def D_beckmann_dr(m: mi.Vector3f, a11: Any, a12: Any, a22: Any) -> Any:
    """Dr.Jit Beckmann NDF with the roughness matrix ``A``: the slopes ``s = (x, y) / z`` of
    the normals are Gaussian with covariance ``A / 2``, ``D(m; A) = exp(-s^T A^-1 s) / (pi
    sqrt(det A) z^4)`` (Walter et al. 2007, eq. 25, with ``alpha^2`` replaced by ``A``; the
    form Kaplanyan et al. 2016 filter: a Gaussian of slope covariance ``Sigma`` convolved
    with it gives ``A + 2 Sigma``, their eq. 9). ``a11 = a22 = alpha^2``, ``a12 = 0`` is
    isotropic Beckmann; 0 for ``m.z <= 0``."""
    x, y, z = m.x, m.y, m.z
    det = a11 * a22 - a12 * a12
    z2 = dr.maximum(z * z, 1e-30)
    q = (a22 * x * x - 2.0 * a12 * x * y + a11 * y * y) / (det * z2)
    return dr.select(z > 0.0, dr.exp(-q) / (dr.pi * dr.sqrt(det) * z2 * z2), 0.0)


def G1_beckmann_dr(w: mi.Vector3f, a11: Any, a12: Any, a22: Any) -> Any:
    """Dr.Jit Smith masking of the Beckmann NDF with roughness matrix ``A`` as Mitsuba
    evaluates it (Walter et al. 2007, eq. 27, rational approximation) with the projected
    roughness ``alpha_w^2 = [x, y] A [x, y]^T / (x^2 + y^2)`` (stretch invariance, Heitz
    2014): ``a = z / sqrt([x, y] A [x, y]^T)``; 1 at normal incidence, 0 for ``w.z <= 0``."""
    x, y, z = w.x, w.y, w.z
    r2 = a11 * x * x + 2.0 * a12 * x * y + a22 * y * y
    a = z * dr.rsqrt(dr.maximum(r2, 1e-30))
    g = (3.535 * a + 2.181 * a * a) / (1.0 + 2.276 * a + 2.577 * a * a)
    g = dr.select((a >= 1.6) | (r2 <= 0.0), 1.0, g)
    return dr.select(z > 0.0, g, 0.0)


def D_lobe_dr(m: mi.Vector3f, a11: Any, a12: Any, a22: Any, beckmann: Any = False) -> Any:
    """The NDF with roughness matrix ``A`` of the lane's distribution: :func:`D_dr` (GGX) or
    :func:`D_beckmann_dr` where ``beckmann`` (a per-lane mask or a bool)."""
    return by_distribution(beckmann, lambda: D_beckmann_dr(m, a11, a12, a22),
                 lambda: D_dr(m, a11, a12, a22))


def G1_lobe_dr(w: mi.Vector3f, a11: Any, a12: Any, a22: Any, beckmann: Any = False) -> Any:
    """Smith masking with roughness matrix ``A`` of the lane's distribution: :func:`G1_dr`
    (GGX) or :func:`G1_beckmann_dr` where ``beckmann`` (a per-lane mask or a bool)."""
    return by_distribution(beckmann, lambda: G1_beckmann_dr(w, a11, a12, a22),
                 lambda: G1_dr(w, a11, a12, a22))


def brdf_separable_dr(wo: mi.Vector3f, wi: mi.Vector3f, a11: Any, a12: Any, a22: Any,
                      beckmann: Any = False) -> Any:
    """``D(h; A) G1(wo; A) G1(wi; A) / (4 wo.z wi.z)`` (no Fresnel, no cosine): the
    covariance GGX (eqs. A.1-3, A.1-4) or Beckmann (:func:`D_beckmann_dr`) lobe with
    Mitsuba's *separable* Smith term, per lane by ``beckmann`` (a mask or a bool); 0 unless
    both directions lie above the surface. With ``A = alpha^2 I`` it is the lobe Mitsuba
    renders (:func:`glossrt.brdf.microfacet.specular_cos` over ``cos_i``)."""
    h = wo + wi
    hn2 = dr.squared_norm(h)
    h = h * dr.rsqrt(dr.maximum(hn2, 1e-30))
    val = (D_lobe_dr(h, a11, a12, a22, beckmann) * G1_lobe_dr(wo, a11, a12, a22, beckmann)
           * G1_lobe_dr(wi, a11, a12, a22, beckmann))
    ok = (wo.z > 0.0) & (wi.z > 0.0) & (hn2 > 0.0)
    return dr.select(ok, val / (4.0 * dr.maximum(wo.z * wi.z, 1e-30)), 0.0)
