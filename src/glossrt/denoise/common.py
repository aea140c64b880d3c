"""Shared pieces of glossrt's screen-space filters (Dr.Jit, one lane per pixel).

Images inside the filters are structure-of-arrays: one flat ``mi.Float`` of H*W values per
channel (``Img`` = list of channels). Neighbour access gathers with clamped coordinates.
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass

import drjit as dr
import numpy as np

from ..backend import mi
from ..brdf.sg import lobe_tap_log_scale, lobe_tap_sharpness, lobe_tap_terms, lobe_weight
from ..errors import FrameError, GlossrtError
from ..frame import RADIANCE
from ..images import (  # noqa: F401 - the shared image helpers, under their old home too
    LUM,
    Grid,
    Img,
    check_frame,
    fetch,
    interleave,
    luminance,
    merge,
    split,
    view_directions,
)
from ..jit import exp_weight, opaque

#: albedo below this is treated as "no albedo": the radiance is filtered as it is
ALBEDO_EPS = 1e-3



def finite(chs: Img) -> tuple[Img, mi.UInt32]:
    """Replace NaN/Inf by 0; also return the number of replaced values (per lane)."""
    bad = mi.UInt32(0)
    out = []
    for ch in chs:
        ok = dr.isfinite(ch)
        bad += dr.select(ok, 0, 1)
        out.append(dr.select(ok, ch, 0.0))
    return out, bad


def demodulate(radiance: Img, albedo: Img) -> Img:
    """Divide by the albedo (Schied 2017, sec. 3: filter untextured illumination); where the
    albedo is ~0 the radiance is kept as it is (and :func:`remodulate` leaves it alone)."""
    return [dr.select(a > ALBEDO_EPS, r / dr.maximum(a, ALBEDO_EPS), r)
            for r, a in zip(radiance, albedo, strict=True)]


def remodulate(illum: Img, albedo: Img) -> Img:
    return [dr.select(a > ALBEDO_EPS, f * a, f) for f, a in zip(illum, albedo, strict=True)]


def add(a: Img, b: Img) -> Img:
    return [x + y for x, y in zip(a, b, strict=True)]


def depth_gradient(grid: Grid, inv_z: mi.Float,
                   inv_z_image: mi.Float | None = None) -> tuple[mi.Float, mi.Float]:
    """Screen-space gradient of 1/z (one-sided difference of smaller magnitude, so a depth
    edge does not inflate it). 1/z is an affine function of clip-space depth, so
    |z(p)-z(q)| / |grad z . (p-q)| is the same for both: Schied 2017 eq. 3 works on it as on
    clip-space depth. ``inv_z_image``: where the neighbours are read when ``grid``'s lanes
    are a part of the image (a row tile; default ``inv_z``, the lanes being the image)."""
    src = inv_z if inv_z_image is None else inv_z_image
    out = []
    for dx, dy in ((1, 0), (0, 1)):
        f = dr.gather(mi.Float, src, grid.index(grid.x + dx, grid.y + dy)) - inv_z
        b = inv_z - dr.gather(mi.Float, src, grid.index(grid.x - dx, grid.y - dy))
        # at the image border only the difference that exists counts
        f_ok = grid.inside(grid.x + dx, grid.y + dy)
        b_ok = grid.inside(grid.x - dx, grid.y - dy)
        use_f = f_ok & (~b_ok | (dr.abs(f) < dr.abs(b)))
        out.append(dr.select(use_f, f, dr.select(b_ok, b, 0.0)))
    return out[0], out[1]


@dataclass
class GBuffer:
    """What the filters read from a Frame, as flat channels (:func:`gbuffer`)."""

    normal: Img
    inv_z: mi.Float  # 1/depth, 0 on background
    dzdx: mi.Float
    dzdy: mi.Float
    mesh: mi.Float
    position: Img | None = None
    roughness: mi.Float | None = None
    #: per pixel: the lobe is Beckmann (the ``distribution`` channel; ``False``: every pixel
    #: GGX, frames without that channel)
    beckmann: mi.Bool | bool = False

    @property
    def hit(self) -> mi.Bool:
        return self.mesh > 0


def finite_guides(*guides) -> mi.Bool:
    """Where every value of ``guides`` (flat channels, or lists of them; None is skipped) is
    finite: the pixels whose guides a filter may use at all."""
    ok = mi.Bool(True)
    for g in guides:
        if g is None:
            continue
        for ch in g if isinstance(g, list | tuple) else (g,):
            ok &= dr.isfinite(ch)
    return ok


def _guides(frame, with_position: bool, with_roughness: bool) -> tuple:
    """The frame's guide channels as read, ``(normal, depth, mesh id, position or None,
    roughness or None)``, and where all of them are finite (:func:`finite_guides`)."""
    normal, depth, mesh = frame.require("normal", "depth", "mesh_id")
    n, z, m = split(normal), split(depth)[0], split(mesh)[0]
    pos = split(frame["position"]) if with_position else None
    rough = split(frame["roughness"])[0] if with_roughness else None
    return n, z, m, pos, rough, finite_guides(n, z, m, pos, rough)


def beckmann_mask(frame) -> mi.Bool | bool:
    """Where the frame's ``distribution`` channel says Beckmann (``False`` without it)."""
    if "distribution" not in frame.names:
        return False
    from ..brdf.microfacet import BECKMANN

    return split(frame["distribution"])[0] == float(BECKMANN)


def gbuffer(frame, grid: Grid, with_position: bool = False,
            with_roughness: bool = False) -> GBuffer:
    """The frame's G-buffer (normal, 1/z and its gradient, mesh id; ``position`` and
    ``roughness`` when asked for). Input hygiene: a pixel with a non-finite value in any of
    the guides read here (or in ``mesh_id`` or ``depth``, where ``+inf`` is the background
    marker) gets the background's guides (docs/FORMATS.md: mesh id 0, 1/z 0, normal =
    position = 0, roughness 0), so that every filter treats it as background: it is never a
    tap nor consistent history, and its own output is its (hygienic) input colour. Selects
    only: no host synchronisation."""
    n, z, m, pos, rough, ok = _guides(frame, with_position, with_roughness)
    inv_z = dr.select(ok & (z > 0), dr.rcp(z), 0.0)
    dzdx, dzdy = depth_gradient(grid, inv_z)
    return GBuffer([dr.select(ok, c, 0.0) for c in n], inv_z, dzdx, dzdy,
                   dr.select(ok, m, 0.0),
                   None if pos is None else [dr.select(ok, c, 0.0) for c in pos],
                   None if rough is None else dr.select(ok, rough, 0.0),
                   beckmann_mask(frame) if with_roughness else False)


@dataclass
class PixelGuides:
    """The guides of the bilateral filter and the upsamplers (:func:`pixel_guides`)."""

    hit: mi.Bool
    z: mi.Float  # the depth, -1 on background
    normal: Img
    roughness: mi.Float | None = None
    beckmann: mi.Bool | bool = False  # as GBuffer.beckmann


def pixel_guides(frame, lobes: bool) -> PixelGuides:
    """A frame's hit mask, depth, normal and, with ``lobes``, roughness (the lobes' view
    directions come from the camera, :func:`pixel_view_directions`). Input hygiene: a pixel
    with a non-finite guide is background (never a tap or sample, keeps its own radiance),
    its guides those of background (docs/FORMATS.md)."""
    normal, z, mesh, _, alpha, ok = _guides(frame, False, lobes)
    hit = (mesh > 0) & (z > 0) & ok
    return PixelGuides(hit, dr.select(hit, z, -1.0), [dr.select(hit, c, 0.0) for c in normal],
                       None if alpha is None else dr.select(hit, alpha, 0.0),
                       beckmann_mask(frame) if lobes else False)


def require_camera(frame, who: str) -> None:
    """docs/FORMATS.md: consumers that reproject refuse frames without a camera."""
    if frame.camera is None:
        raise FrameError(f"{frame.where}: {who} reprojects its history with the motion "
                         "vectors and needs the camera, but the frame has no camera header")


def albedo_channel(channel: str, who: str) -> str:
    """The albedo that demodulates radiance component ``channel`` (``who`` names the caller
    in the error for anything that is not a filterable component)."""
    if channel not in RADIANCE or channel == "emission":
        raise GlossrtError(
            f"{who}: cannot use {channel!r}; choose among "
            f"{', '.join(c for c in RADIANCE if c != 'emission')}")
    return "albedo_specular" if channel.endswith("specular") else "albedo_diffuse"


def frame_jitter(frame) -> tuple[float, float]:
    """The sub-pixel offset ``meta["jitter"]`` (pixels) of the frame's primary rays, (0, 0)
    when absent; a FrameError naming the file when it is not ``[x, y]``."""
    j = (frame.meta or {}).get("jitter", (0.0, 0.0))
    try:
        jx, jy = (float(v) for v in j)
    except (TypeError, ValueError):
        raise FrameError(f"{frame.where}: meta 'jitter' must be [x, y], got {j!r}") from None
    if not (math.isfinite(jx) and math.isfinite(jy)):
        raise FrameError(f"{frame.where}: meta 'jitter' must be finite, got {j!r}")
    return jx, jy


def pixel_view_directions(frame, grid: Grid, purpose: str = "this filter") -> mi.Vector3f:
    """Per-pixel ``wo`` (world space, unit): from the surface a pixel sees towards the camera,
    i.e. its primary ray reversed, through the pixel centre plus ``meta["jitter"]``
    (:func:`frame_jitter`). The ray inverts :meth:`glossrt.frame.Camera.project`: in camera
    space it is ``(t (1 - 2 px / W), t (H - 2 py) / W, 1)``, ``t = tan(fov / 2)``, ``(px,
    py)`` the sample in the camera's ``W x H`` pixels (a frame of another size is scaled).

    For a pinhole G-buffer this is ``normalize(camera position - position)`` (tested against
    it on rendered frames) without reading ``position``: on the CPU the three strided reads
    of that channel cost more than this affine map (measured, docs/PERFORMANCE.md). The map's
    nine coefficients are opaque (a moving camera does not recompile kernels)."""
    return apply_view_coefficients(grid, view_coefficients(frame, purpose))


def view_coefficients(frame, purpose: str = "this filter") -> tuple[list, list, list]:
    """The opaque coefficients ``(a, b, c)`` of :func:`pixel_view_directions`'s affine map
    (camera-space direction ``x a + y b + c`` of pixel ``(x, y)``): computed on the host, so
    that a frozen function can take them as inputs (a recording would bake the camera in)."""
    cam = frame.camera
    if cam is None:
        raise FrameError(f"{frame.where}: {purpose} needs the camera (view directions)")
    jx, jy = frame_jitter(frame)
    cw, chh = cam.resolution
    sx, sy = cw / frame.width, chh / frame.height
    t = cam.tan_half_fov
    rot = np.asarray(cam.to_world, np.float64)[:3, :3]
    # camera-space direction of pixel (x, y): affine in x and y (Camera.project inverted)
    step_x = rot @ np.array([-2.0 * t * sx / cw, 0.0, 0.0])
    step_y = rot @ np.array([0.0, -2.0 * t * sy / cw, 0.0])
    origin = rot @ np.array([t * (1.0 - 2.0 * (0.5 + jx) * sx / cw),
                             t * (chh - 2.0 * (0.5 + jy) * sy) / cw, 1.0])
    return opaque(step_x), opaque(step_y), opaque(origin)


def apply_view_coefficients(grid: Grid, coefficients) -> mi.Vector3f:
    """Per-pixel ``wo`` from :func:`view_coefficients` (see :func:`pixel_view_directions`)."""
    a, b, c = coefficients
    x, y = mi.Float(grid.x), mi.Float(grid.y)
    d = mi.Vector3f(*(dr.fma(x, a[k], dr.fma(y, b[k], c[k])) for k in range(3)))
    return -dr.normalize(d)


# the 5-tap B3 spline kernel of the a-trous transform (Schied 2017, eq. 1)
H5 = (1.0 / 16.0, 1.0 / 4.0, 3.0 / 8.0, 1.0 / 4.0, 1.0 / 16.0)


class Packed:
    """Per-pixel channels interleaved for neighbour reads: ``Packed(chs).fetch(q)`` returns
    the channels at pixels ``q`` with one packet gather per 8 channels (and one 4-wide for a
    remainder of 4 or fewer), instead of one load per channel. ``q`` must be valid (clamped):
    masked packet gathers abort inside ``dr.freeze`` (Dr.Jit 1.5). ``arrays``: the
    interleaved arrays (to ``dr.eval`` them ahead of the kernels that read them)."""

    def __init__(self, chs: Img):
        t = type(chs[0])
        self._xf = sys.modules[t.__module__].ArrayXf
        self._parts = []  # (packet width, number of real channels)
        self.arrays = []
        for k in range(0, len(chs), 8):
            part = list(chs[k:k + 8])
            width = 8 if len(part) > 4 else 4
            self._parts.append((width, len(part)))
            self.arrays.append(interleave(part + [dr.zeros(t, dr.width(chs[0]))] *
                                          (width - len(part))))

    def fetch(self, q: mi.UInt32) -> Img:
        out = []
        for (width, real), arr in zip(self._parts, self.arrays, strict=True):
            v = dr.gather(self._xf, arr, q, shape=(width, dr.width(q)))
            out.extend(v[j] for j in range(real))
        return out


# -- the cross-bilateral filters' taps (bilateral.py, upsampling.py) -------------------------


def tap_channels(normal: Img | None, lobe: Img | None, z: mi.Float,
                 signals: list) -> tuple[Packed, int, int]:
    """What a cross-bilateral tap reads, interleaved for :class:`Packed`: ``[normal (3)]
    [lobe axis (3), sharpness] z [illumination (3) per signal]`` (the bracketed parts only
    when given). Returns the packed channels and the positions of the lobe and of z."""
    chans = list(normal) if normal is not None else []
    i_lobe = len(chans)
    if lobe is not None:
        chans += list(lobe)
    i_z = len(chans)
    chans.append(z)
    for sig in signals:
        chans += sig
    return Packed(chans), i_lobe, i_z


def tap_sharpness(lb: mi.Float, beta, approx: bool) -> mi.Float:
    """The per-pixel sharpness the filters store for :func:`lobe_tap_weight`: the smoothed
    ``lambda_bar`` for the exact weight, ``(beta / 2) lambda_bar`` for the closed form
    (:func:`~glossrt.brdf.sg.lobe_tap_terms`)."""
    return lobe_tap_sharpness(lb, beta) if approx else lb


def lobe_tap_weight(xi_p: mi.Vector3f, s_p: mi.Float, lobe_q: Img, log_w, beta,
                    approx: bool):
    """``exp(log_w)`` times Tokuyoshi 2015's lobe weight (sec. 4.2) between a pixel's lobe
    ``(xi_p, s_p)`` and a tap's ``lobe_q`` (axis (3), sharpness), sharpnesses from
    :func:`tap_sharpness`. ``approx``: the closed form through eq. 7, its ``a_g`` and
    constant joining ``log_w`` in one exponential; else the exact eq. 6."""
    xi_q = mi.Vector3f(lobe_q[0], lobe_q[1], lobe_q[2])
    if approx:
        y_pow, a_g = lobe_tap_terms(xi_p, s_p, xi_q, lobe_q[3], beta)
        return y_pow * exp_weight(lobe_tap_log_scale(beta) + log_w - a_g)
    # sharpnesses already smoothed: kappa=None
    return exp_weight(log_w) * lobe_weight(xi_p, s_p, xi_q, lobe_q[3], beta, None, False)
