"""What deferred polygon-light shading reads from a Frame, and the BRDF it shades with.

The BRDF of glossrt's polygon-light shading (issue 5; LTC and its Monte Carlo reference use
the same one, so their difference is the LTC approximation alone):

* diffuse: Lambert, ``albedo_diffuse / pi``;
* specular: GGX (Walter et al. 2007, eq. 33) with the *height-correlated* Smith
  shadowing-masking ``G2 = 1 / (1 + Lambda(wo) + Lambda(wi))`` (Heitz 2014, "Understanding the
  masking-shadowing function", eq. 99) and Schlick's Fresnel with the material's ``F0``
  (Schlick 1994): ``f = F(wo.h) D(h) G2 / (4 cos_o cos_i)``.

(The path tracer follows Mitsuba's separable Smith form instead; see
:mod:`glossrt.brdf.ggx`. The two differ by a few percent at grazing angles.)

``F0`` is not in a Frame: :func:`f0_image` looks it up per pixel from the scene's materials
through ``mesh_id``.
"""

from __future__ import annotations

from dataclasses import dataclass

from .. import backend

backend.ensure()

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402
import numpy as np  # noqa: E402

from ..brdf.ggx import ALPHA_MIN, D_ggx, fresnel_schlick  # noqa: E402
from ..denoise.common import check_frame, split, view_directions  # noqa: E402
from ..errors import FrameError, GlossrtError  # noqa: E402
from ..jit import owned_float  # noqa: E402

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


def f0_image(setup, frame) -> np.ndarray:
    """Specular F0 (H, W, 3) per pixel from the materials of ``setup``'s shapes, through the
    frame's ``mesh_id`` (0 = background: F0 0)."""
    from ..render.materials import describe_bsdf
    from ..scenes import stable_shapes

    table = np.zeros((len(setup.shapes) + 1, 3))
    for i, s in enumerate(stable_shapes(setup.scene)):
        table[i + 1] = describe_bsdf(s.bsdf()).f0
    ids = frame.numpy("mesh_id")[..., 0].astype(np.int64)
    if ids.min() < 0 or ids.max() >= len(table):
        raise FrameError(f"{frame.where}: mesh_id out of range for scene {setup.name!r} "
                         f"({ids.max()} >= {len(table)})")
    return table[ids].astype(np.float32)


@dataclass
class ShadingPoints:
    """One lane per pixel: world position, normal, view direction (towards the camera),
    GGX alpha, diffuse albedo, F0 and whether the pixel sees a surface."""

    p: mi.Point3f
    n: mi.Vector3f
    wo: mi.Vector3f
    alpha: mi.Float
    albedo: mi.Color3f
    f0: mi.Color3f
    hit: mi.Bool

    @staticmethod
    def of(frame, f0: np.ndarray | None = None) -> ShadingPoints:
        """From a Frame's G-buffer (and its camera); ``f0`` (H, W, 3), default 0."""
        check_frame(frame, NEEDS)
        p = mi.Point3f(*split(frame["position"]))
        wo = view_directions(frame, p, "polygon-light shading")
        return ShadingPoints.of_channels({k: frame[k] for k in NEEDS}, wo,
                                         f0_tensor(frame, f0))

    def take(self, index: mi.UInt32) -> ShadingPoints:
        """The lanes ``index`` (a gather of every field): subsets and repeated pixels."""
        return _take(self, index)

    @staticmethod
    def of_channels(ch: dict, wo: mi.Vector3f, f0: mi.TensorXf) -> ShadingPoints:
        """From G-buffer tensors ``ch`` (the :data:`NEEDS` channels), view directions and an
        (H, W, 3) F0 tensor: only Dr.Jit operations (usable inside ``dr.freeze``)."""
        p = mi.Point3f(*split(ch["position"]))
        n = mi.Vector3f(*split(ch["normal"]))
        hit = split(ch["mesh_id"])[0] > 0
        alpha = dr.maximum(split(ch["roughness"])[0], ALPHA_MIN)
        return ShadingPoints(p, n, wo, alpha, mi.Color3f(*split(ch["albedo_diffuse"])),
                             mi.Color3f(*split(f0)), hit & (dr.dot(n, wo) > 0))


    @staticmethod
    def at_camera(ch: dict, cam: list) -> ShadingPoints:
        """:meth:`of_channels` with the view directions towards the camera position ``cam``
        (three opaque scalars) and F0 from ``ch["f0"]``: the prelude of every frozen shading
        kernel."""
        p = mi.Point3f(*split(ch["position"]))
        wo = dr.normalize(mi.Vector3f(cam[0] - p.x, cam[1] - p.y, cam[2] - p.z))
        return ShadingPoints.of_channels(ch, wo, ch["f0"])


def _take(sp: ShadingPoints, index: mi.UInt32) -> ShadingPoints:
    return ShadingPoints(*(dr.gather(type(v), v, index) for v in (
        sp.p, sp.n, sp.wo, sp.alpha, sp.albedo, sp.f0, sp.hit)))


def f0_tensor(frame, f0: np.ndarray | None) -> mi.TensorXf:
    """``f0`` (H, W, 3) as a tensor of the frame's size (zeros for ``None``); a clear error
    when its size does not match."""
    h, w = frame.height, frame.width
    if f0 is None:
        return dr.zeros(mi.TensorXf, (h, w, 3))
    f0 = np.asarray(f0, np.float32)
    if f0.size != h * w * 3:
        raise FrameError(f"{frame.where}: F0 image has shape {f0.shape}, expected ({h}, {w}, 3)")
    # in Dr.Jit's own memory: an input of the frozen LTC shading (see jit.owned_float)
    return mi.TensorXf(owned_float(f0), (h, w, 3))


def smith_lambda(cos_theta, alpha):
    """GGX Smith ``Lambda(v) = (-1 + sqrt(1 + alpha^2 tan^2 theta)) / 2`` (Heitz 2014, eq. 72),
    written without the tangent (finite at grazing: ``Lambda -> inf`` as ``cos -> 0``)."""
    c2 = dr.maximum(dr.square(cos_theta), 1e-12)
    return 0.5 * (dr.sqrt(1.0 + dr.square(alpha) * (1.0 - c2) / c2) - 1.0)


def brdf_cos(sp: ShadingPoints, wi: mi.Vector3f) -> tuple[mi.Color3f, mi.Color3f]:
    """Diffuse and specular ``f(wo, wi) cos(theta_i)`` (module docstring), world-space
    ``wi``; 0 below the horizon of either direction."""
    cos_i = dr.dot(sp.n, wi)
    cos_o = dr.dot(sp.n, sp.wo)
    ok = sp.hit & (cos_i > 0) & (cos_o > 0)
    h = dr.normalize(sp.wo + wi)
    # Heitz 2014, eq. 99: height-correlated G2
    g2 = dr.rcp(1.0 + smith_lambda(cos_o, sp.alpha) + smith_lambda(cos_i, sp.alpha))
    f = fresnel_schlick(dr.dot(sp.wo, h), sp.f0)
    # Walter et al. 2007, eq. 20 times cos_i
    spec = f * (D_ggx(dr.dot(sp.n, h), sp.alpha) * g2 / (4.0 * dr.maximum(cos_o, 1e-8)))
    diff = sp.albedo * (cos_i / dr.pi)
    return dr.select(ok, diff, 0.0), dr.select(ok, spec, 0.0)
