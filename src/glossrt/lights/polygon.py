"""Convex polygon lights seen from a shading point: horizon clipping and the edge integral of
the clamped cosine (Lambert's formula), in Dr.Jit (one lane per shading point) with NumPy
wrappers.

References:

* J. H. Lambert, *Photometria*, 1760: the irradiance of a uniform polygon as a sum over its
  edges; in vector form J. Arvo, "The Irradiance Jacobian for Partially Occluded Polyhedral
  Sources", SIGGRAPH 1994, sec. 2 (vector irradiance ``Phi = 1/2 sum_i Theta_i Gamma_i``) and
  "Applications of Irradiance Tensors to the Simulation of Non-Lambertian Phenomena",
  SIGGRAPH 1995;
* E. Heitz, J. Dupuy, S. Hill, D. Neubelt, "Real-Time Polygonal-Light Shading with Linearly
  Transformed Cosines", SIGGRAPH 2016: the clamped-cosine integral of a polygon as the edge sum
  of the horizon-clipped polygon (their polygon-integration section), the quantity LTC shading
  evaluates after transforming the polygon;
* E. Heitz, "Geometric Derivation of the Irradiance of Polygonal Lights", Unity Technologies
  technical report, 2017: the *vector form factor* ``F`` of the unclipped polygon and the
  horizon-clipped-sphere approximation that uses it (:func:`form_factor_vector`);
* I. E. Sutherland, G. W. Hodgman, "Reentrant Polygon Clipping", CACM 17(1), 1974
  (:func:`clip_to_horizon`);
* T. Duff et al., "Building an Orthonormal Basis, Revisited", JCGT 6(1), 2017 (the tangent
  frame of :func:`shading_frame`, also Mitsuba's ``mi.Frame3f``).

Conventions
-----------

* **Local frame.** Vertices are given *relative to the shading point* in its local shading
  frame: the shading point is the origin and its normal is ``+z`` (:func:`to_local` maps world
  vertices there).
* **Polygons.** In Dr.Jit a polygon is a Python list of ``K`` 3-vectors (``mi.Vector3f`` or
  another Dr.Jit float 3-vector such as ``mi.Vector3d``), ``3 <= K <= 8``, ``K`` fixed per
  call (it shapes the kernel), one lane per shading point. Lanes with fewer vertices either
  pass a per-lane ``count`` (``mi.UInt32``, vertices ``count..K-1`` are ignored; counts above
  ``K`` are clamped to ``K``, lanes with ``count < 3`` give 0), or repeat their last vertex
  (zero-length edges contribute exactly 0, so both give the same result). Polygons must be
  planar and convex (not checked per lane; the NumPy API checks the vertex count and
  finiteness only). Vertices may be ordered either way round.
* **Winding and sides.** The light's *front* normal is the right-hand normal
  ``(v1 - v0) x (v2 - v0)`` (OpenGL's front face): a one-sided light emits towards its front
  only, so it lights the shading point iff the polygon appears **counter-clockwise seen from
  the shading point**. (This is :mod:`glossrt.lights.mc`'s convention.) Two-sided lights emit
  on both sides: the winding is ignored.
* **Scale.** All results are invariant under scaling all vertices of a lane; the Dr.Jit
  functions first scale each lane's vertices by an exact power of two so that the largest
  coordinate lies in ``[1, 2)`` (no overflow of squared lengths for huge polygons, no
  underflow for tiny ones); the NumPy wrappers do the same in float64 before the float32
  conversion (so float64 input beyond the float32 range works).

What is computed
----------------

The *vector form factor* of the closed polygon ``v_0 .. v_{n-1}`` (Lambert / Arvo; sign chosen
so that ``F`` points towards a front-facing light)::

    F = 1/(2 pi) sum_i theta_i  normalize(v_{i+1} x v_i),   theta_i = angle(v_i, v_{i+1})

equals ``+(1/pi) int_P w dw`` for a front-facing and ``-(1/pi) int_P w dw`` for a back-facing
polygon (``P``: its solid angle). The clamped-cosine integral of :func:`cosine_integral` is::

    I = (1/pi) int_P max(cos theta, 0) dw        (= the integral of D_o = cos / pi over P)

obtained as ``s = F.z`` of the polygon *clipped to the upper hemisphere first* (a signed value:
``+I`` front-facing, ``-I`` back-facing); one-sided: ``max(s, 0)``, two-sided: ``|s|``. (``|F.z|``
of the *unclipped* polygon is not ``I`` for a polygon straddling the horizon: the part below
cancels part of the part above.)

Two edge terms are provided (``robust=`` of every function):

* ``robust=False``, the textbook form on unit vectors: ``acos(u_i . u_j) normalize(u_j x u_i)``
  (Heitz et al. 2016). In float32 ``acos`` near 1 keeps only about half the digits (the angle
  of a 1e-3 rad edge has an absolute error ~6e-5, i.e. 6 %; a repeated vertex would even get
  ``acos(1 - 6e-8) = 3.5e-4``, so zero-length edges are tested for explicitly) and
  ``u_j x u_i`` of nearly parallel unit vectors cancels. Absolute error up to
  ``K sqrt(2 eps) / (2 pi) ~ 5e-4``; small or distant polygons get large relative errors.
* ``robust=True`` (default), on the unnormalised vertices ``a = v_i``, ``b = v_{i+1}``:
  ``c = (b - a) x a`` (``= b x a`` exactly, but computed from the edge vector, so no
  cancellation between nearly parallel vectors), ``theta = atan2(|c|, a . b)`` (full relative
  precision at every angle, unlike ``acos``), term ``theta c / |c|``. Each term has a relative
  error below ~16 eps (Dr.Jit's float32 ``atan2`` alone: up to 13.7 eps, measured), so the
  error of the sum is at most ~``16 eps (sum_i theta_i / (2 pi) + I) <= 32 eps = 1.9e-6``
  absolute (``sum_i theta_i <= 2 pi`` for a convex polygon in a hemisphere). Relative to ``I``
  it grows where the terms cancel: small or distant polygons (``sum theta ~ perimeter``,
  ``I ~ area``) and thin slivers left by the horizon clip.

Measured (``tests/test_polygon.py``, float64 quadrature of 1361 random convex polygons, 608 of
them with ``I > 1e-4``): robust form relative error median 2.7e-6, 99th percentile 1.6e-4, max
absolute error 1.3e-7; acos form median 5.8e-5, 99th percentile 7e-2, max absolute 5.4e-5.
A 1e-3 square at distance 1 (or a unit square at distance 1e3; ``I ~ 2e-7``): robust
relative error 3e-5 to 1e-4, acos form 100 % to 8500 %. (The rational fit of ``theta /
sin(theta)`` used in shipping LTC code, Hill and Heitz 2016, is cheaper but also loses
accuracy for small angles; it is not used here.)

Degenerate input never gives NaN: a zero-length edge or a vertex at the origin (undefined
direction) contributes 0; zero-area polygons (repeated or collinear vertices), polygons
entirely below the horizon and polygons whose plane passes through the shading point (to
within the precision the rounded vertices define that plane, see :data:`PLANE_TOL_ULPS`:
this covers a vertex at the origin, the shading point on the light itself or on its edge,
and lights in the tangent plane) give exactly 0. (The integral is discontinuous there: the
limits from the two sides differ, so 0 is a choice, the value on the plane itself.) NaN or Inf
vertices give NaN results in the Dr.Jit API; the NumPy API rejects them.

Example (NumPy API)::

    >>> import numpy as np
    >>> from glossrt.lights.polygon import clamped_cosine_integral
    >>> # a 2 x 2 square 1 above the shading point, counter-clockwise seen from below (front)
    >>> quad = np.array([[-1, 1, 1], [1, 1, 1], [1, -1, 1], [-1, -1, 1.0]])
    >>> round(float(clamped_cosine_integral(quad, two_sided=False)), 4)
    0.5541
    >>> float(clamped_cosine_integral(quad[::-1], two_sided=False))  # seen from its back
    0.0
    >>> clamped_cosine_integral(np.stack([quad, quad - [0, 0, 2]])).round(4)  # batched
    array([0.5541, 0.    ])
"""

from __future__ import annotations

import math
from typing import Any

import drjit as dr
import numpy as np

from ..backend import mi
from ..errors import GlossrtError

__all__ = [
    "K_MAX",
    "K_MIN",
    "PLANE_TOL_ULPS",
    "clamped_cosine_integral",
    "clip_to_horizon",
    "cosine_integral",
    "edge_term",
    "form_factor_vector",
    "form_factor_vectors",
    "shading_frame",
    "to_local",
]

#: Fewest / most vertices of a polygon.
K_MIN, K_MAX = 3, 8
#: The shading point counts as lying in the light's plane when its distance to that plane is
#: below ``PLANE_TOL_ULPS`` machine epsilons (2^-19 ~ 1.9e-6 in float32) times ``R (R L / |N|)``
#: (``R``: largest vertex distance, ``L``: perimeter, ``|N|``: twice the area), the plane's
#: uncertainty from rounding the vertices (see ``_on_plane``). For a square light centred
#: above the point that is ``h < 2.7e-6 R``. In-plane configurations (a vertex at the origin,
#: the point inside or on an edge of the light, a light in the tangent plane), built in
#: float64 and rounded to float32, give at most ~10 eps: a margin of 3.
PLANE_TOL_ULPS = 32

_INV_TWO_PI = 1.0 / (2.0 * math.pi)


# --------------------------------------------------------------------------------------------
# helpers


def _check_polygon(verts) -> list:
    if not isinstance(verts, list | tuple):
        raise GlossrtError(
            f"a polygon is a list of 3 to 8 Dr.Jit 3-vectors, got {type(verts).__name__}")
    if not K_MIN <= len(verts) <= K_MAX:
        raise GlossrtError(f"a polygon needs 3 to 8 vertices, got {len(verts)}")
    vt = type(verts[0])
    if not (dr.is_array_v(vt) and dr.size_v(vt) == 3):
        raise GlossrtError(f"polygon vertices must be Dr.Jit 3-vectors, got {vt.__name__}")
    return [vt(v) for v in verts]


def _types(verts):
    vt = type(verts[0])
    ft = dr.value_t(vt)
    return vt, ft, dr.uint32_array_t(ft)


def _count(count, k: int, ut):
    """Per-lane vertex count clamped to ``k``, or ``None`` (all ``k`` vertices)."""
    if count is None:
        return None
    if isinstance(count, int):
        if count >= k:
            return None
        return ut(max(count, 0))
    return dr.minimum(ut(count), k)


def _edges(verts: list, n):
    """``(a, b, active)`` for the edges ``v_i -> v_{i+1}`` of the closed polygon made of the
    first ``n`` vertices (``n=None``: all; ``active`` is then the Python ``True``)."""
    k = len(verts)
    for i in range(k):
        if n is None:
            yield verts[i], verts[(i + 1) % k], True
        elif i == k - 1:
            yield verts[i], verts[0], n > i
        else:
            yield verts[i], dr.select(n > i + 1, verts[i + 1], verts[0]), n > i


def _masked(value, active, zero):
    return value if active is True else dr.select(active, value, zero)


def _max_abs(v):
    return dr.maximum(dr.maximum(dr.abs(v.x), dr.abs(v.y)), dr.abs(v.z))


def _prescale(verts: list, n) -> list:
    """Scale each lane by an exact power of two so its largest used coordinate lies in
    ``[1, 2)`` (all results are scale invariant; this avoids overflow of ``|c|^2`` for huge
    and underflow for tiny polygons). Lanes of zeros or with NaN / Inf are left as they are."""
    vt, ft, _ = _types(verts)
    m = _max_abs(verts[0])
    for i in range(1, len(verts)):
        mi_ = _max_abs(verts[i])
        m = dr.maximum(m, mi_ if n is None else dr.select(n > i, mi_, 0.0))
    if dr.type_v(ft) == dr.VarType.Float32:
        it, mask, bias2, top = dr.uint32_array_t(ft), 0x7F800000, 254 << 23, 253 << 23
    else:
        it, mask, bias2, top = dr.uint64_array_t(ft), 0x7FF0000000000000, 2046 << 52, 2045 << 52
    # the power of two 2^e <= m (its exponent bits) and 2^-e, built from the bits: exact
    e_bits = dr.minimum(dr.reinterpret_array(it, m) & mask, top)
    inv = dr.reinterpret_array(ft, bias2 - e_bits)
    inv = dr.select((m > 0) & dr.isfinite(m), inv, 1.0)
    return [v * inv for v in verts]


def _on_plane(verts: list, n):
    """True where the origin lies in the polygon's plane within the precision the vertices
    define that plane (or the polygon has zero area).

    With ``N = sum_i (v_i - v_0) x (v_{i+1} - v_0)`` (twice the area vector, fan from ``v_0``:
    no cancellation for polygons far away), ``R = max_i |v_i|`` and the perimeter ``L``, the
    distance of the origin to the plane is ``h = |N . v_0| / |N|``; moving the vertices by
    their rounding (``eps R``) moves the plane by up to about ``eps R (R L / |N|)`` (the factor
    ``R L / |N|`` grows for thin polygons and small distant ones, whose plane is poorly
    determined). The test ``|N . v_0| <= tol R^2 L``, ``tol = PLANE_TOL_ULPS eps``, is that
    comparison without divisions."""
    vt, ft, _ = _types(verts)
    k = len(verts)
    p0 = verts[0]
    zero = dr.zeros(vt, dr.width(verts))
    area = zero
    r2 = dr.squared_norm(p0)
    for i in range(1, k):
        r2_i = dr.squared_norm(verts[i])
        r2 = dr.maximum(r2, r2_i if n is None else dr.select(n > i, r2_i, 0.0))
        if i < k - 1:
            tri = dr.cross(verts[i] - p0, verts[i + 1] - p0)
            area = area + (tri if n is None else dr.select(n > i + 1, tri, zero))
    perimeter = dr.zeros(ft, dr.width(verts))
    for a, b, active in _edges(verts, n):
        perimeter = perimeter + _masked(dr.norm(b - a), active, 0.0)
    h = dr.abs(dr.dot(area, p0))
    return h <= (PLANE_TOL_ULPS * dr.epsilon(ft)) * r2 * perimeter


def _rcp_norm(v):
    """``1 / |v|``, or 0 for the zero vector (an undefined direction contributes nothing)."""
    n2 = dr.squared_norm(v)
    return dr.select(n2 > 0.0, dr.rsqrt(dr.select(n2 > 0.0, n2, 1.0)), 0.0)


def edge_term(a, b, robust: bool = True):
    """Edge term ``theta normalize(b x a)`` of the edge ``a -> b`` (``theta`` = angle between
    ``a`` and ``b``), without the ``1 / (2 pi)``; summed over a polygon's edges and divided by
    ``2 pi`` it gives :func:`form_factor_vector` (Lambert 1760; Arvo 1994, sec. 2:
    ``Phi = 1/2 sum_i Theta_i Gamma_i``, here with ``Phi / pi``).

    * ``robust=False``: ``acos(u_a . u_b) normalize(u_b x u_a)`` on the unit vectors (Heitz et
      al. 2016's form);
    * ``robust=True``: ``c = (b - a) x a`` (= ``b x a``), ``theta = atan2(|c|, a . b)``,
      ``theta c / |c|``, on the unnormalised vertices (see the module docstring).

    Zero-length edges, a vertex at the origin and antipodal directions (undefined arc) give 0.
    """
    if robust:
        c = dr.cross(b - a, a)  # = b x a, from the edge vector: no cancellation for a ~ b
        s = dr.norm(c)
        # |b x a| = |a||b| sin(theta), a . b = |a||b| cos(theta): atan2 is exact to rounding
        theta = dr.atan2(s, dr.dot(a, b))
        return c * dr.select(s > 0.0, theta / dr.select(s > 0.0, s, 1.0), 0.0)
    ua, ub = a * _rcp_norm(a), b * _rcp_norm(b)
    c = dr.cross(ub, ua)
    # Heitz et al. 2016: acos(<p_i, p_j>) normalize(p_i x p_j) (sign: front-facing positive)
    theta = dr.acos(dr.clip(dr.dot(ua, ub), -1.0, 1.0))
    # a repeated vertex must give exactly 0: with FMA contraction u x u is not exactly 0 and
    # u . u rounds below 1 (acos(1 - 6e-8) = 3.5e-4), so this form needs an explicit test
    same = (a.x == b.x) & (a.y == b.y) & (a.z == b.z)
    return dr.select(same, 0.0, c * (theta * _rcp_norm(c)))


def _edge_sum(verts: list, n, robust: bool):
    vt, _, _ = _types(verts)
    zero = dr.zeros(vt, dr.width(verts))
    acc = zero
    for a, b, active in _edges(verts, n):
        # not `+=`: that would update `zero` in place (acc aliases it)
        acc = acc + _masked(edge_term(a, b, robust), active, zero)
    # Lambert / Arvo: F = Phi / pi = 1/(2 pi) sum_i theta_i Gamma_i
    return acc * _INV_TWO_PI


# --------------------------------------------------------------------------------------------
# Dr.Jit API


def clip_to_horizon(verts, count=None):
    """Clip a convex polygon to the upper half-space ``z >= 0`` (Sutherland and Hodgman 1974,
    one clipping plane), branch-free per lane.

    ``verts``: list of ``K`` Dr.Jit 3-vectors (``3 <= K <= 8``); ``count``: optional per-lane
    vertex count (``mi.UInt32`` or int, clamped to ``K``; ``< 3`` gives an empty result).
    Returns ``(out, count_out)``: a list of ``K + 1`` vectors (a plane cuts a convex ``K``-gon
    into at most ``K + 1`` vertices) and the per-lane ``mi.UInt32`` count (0 when the polygon
    lies entirely below the horizon). Slots ``count_out..K`` repeat the last output vertex
    (all zero when ``count_out = 0``), so ``out`` is also a valid ``K + 1``-gon with
    zero-length edges, usable without ``count_out``. Vertices with ``z = 0`` count as inside
    (a polygon touching the horizon in a vertex gives a zero-area triangle). Non-convex input
    could produce more than ``K + 1`` vertices: the extra ones are dropped.

    Each edge ``a -> b`` emits ``a`` if ``a.z >= 0`` and, if exactly one end is inside, the
    crossing ``a + t (b - a)``, ``t = a.z / (a.z - b.z)`` in ``[0, 1]`` (the denominator is
    ``> 0`` there), with ``z`` set to 0 exactly. Emitted vertices go to slot ``c`` (the running
    count) through ``dr.select``: no Python branching on Dr.Jit values."""
    verts = _check_polygon(verts)
    vt, ft, ut = _types(verts)
    k = len(verts)
    n = _count(count, k, ut)
    width = dr.width(verts)
    zero = dr.zeros(vt, width)
    out = [zero] * (k + 1)
    c = dr.zeros(ut, width)
    j = 0  # emission index: emission j can only land in slots 0..j
    for a, b, active in _edges(verts, n):
        a_in, b_in = a.z >= 0.0, b.z >= 0.0
        emit_a = a_in if active is True else active & a_in
        crosses = (a_in ^ b_in) if active is True else active & (a_in ^ b_in)
        # Sutherland & Hodgman 1974: intersection of the edge with the plane z = 0
        t = a.z / dr.select(crosses, a.z - b.z, 1.0)
        p = a + (b - a) * t
        p = vt(p.x, p.y, dr.zeros(ft, width))
        for value, emit in ((a, emit_a), (p, crosses)):
            for s in range(min(j, k) + 1):
                out[s] = dr.select(emit & (c == s), value, out[s])
            c = c + dr.select(emit, ut(1), ut(0))
            j += 1
    c = dr.minimum(c, k + 1)
    if n is not None:
        c = dr.select(n >= 3, c, 0)
    out[0] = dr.select(c > 0, out[0], zero)
    for s in range(1, k + 1):
        out[s] = dr.select(c > s, out[s], out[s - 1])
    return out, c


def form_factor_vector(verts, count=None, robust: bool = True):
    """Vector form factor ``F`` of the *unclipped* polygon (a Dr.Jit 3-vector per lane).

    Lambert / Arvo (1994, sec. 2): ``F = 1/(2 pi) sum_i theta_i normalize(v_{i+1} x v_i) =
    +-(1/pi) int_P w dw`` (``+`` for a front-facing polygon, i.e. counter-clockwise seen from the
    shading point: ``F`` then points towards it; ``-`` for a back-facing one). ``F.z`` is the
    signed clamped-cosine integral only when the polygon lies entirely above the horizon;
    ``|F|`` and ``F / |F|`` are the inputs of the horizon-clipped-sphere approximation (Heitz
    2017; Hill and Heitz 2016): a sphere light with the same ``F`` has the form factor ``|F|``
    and the direction ``F / |F|``. Degenerate polygons (zero area, plane through the shading
    point) give the zero vector. ``robust``: the edge term (see :func:`edge_term`)."""
    verts = _check_polygon(verts)
    vt, _, ut = _types(verts)
    n = _count(count, len(verts), ut)
    verts = _prescale(verts, n)
    f = _edge_sum(verts, n, robust)
    dead = _on_plane(verts, n)
    if n is not None:
        dead |= n < 3
    return dr.select(dead, dr.zeros(vt, dr.width(verts)), f)


def cosine_integral(verts, count=None, two_sided=True, robust: bool = True):
    """Clamped-cosine integral ``(1/pi) int_P max(cos theta, 0) dw`` of the polygon (a Dr.Jit
    float per lane, in ``[0, 1]``): the form factor from the shading point to the light, i.e.
    the integral of the normalised cosine distribution ``D_o = cos / pi`` over the light.

    Heitz et al. 2016 (polygon integration of the clamped cosine): clip to the upper hemisphere
    (:func:`clip_to_horizon`), then ``s = F.z`` of the clipped polygon (Lambert's edge sum,
    :func:`edge_term`), signed by the winding (``+`` front-facing = counter-clockwise seen
    from the shading point). ``two_sided``: ``|s|``; one-sided: ``max(s, 0)`` (the light emits
    only towards its front). ``two_sided`` may be a Python bool or a per-lane ``mi.Bool``.
    ``count``: optional per-lane vertex count; ``robust``: the edge term.

    Exactly 0 for polygons below the horizon, of zero area, or whose plane passes through the
    shading point (see ``PLANE_TOL_ULPS``)."""
    verts = _check_polygon(verts)
    vt, ft, ut = _types(verts)
    n = _count(count, len(verts), ut)
    verts = _prescale(verts, n)
    dead = _on_plane(verts, n)
    clipped, _ = clip_to_horizon(verts, n)
    # the unused slots of `clipped` repeat its last vertex: all K + 1 edges can be summed
    s = _edge_sum(clipped, None, robust).z
    s = dr.select(dead, 0.0, s)
    if isinstance(two_sided, bool):
        return dr.abs(s) if two_sided else dr.maximum(s, 0.0)
    return dr.select(two_sided, dr.abs(s), dr.maximum(s, 0.0))


# --------------------------------------------------------------------------------------------
# NumPy API


def _np_polygons(vertices: Any, count: Any):
    """Validate ``(..., K, 3)`` vertices (and an optional ``(...)`` count); return the float64
    array scaled per polygon by a power of two so that its largest used coordinate lies in
    ``[1, 2)``, the counts (or None) and the batch shape."""
    try:
        v = np.asarray(vertices, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise GlossrtError(f"polygon vertices must be a numeric (..., K, 3) array: {e}") from e
    if v.ndim < 2 or v.shape[-1] != 3:
        raise GlossrtError(f"polygon vertices must have shape (..., K, 3), got {v.shape}")
    k = v.shape[-2]
    if k < K_MIN:
        raise GlossrtError(f"a polygon needs at least 3 vertices, got K = {k}")
    if k > K_MAX:
        raise GlossrtError(f"a polygon has at most 8 vertices, got K = {k}")
    batch = v.shape[:-2]
    cnt = None
    if count is not None:
        c = np.asarray(count)
        if not np.issubdtype(c.dtype, np.integer):
            raise GlossrtError(f"vertex counts must be integers, got dtype {c.dtype}")
        try:
            c = np.broadcast_to(c, batch)
        except ValueError as e:
            raise GlossrtError(f"vertex counts of shape {c.shape} do not match the polygons' "
                               f"batch shape {batch}") from e
        if c.size and c.min() < K_MIN:
            raise GlossrtError(f"a polygon needs at least 3 vertices, got a count of {c.min()}")
        if c.size and c.max() > k:
            raise GlossrtError(f"vertex count {c.max()} exceeds the K = {k} vertices given")
        cnt = c.reshape(-1).astype(np.uint32)
    v = v.reshape(-1, k, 3)
    bad = ~np.isfinite(v).all(axis=(1, 2))
    if bad.any():
        first = np.unravel_index(int(np.argmax(bad)), batch) if batch else ()
        raise GlossrtError(f"polygon vertices contain NaN or Inf ({int(bad.sum())} polygon(s),"
                           f" the first at batch index {tuple(int(i) for i in first)})")
    used = np.abs(v)
    if cnt is not None:
        used = np.where(np.arange(k)[None, :, None] < cnt[:, None, None], used, 0.0)
    # divide by the power of two 2^(e - 1) <= largest coordinate < 2^e: exact in float64, so
    # float32-representable input (collinear, repeated, in-plane vertices) stays exact
    _, e = np.frexp(used.max(axis=(1, 2)))
    v = np.ldexp(v, (1 - e)[:, None, None])
    return v, cnt, batch


def _dr_polygon(v: np.ndarray, cnt):
    verts = [mi.Vector3f(mi.Float(np.ascontiguousarray(v[:, i, 0])),
                         mi.Float(np.ascontiguousarray(v[:, i, 1])),
                         mi.Float(np.ascontiguousarray(v[:, i, 2]))) for i in range(v.shape[1])]
    return verts, (None if cnt is None else mi.UInt32(cnt))


def clamped_cosine_integral(vertices: Any, two_sided: bool = True, robust: bool = True,
                            count: Any = None) -> np.ndarray:
    """NumPy wrapper of :func:`cosine_integral`: ``(1/pi) int_P max(cos theta, 0) dw`` of each
    polygon (float32 evaluation, returned as float64).

    ``vertices``: ``(..., K, 3)``, ``3 <= K <= 8``, relative to the shading point in its local
    frame (normal ``+z``; see :func:`to_local`), convex and planar, batched over the leading
    axes; front = counter-clockwise seen from the shading point. ``count``: optional integer
    array broadcastable to ``(...)`` with ``3 <= count <= K`` (the remaining vertices are
    ignored). Returns shape ``(...)``. Raises :class:`~glossrt.errors.GlossrtError` for a
    wrong shape, ``K`` outside 3..8, a bad count, NaN or Inf."""
    v, cnt, batch = _np_polygons(vertices, count)
    if v.shape[0] == 0:
        return np.zeros(batch)
    verts, n = _dr_polygon(v, cnt)
    out = cosine_integral(verts, n, two_sided=bool(two_sided), robust=bool(robust))
    return np.asarray(out.numpy(), dtype=np.float64).reshape(batch)


def form_factor_vectors(vertices: Any, robust: bool = True, count: Any = None) -> np.ndarray:
    """NumPy wrapper of :func:`form_factor_vector` (unclipped polygons): ``(..., K, 3)`` ->
    ``(..., 3)``; arguments and errors as :func:`clamped_cosine_integral`."""
    v, cnt, batch = _np_polygons(vertices, count)
    if v.shape[0] == 0:
        return np.zeros((*batch, 3))
    verts, n = _dr_polygon(v, cnt)
    f = form_factor_vector(verts, n, robust=bool(robust))
    out = np.stack([np.asarray(f[i].numpy(), dtype=np.float64) for i in range(3)], axis=-1)
    return out.reshape(*batch, 3)


def shading_frame(normal: Any) -> np.ndarray:
    """Orthonormal right-handed frame ``(..., 3, 3)`` with rows ``(t, b, n)`` for normals
    ``(..., 3)`` (normalised here; float64).

    Tangent choice: Duff et al. 2017, listing 3 (branch-free, continuous except at
    ``n_z = 0`` crossings): with ``s = sign(n_z)`` (+1 at 0), ``a = -1 / (s + n_z)``,
    ``b = n_x n_y a``: ``t = (1 + s n_x^2 a, s b, -s n_x)``, ``b = (b, s + n_y^2 a, -n_y)``;
    ``t x b = n``. This is Mitsuba's ``coordinate_system`` (``mi.Frame3f(n)``: ``s = t``,
    ``t = b``), so local coordinates agree with ``mi.Frame3f(n).to_local``. Raises
    :class:`~glossrt.errors.GlossrtError` for zero-length or non-finite normals."""
    n = np.asarray(normal, dtype=np.float64)
    if n.ndim < 1 or n.shape[-1] != 3:
        raise GlossrtError(f"normals must have shape (..., 3), got {n.shape}")
    length = np.linalg.norm(n, axis=-1, keepdims=True)
    if not (np.isfinite(n).all() and np.all(length > 0)):
        raise GlossrtError("normals must be finite and non-zero")
    n = n / length
    x, y, z = n[..., 0], n[..., 1], n[..., 2]
    s = np.where(z >= 0, 1.0, -1.0)
    # Duff et al. 2017, listing 3
    a = -1.0 / (s + z)
    b = x * y * a
    t = np.stack([1.0 + s * x * x * a, s * b, -s * x], axis=-1)
    bt = np.stack([b, s + y * y * a, -y], axis=-1)
    return np.stack([t, bt, n], axis=-2)


def to_local(vertices_world: Any, position: Any, normal: Any) -> np.ndarray:
    """World-space polygon vertices ``(..., K, 3)`` relative to shading points ``position``
    ``(..., 3)`` in the local frame of ``normal`` ``(..., 3)`` (:func:`shading_frame`: a
    rotation, so windings and one-sidedness are preserved); leading axes broadcast. Returns
    ``(..., K, 3)`` float64, ready for :func:`clamped_cosine_integral`."""
    v = np.asarray(vertices_world, dtype=np.float64)
    p = np.asarray(position, dtype=np.float64)
    if v.ndim < 2 or v.shape[-1] != 3:
        raise GlossrtError(f"polygon vertices must have shape (..., K, 3), got {v.shape}")
    if p.ndim < 1 or p.shape[-1] != 3:
        raise GlossrtError(f"positions must have shape (..., 3), got {p.shape}")
    frame = shading_frame(normal)
    d = v - p[..., None, :]
    return np.einsum("...ij,...kj->...ki", frame, d)
