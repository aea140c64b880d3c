"""Specular antialiasing by NDF filtering (Kaplanyan, Hill, Patney, Lefohn 2016, as evaluated by
Tokuyoshi), with the covariance-matrix GGX of :mod:`glossrt.brdf.covariance_ggx`.

A glossy surface whose normals vary faster than the pixel grid (a normal map, a curved mirror)
shows highlights that alias: one shading sample per pixel catches a narrow lobe or misses it,
and under motion the pixels flicker. NDF filtering widens the roughness by the spread of the
half vector over the pixel footprint, so the lobe one sample sees is the footprint's average.

Methods (``method=`` everywhere; :data:`METHODS` lists the evaluated ones):

* ``"none"``: the unfiltered roughness ``A = alpha^2 I``.
* ``"halfvector"`` (Tokuyoshi sec. 1.1, eqs. 1-2): the slope-space half vector's screen-space
  differences ``dh_u, dh_v`` (fine ``ddx/ddy`` emulated on 2x2 pixel quads), the footprint's
  slope covariance ``Sigma = sigma^2 [dh_u; dh_v]^T [dh_u; dh_v]`` with ``sigma^2 = 0.25``
  (a Gaussian pixel filter), and the filtered roughness matrix ``A = alpha^2 I + 2 Sigma``
  (the Beckmann convolution, applied to GGX). Per light.
* ``"halfvector-bbox"`` (sec. 1.2): the biased, over-filtering variant: the bounding box of the
  parallelogram spanned by ``dh_u, dh_v`` gives axis-aligned (anisotropic) roughness,
  ``A = alpha^2 I + 2 sigma^2 diag(w_x^2, w_y^2)``, ``w = |dh_u| + |dh_v|`` per axis.
* ``"avgnormal"`` (sec. 2): the deferred approximation, from the G-buffer normals alone: the
  3-tap quad average ``n_bar = normalize(n + n_x + n_y)`` (the pixel and its horizontal and
  vertical quad partners, sec. 2.1.1's shortened ``SumNeighborPixels``) replaces the half
  vector: the differences of the normals' slopes measured about ``n_bar`` give ``Sigma``.
* ``"avgnormal-max"``, ``"avgnormal-eig"`` (sec. 3): isotropic approximations of the
  average-normal filter: the larger side of the bounding box (Kaplanyan et al.'s proposal),
  or the largest eigenvalue of ``2 Sigma`` (Tokuyoshi's addition), added to ``alpha^2``.
* ``"projected"`` (beyond the paper: Tokuyoshi & Kaplanyan, "Improved Geometric Specular
  Antialiasing", I3D 2019, and "Stable Geometric Specular Antialiasing with Projected-Space NDF
  Filtering", JCGT 10(2), 2021, eq. 14): isotropic, from the screen-space differences of the
  world-space normal (the projected-space derivative, which does not blow up at grazing
  angles like slopes do): ``alpha'^2 = min(1, alpha^2 + min(2 sigma_p^2 (|dn_u|^2 +
  |dn_v|^2), kappa))`` with ``sigma_p^2 = 1 / (2 pi)`` and the clamp ``kappa = 0.18``. The
  factor 2 is eq. 2's: a Beckmann ``alpha^2`` is twice the variance of the slopes, here the
  variance ``sigma_p^2 (|dn_u|^2 + |dn_v|^2)`` of the projected normal over the footprint.

Every ``SOURCE-FORM`` pair also works (``halfvector-eig``, ``avgnormal-bbox``...): sources
``halfvector`` / ``avgnormal``, forms ``cov`` (default, anisotropic), ``bbox``, ``max``,
``eig``. All methods clamp the filtered matrix's eigenvalues to at most 1 (GGX ``alpha <= 1``);
``kappa`` (Kaplanyan et al.'s clamp of the added kernel's eigenvalues; default: none for the
paper's methods, 0.18 for ``projected``) is set for any method by a suffix of its name,
``METHOD:kappa=K`` (``avgnormal-eig:kappa=0.18``; ``projected:kappa=none`` removes
projected's clamp), which the CLI's ``--specaa METHOD`` accepts too, or by ``kappa=``.

Conventions:

* Quads: pixel ``(x, y)``'s horizontal partner is ``(x ^ 1, y)``, its vertical one ``(x, y ^ 1)``
  (a GPU's 2x2 quads; fine derivatives are the difference across the pair, the same for both
  pixels of a pair). A partner outside the image, on the background or on another mesh
  (``mesh_id``) counts as the pixel itself (zero difference): a G-buffer has no helper lanes.
* Slopes: each pixel shades in its own frame ``(t, b, n)`` (``mi.Frame3f(n)``); a partner's
  half vector (or normal) is carried into it by the smallest rotation taking the partner's
  normal to the pixel's (:func:`transport`), so differences do not depend on how tangent
  frames are chosen and the normal map's variation is seen through it. ``A`` is in that frame.
* Lights: point and directional lights (:mod:`glossrt.lights.analytic`) shade with the
  pixel's distribution (the Frame's ``distribution`` channel): the covariance GGX (Tokuyoshi,
  appendix A.1) or the Beckmann NDF with the same roughness matrix, for which Kaplanyan et
  al.'s ``A = alpha^2 I + 2 Sigma`` is exact in slope space
  (:func:`glossrt.brdf.covariance_ggx.brdf_separable_dr`), with Mitsuba's separable Smith
  term and the pixel's Fresnel term, like :mod:`glossrt.lights.shading`; polygon lights with LTC
  (:mod:`glossrt.lights.ltc`), whose table is isotropic: anisotropic methods pass
  ``alpha = sqrt(lambda_max(A))`` (their ``-eig`` reduction), and the half vector of a polygon
  light points to its centroid. No shadows (direct light only, as LTC). ``masking=
  "material"`` (beyond the paper, :data:`MASKING`) keeps the material's own alpha in the
  Smith term of point and directional lights.

The reference (:func:`reference`) averages the unfiltered shading over ``spp`` stratified
sub-pixel positions: what filtering tries to approximate with one sample. Its pixel filter
(:data:`PIXEL_FILTERS`) is a box (positions in the pixel) or the Gaussian of variance
``sigma^2 = 0.25`` px^2 per axis that Tokuyoshi's eq. 1 assumes (positions spread over the
neighbouring pixels, :func:`subpixel_offsets`).

References:
    A. Kaplanyan, S. Hill, A. Patney, A. Lefohn, "Filtering Distributions of Normals for
    Shading Antialiasing", HPG 2016.
    Y. Tokuyoshi, evaluation of Kaplanyan et al. 2016 (Japanese), secs. 1-3, appendix A.1.
    Y. Tokuyoshi, A. Kaplanyan, "Stable Geometric Specular Antialiasing with Projected-Space
    NDF Filtering", JCGT 10(2), 2021.
"""

from __future__ import annotations

from .filters import (
    KAPPA_PROJECTED,
    MASKING,
    METHODS,
    SIGMA2,
    SIGMA2_PROJECTED,
    Method,
    clamp_eigen,
    filtered_roughness,
    isotropic_alpha,
    kernel,
    material_matrix,
    parse_method,
    quad_partners,
    roughness_image,
    roughness_matrix,
    transport,
)
from .reference import JITTER_LIMIT, PIXEL_FILTERS, reference, subpixel_offsets
from .shade import shade, shade_tensor

__all__ = [
    "JITTER_LIMIT",
    "KAPPA_PROJECTED",
    "MASKING",
    "METHODS",
    "PIXEL_FILTERS",
    "SIGMA2",
    "SIGMA2_PROJECTED",
    "Method",
    "clamp_eigen",
    "filtered_roughness",
    "isotropic_alpha",
    "kernel",
    "material_matrix",
    "parse_method",
    "quad_partners",
    "reference",
    "roughness_image",
    "roughness_matrix",
    "shade",
    "shade_tensor",
    "subpixel_offsets",
    "transport",
]
