"""The supersampled reference of specular antialiasing (:mod:`glossrt.specaa`): the
unfiltered shading averaged over stratified sub-pixel positions of a box or Gaussian pixel
filter (:func:`subpixel_offsets`, :func:`reference`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import drjit as dr
import numpy as np

from ..errors import GlossrtError
from .filters import SIGMA2
from .shade import shade_tensor

#: pixel filters of the supersampled reference (:func:`reference`): ``"box"`` (the pixel's
#: square) or ``"gaussian"`` (variance :data:`SIGMA2` per axis, Tokuyoshi's eq. 1)
PIXEL_FILTERS = ("box", "gaussian")
#: how far a sub-pixel offset may reach from its pixel's centre, in pixels (the renderer's
#: ``jitter_limit`` for the Gaussian pixel filter; Mitsuba's own ``gaussian`` filter stops
#: at 4 standard deviations, 2 px for ``sigma^2 = 0.25``)
JITTER_LIMIT = 2.0


def _normal_quantile(u: np.ndarray, sigma: float) -> np.ndarray:
    """``sigma * Phi^-1(u)`` (the normal distribution's inverse CDF), ``0 < u < 1``."""
    from statistics import NormalDist

    inv = NormalDist(0.0, sigma).inv_cdf
    return np.array([inv(float(v)) for v in np.ravel(u)])


def subpixel_offsets(spp: int, pixel_filter: str = "box",
                     seed: int | None = None) -> np.ndarray:
    """``spp`` stratified sub-pixel offsets (x, y) in pixels from the pixel's centre, equally
    weighted, row-major on a ``sqrt(spp)`` square grid of strata (``spp`` must be a square):

    * ``"box"``: the strata's centres in [-0.5, 0.5)^2;
    * ``"gaussian"``: the Gaussian pixel filter of variance ``sigma^2 = 0.25`` px^2 per axis
      (Tokuyoshi, eq. 1): per axis the normal quantiles ``sigma Phi^-1((i + 1/2) / n)`` of
      the strata's centres (equal probability each), scaled so the set's variance is exactly
      ``sigma^2`` (the centres alone fall 8% short at n = 16: their tails are cut).

    ``seed`` (an int; default None: the strata's centres above) jitters the set: one uniform
    random position per stratum and axis (NumPy ``default_rng(seed)``), mapped per axis as
    above: ``u - 0.5`` for the box, ``sigma Phi^-1(u)`` of ``u`` spread over the truncated
    normal's range ``[Phi(-L / sigma), Phi(L / sigma))`` (``L`` = :data:`JITTER_LIMIT`, 4
    standard deviations, where Mitsuba's ``gaussian`` filter stops too) for the Gaussian,
    without the variance stretch (jittered strata sample the filter without bias).
    Independent seeds give independent references (issue 28's error bars).
    """
    if pixel_filter not in PIXEL_FILTERS:
        raise GlossrtError(f"pixel filter must be one of {PIXEL_FILTERS}, got {pixel_filter!r}")
    n = int(round(math.sqrt(spp))) if isinstance(spp, (int, np.integer)) and spp > 0 else 0
    if n < 1 or n * n != spp:
        raise GlossrtError(f"reference spp must be a square number (16, 64, 256...), got {spp}")
    if seed is not None:
        return _jittered_offsets(n, pixel_filter, int(seed))
    u = (np.arange(n) + 0.5) / n
    if pixel_filter == "box":
        c = u - 0.5
    elif n == 1:
        c = np.zeros(1)
    else:
        c = _normal_quantile(u, math.sqrt(SIGMA2))
        c *= math.sqrt(SIGMA2 / np.mean(c * c))  # symmetric: mean 0, variance sigma^2
    gx, gy = np.meshgrid(c, c)
    return np.stack([gx.ravel(), gy.ravel()], axis=1)


def _jittered_offsets(n: int, pixel_filter: str, seed: int) -> np.ndarray:
    """:func:`subpixel_offsets` with ``seed``: one random position in each of the ``n x n``
    strata (row-major)."""
    from statistics import NormalDist

    rng = np.random.default_rng(seed)
    iy, ix = np.divmod(np.arange(n * n), n)
    u = (np.stack([ix, iy], axis=1) + rng.random((n * n, 2))) / n  # in [0, 1)
    if pixel_filter == "box":
        return u - 0.5
    sigma = math.sqrt(SIGMA2)
    lo = NormalDist(0.0, sigma).cdf(-JITTER_LIMIT)
    c = _normal_quantile(lo + u * (1.0 - 2.0 * lo), sigma).reshape(n * n, 2)
    return np.clip(c, -JITTER_LIMIT, np.nextafter(JITTER_LIMIT, 0.0))


def reference(renderer, frame_index: int, lights: Sequence = (), polygons: Sequence = (),
              f0_of: Callable | None = None, spp: int = 256,
              progress: Callable[[int, int], None] | None = None,
              pixel_filter: str = "box", seed: int | None = None) -> np.ndarray:
    """Supersampled reference (H, W, 3): the unfiltered shading of
    :func:`glossrt.specaa.shade` averaged over ``spp`` stratified sub-pixel primary hits
    (:func:`subpixel_offsets` of ``pixel_filter``: ``"box"``, or ``"gaussian"``, Tokuyoshi's
    eq. 1 filter, whose samples reach into the neighbouring pixels) of ``renderer``'s frame
    ``frame_index`` (a :class:`glossrt.render.Renderer`); ``seed``: jittered strata
    (:func:`subpixel_offsets`), None: their centres. ``f0_of(frame)`` gives each
    sub-sample's F0 image (default: :func:`glossrt.lights.shading.f0_image` of the renderer's
    scene)."""
    from ..lights.shading import f0_image

    offsets = subpixel_offsets(spp, pixel_filter, seed)  # bad spp / filter: first
    if f0_of is None:
        def f0_of(fr):
            return f0_image(renderer.setup, fr)

    acc = None
    cache: dict = {}
    for i, (jx, jy) in enumerate(offsets):
        fr = renderer.render(frame_index, jitter=(float(jx), float(jy)),
                             jitter_limit=JITTER_LIMIT)
        img = shade_tensor(fr, lights, polygons, "none", f0_of(fr), frozen=True,
                           textures=cache)
        acc = img if acc is None else acc + img
        dr.eval(acc)
        if progress is not None:
            progress(i + 1, len(offsets))
    h, w = renderer.height, renderer.width
    return np.array(acc / len(offsets), dtype=np.float32).reshape(h, w, 3)
