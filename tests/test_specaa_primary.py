"""The path tracer's primary hit with a per-pixel roughness (issue 25: specaa feeds the path
tracer, so environment maps and path-traced light see the filtered roughness).

References are independent of :class:`glossrt.render.pathtracer.PrimaryLobe`: Mitsuba's own
BSDFs (the renderer without override, ``bsdf.eval`` / ``bsdf.pdf``), the same scene with the
material's alpha set to the override in the scene dict (traced with Mitsuba's BSDF), and
Mitsuba's own ``path`` integrator (``mi.render``)."""

from __future__ import annotations

import numpy as np
import pytest

from glossrt import backend

backend.ensure()
import mitsuba as mi  # noqa: E402

from glossrt import pipeline, scenes  # noqa: E402
from glossrt.errors import GlossrtError  # noqa: E402
from glossrt.render import Renderer  # noqa: E402
from glossrt.render.pathtracer import PrimaryLobe, ShapeTable  # noqa: E402

SIZE = (24, 16)
RADIANCE = ("emission", "direct_diffuse", "direct_specular", "indirect_diffuse",
            "indirect_specular")


def _env_bitmap(h: int = 16, w: int = 32) -> mi.Bitmap:
    """A smooth sky gradient with one bright patch (so the lobe's width shows)."""
    y, x = np.mgrid[0:h, 0:w]
    img = np.zeros((h, w, 3), np.float32)
    img[..., 0] = 0.2 + 0.8 * x / w
    img[..., 1] = 0.3 + 0.7 * y / h
    img[..., 2] = 0.5
    img[2:5, 6:10] = 8.0
    return mi.Bitmap(img)


def _normal_map() -> mi.Bitmap:
    rng = np.random.default_rng(1)
    n = rng.normal(0.0, 0.25, (32, 32, 3))
    n[..., 2] = 1.0
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return mi.Bitmap(((n + 1.0) / 2.0).astype(np.float32))


def _nmap(bsdf: dict) -> dict:
    return {"type": "normalmap", "bsdf": bsdf,
            "normalmap": {"type": "bitmap", "bitmap": _normal_map(), "raw": True,
                          "filter_type": "bilinear"}}


def _scene(bsdf: dict, lights=("env", "area"), sphere: bool = True,
           sphere_bsdf: dict | None = None) -> dict:
    """A large plane of ``bsdf`` filling the view (and a sphere of it, or of
    ``sphere_bsdf``), under an environment map and/or a rectangular area light out of
    view."""
    d = {"type": "scene",
         "sensor": {"type": "perspective", "fov": 35,
                    "to_world": mi.ScalarTransform4f().look_at(
                        origin=[0, 1.6, 3.0], target=[0, 0.0, 0], up=[0, 1, 0]),
                    "film": {"type": "hdrfilm", "width": SIZE[0], "height": SIZE[1],
                             "rfilter": {"type": "box"}, "pixel_format": "rgb"}},
         "floor": {"type": "rectangle", "bsdf": bsdf,
                   "to_world": mi.ScalarTransform4f().rotate([1, 0, 0], -90).scale(20)}}
    if sphere:
        d["ball"] = {"type": "sphere", "center": [0.0, 0.35, 0.0], "radius": 0.35,
                     "bsdf": sphere_bsdf or bsdf}
    if "env" in lights:
        d["sky"] = {"type": "envmap", "bitmap": _env_bitmap()}
    if "area" in lights:
        d["lamp"] = {"type": "rectangle",
                     "to_world": mi.ScalarTransform4f().look_at(
                         origin=[0.0, 2.5, -2.5], target=[0, 0, 0.5], up=[0, 1, 0]).scale(0.5),
                     "bsdf": {"type": "diffuse",
                              "reflectance": {"type": "rgb", "value": [0, 0, 0]}},
                     "emitter": {"type": "area",
                                 "radiance": {"type": "rgb", "value": [12, 11, 10]}}}
    return d


CONDUCTORS = {
    "conductor-beckmann": {"type": "roughconductor", "alpha": 0.2, "material": "Au"},
    "conductor-ggx": {"type": "roughconductor", "alpha": 0.3, "distribution": "ggx",
                      "material": "Cu"},
    "twosided-ggx": {"type": "twosided",
                     "bsdf": {"type": "roughconductor", "alpha": 0.25, "distribution": "ggx"}},
    "normalmap-beckmann": _nmap({"type": "roughconductor", "alpha": 0.2, "material": "Al"}),
    "twosided-normalmap-ggx": {"type": "twosided", "bsdf": _nmap(
        {"type": "roughconductor", "alpha": 0.15, "distribution": "ggx"})},
}


# -- 1. the material's own alpha reproduces Mitsuba's BSDF -----------------------------------

@pytest.mark.parametrize("name", list(CONDUCTORS))
def test_material_alpha_override_reproduces_the_unoverridden_render(name):
    """Override = the material's alpha (the G-buffer's roughness channel): every radiance
    channel equals the render through Mitsuba's own BSDF within float rounding (same random
    numbers: the reimplemented sample draws the same directions). Env map and area light."""
    setup = scenes.load(_scene(CONDUCTORS[name]), size=SIZE)
    r = Renderer(setup, frozen=False)
    a = r.render(0)
    assert a.meta.get("primary_roughness") is None
    b = r.render(0, roughness=a["roughness"])
    assert b.meta["primary_roughness"] == "override"
    assert a.numpy("direct_specular").max() > 0.5 and a.numpy("indirect_specular").max() > 0.05
    for ch in RADIANCE:
        x, y = a.numpy(ch), b.numpy(ch)
        np.testing.assert_allclose(y, x, rtol=1e-4, atol=1e-5, err_msg=ch)
    # and another alpha changes it (the override is live)
    c = r.render(0, roughness=np.full((SIZE[1], SIZE[0]), 0.6, np.float32))
    assert np.abs(c.numpy("direct_specular") - a.numpy("direct_specular")).max() > 0.1


@pytest.mark.slow
@pytest.mark.parametrize("distribution", ["beckmann", "ggx"])
def test_plastic_specular_lobe_matches_mitsuba_eval_and_pdf(distribution):
    """roughplastic (its sampling mixture is not Mitsuba's, so paths differ): the overridden
    specular lobe's value and pdf at the material's alpha equal Mitsuba's ``eval`` / ``pdf``
    of the glossy lobe alone; the mixture's pdf at each sampled direction is the one
    ``eval_pdf`` gives there, and the diffuse share comes from Mitsuba's diffuse lobe."""
    bsdf = {"type": "twosided", "bsdf": {"type": "roughplastic", "alpha": 0.25,
                                         "distribution": distribution,
                                         "diffuse_reflectance": {"type": "rgb",
                                                                 "value": [0.3, 0.5, 0.2]}}}
    setup = scenes.load(_scene(bsdf, lights=("env",)), size=SIZE)
    scene = setup.scene
    shapes = ShapeTable(scene)
    n = 4096
    rng = np.random.default_rng(3)
    # rays from random points above the plane down to random points of it
    o = np.stack([rng.uniform(-2, 2, n), rng.uniform(0.2, 3, n), rng.uniform(-2, 2, n)], 1)
    t = np.stack([rng.uniform(-1, 1, n), np.zeros(n), rng.uniform(1, 2, n)], 1)
    d = t - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    ray = mi.Ray3f(mi.Point3f(*o.T.astype(np.float32)), mi.Vector3f(*d.T.astype(np.float32)))
    si = scene.ray_intersect(ray)
    b = si.bsdf(ray)
    alpha = mi.Float(np.full(n, 0.25, np.float32))
    lobe = PrimaryLobe(si, b, shapes, alpha, si.is_valid(), shapes.lobe_key)
    on = np.array(lobe.on)
    assert on.mean() > 0.9
    wo = mi.warp.square_to_uniform_hemisphere(
        mi.Point2f(*rng.uniform(0, 1, (2, n)).astype(np.float32)))
    f, pdf_mix, p_s = lobe.eval_pdf(wo)
    ctx_s = mi.BSDFContext()
    ctx_s.type_mask = int(mi.BSDFFlags.Glossy)
    want_f = np.array(b.eval(ctx_s, si, wo, si.is_valid()))
    want_pdf = np.array(b.pdf(ctx_s, si, wo, si.is_valid()))
    np.testing.assert_allclose(np.array(f)[:, on], want_f[:, on], rtol=2e-4, atol=1e-6)
    cos = np.maximum(np.array(wo.z) * np.array(lobe.sign), 0.0)  # twosided: mirrored
    ps = np.array(p_s)
    pdf_spec = (np.array(pdf_mix) - (1 - ps) * cos / np.pi) / ps
    # (below the horizon Mitsuba's roughplastic pdf is not masked to 0, its eval is)
    up = on & (cos > 0)
    np.testing.assert_allclose(pdf_spec[up], want_pdf[up], rtol=2e-3, atol=1e-5)
    # sampling: the returned pdf is the mixture's pdf at the sampled direction
    u1 = mi.Float(rng.uniform(0, 1, n).astype(np.float32))
    u2 = mi.Point2f(*rng.uniform(0, 1, (2, n)).astype(np.float32))
    wo_s, pdf_s, _, _ = lobe.sample(u1, u2)
    _, pdf_at, _ = lobe.eval_pdf(wo_s)
    ok = on & (np.array(pdf_s) > 0)
    assert ok.mean() > 0.8
    np.testing.assert_allclose(np.array(pdf_s)[ok], np.array(pdf_at)[ok], rtol=1e-4)


@pytest.mark.slow
def test_smooth_and_diffuse_bsdfs_are_untouched():
    """Lanes whose BSDF is smooth or diffuse keep Mitsuba's: an override changes nothing."""
    for bsdf in ({"type": "diffuse"}, {"type": "conductor", "material": "Ag"},
                 {"type": "roughconductor", "alpha_u": 0.1, "alpha_v": 0.3}):
        setup = scenes.load(_scene(bsdf, lights=("env",)), size=SIZE)
        r = Renderer(setup, frozen=False)
        a = r.render(0)
        b = r.render(0, roughness=np.full((SIZE[1], SIZE[0], 1), 0.7, np.float32))
        for ch in RADIANCE:
            np.testing.assert_array_equal(a.numpy(ch), b.numpy(ch))


def test_bad_roughness_refused():
    setup = scenes.load(_scene(CONDUCTORS["conductor-ggx"], lights=("env",)), size=SIZE)
    r = Renderer(setup, frozen=False)
    with pytest.raises(GlossrtError, match="one alpha per pixel"):
        r.render(0, roughness=np.zeros((3, 3), np.float32))


# -- 2. a constant override converges to the scene with that alpha -----------------------------

ALPHA_MATERIAL, ALPHA_OVERRIDE = 0.08, 0.35
MATERIALS = {
    "conductor-beckmann": {"type": "roughconductor", "material": "Au"},
    "conductor-ggx": {"type": "roughconductor", "distribution": "ggx", "material": "Cu"},
    "plastic-beckmann": {"type": "roughplastic",
                         "diffuse_reflectance": {"type": "rgb", "value": [0.2, 0.3, 0.5]}},
    "plastic-ggx": {"type": "roughplastic", "distribution": "ggx",
                    "diffuse_reflectance": {"type": "rgb", "value": [0.2, 0.3, 0.5]}},
}


def _with_alpha(bsdf: dict, alpha: float) -> dict:
    return {**bsdf, "alpha": alpha}


@pytest.mark.slow
@pytest.mark.parametrize("lights", ["env", "area"])
@pytest.mark.parametrize("name", list(MATERIALS))
def test_constant_override_converges_to_the_scene_with_that_alpha(name, lights):
    """A plane of material alpha 0.08 traced with a constant override 0.35 against the same
    scene with alpha 0.35 in its dict (Mitsuba's BSDF), both converged (pixel-centre primary
    rays, 256 spp, path depth 3 with a diffuse sphere, so the primary hit's BSDF sample
    also carries indirect light): per pixel of the plane (the sphere's pixels see the
    plane at vertex 1, where the material's alpha stays) within the noise (RMSE of the
    difference below 1.3x that of two independent override renders); the material's own
    alpha is far off. And the image mean against Mitsuba's own ``path`` integrator
    (``mi.render``, 512 spp, plane only) within 4 standard errors plus 0.5% (its pixel filter
    averages over each pixel)."""
    spp = 256
    base = MATERIALS[name]
    ls = (lights,)
    ball = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.6, 0.5, 0.4]}}
    over = Renderer(scenes.load(_scene(_with_alpha(base, ALPHA_MATERIAL), ls,
                                       sphere_bsdf=ball), size=SIZE),
                    max_depth=3, frozen=False)
    ref = Renderer(scenes.load(_scene(_with_alpha(base, ALPHA_OVERRIDE), ls,
                                      sphere_bsdf=ball), size=SIZE),
                   max_depth=3, frozen=False)
    alpha = np.full((SIZE[1], SIZE[0], 1), ALPHA_OVERRIDE, np.float32)
    f1 = over.render_reference(0, spp, seed=1, roughness=alpha)
    plane = f1.numpy("mesh_id")[..., 0] == f1.numpy("mesh_id")[-1, 0, 0]  # bottom row: floor
    assert 0.5 < plane.mean() < 0.95
    # a plastic's diffuse lobe stays Mitsuba's at the material's alpha (its coating
    # transmittance table): compare its specular lobe's light; a conductor's whole light
    spec = name.startswith("plastic")

    def light(f):
        if spec:
            return (f.numpy("direct_specular") + f.numpy("indirect_specular"))[plane]
        return f.numpy("color")[plane]

    a1 = light(f1)
    a2 = light(over.render_reference(0, spp, seed=2, roughness=alpha))
    b = light(ref.render_reference(0, spp, seed=3))
    m = light(over.render_reference(0, spp, seed=4))  # the material's alpha

    def rmse(x, y):
        return float(np.sqrt(np.mean((x - y) ** 2)))

    noise = rmse(a1, a2)
    assert rmse(a1, b) < 1.3 * noise + 1e-6, (rmse(a1, b), noise)
    assert rmse(m, b) > 4.0 * noise, (rmse(m, b), noise)

    # Mitsuba's own path integrator on the plane alone (no edges: its pixel filter and the
    # pixel centres see the same smooth image), image mean
    if spec:  # a black diffuse lobe: the plastic's light is its specular lobe's alone
        base = {**base, "diffuse_reflectance": {"type": "rgb", "value": [0.0, 0.0, 0.0]}}
    flat = scenes.load(_scene(_with_alpha(base, ALPHA_OVERRIDE), ls, sphere=False), size=SIZE)
    r_pl = Renderer(flat, max_depth=3, frozen=False)
    mine = Renderer(scenes.load(_scene(_with_alpha(base, ALPHA_MATERIAL), ls, sphere=False),
                                size=SIZE), max_depth=3, frozen=False)
    spp_m = 512
    img = np.asarray(r_pl.render_mitsuba(0, spp_m, seed=5))
    got = mine.render_reference(0, spp_m, seed=6, roughness=alpha).numpy("color")
    got2 = mine.render_reference(0, spp_m, seed=7, roughness=alpha).numpy("color")
    se = float(np.std(got - got2) / np.sqrt(2.0) / np.sqrt(got.size) * np.sqrt(2.0))
    assert abs(got.mean() - img.mean()) < 4.0 * se + 0.005 * img.mean(), (
        got.mean(), img.mean(), se)


# -- 3. the pipeline's specaa stage feeds the primary hit ------------------------------------

PIPE_SIZE = (32, 24)


def _env_setup():
    bsdf = _nmap({"type": "roughconductor", "alpha": 0.05, "distribution": "ggx",
                  "material": "Al"})
    d = _scene(bsdf, lights=("env",))
    d["sensor"]["film"].update(width=PIPE_SIZE[0], height=PIPE_SIZE[1])
    return scenes.load(d, size=PIPE_SIZE)


@pytest.mark.slow
def test_pipeline_specaa_on_an_env_map_scene_traces_the_filtered_roughness():
    """An environment-map-only scene (nothing for an analytic stage to shade) with
    ``specaa=avgnormal-eig``: the frame's radiance is the path tracer's with the filtered
    roughness (the stage's ``roughness`` channel, wider than the material's where the
    normals vary) at the primary hit: equal to an independent renderer traced with that
    roughness, different from the render with the material's, and converged (the
    ``accumulate`` reference, 64 spp) farther from the unfiltered converged frame than its
    noise. The steady frame does not re-record."""
    md = 3
    pipe = pipeline.Pipeline(_env_setup(), preset="schied2017", specaa="avgnormal-eig",
                             indirect="none", taa=False, max_depth=md, progress=False)
    f = pipe.render(0)
    assert f.meta["pipeline"]["specaa"]["path_tracer"] == "filtered roughness at the primary hit"
    rough, material = f.numpy("roughness"), f.numpy("roughness_material")
    hit = f.numpy("mesh_id")[..., 0] > 0
    assert (rough[hit] >= material[hit] - 1e-6).all()
    assert (rough[hit] > material[hit] + 0.05).mean() > 0.05
    setup = _env_setup()
    r = Renderer(setup, max_depth=md, seed=pipe.opts["seed"], frozen=False)
    want = r.render(0, roughness=f["roughness"])
    plain = r.render(0)
    for ch in ("direct_diffuse", "direct_specular", "indirect_diffuse", "indirect_specular"):
        np.testing.assert_allclose(f.numpy(ch), want.numpy(ch), rtol=1e-5, atol=1e-6,
                                   err_msg=ch)
    assert np.abs(f.numpy("direct_specular") - plain.numpy("direct_specular")).max() > 0.1
    # steady state: frames replay (the first frame after frame 0 may record once more: its
    # motion vectors point back to an explicit previous pose)
    counts = []
    for i in range(1, 6):
        pipe.render(i)
        counts.append(pipe.recordings())
    assert counts[1:] == [counts[1]] * 4, counts

    # converged: the accumulated reference with and without specaa
    def converged(spec, seed):
        p = pipeline.Pipeline(_env_setup(), preset="reference", specaa=spec, spp=32,
                              max_depth=md, seed=seed, progress=False)
        p.render(0)
        return p.render(0)

    on, on2, off = (converged("avgnormal-eig", 1), converged("avgnormal-eig", 2),
                    converged("none", 3))
    assert on.meta["spp"] == 64
    noise = float(np.sqrt(np.mean((on.numpy("color") - on2.numpy("color")) ** 2)))
    diff = float(np.sqrt(np.mean((on.numpy("color") - off.numpy("color")) ** 2)))
    assert diff > 3.0 * noise, (diff, noise)
    # the converged frame is the renderer's converged frame with that roughness
    ref = Renderer(_env_setup(), max_depth=md, frozen=False).render_reference(
        0, 64, seed=9, roughness=on["roughness"])
    err = float(np.sqrt(np.mean((on.numpy("color") - ref.numpy("color")) ** 2)))
    assert err < 1.5 * noise, (err, noise)


def test_cli_specaa_on_an_env_map_only_scene(tmp_path, capsys):
    """``glossrt render --specaa`` on a scene lit only by an environment map (refused
    before): channel ``specaa`` is the path-traced direct light with the filtered roughness
    at the primary hit; a per-light method is refused with one clear line."""
    from glossrt.cli import main
    from glossrt.frame import Frame

    env = tmp_path / "sky.exr"
    _env_bitmap().write(str(env))
    xml = tmp_path / "env.xml"
    xml.write_text(f"""<scene version="3.0.0">
  <sensor type="perspective"><float name="fov" value="35"/>
    <transform name="to_world"><lookat origin="0, 1.6, 3" target="0, 0, 0" up="0, 1, 0"/>
    </transform>
    <film type="hdrfilm"><integer name="width" value="24"/><integer name="height" value="16"/>
    </film></sensor>
  <shape type="sphere"><point name="center" x="0" y="0.35" z="0"/>
    <float name="radius" value="0.35"/>
    <bsdf type="roughconductor"><float name="alpha" value="0.05"/></bsdf></shape>
  <emitter type="envmap"><string name="filename" value="{env}"/></emitter>
</scene>""")
    out = tmp_path / "out"
    assert main(["render", str(xml), "--out", str(out), "--specaa", "avgnormal-eig"]) == 0
    f = Frame.load(next(out.glob("*.exr")))
    assert f.meta["specaa_source"] == "path-traced"
    spec = f.numpy("specaa")
    assert spec.shape == (16, 24, 3) and spec.max() > 0.1
    assert main(["render", str(xml), "--out", str(tmp_path / "o2"), "--specaa",
                 "halfvector"]) != 0
    assert "filters per light" in capsys.readouterr().err
    assert not (tmp_path / "o2").exists() or not any((tmp_path / "o2").iterdir())
