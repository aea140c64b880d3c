"""Any scene Mitsuba renders in RGB: every BSDF through Mitsuba's own interfaces, every
emitter, the integrators and cameras glossrt can stand for, instancing, and the pipeline's
per-light and per-surface fallbacks, on glossrt's trial scenes (src/glossrt/data/scenes).

The references are independent computations: Mitsuba's own ``path`` (and ``direct``)
integrator on the same file through the same film, and Monte Carlo estimates from Mitsuba's
``BSDF.sample`` with random numbers for the G-buffer's albedos."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from glossrt import backend

backend.ensure()
import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

import glossrt.render.integrator  # noqa: E402,F401  (registers "glossrt")
from glossrt import pipeline, scenes  # noqa: E402
from glossrt.brdf.microfacet import BECKMANN, GGX, NO_LOBE  # noqa: E402
from glossrt.errors import GlossrtError, SceneError  # noqa: E402
from glossrt.render import Renderer, emitter_index  # noqa: E402
from glossrt.render.integrator import AOV_LAYERS  # noqa: E402
from glossrt.render.materials import describe_bsdf, lobes_separable  # noqa: E402

SIZE = (32, 24)
TRIALS = scenes.trial_scenes()
RADIANCE = ("emission", "direct_diffuse", "direct_specular", "indirect_diffuse",
            "indirect_specular")
BATCHES, BATCH_SPP = 8, 64


def _load(name: str, size=SIZE, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # (thinlens: rendered as a pinhole)
        return scenes.load(TRIALS[name], size=size, **kw)


def _aov_slices() -> dict[str, slice]:
    """Channel slices of the glossrt integrator's output (R, G, B, then its AOVs)."""
    out, k = {}, 3
    for name, comps in AOV_LAYERS:
        out[name] = slice(k, k + len(comps))
        k += len(comps)
    return out


@pytest.fixture(scope="module", params=sorted(TRIALS))
def trial(request):
    """glossrt's path tracer (its components, through Mitsuba's film and sampler: the
    ``glossrt`` integrator) and Mitsuba's ``path`` on the same scene, sensor and depth, in
    independent batches; the interior of each shape (pixels wholly on it)."""
    name = request.param
    setup = _load(name)
    md = Renderer(setup).mitsuba_max_depth
    rr = setup.rr_depth
    ours = mi.load_dict({"type": "glossrt", "max_depth": md})
    theirs = mi.load_dict({"type": "path", "max_depth": md, "rr_depth": rr})
    sl = _aov_slices()
    a = np.stack([np.array(mi.render(setup.scene, sensor=setup.sensor, integrator=ours,
                                     spp=BATCH_SPP, seed=10 + k)) for k in range(BATCHES)])
    b = np.stack([np.array(mi.render(setup.scene, sensor=setup.sensor, integrator=theirs,
                                     spp=BATCH_SPP, seed=100 + k)) for k in range(BATCHES)])
    parts = {n: a[..., sl[n]].astype(np.float64) for n in RADIANCE}
    ids = a[..., sl["mesh_id"]][..., 0].mean(0)
    return dict(name=name, setup=setup, parts=parts, ours=sum(parts.values()),
                theirs=b.astype(np.float64), ids=ids)


def _z(ours: np.ndarray, theirs: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """z of the difference of two region means per channel: batches (K, H, W, 3), the
    variance of each pixel's mean from its batches, pixels independent."""
    k = ours.shape[0]
    n = mask.sum()
    diff = ours.mean(0)[mask].mean(0) - theirs.mean(0)[mask].mean(0)
    var = (ours.var(0, ddof=1)[mask].sum(0) + theirs.var(0, ddof=1)[mask].sum(0)) / k
    return diff / np.maximum(np.sqrt(var) / n, 1e-12)


def test_components_add_up_to_mitsubas_path(trial):
    """The five components of glossrt's path tracer add up to Mitsuba's `path` image on the
    same file: the whole image and each shape's interior, within 4.5 standard errors; the
    same statistic tells a missing component (its power)."""
    whole = np.ones(trial["ids"].shape, bool)
    z = _z(trial["ours"], trial["theirs"], whole)
    assert np.all(np.abs(z) < 4.5), (trial["name"], z)
    regions = 0
    for i in np.unique(np.round(trial["ids"])):
        m = (trial["ids"] == i)  # wholly on one shape (box-filtered ids are fractional at edges)
        if i == 0 or m.sum() < 12:
            continue
        regions += 1
        z = _z(trial["ours"], trial["theirs"], m)
        assert np.all(np.abs(z) < 4.5), (trial["name"], int(i), z)
    assert regions >= 2, trial["name"]
    biggest = max((k for k in RADIANCE if k != "emission"),
                  key=lambda k: trial["parts"][k].mean())
    z_drop = _z(trial["ours"] - trial["parts"][biggest], trial["theirs"], whole)
    assert np.all(np.abs(z_drop) > 10), (trial["name"], biggest, z_drop)


# -- the lobe split and the G-buffer of BSDFs no analytic lobe represents ----------------------


@pytest.fixture(scope="module")
def glass_frames():
    setup = _load("glass")
    r = Renderer(setup)
    return setup, r.render(0), r.render_reference(0, spp=64)


@pytest.fixture(scope="module")
def material_frames():
    setup = _load("materials", size=(48, 36))
    r = Renderer(setup)
    return setup, r.render(0), r.render_reference(0, spp=64)


def _pixels(setup, frame, sid: str) -> np.ndarray:
    return frame.numpy("mesh_id")[..., 0] == setup.shapes.index(
        next(s for s in setup.shapes if s.id() == sid)) + 1


def test_delta_and_glossy_lobes_are_specular(glass_frames):
    """Smooth glass reflects and transmits through delta lobes: its pixels carry no diffuse
    light at all; the rough glass ball's lobes are glossy: specular too."""
    setup, _, ref = glass_frames
    for sid in ("glass", "frosted", "pane"):
        m = _pixels(setup, ref, sid)
        assert m.sum() > 10, sid
        assert not ref.numpy("direct_diffuse")[m].any(), sid
        assert not ref.numpy("indirect_diffuse")[m].any(), sid
        spec = ref.numpy("direct_specular") + ref.numpy("indirect_specular")
        assert spec[m].mean() > 0.01, sid


def test_distribution_and_roughness_channels(glass_frames, material_frames):
    """``distribution``: the rough glass ball's GGX, the bump-mapped plastic's Beckmann (its
    lobe around a perturbed normal), "no analytic lobe" for smooth glass, principled and a
    blend of unlike lobes; ``roughness``: the microfacet alpha of that lobe."""
    want = {("glass", "glass"): (NO_LOBE, 0.0), ("glass", "frosted"): (GGX, 0.25),
            ("glass", "pane"): (NO_LOBE, 0.0), ("glass", "floor"): (GGX, 1.0),
            ("materials", "principled"): (NO_LOBE, 0.35 ** 2),
            ("materials", "blend"): (NO_LOBE, 0.0),
            ("materials", "bumpy"): (BECKMANN, 0.1)}
    frames = {"glass": glass_frames, "materials": material_frames}
    for (scene, sid), (dist, alpha) in want.items():
        setup, f, _ = frames[scene]
        m = _pixels(setup, f, sid)
        assert m.sum() > 5, sid
        np.testing.assert_array_equal(f.numpy("distribution")[m], dist, err_msg=sid)
        np.testing.assert_allclose(f.numpy("roughness")[m], alpha, rtol=1e-5, err_msg=sid)


def test_sampled_albedo_matches_mitsubas_bsdf_sampling(material_frames, glass_frames):
    """The albedo channels of BSDFs the split-sum tables do not describe are the mean BSDF
    sample weight, split by lobe (16 fixed stratified samples): against 4096 random samples
    of Mitsuba's ``BSDF.sample`` at the same primary hits, the total agrees within the
    stratification's error (one stratum of the lobe choice: 1/16 of the weight) and the
    diffuse albedo is 0 for glass."""
    for setup, f, _ in (material_frames, glass_frames):
        ids = f.numpy("mesh_id")[..., 0].astype(int)
        h, w = ids.shape
        table = {i + 1: describe_bsdf(s.bsdf()) for i, s in enumerate(setup.shapes)}
        for i, mat in table.items():
            if not mat.sampled_albedo:
                continue
            # pixels whose plain first hit is this shape (not behind a masked cut-out)
            x = mi.Float((np.arange(h * w) % w).astype(np.float32) + 0.5) / w
            y = mi.Float((np.arange(h * w) // w).astype(np.float32) + 0.5) / h
            ray, _ = setup.sensor.sample_ray(0.0, 0.5, mi.Point2f(x, y), mi.Point2f(0.5, 0.5))
            hit = np.array(dr.reinterpret_array(mi.UInt32, setup.scene.ray_intersect(ray).shape))
            mine = int(np.array(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(
                setup.shapes[i - 1])))[0])
            ys, xs = np.nonzero((ids == i) & (hit.reshape(h, w) == mine))
            if len(ys) < 4:
                continue
            pick = np.linspace(0, len(ys) - 1, 4).astype(int)
            px = ys[pick] * w + xs[pick]
            n = 4096
            lane = np.repeat(px, n)
            x = mi.Float((lane % w).astype(np.float32) + 0.5) / w
            y = mi.Float((lane // w).astype(np.float32) + 0.5) / h
            ray, _ = setup.sensor.sample_ray(0.0, 0.5, mi.Point2f(x, y), mi.Point2f(0.5, 0.5))
            si = setup.scene.ray_intersect(ray)
            rng = np.random.default_rng(i)
            u = [mi.Float(rng.random(lane.size, np.float32)) for _ in range(3)]
            bs, wt = si.bsdf(ray).sample(mi.BSDFContext(), si, u[0], mi.Point2f(u[1], u[2]))
            wt = np.nan_to_num(np.array(wt, np.float64).reshape(3, len(px), n))
            mc = wt.mean(-1).T  # (pixels, 3)
            se = wt.std(-1).T / np.sqrt(n)
            total = (f.numpy("albedo_diffuse") + f.numpy("albedo_specular")).reshape(-1, 3)[px]
            tol = 4 * se + wt.max(axis=(0, 2))[:, None] / 16 + 1e-3
            assert np.all(np.abs(total - mc) < tol), (setup.name, mat.kind, total, mc, tol)
            if mat.kind in ("SmoothDielectric", "RoughDielectric", "ThinDielectric"):
                assert not f.numpy("albedo_diffuse").reshape(-1, 3)[px].any()


def test_principled_lobes_are_split_without_lobe_masks(material_frames):
    """``principled`` evaluates every lobe whatever ``BSDFContext.type_mask`` asks (Mitsuba
    3.9), so glossrt splits its light by the sampled lobe and its albedos: both components
    are lit and add up to the whole (the whole against Mitsuba: test_components_*); a blend
    of a diffuse and a metal lobe honours the masks."""
    setup, _, ref = material_frames
    bsdfs = {s.id(): s.bsdf() for s in setup.shapes}
    assert not lobes_separable(bsdfs["principled"])
    assert lobes_separable(bsdfs["blend"]) and lobes_separable(bsdfs["floor"])
    m = _pixels(setup, ref, "principled")
    d = ref.numpy("direct_diffuse")[m].mean()
    s = ref.numpy("direct_specular")[m].mean()
    assert d > 0.01 and s > 0.002, (d, s)


def test_a_masked_card_shows_what_lies_behind_its_cutouts(material_frames):
    """Alpha testing: where the card's checkerboard opacity is 0, the primary ray passes
    through it, so the G-buffer (mesh id, depth) is the floor's behind it."""
    setup, f, _ = material_frames
    card = setup.shapes.index(next(s for s in setup.shapes if s.id() == "card")) + 1
    floor = setup.shapes.index(next(s for s in setup.shapes if s.id() == "floor")) + 1
    ids = f.numpy("mesh_id")[..., 0]
    ys, xs = np.nonzero(ids == card)
    assert len(ys) > 10
    box = ids[ys.min():ys.max() + 1, xs.min():xs.max() + 1]
    assert (box == floor).sum() > 0.2 * box.size, box  # the cut-outs show the floor


# -- integrators, cameras, instancing -----------------------------------------------------------


def _write(tmp_path, name: str, text: str) -> str:
    p = tmp_path / name
    p.write_text(text)
    return str(p)


def _with_integrator(name: str, integrator: str) -> str:
    with open(TRIALS[name]) as f:
        text = f.read()
    start = text.index("<integrator")
    end = text.index("\n", start)
    return text[:start] + integrator + text[end:]


@pytest.mark.parametrize("integrator, depth, rr", [
    ('<integrator type="path"><integer name="max_depth" value="5"/>'
     '<integer name="rr_depth" value="2"/></integrator>', 5, 2),
    ('<integrator type="volpath"><integer name="max_depth" value="4"/></integrator>', 4, 5),
    ('<integrator type="direct"/>', 2, 5),
    ('<integrator type="aov"><string name="aovs" value="d:depth"/><integrator type="path">'
     '<integer name="max_depth" value="6"/></integrator></integrator>', 6, 5),
    ('<integrator type="ptracer"><integer name="max_depth" value="3"/></integrator>', 3, 5),
])
def test_integrators_glossrt_renders(tmp_path, integrator, depth, rr):
    path = _write(tmp_path, "s.xml", _with_integrator("lights", integrator))
    setup = scenes.load(path, size=SIZE)
    assert (setup.max_depth, setup.rr_depth, setup.integrator_error) == (depth, rr, None)
    r = Renderer(setup)
    assert (r.mitsuba_max_depth, r.rr_depth) == (depth, rr)
    f = r.render(0)
    assert (f.meta["max_depth"], f.meta["rr_depth"]) == (depth, rr)


@pytest.mark.parametrize("integrator, words", [
    ('<integrator type="depth"/>', "integrator depth.*type=\"path\""),
    ('<integrator type="aov"><string name="aovs" value="d:depth"/></integrator>',
     "aov nests no path tracer"),
    ('<integrator type="volpath"/>', "participating media"),
])
def test_integrators_it_cannot_stand_for_are_one_line_when_tracing(tmp_path, integrator,
                                                                    words):
    """Loading never refuses an integrator (commands that do not trace with it load the
    scene too); a renderer that would trace with the scene's depth refuses it in one line,
    and one given a depth renders."""
    text = _with_integrator("lights", integrator)
    if "volpath" in integrator:  # media inside the ball: what volpath renders and glossrt not
        text = text.replace('<shape type="sphere" id="ball">',
                            '<shape type="sphere" id="ball"><medium type="homogeneous" '
                            'name="interior"/>')
    setup = scenes.load(_write(tmp_path, "s.xml", text), size=SIZE)
    with pytest.raises(GlossrtError, match=words) as e:
        Renderer(setup)
    assert len(str(e.value).splitlines()) == 1
    assert Renderer(setup, max_depth=2).render(0).numpy("color").mean() > 0


def test_the_direct_integrator_is_direct_light():
    """A file whose integrator is ``direct``: glossrt renders direct light only (path depth
    2), and its image through Mitsuba's film agrees with Mitsuba's own ``direct`` integrator
    on the file (the whole image and each shape, as test_components_*)."""
    setup = _load("direct")
    assert setup.integrator == "direct" and setup.max_depth == 2
    r = Renderer(setup)
    f = r.render(0)
    assert not f.numpy("indirect_diffuse").any() and not f.numpy("indirect_specular").any()
    ours = mi.load_dict({"type": "glossrt", "max_depth": r.mitsuba_max_depth})
    theirs = setup.scene.integrator()
    assert "DirectIntegrator" in str(theirs)
    a = np.stack([np.array(mi.render(setup.scene, sensor=setup.sensor, integrator=ours,
                                     spp=BATCH_SPP, seed=10 + k)) for k in range(BATCHES)])
    b = np.stack([np.array(mi.render(setup.scene, sensor=setup.sensor, integrator=theirs,
                                     spp=BATCH_SPP, seed=100 + k)) for k in range(BATCHES)])
    ids = a[..., _aov_slices()["mesh_id"]][..., 0].mean(0)
    for m in [np.ones(ids.shape, bool)] + [ids == i for i in np.unique(np.round(ids))
                                           if (ids == i).sum() >= 12]:
        z = _z(a[..., :3].astype(np.float64), b.astype(np.float64), m)
        assert np.all(np.abs(z) < 4.5), z


def test_a_thin_lens_camera_is_a_pinhole_with_a_warning(tmp_path):
    with pytest.warns(UserWarning, match="depth of field is not rendered"):
        setup = scenes.load(TRIALS["thinlens"], size=SIZE)
    assert setup.sensor_kind == "thinlens"
    with open(TRIALS["thinlens"]) as f:
        text = f.read()
    pinhole = (text.replace('type="thinlens"', 'type="perspective"')
               .replace('<float name="aperture_radius" value="0.08"/>', "")
               .replace('<float name="focus_distance" value="4"/>', ""))
    other = scenes.load(_write(tmp_path, "pinhole.xml", pinhole), size=SIZE)
    a, b = Renderer(setup).render(0), Renderer(other).render(0)
    for k in ("depth", "normal", "mesh_id", "position"):
        np.testing.assert_array_equal(a.numpy(k), b.numpy(k), err_msg=k)


def test_instanced_shapes_have_mesh_ids_and_occlude_bspvt(tmp_path):
    """Shapes in an instanced shape group get mesh ids (after the scene's own shapes; all
    instances of a group share them) and are lit; BSPVT's trees see them as occluders: the
    floor under the middle piece is in shadow in the trees' direct light as in a shadowed
    Monte Carlo estimate of the same light, unlike unshadowed LTC."""
    from glossrt.lights import mc
    from glossrt.lights.ltc import shade_frame
    from glossrt.lights.scene import polygon_lights
    from glossrt.lights.shading import fresnel_image

    # (the floor tessellated: BSPVT's visibility lives at its vertices)
    from test_pipeline import _write_grid

    grid = str(tmp_path / "grid.obj")
    _write_grid(grid, 16)
    text = open(TRIALS["instances"]).read().replace(
        '<shape type="rectangle" id="floor">\n    <transform name="to_world"><rotate x="1" '
        'angle="-90"/><scale value="3"/></transform>',
        f'<shape type="obj" id="floor"><string name="filename" value="{grid}"/>\n'
        '    <transform name="to_world"><scale value="3"/></transform>')
    assert "grid.obj" in text
    setup = scenes.load(_write(tmp_path, "inst.xml", text), size=(48, 36))
    own = len(scenes.stable_shapes(setup.scene))
    assert [s.id() for s in setup.shapes[own:]] == ["piece_box", "piece_plinth"]
    pipe = pipeline.Pipeline(setup, preset="okuno-iwasaki", progress=False,
                             bspvt_resolution=16, indirect="none", taa=False)
    assert pipe.plan.bspvt, pipe.plan.report()
    assert "instanced" in pipe.plan.ratio_shapes["piece_box"]
    f = pipe.render(0)
    ids = f.numpy("mesh_id")[..., 0]
    assert (ids == own + 1).sum() > 5 and (ids == own + 2).sum() > 5
    floor = ids == setup.shape_index["floor"]
    lights = polygon_lights(setup, 0)
    f0 = fresnel_image(setup, f)
    shadowed = np.asarray(mc.render_mc(f, lights, 64, f0=f0, scene=setup.scene, seed=3))
    free = np.asarray(shade_frame(f, lights, f0=f0))
    shade = floor & (shadowed.sum(-1) < 0.5 * free.sum(-1))
    assert shade.sum() > 5, shade.sum()
    bspvt = f.numpy("direct")
    assert bspvt[shade].mean() < 0.6 * free[shade].mean(), (bspvt[shade].mean(),
                                                           free[shade].mean())


# -- the pipeline: every preset, fallbacks, no light counted twice or lost ----------------------


@pytest.mark.parametrize("name, preset", [(n, "full") for n in sorted(TRIALS)]
                         + [("glass", p) for p in pipeline.PRESETS if p != "full"]
                         + [("lights", p) for p in ("okuno-iwasaki", "kimura-tokoi")])
def test_the_pipeline_renders_every_trial_scene(name, preset):
    pipe = pipeline.Pipeline(_load(name), preset=preset, progress=False, bspvt_resolution=8)
    for i in range(2):
        f = pipe.render(i)
    c = f.numpy("color")
    assert np.isfinite(c).all() and c.mean() > 0.005
    p = f.meta["pipeline"]
    assert len(p["lights"]) == len(pipe.setup.scene.emitters())
    for light in p["lights"]:
        assert light["method"] in ("path-traced", "analytic (one shadow ray)", "ltc",
                                   "ltc+bspvt", "ltc+ratio", "highlights"), light
        assert light["method"] != "path-traced" or light["why"], light


def test_the_pipeline_reports_which_method_shaded_what():
    pipe = pipeline.Pipeline(_load("materials"), preset="full", progress=False,
                             bspvt_resolution=8)
    f = pipe.render(0)
    p = f.meta["pipeline"]
    by_kind = {light["kind"]: light for light in p["lights"]}
    assert by_kind["area"]["method"] in ("ltc+bspvt", "ltc+ratio")
    assert by_kind["envmap"]["method"] == "path-traced"
    assert set(p["fallback_shapes"]) >= {"principled", "blend", "bumpy", "card", "sheet"}
    assert set(p["fallback_shapes"]) <= {"principled", "blend", "bumpy", "card", "sheet",
                                         "lamp"}  # (BSPVT: the lamp's own surface emits)
    ids = f.numpy("mesh_id")[..., 0].astype(int)
    fallback = (ids > 0) & ~np.isin(ids, pipe.plan.shapes)
    assert p["fallback_share"] == pytest.approx(fallback.mean(), abs=1e-9)
    assert not f.numpy("direct")[fallback].any()


def test_the_lights_scene_takes_the_path_tracer_for_every_curved_light():
    pipe = pipeline.Pipeline(_load("lights"), preset="full", progress=False)
    methods = {c.id: (c.method, c.why) for c in pipe.plan.lights}
    for sid in ("spot", "projector", "bulb", "disk", "tube"):
        assert methods[sid][0] == "path-traced" and methods[sid][1], (sid, methods[sid])
    assert methods["sun"][0].startswith("analytic")
    assert "not a polygon light" in methods["bulb"][1] or "Sphere" in methods["bulb"][1]


def test_no_light_is_counted_twice_or_lost():
    """The renderer leaves the analytic lights out at the primary hit only on the surfaces
    the direct stage shades: with the same seed, a frame's direct light on the other
    surfaces is, bit for bit, the frame rendered with no exclusion; on the shaded surfaces
    it is the frame with the lights excluded everywhere; the emission and the indirect light
    are the same in all three."""
    setup = _load("materials")
    table = pipeline.Pipeline(setup, preset="full", progress=False,
                              bspvt_resolution=8).plan
    assert table.exclude and len(table.shapes) < table.n_shapes
    part = Renderer(setup, primary_exclude=table.exclude, exclude_on=table.shapes).render(0)
    none = Renderer(setup).render(0)
    every = Renderer(setup, primary_exclude=table.exclude).render(0)
    ids = part.numpy("mesh_id")[..., 0].astype(int)
    shaded = np.isin(ids, table.shapes)
    other = (ids > 0) & ~shaded
    assert shaded.sum() > 50 and other.sum() > 50
    assert part.meta["fallback_pixels"] == other.sum()
    for k in ("direct_diffuse", "direct_specular"):
        np.testing.assert_array_equal(part.numpy(k)[other], none.numpy(k)[other], err_msg=k)
        np.testing.assert_array_equal(part.numpy(k)[shaded], every.numpy(k)[shaded], err_msg=k)
    assert not np.array_equal(none.numpy("direct_diffuse")[shaded],
                              every.numpy("direct_diffuse")[shaded])  # (the test has power)
    for k in ("emission", "indirect_diffuse", "indirect_specular"):
        np.testing.assert_array_equal(part.numpy(k), none.numpy(k), err_msg=k)


def test_the_composed_light_converges_to_the_unexcluded_render():
    """End to end: the pipeline's composition with the lamp shaded by LTC and the ratio
    estimator where the materials allow and the path tracer elsewhere (no denoiser, no TAA),
    averaged over 32 frames, converges to the plain path-traced reference on both kinds of
    surface (within 8%: LTC's fit and the ratio estimator's smoothing, measured +1.0% /
    -1.6%), where counting the lamp twice or losing it would be 35-48% off."""
    size = (32, 24)
    pipe = pipeline.Pipeline(_load("materials", size=size), preset="schied2017",
                             progress=False, direct="ltc+ratio", indirect="none", taa=False,
                             ratio_spp=4)
    acc = np.zeros((size[1], size[0], 3))
    for i in range(32):
        f = pipe.render(i)
        acc += f.numpy("composite") / 32
    setup = _load("materials", size=size)
    ref = Renderer(setup).render_reference(0, spp=512).numpy("color")
    ids = f.numpy("mesh_id")[..., 0].astype(int)
    shaded = np.isin(ids, pipe.plan.shapes) & (ids > 0)
    other = (ids > 0) & ~shaded
    def direct(frame):
        return frame.numpy("direct_diffuse") + frame.numpy("direct_specular")

    lamp = (direct(Renderer(setup).render_reference(0, spp=128))
            - direct(Renderer(setup, primary_exclude=pipe.plan.exclude).render_reference(
                0, spp=128)))
    for m in (shaded, other):
        assert m.sum() > 100
        rel = acc[m].mean() / ref[m].mean() - 1
        assert abs(rel) < 0.08, rel
        assert lamp[m].mean() > 0.25 * ref[m].mean()  # (what a lost lamp would cost)


def test_anisotropic_lobes_fall_back_to_the_path_tracer(tmp_path):
    """An anisotropic floor (the isotropic methods' tables take one alpha) under a polygon
    light: every analytic preset renders it, with the floor left to the path tracer."""
    text = open(TRIALS["direct"]).read().replace(
        '<bsdf type="roughplastic"><string name="distribution" value="ggx"/>'
        '<float name="alpha" value="0.25"/></bsdf>',
        '<bsdf type="roughconductor"><float name="alpha_u" value="0.05"/>'
        '<float name="alpha_v" value="0.3"/></bsdf>')
    path = _write(tmp_path, "aniso.xml", text)
    for preset in ("okuno-iwasaki", "kimura-tokoi", "full"):
        pipe = pipeline.Pipeline(scenes.load(path, size=SIZE), preset=preset, progress=False,
                                 bspvt_resolution=8)
        assert "floor" in pipe.plan.fallback_shapes, preset
        f = pipe.render(0)
        floor = f.numpy("mesh_id")[..., 0] == pipe.setup.shape_index["floor"]
        assert not f.numpy("direct")[floor].any(), preset
        assert np.isfinite(f.numpy("color")).all() and f.numpy("color")[floor].mean() > 0


def test_the_primary_hits_light_alone_keeps_the_scenes_depth():
    """The pipeline's full-resolution half at indirect_scale 2 (``primary_only``): with the
    same seed its direct light is, bit for bit, the full render's, also behind the masked
    card's cut-outs, where the surface the primary ray passed through counts against the
    path depth (tracing it as max_depth 2 lost that light: ``full`` on Mitsuba's
    bsdf_mask_after had twice the RMSE of schied2017)."""
    setup = _load("materials")
    whole = Renderer(setup).render(0)
    alone = Renderer(setup, primary_only=True).render(0)
    assert alone.meta["primary_only"] and alone.meta["max_depth"] == whole.meta["max_depth"]
    for k in ("emission", "direct_diffuse", "direct_specular"):
        np.testing.assert_array_equal(alone.numpy(k), whole.numpy(k), err_msg=k)
    assert not alone.numpy("indirect_diffuse").any() and whole.numpy("indirect_diffuse").any()
    # (behind the cut-outs, where the floor shows through the card)
    card = setup.shapes.index(next(s for s in setup.shapes if s.id() == "card")) + 1
    ids = whole.numpy("mesh_id")[..., 0]
    ys, xs = np.nonzero(ids == card)
    box = np.zeros(ids.shape, bool)
    box[ys.min():ys.max() + 1, xs.min():xs.max() + 1] = True
    behind = box & (ids == setup.shape_index["floor"])
    lit = alone.numpy("direct_diffuse") + alone.numpy("direct_specular")
    assert behind.sum() > 5 and lit[behind].mean() > 0.01


def test_an_emitter_on_a_rectangle_that_is_not_an_area_light_is_path_traced():
    """A ``directionalarea`` emitter sits on a rectangle like an area light but emits along
    one direction: no polygon light, so the path tracer lights it (the analytic stage would
    shade it as a Lambertian polygon)."""
    T = mi.ScalarTransform4f
    d = {"type": "scene",
         "sensor": {"type": "perspective", "to_world": T().look_at([0, 1.5, 3], [0, 0, 0],
                                                                   [0, 1, 0]),
                    "film": {"type": "hdrfilm", "width": 16, "height": 12}},
         "floor": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(2),
                   "bsdf": {"type": "diffuse"}},
         "beam": {"type": "rectangle", "to_world": T().translate([0, 1.5, 0])
                  .rotate([1, 0, 0], 90).scale(0.5),
                  "emitter": {"type": "directionalarea",
                              "radiance": {"type": "rgb", "value": 5.0}}}}
    pipe = pipeline.Pipeline(d, preset="full", progress=False)
    (beam,) = pipe.plan.lights
    assert beam.kind == "directionalarea" and beam.method == "path-traced" and beam.why
    assert not pipe.plan.exclude


def test_emitter_indices_name_every_kind():
    setup = _load("lights")
    kinds = {eid: kind for _, eid, kind, _ in emitter_index(setup)}
    assert kinds["spot"] == "spot" and kinds["projector"] == "projector"
    assert kinds["sun"] == "directional"


# -- loading ------------------------------------------------------------------------------------


def test_scene_parameters_are_given_like_mitsubas_define(tmp_path):
    text = open(TRIALS["direct"]).read().replace(
        '<float name="alpha" value="0.25"/>', '<float name="alpha" value="$rough"/>')
    path = _write(tmp_path, "p.xml", text)
    with pytest.raises(SceneError, match=r"\$rough.*-D rough=VALUE") as e:
        scenes.load(path)
    assert len(str(e.value).splitlines()) == 1
    setup = scenes.load(path, params={"rough": 0.4})
    floor = next(s for s in setup.shapes if s.id() == "floor")
    assert describe_bsdf(floor.bsdf()).alpha == pytest.approx(0.4)
    with pytest.raises(SceneError, match="parameter name"):
        scenes.load(path, params={"bad name": 1})
    with pytest.raises(SceneError, match="XML"):
        scenes.load("glossy-cornell", params={"rough": 1})


def test_the_trial_scenes_are_shipped():
    for name, path in TRIALS.items():
        assert path.endswith(f"{name}.xml")
        with open(path) as f:
            assert "<scene" in f.read()


# -- the command line ----------------------------------------------------------------------------


def test_cli_renders_a_trial_scene_in_full_and_says_how(tmp_path, capsys):
    from glossrt.cli import main
    from glossrt.frame import Frame

    out = tmp_path / "full"
    assert main(["render", TRIALS["lights"], "--pipeline", "full", "--size", "32x24",
                 "--out", str(out)]) == 0
    f = Frame.load(out / "frame_0000.exr")
    methods = {light["id"]: light["method"] for light in f.meta["pipeline"]["lights"]}
    assert methods["spot"] == "path-traced" and methods["sun"].startswith("analytic")


def test_cli_scene_parameters_and_commands_that_do_not_trace(tmp_path, capsys):
    """``-D`` gives a file's $parameter; ``glossrt light`` and ``glossrt bspvt build`` load a
    scene whose integrator glossrt does not render (they do not trace with it), while
    ``glossrt render`` refuses it in one line, before writing anything."""
    from glossrt.cli import main

    text = _with_integrator("direct", '<integrator type="depth"/>').replace(
        '<float name="alpha" value="0.25"/>', '<float name="alpha" value="$rough"/>')
    path = _write(tmp_path, "depth.xml", text)
    out = tmp_path / "r"
    assert main(["render", path, "-D", "rough=0.3", "--size", "16x12", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "integrator depth" in err and len(err.strip().splitlines()) == 1
    assert not out.exists()
    assert main(["render", path, "--size", "16x12", "--out", str(out)]) == 2
    assert "-D rough=VALUE" in capsys.readouterr().err
    assert main(["light", path, "-D", "rough=0.3", "--method", "ltc", "--size", "16x12",
                 "--out", str(tmp_path / "l")]) == 0
    assert (tmp_path / "l" / "frame_0000.exr").is_file()
    trees = tmp_path / "t.bspvt.npz"
    assert main(["bspvt", "build", path, "-D", "rough=0.3", "--resolution", "4",
                 "--out", str(trees)]) == 0
    assert trees.is_file()
    assert main(["render", TRIALS["direct"], "-D", "x=1", "--reference", "--cluster", "local:1",
                 "--size", "8x6", "--out", str(tmp_path / "c")]) == 2
    assert "-D" in capsys.readouterr().err.splitlines()[-1]


def test_a_scene_dr_jit_cannot_freeze_is_traced_anew_with_a_warning():
    """When Dr.Jit refuses to record a frame's kernels (it did for some of Mitsuba's
    documentation scenes while a second copy of the scene was loaded), the renderer warns
    once and traces every frame anew: the same frames, slower."""
    setup = _load("direct")
    r = Renderer(setup)

    def refuse(*args):
        raise RuntimeError("record(): error encountered while recording a frozen function")

    r._trace_frozen = refuse
    with pytest.warns(UserWarning, match="cannot freeze"):
        a = r.render(0)
    assert not r.frozen
    b = Renderer(setup, frozen=False).render(0)
    for k in ("color", "normal", "mesh_id"):
        np.testing.assert_array_equal(a.numpy(k), b.numpy(k), err_msg=k)
    r2 = Renderer(setup)
    r2._trace_frozen = lambda *a: (_ for _ in ()).throw(RuntimeError("another failure"))
    with pytest.raises(RuntimeError, match="another failure"):
        r2.render(0)  # (anything else is not taken for a refusal to freeze)


def test_cli_light_leaves_out_area_lights_that_are_not_polygons(tmp_path, capsys):
    from glossrt.cli import main

    text = open(TRIALS["direct"]).read().replace("</scene>", '''  <shape type="sphere" id="bulb">
    <point name="center" x="1" y="1.5" z="1"/><float name="radius" value="0.1"/>
    <emitter type="area"><rgb name="radiance" value="5, 5, 5"/></emitter>
  </shape>
</scene>''')
    path = _write(tmp_path, "bulb.xml", text)
    with pytest.warns(UserWarning, match="1 area light.s. are not polygons"):
        assert main(["light", path, "--method", "ltc", "--size", "16x12",
                     "--out", str(tmp_path / "l")]) == 0
    assert (tmp_path / "l" / "frame_0000.exr").is_file()


def test_a_quad_floor_is_not_left_to_vertex_visibility():
    """BSPVT's vertex mode interpolates visibility between a mesh's vertices: a 2-triangle
    floor (4 vertices) under one quad light came out uniformly lit, mean 0.0033 against
    0.079 path-traced. Such coarse meshes take the ratio estimator for the BSPVT lights:
    the floor's direct light agrees with a shadowed Monte Carlo estimate of the same light
    (within 10%, the ratio estimator's smoothing; the boxes' shadows included)."""
    from glossrt.lights import mc
    from glossrt.lights.scene import polygon_lights
    from glossrt.lights.shading import fresnel_image

    setup = _load("direct", size=(48, 36))
    pipe = pipeline.Pipeline(setup, preset="okuno-iwasaki", progress=False,
                             bspvt_resolution=8, indirect="none", taa=False, ratio_spp=8)
    assert "too few to carry a shadow" in pipe.plan.ratio_shapes["floor"]
    acc = 0.0
    for i in range(8):
        f = pipe.render(i)
        acc = acc + f.numpy("direct") / 8
    floor = f.numpy("mesh_id")[..., 0] == setup.shape_index["floor"]
    ref = np.asarray(mc.render_mc(f, polygon_lights(setup, 0), 256, f0=fresnel_image(setup, f),
                                  scene=setup.scene, seed=5))
    assert acc[floor].mean() == pytest.approx(ref[floor].mean(), rel=0.10)


_QUAD_FLOORS = {
    "rectangle": '<shape type="rectangle" id="floor">\n'
                 '    <transform name="to_world"><rotate x="1" angle="-90"/><scale value="3"/>'
                 '</transform>',
    "obj": '<shape type="obj" id="floor"><string name="filename" value="{floor}"/>\n'
           '    <transform name="to_world"><scale value="3"/></transform>',
}


@pytest.mark.parametrize("kind", sorted(_QUAD_FLOORS))
def test_a_quad_floor_under_full_matches_mitsubas_path(tmp_path, kind):
    """A 2-triangle floor (a Mitsuba ``rectangle``, or a 4-vertex OBJ) under one quad light,
    shadowed by a card fine enough for BSPVT's trees (so that ``full`` takes ltc+bspvt, and
    the floor the ratio estimator), against Mitsuba's own ``path`` on the same file. Vertex
    visibility left the floor at 0.0117 against 0.0936, its shadow gone. The floor's mean
    colour over 16 frames agrees within 5%: the reference's standard error is 0.06% (8
    batches); the rest is the pipeline's bias, measured +1.5% (0.0950): on such a floor its
    direct light (LTC with the denoised ratio estimator) lies about 2% above Mitsuba's
    depth-2 image, and the half-resolution denoiser keeps little of the floor's indirect
    light (2% of its light). The card's shadow against the lit floor: 0.31 here, 0.24 in
    Mitsuba's (the denoised ratio softens its edges), 0.89 from vertex visibility."""
    from test_pipeline import _write_grid

    card, floor = str(tmp_path / "card.obj"), str(tmp_path / "floor.obj")
    _write_grid(card, 8)  # 81 vertices: the trees cover it
    _write_grid(floor, 1)  # 4 vertices, 2 triangles
    text = f'''<scene version="3.0.0">
  <integrator type="path"><integer name="max_depth" value="3"/></integrator>
  <sensor type="perspective">
    <float name="fov" value="40"/>
    <transform name="to_world"><lookat origin="0, 2, 4.5" target="0, 0.4, 0" up="0, 1, 0"/>
    </transform>
    <film type="hdrfilm"><integer name="width" value="48"/><integer name="height" value="36"/>
    </film>
  </sensor>
  <shape type="rectangle" id="lamp">
    <transform name="to_world"><scale x="0.7" y="0.5"/><rotate x="1" angle="90"/>
      <translate y="2.4" z="0.5"/></transform>
    <emitter type="area"><rgb name="radiance" value="7, 7, 7"/></emitter>
  </shape>
  {_QUAD_FLOORS[kind].format(floor=floor)}
    <bsdf type="roughplastic"><string name="distribution" value="ggx"/>
      <float name="alpha" value="0.25"/></bsdf>
  </shape>
  <shape type="obj" id="card"><string name="filename" value="{card}"/>
    <transform name="to_world"><scale value="0.4"/><translate x="0.2" y="0.8" z="0.3"/>
    </transform>
    <bsdf type="roughconductor"><string name="material" value="Al"/>
      <float name="alpha" value="0.2"/></bsdf>
  </shape>
</scene>'''
    path = _write(tmp_path, "quad.xml", text)
    setup = scenes.load(path)
    pipe = pipeline.Pipeline(setup, preset="full", progress=False, bspvt_resolution=8)
    assert pipe.direct_mode == "ltc+bspvt"
    assert "too few to carry a shadow" in pipe.plan.ratio_shapes["floor"]
    assert "card" not in pipe.plan.ratio_shapes
    n = 16
    color = sum(pipe.render(i).numpy("color").astype(np.float64) for i in range(n - 1))
    f = pipe.render(n - 1)
    color = (color + f.numpy("color")) / n
    on = f.numpy("mesh_id")[..., 0] == setup.shape_index["floor"]
    inner = on.copy()  # (pixels whose neighbours are floor too: no edge pixels)
    inner[1:-1, 1:-1] &= on[:-2, 1:-1] & on[2:, 1:-1] & on[1:-1, :-2] & on[1:-1, 2:]
    inner[[0, -1]], inner[:, [0, -1]] = False, False
    theirs = mi.load_file(path)
    ref = np.stack([np.array(mi.render(theirs, spp=128, seed=k), np.float64)[..., :3]
                    for k in range(8)])
    batch = ref[:, inner].mean(axis=(1, 2))
    se = batch.std(ddof=1) / np.sqrt(len(batch))
    want, got = ref.mean(0)[inner].mean(), color[inner].mean()
    assert abs(got - want) < 0.05 * want + 4 * se, (kind, got, want, se)
    grey_ref, grey = ref.mean(0).mean(-1), color.mean(-1)
    shade = inner & (grey_ref < 0.5 * np.median(grey_ref[inner]))
    assert shade.sum() >= 6, shade.sum()
    lit = inner & ~shade
    assert grey[shade].mean() / grey[lit].mean() == pytest.approx(
        grey_ref[shade].mean() / grey_ref[lit].mean(), abs=0.1)
