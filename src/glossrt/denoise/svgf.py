"""SVGF: spatiotemporal variance-guided filtering (Schied et al. 2017).

Reads (per frame): ``emission``, ``direct_diffuse``, ``direct_specular``,
``indirect_diffuse``, ``indirect_specular``, ``albedo_diffuse``, ``albedo_specular``,
``normal``, ``depth``, ``mesh_id``, ``motion`` and the camera header (cuts; the temporal
filters refuse frames without one, docs/FORMATS.md). Pixels with NaN / Inf in a guide are
background (:func:`~glossrt.denoise.common.gbuffer`).
Produces: the reconstructed RGB image (H, W, 3).

Stages (functions below, named as in the paper / Falcor's pass): ``demodulate`` ->
``reproject`` (temporal accumulation of colour and luminance moments with geometric
consistency tests) -> ``estimate_variance`` (temporal, or the 7x7 spatial fallback) ->
``svgf_level`` x 5 (a-trous with w_z, w_n, w_l; level 1 feeds the colour history) ->
``remodulate`` + emission. Optionally :func:`taa` afterwards.

>>> svgf = SVGF()                        # doctest: +SKIP
>>> for frame in frames:                 # doctest: +SKIP
...     image = svgf(frame)              # mi.TensorXf (H, W, 3)
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import numpy as np

from ..backend import mi
from ..errors import GlossrtError
from ..frame import Frame
from ..jit import exp_weight, no_gc
from .atrous import dammertz_level_multi, pow_int, svgf_level_multi
from .common import (
    GBuffer,
    Grid,
    Img,
    Packed,
    add,
    check_frame,
    demodulate,
    fetch,
    finite,
    gbuffer,
    luminance,
    merge,
    pixel_view_directions,
    remodulate,
    require_camera,
    split,
)

#: the signals filtered separately: (radiance channels summed, albedo channels summed)
SIGNAL_SETS = {
    "separate": [  # direct/indirect x diffuse/specular (4 signals, glossrt's default)
        (("direct_diffuse",), ("albedo_diffuse",)),
        (("direct_specular",), ("albedo_specular",)),
        (("indirect_diffuse",), ("albedo_diffuse",)),
        (("indirect_specular",), ("albedo_specular",)),
    ],
    "direct-indirect": [  # the paper's split: direct and indirect, one albedo
        (("direct_diffuse", "direct_specular"), ("albedo_diffuse", "albedo_specular")),
        (("indirect_diffuse", "indirect_specular"), ("albedo_diffuse", "albedo_specular")),
    ],
    # one half of "separate" (the pipeline's reduced-resolution indirect light and its
    # full-resolution path-traced direct light, glossrt.pipeline.stages)
    "direct": [
        (("direct_diffuse",), ("albedo_diffuse",)),
        (("direct_specular",), ("albedo_specular",)),
    ],
    "indirect": [
        (("indirect_diffuse",), ("albedo_diffuse",)),
        (("indirect_specular",), ("albedo_specular",)),
    ],
    "single": [
        (("direct_diffuse", "direct_specular", "indirect_diffuse", "indirect_specular"),
         ("albedo_diffuse", "albedo_specular")),
    ],
}
GEOMETRY = ("normal", "depth", "mesh_id", "motion")
MIN_TEMPORAL_HISTORY = 4  # frames; below this the variance is estimated spatially (sec. 4.2)


@dataclass
class History:
    """What survives from one frame to the next (flat channels)."""

    color: list  # per signal: Img (3 channels), the first a-trous level's output
    moments: list  # per signal: [mu1, mu2]
    length: mi.Float
    normal: Img
    inv_z: mi.Float
    mesh: mi.Float


def _signal(frame, radiance: tuple, albedo: tuple) -> tuple[Img, Img, mi.UInt32]:
    rad = split(frame[radiance[0]])
    for name in radiance[1:]:
        rad = add(rad, split(frame[name]))
    alb = split(frame[albedo[0]])
    for name in albedo[1:]:
        alb = add(alb, split(frame[name]))
    rad, bad = finite(rad)  # input hygiene: NaN/Inf never enter the history
    return rad, alb, bad


def _consistent(gb: GBuffer, q_geo: Img, inside: mi.Bool) -> mi.Bool:
    """Geometric consistency of a previous-frame pixel (its ``q_geo`` = mesh id, 1/z,
    normal) with the current pixel: same mesh, normals within ~25 degrees, depth within the
    local depth gradient (Schied 2017, 4.1)."""
    mesh_q, z_q = q_geo[0], q_geo[1]
    cos = gb.normal[0] * q_geo[2] + gb.normal[1] * q_geo[3] + gb.normal[2] * q_geo[4]
    # tolerance: 4 pixels' worth of the local 1/z gradient plus 1% of 1/z (camera motion
    # changes a point's depth a little between frames)
    tol = 4.0 * (dr.abs(gb.dzdx) + dr.abs(gb.dzdy)) + 0.01 * gb.inv_z
    return inside & (mesh_q == gb.mesh) & (gb.mesh > 0) & (cos > 0.9) & (
        dr.abs(z_q - gb.inv_z) <= tol)


def previous_position(grid: Grid, motion: Img) -> tuple[mi.Float, mi.Float]:
    """Each pixel's previous-frame position in pixel-index space (pixel centres at integers),
    ``p + motion``. Input hygiene: non-finite motion puts the pixel off the image (a
    disocclusion), and positions are clamped to 2 pixels off the image (every tap outside
    stays outside), so that integer conversions never see NaN or overflow (their result is
    backend-dependent)."""
    moving = dr.isfinite(motion[0]) & dr.isfinite(motion[1])
    px = dr.clip(dr.select(moving, mi.Float(grid.x) + motion[0], -2.0), -2.0, grid.w + 1.0)
    py = dr.clip(dr.select(moving, mi.Float(grid.y) + motion[1], -2.0), -2.0, grid.h + 1.0)
    return px, py


def reproject(grid: Grid, gb: GBuffer, motion: Img, prev: History, colors: list,
              moments: list, alpha: float, moments_alpha: float, packed: bool = True):
    """Temporal accumulation (Schied 2017, sec. 4.1): bilinear 2x2 reprojection with
    per-tap consistency tests and renormalised weights, a 3x3 fallback, else disocclusion.
    Returns accumulated colours and moments per signal, and the new history length.
    ``grid`` may list a subset of the pixels (``grid.idx``: a row tile of
    :mod:`glossrt.denoise.upsampling`); ``packed=False`` reads the history channel by
    channel (the same values) instead of interleaving it first (an interleaved copy of the
    whole history per tile would cost more memory than the tile saves)."""
    # everything read from the previous frame, interleaved: one or a few packet gathers
    # per tap (geometry for the tests, history length, then per signal r, g, b, mu1, mu2)
    hist = [prev.mesh, prev.inv_z, prev.normal[0], prev.normal[1], prev.normal[2],
            prev.length]
    for hc, hm in zip(prev.color, prev.moments, strict=True):
        hist += [hc[0], hc[1], hc[2], hm[0], hm[1]]
    packed = Packed(hist) if packed else None
    px, py = previous_position(grid, motion)
    x0, y0 = mi.Int32(dr.floor(px)), mi.Int32(dr.floor(py))
    fx, fy = px - mi.Float(x0), py - mi.Float(y0)
    bilinear = [(x0 + dx, y0 + dy, wb) for dx, dy, wb in (
        (0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy),
        (1, 1, fx * fy))]

    def weighted_sum(taps, read):
        """Sums of the history over the consistent taps (weights ``wb``, or 1 for None)."""
        acc, w_sum = None, mi.Float(0.0)
        for qx, qy, wb in taps:
            vals = read(grid.index(qx, qy))  # clamped: every load is valid
            ok = _consistent(gb, vals[:5], grid.inside(qx, qy))
            w = dr.select(ok, 1.0 if wb is None else wb, 0.0)
            acc = [w * v for v in vals[5:]] if acc is None else [
                a + w * v for a, v in zip(acc, vals[5:], strict=True)]
            w_sum += w
        return (*acc, w_sum)

    def fallback():
        """The 3x3 fallback around the reprojected pixel (uniform weights on consistent
        taps), which counts only where every bilinear tap failed. Under dr.if_stmt the LLVM
        backend skips it for packets where no lane needs it (most of them, in steady state);
        it reads channel by channel, as masked packet gathers abort inside dr.freeze."""
        rx, ry = mi.Int32(dr.round(px)), mi.Int32(dr.round(py))
        return weighted_sum([(rx + dx, ry + dy, None) for dy in (-1, 0, 1)
                             for dx in (-1, 0, 1)], lambda q: fetch(hist, q))

    *bil, w_bil = weighted_sum(bilinear, packed.fetch if packed is not None
                               else (lambda q: fetch(hist, q)))
    bilinear_ok = w_bil > 1e-2
    zero = dr.zeros(mi.Float, dr.width(grid.idx))
    *fb, w_fb = dr.if_stmt((), ~bilinear_ok, fallback,
                           lambda: tuple(mi.Float(zero) for _ in (*bil, w_bil)))
    success = bilinear_ok | (w_fb > 0)
    norm = dr.rcp(dr.maximum(dr.select(bilinear_ok, w_bil, w_fb), 1e-6))
    res = [dr.select(bilinear_ok, b, f) * norm for b, f in zip(bil, fb, strict=True)]
    length = dr.select(success, res[0] + 1.0, 1.0)
    a_c = dr.select(success, dr.maximum(alpha, dr.rcp(length)), 1.0)
    a_m = dr.select(success, dr.maximum(moments_alpha, dr.rcp(length)), 1.0)
    out_c, out_m = [], []
    for k, (c, m) in enumerate(zip(colors, moments, strict=True)):
        pc, pm = res[1 + 5 * k:4 + 5 * k], res[4 + 5 * k:6 + 5 * k]
        # Schied 2017, eq. (temporal EMA): C'_i = alpha C_i + (1 - alpha) C'_{i-1}
        out_c.append([dr.lerp(p, x, a_c) for p, x in zip(pc, c, strict=True)])
        out_m.append([dr.lerp(p, x, a_m) for p, x in zip(pm, m, strict=True)])
    return out_c, out_m, length


def spatial_variance(grid: Grid, gb: GBuffer, moments: list[mi.Float],
                     sigma_z: float = 1.0, sigma_n: float = 128.0) -> mi.Float:
    """7x7 bilateral estimate of the luminance variance from the moments, weighted by depth
    and world-space normal (Schied 2017, sec. 4.2: used while the history is short)."""
    return spatial_variance_multi(grid, gb, [moments], sigma_z, sigma_n)[0]


def spatial_variance_multi(grid: Grid, gb: GBuffer, moments: list, sigma_z: float = 1.0,
                           sigma_n: float = 128.0, lanes: mi.UInt32 | None = None) -> list:
    """:func:`spatial_variance` for several signals, sharing the geometric weights. Only the
    pixels listed in ``lanes`` (default: all) are computed, the others get 0: after the
    first frames few pixels have a short history, so the caller compacts them."""
    size = grid.w * grid.h
    all_pixels = lanes is None
    lanes = grid.idx if all_pixels else lanes
    px, py = mi.Int32(lanes % grid.w), mi.Int32(lanes // grid.w)
    zp = dr.gather(mi.Float, gb.inv_z, lanes)
    np_ = fetch(gb.normal, lanes)
    gx, gy = dr.gather(mi.Float, gb.dzdx, lanes), dr.gather(mi.Float, gb.dzdy, lanes)
    n_sig = len(moments)
    m1 = [mi.Float(0.0) for _ in range(n_sig)]
    m2 = [mi.Float(0.0) for _ in range(n_sig)]
    w_sum = mi.Float(0.0)
    for dy in range(-3, 4):
        for dx in range(-3, 4):
            qx, qy = px + dx, py + dy
            inside = grid.inside(qx, qy) & (zp > 0)
            q = grid.index(qx, qy)
            z_q = dr.gather(mi.Float, gb.inv_z, q, inside)
            n_q = fetch(gb.normal, q, inside)
            plane = dr.abs(gx * dx + gy * dy)
            w_z = exp_weight(-dr.abs(zp - z_q) / (sigma_z * plane + 1e-3 * zp + 1e-12))
            cos = np_[0] * n_q[0] + np_[1] * n_q[1] + np_[2] * n_q[2]
            w = dr.select(inside & (z_q > 0), w_z * pow_int(dr.maximum(cos, 0.0), sigma_n),
                          0.0)
            for k in range(n_sig):
                m1[k] += w * dr.gather(mi.Float, moments[k][0], q, inside)
                m2[k] += w * dr.gather(mi.Float, moments[k][1], q, inside)
            w_sum += w
    inv = dr.rcp(dr.maximum(w_sum, 1e-6))
    if all_pixels:
        return [dr.maximum(b * inv - dr.square(a * inv), 0.0) for a, b in zip(m1, m2,
                                                                               strict=True)]
    out = []
    for a, b in zip(m1, m2, strict=True):
        full = dr.zeros(mi.Float, size)
        dr.scatter(full, dr.maximum(b * inv - dr.square(a * inv), 0.0), lanes)
        out.append(full)
    return out


def _zeros(size: int) -> mi.Float:
    """A distinct, evaluated array of zeros: literals and aliased arguments would make
    dr.freeze record a second variant of the pipeline."""
    z = dr.zeros(mi.Float, size)
    dr.make_opaque(z)
    return z


def _empty_history(n_signals: int, size: int) -> History:
    return History(
        color=[[_zeros(size) for _ in range(3)] for _ in range(n_signals)],
        moments=[[_zeros(size) for _ in range(2)] for _ in range(n_signals)],
        length=_zeros(size),
        normal=[_zeros(size) for _ in range(3)],
        inv_z=_zeros(size),
        mesh=_zeros(size),
    )


@dataclass
class SVGFParams:
    alpha: float = 0.2  # colour EMA (sec. 4.1)
    moments_alpha: float = 0.2
    sigma_z: float = 1.0  # sec. 4.4
    sigma_n: float = 128.0
    sigma_l: float = 4.0
    levels: int = 5  # 65x65 footprint
    feedback_level: int = 0  # the first level's output feeds the colour history
    signals: str = "separate"  # "separate" (4), "direct-indirect" (the paper's 2), "single"
    variance: str = "temporal"  # or "spatial": always the 7x7 estimate
    spatial: str = "svgf"  # or "dammertz": the a-trous-temporal baseline
    temporal: bool = True
    # "normal": the paper's w_n; "lobe": Tokuyoshi 2015's specular-lobe weight instead of w_n
    # for the specular signals (beyond the papers; needs one component per signal:
    # signals "separate", "direct" or "indirect")
    weights: str = "normal"
    # "color": the remodulated image plus emission; "illumination": the filtered demodulated
    # signals themselves, 3 channels each in SIGNAL_SETS order (an upsampler remodulates them)
    output: str = "color"
    beta: float = 20.0
    kappa: float = 100.0
    # Dammertz 2010 weights (used when spatial == "dammertz")
    sigma_rt: float = 0.5
    sigma_dn: float = 0.3
    sigma_x: float = 0.3


def _accumulate(frame_ch: dict, hist: History, p: SVGFParams, w: int, h: int):
    """Stage 1: demodulate and accumulate temporally. Returns colours, moments, albedos,
    history length, the 'young history' mask and the non-finite input count."""
    grid = Grid(w, h)
    gb = _gbuffer(frame_ch)
    colors, moments, albedos = [], [], []
    bad = mi.UInt32(0)
    for rad, alb, b in frame_ch["signals"]:
        illum = demodulate(rad, alb)
        lum = luminance(illum)
        colors.append(illum)
        moments.append([lum, dr.square(lum)])
        albedos.append(alb)
        bad += b
    if p.temporal:
        colors, moments, length = reproject(grid, gb, frame_ch["motion"], hist, colors,
                                            moments, p.alpha, p.moments_alpha)
    else:
        length = dr.ones(mi.Float, w * h)
    young = (length < MIN_TEMPORAL_HISTORY) & gb.hit
    return colors, moments, albedos, length, young, dr.sum(bad)


def _level(grid: Grid, gb: GBuffer, frame_ch: dict, c: list, variances, level: int,
           p: SVGFParams):
    """A-trous level ``level`` (hole size ``2^level``): SVGF's (Schied 2017, eqs. 1-5, with
    the variance propagated, sec. 4.3) or Dammertz's. Returns the colours and variances."""
    step = 1 << level
    if p.spatial == "svgf":
        lobes = None
        if p.weights == "lobe":
            lobes = (frame_ch["lobe_axis"], frame_ch["lobe_sharpness"],
                     [bool(s) for s in frame_ch["specular"]], p.beta, p.kappa)
        c, variances = svgf_level_multi(grid, c, variances, gb, step, p.sigma_z, p.sigma_n,
                                        p.sigma_l, lobes=lobes)
        dr.eval(c, variances)  # a kernel boundary per level
        return c, variances
    c = dammertz_level_multi(grid, c, gb, step, p.sigma_rt * 2.0**-level, p.sigma_dn,
                             p.sigma_x)
    dr.eval(c)
    return c, variances


def _output(frame_ch: dict, c: list, albedos: list, p: SVGFParams) -> list:
    """The filtered signals remodulated plus emission (or, ``output="illumination"``, the
    filtered signals themselves)."""
    if p.output == "illumination":
        return [ch for k in range(len(c)) for ch in c[k]]
    out = [mi.Float(e) for e in frame_ch["emission"]]
    for k in range(len(c)):
        out = add(out, remodulate(c[k], albedos[k]))
    return out


def _reconstruct(frame_ch: dict, colors, moments, albedos, length, lanes, p: SVGFParams,
                 w: int, h: int):
    """Stage 2: the variance (temporal, or spatial at the pixels in ``lanes``) and the
    first a-trous level (none if ``p.levels`` is 0). Returns the colours, the variances and,
    when no level follows, the output channels (else None): :func:`_refine` runs the later
    levels, each in its own frozen call, because a frozen replay keeps every intermediate
    array until it returns (measured, Dr.Jit 1.5: a chain of five levels replayed frozen
    peaked at all five levels' outputs, traced at two), which at 1920x1080 is gigabytes."""
    grid = Grid(w, h)
    gb = _gbuffer(frame_ch)
    variances = None
    if p.spatial == "svgf":
        spatial = spatial_variance_multi(grid, gb, moments, p.sigma_z, p.sigma_n, lanes)
        if p.variance == "spatial":
            variances = spatial
        else:
            young = length < MIN_TEMPORAL_HISTORY
            variances = [dr.select(young, v_s, dr.maximum(m[1] - dr.square(m[0]), 0.0))
                         for v_s, m in zip(spatial, moments, strict=True)]
    c = colors
    if p.levels > 0:
        c, variances = _level(grid, gb, frame_ch, c, variances, 0, p)
    out = _output(frame_ch, c, albedos, p) if p.levels <= 1 else None
    return c, variances, out


def _refine(frame_ch: dict, c, variances, albedos, level: int, p: SVGFParams, w: int,
            h: int):
    """A-trous level ``level`` >= 1 (:func:`_level`); the last one also gives the output
    channels (else None)."""
    grid = Grid(w, h)
    gb = _gbuffer(frame_ch)
    c, variances = _level(grid, gb, frame_ch, c, variances, level, p)
    out = _output(frame_ch, c, albedos, p) if level == p.levels - 1 else None
    return c, variances, out


def young_lanes(young: mi.Bool, size: int) -> mi.UInt32 | None:
    """The pixels of mask ``young`` (``size`` pixels) as an evaluated index array whose width
    ``dr.freeze`` sees as one input layout whatever the count, so that
    :func:`_reconstruct` replays one recording frame after frame. Measured on Dr.Jit 1.5
    (tests/test_pipeline_recordings.py): a frozen function records again when an input's
    width becomes 1 (a scalar) or equal to another input's (the image's ``size``), or when
    the input is a literal (``dr.zeros``); widths 2 .. size-1 all replay one recording. So:

    * no young pixel: pixels 0 and 1 (their spatial values are computed and not selected);
    * one: that pixel twice (the same value scattered twice);
    * every pixel: every pixel plus pixel 0 again (width ``size + 1``);
    * images under 3 pixels: None (every pixel, a fixed layout)."""
    if size < 3:
        return None
    lanes = dr.compress(young)
    n = dr.width(lanes)
    if n == 0:
        lanes = dr.arange(mi.UInt32, 2)
    elif n == 1:
        lanes = dr.gather(mi.UInt32, lanes, dr.zeros(mi.UInt32, 2))
    elif n == size:
        lanes = dr.arange(mi.UInt32, size + 1) % size
    else:
        return lanes
    dr.make_opaque(lanes)
    return lanes


def _gbuffer(frame_ch: dict) -> GBuffer:
    return GBuffer(normal=frame_ch["normal"], inv_z=frame_ch["inv_z"], dzdx=frame_ch["dzdx"],
                   dzdy=frame_ch["dzdy"], mesh=frame_ch["mesh"],
                   position=frame_ch.get("position"))


class SVGF:
    """Spatiotemporal variance-guided filter (stateful: keeps the history between frames).

    ``SVGF(**params)`` with the fields of :class:`SVGFParams` (paper defaults);
    ``svgf(frame) -> mi.TensorXf`` (H, W, 3); ``svgf.reset()`` drops the history. The
    history is also dropped when the frame size changes or at a camera cut (the frame's
    ``prev_camera`` is not the camera of the frame filtered before). ``frozen=True``
    replays recorded kernels on steady-state frames (``dr.freeze``; :meth:`frozen_functions`
    lists them)."""

    def __init__(self, frozen: bool = True, **params):
        unknown = set(params) - set(SVGFParams.__dataclass_fields__)
        if unknown:
            raise GlossrtError(f"unknown SVGF parameter(s): {sorted(unknown)}")
        self.params = SVGFParams(**params)
        if self.params.signals not in SIGNAL_SETS:
            raise GlossrtError(f"signals must be one of {sorted(SIGNAL_SETS)}")
        if self.params.variance not in ("temporal", "spatial"):
            raise GlossrtError("variance must be 'temporal' or 'spatial'")
        if self.params.weights not in ("normal", "lobe"):
            raise GlossrtError("weights must be 'normal' or 'lobe'")
        if self.params.weights == "lobe" and any(
                len(rad) != 1 for rad, _ in SIGNAL_SETS[self.params.signals]):
            raise GlossrtError("weights='lobe' needs signals='separate' (a lobe per signal; "
                               "or its halves 'direct', 'indirect')")
        if self.params.output not in ("color", "illumination"):
            raise GlossrtError("output must be 'color' or 'illumination'")
        self.frozen = frozen
        # frozen stages: the compaction of young-history pixels between the first two has a
        # data-dependent size, which a single frozen function would re-record every frame;
        # the a-trous levels after the first run one frozen call each (see _reconstruct)
        self._accumulate = dr.freeze(_accumulate) if frozen else _accumulate
        self._reconstruct = dr.freeze(_reconstruct) if frozen else _reconstruct
        self._refine = [dr.freeze(_refine) if frozen else _refine
                        for _ in range(1, self.params.levels)]
        self.nonfinite = 0
        self.reset()

    def frozen_functions(self) -> list:
        """The ``dr.freeze`` functions a frame replays (empty when not frozen)."""
        if not self.frozen:
            return []
        return [self._accumulate, self._reconstruct, *self._refine]

    def reset(self) -> None:
        self.history: History | None = None
        self._size = None
        self._camera = None
        self.frames = 0

    @property
    def needs(self) -> tuple[str, ...]:
        names = {"emission"}
        for rad, alb in SIGNAL_SETS[self.params.signals]:
            names.update(rad)
            names.update(alb)
        names.update(GEOMETRY)
        if self.params.spatial == "dammertz":
            names.add("position")
        if self.params.weights == "lobe":
            names.add("roughness")
        return tuple(sorted(names))

    def _is_cut(self, frame) -> bool:
        if self._camera is None or frame.prev_camera is None:
            return False
        a, b = np.asarray(self._camera.to_world), np.asarray(frame.prev_camera.to_world)
        return not (np.allclose(a, b, atol=1e-5) and
                    abs(self._camera.fov - frame.prev_camera.fov) < 1e-6)

    def _lobes(self, frame, grid: Grid, gb: GBuffer) -> dict:
        """Each pixel's specular lobe as an SG (Tokuyoshi 2015 sec. 4.2; Wang et al. 2009)
        with its distribution's sharpness, from the G-buffer's (hygienic) normal, roughness
        and distribution and the pixels' camera rays
        (:func:`~glossrt.denoise.common.pixel_view_directions`)."""
        from ..brdf.sg import lobe_to_sg

        wo = pixel_view_directions(frame, grid, "weights='lobe'")
        n = mi.Vector3f(*gb.normal)
        axis, lam = lobe_to_sg(n, wo, gb.roughness, gb.beckmann)
        return {"lobe_axis": [axis[0], axis[1], axis[2]], "lobe_sharpness": lam,
                "specular": [1.0 if "specular" in rad[0] else 0.0
                             for rad, _ in SIGNAL_SETS[self.params.signals]]}

    def __call__(self, frame) -> mi.TensorXf:
        """The filtered frame, ``H x W x C`` (C = 3, or 3 per signal set with
        ``output="illumination"``)."""
        return merge(self.planes(frame), frame.height, frame.width)

    def planes(self, frame) -> list:
        """What :meth:`__call__` returns, as its evaluated channel planes (``C`` arrays of
        ``H * W`` floats): a caller that splits the image anyway (the pipeline's
        reduced-resolution indirect light) skips the interleaved copy."""
        if not isinstance(frame, Frame):
            raise GlossrtError(
                f"{type(self).__name__} takes a glossrt.Frame (from Renderer.render or "
                f"Frame.load), not {type(frame).__name__}"
            )
        check_frame(frame, self.needs)
        if self.params.temporal:
            require_camera(frame, f"temporal filter {type(self).__name__}")
        w, h = frame.width, frame.height
        if self._size != (w, h) or self._is_cut(frame):
            self.reset()
        self._size = (w, h)
        grid = Grid(w, h)
        dammertz, lobe = self.params.spatial == "dammertz", self.params.weights == "lobe"
        # input hygiene: pixels with non-finite guides become background (common.gbuffer)
        gb = gbuffer(frame, grid, with_position=dammertz, with_roughness=lobe)
        emission, bad_e = finite(split(frame["emission"]))
        ch = {
            "signals": [_signal(frame, rad, alb) for rad, alb in
                        SIGNAL_SETS[self.params.signals]],
            "emission": emission,
            "normal": gb.normal, "inv_z": gb.inv_z, "dzdx": gb.dzdx, "dzdy": gb.dzdy,
            "mesh": gb.mesh, "motion": split(frame["motion"]),
        }
        if dammertz:
            ch["position"] = gb.position
        if lobe:
            ch.update(self._lobes(frame, grid, gb))
        hist = self.history or _empty_history(len(ch["signals"]), w * h)
        if self.history is None:
            ch["motion"] = [_zeros(w * h) + 1e9 for _ in range(2)]  # nothing to reproject onto
            dr.make_opaque(ch["motion"])
        p = self.params
        with no_gc():
            colors, moments, albedos, length, young, bad = self._accumulate(ch, hist, p, w, h)
        # pixels that need the spatial variance estimate, compacted (few in steady state)
        lanes = None if p.variance == "spatial" else young_lanes(young, w * h)
        with no_gc():
            c, variances, out = self._reconstruct(ch, colors, moments, albedos, length, lanes,
                                                  p, w, h)
            feedback = c if p.feedback_level == 0 or p.levels == 0 else colors
            for level, refine in enumerate(self._refine, start=1):
                c, variances, out = refine(ch, c, variances, albedos, level, p, w, h)
                if level == p.feedback_level:
                    feedback = c
        self.history = History(color=feedback, moments=moments, length=length,
                               normal=ch["normal"], inv_z=ch["inv_z"], mesh=ch["mesh"])
        self.nonfinite += int(bad[0]) + int(dr.sum(bad_e)[0])
        self._camera = frame.camera
        self.frames += 1
        return list(out)


def atrous_filter(frame, levels: int = 5, sigma_rt: float = 0.5, sigma_n: float = 0.3,
           sigma_x: float = 0.3, signals: str = "separate") -> mi.TensorXf:
    """Edge-avoiding a-trous (Dammertz et al. 2010) per frame, no temporal accumulation:
    the demodulated signals are filtered with global colour/normal/position sigmas."""
    f = SVGF(frozen=False, temporal=False, spatial="dammertz", levels=levels,
             sigma_rt=sigma_rt, sigma_dn=sigma_n, sigma_x=sigma_x, signals=signals)
    return f(frame)


class ATrousTemporal(SVGF):
    """The paper's "augmented" prior work: SVGF's temporal accumulation followed by
    Dammertz's edge-avoiding a-trous (global parameters)."""

    def __init__(self, frozen: bool = True, **params):
        params.setdefault("spatial", "dammertz")
        super().__init__(frozen=frozen, **params)


#: TAA's consistency test: a neighbour's surface counts for a pixel when their motion
#: vectors differ by less than this many pixels in x and in y (glossrt's choice: within one
#: pixel, a jittered sample may show either side of an edge that moves with the pixel)
TAA_MOTION_TOLERANCE = 1.0
#: sub-pixel offsets per TAA cycle (Karis 2014 uses 8 of the Halton (2, 3) sequence)
TAA_JITTER_COUNT = 8


def _radical_inverse(i: int, base: int) -> float:
    """The van der Corput radical inverse of ``i`` in ``base`` (its digits mirrored about
    the radix point)."""
    out, scale = 0.0, 1.0 / base
    while i > 0:
        i, digit = divmod(i, base)
        out += digit * scale
        scale /= base
    return out


def taa_jitter(index: int, count: int = TAA_JITTER_COUNT) -> tuple[float, float]:
    """The sub-pixel offset (x, y) in pixels, within [-0.5, 0.5), of frame ``index``'s primary
    rays under TAA: points 1 .. ``count`` of the Halton (2, 3) sequence, cycled (Karis 2014,
    "High quality temporal supersampling": TAA resolves the pixel's area only from samples
    spread over it). Never (0, 0), so every frame of the cycle traces the same kernels."""
    if count < 1:
        raise GlossrtError(f"taa_jitter: count must be >= 1, got {count}")
    k = int(index) % int(count) + 1  # (point 0 of the sequence is the origin)
    return _radical_inverse(k, 2) - 0.5, _radical_inverse(k, 3) - 0.5


def taa(image: mi.TensorXf, history: mi.TensorXf | None, motion: mi.TensorXf,
        alpha: float = 0.1, mesh_id: mi.TensorXf | None = None,
        prev_mesh_id: mi.TensorXf | None = None, neighbours: bool = False) -> mi.TensorXf:
    """Temporal antialiasing (Karis 2014) as a separate pass: reproject ``history`` with the
    motion vectors (bilinear), clamp it to the 3x3 neighbourhood's min/max of ``image``,
    blend with weight ``alpha`` for the new frame. Pass the result as next ``history``.

    ``mesh_id`` / ``prev_mesh_id`` (the G-buffer's ``mesh_id`` of this frame and of the
    history's frame): each of the four bilinear taps counts only if the surface it showed in
    the previous frame is the pixel's own now (the weights renormalised; none left: a
    disocclusion, the history is dropped), a consistency test as SVGF's 2x2 reprojection has
    (Schied 2017, sec. 4.1). Without it the neighbourhood clamp keeps a moving bright
    emitter's trail wherever one of the 3x3 neighbours still shows it.

    ``neighbours`` (for jittered frames, glossrt's extension): a tap also counts if its
    surface is that of a 3x3 neighbour moving with the pixel (motion vectors within
    :data:`TAA_MOTION_TOLERANCE` pixels of the pixel's). Under sub-pixel jitter
    (:func:`taa_jitter`) a pixel on a geometric edge shows one surface or the other from
    frame to frame, and a test against its own alone drops the history there, at every edge
    TAA exists to resolve (measured on polygon-light's light at 48x27 after 16 still frames:
    the edge pixels' RMSE against the box-filtered image 5.97 with the pixel's own surface,
    1.33 with its neighbours', 4.53 without TAA). Without jitter it only does harm: on the
    animated polygon-light at 96x72 it raised schied2017's RMSE from 0.068 to 0.31, twice
    the raw 1 spp input's (docs/RESULTS.md). At the image border the neighbourhood is
    one-sided, and its clamp keeps an edge there aliased.

    Input hygiene: NaN/Inf in ``image`` or ``history`` count as 0 (they reach neither the
    neighbours' clamp nor the next history); non-finite motion drops the pixel's history,
    as a disocclusion."""
    h, w, _ = image.shape
    cur = finite(split(image))[0]
    if history is None or tuple(history.shape) != tuple(image.shape):
        return merge(cur, h, w)
    grid = Grid(w, h)
    lo = [mi.Float(c) for c in cur]
    hi = [mi.Float(c) for c in cur]
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            n = fetch(cur, grid.index(grid.x + dx, grid.y + dy))
            lo = [dr.minimum(a, b) for a, b in zip(lo, n, strict=True)]
            hi = [dr.maximum(a, b) for a, b in zip(hi, n, strict=True)]
    mv = split(motion)
    px, py = previous_position(grid, mv)
    x0, y0 = mi.Int32(dr.floor(px)), mi.Int32(dr.floor(py))
    fx, fy = px - mi.Float(x0), py - mi.Float(y0)
    prev = finite(split(history))[0]
    if (mesh_id is None) != (prev_mesh_id is None):
        raise GlossrtError("taa: give both mesh_id and prev_mesh_id, or neither")
    near_ids = None  # the surfaces of the 3x3 neighbourhood now
    was_ids = split(prev_mesh_id)[0] if mesh_id is not None else None
    if mesh_id is not None:
        cur_id = split(mesh_id)[0]
        mx, my = mv[0], mv[1]
        near_ids = [cur_id]  # the pixel's own surface, and each neighbour's that moves with it
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                if neighbours and (dx or dy):
                    k = grid.index(grid.x + dx, grid.y + dy)
                    along = ((dr.abs(dr.gather(mi.Float, mx, k) - mx) < TAA_MOTION_TOLERANCE)
                             & (dr.abs(dr.gather(mi.Float, my, k) - my)
                                < TAA_MOTION_TOLERANCE))
                    # (-1: no mesh id matches it)
                    near_ids.append(dr.select(along, dr.gather(mi.Float, cur_id, k), -1.0))
    acc = [dr.zeros(mi.Float, w * h) for _ in prev]
    wsum = dr.zeros(mi.Float, w * h)
    for dx, dy, wb in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)),
                       (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
        tap = grid.index(x0 + dx, y0 + dy)
        if near_ids is not None:  # a tap that showed a surface not near now is left out
            was = dr.gather(mi.Float, was_ids, tap)
            seen = was == near_ids[0]
            for n in near_ids[1:]:
                seen |= was == n
            wb = dr.select(seen, wb, 0.0)
        vals = fetch(prev, tap)
        acc = [a + wb * v for a, v in zip(acc, vals, strict=True)]
        wsum += wb
    onscreen = grid.inside(mi.Int32(dr.round(px)), mi.Int32(dr.round(py)))
    if near_ids is not None:
        onscreen &= wsum > 1e-3
        acc = [a / dr.maximum(wsum, 1e-3) for a in acc]
    out = [dr.select(onscreen, dr.lerp(dr.clip(p, l, u), c, alpha), c)
           for p, l, u, c in zip(acc, lo, hi, cur, strict=True)]
    return merge(out, h, w)
