"""Linearly transformed cosines (LTC) fitted to the GGX and Beckmann lobes Mitsuba renders, and
their tables.

Heitz, Dupuy, Hill, Neubelt 2016, "Real-time polygonal-light shading with linearly transformed
cosines" (SIGGRAPH 2016; "HDHN16" below) approximate a BRDF lobe by a *linearly transformed
cosine*: a direction ``w_o`` drawn from the clamped cosine ``D_o(w_o) = max(z_o, 0) / pi`` is
mapped to ``w = M w_o / |M w_o|`` by a 3x3 matrix ``M``. The density of ``w`` is (HDHN16,
sec. 3.1; the Jacobian ``|det M^-1| / |M^-1 w|^3`` is derived in their appendix A)

    D(w) = D_o(M^-1 w / |M^-1 w|) |det M^-1| / |M^-1 w|^3
         = max((M^-1 w)_z, 0) |det M^-1| / (pi |M^-1 w|^4),

which integrates to 1 over the sphere, is sampled by mapping cosine samples through ``M``
(sec. 3.2) and integrates in closed form over polygons (transform the polygon by ``M^-1`` and
integrate the clamped cosine there, sec. 3.2 / 4). :func:`ltc_eval` and :func:`ltc_sample`
implement both (NumPy or Dr.Jit).

**The lobe.** The BRDF is the specular term of glossrt's polygon-light shading
(:mod:`glossrt.lights.shading`), the one Mitsuba's ``roughconductor`` / ``roughplastic``
render: ``D`` GGX (Walter et al. 2007, eq. 33) or Beckmann (eq. 25), one table per
distribution, with Mitsuba's separable Smith term ``G1(wo) G1(wi)`` (eq. 23; GGX eq. 34,
Beckmann's rational approximation eq. 27; :mod:`glossrt.brdf.microfacet`) and Fresnel = 1,
times the clamped cosine:

    rho(wo, wi) cos(theta_i) = D(h) G1(wo) G1(wi) / (4 cos(theta_o))  (Walter et al. 2007, eq. 20)

for ``wi`` and ``wo`` above the surface, else 0. The view lies in the xz-plane,
``wo = (sin theta_o, 0, cos theta_o)``: +x points towards the view's projection on the
tangent plane (the reflection lobe leans towards -x).

**Per table cell** (roughness node ``j``, view node ``i``) the table stores

* ``norm = integral rho(wo, wi) cos(theta_i) dwi`` (the directional albedo with F = 1);
* ``fres = integral rho(wo, wi) cos(theta_i) (1 - wo.h)^5 dwi``, so that with Schlick's Fresnel
  ``F = F0 + (1 - F0)(1 - wo.h)^5`` (Schlick 1994), exactly (no approximation beyond Schlick's)

      integral rho F cos(theta_i) dwi = F0 (norm - fres) + fres  (= F0 norm + (1 - F0) fres)

  (the split-sum form of Karis 2013; ``norm - fres`` and ``fres`` are ``A`` and ``B`` of
  :mod:`glossrt.brdf.ggx`); shading scales the LTC integral (unit mass) by that value;
* ``minv``: four coefficients ``(a, b, c, d)`` of the inverse matrix in the canonical form of
  HDHN16 sec. 4 for a view in the xz-plane, divided by its middle entry (as HDHN16's public
  fitting code has done since 2017)::

      M^-1 = [[a, 0, b],
              [0, 1, 0],
              [c, 0, d]]

  (:func:`minv_matrix` rebuilds it; ``D`` is invariant to the scale of ``M^-1``, hence the
  normalisation). The LTC ``D`` with this matrix approximates the *normalised* lobe
  ``rho cos / norm``. The middle entry is ``1 / m22`` (step 2 below), bounded away from 0,
  so every coefficient stays below 2 (measured: 1.13 GGX, 1.40 Beckmann). Table format 1
  divided by the (2, 2) entry, ``cos(phi) / ...``, which goes to 0 as the lobe turns to the
  horizon: it reached 1.2e13 in the grazing corner of smooth lobes (35 cells beyond float16)
  and is refused by :func:`read_table`.

**Shading frame.** For a shading normal ``n`` and view ``wo`` (world space) take
``t1 = normalize(wo - n (n.wo))`` (any tangent when ``wo`` is parallel to ``n``: the lobe is
then rotationally symmetric), ``t2 = n x t1``; a world direction ``w`` has local coordinates
``R w`` with ``R = [t1; t2; n]`` (rows), so the world-space inverse matrix is ``M^-1 R``
(:func:`world_minv`; HDHN16's shading code does the same). ``det R = 1`` and ``|R w| = |w|``,
so ``ltc_eval(M^-1 R, w) = ltc_eval(M^-1, R w)`` and polygons can be transformed by
``M^-1 R`` directly.

**Table axes** (``size`` nodes per axis, 64 for the shipped tables ``data/ltc_ggx.npz`` and
``data/ltc_beckmann.npz``):

* rows ``j``: perceptual roughness ``r_j = j / (size - 1)``, fitted at
  ``alpha_j = max(r_j^2, ALPHA_MIN)``: ``ALPHA_MIN = 1e-4`` is Mitsuba's clamp (and the one
  :class:`glossrt.lights.shading.ShadingPoints` applies), so row 0 (nominally ``r = 0``) holds
  the fit at ``alpha = 1e-4`` (``r = 0.01``); every other row is unclamped
  (``r_1^2 = 2.5e-4``). Lookups place row 0 where it was fitted, at ``r = 0.01``: between
  ``r = 0.01`` and ``r_1`` they interpolate rows 0 and 1 linearly in ``r``, and every
  ``alpha <= ALPHA_MIN`` reads row 0 (the near-mirror LTC is ~2 alpha wide, so blending
  rows 0 and 1 at ``alpha = ALPHA_MIN``, as a plain ``r (size - 1)`` coordinate would, makes
  it ~1.6x too wide);
* columns ``i``: ``u_i = i / (size - 1)`` with ``u = sqrt(1 - cos theta_o)`` (the
  parameterisation of HDHN16's public fitting code after 2017, which resolves grazing views),
  fitted at ``cos theta_o = max(1 - u_i^2, COS_O_MIN)``, ``COS_O_MIN = cos(1.57)`` (the last
  column, ``u = 1``, is the view at 89.95 degrees, as in that code).

:class:`LTCTable` interpolates bilinearly in ``(r, u)`` (Dr.Jit: :meth:`LTCTable.lookup`;
NumPy: :meth:`LTCTable.lookup_np`), clamping to the grid.

**Fit** (:func:`fit_table`; ``python -m glossrt.lights.ltc.fit`` or ``glossrt ltc-fit``).
Following HDHN16 sec. 4 and the procedure of their public fitting code (re-implemented, not
copied), with one change (step 2: the frame angle is fitted too), per cell:

1. ``norm``, ``fres`` and the lobe's average direction ``integral rho cos wi dwi`` (its y
   component is 0 by symmetry; angle ``avg_phi`` from +z) by deterministic quadrature
   (:func:`brdf_moments`: a Hammersley set mapped through the lobe's sampling, GGX visible
   normals (Heitz 2018) or Beckmann ``D cos``, in float64);
2. ``M = R_y(phi) [[m11, 0, m13], [0, m22, 0], [0, 0, 1]]`` (:func:`ltc_matrix`; ``R_y(phi)``
   turns +z by ``phi`` towards +x). Up to scale this is every matrix of the canonical form
   (an RQ decomposition of its xz block), and ``(M^-1)_22 = cos(phi)``. The four parameters
   ``(m11, m22, m13, phi)`` minimise the L1 error

       E1 = integral |rho cos / norm - D| dw      (``metric="l1"``, the shipped tables)

   which bounds every polygon's error (below), or ``E = integral |rho cos / norm - D|^3 dw``
   (``metric="l3"``, the cubed-difference metric of HDHN16's fitting code). Measured: L1
   fits lower the median polygon error of GGX from 0.044 to 0.034 and its 99th percentile
   from 1.94 to 1.22 (tests/test_ltc.py's 600 polygons), and image errors against
   Mitsuba's ``direct`` integrator by 10-15% (docs/RESULTS.md). HDHN16's code fixes ``phi``
   to the average direction; fitting it as well lowers ``E`` 2-6x at oblique views
   (measured), as it lets the LTC's own horizon (the great circle where
   ``(M^-1 w)_z = 0``) follow the
   surface's, which clips the lobe. ``E`` is estimated with multiple importance sampling
   (Veach 1997, balance heuristic) from ``n x n`` stratified samples (``n = 64``) of *both*
   the LTC (:func:`ltc_sample`) and the lobe (:func:`glossrt.brdf.microfacet.sample_h`: GGX
   visible normals, Beckmann ``D cos``): each sample ``w`` of either strategy contributes
   ``|rho cos / norm - D|^k / (p_brdf(w) + D(w))``. The samples are the same for
   every evaluation of a cell, so ``E`` is a smooth deterministic function of the
   parameters. It is evaluated by one Dr.Jit kernel vectorised over the samples, in float64,
   recorded once with ``dr.freeze`` (every parameter is an input array, so no evaluation
   re-traces or recompiles: ~0.23 ms per evaluation on 2 CPU cores, Python included);
3. SciPy's Nelder-Mead (Nelder & Mead 1965) minimises ``log E1`` (or ``log E``) over
   ``x = (ln m11, ln m22, m13 / m11, atanh(2 phi / pi))`` (scale-free, so one tolerance
   serves every roughness; ``|phi| < pi/2`` keeps ``(M^-1)_22 > 0``), from a simplex of
   size 0.05 around the start (as HDHN16's code), ``xatol = 1e-4``, ``fatol = 1e-6``, at
   most 4000 evaluations;
4. order and warm start as HDHN16's code: rows from rough (``r = 1``) to smooth, each row from
   normal incidence to grazing. At normal incidence the lobe is rotationally symmetric:
   ``phi = 0``, ``m11 = m22``, ``m13 = 0`` (one parameter), started from the normal-incidence
   fit of the next rougher row (``m11 = 1``, the cosine itself, for ``r = 1``). Every other
   cell starts from the previous cell of its row, with the orientation from the average
   direction, as the best (smallest ``E``) of three candidates (:func:`warm_start`): the
   neighbour's four parameters with ``phi`` turned by the change of the average direction;
   the neighbour's ``(m11, m22, m13)`` with ``phi`` = this cell's average direction
   (HDHN16's start); the same with ``m13 = 0``.

   Rows depend on each other only through their normal-incidence cells, so
   :func:`fit_table` fits that column first and then each row on its own (:func:`fit_row`,
   a work item for ``glossrt ltc-fit --cluster``): the same table bit for bit.

The npz also keeps the fit parameters (``params`` ``(m11, m22, m13, phi)`` and ``avg_phi``)
so that any cell can be re-fitted from its neighbours exactly as :func:`fit_table` did
(tests/test_ltc_fit.py does), and two error measures per cell, both estimated with the fit's
samples: ``err_l3`` (``E`` above) and ``err_l1 = integral |rho cos / norm - D| dw`` (in
[0, 2]: twice the total-variation distance between the normalised lobe and the LTC, so
``|integral_P rho cos / norm - integral_P D| <= err_l1 / 2`` for every region ``P``).

**Measured** (shipped tables, 2-core CPU, ``llvm_ad_rgb``, 2026-12-01): the 64 x 64 L1 fit
takes 96 s for GGX (775k error evaluations; 4 cells stop at the 4000-evaluation cap, all at
``alpha <= 2.5e-4`` where the fit is near-exact) and 107 s for Beckmann (708k). Lobe error
``err_l1`` over the cells, GGX: median 0.034, mean 0.067, 95th percentile 0.26, max 0.80
(the grazing column ``u = 1``; without it 0.54); for views up to 69 degrees (``u <= 0.8``)
median 0.030, max 0.20. Beckmann: median 0.34, mean 0.28, 95th percentile 0.45, max 1.0;
``u <= 0.8``: median 0.31, max 0.41. No LTC fits a Beckmann lobe as closely as a GGX one:
GGX's ``D`` is itself a linearly transformed cosine of the normals (HDHN16), Beckmann's has
Gaussian, not power-law, tails. An independent scan of every scaled cosine against a
Beckmann lobe at normal incidence (alpha 0.1, float64 quadrature) finds no L1 below 0.342:
the table's 0.34-0.37 at small alpha is that limit, not a failed fit. It improves towards
rough lobes (0.01-0.04 at alpha >= 0.6, near normal incidence). (The earlier GGX table,
height-correlated Smith and L3: median 0.038, 95th percentile 0.36; the published fit of
HDHN16's code scored with the same samples: median 0.057, 95th percentile 0.47.)

Bilinear lookups midway between nodes (121 midpoints ``r = (j + 1/2) / 63``,
``u = (i + 1/2) / 63``, ``j, i = 1, 7, ..., 61``): the L1 error at the midpoint exceeds the
worst of its four nodes by median -0.001, 90th percentile 0.0043 (GGX; Beckmann 0.0002);
the earlier (2, 2)-normalised table: 90th percentile 0.015, and at views up to 69 degrees a
worst midpoint L1 of 0.58 against 0.35 now. Near-mirror rows (``r < 0.05``) close to
grazing still interpolate poorly with either normalisation (a lobe narrower than the node
spacing moves by more than its width between nodes: L1 up to 1.8 there).

References:
    E. Heitz, J. Dupuy, S. Hill, D. Neubelt, "Real-time polygonal-light shading with linearly
    transformed cosines", ACM TOG 35(4) (SIGGRAPH) 2016.
    E. Heitz, "Understanding the masking-shadowing function in microfacet-based BRDFs",
    JCGT 3(2), 2014.
    E. Heitz, "Sampling the GGX Distribution of Visible Normals", JCGT 7(4), 2018.
    B. Walter, S. Marschner, H. Li, K. Torrance, "Microfacet Models for Refraction through Rough
    Surfaces", EGSR 2007.
    E. Veach, "Robust Monte Carlo Methods for Light Transport Simulation", PhD thesis, 1997.
    J. Nelder, R. Mead, "A simplex method for function minimization", Comput. J. 7(4), 1965.
    C. Schlick, "An Inexpensive BRDF Model for Physically-based Rendering", CGF 13(3), 1994.
    B. Karis, "Real Shading in Unreal Engine 4", SIGGRAPH 2013 course notes.
"""

from __future__ import annotations

import argparse
import functools
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import drjit as dr
import numpy as np
from scipy.optimize import minimize

from ...backend import mi
from ...brdf import microfacet as mf
from ...brdf.ggx import ALPHA_MIN
from ...errors import GlossrtError
from ...jit import no_gc
from .table import (
    COS_O_MIN,
    DEFAULT_SIZE,
    TABLE_FORMAT,
    coeffs_from_minv,
    default_table_path,
    grid_axes,
    minv_matrix,
    node_config,
)

__all__ = [
    "ALPHA_MIN",
    "FIT_SAMPLES",
    "MOMENT_SAMPLES",
    "ltc_matrix",
    "ltc_eval",
    "ltc_sample",
    "world_minv",
    "brdf_moments",
    "CellFit",
    "average_phi",
    "fit_cell",
    "lobe_errors",
    "warm_start",
    "fit_row",
    "fit_table",
    "save_table",
    "main",
]

#: Stratified samples per side and strategy of the fit's error estimate (n x n per strategy).
FIT_SAMPLES = 64
#: Hammersley points per cell for ``norm``, ``fres`` and the average direction.
MOMENT_SAMPLES = 1 << 16
#: Nelder-Mead settings (in ``x = (ln m11, ln m22, m13/m11)``; ``f = log E``).
NM_STEP = 0.05
NM_XATOL = 1e-4
NM_FATOL = 1e-6
NM_MAXFEV = 4000
#: Bound on the fit variable of the frame angle, ``phi = pi/2 tanh(x)``: ``|phi| <=
#: pi/2 (1 - 4e-9)``, so ``(M^-1)_22 = cos(phi) > 0`` (see ``minv``).
PHI_X_MAX = 10.0
_TANH_MAX = math.tanh(PHI_X_MAX)

#: errors a fit can minimise (module docstring)
METRICS = ("l3", "l1")


def _f64() -> type:
    return dr.float64_array_t(mi.Float)


# ----------------------------------------------------------------------------------------------
# LTC matrices, evaluation and sampling
# ----------------------------------------------------------------------------------------------


def ltc_matrix(m11: float, m22: float, m13: float, phi: float) -> np.ndarray:
    """The fit's parameterisation: ``M = R_y(phi) [[m11, 0, m13], [0, m22, 0], [0, 0, 1]]``
    with ``R_y(phi)`` the rotation about +y taking +z to ``(sin phi, 0, cos phi)`` (float64)."""
    s, c = math.sin(phi), math.cos(phi)
    rot = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    return rot @ np.array([[m11, 0.0, m13], [0.0, m22, 0.0], [0.0, 0.0, 1.0]])


def _ltc_eval_xyz(mi_rows, det, x, y, z):
    """``D(w)`` from the rows of ``M^-1``, ``|det M^-1|`` and the components of ``w``
    (HDHN16 sec. 3.1: ``max(v_z, 0) |det M^-1| / (pi |v|^4)``, ``v = M^-1 w``); generic over
    NumPy arrays and Dr.Jit arrays."""
    (a00, a01, a02), (a10, a11, a12), (a20, a21, a22) = mi_rows
    vx = a00 * x + a01 * y + a02 * z
    vy = a10 * x + a11 * y + a12 * z
    vz = a20 * x + a21 * y + a22 * z
    l2 = vx * vx + vy * vy + vz * vz
    if isinstance(l2, np.ndarray | float):
        with np.errstate(divide="ignore", invalid="ignore"):
            d = np.where(vz > 0.0, vz * det / (np.pi * l2 * l2), 0.0)
        return d
    return dr.select(vz > 0.0, vz * det / (dr.pi * l2 * l2), 0.0)


def ltc_eval(minv: Any, w: Any) -> Any:
    """Density ``D(w)`` (per steradian) of the LTC with inverse matrix ``minv`` at ``w``.

    ``D(w) = D_o(M^-1 w / |M^-1 w|) |det M^-1| / |M^-1 w|^3`` with ``D_o = max(z, 0) / pi``
    (HDHN16 sec. 3.1), a density on the unit sphere: pass unit vectors ``w``. ``minv`` may be
    scaled arbitrarily (``D`` does not change).

    NumPy: ``minv`` ``(3, 3)`` or ``(..., 3, 3)``, ``w`` ``(..., 3)`` (broadcast), float64.
    Dr.Jit: ``minv`` a 3x3 matrix (``mi.Matrix3f``, ``Matrix3f64``; per lane or scalar
    entries) and ``w`` a 3-vector of the same precision.
    """
    if isinstance(minv, np.ndarray | list | tuple):
        m = np.asarray(minv, dtype=np.float64)
        w = np.asarray(w, dtype=np.float64)
        det = np.abs(np.linalg.det(m))
        rows = [[m[..., r, c] for c in range(3)] for r in range(3)]
        return _ltc_eval_xyz(rows, det, w[..., 0], w[..., 1], w[..., 2])
    det = dr.abs(dr.det(minv))
    rows = [[minv[r, c] for c in range(3)] for r in range(3)]
    return _ltc_eval_xyz(rows, det, w[0], w[1], w[2])


def ltc_sample(m: Any, u: Any) -> Any:
    """Sample the LTC with (forward) matrix ``m = M`` from uniform numbers ``u`` in [0, 1)^2.

    A cosine-distributed ``w_o = (sqrt(u1) cos 2 pi u2, sqrt(u1) sin 2 pi u2, sqrt(1 - u1))``
    is mapped to ``w = M w_o / |M w_o|`` (HDHN16 sec. 3.2); its density is
    ``ltc_eval(inv(M), w)``.

    NumPy: ``m`` ``(3, 3)`` or ``(..., 3, 3)``, ``u`` ``(..., 2)`` -> ``(..., 3)`` unit vectors.
    Dr.Jit: ``m`` a 3x3 matrix, ``u`` a 2-vector (``mi.Point2f``, ...) -> a 3-vector.
    """
    if isinstance(m, np.ndarray | list | tuple):
        mm = np.asarray(m, dtype=np.float64)
        u = np.asarray(u, dtype=np.float64)
        r = np.sqrt(u[..., 0])
        phi = 2.0 * np.pi * u[..., 1]
        wo = np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(np.maximum(1.0 - u[..., 0], 0))],
                      -1)
        w = np.einsum("...ij,...j->...i", mm, wo)
        return w / np.linalg.norm(w, axis=-1, keepdims=True)
    r = dr.sqrt(u[0])
    s, c = dr.sincos(2.0 * dr.pi * u[1])
    vec_t = dr.value_t(m)  # a row of the matrix: the 3-vector type
    wo = vec_t(r * c, r * s, dr.sqrt(dr.maximum(1.0 - u[0], 0.0)))
    return dr.normalize(m @ wo)


def world_minv(coeffs: mi.Vector4f, n: mi.Vector3f, wo: mi.Vector3f) -> mi.Matrix3f:
    """World-space inverse matrix ``M^-1 R``, ``R = [t1; t2; n]`` (rows; module docstring),
    for table coefficients ``coeffs``, unit shading normal ``n`` and unit view ``wo``
    (towards the viewer). ``ltc_eval(world_minv(...), w)`` is the LTC at world direction ``w``.
    """
    t1 = wo - n * dr.dot(n, wo)
    l2 = dr.squared_norm(t1)
    fallback, _ = mi.coordinate_system(n)
    t1 = dr.select(l2 > 1e-14, t1 * dr.rsqrt(dr.maximum(l2, 1e-30)), fallback)
    t2 = dr.cross(n, t1)
    rot = mi.Matrix3f(t1.x, t1.y, t1.z, t2.x, t2.y, t2.z, n.x, n.y, n.z)
    return minv_matrix(mi.Vector4f(coeffs)) @ rot


# ----------------------------------------------------------------------------------------------
# The lobe (GGX or Beckmann D, separable Smith G1 G1, F = 1) in the local frame, view in xz
# ----------------------------------------------------------------------------------------------


def _lobe(wox, woz, alpha, beckmann, x, y, z):
    """``rho cos(theta_i)`` at ``wi = (x, y, z)`` (separable Smith, F = 1) and the density of
    the BRDF sampling strategy at ``wi`` (:func:`glossrt.brdf.microfacet.pdf_h` over the
    reflection Jacobian ``4 wo.h``)."""
    hx, hy, hz = wox + x, y, woz + z
    inv = dr.rsqrt(dr.maximum(hx * hx + hy * hy + hz * hz, 1e-300))
    hx, hy, hz = hx * inv, hy * inv, hz * inv
    wo_h = wox * hx + woz * hz
    visible = (hz > 0.0) & (wo_h > 0.0)
    # Walter et al. 2007, eqs. 20 and 23 (times cos_i): D G1(wo) G1(wi) / (4 cos_o)
    f = dr.select(visible, mf.specular_cos(woz, z, hz, alpha, beckmann), 0.0)
    pdf = dr.select(visible, mf.pdf_h(woz, wo_h, hz, alpha, beckmann)
                    / (4.0 * dr.maximum(wo_h, 1e-300)), 0.0)
    return f, pdf


def _hammersley(f64, k, n: int):
    u1 = (f64(k) + 0.5) / n
    u2 = f64(dr.brev(k)) * (1.0 / 4294967296.0) + 0.5 / n
    return u1, u2


def brdf_moments(alpha: Any, cos_o: Any, samples: int = MOMENT_SAMPLES,
                 distribution: str = "ggx") -> dict[str, np.ndarray]:
    """``norm``, ``fres`` and the average direction of the lobe at arbitrary points.

    Per point ``(alpha, cos_o)`` (view ``wo = (sin, 0, cos)``): the same ``samples``-point
    Hammersley set mapped to half vectors by :func:`glossrt.brdf.microfacet.sample_h` (GGX
    visible normals, Beckmann ``D cos``), ``wi = reflect(wo, h)``, weight ``rho cos / p``
    (for GGX ``G1(wi)``, for Beckmann ``G1(wo) G1(wi) wo.h / (cos_o cos_h)``; 0 below the
    horizon; bounded, so the quadrature converges fast). Float64, vectorised over all points.

    Returns float64 arrays ``norm``, ``fres`` and ``dir_x``, ``dir_z`` (the unit average
    direction ``integral rho cos wi dwi`` normalised; its y component is 0 by symmetry).
    """
    if samples <= 0 or samples & (samples - 1):
        raise GlossrtError(f"samples must be a positive power of two, got {samples}")
    beck = mf.code(distribution) == mf.BECKMANN
    al = np.asarray(alpha, dtype=np.float64).ravel()
    co = np.asarray(cos_o, dtype=np.float64).ravel()
    if al.shape != co.shape:
        raise GlossrtError("alpha and cos_o must have the same number of elements")
    f64 = _f64()
    log2n = samples.bit_length() - 1
    chunk = max(1, (1 << 21) // samples)
    out = {k: np.empty(al.size) for k in ("norm", "fres", "dir_x", "dir_z")}
    for start in range(0, al.size, chunk):
        stop = min(start + chunk, al.size)
        idx = dr.arange(mi.UInt32, (stop - start) * samples)
        cell = idx >> log2n
        k = idx & (samples - 1)
        a = dr.gather(f64, f64(al[start:stop]), cell)
        c = dr.gather(f64, f64(co[start:stop]), cell)
        s = dr.sqrt(dr.maximum(1.0 - c * c, 0.0))
        u1, u2 = _hammersley(f64, k, samples)
        hx, hy, hz = mf.sample_h(s, dr.zeros(f64, dr.width(c)), c, a, u1, u2, beck)
        cd = s * hx + c * hz  # wo.h = wi.h
        x, z = 2.0 * cd * hx - s, 2.0 * cd * hz - c  # wi (its y component is not needed)
        f, pdf = _lobe(s, c, a, beck, x, 2.0 * cd * hy, z)
        w = dr.select((pdf > 0.0) & (z > 0.0), f / dr.select(pdf > 0.0, pdf, 1.0), 0.0)
        m = 1.0 - dr.clip(cd, 0.0, 1.0)
        m5 = m * m * m * m * m
        sums = {
            "norm": dr.block_sum(w, samples),
            "fres": dr.block_sum(w * m5, samples),
            "dir_x": dr.block_sum(w * x, samples),
            "dir_z": dr.block_sum(w * z, samples),
        }
        dr.eval(sums)
        for key, v in sums.items():
            out[key][start:stop] = v.numpy() / samples
    length = np.hypot(out["dir_x"], out["dir_z"])
    out["dir_x"] = out["dir_x"] / length
    out["dir_z"] = out["dir_z"] / length
    return out


# ----------------------------------------------------------------------------------------------
# Fit of one cell
# ----------------------------------------------------------------------------------------------

# Layout of the per-evaluation parameter array of the error kernel.
_P_ALPHA, _P_WOX, _P_WOZ, _P_INVNORM, _P_M, _P_MINV, _P_DET, _P_BECK = 0, 1, 2, 3, 4, 13, 22, 23
_P_SIZE = 24


def _error_kernel(u1, u2, p):
    """Per-sample terms of the MIS estimates of ``integral |f - D|^3`` and
    ``integral |f - D|`` (``f = rho cos / norm``; their means over the lanes are the
    estimates), one sample per ``(u1, u2)`` of each strategy (module docstring, step 2).

    ``p`` (float64, ``_P_SIZE`` entries) holds the cell and the LTC, so that one recording of
    this function (``dr.freeze``) serves every evaluation: only array contents change."""
    f64 = type(p)

    def g(k):
        return dr.gather(f64, p, k)

    alpha, wox, woz, inv_norm = g(_P_ALPHA), g(_P_WOX), g(_P_WOZ), g(_P_INVNORM)
    m = [[g(_P_M + 3 * r + c) for c in range(3)] for r in range(3)]
    minv = [[g(_P_MINV + 3 * r + c) for c in range(3)] for r in range(3)]
    det = g(_P_DET)
    beck = g(_P_BECK) > 0.5  # the distribution: an array entry, so one recording serves both

    def terms(x, y, z):
        f, p_brdf = _lobe(wox, woz, alpha, beck, x, y, z)
        f = f * inv_norm
        d = _ltc_eval_xyz(minv, det, x, y, z)
        den = p_brdf + d  # balance heuristic, one sample per strategy (Veach 1997, sec. 9.2)
        ok = den > 0.0
        inv_den = dr.select(ok, dr.rcp(dr.select(ok, den, 1.0)), 0.0)
        diff = dr.abs(f - d)
        return diff * diff * diff * inv_den, diff * inv_den

    # strategy 1: the LTC (cosine sample mapped through M, HDHN16 sec. 3.2)
    r = dr.sqrt(u1)
    s, c = dr.sincos(2.0 * dr.pi * u2)
    ox, oy, oz = r * c, r * s, dr.sqrt(dr.maximum(1.0 - u1, 0.0))
    x = m[0][0] * ox + m[0][1] * oy + m[0][2] * oz
    y = m[1][0] * ox + m[1][1] * oy + m[1][2] * oz
    z = m[2][0] * ox + m[2][1] * oy + m[2][2] * oz
    inv = dr.rsqrt(x * x + y * y + z * z)
    e3a, e1a = terms(x * inv, y * inv, z * inv)
    # strategy 2: the BRDF's (GGX visible normals, Heitz 2018; Beckmann D cos), reflected
    hx, hy, hz = mf.sample_h(wox, dr.zeros(f64, dr.width(u1)), woz, alpha, u1, u2, beck)
    cd = wox * hx + woz * hz
    e3b, e1b = terms(2.0 * cd * hx - wox, 2.0 * cd * hy, 2.0 * cd * hz - woz)
    return e3a + e3b, e1a + e1b


_error_frozen = dr.freeze(_error_kernel, warn_after=16)


@functools.lru_cache(maxsize=4)
def _fit_samples(n: int, variant: str):
    """The fixed ``n x n`` stratified set ``((i + 1/2) / n, (j + 1/2) / n)``."""
    f64 = _f64()
    k = np.arange(n * n)
    u1 = f64((k % n + 0.5) / n)
    u2 = f64((k // n + 0.5) / n)
    dr.make_opaque(u1, u2)
    return u1, u2


class _Objective:
    """The fit error of one cell as a function of the LTC parameters ``x``."""

    def __init__(self, alpha: float, cos_o: float, norm: float, isotropic: bool,
                 n: int = FIT_SAMPLES, frozen: bool = True, distribution: str = "ggx",
                 metric: str = "l3"):
        if metric not in METRICS:
            raise GlossrtError(f"metric must be one of {METRICS}, got {metric!r}")
        self.metric = metric
        self.base = np.zeros(_P_SIZE)
        self.base[_P_ALPHA] = alpha
        self.base[_P_BECK] = float(mf.code(distribution) == mf.BECKMANN)
        self.base[_P_WOX] = math.sqrt(max(1.0 - cos_o * cos_o, 0.0))
        self.base[_P_WOZ] = cos_o
        self.base[_P_INVNORM] = 1.0 / norm
        self.isotropic = isotropic
        self.u1, self.u2 = _fit_samples(n, mi.variant())
        self.fn = _error_frozen if frozen else _error_kernel
        self.nfev = 0

    def params(self, x: np.ndarray) -> tuple[float, float, float, float]:
        """``x -> (m11, m22, m13, phi)``: ``x = (ln m11)`` (isotropic: ``m22 = m11``,
        ``m13 = phi = 0``) or ``(ln m11, ln m22, m13 / m11, atanh(2 phi / pi))``: the
        last keeps ``|phi| < pi/2``, i.e. ``(M^-1)_22 = cos(phi) > 0`` (the LTC's support
        hemisphere contains the normal)."""
        m11 = math.exp(float(np.clip(x[0], -60.0, 10.0)))
        if self.isotropic:
            return m11, m11, 0.0, 0.0
        m22 = math.exp(float(np.clip(x[1], -60.0, 10.0)))
        phi = 0.5 * math.pi * math.tanh(float(np.clip(x[3], -PHI_X_MAX, PHI_X_MAX)))
        return m11, m22, float(x[2]) * m11, phi

    def x_of(self, params: Any) -> np.ndarray:
        """Inverse of :meth:`params`."""
        m11, m22, m13, phi = (float(v) for v in params)
        if self.isotropic:
            return np.array([math.log(m11)])
        t = float(np.clip(2.0 * phi / math.pi, -_TANH_MAX, _TANH_MAX))
        return np.array([math.log(m11), math.log(m22), m13 / m11, math.atanh(t)])

    def errors(self, x: np.ndarray) -> tuple[float, float]:
        return self.errors_of(ltc_matrix(*self.params(x)))

    def errors_of(self, m: np.ndarray) -> tuple[float, float]:
        """``(E, L1)`` of the LTC with forward matrix ``m``."""
        minv = np.linalg.inv(m)
        p = self.base.copy()
        p[_P_M:_P_M + 9] = m.ravel()
        p[_P_MINV:_P_MINV + 9] = minv.ravel()
        p[_P_DET] = abs(np.linalg.det(minv))
        with no_gc():  # see glossrt.jit.no_gc: no cyclic GC inside a frozen call
            e3, e1 = self.fn(self.u1, self.u2, _f64()(p))
        self.nfev += 1
        # per-sample terms summed on the host: one kernel launch, no reduction kernels, and
        # NumPy's pairwise summation does not depend on the thread count
        n = dr.width(e3)
        return float(np.sum(e3.numpy())) / n, float(np.sum(e1.numpy())) / n

    def __call__(self, x: np.ndarray) -> float:
        e3, e1 = self.errors(x)
        e = e1 if self.metric == "l1" else e3
        return math.log(e) if e > 0.0 and math.isfinite(e) else 1e300


@dataclass
class CellFit:
    """Result of :func:`fit_cell`: ``params = (m11, m22, m13, phi)`` define
    ``M = ltc_matrix(*params)``; ``coeffs`` are its inverse's ``(a, b, c, d)``."""

    alpha: float
    cos_o: float
    norm: float
    fres: float
    avg_phi: float
    params: np.ndarray
    coeffs: np.ndarray
    err_l3: float
    err_l1: float
    nfev: int

    @property
    def m(self) -> np.ndarray:
        return ltc_matrix(*self.params)

    @property
    def minv(self) -> np.ndarray:
        return minv_matrix(self.coeffs)


def average_phi(moments: dict[str, float]) -> float:
    """Angle from +z (towards +x) of the lobe's average direction."""
    return math.atan2(moments["dir_x"], moments["dir_z"])


def fit_cell(alpha: float, cos_o: float, start: Any, *, isotropic: bool = False,
             moments: dict[str, float] | None = None, fit_samples: int = FIT_SAMPLES,
             moment_samples: int = MOMENT_SAMPLES, frozen: bool = True,
             distribution: str = "ggx", metric: str = "l1") -> CellFit:
    """Fit the LTC of one cell (module docstring, steps 1-3).

    Args:
        alpha: GGX roughness (used as is: clamp it as :func:`node_config` does).
        cos_o: view cosine (likewise).
        start: initial ``(m11, m22, m13, phi)``, or several (``(k, 4)``): Nelder-Mead starts
            from the one with the smallest error (:func:`warm_start`). For ``isotropic``
            only ``m11`` is used.
        isotropic: fit one parameter with ``m11 = m22``, ``m13 = phi = 0`` (normal incidence,
            where the lobe is rotationally symmetric).
        moments: ``norm``, ``fres``, ``dir_x``, ``dir_z`` of the cell when already computed
            (:func:`brdf_moments`); computed here otherwise.
        fit_samples: ``n`` of the ``n x n`` stratified samples per strategy.
        moment_samples: Hammersley points for the moments.
        frozen: evaluate through the ``dr.freeze`` recording (the default) or trace each call.
        distribution: ``"ggx"`` or ``"beckmann"``.
        metric: the error minimised, ``"l3"`` (``E``, HDHN16's) or ``"l1"`` (``err_l1``).
    """
    if moments is None:
        mo = brdf_moments([alpha], [cos_o], moment_samples, distribution)
        moments = {k: float(v[0]) for k, v in mo.items()}
    obj = _Objective(alpha, cos_o, moments["norm"], isotropic, fit_samples, frozen, distribution,
                     metric)
    starts = np.atleast_2d(np.asarray(start, dtype=np.float64))
    candidates = [obj.x_of(st) for st in starts]
    x0 = candidates[0]
    if len(candidates) > 1:
        x0 = min(candidates, key=obj)  # the first of the best (min is stable)
    # HDHN16's code starts from a simplex of size 0.05 around the warm start; here in x
    simplex = np.vstack([x0] + [x0 + NM_STEP * e for e in np.eye(x0.size)])
    res = minimize(obj, x0, method="Nelder-Mead",
                   options={"initial_simplex": simplex, "xatol": NM_XATOL, "fatol": NM_FATOL,
                            "maxfev": NM_MAXFEV})
    params = np.array(obj.params(res.x))
    e3, e1 = obj.errors(res.x)
    coeffs = coeffs_from_minv(np.linalg.inv(ltc_matrix(*params)))
    return CellFit(alpha=float(alpha), cos_o=float(cos_o), norm=float(moments["norm"]),
                   fres=float(moments["fres"]), avg_phi=average_phi(moments), params=params,
                   coeffs=coeffs, err_l3=e3, err_l1=e1, nfev=obj.nfev)


def lobe_errors(alpha: float, cos_o: float, m: np.ndarray, norm: float | None = None,
                fit_samples: int = FIT_SAMPLES, distribution: str = "ggx") -> tuple[float, float]:
    """``(E, L1)`` (module docstring) of any LTC with forward matrix ``m`` (3x3, local frame
    of the view ``(sin, 0, cos)``) against the normalised lobe at ``(alpha, cos_o)``, with the
    fit's ``fit_samples x fit_samples`` samples per strategy. ``norm`` defaults to
    :func:`brdf_moments`'."""
    if norm is None:
        norm = float(brdf_moments([alpha], [cos_o], distribution=distribution)["norm"][0])
    obj = _Objective(alpha, cos_o, norm, False, fit_samples, distribution=distribution)
    return obj.errors_of(np.asarray(m, dtype=np.float64))


def warm_start(params: np.ndarray, avg_phi: np.ndarray, j: int,
               i: int) -> tuple[np.ndarray, bool]:
    """Candidate starts of cell ``(j, i)`` (module docstring, step 4) from the fitted
    ``params`` (``(size, size, 4)``) of the cells fitted before it and the angles
    ``avg_phi`` (``(size, size)``) of the lobes' average directions.

    Returns ``(starts, isotropic)``; ``starts`` is ``(k, 4)``. At normal incidence
    (``i = 0``): the fit of the next rougher row (the cosine for ``j = size - 1``). Otherwise
    three candidates from the previous cell ``(j, i - 1)`` of the row, ``(m11, m22, m13,
    phi)``: (1) all four, ``phi`` turned by the change of the average direction; (2)
    ``(m11, m22, m13)`` with ``phi`` = this cell's average direction (HDHN16's start);
    (3) like (2) with ``m13 = 0``.
    """
    size = params.shape[0]
    if i == 0:
        if j == size - 1:
            return np.array([[1.0, 1.0, 0.0, 0.0]]), True
        return np.array(params[j + 1, 0])[None], True
    m11, m22, m13, phi = params[j, i - 1]
    a = avg_phi[j, i]
    lim = 0.5 * math.pi * _TANH_MAX
    turned = float(np.clip(phi + a - avg_phi[j, i - 1], -lim, lim))
    return np.array([[m11, m22, m13, turned], [m11, m22, m13, a], [m11, m22, 0.0, a]]), False


def fit_row(item: dict) -> dict:
    """Cells ``i = 1 .. size - 1`` of one table row (issue 27: a work item a cluster can run
    in any process), from plain data: ``alpha`` (the row's roughness), ``cos_o``,
    ``avg_phi`` and ``moments`` (``norm``, ``fres``, ``dir_x``, ``dir_z``; lists of ``size``
    floats), ``first`` (the fitted ``(m11, m22, m13, phi)`` of the row's normal-incidence cell
    ``i = 0``), ``fit_samples``, ``distribution``, ``metric``. Each cell warm-starts from the
    previous one of the row (:func:`warm_start`, step 4), exactly as :func:`fit_table`'s
    one-process order does, so the row equals that fit's row bit for bit.

    Returns float64 arrays ``params``, ``minv`` ``(size - 1, 4)``, ``err_l3``, ``err_l1`` and
    int64 ``nfev`` ``(size - 1,)`` for cells ``1 .. size - 1``, and ``j`` (as given)."""
    cos_o = np.asarray(item["cos_o"], np.float64)
    size = len(cos_o)
    mo = {k: np.asarray(item["moments"][k], np.float64)
          for k in ("norm", "fres", "dir_x", "dir_z")}
    avg_phi = np.asarray(item["avg_phi"], np.float64)[None]
    params = np.zeros((1, size, 4))
    params[0, 0] = np.asarray(item["first"], np.float64)
    out = {"params": np.zeros((size - 1, 4)), "minv": np.zeros((size - 1, 4)),
           "err_l3": np.zeros(size - 1), "err_l1": np.zeros(size - 1),
           "nfev": np.zeros(size - 1, np.int64)}
    with no_gc():
        for i in range(1, size):
            start, iso = warm_start(params, avg_phi, 0, i)  # (row 0 of a one-row table)
            cell = fit_cell(float(item["alpha"]), float(cos_o[i]), start, isotropic=iso,
                            moments={k: float(v[i]) for k, v in mo.items()},
                            fit_samples=int(item["fit_samples"]),
                            distribution=item["distribution"], metric=item["metric"])
            params[0, i] = cell.params
            out["params"][i - 1] = cell.params
            out["minv"][i - 1] = cell.coeffs
            out["err_l3"][i - 1] = cell.err_l3
            out["err_l1"][i - 1] = cell.err_l1
            out["nfev"][i - 1] = cell.nfev
    return {"j": item["j"], **out}


def _map_rows(items: list[dict], cluster, progress: bool, desc: str) -> list[dict]:
    """:func:`fit_row` over ``items`` through :func:`glossrt.cluster.map_items`;
    ``cluster=None`` runs them in this process in order."""
    from ...cluster import map_items

    return map_items(fit_row, items, cluster="none" if cluster is None else cluster,
                     desc=desc, progress=progress)


def fit_table(size: int = DEFAULT_SIZE, *, progress: bool = True,
              fit_samples: int = FIT_SAMPLES, moment_samples: int = MOMENT_SAMPLES,
              distribution: str = "ggx", metric: str = "l1",
              cluster=None) -> dict[str, np.ndarray]:
    """Fit the whole ``size x size`` table (module docstring).

    The warm starts (step 4) chain a row's cells from normal incidence to grazing, and the
    rows only through their normal-incidence cells (``(j, 0)`` starts from ``(j + 1, 0)``).
    So the fit runs that column first (``size`` one-parameter fits, ~1% of the work), then
    every row's other cells as an independent work item (:func:`fit_row`): on ``cluster``
    (a :func:`glossrt.cluster.map_items` spec) or one after the other in this process, the
    same table bit for bit as fitting the cells in HDHN16's order.

    Returns float64 arrays ``minv`` ``(size, size, 4)``, ``params`` ``(size, size, 4)``,
    ``norm``, ``fres``, ``avg_phi``, ``err_l3``, ``err_l1``, ``nfev`` ``(size, size)`` and the
    axes ``r``, ``u``, ``alpha``, ``cos_o`` (``size``), indexed ``[j (roughness), i (view)]``.
    """
    if metric not in METRICS:
        raise GlossrtError(f"metric must be one of {METRICS}, got {metric!r}")
    if str(distribution).lower() not in mf.NAMES:
        raise GlossrtError(f"distribution must be one of {mf.NAMES}, got {distribution!r}")
    r, u = grid_axes(size)
    alpha, cos_o = node_config(r, u)
    aa, cc = np.meshgrid(alpha, cos_o, indexing="ij")
    mo = brdf_moments(aa.ravel(), cc.ravel(), moment_samples, distribution)
    mo = {k: v.reshape(size, size) for k, v in mo.items()}
    avg_phi = np.arctan2(mo["dir_x"], mo["dir_z"])
    out = {
        "minv": np.zeros((size, size, 4)),
        "params": np.zeros((size, size, 4)),
        "err_l3": np.zeros((size, size)),
        "err_l1": np.zeros((size, size)),
        "nfev": np.zeros((size, size), dtype=np.int64),
    }
    with no_gc():  # the normal-incidence column, from rough to smooth (a chain)
        for j in range(size - 1, -1, -1):
            start, iso = warm_start(out["params"], avg_phi, j, 0)
            cell = fit_cell(alpha[j], cos_o[0], start, isotropic=iso,
                            moments={k: float(v[j, 0]) for k, v in mo.items()},
                            fit_samples=fit_samples, distribution=distribution, metric=metric)
            out["minv"][j, 0] = cell.coeffs
            out["params"][j, 0] = cell.params
            out["err_l3"][j, 0] = cell.err_l3
            out["err_l1"][j, 0] = cell.err_l1
            out["nfev"][j, 0] = cell.nfev
    items = [{"j": j, "alpha": float(alpha[j]), "cos_o": cos_o.tolist(),
              "avg_phi": avg_phi[j].tolist(),
              "moments": {k: v[j].tolist() for k, v in mo.items()},
              "first": out["params"][j, 0].tolist(), "fit_samples": int(fit_samples),
              "distribution": distribution, "metric": metric}
             for j in range(size - 1, -1, -1)]  # rough to smooth, as HDHN16's order
    for row in _map_rows(items, cluster, progress, f"fitting LTC rows ({distribution})"):
        j = int(row["j"])
        for k in ("minv", "params", "err_l3", "err_l1", "nfev"):
            out[k][j, 1:] = row[k]
    out.update(norm=mo["norm"], fres=mo["fres"], avg_phi=avg_phi, r=r, u=u, alpha=alpha,
               cos_o=cos_o, distribution=distribution, metric=metric)
    return out


# ----------------------------------------------------------------------------------------------
# Shipped table
# ----------------------------------------------------------------------------------------------


def save_table(table: dict[str, np.ndarray], path: Path | str, *, fit_samples: int = FIT_SAMPLES,
               moment_samples: int = MOMENT_SAMPLES, seconds: float = float("nan")) -> None:
    """Write a table from :func:`fit_table`: the runtime arrays (``minv``, ``norm``, ``fres``)
    in float32, the axes and the fit's parameters and errors (float64) as metadata."""
    dist = str(table.get("distribution", "ggx"))
    np.savez_compressed(
        path,
        format=np.int64(TABLE_FORMAT),
        distribution=np.array(dist),
        metric=np.array(str(table.get("metric", "l3"))),
        minv=table["minv"].astype(np.float32),
        norm=table["norm"].astype(np.float32),
        fres=table["fres"].astype(np.float32),
        r=table["r"],
        u=table["u"],
        alpha=table["alpha"],
        cos_o=table["cos_o"],
        params=table["params"],
        avg_phi=table["avg_phi"],
        err_l3=table["err_l3"],
        err_l1=table["err_l1"],
        nfev=table["nfev"],
        alpha_min=np.float64(ALPHA_MIN),
        cos_o_min=np.float64(COS_O_MIN),
        fit_samples=np.int64(fit_samples),
        moment_samples=np.int64(moment_samples),
        fit_seconds=np.float64(seconds),
        layout=np.array(
            "[j, i]: r_j = j/(n-1) (alpha = max(r^2, alpha_min)), u_i = i/(n-1) "
            "(cos_o = max(1 - u^2, cos_o_min)); minv[..., :] = (a, b, c, d) of "
            "M^-1 = [[a,0,b],[0,1,0],[c,0,d]] (divided by its middle element; view in the "
            "xz-plane, +x towards the view); norm = int rho cos, fres = int rho cos "
            f"(1 - wo.h)^5 for {dist} D, Mitsuba's separable Smith G1(wo) G1(wi), F = 1"
        ),
    )


# ----------------------------------------------------------------------------------------------
# Command line
# ----------------------------------------------------------------------------------------------


def main(argv: list[str] | None = None) -> int:
    """Fit the LTC table of a distribution and write it (``python -m glossrt.lights.ltc.fit``)."""
    ap = argparse.ArgumentParser(prog="python -m glossrt.lights.ltc.fit", description=main.__doc__)
    ap.add_argument("--out", type=Path, default=None,
                    help="output .npz (default: the shipped glossrt/data/ltc_<distribution>.npz)")
    ap.add_argument("--distribution", choices=mf.NAMES, default="ggx",
                    help="microfacet distribution of the fitted lobe (default: ggx)")
    ap.add_argument("--metric", choices=METRICS, default="l1",
                    help="error the fit minimises: l3 (Heitz et al.'s) or l1 (default: l1)")
    ap.add_argument("--size", type=int, default=DEFAULT_SIZE, help="nodes per axis (64)")
    ap.add_argument("--progress", action=argparse.BooleanOptionalAction, default=True,
                    help="progress bar on stderr (default: on)")
    ap.add_argument("--fit-samples", type=int, default=FIT_SAMPLES,
                    help="n: n x n stratified samples per strategy in the fit error")
    ap.add_argument("--moment-samples", type=int, default=MOMENT_SAMPLES,
                    help="Hammersley points for norm/fres (power of two)")
    ap.add_argument("--cluster", default=None, metavar="SPEC",
                    help="fit the table's rows on a Ray cluster: local[:N], auto or "
                         "ray://HOST:PORT (default: this process); the same table")
    args = ap.parse_args(argv)
    if args.size < 2:
        ap.error("--size must be at least 2")
    out = args.out or default_table_path(args.distribution)
    t0 = time.perf_counter()
    table = fit_table(args.size, progress=args.progress, fit_samples=args.fit_samples,
                      moment_samples=args.moment_samples, distribution=args.distribution,
                      metric=args.metric, cluster=args.cluster)
    dt = time.perf_counter() - t0
    finite = all(np.all(np.isfinite(table[k])) for k in ("minv", "norm", "fres"))
    if not finite:
        raise SystemExit("non-finite values in the fitted table")
    out.parent.mkdir(parents=True, exist_ok=True)
    save_table(table, out, fit_samples=args.fit_samples, moment_samples=args.moment_samples,
               seconds=dt)
    e1 = table["err_l1"]
    print(f"wrote {out} ({args.distribution}): {args.size} x {args.size} cells in {dt:.1f} s "
          f"({int(table['nfev'].sum())} error evaluations); L1 lobe error median "
          f"{np.median(e1):.4f}, 95% {np.quantile(e1, 0.95):.4f}, max {e1.max():.4f}; "
          f"norm in [{table['norm'].min():.4f}, {table['norm'].max():.4f}]")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
