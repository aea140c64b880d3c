"""glossrt: real-time rendering of glossy surfaces with Mitsuba 3 + Dr.Jit.

The package selects its Dr.Jit backend lazily (see :mod:`glossrt.backend`): importing a module
picks none; the first call that needs Mitsuba does (modules read it through
:data:`glossrt.backend.mi`), unless :func:`glossrt.backend.use` chose one before.
"""

from __future__ import annotations

__version__ = "0.1.0"

__all__ = ["__version__", "Frame", "Camera"]


def __getattr__(name: str):
    if name in ("Frame", "Camera"):
        from . import frame

        return getattr(frame, name)
    raise AttributeError(name)
