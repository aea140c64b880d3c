"""The ``normal-mapped`` built-in scene, its procedural normal map, and the G-buffer normal of
Mitsuba ``normalmap`` BSDFs (checked against Mitsuba's own BSDF evaluation)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from glossrt import backend

backend.ensure()
import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

from glossrt import scenes  # noqa: E402
from glossrt.brdf.fresnel import split_sum  # noqa: E402
from glossrt.errors import GlossrtError  # noqa: E402
from glossrt.render import Renderer  # noqa: E402
from glossrt.render.materials import (  # noqa: E402
    NORMAL_MAP,
    NORMAL_MAP_NONE,
    NORMAL_MAP_TWOSIDED,
    describe_bsdf,
)
from glossrt.scenes import library as L  # noqa: E402
from glossrt.scenes.normalmap import procedural_normal_map  # noqa: E402

SIZE = (64, 36)
T = mi.ScalarTransform4f


@pytest.fixture(scope="module")
def setup():
    return scenes.load("normal-mapped", size=SIZE)


@pytest.fixture(scope="module")
def renderer(setup):
    return Renderer(setup)


@pytest.fixture(scope="module")
def frame0(renderer):
    return renderer.render(0)


def _vec(a: np.ndarray) -> mi.Vector3f:
    a = np.asarray(a, np.float32)
    return mi.Vector3f(a[:, 0], a[:, 1], a[:, 2])


def _np(v) -> np.ndarray:
    return np.array(v, dtype=np.float64).T.reshape(-1, 3)


def _primary_hits(setup, pixels: np.ndarray, frame: int = 0):
    """Mitsuba's own intersection of the primary rays through the centres of ``pixels``
    (indices y*W + x) of ``frame``: (ray, si)."""
    setup.set_frame(frame)
    w, h = setup.size
    x = (pixels % w + 0.5) / w
    y = (pixels // w + 0.5) / h
    ray, _ = setup.sensor.sample_ray(0.0, 0.5, mi.Point2f(x, y), mi.Point2f(0.5, 0.5))
    si = setup.scene.ray_intersect(ray)
    return ray, si


def _flat_conductor_eval(alpha: float, n_world: np.ndarray, wi: np.ndarray,
                         wo: np.ndarray) -> np.ndarray:
    """Mitsuba's plain GGX aluminium ``roughconductor`` (no normal map) evaluated at world
    directions ``wi``, ``wo`` with its shading normal set to ``n_world`` (N, 3 each)."""
    cond = mi.load_dict({"type": "roughconductor", "distribution": "ggx", "material": "Al",
                         "alpha": alpha})
    si = dr.zeros(mi.SurfaceInteraction3f, len(wi))
    si.sh_frame = mi.Frame3f(_vec(n_world))
    si.n = si.sh_frame.n
    si.wi = si.to_local(_vec(wi))
    return _np(cond.eval(mi.BSDFContext(), si, si.to_local(_vec(wo))))


def _shadow_terminator(n_local: np.ndarray, wo_local: np.ndarray) -> np.ndarray:
    """The factor Mitsuba 3.9's ``normalmap`` multiplies its nested BSDF by (its default
    ``use_shadowing_function``; Estevez et al. 2019, ``src/bsdfs/normalmap_helpers.h``):
    ``2 / (1 + sqrt(1 + a2 tan^2(wo)))``, ``a2 = min(tan^2(n) / 8, 1)``, both angles to the
    unperturbed shading normal."""
    def tan2(v):
        z2 = v[:, 2] ** 2
        return np.maximum(1.0 - z2, 0.0) / z2

    a2 = np.minimum(0.125 * tan2(n_local), 1.0)
    return 2.0 / (1.0 + np.sqrt(1.0 + a2 * tan2(wo_local)))


def _directions_around(d: np.ndarray, spread: float, k: int, rng) -> np.ndarray:
    """``k`` unit directions per row of ``d`` (N, 3), tilted off ``d`` by up to ``spread``
    radians (the first one is ``d`` itself): shape (N * k, 3)."""
    out = np.repeat(d, k, 0) + rng.normal(0.0, spread / 2, (len(d) * k, 3))
    out[::k] = d
    return out / np.linalg.norm(out, axis=-1, keepdims=True)


def _check_normal_against_bsdf(setup, frame, shape_ids, alpha_of, rng, index: int = 0) -> int:
    """For pixels of ``shape_ids``: Mitsuba's BSDF at the primary hit (normal map included)
    equals the plain conductor oriented along the G-buffer normal, at the mirror direction
    about that normal and around it (Mitsuba's shadow-terminator factor included). ``index``:
    the frame's number. Returns the number of (pixel, direction) pairs checked.
    The same comparison with the unperturbed shading normal must fail (the test's power)."""
    mesh = frame.numpy("mesh_id")[..., 0].ravel()
    normal = frame.numpy("normal").reshape(-1, 3).astype(np.float64)
    total = 0
    for sid in shape_ids:
        pixels = np.flatnonzero(mesh == setup.shape_index[sid])
        assert pixels.size >= 10, sid
        ray, si = _primary_hits(setup, pixels.astype(np.uint32), index)
        np.testing.assert_allclose(_np(si.p), frame.numpy("position").reshape(-1, 3)[pixels],
                                   atol=1e-4)
        wi = -_np(ray.d)
        n_gb = normal[pixels]
        n_sh = _np(si.sh_frame.n)
        n_sh *= np.sign(np.sum(n_sh * wi, -1, keepdims=True))  # the camera's side
        # normalmap's flip_invalid_normals: the normal it uses always faces wi
        assert np.all(np.sum(wi * n_gb, -1) > 0), sid
        k = 6
        for n_test, expect_match in ((n_gb, True), (n_sh, False)):
            mirror = 2.0 * np.sum(wi * n_test, -1, keepdims=True) * n_test - wi
            wo = _directions_around(mirror, 2.0 * alpha_of[sid], k, rng)
            wi_k, n_k, sh_k = (np.repeat(a, k, 0) for a in (wi, n_test, n_sh))
            idx = np.repeat(np.arange(pixels.size), k)
            # Mitsuba's normalmap also needs wo above the unperturbed surface
            ok = ((np.sum(wo * sh_k, -1) > 0.02) & (np.sum(wo * n_k, -1) > 0.02)
                  & (np.sum(wi_k * n_k, -1) > 0.02))
            assert ok.sum() >= 0.3 * ok.size, sid
            si_k = dr.gather(mi.SurfaceInteraction3f, si, mi.UInt32(idx[ok]))
            bsdf = si_k.bsdf()
            f_map = _np(bsdf.eval(mi.BSDFContext(), si_k, si_k.to_local(_vec(wo[ok]))))
            f_ref = _flat_conductor_eval(alpha_of[sid], n_k[ok], wi_k[ok], wo[ok])
            f_ref *= _shadow_terminator(_np(si_k.to_local(_vec(n_k[ok]))),
                                        _np(si_k.to_local(_vec(wo[ok]))))[:, None]
            rel = np.abs(f_map - f_ref).max(-1) / np.maximum(f_ref.max(-1), 1e-3)
            if expect_match:
                # float32 texture coordinates (tens of tiles of 1024 texels) make a few
                # normals differ by ~1e-3 between kernels, enough at alpha 0.05
                q = np.quantile(rel, [0.5, 0.9, 1.0])
                assert q[0] < 1e-4 and q[1] < 1e-3 and q[2] < 0.1, (sid, q)
                # the mirror direction is the lobe's peak: far above the lobe's mean value
                peak = (np.arange(ok.size) % k == 0)[ok]
                assert np.median(f_map[peak].mean(-1)) > 5.0, sid
                total += int(ok.sum())
            else:
                assert np.median(rel) > 0.5, (sid, np.median(rel))
    return total


# -- (a) the G-buffer normal is the one Mitsuba's normalmap BSDF uses ---------------------------


def test_gbuffer_normal_is_mitsubas_normal_mapped_normal(setup, frame0):
    rng = np.random.default_rng(1)
    alphas = {"floor": L.NORMAL_MAPPED_ALPHA_FLOOR, "sphere": L.NORMAL_MAPPED_ALPHA_SPHERE}
    assert _check_normal_against_bsdf(setup, frame0, ("floor", "sphere"), alphas, rng) > 500
    n = frame0.numpy("normal")
    np.testing.assert_allclose(np.linalg.norm(n[frame0.numpy("mesh_id")[..., 0] > 0], axis=-1),
                               1.0, atol=1e-5)


def test_gbuffer_normal_is_mitsubas_sh_normal_aov(setup, frame0):
    """Mitsuba's ``aov`` integrator reports ``BSDF::sh_frame(si).n`` as ``sh_normal``: the
    normal-mapped frame for a ``normalmap`` BSDF (C++ only, not bound in Python)."""
    mesh = frame0.numpy("mesh_id")[..., 0].ravel()
    pixels = np.flatnonzero(np.isin(mesh, [setup.shape_index[s] for s in ("floor", "sphere")]))
    ray, si = _primary_hits(setup, pixels.astype(np.uint32))
    aov = mi.load_dict({"type": "aov", "aovs": "sn:sh_normal"})
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(0, pixels.size)
    _, _, channels = aov.sample(setup.scene, sampler, mi.RayDifferential3f(ray), None, True)
    want = np.stack([np.array(c, np.float64) for c in channels], -1)
    got = frame0.numpy("normal").reshape(-1, 3)[pixels]
    err = np.abs(got - want).max(-1)
    # float32 texture coordinates (34 tiles of 1024 texels) differ by ulps between kernels
    assert np.median(err) < 1e-5 and err.max() < 3e-3, np.quantile(err, [0.5, 1.0])
    # the unperturbed normal is far from it
    assert np.median(np.abs(_np(si.sh_frame.n) - want).max(-1)) > 0.05


def test_gbuffer_normal_on_a_later_frame(setup, renderer):
    # the camera has moved: the normal is still the one Mitsuba's BSDF uses there
    f = renderer.render(8)
    rng = np.random.default_rng(2)
    alphas = {"floor": L.NORMAL_MAPPED_ALPHA_FLOOR}
    assert _check_normal_against_bsdf(setup, f, ("floor",), alphas, rng, 8) > 300


def _tilted_panel_scene(bsdf: dict, back: bool) -> dict:
    """A panel (rectangle) with ``bsdf`` seen from its front or back, one point light."""
    rot = T().rotate([0, 1, 0], 180.0) if back else T()
    return {
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 40.0,
                   "to_world": T().look_at(origin=[0.3, 0.8, 2.5], target=[0, 0, 0],
                                           up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 24, "height": 18}},
        "panel": {"type": "rectangle", "to_world": rot @ T().rotate([1, 0, 0], -60.0),
                  "bsdf": bsdf},
        "lamp": {"type": "point", "position": [0.0, 2.0, 2.0],
                 "intensity": {"type": "rgb", "value": [5.0, 5.0, 5.0]}},
    }


@pytest.mark.parametrize("twosided, back", [(False, False), (True, False), (True, True)])
def test_constant_normal_map_front_and_back(twosided, back):
    """A constant tilted normal map on a panel, with ``twosided`` seen from the front and the
    back: the G-buffer normal is the peak of Mitsuba's BSDF (the back side of a twosided
    normal map mirrors the local normal's z, it is not the front normal negated)."""
    alpha = 0.05
    nm = {"type": "normalmap",
          "normalmap": {"type": "rgb", "value": [0.75, 0.4, 0.9]},
          "bsdf": {"type": "roughconductor", "distribution": "ggx", "material": "Al",
                   "alpha": alpha}}
    bsdf = {"type": "twosided", "bsdf": nm} if twosided else nm
    setup = scenes.from_spec("panel", scenes.SceneSpec(_tilted_panel_scene(bsdf, back)),
                             size=(24, 18))
    m = describe_bsdf(setup.shapes[0].bsdf())
    assert m.normal_map == (NORMAL_MAP_TWOSIDED if twosided else NORMAL_MAP)
    assert m.alpha == pytest.approx(alpha)
    f = Renderer(setup).render(0)
    rng = np.random.default_rng(3)
    assert _check_normal_against_bsdf(setup, f, ("panel",), {"panel": alpha}, rng) > 100
    # facing the camera's side of the surface
    hit = f.numpy("mesh_id")[..., 0] > 0
    n, p = f.numpy("normal")[hit], f.numpy("position")[hit]
    assert np.all(np.sum(n * (f.camera.position - p), -1) > 0)


def test_specular_albedo_uses_the_mapped_normal(setup, frame0, renderer):
    """On normal-mapped pixels the specular albedo is the split-sum table at the cosine to
    the mapped normal (0 where it faces away from the camera), not at the surface's."""
    mesh = frame0.numpy("mesh_id")[..., 0].ravel()
    pixels = np.flatnonzero(mesh == setup.shape_index["floor"])
    ray, si = _primary_hits(setup, pixels.astype(np.uint32))
    n = frame0.numpy("normal").reshape(-1, 3)[pixels].astype(np.float64)
    cos_m = np.sum(n * -_np(ray.d), -1)
    cos_s = np.abs(np.array(mi.Frame3f.cos_theta(si.wi)))
    mat = renderer.shapes.materials["floor"]
    fr = mat.fresnel
    table = renderer.table

    def lookup(cos):
        # the split-sum table (GGX: the floor declares it) with the exact conductor Fresnel
        # at the lobe's effective angle, as glossrt.brdf.fresnel.split_sum
        c = mi.Float(np.maximum(cos, 1e-4).astype(np.float32))
        assert mat.distribution == "ggx"
        ab = table.lookup_ab(c, mi.Float(L.NORMAL_MAPPED_ALPHA_FLOOR), mi.Bool(False))
        e = split_sum(ab.x + ab.y, ab.y, fr.kind, mi.Color3f(*fr.eta), mi.Color3f(*fr.k),
                      mi.Color3f(*fr.scale), mi.Color3f(*fr.f0))
        return _np(e)

    got = frame0.numpy("albedo_specular").reshape(-1, 3)[pixels]
    want = np.where((cos_m > 0)[:, None], lookup(cos_m), 0.0)
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)
    # and that differs from the unperturbed lookup (grazing: the cosines differ a lot)
    assert np.quantile(np.abs(lookup(cos_s) - got).max(-1), 0.75) > 0.01


# -- (b) shapes without a normal map are unchanged --------------------------------------------


def test_flat_floor_has_the_geometric_normal(setup, frame0):
    mesh = frame0.numpy("mesh_id")[..., 0]
    flat = mesh == setup.shape_index["floor_flat"]
    n = frame0.numpy("normal")
    _, si = _primary_hits(setup, np.flatnonzero(flat.ravel()).astype(np.uint32))
    # (ulp differences: glossrt's kernel and this one intersect a little differently)
    np.testing.assert_allclose(n[flat], np.array(si.sh_frame.n, np.float32).T, atol=1e-6)
    np.testing.assert_allclose(n[flat], np.broadcast_to([0.0, 1.0, 0.0], n[flat].shape),
                               atol=1e-6)
    # while the normal-mapped floor's normals vary
    mapped = n[mesh == setup.shape_index["floor"]]
    assert mapped[:, 0].std() > 0.05 and mapped[:, 2].std() > 0.05
    assert np.all(mapped[:, 1] > 0.3)  # still roughly up


def test_glossy_cornell_normals_are_mitsubas_shading_normals():
    """No normal map: the G-buffer normal is ``si.sh_frame.n`` turned to the camera (computed
    here from Mitsuba's own intersection; equal up to float32 ulps between kernels)."""
    setup = scenes.load("glossy-cornell", size=(32, 24))
    f = Renderer(setup).render(0)
    w, h = setup.size
    pixels = np.arange(w * h, dtype=np.uint32)
    ray, si = _primary_hits(setup, pixels)
    valid = np.array(si.is_valid())
    n = np.array(si.sh_frame.n, dtype=np.float32).T
    d = np.array(ray.d, dtype=np.float32).T
    n = np.where((np.sum(n * -d, -1) < 0)[:, None], -n, n)
    n[~valid] = 0.0
    got = f.numpy("normal").reshape(-1, 3)
    np.testing.assert_allclose(got, n, atol=2e-6)
    assert all(m.normal_map == NORMAL_MAP_NONE for m in Renderer(setup).shapes.materials.values())


# -- (c) the procedural normal map ----------------------------------------------------------------


@pytest.fixture(scope="module")
def small_map():
    return procedural_normal_map(256, seed=5)


def _slopes(nmap: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    n = 2.0 * nmap.astype(np.float64) - 1.0
    return n, np.hypot(n[..., 0], n[..., 1]) / n[..., 2]


def test_normal_map_is_unit_length_and_deterministic(small_map):
    assert small_map.shape == (256, 256, 3) and small_map.dtype == np.float32
    n, _ = _slopes(small_map)
    np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1.0, atol=1e-6)
    assert n[..., 2].min() > 0.3
    np.testing.assert_array_equal(procedural_normal_map(256, seed=5), small_map)
    assert not np.array_equal(procedural_normal_map(256, seed=6), small_map)
    with pytest.raises(GlossrtError, match="size"):
        procedural_normal_map(4)


def _seam_ratio(m: np.ndarray, axis: int) -> float:
    interior = np.abs(np.diff(m, axis=axis)).mean()
    seam = np.abs(np.take(m, 0, axis) - np.take(m, -1, axis)).mean()
    return float(seam / interior)


def test_normal_map_tiles_seamlessly(small_map):
    for axis in (0, 1):
        assert 0.75 < _seam_ratio(small_map, axis) < 1.3
    # the test can tell: a crop of a bigger map is not periodic
    crop = procedural_normal_map(512, seed=5)[:256, :256]
    for axis in (0, 1):
        assert _seam_ratio(crop, axis) > 1.8


def test_normal_map_has_bumps_and_scratches(small_map):
    n, s = _slopes(small_map)
    # smooth bumps: typical slopes 0.1 - 0.4, seen at every texel
    assert 0.12 < np.median(s) < 0.4
    assert np.mean(s < 0.02) < 0.02
    # scratches: a few percent of steep texels, impossible for the Gaussian-like bumps alone
    steep = s > 0.8
    assert 0.005 < steep.mean() < 0.1
    assert s.max() > 1.2
    # ... along straight lines: a few texels along the groove (perpendicular to the slope
    # direction) is steep again, with a parallel slope direction
    iv, iu = np.nonzero(steep)
    g = n[iv, iu, :2] / np.linalg.norm(n[iv, iu, :2], axis=-1, keepdims=True)
    along = np.stack([-g[:, 1], g[:, 0]], -1)  # (du, dv)
    hits = []
    for step in (2.0, -2.0):
        ju = np.round(iu + step * along[:, 0]).astype(int) % 256
        jv = np.round(iv + step * along[:, 1]).astype(int) % 256
        gj = n[jv, ju, :2] / np.linalg.norm(n[jv, ju, :2], axis=-1, keepdims=True)
        hits.append(steep[jv, ju] & (np.abs(np.sum(g * gj, -1)) > 0.8))
    assert np.mean(hits[0] | hits[1]) > 0.6
    # a control without line structure (steep texels shuffled) fails that
    perm = np.random.default_rng(0).permutation(256 * 256).reshape(256, 256)
    shuffled = steep.ravel()[perm]
    assert np.mean(shuffled[np.round(iv + 2 * along[:, 1]).astype(int) % 256,
                            np.round(iu + 2 * along[:, 0]).astype(int) % 256]) < 0.2


# -- (d) the scene --------------------------------------------------------------------------------


def test_scene_loads_and_renders(setup, renderer, frame0):
    assert setup.max_depth == 3 and setup.animated
    assert "Tokuyoshi" in scenes.BUILTIN["normal-mapped"][1]
    assert {"floor", "floor_flat", "sphere"} <= set(setup.shape_index)
    kinds = sorted(e.class_name() for e in setup.scene.emitters())
    assert kinds == ["AreaLight", "DirectionalEmitter", "PointLight"]
    for f in (frame0, renderer.render(8)):
        for name in ("color", "direct_specular", "normal", "albedo_specular", "roughness",
                     "motion"):
            assert np.all(np.isfinite(f.numpy(name))), name
        assert f.meta["nonfinite_samples"] == 0
    mesh = frame0.numpy("mesh_id")[..., 0]
    frac = {sid: float(np.mean(mesh == setup.shape_index[sid]))
            for sid in ("floor", "floor_flat", "sphere")}
    assert 0.12 < frac["floor_flat"] < 0.3, frac
    assert frac["floor"] > 0.35 and frac["sphere"] > 0.02, frac
    assert not np.any(mesh == setup.shape_index["light"])  # the quad light is not seen
    # lit: highlights on the floor, not blown out on average
    c = frame0.numpy("color")[mesh == setup.shape_index["floor"]]
    assert 0.05 < c.mean() < 20.0
    assert frame0.numpy("color")[mesh == setup.shape_index["floor_flat"]].max() > 0.05


def _al_f0() -> np.ndarray:
    """F0 of Mitsuba's aluminium: a smooth ``conductor`` sampled at normal incidence (its
    weight is the Fresnel reflectance)."""
    cond = mi.load_dict({"type": "conductor", "material": "Al"})
    si = dr.zeros(mi.SurfaceInteraction3f)
    si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
    si.wi = mi.Vector3f(0, 0, 1)
    _, w = cond.sample(mi.BSDFContext(), si, 0.5, mi.Point2f(0.5, 0.5))
    return _np(w)[0]


def test_materials_describe_the_nested_conductor(setup, renderer, frame0):
    mats = renderer.shapes.materials
    f0 = _al_f0()
    assert 0.8 < f0.mean() < 1.0
    for sid, alpha, kind in (("floor", L.NORMAL_MAPPED_ALPHA_FLOOR, NORMAL_MAP),
                             ("floor_flat", L.NORMAL_MAPPED_ALPHA_FLOOR, NORMAL_MAP_NONE),
                             ("sphere", L.NORMAL_MAPPED_ALPHA_SPHERE, NORMAL_MAP)):
        m = mats[sid]
        assert m.alpha == pytest.approx(alpha) and not m.alpha_attr, sid
        assert m.has_specular and not m.has_diffuse, sid
        np.testing.assert_allclose(m.f0, f0, rtol=2e-3, err_msg=sid)
        assert m.normal_map == kind, sid
        mask = frame0.numpy("mesh_id")[..., 0] == setup.shape_index[sid]
        np.testing.assert_allclose(frame0.numpy("roughness")[..., 0][mask], alpha, rtol=1e-6)


def test_camera_moves_slowly(setup):
    c0, c8 = setup.camera(0), setup.camera(8)
    np.testing.assert_allclose(c0.to_world, setup.rest_camera, atol=1e-5)
    moved = np.linalg.norm(c8.position - c0.position)
    assert 0.005 < moved < 0.1
    f0, f8 = c0.to_world[:3, 2], c8.to_world[:3, 2]
    angle = math.degrees(math.acos(np.clip(np.dot(f0, f8) / np.linalg.norm(f0)
                                           / np.linalg.norm(f8), -1, 1)))
    assert 0.1 < angle < 2.0
    # 16 frames shift the view by a few pixels at the scene's own 320 px width
    px_per_degree = 320 / setup.fov
    f16 = setup.camera(16).to_world[:3, 2]
    turn16 = math.degrees(math.acos(np.clip(np.dot(f0, f16) / np.linalg.norm(f0)
                                            / np.linalg.norm(f16), -1, 1)))
    assert 1.0 < turn16 * px_per_degree < 12.0


@pytest.mark.parametrize("wrap", ["normalmap", "twosided(normalmap)", "twosided"])
def test_textured_roughness_inside_a_wrapper_is_read_per_texel(wrap):
    """A roughness texture (alpha 0.1 on the left half of the panel's uv square, 0.5 on the
    right, nearest filtering) inside ``normalmap`` / ``twosided`` wrappers: the G-buffer's
    roughness is the texel's alpha at every hit, pixel for pixel the same as the unwrapped
    BSDF's (Mitsuba's own ``alpha`` attribute there), not the texture's mean 0.3 (what the
    G-buffer read before, and what Tokuyoshi 2015's lobe weight then saw on fig. 7's
    Toksvig-filtered scene)."""
    def inner():  # (a fresh dict per load: Mitsuba takes the tensor it is given)
        alphas = np.array([[[0.1], [0.5]]], np.float32)  # (1, 2, 1): two texels across u
        return {"type": "roughconductor", "distribution": "ggx", "material": "Al",
                "alpha": {"type": "bitmap", "data": mi.TensorXf(alphas), "raw": True,
                          "filter_type": "nearest"}}

    flat = {"type": "rgb", "value": [0.5, 0.5, 1.0]}  # the unperturbed normal
    bsdf = {"normalmap": {"type": "normalmap", "normalmap": flat, "bsdf": inner()},
            "twosided(normalmap)": {"type": "twosided", "bsdf": {
                "type": "normalmap", "normalmap": flat, "bsdf": inner()}},
            "twosided": {"type": "twosided", "bsdf": inner()}}[wrap]

    def roughness(b):
        setup = scenes.from_spec("panel", scenes.SceneSpec(_tilted_panel_scene(b, False)),
                                 size=(24, 18))
        f = Renderer(setup).render(0)
        return f.numpy("roughness")[..., 0], f.numpy("mesh_id")[..., 0] > 0

    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # (the mean's warning would be an error here)
        got, hit = roughness(bsdf)
    want, hit0 = roughness(inner())
    assert np.array_equal(hit, hit0) and hit.sum() > 100
    np.testing.assert_allclose(np.unique(want[hit]), [0.1, 0.5], rtol=1e-6)  # both texels
    np.testing.assert_allclose(got[hit], want[hit], rtol=0, atol=1e-7)
