"""A procedural, tileable normal map: smooth random bumps plus thin straight scratches.

The map is built as a periodic height field ``h`` (in texel units, so its finite-difference
gradient is a slope) and encoded the way Mitsuba's ``normalmap`` BSDF reads it: the
tangent-space normal ``n = normalize(-dh/du, -dh/dv, 1)`` (x along the shading frame's
``s``, which Mitsuba's shapes align with ``dp_du``; y along ``t = n x s``; z along the
unperturbed shading normal) stored as ``rgb = (n + 1) / 2``. Array row ``i`` is
``v = (i + 0.5) / size`` and column ``j`` is ``u = (j + 0.5) / size`` (what Mitsuba's
``bitmap`` texture samples at ``(u, v)``). Where ``t`` runs along ``-dp_dv`` (Mitsuba's
``sphere``), mirror the green channel to keep it a height field's normals.

Everything is periodic (Fourier-filtered noise, scratches drawn with wrapped texel indices,
``np.roll`` differences), so a ``bitmap`` texture with ``wrap_mode: repeat`` tiles seamlessly.

Used by the ``normal-mapped`` built-in scene (specular antialiasing of normal-mapped glossy
surfaces: Tokuyoshi & Kaplanyan 2016)."""

from __future__ import annotations

import functools

import numpy as np

from ..errors import GlossrtError

#: standard deviation of each slope component (dh/du, dh/dv) of the bumps alone
BUMP_SLOPE_STD = 0.2
#: scratches per 1024 x 1024 texels (scaled with the map's area)
SCRATCHES_PER_MEGATEXEL = 160
#: peak slope of a scratch's flank (uniform range), and its Gaussian half-width in texels
SCRATCH_SLOPE = (0.9, 2.0)
SCRATCH_WIDTH = (0.5, 0.8)
#: scratch length as a fraction of the map size (uniform range)
SCRATCH_LENGTH = (0.04, 0.35)


def _bump_height(size: int, rng: np.random.Generator) -> np.ndarray:
    """Periodic smooth random height: white noise low-passed at four octaves of Gaussian
    width (1.25 texels to ``size / 100``, i.e. features of a few texels to ~1/30 of the
    map), each octave normalised to unit slope before weighting, so every octave shows."""
    freq = np.fft.fftfreq(size)  # cycles per texel
    f2 = freq[:, None] ** 2 + freq[None, :] ** 2
    sigmas = np.geomspace(1.25, max(1.25, size / 100.0), 4)
    weights = (1.0, 0.9, 0.8, 0.7)
    spectrum = np.fft.fft2(rng.standard_normal((size, size)))
    # slope variance of a low-passed white noise ~ sum(|G|^2 (2 pi f)^2): normalise with it
    total = np.zeros((size, size))
    for sigma, w in zip(sigmas, weights, strict=True):
        g = np.exp(-2.0 * np.pi**2 * sigma**2 * f2)
        slope_var = np.sum(g**2 * (2.0 * np.pi) ** 2 * f2) / 2.0
        total += w * g / np.sqrt(slope_var)
    return np.real(np.fft.ifft2(spectrum * total)) / size


def _scratch_height(size: int, rng: np.random.Generator) -> np.ndarray:
    """Periodic grooves (heights <= 0): straight segments of random position, orientation and
    length, a Gaussian cross-section of half-width ``SCRATCH_WIDTH`` texels whose flanks peak
    at slope ``SCRATCH_SLOPE``, faded out over the last 15% of either end. Where grooves
    cross, the deeper one wins."""
    count = max(1, round(SCRATCHES_PER_MEGATEXEL * size * size / 1024.0**2))
    centre = rng.uniform(0.0, size, (count, 2))  # (u, v) in texels
    theta = rng.uniform(0.0, np.pi, count)
    length = rng.uniform(*SCRATCH_LENGTH, count) * size
    width = rng.uniform(*SCRATCH_WIDTH, count)
    # flank slope of -d exp(-r^2 / 2w^2) peaks at d / w * exp(-1/2)
    depth = rng.uniform(*SCRATCH_SLOPE, count) * width / np.exp(-0.5)
    d = np.stack([np.cos(theta), np.sin(theta)], -1)
    perp = np.stack([-d[:, 1], d[:, 0]], -1)
    # sample points along (0.5 texel steps) and across (+-3.5 texels) every segment; each
    # lands in a texel whose exact value is computed from the texel centre
    n_along = np.ceil(length / 0.5).astype(int) + 1
    k = np.repeat(np.arange(count), n_along)
    first = np.repeat(np.cumsum(n_along) - n_along, n_along)
    t = (np.arange(k.size) - first) * 0.5 - length[k] / 2.0
    across = np.arange(-3.5, 3.51, 0.5)
    kk = np.repeat(k, across.size)
    pts = (centre[kk] + d[kk] * np.repeat(t, across.size)[:, None]
           + perp[kk] * np.tile(across, k.size)[:, None])
    texel = np.floor(pts)
    rel = texel + 0.5 - centre[kk]  # texel centre relative to the segment centre (unwrapped)
    along = np.sum(rel * d[kk], -1)
    r = np.sum(rel * perp[kk], -1)
    half = length[kk] / 2.0
    fade = np.clip((half - np.abs(along)) / (0.15 * half), 0.0, 1.0)
    fade = fade * fade * (3.0 - 2.0 * fade)  # smoothstep
    value = -depth[kk] * np.exp(-0.5 * (r / width[kk]) ** 2) * fade
    h = np.zeros((size, size))
    iu = texel[:, 0].astype(np.int64) % size
    iv = texel[:, 1].astype(np.int64) % size
    np.minimum.at(h, (iv, iu), value)
    return h


@functools.lru_cache(maxsize=4)
def _normal_map(size: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    bumps = _bump_height(size, rng)
    # exact rescale to the target slope std (the gradient is linear in the height)
    gu = (np.roll(bumps, -1, 1) - np.roll(bumps, 1, 1)) / 2.0
    gv = (np.roll(bumps, -1, 0) - np.roll(bumps, 1, 0)) / 2.0
    bumps *= BUMP_SLOPE_STD / np.sqrt(0.5 * (gu.var() + gv.var()))
    h = bumps + _scratch_height(size, rng)
    gu = (np.roll(h, -1, 1) - np.roll(h, 1, 1)) / 2.0  # dh/du, texel units (periodic)
    gv = (np.roll(h, -1, 0) - np.roll(h, 1, 0)) / 2.0  # dh/dv
    n = np.stack([-gu, -gv, np.ones_like(h)], -1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    out = ((n + 1.0) * 0.5).astype(np.float32)
    out.flags.writeable = False
    return out


def procedural_normal_map(size: int = 1024, seed: int = 3) -> np.ndarray:
    """(size, size, 3) float32 tangent-space normal map in Mitsuba's ``normalmap`` encoding
    (``n = 2 rgb - 1``, unit length, z > 0; rows are v, columns u, see the module docstring),
    periodic in both directions (use ``wrap_mode: repeat``, ``raw: True``).

    Height field = smooth random bumps (four octaves, features from a few texels to ~1/30 of
    the map, each slope component's standard deviation :data:`BUMP_SLOPE_STD`) plus
    :data:`SCRATCHES_PER_MEGATEXEL` per 1024^2 texels thin straight grooves (random
    orientation, ~1-2 texels wide, flank slopes 0.9-2, i.e. 40-65 degrees);
    normal = ``normalize(-dh/du, -dh/dv, 1)`` with periodic central differences in texel
    units. Deterministic for a given ``(size, seed)``; about 0.3 s for 1024^2 (cached)."""
    size, seed = int(size), int(seed)
    if size < 8:
        raise GlossrtError(f"normal map size must be at least 8 texels, got {size}")
    return _normal_map(size, seed).copy()


def toksvig(normal_map: np.ndarray, alpha: float, level: int) -> tuple[np.ndarray, np.ndarray]:
    """Toksvig 2005 ("Mipmapping normal maps", J. Graph. Tools 10(3)) at mip ``level`` of a
    normal map in Mitsuba's encoding (``n = 2 rgb - 1``): the box-filtered mean normal
    ``n_bar`` of ``2^level x 2^level`` texels, stored normalised (same encoding), and the
    per-texel roughness widened by its shortening, ``alpha'^2 = alpha^2 + (1 - |n_bar|) /
    |n_bar|`` (Toksvig's variance of the filtered normals, added to the lobe's), clamped to
    1. Returns ``(map, alpha')``: (S / 2^level, S / 2^level, 3) and (..., 1) float32."""
    if level < 0 or normal_map.shape[0] % (1 << level) or normal_map.shape[1] % (1 << level):
        raise GlossrtError(f"toksvig: level {level} does not divide the map "
                           f"{normal_map.shape[1]}x{normal_map.shape[0]}")
    k = 1 << level
    n = 2.0 * np.asarray(normal_map, dtype=np.float64) - 1.0
    h, w = n.shape[0] // k, n.shape[1] // k
    mean = n.reshape(h, k, w, k, 3).mean(axis=(1, 3))
    length = np.maximum(np.linalg.norm(mean, axis=-1, keepdims=True), 1e-6)
    a2 = alpha * alpha + (1.0 - np.minimum(length, 1.0)) / length
    return (((mean / length + 1.0) * 0.5).astype(np.float32),
            np.sqrt(np.minimum(a2, 1.0)).astype(np.float32))
