"""glossrt.render: separated radiance against Mitsuba's own `path` integrator, the G-buffer,
motion vectors, pixel subsets, frozen kernels and the NaN policy.

Statistical tolerances are derived from Monte Carlo standard errors measured in the test (each
estimate is rendered as several independent batches; the spread between batches gives the
per-pixel variance), never from hard-coded expected images. Seeds are fixed; glossrt's own
renders are reproducible across loads (stable shape and emitter order, see
test_renders_are_identical_across_loads_and_processes), but the noise of Mitsuba's `path`
renders can still change between runs because Mitsuba's emitter order changes between loads,
which the 4.5-5 standard-error thresholds absorb (a false alarm has probability ~1e-5 per
check).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import ndimage

from glossrt import backend

backend.ensure()
import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

from glossrt import scenes  # noqa: E402
from glossrt.frame import CHANNELS, RADIANCE, Camera, Frame  # noqa: E402
from glossrt.render import Renderer  # noqa: E402
from glossrt.scenes import SceneSetup  # noqa: E402

W, H = 64, 48
GBUFFER = ("albedo_diffuse", "albedo_specular", "normal", "position", "depth", "roughness",
           "roughness_uv", "tangent", "distribution", "mesh_id", "motion")

# A small XML scene with the plugins the built-ins do not use: smooth plastic, rough plastic,
# smooth conductor, twosided, a point light and a constant environment. max_depth = 6 also
# exercises Russian roulette (from depth 5, as in Mitsuba).
XML_SCENE = """<scene version="3.0.0">
  <integrator type="path"><integer name="max_depth" value="6"/></integrator>
  <sensor type="perspective">
    <float name="fov" value="50"/>
    <transform name="to_world">
      <lookat origin="0, 1.3, 4.2" target="0, 0.4, 0" up="0, 1, 0"/>
    </transform>
    <film type="hdrfilm">
      <integer name="width" value="32"/><integer name="height" value="24"/>
    </film>
  </sensor>
  <emitter type="point">
    <point name="position" x="0.8" y="2.6" z="1.6"/>
    <rgb name="intensity" value="9, 8.5, 8"/>
  </emitter>
  <emitter type="constant"><rgb name="radiance" value="0.25, 0.3, 0.35"/></emitter>
  <shape type="rectangle" id="floor">
    <transform name="to_world"><rotate x="1" angle="-90"/><scale value="2.5"/></transform>
    <bsdf type="roughplastic">
      <float name="alpha" value="0.3"/>
      <rgb name="diffuse_reflectance" value="0.5, 0.45, 0.4"/>
    </bsdf>
  </shape>
  <shape type="rectangle" id="back">
    <transform name="to_world"><scale x="2.5" y="1.5"/><translate x="0" y="1.5" z="-2"/></transform>
    <bsdf type="plastic"><rgb name="diffuse_reflectance" value="0.2, 0.5, 0.3"/></bsdf>
  </shape>
  <shape type="sphere" id="mirror_ball">
    <point name="center" x="-0.8" y="0.5" z="-0.3"/><float name="radius" value="0.5"/>
    <bsdf type="conductor"><string name="material" value="Cu"/></bsdf>
  </shape>
  <shape type="sphere" id="rough_ball">
    <point name="center" x="0.6" y="0.45" z="0.2"/><float name="radius" value="0.45"/>
    <bsdf type="roughconductor">
      <string name="material" value="Al"/><float name="alpha" value="0.25"/>
    </bsdf>
  </shape>
  <shape type="rectangle" id="panel">
    <!-- seen from its back: only the twosided wrapper makes it reflect there -->
    <transform name="to_world">
      <scale value="0.45"/><rotate y="1" angle="160"/><translate x="1.5" y="0.9" z="-0.9"/>
    </transform>
    <bsdf type="twosided">
      <bsdf type="diffuse"><rgb name="reflectance" value="0.8, 0.3, 0.2"/></bsdf>
    </bsdf>
  </shape>
</scene>
"""


# -- helpers -----------------------------------------------------------------------------------


def _shift(a: np.ndarray, dy: int, dx: int, r: int) -> np.ndarray:
    """a[y + dy, x + dx] with edge padding (r >= |dy|, |dx|)."""
    p = np.pad(a, [(r, r), (r, r)] + [(0, 0)] * (a.ndim - 2), mode="edge")
    h, w = a.shape[:2]
    return p[r + dy:r + dy + h, r + dx:r + dx + w]


def interior_mask(frame: Frame, r: int = 2, cos_min: float = 0.3) -> np.ndarray:
    """Surface pixels whose (2r+1)^2 G-buffer neighbourhood has no geometric or material edge.

    Mitsuba's box filter averages radiance over the pixel (random positions) while glossrt
    samples the pixel centre; the two agree only where the image is smooth over a pixel. A
    pixel is kept when every neighbour: has the same mesh_id; has a normal within ~25 degrees;
    lies on the pixel's tangent plane within 1% of its depth (no depth step); has the same
    roughness and diffuse albedo (texture edges). Grazing views (cos < cos_min between normal
    and view direction) are dropped: there a pixel's footprint is stretched by 1/cos and the
    lighting varies non-linearly across it. Background and the image border are excluded."""
    mesh = frame.numpy("mesh_id")[..., 0]
    depth = frame.numpy("depth")[..., 0]
    n = frame.numpy("normal").astype(np.float64)
    p = frame.numpy("position").astype(np.float64)
    rough = frame.numpy("roughness")[..., 0]
    alb = frame.numpy("albedo_diffuse")
    hit = mesh > 0
    d = np.where(hit, depth, 1.0)
    ok = hit.copy()
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            ok &= _shift(mesh, dy, dx, r) == mesh
            ok &= np.sum(_shift(n, dy, dx, r) * n, -1) > 0.9
            ok &= np.abs(np.sum((_shift(p, dy, dx, r) - p) * n, -1)) < 0.01 * d
            ok &= np.abs(_shift(rough, dy, dx, r) - rough) <= 1e-3 * rough + 1e-6
            ok &= np.all(np.abs(_shift(alb, dy, dx, r) - alb) <= 1e-3, -1)
    v = frame.camera.position - p
    v /= np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)
    ok &= np.sum(v * n, -1) > cos_min
    ok[:r] = ok[-r:] = False
    ok[:, :r] = ok[:, -r:] = False
    return ok


def masked_blur(img: np.ndarray, mask: np.ndarray, sigma: float) -> np.ndarray:
    """Normalised Gaussian convolution of an H x W x C image over the pixels in ``mask``."""
    m = mask.astype(np.float64)
    den = ndimage.gaussian_filter(m, sigma, mode="constant")
    out = [ndimage.gaussian_filter(img[..., c] * m, sigma, mode="constant") for c in range(3)]
    return np.stack(out, -1) / np.maximum(den, 1e-12)[..., None]


def masked_blur_variance(var: np.ndarray, mask: np.ndarray, sigma: float) -> np.ndarray:
    """Variance of :func:`masked_blur` of independent pixels with variance ``var``:
    sum g^2 var / (sum g)^2, where g^2 of a unit 2D Gaussian of width sigma is a Gaussian of
    width sigma / sqrt(2) scaled by 1 / (4 pi sigma^2)."""
    m = mask.astype(np.float64)
    den = ndimage.gaussian_filter(m, sigma, mode="constant")
    s2 = sigma / math.sqrt(2.0)
    num = [ndimage.gaussian_filter(var[..., c] * m, s2, mode="constant") for c in range(3)]
    return np.stack(num, -1) / (4 * math.pi * sigma**2) / np.maximum(den, 1e-12)[..., None] ** 2


def batches(render_one, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel mean of ``k`` independent renders and the variance of that mean."""
    imgs = np.stack([np.asarray(render_one(s), dtype=np.float64) for s in range(k)])
    return imgs.mean(0), imgs.var(0, ddof=1) / k


def hits(frame: Frame) -> np.ndarray:
    return frame.numpy("mesh_id")[..., 0] > 0


def forward(cam) -> np.ndarray:
    f = cam.to_world[:3, 2]
    return f / np.linalg.norm(f)


def focal_px(cam) -> float:
    return (cam.resolution[0] / 2) / math.tan(math.radians(cam.fov) / 2)


def apply(m: np.ndarray, p: np.ndarray) -> np.ndarray:
    return p @ m[:3, :3].T + m[:3, 3]


def project_direction(cam, d: np.ndarray) -> np.ndarray:
    """Pixel coordinates of the direction ``d`` (a point at infinity) seen by ``cam``: the
    camera's rotation only."""
    m = cam.to_world.copy()
    m[:3, 3] = 0.0
    return Camera(m, cam.fov, cam.resolution).project(d)


# -- fixtures ----------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def xml_path(tmp_path_factory):
    path = tmp_path_factory.mktemp("xml") / "plugins.xml"
    path.write_text(XML_SCENE)
    return str(path)


@pytest.fixture(scope="module")
def cornell():
    return scenes.load("glossy-cornell", size=(W, H))


@pytest.fixture(scope="module")
def cornell_renderer(cornell):
    return Renderer(cornell)


@pytest.fixture(scope="module")
def cornell_frame0(cornell_renderer):
    return cornell_renderer.render(0)


@pytest.fixture(scope="module")
def cornell_ref0(cornell_renderer):
    return cornell_renderer.render_reference(0, spp=16)


# -- 1. separated radiance against Mitsuba's `path` ----------------------------------------------

# scene -> (size, component whose removal must be detected)
MITSUBA_CASES = {
    "glossy-cornell": ((W, H), "indirect_diffuse"),
    "roughness-map": ((W, H), "direct_specular"),
    "xml": ((W, H), "indirect_diffuse"),
}
BATCHES, BATCH_SPP = 4, 256  # 1024 spp per image, as 4 independent batches (for the variance)
ROUGH_MIN = 0.2


def _load_case(name, xml_path, size):
    return scenes.load(xml_path if name == "xml" else name, size=size)


@pytest.fixture(scope="module", params=sorted(MITSUBA_CASES))
def mitsuba_case(request, xml_path):
    name = request.param
    size, dropped = MITSUBA_CASES[name]
    setup = _load_case(name, xml_path, size)
    r = Renderer(setup)
    refs = [r.render_reference(0, spp=BATCH_SPP, seed=s) for s in range(BATCHES)]
    ours, ours_var = batches(lambda s: refs[s].numpy("color"), BATCHES)
    drop = np.mean([f.numpy(dropped) for f in refs], 0)
    theirs, theirs_var = batches(lambda s: r.render_mitsuba(0, spp=BATCH_SPP, seed=100 + s),
                                 BATCHES)
    rough = refs[0].numpy("roughness")[..., 0]
    # Near-mirror lobes (alpha < 0.2) reflect sub-pixel detail (minified reflections in the
    # sphere, sharp highlights), which a box filter averages and a pixel centre does not:
    # measured at 64x48, the alpha=0.05 sphere of glossy-cornell differs by ~17% between
    # the two, but agrees with Mitsuba within 1.5% once glossrt is supersampled 8x8 (see
    # test_near_mirror_pixels_match_mitsuba_when_supersampled). Here only wider lobes count.
    mask = interior_mask(refs[0]) & (rough >= ROUGH_MIN)
    return dict(name=name, setup=setup, refs=refs, ours=ours, ours_var=ours_var, theirs=theirs,
                theirs_var=theirs_var, mask=mask, drop=drop, dropped=dropped)


@pytest.mark.slow
def test_mitsuba_case_has_enough_interior_pixels(mitsuba_case):
    # the comparison must not become vacuous when scenes or the mask change
    assert mitsuba_case["mask"].sum() >= 150, mitsuba_case["mask"].sum()


def test_component_sum_matches_mitsuba_path_interior_mean(mitsuba_case):
    c = mitsuba_case
    m = c["mask"]
    n = m.sum()
    diff = c["ours"][m].mean(0) - c["theirs"][m].mean(0)
    # standard error of the difference of the two interior means (pixels are independent)
    se = np.sqrt(c["ours_var"][m].sum(0) + c["theirs_var"][m].sum(0)) / n
    z = diff / se
    # 4.5 sigma: a false alarm has probability ~7e-6 per channel; seeds are fixed anyway
    assert np.all(np.abs(z) < 4.5), (c["name"], diff, se, z)
    # and the same statistic detects a dropped component: the test has power
    z_drop = (diff - c["drop"][m].mean(0)) / se
    assert np.all(np.abs(z_drop) > 10), (c["name"], c["dropped"], z_drop)


def test_component_sum_matches_mitsuba_path_blurred(mitsuba_case):
    c = mitsuba_case
    m = c["mask"]
    sigma = 2.0  # ~25 pixels effective support: noise drops 5x, edges stay excluded
    ours, theirs = masked_blur(c["ours"], m, sigma), masked_blur(c["theirs"], m, sigma)
    se = np.sqrt(masked_blur_variance(c["ours_var"] + c["theirs_var"], m, sigma))
    err = np.abs(ours - theirs)[m]
    # 5 standard errors (over ~1000 pixels x 3 channels a 5-sigma outlier has probability
    # ~2e-3), plus 1% of the value for what pixel-centre vs box-filter sampling still leaves in
    # smooth regions (second-order term of the box average, h^2 f'' / 24), plus 1e-4 absolute
    # for float32 rounding where the variance is zero (constant emitters).
    tol = 5 * se[m] + 0.01 * np.abs(theirs[m]) + 1e-4
    bad = err > tol
    assert not bad.any(), (c["name"], bad.sum(), (err / np.maximum(theirs[m], 1e-6))[bad][:5])


@pytest.mark.slow
def test_near_mirror_pixels_match_mitsuba_when_supersampled():
    """Pixel-centre sampling differs from a box filter on near-mirror surfaces; rendering glossrt
    at 4x4 the resolution and box-downsampling it integrates the pixel like Mitsuba does, so the
    near-mirror pixels (alpha 0.05 gold sphere) can be compared too."""
    s, k, spp = 4, 4, 1024  # highlights of the light in the sphere are noisy: 4096 spp in all
    setup = scenes.load("glossy-cornell", size=(W, H))
    big = scenes.load("glossy-cornell", size=(W * s, H * s))
    r, rb = Renderer(setup), Renderer(big)

    def ours_one(seed):
        img = rb.render_reference(0, spp=spp // (s * s), seed=seed).numpy("color")
        return img.astype(np.float64).reshape(H, s, W, s, 3).mean((1, 3))

    ours, ours_var = batches(ours_one, k)
    theirs, theirs_var = batches(lambda i: r.render_mitsuba(0, spp=spp, seed=200 + i), k)
    centre = r.render_reference(0, spp=spp, seed=7)
    rough = centre.numpy("roughness")[..., 0]
    m = interior_mask(centre) & (rough < ROUGH_MIN)
    assert m.sum() >= 30, m.sum()
    n = m.sum()
    ref = theirs[m].mean(0)
    diff = ours[m].mean(0) - ref
    se = np.sqrt(ours_var[m].sum(0) + theirs_var[m].sum(0)) / n  # ~1.2% of the mean
    # 4.5 standard errors plus 3% for the 4x4 grid only approximating the box integral of
    # sub-pixel reflected detail (the residual measured with an 8x8 grid was 1.5%)
    tol = 4.5 * se + 0.03 * ref
    assert np.all(np.abs(diff) < tol), (diff / ref, se / ref)
    # pixel centres alone miss ~17% here: why test_component_sum_* leave these pixels out
    centre_diff = centre.numpy("color")[m].mean(0) - ref
    assert np.all(np.abs(centre_diff) > tol), (centre_diff / ref, tol / ref)


# -- 2. channel bookkeeping ----------------------------------------------------------------------


def _check_sum(frame: Frame, rtol: float) -> None:
    color = frame.numpy("color").astype(np.float64)
    total = sum(frame.numpy(name).astype(np.float64) for name in RADIANCE)
    scale = max(float(np.abs(color).max()), 1e-30)
    np.testing.assert_allclose(color, total, rtol=0, atol=rtol * scale)


def test_color_is_sum_of_components_1spp(cornell_frame0):
    # five float32 additions in the kernel: a few ulps of the largest value
    _check_sum(cornell_frame0, 1e-6)
    assert set(RADIANCE) | {"color"} | set(GBUFFER) == set(cornell_frame0.names)
    for name in cornell_frame0.names:
        assert cornell_frame0[name].shape == (H, W, len(CHANNELS[name]))


def test_color_is_sum_of_components_reference(cornell_ref0):
    # per-component sums over 16 samples, each rounded in float32: ~1e-6 relative
    _check_sum(cornell_ref0, 1e-5)
    assert cornell_ref0.meta["spp"] == 16 and cornell_ref0.meta["reference"] is True


def test_gbuffer_is_deterministic_and_radiance_is_not(cornell_renderer, cornell_frame0,
                                                      cornell_ref0):
    other = cornell_renderer.render(0, seed=12345)
    for name in GBUFFER:
        np.testing.assert_array_equal(other.numpy(name), cornell_frame0.numpy(name), err_msg=name)
        np.testing.assert_array_equal(cornell_ref0.numpy(name), cornell_frame0.numpy(name),
                                      err_msg=name)
    # 1 spp radiance with a different seed differs at most lit pixels
    a, b = cornell_frame0.numpy("color"), other.numpy("color")
    lit = hits(cornell_frame0) & (cornell_ref0.numpy("color").sum(-1) > 0.05)
    changed = np.any(a != b, -1)[lit].mean()
    assert changed > 0.5, changed
    # same seed: bit-identical
    again = cornell_renderer.render(0)
    np.testing.assert_array_equal(again.numpy("color"), a)


def test_max_depth_1_is_emission_only(cornell):
    f = Renderer(cornell, max_depth=1).render(0)
    for name in ("direct_diffuse", "direct_specular", "indirect_diffuse", "indirect_specular"):
        assert not np.any(f.numpy(name)), name
    em = f.numpy("emission")
    assert em.max() > 1.0  # the light is visible
    np.testing.assert_array_equal(f.numpy("color"), em)


def test_max_depth_2_has_no_indirect_light(cornell):
    r = Renderer(cornell, max_depth=2)
    for f in (r.render(1), r.render_reference(1, spp=8)):
        assert not np.any(f.numpy("indirect_diffuse"))
        assert not np.any(f.numpy("indirect_specular"))
        assert f.numpy("direct_diffuse").max() > 0
        assert f.numpy("direct_specular").max() > 0
    assert r.render(1).meta["max_depth"] == 2


def test_default_max_depth_has_indirect_light(cornell_ref0):
    assert cornell_ref0.meta["max_depth"] == 3
    assert cornell_ref0.numpy("indirect_diffuse").max() > 0
    assert cornell_ref0.numpy("indirect_specular").max() > 0


def test_lobes_are_attributed_to_the_primary_hit_material(cornell_ref0, cornell):
    mesh = cornell_ref0.numpy("mesh_id")[..., 0]
    sphere = mesh == cornell.shape_index["sphere"]  # conductor: specular lobe only
    box = mesh == cornell.shape_index["box"]  # rough plastic: both lobes
    walls = np.isin(mesh, [cornell.shape_index[s] for s in ("left", "right")])  # diffuse only
    for name in ("direct_diffuse", "indirect_diffuse"):
        assert not np.any(cornell_ref0.numpy(name)[sphere]), name
        assert cornell_ref0.numpy(name)[box].mean() > 0, name
    for name in ("direct_specular", "indirect_specular"):
        assert not np.any(cornell_ref0.numpy(name)[walls]), name
        assert cornell_ref0.numpy(name)[box].mean() > 0, name
        assert cornell_ref0.numpy(name)[sphere].mean() > 0, name
    assert not np.any(cornell_ref0.numpy("emission")[sphere | box | walls])


def test_render_averages_to_render_reference(cornell, cornell_renderer):
    """The 1 spp frames are unbiased estimates of the reference, component by component (same
    pixel-centre primary hits, so every pixel is comparable, edges included)."""
    n = 64
    frames = [cornell_renderer.render(1, seed=1000 + s) for s in range(n)]
    ref = [cornell_renderer.render_reference(1, spp=128, seed=s) for s in range(4)]
    for name in RADIANCE:
        ones = np.stack([f.numpy(name).astype(np.float64) for f in frames])
        refs = np.stack([f.numpy(name).astype(np.float64) for f in ref])
        a, va = ones.mean(0), ones.var(0, ddof=1) / n
        b, vb = refs.mean(0), refs.var(0, ddof=1) / len(ref)
        diff = a.mean((0, 1)) - b.mean((0, 1))
        se = np.sqrt(va.sum((0, 1)) + vb.sum((0, 1))) / (W * H)
        # 4.5 standard errors; zero-variance components (no emission variance) must match
        # to float rounding
        assert np.all(np.abs(diff) <= 4.5 * se + 1e-6 * np.abs(b).mean((0, 1))), (name, diff, se)


def _lobe_albedos(bsdf, cos_o: np.ndarray, n: int = 64) -> dict[str, np.ndarray]:
    """Per view cosine: each lobe's directional albedo integral f_lobe(wo, wi) cos dwi, by
    quadrature of Mitsuba's own ``eval`` restricted to that lobe (``BSDFContext.type_mask``)
    over n^2 stratified cosine-distributed directions (an isotropic BSDF: the view azimuth
    does not matter)."""
    k = np.arange(n * n)
    u = (np.tile(((k % n) + 0.5) / n, cos_o.size), np.tile(((k // n) + 0.5) / n, cos_o.size))
    wi = mi.warp.square_to_cosine_hemisphere(mi.Point2f(*u))
    c = np.repeat(cos_o, n * n)
    si = dr.zeros(mi.SurfaceInteraction3f, c.size)
    si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
    si.wi = mi.Vector3f(np.sqrt(np.maximum(1 - c * c, 0)), 0.0, c)
    si.uv = mi.Point2f(0.5, 0.5)
    out = {}
    for name, mask in (("diffuse", mi.BSDFFlags.DiffuseReflection),
                       ("specular", mi.BSDFFlags.GlossyReflection)):
        ctx = mi.BSDFContext()
        ctx.type_mask = int(mask)
        val = np.array(bsdf.eval(ctx, si, wi), np.float64)[0].reshape(cos_o.size, n * n)
        # cosine sampling: pdf cos / pi, and eval includes the cosine
        out[name] = (val * np.pi / np.array(wi.z).reshape(cos_o.size, n * n)).mean(-1)
    return out


def test_lobe_channels_are_each_lobes_own_integral():
    """roughplastic (diffuse + glossy lobes, one sampling mixture) inside a closed sphere that
    emits Le = 1 and reflects rho = 0.5 (diffuse): every direction brings the floor radiance
    Le directly and, to 0.5% (the floor hides a little of the sphere from itself), rho Le
    after one more bounce. So each lobe's channel is its own directional albedo A_lobe
    (quadrature of Mitsuba's eval of that lobe alone) times Le (direct_*) or rho Le
    (indirect_*). Splitting a sample by the lobe it came from (weight f / p_mix for the
    sampled lobe) put ~13% of indirect_specular into indirect_diffuse."""
    rho = 0.5
    t = mi.ScalarTransform4f
    scene = mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 14.0,
                   "to_world": t().look_at([0, 3, 0], [0, 0, 0], [0, 0, -1]),
                   "film": {"type": "hdrfilm", "width": 16, "height": 16}},
        "floor": {"type": "rectangle", "to_world": t().rotate([1, 0, 0], -90).scale(0.5),
                  "bsdf": {"type": "roughplastic", "alpha": 0.3, "distribution": "ggx",
                           "diffuse_reflectance": {"type": "rgb", "value": [0.6] * 3}}},
        "dome": {"type": "sphere", "radius": 10.0, "flip_normals": True,
                 "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [rho] * 3}},
                 "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [1.0] * 3}}},
    })
    setup = SceneSetup("dome", scene)
    f = Renderer(setup, max_depth=3, frozen=False).render_reference(0, spp=256)
    floor = f.numpy("mesh_id")[..., 0] == setup.shape_index["floor"]
    assert floor.all()
    view = f.camera.position - f.numpy("position")[floor].astype(np.float64)
    cos_o = view[:, 1] / np.linalg.norm(view, axis=-1)  # the floor's normal is +y
    bsdf = next(s for s in scene.shapes() if s.id() == "floor").bsdf()
    albedo = _lobe_albedos(bsdf, cos_o)
    for kind, scale, slack in (("direct", 1.0, 0.002), ("indirect", rho, 0.006)):
        for lobe in ("diffuse", "specular"):
            v = f.numpy(f"{kind}_{lobe}")[floor][:, 0].astype(np.float64)
            want = scale * albedo[lobe]
            se = v.std() / np.sqrt(v.size)  # per-pixel estimates are independent
            # the indirect light falls short of rho Le by the floor's occlusion (< 0.5%)
            err = v.mean() - want.mean()
            assert -(slack * want.mean() + 4.5 * se) < err < 0.002 * want.mean() + 4.5 * se, (
                kind, lobe, v.mean(), want.mean(), se)
    # power: the lobes differ by more than 10x, so a 13% leak is far beyond the tolerance
    assert albedo["diffuse"].mean() > 10 * albedo["specular"].mean()


# -- 3. motion vectors ---------------------------------------------------------------------------

T_MOTION = 5  # between frames 4 and 5 the camera sways ~0.6 degrees and the sphere slides 0.027


@pytest.fixture(scope="module")
def motion_frames(cornell_renderer):
    return cornell_renderer.render(T_MOTION - 1), cornell_renderer.render(T_MOTION)


def _expected_previous_points(setup, frame: Frame, t: int) -> tuple[np.ndarray, np.ndarray]:
    """(H, W, 3) world positions the pixels' surface points had at frame t - 1, and the
    (H, W) mask of hits."""
    p = frame.numpy("position").astype(np.float64)
    mesh = frame.numpy("mesh_id")[..., 0].astype(int)
    cur, prev = setup.object_transforms(t), setup.object_transforms(t - 1)
    out = p.copy()
    for m, mc in cur.items():
        sel = mesh == m
        out[sel] = apply(prev[m] @ np.linalg.inv(mc), p[sel])
    return out, mesh > 0


def _reprojected(frame: Frame) -> np.ndarray:
    ys, xs = np.mgrid[0:H, 0:W]
    return np.stack([xs + 0.5, ys + 0.5], -1) + frame.numpy("motion").astype(np.float64)


def test_motion_is_zero_on_the_first_frame(cornell_frame0):
    assert cornell_frame0.prev_camera == cornell_frame0.camera
    # re-projection through the same camera in float32: a few ulps of the pixel coordinate
    assert np.abs(cornell_frame0.numpy("motion")).max() < 1e-4


def test_motion_matches_previous_camera_projection(cornell, motion_frames):
    _, f = motion_frames
    prev_pts, hit = _expected_previous_points(cornell, f, T_MOTION)
    expected = cornell.camera(T_MOTION - 1).project(prev_pts)
    got = _reprojected(f)
    err = np.linalg.norm(got - expected, axis=-1)[hit]
    assert err.max() < 0.01, err.max()
    # the sphere moves relative to the static walls: its motion is not the camera's alone
    sphere = f.numpy("mesh_id")[..., 0] == cornell.shape_index["sphere"]
    static_only = cornell.camera(T_MOTION - 1).project(f.numpy("position").astype(np.float64))
    assert np.linalg.norm(got - static_only, axis=-1)[sphere].min() > 0.3
    # and the camera motion is not negligible either
    assert np.abs(f.numpy("motion")[hit & ~sphere]).max() > 0.1


def test_motion_of_background_is_camera_rotation_only(cornell, motion_frames):
    _, f = motion_frames
    bg = ~hits(f)
    assert bg.sum() > 10
    cur, prev = cornell.camera(T_MOTION), cornell.camera(T_MOTION - 1)
    # world direction of each background pixel's primary ray, seen from the previous camera
    # as a point at infinity (rotation only)
    ys, xs = np.nonzero(bg)
    cornell.set_frame(T_MOTION)
    uv = mi.Point2f((xs + 0.5) / W, (ys + 0.5) / H)
    ray, _ = cornell.sensor.sample_ray(0.0, 0.5, uv, mi.Point2f(0.5, 0.5))
    d = np.array(ray.d, dtype=np.float64).T
    far = project_direction(prev, d)
    got = _reprojected(f)[bg]
    assert np.linalg.norm(got - far, axis=-1).max() < 0.01
    assert cur != prev


def test_motion_hits_the_point_with_mitsubas_previous_sensor(cornell, motion_frames):
    """Independent of Camera.project: a ray shot by Mitsuba's sensor, posed at the previous
    frame, through the reprojected location passes through the point's previous position."""
    _, f = motion_frames
    prev_pts, hit = _expected_previous_points(cornell, f, T_MOTION)
    q = _reprojected(f)[hit]
    target = prev_pts[hit]
    cornell.set_frame(T_MOTION - 1)
    uv = mi.Point2f(q[:, 0] / W, q[:, 1] / H)
    ray, _ = cornell.sensor.sample_ray(0.0, 0.5, uv, mi.Point2f(0.5, 0.5))
    o = np.array(ray.o, dtype=np.float64).T
    d = np.array(ray.d, dtype=np.float64).T
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    dist = np.linalg.norm(np.cross(target - o, d), axis=-1)
    prev_cam = cornell.camera(T_MOTION - 1)
    z = (target - prev_cam.position) @ forward(prev_cam)
    err_px = dist / z * focal_px(prev_cam)
    assert err_px.max() < 0.01, err_px.max()


def test_motion_fetches_previous_position_on_moving_sphere(cornell, motion_frames):
    """Bilinearly sampling the previous frame's position channel at the reprojected location
    gives the point's previous position (interior of the moving sphere only)."""
    f_prev, f = motion_frames
    sid = cornell.shape_index["sphere"]
    prev_pts, _ = _expected_previous_points(cornell, f, T_MOTION)
    mesh = f.numpy("mesh_id")[..., 0]
    mesh_prev = f_prev.numpy("mesh_id")[..., 0]
    n = f.numpy("normal").astype(np.float64)
    p = f.numpy("position").astype(np.float64)
    v = f.camera.position - p
    v /= np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)
    sphere = mesh == sid
    # away from the silhouette: facing the camera, 3x3 neighbourhood on the sphere
    inner = sphere & (np.sum(n * v, -1) > 0.5) & (ndimage.minimum_filter(sphere.astype(int), 3) > 0)
    q = _reprojected(f)[inner] - 0.5  # continuous pixel-centre index coordinates (x, y)
    x0, y0 = np.floor(q[:, 0]).astype(int), np.floor(q[:, 1]).astype(int)
    taps_ok = np.ones(len(q), bool)
    for dy in (0, 1):
        for dx in (0, 1):
            yy, xx = np.clip(y0 + dy, 0, H - 1), np.clip(x0 + dx, 0, W - 1)
            taps_ok &= mesh_prev[yy, xx] == sid
    assert taps_ok.sum() >= 40, taps_ok.sum()
    pos_prev = f_prev.numpy("position").astype(np.float64)
    fetched = np.stack([ndimage.map_coordinates(pos_prev[..., c], [q[:, 1], q[:, 0]], order=1)
                        for c in range(3)], -1)[taps_ok]
    expected = prev_pts[inner][taps_ok]
    # Bilinear interpolation of the sphere's positions (radius R) between pixel centres misses
    # the surface by up to about h^2 / (4 R cos^3) (the sagitta over one pixel along both axes;
    # h = depth / focal is a pixel's world size and the footprint along the slope grows as
    # 1 / cos). Measured: at most half of that. A wrong object transform misses by the
    # per-frame slide (~0.027), above the largest tolerance used here (~0.009).
    err = np.linalg.norm(fetched - expected, axis=-1)
    cos = np.sum(n * v, -1)[inner][taps_ok]
    h = f.numpy("depth")[..., 0][inner][taps_ok] / focal_px(f.camera)
    tol = h**2 / (4 * 0.38 * cos**3)
    assert tol.max() < 0.01
    assert np.all(err < tol), (err / tol).max()
    # the sphere really moved between the frames (else this check would have no power)
    moved = np.linalg.norm(expected - p[inner][taps_ok], axis=-1)
    assert moved.min() > 0.02


def test_motion_of_a_jittered_frame_is_that_of_the_pixel_centre():
    """docs/FORMATS.md: the surface point seen through the pixel CENTRE was at centre + motion
    (what svgf's reprojection, taa and the spatio-temporal upsampler fetch). A jittered frame
    shades centre + jitter, but its motion must still be the centre's: reference from
    Mitsuba's own intersection of the pixel-centre rays, projected with the previous camera
    (NumPy). It was the jittered sample's motion (the motion field's gradient times the
    jitter, and another surface's motion at silhouettes)."""
    w, h, t, jitter = 32, 24, 2, (0.45, -0.4)
    setup = scenes.load("glossy-spheres", size=(w, h), orbit=40.0, frames=3)
    r = Renderer(setup)
    f = r.render(t, jitter=jitter)
    assert f.meta["jitter"] == list(jitter)
    setup.set_frame(t)
    ys, xs = np.mgrid[0:h, 0:w]
    centre = np.stack([xs + 0.5, ys + 0.5], -1).astype(np.float64)
    uv = mi.Point2f(mi.Float(centre[..., 0].ravel() / w), mi.Float(centre[..., 1].ravel() / h))
    ray, _ = setup.sensor.sample_ray(0.0, 0.5, uv, mi.Point2f(0.5, 0.5))
    si = setup.scene.ray_intersect(ray)
    hit = np.array(si.is_valid()).reshape(h, w)
    p = np.array(si.p, np.float64).T.reshape(h, w, 3)
    prev = setup.camera(t - 1)
    want = prev.project(p[hit]) - centre[hit]
    got = f.numpy("motion").astype(np.float64)[hit]
    assert hit.sum() > 100
    np.testing.assert_allclose(got, want, atol=0.01)
    # the check has power: the jittered samples' own motion differs from the centres'
    both = hits(f)[hit]  # the jittered sample hit something too
    own = prev.project(f.numpy("position").astype(np.float64)[hit]) - (centre[hit] + jitter)
    assert np.abs(own - want)[both].max() > 0.05
    # the unjittered frame agrees (its motion comes from its own pixel-centre hits)
    np.testing.assert_allclose(r.render(t).numpy("motion").astype(np.float64)[hit], want,
                               atol=0.01)


# -- 4. pixel subsets ----------------------------------------------------------------------------


def test_render_pixels_equals_full_render(cornell_renderer):
    full = cornell_renderer.render(2)
    idx = np.random.default_rng(3).choice(W * H, 257, replace=False)
    sub = cornell_renderer.render_pixels(2, idx)
    ys, xs = np.divmod(idx, W)
    assert set(sub) == set(full.names)
    for name, v in sub.items():
        np.testing.assert_array_equal(v, full.numpy(name)[ys, xs].reshape(len(idx), -1),
                                      err_msg=name)


@pytest.mark.slow
def test_render_pixels_launches_bounded_chunks_with_the_same_values(cornell_renderer,
                                                                    monkeypatch):
    """Many samples of many pixels go in launches of at most MAX_LANES lanes (adaptive
    re-sampling of every pixel at 1000 spp was killed for memory when it went in one), and
    the chunks give the values of a single launch."""
    import glossrt.render as render_mod

    idx = np.arange(0, W * H, 7)
    one = cornell_renderer.render_pixels(1, idx, spp=6)
    lanes = []
    trace = cornell_renderer.trace
    monkeypatch.setattr(render_mod, "MAX_LANES", 64)
    monkeypatch.setattr(cornell_renderer, "trace", lambda f, px, *a, **k: (
        lanes.append(dr.width(px)), trace(f, px, *a, **k))[1])
    chunked = cornell_renderer.render_pixels(1, idx, spp=6)
    assert len(lanes) == -(-idx.size // (64 // 6)) and max(lanes) <= 64
    assert set(one) == set(chunked)
    for k in one:
        np.testing.assert_allclose(chunked[k], one[k], rtol=1e-6, atol=1e-7, err_msg=k)


def test_render_pixels_rejects_out_of_range(cornell_renderer):
    with pytest.raises(ValueError):
        cornell_renderer.render_pixels(0, [W * H])


# -- 5. frozen kernels ---------------------------------------------------------------------------


def test_frozen_and_plain_renders_are_identical():
    # one SceneSetup for both: mesh_id numbering depends on the load (see test_scenes.py)
    setup = scenes.load("glossy-cornell", size=(W, H))
    frozen = Renderer(setup, frozen=True)
    plain = Renderer(setup, frozen=False)
    for t in range(3):  # moving camera and sphere: replays must see the new poses
        a, b = frozen.render(t), plain.render(t)
        assert a.names == b.names
        for name in a.names:
            np.testing.assert_array_equal(a.numpy(name), b.numpy(name), err_msg=f"{t} {name}")
        assert a.meta["nonfinite_samples"] == b.meta["nonfinite_samples"]
    # a replay after other frames still gives frame 0, not the last pose
    np.testing.assert_array_equal(frozen.render(0).numpy("color"), plain.render(0).numpy("color"))
    assert not np.array_equal(a.numpy("position"), plain.render(0).numpy("position"))


# -- 6. G-buffer sanity --------------------------------------------------------------------------


def test_gbuffer_geometry(cornell_renderer):
    f = cornell_renderer.render(3)
    hit = hits(f)
    assert 0 < hit.sum() < H * W  # there is background at the sides of the open box
    n = f.numpy("normal").astype(np.float64)
    p = f.numpy("position").astype(np.float64)
    np.testing.assert_allclose(np.linalg.norm(n[hit], axis=-1), 1.0, atol=1e-5)
    cam = f.camera
    assert cam == cornell_renderer.setup.camera(3)
    assert np.all(np.sum(n * (cam.position - p), -1)[hit] > 0)
    # background: mesh 0, depth +inf, zero normal / position / albedo / roughness
    assert np.all(np.isposinf(f.numpy("depth")[~hit]))
    for name in ("normal", "position", "albedo_diffuse", "albedo_specular", "roughness"):
        assert not np.any(f.numpy(name)[~hit]), name
    # mesh_id and position against Mitsuba's own intersection of the pixel-centre rays
    setup = cornell_renderer.setup
    setup.set_frame(3)
    ys, xs = np.mgrid[0:H, 0:W]
    uv = mi.Point2f(mi.Float((xs.ravel() + 0.5) / W), mi.Float((ys.ravel() + 0.5) / H))
    ray, _ = setup.sensor.sample_ray(0.0, 0.5, uv, mi.Point2f(0.5, 0.5))
    si = setup.scene.ray_intersect(ray)
    valid = np.array(si.is_valid()).reshape(H, W)
    np.testing.assert_array_equal(valid, hit)
    np.testing.assert_allclose(np.array(si.p).T.reshape(H, W, 3)[hit], p[hit], atol=1e-4)
    shape_of = np.array(dr.reinterpret_array(mi.UInt32, si.shape)).reshape(H, W)
    mesh = f.numpy("mesh_id")[..., 0]
    # mesh_id i is the i-th shape of setup.shapes (a load-independent order)
    assert sorted(setup.shapes, key=id) == sorted(setup.scene.shapes(), key=id)
    for i, shape in enumerate(setup.shapes, start=1):
        rid = int(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(shape))[0])
        np.testing.assert_array_equal(mesh[hit & (shape_of == rid)], i)
    assert setup.shape_index == {s.id(): i for i, s in enumerate(setup.shapes, 1) if s.id()}


def test_gbuffer_depth_is_camera_space_z(cornell_renderer):
    f = cornell_renderer.render(3)
    hit = hits(f)
    p = f.numpy("position").astype(np.float64)
    z = (p - f.camera.position) @ forward(f.camera)
    depth = f.numpy("depth")[..., 0].astype(np.float64)
    # float32 positions ~4 units from the camera: ~1e-6 relative
    np.testing.assert_allclose(depth[hit], z[hit], rtol=1e-5)
    # the primary hit is where the pixel centre projects
    ys, xs = np.nonzero(hit)
    proj = f.camera.project(p[hit])
    np.testing.assert_allclose(proj, np.stack([xs + 0.5, ys + 0.5], -1), atol=2e-3)


def test_gbuffer_roughness_cornell(cornell_frame0, cornell):
    mesh = cornell_frame0.numpy("mesh_id")[..., 0]
    rough = cornell_frame0.numpy("roughness")[..., 0]
    sphere, box = mesh == cornell.shape_index["sphere"], mesh == cornell.shape_index["box"]
    assert sphere.sum() > 50 and box.sum() > 50
    np.testing.assert_allclose(rough[sphere], 0.05, rtol=1e-6)
    np.testing.assert_allclose(rough[box], 0.3, rtol=1e-6)
    walls = (mesh > 0) & ~sphere & ~box
    np.testing.assert_array_equal(rough[walls], 1.0)
    # every shape is seen (ids 1..n; Mitsuba merges the id-less walls into one mesh)
    assert set(np.unique(mesh)) == {float(i) for i in range(len(cornell.shapes) + 1)}


def test_gbuffer_roughness_map_takes_texture_values():
    setup = scenes.load("roughness-map", size=(W, H))
    f = Renderer(setup).render(0)
    mesh = f.numpy("mesh_id")[..., 0]
    rough = f.numpy("roughness")[..., 0]
    for sid in ("floor", "wall"):
        vals = np.unique(rough[mesh == setup.shape_index[sid]])
        np.testing.assert_allclose(vals, [0.02, 0.5], rtol=1e-6, err_msg=sid)
    diffuse = np.isin(mesh, [setup.shape_index[s] for s in ("block_red", "block_blue", "ball")])
    assert diffuse.sum() > 20
    np.testing.assert_array_equal(rough[diffuse], 1.0)


def _conductor_f0(bsdf) -> np.ndarray:
    """Fresnel reflectance at normal incidence of a complex IOR eta + i k (exact)."""
    params = mi.traverse(bsdf)
    eta = np.array(params["eta.value"], dtype=np.float64).ravel()
    k = np.array(params["k.value"], dtype=np.float64).ravel()
    return ((eta - 1) ** 2 + k**2) / ((eta + 1) ** 2 + k**2)


def _mitsuba_albedo(bsdf, cos_o: np.ndarray, n_samples: int) -> np.ndarray:
    """Directional albedo of a Mitsuba BSDF by Monte Carlo: mean of bsdf.sample's weight
    (f cos / pdf), stratified over n_samples per direction."""
    m = len(cos_o)
    cos = np.repeat(np.clip(cos_o, 1e-4, 1.0), n_samples)
    sin = np.sqrt(1 - cos**2)
    si = dr.zeros(mi.SurfaceInteraction3f, m * n_samples)
    si.wi = mi.Vector3f(mi.Float(sin), 0.0, mi.Float(cos))
    si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
    side = int(math.sqrt(n_samples))
    j = np.tile(np.arange(n_samples), m)
    rng = np.random.default_rng(0)
    u = ((j % side) + rng.random(j.size)) / side
    v = ((j // side) + rng.random(j.size)) / side
    _, weight = bsdf.sample(mi.BSDFContext(), si, mi.Float(rng.random(j.size)),
                            mi.Point2f(mi.Float(u), mi.Float(v)))
    w = np.array(weight, dtype=np.float64).T.reshape(m, n_samples, 3)
    return w.mean(1)


def test_gbuffer_specular_albedo_of_gold_sphere(cornell_frame0, cornell):
    f = cornell_frame0
    sphere = f.numpy("mesh_id")[..., 0] == cornell.shape_index["sphere"]
    n = f.numpy("normal").astype(np.float64)[sphere]
    p = f.numpy("position").astype(np.float64)[sphere]
    v = f.camera.position - p
    cos_o = np.sum(n * v, -1) / np.linalg.norm(v, axis=-1)
    alb = f.numpy("albedo_specular").astype(np.float64)[sphere]
    shape = next(s for s in cornell.scene.shapes() if s.id() == "sphere")
    # Against Mitsuba's own roughconductor (GGX, alpha 0.05, gold) and its exact conductor
    # Fresnel term: the G-buffer evaluates that term at the lobe's effective angle
    # (glossrt.brdf.fresnel), measured within 0.0037 for cos > 0.8 and 0.0057 for cos > 0.3
    # (Schlick's split with the same F0, used before: 0.006 and 0.038, growing towards grazing
    # in the blue channel). The MC error (4096 stratified samples) is ~1e-3 there. A wrong
    # F0, alpha, distribution or view angle shifts E by far more (F0 alone: 0.3 to 0.97).
    for cos_min, atol in ((0.3, 0.008), (0.8, 0.005)):
        sel = cos_o > cos_min
        assert sel.sum() > 40
        mc = _mitsuba_albedo(shape.bsdf(), cos_o[sel], 4096)
        np.testing.assert_allclose(alb[sel], mc, atol=atol, err_msg=str(cos_min))
    # the diffuse albedo of a pure conductor is 0
    assert not np.any(f.numpy("albedo_diffuse")[sphere])


def test_gbuffer_diffuse_albedo_of_walls(cornell_frame0, cornell):
    mesh = cornell_frame0.numpy("mesh_id")[..., 0]
    alb = cornell_frame0.numpy("albedo_diffuse")
    np.testing.assert_allclose(alb[mesh == cornell.shape_index["left"]][0], (0.63, 0.065, 0.05),
                               rtol=1e-5)
    np.testing.assert_allclose(alb[mesh == cornell.shape_index["right"]][0], (0.14, 0.45, 0.09),
                               rtol=1e-5)
    spec = cornell_frame0.numpy("albedo_specular")
    assert not np.any(spec[mesh == cornell.shape_index["left"]])  # purely diffuse


# -- 7. NaN / Inf policy -------------------------------------------------------------------------


def test_frames_report_nonfinite_samples(cornell_frame0, cornell_ref0):
    for f in (cornell_frame0, cornell_ref0):
        bad = f.meta["nonfinite_samples"]
        assert isinstance(bad, int) and bad >= 0
        for name in RADIANCE + ("color",):
            assert np.all(np.isfinite(f.numpy(name))), name
        counts = f.nonfinite_counts()
        assert all(counts.get(name, 0) == 0 for name in RADIANCE + ("color",))


def test_nonfinite_samples_are_replaced_and_counted():
    """An environment with infinite radiance makes every background sample infinite: the
    renderer must write 0 there and count them instead of writing Inf/NaN."""
    inf = float("inf")
    scene = mi.load_dict({
        "type": "scene",
        "sensor": {
            "type": "perspective", "fov": 40.0,
            "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 4], target=[0, 0, 0],
                                                       up=[0, 1, 0]),
            "film": {"type": "hdrfilm", "width": 16, "height": 12},
        },
        "ball": {"type": "sphere", "radius": 0.5, "bsdf": {"type": "diffuse"}},
        "sky": {"type": "constant", "radiance": {"type": "rgb", "value": [inf, inf, inf]}},
    })
    setup = SceneSetup("inf-sky", scene)
    r = Renderer(setup)
    f = r.render(0)
    bg = ~hits(f)
    assert bg.sum() > 0
    for name in RADIANCE + ("color",):
        assert np.all(np.isfinite(f.numpy(name))), name
    assert not np.any(f.numpy("emission")[bg])
    # every background pixel had 3 non-finite emission values at least
    assert f.meta["nonfinite_samples"] >= 3 * bg.sum()
    ref = r.render_reference(0, spp=4)
    assert ref.meta["nonfinite_samples"] >= 4 * 3 * bg.sum()
    for name in RADIANCE + ("color",):
        assert np.all(np.isfinite(ref.numpy(name))), name


# -- 8. reproducible emitter sampling ------------------------------------------------------------

REPRO_SIZE = (32, 24)
# prints md5 digests of every radiance channel of roughness-map's frame 0 (another process)
_REPRO_SCRIPT = """
import hashlib, json, sys
import numpy as np
from glossrt import scenes
from glossrt.render import Renderer
f = Renderer(scenes.load("roughness-map", size=(32, 24))).render(0)
print(json.dumps({n: hashlib.md5(np.ascontiguousarray(f.numpy(n)).tobytes()).hexdigest()
                  for n in sys.argv[1:]}))
"""


def _digests(frame: Frame, names) -> dict[str, str]:
    import hashlib

    return {n: hashlib.md5(np.ascontiguousarray(frame.numpy(n)).tobytes()).hexdigest()
            for n in names}


def _emitter_order(setup) -> tuple:
    """Mitsuba's own emitter order, by owning shape (area lights) or id."""
    return tuple(e.get_shape().id() if e.get_shape() is not None else e.id()
                 for e in setup.scene.emitters())


def test_renders_are_identical_across_loads_and_processes():
    """Mitsuba orders scene.emitters() differently from load to load (roughness-map: two area
    lights and a constant sky); glossrt's NEE picks emitters in a load-independent order, so a
    seed gives bit-identical radiance on every load, frozen or not, and in another process."""
    import json
    import subprocess
    import sys

    names = RADIANCE + ("color",)
    first = None
    orders = set()
    rendered = 0
    # Mitsuba's order is random (measured: the two area lights swap in about 1 load in 4).
    # Render the first two loads (frozen and not) and then every load whose order is new,
    # until the two orders have both been rendered: that is what gives the check its power.
    for k in range(40):
        setup = scenes.load("roughness-map", size=REPRO_SIZE)
        order = _emitter_order(setup)
        if rendered >= 2 and order in orders:
            continue
        orders.add(order)
        f = Renderer(setup, frozen=rendered % 2 == 0).render(0)
        rendered += 1
        if first is None:
            first = f
            assert np.any(f.numpy("indirect_diffuse") > 0) and np.any(f.numpy("direct_diffuse") > 0)
            continue
        for n in names:
            np.testing.assert_array_equal(f.numpy(n), first.numpy(n), err_msg=f"load {k}: {n}")
        if len(orders) >= 2 and rendered >= 2:
            break
    # the measured side: Mitsuba's emitter order did change between the loads compared
    # (P(no change in 40 loads) ~ 1e-5)
    assert len(orders) >= 2, orders
    out = subprocess.run([sys.executable, "-c", _REPRO_SCRIPT, *names], capture_output=True,
                         text=True, timeout=300, check=True)
    assert json.loads(out.stdout.strip().splitlines()[-1]) == _digests(first, names)


def test_emitter_table_order_and_pmf():
    """The table lists area lights in stable shape order, then the rest; each entry carries
    Mitsuba's selection probability of that emitter; the CDF ends at exactly 1."""
    from glossrt.render.pathtracer import EmitterTable

    for _ in range(3):
        setup = scenes.load("roughness-map", size=REPRO_SIZE)
        scene = setup.scene
        t = EmitterTable(scene)
        assert len(t) == 3
        rid = np.array(dr.reinterpret_array(mi.UInt32, t.emitter))
        by_rid = {int(dr.reinterpret_array(mi.UInt32, mi.EmitterPtr(e))[0]): (i, e)
                  for i, e in enumerate(scene.emitters())}
        owners = [by_rid[r][1].get_shape() for r in rid]
        assert [s.id() if s is not None else None for s in owners] == \
            ["strip_light", "top_light", None]  # stable_shapes order: alphabetical ids
        assert by_rid[rid[2]][1].id() == "sky"
        mitsuba_pmf = [float(scene.pdf_emitter(by_rid[r][0])[0]) for r in rid]
        np.testing.assert_array_equal(np.array(t.pmf), np.float32(mitsuba_pmf))
        np.testing.assert_allclose(np.array(t.cdf), [1 / 3, 2 / 3, 1.0], rtol=1e-6)
        assert np.array(t.cdf)[-1] == 1.0


# A small room lit by two area lights and an environment with unequal ``sampling_weight``s
# (Mitsuba then samples emitters from a discrete distribution instead of uniformly).
SW_WEIGHTS = {"lamp_big": 4.0, "lamp_small": 0.5, "sky": 1.0}


def _sampling_weight_scene(size=(48, 36)) -> SceneSetup:
    T = mi.ScalarTransform4f
    area = lambda radiance, w: {"type": "area", "sampling_weight": w,  # noqa: E731
                                "radiance": {"type": "rgb", "value": radiance}}
    scene = mi.load_dict({
        "type": "scene",
        "sensor": {
            "type": "perspective", "fov": 50.0,
            "to_world": T().look_at(origin=[0, 1.2, 3.6], target=[0, 0.5, 0], up=[0, 1, 0]),
            "film": {"type": "hdrfilm", "width": size[0], "height": size[1]},
        },
        "floor": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(2.5),
                  "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb",
                                                              "value": [0.6, 0.55, 0.5]}}},
        "back": {"type": "rectangle",
                 "to_world": T().translate([0, 1.5, -1.5]).scale([2.5, 1.5, 1]),
                 "bsdf": {"type": "roughplastic", "alpha": 0.3,
                          "diffuse_reflectance": {"type": "rgb", "value": [0.3, 0.5, 0.4]}}},
        "ball": {"type": "sphere", "center": [0.3, 0.5, -0.2], "radius": 0.5,
                 "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb",
                                                             "value": [0.7, 0.3, 0.2]}}},
        "lamp_big": {"type": "rectangle",
                     "to_world": T().translate([-0.8, 2.4, 0.3]).rotate([1, 0, 0], 90)
                     .scale(0.6),
                     "emitter": area([3.0, 3.0, 2.8], SW_WEIGHTS["lamp_big"])},
        "lamp_small": {"type": "rectangle",
                       "to_world": T().translate([1.2, 1.6, 0.8]).rotate([0, 1, 0], -60)
                       .scale(0.2),
                       "emitter": area([20.0, 16.0, 12.0], SW_WEIGHTS["lamp_small"])},
        "sky": {"type": "constant", "sampling_weight": SW_WEIGHTS["sky"],
                "radiance": {"type": "rgb", "value": [0.15, 0.2, 0.3]}},
    })
    return SceneSetup("sampling-weight", scene)


def _owner(e) -> str:
    return e.get_shape().id() if e.get_shape() is not None else e.id()


def test_emitter_sampling_matches_mitsuba_with_sampling_weights():
    """At surface points of a scene with unequal emitter sampling_weights, glossrt's
    sample_emitter_direction picks emitters with Mitsuba's probabilities, its pdf is the one
    ``scene.pdf_emitter_direction`` gives (the MIS pdf of the path tracer), and its weights
    have the expectation of ``scene.sample_emitter_direction``'s."""
    from glossrt.render.pathtracer import EmitterTable, PixelSampler, sample_emitter_direction

    setup = _sampling_weight_scene(size=(12, 9))
    scene = setup.scene
    table = EmitterTable(scene)
    # primary hits through the pixel centres, each repeated m times
    w, h = setup.size
    m = 4096
    pix = dr.arange(mi.UInt32, w * h)
    pos = mi.Point2f((mi.Float(pix % w) + 0.5) / w, (mi.Float(pix // w) + 0.5) / h)
    ray, _ = setup.sensor.sample_ray(0.0, 0.5, pos, mi.Point2f(0.5))
    si0 = scene.ray_intersect(ray)
    valid = np.array(si0.is_valid())
    assert valid.sum() >= 60
    lane = dr.arange(mi.UInt32, w * h * m)
    ray_m = dr.gather(mi.Ray3f, ray, lane // m)
    si = scene.ray_intersect(ray_m)
    sampler = PixelSampler(lane, mi.UInt32(17))
    ds, spec = sample_emitter_direction(scene, table, si, sampler.next_2d(), si.is_valid())
    ds_m, spec_m = scene.sample_emitter_direction(si, sampler.next_2d(), True, si.is_valid())

    # selection frequencies (every valid lane picks an emitter) against w_i / sum(w)
    total = sum(SW_WEIGHTS.values())
    picked = np.array(dr.reinterpret_array(mi.UInt32, ds.emitter))
    ok = np.repeat(valid, m)
    n = ok.sum()
    for e in scene.emitters():
        p = SW_WEIGHTS[_owner(e)] / total
        rid = int(dr.reinterpret_array(mi.UInt32, mi.EmitterPtr(e))[0])
        freq = np.mean(picked[ok] == rid)
        assert abs(freq - p) < 5 * math.sqrt(p * (1 - p) / n), (_owner(e), freq, p)
    assert np.all(picked[~ok] == 0)

    # the pdf of the technique is Mitsuba's MIS pdf, where a sample contributes (Mitsuba's
    # area lights return a pdf but no radiance for points behind them, and pdf_direction 0)
    pdf = np.array(ds.pdf)
    pdf_m = np.array(scene.pdf_emitter_direction(si, ds, ds.pdf > 0))
    lit = (pdf > 0) & np.any(np.array(spec) > 0, axis=0)
    assert lit.sum() > n // 4
    np.testing.assert_allclose(pdf[lit], pdf_m[lit], rtol=1e-4)

    # per pixel: mean weight of both techniques (same integral) within 5 standard errors
    a = np.array(spec).T.reshape(w * h, m, 3)[valid].astype(np.float64)
    b = np.array(spec_m).T.reshape(w * h, m, 3)[valid].astype(np.float64)
    assert np.all(np.isfinite(a))
    se = np.sqrt(a.var(1) / m + b.var(1) / m)
    z = (a.mean(1) - b.mean(1)) / np.maximum(se, 1e-12)
    assert np.all(np.abs(z) < 5), np.abs(z).max()
    # power: ignoring sampling_weight (uniform choice) would be caught by the frequencies
    assert abs(1 / 3 - SW_WEIGHTS["lamp_big"] / total) > 100 / math.sqrt(n)


@pytest.mark.slow
def test_sampling_weight_scene_matches_mitsuba_path():
    """Whole-image check as in test_component_sum_matches_mitsuba_path_interior_mean, on a
    scene where Mitsuba samples emitters by sampling_weight."""
    setup = _sampling_weight_scene()
    r = Renderer(setup)
    refs = [r.render_reference(0, spp=BATCH_SPP, seed=s) for s in range(BATCHES)]
    ours, ours_var = batches(lambda s: refs[s].numpy("color"), BATCHES)
    theirs, theirs_var = batches(lambda s: r.render_mitsuba(0, spp=BATCH_SPP, seed=100 + s),
                                 BATCHES)
    rough = refs[0].numpy("roughness")[..., 0]
    m = interior_mask(refs[0]) & (rough >= ROUGH_MIN)  # (diffuse surfaces have roughness 1)
    n = m.sum()
    assert n >= 150, n
    diff = ours[m].mean(0) - theirs[m].mean(0)
    se = np.sqrt(ours_var[m].sum(0) + theirs_var[m].sum(0)) / n
    assert np.all(np.abs(diff / se) < 4.5), (diff, se)
    drop = np.mean([f.numpy("direct_diffuse") for f in refs], 0)
    assert np.all(np.abs((diff - drop[m].mean(0)) / se) > 10)


def test_scene_without_emitters_renders_black():
    from glossrt.render.pathtracer import EmitterTable

    scene = mi.load_dict({
        "type": "scene",
        "sensor": {
            "type": "perspective", "fov": 40.0,
            "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 4], target=[0, 0, 0],
                                                       up=[0, 1, 0]),
            "film": {"type": "hdrfilm", "width": 16, "height": 12},
        },
        "ball": {"type": "sphere", "radius": 0.5, "bsdf": {"type": "diffuse"}},
    })
    assert len(EmitterTable(scene)) == 0
    r = Renderer(SceneSetup("dark", scene))
    for f in (r.render(0), r.render_reference(0, spp=4)):
        assert f.meta["nonfinite_samples"] == 0
        assert hits(f).sum() > 0
        for name in RADIANCE + ("color",):
            assert not np.any(f.numpy(name)), name


def test_frozen_trace_is_not_shared_between_scenes():
    """Each Renderer records its own frozen trace: a module-wide one replayed a recording made
    with another scene object of the same layout (wrong G-buffers, now and then a segfault
    once that scene was freed; reproduced in 1 of 6 tries then). The first scene is rendered
    (recorded, then replayed); a second load of the same scene with other wall colours must
    then render frozen exactly as traced, on a first call and on replays. This checks the
    outcome, not the cause: the old identity check (``second._trace_frozen is not
    first._trace_frozen``) held by construction and could not fail, and with one module-wide
    frozen function patched back in, this test and the old repro (coarse polygon-light
    scenes, first one freed) passed 6 of 6 on 2026-12-02 (Dr.Jit re-records for the other
    scene here), so a shared recording is no longer shown to go wrong."""
    import gc

    first = Renderer(scenes.load("glossy-cornell", size=(16, 12)))
    first.render(0)
    first.render(1)  # a replay
    second_setup = scenes.load("glossy-cornell", size=(16, 12))
    params = mi.traverse(second_setup.scene)
    for key in ("left.bsdf.reflectance.value", "right.bsdf.reflectance.value"):
        params[key] = mi.Color3f(0.1, 0.9, 0.3)
    params.update()
    second = Renderer(second_setup)
    del first
    gc.collect()
    traced = Renderer(second_setup, frozen=False)
    for t in (0, 1, 0):
        a, b = second.render(t), traced.render(t)
        for name in ("albedo_diffuse", "normal", "position", "color"):
            np.testing.assert_array_equal(a.numpy(name), b.numpy(name), err_msg=f"{t} {name}")
    # the walls' new colour is in the G-buffer (the two scenes really differ)
    alb = b.numpy("albedo_diffuse")
    assert np.any(np.all(np.isclose(alb, (0.1, 0.9, 0.3), atol=1e-6), axis=-1))
