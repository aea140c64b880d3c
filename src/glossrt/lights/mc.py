"""Monte Carlo reference for direct lighting from polygon lights (``glossrt light --method
mc``): the same BRDF as the LTC shading (:mod:`glossrt.lights.shading`), the same G-buffer
shading points, visibility optional.

Estimator, per pixel and per light (Veach 1997, multiple importance sampling, balance
heuristic), each sample drawing one direction from each of two strategies:

* light sampling: a uniform point ``y`` on the polygon (fan triangulation, triangle chosen by
  area), ``p_l(w) = |y - x|^2 / (A |n_l . w|)``;
* BRDF sampling: with probability ``q`` a cosine-distributed direction, else a half vector
  of the pixel's distribution (:func:`glossrt.brdf.microfacet.sample_h`: GGX visible normals,
  Heitz 2018; Beckmann ``D cos``) reflected about, ``p_b(w) = q cos/pi + (1 - q) p_h(h) /
  (4 wo.h)``;
  the direction counts if its ray meets the polygon on its emitting side.

``L(y)`` is the light's radiance times its texture (bilinear, full resolution) at ``y``'s
texture coordinates, which are the affine map of the polygon's first three vertices (exact
for parallelograms, e.g. Mitsuba rectangles). With ``shadows=True`` a shadow ray through the
scene (Mitsuba ``ray_test``, up to just before ``y``) gates every contribution.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import drjit as dr
import numpy as np

from ..backend import mi
from ..brdf import microfacet as mf
from ..errors import GlossrtError
from ..images import LUM
from ..jit import opaque
from .shading import ShadingPoints, brdf_cos, light_vertices

#: lanes (pixels x samples) per launch
MAX_LANES = 1 << 21
#: relative shortening of shadow rays so they stop before the light's own surface
SHADOW_EPS = 1e-3


class _Light:
    """A polygon light as opaque Dr.Jit constants (no recompiles when it moves)."""

    def __init__(self, light):
        v = light_vertices(light)
        n = np.cross(v[1] - v[0], v[2] - v[0])
        for k in range(3, len(v)):
            n = n + np.cross(v[k - 1] - v[0], v[k] - v[0])
        area2 = np.linalg.norm(n)
        if not area2 > 1e-12:
            raise GlossrtError("polygon light has zero area (collinear or repeated vertices)")
        self.normal = n / area2
        tri = [0.5 * np.linalg.norm(np.cross(v[k] - v[0], v[k + 1] - v[0]))
               for k in range(1, len(v) - 1)]
        self.area = float(sum(tri))
        self.cdf = np.cumsum(tri) / self.area
        self.v = [mi.Vector3f(*opaque(p)) for p in v]
        self.n = mi.Vector3f(*opaque(self.normal))
        self.cdf_dr = opaque(self.cdf[:-1])
        self.radiance = mi.Color3f(*opaque(np.asarray(light.radiance, float).ravel()[:3]))
        self.two_sided = bool(getattr(light, "two_sided", False))
        tex = getattr(light, "texture", None)
        self.texture = None
        if tex is not None:
            uv = np.asarray(light.uv, np.float64)
            # affine map from (s, t) along edges v0->v1, v0->v2 to uv
            e1, e2 = v[1] - v[0], v[2] - v[0]
            g = np.array([[e1 @ e1, e1 @ e2], [e1 @ e2, e2 @ e2]])
            self.gram_inv = [opaque(row) for row in np.linalg.inv(g)]
            self.uv0, self.duv1, self.duv2 = opaque(uv[0]), opaque(uv[1] - uv[0]), opaque(
                uv[2] - uv[0])
            self.e1, self.e2 = mi.Vector3f(*opaque(e1)), mi.Vector3f(*opaque(e2))
            self.texture = mi.Texture2f(mi.TensorXf(np.asarray(tex, np.float32)),
                                        filter_mode=dr.FilterMode.Linear,
                                        wrap_mode=dr.WrapMode.Clamp)

    def sample(self, u1: mi.Float, u2: mi.Float, u3: mi.Float) -> mi.Point3f:
        """Uniform point: triangle (v0, v_k, v_k+1) by area, then uniform in it."""
        k = mi.UInt32(0)
        for c in self.cdf_dr:
            k += dr.select(u1 >= c, 1, 0)
        a, b = mi.Vector3f(self.v[1]), mi.Vector3f(self.v[2])
        for j in range(1, len(self.v) - 1):
            a = dr.select(k == j - 1, self.v[j], a)
            b = dr.select(k == j - 1, self.v[j + 1], b)
        su = dr.sqrt(u2)
        return mi.Point3f(self.v[0] * (1.0 - su) + a * (su * (1.0 - u3)) + b * (su * u3))

    def intersect(self, o: mi.Point3f, d: mi.Vector3f):
        """Distance along the ray to the polygon (inf when missed) and the hit point."""
        denom = dr.dot(d, self.n)
        t = dr.dot(self.v[0] - o, self.n) / dr.select(dr.abs(denom) > 1e-12, denom, 1e-12)
        y = o + d * t
        inside = (t > 0) & (dr.abs(denom) > 1e-12)
        for j in range(len(self.v)):
            a, b = self.v[j], self.v[(j + 1) % len(self.v)]
            inside &= dr.dot(dr.cross(b - a, y - a), self.n) >= 0.0  # convex, counter-clockwise
        return dr.select(inside, t, dr.inf), mi.Point3f(y)

    def emitted(self, y: mi.Point3f, w: mi.Vector3f) -> mi.Color3f:
        """Radiance leaving ``y`` towards the shading point (``w`` points at the light)."""
        front = dr.dot(w, self.n) < 0.0  # the light faces the point
        ok = front | self.two_sided
        le = mi.Color3f(self.radiance)
        if self.texture is not None:
            r = y - self.v[0]
            b1, b2 = dr.dot(r, self.e1), dr.dot(r, self.e2)
            s = self.gram_inv[0][0] * b1 + self.gram_inv[0][1] * b2
            t = self.gram_inv[1][0] * b1 + self.gram_inv[1][1] * b2
            u = self.uv0[0] + s * self.duv1[0] + t * self.duv2[0]
            v = self.uv0[1] + s * self.duv1[1] + t * self.duv2[1]
            tex = self.texture.eval(mi.Point2f(u, v))
            le = le * mi.Color3f(tex[0], tex[1], tex[2])
        return dr.select(ok, le, 0.0)

    def pdf(self, x: mi.Point3f, y: mi.Point3f, w: mi.Vector3f) -> mi.Float:
        """Solid-angle density of light sampling towards ``y``."""
        d2 = dr.squared_norm(y - x)
        return d2 / (self.area * dr.maximum(dr.abs(dr.dot(w, self.n)), 1e-12))


def _visible(scene, x: mi.Point3f, n: mi.Vector3f, y: mi.Point3f, active) -> mi.Bool:
    o = x + n * (1e-4 * (1.0 + dr.max(dr.abs(x))))
    d = y - o
    dist = dr.norm(d)
    ray = mi.Ray3f(mi.Point3f(o), mi.Vector3f(d / dist), mi.Float(dist * (1.0 - SHADOW_EPS)),
                   mi.Float(0.0), mi.Color0f())
    return ~scene.ray_test(ray, active)


def _spec_weight(sp: ShadingPoints) -> mi.Float:
    la = LUM[0] * sp.albedo[0] + LUM[1] * sp.albedo[1] + LUM[2] * sp.albedo[2]
    ls = dr.maximum(LUM[0] * sp.f0[0] + LUM[1] * sp.f0[1] + LUM[2] * sp.f0[2], 0.04)
    return la / (la + ls)  # q: probability of the cosine strategy


@dataclass
class Strategy:
    """One MIS strategy's sample towards a light: the light point ``y``, the BRDF terms
    ``fd, fs`` (f cos, :func:`brdf_cos`), the emitted radiance ``le``, the balance-heuristic
    denominator ``p_l + p_b`` and whether the sample counts (``ok``, no visibility)."""

    y: mi.Point3f
    fd: mi.Color3f
    fs: mi.Color3f
    le: mi.Color3f
    denom: mi.Float
    ok: mi.Bool


def strategies(sp: ShadingPoints, lt, frame: mi.Frame3f, wo_l: mi.Vector3f, q: mi.Float,
               rng: mi.PCG32) -> tuple[Strategy, Strategy]:
    """The two MIS samples of :func:`estimate` for light ``lt`` (light sampling, then BRDF
    sampling: cosine with probability ``q``, else GGX visible normals), drawing 3 + 3 random
    numbers from ``rng`` in that order."""
    # -- strategy 1: light sampling
    y = lt.sample(rng.next_float32(), rng.next_float32(), rng.next_float32())
    w = dr.normalize(y - sp.p)
    fd, fs = brdf_cos(sp, w)
    p_l = lt.pdf(sp.p, y, w)
    p_b = _pdf_brdf(sp, frame, wo_l, q, w)
    ok = sp.hit & (p_l > 0) & dr.isfinite(p_l)
    s1 = Strategy(y, fd, fs, lt.emitted(y, w), dr.maximum(p_l + p_b, 1e-30), ok)
    # -- strategy 2: BRDF sampling
    u0, u1, u2 = rng.next_float32(), rng.next_float32(), rng.next_float32()
    wd = mi.warp.square_to_cosine_hemisphere(mi.Point2f(u1, u2))
    if sp.alpha_uv is not None:
        h = mf.sample_h_aniso(wo_l, sp.alpha_uv.x, sp.alpha_uv.y, u1, u2, sp.beckmann)
    else:
        hx, hy, hz = mf.sample_h(wo_l.x, wo_l.y, wo_l.z, sp.alpha, u1, u2, sp.beckmann)
        h = mi.Vector3f(hx, hy, hz)
    wl = dr.select(u0 < q, wd, 2.0 * dr.dot(wo_l, h) * h - wo_l)
    w2 = frame.to_world(wl)
    t, y2 = lt.intersect(sp.p, w2)
    fd2, fs2 = brdf_cos(sp, w2)
    p_b2 = _pdf_brdf(sp, frame, wo_l, q, w2)
    p_l2 = lt.pdf(sp.p, y2, w2)
    ok2 = sp.hit & dr.isfinite(t) & (p_b2 > 0) & (wl.z > 0)
    s2 = Strategy(y2, fd2, fs2, lt.emitted(y2, w2), dr.maximum(p_l2 + p_b2, 1e-30), ok2)
    return s1, s2


def estimate(sp: ShadingPoints, lights: list, rng: mi.PCG32, scene=None) -> mi.Color3f:
    """One two-strategy MIS sample per lane of the direct light from ``lights`` (diffuse +
    specular summed); ``scene`` given: with shadows."""
    frame = sp.local_frame()  # anisotropic lobes: the axes of alpha_u, alpha_v
    wo_l = frame.to_local(sp.wo)
    q = _spec_weight(sp)
    total = dr.zeros(mi.Color3f, dr.width(sp.p))
    for lt in lights:
        for st in strategies(sp, lt, frame, wo_l, q, rng):
            ok = st.ok
            if scene is not None:
                ok &= _visible(scene, sp.p, sp.n, st.y, ok)
            # Veach 1997, balance heuristic: f L / p_l * p_l / (p_l + p_b), either strategy
            total += dr.select(ok, (st.fd + st.fs) * st.le / st.denom, 0.0)
    return total


def _pdf_brdf(sp: ShadingPoints, frame: mi.Frame3f, wo_l: mi.Vector3f, q: mi.Float,
              w: mi.Vector3f) -> mi.Float:
    """Density of the BRDF strategy: ``q cos/pi + (1 - q) p_h(h) / (4 wo.h)``."""
    wl = frame.to_local(w)
    cos_i = wl.z
    h = dr.normalize(wl + wo_l)
    wo_h = dr.dot(wo_l, h)
    # the half vector's density (Heitz 2018 / Walter et al. 2007); Jacobian 1 / (4 wo.h)
    if sp.alpha_uv is not None:
        p_h = mf.pdf_h_aniso(wo_l, h, sp.alpha_uv.x, sp.alpha_uv.y, sp.beckmann)
    else:
        p_h = mf.pdf_h(wo_l.z, wo_h, h.z, sp.alpha, sp.beckmann, dr.square(h.x) + dr.square(h.y))
    p_s = p_h / dr.maximum(4.0 * wo_h, 1e-8)
    return dr.select(cos_i > 0, q * cos_i / dr.pi + (1.0 - q) * p_s, 0.0)


def sample_batches(sp_full: ShadingPoints, spp: int, seed: int):
    """``spp`` samples per pixel of ``sp_full`` in batches of at most :data:`MAX_LANES` lanes:
    yields ``(shading points, rng, k)`` with ``k`` consecutive lanes per pixel (sum them with
    ``dr.block_sum(x, k)``) and the random stream of sample ``s`` of pixel ``p`` seeded by
    ``s n_pix + p`` and ``seed``, so results do not depend on the batching."""
    n_pix = dr.width(sp_full.p)
    kk = max(1, min(spp, MAX_LANES // max(n_pix, 1)))
    done = 0
    while done < spp:
        k = min(kk, spp - done)
        lane = dr.arange(mi.UInt32, n_pix * k)
        pix = lane // k
        rng = mi.PCG32(n_pix * k, mi.UInt64(lane % k + done) * n_pix + mi.UInt64(pix),
                       dr.opaque(mi.UInt64, seed))
        yield sp_full.take(pix), rng, k
        done += k


def render_mc(frame, lights: list, spp: int, f0: np.ndarray | None = None, scene=None,
              seed: int = 0, progress: Callable[[int, int], None] | None = None) -> np.ndarray:
    """Monte Carlo direct lighting (H, W, 3) of ``frame``'s G-buffer by the polygon
    ``lights`` (objects with ``vertices``, ``radiance``, ``two_sided``, optional ``texture``
    and ``uv``, e.g. :class:`glossrt.lights.scene.PolygonLight`), ``spp`` samples per pixel
    (each one light sample and one BRDF sample per light). ``scene``: a Mitsuba scene for
    shadow rays (``None``: unshadowed)."""
    if spp < 1:
        raise GlossrtError(f"spp must be >= 1, got {spp}")
    h, w = frame.height, frame.width
    lts = [_Light(lt) for lt in lights]
    acc = dr.zeros(mi.Color3f, w * h)
    done = 0
    for sp, rng, k in sample_batches(ShadingPoints.of(frame, f0), spp, seed):
        est = estimate(sp, lts, rng, scene)
        est = dr.select(dr.isfinite(est), est, 0.0)
        acc += mi.Color3f(*(dr.block_sum(est[c], k) for c in range(3)))
        dr.eval(acc)
        done += k
        if progress is not None:
            progress(done, spp)
    out = np.stack([np.array(acc[c]) for c in range(3)], -1) / spp
    return out.reshape(h, w, 3).astype(np.float32)
