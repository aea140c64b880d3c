"""glossrt: real-time rendering of glossy surfaces with Mitsuba 3 + Dr.Jit.

The package selects its Dr.Jit backend lazily (see :mod:`glossrt.backend`); modules that
need Mitsuba types call :func:`glossrt.backend.ensure` first.
"""

from __future__ import annotations

__version__ = "0.1.0"

__all__ = ["__version__", "Frame", "Camera"]


def __getattr__(name: str):
    if name in ("Frame", "Camera"):
        from . import frame

        return getattr(frame, name)
    raise AttributeError(name)
