"""Joint bilateral upsampling, spatio-temporal upsampling and adaptive re-sampling of
low-resolution indirect light with normal-aware or specular-lobe-aware weights
(Tokuyoshi 2015, secs. 5.3-5.4; after Kopf et al. 2007 and Herzog et al. 2010).

A typical pipeline renders the full-resolution G-buffer and direct light, and the indirect
light at 1/2 or 1/4 resolution (a second :class:`~glossrt.render.Renderer` on the same scene
at the smaller size, which also gives the low-resolution G-buffer)::

    from glossrt import render, scenes
    from glossrt.denoise import upsample
    full = render.Renderer(scenes.load("roughness-map", size=(320, 240))).render(0)
    low_r = render.Renderer(scenes.load("roughness-map", size=(80, 60)))
    low = low_r.render_reference(0, spp=64)  # or a denoised 1 spp render
    rgb = upsample(full, low, weight="lobe")

**Joint bilateral upsampling** (Kopf 2007, the weights of Tokuyoshi 2015 sec. 2.2 / 4.2): a
full-resolution pixel ``p`` at low-resolution coordinates ``u(p) = (p + 0.5) / f - 0.5 -
jitter`` averages the low-resolution samples ``q`` of the ``2r x 2r`` window around ``u(p)``::

    I'(p) = sum_q W(p, q) I_low(q) / sum_q W(p, q)                      (Tokuyoshi eq. 1)
    W(p, q) = exp(-|u(p) - q|^2 / (2 sigma_s^2)) w_z(p, q) w_dir(p, q)

with the depth weight and ``w_dir`` = the normal weight or, for specular channels with
``weight="lobe"``, the lobe weight, exactly as in :func:`glossrt.denoise.bilateral` but with
the *full-resolution* pixel's G-buffer on one side and the *low-resolution* sample's on the
other. Each listed radiance component is demodulated by the low-resolution albedo, upsampled,
and remodulated by the full-resolution albedo; every other component comes from the
full-resolution frame. ``sigma_s`` is in low-resolution pixels (default 1, window ``r = 2``:
4x4 samples), glossrt's choice as the paper gives none.

Where no sample in the window is similar (every guide weight underflows) the estimate falls
back to the purely spatial average, which may mix surfaces: those are the pixels that the
normalised weight sum ``sum W / sum f`` (returned with ``return_weights=True``) flags and that
:func:`adaptive_resample` re-renders (sec. 5.4: re-sampling where the denominator of eq. 1
is small).

**Spatio-temporal upsampling** (:class:`SpatioTemporalUpsampler`, after Herzog et al. 2010):
the previous full-resolution result (demodulated) is reprojected with the frame's motion
vectors, with SVGF's per-tap consistency tests (depth, normal, mesh id) and 3x3 fallback
(:func:`glossrt.denoise.svgf.reproject`), and blended with the current spatial upsample by an
exponential moving average, ``a = max(alpha, 1 / history length)``. Rendering the
low-resolution frames with a sub-pixel jitter that cycles over frames
(``Renderer.render(jitter=...)``, see :func:`jitter_sequence`) lets the history collect
samples at every sub-position, as Herzog's method does. ``history="herzog"`` replaces the
moving average by Herzog 2010's confidence-weighted accumulation on the same reprojection
(a per-pixel history confidence that decays each frame, weighed against the new value's
confidence from its distance to the nearest jittered sample: :func:`_temporal_herzog`).

Reads: the full frame's radiance components, albedos, ``normal``, ``depth``, ``mesh_id`` (and
``roughness`` and the camera for lobes; ``motion`` for the temporal upsampler); the low
frame's listed components, albedos, ``normal``, ``depth``, ``mesh_id`` (and ``roughness`` and
the camera for lobes) and ``meta["jitter"]`` when present. The lobes' view directions are the
pixels' camera rays (:func:`~glossrt.denoise.common.pixel_view_directions`), so ``position``
is not read. A pixel with a NaN / Inf in a guide read (``normal``, ``depth``; ``roughness``
for lobes) is treated as background on either side; the spatio-temporal upsampler refuses
frames without a camera.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import drjit as dr
import numpy as np

from ..backend import mi
from ..brdf.sg import lobe_to_sg, smoothed_sharpness
from ..errors import FrameError, GlossrtError
from ..frame import RADIANCE
from ..images import TILE_PIXELS, tile_rows, tile_starts
from ..jit import exp_weight, no_gc, opaque
from .bilateral import BETA, KAPPA, SIGMA_N2, SIGMA_Z2
from .common import (
    Grid,
    albedo_channel,
    apply_view_coefficients,
    check_frame,
    demodulate,
    depth_gradient,
    finite,
    frame_jitter,
    lobe_tap_weight,
    merge,
    pixel_guides,
    remodulate,
    require_camera,
    split,
    tap_channels,
    tap_sharpness,
    view_coefficients,
)

#: default screen kernel in *low-resolution* pixels, and the window half width (2r x 2r taps)
SIGMA_S = 1.0
RADIUS = 2
#: default blending factor of the spatio-temporal upsampler (as SVGF's colour alpha)
ALPHA = 0.2
#: the guide weights of the upsamplers (Tokuyoshi 2015, sec. 2.2 and 4.2)
WEIGHTS = ("normal", "lobe")
#: default threshold on the normalised weight sum below which pixels are re-rendered
THRESHOLD = 0.05
#: images of more pixels than this run :class:`SpatioTemporalUpsampler` in row tiles (see
#: "row tiles" below) of at most :data:`TILE_SIZE` pixels, rounded down to whole rows.
#: Images up to this size (320x180, 640x360) run untiled: at 640x360 four tiles of 2^16
#: pixels cost about 20 ms a frame more on 2 CPU cores (87 -> 106 and 78 -> 98 ms, ``full``
#: on polygon-light, alternating fresh processes)
PIXELS_PER_TILE = TILE_PIXELS
#: the most pixels of one row tile: 1920x1080 runs 32 tiles of 34 rows. The transient of
#: the upsampler's frozen call scales with the tile's pixels (~300 bytes per pixel): at
#: 1920x1080, ``full`` on polygon-light, tiles of 2^16 instead of 2^18 pixels lower the
#: indirect stage's peak by about 34 MiB (docs/PERFORMANCE.md); the frame time moved within
#: the machine's noise (medians 760 / 815 ms over three alternating pairs)
TILE_SIZE = 1 << 16
#: guide weights are floored at this fraction of the spatial weight (the spatial fallback)
_FLOOR = 1e-6
#: the histories of :class:`SpatioTemporalUpsampler`: glossrt's simplified exponential
#: moving average, or Herzog 2010's confidence-weighted accumulation (see "history=herzog")
HISTORIES = ("ema", "herzog")
#: ``history="herzog"``: per-frame decay of the history's confidence, the width (in
#: full-resolution pixels) of the Gaussian confidence of a new spatially upsampled value,
#: and its floor (glossrt's choices: see :func:`_temporal_herzog`)
HERZOG_DECAY = 0.9
HERZOG_SIGMA = 0.5
HERZOG_FLOOR = 0.05
#: the history-length slot of a Herzog history (makes :func:`~glossrt.denoise.svgf.reproject`
#: return the reprojected history unblended: its blend ``max(alpha, 1 / length)`` is ~0)
_HUGE_LENGTH = 1e30

__all__ = ["ALPHA", "HERZOG_DECAY", "HERZOG_FLOOR", "HERZOG_SIGMA", "HISTORIES", "RADIUS",
           "SIGMA_S", "THRESHOLD", "WEIGHTS", "SpatioTemporalUpsampler",
           "Upsampler", "adaptive_resample", "factor_of", "herzog_confidence",
           "jitter_sequence", "upsample"]


def factor_of(frame, low) -> int:
    """The integer upsampling factor between ``low`` and ``frame`` (same in x and y)."""
    fw, fh = frame.width / low.width, frame.height / low.height
    if fw != fh or fw != int(fw) or fw < 1:
        raise FrameError(
            f"upsample: the full frame ({frame.width}x{frame.height}) must be an integer "
            f"multiple (the same in x and y) of the low-resolution frame "
            f"({low.width}x{low.height})")
    return int(fw)


def jitter_sequence(factor: int, index: int) -> tuple[float, float]:
    """Sub-pixel jitter (low-resolution pixels) of frame ``index`` that makes the low
    -resolution samples land on each of the ``factor^2`` full-resolution pixel centres of a
    low-resolution pixel in turn (a cycle of ``factor^2`` frames)."""
    if factor < 1:
        raise GlossrtError(f"factor must be >= 1, got {factor}")
    k = index % (factor * factor)
    i, j = k % factor, k // factor
    # full pixel centre i of the low pixel: (i + 0.5) / f - 0.5 relative to the low centre
    return ((i + 0.5) / factor - 0.5, (j + 0.5) / factor - 0.5)


@dataclass
class _Guides:
    """Per-pixel guidance of one frame: hit mask, depth, normal and (optionally) the SG of
    the GGX lobe (Tokuyoshi 2015, sec. 4.2, Wang et al.'s warp) with its *smoothed*
    sharpness ``lambda_bar``."""

    hit: mi.Bool
    z: mi.Float
    normal: mi.Vector3f
    xi: mi.Vector3f | None = None
    lam: mi.Float | None = None

    @staticmethod
    def of(frame, grid: Grid, lobes: bool, kappa: float | None = KAPPA,
           view=None) -> _Guides:
        pg = pixel_guides(frame, lobes)  # non-finite guides: background (never a sample)
        hit, n = pg.hit, mi.Vector3f(*pg.normal)
        g = _Guides(hit, pg.z, n)
        if lobes:
            wo = apply_view_coefficients(grid, view)  # the camera's terms (_camera_terms)
            xi, lam = lobe_to_sg(n, wo, pg.roughness, pg.beckmann)
            g.xi = dr.select(hit, xi, mi.Vector3f(0.0, 0.0, 1.0))
            # Tokuyoshi 2015, sec. 4.2: the smoothed sharpness lambda_bar, once per pixel
            g.lam = smoothed_sharpness(dr.select(hit, lam, 1.0), kappa)
        return g


def _check(frame, low, channels, weight) -> tuple[tuple, dict, bool]:
    if weight not in WEIGHTS:
        raise GlossrtError(f"upsample: unknown weight {weight!r}; choose one of "
                           f"{', '.join(WEIGHTS)}")
    channels = tuple(dict.fromkeys(channels))
    albedo_of = {c: albedo_channel(c, "upsample") for c in channels}
    use_lobe = weight == "lobe" and any(c.endswith("specular") for c in channels)
    geo = ["normal", "depth", "mesh_id"] + (["roughness"] if use_lobe else [])
    check_frame(frame, [*RADIANCE, *sorted(set(albedo_of.values())), *geo])
    check_frame(low, [*channels, *sorted(set(albedo_of.values())), *geo])
    factor_of(frame, low)
    return channels, albedo_of, use_lobe


class _Channels:
    """The channels of a frame as plain arrays (what a frozen function may take as input),
    with the parts of :class:`~glossrt.frame.Frame` the upsampling kernels read."""

    def __init__(self, chs: dict, width: int, height: int):
        self.chs, self.width, self.height = chs, width, height

    def __getitem__(self, name):
        return self.chs[name]

    def require(self, *names):
        return tuple(self.chs[n] for n in names)

    @property
    def names(self) -> tuple:
        return tuple(self.chs)


def _camera_terms(frame, low, use_lobe: bool) -> dict:
    """The per-frame camera terms of the kernels, computed on the host and opaque: the low
    frame's jitter and, for lobes, both frames' view-direction maps. Inputs of the frozen
    functions (a recording would bake them in as literals)."""
    terms = {"jitter": opaque(frame_jitter(low))}
    if use_lobe:
        terms["view"] = view_coefficients(frame, "weight='lobe'")
        terms["view_low"] = view_coefficients(low, "weight='lobe'")
    return terms


def _arrays(frame, names) -> dict:
    return {n: frame[n] for n in names if n in frame.names}


def _low_taps(low, terms, channels, albedo_of, use_lobe, beta, kappa, approx):
    """The low-resolution data a tap reads, interleaved (one packet gather per 8 channels):
    ``(Packed, i_lobe, i_z)`` (:func:`~glossrt.denoise.common.tap_channels`), evaluated."""
    lgrid = Grid(low.width, low.height)
    lo = _Guides.of(low, lgrid, use_lobe, kappa, terms.get("view_low"))
    specular = [c.endswith("specular") for c in channels]
    # the normal weight is needed unless the lobe weight serves every channel
    need_normal = not (use_lobe and all(specular))
    packed, i_lobe, i_z = tap_channels(
        lo.normal if need_normal else None,
        [lo.xi[0], lo.xi[1], lo.xi[2], tap_sharpness(lo.lam, beta, approx)] if use_lobe
        else None, lo.z,
        # input hygiene: NaN / Inf low-resolution illumination is 0 (never spread by taps)
        [finite(demodulate(split(low[c]), split(low[albedo_of[c]])))[0] for c in channels])
    dr.eval(packed.arrays)
    return packed, i_lobe, i_z


def _upsample_illum(frame, low, terms, channels, albedo_of, use_lobe, radius, sigma_s,
                    sigma_n2, beta, kappa, approx, sigma_z2, grid=None, taps=None):
    """Upsampled demodulated illumination per channel (full resolution, or the pixels of the
    row tile ``grid``) and the normalised weight sum per channel (``terms``:
    :func:`_camera_terms`; ``taps``: :func:`_low_taps`' result when computed already)."""
    f = factor_of(frame, low)
    grid = Grid(frame.width, frame.height) if grid is None else grid
    lgrid = Grid(low.width, low.height)
    jx, jy = terms["jitter"]
    hi = _Guides.of(frame, grid, use_lobe, kappa, terms.get("view"))
    # position of each full-resolution pixel centre in low-resolution pixel-index units
    u = (mi.Float(grid.x) + 0.5) / f - 0.5 - jx
    v = (mi.Float(grid.y) + 0.5) / f - 0.5 - jy
    x0, y0 = mi.Int32(dr.floor(u)), mi.Int32(dr.floor(v))

    specular = [c.endswith("specular") for c in channels]
    # the normal weight is needed unless the lobe weight serves every channel
    need_normal = not (use_lobe and all(specular))
    lam_p = tap_sharpness(hi.lam, beta, approx) if use_lobe else None
    packed, i_lobe, i_z = (_low_taps(low, terms, channels, albedo_of, use_lobe, beta, kappa,
                                     approx) if taps is None else taps)
    # window rows per kernel: the default 4x4 window is one kernel for one weight and one
    # channel (the full pixel's guides computed in it); more work per tap is split into
    # smaller kernels (measured: a single kernel for both weights and two channels ran 2x
    # slower than four), the guides then evaluated once beforehand
    rows = max(1, 4 // ((int(need_normal) + int(use_lobe)) * len(channels)))
    per_row = rows < 2 * radius
    if per_row:
        dr.eval(hi.hit, hi.z, hi.normal if need_normal else (), hi.xi, lam_p, u, v)

    inv_2s2 = 1.0 / (2.0 * sigma_s * sigma_s)
    sums = [mi.Float(0.0) for _ in channels]
    accs = [[mi.Float(0.0)] * 3 for _ in channels]
    spatial_sum = mi.Float(0.0)
    for dy in range(-radius + 1, radius + 1):
        for dx in range(-radius + 1, radius + 1):
            qx, qy = x0 + dx, y0 + dy
            inside = lgrid.inside(qx, qy)
            q = lgrid.index(qx, qy)
            vals = packed.fetch(q)
            z_q = vals[i_z]
            # Kopf 2007: spatial Gaussian on the low-resolution grid
            d2 = dr.square(mi.Float(qx) - u) + dr.square(mi.Float(qy) - v)
            w_sp = dr.select(inside, exp_weight(-d2 * inv_2s2), 0.0)
            spatial_sum += w_sp
            valid = inside & hi.hit & (z_q > 0)  # never a background sample
            log_w = 0.0
            if sigma_z2 is not None:
                # Tokuyoshi 2015, sec. 2.2: w_z, on the depth relative to z_p
                log_w = -dr.square((hi.z - z_q) / hi.z) / (2.0 * sigma_z2)
            if need_normal:
                # sec. 2.2: w_n = exp(-|n_p - n_q|^2 / (2 sigma_n^2)), in w_z's exponent
                dn2 = dr.squared_norm(hi.normal - mi.Vector3f(vals[0], vals[1], vals[2]))
                w_nrm = dr.select(valid, w_sp * exp_weight(log_w - dn2 / (2.0 * sigma_n2)), 0.0)
            if use_lobe:
                # sec. 4.2: the lobe weight between the full pixel's and the sample's lobes
                w_lobe = dr.select(valid, w_sp * lobe_tap_weight(
                    hi.xi, lam_p, vals[i_lobe:i_lobe + 4], log_w, beta, approx), 0.0)
            for k in range(len(channels)):
                wk = w_lobe if (use_lobe and specular[k]) else w_nrm
                val = vals[i_z + 1 + 3 * k:i_z + 4 + 3 * k]
                # eq. 1, with the spatial fallback floor (module docstring)
                wk = wk + _FLOOR * w_sp
                sums[k] += wk
                accs[k] = [a + wk * val[j] for j, a in enumerate(accs[k])]
        if per_row and (dy + radius) % rows == 0:
            dr.eval(sums, accs, spatial_sum)
    illum = [[a / dr.maximum(s, 1e-30) for a in acc] for acc, s in zip(accs, sums, strict=True)]
    weights = [dr.maximum(s / dr.maximum(spatial_sum, 1e-30) - _FLOOR, 0.0) for s in sums]
    return illum, weights, hi.hit


def _compose(frame, channels, albedo_of, illum, hit) -> list:
    """Full-resolution RGB: unlisted components from ``frame`` plus the remodulated
    upsampled ones (background pixels keep ``frame``'s own radiance)."""
    out = [dr.zeros(mi.Float, dr.width(hit)) for _ in range(3)]
    for c in RADIANCE:
        if c not in channels:
            out = [o + r for o, r in zip(out, split(frame[c]), strict=True)]
    for k, c in enumerate(channels):
        mod = remodulate(illum[k], split(frame[albedo_of[c]]))
        raw = split(frame[c])
        out = [o + dr.select(hit, m, r) for o, m, r in zip(out, mod, raw, strict=True)]
    return out


def upsample(frame, low, weight: str = "normal",
             channels: tuple[str, ...] = ("indirect_diffuse", "indirect_specular"),
             radius: int = RADIUS, sigma_s: float = SIGMA_S, sigma_n2: float = SIGMA_N2,
             beta: float = BETA, kappa: float | None = KAPPA, approx: bool = True,
             sigma_z2: float | None = SIGMA_Z2, return_weights: bool = False):
    """Joint bilateral upsampling of the ``channels`` of the low-resolution frame ``low`` to
    the G-buffer of ``frame`` (see the module docstring); the other radiance components come
    from ``frame``. Returns the RGB image (H, W, 3); with ``return_weights=True`` also the
    normalised weight sums (H, W, len(channels)) in [0, 1] (0: no similar sample)."""
    return Upsampler(weight, channels, frozen=False, radius=radius, sigma_s=sigma_s,
                     sigma_n2=sigma_n2, beta=beta, kappa=kappa, approx=approx,
                     sigma_z2=sigma_z2)(frame, low, return_weights=return_weights)


_FULL = (*RADIANCE, "albedo_diffuse", "albedo_specular", "normal", "depth", "mesh_id",
         "roughness", "distribution", "motion")


def _spatial(fch, lch, terms, static):
    """:func:`upsample` on arrays (the function :class:`Upsampler` freezes): ``fch`` /
    ``lch`` the full / low frames' channels, ``terms`` the camera terms, ``static`` the
    sizes and parameters (part of a recording's key)."""
    (fw, fh, lw, lh, channels, albedo_of, use_lobe, p, return_weights) = static
    frame, low = _Channels(fch, fw, fh), _Channels(lch, lw, lh)
    albedo_of = dict(albedo_of)
    illum, weights, hit = _upsample_illum(frame, low, terms, channels, albedo_of, use_lobe,
                                          *p)
    img = merge(_compose(frame, channels, albedo_of, illum, hit), fh, fw)
    if return_weights:
        wts = [dr.select(hit, wk, 1.0) for wk in weights]  # background needs nothing
        return img, merge(wts, fh, fw)
    return img


def _params(who: str, params: dict) -> dict:
    p = dict(radius=RADIUS, sigma_s=SIGMA_S, sigma_n2=SIGMA_N2, beta=BETA, kappa=KAPPA,
             approx=True, sigma_z2=SIGMA_Z2)
    unknown = set(params) - set(p)
    if unknown:
        raise GlossrtError(f"{who}: unknown parameters {sorted(unknown)}")
    p.update(params)
    p["radius"] = int(p["radius"])
    if p["radius"] < 1 or not p["sigma_s"] > 0 or not p["sigma_n2"] > 0:
        raise GlossrtError(f"{who}: need radius >= 1, sigma_s > 0 and sigma_n2 > 0")
    return p


def _static(frame, low, channels, albedo_of, use_lobe, p, *extra) -> tuple:
    return (frame.width, frame.height, low.width, low.height, channels,
            tuple(albedo_of.items()), use_lobe,
            (p["radius"], p["sigma_s"], p["sigma_n2"], p["beta"], p["kappa"], p["approx"],
             p["sigma_z2"]), *extra)


class Upsampler:
    """:func:`upsample` as an object: ``up(frame, low, return_weights=False)``, with
    ``frozen=True`` replaying recorded kernels on steady-state frames (``dr.freeze``; the
    camera terms and the jitter are opaque inputs, so a moving camera replays too).
    ``up.n_recordings``: the recordings made so far (0 when not frozen)."""

    def __init__(self, weight: str = "normal",
                 channels: tuple[str, ...] = ("indirect_diffuse", "indirect_specular"),
                 frozen: bool = True, **params):
        self.weight, self.channels = weight, tuple(channels)
        if weight not in WEIGHTS:
            raise GlossrtError(f"upsample: unknown weight {weight!r}; choose one of "
                               f"{', '.join(WEIGHTS)}")
        self.params = _params("upsample", params)
        self.frozen = frozen
        self._fn = dr.freeze(_spatial) if frozen else _spatial

    @property
    def n_recordings(self) -> int:
        return int(self._fn.n_recordings) if self.frozen else 0

    def reset(self) -> None:
        """Nothing to forget (no history): for the stages' interface."""

    def __call__(self, frame, low, return_weights: bool = False):
        channels, albedo_of, use_lobe = _check(frame, low, self.channels, self.weight)
        terms = _camera_terms(frame, low, use_lobe)
        static = _static(frame, low, channels, albedo_of, use_lobe, self.params,
                         bool(return_weights))
        with no_gc():
            return self._fn(_arrays(frame, _FULL), _arrays(low, _FULL), terms, static)


def adaptive_resample(renderer, frame_index: int, frame, image, weights,
                      threshold: float = THRESHOLD,
                      channels: tuple[str, ...] = ("indirect_diffuse", "indirect_specular"),
                      spp: int = 1) -> tuple[mi.TensorXf, np.ndarray]:
    """Tokuyoshi 2015, sec. 5.4: re-render at full resolution the pixels whose normalised
    weight sum (any channel, from :func:`upsample` with ``return_weights=True``) is below
    ``threshold``, with ``renderer`` (the full-resolution Renderer of ``frame``'s scene) at
    ``spp`` samples; their listed channels replace the upsampled ones. Returns the new image
    and the boolean (H, W) mask of re-rendered pixels."""
    h, w = frame.height, frame.width
    if (renderer.width, renderer.height) != (w, h):
        raise GlossrtError(f"adaptive_resample: renderer is {renderer.width}x"
                           f"{renderer.height}, the frame {w}x{h}")
    img = np.array(image, dtype=np.float32).reshape(h, w, 3)
    wts = np.array(weights, dtype=np.float32).reshape(h, w, -1)
    if not math.isfinite(threshold) or threshold < 0:
        raise GlossrtError(f"adaptive_resample: threshold must be >= 0, got {threshold}")
    mask = np.min(wts, axis=-1) < threshold
    idx = np.flatnonzero(mask)
    if idx.size:
        got = renderer.render_pixels(frame_index, idx, spp=spp)
        rest = sum(frame.numpy(c).reshape(-1, 3)[idx] for c in RADIANCE if c not in channels)
        flat = img.reshape(-1, 3)
        flat[idx] = rest + sum(got[c] for c in channels)
    return mi.TensorXf(img), mask


class SpatioTemporalUpsampler:
    """Spatio-temporal upsampling (Tokuyoshi 2015 sec. 5.3 after Herzog et al. 2010; see the
    module docstring): ``up(frame, low) -> mi.TensorXf`` per frame, ``up.reset()`` on cuts.
    Parameters are those of :func:`upsample` plus ``alpha`` (the blend of new samples).

    ``history="herzog"`` replaces the moving average by Herzog 2010's confidence-weighted
    accumulation (:func:`_temporal_herzog`; ``decay``, ``sigma_c`` and ``floor`` are its
    parameters, ``alpha`` is unused); it runs untiled and unfrozen."""

    def __init__(self, weight: str = "normal",
                 channels: tuple[str, ...] = ("indirect_diffuse", "indirect_specular"),
                 alpha: float = ALPHA, frozen: bool = False,
                 tile_pixels: int = PIXELS_PER_TILE, history: str = "ema",
                 decay: float = HERZOG_DECAY, sigma_c: float = HERZOG_SIGMA,
                 floor: float = HERZOG_FLOOR, **params):
        if not 0.0 < alpha <= 1.0:
            raise GlossrtError(f"SpatioTemporalUpsampler: alpha must be in (0, 1], got {alpha}")
        if history not in HISTORIES:
            raise GlossrtError(f"SpatioTemporalUpsampler: unknown history {history!r}; "
                               f"choose one of {', '.join(HISTORIES)}")
        if history == "herzog":
            if frozen:
                raise GlossrtError("SpatioTemporalUpsampler: history='herzog' is not frozen "
                                   "(use frozen=False)")
            for name, val, lo, hi in (("decay", decay, 0.0, 1.0), ("floor", floor, 0.0, 1.0)):
                if not (isinstance(val, int | float) and lo <= val <= hi):
                    raise GlossrtError(f"SpatioTemporalUpsampler: {name} must be in "
                                       f"[{lo}, {hi}], got {val!r}")
            if not (isinstance(sigma_c, int | float) and math.isfinite(sigma_c)
                    and sigma_c > 0):
                raise GlossrtError("SpatioTemporalUpsampler: sigma_c must be > 0, got "
                                   f"{sigma_c!r}")
        self.history = history
        self.herzog = (float(decay), float(sigma_c), float(floor))
        if isinstance(tile_pixels, bool) or not isinstance(tile_pixels, int) \
                or tile_pixels < 1:
            raise GlossrtError("SpatioTemporalUpsampler: tile_pixels must be a positive "
                               f"integer, got {tile_pixels!r}")
        self.weight, self.channels, self.alpha = weight, tuple(channels), float(alpha)
        self.params = _params("SpatioTemporalUpsampler", params)
        self.frozen = frozen
        #: images of more pixels run in row tiles of at most this many pixels and
        #: :data:`TILE_SIZE` (:data:`PIXELS_PER_TILE`)
        self.tile_pixels = int(tile_pixels)
        self._fn = dr.freeze(_temporal) if frozen else _temporal
        self._prepare = dr.freeze(_temporal_prepare) if frozen else _temporal_prepare
        self._tile = dr.freeze(_temporal_tile) if frozen else _temporal_tile
        self._geometry = dr.freeze(_temporal_geometry) if frozen else _temporal_geometry
        self._zero = None
        self.reset()

    @property
    def n_recordings(self) -> int:
        if not self.frozen:
            return 0
        return sum(int(f.n_recordings)
                   for f in (self._fn, self._prepare, self._tile, self._geometry))

    def frozen_functions(self) -> list:
        """The ``dr.freeze`` functions a frame of the last size replays (the untiled one,
        or the row tiles' three; empty when not frozen)."""
        if not self.frozen:
            return []
        size = self._size or (0, 0)
        return ([self._prepare, self._tile, self._geometry]
                if size[0] * size[1] > self.tile_pixels
                else [self._fn])

    def reset(self) -> None:
        """Forget the history (the next frame is the spatial upsample alone)."""
        self._history = None
        self._size = None

    def __call__(self, frame, low) -> mi.TensorXf:
        from .svgf import History

        channels, albedo_of, use_lobe = _check(frame, low, self.channels, self.weight)
        check_frame(frame, ["motion"])
        require_camera(frame, "SpatioTemporalUpsampler")
        size = (frame.width, frame.height)
        if self.history == "herzog":
            return self._herzog(frame, low, channels, albedo_of, use_lobe)
        if self._history is None or self._size != size:
            n = size[0] * size[1]
            zero = [dr.zeros(mi.Float, n) for _ in range(4 + 3 * len(channels))]
            dr.make_opaque(zero)  # the layout of a history of evaluated arrays (one recording)
            prev = History(color=[zero[4 + 3 * k:7 + 3 * k] for k in range(len(channels))],
                           moments=[[zero[0], zero[0]] for _ in channels],
                           length=zero[0], normal=zero[1:4], inv_z=zero[0], mesh=zero[0])
        else:
            prev = self._history
        if size[0] * size[1] > self.tile_pixels:
            self._history = prev
            del prev  # (_tiled lets the old history go before it writes the new geometry)
            img = self._tiled(frame, low, channels, albedo_of, use_lobe)
        else:
            static = _static(frame, low, channels, albedo_of, use_lobe, self.params,
                             self.alpha)
            with no_gc():
                img, self._history = self._fn(_arrays(frame, _FULL), _arrays(low, _FULL),
                                              _camera_terms(frame, low, use_lobe), prev,
                                              static)
        self._size = size
        return img

    def _herzog(self, frame, low, channels, albedo_of, use_lobe) -> mi.TensorXf:
        """One frame of ``history="herzog"`` (untiled, unfrozen)."""
        from .svgf import History

        size = (frame.width, frame.height)
        prev = self._history
        if prev is None or self._size != size:
            n = size[0] * size[1]
            zero = dr.zeros(mi.Float, n)
            # zero confidence: the first frame is the spatial upsample alone
            prev = History(color=[[zero] * 3 for _ in channels],
                           moments=[[zero, zero] for _ in channels], length=zero,
                           normal=[zero] * 3, inv_z=zero, mesh=zero)
        static = _static(frame, low, channels, albedo_of, use_lobe, self.params, 0.0)
        with no_gc():
            img, self._history = _temporal_herzog(
                _arrays(frame, _FULL), _arrays(low, _FULL),
                _camera_terms(frame, low, use_lobe), prev, static, *self.herzog)
        self._size = size
        return img

    def _tiled(self, frame, low, channels, albedo_of, use_lobe) -> mi.TensorXf:
        """One frame in row tiles (the same values as the untiled call; see
        :data:`PIXELS_PER_TILE`): new full-size buffers for the image and the history's
        colours and lengths, the previous history (``self._history``) read as it is. The new
        history's geometry (normal, 1/z, mesh id: the frame's own G-buffer) is written after
        the previous history is let go, so that the two histories' geometry are never held
        at once (40 MiB at 1920x1080); its 1/z is the full-frame 1/z the tiles read."""
        from .svgf import History

        w, h = frame.width, frame.height
        n = w * h
        rows = tile_rows(w, h, min(self.tile_pixels, TILE_SIZE))
        static = _static(frame, low, channels, albedo_of, use_lobe, self.params, self.alpha,
                         rows)
        if self._zero is None or dr.width(self._zero) != n:
            # the history's moments: the upsampler keeps none (zeros for reproject's reads)
            self._zero = dr.zeros(mi.Float, n)
            dr.make_opaque(self._zero)
        old = self._history
        prev = History(color=old.color, moments=[[self._zero, self._zero] for _ in channels],
                       length=old.length, normal=old.normal, inv_z=old.inv_z, mesh=old.mesh)
        del old
        fch, lch = _arrays(frame, _FULL), _arrays(low, _FULL)
        terms = _camera_terms(frame, low, use_lobe)
        out = {"history": [dr.empty(mi.Float, n) for _ in range(3 * len(channels) + 1)],
               "image": dr.empty(mi.Float, 3 * n)}
        dr.eval(out)
        with no_gc():
            taps, inv_z = self._prepare(fch, lch, terms, static)
            for r in tile_starts(h, rows):
                start = dr.opaque(mi.UInt32, r * w)
                values, img = self._tile(fch, lch, terms, prev, taps, inv_z, start, static)
                # copied here, not inside the frozen call (see _temporal_tile)
                idx = start + dr.arange(mi.UInt32, rows * w)
                for dst, val in zip(out["history"], values, strict=True):
                    dr.scatter(dst, val, idx)
                for k in range(3):
                    dr.scatter(out["image"], img[k], idx * 3 + k)
                dr.eval(out)
                del values, img
            del taps, prev
            self._history = None  # (the previous history goes here)
            normal, mesh = self._geometry(fch, static)
        hist = out["history"]
        k = 3 * len(channels)
        self._history = History(color=[hist[3 * j:3 * j + 3] for j in range(len(channels))],
                                moments=None, length=hist[k], normal=normal, inv_z=inv_z,
                                mesh=mesh)
        return mi.TensorXf(out["image"], (h, w, 3))


def _spatial_step(fch, lch, terms, static):
    """What both histories start from: the frame and its channels, the spatial upsample
    ``illum`` of the frame's pixels (eq. 1) with its ``hit`` mask, the grid and the
    geometry the consistency tests compare (background where ``_Guides.of`` says so)."""
    from .common import gbuffer

    (fw, fh, lw, lh, channels, albedo_of, use_lobe, p, _alpha) = static
    frame, low = _Channels(fch, fw, fh), _Channels(lch, lw, lh)
    albedo_of = dict(albedo_of)
    illum, _, hit = _upsample_illum(frame, low, terms, channels, albedo_of, use_lobe, *p)
    grid = Grid(fw, fh)
    gb = gbuffer(frame, grid, with_roughness=use_lobe)
    return frame, channels, albedo_of, illum, hit, grid, gb


def _temporal(fch, lch, terms, prev, static):
    """One frame of :class:`SpatioTemporalUpsampler` on arrays (the function it freezes):
    the output image and the new history."""
    from .svgf import History, reproject

    alpha = static[-1]
    frame, channels, albedo_of, illum, hit, grid, gb = _spatial_step(fch, lch, terms, static)
    fw, fh = grid.w, grid.h
    n = fw * fh
    moments = [[dr.zeros(mi.Float, n)] * 2 for _ in channels]
    # Herzog 2010 / Schied 2017 sec. 4.1: reprojected history, consistency-tested, blended
    # with the new spatial estimate by an exponential moving average
    blended, _, length = reproject(grid, gb, split(frame["motion"]), prev, illum, moments,
                                   alpha, 1.0)
    blended = [[dr.select(hit, b, 0.0) for b in bl] for bl in blended]
    length = dr.select(hit, length, 0.0)
    dr.eval(blended, length)
    # moments are SVGF's; the upsampler keeps none (zeros satisfy reproject's interface)
    history = History(color=blended, moments=moments, length=length,
                      normal=gb.normal, inv_z=gb.inv_z, mesh=gb.mesh)
    return merge(_compose(frame, channels, albedo_of, blended, hit), fh, fw), history


def herzog_confidence(grid: Grid, factor: int, jitter, sigma_c: float, floor: float):
    """Confidence of the new spatially upsampled value at each full-resolution pixel of
    ``grid`` (``history="herzog"``): a Gaussian of the distance, in full-resolution pixels,
    from the pixel centre to the nearest low-resolution sample (``jitter``: the low frame's
    sub-pixel offset), ``max(floor, exp(-d^2 / (2 sigma_c^2)))``. With
    :func:`jitter_sequence` a sample lands exactly on each pixel once per ``factor^2``
    frames (confidence 1); interpolated values count less."""
    jx, jy = jitter
    u = (mi.Float(grid.x) + 0.5) / factor - 0.5 - jx
    v = (mi.Float(grid.y) + 0.5) / factor - 0.5 - jy
    d2 = (dr.square(u - dr.round(u)) + dr.square(v - dr.round(v))) * float(factor * factor)
    return dr.maximum(floor, dr.exp(-d2 / (2.0 * sigma_c * sigma_c)))


def _temporal_herzog(fch, lch, terms, prev, static, decay, sigma_c, floor):
    """One frame of ``history="herzog"``: confidence-weighted temporal accumulation after
    Herzog, Eisemann, Myszkowski, Seidel, "Spatio-Temporal Upsampling on the GPU", I3D 2010
    (sec. 4, temporal refinement; as summarised there and in Tokuyoshi 2015 sec. 5.3 [4]).

    Each full-resolution pixel keeps, with its value ``y``, a confidence ``c`` (how much
    sample evidence the history holds). Per frame::

        c_h = decay * reproject(c)                      (0 where reprojection fails)
        y'  = (c_s x + c_h reproject(y)) / (c_s + c_h)  (confidence-weighted mean)
        c'  = c_s + c_h

    with ``x`` the new spatial upsample and ``c_s`` its confidence
    (:func:`herzog_confidence`). The history is reprojected exactly as the simplified one
    (SVGF's bilinear taps with consistency tests and 3x3 fallback: reproject(y) and
    reproject(c) are the same renormalised taps). The exponential decay of the confidence
    is what lets the history follow changes (the weight of a new exact sample settles at
    ``1 - decay``). Choices glossrt made, named (the paper's full text was not available
    to this implementation; the structure above is Herzog's: a per-pixel history
    confidence that decays over time and is weighed against the new sample's confidence):
    the distance Gaussian ``sigma_c`` = 0.5 full-resolution pixels with a floor of 0.05 as
    the new sample's confidence, one confidence for all channels, no upper clamp of ``c``
    (the decay bounds it by ``1 / (1 - decay)``), ``decay`` = 0.9."""
    from .svgf import History, reproject

    frame, channels, albedo_of, illum, hit, grid, gb = _spatial_step(fch, lch, terms, static)
    fw, fh, lw = grid.w, grid.h, static[2]
    n = fw * fh
    zero = dr.zeros(mi.Float, n)
    c_s = herzog_confidence(grid, fw // lw, terms["jitter"], sigma_c, floor)
    # the history's confidence rides in the moments slot and its length slot is huge, so
    # reproject() (alpha 0) returns the reprojected value and confidence unblended, the new
    # value and confidence 0 where reprojection fails
    src = History(color=prev.color, moments=prev.moments,
                  length=dr.full(mi.Float, _HUGE_LENGTH, n),
                  normal=prev.normal, inv_z=prev.inv_z, mesh=prev.mesh)
    hist, conf, _ = reproject(grid, gb, split(frame["motion"]), src, illum,
                              [[zero, zero] for _ in channels], 0.0, 0.0)
    c_h = decay * dr.maximum(conf[0][0], 0.0)
    inv = dr.rcp(c_s + c_h)
    out = [[dr.select(hit, (c_s * x + c_h * h) * inv, 0.0) for x, h in zip(xs, hs, strict=True)]
           for xs, hs in zip(illum, hist, strict=True)]
    c_new = dr.select(hit, c_s + c_h, 0.0)
    dr.eval(out, c_new)
    history = History(color=out, moments=[[c_new, c_new] for _ in channels],
                      length=dr.select(hit, 1.0, 0.0), normal=gb.normal, inv_z=gb.inv_z,
                      mesh=gb.mesh)
    return merge(_compose(frame, channels, albedo_of, out, hit), fh, fw), history


# -- row tiles of the spatio-temporal upsampler --------------------------------------------
#
# A frozen replay (dr.freeze, Dr.Jit 1.5) keeps every intermediate buffer of the recorded
# function until the call returns (measured: six chained evaluated steps of an 8 MB array
# held 56 MB replayed, 24 MB traced). The full-resolution upsampler's intermediates (its
# guides, the per-row sums of eq. 1, the interleaved history, the reprojection) came to
# ~640 MB at 1920x1080. Large images therefore replay one recording per row tile of
# ``rows x W`` pixels (the tile's first pixel an opaque input), writing the image and the
# new history into full-size buffers (copied there outside the frozen call, which would
# copy a whole input buffer it scatters into); the per-frame low-resolution taps and the
# full-resolution 1/z (whose neighbours the depth gradient reads) are computed once, before
# the tiles. The last tile is moved up to end at the last row (overlapping the one before:
# the same pixels get the same values), so every tile has one shape and one recording.
# The new history's geometry (normal, mesh id: the frame's own G-buffer; its 1/z is the
# full-resolution one above) is written after the tiles, once the previous history is let
# go, so that the two histories' geometry planes are never held together.



class _TileGrid(Grid):
    """The pixels ``offset .. offset + n - 1`` of a W x H image (absolute coordinates:
    :meth:`Grid.index` and :meth:`Grid.inside` address the whole image)."""

    def __init__(self, w: int, h: int, offset, n: int):  # noqa: D107  (no dataclass init)
        self.w, self.h = w, h
        self.idx = offset + dr.arange(mi.UInt32, n)
        self.x = mi.Int32(self.idx % w)
        self.y = mi.Int32(self.idx // w)


def _tile_channels(fch: dict, idx: mi.UInt32, rows: int, w: int) -> dict:
    """The full frame's channels at the tile's pixels, as (rows, W, C) tensors."""
    from ..images import interleave

    return {k: mi.TensorXf(interleave(split(t, idx)), (rows, w, t.shape[2]))
            for k, t in fch.items()}


def _temporal_prepare(fch, lch, terms, static):
    """Once per frame before the tiles: the low-resolution taps (interleaved arrays) and
    the full-resolution 1/z of the SVGF G-buffer (:func:`glossrt.denoise.common.gbuffer`)."""
    from .common import gbuffer

    (fw, fh, lw, lh, channels, albedo_of, use_lobe, p, _alpha, _rows) = static
    low = _Channels(lch, lw, lh)
    beta, kappa, approx = p[3], p[4], p[5]
    packed, _, _ = _low_taps(low, terms, channels, dict(albedo_of), use_lobe, beta, kappa,
                             approx)
    inv_z = gbuffer(_Channels(fch, fw, fh), Grid(fw, fh), with_roughness=use_lobe).inv_z
    dr.eval(inv_z)
    return list(packed.arrays), inv_z


def _temporal_geometry(fch, static):
    """After the tiles: the new history's normal and mesh id, the frame's G-buffer
    (:func:`glossrt.denoise.common.gbuffer`, as each tile computes it for its pixels)."""
    from .common import gbuffer

    fw, fh, use_lobe = static[0], static[1], static[6]
    gb = gbuffer(_Channels(fch, fw, fh), Grid(fw, fh), with_roughness=use_lobe)
    dr.eval(gb.normal, gb.mesh)
    return list(gb.normal), gb.mesh


def _packed_taps(arrays: list, channels: tuple, use_lobe: bool) -> tuple:
    """:func:`_low_taps`' ``(Packed, i_lobe, i_z)`` again from its interleaved ``arrays``
    (what a frozen function takes as input), with the layout of
    :func:`~glossrt.denoise.common.tap_channels`."""
    import sys

    from .common import Packed

    need_normal = not (use_lobe and all(c.endswith("specular") for c in channels))
    i_lobe = 3 if need_normal else 0
    i_z = i_lobe + (4 if use_lobe else 0)
    count = i_z + 1 + 3 * len(channels)
    packed = Packed.__new__(Packed)
    packed._xf = sys.modules[mi.Float.__module__].ArrayXf
    packed._parts = [(8 if min(8, count - k) > 4 else 4, min(8, count - k))
                     for k in range(0, count, 8)]
    packed.arrays = list(arrays)
    return packed, i_lobe, i_z


def _temporal_tile(fch, lch, terms, prev, taps, inv_z_full, offset, static):
    """One row tile of :func:`_temporal` (the function :class:`SpatioTemporalUpsampler`
    freezes for large images): the tile's new history values and image components (its
    caller copies them into the full-size buffers, outside the frozen call: a frozen
    function scattering into an input buffer copies the whole buffer first, measured with
    drjit 1.5)."""
    import dataclasses

    from .common import gbuffer
    from .svgf import reproject

    (fw, fh, lw, lh, channels, albedo_of, use_lobe, p, alpha, rows) = static
    albedo_of = dict(albedo_of)
    n = rows * fw
    grid = _TileGrid(fw, fh, offset, n)
    frame = _Channels(_tile_channels(fch, grid.idx, rows, fw), fw, fh)
    low = _Channels(lch, lw, lh)
    packed, i_lobe, i_z = _packed_taps(taps, channels, use_lobe)
    illum, _, hit = _upsample_illum(frame, low, terms, channels, albedo_of, use_lobe, *p,
                                    grid=grid, taps=(packed, i_lobe, i_z))
    gb = gbuffer(frame, grid, with_roughness=use_lobe)
    inv_z = dr.gather(mi.Float, inv_z_full, grid.idx)
    dzdx, dzdy = depth_gradient(grid, inv_z, inv_z_full)
    gb = dataclasses.replace(gb, inv_z=inv_z, dzdx=dzdx, dzdy=dzdy)
    moments = [[dr.zeros(mi.Float, n)] * 2 for _ in channels]
    blended, _, length = reproject(grid, gb, split(frame["motion"]), prev, illum, moments,
                                   alpha, 1.0, packed=False)
    blended = [[dr.select(hit, b, 0.0) for b in bl] for bl in blended]
    length = dr.select(hit, length, 0.0)
    dr.eval(blended, length)
    img = _compose(frame, channels, albedo_of, blended, hit)
    values = [c for bl in blended for c in bl] + [length]  # (the geometry: _temporal_geometry)
    img = [img[k] for k in range(3)]
    dr.eval(values, img)
    return values, img
