"""What deferred polygon-light shading reads from a Frame, and the BRDF it shades with.

The BRDF of glossrt's polygon-light shading (LTC and its Monte Carlo reference use the same
one, so their difference is the LTC approximation alone), Mitsuba's rough BSDFs as the
renderer renders them, per pixel with the distribution of the ``distribution`` channel (GGX
where a frame has no such channel):

* diffuse: Lambert, ``albedo_diffuse / pi``;
* specular: GGX (Walter et al. 2007, eq. 33) or Beckmann (eq. 25) with Mitsuba's *separable*
  Smith shadowing-masking ``G1(wo) G1(wi)`` (eq. 23; :mod:`glossrt.brdf.microfacet`) and
  Schlick's Fresnel with the material's ``F0`` (Schlick 1994):
  ``f = F(wo.h) D(h) G1(wo) G1(wi) / (4 cos_o cos_i)``.

The Fresnel term is Mitsuba's exact conductor or dielectric one when the shading functions are
given :func:`fresnel_image` (the CLI's choice: per sample in the Monte Carlo reference, at the
lobe's effective angle in LTC's split sum, :mod:`glossrt.brdf.fresnel`), Schlick's with the
material's F0 when given an (H, W, 3) F0 image. A material without a specular lobe
(Mitsuba's ``diffuse``) has no specular term in :func:`fresnel_image`'s rows (Fresnel kind
NONE: ``F = 0``); an F0 image cannot say so, and Schlick's form with its F0 = 0 keeps a faint
grazing ``(1 - wo.h)^5`` lobe there. What it still approximates: LTC's fit of the
lobe and the effective angle of its Fresnel weight, and ``roughplastic``'s diffuse lobe, taken
as Lambert with the ``albedo_diffuse`` the renderer writes.

``F0`` is not in a Frame: :func:`f0_image` looks it up per pixel from the scene's materials
through ``mesh_id``.
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import numpy as np

from ..backend import mi
from ..brdf import microfacet as mf
from ..brdf.fresnel import NONE, ROW, Fresnel, fresnel_exact, split_sum
from ..brdf.ggx import ALPHA_MIN, fresnel_schlick
from ..errors import FrameError, GlossrtError
from ..images import check_frame, split, view_directions
from ..jit import owned_float

NEEDS = ("position", "normal", "roughness", "albedo_diffuse", "mesh_id")


def light_vertices(light) -> np.ndarray:
    """A polygon light's world-space vertices (K, 3) float64, checked: 3 to 8 of them,
    all finite (a clear GlossrtError otherwise)."""
    v = np.asarray(light.vertices, np.float64)
    if v.ndim != 2 or v.shape[1] != 3 or not 3 <= len(v) <= 8:
        raise GlossrtError(f"polygon light needs 3 to 8 vertices (K, 3), got {v.shape}")
    if not np.all(np.isfinite(v)):
        raise GlossrtError("polygon light vertices contain NaN or Inf")
    return v


def check_isotropic(setup) -> None:
    """A clear :class:`GlossrtError` naming the first shape whose rough lobe is anisotropic
    (``alpha_u != alpha_v``), for the methods that take one ``alpha`` per pixel (LTC, BSPVT,
    the ratio estimator, highlights): an anisotropic LTC would need a table over two more
    dimensions. The Monte Carlo reference and specular antialiasing shade such lobes, the
    path tracer renders them (Mitsuba's own BSDF)."""
    from ..render.materials import describe_bsdf
    from ..scenes import stable_shapes

    for i, s in enumerate(stable_shapes(setup.scene)):
        m = describe_bsdf(s.bsdf())
        if m.anisotropic is not None:
            name = s.id() or f"shape {i + 1}"
            au, av = m.anisotropic
            raise GlossrtError(
                f"{setup.name}: shape {name!r} ({m.kind}, {m.distribution}, alpha_u {au:g} != "
                f"alpha_v {av:g}) is anisotropic; this method handles isotropic lobes only "
                "(set alpha_u = alpha_v, or shade it with --method mc, or render it with "
                "'glossrt render --mitsuba')")


#: columns of :func:`fresnel_image`: the Fresnel row (kind, eta, k, scale, F0), then the
#: diffuse scale (RGB)
MATERIAL_ROW = ROW + 3
#: where F0 sits in a :func:`fresnel_image` row
F0_COLUMNS = slice(ROW - 3, ROW)


#: diffuse_scale per BSDF description (its parameters: the scale does not depend on a
#: texture's values), so that a frame's fresnel_image does not integrate it again
_SCALES: dict[str, np.ndarray] = {}


def _diffuse_scale_cached(bsdf) -> np.ndarray:
    from ..render.materials import diffuse_scale

    key = f"{mi.variant()} {bsdf}"
    if key not in _SCALES:
        if len(_SCALES) > 256:
            _SCALES.clear()
        _SCALES[key] = diffuse_scale(bsdf)
    return _SCALES[key]


def _material_rows(setup, frame,
                   with_scale: bool = True) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """Per mesh id (0 = background): the Fresnel rows ``(n, ROW)`` and (``with_scale``) the
    diffuse-scale tables ``(n, DIFFUSE_SCALE_NODES, 3)`` of ``setup``'s materials
    (:func:`mesh_material_tables`), and the frame's mesh ids (H, W), checked against them."""
    from ..render.materials import DIFFUSE_SCALE_NODES
    from ..scenes import render_shapes

    shape_rows, shape_scales = mesh_material_tables(render_shapes(setup.scene), with_scale)
    rows = np.concatenate([np.zeros((1, ROW)), shape_rows])
    scales = (None if shape_scales is None else
              np.concatenate([np.ones((1, DIFFUSE_SCALE_NODES, 3)), shape_scales]))
    ids = frame.numpy("mesh_id")[..., 0].astype(np.int64)
    if ids.min() < 0 or ids.max() >= len(rows):
        raise FrameError(f"{frame.where}: mesh_id out of range for scene {setup.name!r} "
                         f"({ids.max()} >= {len(rows)})")
    return rows, scales, ids


def fresnel_image(setup, frame) -> np.ndarray:
    """Every pixel's material as Mitsuba renders it, (H, W, 16) float32: the Fresnel term,
    :meth:`glossrt.brdf.fresnel.Fresnel.row` (kind, eta, k, specular_reflectance, F0), then
    the diffuse scale at the pixel's view (:func:`glossrt.render.materials.diffuse_scale`:
    Mitsuba's diffuse lobe integrated over the light directions over its reflectance; 1 for
    Lambert, 0.47-0.96 for plastic coatings of eta 1.5), from the materials of ``setup``'s
    shapes through the frame's ``mesh_id`` (0 = background). Pass it as ``f0`` to the
    shading functions to shade with Mitsuba's exact Fresnel terms and coated diffuse lobes
    (the CLI does)."""
    rows, scales, ids = _material_rows(setup, frame)
    if frame.camera is not None and "position" in frame.names and "normal" in frame.names:
        return material_rows_at(rows, scales, ids, frame.numpy("position"),
                                frame.numpy("normal"), frame.camera.position)
    return material_rows_at(rows, scales, ids)


def material_rows_at(rows: np.ndarray, scales: np.ndarray, ids: np.ndarray, positions=None,
                     normals=None, camera=None) -> np.ndarray:
    """The :func:`fresnel_image` rows (..., 16) float32 of points with material ``ids``
    (indices into ``rows`` (n, ROW) and ``scales`` (n, DIFFUSE_SCALE_NODES, 3)), the
    diffuse scale taken at each point's view cosine towards ``camera`` (normal incidence
    without positions)."""
    from ..render.materials import DIFFUSE_SCALE_NODES

    out = np.empty(ids.shape + (MATERIAL_ROW,), np.float32)
    out[..., :ROW] = rows.astype(np.float32)[ids]
    if positions is not None:
        v = np.asarray(camera, np.float32) - np.asarray(positions, np.float32)
        d = np.einsum("...i,...i->...", v, np.asarray(normals, np.float32))
        cos_o = np.clip(d / np.maximum(np.sqrt(np.einsum("...i,...i->...", v, v)), 1e-12),
                        0.0, 1.0)
    else:
        cos_o = np.ones(ids.shape, np.float32)
    # the table's nodes are uniform in sqrt(cos_o): linear interpolation there
    x = np.sqrt(cos_o) * np.float32(DIFFUSE_SCALE_NODES - 1)
    i0 = np.minimum(x.astype(np.int64), DIFFUSE_SCALE_NODES - 2)
    t = (x - i0)[..., None]
    sc = scales.astype(np.float32)
    out[..., ROW:] = (1 - t) * sc[ids, i0] + t * sc[ids, i0 + 1]
    return out


def mesh_material_tables(meshes, with_scale: bool = True
                         ) -> tuple[np.ndarray, np.ndarray | None]:
    """Fresnel rows (n, ROW) and (``with_scale``) diffuse-scale tables
    (n, DIFFUSE_SCALE_NODES, 3) of a list of shapes' BSDFs (:func:`material_rows_at`'s
    ``rows`` and ``scales``)."""
    from ..render.materials import DIFFUSE_SCALE_NODES, describe_bsdf

    # a BSDF without a specular lobe (Mitsuba's ``diffuse``) gets the Fresnel term NONE
    # (F = 0): Schlick's form with F0 = 0 would give it a grazing (1 - wo.h)^5 lobe that
    # Mitsuba does not render
    # a BSDF outside the analytic classes (glass, principled, ...: its pixels are the path
    # tracer's) gets the Fresnel term NONE and a diffuse scale of 1 (never read)
    mats = [describe_bsdf(m.bsdf()) for m in meshes]
    rows = np.array([(mt.fresnel if mt.has_specular and not mt.sampled_albedo
                      else Fresnel(NONE)).row() for mt in mats],
                    np.float64).reshape(len(meshes), ROW)
    if not with_scale:
        return rows, None
    scales = np.array([np.ones((DIFFUSE_SCALE_NODES, 3)) if mt.sampled_albedo
                       else _diffuse_scale_cached(m.bsdf())
                       for m, mt in zip(meshes, mats, strict=True)],
                      np.float64).reshape(len(meshes), DIFFUSE_SCALE_NODES, 3)
    return rows, scales


def points_with_materials(p, n, wo, alpha, albedo, hit, beckmann, mat: np.ndarray
                          ) -> ShadingPoints:
    """ShadingPoints of device fields and a (N, 16) :func:`material_rows_at` array: exact
    Fresnel lanes, F0 and the diffuse reflectance ``albedo`` scaled as Mitsuba's coated
    diffuse lobes."""
    f = [mi.Float(owned_float(np.ascontiguousarray(mat[:, c]))) for c in range(MATERIAL_ROW)]
    fres, f0, scale = FresnelLanes.of_columns(f)
    return ShadingPoints(p, n, wo, alpha, albedo * scale, f0, hit, beckmann, fres)


def f0_image(setup, frame) -> np.ndarray:
    """Specular F0 (H, W, 3) per pixel (:func:`fresnel_image`'s F0 columns), for shading
    with Schlick's Fresnel and Lambert's diffuse reflectance as the G-buffer's
    ``albedo_diffuse``."""
    rows, _, ids = _material_rows(setup, frame, with_scale=False)
    return np.ascontiguousarray(rows[ids][..., F0_COLUMNS]).astype(np.float32)


@dataclass
class FresnelLanes:
    """Per-lane Fresnel terms (:class:`glossrt.brdf.fresnel.Fresnel`): kind, eta, k, scale."""

    kind: mi.UInt32
    eta: mi.Color3f
    k: mi.Color3f
    scale: mi.Color3f

    def take(self, index: mi.UInt32) -> FresnelLanes:
        return FresnelLanes(*(dr.gather(type(v), v, index) for v in (
            self.kind, self.eta, self.k, self.scale)))

    @staticmethod
    def of_columns(f: list) -> tuple[FresnelLanes, mi.Color3f, mi.Color3f]:
        """The lanes' Fresnel terms, F0 and diffuse scale from the 16 per-lane columns of
        :func:`fresnel_image` rows."""
        return (FresnelLanes(mi.UInt32(f[0]), mi.Color3f(*f[1:4]), mi.Color3f(*f[4:7]),
                             mi.Color3f(*f[7:10])),
                mi.Color3f(*f[F0_COLUMNS]), mi.Color3f(*f[ROW:]))


@dataclass
class ShadingPoints:
    """One lane per pixel: world position, normal, view direction (towards the camera),
    microfacet alpha, diffuse albedo, F0, whether the pixel sees a surface, whether its
    distribution is Beckmann (a per-lane ``mi.Bool``, or a Python bool for all lanes) and
    its exact Fresnel term (``None``: Schlick's with ``f0``)."""

    p: mi.Point3f
    n: mi.Vector3f
    wo: mi.Vector3f
    alpha: mi.Float
    albedo: mi.Color3f
    f0: mi.Color3f
    hit: mi.Bool
    beckmann: mi.Bool | bool = False
    fresnel: FresnelLanes | None = None
    #: anisotropic lobes: the unit tangent along which ``alpha_u`` applies, and
    #: ``(alpha_u, alpha_v)`` (``None``: every lane isotropic with ``alpha``)
    tangent: mi.Vector3f | None = None
    alpha_uv: mi.Vector2f | None = None

    @staticmethod
    def of(frame, f0: np.ndarray | None = None) -> ShadingPoints:
        """From a Frame's G-buffer (and its camera); ``f0`` (H, W, 3) F0 for Schlick's
        Fresnel, or (H, W, 16) from :func:`fresnel_image` for the exact terms and Mitsuba's
        coated diffuse lobes; default 0."""
        check_frame(frame, NEEDS)
        p = mi.Point3f(*split(frame["position"]))
        wo = view_directions(frame, p, "polygon-light shading")
        return ShadingPoints.of_channels(shading_channels(frame), wo, f0_tensor(frame, f0))

    def take(self, index: mi.UInt32) -> ShadingPoints:
        """The lanes ``index`` (a gather of every field): subsets and repeated pixels."""
        return _take(self, index)

    @staticmethod
    def of_channels(ch: dict, wo: mi.Vector3f, f0: mi.TensorXf) -> ShadingPoints:
        """From G-buffer tensors ``ch`` (the :data:`NEEDS` channels and, when present,
        ``distribution``), view directions and an (H, W, 3) F0 or (H, W, 16) material tensor
        (:func:`f0_tensor`): only Dr.Jit operations (usable inside ``dr.freeze``)."""
        p = mi.Point3f(*split(ch["position"]))
        n = mi.Vector3f(*split(ch["normal"]))
        hit = split(ch["mesh_id"])[0] > 0
        alpha = dr.maximum(split(ch["roughness"])[0], ALPHA_MIN)
        beckmann = (split(ch["distribution"])[0] == float(mf.BECKMANN)
                    if "distribution" in ch else False)
        f = split(f0)
        fresnel = None
        tangent = alpha_uv = None
        if "tangent" in ch and "roughness_uv" in ch:
            tangent = mi.Vector3f(*split(ch["tangent"]))
            auv = split(ch["roughness_uv"])
            alpha_uv = mi.Vector2f(dr.maximum(auv[0], ALPHA_MIN), dr.maximum(auv[1], ALPHA_MIN))
        albedo = mi.Color3f(*split(ch["albedo_diffuse"]))
        f0_rgb = mi.Color3f(*f) if len(f) == 3 else None
        if len(f) == MATERIAL_ROW:
            fresnel, f0_rgb, scale = FresnelLanes.of_columns(f)
            albedo = albedo * scale  # Mitsuba's coated diffuse lobe
        return ShadingPoints(p, n, wo, alpha, albedo, f0_rgb, hit & (dr.dot(n, wo) > 0),
                             beckmann, fresnel, tangent, alpha_uv)

    def local_frame(self) -> mi.Frame3f:
        """The lanes' shading frame: ``(tangent, n x tangent, n)`` for anisotropic lobes
        (the axes of ``alpha_u``, ``alpha_v``), else Mitsuba's frame about ``n``."""
        if self.tangent is None:
            return mi.Frame3f(self.n)
        t = self.tangent - self.n * dr.dot(self.n, self.tangent)
        ok = dr.squared_norm(t) > 1e-12
        fallback = mi.Frame3f(self.n)
        t = dr.select(ok, dr.normalize(t), fallback.s)
        return mi.Frame3f(t, dr.cross(self.n, t), self.n)

    def spec_weight(self, norm: mi.Float, fres: mi.Float) -> mi.Color3f:
        """``integral f F cos`` per unit LTC mass from a split-sum table's ``norm`` and
        ``fres``: Schlick's split ``F0 (norm - fres) + fres``, or Mitsuba's exact term at the
        lobe's effective angle (:func:`glossrt.brdf.fresnel.split_sum`)."""
        if self.fresnel is None:
            return self.f0 * (norm - fres) + fres
        fr = self.fresnel
        return split_sum(norm, fres, fr.kind, fr.eta, fr.k, fr.scale, self.f0)

    def fresnel_at(self, cos: mi.Float) -> mi.Color3f:
        """The Fresnel term at ``cos = wo.h``: Schlick's with ``f0`` or the exact one."""
        if self.fresnel is None:
            return fresnel_schlick(cos, self.f0)
        fr = self.fresnel
        return fresnel_exact(cos, fr.kind, fr.eta, fr.k, fr.scale, self.f0)


    @staticmethod
    def at_camera(ch: dict, cam: list) -> ShadingPoints:
        """:meth:`of_channels` with the view directions towards the camera position ``cam``
        (three opaque scalars) and F0 from ``ch["f0"]``: the prelude of every frozen shading
        kernel."""
        p = mi.Point3f(*split(ch["position"]))
        wo = dr.normalize(mi.Vector3f(cam[0] - p.x, cam[1] - p.y, cam[2] - p.z))
        return ShadingPoints.of_channels(ch, wo, ch["f0"])


def _take(sp: ShadingPoints, index: mi.UInt32) -> ShadingPoints:
    beck = sp.beckmann
    if not isinstance(beck, bool):
        beck = dr.gather(mi.Bool, beck, index)
    fres = None if sp.fresnel is None else sp.fresnel.take(index)
    aniso = [None if v is None else dr.gather(type(v), v, index)
             for v in (sp.tangent, sp.alpha_uv)]
    return ShadingPoints(*(dr.gather(type(v), v, index) for v in (
        sp.p, sp.n, sp.wo, sp.alpha, sp.albedo, sp.f0, sp.hit)), beck, fres, *aniso)


def shading_channels(frame) -> dict:
    """The frame's :data:`NEEDS` channels, ``distribution`` when it has one (frames written
    before that channel existed shade as GGX), and ``tangent`` and ``roughness_uv`` when its
    scene has anisotropic lobes (``meta["anisotropic"]``)."""
    names = NEEDS + (("distribution",) if "distribution" in frame.names else ())
    if frame.meta.get("anisotropic") and {"tangent", "roughness_uv"} <= set(frame.names):
        names += ("tangent", "roughness_uv")
    return {k: frame[k] for k in names}


def refuse_anisotropic(frame, who: str) -> None:
    """A clear :class:`GlossrtError` for a frame whose scene has anisotropic lobes, from a
    method that shades isotropic lobes only (LTC's 2-D table and what builds on it: BSPVT,
    the ratio estimator; the highlights); :func:`check_isotropic` names the shapes. (The
    Monte Carlo reference and specular antialiasing shade anisotropic lobes.)"""
    if frame.meta.get("anisotropic"):
        raise GlossrtError(
            f"{frame.where}: its scene has anisotropic lobes (alpha_u != alpha_v); {who} "
            "handles isotropic lobes only (the Monte Carlo reference, --method mc, shades "
            "them; check_isotropic names the shapes)")


def f0_tensor(frame, f0: np.ndarray | None) -> mi.TensorXf:
    """``f0`` (H, W, 3) F0 or (H, W, 16) :func:`fresnel_image` as a tensor of the frame's
    size (zeros for ``None``); a clear error when its size does not match."""
    h, w = frame.height, frame.width
    if f0 is None:
        return dr.zeros(mi.TensorXf, (h, w, 3))
    if isinstance(f0, mi.TensorXf):  # already on the device (the pipeline's direct stage)
        if tuple(f0.shape) not in ((h, w, 3), (h, w, MATERIAL_ROW)):
            raise FrameError(f"{frame.where}: F0 tensor has shape {tuple(f0.shape)}, expected "
                             f"({h}, {w}, 3) or ({h}, {w}, {MATERIAL_ROW})")
        return f0
    f0 = np.asarray(f0, np.float32)
    c = f0.shape[-1] if f0.ndim == 3 else 3
    if f0.size != h * w * c or c not in (3, MATERIAL_ROW):
        raise FrameError(f"{frame.where}: F0 image has shape {f0.shape}, expected ({h}, {w}, 3) "
                         f"or ({h}, {w}, {MATERIAL_ROW}) (fresnel_image)")
    # in Dr.Jit's own memory: an input of the frozen LTC shading (see jit.owned_float)
    return mi.TensorXf(owned_float(f0), (h, w, c))


def brdf_cos(sp: ShadingPoints, wi: mi.Vector3f) -> tuple[mi.Color3f, mi.Color3f]:
    """Diffuse and specular ``f(wo, wi) cos(theta_i)`` (module docstring), world-space
    ``wi``; 0 below the horizon of either direction."""
    cos_i = dr.dot(sp.n, wi)
    cos_o = dr.dot(sp.n, sp.wo)
    ok = sp.hit & (cos_i > 0) & (cos_o > 0)
    h = dr.normalize(sp.wo + wi)
    f = sp.fresnel_at(dr.dot(sp.wo, h))
    if sp.alpha_uv is not None:
        # anisotropic lobes in the frame of their tangent (Mitsuba's alpha_u, alpha_v axes)
        fr = sp.local_frame()
        spec = f * mf.aniso_specular_cos(fr.to_local(sp.wo), fr.to_local(wi), sp.alpha_uv.x,
                                         sp.alpha_uv.y, sp.beckmann)
    else:
        # Walter et al. 2007, eqs. 20 and 23 times cos_i: D G1(wo) G1(wi) / (4 cos_o)
        spec = f * mf.specular_cos(cos_o, cos_i, dr.dot(sp.n, h), sp.alpha, sp.beckmann,
                                   dr.squared_norm(dr.cross(sp.n, h)))
    diff = sp.albedo * (cos_i / dr.pi)
    return dr.select(ok, diff, 0.0), dr.select(ok, spec, 0.0)
