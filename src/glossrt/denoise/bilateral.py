"""Cross-bilateral denoising of demodulated indirect illumination with a normal-aware, a
sharpness-adapted screen-kernel or a specular-lobe-aware weight (Tokuyoshi 2015, sec. 2.2 and
4; parameters of sec. 5; the screen-kernel baseline of sec. 5.1 / fig. 4(c)).

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
  :func:`glossrt.brdf.sg.ggx_lobe_to_sg`) built from its normal, its view direction (the
  reversed camera ray through the pixel, :func:`~glossrt.denoise.common.pixel_view_directions`:
  ``normalize(camera position - position)`` without reading ``position``) and its
  roughness. ``approx=False`` uses the exact eq. 6 instead of eq. 7 inside eqs. 4-5. For
  *diffuse* components the weight stays the normal weight ``w_n``: the paper states (end of
  sec. 4.2) that the normal-aware weight *is* its lobe weight for a diffuse surface (axis =
  normal, ``lb_i = lb_j``), and it filters only the specular buffer with lobes (sec. 5);
  keeping ``w_n`` there means ``weight`` changes the specular filtering only;
* ``weight="screen"``: the baseline of the paper's fig. 4(c), "frequency-analysis methods
  adjust the screen-space kernel bandwidth to the sharpness of the specular reflection"
  (sec. 5.1). The paper does not give its formula; this one is glossrt's. For *specular*
  components the screen sigma becomes per pixel

      ``sigma_s,i = clip(k_s / (sqrt(lambda_i) theta_px), sigma_min, sigma_s)``

  where ``lambda_i`` is the pixel's SG sharpness (the same :func:`ggx_lobe_to_sg` lobe as the
  lobe weight, *not* smoothed by ``kappa``), ``theta_px = 2 tan(fov / 2) / W`` the angle one
  pixel subtends at the image centre (``fov`` = the camera's horizontal field of view, ``W``
  the image width) and ``k_s`` a scale (default 1). Rationale: an SG ``exp(lambda (cos t -
  1))`` has the angular standard deviation ``1 / sqrt(lambda)``; on a planar mirror the
  reflected direction turns by ``theta_px`` per pixel, so the lobe averages the incident
  radiance over about ``1 / (sqrt(lambda) theta_px)`` pixels, the scale below which the
  reflection carries no detail. The kernel never grows beyond ``sigma_s`` (nor the window
  beyond ``radius``) and never shrinks below ``sigma_min`` (default 0.5 px). The other factors
  are those of ``weight="normal"`` (``W = f_i(s_i, s_j) w_z w_n``): the sharpness only sets
  the bandwidth; unlike the lobe weight it does not compare the two pixels' lobes. *Diffuse*
  components keep the normal weight with ``sigma_s``.

The paper does not state its screen kernel (sigma_s, radius); the defaults here,
``sigma_s = 2`` px and ``radius = 6`` (the Gaussian truncated at 3 sigma_s), are glossrt's.

Background pixels (``mesh_id == 0``) are returned unfiltered and are never used as taps; taps
outside the image are skipped (no clamping / mirroring). A pixel with a NaN / Inf in a guide
the filter reads (``normal``, ``depth``; ``roughness`` for the lobes) is treated as
background.

Reads: the five radiance components, ``albedo_diffuse``, ``albedo_specular``, ``normal``,
``depth``, ``mesh_id`` and, for ``weight="lobe"`` or ``"screen"`` (with a specular channel),
``roughness`` and the camera (with ``meta["jitter"]`` when present).
Produces: the RGB image (H, W, 3).

Parameter sweeps: ``sigma_n2``, ``beta`` and ``k_s`` may also be passed as opaque Dr.Jit
scalars (``dr.opaque(mi.Float, v)``); the kernels then do not depend on the value and are
compiled once for the whole sweep (a Python float is a literal of the kernel, so each new
value recompiles). Results agree with the Python-float call to float32 rounding.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import drjit as dr

from ..backend import mi
from ..brdf.sg import lobe_to_sg, smoothed_sharpness
from ..errors import FrameError, GlossrtError
from ..frame import RADIANCE
from ..jit import exp_weight
from .common import (
    Grid,
    albedo_channel,
    check_frame,
    demodulate,
    finite,
    lobe_tap_weight,
    merge,
    pixel_guides,
    pixel_view_directions,
    remodulate,
    split,
    tap_channels,
    tap_sharpness,
    view_directions,
)

#: default screen-space kernel: sigma_s in pixels and the half width of the window
SIGMA_S = 2.0
RADIUS = 6
#: default variance of the *relative* depth difference |z_i - z_j| / z_i in w_z
SIGMA_Z2 = 0.01
#: the paper's parameters (Tokuyoshi 2015, sec. 5)
SIGMA_N2 = 0.01
BETA = 20.0
KAPPA = 100.0
#: weight="screen" (glossrt's form of the fig. 4(c) baseline): scale k_s of the adapted
#: sigma and its floor in pixels
K_S = 1.0
SIGMA_MIN = 0.5

WEIGHTS = ("normal", "lobe", "screen")

__all__ = ["BETA", "KAPPA", "K_S", "RADIUS", "SIGMA_MIN", "SIGMA_N2", "SIGMA_S", "SIGMA_Z2",
           "WEIGHTS", "bilateral", "pixel_angle", "pixel_view_directions", "screen_sigma",
           "view_directions"]


def pixel_angle(frame) -> float:
    """``theta_px = 2 tan(fov / 2) / W``: the angle (radians) one pixel subtends at the image
    centre, from the frame's camera (horizontal ``fov``) and its width ``W`` (glossrt's
    ``weight="screen"``, see the module docstring)."""
    if frame.camera is None:
        raise FrameError(f"{frame.where}: weight='screen' needs the camera (field of view)")
    return frame.camera.pixel_angle(frame.width)


def screen_sigma(lambda_, theta_px: float, k_s: float = K_S, sigma_min: float = SIGMA_MIN,
                 sigma_s: float = SIGMA_S):
    """Sharpness-adapted screen sigma (pixels) of ``weight="screen"``:
    ``clip(k_s / (sqrt(lambda) theta_px), sigma_min, sigma_s)`` (glossrt's form of the
    frequency-analysis baseline of Tokuyoshi 2015, sec. 5.1 / fig. 4(c)). Works on Dr.Jit
    arrays and Python floats; ``lambda = 0`` gives ``sigma_s``."""
    lam = dr.maximum(lambda_, 1e-30)
    # Tokuyoshi 2015, sec. 5.1 / fig. 4(c) baseline: the kernel bandwidth follows the
    # specular sharpness (the lobe's angular std 1 / sqrt(lambda), in pixels)
    return dr.clip(k_s / (dr.sqrt(lam) * theta_px), sigma_min, sigma_s)


def bilateral(frame, weight: str = "normal",
              channels: tuple[str, ...] = ("indirect_diffuse", "indirect_specular"),
              radius: int = RADIUS, sigma_s: float = SIGMA_S, sigma_n2: float = SIGMA_N2,
              beta: float = BETA, kappa: float | None = KAPPA, approx: bool = True,
              sigma_z2: float | None = SIGMA_Z2, k_s: float = K_S,
              sigma_min: float = SIGMA_MIN, ndf_sharpness: float | None = None) -> mi.TensorXf:
    """Denoise ``frame`` with the cross-bilateral filter of Tokuyoshi 2015 (see the module
    docstring for the weights) and return the RGB image (H, W, 3).

    ``weight``: ``"normal"`` (sec. 2.2's normal-aware weight), ``"lobe"`` (sec. 4.2's
    specular-lobe-aware weight for the specular components) or ``"screen"`` (the normal
    weight with a screen sigma adapted per pixel to the specular sharpness for the specular
    components, ``k_s`` / ``sigma_min``: glossrt's form of the fig. 4(c) baseline).
    ``channels``: the radiance components to demodulate / filter / remodulate; the others are
    added unfiltered. ``sigma_z2=None`` disables the depth weight. ``ndf_sharpness``: the NDF
    SG sharpness times ``alpha^2`` used to build the lobes of ``"lobe"`` and ``"screen"``
    (default: each pixel's distribution's own, :func:`glossrt.brdf.sg.lobe_to_sg`: 4 for GGX,
    Wang et al.'s 2 for Beckmann)."""
    radius = _check_args(weight, radius, sigma_s, sigma_n2, k_s, sigma_min)
    channels = tuple(dict.fromkeys(channels))
    albedo_of = {c: albedo_channel(c, "bilateral") for c in channels}
    any_specular = any(c.endswith("specular") for c in channels)
    use_lobe = weight == "lobe" and any_specular
    use_screen = weight == "screen" and any_specular
    needs = [*RADIANCE, *sorted(set(albedo_of.values())), "normal", "depth", "mesh_id"]
    if use_lobe or use_screen:
        needs += ["roughness"]
    check_frame(frame, needs)
    h, w = frame.height, frame.width
    grid = Grid(w, h)

    # background (and pixels with non-finite guides) returned unfiltered, never a tap
    g = pixel_guides(frame, use_lobe or use_screen)
    c = _Centre(hit=g.hit, z=g.z, n=mi.Vector3f(*g.normal))  # z = -1 marks background
    if use_lobe or use_screen:
        _add_lobes(c, frame, grid, g, use_lobe, use_screen, beta=beta, kappa=kappa,
                   approx=approx, ndf_sharpness=ndf_sharpness, k_s=k_s, sigma_min=sigma_min,
                   sigma_s=sigma_s)

    signals, albedos, specular = _demodulated(frame, channels, albedo_of)
    # the normal weight is needed unless the lobe weight serves every channel
    need_normal = not (use_lobe and all(specular))
    # everything a tap reads, interleaved: one packet gather per 8 channels
    packed, i_lobe, i_z = tap_channels(
        g.normal if need_normal else None,
        [c.xi[0], c.xi[1], c.xi[2], c.lb] if use_lobe else None, c.z, signals)
    # the centre pixel's guides once (one kernel), not re-derived in every window-row kernel
    # (and the demodulated signals, the centre tap's values)
    dr.eval(packed.arrays, c.hit, c.z, c.n, signals, *((c.xi, c.lb) if use_lobe else ()))

    taps = _Taps(packed, i_lobe, i_z, need_normal, use_lobe, use_screen)
    sums, accs = _window_sums(c, taps, grid, radius, signals, specular, sigma_s=sigma_s,
                              sigma_z2=sigma_z2, sigma_n2=sigma_n2, beta=beta, approx=approx)
    return _remodulated(frame, channels, c.hit, signals, albedos, sums, accs)


def _check_args(weight: str, radius, sigma_s, sigma_n2, k_s, sigma_min) -> int:
    """Refuse an unknown weight and parameters the filter cannot use; the radius as an int."""
    if weight not in WEIGHTS:
        raise GlossrtError(f"bilateral: unknown weight {weight!r}; choose one of "
                           f"{', '.join(WEIGHTS)}")
    radius = int(radius)
    if radius < 0 or not sigma_s > 0 or not sigma_n2 > 0:
        raise GlossrtError("bilateral: need radius >= 0, sigma_s > 0 and sigma_n2 > 0")
    if weight == "screen" and not (k_s > 0 and 0 < sigma_min <= sigma_s):
        raise GlossrtError("bilateral: weight='screen' needs k_s > 0 and "
                           f"0 < sigma_min <= sigma_s (got k_s={k_s}, sigma_min={sigma_min}, "
                           f"sigma_s={sigma_s})")
    return radius


@dataclass
class _Centre:
    """The filtered pixel's guides, computed once and read by every tap of its window."""

    hit: Any
    #: depth, -1 on background
    z: Any
    #: the shading normal (mi.Vector3f)
    n: Any
    #: weight="lobe" / "screen": the lobe's SG axis
    xi: Any = None
    #: weight="lobe": the tap sharpness of the smoothed lobe sharpness
    lb: Any = None
    #: weight="screen": 1 / (2 sigma_s,i^2) of the pixel's adapted screen sigma
    inv_2si2: Any = None


def _add_lobes(c: _Centre, frame, grid, g, use_lobe: bool, use_screen: bool, *, beta, kappa,
               approx: bool, ndf_sharpness, k_s, sigma_min, sigma_s) -> None:
    """The centre pixel's specular lobe (Tokuyoshi 2015, sec. 4.2) for weight="lobe" or
    "screen": its SG axis and, per weight, its tap sharpness or its adapted screen sigma."""
    wo = pixel_view_directions(frame, grid, "weight='lobe' or 'screen'")
    # Tokuyoshi 2015, sec. 4.2: a_i(w) ~ G(w, xi_i, lambda_i) (Wang et al.'s SG of the lobe)
    xi_p, lam_p = lobe_to_sg(c.n, wo, g.roughness, g.beckmann, ndf_sharpness)
    c.xi = dr.select(c.hit, xi_p, mi.Vector3f(0.0, 0.0, 1.0))
    lam_p = dr.select(c.hit, lam_p, 1.0)
    if use_lobe:
        # sec. 4.2: the smoothed sharpness lambda_bar = lambda kappa / (lambda + kappa), once
        # per pixel (not per tap), read by the taps beside the lobe axis
        c.lb = tap_sharpness(smoothed_sharpness(lam_p, kappa), beta, approx)
    if use_screen:
        # glossrt's fig. 4(c) baseline: per-pixel sigma_s,i from the lobe sharpness
        sig_i = screen_sigma(lam_p, pixel_angle(frame), k_s, sigma_min, sigma_s)
        c.inv_2si2 = 1.0 / (2.0 * dr.square(sig_i))
        dr.eval(c.inv_2si2)


def _demodulated(frame, channels, albedo_of) -> tuple[list, list, list[bool]]:
    """Each channel's illumination (radiance / albedo; sec. 4: filtering works on the
    indirect illumination without albedo, NaN / Inf as 0), its albedo, and whether it is
    specular."""
    signals, albedos, specular = [], [], []
    for c in channels:
        alb = split(frame[albedo_of[c]])
        # input hygiene: NaN / Inf illumination is 0 (never spread to other pixels by taps)
        illum, _ = finite(demodulate(split(frame[c]), alb))
        signals.append(illum)
        albedos.append(alb)
        specular.append(c.endswith("specular"))
    return signals, albedos, specular


@dataclass(frozen=True)
class _Taps:
    """What a tap gathers (:func:`glossrt.denoise.common.tap_channels`) and which weights the
    window computes."""

    packed: Any
    i_lobe: int
    i_z: int
    need_normal: bool
    use_lobe: bool
    use_screen: bool


def _window_sums(c: _Centre, t: _Taps, grid, radius: int, signals, specular, *, sigma_s,
                 sigma_z2, sigma_n2, beta, approx: bool) -> tuple[list, list]:
    """Eq. 1's denominator and numerator per signal over the ``(2r+1)^2`` window (sec. 2.2's
    weights, sec. 4.2's lobe weight for the specular signals of weight="lobe"), one kernel
    per window row."""
    # centre tap: W(i, i) = 1 (f = w_z = w_n = w_lobe = 1)
    sums = [mi.Float(1.0) for _ in signals]
    accs = [[mi.Float(ch) for ch in s] for s in signals]
    inv_2s2 = 1.0 / (2.0 * sigma_s * sigma_s)
    i_z = t.i_z
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            if dx == 0 and dy == 0:
                continue
            qx, qy = grid.x + dx, grid.y + dy
            q = grid.index(qx, qy)  # clamped, hence a valid gather
            vals = t.packed.fetch(q)
            z_q = vals[i_z]
            valid = c.hit & grid.inside(qx, qy) & (z_q > 0)  # never a background tap
            # sec. 2.2: f(s_i, s_j) = exp(-|s_i - s_j|^2 / (2 sigma_s^2))
            log_w = -float(dx * dx + dy * dy) * inv_2s2
            if t.use_screen:
                # fig. 4(c) baseline: f with the pixel's adapted sigma_s,i
                log_ws = -float(dx * dx + dy * dy) * c.inv_2si2
            if sigma_z2 is not None:
                # sec. 2.2: w_z = g(|z_i - z_j|, sigma_z^2), on the depth relative to z_i
                rel = (c.z - z_q) / c.z  # z = the depth wherever valid
                log_z = dr.square(rel) / (2.0 * sigma_z2)
                log_w = log_w - log_z
                if t.use_screen:
                    log_ws = log_ws - log_z
            # sec. 2.2: w_n = g(|n_i - n_j|, sigma_n^2) = exp(-|n_i - n_j|^2 / (2 sigma_n^2)),
            # folded into one exponential with f and w_z
            if t.need_normal:
                dn2 = dr.squared_norm(c.n - mi.Vector3f(vals[0], vals[1], vals[2]))
                log_n = dn2 / (2.0 * sigma_n2)
                w_nrm = dr.select(valid, exp_weight(log_w - log_n), 0.0)
                if t.use_screen:
                    w_scr = dr.select(valid, exp_weight(log_ws - log_n), 0.0)
            if t.use_lobe:
                # sec. 4.2: w = (2 sqrt(lb_i lb_j) / (lb_i + lb_j))^beta
                #               G(xi_i, xi_j, beta lb_i lb_j / (lb_i + lb_j)), times f w_z
                w_lobe = dr.select(valid, lobe_tap_weight(
                    c.xi, c.lb, vals[t.i_lobe:t.i_lobe + 4], log_w, beta, approx), 0.0)
            for k in range(len(signals)):
                if specular[k] and t.use_lobe:
                    wk = w_lobe
                elif specular[k] and t.use_screen:
                    wk = w_scr
                else:
                    wk = w_nrm
                v = vals[i_z + 1 + 3 * k:i_z + 4 + 3 * k]
                # eq. 1: numerator and denominator
                sums[k] += wk
                accs[k] = [a + wk * v[j] for j, a in enumerate(accs[k])]
        dr.eval(sums, accs)  # one kernel per window row keeps the traced kernels small
    return sums, accs


def _remodulated(frame, channels, hit, signals, albedos, sums, accs) -> mi.TensorXf:
    """Eq. 1, then remodulate and add the unfiltered components (sec. 4); background pixels
    keep their radiance."""
    h, w = frame.height, frame.width
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
