"""Image error metrics for linear-radiance renderings.

Every metric takes images as ``mi.TensorXf`` or NumPy arrays of shape (H, W, C) (a 2-D array
is read as one channel; a glossrt ``Frame`` is read as its ``"color"`` channel), checks that
the two shapes agree and that all values are finite, and returns a Python ``float``:

* :func:`rmse` -- root mean squared error over all pixels and channels.
* :func:`relmse` -- relative MSE, mean of ``(x - r)^2 / (r^2 + eps)`` over pixels and channels.
* :func:`ssim` -- SSIM (scikit-image) of the *displayed* images: radiance clamped to [0, 1],
  sRGB-encoded, compared per colour channel and averaged.
* :func:`flip` -- mean HDR-FLIP (NVIDIA ``flip_evaluator``) of the linear images.
* :func:`temporal_error` -- mean absolute luminance change between consecutive frames.
* :func:`flicker` -- the part of a sequence's frame-to-frame luminance change that its
  reference sequence does not have.

Metrics convert to NumPy (float64) internally; :func:`luminance` keeps the input's type.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from .errors import GlossrtError

__all__ = [
    "LUMINANCE_WEIGHTS",
    "as_array",
    "luminance",
    "srgb_encode",
    "rmse",
    "relmse",
    "ssim",
    "flip",
    "temporal_error",
    "flicker",
]

#: Rec. 709 / linear sRGB luminance weights (R, G, B).
LUMINANCE_WEIGHTS = (0.2126, 0.7152, 0.0722)

# HDR-FLIP derives its exposure range from the reference's luminance and aborts the whole
# process (not an exception) when the reference's maximum luminance is ~0; below this
# threshold the range is taken from the test image instead (see :func:`flip`).
_FLIP_BLACK = 1e-6


def _is_frame(obj: Any) -> bool:
    return hasattr(obj, "meta") and hasattr(obj, "index") and callable(getattr(obj, "numpy", None))


def as_array(img: Any, name: str = "image", check_finite: bool = True) -> np.ndarray:
    """``img`` as a float64 NumPy array of shape (H, W, C).

    Accepts a Dr.Jit/Mitsuba tensor, anything ``np.asarray`` understands, or a glossrt
    ``Frame`` (its ``"color"`` channel). A 2-D input gets a trailing channel axis. Raises
    :class:`GlossrtError` for another number of dimensions, an empty image, or (when
    ``check_finite``) NaN/Inf values, saying how many there are.
    """
    if _is_frame(img):
        arr = img.numpy("color")
    elif not isinstance(img, np.ndarray) and callable(getattr(img, "numpy", None)):
        arr = img.numpy()
    else:
        arr = np.asarray(img)
    arr = np.asarray(arr, dtype=np.float64)
    if arr.ndim == 2:
        arr = arr[:, :, None]
    if arr.ndim != 3:
        raise GlossrtError(f"{name} must have shape (H, W, C), got {arr.shape}")
    if arr.size == 0:
        raise GlossrtError(f"{name} is empty (shape {arr.shape})")
    if check_finite:
        bad = int(arr.size - np.count_nonzero(np.isfinite(arr)))
        if bad:
            raise GlossrtError(
                f"{name} contains {bad} NaN/Inf value(s) out of {arr.size} (shape {arr.shape})"
            )
    return arr


def _pair(img: Any, ref: Any) -> tuple[np.ndarray, np.ndarray]:
    x = as_array(img, "image")
    r = as_array(ref, "reference")
    if x.shape != r.shape:
        raise GlossrtError(
            f"image and reference differ in size: image {x.shape} vs reference {r.shape}"
        )
    return x, r


def _rgb(a: np.ndarray, what: str) -> np.ndarray:
    """First three channels; a single channel is repeated to grey."""
    c = a.shape[2]
    if c == 1:
        return np.repeat(a, 3, axis=2)
    if c >= 3:
        return a[:, :, :3]
    raise GlossrtError(f"{what} needs 1, 3 or 4 channels, got {c}")


def luminance(img: Any) -> Any:
    """Rec. 709 luminance ``0.2126 R + 0.7152 G + 0.0722 B`` of a linear image, shape (H, W).

    A Dr.Jit tensor gives a Dr.Jit tensor, anything else a NumPy array. A one-channel image
    is its own luminance; extra channels after RGB (alpha) are ignored.
    """
    import drjit as dr

    if dr.is_tensor_v(img):
        if len(img.shape) != 3:
            raise GlossrtError(f"luminance needs shape (H, W, C), got {tuple(img.shape)}")
        c = img.shape[2]
        if c == 1:
            return img[:, :, 0]
        if c < 3:
            raise GlossrtError(f"luminance needs 1, 3 or 4 channels, got {c}")
        wr, wg, wb = LUMINANCE_WEIGHTS
        return wr * img[:, :, 0] + wg * img[:, :, 1] + wb * img[:, :, 2]
    a = as_array(img, "image", check_finite=False)
    if a.shape[2] == 1:
        return a[:, :, 0]
    return _rgb(a, "luminance") @ np.asarray(LUMINANCE_WEIGHTS)


def srgb_encode(x: np.ndarray) -> np.ndarray:
    """sRGB transfer function (IEC 61966-2-1) of linear values, clamped to [0, 1] first."""
    x = np.clip(np.asarray(x, dtype=np.float64), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055)


def rmse(img: Any, ref: Any) -> float:
    """Root mean squared error ``sqrt(mean((x - r)^2))`` over all pixels and channels."""
    x, r = _pair(img, ref)
    return float(np.sqrt(np.mean((x - r) ** 2)))


def relmse(img: Any, ref: Any, eps: float = 1e-2) -> float:
    """Relative MSE ``mean((x - r)^2 / (r^2 + eps))`` over all pixels and channels.

    Every channel has the same number of pixels, so this equals the average of the
    per-channel means. ``eps`` keeps dark reference pixels from dominating.
    """
    if not eps > 0:
        raise GlossrtError(f"relmse eps must be > 0, got {eps}")
    x, r = _pair(img, ref)
    return float(np.mean((x - r) ** 2 / (r**2 + eps)))


def ssim(img: Any, ref: Any) -> float:
    """Mean structural similarity of the images as displayed (1 = identical).

    Both images are clamped to [0, 1], sRGB-encoded (:func:`srgb_encode`) and compared with
    ``skimage.metrics.structural_similarity(..., data_range=1.0, channel_axis=-1)``: the
    default 7x7 uniform window, computed per channel (RGB, or the single channel) and
    averaged. Images smaller than 7 pixels use the largest odd window that fits (at least 3).
    """
    from skimage.metrics import structural_similarity

    x, r = _pair(img, ref)
    if x.shape[2] >= 3:
        x, r = x[:, :, :3], r[:, :, :3]
    side = min(x.shape[0], x.shape[1])
    win = min(7, side if side % 2 else side - 1)
    if win < 3:
        raise GlossrtError(f"ssim needs images of at least 3x3 pixels, got {x.shape}")
    return float(
        structural_similarity(
            srgb_encode(x), srgb_encode(r), data_range=1.0, channel_axis=-1, win_size=win
        )
    )


def flip(img: Any, ref: Any) -> float:
    """Mean HDR-FLIP error of ``img`` against ``ref`` (0 = identical, at most 1).

    Uses ``flip_evaluator.evaluate(ref, img, "HDR")`` with FLIP's defaults (67 pixels per
    degree, ACES tone mapper, exposure range from the reference's luminance). Inputs are
    linear RGB: negative values are clamped to 0 (HDR-FLIP requires non-negative input) and
    a one-channel image is repeated to grey. If the reference is black (max luminance below
    1e-6, where FLIP would abort the process) the exposure range comes from the test image;
    if both are black the error is 0.
    """
    import flip_evaluator

    x, r = _pair(img, ref)
    x = np.ascontiguousarray(np.maximum(_rgb(x, "flip"), 0.0), dtype=np.float32)
    r = np.ascontiguousarray(np.maximum(_rgb(r, "flip"), 0.0), dtype=np.float32)
    params: dict[str, Any] = {}
    if float(luminance(r).max()) < _FLIP_BLACK:
        if float(luminance(x).max()) < _FLIP_BLACK:
            return 0.0
        _, _, used = flip_evaluator.evaluate(x, x, "HDR", applyMagma=False)
        params = {k: used[k] for k in ("startExposure", "stopExposure", "numExposures")}
    _, mean, _ = flip_evaluator.evaluate(r, x, "HDR", applyMagma=False, parameters=params)
    return float(mean)


def temporal_error(frames: Sequence[Any]) -> float:
    """Mean absolute luminance difference between consecutive frames.

    ``(1 / (N - 1)) * sum_t mean_pixels |L_t - L_{t-1}|`` with Rec. 709 luminance ``L``; 0 for
    a static image sequence, larger for flicker. Needs at least two frames of one size.
    """
    # Temporal stability measure of Schied et al. 2017, "Spatiotemporal Variance-Guided
    # Filtering: Real-Time Reconstruction for Path-Traced Global Illumination", HPG 2017,
    # Sec. 5.4: the average luminance of the difference between consecutive frames.
    if len(frames) < 2:
        raise GlossrtError(f"temporal_error needs at least 2 frames, got {len(frames)}")
    prev: np.ndarray | None = None
    total = 0.0
    for i, f in enumerate(frames):
        lum = luminance(as_array(f, f"frame {i}"))
        if prev is not None:
            if lum.shape != prev.shape:
                raise GlossrtError(
                    f"frame {i} has size {lum.shape}, frame {i - 1} has size {prev.shape}"
                )
            total += float(np.mean(np.abs(lum - prev)))
        prev = lum
    return total / (len(frames) - 1)


def flicker(frames: Sequence[Any], refs: Sequence[Any]) -> float:
    """The part of ``frames``' frame-to-frame luminance change that ``refs`` (one reference
    per frame) does not have: ``mean_t mean_pixels |(L_t - L_{t-1}) - (R_t - R_{t-1})|``
    (luminance ``L`` of the frames, ``R`` of the references); with one constant reference it
    is :func:`temporal_error`. Needs two or more frames."""
    if len(frames) != len(refs) or len(frames) < 2:
        raise GlossrtError("flicker needs two or more frames and one reference per frame")
    d = [luminance(np.asarray(f)) - luminance(np.asarray(r))
         for f, r in zip(frames, refs, strict=True)]
    return float(np.mean([np.mean(np.abs(d[t] - d[t - 1])) for t in range(1, len(d))]))
