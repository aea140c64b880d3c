"""Spherical Gaussians (SG) and the specular-lobe-aware bilateral weight of Tokuyoshi 2015.

Reference: Y. Tokuyoshi, "Specular Lobe-Aware Filtering and Upsampling for Interactive
Indirect Illumination", IPSJ Journal 56(8), 2015 (lobe-aware filtering; sections 3-4).

All Dr.Jit functions take ``mi.Float`` / ``mi.Vector3f`` (or any Dr.Jit float / 3-vector type,
e.g. ``Float64``; Python scalars are accepted for scalar parameters) and run per pixel inside
filters. Directions (``w``, ``xi``, ``n``, ``wo``) must be unit vectors.

Numerically safe forms (documented at each function):

* ``w . xi - 1`` is evaluated as ``-|w - xi|^2 / 2`` (identical for unit vectors) so a sharp
  lobe (``lambda`` ~ 1e6) is not destroyed by the cancellation in ``1 - cos`` at small angles;
* ``(1 - exp(-x)) / x`` (:func:`_one_minus_exp_neg_over`) uses a Taylor series below 0.1
  (an ``expm1`` substitute: Dr.Jit 1.5 has no ``expm1``), so ``lambda -> 0`` gives the finite
  limits (``sg_integral(0) = 4 pi``);
* eq. 6 is rewritten as ``2 pi exp(r - s) (1 - exp(-2 r)) / r`` with ``s = l1 + l2`` (an
  exponential of a *difference*: no overflow of ``sinh(r)`` or ``exp(l1 + l2)``), where
  ``r^2 = (l1 - l2)^2 + l1 l2 |xi1 + xi2|^2`` and ``r - s = -l1 l2 |xi1 - xi2|^2 / (r + s)``
  (both identities hold for unit axes and are free of cancellation, also near-antipodal);
* weights are formed in the log domain, ``w = exp(beta log q)``, and clamped to ``[0, 1]``.

Sharpness range: ``lambda`` in ``[0, 1e12]`` (products ``l1 l2`` must stay below the float32
maximum 3e38); the lobe constructors clamp to :data:`LAMBDA_MAX`.
"""

from __future__ import annotations

import math

import drjit as dr

from ..backend import mi  # noqa: F401  (read as sg.mi by glossrt.report.figures)
from ..jit import pow_int
from .microfacet import by_distribution

__all__ = [
    "ALPHA_MIN",
    "COS_MIN",
    "GGX_SG_PEAK",
    "LAMBDA_MAX",
    "LAMBDA_MIN",
    "WANG_SG",
    "beckmann_lobe_to_sg",
    "gaussian_weight",
    "ggx_lobe_to_sg",
    "lobe_weight",
    "lobe_tap_log_scale",
    "lobe_tap_sharpness",
    "lobe_tap_terms",
    "phong_lobe_to_sg",
    "reflect",
    "sg_eval",
    "sg_integral",
    "sg_product_integral",
    "sg_product_integral_approx",
    "smoothed_sharpness",
    "lobe_to_sg",
]

#: Smallest roughness used by the lobe constructors (Mitsuba's microfacet ``ALPHA_MIN``).
ALPHA_MIN = 1e-4
#: Smallest ``|n . wo|`` used by the lobe constructors (grazing view).
COS_MIN = 1e-6
#: Sharpness clamp of the lobe constructors.
LAMBDA_MAX = 1e12
#: Floor of the (smoothed) sharpness inside the weights, so ``lambda = 0`` gives no 0 / 0.
LAMBDA_MIN = 1e-8

#: NDF sharpness ``lambda_h = WANG_SG / alpha^2`` of Wang et al. 2009's SG fit of the
#: Cook-Torrance (Beckmann) NDF: ``exp(-tan^2 / alpha^2) ~ exp((2 / alpha^2)(h . n - 1))``.
WANG_SG = 2.0
#: ``lambda_h = GGX_SG_PEAK / alpha^2`` matches the GGX NDF's curvature at its peak:
#: ``D(h) / D(n) = (1 + tan^2 / alpha^2)^-2 ~ 1 - 2 theta^2 / alpha^2``. (A least-squares fit
#: over the sphere gives ~2.7 for alpha in [0.05, 0.2]: GGX's heavy tail widens it.)
GGX_SG_PEAK = 4.0

_FOUR_PI = 4.0 * math.pi
_LOG_FOUR_PI = math.log(_FOUR_PI)


# --------------------------------------------------------------------------------------------
# helpers


def _one_minus_exp_neg_over(x):
    """``(1 - exp(-x)) / x`` for ``x >= 0``, with the limit 1 at ``x = 0``.

    Below ``x = 0.1`` a 5-term Taylor series (truncation < 1.4e-8) replaces the cancelling
    ``1 - exp(-x)`` (it plays the role of ``-expm1(-x) / x``)."""
    x = dr.maximum(x, 0.0)
    series = 1.0 + x * (-1.0 / 2.0 + x * (1.0 / 6.0 + x * (-1.0 / 24.0 + x * (1.0 / 120.0))))
    direct = (1.0 - dr.exp(-x)) / dr.maximum(x, 1e-30)
    return dr.select(x < 0.1, series, direct)


def _cos_minus_one(a, b):
    """``a . b - 1`` for unit vectors, as ``-|a - b|^2 / 2`` (no cancellation near a = b)."""
    return -0.5 * dr.squared_norm(a - b)


def reflect(wo, n):
    """Mirror direction of ``wo`` about ``n``: ``2 (n . wo) n - wo``."""
    return 2.0 * dr.dot(n, wo) * n - wo


# --------------------------------------------------------------------------------------------
# spherical Gaussians (Tokuyoshi 2015, sec. 4.1)


def sg_eval(w, xi, lambda_):
    """SG ``G(w; xi, lambda) = exp(lambda (w . xi - 1))``.

    Tokuyoshi 2015, sec. 4.1 (SG definition, ``= g(|w - xi|, 1 / lambda)``). ``w . xi - 1``
    is evaluated as ``-|w - xi|^2 / 2``."""
    # Tokuyoshi 2015, sec. 4.1: G(w, xi, lambda) = exp(lambda ((w . xi) - 1))
    return dr.exp(lambda_ * _cos_minus_one(w, xi))


def sg_integral(lambda_):
    """Integral of ``G(w; xi, lambda)`` over the sphere: ``2 pi (1 - exp(-2 lambda)) / lambda``.

    Evaluated as ``4 pi (1 - exp(-2 lambda)) / (2 lambda)`` with the safe ``(1 - e^-x) / x``:
    finite for ``lambda -> 0`` (limit ``4 pi``) and for large ``lambda`` (``-> 2 pi / lambda``).
    """
    return _FOUR_PI * _one_minus_exp_neg_over(2.0 * lambda_)


def _product_terms(xi1, l1, xi2, l2):
    """``(r, r - s)`` of eq. 6: ``r = |l1 xi1 + l2 xi2|``, ``s = l1 + l2``, for unit axes."""
    l12 = l1 * l2
    s = l1 + l2
    # |l1 xi1 + l2 xi2|^2 = (l1 - l2)^2 + l1 l2 |xi1 + xi2|^2 (unit axes): no cancellation
    r = dr.sqrt(dr.maximum(dr.square(l1 - l2) + l12 * dr.squared_norm(xi1 + xi2), 0.0))
    # r - s = (r^2 - s^2) / (r + s) = -l1 l2 |xi1 - xi2|^2 / (r + s)
    r_minus_s = -l12 * dr.squared_norm(xi1 - xi2) / dr.maximum(r + s, 1e-30)
    return r, r_minus_s


def sg_product_integral(xi1, l1, xi2, l2):
    """Exact integral over the sphere of ``G(w; xi1, l1) G(w; xi2, l2)``.

    Tokuyoshi 2015, eq. 6 (Tsai and Shih 2006): ``4 pi sinh(r) / (exp(l1 + l2) r)`` with
    ``r = |l1 xi1 + l2 xi2|``, evaluated as ``4 pi exp(r - s) (1 - exp(-2 r)) / (2 r)``
    (``s = l1 + l2``; see the module docstring): no overflow for large sharpness, the limit
    ``4 pi exp(-s)`` for ``r -> 0`` (equal, antipodal lobes) and ``4 pi`` for ``l1, l2 -> 0``.
    """
    r, r_minus_s = _product_terms(xi1, l1, xi2, l2)
    # Tokuyoshi 2015, eq. 6: 4 pi sinh(r) / (exp(l1 + l2) r)
    #   = 4 pi exp(r - s) (1 - exp(-2r)) / (2r)
    return _FOUR_PI * dr.exp(r_minus_s) * _one_minus_exp_neg_over(2.0 * r)


def _log_sg_product_integral(xi1, l1, xi2, l2):
    """``log`` of eq. 6 (same safe form), for the log-domain weight."""
    r, r_minus_s = _product_terms(xi1, l1, xi2, l2)
    # Tokuyoshi 2015, eq. 6 in the log domain
    return _LOG_FOUR_PI + r_minus_s + dr.log(_one_minus_exp_neg_over(2.0 * r))


def sg_product_integral_approx(xi1, l1, xi2, l2):
    """Iwasaki et al.'s approximation of the SG product integral.

    Tokuyoshi 2015, eq. 7: ``2 pi G(xi1; xi2, l1 l2 / (l1 + l2)) / (l1 + l2)``. Accurate for
    large sharpness (relative error ``exp(-2 (l1 + l2))`` for aligned axes); it tends to
    ``2 pi / (l1 + l2)`` instead of ``4 pi`` as both sharpnesses go to 0, so ``l1 + l2`` is
    floored at :data:`LAMBDA_MIN` to stay finite."""
    s = dr.maximum(l1 + l2, LAMBDA_MIN)
    mu = l1 * l2 / s
    # Tokuyoshi 2015, eq. 7: 2 pi G(xi1, xi2, l1 l2 / (l1 + l2)) / (l1 + l2)
    return (2.0 * math.pi) * dr.exp(mu * _cos_minus_one(xi1, xi2)) / s


# --------------------------------------------------------------------------------------------
# specular lobes as SGs (Tokuyoshi 2015, sec. 4.2: a_i(w) ~ G(w, xi_i, lambda_i), after Wang
# et al. 2009)


def _warped_lobe(n, wo, lambda_h):
    """Warp an NDF SG of sharpness ``lambda_h`` (about ``n``, in half-vector space) to the
    reflected direction: axis ``reflect(wo, n)``, sharpness ``lambda_h / (4 |n . wo|)``
    (Jacobian ``d w_h / d w_i = 1 / (4 |wo . h|)`` at ``h = n``; Wang et al. 2009, sec. 4)."""
    cos_o = dr.maximum(dr.abs(dr.dot(n, wo)), COS_MIN)
    lam = dr.minimum(lambda_h / (4.0 * cos_o), LAMBDA_MAX)
    return reflect(wo, n), lam


def ggx_lobe_to_sg(n, wo, alpha, ndf_sharpness=WANG_SG):
    """SG ``(axis, lambda)`` of a GGX specular lobe (Tokuyoshi 2015, sec. 4.2, via Wang et al.
    2009): axis ``reflect(wo, n)``, ``lambda = ndf_sharpness / (4 alpha^2 |n . wo|)``.

    The default ``ndf_sharpness = 2`` (:data:`WANG_SG`) gives ``lambda = 1 / (2 alpha^2
    |n . wo|)``, Wang et al.'s SG of the Cook-Torrance NDF (exact peak curvature for Beckmann).
    For GGX the peak curvature is matched by ``ndf_sharpness = GGX_SG_PEAK = 4`` (twice as
    sharp); a least-squares fit gives ~2.7. ``alpha`` is clamped to :data:`ALPHA_MIN`,
    ``|n . wo|`` to :data:`COS_MIN` and ``lambda`` to :data:`LAMBDA_MAX` (grazing, mirror-like
    lobes stay finite). The isotropic SG's ``lambda`` is the geometric mean of the warped
    lobe's in-plane (``lambda_h / 4``) and out-of-plane (``lambda_h / (4 cos^2)``) curvatures.
    """
    a = dr.maximum(alpha, ALPHA_MIN)
    return _warped_lobe(n, wo, ndf_sharpness / dr.square(a))


def lobe_to_sg(n, wo, alpha, beckmann=False, ndf_sharpness=None):
    """SG ``(axis, lambda)`` of a pixel's specular lobe with the NDF sharpness of its own
    distribution: ``lambda_h = GGX_SG_PEAK / alpha^2`` for GGX and ``WANG_SG / alpha^2`` for
    Beckmann, each matching its NDF's curvature at the peak (the criterion Wang et al.'s 2
    meets for Beckmann), warped as :func:`ggx_lobe_to_sg`. ``beckmann``: a per-lane mask (the
    Frame's ``distribution`` channel) or a bool; ``ndf_sharpness``: one value for every
    pixel instead (experiments)."""
    if ndf_sharpness is None:
        ndf_sharpness = by_distribution(beckmann, lambda: WANG_SG, lambda: GGX_SG_PEAK)
    return ggx_lobe_to_sg(n, wo, alpha, ndf_sharpness)


def beckmann_lobe_to_sg(n, wo, alpha):
    """SG of a Beckmann lobe: ``lambda_h = 2 / alpha^2`` (Wang et al. 2009), i.e.
    ``lambda = 1 / (2 alpha^2 |n . wo|)`` about ``reflect(wo, n)``. (The paper does not name
    Beckmann; this is the same warp as :func:`ggx_lobe_to_sg` with its default.)"""
    return ggx_lobe_to_sg(n, wo, alpha, WANG_SG)


def phong_lobe_to_sg(n, wo, s):
    """SG of a Phong lobe ``max(w . r, 0)^s`` about the mirror direction ``r = reflect(wo,
    n)``: ``lambda = s`` (``cos^s(t) ~ exp(-s t^2 / 2) ~ exp(s (cos t - 1))``)."""
    return reflect(wo, n), dr.minimum(dr.maximum(s, 0.0), LAMBDA_MAX)


# --------------------------------------------------------------------------------------------
# distribution-aware weights (Tokuyoshi 2015, sec. 3 and 4.2)


def smoothed_sharpness(lambda_, kappa):
    """``lambda_bar = lambda kappa / (lambda + kappa)``: the SG lobe convolved with the SG
    smoothing kernel ``b(w', w) ~ G(w', w, kappa)`` through eq. 7 (Tokuyoshi 2015, eq. 3 and
    sec. 4.2). ``kappa=None`` means no smoothing (``lambda_bar = lambda``)."""
    lam = dr.maximum(lambda_, LAMBDA_MIN)
    if kappa is None:
        return lam
    # Tokuyoshi 2015, sec. 4.2 (eq. 3 with eq. 7): lambda_bar = lambda kappa / (lambda + kappa)
    return dr.maximum(lam * kappa / (lam + kappa), LAMBDA_MIN)


def lobe_weight(xi_p, l_p, xi_q, l_q, beta=20.0, kappa=100.0, approx=False):
    """Specular-lobe-aware weight ``w(p, q) = q_pq^beta`` between two SG lobes.

    Tokuyoshi 2015, eqs. 3-5 with SG lobes (sec. 4.2): the lobes are smoothed by the SG kernel
    of sharpness ``kappa`` (``lambda_bar``, see :func:`smoothed_sharpness`), normalised so
    that ``int p^2 = 1`` (eq. 4) and ``q = int p_p p_q`` (eq. 5), hence ``w(p, p) = 1`` and
    ``0 <= w <= 1``.

    * ``approx=True``: the paper's closed form (sec. 4.2, eqs. 4-5 through eq. 7)
      ``w = (2 sqrt(lb_p lb_q) / (lb_p + lb_q))^beta G(xi_p; xi_q, beta lb_p lb_q / (lb_p +
      lb_q))``;
    * ``approx=False``: eqs. 4-5 through the exact eq. 6,
      ``q = I(p, q) / sqrt(I(p, p) I(q, q))`` with ``I`` the SG product integral (the "exact"
      curve of the paper's fig. 3).

    Both are evaluated in the log domain and clamped to ``[0, 1]``. ``kappa=None``: no
    smoothing. Defaults ``beta = 20``, ``kappa = 100`` are the paper's (sec. 5)."""
    a = smoothed_sharpness(l_p, kappa)
    b = smoothed_sharpness(l_q, kappa)
    if approx:
        s = a + b
        # Tokuyoshi 2015, sec. 4.2: q ~ 2 sqrt(a b) / (a + b) G(xi_p, xi_q, a b / (a + b));
        # log(2 sqrt(ab) / (a + b)) = log(4 a b / (a + b)^2) / 2 (exactly 0 for a = b)
        cm1 = _cos_minus_one(xi_p, xi_q)
        log_q = 0.5 * dr.log(4.0 * a * b / dr.square(s)) + (a * b / s) * cm1
    else:
        # Tokuyoshi 2015, eqs. 4-5 with eq. 6: q = I(p, q) / sqrt(I(p, p) I(q, q))
        log_q = _log_sg_product_integral(xi_p, a, xi_q, b) - 0.5 * (
            _log_sg_product_integral(xi_p, a, xi_p, a) + _log_sg_product_integral(xi_q, b, xi_q, b)
        )
    # Tokuyoshi 2015, sec. 3: w(i, j) = q_ij^beta
    return dr.exp(beta * dr.minimum(log_q, 0.0))


def lobe_tap_sharpness(lb, beta=20.0):
    """The per-pixel value the filters store for :func:`lobe_tap_terms`: ``s = (beta / 2)
    lambda_bar`` (``lb`` from :func:`smoothed_sharpness`)."""
    return (0.5 * beta) * lb


def lobe_tap_log_scale(beta=20.0):
    """``log(4^(beta / 2))``: the constant factor of :func:`lobe_tap_terms`' weight, which a
    filter adds to the constant part of its exponent (free for a Python ``beta``)."""
    return (0.5 * beta) * math.log(4.0)


def lobe_tap_terms(xi_p, s_p, xi_q, s_q, beta=20.0):
    """The closed-form lobe weight (``lobe_weight(..., approx=True)``) in the form filters
    evaluate per tap, from the per-pixel ``s = (beta / 2) lambda_bar``
    (:func:`lobe_tap_sharpness`, once per pixel rather than per tap):

        w = 4^(beta / 2) * y_pow * exp(-a_g)

    Tokuyoshi 2015, sec. 4.2: ``(2 sqrt(lb_p lb_q) / (lb_p + lb_q))^beta = (4 y)^(beta / 2)``
    with ``y = lb_p lb_q / (lb_p + lb_q)^2 = r / (s_p + s_q)`` (scale-free), so ``y_pow =
    y^(beta / 2)`` (by repeated squaring when ``beta / 2`` is an integer, as for the paper's
    20); and ``G(xi_p; xi_q, beta lb_p lb_q / (lb_p + lb_q)) = exp(-a_g)`` with ``a_g = r
    |xi_p - xi_q|^2``, ``r = s_p s_q / (s_p + s_q) = (beta / 2) lb_p lb_q / (lb_p + lb_q)``
    (``cos - 1 = -|xi_p - xi_q|^2 / 2``: no cancellation for sharp lobes a hair apart).

    The constant ``4^(beta / 2)`` (:func:`lobe_tap_log_scale` in the log domain) is left to
    the caller, which folds it into constants it already has, and ``a_g`` joins the exponent
    of the filter's other Gaussian weights: the lobe weight costs no ``exp`` or constant
    multiply of its own. Returns ``(y_pow, a_g)``."""
    inv_s = dr.rcp(s_p + s_q)
    r = s_p * s_q * inv_s
    y = r * inv_s  # <= 1/4 (AM-GM)
    if isinstance(beta, int | float):
        y_pow = pow_int(y, 0.5 * beta)
    else:  # an opaque Dr.Jit beta (parameter sweeps without recompiling)
        y_pow = dr.exp((0.5 * beta) * dr.log(dr.maximum(y, 1e-30)))
    d = xi_p - xi_q
    return y_pow, r * (d[0] * d[0] + d[1] * d[1] + d[2] * d[2])


def gaussian_weight(mu_p, var_p, mu_q, var_q, beta=20.0, kappa=100.0, dim=1):
    """Distribution-aware weight between two isotropic Gaussians ``a ~ g(|x - mu|, var)`` in
    ``R^dim`` (Tokuyoshi 2015, sec. 3, the mean / variance filter of fig. 2).

    The smoothing kernel is ``b(x', x) ~ g(|x' - x|, 1 / kappa)`` (variance ``v^2 = 1 /
    kappa``, the Euclidean counterpart of the SG kernel ``G(w', w, kappa) = g(|w' - w|, 1 /
    kappa)``), so ``tb^2 = var + 1 / kappa`` (eq. 3) and eqs. 4-5 give exactly

        w = (2 tb_p tb_q / (tb_p^2 + tb_q^2))^(beta dim / 2)
            g(|mu_p - mu_q|, (tb_p^2 + tb_q^2) / beta).

    The paper's printed formula (sec. 3) has the exponent ``beta``, i.e. ``dim = 2``; for 1-D
    Gaussians (``dim = 1``, the default) eqs. 2-5 give ``beta / 2`` (see tests/test_sg.py).
    ``kappa=None``: no smoothing. Works on Dr.Jit arrays and Python floats alike."""
    v2 = 0.0 if kappa is None else 1.0 / kappa
    # Tokuyoshi 2015, sec. 3 (eq. 3): tau_bar^2 = tau^2 + v^2
    tp = dr.maximum(var_p + v2, 1e-30)
    tq = dr.maximum(var_q + v2, 1e-30)
    ssum = tp + tq
    d2 = dr.square(mu_p - mu_q)
    # Tokuyoshi 2015, sec. 3 (eqs. 4-5, fig. 2 formula): log of the ratio term and the Gaussian
    log_ratio = 0.5 * dr.log(4.0 * tp * tq / dr.square(ssum))  # log(2 tb_p tb_q / (sum))
    log_w = (0.5 * beta * dim) * dr.minimum(log_ratio, 0.0) - beta * d2 / (2.0 * ssum)
    return dr.exp(log_w)
