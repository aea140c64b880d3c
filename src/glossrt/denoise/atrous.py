"""Edge-avoiding a-trous wavelet filtering: SVGF's variance-guided levels (Schied 2017,
sec. 4.3-4.4) and the original edge-avoiding a-trous of Dammertz et al. 2010 (``atrous``).

Reads: ``color`` and the radiance components, ``albedo_diffuse``, ``albedo_specular``,
``normal``, ``depth``, ``mesh_id`` (and ``position`` for Dammertz's weights).
Produces: the filtered RGB image (H, W, 3).
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from .common import H5, GBuffer, Grid, Img, fetch, luminance

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


def svgf_level(grid: Grid, color: Img, var: mi.Float, gb: GBuffer, step: int,
               sigma_z: float = 1.0, sigma_n: float = 128.0, sigma_l: float = 4.0,
               lum_weights: bool = True, normal_weight=None) -> tuple[Img, mi.Float]:
    """One level of the variance-guided edge-avoiding a-trous transform with hole size
    ``step`` (1, 2, 4, ...). Returns the filtered colour and its propagated variance.

    ``normal_weight(p_index, q_index) -> Float`` may replace w_n (later: lobe weights)."""
    lum_p = luminance(color)
    std_p = dr.sqrt(dr.maximum(gaussian3x3(grid, var), 0.0))
    hit_p = gb.hit
    sum_w = mi.Float(1.0)  # the centre tap: h(0)^2 * w(p, p) normalised out below
    h0 = H5[2] * H5[2]
    sum_w = mi.Float(h0)
    acc = [h0 * c for c in color]
    acc_var = mi.Float(h0 * h0) * var
    for dy in range(-2, 3):
        for dx in range(-2, 3):
            if dx == 0 and dy == 0:
                continue
            qx, qy = grid.x + dx * step, grid.y + dy * step
            inside = grid.inside(qx, qy) & hit_p
            q = grid.index(qx, qy)
            c_q = fetch(color, q, inside)
            var_q = dr.gather(mi.Float, var, q, inside)
            z_q = dr.gather(mi.Float, gb.inv_z, q, inside)
            mesh_q = dr.gather(mi.Float, gb.mesh, q, inside)
            # Schied 2017, eq. 3 (on 1/z, an affine function of clip-space depth)
            plane = dr.abs(gb.dzdx * (dx * step) + gb.dzdy * (dy * step))
            w_z = dr.exp(-dr.abs(gb.inv_z - z_q) / (sigma_z * plane + EPS_Z * gb.inv_z + 1e-12))
            if normal_weight is None:
                n_q = fetch(gb.normal, q, inside)
                cos = gb.normal[0] * n_q[0] + gb.normal[1] * n_q[1] + gb.normal[2] * n_q[2]
                w_n = dr.power(dr.maximum(cos, 0.0), sigma_n)  # Schied 2017, eq. 4
            else:
                w_n = normal_weight(grid.idx, q)
            w = w_z * w_n
            if lum_weights:
                # Schied 2017, eq. 5
                w_l = dr.exp(-dr.abs(lum_p - luminance(c_q)) / (sigma_l * std_p + EPS_L))
                w = w * w_l
            w = dr.select(inside & (mesh_q > 0), w, 0.0)
            hw = (H5[dx + 2] * H5[dy + 2]) * w
            sum_w += hw
            acc = [a + hw * c for a, c in zip(acc, c_q, strict=True)]
            acc_var += dr.square(hw) * var_q
    out = [dr.select(hit_p, a / sum_w, c) for a, c in zip(acc, color, strict=True)]
    # variance propagation with squared weights (Schied 2017, sec. 4.3)
    out_var = dr.select(hit_p, acc_var / dr.square(sum_w), var)
    return out, out_var


def dammertz_level(grid: Grid, color: Img, gb: GBuffer, step: int, sigma_rt: float,
                   sigma_n: float, sigma_x: float) -> Img:
    """One level of Dammertz et al. 2010: weights exp(-|dc|^2/sigma_rt^2) *
    exp(-|dn|^2/sigma_n^2) * exp(-|dx|^2/sigma_x^2) with global sigmas (their eq. 5-6)."""
    hit_p = gb.hit
    h0 = H5[2] * H5[2]
    sum_w = mi.Float(h0)
    acc = [h0 * c for c in color]
    inv_rt, inv_n, inv_x = 1 / sigma_rt**2, 1 / sigma_n**2, 1 / sigma_x**2
    for dy in range(-2, 3):
        for dx in range(-2, 3):
            if dx == 0 and dy == 0:
                continue
            qx, qy = grid.x + dx * step, grid.y + dy * step
            inside = grid.inside(qx, qy) & hit_p
            q = grid.index(qx, qy)
            c_q = fetch(color, q, inside)
            n_q = fetch(gb.normal, q, inside)
            x_q = fetch(gb.position, q, inside)
            mesh_q = dr.gather(mi.Float, gb.mesh, q, inside)
            d_c = sum(dr.square(a - b) for a, b in zip(color, c_q, strict=True))
            # Dammertz: the normal distance is divided by the squared step width
            d_n = sum(dr.square(a - b) for a, b in zip(gb.normal, n_q, strict=True)) / (
                step * step)
            d_x = sum(dr.square(a - b) for a, b in zip(gb.position, x_q, strict=True))
            w = dr.exp(-d_c * inv_rt) * dr.exp(-d_n * inv_n) * dr.exp(-d_x * inv_x)
            w = dr.select(inside & (mesh_q > 0), w, 0.0)
            hw = (H5[dx + 2] * H5[dy + 2]) * w
            sum_w += hw
            acc = [a + hw * c for a, c in zip(acc, c_q, strict=True)]
    return [dr.select(hit_p, a / sum_w, c) for a, c in zip(acc, color, strict=True)]
