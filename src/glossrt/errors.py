"""Exceptions glossrt raises for bad input; the CLI turns them into one-line messages."""

from __future__ import annotations


class GlossrtError(ValueError):
    """Base class: a problem with the user's input or environment, with a message that names it.

    A ValueError, so code written against the plain ``ValueError`` some functions raised before
    still catches it."""


class BackendError(GlossrtError):
    """No usable Dr.Jit backend (missing libLLVM, no CUDA device when one was asked for)."""


class FrameError(GlossrtError):
    """An EXR frame is unreadable, incomplete, or does not match the frames it is used with."""


class SceneError(GlossrtError):
    """A scene cannot be loaded or uses a plugin glossrt does not support."""
