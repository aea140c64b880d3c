"""The filtered roughness of specular antialiasing (:mod:`glossrt.specaa`): method names
(:func:`parse_method`), 2x2 quad partners and the slope differences across them, the kernels
of Tokuyoshi's eqs. 1-2 and their reductions (:func:`kernel`), and the filtered roughness
matrix per pixel (:func:`filtered_roughness`, :func:`roughness_image`). The methods and
conventions are described in the package docstring.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import drjit as dr
import numpy as np

from ..backend import mi
from ..errors import GlossrtError
from ..images import check_frame, merge, split
from ..jit import opaque
from ..lights import analytic
from ..lights.shading import NEEDS, ShadingPoints

#: the methods glossrt evaluates (any ``halfvector|avgnormal`` + ``-cov|-bbox|-max|-eig`` works)
METHODS = ("none", "halfvector", "halfvector-bbox", "avgnormal", "avgnormal-max",
           "avgnormal-eig", "projected")
#: variance of the Gaussian pixel filter in pixels^2 (Tokuyoshi, eq. 1)
SIGMA2 = 0.25
#: pixel-filter variance and kernel clamp of projected-space filtering (Tokuyoshi & Kaplanyan
#: 2021, eq. 14)
SIGMA2_PROJECTED = 1.0 / (2.0 * math.pi)
KAPPA_PROJECTED = 0.18
#: Smith masking-shadowing of point / directional lights: ``"filtered"`` (the paper: the
#: filtered roughness matrix ``A`` for ``D`` and ``G2``) or ``"material"`` (beyond the paper:
#: ``D`` of ``A``, ``G2`` of the material's own ``alpha``: the normal variation ``A`` stands
#: for is macro-geometry, which the supersampled reference does not shadow). Polygon lights
#: (LTC, whose fit bakes masking into one isotropic alpha) always use the filtered alpha.
MASKING = ("filtered", "material")
_SOURCES = ("halfvector", "avgnormal")
_FORMS = ("cov", "bbox", "max", "eig")
_EPS = 1e-6


@dataclass(frozen=True)
class Method:
    """A parsed method name: ``source`` (none, halfvector, avgnormal, projected), ``form``
    (cov, bbox, max, eig) and the kernel clamp ``kappa`` (None: no clamp)."""

    source: str
    form: str = "cov"
    kappa: float | None = None
    masking: str = "filtered"

    @property
    def isotropic(self) -> bool:
        return self.source in ("none", "projected") or self.form in ("max", "eig")

    @property
    def per_light(self) -> bool:
        return self.source == "halfvector"


_NO_CLAMP = "none"


def _parse_kappa(name: str, option: str) -> float | str:
    """The clamp of a ``METHOD:kappa=K`` suffix: a positive finite number or ``"none"``."""
    key, eq, value = option.partition("=")
    value = value.strip()
    if key.strip() != "kappa" or not eq or not value:
        raise GlossrtError(f"specular antialiasing method {name!r}: the only option is "
                           f"':kappa=K' (K > 0, or 'none'), got {option!r}")
    if value == _NO_CLAMP:
        return _NO_CLAMP
    try:
        return float(value)
    except ValueError:
        raise GlossrtError(f"specular antialiasing method {name!r}: kappa must be a number "
                           f"or 'none', got {value!r}") from None


def parse_method(name: str, kappa: float | None = None, masking: str = "filtered") -> Method:
    """The :class:`Method` of ``name`` (see :mod:`glossrt.specaa`); a clear error otherwise.
    ``name`` may end in ``:kappa=K`` (a positive clamp of the added kernel's eigenvalues,
    Kaplanyan et al. 2016; ``none``: no clamp); ``kappa`` does the same as an argument (both
    given: an error unless they agree). Default clamp: ``projected`` 0.18, others none.
    ``masking``: :data:`MASKING`."""
    key = str(name).strip().lower()
    if masking not in MASKING:
        raise GlossrtError(f"masking must be one of {MASKING}, got {masking!r}")
    key, colon, option = key.partition(":")
    key = key.strip()
    clamp: float | str | None = kappa
    if colon:
        k_opt = _parse_kappa(name, option)
        if kappa is not None and k_opt != kappa:
            raise GlossrtError(f"specular antialiasing method {name!r}: kappa given twice "
                               f"({k_opt} in the name, {kappa} as an argument)")
        clamp = k_opt
    if isinstance(clamp, (int, float)) and not (math.isfinite(clamp) and clamp > 0):
        raise GlossrtError(f"kappa must be a positive finite number, got {clamp}")
    if key == "none":
        if clamp is not None:
            raise GlossrtError(f"specular antialiasing method {name!r}: 'none' adds no "
                               f"kernel, so it takes no kappa")
        return Method(key, "cov", None, masking)
    if key == "projected":  # Tokuyoshi & Kaplanyan 2021, eq. 14: KAPPA = 0.18 by default
        k = KAPPA_PROJECTED if clamp is None else clamp
        return Method(key, "cov", None if k == _NO_CLAMP else float(k), masking)
    source, _, form = key.partition("-")
    form = form or "cov"
    if source not in _SOURCES or form not in _FORMS:
        raise GlossrtError(
            f"unknown specular antialiasing method {name!r}: use none, projected, or "
            f"SOURCE[-FORM] with SOURCE in {_SOURCES} and FORM in {_FORMS}, optionally "
            f"followed by ':kappa=K' (evaluated: {', '.join(METHODS)})")
    return Method(source, form, None if clamp in (None, _NO_CLAMP) else float(clamp), masking)


# -- geometry ---------------------------------------------------------------------------------
def transport(v: mi.Vector3f, n_from: mi.Vector3f, n_to: mi.Vector3f) -> mi.Vector3f:
    """``v`` rotated by the smallest rotation taking unit ``n_from`` to unit ``n_to`` (about
    their common perpendicular ``k = n_from x n_to``; Rodrigues' formula written without the
    angle: ``R v = c v + k x v + k (k . v) / (1 + c)``, ``c = n_from . n_to``)."""
    k = dr.cross(n_from, n_to)
    c = dr.dot(n_from, n_to)
    return c * v + dr.cross(k, v) + k * (dr.dot(k, v) / dr.maximum(1.0 + c, _EPS))


def _slope(v: mi.Vector3f, t: mi.Vector3f, b: mi.Vector3f, n: mi.Vector3f) -> tuple:
    """Slope-space coordinates ``(v.t / v.n, v.b / v.n)`` (``v.n`` kept positive)."""
    inv_z = dr.rcp(dr.maximum(dr.dot(v, n), _EPS))
    return dr.dot(v, t) * inv_z, dr.dot(v, b) * inv_z


def quad_partners(width: int, height: int) -> tuple[mi.UInt32, mi.UInt32]:
    """Flat indices of every pixel's horizontal ``(x ^ 1, y)`` and vertical ``(x, y ^ 1)``
    quad partner (the pixel itself where the partner would fall outside the image)."""
    idx = dr.arange(mi.UInt32, width * height)
    x, y = idx % width, idx // width
    xp, yp = x ^ 1, y ^ 1
    xp = dr.select(xp < width, xp, x)
    yp = dr.select(yp < height, yp, y)
    return y * width + xp, yp * width + x


# -- eqs. 1-2 and the reductions --------------------------------------------------------------
def kernel(du: tuple, dv: tuple, form: str, sigma2: float = SIGMA2) -> tuple:
    """The roughness added by the footprint, ``(k11, k12, k22, det)`` (a symmetric 2x2 matrix
    and its determinant, computed without cancellation), from the slope differences
    ``du = (du_x, du_y)``, ``dv`` across the pixel's quad (Dr.Jit or NumPy values):

    * ``cov``: ``2 Sigma``, ``Sigma = sigma^2 [du; dv]^T [du; dv]`` (Tokuyoshi, eqs. 1-2);
    * ``bbox``: ``2 sigma^2 diag(w_x^2, w_y^2)``, ``w = |du| + |dv|`` per axis (sec. 1.2);
    * ``max``: ``2 sigma^2 max(w_x^2, w_y^2) I`` (sec. 3, Kaplanyan et al.'s isotropic box);
    * ``eig``: ``lambda_max(2 Sigma) I`` (sec. 3, Tokuyoshi's largest eigenvalue).
    """
    s2 = 2.0 * sigma2
    if form in ("cov", "eig"):
        # Tokuyoshi, eq. 1 (times 2, eq. 2): Sigma = sigma^2 (du du^T + dv dv^T)
        k11 = s2 * (du[0] * du[0] + dv[0] * dv[0])
        k12 = s2 * (du[0] * du[1] + dv[0] * dv[1])
        k22 = s2 * (du[1] * du[1] + dv[1] * dv[1])
        cross = du[0] * dv[1] - du[1] * dv[0]
        det = s2 * s2 * cross * cross  # det(du du^T + dv dv^T) = (du x dv)^2
        if form == "cov":
            return k11, k12, k22, det
        lam = _eigen(k11, k12, k22, det)[0]
        return lam, 0.0 * lam, lam, lam * lam
    wx = abs(du[0]) + abs(dv[0])
    wy = abs(du[1]) + abs(dv[1])
    if form == "bbox":  # Tokuyoshi, sec. 1.2
        kx, ky = s2 * wx * wx, s2 * wy * wy
        return kx, 0.0 * wx, ky, kx * ky
    if form == "max":  # Tokuyoshi, sec. 3
        m = _maximum(wx * wx, wy * wy) * s2
        return m, 0.0 * m, m, m * m
    raise GlossrtError(f"unknown kernel form {form!r} (use one of {_FORMS})")


def _is_np(a) -> bool:
    return isinstance(a, (np.ndarray, np.floating, float, int))


def _maximum(a, b):
    return np.maximum(a, b) if _is_np(a) else dr.maximum(a, b)


def _minimum(a, b):
    return np.minimum(a, b) if _is_np(a) else dr.minimum(a, b)


def _sqrt(a):
    return np.sqrt(a) if _is_np(a) else dr.sqrt(a)


def _eigen(a11, a12, a22, det=None) -> tuple:
    """Eigenvalues ``(lambda_max, lambda_min)`` of the symmetric 2x2 ``[[a11, a12], [a12,
    a22]]``; with its determinant ``det`` given, ``lambda_min = det / lambda_max`` (exact
    where ``m - r`` would cancel: huge, nearly singular kernels at grazing angles)."""
    m = 0.5 * (a11 + a22)
    r = _sqrt(_maximum(0.25 * (a11 - a22) * (a11 - a22) + a12 * a12, 0.0))
    l1 = m + r
    if det is None:
        return l1, m - r
    return l1, _maximum(det, 0.0) / _maximum(l1, 1e-30)


def _with_eigenvalues(a11, a12, a22, l1, l2, c1, c2) -> tuple:
    """The matrix with ``[[a11, a12], [a12, a22]]``'s eigenvectors (eigenvalues ``l1 >= l2``)
    and eigenvalues ``c1, c2``: ``c2 I + (c1 - c2) P1``, ``P1 = (A - l2 I) / (l1 - l2)``."""
    gap = l1 - l2
    if _is_np(gap):
        s = np.where(gap > 1e-12, (c1 - c2) / np.where(gap > 1e-12, gap, 1.0), 0.0)
    else:
        s = dr.select(gap > 1e-12, (c1 - c2) / dr.maximum(gap, 1e-12), 0.0)
    return c2 + s * (a11 - l2), s * a12, c2 + s * (a22 - l2)


def clamp_eigen(a11, a12, a22, hi, det=None) -> tuple:
    """The symmetric 2x2 matrix with the same eigenvectors and eigenvalues ``min(lambda,
    hi)`` (Dr.Jit or NumPy values, ``hi`` > 0; ``det``: see :func:`_eigen`)."""
    l1, l2 = _eigen(a11, a12, a22, det)
    return _with_eigenvalues(a11, a12, a22, l1, l2, _minimum(l1, hi), _minimum(l2, hi))


def roughness_matrix(alpha2, k: tuple, kappa: float | None = None) -> tuple:
    """``A = alpha^2 I + k`` (Tokuyoshi, eq. 2) with the kernel's eigenvalues clamped to
    ``kappa`` (None: not clamped) and ``A``'s to 1 (GGX's range): ``(a11, a12, a22)``.
    ``k``: ``(k11, k12, k22[, det])`` as :func:`kernel` returns it."""
    k11, k12, k22 = k[:3]
    l1, l2 = _eigen(k11, k12, k22, k[3] if len(k) > 3 else None)
    if kappa is not None:
        l1c, l2c = _minimum(l1, kappa), _minimum(l2, kappa)
    else:
        l1c, l2c = l1, l2
    # Tokuyoshi, eq. 2, with A's eigenvalues alpha^2 + lambda(k) clamped to 1
    c1, c2 = _minimum(alpha2 + l1c, 1.0), _minimum(alpha2 + l2c, 1.0)
    return _with_eigenvalues(k11, k12, k22, l1, l2, c1, c2)


def isotropic_alpha(a11, a12, a22):
    """``sqrt(lambda_max(A))``: the isotropic GGX alpha an anisotropic ``A`` is shaded with
    where only isotropic roughness is possible (LTC tables, a one-channel G-buffer)."""
    return _minimum(_sqrt(_eigen(a11, a12, a22)[0]), 1.0)


# -- per-pixel filtering ----------------------------------------------------------------------
@dataclass
class _Quad:
    """A pixel's shading point, its tangent frame and its two quad partners' normals and
    positions (``x``: horizontal, ``y``: vertical; a missing partner is the pixel itself).

    With positions (the per-light methods) also each partner's frame ``(t', b', n')``: the
    pixel's ``(t, b)`` rotated by the smallest rotation taking ``n`` to the partner's normal
    ``n'``. A partner's vector ``v`` carried into the pixel's frame (the inverse rotation,
    :func:`transport` from ``n'`` to ``n``) has slopes ``(v.t', v.b') / v.n'``, so carrying
    costs three dot products per light instead of a rotation."""

    sp: ShadingPoints
    t: mi.Vector3f
    b: mi.Vector3f
    nx: mi.Vector3f
    ny: mi.Vector3f
    px: mi.Point3f
    py: mi.Point3f
    cam: mi.Point3f
    okx: mi.Bool  # whether the partner is another pixel (else its difference is 0)
    oky: mi.Bool
    frames: tuple | None = None  # ((tx, bx), (ty, by)) with positions, else None


def _quad(ch: dict, sp: ShadingPoints, cam: mi.Point3f, size: tuple[int, int],
          positions: bool, partners: bool = True) -> _Quad:
    """The quad partners' normals (and, for ``positions``, positions), gathered from the
    G-buffer tensors, and whether each is another pixel of the same mesh. ``partners=False``
    (unfiltered shading): no partner is read (each is the pixel itself, ``ok`` false).

    Measured (session 20, 640x360, kernel time): gathering each component where it lies beat
    an interleaved (normal, mesh id) copy read by one 4-wide packet gather per partner, as the
    copy is a kernel of its own (0.4-0.5 ms, more than the gathers it saves)."""
    frame = mi.Frame3f(sp.n)
    if not partners:
        no = dr.zeros(mi.Bool, dr.width(sp.p))
        return _Quad(sp, frame.s, frame.t, sp.n, sp.n, sp.p, sp.p, cam, no, no)
    h, w = size
    ix, iy = quad_partners(w, h)
    mesh = ch["mesh_id"].array  # (H, W, 1): one value per pixel

    def partner(ip):
        ok = sp.hit & (dr.gather(mi.Float, mesh, ip) == mesh) & (
            ip != dr.arange(mi.UInt32, w * h))
        n = dr.select(ok, mi.Vector3f(*split(ch["normal"], ip)), sp.n)
        if not positions:
            return n, sp.p, ok
        return n, dr.select(ok, mi.Point3f(*split(ch["position"], ip)), sp.p), ok

    (nx, px, okx), (ny, py, oky) = partner(ix), partner(iy)
    q = _Quad(sp, frame.s, frame.t, nx, ny, px, py, cam, okx, oky)
    if positions:
        q.frames = tuple((transport(q.t, sp.n, n), transport(q.b, sp.n, n)) for n in (nx, ny))
    return q


def _half(p: mi.Point3f, cam: mi.Point3f, light, kind: str) -> mi.Vector3f:
    wo = dr.normalize(cam - p)
    wi = dr.normalize(light - p) if kind == "polygon" else analytic.incident(light, p)[0]
    return dr.normalize(wo + wi)


def _slopes(q: _Quad, method: Method, light=None, kind: str = "") -> tuple:
    """The slopes ``(s0, sx, sy)`` of the pixel's and its partners' vectors that the method
    differentiates across the quad, in one tangent basis. Half vector (Tokuyoshi sec. 1.1):
    the half vectors about the pixel's normal, the partners' carried into the pixel's frame
    (through ``q.frames``). Average normal (sec. 2): the three normals about their 3-tap
    average ``N`` (the pixel's basis carried to ``N``; any basis about it for the isotropic
    forms)."""
    n = q.sp.n
    if method.source == "halfvector":
        (tx, bx), (ty, by) = q.frames
        return (_slope(_half(q.sp.p, q.cam, light, kind), q.t, q.b, n),
                _slope(_half(q.px, q.cam, light, kind), tx, bx, q.nx),
                _slope(_half(q.py, q.cam, light, kind), ty, by, q.ny))
    big_n = dr.normalize(n + q.nx + q.ny)
    if method.isotropic:  # any tangent basis about n_bar will do
        fb = mi.Frame3f(big_n)
        t, b = fb.s, fb.t
    else:  # A must be in the pixel's frame: carry (t, b) from n to n_bar
        t, b = transport(q.t, n, big_n), transport(q.b, n, big_n)
    return tuple(_slope(v, t, b, big_n) for v in (n, q.nx, q.ny))


def _differences(q: _Quad, method: Method, light=None, kind: str = "") -> tuple:
    """Slope differences ``(du, dv)`` across the quad for the method's source, in the
    pixel's tangent basis (carried to the average normal for ``avgnormal``; any basis about
    it for the isotropic forms)."""
    s0, sx, sy = _slopes(q, method, light, kind)
    # a missing partner differs by exactly 0 (not by the rounding of two huge grazing slopes)
    du = tuple(dr.select(q.okx, sx[i] - s0[i], 0.0) for i in range(2))
    dv = tuple(dr.select(q.oky, sy[i] - s0[i], 0.0) for i in range(2))
    return du, dv


def _largest_eigenvalue_avgnormal(q: _Quad):
    """``lambda_max(2 Sigma)`` (Tokuyoshi sec. 3) of the average-normal source without a
    tangent basis: the slope of ``v`` about ``N`` is the tangent vector ``(v - (v.N) N) /
    (v.N)``, so the differences ``du, dv`` are 3D vectors in ``N``'s tangent plane and
    ``Sigma``'s eigenvalues are those of their Gram matrix ``sigma^2 [[du.du, du.dv], [du.dv,
    dv.dv]]`` (the same as :func:`kernel`'s ``eig`` form in any basis, with less work)."""
    n = q.sp.n
    big_n = dr.normalize(n + q.nx + q.ny)

    def lift(v):  # the tangential part over the normal one (clamped like _slope)
        z = dr.dot(v, big_n)
        return (v - z * big_n) / dr.maximum(z, _EPS)

    q0 = lift(n)
    du = dr.select(q.okx, lift(q.nx) - q0, 0.0)
    dv = dr.select(q.oky, lift(q.ny) - q0, 0.0)
    gram = (dr.squared_norm(du), dr.dot(du, dv), dr.squared_norm(dv))
    # Tokuyoshi, eqs. 1-2: 2 sigma^2 times the Gram matrix's largest eigenvalue
    return 2.0 * SIGMA2 * _eigen(*gram)[0]


def material_matrix(q: _Quad) -> tuple | None:
    """The material's own roughness matrix in the pixel's frame ``(q.t, q.b)`` for
    anisotropic lobes: ``R diag(alpha_u^2, alpha_v^2) R^T`` with ``R`` the rotation from the
    lobe's tangent to ``q.t``; ``None`` where every lane is isotropic (``alpha^2 I``)."""
    sp = q.sp
    if sp.alpha_uv is None:
        return None
    c, s = dr.dot(sp.tangent, q.t), dr.dot(sp.tangent, q.b)
    inv = dr.rsqrt(dr.maximum(c * c + s * s, 1e-30))
    c, s = c * inv, s * inv
    u2, v2 = dr.square(sp.alpha_uv.x), dr.square(sp.alpha_uv.y)
    return c * c * u2 + s * s * v2, c * s * (u2 - v2), s * s * u2 + c * c * v2


def _add_clamped(am: tuple, k: tuple) -> tuple:
    """``A_m + K`` with ``A``'s eigenvalues clamped to 1 (GGX's range)."""
    a = (am[0] + k[0], am[1] + k[1], am[2] + k[2])
    l1, l2 = _eigen(*a)
    return _with_eigenvalues(*a, l1, l2, _minimum(l1, 1.0), _minimum(l2, 1.0))


def filtered_roughness(q: _Quad, method: Method, light=None, kind: str = "") -> tuple:
    """``(a11, a12, a22)`` per lane in the pixel's frame for ``method`` (``light``: the
    light's device value for per-light methods). Isotropic results have a literal-zero
    ``a12`` (the shading kernel then simplifies as for unfiltered roughness). An anisotropic
    material's own matrix (:func:`material_matrix`) takes the place of ``alpha^2 I``:
    Kaplanyan et al. 2016 add the filter kernel to whatever roughness matrix the NDF has."""
    a2 = dr.square(q.sp.alpha)
    zero = dr.zeros(mi.Float, dr.width(a2))
    am = material_matrix(q)
    if method.source == "none":
        return (a2, zero, a2) if am is None else am
    if method.source == "projected":
        # Tokuyoshi & Kaplanyan 2021, eq. 14 (world-space normal differences):
        # kernel alpha^2 = 2 sigma_p^2 (|dn_u|^2 + |dn_v|^2), twice the projected normal's
        # variance over the footprint (the Beckmann alpha^2 = 2 variance of Tokuyoshi, eq. 2)
        du, dv = q.nx - q.sp.n, q.ny - q.sp.n
        k = 2.0 * SIGMA2_PROJECTED * (dr.squared_norm(du) + dr.squared_norm(dv))
    elif method.form == "eig" and method.source == "avgnormal":
        k = _largest_eigenvalue_avgnormal(q)
    else:
        du, dv = _differences(q, method, light, kind)
        k = kernel(du, dv, method.form)
        if not method.isotropic:
            if am is not None:  # the kernel (eigenvalues clamped to kappa) on A_m
                return _add_clamped(am, roughness_matrix(0.0, k, method.kappa))
            return roughness_matrix(a2, k, method.kappa)
        k = k[0]
    if method.kappa is not None:
        k = dr.minimum(k, method.kappa)
    if am is not None:
        return _add_clamped(am, (k, zero, k))
    a = dr.minimum(a2 + k, 1.0)  # Tokuyoshi, eq. 2 (isotropic kernel), clamped to alpha <= 1
    return a, zero, a



def roughness_image(frame, method: str, light=None, kappa: float | None = None) -> np.ndarray:
    """The filtered roughness matrix per pixel, (H, W, 3) = ``(a11, a12, a22)`` in each
    pixel's frame ``mi.Frame3f(n)``; per-light methods need ``light`` (a point or directional
    light). For inspection and tests; 0 on the background."""
    check_frame(frame, NEEDS)
    m = parse_method(method, kappa)
    if m.per_light and light is None:
        raise GlossrtError(f"method {method!r} filters per light: pass light=")
    h, w = frame.height, frame.width
    sp = ShadingPoints.of(frame)
    ch = {k: frame[k] for k in NEEDS}
    q = _quad(ch, sp, mi.Point3f(*opaque(frame.camera.position)), (h, w), m.per_light)
    dev = analytic.device_lights([light])[0] if light is not None else None
    a = filtered_roughness(q, m, dev, "analytic")
    out = merge([dr.select(sp.hit, mi.Float(v), 0.0) for v in a], h, w)
    return np.array(out, dtype=np.float32).reshape(h, w, 3)
