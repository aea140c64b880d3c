"""Cube maps of directions, as the BSPVT visibility maps (Okuno & Iwasaki) and the light
environment maps of the highlights (Kimura & Tokoi) both store them.

**Conventions.** Faces ``f = 0..5`` are +X, -X, +Y, -Y, +Z, -Z: axis ``k = f // 2``, sign
``sg = +1`` for even ``f``, in-face axes ``u = (k + 1) % 3``, ``v = (k + 2) % 3``. A direction
``d`` belongs to face ``f`` when ``sg d[k] >= max(|d[u]|, |d[v]|)`` (ties: the lowest ``f``);
its gnomonic coordinates are ``s = d[u] / (sg d[k])``, ``t = d[v] / (sg d[k])`` in [-1, 1], so
great circles are straight lines in ``(s, t)``; ``dir(f, s, t) = sg e_k + s e_u + t e_v``.
Texel ``(i, j)`` (``i`` along ``s``) of a resolution-``R`` face has centre
``s = -1 + (2i + 1)/R``, ``t = -1 + (2j + 1)/R`` and is stored at ``[face, j, i]``.
"""

from __future__ import annotations

import numpy as np

from ..errors import GlossrtError

__all__ = ["DEFAULT_RESOLUTION", "cube_coords", "cube_dir", "cube_directions", "texel_centres"]

#: default cube map resolution (Okuno & Iwasaki's 64 x 64 per face)
DEFAULT_RESOLUTION = 64
_EYE = np.eye(3)


def _face_axes(face: np.ndarray):
    face = np.asarray(face)
    k = face // 2
    sg = 1.0 - 2.0 * (face % 2)
    return k, sg, (k + 1) % 3, (k + 2) % 3


def texel_centres(resolution: int) -> np.ndarray:
    """``(R,)`` float64 gnomonic coordinates of the texel centres, ``-1 + (2i + 1)/R``."""
    r = _check_resolution(resolution)
    return -1.0 + (2.0 * np.arange(r) + 1.0) / r


def cube_dir(face, s, t) -> np.ndarray:
    """``dir(f, s, t) = sg e_k + s e_u + t e_v`` (unnormalised), broadcast over the inputs:
    ``(..., 3)`` float64."""
    face = np.asarray(face, dtype=np.int64)
    if np.any((face < 0) | (face > 5)):
        raise GlossrtError("cube face indices must lie in 0..5")
    s, t = np.asarray(s, dtype=np.float64), np.asarray(t, dtype=np.float64)
    face, s, t = np.broadcast_arrays(face, s, t)
    k, sg, u, v = _face_axes(face)
    return sg[..., None] * _EYE[k] + s[..., None] * _EYE[u] + t[..., None] * _EYE[v]


def cube_coords(dirs) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(face, s, t)`` of directions ``(..., 3)`` (any length, not zero): ``face`` int64,
    ``s, t`` float64 in [-1, 1] (the conventions in the module docstring; ties between faces
    go to the lowest face index)."""
    d = np.asarray(dirs, dtype=np.float64)
    if d.ndim < 1 or d.shape[-1] != 3:
        raise GlossrtError(f"directions must have shape (..., 3), got {d.shape}")
    if not np.all(np.isfinite(d)):
        raise GlossrtError("directions contain NaN or Inf")
    a = np.abs(d)
    conds = []
    for f in range(6):
        k, sg, u, v = f // 2, 1.0 - 2.0 * (f % 2), (f // 2 + 1) % 3, (f // 2 + 2) % 3
        lead = sg * d[..., k]
        conds.append((lead >= np.maximum(a[..., u], a[..., v])) & (lead > 0))
    cond = np.stack(conds, -1)
    if not np.all(cond.any(-1)):
        raise GlossrtError("directions must not be zero vectors")
    face = np.argmax(cond, -1)
    k, sg, u, v = _face_axes(face)
    den = sg * np.take_along_axis(d, k[..., None], -1)[..., 0]
    s = np.take_along_axis(d, u[..., None], -1)[..., 0] / den
    t = np.take_along_axis(d, v[..., None], -1)[..., 0] / den
    return face, s, t


def cube_directions(resolution: int = DEFAULT_RESOLUTION) -> np.ndarray:
    """``(6, R, R, 3)`` float64 unit directions of the texel centres, indexed
    ``[face, j, i]`` like the visibility maps."""
    c = texel_centres(resolution)
    r = len(c)
    face = np.arange(6)[:, None, None]
    d = cube_dir(face, c[None, None, :], c[None, :, None])
    assert d.shape == (6, r, r, 3)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def _texel_index(s: np.ndarray, t: np.ndarray, r: int) -> tuple[np.ndarray, np.ndarray]:
    i = np.clip(np.floor((s + 1.0) * (0.5 * r)), 0, r - 1).astype(np.int64)
    j = np.clip(np.floor((t + 1.0) * (0.5 * r)), 0, r - 1).astype(np.int64)
    return i, j


def _check_resolution(resolution) -> int:
    try:
        r = int(resolution)
    except (TypeError, ValueError):
        raise GlossrtError(f"cube map resolution must be an integer, got {resolution!r}") from None
    if r != resolution or r < 1 or r > 1024:
        raise GlossrtError(f"cube map resolution must be an integer in 1..1024, got {resolution}")
    return r
