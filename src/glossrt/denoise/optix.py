"""The OptiX AI denoiser (through Mitsuba's ``mi.OptixDenoiser``): GPU baseline, temporal mode.

:class:`OptixTemporal` is a per-sequence denoiser with the interface of glossrt's other
denoisers (``__call__(frame) -> mi.TensorXf`` and ``reset()``). It needs the ``cuda_ad_rgb``
variant: Mitsuba only builds ``OptixDenoiser`` for CUDA, and constructing an
:class:`OptixTemporal` on the CPU (LLVM) variant raises :class:`GlossrtError`.

How glossrt's channels map onto Mitsuba's wrapper (``src/render/optixdenoiser.cpp``, 3.9)::

    denoiser = mi.OptixDenoiser(mi.ScalarVector2u(W, H), albedo=True, normals=True,
                                temporal=True)
    out = denoiser(noisy, albedo=..., normals=..., to_sensor=..., flow=...,
                   previous_denoised=...)       # all (H, W, C) TensorXf, C = 3 or 2

* ``noisy``: the linear ``color`` (OptiX HDR model; Mitsuba computes the HDR intensity).
  As in :func:`glossrt.denoise.oidn.oidn_denoise`, the noise-free first-hit ``emission`` is
  taken out before denoising and added back afterwards (``separate_emission``), so that
  emitters seen directly (albedo 0, large radiance) are not smeared by the network.
* ``albedo``: ``albedo_diffuse + albedo_specular`` clamped to [0, 1].
* ``normals``: the world-space ``normal`` channel with ``to_sensor`` = the camera's
  world-to-camera transform (:attr:`glossrt.frame.Camera.world_to_camera`, the inverse of the
  sensor's ``to_world``). Mitsuba applies ``to_sensor`` to the normals and then negates X and Z,
  turning Mitsuba's camera frame (X left, Y up, Z forward) into the one OptiX expects for its
  normal guide (X right, Y up, Z towards the viewer). Without ``to_sensor`` the world normals
  would be passed through unchanged, which is wrong for OptiX.
* ``flow``: OptiX defines the flow guide as the "pixel flow from previous to current frame for
  each pixel" (``OptixDenoiserGuideLayer::flow`` in ``optix_types.h``), in pixels: the point
  shown at pixel ``p`` now was at ``p - flow`` in the previous frame. glossrt's ``motion``
  points the other way (``p + motion`` is where it was, docs/FORMATS.md), so ``flow = -motion``
  for both components. Both images use the same row order (row 0 first in memory, y growing
  with the row index), so no y flip is needed. Blender Cycles makes the same conversion: its
  motion pass stores ``previous - current`` and it hands OptiX ``-motion``.
* ``previous_denoised``: this object's previous output (before the emission is added back);
  on the first frame of a sequence, after :meth:`OptixTemporal.reset`, or when the frame has no
  ``prev_camera``, the noisy input itself, as the OptiX documentation recommends.

When OptiX cannot build its temporal model, or with ``temporal=False``, the denoiser runs in
its spatial (per-frame) HDR mode with albedo and normals; :attr:`OptixTemporal.temporal`
says which mode is in use.
"""

from __future__ import annotations

import warnings
from typing import TYPE_CHECKING, Any

from .. import backend
from ..errors import FrameError, GlossrtError

if TYPE_CHECKING:  # pragma: no cover - typing only
    import mitsuba as mi

    from ..frame import Frame

__all__ = ["OptixTemporal", "optix_available"]

_NEEDS_CUDA = "OptiX needs the cuda_ad_rgb variant (a NVIDIA GPU)"


def optix_available() -> bool:
    """True when glossrt runs on the CUDA variant and Mitsuba has ``OptixDenoiser``."""
    if backend.ensure() != backend.GPU_VARIANT:
        return False
    import mitsuba

    return hasattr(mitsuba, "OptixDenoiser")


def _count_nonfinite(t: Any) -> int:
    import drjit as dr

    return int(dr.count(~dr.isfinite(t.array))[0])


class OptixTemporal:
    """OptiX AI denoiser over a frame sequence (temporal when available, else per frame).

    Args:
        temporal: ask for OptiX's temporal model (falls back to the spatial HDR model, with a
            warning, when OptiX cannot create it).
        separate_emission: denoise ``color - emission`` and add ``emission`` back when the
            frame has an ``emission`` channel.

    Raises:
        GlossrtError: on the CPU variant (``"OptiX needs the cuda_ad_rgb variant (a NVIDIA
            GPU)"``) or when Mitsuba cannot create the denoiser.
    """

    def __init__(self, temporal: bool = True, separate_emission: bool = True) -> None:
        if not optix_available():
            raise GlossrtError(_NEEDS_CUDA)
        self.requested_temporal = bool(temporal)
        self.separate_emission = bool(separate_emission)
        #: Whether the current denoiser runs OptiX's temporal model (set on the first frame).
        self.temporal = self.requested_temporal
        self._denoiser: Any = None
        self._size: tuple[int, int] | None = None
        self._prev: mi.TensorXf | None = None

    def reset(self) -> None:
        """Forget the previous output: the next frame starts a new sequence."""
        self._prev = None

    def _make(self, size: tuple[int, int]) -> None:
        import mitsuba

        res = mitsuba.ScalarVector2u(*size)
        self._denoiser = None
        if self.requested_temporal:
            try:
                self._denoiser = mitsuba.OptixDenoiser(
                    res, albedo=True, normals=True, temporal=True
                )
                self.temporal = True
            except Exception as e:  # pragma: no cover - needs an OptiX without temporal
                warnings.warn(
                    f"OptiX temporal denoising is unavailable ({e}); using the per-frame model",
                    RuntimeWarning,
                    stacklevel=3,
                )
        if self._denoiser is None:
            try:
                self._denoiser = mitsuba.OptixDenoiser(
                    res, albedo=True, normals=True, temporal=False
                )
            except Exception as e:
                raise GlossrtError(f"could not create the OptiX denoiser: {e}") from e
            self.temporal = False
        self._size = size
        self._prev = None

    def __call__(self, frame: Frame) -> mi.TensorXf:
        """Denoise ``frame`` (needs ``color``, ``albedo_diffuse``, ``albedo_specular``,
        ``normal``, plus ``motion`` in temporal mode, and the ``camera`` header) and return
        the (H, W, 3) linear result."""
        import drjit as dr
        import mitsuba

        frame.require("color", "albedo_diffuse", "albedo_specular", "normal")
        if frame.camera is None:
            raise FrameError(
                f"{frame.where} has no camera header, which OptiX needs to put the normals "
                "in camera space"
            )
        size = (frame.width, frame.height)
        if size != self._size:
            self._make(size)
        if self.temporal:
            frame.require("motion")

        color = frame["color"]
        bad = _count_nonfinite(color)
        if bad:
            raise GlossrtError(
                f"{frame.where}: channel 'color' has {bad} NaN or Inf value(s); the OptiX "
                "denoiser needs finite input"
            )
        emission = None
        if self.separate_emission and "emission" in frame:
            emission = frame["emission"]
            color = dr.maximum(color - emission, 0.0)
        albedo = dr.clip(frame["albedo_diffuse"] + frame["albedo_specular"], 0.0, 1.0)
        normals = frame["normal"]
        to_sensor = mitsuba.AffineTransform4f(frame.camera.world_to_camera)

        if self.temporal:
            # OptiX flow = motion from the previous to the current frame = -glossrt motion.
            flow = -frame["motion"]
            first = self._prev is None or frame.prev_camera is None
            previous = color if first else self._prev
            out = self._denoiser(
                color,
                albedo=albedo,
                normals=normals,
                to_sensor=to_sensor,
                flow=flow,
                previous_denoised=previous,
            )
            self._prev = out
        else:
            out = self._denoiser(color, albedo=albedo, normals=normals, to_sensor=to_sensor)
        if emission is not None:
            out = out + emission
        return out
