"""Kimura & Tokoi's ellipsoidal microfacet distribution and its GPU samplers.

M. Kimura, K. Tokoi, "Highlight generation considering both of light source shape and the
roughness on the surface using GPU" (in Japanese). The paper blurs the mirror reflection of an
environment map with a few microfacet normals per pixel, drawn from a 1D "ellipsoidal"
distribution of the microfacet angle ``delta`` and read from a texture with baked random numbers.

Model (sec. 4.1). With the axis ratio ``R = R_r >= 1`` of the ellipse and ``k = sqrt(R^2 - 1)``::

    D_s(delta) = k / (2 R atan k) * cos(delta) / (cos^2(delta) / R + R sin^2(delta))
               = (k / atan k) * cos(delta) / (2 (1 + k^2 sin^2 delta)),   delta in [-pi/2, pi/2]

and ``integral D_s = 1``: with ``s = sin(delta)`` it is the density ``(k / (2 atan k)) / (1 +
k^2 s^2)`` of ``s`` on [-1, 1] (a Cauchy law truncated to [-1, 1]). Hence the CDF and the
paper's inverse CDF (sec. 5.1)::

    F(delta) = 1/2 + atan(k sin delta) / (2 atan k)
    delta(U) = asin(tan((2U - 1) atan k) / k)

``R = 1`` is the limit ``k -> 0``: ``D_s = cos(delta) / 2`` (``sin(delta)`` uniform), which the
code evaluates with the series ``k / atan k = 1 + k^2/3``, ``atan(k s) / atan k = s (1 + k^2
(1 - s^2) / 3)`` and ``tan(t atan k) / k = t (1 - k^2 (1 - t^2) / 3)`` (errors ``O(k^4)``) when
``k < 1e-3``: no NaN at ``R = 1`` or just above. Larger ``R`` means a smoother surface.

Microfacet normal (sec. 5.1): ``theta = pi V`` is uniform in [0, pi) and the sign of ``delta``
covers the other half plane, so the normal is

    h = cos(delta) n + sin(delta) (cos(theta) t + sin(theta) b)

with ``(t, b, n)`` an orthonormal frame of the surface normal ``n``. Note that ``D_s`` is a
density of the *angle* ``delta`` (a profile), not a density per solid angle: per steradian the
normals have density ``D_s(|delta|) / (pi sin|delta|)``, which peaks at ``h = n``.

Frames (sec. 5.2). The paper stores ``(H_x, H_y, H_z) = (cos d, sin d cos t, sin d sin t)``
around the reference axis ``I_delta = (1, 0, 0)`` and rotates it to ``n`` with the DirectX
(row-vector, left-handed) matrix whose rows are ``n``, ``(0, n_z, -n_y) = n x e_x`` and
``(n_y^2 + n_z^2, -n_x n_y, -n_x n_z) = e_x - (n.e_x) n``. Its two tangent rows have length
``sqrt(1 - n_x^2)`` (they are orthonormal only for ``n`` perpendicular to ``e_x``, and vanish at
``n = +-e_x``), and in right-handed coordinates the frame is mirrored (for ``n = e_z`` the rows
give ``r1 x r2 = -n``). glossrt instead uses the reference axis ``z``: local normals are
``(sin d cos t, sin d sin t, cos d) = (H_y, H_z, H_x)`` (a cyclic, handedness-preserving
relabelling of the paper's texel) and are taken to world space with Mitsuba's ``mi.Frame3f(n)``
(``t = s``, ``b = t`` of the frame, built by ``coordinate_system``: Duff et al. 2017), which is
orthonormal and right-handed (``t x b = n``) for every unit ``n``. Because ``theta`` is uniform
and ``D_s`` is even, a rotation or mirror of the tangent plane does not change the distribution
of ``h``, so the result is the paper's sampling with a well-defined frame everywhere.

Geometric attenuation (sec. 4.2). The paper's typeset formulas are garbled (both of its terms
use ``N.L``); glossrt uses Blinn 1977 / Cook & Torrance 1982 (after Torrance & Sparrow 1967):
masking (the view direction ``v``) ``G_m = 2 (n.h)(n.v) / (v.h)``, shadowing (the light
direction ``l``) ``G_s = 2 (n.h)(n.l) / (v.h)``, ``G = min(1, G_m, G_s)``.

Random numbers on the GPU (sec. 5.3): the paper bakes the random numbers into the
microfacet-normal texture (:class:`NormalTexture`); beside it :func:`hash_uniforms` is a
per-pixel hash generator (PCG hash of Jarzynski & Olano 2020). The paper uses 4 random samples
per pixel (sec. 7.3, :data:`DEFAULT_RANDOM_SAMPLES`) or 13 regular ones weighted by ``D_s``
(sec. 7.2, :func:`regular_samples`).

References:
    M. Kimura, K. Tokoi, GPU highlight generation on rough surfaces reflecting light shapes
    (Japanese), secs. 4.1, 4.2, 5.1-5.3, 7.2.
    J. Blinn, "Models of Light Reflection for Computer Synthesized Pictures", SIGGRAPH 1977.
    R. Cook, K. Torrance, "A Reflectance Model for Computer Graphics", ACM TOG 1(1), 1982.
    K. Torrance, E. Sparrow, "Theory for Off-Specular Reflection from Roughened Surfaces",
    JOSA 57, 1967.
    T. Duff et al., "Building an Orthonormal Basis, Revisited", JCGT 6(1), 2017.
    M. Jarzynski, M. Olano, "Hash Functions for GPU Rendering", JCGT 9(3), 2020.
    M. Roberts, "The Unreasonable Effectiveness of Quasirandom Sequences" (R2 sequence), 2018.
"""

from __future__ import annotations

import functools
import math
from typing import Any

import drjit as dr
import numpy as np

from ..backend import VariantStruct, mi
from ..errors import GlossrtError

__all__ = [
    "ALPHA_MAX",
    "BECKMANN_MEDIAN",
    "DEFAULT_RANDOM_SAMPLES",
    "DEFAULT_TEXTURE_SIZE",
    "REGULAR_SAMPLE_COUNT",
    "ellipsoidal_pdf",
    "ellipsoidal_cdf",
    "ellipsoidal_sample",
    "ratio_from_alpha",
    "alpha_from_ratio",
    "local_normal",
    "to_world",
    "microfacet_normal",
    "reflect",
    "geometric_attenuation",
    "pcg_hash",
    "hash_uniforms",
    "hash_normals",
    "NormalTexture",
    "regular_samples",
    "regular_normals",
]

#: Random samples per pixel (sec. 7.3: four, to use 4 x 4 matrix arithmetic).
DEFAULT_RANDOM_SAMPLES = 4
#: Points of the regular sampling (sec. 7.2: 13, the pixel-shader program length limit).
REGULAR_SAMPLE_COUNT = 13
#: Side of the microfacet-normal texture (texels per axis).
DEFAULT_TEXTURE_SIZE = 64
#: GGX roughness whose median microfacet angle (30 degrees) equals that of ``R = 1``, the
#: roughest ellipsoidal distribution: :func:`ratio_from_alpha` maps larger alphas to 1.
ALPHA_MAX = 1.0 / math.sqrt(3.0)
#: Beckmann's median ``tan theta_m`` per unit alpha, ``sqrt(ln 2)`` (:func:`median_alpha`).
BECKMANN_MEDIAN = math.sqrt(math.log(2.0))

_K_SERIES = 1e-3  # below this k the R -> 1 series replace the closed forms (error O(k^4))

# R2 low-discrepancy sequence (Roberts 2018) in 32-bit fixed point: 2^32 / g and 2^32 / g^2 with
# g = 1.3247179572... the plastic number. Used for the per-sample texture offsets.
_R2_X = 3242174889
_R2_Y = 2447445414


# ----------------------------------------------------------------------------------------------
# Input checks
# ----------------------------------------------------------------------------------------------


def _is_dr(x: Any) -> bool:
    return isinstance(x, dr.ArrayBase)


def _np_array(name: str, x: Any) -> np.ndarray:
    """``x`` as a finite float64 array, or a GlossrtError naming ``name``."""
    try:
        a = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise GlossrtError(f"{name} must be numeric, got {type(x).__name__}") from e
    if not np.all(np.isfinite(a)):
        raise GlossrtError(f"{name} contains NaN or Inf")
    return a


def _np_ratio(ratio: Any) -> np.ndarray:
    r = _np_array("ratio", ratio)
    if np.any(r < 1.0):
        raise GlossrtError(f"ratio R_r must be >= 1 (got min {float(r.min())})")
    return r


def _broadcast(*arrays: np.ndarray) -> list[np.ndarray]:
    try:
        return list(np.broadcast_arrays(*arrays))
    except ValueError as e:
        shapes = ", ".join(str(a.shape) for a in arrays)
        raise GlossrtError(f"shapes do not broadcast: {shapes}") from e


def _dr_ratio(ratio: Any, like: Any) -> Any:
    """Ratio for a Dr.Jit kernel: Python / NumPy scalars are checked and made opaque (a changing
    literal would compile a new kernel); Dr.Jit arrays are trusted (checking them would need a
    device sync) and clamped to ``>= 1``."""
    t = type(like) if dr.is_float_v(like) else mi.Float
    if _is_dr(ratio):
        return dr.maximum(t(ratio), 1.0)
    r = _np_ratio(ratio)
    if r.ndim != 0:
        raise GlossrtError("with Dr.Jit arguments, ratio must be a scalar or a Dr.Jit array")
    return dr.opaque(t, float(r))


def _k_np(r: np.ndarray) -> np.ndarray:
    return np.sqrt((r - 1.0) * (r + 1.0))  # sqrt(R^2 - 1) without cancellation near R = 1


def _k_dr(r: Any) -> Any:
    return dr.sqrt(dr.maximum((r - 1.0) * (r + 1.0), 0.0))


# ----------------------------------------------------------------------------------------------
# The distribution D_s (sec. 4.1) and its inverse CDF (sec. 5.1)
# ----------------------------------------------------------------------------------------------


def ellipsoidal_pdf(delta: Any, ratio: Any) -> Any:
    """The ellipsoidal microfacet distribution ``D_s(delta; R_r)`` (Kimura & Tokoi, sec. 4.1).

    ``D_s = sqrt(R^2-1) / (2 R atan sqrt(R^2-1)) * cos(delta) / (cos^2(delta)/R + R sin^2(delta))``,
    a density of ``delta`` in [-pi/2, pi/2] (0 outside) that integrates to 1; ``R = 1`` gives
    the limit ``cos(delta) / 2``.

    Args:
        delta: microfacet angle(s) from the normal, NumPy array-like or a Dr.Jit float array.
        ratio: axis ratio ``R_r >= 1`` (scalar, or an array broadcast with ``delta``).

    Returns:
        float64 NumPy array (NumPy input) or an array of ``delta``'s Dr.Jit type.
    """
    if _is_dr(delta):
        r = _dr_ratio(ratio, delta)
        k = _k_dr(r)
        k_over_atan = dr.select(k < _K_SERIES, 1.0 + k * k / 3.0, k / dr.atan(k))
        s, c = dr.sincos(delta)
        # Kimura & Tokoi, eq. of sec. 4.1, rewritten with cos^2/R + R sin^2 = (1 + k^2 s^2) / R.
        d = k_over_atan * c / (2.0 * (1.0 + k * k * s * s))
        return dr.select(dr.abs(delta) <= 0.5 * dr.pi, dr.maximum(d, 0.0), 0.0)
    d_np, r_np = _broadcast(_np_array("delta", delta), _np_ratio(ratio))
    k = _k_np(r_np)
    with np.errstate(divide="ignore", invalid="ignore"):
        k_over_atan = np.where(k < _K_SERIES, 1.0 + k * k / 3.0, k / np.arctan(k))
    s, c = np.sin(d_np), np.cos(d_np)
    d = k_over_atan * c / (2.0 * (1.0 + k * k * s * s))  # Kimura & Tokoi, sec. 4.1
    return np.where(np.abs(d_np) <= 0.5 * np.pi, np.maximum(d, 0.0), 0.0)


def ellipsoidal_cdf(delta: Any, ratio: Any) -> Any:
    """CDF ``F(delta) = 1/2 + atan(k sin delta) / (2 atan k)`` of :func:`ellipsoidal_pdf`
    (``k = sqrt(R^2 - 1)``; the paper's ``SD[-pi/2, delta]``, sec. 5.1). 0 below ``-pi/2``,
    1 above ``pi/2``. NumPy or Dr.Jit, as :func:`ellipsoidal_pdf`."""
    if _is_dr(delta):
        r = _dr_ratio(ratio, delta)
        k = _k_dr(r)
        s = dr.sin(dr.clip(delta, -0.5 * dr.pi, 0.5 * dr.pi))
        q = dr.select(
            k < _K_SERIES, s * (1.0 + k * k * (1.0 - s * s) / 3.0), dr.atan(k * s) / dr.atan(k)
        )
        return dr.clip(0.5 + 0.5 * q, 0.0, 1.0)
    d_np, r_np = _broadcast(_np_array("delta", delta), _np_ratio(ratio))
    k = _k_np(r_np)
    s = np.sin(np.clip(d_np, -0.5 * np.pi, 0.5 * np.pi))
    with np.errstate(divide="ignore", invalid="ignore"):
        q = np.where(
            k < _K_SERIES, s * (1.0 + k * k * (1.0 - s * s) / 3.0), np.arctan(k * s) / np.arctan(k)
        )
    return np.clip(0.5 + 0.5 * q, 0.0, 1.0)


def ellipsoidal_sample(u: Any, ratio: Any) -> Any:
    """Inverse CDF ``delta(U) = asin(tan((2U - 1) atan k) / k)`` (Kimura & Tokoi, sec. 5.1).

    Maps uniform ``u`` in [0, 1] to ``delta`` in [-pi/2, pi/2] distributed as ``D_s``.
    NumPy input must lie in [0, 1] (GlossrtError otherwise); Dr.Jit input is clamped.
    """
    if _is_dr(u):
        r = _dr_ratio(ratio, u)
        k = _k_dr(r)
        t = 2.0 * dr.clip(u, 0.0, 1.0) - 1.0
        s = dr.select(
            k < _K_SERIES, t * (1.0 - k * k * (1.0 - t * t) / 3.0), dr.tan(t * dr.atan(k)) / k
        )
        return dr.asin(dr.clip(s, -1.0, 1.0))  # Kimura & Tokoi, delta(U), sec. 5.1
    u_np, r_np = _broadcast(_np_array("u", u), _np_ratio(ratio))
    if np.any((u_np < 0.0) | (u_np > 1.0)):
        raise GlossrtError("u must lie in [0, 1]")
    k = _k_np(r_np)
    t = 2.0 * u_np - 1.0
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(
            k < _K_SERIES, t * (1.0 - k * k * (1.0 - t * t) / 3.0), np.tan(t * np.arctan(k)) / k
        )
    return np.arcsin(np.clip(s, -1.0, 1.0))  # Kimura & Tokoi, delta(U), sec. 5.1


# ----------------------------------------------------------------------------------------------
# Matching GGX roughness
# ----------------------------------------------------------------------------------------------


def median_alpha(alpha: Any, distribution: str = "ggx") -> np.ndarray:
    """The GGX roughness with the same median microfacet angle as ``distribution``'s
    ``alpha``: GGX itself, or for Beckmann ``alpha sqrt(ln 2)`` (its projected NDF has
    ``P(tan^2 theta_h < x) = 1 - exp(-x / alpha^2)`` (Walter et al. 2007, eq. 28), median
    ``tan theta_m = alpha sqrt(ln 2)``, GGX's median is ``tan theta_m = alpha``)."""
    a = _np_array("alpha", alpha)
    if distribution == "beckmann":
        return a * BECKMANN_MEDIAN
    if distribution != "ggx":
        raise GlossrtError(f"distribution must be 'ggx' or 'beckmann', got {distribution!r}")
    return a


def ratio_from_alpha(alpha: Any, distribution: str = "ggx") -> np.ndarray:
    """The ratio ``R_r`` whose median microfacet angle equals that of the microfacet
    ``distribution`` (GGX, or Beckmann through :func:`median_alpha`) for roughness ``alpha``.

    GGX normals sampled with the projected NDF ``D(h) cos(theta_h)`` have ``P(tan theta_h < x)
    = x^2 / (alpha^2 + x^2)``, median ``theta_m = atan(alpha)``. The folded ellipsoidal angle has
    ``P(|delta| < d) = atan(k sin d) / atan(k)``; its median solves ``atan(k sin d) =
    atan(k) / 2``, i.e. ``k sin d = tan(atan(k) / 2) = k / (1 + sqrt(1 + k^2)) = k / (1 + R)``:
    ``sin d = 1 / (1 + R)``. Equating ``sin d = sin(theta_m) = alpha / sqrt(1 + alpha^2)`` gives
    the closed form

        R = sqrt(1 + alpha^2) / alpha - 1.

    ``R >= 1`` needs ``alpha <= 1/sqrt(3)`` (:data:`ALPHA_MAX`, median 30 degrees, that of
    ``R = 1``); rougher alphas map to ``R = 1``, the roughest ellipsoidal distribution. Small
    alphas give ``R ~ 1 / alpha``. Vectorised over NumPy arrays (float64 out).
    """
    a = _np_array("alpha", alpha)
    if np.any(a <= 0.0):
        raise GlossrtError("alpha must be > 0 (alpha = 0 is a mirror: R_r = infinity)")
    a = median_alpha(a, distribution)
    r = np.sqrt(1.0 + a * a) / a - 1.0
    return np.maximum(r, 1.0)


def alpha_from_ratio(ratio: Any) -> np.ndarray:
    """Inverse of :func:`ratio_from_alpha`: ``alpha = 1 / sqrt(R (R + 2))`` (the GGX roughness
    with the same median microfacet angle ``asin(1 / (1 + R))``). ``R = 1`` gives
    :data:`ALPHA_MAX`."""
    r = _np_ratio(ratio)
    return 1.0 / np.sqrt(r * (r + 2.0))


# ----------------------------------------------------------------------------------------------
# Microfacet normals, reflection, geometric attenuation (secs. 4.2, 5.1, 5.2)
# ----------------------------------------------------------------------------------------------


def _np_vec3(name: str, x: Any) -> np.ndarray:
    a = _np_array(name, x)
    if a.shape[-1:] != (3,):
        raise GlossrtError(f"{name} must have shape (..., 3), got {a.shape}")
    return a


def _dr_vec3(x: Any) -> mi.Vector3f:
    return x if isinstance(x, mi.Vector3f) else mi.Vector3f(x)


def local_normal(delta: Any, theta: Any) -> Any:
    """Microfacet normal in the reference frame (z = reference axis = surface normal):
    ``(sin d cos t, sin d sin t, cos d)``, the paper's texel ``(H_y, H_z, H_x)`` (sec. 5.1).

    Dr.Jit floats give an ``mi.Vector3f``; NumPy input gives a ``(..., 3)`` float64 array.
    """
    if _is_dr(delta) or _is_dr(theta):
        sd, cd = dr.sincos(mi.Float(delta))
        st, ct = dr.sincos(mi.Float(theta))
        return mi.Vector3f(sd * ct, sd * st, cd)
    d, t = _broadcast(_np_array("delta", delta), _np_array("theta", theta))
    sd = np.sin(d)
    return np.stack([sd * np.cos(t), sd * np.sin(t), np.cos(d)], axis=-1)


def to_world(n: Any, h_local: Any) -> Any:
    """Rotate local normals (z = reference axis) to the surface normal ``n`` (unit).

    Uses ``mi.Frame3f(n)``: ``h = h_x s + h_y t + h_z n`` with the right-handed orthonormal
    ``(s, t, n)`` of Mitsuba's ``coordinate_system`` (Duff et al. 2017); glossrt's equivalent of
    the paper's rotation matrix from ``(1, 0, 0)`` to ``n`` (sec. 5.2, see the module notes).
    NumPy ``(..., 3)`` arrays in give NumPy out (float64, the same frame).
    """
    if _is_dr(n) or _is_dr(h_local):
        return mi.Frame3f(_dr_vec3(n)).to_world(_dr_vec3(h_local))
    n_np, h_np = _broadcast(_np_vec3("n", n), _np_vec3("h_local", h_local))
    s, t = _coordinate_system_np(n_np)
    return h_np[..., :1] * s + h_np[..., 1:2] * t + h_np[..., 2:] * n_np


def _coordinate_system_np(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Float64 twin of Mitsuba's ``coordinate_system`` (Duff et al. 2017, listing 3): the
    tangents ``(s, t)`` of ``mi.Frame3f(n)``, with ``s x t = n``."""
    x, y, z = n[..., 0], n[..., 1], n[..., 2]
    sign = np.where(z >= 0.0, 1.0, -1.0)  # dr.sign: +1 for +-0
    a = -1.0 / (sign + z)
    b = x * y * a
    s = np.stack([1.0 + sign * x * x * a, sign * b, -sign * x], axis=-1)
    t = np.stack([b, sign + y * y * a, -y], axis=-1)
    return s, t


def microfacet_normal(n: Any, delta: Any, theta: Any) -> Any:
    """World-space microfacet normal ``h = cos(d) n + sin(d) (cos(t) s + sin(t) t_)`` for the
    unit surface normal ``n`` (Kimura & Tokoi, secs. 5.1-5.2, in the right-handed frame
    ``mi.Frame3f(n) = (s, t_, n)``). ``h`` is a unit vector at angle ``|delta|`` from ``n``.
    Dr.Jit in, Dr.Jit out; NumPy in (``n`` of shape ``(..., 3)``), NumPy out."""
    if _is_dr(n) or _is_dr(delta) or _is_dr(theta):
        return to_world(_dr_vec3(n), local_normal(mi.Float(delta), mi.Float(theta)))
    return to_world(_np_vec3("n", n), local_normal(delta, theta))


def reflect(v: Any, h: Any) -> Any:
    """Mirror ``v`` (pointing away from the surface, like the view direction) about the unit
    normal ``h``: ``2 (v.h) h - v`` (sec. 5.2: "the view's specular reflection about the
    microfacet normal"). Dr.Jit vectors or NumPy ``(..., 3)`` arrays."""
    if _is_dr(v) or _is_dr(h):
        v, h = _dr_vec3(v), _dr_vec3(h)
        return 2.0 * dr.dot(v, h) * h - v
    v_np, h_np = _broadcast(_np_vec3("v", v), _np_vec3("h", h))
    return 2.0 * np.sum(v_np * h_np, axis=-1, keepdims=True) * h_np - v_np


def geometric_attenuation(n: Any, h: Any, v: Any, l: Any) -> Any:
    """Geometric attenuation ``G = min(1, G_m, G_s)`` (Kimura & Tokoi, sec. 4.2).

    Masking of the view direction ``v``: ``G_m = 2 (n.h)(n.v) / (v.h)``; shadowing of the light
    direction ``l``: ``G_s = 2 (n.h)(n.l) / (v.h)`` (Blinn 1977; Cook & Torrance 1982, after
    Torrance & Sparrow 1967: the paper's typeset formulas are garbled). ``h`` is the half vector
    of ``v`` and ``l`` (``l = reflect(v, h)``), so ``v.h = l.h`` and ``G`` is symmetric in ``v``
    and ``l``. ``G = 0`` where ``n.v``, ``n.l``, ``n.h`` or ``v.h`` is not positive (below the
    horizon). All unit vectors; Dr.Jit vectors or NumPy ``(..., 3)`` arrays.
    """
    if any(_is_dr(x) for x in (n, h, v, l)):
        n, h, v, l = (_dr_vec3(x) for x in (n, h, v, l))
        nh, nv, nl, vh = dr.dot(n, h), dr.dot(n, v), dr.dot(n, l), dr.dot(v, h)
        ok = (nh > 0.0) & (nv > 0.0) & (nl > 0.0) & (vh > 0.0)
        inv = dr.select(ok, 2.0 * nh / dr.select(ok, vh, 1.0), 0.0)
        g = dr.minimum(1.0, dr.minimum(inv * nv, inv * nl))  # sec. 4.2, G = Min(1, G_m, G_s)
        return dr.select(ok, g, 0.0)
    n_np, h_np, v_np, l_np = _broadcast(
        _np_vec3("n", n), _np_vec3("h", h), _np_vec3("v", v), _np_vec3("l", l)
    )
    nh = np.sum(n_np * h_np, -1)
    nv = np.sum(n_np * v_np, -1)
    nl = np.sum(n_np * l_np, -1)
    vh = np.sum(v_np * h_np, -1)
    ok = (nh > 0.0) & (nv > 0.0) & (nl > 0.0) & (vh > 0.0)
    inv = np.where(ok, 2.0 * nh / np.where(ok, vh, 1.0), 0.0)
    return np.where(ok, np.minimum(1.0, np.minimum(inv * nv, inv * nl)), 0.0)


# ----------------------------------------------------------------------------------------------
# Per-pixel hash random numbers (beside the paper's texture, sec. 5.3)
# ----------------------------------------------------------------------------------------------


def _u32(x: Any) -> mi.UInt32:
    """Dr.Jit UInt32 from an int (made opaque: frame numbers change every call) or an array."""
    if _is_dr(x):
        return mi.UInt32(x)
    if isinstance(x, (int, np.integer)):
        if x < 0:
            raise GlossrtError(f"indices must be >= 0, got {x}")
        return dr.opaque(mi.UInt32, int(x) & 0xFFFFFFFF)
    a = np.asarray(x)
    if a.dtype.kind not in "iu" or np.any(a < 0):
        raise GlossrtError("indices must be non-negative integers")
    return mi.UInt32(a.astype(np.uint32).ravel())


def pcg_hash(x: mi.UInt32) -> mi.UInt32:
    """The PCG hash (Jarzynski & Olano 2020, sec. 2 "pcg"): one LCG step of PCG32 followed by
    its RXS-M-XS output permutation; a bijection of 32-bit integers."""
    state = x * 747796405 + 2891336453
    word = ((state >> ((state >> 28) + 4)) ^ state) * 277803737
    return (word >> 22) ^ word


def _unit(bits: mi.UInt32) -> mi.Float:
    return mi.Float(bits >> 8) * (1.0 / 16777216.0)  # top 24 bits: [0, 1) exactly in float32


def hash_uniforms(pixel_index: Any, sample_index: Any, frame: Any = 0) -> tuple[Any, Any]:
    """Two uniform numbers in [0, 1) per (pixel, sample, frame) from a stateless hash.

    ``h1 = pcg(pixel + pcg(sample + pcg(frame)))`` (nested hashing of a multi-dimensional seed,
    Jarzynski & Olano 2020, sec. 4), ``u = h1 / 2^32`` and ``v = pcg(h1) / 2^32`` (top 24 bits).
    The GPU counterpart of the paper's random numbers baked into a texture (sec. 5.3): every
    pixel draws its own stream, with no state between pixels. Arguments are Python ints (made
    opaque), integer NumPy arrays or Dr.Jit ``UInt32`` arrays (broadcast together).
    """
    p, s, f = _u32(pixel_index), _u32(sample_index), _u32(frame)
    h1 = pcg_hash(p + pcg_hash(s + pcg_hash(f)))
    return _unit(h1), _unit(pcg_hash(h1))


def hash_normals(
    n: mi.Vector3f,
    pixel_index: Any,
    ratio: Any,
    count: int = DEFAULT_RANDOM_SAMPLES,
    frame: Any = 0,
) -> list[mi.Vector3f]:
    """``count`` world-space microfacet normals per lane from :func:`hash_uniforms`:
    ``delta = delta(u)`` (sec. 5.1), ``theta = pi v``, rotated to ``n``
    (:func:`microfacet_normal`). Sample ``i`` uses ``sample_index = i``."""
    if count < 1:
        raise GlossrtError(f"count must be >= 1, got {count}")
    out = []
    for i in range(count):
        u, v = hash_uniforms(pixel_index, i, frame)
        delta = ellipsoidal_sample(u, ratio)
        out.append(microfacet_normal(n, delta, dr.pi * v))  # theta(V) = pi V, sec. 5.1
    return out


# ----------------------------------------------------------------------------------------------
# The microfacet-normal texture with embedded random numbers (secs. 5.1, 5.3)
# ----------------------------------------------------------------------------------------------


class NormalTexture:
    """A ``width x height`` texture of microfacet normals for one ratio, with the random numbers
    baked in (Kimura & Tokoi, secs. 5.1 and 5.3).

    Texel ``(i, j)`` (column ``i``, row ``j``) holds the local normal
    :func:`local_normal` ``(delta(U_ij), pi V_ij)`` for uniform ``U_ij, V_ij`` drawn at build time
    from ``numpy.random.default_rng(seed)``. With ``stratify=True`` (default) the ``W H`` values
    of ``U`` (and, independently, of ``V``) are stratified: one uniform number in each interval
    ``[m / (W H), (m + 1) / (W H))``, scattered over the texels by a random permutation. The
    texture's ``delta`` values then follow ``D_s`` to within ``1 / (W H)`` in CDF, while each
    texel's value is still uniformly random. ``stratify=False`` draws independent numbers as the
    paper does; 4096 i.i.d. numbers deviate from ``D_s`` by chance (a chi-square test with 20
    bins rejects the set of the default seed at p = 0.002). The reference axis is z (the
    paper's is x; see the module notes). ``quantize=True`` stores the normal as the paper's
    RGBA8 texel
    ``round(255 (H + 1) / 2)`` (sec. 5.1, resolution 2/255 per component) and decodes
    ``2 c / 255 - 1``; lookups renormalise. The 8-bit normals are off by up to ~0.0065 rad,
    harmless for rough surfaces but not for smooth ones: measured with a 20-bin chi-square test
    of the 4096 texels of a 64 x 64 texture against ``D_s``, quantised textures pass for
    ``R_r <= 4`` and are rejected from ``R_r ~ 6`` on (use float textures there).

    Lookups (:meth:`texel_index`): sample ``s`` of pixel ``(x, y)`` in frame ``f`` reads texel

        ((x + ox(s) + fx(f)) mod W, (y + oy(s) + fy(f)) mod H)

    with ``(ox(s), oy(s)) = floor((W, H) * frac(s (a1, a2)))`` the R2 sequence (Roberts 2018,
    ``a1 = 1/g``, ``a2 = 1/g^2``, ``g`` the plastic number, in 16-bit fixed point; ``s = 0``
    gives ``(0, 0)``) and ``(fx, fy)`` from the PCG hash of the frame number. For each sample the
    map pixel -> texel is a bijection on every ``W x H`` block of pixels, so neighbouring pixels
    read different, independently drawn texels; the samples of one pixel read distinct texels
    for ``s < distinct_samples`` (256 for 64 x 64); the frame offset moves the whole pattern
    between frames. The image tiles with period ``(W, H)``, as with the paper's texture.

    The class is a Dr.Jit PyTree (``DRJIT_STRUCT``): instances can go into frozen functions.
    """

    DRJIT_STRUCT = VariantStruct(lambda: {"data": mi.Float, "width": int, "height": int})

    def __init__(
        self,
        ratio: float,
        width: int = DEFAULT_TEXTURE_SIZE,
        height: int = DEFAULT_TEXTURE_SIZE,
        seed: int = 0,
        quantize: bool = False,
        stratify: bool = True,
    ) -> None:
        r = _np_ratio(ratio)
        if r.ndim != 0:
            raise GlossrtError("NormalTexture needs a scalar ratio")
        if not (isinstance(width, (int, np.integer)) and isinstance(height, (int, np.integer))):
            raise GlossrtError("width and height must be integers")
        if not (1 <= width <= 65536 and 1 <= height <= 65536):
            raise GlossrtError(f"texture size must be in [1, 65536], got {width} x {height}")
        self.ratio = float(r)
        self.width = int(width)
        self.height = int(height)
        self.seed = int(seed)
        self.quantize = bool(quantize)
        self.stratify = bool(stratify)
        rng = np.random.default_rng(self.seed)
        shape = (self.height, self.width)
        n = self.width * self.height
        if self.stratify:  # one number per stratum [i/n, (i+1)/n), in random texel order
            self.u = ((rng.permutation(n) + rng.random(n)) / n).reshape(shape)
            self.v = ((rng.permutation(n) + rng.random(n)) / n).reshape(shape)
        else:  # independent uniform numbers, as the paper (sec. 5.3)
            self.u = rng.random(shape)
            self.v = rng.random(shape)
        self.delta = ellipsoidal_sample(self.u, self.ratio)  # delta(U), sec. 5.1
        self.theta = np.pi * self.v  # theta(V) = pi V, sec. 5.1
        h = local_normal(self.delta, self.theta)
        self.codes: np.ndarray | None = None
        if self.quantize:
            # RGBA8 texel ((H + 1) / 2 scaled to 0..255, A = 1), sec. 5.1
            rgb = np.rint((h + 1.0) * 127.5).clip(0, 255).astype(np.uint8)
            self.codes = np.concatenate([rgb, np.full(rgb.shape[:-1] + (1,), 255, np.uint8)], -1)
            h = rgb.astype(np.float64) / 127.5 - 1.0
        self.texels = h.astype(np.float32)  # (H, W, 3) as the shader reads them
        self.data = mi.Float(np.ascontiguousarray(self.texels).ravel())
        dr.make_opaque(self.data)

    @property
    def distinct_samples(self) -> int:
        """How many leading sample indices read pairwise distinct texels in every pixel."""
        seen: set[tuple[int, int]] = set()
        for s in range(self.width * self.height):
            o = (_offset_int(s, _R2_X, self.width), _offset_int(s, _R2_Y, self.height))
            if o in seen:
                return s
            seen.add(o)
        return self.width * self.height

    def texel_index(self, pixel_x: Any, pixel_y: Any, sample_index: Any, frame: Any = 0) -> Any:
        """Flat texel index ``row * W + column`` read by sample ``sample_index`` of pixel
        ``(pixel_x, pixel_y)`` in ``frame`` (``mi.UInt32``; see the class notes)."""
        x, y = _u32(pixel_x), _u32(pixel_y)
        if isinstance(sample_index, (int, np.integer)):
            if sample_index < 0:
                raise GlossrtError(f"sample_index must be >= 0, got {sample_index}")
            # small fixed set of sample indices: literals, folded into the kernel
            ox = _offset_int(int(sample_index), _R2_X, self.width)
            oy = _offset_int(int(sample_index), _R2_Y, self.height)
        else:
            s = _u32(sample_index)
            ox = _offset_u32(s, _R2_X, self.width)
            oy = _offset_u32(s, _R2_Y, self.height)
        hf = pcg_hash(_u32(frame))
        fx = ((hf & 0xFFFF) * self.width) >> 16
        fy = ((hf >> 16) * self.height) >> 16
        col = (x % self.width + ox + fx) % self.width
        row = (y % self.height + oy + fy) % self.height
        return row * self.width + col

    def lookup(
        self, pixel_x: Any, pixel_y: Any, sample_index: Any, frame: Any = 0
    ) -> mi.Vector3f:
        """Local microfacet normal (z = reference axis, unit length) for sample
        ``sample_index`` of pixel ``(pixel_x, pixel_y)``: the texel of :meth:`texel_index`
        (sec. 5.3: random numbers from the texture, indexed by the pixel coordinates)."""
        idx = self.texel_index(pixel_x, pixel_y, sample_index, frame)
        return dr.normalize(dr.gather(mi.Vector3f, self.data, idx))

    def sample_normals(
        self,
        n: mi.Vector3f,
        pixel_x: Any,
        pixel_y: Any,
        count: int = DEFAULT_RANDOM_SAMPLES,
        frame: Any = 0,
    ) -> list[mi.Vector3f]:
        """``count`` world-space microfacet normals per lane: :meth:`lookup` rotated to the unit
        normal ``n`` with :func:`to_world` (sec. 5.2)."""
        if count < 1:
            raise GlossrtError(f"count must be >= 1, got {count}")
        n = _dr_vec3(n)
        return [to_world(n, self.lookup(pixel_x, pixel_y, i, frame)) for i in range(count)]

    def __repr__(self) -> str:
        return (f"NormalTexture(ratio={self.ratio}, width={self.width}, height={self.height}, "
                f"seed={self.seed}, quantize={self.quantize}, stratify={self.stratify})")


def _offset_int(s: int, a: int, size: int) -> int:
    """``floor(size * frac(s * a / 2^32))`` with 16 fraction bits (R2 offset, Python int)."""
    return ((((s * a) & 0xFFFFFFFF) >> 16) * size) >> 16


def _offset_u32(s: mi.UInt32, a: int, size: int) -> mi.UInt32:
    """:func:`_offset_int` in Dr.Jit (UInt32 multiplication wraps modulo 2^32)."""
    return (((s * a) >> 16) * size) >> 16


# ----------------------------------------------------------------------------------------------
# 13-point regular sampling weighted by D_s (sec. 7.2)
# ----------------------------------------------------------------------------------------------


# 3-point Gauss-Radau rule on [0, 1] with the node 0 fixed (exact for polynomials of degree 4):
# nodes 0, (6 -+ sqrt 6) / 10, weights 1/9, (16 +- sqrt 6) / 36.
_RADAU_T = ((6.0 - math.sqrt(6.0)) / 10.0, (6.0 + math.sqrt(6.0)) / 10.0)
_RADAU_W = (1.0 / 9.0, (16.0 + math.sqrt(6.0)) / 36.0, (16.0 - math.sqrt(6.0)) / 36.0)


@functools.lru_cache(maxsize=64)
def _regular_cached(ratio: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    # ring angles: folded D_s quantiles P(|delta| < d) = t, i.e. F(d) = (1 + t) / 2 (sec. 5.1)
    d_ring = ellipsoidal_sample(0.5 * (1.0 + np.array(_RADAU_T)), ratio)
    deltas, thetas, weights = [0.0], [0.0], [_RADAU_W[0]]
    for ring, (d, wr) in enumerate(zip(d_ring, _RADAU_W[1:], strict=True)):
        for j in range(6):
            phi = math.pi / 3.0 * j + ring * math.pi / 6.0  # second ring rotated by 30 degrees
            # azimuth phi in [0, 2 pi) as (signed delta, theta in [0, pi)), sec. 5.1
            if phi < math.pi:
                deltas.append(float(d))
                thetas.append(phi)
            else:
                deltas.append(-float(d))
                thetas.append(phi - math.pi)
            weights.append(wr / 6.0)
    wts = np.array(weights)
    return np.array(deltas), np.array(thetas), wts / wts.sum()


def regular_samples(ratio: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The 13-point regular sampling of sec. 7.2, weighted by ``D_s``: ``(delta, theta, weight)``,
    each of shape ``(13,)``, weights summing to 1.

    The paper fixes 13 points around the reference normal and accumulates the samples weighted by
    the precomputed ``D_s``, without giving the pattern. glossrt's pattern is a product rule in
    the folded ``D_s`` mass ``t = P(|delta'| < |delta|) = atan(k sin|delta|) / atan(k)`` (uniform
    in [0, 1] under ``D_s``) and the azimuth: the normal itself (``t = 0``) plus two rings of 6
    azimuths (the second rotated by 30 degrees so the 12 ring points interleave) at the ``D_s``
    quantiles ``t = (6 -+ sqrt 6) / 10``, with the 3-point Gauss-Radau weights ``1/9`` (centre),
    ``(16 +- sqrt 6) / 36`` (each ring, shared by its 6 points). In ``delta`` this is the weight
    ``D_s(delta_i)`` times the ring's share of the ``delta`` axis: ``dt = 2 D_s d|delta|``.

    It integrates exactly, under ``D_s`` and uniform ``theta``, every function whose azimuthal
    mean is a polynomial of degree <= 4 in ``t`` plus azimuthal Fourier modes 1..5. Because the
    points sit at ``D_s`` quantiles they follow the roughness (the rings shrink towards the
    normal for large ``R_r``) and stay inside the lobe's body: placing them by polynomial moments
    in ``cos(delta)`` instead (the classical Gauss-Radau rule in ``cos delta``) puts the rings
    in the heavy ``1 / sin^2`` tail of ``D_s`` (at 25 and 68 degrees for ``R_r = 1e4``) and
    misses functions that vary at the lobe's scale, the highlights the paper renders (errors up
    to 4 times the RMS error of 13 random samples for ``R_r >= 5``). Measured on the smooth and
    lobe-sized test functions of ``tests/test_ellipsoidal.py`` (``R_r`` = 1, 2, 20, 1e4) this
    rule's error is 0.004-0.42 times (median 0.07) the RMS error of 13 random ``D_s`` samples.
    """
    r = _np_ratio(ratio)
    if r.ndim != 0:
        raise GlossrtError("regular_samples needs a scalar ratio")
    d, t, w = _regular_cached(float(r))
    return d.copy(), t.copy(), w.copy()


def regular_normals(n: mi.Vector3f, ratio: float) -> list[tuple[mi.Vector3f, float]]:
    """The 13 world-space normals of :func:`regular_samples` around the unit normal ``n`` with
    their weights (Python floats, constant per ratio)."""
    d, t, w = regular_samples(ratio)
    n = _dr_vec3(n)
    return [
        (microfacet_normal(n, dr.opaque(mi.Float, float(di)), dr.opaque(mi.Float, float(ti))),
         float(wi))
        for di, ti, wi in zip(d, t, w, strict=True)
    ]
