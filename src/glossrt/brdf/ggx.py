"""GGX specular lobe and its pre-integrated directional albedo (the split-sum table).

The microfacet model follows Mitsuba 3's ``MicrofacetDistribution`` (GGX type, used by the
``roughconductor`` and ``roughplastic`` plugins, ``include/mitsuba/render/microfacet.h``):

* normal distribution: GGX / Trowbridge-Reitz, Walter et al. 2007, eq. 33;
* shadowing-masking: Smith's *separable* form ``G(wo, wi, h) = G1(wo, h) G1(wi, h)``
  (Walter et al. 2007, eq. 23), with the GGX ``G1`` of eq. 34. Mitsuba uses this uncorrelated
  product (``MicrofacetDistribution::G``), not the height-correlated form, and so does glossrt.

The specular BRDF is ``f(wo, wi) = F(wo.h) D(h) G(wo, wi, h) / (4 cos_o cos_i)`` (Walter et al.
2007, eq. 20) with Schlick's Fresnel approximation ``F = F0 + (1 - F0)(1 - wo.h)^5`` (Schlick
1994). Its directional albedo

    E(mu, alpha, F0) = integral over the hemisphere of f(wo, wi) cos(theta_i) dwi

is linear in ``F0``: ``E = F0 A(mu, alpha) + B(mu, alpha)`` with ``A`` the integral weighted by
``1 - (1 - wo.h)^5`` and ``B`` the integral weighted by ``(1 - wo.h)^5`` (the "split sum"
scale / bias of Karis 2013, "Real Shading in Unreal Engine 4", SIGGRAPH course notes). The
renderer writes ``E`` per pixel (``albedo_specular``) to demodulate specular radiance.

Table grid (see :func:`generate_albedo_table`): node ``(j, i)`` sits at

* ``mu_i = s_i^2`` with ``s_i = i / (n_mu - 1)``: uniform in ``s = sqrt(mu)``, ``mu`` the
  cosine of the view angle (column 0 is integrated at ``MU_MIN = 1e-6``: ``mu = 0`` is the
  grazing limit);
* ``alpha_j = r_j^2`` with ``r_j = j / (n_alpha - 1)``: uniform in the *perceptual roughness*
  ``r = sqrt(alpha)`` in [0, 1], which resolves small ``alpha`` (a quarter of the rows lie below
  ``alpha = 1/16``). Row 0 holds the exact ``alpha -> 0`` limit ``A = 1 - (1 - mu)^5``,
  ``B = (1 - mu)^5`` (a mirror: ``h = n``, ``G = 1``). Mitsuba clamps alpha to
  ``ALPHA_MIN = 1e-4``, where the integral matches that limit to ~1e-5 except within
  ``mu ~ alpha`` of grazing.

Both axes use square roots because for small roughness the albedo changes where
``mu ~ alpha`` (shadowing at grazing angles): in ``(s, r)`` that transition is a straight line
through the origin that bilinear interpolation follows far better than in ``(mu, r)``.
Measured max. interpolation error of ``A`` and ``B`` with the default 65 x 65 nodes: 6e-4 for
``mu >= 0.1``, 1.2e-3 for ``mu >= 0.05``, 1.4e-3 for ``alpha >= 0.01``, 5e-3 for
``mu >= 0.005``, 1.3e-2 for ``mu >= 0.001``. Only near-mirrors seen within 0.06 degrees of
grazing (``mu < 0.001``, ``alpha < 0.01``), where ``E`` jumps between the mirror limit and the
rough grazing limit, reach 0.12 (tests/test_ggx.py checks these bounds).

Lookups interpolate bilinearly in ``(s, r) = (sqrt(mu), sqrt(alpha))`` and clamp to the grid
(``alpha > 1`` reads the ``alpha = 1`` row).

References:
    B. Walter, S. Marschner, H. Li, K. Torrance, "Microfacet Models for Refraction through Rough
    Surfaces", EGSR 2007.
    C. Schlick, "An Inexpensive BRDF Model for Physically-based Rendering", CGF 13(3), 1994.
    B. Karis, "Real Shading in Unreal Engine 4", SIGGRAPH 2013 course notes.
    E. Heitz, "Sampling the GGX Distribution of Visible Normals", JCGT 7(4), 2018.
    J. Hammersley, D. Handscomb, "Monte Carlo Methods", 1964 (Hammersley point set).

Regenerate the shipped tables with ``python -m glossrt.brdf.ggx [--distribution beckmann]``
(``data/ggx_albedo.npz``, ``data/beckmann_albedo.npz``: Beckmann's ``D`` and ``G1`` of
:mod:`glossrt.brdf.microfacet`, the same grid and Fresnel split).
"""

from __future__ import annotations

import argparse
import functools
import math
import time
from collections.abc import Callable, Sequence
from importlib import resources
from pathlib import Path
from typing import Any, TypeVar

import drjit as dr
import numpy as np

from ..backend import VariantStruct, mi
from ..errors import GlossrtError

__all__ = [
    "ALPHA_MIN",
    "MU_MIN",
    "DEFAULT_N_MU",
    "DEFAULT_N_ALPHA",
    "DEFAULT_SAMPLES",
    "D_ggx",
    "G1_smith",
    "fresnel_schlick",
    "sample_vndf",
    "vndf_quadrature",
    "albedo_ab",
    "generate_albedo_table",
    "grid_nodes",
    "default_table_path",
    "save_table",
    "SpecularAlbedoTable",
    "main",
]

#: Smallest roughness: Mitsuba's ``MicrofacetDistribution::configure`` clamps alpha to 1e-4.
ALPHA_MIN = 1e-4
#: Cosine at which the grazing column ``mu = 0`` is integrated.
MU_MIN = 1e-6
#: Default table size: 64 intervals per axis (65 nodes), so halved grids (33, 17, 9, 5, 3
#: nodes) share nodes with it.
DEFAULT_N_MU = 65
DEFAULT_N_ALPHA = 65
#: Hammersley points per cell for the shipped table (power of two).
DEFAULT_SAMPLES = 1 << 16

F = TypeVar("F")  # a Dr.Jit floating point array type (mi.Float, Float64, ...)


# ----------------------------------------------------------------------------------------------
# Microfacet model (generic over Dr.Jit float types; usable inside symbolic loops / vcalls)
# ----------------------------------------------------------------------------------------------


def D_ggx(cos_theta_h: F, alpha: F | float) -> F:
    """GGX / Trowbridge-Reitz normal distribution ``D(h)`` (Walter et al. 2007, eq. 33).

    ``D = alpha^2 / (pi (cos^2 (alpha^2 - 1) + 1)^2)`` for ``cos_theta_h > 0``, else 0; the same
    function as Mitsuba's ``MicrofacetDistribution::eval`` (isotropic GGX), written in terms of
    ``cos_theta_h = n.h``. It is normalised so that ``integral D(h) cos(theta_h) dh = 1``.

    Args:
        cos_theta_h: cosine between the half vector and the macro normal.
        alpha: GGX roughness (Mitsuba's ``alpha``; clamp to :data:`ALPHA_MIN` as Mitsuba does).
    """
    a2 = alpha * alpha
    c2 = cos_theta_h * cos_theta_h
    # (1 - c2) + c2 a2 == c2 (a2 - 1) + 1, ordered to limit cancellation near c = 1.
    d = (1.0 - c2) + c2 * a2
    return dr.select(cos_theta_h > 0.0, a2 / (dr.pi * d * d), 0.0)


def G1_smith(cos_theta: F, alpha: F | float) -> F:
    """Smith's GGX masking term ``G1(v)`` for a direction with ``cos_theta = n.v``.

    Walter et al. 2007, eq. 34: ``G1 = 2 / (1 + sqrt(1 + alpha^2 tan^2 theta))``, as Mitsuba's
    ``MicrofacetDistribution::smith_g1`` (GGX), rewritten as
    ``2 c / (c + sqrt(c^2 + alpha^2 (1 - c^2)))`` so that it is finite at ``c = 0``. It returns 0
    for ``cos_theta <= 0``. Mitsuba's ``G1(v, h)`` additionally returns 0 when ``v.h`` and
    ``n.v`` have opposite signs (Walter's ``chi+`` term); callers check that themselves (for a
    reflection ``wi.h = wo.h``, so ``wo.h > 0`` suffices).
    """
    c = dr.maximum(cos_theta, 0.0)
    a2 = alpha * alpha
    s = dr.sqrt(dr.maximum(c * c + a2 * (1.0 - c * c), 0.0))
    denom = c + s
    return dr.select((c > 0.0) & (denom > 0.0), 2.0 * c / denom, 0.0)


def fresnel_schlick(cos_theta: F, f0: Any) -> Any:
    """Schlick's approximation ``F0 + (1 - F0)(1 - cos)^5`` (Schlick 1994).

    ``cos_theta`` (= ``wo.h``) is clamped to [0, 1]; ``f0`` may be a float, a Dr.Jit float or
    an RGB colour (``mi.Color3f``), and the result has the type of ``f0 * cos_theta``.
    """
    c = dr.clip(cos_theta, 0.0, 1.0)
    m = 1.0 - c
    m2 = m * m
    w = m2 * m2 * m
    return f0 + (1.0 - f0) * w


def sample_vndf(wo_x: F, wo_y: F, wo_z: F, alpha: F | float, u1: F, u2: F) -> tuple[F, F, F]:
    """Sample a half vector from the GGX distribution of visible normals ``D_wo(h)``.

    ``D_wo(h) = G1(wo) max(0, wo.h) D(h) / cos_o`` (Heitz 2018), sampled with the
    stretch / project-on-hemisphere / unstretch construction of Heitz 2018,
    which draws exactly the same distribution as Mitsuba's ``sample_visible`` mode. ``wo`` is a
    unit vector in the local frame (``z`` = normal, ``wo_z > 0``); ``u1, u2`` are in [0, 1).
    Returns the components of the unit half vector ``h``.
    """
    # Stretch the view vector to the alpha = 1 configuration.
    vx, vy, vz = alpha * wo_x, alpha * wo_y, wo_z
    inv = dr.rsqrt(vx * vx + vy * vy + vz * vz)
    vx, vy, vz = vx * inv, vy * inv, vz * inv
    # Orthonormal basis (t1, t2, v) around the stretched view vector.
    lensq = vx * vx + vy * vy
    inv_len = dr.rsqrt(dr.maximum(lensq, 1e-30))
    has_t = lensq > 0.0
    t1x = dr.select(has_t, -vy * inv_len, 1.0)
    t1y = dr.select(has_t, vx * inv_len, 0.0)
    t2x, t2y, t2z = -vz * t1y, vz * t1x, vx * t1y - vy * t1x  # v x t1 (t1 has no z)
    # Uniform point on the unit disk, warped onto the visible projected half disk.
    r = dr.sqrt(u1)
    phi = 2.0 * dr.pi * u2
    sp, cp = dr.sincos(phi)
    p1 = r * cp
    p2 = r * sp
    s = 0.5 * (1.0 + vz)
    p2 = (1.0 - s) * dr.sqrt(dr.maximum(1.0 - p1 * p1, 0.0)) + s * p2
    pz = dr.sqrt(dr.maximum(1.0 - p1 * p1 - p2 * p2, 0.0))
    nx = p1 * t1x + p2 * t2x + pz * vx
    ny = p1 * t1y + p2 * t2y + pz * vy
    nz = p2 * t2z + pz * vz
    # Unstretch back to the alpha configuration.
    hx, hy, hz = alpha * nx, alpha * ny, dr.maximum(nz, 0.0)
    inv = dr.rsqrt(dr.maximum(hx * hx + hy * hy + hz * hz, 1e-30))
    return hx * inv, hy * inv, hz * inv


# ----------------------------------------------------------------------------------------------
# Deterministic integration of A and B
# ----------------------------------------------------------------------------------------------


def _float64_t() -> type:
    return dr.float64_array_t(mi.Float)


def vndf_quadrature(
    mu: Any,
    alpha: Any,
    weights: Callable[[Any], Sequence[Any]],
    samples: int = DEFAULT_SAMPLES,
    distribution: str = "ggx",
) -> list[np.ndarray]:
    """Integrate ``weights(wo.h) * f_spec cos_i / F`` over the hemisphere at arbitrary points.

    For each point ``(mu, alpha)`` this returns the deterministic estimate of
    ``integral w(wo.h) D(h) G(wo, wi) / (4 cos_o) dwi`` for every weight function ``w`` in
    ``weights(c)`` (``c = wo.h``, a float64 Dr.Jit array). Each point uses the same
    ``samples``-point Hammersley set (``u1 = (k + 1/2) / N``, ``u2 = radical_inverse_2(k) +
    1/(2N)``) mapped to half vectors with :func:`sample_vndf`. With visible-normal sampling,
    ``wi = reflect(wo, h)`` has density ``D_wo(h) / (4 wo.h)`` and the estimator reduces to
    ``w(wo.h) G1(wi)`` (see Heitz 2018), which is bounded, so the quadrature converges
    quickly (error ~1e-5 at ``N = 2^16``). Computed in double precision, vectorised over all
    points at once.

    Args:
        mu: cosines of the view angle (array-like; clamped to [``MU_MIN``, 1]).
        alpha: GGX roughness per point (array-like, same length; clamped to
            [``ALPHA_MIN``, 1]).
        weights: maps ``c = wo.h`` to a sequence of weights (Dr.Jit float64 arrays).
        samples: Hammersley points per point; a power of two.
        distribution: ``"ggx"`` (the above) or ``"beckmann"``: Beckmann's ``D`` and ``G1``
            (:mod:`glossrt.brdf.microfacet`), half vectors drawn from ``D(h) cos(theta_h)``,
            estimator ``w(wo.h) G1(wo) G1(wi) wo.h / (cos_o cos_h)`` (Walter et al. 2007,
            eq. 38).

    Returns:
        One float64 numpy array per weight, one value per point.
    """
    if samples <= 0 or samples & (samples - 1):
        raise GlossrtError(f"samples must be a positive power of two, got {samples}")
    mu_np = np.clip(np.asarray(mu, dtype=np.float64).ravel(), MU_MIN, 1.0)
    al_np = np.clip(np.asarray(alpha, dtype=np.float64).ravel(), ALPHA_MIN, 1.0)
    if mu_np.shape != al_np.shape:
        raise GlossrtError("mu and alpha must have the same number of elements")
    n_pts = mu_np.size
    from . import microfacet as mf

    beck = mf.code(distribution) == mf.BECKMANN
    f64 = _float64_t()
    u32 = mi.UInt32
    log2n = samples.bit_length() - 1

    # Points per launch: keep each kernel around 2^21 lanes (~100 MB of float64 temporaries).
    chunk = max(1, (1 << 21) // samples)
    out: list[np.ndarray] = []
    for start in range(0, n_pts, chunk):
        stop = min(start + chunk, n_pts)
        mu_c = f64(mu_np[start:stop])
        al_c = f64(al_np[start:stop])
        idx = dr.arange(u32, (stop - start) * samples)
        cell = idx >> log2n
        k = idx & (samples - 1)
        m = dr.gather(f64, mu_c, cell)
        a = dr.gather(f64, al_c, cell)
        u1 = (f64(k) + 0.5) / samples
        u2 = f64(dr.brev(k)) * (1.0 / 4294967296.0) + 0.5 / samples

        wx = dr.sqrt(dr.maximum(1.0 - m * m, 0.0))
        wz = m
        zero = dr.zeros(f64, dr.width(m))
        hx, hy, hz = mf.sample_h(wx, zero, wz, a, u1, u2, beck)
        c = wx * hx + wz * hz  # wo.h (= wi.h)
        wi_z = 2.0 * c * hz - wz
        # G1(wi), with Mitsuba's orientation check (wi.h and n.wi of the same sign).
        g1 = dr.select(c > 0.0, mf.G1(wi_z, a, beck), 0.0)
        if beck:  # Walter et al. 2007, eq. 38 with the reflection Jacobian
            g1 = g1 * mf.G1(wz, a, True) * c / (wz * dr.maximum(hz, 1e-30))
        sums = [dr.block_sum(f64(w) * g1, samples) / samples for w in weights(c)]
        dr.eval(sums)
        if not out:
            out = [np.empty(n_pts) for _ in sums]
        for o, v in zip(out, sums, strict=True):
            o[start:stop] = v.numpy()
    return out


def albedo_ab(mu: Any, alpha: Any, samples: int = DEFAULT_SAMPLES,
              distribution: str = "ggx") -> tuple[np.ndarray, np.ndarray]:
    """Integrate ``A(mu, alpha)`` and ``B(mu, alpha)`` at arbitrary points.

    ``A`` weights the GGX lobe with ``1 - (1 - wo.h)^5`` and ``B`` with ``(1 - wo.h)^5``, so that
    ``E = F0 A + B`` with Schlick's Fresnel; see :func:`vndf_quadrature` for the deterministic
    integration and the arguments. Returns ``(A, B)`` as float64 numpy arrays.
    """

    def ab(c: Any) -> tuple[Any, Any]:
        w5 = fresnel_schlick(c, 0.0)  # (1 - c)^5
        return 1.0 - w5, w5

    a, b = vndf_quadrature(mu, alpha, ab, samples, distribution)
    return a, b


def grid_nodes(n_mu: int, n_alpha: int) -> tuple[np.ndarray, np.ndarray]:
    """Nominal node positions ``(mu, alpha)`` of an ``n_alpha x n_mu`` table.

    ``mu_i = (i / (n_mu - 1))^2`` and ``alpha_j = (j / (n_alpha - 1))^2``. (The column ``mu = 0``
    is integrated at :data:`MU_MIN`; the row ``alpha = 0`` is the analytic mirror limit.)
    """
    if n_mu < 2 or n_alpha < 2:
        raise GlossrtError("the table needs at least 2 nodes per axis")
    s = np.linspace(0.0, 1.0, n_mu)
    r = np.linspace(0.0, 1.0, n_alpha)
    return s * s, r * r


def generate_albedo_table(
    n_mu: int = DEFAULT_N_MU, n_alpha: int = DEFAULT_N_ALPHA, samples: int = DEFAULT_SAMPLES,
    distribution: str = "ggx",
) -> np.ndarray:
    """Compute the split-sum table ``(A, B)`` on the grid of :func:`grid_nodes`.

    Returns a float64 array of shape ``(n_alpha, n_mu, 2)`` with ``[..., 0] = A`` (scale of
    ``F0``) and ``[..., 1] = B`` (bias): ``E = F0 A + B``. All cells are integrated with the
    same deterministic Hammersley set (see :func:`albedo_ab`), so any cell can be reproduced
    exactly on a coarser grid that shares its node. Row 0 (``alpha = 0``) is set to the
    analytic mirror limit ``A = 1 - (1 - mu)^5``, ``B = (1 - mu)^5``.
    """
    mu, alpha = grid_nodes(n_mu, n_alpha)
    mm, aa = np.meshgrid(mu, alpha[1:])  # (n_alpha - 1, n_mu)
    a, b = albedo_ab(mm.ravel(), aa.ravel(), samples, distribution)
    table = np.empty((n_alpha, n_mu, 2))
    table[1:] = np.stack([a, b], axis=-1).reshape(n_alpha - 1, n_mu, 2)
    w5 = (1.0 - mu) ** 5
    table[0, :, 0] = 1.0 - w5
    table[0, :, 1] = w5
    return table


def default_table_path(distribution: str = "ggx") -> Path:
    """Path of the shipped table of ``distribution``: ``glossrt/data/ggx_albedo.npz`` or
    ``beckmann_albedo.npz``."""
    from . import microfacet as mf

    name = mf.NAMES[mf.code(distribution)]
    return Path(str(resources.files("glossrt") / "data" / f"{name}_albedo.npz"))


def save_table(table: np.ndarray, path: Path | str, samples: int,
               distribution: str = "ggx") -> None:
    """Write a table produced by :func:`generate_albedo_table` with its grid description."""
    n_alpha, n_mu, _ = table.shape
    mu, alpha = grid_nodes(n_mu, n_alpha)
    np.savez_compressed(
        path,
        table=table.astype(np.float32),
        mu=mu.astype(np.float32),
        alpha=alpha.astype(np.float32),
        samples=np.int64(samples),
        mu_min=np.float64(MU_MIN),
        alpha_min=np.float64(ALPHA_MIN),
        distribution=np.array(distribution),
        layout=np.array(
            "table[j, i, c]: alpha_j = (j/(n_alpha-1))^2, mu_i = (i/(n_mu-1))^2, c=0: A, c=1: B; "
            f"E = F0*A + B for {distribution} D + separable Smith G + Schlick Fresnel"
        ),
    )


# ----------------------------------------------------------------------------------------------
# Runtime table
# ----------------------------------------------------------------------------------------------


class SpecularAlbedoTable:
    """The ``(A, B)`` tables on the device, one per distribution, with a Dr.Jit bilinear
    lookup.

    ``data`` is a flat ``mi.Float`` of length ``n_d * n_alpha * n_mu * 2`` (row-major
    ``[distribution][alpha][mu][A, B]``; the shipped pair is GGX, then Beckmann). The class
    is a Dr.Jit PyTree (``DRJIT_STRUCT``), so instances can be passed to
    ``dr.freeze``-decorated functions, loops and vcalls: ``data`` is traversed as a variable
    and the integer sizes are hashed (a table of another size re-traces).
    ``DRJIT_STRUCT`` names the ``mi.Float`` of the active variant
    (:class:`glossrt.backend.VariantStruct`).
    """

    DRJIT_STRUCT = VariantStruct(lambda: {"data": mi.Float, "n_mu": int, "n_alpha": int,
                                          "n_d": int})

    def __init__(self, data: mi.Float | None = None, n_mu: int = 0, n_alpha: int = 0,
                 n_d: int = 1) -> None:
        self.data = data if data is not None else mi.Float()
        self.n_mu = int(n_mu)
        self.n_alpha = int(n_alpha)
        self.n_d = int(n_d)

    @classmethod
    def from_array(cls, table: np.ndarray) -> SpecularAlbedoTable:
        """Build from an ``(n_alpha, n_mu, 2)`` array laid out as :func:`generate_albedo_table`
        (or ``(n_d, n_alpha, n_mu, 2)``: GGX, then Beckmann)."""
        table = np.asarray(table, dtype=np.float32)
        if table.ndim == 3:
            table = table[None]
        if table.ndim != 4 or table.shape[3] != 2 or min(table.shape[1:3]) < 2:
            raise GlossrtError(f"expected an (n_alpha, n_mu, 2) table, got {table.shape}")
        n_d, n_alpha, n_mu, _ = table.shape
        data = mi.Float(np.ascontiguousarray(table).ravel())
        dr.make_opaque(data)
        return cls(data, n_mu, n_alpha, n_d)

    @classmethod
    def load(cls, path: Path | str | None = None) -> SpecularAlbedoTable:
        """The shipped tables of GGX and Beckmann (or the one table at ``path``); cached per
        path and Mitsuba variant."""
        p = str(Path(path).resolve()) if path is not None else ""
        return _load_cached(p, mi.variant())

    def numpy(self) -> np.ndarray:
        """The tables as an ``(n_d, n_alpha, n_mu, 2)`` float32 array."""
        return np.asarray(self.data.numpy()).reshape(self.n_d, self.n_alpha, self.n_mu, 2)

    def lookup_ab(self, cos_o: mi.Float, alpha: mi.Float,
                  beckmann: mi.Bool | None = None) -> mi.Vector2f:
        """Bilinearly interpolated ``(A, B)`` at ``mu = cos_o`` and roughness ``alpha``, from
        the Beckmann table where ``beckmann`` (per lane; a table of one distribution ignores
        it) and the GGX one elsewhere.

        Interpolation is bilinear in ``(sqrt(mu), sqrt(alpha))``, the table's grid. Inputs are
        clamped to the grid: ``mu`` to [0, 1] (NaN and negative values read the grazing column)
        and ``alpha`` to [0, 1]. Only Dr.Jit operations (``dr.gather``), so it
        can run inside symbolic loops, vcalls and frozen functions.
        """
        cos_o = mi.Float(cos_o)
        alpha = mi.Float(alpha)
        n_mu, n_alpha = self.n_mu, self.n_alpha
        s = dr.sqrt(dr.minimum(dr.select(cos_o > 0.0, cos_o, 0.0), 1.0))
        r = dr.sqrt(dr.minimum(dr.select(alpha > 0.0, alpha, 0.0), 1.0))
        x = s * (n_mu - 1)
        y = r * (n_alpha - 1)
        i0 = dr.minimum(mi.UInt32(x), n_mu - 2)
        j0 = dr.minimum(mi.UInt32(y), n_alpha - 2)
        tx = x - mi.Float(i0)
        ty = y - mi.Float(j0)
        base = j0 * n_mu + i0
        if beckmann is not None and self.n_d > 1:
            base = base + dr.select(beckmann, n_alpha * n_mu, 0)
        v00 = dr.gather(mi.Vector2f, self.data, base)
        v10 = dr.gather(mi.Vector2f, self.data, base + 1)
        v01 = dr.gather(mi.Vector2f, self.data, base + n_mu)
        v11 = dr.gather(mi.Vector2f, self.data, base + n_mu + 1)
        return dr.lerp(dr.lerp(v00, v10, tx), dr.lerp(v01, v11, tx), ty)

    def lookup(self, cos_o: mi.Float, alpha: mi.Float, f0: mi.Color3f,
               beckmann: mi.Bool | None = None) -> mi.Color3f:
        """Directional albedo ``E = F0 A + B`` of the lobe for RGB ``f0``.

        See :meth:`lookup_ab` for the interpolation, clamping and ``beckmann``.
        """
        ab = self.lookup_ab(cos_o, alpha, beckmann)
        return mi.Color3f(f0) * ab.x + ab.y

    def __repr__(self) -> str:
        return (f"SpecularAlbedoTable(n_d={self.n_d}, n_alpha={self.n_alpha}, "
                f"n_mu={self.n_mu})")


@functools.lru_cache(maxsize=8)
def _load_cached(path: str, variant: str) -> SpecularAlbedoTable:
    paths = [path] if path else [str(default_table_path(d)) for d in ("ggx", "beckmann")]
    tables = []
    for p in paths:
        with np.load(p, allow_pickle=False) as f:
            tables.append(f["table"])
    return SpecularAlbedoTable.from_array(np.stack(tables))


# ----------------------------------------------------------------------------------------------
# Command line: regenerate the shipped table
# ----------------------------------------------------------------------------------------------


def main(argv: list[str] | None = None) -> int:
    """Regenerate ``glossrt/data/<distribution>_albedo.npz`` (``python -m glossrt.brdf.ggx``)."""
    ap = argparse.ArgumentParser(prog="python -m glossrt.brdf.ggx", description=main.__doc__)
    ap.add_argument("--out", type=Path, default=None, help="output .npz (default: shipped file)")
    ap.add_argument("--n-mu", type=int, default=DEFAULT_N_MU)
    ap.add_argument("--n-alpha", type=int, default=DEFAULT_N_ALPHA)
    ap.add_argument("--samples", type=int, default=DEFAULT_SAMPLES, help="power of two")
    ap.add_argument("--distribution", choices=("ggx", "beckmann"), default="ggx")
    args = ap.parse_args(argv)
    out = args.out or default_table_path(args.distribution)
    t0 = time.perf_counter()
    table = generate_albedo_table(args.n_mu, args.n_alpha, args.samples, args.distribution)
    dt = time.perf_counter() - t0
    out.parent.mkdir(parents=True, exist_ok=True)
    save_table(table, out, args.samples, args.distribution)
    mu, _ = grid_nodes(args.n_mu, args.n_alpha)
    limit = np.abs(table[0, :, 1] - (1.0 - mu) ** 5).max()
    print(
        f"wrote {out}: {args.n_alpha} x {args.n_mu} cells, {args.samples} samples/cell, "
        f"{dt:.2f} s; E(F0=1) in [{table.sum(-1).min():.4f}, {table.sum(-1).max():.4f}], "
        f"alpha->0 row deviates {limit:.2e} from (1-mu)^5"
    )
    if not math.isfinite(float(table.sum())):
        raise SystemExit("non-finite values in the table")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
