"""What the viewer can show, as 8-bit images (issue 26): the composed frame, each stage's
layer, any G-buffer or radiance channel, the progressive reference and an error map.

Radiance layers go through the pipeline's display transform (exposure, then the sRGB or
filmic tonemap). The others are visualised for a person, not measured: normals and
tangents as ``0.5 + 0.5 v``; depth and positions normalised over the finite values of the
image; roughness, alpha and distribution as grey levels in [0, 1]; mesh ids as distinct
hues; motion as ``0.5 + v / 16`` pixels in red and green.
"""

from __future__ import annotations

import numpy as np

#: layers in linear radiance (shown through exposure and tonemap)
RADIANCE = ("color", "composite", "direct", "indirect", "emission", "direct_diffuse",
            "direct_specular", "indirect_diffuse", "indirect_specular", "reference")
#: layers the viewer adds to a frame's own
EXTRA = ("reference", "error")


def names(frame_names) -> list[str]:
    """The layers of a frame with ``frame_names`` channels, the composed ones first, then the
    reference and error map, then the rest in the frame's order."""
    first = [n for n in ("color", "composite", "direct", "indirect") if n in frame_names]
    rest = [n for n in frame_names if n not in first]
    return first + list(EXTRA) + rest


def _u8(x: np.ndarray) -> np.ndarray:
    """Values in [0, 1] (clamped) as 8 bits, linearly."""
    return np.round(np.clip(x, 0.0, 1.0) * 255.0).astype(np.uint8)


def _rgb(x: np.ndarray) -> np.ndarray:
    if x.ndim == 2:
        x = x[..., None]
    if x.shape[-1] == 1:
        return np.repeat(x, 3, axis=-1)
    if x.shape[-1] == 2:
        return np.concatenate([x, np.zeros_like(x[..., :1])], axis=-1)
    return x[..., :3]


def _normalised(x: np.ndarray) -> np.ndarray:
    finite = np.isfinite(x)
    if not finite.any():
        return np.zeros_like(x)
    lo, hi = float(x[finite].min()), float(x[finite].max())
    y = (x - lo) / (hi - lo) if hi > lo else np.zeros_like(x)
    return np.where(finite, y, 0.0)


def _hues(ids: np.ndarray) -> np.ndarray:
    """A distinct colour per integer id (0, background, black)."""
    i = np.asarray(ids, np.int64)
    golden = ((i * 0.6180339887) % 1.0)[..., None]
    base = 0.5 + 0.5 * np.cos(2.0 * np.pi * (golden + np.array([0.0, 1.0 / 3.0, 2.0 / 3.0])))
    return np.where((i > 0)[..., None], base, 0.0)


def visualise(name: str, data: np.ndarray, exposure: float = 0.0,
              tonemap: str = "filmic") -> np.ndarray:
    """(H, W, 3) ``uint8`` of layer ``name`` whose values are ``data`` (H, W, C)."""
    from ..pipeline import display

    x = np.asarray(data, np.float64)
    if name in RADIANCE or name.startswith(("direct_", "indirect_")):
        return display(_rgb(x), exposure, tonemap)
    if name in ("normal", "tangent"):
        return _u8(0.5 + 0.5 * _rgb(x))
    if name == "mesh_id":
        return _u8(_hues(_rgb(x)[..., 0]))
    if name == "motion":
        m = _rgb(x)
        m[..., :2] = 0.5 + m[..., :2] / 16.0
        return _u8(m)
    if name in ("depth", "position"):
        return _u8(_rgb(_normalised(x)))
    if name.startswith("albedo"):
        return display(_rgb(x), 0.0, "srgb")  # reflectances: sRGB-encoded, no tonemap
    return _u8(np.nan_to_num(_rgb(x)))


def error_map(image: np.ndarray, reference: np.ndarray, scale: float = 0.25) -> np.ndarray:
    """(H, W, 3) ``uint8``: the per-pixel RMSE over RGB of ``image`` against ``reference``,
    divided by ``scale`` and shown with Matplotlib's ``magma`` colour map (black: no error,
    white: ``scale`` or more)."""
    from matplotlib import colormaps

    a = np.nan_to_num(np.asarray(image, np.float64)[..., :3])
    b = np.nan_to_num(np.asarray(reference, np.float64)[..., :3])
    e = np.sqrt(np.mean((a - b) ** 2, axis=-1)) / float(scale)
    rgba = colormaps["magma"](np.clip(e, 0.0, 1.0))
    return np.round(rgba[..., :3] * 255.0).astype(np.uint8)
