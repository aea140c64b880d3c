"""Light environment cube maps (Kimura & Tokoi 2004, issue 7): the scene's polygon lights
rendered into a cube map as seen from a probe point, bounding spheres for culling, and the
filtered-importance-sampling level of detail used to read pre-filtered levels.

M. Kimura, K. Tokoi, "Highlight generation considering both of light source shape and the
roughness on the surface using GPU" (in Japanese):

* sec. 3: the lights are polygon models; the shape a highlight reflects is taken from an
  environment map in which the lights are rendered as seen from the lit position (fig. 2).
  :meth:`LightCubeMap.render` is that map: for each texel the radiance of the first polygon
  light its ray from ``probe`` meets, black elsewhere (only lights are in the map). The
  probe is by default each object's centre (:func:`probe_points`; the paper renders one map
  per object, sec. 7 uses 256 x 256 maps).
* sec. 6: each light is wrapped in a sphere somewhat larger than the light, one sphere per
  surface roughness, and a pixel computes its highlight only where the mirror direction of
  the view about the (reference) normal points into a sphere. Here the spheres are the
  lights' smallest enclosing spheres (:func:`light_spheres`) and the enlargement is made
  exact per pixel as a cone test (:func:`cull_mask`): keep the pixel when the angle between
  the mirror direction and the direction to the sphere's centre is at most the sphere's
  angular radius plus the lobe's angular spread (:func:`lobe_spread`: twice a quantile
  angle of the microfacet normals, since reflection doubles the normal's deviation).
* Beyond the paper: pre-filtered levels (a mip chain) and :func:`fis_lod`, the level that
  filtered importance sampling (Colbert & Krivanek 2007, GPU Gems 3 ch. 20) reads for a
  sample of density ``pdf``.

**Probe grids** (beyond the paper; :func:`probe_grids`, :class:`ProbeGridMaps`): several
probes per large object on a grid over its bounding box, each pixel blending the maps of
the probes around its surface point (trilinear); the maps are rendered on the device, only
the faces from which some light's bounding sphere can be seen (:func:`_faces_seen`), and
kept on the device (one level: what the ellipsoidal estimator reads).

**Cube conventions** are glossrt's (:mod:`glossrt.lights.cubemap`): faces ``f = 0..5`` = +X,
-X, +Y, -Y, +Z, -Z, axis ``k = f // 2``, sign ``sg = +1`` for even ``f``, in-face axes
``u = (k + 1) % 3``, ``v = (k + 2) % 3``; gnomonic ``s = d[u] / (sg d[k])``, ``t = d[v] /
(sg d[k])``; ties between faces go to the lowest face index; texel ``(i, j)`` (``i`` along
``s``) has centre ``s = -1 + (2i + 1)/R`` and is stored at ``[face, j, i]``.

**Rendering** (Dr.Jit, one lane per texel sample): ``supersample x supersample`` samples per
texel on a regular grid (the centres of the sub-squares of the texel in ``(s, t)``),
averaged: a texel on a light's edge holds the covered fraction of its samples (anti-aliased
edges). A ray sees the *nearest* light it meets, whichever side faces it; a one-sided light
seen from behind is black and hides the lights behind it (as Mitsuba's area-light
rectangles do, whose back is an opaque black surface). The emitted radiance, texture
included, is :class:`glossrt.lights.mc._Light`'s (the Monte Carlo reference's): radiance x
the bilinear (clamped) texture at the hit point's uv, uv the affine map of the first three
vertices. No lights: a black map (not an error).

**Levels** (:func:`mip_chain`): level ``l + 1`` has ``ceil(R_l / 2)`` texels a side, down to
1 x 1. Each face is filtered on its own (no filtering across face edges); a coarse texel is
the *solid-angle-weighted* mean of the fine texels it covers (a 2 x 2 box for even ``R_l``;
for odd ``R_l`` the fine texels on the split line count with their covered fraction), so the
solid-angle integral of the map, ``sum Omega_texel L_texel``, is the same at every level
(exactly for even ``R_l``: the exact solid angles of four texels add up to their parent's).

**Lookup** (:meth:`LightCubeMap.lookup`, Dr.Jit; :meth:`LightCubeMap.lookup_np`, NumPy):
face and ``(s, t)`` from the direction, bilinear between the four nearest texel centres of
the face, *clamped at the face edges*: within half a texel of a face edge the lookup reads
that edge's texels only (no blending with the neighbouring face: a seam of up to half a
texel, wider at coarse levels, where a 1 x 1 face is a single value); linear between the two
levels around a fractional ``lod`` (trilinear), ``lod`` clamped to ``[0, levels - 1]``
(NaN reads level 0). Zero, NaN or Inf directions read 0.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import drjit as dr
import numpy as np

from ...backend import mi
from ...errors import GlossrtError
from ...jit import opaque, owned, owned_float
from ..cubemap import cube_coords
from ..shading import light_vertices

__all__ = [
    "CubeMapSet",
    "DEFAULT_PROBES",
    "DEFAULT_RESOLUTION",
    "LightCubeMap",
    "cull_mask",
    "fis_lod",
    "level_resolutions",
    "light_spheres",
    "lobe_spread",
    "mip_chain",
    "ProbeGrid",
    "ProbeGridMaps",
    "grid_lookup",
    "probe_grids",
    "probe_points",
    "texel_solid_angles",
]

#: default base resolution (texels per face side)
DEFAULT_RESOLUTION = 128
#: largest base resolution accepted
MAX_RESOLUTION = 2048
#: largest supersampling factor accepted (samples per texel side)
MAX_SUPERSAMPLE = 16
#: texel samples (lanes) per rendering launch
MAX_LANES = 1 << 22
#: relative enlargement of the smallest enclosing sphere (keeps the vertices inside it
#: despite rounding)
SPHERE_EPS = 1e-9


# -- checks ------------------------------------------------------------------------------------

def _check_int(name: str, value, lo: int, hi: int) -> int:
    try:
        r = int(value)
    except (TypeError, ValueError):
        raise GlossrtError(f"{name} must be an integer, got {value!r}") from None
    if r != value or not lo <= r <= hi:
        raise GlossrtError(f"{name} must be an integer in {lo}..{hi}, got {value!r}")
    return r


def _check_point(name: str, p) -> np.ndarray:
    try:
        a = np.asarray(p, dtype=np.float64)
    except (TypeError, ValueError):
        raise GlossrtError(f"{name} must be a 3-vector of numbers, got {p!r}") from None
    if a.shape != (3,):
        raise GlossrtError(f"{name} must have shape (3,), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise GlossrtError(f"{name} contains NaN or Inf: {a.tolist()}")
    return a


def level_resolutions(resolution: int, levels: int | None = None) -> list[int]:
    """Texels per face side of each level: ``R_0 = resolution``, ``R_{l+1} = ceil(R_l / 2)``,
    down to 1 (``levels=None``: the full chain) or ``levels`` of them."""
    r = _check_int("cube map resolution", resolution, 1, MAX_RESOLUTION)
    res = [r]
    while res[-1] > 1:
        res.append((res[-1] + 1) // 2)
    if levels is None:
        return res
    n = _check_int("levels", levels, 1, len(res))
    return res[:n]


# -- solid angles ----------------------------------------------------------------------------

def _corner_term(s: np.ndarray, t: np.ndarray) -> np.ndarray:
    # solid angle of the gnomonic rectangle [0, s] x [0, t] on a cube face at distance 1
    return np.arctan2(s * t, np.sqrt(s * s + t * t + 1.0))


def texel_solid_angles(resolution: int) -> np.ndarray:
    """``(R, R)`` float64 exact solid angle of each texel ``[j, i]`` of a face (the same on
    every face): ``Omega = A(s1, t1) - A(s0, t1) - A(s1, t0) + A(s0, t0)`` with
    ``A(s, t) = atan2(s t, sqrt(1 + s^2 + t^2))``, the integral of ``(1 + s^2 + t^2)^(-3/2)``
    over ``[0, s] x [0, t]``. The ``6 R^2`` texels sum to ``4 pi``."""
    r = _check_int("cube map resolution", resolution, 1, MAX_RESOLUTION)
    e = -1.0 + 2.0 * np.arange(r + 1) / r
    a = _corner_term(e[None, :], e[:, None])  # [t index, s index]
    return a[1:, 1:] - a[1:, :-1] - a[:-1, 1:] + a[:-1, :-1]


def _overlap(r_new: int, r_old: int) -> np.ndarray:
    """``(r_new, r_old)``: the fraction of each old texel (1D) inside each new one."""
    a = np.arange(r_new)[:, None]
    b = np.arange(r_old)[None, :]
    lo = np.maximum(a / r_new, b / r_old)
    hi = np.minimum((a + 1) / r_new, (b + 1) / r_old)
    return np.maximum(hi - lo, 0.0) * r_old


def mip_chain(base, levels: int | None = None) -> list[np.ndarray]:
    """The levels ``[(6, R_l, R_l, C)]`` float64 of a cube map ``base`` ``(6, R, R, C)``:
    each coarse texel the solid-angle-weighted mean of the fine texels it covers, faces
    filtered independently (see the module docstring)."""
    b = np.asarray(base, dtype=np.float64)
    if b.ndim != 4 or b.shape[0] != 6 or b.shape[1] != b.shape[2]:
        raise GlossrtError(f"cube map faces must have shape (6, R, R, C), got {b.shape}")
    if not np.all(np.isfinite(b)):
        raise GlossrtError("cube map faces contain NaN or Inf")
    res = level_resolutions(b.shape[1], levels)
    out = [b]
    for r_old, r_new in zip(res[:-1], res[1:], strict=False):
        w = _overlap(r_new, r_old)
        om = texel_solid_angles(r_old)
        # separable: rows then columns (two small matrix products per face and channel)
        weighted = om[None, :, :, None] * out[-1]
        num = np.einsum("aj,fjbc->fabc", w, np.einsum("bi,fjic->fjbc", w, weighted))
        den = w @ om @ w.T
        out.append(num / den[None, :, :, None])
    return out


# -- light cube map ----------------------------------------------------------------------------

def _dir_dr(face: mi.UInt32, s: mi.Float, t: mi.Float) -> mi.Vector3f:
    """``dir(f, s, t) = sg e_k + s e_u + t e_v`` per lane (cubemap.cube_dir)."""
    k = face // 2
    sg = dr.select((face & 1) == 0, 1.0, -1.0)
    comp = []
    for c in range(3):
        comp.append(dr.select(k == c, sg, dr.select((k + 1) % 3 == c, s, t)))
    return mi.Vector3f(*comp)


def _face_coords_dr(d: mi.Vector3f):
    """``(face, s, t, valid)`` of directions (cubemap.cube_coords, ties to the lowest
    face); ``valid`` is False for zero, NaN or Inf directions."""
    ax, ay, az = dr.abs(d.x), dr.abs(d.y), dr.abs(d.z)
    kx = (ax >= ay) & (ax >= az)
    ky = ~kx & (ay >= az)
    lead = dr.select(kx, d.x, dr.select(ky, d.y, d.z))
    du = dr.select(kx, d.y, dr.select(ky, d.z, d.x))
    dv = dr.select(kx, d.z, dr.select(ky, d.x, d.y))
    k = dr.select(kx, mi.UInt32(0), dr.select(ky, mi.UInt32(1), mi.UInt32(2)))
    face = 2 * k + dr.select(lead < 0, mi.UInt32(1), mi.UInt32(0))
    alead = dr.abs(lead)
    valid = (alead > 0) & dr.isfinite(alead) & dr.isfinite(du) & dr.isfinite(dv)
    inv = dr.rcp(dr.select(valid, alead, 1.0))
    s = dr.select(valid, du * inv, 0.0)
    t = dr.select(valid, dv * inv, 0.0)
    return face, s, t, valid


def _bilinear_dr(data: mi.Float, base: mi.UInt32, level: mi.UInt32, res_f: mi.Float,
                 res_u: mi.UInt32, off_u: mi.UInt32, face, s, t, active) -> mi.Color3f:
    r_u = dr.gather(mi.UInt32, res_u, level, active)
    r_f = dr.gather(mi.Float, res_f, level, active)
    off = dr.gather(mi.UInt32, off_u, level, active) + base
    top = r_f - 1.0
    x = dr.clip((s + 1.0) * 0.5 * r_f - 0.5, 0.0, top)
    y = dr.clip((t + 1.0) * 0.5 * r_f - 0.5, 0.0, top)
    x0f, y0f = dr.floor(x), dr.floor(y)
    fx, fy = x - x0f, y - y0f
    i0, j0 = mi.UInt32(x0f), mi.UInt32(y0f)
    i1 = dr.minimum(i0 + 1, r_u - 1)
    j1 = dr.minimum(j0 + 1, r_u - 1)
    row0 = off + (face * r_u + j0) * r_u
    row1 = off + (face * r_u + j1) * r_u

    def tex(idx):
        return dr.gather(mi.Color3f, data, idx, active)

    a = dr.lerp(tex(row0 + i0), tex(row0 + i1), fx)
    b = dr.lerp(tex(row1 + i0), tex(row1 + i1), fx)
    return dr.lerp(a, b, fy)


def _lookup_dr(data: mi.Float, base: mi.UInt32, active, tables, n_levels: int,
               d: mi.Vector3f, lod) -> mi.Color3f:
    res_f, res_u, off_u = tables
    face, s, t, valid = _face_coords_dr(mi.Vector3f(d))
    active = active & valid
    if isinstance(lod, (int, float)):
        lod = dr.opaque(mi.Float, float(lod))
    lod = mi.Float(lod)
    top = float(n_levels - 1)
    lod = dr.select(lod > 0.0, dr.minimum(lod, top), 0.0)  # NaN -> 0
    l0f = dr.floor(lod)
    frac = lod - l0f
    l0 = mi.UInt32(l0f)
    l1 = dr.minimum(l0 + 1, n_levels - 1)
    c0 = _bilinear_dr(data, base, l0, res_f, res_u, off_u, face, s, t, active)
    c1 = _bilinear_dr(data, base, l1, res_f, res_u, off_u, face, s, t, active & (frac > 0))
    out = dr.lerp(c0, c1, frac)
    return dr.select(active, out, 0.0)


def _bilinear_np(faces: np.ndarray, face, s, t) -> np.ndarray:
    r = faces.shape[1]
    x = np.clip((s + 1.0) * 0.5 * r - 0.5, 0.0, r - 1.0)
    y = np.clip((t + 1.0) * 0.5 * r - 0.5, 0.0, r - 1.0)
    i0 = np.floor(x).astype(np.int64)
    j0 = np.floor(y).astype(np.int64)
    fx, fy = (x - i0)[..., None], (y - j0)[..., None]
    i1, j1 = np.minimum(i0 + 1, r - 1), np.minimum(j0 + 1, r - 1)
    a = faces[face, j0, i0] * (1 - fx) + faces[face, j0, i1] * fx
    b = faces[face, j1, i0] * (1 - fx) + faces[face, j1, i1] * fx
    return a * (1 - fy) + b * fy


class LightCubeMap:
    """A light environment cube map with its pre-filtered levels.

    ``levels`` is the list of ``(6, R_l, R_l, 3)`` float32 arrays (NumPy, ``[face, j, i]``),
    level 0 the base; :attr:`data` holds them all as one flat ``mi.Float`` (levels in order,
    then face, row ``j``, column ``i``, RGB interleaved), :attr:`level_offsets` the first
    texel of each level in it. ``probe`` is the point the map was rendered from (None for
    maps made with :meth:`from_faces`)."""

    def __init__(self, levels: Sequence[np.ndarray], probe: np.ndarray | None = None):
        levels = [np.ascontiguousarray(np.asarray(lv, dtype=np.float32)) for lv in levels]
        if not levels:
            raise GlossrtError("a cube map needs at least one level")
        res = level_resolutions(levels[0].shape[1], len(levels))
        for lv, r in zip(levels, res, strict=True):
            if lv.shape != (6, r, r, 3):
                raise GlossrtError(f"cube map level must have shape (6, {r}, {r}, 3), got "
                                   f"{lv.shape}")
            if not np.all(np.isfinite(lv)):
                raise GlossrtError("cube map level contains NaN or Inf")
        self.levels = levels
        self.resolutions = res
        self.probe = None if probe is None else np.asarray(probe, dtype=np.float64)
        sizes = [6 * r * r for r in res]
        self.level_offsets = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
        self.texel_count = int(sum(sizes))
        self.flat = np.concatenate([lv.ravel() for lv in levels])
        self.data = owned_float(self.flat)
        self._tables = _tables(res, self.level_offsets)

    # -- construction ---------------------------------------------------------------------
    @classmethod
    def from_faces(cls, faces, levels: int | None = None,
                   probe: np.ndarray | None = None) -> LightCubeMap:
        """A map from its base level ``(6, R, R, 3)`` (``[face, j, i]``), with the
        pre-filtered levels of :func:`mip_chain` (``levels=None``: down to 1 x 1)."""
        f = np.asarray(faces, dtype=np.float64)
        if f.ndim != 4 or f.shape[-1] != 3:
            raise GlossrtError(f"cube map faces must have shape (6, R, R, 3), got {f.shape}")
        return cls(mip_chain(f, levels), probe)

    @classmethod
    def render(cls, lights: Sequence, probe, resolution: int = DEFAULT_RESOLUTION,
               levels: int | None = None, supersample: int = 2) -> LightCubeMap:
        """Render the polygon ``lights`` (:class:`glossrt.lights.scene.PolygonLight` or any
        object with ``vertices``, ``radiance``, ``two_sided``, optional ``texture``/``uv``)
        as seen from the point ``probe`` (3,): ``resolution`` texels per face side,
        ``supersample^2`` samples per texel (Kimura & Tokoi, sec. 3: the light environment
        map). See the module docstring for visibility, textures and levels."""
        p = _check_point("probe", probe)
        r = _check_int("cube map resolution", resolution, 1, MAX_RESOLUTION)
        ss = _check_int("supersample", supersample, 1, MAX_SUPERSAMPLE)
        level_resolutions(r, levels)  # checks levels
        base = _render_faces(list(lights), p, r, ss)
        return cls(mip_chain(base, levels), p)

    # -- properties -----------------------------------------------------------------------
    @property
    def resolution(self) -> int:
        """Texels per face side of the base level."""
        return self.resolutions[0]

    @property
    def n_levels(self) -> int:
        return len(self.levels)

    def solid_angle_texel(self, level: int = 0) -> float:
        """The average solid angle of a texel of ``level``, ``4 pi / (6 R_l^2)`` (Colbert &
        Krivanek's ``Omega_p``; :func:`texel_solid_angles` gives the exact ones)."""
        lv = _check_int("level", level, 0, self.n_levels - 1)
        return 4.0 * math.pi / (6.0 * self.resolutions[lv] ** 2)

    def integral(self, level: int = 0) -> np.ndarray:
        """``(3,)`` ``sum Omega_texel L_texel`` over the map at ``level`` (exact texel solid
        angles): the map's radiance integrated over the sphere."""
        lv = _check_int("level", level, 0, self.n_levels - 1)
        om = texel_solid_angles(self.resolutions[lv])
        return np.einsum("ji,fjic->c", om, self.levels[lv].astype(np.float64))

    # -- lookups --------------------------------------------------------------------------
    def lookup(self, d: mi.Vector3f, lod: mi.Float | float = 0.0) -> mi.Color3f:
        """Radiance in direction ``d`` (any length) at level of detail ``lod`` (Dr.Jit):
        bilinear within a face (clamped at face edges), linear between levels."""
        return _lookup_dr(self.data, mi.UInt32(0), mi.Bool(True), self._tables,
                          self.n_levels, d, lod)

    def lookup_np(self, dirs, lod=0.0) -> np.ndarray:
        """NumPy version of :meth:`lookup`: ``dirs`` (..., 3), ``lod`` broadcast to
        ``dirs.shape[:-1]``; returns (..., 3) float64."""
        d = np.asarray(dirs, dtype=np.float64)
        if d.ndim < 1 or d.shape[-1] != 3:
            raise GlossrtError(f"directions must have shape (..., 3), got {d.shape}")
        lod = np.broadcast_to(np.asarray(lod, dtype=np.float64), d.shape[:-1])
        ok = np.all(np.isfinite(d), axis=-1) & np.any(d != 0, axis=-1)
        face, s, t = cube_coords(np.where(ok[..., None], d, 1.0))
        top = self.n_levels - 1
        lod = np.where(lod > 0, np.minimum(lod, top), 0.0)
        l0 = np.floor(lod).astype(np.int64)
        frac = (lod - l0)[..., None]
        l1 = np.minimum(l0 + 1, top)
        out = np.zeros(d.shape[:-1] + (3,))
        for lv in range(self.n_levels):  # loop over levels, vectorised over directions
            faces = self.levels[lv].astype(np.float64)
            m0, m1 = l0 == lv, (l1 == lv) & (frac[..., 0] > 0)
            if np.any(m0):
                out[m0] += ((1 - frac) * _bilinear_np(faces, face, s, t))[m0]
            if np.any(m1):
                out[m1] += (frac * _bilinear_np(faces, face, s, t))[m1]
        return np.where(ok[..., None], out, 0.0)


def _tables(res: list[int], offsets: np.ndarray):
    return (owned(mi.Float, np.asarray(res, np.float32)),
            owned(mi.UInt32, np.asarray(res, np.uint32)),
            owned(mi.UInt32, np.asarray(offsets, np.uint32)))


def _texel_radiance(lts, o, face, i, j, sub, ss: int, r: int, n_sub: int) -> mi.Color3f:
    """The light radiance of cube-map texel ``(face, i, j)`` seen from ``o`` (one lane per
    subsample ``sub`` of its ``ss x ss`` grid, averaged over blocks of ``n_sub`` lanes when
    ``n_sub > 1``): Kimura & Tokoi, sec. 3, the lights seen from the probe, the nearest wins."""
    # sample (a, b) of the ss x ss grid of texel (i, j): s = -1 + 2 (i + (a + 1/2)/ss)/R
    a = mi.Float(sub % ss) + 0.5
    b = mi.Float(sub // ss) + 0.5
    s = -1.0 + 2.0 * (mi.Float(i) + a / ss) / r
    t = -1.0 + 2.0 * (mi.Float(j) + b / ss) / r
    d = dr.normalize(_dir_dr(face, s, t))
    best = dr.full(mi.Float, dr.inf, dr.width(d))
    col = dr.zeros(mi.Color3f, dr.width(d))
    for lt in lts:
        dist, y = lt.intersect(o, d)
        hit = dist < best
        best = dr.select(hit, dist, best)
        col = dr.select(hit, lt.emitted(y, d), col)
    if n_sub > 1:
        col = mi.Color3f(*(dr.block_sum(col[c], n_sub) for c in range(3))) / n_sub
    return col


def _render_faces(lights: list, probe: np.ndarray, r: int, ss: int) -> np.ndarray:
    """``(6, R, R, 3)`` float64: the radiance of the nearest light per texel sample,
    averaged over the ``ss x ss`` samples of each texel."""
    from ..mc import _Light  # the Monte Carlo reference's intersection and emission

    out = np.zeros((6, r, r, 3))
    if not lights:
        return out
    lts = [_Light(lt) for lt in lights]
    o = mi.Point3f(*opaque(probe))
    per_face = r * r * ss * ss
    step = max(1, min(6, MAX_LANES // per_face))
    n_sub = ss * ss
    for f0 in range(0, 6, step):
        nf = min(step, 6 - f0)
        lane = dr.arange(mi.UInt32, nf * per_face)
        sub = lane % n_sub
        texel = lane // n_sub
        i = texel % r
        j = (texel // r) % r
        face = texel // (r * r) + dr.opaque(mi.UInt32, f0)
        col = _texel_radiance(lts, o, face, i, j, sub, ss, r, n_sub)
        dr.eval(col)
        vals = np.stack([np.asarray(col[c], dtype=np.float64) for c in range(3)], -1)
        out[f0:f0 + nf] = vals.reshape(nf, r, r, 3)
    return out


# -- filtered importance sampling --------------------------------------------------------------

def fis_lod(pdf, n_samples: int, level0_resolution: int, bias: float = 0.0):
    """Level of detail for a sample of solid-angle density ``pdf`` among ``n_samples``
    (Colbert & Krivanek 2007, GPU Gems 3 ch. 20, sec. 20.4 "Mipmap Filtered Samples", the
    mip-level equation, with its bias as a parameter)::

        lod = max(0.5 log2(Omega_s / Omega_p) + bias, 0),
        Omega_s = 1 / (N pdf),   Omega_p = 4 pi / (6 W^2)

    ``Omega_s`` is the solid angle the sample stands for, ``Omega_p`` a base-level texel's
    (the cube's average; ``W = level0_resolution``); ``0.5 log2`` because a level's texel
    has 4 times its finer level's solid angle. Colbert & Krivanek's equation adds a constant
    ``+1``: it reads one level coarser than the sample density asks for (a filter footprint
    4 times the sample's solid angle), an empirical bias towards blur over noise and
    aliasing. ``bias=0`` (the default) leaves it out; ``bias=1`` gives their equation.
    (Their ``Omega_p`` also carries the varying texel solid angle of their dual-paraboloid
    map; here the cube's average, as the issue specifies.)

    ``pdf``: ``mi.Float`` (returns ``mi.Float``) or a number / NumPy array (returns
    float64). ``pdf <= 0`` or NaN gives ``inf`` (the coarsest level after clamping in
    lookups)."""
    n = _check_int("n_samples", n_samples, 1, 1 << 30)
    w = _check_int("level0_resolution", level0_resolution, 1, MAX_RESOLUTION)
    omega_p = 4.0 * math.pi / (6.0 * w * w)
    # Colbert & Krivanek 2007, sec. 20.4: 0.5 log2(Omega_s / Omega_p) = -0.5 log2(N pdf Omega_p)
    if isinstance(pdf, (mi.Float, dr.ArrayBase)):
        c = dr.opaque(mi.Float, n * omega_p)
        b = dr.opaque(mi.Float, float(bias))
        pdf = mi.Float(pdf)
        lod = -0.5 * dr.log2(dr.maximum(pdf * c, 0.0)) + b
        return dr.select(pdf > 0.0, dr.maximum(lod, 0.0), dr.inf)
    p = np.asarray(pdf, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        lod = -0.5 * np.log2(p * (n * omega_p)) + float(bias)
    out = np.where(p > 0, np.maximum(lod, 0.0), np.inf)
    return float(out) if out.ndim == 0 else out


# -- bounding spheres (Kimura & Tokoi, sec. 6) ---------------------------------------------------

def _circumcentres(a: np.ndarray, b: np.ndarray, c: np.ndarray):
    """Centres of the circles through triangles (a, b, c) in 3D (..., 3) and whether the
    triangle is non-degenerate."""
    ab, ac = b - a, c - a
    n = np.cross(ab, ac)
    n2 = np.einsum("...i,...i->...", n, n)
    scale = np.maximum(np.einsum("...i,...i->...", ab, ab), np.einsum("...i,...i->...", ac, ac))
    ok = n2 > 1e-20 * scale * scale
    num = (np.einsum("...i,...i->...", ac, ac)[..., None] * np.cross(n, ab)
           + np.einsum("...i,...i->...", ab, ab)[..., None] * np.cross(ac, n))
    return a + num / (2.0 * np.where(ok, n2, 1.0)[..., None]), ok


def _min_sphere(v: np.ndarray) -> tuple[np.ndarray, float]:
    """Smallest sphere enclosing the coplanar points ``v`` (K, 3): the smallest of the
    candidate spheres (on every pair as diameter, through every triple) that holds all
    points; exact since the minimal enclosing circle is fixed by 2 or 3 of the points."""
    k = len(v)
    ii, jj = np.triu_indices(k, 1)
    cands = [(v[ii] + v[jj]) / 2.0]
    tri = np.array([(a, b, c) for a in range(k) for b in range(a + 1, k)
                    for c in range(b + 1, k)], dtype=np.int64).reshape(-1, 3)
    if len(tri):
        cc, ok = _circumcentres(v[tri[:, 0]], v[tri[:, 1]], v[tri[:, 2]])
        cands.append(cc[ok])
    cand = np.concatenate(cands)
    rad = np.linalg.norm(v[None, :, :] - cand[:, None, :], axis=-1).max(1)
    best = int(np.argmin(rad))
    return cand[best], float(rad[best])


def light_spheres(lights: Sequence) -> tuple[np.ndarray, np.ndarray]:
    """``(centres (L, 3), radii (L,))`` float64: the smallest sphere enclosing each
    polygon light's vertices (hence the whole convex polygon), radius enlarged by a relative
    ``1e-9`` against rounding. The paper's spheres are "somewhat larger than the light"
    (sec. 6); the enlargement per roughness is :func:`cull_mask`'s ``spread``. No lights:
    empty arrays."""
    centres = np.zeros((len(lights), 3))
    radii = np.zeros(len(lights))
    for m, lt in enumerate(lights):  # a few lights, a few vertices each
        c, rad = _min_sphere(light_vertices(lt))
        centres[m] = c
        radii[m] = rad * (1.0 + SPHERE_EPS)
    return centres, radii


def lobe_spread(quantile_angle_of_normals):
    """Angular spread of the reflection lobe for a quantile angle of the microfacet normals
    (radians): ``2 x angle``, since tilting the normal by ``delta`` turns the mirror
    direction by ``2 delta`` (in the plane of incidence). Accepts numbers, NumPy arrays or
    Dr.Jit arrays; a negative, NaN or Inf number raises :class:`GlossrtError`."""
    q = quantile_angle_of_normals
    if isinstance(q, dr.ArrayBase):
        return 2.0 * q
    a = np.asarray(q, dtype=np.float64)
    if not np.all(np.isfinite(a)) or np.any(a < 0):
        raise GlossrtError(f"quantile angle of the normals must be finite and >= 0, got {q!r}")
    return 2.0 * float(a) if a.ndim == 0 else 2.0 * a


def cull_mask(p: mi.Point3f, r: mi.Vector3f, centres, radii, spread) -> mi.Bool:
    """True where the ray from ``p`` in the unit direction ``r`` passes within the sphere
    of some light enlarged by ``spread`` (Kimura & Tokoi, sec. 6, made exact per pixel):
    ``angle(r, c - p) <= asin(min(radius / |c - p|, 1)) + spread`` (a cone test), or ``p``
    is inside the sphere. ``spread`` (radians): a number or an ``mi.Float`` per lane
    (:func:`lobe_spread`). ``centres`` (L, 3), ``radii`` (L,) from :func:`light_spheres`;
    no lights: all False."""
    c = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
    rad = np.asarray(radii, dtype=np.float64).ravel()
    if len(c) != len(rad):
        raise GlossrtError(f"cull_mask: {len(c)} centres but {len(rad)} radii")
    if not (np.all(np.isfinite(c)) and np.all(np.isfinite(rad))) or np.any(rad < 0):
        raise GlossrtError("cull_mask: sphere centres and radii must be finite, radii >= 0")
    if isinstance(spread, (int, float)):
        if not math.isfinite(spread) or spread < 0:
            raise GlossrtError(f"cull_mask: spread must be finite and >= 0, got {spread}")
        spread = dr.opaque(mi.Float, float(spread))
    p, r = mi.Point3f(p), mi.Vector3f(r)
    keep = dr.zeros(mi.Bool, max(dr.width(p), dr.width(r)))
    for cm, rm in zip(c, rad, strict=True):
        cc = mi.Point3f(*opaque(cm))
        rr = dr.opaque(mi.Float, float(rm))
        to = cc - p
        dist = dr.norm(to)
        inside = dist <= rr
        # angle between r and the centre's direction: atan2(|r x to|, r . to)
        ang = dr.atan2(dr.norm(dr.cross(r, to)), dr.dot(r, to))
        half = dr.asin(dr.minimum(rr / dr.maximum(dist, 1e-30), 1.0))
        keep |= inside | (ang <= half + spread)  # Kimura & Tokoi, sec. 6 (as a cone test)
    return keep


# -- probes and map sets ---------------------------------------------------------------------------

def probe_points(setup, frame: int | None = None) -> dict[int, np.ndarray]:
    """Default probes: ``{mesh_id: centre (3,)}``, the bounding-box centre of every
    non-emitting shape, keyed by its 1-based ``mesh_id`` (``stable_shapes(scene)[k - 1]``).
    ``setup``: a :class:`glossrt.scenes.SceneSetup` (posed for ``frame`` first when given)
    or a bare ``mi.Scene``."""
    from ...scenes import stable_shapes

    if frame is not None and hasattr(setup, "set_frame"):
        setup.set_frame(int(frame))
    scene = getattr(setup, "scene", setup)
    out = {}
    for k, shape in enumerate(stable_shapes(scene), start=1):
        if shape.is_emitter():
            continue
        b = shape.bbox()
        c = np.array([(float(b.min[i]) + float(b.max[i])) / 2.0 for i in range(3)])
        if np.all(np.isfinite(c)):
            out[k] = c
    return out


class CubeMapSet:
    """Light cube maps per ``mesh_id`` (all with the same resolution and levels), stacked in
    one flat array (map ``m`` starts at texel ``m x texel_count``), with a lookup that picks
    each lane's map by its ``mesh_id``."""

    def __init__(self, maps: Mapping[int, LightCubeMap]):
        ids = sorted(maps)
        for i in ids:
            if not isinstance(i, (int, np.integer)) or i < 0 or i >= 1 << 24:
                raise GlossrtError(f"mesh ids must be integers in 0..2^24, got {i!r}")
        self.maps = {int(i): maps[i] for i in ids}
        first = next(iter(self.maps.values()), None)
        self.resolutions = first.resolutions if first is not None else [1]
        for i, m in self.maps.items():
            if m.resolutions != self.resolutions:
                raise GlossrtError(f"cube map of mesh {i} has levels {m.resolutions}, "
                                   f"expected {self.resolutions} like the others")
        self.texel_count = first.texel_count if first is not None else 6
        n_ids = (max(ids) + 1) if ids else 1
        base = np.zeros(n_ids, np.uint32)
        has = np.zeros(n_ids, np.uint32)
        for m, i in enumerate(ids):
            base[i] = m * self.texel_count
            has[i] = 1
        flat = (np.concatenate([m.flat for m in self.maps.values()]) if ids
                else np.zeros(3 * self.texel_count, np.float32))
        self.data = owned_float(flat)
        self._base = owned(mi.UInt32, base)  # frozen-function inputs: see jit.owned_float
        self._has = owned(mi.UInt32, has)
        self._n_ids = n_ids
        offsets = maps[ids[0]].level_offsets if ids else np.zeros(1, np.int64)
        self._tables = _tables(self.resolutions, offsets)

    @classmethod
    def render(cls, lights: Sequence, probes: Mapping[int, np.ndarray],
               resolution: int = DEFAULT_RESOLUTION, levels: int | None = None,
               supersample: int = 2) -> CubeMapSet:
        """One :meth:`LightCubeMap.render` per probe (e.g. :func:`probe_points`)."""
        return cls({i: LightCubeMap.render(lights, p, resolution, levels, supersample)
                    for i, p in probes.items()})

    @classmethod
    def for_scene(cls, setup, frame: int | None = None, resolution: int = DEFAULT_RESOLUTION,
                  levels: int | None = None, supersample: int = 2) -> CubeMapSet:
        """Maps of ``setup``'s polygon lights at every default probe (:func:`probe_points`)."""
        from ..scene import polygon_lights

        lights = polygon_lights(setup, frame)
        return cls.render(lights, probe_points(setup), resolution, levels, supersample)

    @property
    def n_levels(self) -> int:
        return len(self.resolutions)

    def __len__(self) -> int:
        return len(self.maps)

    def lookup(self, mesh_id, d: mi.Vector3f, lod: mi.Float | float = 0.0) -> mi.Color3f:
        """Per lane, the map of ``mesh_id`` (``mi.UInt32``, or ``mi.Float`` rounded to the
        nearest integer) looked up like :meth:`LightCubeMap.lookup`; lanes whose id has no
        map (or is negative / NaN) get 0."""
        if isinstance(mesh_id, (int, np.integer)):
            mesh_id = dr.opaque(mi.UInt32, int(mesh_id)) if mesh_id >= 0 else None
        if mesh_id is None:
            return dr.zeros(mi.Color3f, dr.width(d))
        if not isinstance(mesh_id, mi.UInt32):
            fid = mi.Float(mesh_id)
            ok = (fid > -0.5) & (fid < float(self._n_ids) - 0.5)  # False for NaN
            mesh_id = dr.select(ok, mi.UInt32(dr.round(dr.select(ok, fid, 0.0))),
                                mi.UInt32(self._n_ids))
        n = self._n_ids
        inside = mesh_id < n
        idx = dr.select(inside, mesh_id, 0)
        active = inside & (dr.gather(mi.UInt32, self._has, idx, inside) > 0)
        base = dr.gather(mi.UInt32, self._base, idx, active)
        return _lookup_dr(self.data, base, active, self._tables, self.n_levels, d, lod)



# -- probe grids on large receivers (beyond the paper) ---------------------------------------------

#: default probes along the largest object's longest side (the pipeline's ``highlight_probes``,
#: whose comment in glossrt.pipeline.config gives the numbers; 1: the paper's one map per
#: object at its centre)
DEFAULT_PROBES = 4
#: largest ``probes`` accepted
MAX_PROBES = 16


class ProbeGrid:
    """The probes of one object: ``counts`` (3,) per world axis, probe ``(i, j, k)`` at
    ``origin + (i, j, k) * step`` (the centres of the ``counts`` cells of the object's
    bounding box), ``points`` (n, 3) in order ``(k * ny + j) * nx + i``."""

    def __init__(self, lo: np.ndarray, hi: np.ndarray, counts):
        self.counts = np.asarray(counts, np.int64)
        ext = hi - lo
        self.step = ext / self.counts
        self.origin = lo + 0.5 * self.step
        i, j, k = np.meshgrid(*(np.arange(c) for c in self.counts), indexing="ij")
        idx = np.stack([i.ravel(order="F"), j.ravel(order="F"), k.ravel(order="F")], -1)
        self.points = self.origin + idx * self.step

    def __len__(self) -> int:
        return int(np.prod(self.counts))


def probe_grids(setup, probes: int = DEFAULT_PROBES,
                frame: int | None = None) -> dict[int, ProbeGrid]:
    """Probes per object (``{mesh_id: ProbeGrid}``), beyond Kimura & Tokoi's one map per
    object (sec. 3: the light environment map is rendered "as seen from the lit position";
    the paper takes one position per object). One map per object is right for objects small
    against their distance to the lights, but a large receiver (polygon-light's 6 m floor, 2 m
    under its light) then reflects the lights as they look from its centre at every pixel:
    the lights' directions and solid angles are off by the parallax of the pixel's distance
    to the probe (polygon-light's floor highlight read 2.4x a per-pixel reference of the same
    model with one probe, 2.6x Monte Carlo's for the GGX variant;
    tests/test_pipeline_highlights.py).

    A grid of cubic-ish cells of side ``s = L / probes`` (``L`` the longest bounding-box side
    of all the scene's non-emitting objects) covers each object's bounding box: ``max(1,
    ceil(extent_a / s))`` cells along each world axis ``a``, a probe at each cell's centre.
    ``probes=1``: every object gets one probe at its bounding-box centre (the paper);
    larger values refine the largest objects first (the small ones keep one probe until
    ``s`` falls below their size). A pixel blends the maps of the probes around it
    (:meth:`ProbeGridMaps.lookup`: trilinear in the grid, clamped at its edges)."""
    from ...scenes import stable_shapes

    n = _check_int("highlight probes", probes, 1, MAX_PROBES)
    if frame is not None and hasattr(setup, "set_frame"):
        setup.set_frame(int(frame))
    scene = getattr(setup, "scene", setup)
    boxes = {}
    for k, shape in enumerate(stable_shapes(scene), start=1):
        if shape.is_emitter():
            continue
        b = shape.bbox()
        lo = np.array([float(b.min[i]) for i in range(3)])
        hi = np.array([float(b.max[i]) for i in range(3)])
        if np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)):
            boxes[k] = (lo, hi)
    if not boxes:
        return {}
    side = max(float(np.max(hi - lo)) for lo, hi in boxes.values()) / n
    out = {}
    for k, (lo, hi) in boxes.items():
        ext = hi - lo
        counts = np.ones(3, np.int64) if side <= 0 else np.maximum(
            1, np.ceil(ext / side - 1e-6)).astype(np.int64)
        out[k] = ProbeGrid(lo, hi, counts)
    return out


#: samples per face edge of :func:`_faces_seen`'s test
_EDGE_SAMPLES = 64


def _faces_seen(lights: list, points: np.ndarray) -> np.ndarray:
    """``(P, 6)`` bool: whether face ``f`` of the map at probe ``p`` can show a light, i.e.
    some light's bounding sphere (:func:`light_spheres`) reaches into the face's pyramid of
    directions as seen from the probe (a conservative test: the angle from the sphere's
    centre direction to the face's region, measured to samples along the face's boundary,
    at most the sphere's angular radius plus the sample spacing). Faces that fail stay black
    and are not rendered."""
    from ..cubemap import cube_dir

    n_p = len(points)
    if not lights or n_p == 0:
        return np.zeros((n_p, 6), bool)
    centres, radii = light_spheres(lights)
    e = np.linspace(-1.0, 1.0, _EDGE_SAMPLES + 1)
    one = np.ones_like(e)
    border = []
    for f in range(6):  # the four edges of each face, unit directions
        s = np.concatenate([e, e, -one, one])
        t = np.concatenate([-one, one, e, e])
        d = cube_dir(np.full(s.shape, f), s, t)
        border.append(d / np.linalg.norm(d, axis=-1, keepdims=True))
    border = np.stack(border)  # (6, B, 3)
    slack = 2.0 / _EDGE_SAMPLES  # angular spacing of the samples (at most, on a face)
    out = np.zeros((n_p, 6), bool)
    for c, rad in zip(centres, radii, strict=True):
        to = c[None, :] - points  # (P, 3)
        dist = np.linalg.norm(to, axis=-1)
        inside = dist <= rad
        u = to / np.maximum(dist, 1e-30)[:, None]
        half = np.arcsin(np.minimum(rad / np.maximum(dist, 1e-30), 1.0))
        face, _, _ = cube_coords(np.where(inside[:, None], 1.0, u))
        hit = np.zeros((n_p, 6), bool)
        hit[np.arange(n_p), face] = True  # the centre's own face
        cosang = np.einsum("pk,fbk->pfb", u, border)
        near = np.arccos(np.clip(cosang.max(-1), -1.0, 1.0))  # (P, 6)
        hit |= near <= (half + slack)[:, None]
        hit |= inside[:, None]
        out |= hit
    return out


def _render_probes_dr(lights: list, points: np.ndarray, r: int, ss: int) -> mi.Float:
    """All probes' level-0 maps in Dr.Jit (Kimura & Tokoi, sec. 3, as :func:`_render_faces`:
    the nearest light per texel sample, ``ss x ss`` samples averaged), left on the device:
    a flat ``mi.Float`` of ``P x 6 x r x r`` RGB texels (probe, face, row ``j``, column
    ``i``), the layout of :class:`LightCubeMap`'s level 0. Only the faces that can show a
    light (:func:`_faces_seen`) are rendered; the others are black."""
    from ..mc import _Light

    n_p = len(points)
    texels = 6 * r * r
    n_sub = ss * ss
    data = dr.zeros(mi.Float, 3 * n_p * texels)
    if not lights or n_p == 0:
        return data
    pairs = np.flatnonzero(_faces_seen(lights, np.asarray(points, np.float64)).ravel())
    if len(pairs) == 0:
        return data
    lts = [_Light(lt) for lt in lights]
    pts = owned(mi.Float, np.asarray(points, np.float32).ravel())
    pair_t = owned(mi.UInt32, pairs.astype(np.uint32))  # probe * 6 + face
    per_face = r * r * n_sub
    step = max(1, min(len(pairs), MAX_LANES // per_face))
    for q0 in range(0, len(pairs), step):
        nq = min(step, len(pairs) - q0)
        lane = dr.arange(mi.UInt32, nq * per_face)
        sub = lane % n_sub
        texel = lane // n_sub  # (pair - q0) * r^2 + j * r + i
        i = texel % r
        j = (texel // r) % r
        pf = dr.gather(mi.UInt32, pair_t, texel // (r * r) + dr.opaque(mi.UInt32, q0))
        face = pf % 6
        probe = pf // 6
        o = mi.Point3f(*(dr.gather(mi.Float, pts, 3 * probe + c) for c in range(3)))
        col = _texel_radiance(lts, o, face, i, j, sub, ss, r, n_sub)
        tx = dr.arange(mi.UInt32, nq * r * r)
        out = dr.gather(mi.UInt32, pair_t, tx // (r * r) + dr.opaque(mi.UInt32, q0)) * (r * r) \
            + tx % (r * r)
        for c in range(3):
            dr.scatter(data, col[c], 3 * out + c)
        dr.eval(data)
    return data


class ProbeGridMaps:
    """Light cube maps at every probe of :func:`probe_grids` (all with the same resolution
    and levels; map ``m`` starts at texel ``m x texel_count`` of :attr:`data`) with a lookup
    that blends, per lane, the maps of the probes around the lane's shading point on its
    object's grid. ``levels=1`` (the ellipsoidal estimator reads level 0 only) renders and
    keeps everything on the device; more levels go through :func:`mip_chain` in NumPy."""

    def __init__(self, lights: Sequence, grids: Mapping[int, ProbeGrid],
                 resolution: int = DEFAULT_RESOLUTION, levels: int | None = 1,
                 supersample: int = 2):
        r = _check_int("cube map resolution", resolution, 1, MAX_RESOLUTION)
        ss = _check_int("supersample", supersample, 1, MAX_SUPERSAMPLE)
        self.resolutions = level_resolutions(r, levels)
        ids = sorted(grids)
        self.grids = {int(i): grids[i] for i in ids}
        pts = (np.concatenate([g.points for g in self.grids.values()]) if ids
               else np.zeros((0, 3)))
        self.points = pts
        sizes = [6 * q * q for q in self.resolutions]
        offsets = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
        self.texel_count = int(sum(sizes))
        base = _render_probes_dr(list(lights), pts, r, ss)
        if len(self.resolutions) > 1 and len(pts):
            lv0 = np.asarray(base, np.float64).reshape(len(pts), 6, r, r, 3)
            flat = np.concatenate([np.concatenate([lv.astype(np.float32).ravel() for lv in
                                                   mip_chain(m, len(self.resolutions))])
                                   for m in lv0])
            base = owned_float(flat)
        self.data = base if len(pts) else dr.zeros(mi.Float, 3 * self.texel_count)
        self._n_ids = (max(ids) + 1) if ids else 1
        n = self._n_ids
        first = np.zeros(n, np.uint32)
        has = np.zeros(n, np.uint32)
        counts = np.ones((n, 3), np.uint32)
        origin = np.zeros((n, 3), np.float32)
        inv = np.zeros((n, 3), np.float32)
        m = 0
        for i, g in self.grids.items():
            first[i], has[i], counts[i] = m, 1, g.counts
            origin[i] = g.origin
            inv[i] = np.where(g.counts > 1, 1.0 / np.maximum(g.step, 1e-30), 0.0)
            m += len(g)
        #: world axes along which some object has more than one probe (static: the number
        #: of maps a lookup blends, 2^len(axes))
        self.axes = tuple(a for a in range(3) if np.any(counts[:, a] > 1))
        self._grid = (owned(mi.UInt32, first), owned(mi.UInt32, has),
                      owned(mi.UInt32, counts.T.ravel()), owned(mi.Float, origin.T.ravel()),
                      owned(mi.Float, inv.T.ravel()))
        self._tables = _tables(self.resolutions, offsets)

    @property
    def n_levels(self) -> int:
        return len(self.resolutions)

    def __len__(self) -> int:
        return len(self.points)

    def lookup(self, mesh_id: mi.UInt32, p: mi.Point3f, d: mi.Vector3f,
               lod: mi.Float | float = 0.0) -> mi.Color3f:
        """Per lane: the maps of ``mesh_id``'s probes around ``p`` looked up like
        :meth:`LightCubeMap.lookup` and blended trilinearly (the grid coordinate of ``p``
        clamped to the outermost probes); 0 where the id has no maps."""
        return grid_lookup(self.data, self._grid, self._tables, self.n_levels,
                           self.texel_count, self._n_ids, self.axes, mesh_id, p, d, lod)


def grid_lookup(data, grid, tables, n_levels: int, texel_count: int, n_ids: int, axes: tuple,
                mesh_id: mi.UInt32, p: mi.Point3f, d: mi.Vector3f, lod) -> mi.Color3f:
    """:meth:`ProbeGridMaps.lookup` on its tables (the frozen kernels' form)."""
    first_t, has_t, counts_t, origin_t, inv_t = grid
    mesh_id = mi.UInt32(mesh_id)
    inside = mesh_id < n_ids
    idx = dr.select(inside, mesh_id, 0)
    active = inside & (dr.gather(mi.UInt32, has_t, idx, inside) > 0)
    first = dr.gather(mi.UInt32, first_t, idx, active)
    cell, frac, cnt = [], [], []
    for a in range(3):
        n_a = dr.gather(mi.UInt32, counts_t, a * n_ids + idx, active)
        o_a = dr.gather(mi.Float, origin_t, a * n_ids + idx, active)
        s_a = dr.gather(mi.Float, inv_t, a * n_ids + idx, active)
        top = mi.Float(n_a - 1)
        g = dr.clip((p[a] - o_a) * s_a, 0.0, top)
        g = dr.select(dr.isfinite(g), g, 0.0)
        i0 = dr.minimum(mi.UInt32(dr.floor(g)), dr.maximum(n_a, 2) - 2)
        cell.append(i0)
        frac.append(g - mi.Float(i0))
        cnt.append(n_a)
    out = dr.zeros(mi.Color3f, dr.width(d))
    for corner in range(1 << len(axes)):
        w = mi.Float(1.0)
        ijk = list(cell)
        for b, a in enumerate(axes):
            if (corner >> b) & 1:
                w = w * frac[a]
                ijk[a] = ijk[a] + 1
            else:
                w = w * (1.0 - frac[a])
        local = (ijk[2] * cnt[1] + ijk[1]) * cnt[0] + ijk[0]
        on = active & (w > 0.0)
        base = (first + local) * texel_count
        out += w * _lookup_dr(data, base, on, tables, n_levels, d, lod)
    return dr.select(active, out, 0.0)
