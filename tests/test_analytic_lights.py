"""Point and directional lights (glossrt.lights.analytic): extraction from Mitsuba scenes and
unshadowed deferred shading, checked against independent NumPy closed forms of the BRDF times
the light (Lambert; Mitsuba's roughconductor with the complex Fresnel equations) and what
Mitsuba renders (its ``direct`` integrator). glossrt's path tracer (whose next-event estimation
calls Mitsuba's emitters and BSDFs) is checked against the same closed forms."""

from __future__ import annotations

import gc

import numpy as np
import pytest

from glossrt import backend

backend.ensure()
import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

from glossrt import scenes  # noqa: E402
from glossrt.errors import GlossrtError  # noqa: E402
from glossrt.lights.analytic import (  # noqa: E402
    DirectionalLight,
    PointLight,
    analytic_lights,
    device_lights,
    incident,
    shade_unfiltered,
)
from glossrt.lights.shading import ShadingPoints, f0_image  # noqa: E402
from glossrt.render import Renderer  # noqa: E402

T = mi.ScalarTransform4f
SIZE = (48, 36)
FLOOR_RGB = [0.7, 0.5, 0.3]


def floor_scene(light: dict | None, bsdf: dict | None = None,
                extra: dict | None = None) -> dict:
    """A 6 x 6 floor in z = 0 that fills the view of an oblique camera, lit by ``light``
    (id "light") and the emitters in ``extra``."""
    d = {
        "type": "scene",
        "sensor": {
            "type": "perspective",
            "fov": 45.0,
            "to_world": T().look_at([0.0, -2.2, 1.8], [0.0, 0.2, 0.0], [0.0, 0.0, 1.0]),
            "film": {"type": "hdrfilm", "width": SIZE[0], "height": SIZE[1]},
        },
        "floor": {
            "type": "rectangle",
            "to_world": T().scale([3.0, 3.0, 1.0]),
            "bsdf": bsdf or {"type": "diffuse", "reflectance": {"type": "rgb",
                                                               "value": FLOOR_RGB}},
        },
    }
    if light is not None:
        d["light"] = light
    d.update(extra or {})
    return d


def setup_of(d: dict) -> scenes.SceneSetup:
    return scenes.from_spec("analytic-test", scenes.SceneSpec(d), size=SIZE)


def shade(setup: scenes.SceneSetup, frame) -> tuple[np.ndarray, np.ndarray]:
    """Diffuse and specular (H, W, 3) from analytic_lights + shade_unfiltered."""
    sp = ShadingPoints.of(frame, f0_image(setup, frame))
    diff, spec = shade_unfiltered(sp, device_lights(analytic_lights(setup, 0)))
    h, w = frame.height, frame.width
    return (np.array(diff).T.reshape(h, w, 3), np.array(spec).T.reshape(h, w, 3))


POINT = {"type": "point", "position": [0.4, 0.3, 1.1],
         "intensity": {"type": "rgb", "value": [3.0, 2.0, 1.5]}}
DIRECTIONAL = {"type": "directional", "direction": [-0.4, 0.5, -1.0],
               "irradiance": {"type": "rgb", "value": [1.5, 1.2, 0.8]}}


def incident_np(light: dict, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Independent NumPy closed form (float64) of a point / directional light's unit direction
    ``wi`` (towards the light) and the irradiance ``E`` on a surface facing it, at points ``x``
    (..., 3): ``I / d^2`` and the irradiance as given (Mitsuba's documented units)."""
    if light["type"] == "point":
        d = np.asarray(light["position"], float) - x
        dist2 = np.sum(d * d, -1, keepdims=True)
        return d / np.sqrt(dist2), np.asarray(light["intensity"]["value"], float) / dist2
    d = np.asarray(light["direction"], float)
    wi = np.broadcast_to(-d / np.linalg.norm(d), x.shape)
    return wi, np.broadcast_to(np.asarray(light["irradiance"]["value"], float), x.shape)


def fresnel_conductor_np(cos_i: np.ndarray, eta: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Unpolarised Fresnel reflectance of a conductor with complex index ``eta + i k`` from
    the Fresnel equations with a complex refractive index (Born & Wolf, sec. 14.2):
    ``r_s = (c - w) / (c + w)``, ``r_p = (n^2 c - w) / (n^2 c + w)``, ``w = sqrt(n^2 - s^2)``."""
    c = np.asarray(cos_i, float)[..., None]
    n2 = (np.asarray(eta, float) + 1j * np.asarray(k, float)) ** 2
    w = np.sqrt(n2 - (1.0 - c * c))
    rs = (c - w) / (c + w)
    rp = (n2 * c - w) / (n2 * c + w)
    return 0.5 * (np.abs(rs) ** 2 + np.abs(rp) ** 2)


def ggx_conductor_np(wo, wi, n, alpha, eta, k) -> np.ndarray:
    """``f cos(theta_i)`` of Mitsuba's ``roughconductor`` (GGX, its separable Smith term
    ``G1(wo) G1(wi)``, exact conductor Fresnel at ``wi.h``), typed here from the formulas:
    ``D = 1 / (pi a^2 cos^4 (1 + tan^2 / a^2)^2)``, ``G1 = 2 / (1 + sqrt(1 + a^2 tan^2))``,
    ``f cos_i = F D G / (4 cos_o)``; 0 below either horizon. Arrays (..., 3) -> (..., 3)."""
    co, ci = np.sum(wo * n, -1), np.sum(wi * n, -1)
    h = wo + wi
    h /= np.linalg.norm(h, axis=-1, keepdims=True)
    ch = np.sum(h * n, -1)
    a2 = alpha * alpha

    def tan2(c):
        return (1.0 - c * c) / (c * c)

    d = 1.0 / (np.pi * a2 * ch**4 * (1.0 + tan2(ch) / a2) ** 2)
    g = (2.0 / (1.0 + np.sqrt(1.0 + a2 * tan2(co)))) * (2.0 / (1.0 + np.sqrt(1.0 + a2 * tan2(ci))))
    f = fresnel_conductor_np(np.sum(wi * h, -1), eta, k)
    val = f * (d * g / (4.0 * co))[..., None]
    return np.where(((co > 0) & (ci > 0))[..., None], val, 0.0)


# -- (a) diffuse shading against Mitsuba ---------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize("light", [POINT, DIRECTIONAL], ids=["point", "directional"])
def test_lambertian_floor_matches_mitsuba(light):
    setup = setup_of(floor_scene(light))
    r = Renderer(setup, frozen=False)
    frame = r.render(0)
    ours_d, ours_s = shade(setup, frame)
    hit = frame.numpy("mesh_id")[..., 0] > 0
    assert hit.all()  # the floor fills the image: no silhouette edges
    # independent reference: the closed form albedo / pi * E cos at the G-buffer's pixel-centre
    # hits (float64 NumPy). A delta light's next-event estimate is exact (no occluder, BSDF
    # sampling never hits it), so glossrt's 1 spp path tracer, which calls Mitsuba's emitter
    # and BSDF, matches it to float32 precision
    x = frame.numpy("position").astype(np.float64)
    wi, e = incident_np(light, x)
    ref = np.asarray(FLOOR_RGB) / np.pi * e * np.maximum(wi[..., 2:3], 0.0)
    np.testing.assert_allclose(frame.numpy("direct_diffuse"), ref, rtol=2e-5, atol=1e-7)
    # a diffuse floor has F0 = 0, but brdf_cos's Schlick Fresnel keeps its (1 - wo.h)^5
    # term, so a faint grazing "specular" remains (Mitsuba's diffuse BSDF has none)
    assert np.abs(ours_s).max() < 1e-3 * ours_d.max()
    # glossrt's path tracer shades the pixel-centre hits the G-buffer holds: float precision
    np.testing.assert_allclose(ours_d, ref, rtol=1e-3, atol=1e-6)
    # the colour is the floor's times the light's: ours = albedo / pi * cos * E per pixel
    rgb = np.array(FLOOR_RGB) * light.get("intensity", light.get("irradiance"))["value"]
    assert ours_d.mean(axis=(0, 1)) / ours_d.mean() == pytest.approx(rgb / rgb.mean(),
                                                                     rel=1e-4)
    # Mitsuba's own `direct` integrator, box-filtered over each pixel (random positions in the
    # pixel, not its centre). The shading varies smoothly over a pixel, so the pixel average
    # differs from the centre value by a curvature term well below 1%; what remains is the
    # noise of averaging over the pixel (largest in the far rows, where a pixel spans the
    # most floor): measured up to 1.3% at 256 spp for the point light over three seeds, 0.7%
    # at 1024 spp, 2e-5 for the directional light (constant over the flat floor)
    img = mi.render(setup.scene, sensor=setup.sensor, spp=256, seed=3,
                    integrator=mi.load_dict({"type": "direct"}))
    img = np.array(img)[..., :3]
    rel = np.abs(ours_d - img) / img
    assert rel.max() < 0.025, rel.max()
    # and the magnitude is the physical one, not off by pi or by a cosine
    assert ours_d.mean() == pytest.approx(img.mean(), rel=1e-3)


def test_shading_by_hand():
    """incident(): wi and E of a point and a directional light against NumPy."""
    lights = [PointLight([0.5, -1.0, 2.0], [4.0, 2.0, 1.0]),
              DirectionalLight([1.0, 2.0, -2.0], [0.5, 0.25, 1.0])]
    pts = np.array([[0.0, 0.0, 0.0], [1.0, 2.0, -1.0], [-3.0, 0.5, 0.25]])
    p = mi.Point3f(*pts.T.astype(np.float32))
    dev = device_lights(lights)
    wi, e = incident(dev[0], p)
    d = lights[0].position - pts
    dist = np.linalg.norm(d, axis=1)
    np.testing.assert_allclose(np.array(wi).T, d / dist[:, None], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(np.array(e).T, lights[0].intensity / dist[:, None] ** 2,
                               rtol=1e-5)
    wi, e = incident(dev[1], p)
    assert np.array(wi).shape == (3, 3)
    np.testing.assert_allclose(np.array(wi).T, -np.tile([1.0, 2.0, -2.0], (3, 1)) / 3.0,
                               rtol=1e-6)
    np.testing.assert_allclose(np.array(e).T, np.tile([0.5, 0.25, 1.0], (3, 1)))


def test_moving_light_reuses_kernels():
    """New light positions and colours are opaque inputs: the second evaluation of the same
    shading with other values compiles nothing new."""
    n = 64
    rng = np.random.default_rng(1)
    sp = ShadingPoints(
        p=mi.Point3f(*rng.uniform(-1, 1, (3, n)).astype(np.float32)),
        n=mi.Vector3f(0.0, 0.0, 1.0), wo=mi.Vector3f(0.0, 0.6, 0.8),
        alpha=mi.Float(np.full(n, 0.3, np.float32)), albedo=mi.Color3f(0.5, 0.5, 0.5),
        f0=mi.Color3f(0.04, 0.04, 0.04), hit=mi.Bool(np.ones(n, bool)))

    def run(k: float):
        lights = [PointLight([0.3 * k, 0.1, 2.0 + k], [1.0 + k, 2.0, 3.0]),
                  DirectionalLight([0.1 * k, 0.2, -1.0], [0.5, 0.5 + k, 0.5])]
        out = shade_unfiltered(sp, device_lights(lights))
        dr.eval(out)
        return out

    run(0.0)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history()  # clear
        a = run(0.37)
        hist = [h for h in dr.kernel_history() if h["type"] == dr.KernelType.JIT]
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    assert hist and all(h["cache_hit"] for h in hist), hist
    b = run(0.91)
    assert not np.allclose(np.array(a[0]), np.array(b[0]))


# -- (b) point light given by position or to_world ----------------------------------------


@pytest.mark.slow
def test_point_light_position_or_to_world():
    base = {"intensity": {"type": "rgb", "value": [1.0, 2.0, 3.0]}}
    by_pos = setup_of(floor_scene({"type": "point", "position": [0.4, -0.3, 1.2], **base}))
    by_tw = setup_of(floor_scene({"type": "point", **base,
                                  "to_world": T().translate([0.4, -0.3, 1.2])}))
    # rotation and scale of a point light do nothing: its position is the translation
    by_rs = setup_of(floor_scene({"type": "point", **base, "to_world": (
        T().translate([0.4, -0.3, 1.2]) @ T().rotate([1.0, 1.0, 0.0], 40.0) @ T().scale(2.5))}))
    got = [analytic_lights(s, frame=0) for s in (by_pos, by_tw, by_rs)]
    assert by_pos.frame == 0  # frame given: the setup was posed
    for lights in got:
        assert len(lights) == 1 and isinstance(lights[0], PointLight)
        np.testing.assert_allclose(lights[0].position, [0.4, -0.3, 1.2], atol=1e-6)
        np.testing.assert_allclose(lights[0].intensity, [1.0, 2.0, 3.0])
    # and Mitsuba lights the floor alike for all three
    imgs = [Renderer(s, frozen=False).render(0).numpy("direct_diffuse")
            for s in (by_pos, by_rs)]
    np.testing.assert_allclose(imgs[0], imgs[1], rtol=1e-5, atol=1e-7)


def test_directional_direction_or_to_world():
    d = np.array([1.0, -2.0, -2.0]) / 3.0
    a = setup_of(floor_scene({"type": "directional", "direction": d.tolist(),
                              "irradiance": 2.0}))
    b = setup_of(floor_scene({"type": "directional", "irradiance": 2.0,
                              "to_world": T().look_at([0.0, 0.0, 0.0], d.tolist(),
                                                      [0.0, 1.0, 0.0])}))
    for s in (a, b):
        (light,) = analytic_lights(s)
        assert isinstance(light, DirectionalLight)
        np.testing.assert_allclose(light.direction, d, atol=1e-6)
        np.testing.assert_allclose(light.irradiance, [2.0, 2.0, 2.0])
        # Mitsuba's own sample towards the light: -direction, weight = irradiance
        (em,) = [e for e in s.scene.emitters()]
        it = dr.zeros(mi.Interaction3f)
        it.p = mi.Point3f(0.1, 0.2, 0.0)
        ds, w = em.sample_direction(it, mi.Point2f(0.5, 0.5))
        np.testing.assert_allclose(np.array(ds.d).ravel(), -d, atol=1e-6)
        np.testing.assert_allclose(np.array(w).ravel(), light.irradiance, rtol=1e-6)


# -- (c) order, other emitters, errors ----------------------------------------------------


def lights_scene(order: list[str]) -> dict:
    items = {
        "b_point": {"type": "point", "position": [1.0, 0.0, 1.0], "intensity": 2.0},
        "a_point": {"type": "point", "position": [-1.0, 0.0, 1.0],
                    "intensity": {"type": "rgb", "value": [1.0, 0.5, 0.25]}},
        "c_sun": {"type": "directional", "direction": [0.0, 0.0, -1.0], "irradiance": 0.5},
        "sky": {"type": "constant", "radiance": 0.1},
        "lamp": {"type": "rectangle", "to_world": T().translate([0.0, 0.0, 2.0]),
                 "emitter": {"type": "area", "radiance": 3.0}},
    }
    return floor_scene(None, extra={k: items[k] for k in order})


def test_stable_order_and_other_emitters_skipped():
    orders = [["a_point", "b_point", "c_sun", "sky", "lamp"],
              ["lamp", "c_sun", "sky", "b_point", "a_point"],
              ["sky", "b_point", "lamp", "a_point", "c_sun"]]
    got = []
    for order in orders:
        setup = setup_of(lights_scene(order))
        assert len(setup.scene.emitters()) == 5
        lights = analytic_lights(setup)
        got.append(lights)
        # area and constant emitters left out; the rest by id (stable_emitters' order)
        assert [light.id for light in lights] == ["a_point", "b_point", "c_sun"]
    for lights in got[1:]:
        for x, y in zip(lights, got[0], strict=True):
            assert type(x) is type(y)
            for f in ("position", "intensity") if isinstance(x, PointLight) else (
                    "direction", "irradiance"):
                np.testing.assert_array_equal(getattr(x, f), getattr(y, f))
    a, b, c = got[0]
    np.testing.assert_allclose(a.intensity, [1.0, 0.5, 0.25])
    np.testing.assert_allclose(b.intensity, [2.0, 2.0, 2.0])  # a float: grey
    np.testing.assert_allclose(c.direction, [0.0, 0.0, -1.0], atol=1e-7)
    # no analytic lights at all
    only_area = setup_of(floor_scene({"type": "constant", "radiance": 1.0}))
    assert analytic_lights(only_area) == []
    sp = ShadingPoints(p=mi.Point3f(0.0, 0.0, 0.0), n=mi.Vector3f(0.0, 0.0, 1.0),
                       wo=mi.Vector3f(0.0, 0.0, 1.0), alpha=mi.Float(0.5),
                       albedo=mi.Color3f(1.0), f0=mi.Color3f(0.0), hit=mi.Bool(True))
    d, s = shade_unfiltered(sp, device_lights([]))
    assert np.array(d).ravel().tolist() == [0.0] * 3 and np.array(s).ravel().tolist() == [0.0] * 3


@pytest.mark.parametrize("plugin,key", [("point", "intensity"), ("directional", "irradiance")])
def test_spectral_or_textured_intensity_errors(plugin, key):
    spectral = {"type": "blackbody", "temperature": 3000.0}
    regular = {"type": "regular", "wavelength_min": 400.0, "wavelength_max": 700.0,
               "values": "1, 2, 3"}
    try:
        # the emitter is named by its id ("light", the scene dict's key)
        with pytest.raises(GlossrtError, match=rf"'light'.*{key}.*not a constant.*temperature"):
            analytic_lights(setup_of(floor_scene({"type": plugin, key: spectral})))
        with pytest.raises(GlossrtError, match=rf"{key}\.values"):
            analytic_lights(setup_of(floor_scene({"type": plugin, key: regular})))
    finally:
        # a live blackbody emitter breaks every later Mitsuba render in this process: Dr.Jit
        # traces each emitter call for all registered emitters, and BlackBodySpectrum raises
        # "Not implemented for non-spectral modes"; the traceback cycles keep it alive
        gc.collect()
    # a textured intensity never reaches glossrt: Mitsuba refuses it when loading
    bitmap = {"type": "bitmap", "bitmap": mi.Bitmap(np.ones((2, 2, 3), np.float32))}
    with pytest.raises(Exception, match="non-spatially varying"):
        mi.load_dict({"type": plugin, key: bitmap})


def test_bad_light_values():
    with pytest.raises(GlossrtError, match="direction is zero"):
        DirectionalLight([0.0, 0.0, 0.0], [1.0, 1.0, 1.0])
    with pytest.raises(GlossrtError, match="intensity"):
        PointLight([0.0, 0.0, 0.0], [1.0, np.nan, 1.0])
    with pytest.raises(GlossrtError, match="not a point or directional"):
        device_lights([object()])


# -- (d) glossy floor ---------------------------------------------------------------------


@pytest.mark.parametrize("material,tol", [("none", 1e-3), ("Cu", 0.02), ("Au", 0.06)])
def test_glossy_floor_matches_mitsuba(material, tol):
    bsdf = {"type": "roughconductor", "distribution": "ggx", "alpha": 0.2,
            "material": material}
    # the light mirrored in the floor sits inside the image: a highlight around pixel centre
    light = {"type": "point", "position": [0.0, 1.2, 1.2],
             "intensity": {"type": "rgb", "value": [2.0, 2.0, 2.0]}}
    setup = setup_of(floor_scene(light, bsdf))
    r = Renderer(setup, frozen=False)
    frame = r.render(0)
    # independent reference: Mitsuba's roughconductor typed here in NumPy (float64) with its
    # documented eta, k (mi.traverse of the BSDF) times the light's E, at the pixel-centre
    # hits; glossrt's 1 spp path tracer (delta light, no occluder: exact) matches it to float32
    x = frame.numpy("position").astype(np.float64)
    wi, e = incident_np(light, x)
    wo = np.asarray(frame.camera.position, np.float64) - x
    wo /= np.linalg.norm(wo, axis=-1, keepdims=True)
    params = mi.traverse(mi.load_dict(bsdf))
    eta = np.broadcast_to(np.asarray(params["eta.value"], float).ravel(), (3,))
    kk = np.broadcast_to(np.asarray(params["k.value"], float).ravel(), (3,))
    ref = e * ggx_conductor_np(wo, wi, np.array([0.0, 0.0, 1.0]), 0.2, eta, kk)
    np.testing.assert_allclose(frame.numpy("direct_specular"), ref, rtol=1e-4,
                               atol=1e-6 * ref.max())
    ours_d, ours_s = shade(setup, frame)
    assert np.abs(ours_d).max() == 0.0 and np.abs(frame.numpy("direct_diffuse")).max() == 0.0
    lum = ref.mean(-1)
    high = lum > 0.05 * lum.max()
    assert high.sum() > 50 and not high.all()  # a highlight, not the whole floor
    rel = np.abs(ours_s[high] - ref[high]) / ref[high]
    # The models differ in two ways (view and light stay within ~62 degrees of the normal on
    # the highlight's pixels):
    # * G: height-correlated 1 / (1 + L_o + L_i) against Mitsuba's separable
    #   1 / ((1 + L_o)(1 + L_i)); with alpha = 0.2, Lambda <= 0.04, so they differ by about
    #   L_o L_i, < 0.2%;
    # * Fresnel: for material "none" (eta 0, k 1) Mitsuba's conductor Fresnel is exactly 1,
    #   and so is Schlick's with F0 = 1 (measured: 0.02%). For metals, Schlick's curve with the
    #   normal-incidence F0 of the complex IOR departs from the exact conductor Fresnel as
    #   wo.h falls, most where F0 is low (measured: copper 0.8%, gold's blue channel, F0 0.32,
    #   4.2%).
    assert rel.max() < tol, rel.max()
    # and over the whole floor, the total specular light agrees as well
    assert ours_s.sum() == pytest.approx(ref.sum(), rel=tol)
