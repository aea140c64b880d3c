"""glossrt.lights.bspvt.scene: BSPVT shadows of Frames (Okuno & Iwasaki) and the glue to scenes.

* pixel_triangles finds the triangle and barycentrics each pixel sees (they rebuild the
  G-buffer's positions);
* with nothing in the way (a floor under a quad light) the per-pixel BSPVT shading equals
  unshadowed LTC, and the per-vertex shading is LTC interpolated from the vertices;
* on a coarse polygon-light scene, BSPVT (per vertex and per pixel) is far closer to a
  shadowed Monte Carlo reference of the same BRDF than unshadowed LTC, and per pixel beats
  per vertex;
* the CLI builds trees and shades with them (bspvt, ratio), with clear errors."""

from __future__ import annotations

import numpy as np
import pytest

from glossrt import backend

backend.ensure()

import mitsuba as mi  # noqa: E402

from glossrt import render, scenes  # noqa: E402
from glossrt.errors import GlossrtError  # noqa: E402
from glossrt.lights.bspvt import scene_vertices  # noqa: E402
from glossrt.lights.bspvt.scene import (  # noqa: E402
    build_scene_trees,
    pixel_triangles,
    scene_meshes,
    shade_bspvt,
    vertex_materials,
)
from glossrt.lights.bspvt.shade import shade_pixels, shade_vertices  # noqa: E402
from glossrt.lights.ltc import shade_frame  # noqa: E402
from glossrt.lights.mc import render_mc  # noqa: E402
from glossrt.lights.scene import polygon_lights  # noqa: E402
from glossrt.lights.shading import f0_image  # noqa: E402
from glossrt.scenes.library import polygon_light_scene  # noqa: E402
from glossrt.scenes.teapot import grid_mesh, mesh_shape  # noqa: E402

T = mi.ScalarTransform4f


def _setup(spec_or_dict, size, name="test"):
    spec = spec_or_dict if isinstance(spec_or_dict, scenes.SceneSpec) else \
        scenes.SceneSpec(spec_or_dict)
    return scenes.from_spec(name, spec, size=size)


def coarse_polygon_light(size=(48, 36), alpha=0.25):
    return _setup(polygon_light_scene(alpha, teapot_n=3, floor_n=16, sphere_n=6), size,
                  "polygon-light-coarse")


def floor_only(size=(32, 24), name="floor-only", **extra):
    """A floor mesh lit by a rectangle (``extra``: more shapes by id)."""
    return _setup({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 50.0,
                   "to_world": T().look_at([0, 2.0, 2.5], [0, 0, 0], [0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": size[0], "height": size[1]}},
        "floor": mesh_shape("floor", *grid_mesh(6), T().rotate([1, 0, 0], -90).scale(1.5),
                            {"type": "roughplastic", "distribution": "ggx", "alpha": 0.3}),
        "light": {"type": "rectangle", "to_world": T().translate([0, 1.2, -0.5])
                  .rotate([1, 0, 0], 60).scale(0.4),
                  "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 5.0}}},
        **extra,
    }, size, name)


@pytest.mark.slow
def test_pixel_triangles_rebuild_positions():
    setup = coarse_polygon_light()
    gb = render.Renderer(setup).render(0)
    meshes = scene_meshes(setup.scene)
    pos, _, offsets = scene_vertices(setup.scene)
    pt = pixel_triangles(setup.scene, gb, meshes, offsets)
    ids = gb.numpy("mesh_id")[..., 0].ravel()
    light_id = 1 + [s.id() for s in scenes.stable_shapes(setup.scene)].index("light")
    # every surface pixel but the light's own has a triangle
    np.testing.assert_array_equal(pt.valid, (ids > 0) & (ids != light_id))
    rec = np.einsum("pk,pkc->pc", pt.bary[pt.valid], pos[pt.vertices[pt.valid]])
    want = gb.numpy("position").reshape(-1, 3)[pt.valid]
    assert np.abs(rec - want).max() < 1e-4
    assert np.all(pt.bary[pt.valid] >= -1e-5)


def test_unoccluded_floor_matches_ltc():
    setup = floor_only()
    gb = render.Renderer(setup).render(0)
    lights = polygon_lights(setup, 0)
    f0 = f0_image(setup, gb)
    trees = build_scene_trees(setup.scene, resolution=8, progress=False)
    ltc = shade_frame(gb, lights, f0=f0)
    pix = shade_bspvt(setup.scene, gb, trees, lights, "pixel", f0=f0)
    assert ltc.max() > 0.1
    np.testing.assert_allclose(pix, ltc, rtol=2e-4, atol=2e-5)
    # per vertex: LTC at the vertices, interpolated; close to per-pixel on a fine-ish grid
    vtx = shade_bspvt(setup.scene, gb, trees, lights, "vertex")
    hit = gb.numpy("mesh_id")[..., 0] > 0
    rel = np.abs(vtx - ltc)[hit].mean() / ltc[hit].mean()
    assert 0 < rel < 0.25, rel


@pytest.mark.slow
def test_bspvt_against_shadowed_reference():
    setup = coarse_polygon_light()
    gb = render.Renderer(setup).render(0)
    lights = polygon_lights(setup, 0)
    f0 = f0_image(setup, gb)
    trees = build_scene_trees(setup.scene, resolution=16, progress=False)
    ref = render_mc(gb, lights, 256, f0=f0, scene=setup.scene, seed=3)
    ltc = shade_frame(gb, lights, f0=f0)
    hit = gb.numpy("mesh_id")[..., 0] > 0
    err = {"ltc": np.abs(ltc - ref)[hit].mean()}
    imgs = {}
    for mode in ("vertex", "pixel"):
        img = imgs[mode] = shade_bspvt(setup.scene, gb, trees, lights, mode, f0=f0)
        assert np.all(np.isfinite(img))
        err[mode] = np.abs(img - ref)[hit].mean()
        # frozen (the fused traversal, replayed) == traced
        frozen = shade_bspvt(setup.scene, gb, trees, lights, mode, f0=f0, frozen=True)
        np.testing.assert_allclose(frozen, img, rtol=1e-5, atol=1e-6)
    print("mean abs error", err)
    assert err["pixel"] < 0.4 * err["ltc"]
    assert err["vertex"] < 0.6 * err["ltc"]
    assert err["pixel"] < err["vertex"]
    # the device per-vertex path == shade_vertices at the vertices, blended in NumPy
    _, _, offsets = scene_vertices(setup.scene)
    pt = pixel_triangles(setup.scene, gb, scene_meshes(setup.scene), offsets)
    wo = np.asarray(gb.camera.position, np.float64) - trees.positions
    wo /= np.linalg.norm(wo, axis=1, keepdims=True)
    d, s = shade_vertices(trees, lights, wo, *vertex_materials(setup.scene))
    want = np.zeros((pt.valid.size, 3))
    want[pt.valid] = np.einsum("pk,pkc->pc", pt.bary[pt.valid], (d + s)[pt.vertices[pt.valid]])
    np.testing.assert_allclose(imgs["vertex"].reshape(-1, 3), want, rtol=1e-5, atol=1e-6)
    # the device per-pixel path == shade_pixels on the pixels with a triangle (NumPy inputs)
    sel = np.flatnonzero(pt.valid)
    p = gb.numpy("position").reshape(-1, 3)[sel]
    wo = np.asarray(gb.camera.position, np.float64) - p
    d, s = shade_pixels(trees, lights, p, gb.numpy("normal").reshape(-1, 3)[sel],
                        wo / np.linalg.norm(wo, axis=1, keepdims=True),
                        gb.numpy("roughness").reshape(-1)[sel],
                        gb.numpy("albedo_diffuse").reshape(-1, 3)[sel], f0.reshape(-1, 3)[sel],
                        pt.vertices[sel], pt.bary[sel])
    want = np.zeros((pt.valid.size, 3))
    want[sel] = d + s
    np.testing.assert_allclose(imgs["pixel"].reshape(-1, 3), want, rtol=1e-4, atol=1e-5)


def test_vertex_materials_follow_the_bsdfs():
    setup = coarse_polygon_light(alpha=0.5)
    alpha, albedo, f0 = vertex_materials(setup.scene)
    meshes = scene_meshes(setup.scene)
    k = {m.id(): m.vertex_count() for m in meshes}
    order = [m.id() for m in meshes]
    start = dict(zip(order, np.cumsum([0] + [k[i] for i in order])[:-1], strict=True))
    np.testing.assert_allclose(alpha, 0.5)
    np.testing.assert_allclose(albedo[start["teapot"]], [0.75, 0.32, 0.1], atol=1e-6)
    np.testing.assert_array_equal(albedo[start["sphere"]], 0.0)  # copper: no diffuse lobe
    assert f0[start["sphere"]][0] > 0.5 and f0[start["floor"]][0] == pytest.approx(0.0962, 1e-3)


@pytest.mark.slow
def test_trees_of_another_scene_are_refused():
    setup = floor_only()
    trees = build_scene_trees(setup.scene, resolution=4, progress=False)
    other = coarse_polygon_light()
    gb = render.Renderer(other).render(0)
    with pytest.raises(GlossrtError, match="another scene"):
        shade_bspvt(other.scene, gb, trees, polygon_lights(other, 0))
    with pytest.raises(GlossrtError, match="mode"):
        shade_bspvt(setup.scene, gb, trees, [], "bogus")


@pytest.mark.slow
def test_cli_build_and_shade(tmp_path, capsys):
    from glossrt.cli import main

    f = tmp_path / "t.npz"
    assert main(["bspvt", "build", "polygon-light", "--out", str(f), "--resolution", "4",
                 "--epsilon", "2", "--engine", "drjit"]) == 0
    assert "leaves_per_vertex" in capsys.readouterr().out
    for extra in (["--method", "bspvt", "--bspvt", str(f), "--mode", "pixel"],
                  ["--method", "ratio"]):
        out = tmp_path / extra[1]
        assert main(["light", "polygon-light", *extra, "--size", "24x18", "--out",
                     str(out)]) == 0
        assert (out / "frame_0000.exr").exists()
    assert main(["light", "polygon-light", "--method", "bspvt", "--size", "24x18", "--out",
                 str(tmp_path / "x")]) == 2
    assert "--bspvt FILE" in capsys.readouterr().err


def test_vertex_inside_geometry_is_dark_not_nan():
    """A vertex inside a closed mesh sees nothing: every texel blocked, one leaf of value 0
    per face, and its shading is exactly 0 (no NaN), while a vertex outside is lit."""
    from glossrt.lights.bspvt.build import build_trees, occluders, visibility_cubemaps
    from glossrt.lights.bspvt.shade import shade_vertices
    from glossrt.scenes.teapot import sphere_mesh

    scene = mi.load_dict({"type": "scene", "ball": mesh_shape("ball", *sphere_mesh(8))})
    # (off-centre: rays through the exact centre graze the mesh's vertices and edges)
    pos = np.array([[0.013, -0.021, 0.007], [0.0, 0.0, 3.0]])
    nrm = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    vis = visibility_cubemaps(occluders(scene), pos, nrm, 8, progress=False)
    assert vis[0].max() == 0 and vis[1, 4].min() == 1  # +z face of the outside vertex
    trees = build_trees(vis, positions=pos, normals=nrm, progress=False)
    assert np.all(trees.roots[0] < 0) and np.all(trees.leaf_value[~trees.roots[0]] == 0)

    class Quad:
        vertices = np.array([[-1, -1, 5.0], [-1, 1, 5.0], [1, 1, 5.0], [1, -1, 5.0]])
        radiance = np.ones(3)
        two_sided = True

    d, s = shade_vertices(trees, [Quad()], np.array([[0, 0, 1.0]] * 2), 0.3,
                          np.full((2, 3), 0.5), np.full((2, 3), 0.04))
    assert np.all(np.isfinite(d)) and np.all(np.isfinite(s))
    assert np.all(d[0] == 0) and np.all(s[0] == 0)
    assert d[1].min() > 0.01 and s[1].min() > 0.001


@pytest.mark.slow
def test_textured_light_with_shadows():
    """The textured light (prefiltered texture per visible piece) with BSPVT shadows: far
    closer to the shadowed Monte Carlo reference than unshadowed textured LTC."""
    setup = _setup(polygon_light_scene(0.25, textured=True, teapot_n=3, floor_n=16,
                                       sphere_n=6), (40, 30), "textured-coarse")
    gb = render.Renderer(setup).render(0)
    lights = polygon_lights(setup, 0)
    f0 = f0_image(setup, gb)
    trees = build_scene_trees(setup.scene, resolution=12, progress=False)
    cache: dict = {}
    ref = render_mc(gb, lights, 256, f0=f0, scene=setup.scene, seed=5)
    hit = gb.numpy("mesh_id")[..., 0] > 0
    ltc = shade_frame(gb, lights, f0=f0, textures=cache)
    img = shade_bspvt(setup.scene, gb, trees, lights, "pixel", f0=f0, textures=cache)
    assert np.all(np.isfinite(img))
    e_ltc = np.abs(ltc - ref)[hit].mean()
    e_bs = np.abs(img - ref)[hit].mean()
    print("textured: ltc", e_ltc, "bspvt", e_bs)
    assert e_bs < 0.4 * e_ltc


def floor_and_ball(size=(32, 24)):
    """:func:`floor_only` with an analytic sphere hovering over the floor."""
    return floor_only(size, "floor-and-ball", ball={
        "type": "sphere", "to_world": T().translate([0, 0.5, 0]).scale(0.3),
        "bsdf": {"type": "diffuse"}})


@pytest.mark.slow
def test_trees_refuse_occluders_moved_since_the_build(tmp_path):
    """Okuno & Iwasaki's visibility is precomputed for static occluders: trees shaded after
    an analytic occluder moved (or a mesh was edited in place, after a cached pass) would
    give wrong shadows without a word, so shading refuses them and names the shape."""
    from glossrt.lights.bspvt import BSPVT

    setup = floor_and_ball()
    trees = build_scene_trees(setup.scene, resolution=4, progress=False)
    rec = trees.info["occluder_bounds"]
    assert [o["shape"] for o in rec] == ["ball"]
    np.testing.assert_allclose(rec[0]["min"], [-0.3, 0.2, -0.3], atol=1e-5)
    f = tmp_path / "t.npz"
    trees.save(str(f))
    assert BSPVT.load(str(f)).info["occluder_bounds"] == rec  # the record is kept in files
    gb = render.Renderer(setup).render(0)
    lights = polygon_lights(setup, 0)
    shade_bspvt(setup.scene, gb, trees, lights)  # as built: accepted

    params = mi.traverse(setup.scene)
    ball = [k for k in params.keys() if k.startswith("ball") and k.endswith("to_world")]
    assert ball, list(params.keys())
    rest = mi.Transform4f(np.array(params[ball[0]].matrix))  # a copy, not the live value
    params[ball[0]] = mi.Transform4f().translate([0.4, 0.0, 0.0]) @ rest
    params.update()
    with pytest.raises(GlossrtError, match="'ball'.*moved"):
        shade_bspvt(setup.scene, gb, trees, lights)
    params[ball[0]] = rest  # back where it was: accepted again
    params.update()
    shade_bspvt(setup.scene, gb, trees, lights)

    # a mesh edited in place after a remembered pass is compared anew
    key = [k for k in params.keys() if k.startswith("floor") and k.endswith("vertex_positions")]
    assert key, list(params.keys())
    v = np.array(params[key[0]]).reshape(-1, 3)
    params[key[0]] = mi.Float((v + [0.0, 0.2, 0.0]).astype(np.float32).ravel())
    params.update()
    with pytest.raises(GlossrtError, match="before an edit"):
        shade_bspvt(setup.scene, gb, trees, lights)

    # trees written before the record (no "occluder_bounds") are still shaded
    old = build_scene_trees(floor_and_ball().scene, resolution=4, progress=False)
    del old.info["occluder_bounds"]
    other = floor_and_ball()
    p2 = mi.traverse(other.scene)
    p2[ball[0]] = mi.Transform4f().translate([0.4, 0.0, 0.0]) @ p2[ball[0]]
    p2.update()
    shade_bspvt(other.scene, render.Renderer(other).render(0), old, polygon_lights(other, 0))
