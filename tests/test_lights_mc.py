"""glossrt.lights.mc / shading: the Monte Carlo reference for polygon lights against
independent float64 NumPy computations (Lambert's edge formula for diffuse light, a dense
midpoint quadrature over the light's area for GGX specular light), one-sided / two-sided
emission, shadows, and errors."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pytest

from glossrt import backend

backend.ensure()
import mitsuba as mi  # noqa: E402

from glossrt.errors import GlossrtError  # noqa: E402
from glossrt.frame import RADIANCE, Camera, Frame  # noqa: E402
from glossrt.lights.mc import render_mc  # noqa: E402

CAM = np.array([0.3, -0.2, 2.0])


@dataclass
class Light:
    vertices: np.ndarray
    radiance: tuple
    two_sided: bool = False
    texture: object = None
    uv: object = None


def plane_frame(w=8, h=6, alpha=0.3, albedo=0.5):
    xs, ys = np.linspace(-0.5, 0.5, w), np.linspace(-0.3, 0.3, h)
    px, py = np.meshgrid(xs, ys)
    ch = {c: np.zeros((h, w, 3)) for c in RADIANCE}
    ch["position"] = np.stack([px, py, np.zeros_like(px)], -1)
    ch["normal"] = np.broadcast_to([0, 0, 1.0], (h, w, 3))
    ch["albedo_diffuse"] = np.full((h, w, 3), albedo)
    ch["albedo_specular"] = np.zeros((h, w, 3))
    ch["roughness"] = np.full((h, w, 1), alpha)
    ch["mesh_id"] = np.ones((h, w, 1))
    ch["depth"] = np.ones((h, w, 1))
    m = np.eye(4)
    m[:3, 3] = CAM
    return Frame(channels={k: np.asarray(v, np.float32) for k, v in ch.items()},
                 camera=Camera(m, 45.0, (w, h)))


# a quad at height 1 facing down (-z, towards the plane): counter-clockwise seen from below
QUAD_DOWN = np.array([[-0.3, 0.3, 1.0], [0.3, 0.3, 1.0], [0.3, -0.3, 1.0], [-0.3, -0.3, 1.0]])


def lambert(verts) -> float:
    """(1/pi) * integral of cos over the polygon (Lambert 1760 / Arvo 1995 edge sum)."""
    v = verts / np.linalg.norm(verts, axis=1, keepdims=True)
    s = 0.0
    for i in range(len(v)):
        a, b = v[i], v[(i + 1) % len(v)]
        c = np.cross(a, b)
        s += math.acos(np.clip(a @ b, -1, 1)) * c[2] / np.linalg.norm(c)
    return abs(s) / (2 * math.pi)


def ggx_spec_quadrature(x, n, wo, alpha, f0, verts, m=400) -> float:
    """integral over the light's area of f_s(wo, wi) cos_i |cos_l| / d^2 (midpoint rule on an
    m x m grid of the quad), GGX + height-correlated Smith + Schlick, float64."""
    a, b, d = verts[0], verts[1], verts[3]
    s = (np.arange(m) + 0.5) / m
    su, sv = np.meshgrid(s, s)
    y = a + su[..., None] * (b - a) + sv[..., None] * (d - a)
    area = np.linalg.norm(np.cross(b - a, d - a))
    r = y - x
    dist2 = np.sum(r * r, -1)
    wi = r / np.sqrt(dist2)[..., None]
    nl = np.cross(b - a, d - a) / area
    cos_l = np.abs(wi @ nl)
    cos_i = wi @ n
    cos_o = wo @ n
    h = wi + wo
    h /= np.linalg.norm(h, axis=-1, keepdims=True)
    ch = h @ n
    a2 = alpha * alpha
    dd = a2 / (math.pi * ((1 - ch**2) + ch**2 * a2) ** 2)

    def lam(c):
        return 0.5 * (np.sqrt(1 + a2 * (1 - c * c) / (c * c)) - 1)

    g2 = 1 / (1 + lam(cos_o) + lam(cos_i))
    fr = f0 + (1 - f0) * (1 - np.clip(wo @ h if h.ndim == 1 else h @ wo, 0, 1)) ** 5
    f = fr * dd * g2 / (4 * cos_o * np.maximum(cos_i, 1e-12))  # Walter 2007, eq. 20
    return float(np.sum(np.where(cos_i > 0, f * cos_i * cos_l / dist2, 0.0)) * area / m**2)


def test_diffuse_matches_lamberts_formula():
    f = plane_frame()
    img = render_mc(f, [Light(QUAD_DOWN, (2.0, 2.0, 2.0))], spp=4096)
    pos = f.numpy("position")
    want = np.array([[0.5 * 2.0 * lambert(QUAD_DOWN - pos[y, x]) for x in range(8)]
                     for y in range(6)])
    rel = np.abs(img[..., 0] / want - 1)
    print(f"\ndiffuse MC (4096 spp) vs Lambert: max rel. error {rel.max():.4f}")
    assert rel.max() < 0.03


@pytest.mark.parametrize("alpha", [0.1, 0.3, 0.7])
def test_specular_matches_quadrature(alpha):
    f = plane_frame(w=4, h=3, alpha=alpha, albedo=0.0)
    f0 = np.full((3, 4, 3), 0.9, np.float32)
    img = render_mc(f, [Light(QUAD_DOWN, (1.0, 1.0, 1.0))], spp=8192, f0=f0)
    pos = f.numpy("position")
    want = np.zeros((3, 4))
    for y in range(3):
        for x in range(4):
            p = pos[y, x].astype(np.float64)
            wo = (CAM - p) / np.linalg.norm(CAM - p)
            want[y, x] = ggx_spec_quadrature(p, np.array([0, 0, 1.0]), wo, alpha, 0.9,
                                             QUAD_DOWN)
    rel = np.abs(img[..., 0] / want - 1)
    print(f"\nspecular MC (8192 spp) vs quadrature, alpha {alpha}: max rel. error "
          f"{rel.max():.4f} (values {want.min():.3g}..{want.max():.3g})")
    assert rel.max() < 0.03


def test_one_sided_and_two_sided():
    f = plane_frame(w=4, h=3)
    up = QUAD_DOWN[::-1].copy()  # faces away from the plane
    assert render_mc(f, [Light(up, (1.0, 1.0, 1.0))], spp=64).max() == 0.0
    a = render_mc(f, [Light(up, (1.0, 1.0, 1.0), two_sided=True)], spp=2048)
    b = render_mc(f, [Light(QUAD_DOWN, (1.0, 1.0, 1.0))], spp=2048)
    np.testing.assert_allclose(a, b, rtol=0.05)


def test_shadows_block_light():
    """A large opaque rectangle between the plane and the light: black with shadows."""
    scene = mi.load_dict({"type": "scene", "blocker": {
        "type": "rectangle", "to_world": mi.ScalarTransform4f().translate([0, 0, 0.5]).scale(3)}})
    f = plane_frame(w=4, h=3)
    lt = [Light(QUAD_DOWN, (1.0, 1.0, 1.0))]
    assert render_mc(f, lt, spp=64, scene=scene).max() == 0.0
    assert render_mc(f, lt, spp=64).min() > 0.0
    empty = mi.load_dict({"type": "scene", "far": {
        "type": "rectangle", "to_world": mi.ScalarTransform4f().translate([0, 0, 5.0])}})
    np.testing.assert_array_equal(render_mc(f, lt, spp=64, scene=empty),
                                  render_mc(f, lt, spp=64))


def test_bad_lights_are_clear_errors():
    f = plane_frame(w=4, h=3)
    with pytest.raises(GlossrtError, match="zero area"):
        render_mc(f, [Light(np.array([[0, 0, 1.0], [1, 0, 1], [2, 0, 1]]), (1, 1, 1))], 4)
    with pytest.raises(GlossrtError, match="3 to 8"):
        render_mc(f, [Light(np.zeros((2, 3)), (1, 1, 1))], 4)
    with pytest.raises(GlossrtError, match="NaN"):
        render_mc(f, [Light(np.full((4, 3), np.nan), (1, 1, 1))], 4)
    with pytest.raises(GlossrtError, match="spp"):
        render_mc(f, [Light(QUAD_DOWN, (1, 1, 1))], 0)


# -- a surface without a specular lobe (Mitsuba's diffuse) gets no specular light -------------

GRAZING_SIZE = (16, 12)


def _grazing_diffuse_scene(albedo=(0.2, 0.5, 0.8), radiance=(9.0, 3.0, 1.0)):
    """A Lambert plane (Mitsuba ``diffuse``) seen at grazing angles, lit by one quad light low
    on its far side (forward scattering: the half vector near the normal, ``wo.h`` small,
    where Schlick's ``(1 - wo.h)^5`` is largest); nothing occludes. The light is red, the
    plane blue: a term that follows the light's colour shows."""
    from glossrt import scenes

    T = mi.ScalarTransform4f
    rgb = lambda v: {"type": "rgb", "value": list(v)}  # noqa: E731
    d = {"type": "scene",
         "sensor": {"type": "perspective", "fov": 40.0,
                    "to_world": T().look_at(origin=[0, 0.45, 3.0], target=[0, 0, 0.3],
                                            up=[0, 1, 0]),
                    "film": {"type": "hdrfilm", "width": GRAZING_SIZE[0],
                             "height": GRAZING_SIZE[1]}},
         "floor": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(2.0),
                   "bsdf": {"type": "diffuse", "reflectance": rgb(albedo)}},
         "light": {"type": "rectangle",
                   "to_world": T().translate([0, 0.3, -2.2]).rotate([1, 0, 0], -8)
                   .scale([1.0, 0.25, 1.0]),
                   "bsdf": {"type": "diffuse", "reflectance": rgb((0, 0, 0))},
                   "emitter": {"type": "area", "radiance": rgb(radiance)}}}
    return scenes.load(d)


def _mitsuba_direct_at_centres(setup, spp: int) -> np.ndarray:
    """Mitsuba's own ``direct`` integrator (``integrator.sample``) on primary rays through the
    pixel centres, the points the G-buffer holds: (H, W, 3), ``spp`` estimates averaged."""
    import drjit as dr

    w, h = GRAZING_SIZE
    n = w * h
    pix = dr.arange(mi.UInt32, n * spp) // spp
    pos = mi.Point2f(mi.Float(pix % w) + 0.5, mi.Float(pix // w) + 0.5)
    ray, _ = setup.sensor.sample_ray(0.0, 0.5, pos / mi.ScalarVector2f(w, h),
                                     mi.Point2f(0.5, 0.5))
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(7, n * spp)
    li, _, _ = mi.load_dict({"type": "direct"}).sample(setup.scene, sampler, ray)
    return np.stack([np.array(dr.block_sum(li[c], spp)) / spp for c in range(3)],
                    -1).reshape(h, w, 3)


@pytest.mark.slow
def test_diffuse_surface_gets_no_specular_at_grazing_light():
    """On a plain ``diffuse`` plane under a grazing quad light, the Monte Carlo reference and
    LTC with the materials' Fresnel terms (``fresnel_image``, the CLI's and the pipeline's
    choice) equal Mitsuba's own ``direct`` integrator at the pixel centres, per channel, and
    their specular part is exactly 0. Before, a material without a specular lobe shaded as
    Schlick with F0 = 0 kept its grazing ``(1 - wo.h)^5`` GGX lobe (alpha 1): here 50 / 20 /
    12% too bright per channel in the Monte Carlo reference, 7 / 2.5 / 1.4% in LTC, following
    the light's red rather than the plane's blue."""
    from glossrt import render
    from glossrt.brdf.fresnel import NONE
    from glossrt.lights.ltc import shade_frame
    from glossrt.lights.scene import polygon_lights
    from glossrt.lights.shading import fresnel_image

    setup = _grazing_diffuse_scene()
    fr = render.Renderer(setup).render(0)
    ids = fr.numpy("mesh_id")[..., 0]
    floor = ids == np.bincount(ids.astype(int).ravel()).argmax()
    assert floor.sum() > 100
    lights = polygon_lights(setup, 0)
    f0 = fresnel_image(setup, fr)
    assert np.all(f0[floor][:, 0] == NONE) and np.all(f0[floor][:, 10:13] == 0.0)
    ref = _mitsuba_direct_at_centres(setup, 1024)
    mc = render_mc(fr, lights, 256, f0=f0, seed=1)
    ltc = shade_frame(fr, lights, f0=f0)
    for name, img, tol in (("Monte Carlo", mc, 0.01), ("LTC", ltc, 0.01)):
        ratio = img[floor].mean(0) / ref[floor].mean(0)
        print(f"\n{name} / Mitsuba direct on a diffuse plane, grazing light: {ratio.round(4)}")
        np.testing.assert_allclose(ratio, 1.0, atol=tol)
    # the specular part alone (no diffuse albedo): exactly zero
    ch = dict(fr.channels)
    ch["albedo_diffuse"] = mi.TensorXf(np.zeros(fr.numpy("albedo_diffuse").shape, np.float32))
    dark = Frame(channels=ch, camera=fr.camera, index=fr.index, meta=fr.meta)
    assert render_mc(dark, lights, 16, f0=f0, seed=1).max() == 0.0
    assert shade_frame(dark, lights, f0=f0).max() == 0.0
