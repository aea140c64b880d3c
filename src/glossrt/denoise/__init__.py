"""Denoisers: SVGF (Schied 2017), its baselines, and the tools a user would pick instead.

Every method is available as a per-sequence callable through :func:`make`:
``d = make("svgf"); for f in frames: img = d(f)`` (``d.reset()`` between sequences).
"""

from __future__ import annotations

from ..errors import GlossrtError
from .bilateral import bilateral  # the function; the module stays importable
from .svgf import SVGF, ATrousTemporal, SVGFParams, atrous_filter, taa, taa_jitter
from .upsampling import (  # module glossrt.denoise.upsampling
    SpatioTemporalUpsampler,
    adaptive_resample,
    jitter_sequence,
    upsample,
)

METHODS = ("svgf", "svgf-lobe", "svgf-spatial-variance", "atrous", "atrous-temporal", "oidn",
           "optix")


class _PerFrame:
    """A stateless per-frame denoiser with the same interface as the stateful ones."""

    def __init__(self, fn, needs=()):
        self.fn = fn
        self.needs = needs

    def __call__(self, frame):
        return self.fn(frame)

    def reset(self) -> None:
        pass


def make(method: str, **params):
    """A denoiser by name: ``__call__(frame) -> mi.TensorXf`` and ``reset()``."""
    if method == "svgf":
        return SVGF(**params)
    if method == "svgf-lobe":
        return SVGF(weights="lobe", **params)
    if method == "svgf-spatial-variance":
        return SVGF(variance="spatial", **params)
    if method == "atrous":
        return _PerFrame(lambda f: atrous_filter(f, **params))
    if method == "atrous-temporal":
        return ATrousTemporal(**params)
    if method == "oidn":
        from .oidn import oidn_denoise

        return _PerFrame(lambda f: oidn_denoise(f, **params))
    if method == "optix":
        from .optix import OptixTemporal

        return OptixTemporal(**params)
    raise GlossrtError(f"unknown denoiser {method!r}; choose one of {', '.join(METHODS)}")


__all__ = ["METHODS", "SVGF", "ATrousTemporal", "SVGFParams", "SpatioTemporalUpsampler",
           "adaptive_resample", "atrous_filter", "bilateral", "jitter_sequence", "make", "taa",
           "taa_jitter", "upsample"]
