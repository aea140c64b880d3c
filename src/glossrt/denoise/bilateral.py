"""Cross-bilateral denoising of demodulated indirect illumination with a normal-aware or a
specular-lobe-aware weight (Tokuyoshi 2015, sec. 2.2 and 4; parameters of sec. 5).

Reference: Y. Tokuyoshi, "Specular Lobe-Aware Filtering and Upsampling for Interactive
Indirect Illumination", IPSJ Journal 56(8), 2015.

Pipeline (sec. 4, after [16]): each listed radiance component is divided by its albedo
(diffuse components by ``albedo_diffuse``, specular ones by ``albedo_specular``), filtered by
the weighted average of eq. 1, multiplied by the albedo again, and every other radiance
component (emission, direct lighting, unlisted components) is added unfiltered.

Weights (``i`` = the filtered pixel, ``j`` = a tap of the ``(2r+1)^2`` window):

* eq. 1: ``I'(i) = sum_j W(i, j) I(j) / sum_j W(i, j)``;
* sec. 2.2: ``W(i, j) = f(s_i, s_j) w_z(i, j) w_dir(i, j)``, with the screen-space Gaussian
  ``f = g(|s_i - s_j|, sigma_s^2) = exp(-|s_i - s_j|^2 / (2 sigma_s^2))``;
* sec. 2.2 depth weight ``w_z = g(|z_i - z_j|, sigma_z^2)``. The paper gives no sigma_z; here
  the depth difference is taken *relative to* ``z_i`` (``g(|z_i - z_j| / z_i, sigma_z2)``) so
  that one value works at any scene scale (:data:`SIGMA_Z2`, a glossrt choice);
* ``weight="normal"``: sec. 2.2 ``w_n = g(|n_i - n_j|, sigma_n^2) = G(n_i, n_j, 1/sigma_n^2)``
  (sec. 4.2), ``sigma_n^2 = 0.01`` (sec. 5);
* ``weight="lobe"``: for *specular* components the lobe weight of sec. 4.2,
  ``w = (2 sqrt(lb_i lb_j) / (lb_i + lb_j))^beta G(xi_i, xi_j, beta lb_i lb_j / (lb_i +
  lb_j))``, ``lb = lambda kappa / (lambda + kappa)``, ``beta = 20``, ``kappa = 100`` (sec. 5),
  where ``(xi, lambda)`` is the pixel's GGX lobe as an SG (Wang et al.'s warp, sec. 4.2,
  :func:`glossrt.brdf.sg.ggx_lobe_to_sg`) built from its normal, its view direction
  ``normalize(camera position - position)`` and its roughness. ``approx=False`` uses the exact
  eq. 6 instead of eq. 7 inside eqs. 4-5. For *diffuse* components the weight stays the
  normal weight ``w_n``: the paper states (end of sec. 4.2) that the normal-aware weight *is*
  its lobe weight for a diffuse surface (axis = normal, ``lb_i = lb_j``), and it filters only
  the specular buffer with lobes (sec. 5); keeping ``w_n`` there means ``weight`` changes the
  specular filtering only.

The paper does not state its screen kernel (sigma_s, radius); the defaults here,
``sigma_s = 2`` px and ``radius = 6`` (the Gaussian truncated at 3 sigma_s), are glossrt's.

Background pixels (``mesh_id == 0``) are returned unfiltered and are never used as taps; taps
outside the image are skipped (no clamping / mirroring).

Reads: the five radiance components, ``albedo_diffuse``, ``albedo_specular``, ``normal``,
``depth``, ``mesh_id`` and, for ``weight="lobe"``, ``position``, ``roughness`` and the camera.
Produces: the RGB image (H, W, 3).
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from ..brdf.sg import ggx_lobe_to_sg, lobe_weight
from ..errors import FrameError, GlossrtError
from ..frame import RADIANCE
from .common import Grid, check_frame, demodulate, merge, remodulate, split

#: default screen-space kernel: sigma_s in pixels and the half width of the window
SIGMA_S = 2.0
RADIUS = 6
#: default variance of the *relative* depth difference |z_i - z_j| / z_i in w_z
SIGMA_Z2 = 0.01
#: the paper's parameters (Tokuyoshi 2015, sec. 5)
SIGMA_N2 = 0.01
BETA = 20.0
KAPPA = 100.0

WEIGHTS = ("normal", "lobe")

__all__ = ["BETA", "KAPPA", "RADIUS", "SIGMA_N2", "SIGMA_S", "SIGMA_Z2", "WEIGHTS", "bilateral"]


def _albedo_name(channel: str) -> str:
    if channel not in RADIANCE or channel == "emission":
        raise GlossrtError(
            f"bilateral: cannot filter {channel!r}; choose among "
            f"{', '.join(c for c in RADIANCE if c != 'emission')}")
    return "albedo_specular" if channel.endswith("specular") else "albedo_diffuse"


def view_directions(frame, position) -> mi.Vector3f:
    """Per-pixel ``wo = normalize(camera position - position)`` (world space)."""
    if frame.camera is None:
        raise FrameError(f"{frame.where}: weight='lobe' needs the camera (view directions)")
    c = [float(v) for v in frame.camera.position]
    return dr.normalize(mi.Vector3f(c[0] - position[0], c[1] - position[1], c[2] - position[2]))


def bilateral(frame, weight: str = "normal",
              channels: tuple[str, ...] = ("indirect_diffuse", "indirect_specular"),
              radius: int = RADIUS, sigma_s: float = SIGMA_S, sigma_n2: float = SIGMA_N2,
              beta: float = BETA, kappa: float | None = KAPPA, approx: bool = True,
              sigma_z2: float | None = SIGMA_Z2) -> mi.TensorXf:
    """Denoise ``frame`` with the cross-bilateral filter of Tokuyoshi 2015 (see the module
    docstring for the weights) and return the RGB image (H, W, 3).

    ``weight``: ``"normal"`` (sec. 2.2's normal-aware weight) or ``"lobe"`` (sec. 4.2's
    specular-lobe-aware weight for the specular components). ``channels``: the radiance
    components to demodulate / filter / remodulate; the others are added unfiltered.
    ``sigma_z2=None`` disables the depth weight."""
    if weight not in WEIGHTS:
        raise GlossrtError(f"bilateral: unknown weight {weight!r}; choose one of "
                           f"{', '.join(WEIGHTS)}")
    radius = int(radius)
    if radius < 0 or not sigma_s > 0 or not sigma_n2 > 0:
        raise GlossrtError("bilateral: need radius >= 0, sigma_s > 0 and sigma_n2 > 0")
    channels = tuple(dict.fromkeys(channels))
    albedo_of = {c: _albedo_name(c) for c in channels}
    use_lobe = weight == "lobe" and any(c.endswith("specular") for c in channels)
    needs = [*RADIANCE, *sorted(set(albedo_of.values())), "normal", "depth", "mesh_id"]
    if use_lobe:
        needs += ["position", "roughness"]
    check_frame(frame, needs)
    h, w = frame.height, frame.width
    grid = Grid(w, h)

    normal = split(frame["normal"])
    z = split(frame["depth"])[0]
    hit = (split(frame["mesh_id"])[0] > 0) & dr.isfinite(z) & (z > 0)
    # packed guidance (n, z) with z = -1 marking background: one packet gather per tap
    zkey = dr.select(hit, z, -1.0)
    geo = dr.ravel(mi.Vector4f(normal[0], normal[1], normal[2], zkey))
    n_p = mi.Vector3f(*normal)
    if use_lobe:
        pos = split(frame["position"])
        alpha = split(frame["roughness"])[0]
        wo = view_directions(frame, pos)
        # Tokuyoshi 2015, sec. 4.2: a_i(w) ~ G(w, xi_i, lambda_i) (Wang et al.'s SG of the lobe)
        xi_p, lam_p = ggx_lobe_to_sg(n_p, wo, alpha)
        xi_p = dr.select(hit, xi_p, mi.Vector3f(0.0, 0.0, 1.0))
        lam_p = dr.select(hit, lam_p, 1.0)
        lobes = dr.ravel(mi.Vector4f(xi_p[0], xi_p[1], xi_p[2], lam_p))
        dr.eval(lobes)

    # demodulate (sec. 4: filtering works on the indirect illumination without albedo)
    signals, albedos, specular = [], [], []
    for c in channels:
        alb = split(frame[albedo_of[c]])
        illum = demodulate(split(frame[c]), alb)
        signals.append(illum)
        albedos.append(alb)
        specular.append(c.endswith("specular"))
    packed = [dr.ravel(mi.Vector4f(s[0], s[1], s[2], 0.0)) for s in signals]
    dr.eval(geo, packed)

    # centre tap: W(i, i) = 1 (f = w_z = w_n = w_lobe = 1)
    sums = [mi.Float(1.0) for _ in signals]
    accs = [[mi.Float(ch) for ch in s] for s in signals]
    inv_2s2 = 1.0 / (2.0 * sigma_s * sigma_s)
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            if dx == 0 and dy == 0:
                continue
            qx, qy = grid.x + dx, grid.y + dy
            q = grid.index(qx, qy)  # clamped, hence a valid gather
            g = dr.gather(mi.Vector4f, geo, q)
            valid = hit & grid.inside(qx, qy) & (g[3] > 0)  # never a background tap
            # sec. 2.2: f(s_i, s_j) = exp(-|s_i - s_j|^2 / (2 sigma_s^2))
            log_w = -float(dx * dx + dy * dy) * inv_2s2
            if sigma_z2 is not None:
                # sec. 2.2: w_z = g(|z_i - z_j|, sigma_z^2), on the depth relative to z_i
                rel = (z - g[3]) / z
                log_w = log_w - dr.square(rel) / (2.0 * sigma_z2)
            w_geo = dr.select(valid, dr.exp(log_w), 0.0)
            # sec. 2.2: w_n = g(|n_i - n_j|, sigma_n^2) = exp(-|n_i - n_j|^2 / (2 sigma_n^2))
            dn2 = dr.squared_norm(n_p - mi.Vector3f(g[0], g[1], g[2]))
            w_nrm = w_geo * dr.exp(-dn2 / (2.0 * sigma_n2))
            if use_lobe:
                lq = dr.gather(mi.Vector4f, lobes, q)
                # sec. 4.2: w = (2 sqrt(lb_i lb_j) / (lb_i + lb_j))^beta
                #               G(xi_i, xi_j, beta lb_i lb_j / (lb_i + lb_j))
                w_lobe = w_geo * lobe_weight(xi_p, lam_p, mi.Vector3f(lq[0], lq[1], lq[2]),
                                             lq[3], beta, kappa, approx)
            for k, s in enumerate(packed):
                wk = w_lobe if (use_lobe and specular[k]) else w_nrm
                v = dr.gather(mi.Vector4f, s, q)
                # eq. 1: numerator and denominator
                sums[k] += wk
                accs[k] = [a + wk * v[j] for j, a in enumerate(accs[k])]
        dr.eval(sums, accs)  # one kernel per window row keeps the traced kernels small

    # eq. 1, then remodulate and add the unfiltered components (sec. 4)
    out = [dr.zeros(mi.Float, w * h) for _ in range(3)]
    for c in RADIANCE:
        if c in channels:
            continue
        out = [o + r for o, r in zip(out, split(frame[c]), strict=True)]
    for k, c in enumerate(channels):
        filt = [dr.select(hit, a / sums[k], s) for a, s in zip(accs[k], signals[k], strict=True)]
        mod = remodulate(filt, albedos[k])
        raw = split(frame[c])  # background: the radiance itself, untouched
        out = [o + dr.select(hit, m, r) for o, m, r in zip(out, mod, raw, strict=True)]
    return merge(out, h, w)
