"""G-buffer + separated 1 spp path tracer (Dr.Jit kernels, Mitsuba scenes).

Reads a :class:`glossrt.scenes.SceneSetup`; produces every channel of the Frame schema:
``color, emission, direct_diffuse, direct_specular, indirect_diffuse, indirect_specular,
albedo_diffuse, albedo_specular, normal, position, depth, roughness, distribution, mesh_id,
motion``.

The light transport is Mitsuba's ``path`` integrator (next-event estimation with
power-heuristic MIS, Russian roulette from depth 5) with the contributions split:

* ``emission``: radiance of an emitter hit by the primary ray (or the environment);
* ``direct_*``: paths with exactly one scattering event (NEE at the primary hit, plus the
  BSDF-sampled ray from the primary hit that reaches an emitter), split by BSDF lobe with
  ``BSDFContext.type_mask`` (diffuse vs everything else: glossy and delta);
* ``indirect_*``: longer paths, split between the lobes of the primary hit by each lobe's
  own ``f_lobe / p`` at the sampled direction (``p`` the pdf of the BSDF's sampling
  mixture), so each channel estimates its lobe's integral ``∫ f_lobe L cos``; the
  BSDF-sampled part of ``direct_*`` is split the same way.

Emitters that an analytic shading stage lights instead can be left out of ``direct_*``
(``Renderer(primary_exclude=...)``, :func:`shade`'s ``primary`` table): no next-event
estimation towards them at the primary hit, and nothing when the primary hit's BSDF sample
reaches them; they still light every deeper vertex, so ``indirect_*`` is unchanged.

Primary rays go through pixel centres, so the G-buffer is noise-free and deterministic;
random numbers come from a PCG32 stream keyed by (pixel index, seed), so rendering a subset
of pixels gives exactly the values a full render gives for those pixels. Next-event estimation
picks emitters through an :class:`EmitterTable` (Mitsuba's selection probabilities, in an
order that does not change between loads) rather than ``scene.sample_emitter_direction``,
whose emitter order changes from load to load: the same seed gives the same image on every
load of a scene.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import drjit as dr
import numpy as np

from ..backend import VariantStruct, mi
from ..brdf.fresnel import ROW, split_sum
from ..brdf.microfacet import GGX
from ..errors import GlossrtError
from ..scenes import MITSUBA_DEFAULT_RR_DEPTH, render_shapes, stable_emitters
from .materials import NORMAL_MAP_TWOSIDED

RR_DEPTH = MITSUBA_DEFAULT_RR_DEPTH
#: what Mitsuba's max_depth = -1 ("no limit") becomes: Russian roulette ends the paths
UNBOUNDED_DEPTH = 1 << 30


def resolve_max_depth(max_depth: int) -> int:
    """Mitsuba's convention: -1 = unbounded; 0, below -1 or above :data:`UNBOUNDED_DEPTH`
    (2^30: deeper paths end by Russian roulette long before) is an error."""
    if isinstance(max_depth, bool) or not isinstance(max_depth, int | np.integer):
        raise GlossrtError(f"max_depth must be an integer, got {max_depth!r}")
    if max_depth == 0 or max_depth < -1 or max_depth > UNBOUNDED_DEPTH:
        raise GlossrtError(f"max_depth must be in 1..{UNBOUNDED_DEPTH}, or -1 for unbounded; "
                           f"got {max_depth}")
    return UNBOUNDED_DEPTH if max_depth == -1 else max_depth

#: the G-buffer channels of anisotropic lobes (``tangent``; ``roughness_uv``, which equals
#: ``(roughness, roughness)`` on isotropic lobes): a caller that reads neither may skip them
ANISOTROPY_OUT = ("roughness_uv", "tangent")
RADIANCE_OUT = ("emission", "direct_diffuse", "direct_specular", "indirect_diffuse",
                "indirect_specular")


@functools.cache
def lobe_masks() -> tuple[int, int]:
    """Lobe masks (``BSDFContext.type_mask``): diffuse, and everything that is not diffuse
    (glossy + delta). Also readable as ``DIFFUSE_MASK`` and ``SPECULAR_MASK``."""
    diffuse = int(mi.BSDFFlags.Diffuse)
    return diffuse, int(mi.BSDFFlags.All) & ~diffuse


def __getattr__(name: str):
    if name == "DIFFUSE_MASK":
        return lobe_masks()[0]
    if name == "SPECULAR_MASK":
        return lobe_masks()[1]
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


class PixelSampler:
    """Independent uniform numbers from a PCG32 stream per (pixel, seed).

    Same ``next_1d``/``next_2d`` interface as ``mi.Sampler`` so the shading code can use
    either."""

    DRJIT_STRUCT = VariantStruct(lambda: {"rng": mi.PCG32})

    def __init__(self, pixel: mi.UInt32 | None = None, seed: mi.UInt32 | None = None):
        if pixel is None:
            self.rng = mi.PCG32()
            return
        v0, v1 = mi.sample_tea_32(pixel, seed, 4)
        # size=1: the per-lane state comes from (pixel, seed) only, not from the lane index
        self.rng = mi.PCG32(1, mi.UInt64(v0) | (mi.UInt64(v1) << 32), mi.UInt64(pixel))

    def next_1d(self, active=True) -> mi.Float:
        return self.rng.next_float32()

    def next_2d(self, active=True) -> mi.Point2f:
        return mi.Point2f(self.rng.next_float32(), self.rng.next_float32())


def _mis(a: mi.Float, b: mi.Float) -> mi.Float:
    """Power heuristic (Veach 1997, eq. 9.13 with beta = 2)."""
    a2, b2 = dr.square(a), dr.square(b)
    return dr.detach(dr.select(a2 > 0, a2 / (a2 + b2), 0.0))


def _context(mask: int) -> mi.BSDFContext:
    ctx = mi.BSDFContext()
    ctx.type_mask = mask
    return ctx


class EmitterTable:
    """The scene's emitters in a load-independent order (:func:`glossrt.scenes.stable_emitters`)
    with Mitsuba's selection probabilities (``scene.pdf_emitter``, which honours each emitter's
    ``sampling_weight``) and their CDF, for :func:`sample_emitter_direction`.

    ``emitter``, ``pmf``, ``cdf``: one entry per emitter (a single null entry with pmf 0 when
    the scene has none); ``last``: index of the last emitter with a nonzero pmf (the CDF is
    exactly 1 from there on), the end of the binary search.

    ``exclude``: indices (into this order) of emitters this table never picks: their pmf is 0
    and the others' are Mitsuba's renormalised to sum to 1 (all excluded: every pmf 0, and
    :func:`sample_emitter_direction` returns weight 0). :func:`shade` uses such a table for
    next-event estimation at the primary hit only (``Renderer(primary_exclude=)``). The
    per-emitter ``mis_scale`` (this table's pmf over Mitsuba's, 0 where Mitsuba's is 0) turns
    ``scene.pdf_emitter_direction`` into this table's pdf for MIS; ``excluded`` flags the
    excluded entries; ``slot`` maps an emitter's Dr.Jit registry id (what an ``EmitterPtr``
    holds) to its index + 1 here (0: not an emitter of the scene).

    ``apply``: per shape registry id (what ``si.shape`` holds), whether the exclusion applies
    at a primary hit on that shape; a primary hit elsewhere samples every emitter (the
    scene's own table: those pixels' direct light is path-traced in full).
    ``apply_on``: the shapes (``mi.Shape`` objects) to apply it on; None: every shape."""

    DRJIT_STRUCT = VariantStruct(lambda: {"emitter": mi.EmitterPtr, "pmf": mi.Float,
                                          "cdf": mi.Float, "last": mi.UInt32,
                                          "mis_scale": mi.Float, "excluded": mi.Bool,
                                          "slot": mi.UInt32, "apply": mi.Bool})

    def __init__(self, scene: mi.Scene | None = None, exclude=(), apply_on=None):
        if scene is None:
            self.emitter, self.pmf, self.cdf, self.last = (
                mi.EmitterPtr(), mi.Float(), mi.Float(), mi.UInt32())
            self.mis_scale, self.excluded, self.slot = mi.Float(), mi.Bool(), mi.UInt32()
            self.apply = mi.Bool()
            return
        ordered = stable_emitters(scene)
        n = len(ordered)
        exclude = sorted({int(i) for i in exclude})
        if exclude and not 0 <= exclude[0] <= exclude[-1] < n:
            raise GlossrtError(f"emitter indices must lie in [0, {n}): the scene has {n} "
                               f"emitter(s); got {exclude}")

        def rid(e) -> int:  # Dr.Jit registry id: what an EmitterPtr holds
            return int(dr.reinterpret_array(mi.UInt32, mi.EmitterPtr(e))[0])

        if n == 0:
            ids, pmf = np.zeros(1, np.uint32), np.zeros(1, np.float32)
        else:
            position = {rid(e): i for i, e in enumerate(scene.emitters())}
            # Mitsuba's pmf by its own emitter index (uniform: one value for all of them)
            mitsuba_pmf = np.broadcast_to(
                np.array(scene.pdf_emitter(dr.arange(mi.UInt32, n)), np.float32).ravel(), (n,))
            ids = np.array([rid(e) for e in ordered], np.uint32)
            pmf = np.array([mitsuba_pmf[position[rid(e)]] for e in ordered], np.float32)
        full = pmf
        excluded = np.zeros(len(pmf), bool)
        excluded[exclude] = True
        if exclude:
            kept = np.where(excluded, 0.0, full.astype(np.float64))
            total = kept.sum()
            pmf = (kept / total if total > 0 else kept).astype(np.float32)
        scale = np.where(full > 0, pmf.astype(np.float64) / np.where(full > 0, full, 1.0), 0.0)
        cdf = np.cumsum(pmf, dtype=np.float64)
        positive = np.flatnonzero(pmf > 0)
        last = int(positive[-1]) if positive.size else 0
        if positive.size:
            cdf /= cdf[last]
        cdf[last:] = 1.0
        slot = np.zeros(int(ids.max()) + 1, np.uint32)
        if n:
            slot[ids] = np.arange(1, n + 1, dtype=np.uint32)
        self.emitter = dr.reinterpret_array(mi.EmitterPtr, mi.UInt32(ids))
        self.pmf = mi.Float(pmf)
        self.cdf = mi.Float(cdf.astype(np.float32))
        self.last = dr.opaque(mi.UInt32, last)
        self.mis_scale = mi.Float(scale.astype(np.float32))
        self.excluded = mi.Bool(excluded)
        self.slot = mi.UInt32(slot)
        shapes = render_shapes(scene)
        sids = [int(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(sh))[0]) for sh in shapes]
        apply = np.zeros(max(sids, default=0) + 1, bool)
        if apply_on is None:
            apply[:] = True
        else:
            for sh in apply_on:
                apply[int(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(sh))[0])] = True
        self.apply = mi.Bool(apply)
        #: the excluded indices (a Python tuple, not part of the Dr.Jit struct)
        self.exclude = tuple(exclude)
        dr.make_opaque(self.emitter, self.pmf, self.cdf, self.mis_scale, self.excluded,
                       self.slot, self.apply)

    def __len__(self) -> int:
        """Number of emitters (the null entry of an emitter-less scene does not count)."""
        return int(np.count_nonzero(np.array(dr.reinterpret_array(mi.UInt32, self.emitter))))


@dr.syntax
def sample_emitter_direction(scene: mi.Scene, emitters: EmitterTable,
                             si: mi.SurfaceInteraction3f, sample: mi.Point2f,
                             active: mi.Bool, other: EmitterTable | None = None,
                             use_other: mi.Bool | None = None
                             ) -> tuple[mi.DirectionSample3f, mi.Color3f]:
    """``scene.sample_emitter_direction(si, sample, True, active)`` with the emitter picked
    from ``emitters`` (a load-independent order) instead of Mitsuba's emitter list; where
    ``use_other`` is set, from the table ``other`` (of the same emitters) instead.

    Same semantics as Mitsuba's ``Scene::sample_emitter_direction``: the emitter is chosen
    with probability ``pmf`` (Mitsuba's, so ``scene.pdf_emitter_direction`` stays the MIS pdf
    of this technique) from ``sample.x``, which is then rescaled and reused; the weight is
    divided by ``pmf`` and ``ds.pdf`` multiplied by it; occluded samples get weight and pdf 0
    (shadow ray ``si.spawn_ray_to(ds.p)``; for environment emitters ``ds.p`` lies on a sphere
    around the scene). A scene without emitters gives weight 0 and pdf 0."""
    x = sample.x
    two = other is not None
    alt = use_other if two else mi.Bool(False)

    def read(name: str, index: mi.UInt32, mask: mi.Bool) -> mi.Float:
        v = dr.gather(mi.Float, getattr(emitters, name), index, mask & ~alt)
        if two:
            v = dr.select(alt, dr.gather(mi.Float, getattr(other, name), index, mask & alt), v)
        return v

    # first index with cdf > x in [0, last] (the CDF is exactly 1 from ``last`` on, and
    # zero-pmf entries repeat the previous CDF value, so they are never chosen)
    lo = mi.UInt32(0)
    hi = mi.UInt32(emitters.last)
    if two:
        hi = dr.select(alt, mi.UInt32(other.last), hi)
    while active & (lo < hi):
        mid = (lo + hi) >> 1
        right = read("cdf", mid, active) <= x
        lo = dr.select(right, mid + 1, lo)
        hi = dr.select(right, hi, mid)
    pmf = read("pmf", lo, active)
    cdf_hi = read("cdf", lo, active)
    cdf_lo = read("cdf", lo - 1, active & (lo > 0))
    active = active & (pmf > 0)
    # reuse sample.x: its position within the chosen emitter's CDF interval
    x_re = dr.select(active, (x - cdf_lo) / (cdf_hi - cdf_lo), 0.0)
    x_re = dr.clip(x_re, 0.0, dr.one_minus_epsilon(mi.Float))
    emitter = dr.gather(mi.EmitterPtr, emitters.emitter, lo, active)
    ds, spec = emitter.sample_direction(si, mi.Point2f(x_re, sample.y), active)
    ds.pdf *= pmf
    spec = dr.select(active, spec / pmf, 0.0)
    active &= ds.pdf != 0
    occluded = scene.ray_test(si.spawn_ray_to(ds.p), active)
    spec = dr.select(occluded, 0.0, spec)
    ds.pdf = dr.select(occluded, 0.0, ds.pdf)
    return ds, mi.Color3f(spec)


@dataclass
class ShadeResult:
    emission: mi.Color3f
    direct_diffuse: mi.Color3f
    direct_specular: mi.Color3f
    indirect_diffuse: mi.Color3f
    indirect_specular: mi.Color3f
    si: mi.SurfaceInteraction3f
    bsdf: mi.BSDFPtr
    #: the primary hit's lobe albedos from Mitsuba's sampling where the shape's material
    #: needs them (:func:`sampled_albedo`; None: no shape of the scene does)
    albedo: tuple[mi.Color3f, mi.Color3f] | None = None
    #: per lane: a primary hit on a shape where ``primary``'s exclusion does not apply (its
    #: direct light is path-traced from every emitter); None without a ``primary`` table
    fallback: mi.Bool | None = None


def _diffuse_share(bsdf, ctx_d, ctx_s, si, bs, active,
                   separable: mi.Bool | None = None) -> mi.Color3f:
    """The diffuse lobe's share of what a BSDF sample carries: ``f_d / p_mix`` of the sampled
    direction over the sample's weight ``f / p_mix``, i.e. ``f_d / f`` (the lobes' f sum to
    f), so ``indirect_diffuse`` estimates the integral of ``f_d L`` and ``indirect_specular``
    that of ``f_s L`` whatever lobe the sample came from (a mixture's sample weight holds
    every lobe: roughplastic's ``f / p_mix`` is diffuse and glossy). A delta sample is all
    specular (its direction has measure zero for the other lobes, which eval() reports as 0);
    where both lobes evaluate to 0 the sampled lobe takes it all. Where ``separable`` is
    False (a BSDF whose ``eval`` ignores the lobe masks: :func:`glossrt.render.materials.
    lobes_separable`) the sampled lobe's flag decides alone (``bs.sampled_type``)."""
    delta = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
    sampled_diffuse = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Diffuse)
    by_eval = active & ~delta if separable is None else active & ~delta & separable
    f_d = mi.Color3f(bsdf.eval(ctx_d, si, bs.wo, by_eval))
    f_s = mi.Color3f(bsdf.eval(ctx_s, si, bs.wo, by_eval))
    f = f_d + f_s
    share = dr.select(f > 0, f_d / dr.select(f > 0, f, 1.0), dr.select(sampled_diffuse, 1.0, 0.0))
    if separable is not None:
        share = dr.select(separable, share, dr.select(sampled_diffuse, 1.0, 0.0))
    return dr.select(delta, 0.0, share)


#: BSDF samples per pixel of :func:`sampled_albedo` (a fixed, stratified set: the G-buffer
#: stays noise-free)
ALBEDO_SAMPLES = 16


def _stratum(i: mi.UInt32) -> tuple[mi.Float, mi.Point2f]:
    """Sample ``i`` of :data:`ALBEDO_SAMPLES` fixed stratified ones: ``u1 = (j + 1/2) / N``
    with ``j`` a permutation of ``i`` (7 is coprime to 16), ``u2`` on a 4 x 4 grid."""
    n = ALBEDO_SAMPLES
    side = int(round(n ** 0.5))
    j = (i * 7 + 3) % n
    return ((mi.Float(j) + 0.5) / n,
            mi.Point2f((mi.Float(i % side) + 0.5) / side, (mi.Float(i // side) + 0.5) / side))


@dr.syntax
def sampled_albedo(bsdf: mi.BSDFPtr, si: mi.SurfaceInteraction3f, active: mi.Bool,
                   separable: mi.Bool) -> tuple[mi.Color3f, mi.Color3f]:
    """The directional albedos of a BSDF's diffuse and non-diffuse lobes at ``si`` (towards
    ``si.wi``) from Mitsuba's own ``sample`` and ``eval`` with :data:`ALBEDO_SAMPLES` fixed
    stratified numbers (:func:`_stratum`: deterministic, so the G-buffer stays noise-free):
    the albedos of BSDFs the split-sum tables do not describe (glass, principled, blends,
    masks, bump maps, ...; docs/FORMATS.md).

    * The non-diffuse lobes: the mean of the BSDF's sample weights ``f cos / pdf``, each
      split between the lobes as the path tracer splits it (:func:`_diffuse_share`).
    * The diffuse lobes, where ``separable`` (``eval`` honours ``BSDFContext.type_mask``):
      cosine-weighted quadrature of ``eval`` with the diffuse mask over the hemisphere of
      ``wi`` (a plastic's mixture may send all of its samples to the coating, and Mitsuba's
      ``pplastic`` does not weight a sample drawn with one lobe's mask correctly, so neither
      sampling gives a diffuse lobe its albedo reliably). Elsewhere (``principled``) the
      sampled split's diffuse part."""
    ctx = mi.BSDFContext()
    diffuse_mask, specular_mask = lobe_masks()
    ctx_d, ctx_s = _context(diffuse_mask), _context(specular_mask)
    a_d = dr.zeros(mi.Color3f)
    a_s = dr.zeros(mi.Color3f)
    q_d = dr.zeros(mi.Color3f)
    up = dr.select(mi.Frame3f.cos_theta(si.wi) < 0.0, -1.0, 1.0)
    i = mi.UInt32(0)
    while active & (i < ALBEDO_SAMPLES):
        u1, u2 = _stratum(i)
        bs, w = bsdf.sample(ctx, si, u1, u2, active)
        w = dr.select(dr.isfinite(w), mi.Color3f(w), 0.0)
        share = _diffuse_share(bsdf, ctx_d, ctx_s, si, bs, active, separable)
        a_d += w * share
        a_s += w * (1.0 - share)
        # (cosine sampling: pdf cos / pi, and eval includes the cosine)
        wo = mi.warp.square_to_cosine_hemisphere(u2)
        wo.z = wo.z * up
        f_d = mi.Color3f(bsdf.eval(ctx_d, si, wo, active & separable))
        q_d += dr.select(wo.z * up > 0.0, f_d * dr.pi / (wo.z * up), 0.0)
        i += 1
    n = ALBEDO_SAMPLES
    return dr.select(separable, q_d, a_d) / n, a_s / n


def _primary_hit_weight(primary: EmitterTable | None, dsk: mi.DirectionSample3f,
                        em_pdf: mi.Float, first: mi.Bool, applies: mi.Bool,
                        active: mi.Bool) -> tuple[mi.Float, mi.Bool]:
    """For a BSDF-sampled ray that hit an emitter: the MIS pdf of the emitter-sampling
    technique that could have drawn the same direction, and whether the hit counts.

    Without a primary table (``primary`` None) that is Mitsuba's ``em_pdf`` and every hit
    counts. With one, at the primary hit (``first``: the ray left path vertex 0) of a lane
    where its exclusion ``applies`` the next-event estimation there picked emitters from
    ``primary``, so the pdf is ``em_pdf * mis_scale`` (its selection probability instead of
    Mitsuba's; Veach 1997, eq. 9.13 needs the pdf of the technique actually used), and hits
    of excluded emitters do not count; from deeper vertices, and on lanes where the
    exclusion does not apply, both stay as they are."""
    if primary is None:
        return em_pdf, active
    rid = dr.reinterpret_array(mi.UInt32, dsk.emitter)
    on = active & first & applies & (rid != 0)
    k = dr.gather(mi.UInt32, primary.slot, rid, on)
    on &= k != 0
    scale = dr.gather(mi.Float, primary.mis_scale, k - 1, on)
    excluded = dr.gather(mi.Bool, primary.excluded, k - 1, on)
    return dr.select(on, em_pdf * scale, em_pdf), active & ~(on & excluded)


#: most fully transparent surfaces (a ``mask`` of opacity 0, a ``null`` BSDF) a primary ray
#: passes through before the G-buffer takes its hit (:func:`primary_hit`)
NULL_SKIPS = 8


@dr.syntax
def primary_hit(scene: mi.Scene, ray: mi.Ray3f, shapes: ShapeTable | None
                ) -> tuple[mi.SurfaceInteraction3f, mi.UInt32]:
    """The primary hit of ``ray`` and how many surfaces the ray passed through to reach it:
    the first surface that is not fully transparent. A surface whose BSDF passes all light
    through unchanged (``eval_null_transmission`` 1 in every channel: a ``mask`` BSDF where
    its opacity is 0, a ``null`` BSDF) and that emits nothing is passed through, up to
    :data:`NULL_SKIPS` times, so an alpha-masked leaf shows what lies behind its cut-out in
    every G-buffer channel (alpha testing). Light transport is unchanged: Mitsuba samples
    such a surface's null lobe with probability 1 and weight 1, a straight continuation,
    which counts as a path vertex of its ``max_depth`` (:func:`shade` counts the surfaces
    passed through so). Scenes without such BSDFs (``shapes.any_null`` False) trace one
    ray."""
    si = scene.ray_intersect(ray, ray_flags=mi.RayFlags.All, coherent=True)
    k = mi.UInt32(0)
    if dr.hint(shapes is None or not shapes.any_null, mode="scalar"):
        return si, k
    null = shapes.null  # (read here: the loop's state holds Dr.Jit values only)
    through = mi.Bool(True)
    while through & (k < NULL_SKIPS):
        rid = dr.select(si.is_valid(), dr.reinterpret_array(mi.UInt32, si.shape), 0)
        candidate = si.is_valid() & dr.gather(mi.Bool, null, rid, si.is_valid())
        t = mi.Color3f(si.bsdf(ray).eval_null_transmission(si, candidate))
        through = candidate & dr.all(t >= 1.0)
        if through:
            si = scene.ray_intersect(si.spawn_ray(ray.d), ray_flags=mi.RayFlags.All,
                                     coherent=True, active=through)
            k += 1
    return si, k


def _shadow_terminator(n: mi.Vector3f, w: mi.Vector3f) -> mi.Float:
    """Mitsuba's ``normalmap`` shadowing term (its ``use_shadowing_function``, default on;
    Conty Estevez, Lecocq, Stein 2019, "A Microfacet-Based Shadowing Function to Solve the
    Bump Terminator Problem"): ``2 / (1 + sqrt(1 + a2 tan^2(w)))`` with
    ``a2 = min(tan^2(n) / 8, 1)``; ``n`` the perturbed normal and ``w`` a direction, both in
    the unperturbed shading frame."""
    a2 = dr.minimum(0.125 * mi.Frame3f.tan_theta_2(n), 1.0)
    return 2.0 / (1.0 + dr.sqrt(1.0 + a2 * mi.Frame3f.tan_theta_2(w)))


class PrimaryLobe:
    """The primary hit's rough lobe with a per-pixel roughness ``alpha`` in place of the
    material's: Mitsuba's ``roughconductor`` and ``roughplastic`` specular lobe re-evaluated
    (eval, sampling, pdf) from Mitsuba's own pieces with a per-lane alpha
    (``mi.MicrofacetDistribution``: the material's ``distribution``, Beckmann or GGX, with
    visible-normal sampling; its separable Smith ``G1(wi) G1(wo)``; ``mi.fresnel_conductor``
    / ``mi.fresnel`` times ``specular_reflectance``), inside a one-BSDF ``twosided`` and a
    ``normalmap`` as those plugins evaluate their nested BSDF (mirrored ``wi`` / ``wo``;
    perturbed frame with ``flip_invalid_normals`` and the shadow-terminator term).

    ``on``: the lanes it applies to: a valid hit, a shape whose BSDF
    :func:`glossrt.render.materials.lobe_override` accepts, and ``alpha >= 0`` (a negative or
    NaN alpha keeps the material's). Every other lane (smooth, diffuse or other BSDFs) keeps
    Mitsuba's BSDF. ``roughplastic``'s diffuse lobe is always Mitsuba's (see
    :class:`glossrt.render.materials.LobeOverride`); its sampling mixture picks the specular
    lobe with ``p_s = (1 - t) w / ((1 - t) w + t (1 - w))`` (Mitsuba's form, ``w`` the
    ``specular_sampling_weight``) with ``t = 1 - F(cos_i)``, the smooth interface's
    transmittance, instead of Mitsuba's table of the rough interface at the material's alpha:
    another valid sampling technique, whose pdf the MIS weights use, so the estimate stays
    unbiased. With the material's own alpha a ``roughconductor`` reproduces Mitsuba's
    samples, values and pdfs (to float rounding); a ``roughplastic`` its values and its
    specular pdf, with this mixture.

    ``key``: :attr:`ShapeTable.lobe_key` (which distributions to trace, any normal map)."""

    def __init__(self, si: mi.SurfaceInteraction3f, bsdf: mi.BSDFPtr, shapes, alpha: mi.Float,
                 active: mi.Bool, key: tuple[bool, bool, bool]):
        from .materials import LOBE_CONDUCTOR, LOBE_NONE, LOBE_PLASTIC

        self.key = key
        valid = active & si.is_valid()
        rid = dr.select(valid, dr.reinterpret_array(mi.UInt32, si.shape), 0)
        kind = dr.gather(mi.UInt32, shapes.lobe, rid, valid)
        self.on = valid & (kind != LOBE_NONE) & (alpha >= 0.0)
        on = self.on
        self.conductor = kind == LOBE_CONDUCTOR
        self.plastic = kind == LOBE_PLASTIC
        # Mitsuba's MicrofacetDistribution clamps alpha below at 1e-4 itself
        self.alpha = dr.select(on, alpha, 0.5)
        self.beckmann = dr.gather(mi.Bool, shapes.beckmann, rid, on)
        self.eta = dr.gather(mi.Color3f, shapes.eta, rid, on)
        self.k = dr.gather(mi.Color3f, shapes.k, rid, on)
        self.scale = dr.gather(mi.Color3f, shapes.spec_scale, rid, on)
        self.weight = dr.gather(mi.Float, shapes.spec_weight, rid, on)
        twosided = dr.gather(mi.Bool, shapes.lobe_twosided, rid, on)
        wi = mi.Vector3f(si.wi)
        # twosided (one BSDF): wi mirrored to the front, wo.z by wi.z's sign
        self.sign = dr.select(twosided & (wi.z < 0.0), -1.0, 1.0)
        wi.z = wi.z * self.sign
        self.mapped = mi.Bool(False)
        self.n = mi.Vector3f(0.0, 0.0, 1.0)
        self.frame = mi.Frame3f(mi.Vector3f(1, 0, 0), mi.Vector3f(0, 1, 0), mi.Vector3f(0, 0, 1))
        if key[2]:
            self.mapped = on & dr.gather(mi.Bool, shapes.lobe_normal_map, rid, on)
            n = dr.fma(mi.Vector3f(bsdf.eval_attribute_3("normalmap", si, self.mapped)),
                       2.0, -1.0)
            flip = mi.Frame3f.cos_theta(wi) * dr.dot(wi, n) <= 0.0  # flip_invalid_normals
            n.x = dr.select(flip, -n.x, n.x)
            n.y = dr.select(flip, -n.y, n.y)
            inv = dr.rsqrt(dr.squared_norm(n))
            n = dr.select((inv > 0.0) & dr.isfinite(inv), n * inv, mi.Vector3f(0, 0, 1))
            t = dr.fma(-n, n.x, mi.Vector3f(1, 0, 0))  # Gram-Schmidt of (1, 0, 0)
            inv_t = dr.rsqrt(dr.squared_norm(t))
            t = dr.select(dr.isfinite(inv_t), t * inv_t, mi.Vector3f(0, 1, 0))
            n = dr.select(self.mapped, n, mi.Vector3f(0, 0, 1))
            t = dr.select(self.mapped, t, mi.Vector3f(1, 0, 0))
            self.n = n
            self.frame = mi.Frame3f(t, dr.cross(n, t), n)
        self.wi_base = wi
        self.wi = dr.select(self.mapped, self.frame.to_local(wi), wi)

    # -- the nested lobe, in its own (perturbed) frame ----------------------------------------
    def _distributions(self):
        out = []
        if self.key[0]:
            out.append((self.beckmann, mi.MicrofacetDistribution(mi.MicrofacetType.Beckmann,
                                                                 self.alpha, True)))
        if self.key[1]:
            out.append((~self.beckmann, mi.MicrofacetDistribution(mi.MicrofacetType.GGX,
                                                                  self.alpha, True)))
        return out

    def _pick(self, fn):
        """``fn(distribution)`` for each distribution the scene uses, per lane the lane's."""
        res = None
        for mask, d in self._distributions():
            v = fn(d)
            res = v if res is None else dr.select(mask, v, res)
        return res

    def _fresnel(self, cos: mi.Float) -> mi.Color3f:
        cond = mi.Color3f(*(mi.fresnel_conductor(cos, mi.Complex2f(self.eta[c], self.k[c]))
                            for c in range(3)))
        diel = mi.Float(mi.fresnel(cos, self.eta[0])[0])
        return dr.select(self.conductor, cond, mi.Color3f(diel)) * self.scale

    def _p_specular(self) -> mi.Float:
        """Probability of sampling the specular lobe (1 for a conductor; see the class)."""
        t = 1.0 - mi.fresnel(mi.Float(self.wi.z), self.eta[0])[0]
        a = (1.0 - t) * self.weight
        b = t * (1.0 - self.weight)
        p = dr.select(a + b > 0.0, a / dr.select(a + b > 0.0, a + b, 1.0), 1.0)
        return dr.select(self.conductor, 1.0, p)

    def _spec(self, wi: mi.Vector3f, wo: mi.Vector3f) -> tuple[mi.Color3f, mi.Float]:
        """The nested specular lobe's value (cosine included, as Mitsuba's ``eval``) and its
        own sampling pdf (visible normals), both 0 outside the upper hemisphere."""
        ok = (wi.z > 0.0) & (wo.z > 0.0)
        h = dr.normalize(wo + wi)

        def terms(d):
            D = d.eval(h)
            g1_i = d.smith_g1(wi, h)
            return mi.Vector3f(D, g1_i, d.smith_g1(wo, h))

        dgg = self._pick(terms)
        f = self._fresnel(dr.dot(wi, h)) * (dgg.x * dgg.y * dgg.z / (4.0 * wi.z))
        pdf = dgg.x * dgg.y / (4.0 * wi.z)
        # roughconductor's pdf also requires both directions above the microfacet
        pdf_ok = ok & (~self.conductor | ((dr.dot(wi, h) > 0.0) & (dr.dot(wo, h) > 0.0)))
        return dr.select(ok, f, 0.0), dr.select(pdf_ok, pdf, 0.0)

    def _to_lobe(self, wo: mi.Vector3f) -> tuple[mi.Vector3f, mi.Vector3f, mi.Bool]:
        """``wo`` (local to ``si.sh_frame``) mirrored like ``wi`` (twosided) and in the
        perturbed frame (normalmap), and whether the normal map keeps it (same side of both
        frames)."""
        wb = mi.Vector3f(wo.x, wo.y, wo.z * self.sign)
        wp = dr.select(self.mapped, self.frame.to_local(wb), wb)
        keep = ~self.mapped | (mi.Frame3f.cos_theta(wb) * mi.Frame3f.cos_theta(wp) > 0.0)
        return wb, wp, keep

    def _shadow(self, wb: mi.Vector3f) -> mi.Float:
        return dr.select(self.mapped, _shadow_terminator(self.n, wb), 1.0)

    # -- what the path tracer calls (directions local to si.sh_frame) --------------------------
    def eval_pdf(self, wo: mi.Vector3f) -> tuple[mi.Color3f, mi.Float, mi.Float]:
        """The overridden specular lobe's value at ``wo``, the pdf of the whole BSDF's
        sampling mixture there (the diffuse lobe's cosine sampling included) and ``p_s``."""
        wb, wp, keep = self._to_lobe(wo)
        f, pdf_s = self._spec(self.wi, wp)
        p_s = self._p_specular()
        ok = self.on & keep & (self.wi.z > 0.0) & (wp.z > 0.0)
        pdf = p_s * pdf_s + (1.0 - p_s) * dr.maximum(wp.z, 0.0) * dr.inv_pi
        f = f * self._shadow(wb)
        return dr.select(ok, f, 0.0), dr.select(ok, pdf, 0.0), p_s

    def sample(self, sample1: mi.Float,
               sample2: mi.Point2f) -> tuple[mi.Vector3f, mi.Float, mi.Bool, mi.Color3f]:
        """One sample of the mixture: direction ``wo`` (local to ``si.sh_frame``), its pdf,
        whether the diffuse lobe drew it, and for conductors Mitsuba's own sample weight
        ``F G1(wo) specular_reflectance`` (times the shadow term under a normal map);
        plastic lanes get their weight from the caller (value over pdf)."""
        wi = self.wi
        p_s = self._p_specular()
        pick_s = self.conductor | (sample1 < p_s)

        def draw(d):
            m, pm = d.sample(wi, sample2)
            return mi.Vector4f(m.x, m.y, m.z, pm)

        mp = self._pick(draw)
        m = mi.Vector3f(mp.x, mp.y, mp.z)
        wo_s = mi.reflect(wi, m)
        wo_d = mi.warp.square_to_cosine_hemisphere(sample2)
        wp = dr.select(pick_s, wo_s, wo_d)
        ok = self.on & (wi.z > 0.0) & (wp.z > 0.0)
        # roughconductor's sample: weight G1(wo, m) F(wi.m) and pdf p(m) / (4 wo.m)
        g1_o = self._pick(lambda d: d.smith_g1(wp, m))
        w_cond = self._fresnel(dr.dot(wi, m)) * g1_o
        pdf_cond = mp.w / (4.0 * dr.dot(wp, m))
        ok_cond = ok & (mp.w != 0.0)
        _, pdf_mix, _ = self._pdf_nested(wp)
        pdf = dr.select(self.conductor, dr.select(ok_cond, pdf_cond, 0.0), pdf_mix)
        # back to the unperturbed frame (normalmap), then un-mirror (twosided)
        wb = dr.select(self.mapped, self.frame.to_world(wp), wp)
        keep = ~self.mapped | (mi.Frame3f.cos_theta(wp) * mi.Frame3f.cos_theta(wb) > 0.0)
        ok &= keep & dr.select(self.conductor, ok_cond, pdf > 0.0)
        w_cond = w_cond * self._shadow(wb)
        wo = mi.Vector3f(wb.x, wb.y, wb.z * self.sign)
        return wo, dr.select(ok, pdf, 0.0), ~pick_s, dr.select(ok, w_cond, 0.0)

    def _pdf_nested(self, wp: mi.Vector3f):
        _, pdf_s = self._spec(self.wi, wp)
        p_s = self._p_specular()
        pdf = p_s * pdf_s + (1.0 - p_s) * dr.maximum(wp.z, 0.0) * dr.inv_pi
        ok = (self.wi.z > 0.0) & (wp.z > 0.0)
        return None, dr.select(ok, pdf, 0.0), p_s


def _primary_eval(lobe: PrimaryLobe | None, bsdf, ctx_s, ctx_all, si, wo, active):
    """At the primary hit: the non-diffuse lobes' value and the whole BSDF's sampling pdf at
    ``wo``: Mitsuba's, or :class:`PrimaryLobe`'s on its lanes."""
    if lobe is None:
        return bsdf.eval(ctx_s, si, wo, active), bsdf.pdf(ctx_all, si, wo, active)
    rest = active & ~lobe.on
    f_s = mi.Color3f(bsdf.eval(ctx_s, si, wo, rest))
    pdf = mi.Float(bsdf.pdf(ctx_all, si, wo, rest))
    f_o, pdf_o, _ = lobe.eval_pdf(wo)
    return dr.select(lobe.on, f_o, f_s), dr.select(lobe.on, pdf_o, pdf)


def _primary_sample(lobe: PrimaryLobe | None, bsdf, ctx_d, ctx_s, ctx_all, si, sample1,
                    sample2, active, separable=None):
    """BSDF sampling at the primary hit: ``(wo local, pdf, delta, weight, diffuse share,
    eta)`` (``eta``: the sample's relative index of refraction, for Russian roulette),
    Mitsuba's or :class:`PrimaryLobe`'s on its lanes (a plastic's weight is its value, the
    overridden specular lobe plus Mitsuba's diffuse lobe, over the mixture's pdf);
    ``separable``: :func:`_diffuse_share`'s."""
    rest = active if lobe is None else active & ~lobe.on
    bs, w = bsdf.sample(ctx_all, si, sample1, sample2, rest)
    share_d = _diffuse_share(bsdf, ctx_d, ctx_s, si, bs, rest, separable)
    wo, pdf = mi.Vector3f(bs.wo), mi.Float(bs.pdf)
    delta = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
    weight = mi.Color3f(w)
    eta = dr.select(rest, mi.Float(bs.eta), 1.0)  # (the overridden lobes reflect: 1)
    if lobe is None:
        return wo, pdf, delta, weight, share_d, eta
    on = lobe.on
    wo_o, pdf_o, diffuse_o, w_cond = lobe.sample(sample1, sample2)
    f_d = mi.Color3f(bsdf.eval(ctx_d, si, wo_o, on & lobe.plastic & (pdf_o > 0.0)))
    f_s, _, _ = lobe.eval_pdf(wo_o)
    f = f_d + f_s
    w_plastic = dr.select(pdf_o > 0.0, f / dr.select(pdf_o > 0.0, pdf_o, 1.0), 0.0)
    w_o = dr.select(lobe.conductor, w_cond, w_plastic)
    share_o = dr.select(f > 0.0, f_d / dr.select(f > 0.0, f, 1.0),
                        dr.select(diffuse_o, 1.0, 0.0))
    return (dr.select(on, wo_o, wo), dr.select(on, pdf_o, pdf), delta & ~on,
            dr.select(on, w_o, weight), dr.select(on, share_o, share_d), eta)


@dr.syntax
def shade(scene: mi.Scene, sampler, ray: mi.Ray3f, max_depth: int,
          emitters: EmitterTable | None = None,
          primary: EmitterTable | None = None, alpha0: mi.Float | None = None,
          shapes: ShapeTable | None = None, rr_depth: int = RR_DEPTH,
          primary_only: bool = False) -> ShadeResult:
    """Trace one path per lane from ``ray`` and return its separated contributions.
    ``emitters``: the scene's :class:`EmitterTable` (built here when not given; pass it in
    from outside when tracing inside ``dr.freeze``). ``shapes``: the scene's
    :class:`ShapeTable` (needed for ``alpha0``, and for the lobe split and albedos of BSDFs
    whose ``eval`` ignores the lobe masks, and the primary hit through fully transparent
    surfaces: :func:`primary_hit`). ``rr_depth``: the depth Russian roulette starts at
    (Mitsuba's ``rr_depth``). ``primary_only``: no vertex after the first bounce (only the
    emitter its BSDF sample hits): the primary hit's light alone, within ``max_depth``.

    ``primary``: an :class:`EmitterTable` with excluded emitters (``EmitterTable(scene,
    exclude=...)``), for path vertex 0 only: where its exclusion applies (``primary.apply``
    of the hit shape), next-event estimation there samples the other emitters from it
    (renormalised probabilities, so no sample is wasted), and a BSDF-sampled ray from vertex
    0 that hits an excluded emitter brings nothing, one that hits another emitter is
    MIS-weighted with that table's pdf (:func:`_primary_hit_weight`). So ``direct_*`` lacks
    the excluded emitters' light there; ``emission`` (seen by the camera) and every deeper
    vertex (``indirect_*``) are unchanged, with the same random numbers. On shapes where the
    exclusion does not apply, vertex 0 samples ``emitters`` (every light, path-traced).

    ``alpha0``: a per-lane microfacet alpha for path vertex 0 only (``shapes``: the scene's
    :class:`ShapeTable`): where the primary hit's BSDF is a rough conductor or rough plastic
    (:class:`PrimaryLobe` says which), its rough lobe takes ``alpha0`` instead of the
    material's roughness in the next-event estimation there (value and MIS pdf), in the
    BSDF sample drawn there (direction, weight, and the pdf the emitter hit from it is
    MIS-weighted with) and in the lobe split of what follows. A negative alpha keeps the
    material's; deeper vertices always do. Used by specular antialiasing (Kaplanyan et al.
    2016's filtered roughness, :mod:`glossrt.specaa`) so that environment maps and
    path-traced light see the filtered roughness too.

    The lobe split at vertex 0 (module docstring) evaluates the lobes through
    ``BSDFContext.type_mask``; for a BSDF whose ``eval`` ignores the mask (``principled``:
    ``ShapeTable.separable``) the BSDF-sampled light goes to the sampled lobe
    (``sampled_type``) and the next-event estimate is split in the ratio of the lobes'
    albedos (:func:`sampled_albedo`, the expected share of the sampled split)."""
    if emitters is None:
        emitters = EmitterTable(scene)
    ctx_all = mi.BSDFContext()
    diffuse_mask, specular_mask = lobe_masks()
    ctx_d, ctx_s = _context(diffuse_mask), _context(specular_mask)
    zero = dr.zeros(mi.Color3f)

    # --- primary hit (path vertex 0) --------------------------------------------------
    # (``passed``: fully transparent surfaces the primary ray went through, path vertices
    # of Mitsuba's max_depth)
    si0, passed = primary_hit(scene, ray, shapes)
    valid0 = si0.is_valid()
    emission = mi.Color3f(si0.emitter(scene).eval(si0))
    bsdf0 = si0.bsdf(ray)
    direct_d, direct_s = mi.Color3f(zero), mi.Color3f(zero)
    act0 = valid0 & (passed + 1 < max_depth)
    rid0 = dr.select(valid0, dr.reinterpret_array(mi.UInt32, si0.shape), 0)
    # where the primary table's exclusion applies (the analytic stage shades those pixels)
    applies = mi.Bool(True)
    fallback = None
    if primary is not None:
        applies = dr.gather(mi.Bool, primary.apply, rid0, valid0)
        fallback = valid0 & ~applies
    separable = None
    albedo = None
    if shapes is not None and shapes.any_sampled:
        on = valid0 & dr.gather(mi.Bool, shapes.sampled, rid0, valid0)
        separable = dr.gather(mi.Bool, shapes.separable, rid0, valid0) | ~valid0
        a_d, a_s = sampled_albedo(bsdf0, si0, on, separable)
        albedo = (dr.select(on, a_d, 0.0), dr.select(on, a_s, 0.0))
        if not shapes.any_inseparable:
            separable = None

    # (a scene without rough conductors or plastics: nothing to override)
    lobe = (None if alpha0 is None or not any(shapes.lobe_key[:2])
            else PrimaryLobe(si0, bsdf0, shapes, alpha0, act0, shapes.lobe_key))

    # next-event estimation, split by lobe; MIS against the full BSDF's pdf
    if primary is None:
        ds, em_w = sample_emitter_direction(scene, emitters, si0, sampler.next_2d(), act0)
    else:
        ds, em_w = sample_emitter_direction(scene, emitters, si0, sampler.next_2d(), act0,
                                            primary, applies)
    wo = si0.to_local(ds.d)
    f_d = bsdf0.eval(ctx_d, si0, wo, act0)
    f_s, pdf_b = _primary_eval(lobe, bsdf0, ctx_s, ctx_all, si0, wo, act0)
    if separable is not None:
        # eval ignores the lobe masks (f_d and f_s are each the whole BSDF): the whole
        # value, split in the ratio of the lobes' albedos
        whole = dr.select(separable, f_d + f_s, f_d)
        a_sum = albedo[0] + albedo[1]
        ratio = dr.select(a_sum > 0, albedo[0] / dr.select(a_sum > 0, a_sum, 1.0), 0.5)
        f_d = dr.select(separable, f_d, whole * ratio)
        f_s = dr.select(separable, f_s, whole * (1.0 - ratio))
    w_em = dr.select(ds.delta, 1.0, _mis(ds.pdf, pdf_b))
    direct_d += dr.select(act0, em_w * f_d * w_em, 0.0)
    direct_s += dr.select(act0, em_w * f_s * w_em, 0.0)

    # BSDF sampling at the primary hit decides the lobe of everything further along
    wo0, pdf0, delta0, bsdf_w, share_d, eta = _primary_sample(
        lobe, bsdf0, ctx_d, ctx_s, ctx_all, si0, sampler.next_1d(), sampler.next_2d(), act0,
        separable)
    share_s = 1.0 - share_d
    beta = mi.Spectrum(bsdf_w)
    prev_si = dr.detach(si0)
    prev_pdf = mi.Float(pdf0)
    prev_delta = mi.Bool(delta0)
    ray_k = si0.spawn_ray(si0.to_world(wo0))
    depth = passed + 1  # (Mitsuba's vertex count)
    first = mi.Bool(True)  # the ray left the primary hit
    active = act0 & dr.any(beta != 0.0)
    L_dir = mi.Color3f(zero)  # BSDF-sampled hits of emitters from vertex 0
    L_ind = mi.Color3f(zero)

    # --- vertices 1, 2, ... ----------------------------------------------------------
    while active:
        si = scene.ray_intersect(ray_k, ray_flags=mi.RayFlags.All, coherent=False)
        # emitter hit by BSDF sampling, MIS-weighted against emitter sampling
        dsk = mi.DirectionSample3f(scene, si=si, ref=prev_si)
        em_pdf = scene.pdf_emitter_direction(prev_si, dsk, ~prev_delta)
        em_pdf, counts = _primary_hit_weight(primary, dsk, em_pdf, first, applies, active)
        w_b = dr.select(prev_delta, 1.0, _mis(prev_pdf, em_pdf))
        contrib = beta * w_b * si.emitter(scene).eval(si, counts)
        L_dir += dr.select(active & first, contrib, 0.0)
        L_ind += dr.select(active & ~first, contrib, 0.0)

        active_next = active & si.is_valid() & (depth + 1 < max_depth)
        if primary_only:
            active_next = mi.Bool(False)
        bsdf = si.bsdf(ray_k)
        dsn, em_wn = sample_emitter_direction(scene, emitters, si, sampler.next_2d(),
                                              active_next)
        won = si.to_local(dsn.d)
        f_n, pdf_n = bsdf.eval_pdf(ctx_all, si, won, active_next)
        w_en = dr.select(dsn.delta, 1.0, _mis(dsn.pdf, pdf_n))
        L_ind += dr.select(active_next, beta * em_wn * f_n * w_en, 0.0)

        bsn, wn = bsdf.sample(ctx_all, si, sampler.next_1d(), sampler.next_2d(), active_next)
        beta *= wn
        eta *= dr.select(active_next, mi.Float(bsn.eta), 1.0)
        # Russian roulette as in Mitsuba's path integrator (the throughput times eta^2:
        # radiance compressed into a denser medium is not a reason to end the path)
        q = dr.minimum(dr.max(beta) * dr.square(eta), 0.95)
        rr = active_next & (depth + 1 >= rr_depth)
        survive = sampler.next_1d() < q
        beta = dr.select(rr, beta / q, beta)
        active_next &= ~rr | survive
        prev_si = dr.detach(si)
        prev_pdf = mi.Float(bsn.pdf)
        prev_delta = mi.has_flag(bsn.sampled_type, mi.BSDFFlags.Delta)
        ray_k = si.spawn_ray(si.to_world(bsn.wo))
        depth += 1
        first = mi.Bool(False)
        active = active_next & dr.any(beta != 0.0)

    direct_d += L_dir * share_d
    direct_s += L_dir * share_s
    return ShadeResult(
        emission=emission,
        direct_diffuse=direct_d,
        direct_specular=direct_s,
        indirect_diffuse=L_ind * share_d,
        indirect_specular=L_ind * share_s,
        si=si0,
        bsdf=bsdf0,
        albedo=albedo,
        fallback=fallback,
    )


class ShapeTable:
    """Per-shape constants, indexed by the shape's Dr.Jit registry id (``si.shape``).

    mesh index (1-based position in ``scene.shapes()``), whether the BSDF has a diffuse /
    non-diffuse lobe, its specular F0 (RGB) and roughness: a constant, or the BSDF's
    ``alpha`` attribute evaluated per hit when it is textured; ``normal_map``: whether a
    Mitsuba ``normalmap`` BSDF perturbs the shading normal
    (:data:`glossrt.render.materials.NORMAL_MAP` and friends; 0: no); ``beckmann``: whether
    its rough lobe has Beckmann's microfacet distribution (Mitsuba's default);
    ``distribution``: the ``distribution`` channel's code (:data:`glossrt.brdf.microfacet.
    GGX`, ``BECKMANN`` or ``NO_LOBE``); ``analytic``: whether the analytic shading represents
    the material (:attr:`glossrt.render.materials.Material.analytic`); ``sampled``: whether
    its G-buffer albedos come from Mitsuba's sampling (:func:`sampled_albedo`);
    ``separable``: whether its ``eval`` honours the lobe masks; ``null``: whether a primary
    ray may pass through it (a BSDF with a null lobe on a shape that emits nothing:
    :func:`primary_hit`). Shapes in :func:`glossrt.scenes.render_shapes` order (instanced
    shapes after the scene's own)."""

    DRJIT_STRUCT = VariantStruct(lambda: {
        "index": mi.UInt32,
        "has_diffuse": mi.Bool,
        "has_specular": mi.Bool,
        "alpha_bsdf": mi.UInt32,
        "alpha": mi.Float,
        "f0": mi.Color3f,
        "normal_map": mi.UInt32,
        "beckmann": mi.Bool,
        "alpha_uv": mi.Vector2f,
        "fresnel_kind": mi.UInt32,
        "eta": mi.Color3f,
        "k": mi.Color3f,
        "spec_scale": mi.Color3f,
        "lobe": mi.UInt32,
        "lobe_twosided": mi.Bool,
        "lobe_normal_map": mi.Bool,
        "spec_weight": mi.Float,
        "distribution": mi.Float,
        "analytic": mi.Bool,
        "sampled": mi.Bool,
        "separable": mi.Bool,
        "null": mi.Bool,
    })

    def __init__(self, scene: mi.Scene):
        from ..brdf.microfacet import NO_LOBE, code
        from .materials import alpha_source, describe_bsdf, lobe_override

        shapes = render_shapes(scene)
        ids = [int(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(s))[0]) for s in shapes]
        n = max(ids, default=0) + 1
        index, has_d, has_s, alpha = [0] * n, [False] * n, [False] * n, [0.0] * n
        alpha_bsdf = [0] * n
        f0 = [[0.0] * n for _ in range(3)]
        normal_map = [0] * n
        beckmann = [False] * n
        fres = np.zeros((n, ROW))
        alpha_uv = np.zeros((n, 2))
        lobe, lobe_ts, lobe_nm, spec_w = [0] * n, [False] * n, [False] * n, [1.0] * n
        dist, analytic = [float(NO_LOBE)] * n, [False] * n
        sampled, separable, null = [False] * n, [True] * n, [False] * n
        null_flag = int(mi.BSDFFlags.Null)
        self.materials = {}
        for i, (s, rid) in enumerate(zip(shapes, ids, strict=True)):
            m = describe_bsdf(s.bsdf())
            self.materials[s.id() or f"shape_{i}"] = m
            analytic[rid], sampled[rid], separable[rid] = m.analytic, m.sampled_albedo, \
                m.separable
            null[rid] = bool(int(s.bsdf().flags()) & null_flag) and not s.is_emitter()
            if m.distribution is not None:
                dist[rid] = float(code(m.distribution))
            elif m.analytic:  # no rough lobe: a mirror (alpha 0) or Lambert, as GGX
                dist[rid] = float(code("ggx"))
            index[rid] = i + 1
            has_d[rid], has_s[rid], alpha[rid] = m.has_diffuse, m.has_specular, m.alpha
            if m.alpha_attr:  # (the wrapped BSDF's id where a wrapper has the texture)
                alpha_bsdf[rid] = int(dr.reinterpret_array(
                    mi.UInt32, mi.BSDFPtr(alpha_source(s.bsdf())))[0])
            normal_map[rid] = m.normal_map
            beckmann[rid] = m.beckmann
            fres[rid] = m.fresnel.row()
            alpha_uv[rid] = m.anisotropic if m.anisotropic is not None else (m.alpha, m.alpha)
            for c in range(3):
                f0[c][rid] = m.f0[c]
            o = lobe_override(s.bsdf())
            if o is not None:
                lobe[rid], lobe_ts[rid], lobe_nm[rid], spec_w[rid] = (
                    o.kind, o.twosided, o.normal_map, o.spec_weight)
        self.index = mi.UInt32(index)
        self.has_diffuse = mi.Bool(has_d)
        self.has_specular = mi.Bool(has_s)
        #: per shape with a textured roughness: the registry id of the BSDF whose ``alpha``
        #: attribute to evaluate (the shape's own, or the one inside its ``normalmap`` /
        #: ``twosided``: :func:`glossrt.render.materials.alpha_source`); 0 (no object):
        #: the constant ``alpha``
        self.alpha_bsdf = mi.UInt32(alpha_bsdf)
        self.alpha = mi.Float(alpha)
        self.f0 = mi.Color3f(*f0)
        self.normal_map = mi.UInt32(normal_map)
        #: per shape: its rough lobe has Beckmann's distribution (else GGX or no rough lobe)
        self.beckmann = mi.Bool(beckmann)
        #: per shape: (alpha_u, alpha_v) of its rough lobe (both alpha when isotropic)
        self.alpha_uv = mi.Vector2f(*(alpha_uv[:, c].astype(np.float32) for c in range(2)))
        #: whether any shape's rough lobe is anisotropic (a Python bool: the frames say so in
        #: ``meta["anisotropic"]``, and the analytic shading reads the tangent frame then)
        self.any_anisotropic = bool(np.any(alpha_uv[:, 0] != alpha_uv[:, 1]))
        #: per shape: its Fresnel term (:class:`glossrt.brdf.fresnel.Fresnel`)
        self.fresnel_kind = mi.UInt32(fres[:, 0].astype(np.uint32))
        self.eta = mi.Color3f(*(fres[:, 1 + c].astype(np.float32) for c in range(3)))
        self.k = mi.Color3f(*(fres[:, 4 + c].astype(np.float32) for c in range(3)))
        self.spec_scale = mi.Color3f(*(fres[:, 7 + c].astype(np.float32) for c in range(3)))
        #: per shape: whether (and how) a per-pixel roughness replaces the material's at the
        #: primary hit (:data:`glossrt.render.materials.LOBE_NONE` and friends,
        #: :class:`PrimaryLobe`), inside a one-BSDF ``twosided``, inside a ``normalmap``, and
        #: ``roughplastic``'s ``specular_sampling_weight``
        self.lobe = mi.UInt32(lobe)
        self.lobe_twosided = mi.Bool(lobe_ts)
        self.lobe_normal_map = mi.Bool(lobe_nm)
        self.spec_weight = mi.Float(spec_w)
        #: which distributions the overridable lobes use, and whether any is normal-mapped
        #: (Python values: :class:`PrimaryLobe` traces only what the scene needs)
        self.lobe_key = (
            any(lobe[r] and beckmann[r] for r in range(n)),
            any(lobe[r] and not beckmann[r] for r in range(n)),
            any(lobe[r] and lobe_nm[r] for r in range(n)))
        #: whether any shape is normal-mapped (a Python bool: pass it to gbuffer(), so scenes
        #: without normal maps keep the texture lookup's virtual call out of their kernels)
        self.any_normal_map = any(v != 0 for v in normal_map)
        self.distribution = mi.Float(dist)
        self.analytic = mi.Bool(analytic)
        self.sampled = mi.Bool(sampled)
        self.separable = mi.Bool(separable)
        self.null = mi.Bool(null)
        #: Python flags (keys of the traced kernels: what a scene does not need is not
        #: traced): any shape's albedo sampled, any BSDF not separable by lobe masks, any
        #: surface a primary ray may pass through
        self.any_sampled = any(sampled)
        self.any_inseparable = any(sampled[r] and not separable[r] for r in range(n))
        self.any_null = any(null)
        #: those three flags together: a key of the frozen trace (render.Renderer)
        self.material_key = (self.any_sampled, self.any_inseparable, self.any_null)
        #: the 1-based mesh ids of the shapes whose material the analytic shading represents
        self.analytic_ids = tuple(index[r] for r in range(n) if index[r] and analytic[r])


def camera_axes(sensor: mi.Sensor) -> tuple[mi.Point3f, mi.Vector3f]:
    """Camera position and unit viewing axis (camera-space +z) of a sensor."""
    to_world = sensor.world_transform()
    return to_world.translation(), dr.normalize(to_world @ mi.Vector3f(0, 0, 1))


def shading_normal(si: mi.SurfaceInteraction3f, bsdf: mi.BSDFPtr, ray: mi.Ray3f,
                   normal_map: mi.UInt32 | None, active: mi.Bool) -> tuple[mi.Vector3f, mi.Bool]:
    """World-space unit shading normal of the hit ``si`` (seen along ``ray``) that the
    BSDF's reflection is centred on, turned to the camera's side of the surface, and whether
    it is a normal-mapped one.

    Without a normal map (``normal_map`` 0): ``si.sh_frame.n``, negated when it faces away
    from the camera. With one (``normal_map`` :data:`~glossrt.render.materials.NORMAL_MAP`):
    what Mitsuba 3.9's ``normalmap`` BSDF uses (its ``BSDF::sh_frame``, the ``sh_normal`` AOV):
    ``n = 2 tex - 1`` with ``tex`` the normal map at the hit
    (``bsdf.eval_attribute_3("normalmap")``), its tangential part negated when ``wi`` lies
    below it (the plugin's default ``flip_invalid_normals``; a plugin built with that option
    off is not recognised), normalised and taken to world space by ``si.sh_frame``; negated
    like the unperturbed normal on the back side. For ``twosided`` around a normal map
    (:data:`~glossrt.render.materials.NORMAL_MAP_TWOSIDED`) the back side is evaluated as
    Mitsuba's ``twosided`` does: with ``wi`` and the normal's local z mirrored.
    ``normal_map=None`` (no shape of the scene has one): the texture's virtual call is not
    traced at all."""
    n = mi.Vector3f(si.sh_frame.n)
    back = dr.dot(n, -ray.d) < 0
    if normal_map is None:
        return dr.select(back, -n, n), mi.Bool(False)
    mapped = active & (normal_map != 0)
    mirror = back & (normal_map == NORMAL_MAP_TWOSIDED)
    tex = mi.Vector3f(bsdf.eval_attribute_3("normalmap", si, mapped))
    local = dr.fma(tex, 2.0, -1.0)
    wi = mi.Vector3f(si.wi)
    wi.z = dr.select(mirror, -wi.z, wi.z)
    # normalmap's flip_invalid_normals: keep wi above the perturbed normal
    flip = mi.Frame3f.cos_theta(wi) * dr.dot(wi, local) <= 0.0
    local.x = dr.select(flip, -local.x, local.x)
    local.y = dr.select(flip, -local.y, local.y)
    local = dr.normalize(local)
    local.z = dr.select(mirror, -local.z, local.z)
    n = dr.select(mapped, si.sh_frame.to_world(local), n)
    n = dr.select(back & ~mirror, -n, n)  # face the camera
    return n, mapped


def gbuffer(si: mi.SurfaceInteraction3f, bsdf: mi.BSDFPtr, ray: mi.Ray3f, sensor: mi.Sensor,
            shapes: ShapeTable, table,
            albedo: tuple[mi.Color3f, mi.Color3f] | None = None) -> dict:
    """Noise-free G-buffer values of the primary hit. ``normal`` is :func:`shading_normal`
    (normal-mapped where the BSDF is a ``normalmap``); on normal-mapped surfaces the specular
    albedo is looked up at the cosine to that normal (0 should it face away from the camera;
    the plugin's shadow-terminator factor is not included). Scenes without normal maps
    (``ShapeTable.any_normal_map`` False) skip the lookup. ``albedo``: :func:`shade`'s
    sampled lobe albedos (``ShadeResult.albedo``), the albedo channels of the shapes whose
    BSDF the split-sum tables do not describe (``ShapeTable.sampled``)."""
    valid = si.is_valid()
    rid = dr.reinterpret_array(mi.UInt32, si.shape)
    rid = dr.select(valid, rid, 0)
    index = dr.gather(mi.UInt32, shapes.index, rid, valid)
    has_d = dr.gather(mi.Bool, shapes.has_diffuse, rid, valid)
    has_s = dr.gather(mi.Bool, shapes.has_specular, rid, valid)
    alpha = dr.gather(mi.Float, shapes.alpha, rid, valid)
    f0 = dr.gather(mi.Color3f, shapes.f0, rid, valid)
    beckmann = dr.gather(mi.Bool, shapes.beckmann, rid, valid) & valid
    # a textured roughness: evaluated per hit on the BSDF that has it (inside a wrapper: the
    # nested one, at the same texture coordinates)
    source_id = dr.gather(mi.UInt32, shapes.alpha_bsdf, rid, valid)
    attr = valid & (source_id != 0)
    source = dr.reinterpret_array(mi.BSDFPtr, source_id)
    alpha = dr.select(attr, source.eval_attribute_1("alpha", si, valid & attr), alpha)
    normal_map = (dr.gather(mi.UInt32, shapes.normal_map, rid, valid)
                  if shapes.any_normal_map else None)
    n, mapped = shading_normal(si, bsdf, ray, normal_map, valid)
    cos_o = dr.abs(mi.Frame3f.cos_theta(si.wi))
    cos_m = dr.dot(n, -ray.d)
    cos_o = dr.select(mapped, dr.maximum(cos_m, 1e-4), cos_o)
    diffuse_ref = valid & has_d
    if albedo is not None:  # (not asked of the BSDFs whose albedo is sampled)
        diffuse_ref &= ~dr.gather(mi.Bool, shapes.sampled, rid, valid)
    albedo_d = dr.select(diffuse_ref, bsdf.eval_diffuse_reflectance(si, diffuse_ref), 0.0)
    # the split-sum table of the pixel's distribution with Mitsuba's exact Fresnel term at the
    # lobe's effective angle (glossrt.brdf.fresnel)
    ab = table.lookup_ab(cos_o, alpha, beckmann)
    kind = dr.gather(mi.UInt32, shapes.fresnel_kind, rid, valid)
    eta = dr.gather(mi.Color3f, shapes.eta, rid, valid)
    kk = dr.gather(mi.Color3f, shapes.k, rid, valid)
    scale = dr.gather(mi.Color3f, shapes.spec_scale, rid, valid)
    e_spec = split_sum(ab.x + ab.y, ab.y, kind, eta, kk, scale, f0)
    albedo_s = dr.select(valid & has_s, e_spec, 0.0)
    albedo_s = dr.select(mapped & (cos_m <= 0), 0.0, albedo_s)
    if albedo is not None:
        sampled = valid & dr.gather(mi.Bool, shapes.sampled, rid, valid)
        albedo_d = dr.select(sampled, albedo[0], albedo_d)
        albedo_s = dr.select(sampled, albedo[1], albedo_s)
    # the microfacet frame's first axis (Mitsuba's local x, where alpha_u applies) in the
    # plane of the G-buffer normal
    s = mi.Vector3f(si.sh_frame.s)
    s = s - n * dr.dot(n, s)
    tangent = dr.select(valid, dr.normalize(s), 0.0)
    auv = dr.gather(mi.Vector2f, shapes.alpha_uv, rid, valid)
    iso = auv.x == auv.y
    # an isotropic lobe's (alpha, alpha) follows a textured alpha too
    auv = dr.select(iso, mi.Vector2f(alpha, alpha), auv)
    origin, forward = camera_axes(sensor)
    # camera-space z (not si.t: Mitsuba's rays start on the near-clip plane)
    depth = dr.select(valid, dr.dot(si.p - origin, forward), dr.inf)
    return {
        "albedo_diffuse": mi.Color3f(albedo_d),
        "albedo_specular": mi.Color3f(albedo_s),
        "normal": dr.select(valid, n, 0.0),
        "position": dr.select(valid, mi.Vector3f(si.p), 0.0),
        "depth": depth,
        "roughness": dr.select(valid, alpha, 0.0),
        "roughness_uv": dr.select(valid, auv, 0.0),
        "tangent": tangent,
        "distribution": dr.select(valid, dr.gather(mi.Float, shapes.distribution, rid, valid),
                                  float(GGX)),
        "mesh_id": mi.Float(index),
    }


def trace_pixels(scene: mi.Scene, sensor: mi.Sensor, shapes: ShapeTable,
                 emitters: EmitterTable, table, motion_inputs, pixel: mi.UInt32,
                 seed: mi.UInt32, width: int, height: int, max_depth: int,
                 jitter: mi.Point2f | None = None,
                 primary: EmitterTable | None = None,
                 roughness: mi.Float | None = None, skip: tuple[str, ...] = (),
                 rr_depth: int = RR_DEPTH, primary_only: bool = False) -> dict:
    """Every channel for the pixel indices ``pixel`` (y*W + x), plus ``nonfinite``: how many
    radiance values were not finite and were replaced by 0 (see the package docstring), and
    ``fallback``: how many primary hits lie on shapes where ``primary``'s exclusion does
    not apply (their direct light path-traced from every emitter; 0 without ``primary``).
    ``skip``: radiance channels (of :data:`RADIANCE_OUT` and ``color``) and the anisotropy
    channels (:data:`ANISOTROPY_OUT`) left out of the result, so that the kernel writes no
    buffer for them (:func:`pixel_channels`).
    ``jitter`` (pixels, in [-0.5, 0.5), or wider by ``Renderer.render``'s ``jitter_limit``)
    moves every primary ray off the pixel centre; the ``motion`` channel stays that of the
    pixel centre (docs/FORMATS.md: where the surface point seen through the pixel centre was
    in the previous frame, what the reprojecting consumers fetch at ``centre + motion``),
    from a primary ray of its own through the centre. ``primary``: the table of
    :func:`shade`'s next-event estimation at the primary hit (None: ``emitters``).
    ``roughness``: a microfacet alpha per *pixel* (flat, ``width * height``, read at each
    lane's ``pixel``) for the rough lobes of the primary hit (:func:`shade`'s ``alpha0``);
    the G-buffer keeps the material's roughness. ``rr_depth``, ``primary_only``:
    :func:`shade`'s."""
    out, bad, fallback = pixel_channels(scene, sensor, shapes, emitters, table, motion_inputs,
                                        pixel, seed, width, height, max_depth, jitter, primary,
                                        roughness, skip, rr_depth, primary_only)
    # one kernel for everything (a reduction first would re-run the path tracing for it)
    dr.eval(out, bad, fallback)
    out["nonfinite"] = dr.sum(bad)
    out["fallback"] = dr.sum(fallback)
    return out


def pixel_channels(scene: mi.Scene, sensor: mi.Sensor, shapes: ShapeTable,
                   emitters: EmitterTable, table, motion_inputs, pixel: mi.UInt32,
                   seed: mi.UInt32, width: int, height: int, max_depth: int,
                   jitter: mi.Point2f | None = None, primary: EmitterTable | None = None,
                   roughness: mi.Float | None = None,
                   skip: tuple[str, ...] = (),
                   rr_depth: int = RR_DEPTH,
                   primary_only: bool = False) -> tuple[dict, mi.UInt32, mi.UInt32]:
    """:func:`trace_pixels`' channels, not evaluated, the per-lane count of non-finite
    radiance values and whether the lane's primary hit fell back (``ShadeResult.fallback``,
    1 or 0). A skipped channel is still computed and counted (and summed into ``color``):
    only its output is dropped, so the other channels and the count are those of the full
    set (the same arithmetic)."""
    from .motion import motion

    xc = mi.Float(pixel % width) + 0.5
    yc = mi.Float(pixel // width) + 0.5
    x, y = xc, yc
    if jitter is not None:
        x, y = x + jitter.x, y + jitter.y
    pos = mi.Point2f(x / width, y / height)
    ray, _ = sensor.sample_ray(0.0, 0.5, pos, mi.Point2f(0.5, 0.5))
    sampler = PixelSampler(pixel, seed)
    alpha0 = None if roughness is None else dr.gather(mi.Float, roughness, pixel)
    r = shade(scene, sampler, ray, max_depth, emitters, primary, alpha0, shapes, rr_depth,
              primary_only)
    out = gbuffer(r.si, r.bsdf, ray, sensor, shapes, table, r.albedo)
    for name in ANISOTROPY_OUT:  # (the optional G-buffer channels a caller may skip)
        if name in skip:
            del out[name]
    bad = mi.UInt32(0)  # per lane: radiance values that were not finite
    color = dr.zeros(mi.Color3f)
    for name in RADIANCE_OUT:
        v = getattr(r, name)
        ok = dr.isfinite(v)
        for c in range(3):
            bad += dr.select(ok[c], 0, 1)
        v = dr.select(ok, v, 0.0)
        if name not in skip:
            out[name] = v
        color += v
    if "color" not in skip:
        out["color"] = color
    if jitter is None:
        ray_c, si_c, mesh_c = ray, r.si, mi.UInt32(out["mesh_id"])
    else:  # the pixel centre's own primary hit
        ray_c, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f(xc / width, yc / height),
                                     mi.Point2f(0.5, 0.5))
        si_c = (primary_hit(scene, ray_c, shapes)[0] if shapes.any_null else
                scene.ray_intersect(ray_c, ray_flags=mi.RayFlags.Minimal, coherent=True))
        rid = dr.select(si_c.is_valid(), dr.reinterpret_array(mi.UInt32, si_c.shape), 0)
        mesh_c = dr.gather(mi.UInt32, shapes.index, rid, si_c.is_valid())
    # background: a far point along the ray, so camera rotation still moves the sky
    p_motion = dr.select(si_c.is_valid(), mi.Vector3f(si_c.p),
                         mi.Vector3f(ray_c.o + ray_c.d * 1e6))
    out["motion"] = motion(p_motion, mesh_c, mi.Bool(True), mi.Point2f(xc, yc),
                           motion_inputs)
    fallback = (mi.UInt32(0) if r.fallback is None
                else dr.select(r.fallback, mi.UInt32(1), mi.UInt32(0)))
    return out, bad, fallback
