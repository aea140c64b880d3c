"""Polygon-light shading with linearly transformed cosines (Heitz, Dupuy, Hill, Neubelt 2016,
"Real-Time Polygonal-Light Shading with Linearly Transformed Cosines"), using glossrt's own
LTC fit of GGX (:mod:`glossrt.lights.ltc.fit`) and polygon integration
(:mod:`glossrt.lights.polygon`).

For a shading point with normal ``n``, view ``wo`` and GGX ``alpha``, in the frame whose x axis
is ``wo``'s projection on the tangent plane (``T1 = normalize(wo - n (n.wo))``, ``T2 = n x
T1``, z = ``n``) the LTC fit gives ``M^-1`` (4 coefficients), the directional albedo ``norm``
and the Fresnel moment ``fres``. Then (Heitz et al. 2016, sec. 3-4):

* ``int_P D(w) dw = int_{M^-1 P} D_o(w) dw``: the clamped-cosine integral of the polygon
  transformed by ``M^-1`` (:func:`glossrt.lights.polygon.cosine_integral`);
* specular: ``int_P f_s cos dw ~= (F0 (norm - fres) + fres) int_{M^-1 P} D_o`` (Schlick's F,
  split as in the fit);
* diffuse (Lambert): ``int_P (albedo / pi) cos dw = albedo int_P D_o`` (identity transform).

Textured lights (Heitz et al. 2016, sec. 5.3 "textured polygonal lights"): the integral above
times the light's texture prefiltered over the footprint of the (transformed) cosine lobe on
the light, looked up where the vector form factor ``F`` of the transformed polygon (its mean
direction, :func:`glossrt.lights.polygon.form_factor_vector`) meets the light's plane, at a
level of detail set by the distance ``d`` of that plane along ``F`` relative to the polygon's
size in the transformed space: ``sigma_uv = c d / sqrt(A)`` (glossrt's form of the idea: the
paper does not give its constants; ``c`` = :data:`FOOTPRINT_SCALE`, fitted against Monte
Carlo on several textures and roughnesses by
:func:`glossrt.experiments.ltc.texture_footprint`, docs/RESULTS.md).
:class:`PrefilteredTexture` stores Gaussian-filtered levels (normalised convolution over a
padded domain, so the average only counts texels inside the light and lookups slightly
outside the polygon see its edge colours; each level centred on the texels its bilinear
lookup reads) and blends the two levels that bracket the width linearly in ``log2`` of it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import drjit as dr
import numpy as np

from ...backend import mi
from ...errors import FrameError, GlossrtError
from ...images import check_frame, merge
from ...jit import no_gc, opaque
from ..polygon import K_MAX, K_MIN, cosine_integral, form_factor_vector
from ..shading import (
    NEEDS,
    ShadingPoints,
    f0_tensor,
    light_vertices,
    refuse_anisotropic,
    shading_channels,
)
from .table import LTCTable

__all__ = ["PrefilteredTexture", "ltc_frame", "polygon_integral", "shade_frame", "shade_tensor"]


def _table():
    return LTCTable.load()


def ltc_frame(n: mi.Vector3f, wo: mi.Vector3f) -> tuple[mi.Vector3f, mi.Vector3f]:
    """``(T1, T2)``: ``T1`` along ``wo``'s projection on the tangent plane, ``T2 = n x T1``;
    for ``wo`` along ``n`` (isotropic: any tangent does) Mitsuba's ``coordinate_system``."""
    t = wo - n * dr.dot(n, wo)
    len2 = dr.squared_norm(t)
    fallback, _ = mi.coordinate_system(n)
    t1 = dr.select(len2 > 1e-12, t * dr.rsqrt(dr.maximum(len2, 1e-30)), fallback)
    return t1, dr.cross(n, t1)


def _local(verts_world: Sequence, p, t1, t2, n) -> list:
    out = []
    for v in verts_world:
        d = v - p
        out.append(mi.Vector3f(dr.dot(d, t1), dr.dot(d, t2), dr.dot(d, n)))
    return out


def _apply_minv(coeffs, verts: list) -> list:
    """``M^-1 v`` with Heitz's canonical ``M^-1 = [[a, 0, b], [0, 1, 0], [c, 0, d]]``
    (divided by its middle element, :func:`glossrt.lights.ltc.table.minv_matrix`)."""
    a, b, c, d = coeffs
    return [mi.Vector3f(a * v.x + b * v.z, v.y, c * v.x + d * v.z) for v in verts]


def _mask(beckmann) -> mi.Bool | None:
    """A per-lane Beckmann mask for table lookups (``None``: every lane GGX)."""
    if isinstance(beckmann, bool):
        return mi.Bool(True) if beckmann else None
    return beckmann


def _integrals(local: list, coeffs, two_sided):
    """(diffuse, specular) clamped-cosine integrals: identity and ``M^-1``-transformed."""
    i_d = cosine_integral(local, None, two_sided)
    i_s = cosine_integral(_apply_minv(coeffs, local), None, two_sided)
    return i_d, i_s


def polygon_integral(vertices, normal, view, alpha, two_sided: bool = True,
                     table=None, distribution: str = "ggx") -> np.ndarray:
    """Integral over the polygon of the microfacet BRDF (``distribution`` ``"ggx"`` or
    ``"beckmann"``, Mitsuba's separable Smith term, Fresnel = 1) times the clamped cosine, by
    LTC: ``norm * int_{M^-1 P} D_o``.

    NumPy in and out, batched over leading axes: ``vertices`` (..., K, 3) *relative to the
    shading point* (world axes, 3 <= K <= 8), ``normal`` and ``view`` (..., 3) unit vectors
    (``view`` points away from the surface, towards the eye), ``alpha`` (...). Returns (...).
    One-sided polygons emit towards their counter-clockwise side (see
    :mod:`glossrt.lights.polygon`). ``table``: an :class:`~glossrt.lights.ltc.table.LTCTable`
    (default: glossrt's shipped fits), e.g. another fit to compare (a table of one
    distribution is used as it is).

    >>> import numpy as np
    >>> from glossrt.lights.ltc import polygon_integral
    >>> quad = np.array([[-1, -1, 2], [1, -1, 2], [1, 1, 2], [-1, 1, 2.0]])
    >>> v = polygon_integral(quad, [0, 0, 1.0], [0, 0, 1.0], 0.3)  # doctest: +SKIP
    """
    try:
        verts = np.asarray(vertices, np.float64)
        n = np.asarray(normal, np.float64)
        wo = np.asarray(view, np.float64)
        a = np.asarray(alpha, np.float64)
    except (TypeError, ValueError) as e:
        raise GlossrtError(f"polygon_integral: inputs must be numeric arrays: {e}") from e
    if distribution not in ("ggx", "beckmann"):
        raise GlossrtError(f"polygon_integral: distribution must be 'ggx' or 'beckmann', "
                           f"got {distribution!r}")
    if verts.ndim < 2 or verts.shape[-1] != 3 or not K_MIN <= verts.shape[-2] <= K_MAX:
        raise GlossrtError(f"polygon_integral: vertices must be (..., K, 3) with "
                           f"{K_MIN} <= K <= {K_MAX}, got {verts.shape}")
    batch = np.broadcast_shapes(verts.shape[:-2], n.shape[:-1], wo.shape[:-1], a.shape)
    for name, arr in (("vertices", verts), ("normal", n), ("view", wo), ("alpha", a)):
        if not np.all(np.isfinite(arr)):
            raise GlossrtError(f"polygon_integral: {name} contains NaN or Inf")
    if np.any(a < 0):
        raise GlossrtError(f"polygon_integral: alpha must be >= 0, got {float(a.min()):g}")
    k = verts.shape[-2]
    verts = np.broadcast_to(verts, (*batch, k, 3)).reshape(-1, k, 3)
    n = np.broadcast_to(n, (*batch, 3)).reshape(-1, 3)
    wo = np.broadcast_to(wo, (*batch, 3)).reshape(-1, 3)
    a = np.broadcast_to(a, batch).reshape(-1)
    nn = np.linalg.norm(n, axis=-1, keepdims=True)
    if np.any(nn < 1e-12):
        raise GlossrtError("polygon_integral: zero normal")
    n = n / nn
    wo = wo / np.maximum(np.linalg.norm(wo, axis=-1, keepdims=True), 1e-300)
    # scale each polygon so its largest coordinate is ~1 (the integral is scale invariant)
    scale = np.maximum(np.abs(verts).max(axis=(1, 2)), 1e-300)[:, None, None]
    verts = verts / scale
    _check_planar(verts)
    # the shading frame and M^-1 in float64: the integral depends on the polygon's shape and
    # distance only through their ratio, so a light seen nearly edge-on (its plane 2e-6 of
    # its size from the shading point) is as well defined as any other; float32 vertices
    # would put such planes within rounding of the point (polygon.PLANE_TOL_ULPS: 0)
    t1, t2 = _ltc_frame_np(n, wo)
    local = np.einsum("pkc,pjc->pkj", verts, np.stack([t1, t2, n], 1))  # (T1, T2, n) coords
    cos_o = np.clip(np.sum(n * wo, -1), 0.0, 1.0)
    coeffs, norm, _ = (table or _table()).lookup(
        mi.Float(a.astype(np.float32)), mi.Float(cos_o.astype(np.float32)),
        _mask(distribution == "beckmann"))
    c = np.array(coeffs, dtype=np.float64).reshape(4, -1)
    tx = c[0][:, None] * local[..., 0] + c[1][:, None] * local[..., 2]
    tz = c[2][:, None] * local[..., 0] + c[3][:, None] * local[..., 2]
    transformed = np.stack([tx, local[..., 1], tz], -1)  # M^-1 v (_apply_minv)

    def vec(x):
        return mi.Vector3d(*(mi.Float64(np.ascontiguousarray(x[:, c_])) for c_ in range(3)))

    i_s = np.array(cosine_integral([vec(transformed[:, j]) for j in range(k)], None,
                                   two_sided), dtype=np.float64)
    out = np.array(norm, dtype=np.float64) * i_s
    out[np.sum(n * wo, -1) <= 0] = 0.0  # view below the surface: no reflection
    return out.reshape(batch)


def _ltc_frame_np(n: np.ndarray, wo: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Float64 :func:`ltc_frame` for (P, 3) unit ``n`` and ``wo``: ``T1`` along ``wo``'s
    projection on the tangent plane, ``T2 = n x T1``; ``wo`` along ``n``: the tangents of
    Mitsuba's ``coordinate_system`` (Duff et al. 2017, listing 3)."""
    t = wo - n * np.sum(n * wo, -1, keepdims=True)
    len2 = np.sum(t * t, -1, keepdims=True)
    x, y, z = n[:, 0], n[:, 1], n[:, 2]
    sign = np.where(z >= 0.0, 1.0, -1.0)
    aa = -1.0 / (sign + z)
    b = x * y * aa
    fallback = np.stack([1.0 + sign * x * x * aa, sign * b, -sign * x], -1)
    t1 = np.where(len2 > 1e-12, t / np.sqrt(np.maximum(len2, 1e-300)), fallback)
    return t1, np.cross(n, t1)


def _check_planar(verts: np.ndarray) -> None:
    """GlossrtError unless every polygon of ``verts`` (P, K, 3) is planar within the
    tolerance the scene loader gives mesh lights (:data:`glossrt.lights.scene.PLANE_TOL` of
    its size: the largest distance of a vertex from the best-fit plane)."""
    from ..scene import PLANE_TOL

    if verts.shape[1] == 3:
        return
    centre = verts.mean(1, keepdims=True)
    _, _, vt = np.linalg.svd(verts - centre, full_matrices=False)
    off = np.abs(np.einsum("pkc,pc->pk", verts - centre, vt[:, 2])).max(1)
    size = np.linalg.norm(verts.max(1) - verts.min(1), axis=-1)
    bad = off > PLANE_TOL * size
    if np.any(bad):
        i = int(np.argmax(bad))
        raise GlossrtError(
            f"polygon_integral: polygon {i} is not planar (a vertex lies {off[i] / size[i]:.3g}"
            f" of its size off its best-fit plane, more than {PLANE_TOL:g}); split it into "
            "planar pieces")


def strided_gaussian(n: int, sigma: float, step: int, truncate: float = 4.0,
                     centred: bool = False) -> np.ndarray:
    """The 1D Gaussian filter of ``scipy.ndimage.gaussian_filter`` (same truncation radius
    ``int(truncate sigma + 0.5)``, weights normalised over it, zeros outside the signal:
    ``mode="constant"``) as a matrix evaluated at every ``step``-th sample: shape
    ``(ceil(n / step), n)``, float64. ``centred=True``: evaluated instead at the centres of
    the ``ceil(n / step)`` texels a texture of that many samples spreads over the same
    domain (sample ``j`` at ``(j + 0.5) n / m - 0.5``), where a bilinear lookup reads them;
    the every-``step``-th samples sit ``(step - 1) / 2`` texels off those centres."""
    r = int(truncate * float(sigma) + 0.5)
    m = -(-n // step)
    out = (np.arange(m) + 0.5) * (n / m) - 0.5 if centred else np.arange(0, n, step)
    d = np.arange(n)[None, :] - out[:, None]
    w = np.exp(-0.5 * (d / float(sigma)) ** 2)
    w[np.abs(d) > r + (0.5 if centred else 0.0)] = 0.0
    x = np.arange(-r, r + 1)
    return w / np.exp(-0.5 * (x / float(sigma)) ** 2).sum()


#: the scale ``c`` of the prefiltered lookup's filter width ``sigma_uv = c d / sqrt(A)``
#: (module docstring), fitted against Monte Carlo by
#: :func:`glossrt.experiments.ltc.texture_footprint` (docs/RESULTS.md)
FOOTPRINT_SCALE = 0.63


class PrefilteredTexture:
    """A light texture filtered for LTC lookups (module docstring): level ``k`` is the
    normalised Gaussian convolution (sigma ``2^k`` texels of the base level) of the texture
    padded by ``pad`` of its size on each side, stored at ``1 / 2^k`` resolution; ``eval(uv,
    sigma_uv)`` blends the two levels around the requested filter width (in uv units, the
    light's texture spans [0, 1]^2) and returns RGB.

    ``scale``: the footprint scale ``c`` of the lookups made for LTC shading (``sigma_uv =
    c d / sqrt(A)``; default :data:`FOOTPRINT_SCALE`). ``blend``: ``"log"`` (default)
    interpolates linearly in ``log2 sigma`` between the two levels that bracket it, as
    trilinear mipmapping does (the levels' widths double from one to the next, so the level
    index is ``log2`` of the width in texels); ``"linear"`` interpolates linearly in
    ``sigma`` (kept for comparison: between level 0 and level 1 it weights the sharp level
    too little, and in general it leans to the coarser level)."""

    def __init__(self, image: np.ndarray, pad: float = 0.5, levels: int | None = None,
                 scale: float | None = None, blend: str = "log"):
        if blend not in ("log", "linear"):
            raise GlossrtError(f"blend must be 'log' or 'linear', got {blend!r}")
        self.scale = FOOTPRINT_SCALE if scale is None else float(scale)
        if not (math.isfinite(self.scale) and self.scale > 0):
            raise GlossrtError(f"footprint scale must be a positive number, got {scale!r}")
        self.blend = blend
        img = np.asarray(image, np.float32)
        if img.ndim != 3 or img.shape[2] != 3 or min(img.shape[:2]) < 1:
            raise GlossrtError(f"light texture must be (H, W, 3), got {img.shape}")
        if not np.all(np.isfinite(img)):
            raise GlossrtError("light texture contains NaN or Inf")
        h, w = img.shape[:2]
        self.texels = max(h, w)
        self.pad = float(pad)
        ph, pw = int(math.ceil(h * pad)), int(math.ceil(w * pad))
        data = np.zeros((h + 2 * ph, w + 2 * pw, 3), np.float32)
        mask = np.zeros(data.shape[:2], np.float32)
        data[ph:ph + h, pw:pw + w] = img
        mask[ph:ph + h, pw:pw + w] = 1.0
        # uv of the padded domain: [-pad', 1 + pad'] with pad' = ph / h (rounded up)
        self.lo = (-pw / w, -ph / h)
        self.span = ((w + 2 * pw) / w, (h + 2 * ph) / h)
        # up to sigma = 4x the texture size: the widest level is ~ the light's mean colour
        n_levels = levels or max(1, int(math.log2(max(h, w))) + 3)
        self.sigmas, self.textures = [], []
        for k in range(n_levels):
            sigma = 0.0 if k == 0 else 2.0 ** k
            step = 2 ** k
            if sigma > 0:
                # the Gaussian at every step-th texel only (what the level keeps): separable
                # strided matrices, not a full-resolution filter of radius 4 sigma
                # centred on the texels a bilinear lookup reads (a level filtered at
                # every step-th texel would sit (step - 1) / 2 texels off the base level)
                gy = strided_gaussian(data.shape[0], sigma, step, centred=True)
                gx = strided_gaussian(data.shape[1], sigma, step, centred=True)
                num = np.stack([gy @ (data[..., c] * mask) @ gx.T for c in range(3)], -1)
                den = (gy @ mask @ gx.T)[..., None]
                lvl = np.where(den > 1e-6, num / np.maximum(den, 1e-6), 0.0)
            else:
                # level 0: the texture, with edge colours continued into the padding
                lvl = np.pad(img, ((ph, ph), (pw, pw), (0, 0)), mode="edge")
            self.sigmas.append(sigma / max(h, w))  # filter width in uv units
            self.textures.append(mi.Texture2f(mi.TensorXf(np.ascontiguousarray(
                lvl, np.float32)), filter_mode=dr.FilterMode.Linear,
                wrap_mode=dr.WrapMode.Clamp))

    def eval(self, uv: mi.Point2f, sigma_uv: mi.Float) -> mi.Color3f:
        """Trilinear lookup: the two levels whose filter widths bracket ``sigma_uv``
        (blended as ``blend`` says; below level 1's width in ``"log"``: down to 1 texel,
        the base level's own bilinear footprint, the blend runs from level 0; under that,
        level 0)."""
        p = mi.Point2f((uv.x - self.lo[0]) / self.span[0], (uv.y - self.lo[1]) / self.span[1])
        vals = [t.eval(p) for t in self.textures]
        cols = [mi.Color3f(v[0], v[1], v[2]) for v in vals]
        out = cols[0]
        if self.blend == "log":
            # the level index: level k has width 2^k texels (k >= 1), level 0 counts as 1
            # texel; linear in log2(sigma) between consecutive levels, beyond the last: it
            lod = dr.log2(dr.maximum(sigma_uv * self.texels, 1e-30))
            for k in range(1, len(cols)):
                t = dr.clip(lod - (k - 1), 0.0, 1.0)
                out = dr.select(lod > k - 1, dr.lerp(cols[k - 1], cols[k], t), out)
            return out
        # piecewise-linear in sigma between consecutive levels; beyond the last: the last
        for k in range(1, len(cols)):
            s0, s1 = self.sigmas[k - 1], self.sigmas[k]
            t = dr.clip((sigma_uv - s0) / (s1 - s0), 0.0, 1.0)
            out = dr.select(sigma_uv > s0, dr.lerp(cols[k - 1], cols[k], t), out)
        return out


def _tex_plane(verts: list) -> tuple:
    """The whole light's plane data for :func:`_tex_eval`: ``(v0, e1, e2, unit normal, area)``
    of the (possibly ``M^-1``-transformed) local polygon, as in :func:`_texture_lookup`."""
    e1, e2 = verts[1] - verts[0], verts[len(verts) - 1] - verts[0]
    area = dr.zeros(mi.Float, dr.width(verts[0]))
    for j in range(1, len(verts) - 1):
        area = area + 0.5 * dr.norm(dr.cross(verts[j] - verts[0], verts[j + 1] - verts[0]))
    return (mi.Vector3f(verts[0]), mi.Vector3f(e1), mi.Vector3f(e2),
            dr.normalize(dr.cross(e1, e2)), area)


def _tex_eval(uv: tuple, tex: PrefilteredTexture, plane: tuple, f: mi.Vector3f) -> mi.Color3f:
    """Heitz et al. 2016, sec. 5.3, for a vector form factor ``f`` (of the whole polygon,
    or of a piece of it: BSPVT shadows) and the whole light's ``plane`` (:func:`_tex_plane`): the
    prefiltered texture where ``f`` meets the plane, uv by the light's affine map (``uv``:
    opaque ``(u0, v0, u1, v1, ul, vl)`` at its vertices 0, 1 and last), filter width
    ``c |t| / sqrt(area)`` (``c``: the texture's footprint ``scale``)."""
    v0, e1, e2, nrm, area = plane
    dirn = dr.normalize(f)
    denom = dr.dot(dirn, nrm)
    t = dr.dot(v0, nrm) / dr.select(dr.abs(denom) > 1e-8, denom, 1e-8)
    r = dirn * t - v0
    g11, g12, g22 = dr.dot(e1, e1), dr.dot(e1, e2), dr.dot(e2, e2)
    b1, b2 = dr.dot(r, e1), dr.dot(r, e2)
    det = dr.maximum(g11 * g22 - g12 * g12, 1e-30)
    s = (g22 * b1 - g12 * b2) / det
    q = (g11 * b2 - g12 * b1) / det
    u0, w0, u1, w1, ul, wl = uv
    u = u0 + s * (u1 - u0) + q * (ul - u0)
    v = w0 + s * (w1 - w0) + q * (wl - w0)
    # Heitz et al. 2016, sec. 5.3: the filter width grows with the distance to the light's
    # plane relative to the light's size; c fitted against Monte Carlo (FOOTPRINT_SCALE)
    sigma_uv = tex.scale * dr.abs(t) / dr.sqrt(dr.maximum(area, 1e-30))
    return tex.eval(mi.Point2f(u, v), sigma_uv)


def light_uv(light) -> tuple:
    """A textured light's uv at its vertices 0, 1 and last, as opaque scalars for
    :func:`_tex_eval`."""
    uv = np.asarray(light.uv, np.float64)
    return tuple(opaque([uv[0][0], uv[0][1], uv[1][0], uv[1][1], uv[-1][0], uv[-1][1]]))


def _texture_lookup(light, tex: PrefilteredTexture, local: list, coeffs) -> mi.Color3f:
    """Heitz et al. 2016, sec. 5.3: the prefiltered texture where the transformed polygon's
    vector form factor points, at a width from its distance and size (module docstring)."""
    verts = local if coeffs is None else _apply_minv(coeffs, local)
    return _tex_eval(light_uv(light), tex, _tex_plane(verts), form_factor_vector(verts))


def prefiltered(light, cache: dict) -> tuple | None:
    """``(light, PrefilteredTexture)`` for a textured light (built once per texture and kept
    in ``cache``, keyed by the texture's id), ``None`` for an untextured one."""
    img = getattr(light, "texture", None)
    if img is None:
        return None
    if id(img) not in cache:
        cache[id(img)] = PrefilteredTexture(img)
    return light, cache[id(img)]


def _finite(c: mi.Color3f) -> mi.Color3f:
    return dr.select(dr.isfinite(c[0] + c[1] + c[2]), c, 0.0)


def _shade(sp: ShadingPoints, table, lights: list, two_sided: Sequence[bool],
           textures: Sequence = ()) -> mi.Color3f:
    """LTC direct light per lane (module docstring): ``lights`` a list of (world vertices as
    ``mi.Point3f``, radiance ``mi.Color3f``), ``textures`` per light ``(light, prefiltered)``
    or ``None``."""
    t1, t2 = ltc_frame(sp.n, sp.wo)
    cos_o = dr.clip(dr.dot(sp.n, sp.wo), 0.0, 1.0)
    coeffs, norm, fres = table.lookup(sp.alpha, cos_o, _mask(sp.beckmann))
    # the fit's split sum: int f F cos per unit D integral (Schlick, or the exact term)
    spec_w = sp.spec_weight(norm, fres)
    total = dr.zeros(mi.Color3f, dr.width(sp.p))
    for k, (world, le) in enumerate(lights):
        local = _local(world, sp.p, t1, t2, sp.n)
        i_d, i_s = _integrals(local, coeffs, bool(two_sided[k]))
        tex = textures[k] if k < len(textures) else None
        if tex is not None:
            # points on the light's own plane (the light's pixels) have no lookup direction:
            # their integrals are 0, and so must the colour be (not NaN)
            col_d = le * _finite(_texture_lookup(tex[0], tex[1], local, None))
            col_s = le * _finite(_texture_lookup(tex[0], tex[1], local, coeffs))
        else:
            col_d = col_s = le
        total += col_d * (sp.albedo * i_d) + col_s * (spec_w * i_s)
    return dr.select(sp.hit, total, 0.0)


def _device_lights(lights: list) -> tuple[list, tuple[bool, ...]]:
    """World vertices and radiance of ``lights`` as opaque Dr.Jit values (a moving light does
    not recompile kernels), and their two-sidedness."""
    dev = [([mi.Point3f(*opaque(p)) for p in light_vertices(lt)],
            mi.Color3f(*opaque(np.asarray(lt.radiance, float).ravel()[:3]))) for lt in lights]
    return dev, tuple(bool(getattr(lt, "two_sided", False)) for lt in lights)


def _shade_kernel(ch: dict, cam: list, lights: list, two_sided: tuple, table,
                  size: tuple[int, int]) -> mi.TensorXf:
    # ``size`` (H, W) is an explicit argument, part of dr.freeze's key: a recording made for
    # another image size can otherwise be replayed with that size baked in
    h, w = size
    sp = ShadingPoints.at_camera(ch, cam)
    total = _shade(sp, table, lights, two_sided)
    return merge([total[0], total[1], total[2]], h, w)


_shade_frozen = dr.freeze(_shade_kernel, warn_after=16)


def shade_tensor(frame, lights: list, f0: np.ndarray | None = None,
                 textures: dict | None = None, frozen: bool = False) -> mi.TensorXf:
    """:func:`shade_frame` as an (H, W, 3) ``mi.TensorXf`` left on the device.

    ``frozen=True`` records the shading kernels once with ``dr.freeze`` and replays them for
    later frames of the same size and light set (only the G-buffer, camera and light
    positions change): the real-time path, without Python's per-frame tracing overhead.
    Textured lights are always traced anew (their prefiltered textures are not frozen)."""
    check_frame(frame, NEEDS)
    refuse_anisotropic(frame, "LTC shading")
    dev, two = _device_lights(lights)
    f0_t = f0_tensor(frame, f0)
    has_tex = any(getattr(lt, "texture", None) is not None for lt in lights)
    if frozen and not has_tex:
        if frame.camera is None:
            raise FrameError(f"{frame.where}: polygon-light shading needs the camera")
        ch = shading_channels(frame)
        ch["f0"] = f0_t
        with no_gc():
            return _shade_frozen(ch, opaque(frame.camera.position), dev, two, _table(),
                                 (frame.height, frame.width))
    sp = ShadingPoints.of(frame, f0)
    cache = {} if textures is None else textures
    total = _shade(sp, _table(), dev, two, [prefiltered(lt, cache) for lt in lights])
    return merge([total[0], total[1], total[2]], frame.height, frame.width)


def shade_frame(frame, lights: list, f0: np.ndarray | None = None,
                textures: dict | None = None, frozen: bool = False) -> np.ndarray:
    """Direct light (H, W, 3) of ``frame``'s G-buffer from the polygon ``lights`` by LTC:
    GGX or Beckmann specular (the ``distribution`` channel) with Schlick Fresnel (``f0`` per
    pixel, see :func:`glossrt.lights.shading.f0_image`; default 0) plus Lambertian diffuse
    (``albedo_diffuse``), unshadowed. Lights: objects with ``vertices`` (K, 3) world space,
    ``radiance`` RGB, ``two_sided``, optional ``texture`` (H, W, 3) and ``uv`` (K, 2)
    (:class:`glossrt.lights.scene.PolygonLight`). ``textures``: a cache {id(light texture):
    PrefilteredTexture} reused across frames. ``frozen``: see :func:`shade_tensor`."""
    out = shade_tensor(frame, lights, f0, textures, frozen)
    return np.array(out, dtype=np.float32).reshape(frame.height, frame.width, 3)
