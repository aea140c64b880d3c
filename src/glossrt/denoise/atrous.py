"""Edge-avoiding a-trous wavelet filtering: SVGF's variance-guided levels (Schied 2017,
sec. 4.3-4.4) and the original edge-avoiding a-trous of Dammertz et al. 2010 (``atrous``).

Reads: ``color`` and the radiance components, ``albedo_diffuse``, ``albedo_specular``,
``normal``, ``depth``, ``mesh_id`` (and ``position`` for Dammertz's weights).
Produces: the filtered RGB image (H, W, 3).
"""

from __future__ import annotations

import math

import drjit as dr

from ..backend import mi
from ..jit import exp_weight, pow_int
from .common import H5, GBuffer, Grid, Img, Packed, luminance

__all__ = ["atrous_taps", "dammertz_level", "dammertz_level_multi", "gaussian3x3", "pow_int",
           "svgf_level", "svgf_level_multi"]

EPS_Z = 1e-3  # relative: |d(1/z)| below 1e-3 of 1/z counts as "on the plane"
EPS_L = 1e-10


def gaussian3x3(grid: Grid, v: mi.Float) -> mi.Float:
    """3x3 Gaussian prefilter of the variance, used only inside w_l (Schied 2017, eq. 5)."""
    k = (0.25, 0.5, 0.25)
    acc = dr.zeros(mi.Float, dr.width(v))
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            acc += k[dx + 1] * k[dy + 1] * dr.gather(
                mi.Float, v, grid.index(grid.x + dx, grid.y + dy))
    return acc


def atrous_taps(grid: Grid, step: int, active: mi.Bool):
    """The 24 off-centre taps of a 5x5 a-trous level with hole size ``step``: yields
    (dx, dy, clamped neighbour index, whether the neighbour is inside and ``active``)."""
    for dy in range(-2, 3):
        for dx in range(-2, 3):
            if dx == 0 and dy == 0:
                continue
            qx, qy = grid.x + dx * step, grid.y + dy * step
            yield dx, dy, grid.index(qx, qy), grid.inside(qx, qy) & active


def svgf_level(grid: Grid, color: Img, var: mi.Float, gb: GBuffer, step: int,
               sigma_z: float = 1.0, sigma_n: float = 128.0, sigma_l: float = 4.0,
               lum_weights: bool = True) -> tuple[Img, mi.Float]:
    """One level of the variance-guided edge-avoiding a-trous transform with hole size
    ``step`` (1, 2, 4, ...) for one signal. Returns the filtered colour and its variance."""
    (c,), (v,) = svgf_level_multi(grid, [color], [var], gb, step, sigma_z, sigma_n, sigma_l,
                                  lum_weights)
    return c, v


def svgf_level_multi(grid: Grid, colors: list, variances: list, gb: GBuffer, step: int,
                     sigma_z: float = 1.0, sigma_n: float = 128.0, sigma_l: float = 4.0,
                     lum_weights: bool = True, lobes=None) -> tuple[list, list]:
    """:func:`svgf_level` for several signals at once: the geometric weights w_z * w_n are
    computed once per tap and shared; the geometry and every signal's colour + variance are
    interleaved per pixel and read with one packet gather per 8 floats (:class:`Packed`).

    ``lobes = (axis (3 Floats), sharpness, use_lobe (list of bool per signal), beta, kappa)``
    replaces w_n by Tokuyoshi 2015's lobe weight for the signals marked True."""
    n_sig = len(colors)
    # (nx, ny, nz, 1/z) for the geometry, [(xi, lambda_bar) for the lobe weight]
    # and (r, g, b, var) per signal interleaved, read with one packet gather per 8 channels
    # and tap (Dr.Jit's PacketOps)
    chans = [gb.normal[0], gb.normal[1], gb.normal[2], gb.inv_z]
    if lobes is not None:
        from ..brdf.sg import (
            lobe_tap_log_scale,
            lobe_tap_sharpness,
            lobe_tap_terms,
            smoothed_sharpness,
        )

        axis_p, lam_p, use_lobe, beta, kappa = lobes
        xi_p = mi.Vector3f(axis_p[0], axis_p[1], axis_p[2])
        # Tokuyoshi 2015, sec. 4.2: lambda_bar once per pixel, not per tap, stored as
        # (beta / 2) lambda_bar for lobe_tap_terms
        lb_p = lobe_tap_sharpness(smoothed_sharpness(lam_p, kappa), beta)
        scale = math.exp(lobe_tap_log_scale(beta))  # the constant 4^(beta / 2), into h
        chans += [xi_p[0], xi_p[1], xi_p[2], lb_p]
    i_sig = len(chans)
    for c, v in zip(colors, variances, strict=True):
        chans += [c[0], c[1], c[2], v]
    packed = Packed(chans)
    hit_p = gb.inv_z > 0
    lum_p = [luminance(c) for c in colors]
    inv_den_l = [dr.rcp(sigma_l * dr.sqrt(dr.maximum(gaussian3x3(grid, v), 0.0)) + EPS_L)
                 for v in variances]
    h0 = H5[2] * H5[2]
    sum_w = [mi.Float(h0) for _ in range(n_sig)]
    acc = [[h0 * ch for ch in c] for c in colors]
    acc_var = [mi.Float(h0 * h0) * v for v in variances]
    eps_z = EPS_Z * gb.inv_z + 1e-12
    for dx, dy, q, inside in atrous_taps(grid, step, hit_p):
        allq = packed.fetch(q)  # packet gathers; q is clamped: valid
        nq = allq[:4]
        z_q = nq[3]
        # Schied 2017, eq. 3 (on 1/z, an affine function of clip-space depth)
        plane = dr.abs(gb.dzdx * (dx * step) + gb.dzdy * (dy * step))
        a_z = dr.abs(gb.inv_z - z_q) / (sigma_z * plane + eps_z)
        cos = gb.normal[0] * nq[0] + gb.normal[1] * nq[1] + gb.normal[2] * nq[2]
        w_n = pow_int(dr.maximum(cos, 0.0), sigma_n)  # Schied 2017, eq. 4
        # h(q) and the background test folded into w_n; w_z's exp is merged with w_l's
        h = H5[dx + 2] * H5[dy + 2]
        valid_q = inside & (z_q > 0)  # never across into background
        w_n = dr.select(valid_q, h * w_n, 0.0)
        if lobes is not None:
            xi_q = mi.Vector3f(allq[4], allq[5], allq[6])
            # Tokuyoshi 2015, sec. 4.2 (closed form): the lobe weight in place of w_n, as
            # 4^(beta / 2) y_pow exp(-a_g) with a_g joining the exponent of w_z * w_l below
            y_pow, a_lobe = lobe_tap_terms(xi_p, lb_p, xi_q, allq[7], beta)
            w_lobe = dr.select(valid_q, (h * scale) * y_pow, 0.0)
        for k in range(n_sig):
            cq = allq[i_sig + 4 * k:i_sig + 4 + 4 * k]
            lobe_k = lobes is not None and use_lobe[k]
            w_g = w_lobe if lobe_k else w_n
            a_g = a_z + a_lobe if lobe_k else a_z
            if lum_weights:
                # Schied 2017, eq. 3 * eq. 5: exp(-a_z) exp(-a_l) = exp(-(a_z + a_l))
                l_q = luminance([cq[0], cq[1], cq[2]])
                hw = w_g * exp_weight(-(a_g + dr.abs(lum_p[k] - l_q) * inv_den_l[k]))
            else:
                hw = w_g * exp_weight(-a_g)
            sum_w[k] += hw
            acc[k] = [a + hw * cq[j] for j, a in enumerate(acc[k])]
            acc_var[k] += dr.square(hw) * cq[3]
    out, out_var = [], []
    for k in range(n_sig):
        inv = dr.rcp(sum_w[k])
        out.append([dr.select(hit_p, a * inv, c) for a, c in zip(acc[k], colors[k], strict=True)])
        # variance propagation with squared weights (Schied 2017, sec. 4.3)
        out_var.append(dr.select(hit_p, acc_var[k] * dr.square(inv), variances[k]))
    return out, out_var


def dammertz_level(grid: Grid, color: Img, gb: GBuffer, step: int, sigma_rt: float,
                   sigma_n: float, sigma_x: float) -> Img:
    """One level of Dammertz et al. 2010: weights exp(-|dc|^2/sigma_rt^2) *
    exp(-|dn|^2/sigma_n^2) * exp(-|dx|^2/sigma_x^2) with global sigmas (their eq. 5-6)."""
    return dammertz_level_multi(grid, [color], gb, step, sigma_rt, sigma_n, sigma_x)[0]


def dammertz_level_multi(grid: Grid, colors: list, gb: GBuffer, step: int, sigma_rt: float,
                         sigma_n: float, sigma_x: float) -> list:
    """:func:`dammertz_level` for several signals: the normal and position weights are
    computed once per tap and shared, data are read with packet gathers of interleaved
    channels (as in :func:`svgf_level_multi`, so that the two are compared on equal
    terms)."""
    hit_p = gb.hit
    h0 = H5[2] * H5[2]
    sum_w = [mi.Float(h0) for _ in colors]
    acc = [[h0 * ch for ch in c] for c in colors]
    inv_rt, inv_n, inv_x = 1 / sigma_rt**2, 1 / sigma_n**2, 1 / sigma_x**2
    n, x = gb.normal, gb.position
    # normal, position, mesh id and every signal's colour interleaved: one packet gather
    # per 8 channels and tap
    chans = [n[0], n[1], n[2], x[0], x[1], x[2], gb.mesh]
    for c in colors:
        chans += [c[0], c[1], c[2]]
    packed = Packed(chans)
    for dx, dy, q, inside in atrous_taps(grid, step, hit_p):
        vals = packed.fetch(q)  # q is clamped: always valid
        # Dammertz: the normal distance is divided by the squared step width
        d_n = (dr.square(n[0] - vals[0]) + dr.square(n[1] - vals[1]) +
               dr.square(n[2] - vals[2])) / (step * step)
        d_x = dr.square(x[0] - vals[3]) + dr.square(x[1] - vals[4]) + dr.square(x[2] - vals[5])
        h = H5[dx + 2] * H5[dy + 2]
        w_g = dr.select(inside & (vals[6] > 0), h * exp_weight(-(d_n * inv_n + d_x * inv_x)),
                        0.0)
        for k, c in enumerate(colors):
            cq = vals[7 + 3 * k:10 + 3 * k]
            d_c = dr.square(c[0] - cq[0]) + dr.square(c[1] - cq[1]) + dr.square(c[2] - cq[2])
            hw = w_g * exp_weight(-d_c * inv_rt)
            sum_w[k] += hw
            acc[k] = [a + hw * cq[j] for j, a in enumerate(acc[k])]
    return [[dr.select(hit_p, a / sw, ch) for a, ch in zip(ak, c, strict=True)]
            for ak, sw, c in zip(acc, sum_w, colors, strict=True)]
