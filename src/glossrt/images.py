"""Images as Dr.Jit channel lists, one lane per pixel: what the screen-space filters
(:mod:`glossrt.denoise`) and the shading techniques (:mod:`glossrt.lights`,
:mod:`glossrt.specaa`) share.

An image is structure-of-arrays: one flat ``mi.Float`` of H*W values per channel (``Img`` =
list of channels), row-major, row 0 on top.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass

import drjit as dr

from .backend import mi
from .errors import FrameError, GlossrtError
from .frame import Frame
from .jit import opaque

__all__ = ["LUM", "Grid", "Img", "check_frame", "fetch", "interleave", "luminance", "merge",
           "split", "view_directions"]

#: Rec. 709 luminance weights (linear RGB)
LUM = (0.2126, 0.7152, 0.0722)

Img = list  # list[mi.Float], one flat array per channel


@dataclass
class Grid:
    """Pixel coordinates of a W x H image, one lane per pixel (row-major, row 0 on top)."""

    w: int
    h: int

    def __post_init__(self):
        self.idx = dr.arange(mi.UInt32, self.w * self.h)
        self.x = mi.Int32(self.idx % self.w)
        self.y = mi.Int32(self.idx // self.w)

    def index(self, x: mi.Int32, y: mi.Int32) -> mi.UInt32:
        """Flat index of (x, y) clamped to the image."""
        xc = dr.clip(x, 0, self.w - 1)
        yc = dr.clip(y, 0, self.h - 1)
        return mi.UInt32(yc * self.w + xc)

    def inside(self, x: mi.Int32, y: mi.Int32) -> mi.Bool:
        return (x >= 0) & (x < self.w) & (y >= 0) & (y < self.h)


def split(t: mi.TensorXf, index: mi.UInt32 | None = None) -> Img:
    """(H, W, C) tensor -> C flat channels: every pixel's, or those of the flat pixel
    indices ``index``."""
    h, w, c = t.shape
    idx = (dr.arange(mi.UInt32, h * w) if index is None else index) * c
    return [dr.gather(mi.Float, t.array, idx + k) for k in range(c)]


def interleave(chs: Img):
    """C flat channels -> one flat array ``[c0[0], c1[0], .., c0[1], ..]``, in one kernel.
    (One ``dr.scatter`` per channel would launch a kernel per channel, each evaluating the
    channels' whole unevaluated expression again.)"""
    t = type(chs[0])
    return dr.ravel(sys.modules[t.__module__].ArrayXf([t(ch) for ch in chs]))


def merge(chs: Img, h: int, w: int) -> mi.TensorXf:
    """C flat channels -> (H, W, C) tensor (:func:`interleave`)."""
    return mi.TensorXf(interleave(chs), (h, w, len(chs)))


def fetch(chs: Img, index: mi.UInt32, active=True) -> Img:
    return [dr.gather(mi.Float, ch, index, active) for ch in chs]


def luminance(rgb: Img) -> mi.Float:
    return LUM[0] * rgb[0] + LUM[1] * rgb[1] + LUM[2] * rgb[2]


def view_directions(frame, position, purpose: str = "this filter") -> mi.Vector3f:
    """Per-pixel ``wo = normalize(camera position - position)`` (world space), the camera
    position opaque (a moving camera does not recompile kernels)."""
    if frame.camera is None:
        raise FrameError(f"{frame.where}: {purpose} needs the camera (view directions)")
    c = opaque(frame.camera.position)
    return dr.normalize(mi.Vector3f(c[0] - position[0], c[1] - position[1], c[2] - position[2]))


def check_frame(frame, names) -> None:
    """Raise FrameError unless all ``names`` exist (naming file and channel)."""
    if not isinstance(frame, Frame):
        raise GlossrtError(
            f"a glossrt.Frame (from Renderer.render or Frame.load) is needed, "
            f"not {type(frame).__name__}"
        )
    frame.require(*names)
    h, w = frame.height, frame.width
    for n in names:
        if tuple(frame[n].shape[:2]) != (h, w):
            raise FrameError(f"{frame.where}: channel {n!r} has size {frame[n].shape[:2]}, "
                             f"expected {(h, w)}")


#: pixels per row tile of the frozen full-resolution passes that run in tiles (the G-buffer
#: trace, glossrt.render; the spatio-temporal upsampler, glossrt.denoise.upsampling): 2^18,
#: so 320x180 and 640x360 run untiled, 1920x1080 in 8 tiles (docs/PERFORMANCE.md, memory)
TILE_PIXELS = 1 << 18


def tile_rows(width: int, height: int, pixels: int = TILE_PIXELS) -> int:
    """Rows per tile of a ``width x height`` image (``height``: untiled)."""
    return int(min(height, max(1, pixels // max(width, 1))))


def tile_starts(height: int, rows: int) -> list[int]:
    """First row of each tile; the last tile ends at the last row (equal shapes)."""
    return [min(r, height - rows) for r in range(0, height, rows)]
