"""Bad input to the polygon-light and BSPVT code gives clear errors, not wrong pictures:

* :meth:`BSPVT.save` is atomic (an interrupted save leaves no half-written file, and an old
  file intact);
* :meth:`BSPVT.load` of a file that is not a tree file (text, EXR, .npy) or of a missing path
  says so in one line naming the file;
* trees built for another scene (same vertex count, other positions or normals) are refused,
  naming the trees' file, and the check runs once per trees / scene pair;
* a polygon light with NaN, Inf or negative radiance, or a NaN transform, is refused with a
  message naming the light (not "zero area")."""

from __future__ import annotations

import os

import numpy as np
import pytest

from glossrt import backend

backend.ensure()

import mitsuba as mi  # noqa: E402

from glossrt import render, scenes  # noqa: E402
from glossrt.errors import GlossrtError, SceneError  # noqa: E402
from glossrt.lights.bspvt import (  # noqa: E402
    BSPVT,  # noqa: E402
    build_scene_trees,
    shade_bspvt,
)
from glossrt.lights.bspvt import build as bspvt  # noqa: E402
from glossrt.lights.scene import polygon_lights  # noqa: E402
from glossrt.scenes.teapot import grid_mesh, mesh_shape  # noqa: E402

T = mi.ScalarTransform4f
SIZE = (32, 24)


def _floor_scene(shift=(0.0, 0.0, 0.0), radiance=5.0, light_to_world=None):
    """A 4x4-quad floor (25 vertices) under a quad light; ``shift`` moves the floor."""
    light_xf = light_to_world if light_to_world is not None else \
        T().translate([0, 1.2, -0.5]).rotate([1, 0, 0], 60).scale(0.4)
    d = {
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 50.0,
                   "to_world": T().look_at([0, 2.0, 2.5], [0, 0, 0], [0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": SIZE[0], "height": SIZE[1]}},
        "floor": mesh_shape("floor", *grid_mesh(4),
                            T().translate(list(shift)).rotate([1, 0, 0], -90).scale(1.5),
                            {"type": "roughplastic", "distribution": "ggx", "alpha": 0.3}),
        "light": {"type": "rectangle", "to_world": light_xf,
                  "emitter": {"type": "area", "radiance": {"type": "rgb", "value": radiance}}},
    }
    return scenes.from_spec("floor-test", scenes.SceneSpec(d), size=SIZE)


@pytest.fixture(scope="module")
def tiny_trees():
    return build_scene_trees(_floor_scene().scene, resolution=4, progress=False)


# -- save ------------------------------------------------------------------------------------

def _interrupted_savez(f, **arrays):
    f.write(b"PK\x03\x04 half of an archive")
    raise KeyboardInterrupt("interrupted mid-save")


def test_save_is_atomic(tmp_path, tiny_trees, monkeypatch):
    fresh = tmp_path / "fresh.npz"
    old = tmp_path / "old.npz"
    tiny_trees.save(str(old))
    before = old.read_bytes()
    with monkeypatch.context() as m:
        m.setattr(np, "savez_compressed", _interrupted_savez)
        with pytest.raises(KeyboardInterrupt):
            tiny_trees.save(str(fresh))
        with pytest.raises(KeyboardInterrupt):
            tiny_trees.save(str(old))
    assert not fresh.exists()
    assert old.read_bytes() == before
    assert sorted(os.listdir(tmp_path)) == ["old.npz"]  # no temporary left behind
    back = BSPVT.load(str(old))
    assert np.array_equal(back.lines, tiny_trees.lines)
    # a normal save replaces the old file and leaves nothing else
    tiny_trees.save(str(old))
    assert sorted(os.listdir(tmp_path)) == ["old.npz"]
    assert np.array_equal(BSPVT.load(str(old)).roots, tiny_trees.roots)


# -- load ------------------------------------------------------------------------------------

def _load_error(path) -> str:
    with pytest.raises(GlossrtError) as e:
        BSPVT.load(str(path))
    msg = str(e.value)
    assert "\n" not in msg and "pickle" not in msg, msg
    return msg


def test_load_non_tree_files(tmp_path):
    text = tmp_path / "notes.txt"
    text.write_text("these are not trees\n")
    exr = tmp_path / "frame.exr"
    mi.Bitmap(np.zeros((2, 3, 3), np.float32)).write(str(exr))
    npy = tmp_path / "array.npy"
    np.save(npy, np.zeros(4))
    other = tmp_path / "other.npz"
    np.savez(other, a=np.zeros(3))
    for f in (text, exr, npy, other):
        msg = _load_error(f)
        assert str(f) in msg and "not a BSPVT tree file" in msg, msg
        assert "glossrt bspvt build" in msg, msg
    msg = _load_error(tmp_path / "missing.npz")
    assert "missing.npz" in msg and "not found" in msg, msg


# -- trees of another scene ------------------------------------------------------------------

def test_trees_of_a_moved_floor_are_refused(tmp_path, tiny_trees):
    path = tmp_path / "floor.npz"
    tiny_trees.save(str(path))
    trees = BSPVT.load(str(path))
    good = _floor_scene()
    moved = _floor_scene(shift=(0.0, 0.0, 0.3))  # same vertex count, other positions
    gb = render.Renderer(moved).render(0)
    with pytest.raises(GlossrtError, match="another scene") as e:
        shade_bspvt(moved.scene, gb, trees, polygon_lights(moved, 0), "pixel")
    assert str(path) in str(e.value) and "\n" not in str(e.value)
    # the right scene is accepted
    gb = render.Renderer(good).render(0)
    img = shade_bspvt(good.scene, gb, trees, polygon_lights(good, 0), "pixel")
    assert np.isfinite(img).all() and img.max() > 0


def test_flipped_normals_are_refused(tiny_trees):
    good = _floor_scene()
    gb = render.Renderer(good).render(0)
    lights = polygon_lights(good, 0)
    trees = BSPVT(lines=tiny_trees.lines, children=tiny_trees.children,
                  leaf_value=tiny_trees.leaf_value, roots=tiny_trees.roots,
                  resolution=tiny_trees.resolution, epsilon=tiny_trees.epsilon,
                  positions=tiny_trees.positions, normals=-tiny_trees.normals)
    with pytest.raises(GlossrtError, match="another scene"):
        shade_bspvt(good.scene, gb, trees, lights, "pixel")


def test_scene_match_is_checked_once(tiny_trees, monkeypatch):
    good = _floor_scene()
    gb = render.Renderer(good).render(0)
    lights = polygon_lights(good, 0)
    calls = []
    real = bspvt.scene_vertices
    monkeypatch.setattr(bspvt, "scene_vertices", lambda s: calls.append(1) or real(s))
    trees = BSPVT(lines=tiny_trees.lines, children=tiny_trees.children,
                  leaf_value=tiny_trees.leaf_value, roots=tiny_trees.roots,
                  resolution=tiny_trees.resolution, epsilon=tiny_trees.epsilon,
                  positions=tiny_trees.positions, normals=tiny_trees.normals)
    a = shade_bspvt(good.scene, gb, trees, lights, "vertex", frozen=True)
    b = shade_bspvt(good.scene, gb, trees, lights, "vertex", frozen=True)
    assert len(calls) == 1
    np.testing.assert_array_equal(a, b)


# -- polygon lights with bad numbers ---------------------------------------------------------

@pytest.mark.parametrize("value", [[float("nan"), 5.0, 5.0], [5.0, float("inf"), 5.0],
                                   [5.0, -1.0, 5.0]])
def test_bad_radiance_is_refused(value):
    setup = _floor_scene(radiance=value)
    with pytest.raises(GlossrtError, match="radiance") as e:
        polygon_lights(setup, 0)
    msg = str(e.value)
    assert "light" in msg and "floor-test" in msg, msg


def test_bad_radiance_from_xml_fails_in_the_cli(tmp_path, capsys):
    from glossrt.cli import main

    xml = tmp_path / "nanrad.xml"
    xml.write_text(
        '<scene version="3.0.0"><sensor type="perspective"><float name="fov" value="45"/>'
        '<transform name="to_world"><lookat origin="0,-4,3" target="0,0,0" up="0,0,1"/>'
        '</transform><film type="hdrfilm"><integer name="width" value="16"/>'
        '<integer name="height" value="12"/></film></sensor><shape type="rectangle">'
        '<bsdf type="roughconductor"><float name="alpha" value="0.2"/></bsdf></shape>'
        '<shape type="rectangle" id="lamp"><transform name="to_world"><scale value="0.5"/>'
        '<rotate x="1" angle="180"/><translate z="2"/></transform><emitter type="area">'
        '<rgb name="radiance" value="nan,5,5"/></emitter></shape></scene>')
    for method in ("ltc", "mc"):
        assert main(["light", str(xml), "--method", method, "--spp", "1", "--out",
                     str(tmp_path / method)]) == 2
        err = capsys.readouterr().err
        assert "lamp" in err and "radiance" in err and "nanrad" in err, err
        assert not (tmp_path / method / "frame_0000.exr").exists()


def test_nan_transform_is_not_called_zero_area():
    nan_xf = T().translate([0, 1.2, -0.5]).scale(float("nan"))
    with pytest.raises(SceneError, match="area light 'light' has NaN/Inf"):
        _floor_scene(light_to_world=nan_xf)  # refused when the scene loads
    setup = _floor_scene()  # a light made NaN after loading: polygon_lights' own check
    setup.params["light.to_world"] = nan_xf
    setup.params.update()
    with pytest.raises(GlossrtError) as e:
        polygon_lights(setup, 0)
    msg = str(e.value)
    assert "zero area" not in msg and "finite" in msg and "light" in msg, msg
    # a truly degenerate (flat) light still says zero area
    flat = _floor_scene(light_to_world=T().translate([0, 1.2, -0.5]).scale([0.4, 0.0, 1.0]))
    with pytest.raises(GlossrtError, match="zero area"):
        polygon_lights(flat, 0)


def test_collinear_triangle_light_says_zero_area(tmp_path, capsys):
    """A triangle light whose corners lie on one line used to be refused with "its normals do
    not all point to the same side of its plane" (Mitsuba's normals of a zero-area triangle
    are NaN): now one line saying it has zero area because its vertices are collinear, from
    the scene loader and through the CLI; a mesh of degenerate triangles whose vertices span
    a plane says so too."""
    from glossrt.cli import main

    def obj(name, verts, faces):
        path = tmp_path / f"{name}.obj"
        path.write_text("".join(f"v {x} {y} {z}\n" for x, y, z in verts)
                        + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in faces))
        return str(path)

    line = obj("line", [[0, 0, 2.0], [0.5, 0.25, 2.0], [1.0, 0.5, 2.0]], [(0, 1, 2)])
    fan = obj("fan", [[0, 0, 2.0], [1, 0, 2.0], [2, 0, 2.0], [0, 1, 2.0], [0, 2, 2.0]],
              [(0, 1, 2), (0, 3, 4)])
    for name, path, why in (("stick", line, "vertices are collinear"),
                            ("fan", fan, "triangles has collinear or repeated corners")):
        scene = mi.load_dict({"type": "scene", name: {
            "type": "obj", "filename": path,
            "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [5.0, 5.0, 5.0]}}}})
        with pytest.raises(GlossrtError) as e:
            polygon_lights(scene)
        msg = str(e.value)
        assert "\n" not in msg and repr(name) in msg and "zero area" in msg and why in msg, msg
        assert "normals" not in msg, msg
    xml = tmp_path / "stick.xml"
    xml.write_text(
        '<scene version="3.0.0"><sensor type="perspective"><float name="fov" value="45"/>'
        '<transform name="to_world"><lookat origin="0,-4,3" target="0,0,0" up="0,0,1"/>'
        '</transform><film type="hdrfilm"><integer name="width" value="16"/>'
        '<integer name="height" value="12"/></film></sensor><shape type="rectangle">'
        '<bsdf type="roughconductor"><float name="alpha" value="0.2"/></bsdf></shape>'
        f'<shape type="obj" id="stick"><string name="filename" value="{line}"/>'
        '<emitter type="area"><rgb name="radiance" value="5,5,5"/></emitter></shape></scene>')
    assert main(["light", str(xml), "--method", "ltc", "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    errors = [ln for ln in err.splitlines() if "error" in ln]  # (the rest: progress)
    assert len(errors) == 1 and "'stick'" in errors[0] and "collinear" in errors[0], err
    assert not (tmp_path / "out" / "frame_0000.exr").exists()
