"""Intel Open Image Denoise (OIDN) on one glossrt frame: the single-frame CPU baseline.

:func:`oidn_denoise` runs OIDN's ``RT`` filter (``hdr=True``) on a frame's linear ``color``,
guided by the auxiliary features OIDN was trained with:

* ``albedo`` = ``albedo_diffuse + albedo_specular``, clamped to [0, 1] (OIDN wants albedo in
  [0, 1]; for glossy and metallic surfaces it asks for the specular reflectance, which is what
  ``albedo_specular`` holds, so the sum is the total first-hit reflectance);
* ``normal`` = the frame's world-space shading normal (OIDN accepts world- or view-space
  normals of any length with components in [-1, 1]; glossrt's normals are unit vectors and 0 on
  the background, which OIDN also accepts).

OIDN supports colour only, colour + albedo, or colour + albedo + normal (never normal without
albedo); ``use_aux=False`` gives colour only.

**Directly visible emitters.** OIDN smears emitters seen at the first hit: their albedo is 0
while their radiance is large, which its network does not expect (on ``glossy-cornell`` at
64x48 the ceiling light, radiance 12, came out between 1.5 and 19.5, and the image's RMSE
against a 256-spp reference *rose* from 0.250 at 1 spp to 0.275). glossrt frames carry the
emitted radiance of the first hit as its own ``emission`` channel, which has no Monte Carlo
noise, so by default (``separate_emission=True``, when that channel is present) OIDN filters
``color - emission`` and the emission is added back afterwards (RMSE 0.084 on that frame).

Uses the ``pyoidn`` package (OIDN 2.x C API through cffi): ``pyoidn.Device()`` (CPU),
``device.commit()``, ``pyoidn.Filter(device, "RT")``, ``filter.set_image(name, ndarray,
OIDN_FORMAT_FLOAT3)`` (shares the NumPy array's memory with OIDN), ``filter.set_bool("hdr",
True)``, ``filter.set_int("quality", ...)``, ``filter.commit()``, ``filter.execute()`` and
``device.get_error()``. The device, the filter and the shared image arrays are cached per
(width, height, quality, use_aux) so that repeated calls only copy pixels in and out and run the
network; this cache is private and :func:`oidn_denoise` behaves as a pure function.

>>> out = oidn_denoise(frame, quality="balanced")       # doctest: +SKIP
>>> out.shape                                           # doctest: +SKIP
(720, 1280, 3)
"""

from __future__ import annotations

import atexit
import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from ..backend import mi
from ..errors import GlossrtError

if TYPE_CHECKING:  # pragma: no cover - typing only
    from ..frame import Frame

__all__ = ["QUALITIES", "oidn_available", "oidn_denoise"]

#: OIDN quality modes (``OIDN_QUALITY_*`` values of the OIDN 2 C API).
QUALITIES: dict[str, int] = {"default": 0, "fast": 4, "balanced": 5, "high": 6}

_OIDN_FORMAT_FLOAT3 = 3  # OIDN_FORMAT_FLOAT3
_MAX_CACHED = 4  # filters kept alive (one per image size / mode); oldest dropped first


def oidn_available() -> bool:
    """True when ``pyoidn`` imports and OIDN's CPU device works on this machine."""
    try:
        import pyoidn
    except Exception:
        return False
    try:
        return bool(pyoidn.Device.is_cpu_available())
    except Exception:
        return False


@dataclass
class _Slot:
    """An OIDN device + committed RT filter bound to NumPy arrays of one size."""

    device: Any
    filter: Any
    color: np.ndarray
    albedo: np.ndarray | None
    normal: np.ndarray | None
    output: np.ndarray

    def release(self) -> None:
        try:
            self.filter.release()
        finally:
            self.device.release()


_lock = threading.Lock()
_slots: dict[tuple[int, int, int, bool], _Slot] = {}


def _check(device: Any, what: str) -> None:
    """Raise GlossrtError when OIDN reported an error since the last check."""
    err = device.get_error()
    if err is not None:
        raise GlossrtError(f"Open Image Denoise failed during {what}: {err}")


def _make_slot(width: int, height: int, quality: int, use_aux: bool) -> _Slot:
    import pyoidn

    device = pyoidn.Device(pyoidn.OIDN_DEVICE_TYPE_CPU)
    try:
        _check(device, "device creation")
        device.commit()
        _check(device, "device commit")
        flt = pyoidn.Filter(device, pyoidn.OIDN_FILTER_TYPE_RT)
        _check(device, "filter creation")
    except BaseException:
        device.release()
        raise

    def image() -> np.ndarray:
        return np.zeros((height, width, 3), dtype=np.float32)

    slot = _Slot(
        device, flt, image(), image() if use_aux else None, image() if use_aux else None, image()
    )
    try:
        flt.set_image(pyoidn.OIDN_IMAGE_COLOR, slot.color, _OIDN_FORMAT_FLOAT3)
        if use_aux:
            flt.set_image(pyoidn.OIDN_IMAGE_ALBEDO, slot.albedo, _OIDN_FORMAT_FLOAT3)
            flt.set_image(pyoidn.OIDN_IMAGE_NORMAL, slot.normal, _OIDN_FORMAT_FLOAT3)
        flt.set_image(pyoidn.OIDN_IMAGE_OUTPUT, slot.output, _OIDN_FORMAT_FLOAT3)
        flt.set_bool("hdr", True)
        flt.set_bool("cleanAux", False)  # 1-spp aux features are (mildly) noisy at edges
        flt.set_int("quality", quality)
        _check(device, "filter set-up")
        flt.commit()
        _check(device, "filter commit")
    except BaseException:
        slot.release()
        raise
    return slot


def _slot(width: int, height: int, quality: int, use_aux: bool) -> _Slot:
    """The cached filter for this size and mode (caller holds ``_lock``)."""
    key = (width, height, quality, use_aux)
    slot = _slots.pop(key, None)
    if slot is None:
        slot = _make_slot(width, height, quality, use_aux)
        while len(_slots) >= _MAX_CACHED:
            _slots.pop(next(iter(_slots))).release()
    _slots[key] = slot  # re-insert: most recently used last
    return slot


@atexit.register
def _release_all() -> None:
    """Release the cached OIDN objects (filters before their devices) at exit."""
    with _lock:
        while _slots:
            _slots.popitem()[1].release()


def _finite(a: np.ndarray, name: str, where: str) -> None:
    bad = ~np.isfinite(a)
    if bad.any():
        n = int(np.count_nonzero(bad.any(axis=-1)))
        raise GlossrtError(
            f"{where}: channel {name!r} has {n} pixel(s) with NaN or Inf values; "
            "Open Image Denoise needs finite input"
        )


def oidn_denoise(
    frame: Frame, quality: str = "high", use_aux: bool = True, separate_emission: bool = True,
    timings: dict | None = None,
) -> mi.TensorXf:
    """Denoise ``frame``'s ``color`` with OIDN's ``RT`` filter and return it as (H, W, 3).

    Args:
        frame: needs ``color``; with ``use_aux`` also ``albedo_diffuse``, ``albedo_specular``
            and ``normal`` (FrameError naming the missing channels and the file otherwise).
        quality: ``"high"`` (best, slowest), ``"balanced"``, ``"fast"`` or ``"default"``
            (OIDN's default, currently ``high``).
        use_aux: guide the filter with albedo and normal (recommended); False denoises the
            colour alone.
        separate_emission: when the frame has an ``emission`` channel, denoise
            ``color - emission`` and add ``emission`` back (see the module notes); frames without
            that channel are denoised as they are.
        timings: a dict to which ``oidn_ms`` (added to what it holds) is the host time of
            everything after the colour is read back: the NumPy checks and copies and the
            filter, not the wait for the Dr.Jit work that makes the inputs (the pipeline adds
            it to the stage's kernel time, ``timing.StageClock``).

    Returns:
        A new float32 :class:`mitsuba.TensorXf` of shape ``(H, W, 3)``: linear radiance.

    Raises:
        GlossrtError: unknown ``quality``, NaN/Inf in the inputs (with the number of bad
            pixels), pyoidn missing, or an OIDN error. FrameError for missing channels.

    Negative colour values (which OIDN's HDR mode does not accept) are clamped to 0. The
    function keeps no state between calls except a private cache of OIDN objects.
    """
    if quality not in QUALITIES:
        raise GlossrtError(
            f"unknown OIDN quality {quality!r}; choose one of {', '.join(QUALITIES)}"
        )
    if not oidn_available():
        raise GlossrtError(
            "Open Image Denoise is not available: install the 'pyoidn' package "
            "(pip install pyoidn) on a machine with a supported CPU"
        )
    names = ("color", "albedo_diffuse", "albedo_specular", "normal") if use_aux else ("color",)
    frame.require(*names)
    where = frame.where
    h, w = frame.height, frame.width

    color = frame.numpy("color")  # (waits for the Dr.Jit work that makes the inputs)
    t0 = time.perf_counter()
    _finite(color, "color", where)
    emission = None
    if separate_emission and "emission" in frame:
        emission = frame.numpy("emission")
        _finite(emission, "emission", where)
        color -= emission
    np.maximum(color, 0.0, out=color)
    if use_aux:
        albedo = frame.numpy("albedo_diffuse") + frame.numpy("albedo_specular")
        _finite(albedo, "albedo_diffuse + albedo_specular", where)
        np.clip(albedo, 0.0, 1.0, out=albedo)
        normal = frame.numpy("normal")
        _finite(normal, "normal", where)
        np.clip(normal, -1.0, 1.0, out=normal)

    with _lock:
        slot = _slot(w, h, QUALITIES[quality], use_aux)
        slot.color[...] = color
        if use_aux:
            slot.albedo[...] = albedo
            slot.normal[...] = normal
        slot.filter.execute()
        try:
            _check(slot.device, "filtering")
        except GlossrtError:
            _slots.pop((w, h, QUALITIES[quality], use_aux), None)
            slot.release()
            raise
        out = slot.output.copy()
    if emission is not None:
        out += emission
    if timings is not None:
        timings["oidn_ms"] = timings.get("oidn_ms", 0.0) + 1000.0 * (time.perf_counter() - t0)
    return mi.TensorXf(out)
