"""BRDF helpers: the GGX specular lobe as Mitsuba 3 evaluates it, and its pre-integrated albedo.

The names below are read from :mod:`glossrt.brdf.ggx`, imported on first use (importing it
picks no Dr.Jit backend either: its first call does).
"""

from __future__ import annotations

from typing import Any

__all__ = [
    "D_ggx",
    "G1_smith",
    "fresnel_schlick",
    "albedo_ab",
    "generate_albedo_table",
    "SpecularAlbedoTable",
]


def __getattr__(name: str) -> Any:
    if name in __all__:
        from . import ggx

        return getattr(ggx, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
