"""What the G-buffer needs to know about a Mitsuba BSDF: lobes, roughness, specular F0 and
whether a ``normalmap`` wrapper perturbs its shading normal.

Wrappers are looked through by their parameter prefixes (``mi.traverse`` keys): ``twosided``
(``brdf_0.``), ``normalmap`` (``nested_bsdf.``) and their combinations."""

from __future__ import annotations

import re
import warnings
from dataclasses import dataclass, field

import drjit as dr
import numpy as np

from ..backend import mi
from ..brdf.fresnel import CONDUCTOR, DIELECTRIC, SCHLICK, Fresnel
from ..errors import GlossrtError


@dataclass
class Material:
    kind: str
    has_diffuse: bool
    has_specular: bool
    alpha: float  # constant microfacet alpha (1 for purely diffuse, 0 for smooth)
    alpha_attr: bool  # evaluate bsdf.eval_attribute_1("alpha") per hit instead
    f0: tuple[float, float, float]
    #: :data:`NORMAL_MAP_NONE`, :data:`NORMAL_MAP` (the BSDF is a ``normalmap``) or
    #: :data:`NORMAL_MAP_TWOSIDED` (a ``twosided`` around one ``normalmap``)
    normal_map: int = 0
    #: the microfacet distribution Mitsuba renders (``"ggx"`` or ``"beckmann"``; Mitsuba's
    #: rough plugins default to Beckmann), ``None`` for a BSDF without a rough lobe
    distribution: str | None = None
    #: ``(alpha_u, alpha_v)`` when they differ (an anisotropic lobe; ``alpha`` is then their
    #: geometric mean), else ``None``
    anisotropic: tuple[float, float] | None = None
    #: the Fresnel term Mitsuba weights the specular lobe with (exact conductor or dielectric)
    fresnel: Fresnel = field(default_factory=Fresnel)
    #: whether glossrt's analytic shading represents the BSDF: Lambert plus at most one
    #: isotropic GGX or Beckmann reflection lobe with an exact conductor or dielectric
    #: Fresnel term (:data:`ANALYTIC_CLASSES`, through ``twosided`` and ``normalmap``). The
    #: others (glass, transmission, blends, masks, bump maps, principled, anisotropic
    #: lobes, ...) are rendered through Mitsuba's own BSDF by the path tracer alone, and
    #: their G-buffer albedos come from Mitsuba's sampling (:func:`glossrt.render.pathtracer.
    #: sampled_albedo`)
    analytic: bool = True
    #: whether Mitsuba's ``eval`` of the BSDF honours ``BSDFContext.type_mask``, so that the
    #: lobes' values can be asked for one at a time (``principled`` evaluates every lobe
    #: whatever the mask: :func:`lobes_separable`)
    separable: bool = True
    #: whether the G-buffer's albedo channels come from Mitsuba's sampling of the BSDF
    #: (:func:`glossrt.render.pathtracer.sampled_albedo`) rather than the split-sum tables
    #: and ``eval_diffuse_reflectance``: BSDFs outside :data:`ANALYTIC_CLASSES`
    sampled_albedo: bool = False

    @property
    def beckmann(self) -> bool:
        """Whether the rough lobe uses Beckmann's distribution."""
        return self.distribution == "beckmann"


#: Mitsuba classes whose BSDF glossrt's analytic shading represents (with the wrappers
#: ``twosided`` and ``normalmap`` around them): Lambert and one microfacet reflection lobe
ANALYTIC_CLASSES = {"SmoothDiffuse", "SmoothConductor", "RoughConductor", "SmoothPlastic",
                    "RoughPlastic", "TwoSidedBRDF", "NormalMap"}
#: Mitsuba classes whose ``eval`` ignores ``BSDFContext.type_mask`` (checked on Mitsuba
#: 3.9: ``principled``'s diffuse, glossy and transmission masks each return the whole BSDF)
NOT_SEPARABLE = {"Principled", "PrincipledThin"}
#: the wrappers whose one nested BSDF carries the lobes (for the ``roughness`` and
#: ``distribution`` channels of BSDFs the analytic shading does not represent)
_WRAPPERS = {"TwoSidedBRDF": "brdf_0", "NormalMap": "nested_bsdf", "BumpMap": "nested_bsdf"}

#: ``Material.normal_map``: no normal map (the shading normal is the shape's)
NORMAL_MAP_NONE = 0
#: a ``normalmap`` BSDF: shading normal ``sh_frame.to_world(normalize(2 tex - 1))``, its
#: tangential part negated where ``wi`` lies below it (see
#: :func:`glossrt.render.pathtracer.shading_normal`)
NORMAL_MAP = 1
#: ``twosided`` with one ``normalmap`` for both sides: seen from the back, Mitsuba evaluates
#: it with ``wi``'s and the normal's local z mirrored
NORMAL_MAP_TWOSIDED = 2

#: parameter prefixes of the BSDF that carries the lobes, through supported wrappers
_PREFIXES = ("", "brdf_0.", "nested_brdf_0.", "nested_bsdf.", "nested_bsdf.brdf_0.",
             "brdf_0.nested_bsdf.")


def _rgb(value) -> np.ndarray:
    a = np.array(value, dtype=np.float64).ravel()
    return np.repeat(a, 3)[:3] if a.size == 1 else a[:3]


def _t3(a) -> tuple[float, float, float]:
    return tuple(float(v) for v in np.asarray(a, np.float64).ravel()[:3])


def _param(params: mi.SceneParameters, *names: str):
    keys = set(params.keys())
    for prefix in _PREFIXES:
        for n in names:
            if prefix + n in keys:
                return params[prefix + n], prefix + n
    return None, None


def _normal_map_kind(bsdf: mi.BSDF, keys: set[str]) -> int:
    """:data:`NORMAL_MAP_NONE` / :data:`NORMAL_MAP` / :data:`NORMAL_MAP_TWOSIDED` for ``bsdf``."""
    kind = bsdf.class_name()
    if kind == "NormalMap":
        return NORMAL_MAP
    if kind == "TwoSidedBRDF" and any(k.startswith("brdf_0.normalmap.") for k in keys):
        if any(k.startswith("brdf_1.") for k in keys):
            warnings.warn(
                "twosided BSDF with two different sides and a normal map: the G-buffer normal "
                "ignores the normal map",
                stacklevel=3,
            )
            return NORMAL_MAP_NONE
        return NORMAL_MAP_TWOSIDED
    return NORMAL_MAP_NONE


_DISTRIBUTION = re.compile(r"distribution\s*=\s*(\w+)")


def bsdf_distribution(bsdf: mi.BSDF) -> str | None:
    """The microfacet distribution of ``bsdf`` (through wrappers: the first rough BSDF in its
    description, which for ``twosided`` is its front side), as Mitsuba prints it (``ggx`` or
    ``beckmann``); ``None`` when it has no rough lobe. Mitsuba 3 exposes the choice only in
    the plugin's string form."""
    m = _DISTRIBUTION.search(str(bsdf))
    return m.group(1).lower() if m else None


#: view cosines of :func:`diffuse_scale`'s table: ``(i / (n - 1))^2``, uniform in sqrt(cos)
DIFFUSE_SCALE_NODES = 33


def diffuse_scale(bsdf: mi.BSDF, samples: int = 32) -> np.ndarray:
    """Mitsuba's diffuse lobe of ``bsdf`` integrated over the light directions, divided by its
    diffuse reflectance: ``s(cos_o) = integral f_d(wo, wi) cos_i dwi / rho`` per RGB channel
    at :data:`DIFFUSE_SCALE_NODES` view cosines ``(i / (n - 1))^2`` (``(n, 3)``), from
    Mitsuba's own ``eval`` with ``type_mask = DiffuseReflection`` on ``samples^2``
    cosine-stratified directions. 1 for Lambert; ``plastic`` and ``roughplastic`` scale their
    diffuse reflectance by the coating's transmission in and out (``(1 - F_i)(1 - F_o) /
    eta^2`` and internal reflections): for ``eta = 1.49`` 0.96 at normal incidence for
    ``plastic``, 0.66 (normal) to 0.47 (grazing) for ``roughplastic`` (alpha 0.3). Zeros
    for a BSDF without a diffuse lobe; ones for a normal-mapped one (``Material.normal_map``),
    whose canonical evaluation would read its texture (not modelled)."""
    n = DIFFUSE_SCALE_NODES
    cos_o = (np.arange(n) / (n - 1.0)) ** 2
    if not int(bsdf.flags()) & int(mi.BSDFFlags.DiffuseReflection):
        return np.zeros((n, 3))
    if _normal_map_kind(bsdf, set(mi.traverse(bsdf).keys())) != NORMAL_MAP_NONE:
        return np.ones((n, 3))
    m = samples * samples
    k = np.arange(m)
    u = mi.Point2f(mi.Float(np.tile(((k % samples) + 0.5) / samples, n)),
                   mi.Float(np.tile(((k // samples) + 0.5) / samples, n)))
    wi = mi.warp.square_to_cosine_hemisphere(u)
    c = np.repeat(np.maximum(cos_o, 1e-4), m)
    si = dr.zeros(mi.SurfaceInteraction3f, n * m)
    si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
    si.wi = mi.Vector3f(mi.Float(np.sqrt(1 - c * c)), 0.0, mi.Float(c))
    si.uv = mi.Point2f(0.5, 0.5)
    ctx = mi.BSDFContext()
    ctx.type_mask = int(mi.BSDFFlags.DiffuseReflection)
    val = np.array(bsdf.eval(ctx, si, wi), np.float64).reshape(3, n, m)
    # cosine sampling: pdf cos / pi, and eval includes the cosine: weight pi eval / cos
    e = (val * np.pi / np.maximum(np.array(wi.z), 1e-8).reshape(n, m)).mean(-1)
    rho = np.array(bsdf.eval_diffuse_reflectance(si), np.float64).reshape(3, -1)
    rho = np.broadcast_to(rho, (3, n * m)).reshape(3, n, m)[..., 0]  # constant: width 1
    return np.where(rho > 0, e / np.maximum(rho, 1e-12), 1.0).T


def _children(obj) -> dict:
    """The objects a Mitsuba plugin hands to ``traverse`` (a wrapper's nested BSDFs), by
    name (:func:`glossrt.scenes.children`)."""
    from ..scenes import children

    return children(obj)


def nested_classes(bsdf: mi.BSDF) -> set[str]:
    """The Mitsuba class names of ``bsdf`` and every BSDF nested in it."""
    out = {bsdf.class_name()}
    for child in _children(bsdf).values():
        if isinstance(child, mi.BSDF):
            out |= nested_classes(child)
    return out


def _unwrapped(bsdf: mi.BSDF) -> mi.BSDF:
    """The BSDF inside ``twosided`` (one BSDF for both sides), ``normalmap`` and ``bumpmap``
    wrappers (``bsdf`` itself when it is none of them)."""
    name = _WRAPPERS.get(bsdf.class_name())
    if name is None:
        return bsdf
    objects = _children(bsdf)
    if bsdf.class_name() == "TwoSidedBRDF" and objects.get("brdf_1", objects.get("brdf_0")) \
            is not objects.get("brdf_0"):
        return bsdf  # two different sides
    nested = objects.get(name)
    return _unwrapped(nested) if isinstance(nested, mi.BSDF) else bsdf


def _probe_interactions(n: int, seed: int = 1) -> tuple:
    """``n`` surface interactions with random texture coordinates and view directions (both
    hemispheres), a plausible frame and differentials, and ``n`` random directions."""
    rng = np.random.default_rng(seed)

    def unit(v):
        return v / np.linalg.norm(v, axis=1, keepdims=True)

    def vec(a):
        return mi.Vector3f(*(mi.Float(np.ascontiguousarray(a[:, i], np.float32))
                             for i in range(3)))

    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.n = mi.Normal3f(0.0, 0.0, 1.0)
    si.sh_frame = mi.Frame3f(mi.Vector3f(0.0, 0.0, 1.0))
    si.dp_du = mi.Vector3f(1.0, 0.0, 0.0)
    si.dp_dv = mi.Vector3f(0.0, 1.0, 0.0)
    si.uv = mi.Point2f(mi.Float(rng.random(n, np.float32)), mi.Float(rng.random(n, np.float32)))
    si.p = mi.Point3f(si.uv.x, si.uv.y, 0.0)
    si.wi = vec(unit(rng.normal(size=(n, 3))))
    return si, vec(unit(rng.normal(size=(n, 3))))


def lobes_separable(bsdf: mi.BSDF, samples: int = 256) -> bool:
    """Whether Mitsuba's ``eval`` of ``bsdf`` honours ``BSDFContext.type_mask``: the diffuse
    and the non-diffuse values add up to the whole (to 1e-3 of the largest value) at
    ``samples`` random texture coordinates and direction pairs. Classes known either way
    are not evaluated (:data:`ANALYTIC_CLASSES` are, :data:`NOT_SEPARABLE` are not)."""
    classes = nested_classes(bsdf)
    if classes & NOT_SEPARABLE:
        return False
    if classes <= ANALYTIC_CLASSES | {"SmoothDielectric", "RoughDielectric", "ThinDielectric",
                                      "BlendBSDF", "MaskBSDF", "BumpMap", "Null"}:
        return True
    diffuse = int(mi.BSDFFlags.Diffuse)
    si, wo = _probe_interactions(samples)
    whole = np.array(bsdf.eval(mi.BSDFContext(), si, wo), np.float64)
    parts = 0.0
    for mask in (diffuse, int(mi.BSDFFlags.All) & ~diffuse):
        ctx = mi.BSDFContext()
        ctx.type_mask = mask
        parts = parts + np.array(bsdf.eval(ctx, si, wo), np.float64)
    scale = float(np.max(np.abs(whole), initial=0.0))
    return not scale > 0 or float(np.max(np.abs(parts - whole))) <= 1e-3 * scale


def _generic(bsdf: mi.BSDF, params) -> Material:
    """The :class:`Material` of a BSDF the analytic shading does not represent: its lobes
    from Mitsuba's flags; ``distribution``: the microfacet distribution of a rough plugin
    without nested BSDFs (dielectric, conductor, plastic, polarized plastic), also inside
    ``twosided``, ``normalmap`` and ``bumpmap`` wrappers (a bump-mapped rough plastic is
    still its lobe; None: no single microfacet lobe describes the surface, the
    ``distribution`` channel's "no analytic lobe"); ``alpha``:
    that lobe's roughness (``alpha_attr`` when textured), a ``principled`` BSDF's
    ``roughness^2`` (its alpha), else 0 for a BSDF with a delta or glossy lobe and 1 for a
    diffuse one."""
    flags = int(bsdf.flags())
    has_d = bool(flags & int(mi.BSDFFlags.Diffuse))
    has_s = bool(flags & (int(mi.BSDFFlags.Glossy) | int(mi.BSDFFlags.Delta)))
    inner = _unwrapped(bsdf)
    alpha, alpha_attr, distribution = (0.0 if has_s else 1.0), False, None
    # one microfacet lobe: a rough plugin without nested BSDFs (rough dielectric, conductor,
    # plastic, polarized plastic, ...) that prints its distribution
    single = (bsdf_distribution(inner) is not None
              and not any(isinstance(c, mi.BSDF) for c in _children(inner).values()))
    if single:
        distribution = bsdf_distribution(inner)
        ip = mi.traverse(inner)
        if "alpha.value" in ip.keys():
            alpha = float(np.array(ip["alpha.value"]).ravel()[0])
        elif "alpha_u.value" in ip.keys() and "alpha_v.value" in ip.keys():
            alpha = float(np.sqrt(np.array(ip["alpha_u.value"]).ravel()[0]
                                  * np.array(ip["alpha_v.value"]).ravel()[0]))
        else:
            alpha_attr = alpha_source(bsdf) is not None
    else:
        r, _ = _param(params, "roughness.value")
        if r is not None:
            alpha = float(np.array(r).ravel()[0]) ** 2
    return Material(bsdf.class_name(), has_d, has_s, alpha, alpha_attr, (0.0, 0.0, 0.0),
                    NORMAL_MAP_NONE, distribution, None, Fresnel(), analytic=False,
                    separable=lobes_separable(bsdf), sampled_albedo=True)


def alpha_source(bsdf: mi.BSDF) -> mi.BSDF | None:
    """The BSDF whose ``alpha`` attribute gives ``bsdf``'s roughness at a hit: ``bsdf``
    itself when it has one (a textured roughness), else, through a ``normalmap`` (its
    ``nested_bsdf``) or a ``twosided`` with one BSDF for both sides (its ``brdf_0``), the
    wrapped BSDF's, at any depth; ``None`` when there is none (a constant roughness). The
    wrappers evaluate the nested BSDF at the same texture coordinates, so the nested
    BSDF's attribute is the roughness Mitsuba renders there. (A constant ``alpha`` is an
    attribute too: :func:`describe_bsdf` reads it as a constant before asking.)"""
    if bsdf.has_attribute("alpha"):
        return bsdf
    kind = bsdf.class_name()
    if kind not in _WRAPPERS:
        return None
    objects = _children(bsdf)
    if kind == "TwoSidedBRDF" and objects.get("brdf_1", objects.get("brdf_0")) \
            is not objects.get("brdf_0"):
        return None  # two different sides: no one texture
    nested = objects.get(_WRAPPERS[kind])
    return alpha_source(nested) if isinstance(nested, mi.BSDF) else None


#: textured parameters of the analytic classes that their analytic description has no
#: place for (it takes one Fresnel term and one specular colour per material)
_TEXTURED_FRESNEL = ("specular_reflectance", "eta", "k")


def _beyond_analytic(bsdf: mi.BSDF, params) -> bool:
    """Whether a BSDF of the analytic classes still lies beyond the analytic description: a
    ``twosided`` with two different sides (the description is one material), or a textured
    Fresnel parameter or specular colour (``specular_reflectance``, ``eta``, ``k``)."""
    if bsdf.class_name() == "TwoSidedBRDF":
        objects = _children(bsdf)
        if objects.get("brdf_1", objects.get("brdf_0")) is not objects.get("brdf_0"):
            return True
    for key in params.keys():
        name = key.rsplit(".", 2)
        if len(name) >= 2 and name[-2] in _TEXTURED_FRESNEL and name[-1] != "value":
            return True
    return False


def describe_bsdf(bsdf: mi.BSDF) -> Material:
    """Lobes, roughness and Fresnel F0 (normal incidence) of a Mitsuba BSDF, looking through
    ``twosided`` and ``normalmap`` wrappers (the nested BSDF's roughness and F0), whether a
    normal map perturbs its shading normal (``Material.normal_map``) and whether the
    analytic shading represents it (``Material.analytic``; the others: :func:`_generic`). A
    negative or non-finite roughness raises :class:`glossrt.errors.SceneError` naming the
    BSDF."""
    from ..scenes import check_roughness

    check_roughness(bsdf)  # a negative alpha never reaches the roughness channel
    params = mi.traverse(bsdf)
    if not nested_classes(bsdf) <= ANALYTIC_CLASSES or _beyond_analytic(bsdf, params):
        return _generic(bsdf, params)
    flags = int(bsdf.flags())
    has_d = bool(flags & int(mi.BSDFFlags.Diffuse))
    has_s = bool(flags & (int(mi.BSDFFlags.Glossy) | int(mi.BSDFFlags.Delta)))
    glossy = bool(flags & int(mi.BSDFFlags.Glossy))
    kind = bsdf.class_name()

    alpha, alpha_attr = (0.0 if has_s else 1.0), False
    distribution, aniso = None, None
    if glossy:
        distribution = bsdf_distribution(bsdf)
        if distribution is None:
            raise GlossrtError(f"{kind}: a rough lobe whose microfacet distribution Mitsuba "
                               f"does not print; glossrt never assumes GGX")
        if distribution not in ("ggx", "beckmann"):
            raise GlossrtError(f"{kind}: microfacet distribution {distribution!r} is not "
                               f"supported (ggx or beckmann)")
        val, key = _param(params, "alpha.value", "alpha")
        if val is not None:
            alpha = float(np.array(val).ravel()[0])
        else:
            au, _ = _param(params, "alpha_u.value", "alpha_u")
            av, _ = _param(params, "alpha_v.value", "alpha_v")
            tex, tkey = _param(params, "alpha.data")
            if au is not None and av is not None:
                a_u, a_v = float(np.array(au).ravel()[0]), float(np.array(av).ravel()[0])
                alpha = float(np.sqrt(a_u * a_v))
                if a_u != a_v:
                    aniso = (a_u, a_v)
            elif alpha_source(bsdf) is not None:
                alpha_attr = True  # per hit, from the BSDF of alpha_source (maybe nested)
            elif tex is not None:
                alpha = float(np.mean(np.array(tex)))
                warnings.warn(
                    f"{kind}: textured roughness inside a wrapper BSDF; the roughness channel "
                    f"uses its mean {alpha:.3f}",
                    stacklevel=2,
                )

    f0 = np.zeros(3)
    fresnel = Fresnel()
    if has_s:
        eta, _ = _param(params, "eta.value", "eta")
        k, _ = _param(params, "k.value")
        spec, _ = _param(params, "specular_reflectance.value")
        scale = _rgb(spec) if spec is not None else np.ones(3)
        if k is not None:  # conductor: Fresnel at normal incidence with complex IOR
            e, kk = _rgb(eta), _rgb(k)
            f0 = ((e - 1) ** 2 + kk**2) / ((e + 1) ** 2 + kk**2)
            fresnel = Fresnel(CONDUCTOR, _t3(e), _t3(kk), _t3(scale), _t3(f0 * scale))
        elif eta is not None:  # dielectric coating (plastic)
            e = _rgb(eta)
            f0 = ((e - 1) / (e + 1)) ** 2
            fresnel = Fresnel(DIELECTRIC, _t3(e), (0.0, 0.0, 0.0), _t3(scale), _t3(f0 * scale))
        else:
            f0 = np.ones(3)
            fresnel = Fresnel(SCHLICK, scale=_t3(scale), f0=_t3(f0 * scale))
        f0 = f0 * scale
    # an anisotropic lobe is rendered by the path tracer alone (the analytic methods take
    # one alpha per pixel)
    return Material(kind, has_d, has_s, alpha, alpha_attr, tuple(float(v) for v in f0),
                    _normal_map_kind(bsdf, set(params.keys())),
                    distribution, aniso, fresnel, analytic=aniso is None)


#: ``LobeOverride.kind``: no per-pixel roughness override (the material's own lobes stay)
LOBE_NONE = 0
#: Mitsuba's ``roughconductor``: the whole BSDF is the microfacet lobe
LOBE_CONDUCTOR = 1
#: Mitsuba's ``roughplastic``: its specular (dielectric-Fresnel microfacet) lobe is overridden,
#: its diffuse lobe stays Mitsuba's (see :class:`LobeOverride`)
LOBE_PLASTIC = 2

_SAMPLE_VISIBLE = re.compile(r"sample_visible\s*=\s*(\d)")
_SPEC_WEIGHT = re.compile(r"specular_sampling_weight\s*=\s*\[?\s*([0-9.eE+-]+)")


@dataclass(frozen=True)
class LobeOverride:
    """What the path tracer needs to evaluate, sample and give the pdf of a BSDF's rough lobe
    with a per-pixel roughness instead of the material's (:func:`lobe_override`; the
    Dr.Jit side is :class:`glossrt.render.pathtracer.PrimaryLobe`).

    ``kind``: :data:`LOBE_CONDUCTOR` (``roughconductor``) or :data:`LOBE_PLASTIC`
    (``roughplastic``). ``twosided``: inside a ``twosided`` with one BSDF for both sides
    (Mitsuba mirrors ``wi`` and ``wo`` to the front); ``normal_map``: inside a ``normalmap``
    (perturbed frame, ``flip_invalid_normals`` and ``use_shadowing_function`` at Mitsuba's
    defaults, true, which the plugin does not print). ``spec_weight``: ``roughplastic``'s
    ``specular_sampling_weight``. The Fresnel term (exact conductor or dielectric, times
    ``specular_reflectance``) and the distribution come from :func:`describe_bsdf`.

    ``roughplastic``'s diffuse lobe is NOT re-derived for another roughness: Mitsuba scales it
    by ``t(cos_i) t(cos_o)``, the transmittance of the rough interface tabulated once for the
    material's alpha (``m_external_transmittance``), and by ``1 / (1 - R_int)`` of that
    alpha. Those tables are not reachable from Python, so the diffuse lobe stays Mitsuba's
    own (its eval at the material's alpha): exact for the specular lobe, an approximation
    for the coating's energy exchange (the diffuse lobe does not lose or gain what the
    wider or narrower specular lobe gains or loses)."""

    kind: int
    twosided: bool
    normal_map: bool
    spec_weight: float = 1.0


def lobe_override(bsdf: mi.BSDF) -> LobeOverride | None:
    """The :class:`LobeOverride` of ``bsdf``, or None where a per-pixel roughness cannot
    replace the material's exactly and the material's lobes stay: a BSDF that is not a rough
    conductor or rough plastic (smooth and diffuse BSDFs, among others), an anisotropic lobe,
    ``sample_visible = false`` (not reimplemented), a textured Fresnel parameter (``eta``,
    ``k``, ``specular_reflectance``), a ``twosided`` with two different sides, a
    ``normalmap`` around a ``twosided``, or any other wrapper."""
    kind = bsdf.class_name()
    keys = set(mi.traverse(bsdf).keys())
    if kind == "TwoSidedBRDF" and any(k.startswith("brdf_1.") for k in keys):
        return None
    text = str(bsdf)
    inner = [c for c in ("RoughConductor[", "RoughPlastic[") if c in text]
    if len(inner) != 1:
        return None
    if kind == "TwoSidedBRDF":
        nmap = any(k.startswith("brdf_0.normalmap.") for k in keys)
        twosided, prefix = True, "brdf_0.nested_bsdf." if nmap else "brdf_0."
    elif kind == "NormalMap":
        twosided, nmap, prefix = False, True, "nested_bsdf."
    elif kind == inner[0][:-1]:
        twosided, nmap, prefix = False, False, ""
    else:
        return None
    own = {k[len(prefix):] for k in keys if k.startswith(prefix)}
    if any(k.startswith(("brdf_0.", "brdf_1.", "nested_bsdf.")) for k in own):
        return None  # a deeper wrapper (normalmap around twosided, ...)
    if "alpha_u.value" in own or "alpha_v.value" in own:
        return None  # anisotropic
    m = _SAMPLE_VISIBLE.search(text)
    if m is None or m.group(1) != "1":
        return None
    if any(k.startswith("specular_reflectance.") and k != "specular_reflectance.value"
           for k in own):
        return None
    if inner[0] == "RoughConductor[":
        if not {"eta.value", "k.value"} <= own:
            return None
        return LobeOverride(LOBE_CONDUCTOR, twosided, nmap)
    if "eta" not in own:
        return None
    w = _SPEC_WEIGHT.search(text)
    return LobeOverride(LOBE_PLASTIC, twosided, nmap, float(w.group(1)) if w else 0.5)
