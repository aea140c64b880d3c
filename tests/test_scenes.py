"""glossrt.scenes: built-in scenes, XML loading (supported and unsupported plugins, errors),
size override, animation (set_frame, orbit) and the integrator's max_depth."""

from __future__ import annotations

import math

import numpy as np
import pytest

from glossrt import backend

backend.ensure()
import mitsuba as mi  # noqa: E402

from glossrt import scenes  # noqa: E402
from glossrt.errors import GlossrtError, SceneError  # noqa: E402
from glossrt.frame import RADIANCE, Camera  # noqa: E402
from glossrt.render import Renderer  # noqa: E402

SIZE = (24, 18)

SENSOR = """
  <sensor type="perspective">
    <float name="fov" value="{fov}"/>{extra}
    <transform name="to_world">
      <lookat origin="0, 1, 4" target="0, 0.3, 0" up="0, 1, 0"/>
    </transform>
    <film type="hdrfilm">
      <integer name="width" value="40"/><integer name="height" value="30"/>
    </film>
  </sensor>"""

FLOOR = """
  <shape type="rectangle" id="floor">
    <transform name="to_world"><rotate x="1" angle="-90"/><scale value="3"/></transform>
    <bsdf type="diffuse"><rgb name="reflectance" value="0.5, 0.5, 0.5"/></bsdf>
  </shape>"""

AREA_LIGHT = """
  <shape type="rectangle" id="lamp">
    <transform name="to_world">
      <rotate x="1" angle="90"/><scale value="0.5"/><translate y="2.5"/>
    </transform>
    <emitter type="area"><rgb name="radiance" value="10, 10, 10"/></emitter>
  </shape>"""

CONSTANT = '\n  <emitter type="constant"><rgb name="radiance" value="0.2, 0.3, 0.4"/></emitter>'


def scene_xml(body: str, *, integrator: str = "", fov: float = 45.0, sensor_extra: str = "",
              defaults: str = "") -> str:
    return (f'<scene version="3.0.0">{defaults}{integrator}'
            f'{SENSOR.format(fov=fov, extra=sensor_extra)}{body}\n</scene>\n')


def write(tmp_path, text: str, name: str = "scene.xml") -> str:
    path = tmp_path / name
    path.write_text(text)
    return str(path)


def sphere(bsdf: str, sid: str = "object") -> str:
    return (f'\n  <shape type="sphere" id="{sid}">'
            f'<point name="center" x="0" y="0.5" z="0"/><float name="radius" value="0.5"/>'
            f"{bsdf}</shape>")


# -- built-ins -----------------------------------------------------------------------------------


def test_builtins_are_listed_with_descriptions():
    from glossrt.scenes import library  # noqa: F401  (registers the built-ins)

    assert {"glossy-cornell", "roughness-map"} <= set(scenes.BUILTIN)
    for name, (fn, description) in scenes.BUILTIN.items():
        assert callable(fn) and description.strip(), name


@pytest.mark.parametrize("name", ["glossy-cornell", "roughness-map"])
def test_builtins_load(name):
    setup = scenes.load(name)
    assert setup.name == name
    assert setup.size == (320, 240)  # the scenes' own film
    assert setup.max_depth == 3
    assert setup.animated
    assert setup.source is None
    cam = setup.camera(0)
    assert cam.resolution == setup.size and cam.fov > 0
    assert setup.camera(-1) is None
    assert len(setup.scene.shapes()) >= 3
    # 1-based mesh indices, one per shape; shape_index names those with an id (Mitsuba
    # merges shapes that share a BSDF into one mesh without an id)
    assert len(setup.shapes) == len(setup.scene.shapes())
    named = [i for i, s in enumerate(setup.shapes, 1) if s.id()]
    assert sorted(setup.shape_index.values()) == named


def test_size_override():
    setup = scenes.load("glossy-cornell", size=(40, 30))
    assert setup.size == (40, 30)
    assert tuple(setup.sensor.film().size()) == (40, 30)
    assert setup.camera(0).resolution == (40, 30)
    f = Renderer(setup).render(0)
    assert f.numpy("color").shape == (30, 40, 3)
    assert f.camera.resolution == (40, 30)


def test_load_static_holds_the_rest_pose():
    setup = scenes.load_static("glossy-cornell", size=(40, 30))
    assert not setup.animated and setup.size == (40, 30)
    np.testing.assert_array_equal(setup.camera_matrix(7), setup.rest_camera)
    assert setup.object_transforms(7) == {}


def test_set_frame_moves_camera_and_objects():
    setup = scenes.load("glossy-cornell", size=SIZE)
    sphere_shape = next(s for s in setup.scene.shapes() if s.id() == "sphere")

    def centre():
        bb = sphere_shape.bbox()
        return np.array([bb.center()[i] for i in range(3)], dtype=np.float64)

    setup.set_frame(0)
    cam0, c0 = Camera.from_sensor(setup.sensor), centre()
    setup.set_frame(10)
    cam10, c10 = Camera.from_sensor(setup.sensor), centre()
    # the sensor really is posed as camera(frame) says
    np.testing.assert_allclose(cam0.to_world, setup.camera(0).to_world, atol=1e-6)
    np.testing.assert_allclose(cam10.to_world, setup.camera(10).to_world, atol=1e-6)
    assert np.linalg.norm(cam10.position - cam0.position) > 0.1
    # the sphere slides along x by its object path
    moved = setup.object_transforms(10)[setup.shape_index["sphere"]][:3, 3]
    np.testing.assert_allclose(c10 - c0, moved - setup.object_transforms(0)[
        setup.shape_index["sphere"]][:3, 3], atol=1e-5)
    assert abs(c10[0] - c0[0]) > 0.05
    # back to frame 0 restores the rest pose exactly (no accumulated drift)
    setup.set_frame(0)
    np.testing.assert_allclose(centre(), c0, atol=1e-6)


def test_mesh_ids_are_stable_across_loads():
    """mesh_id (1-based index of a shape) must name the same shape every time a scene is loaded,
    or frames rendered in different runs (a reference and its 1 spp frames) disagree."""
    first = scenes.load("glossy-cornell", size=SIZE).shape_index
    for _ in range(20):
        assert scenes.load("glossy-cornell", size=SIZE).shape_index == first


# -- XML scenes ----------------------------------------------------------------------------------


def test_xml_scene_uses_its_film_and_name(tmp_path):
    path = write(tmp_path, scene_xml(FLOOR + CONSTANT), "my_room.xml")
    setup = scenes.load(path)
    assert setup.name == "my_room"
    assert setup.source == path
    assert setup.size == (40, 30)
    # no integrator in the file: Mitsuba's default path depth, -1 (no limit), as Mitsuba renders it
    assert setup.max_depth == -1 and setup.scene.integrator() is None
    r = Renderer(setup)
    assert r.mitsuba_max_depth == -1 and r.max_depth_from.startswith("Mitsuba's default")
    assert not setup.animated
    np.testing.assert_array_equal(setup.camera(7).to_world, setup.camera(0).to_world)


def test_xml_sensor_is_reproduced(tmp_path):
    """glossrt's own sensor shoots the same rays as the file's sensor, also for a vertical
    field of view (Mitsuba converts it to x_fov)."""
    extra = '\n    <string name="fov_axis" value="y"/>'
    path = write(tmp_path, scene_xml(FLOOR + CONSTANT, fov=30.0, sensor_extra=extra))
    setup = scenes.load(path)
    expected_x_fov = 2 * math.degrees(math.atan(math.tan(math.radians(15.0)) * 40 / 30))
    assert setup.fov == pytest.approx(expected_x_fov, rel=1e-5)
    uv = mi.Point2f([0.0, 1.0, 0.5, 0.25], [0.0, 1.0, 0.5, 0.8])
    ours, _ = setup.sensor.sample_ray(0.0, 0.5, uv, mi.Point2f(0.5, 0.5))
    theirs, _ = setup.scene.sensors()[0].sample_ray(0.0, 0.5, uv, mi.Point2f(0.5, 0.5))
    np.testing.assert_allclose(np.array(ours.d), np.array(theirs.d), atol=1e-6)
    np.testing.assert_allclose(np.array(ours.o), np.array(theirs.o), atol=1e-6)


def test_orbit_rotates_about_the_look_at_point(tmp_path):
    path = write(tmp_path, scene_xml(FLOOR + sphere('<bsdf type="diffuse"/>') + CONSTANT))
    frames, degrees = 5, 40.0
    setup = scenes.load(path, size=SIZE, orbit=degrees, frames=frames)
    assert setup.animated
    static = scenes.load(path, size=SIZE)
    pivot = setup.look_at_point()
    rest = static.camera(0)
    np.testing.assert_array_equal(setup.camera(0).to_world, rest.to_world)
    # the pivot lies on the rest camera's view axis
    f0 = rest.to_world[:3, 2]
    off = pivot - rest.position
    assert np.linalg.norm(np.cross(off, f0)) < 1e-6 * np.linalg.norm(off)
    up = rest.to_world[:3, 1]
    r0 = rest.position - pivot
    # the transforms are built in float32 (Mitsuba's ScalarTransform4f): ~1e-6 relative
    for k in range(frames):
        cam = setup.camera(k)
        r = cam.position - pivot
        # same distance to the pivot, same height along the up axis
        assert np.linalg.norm(r) == pytest.approx(np.linalg.norm(r0), rel=1e-6)
        assert np.dot(r, up) == pytest.approx(np.dot(r0, up), abs=1e-5)
        # still looking at the pivot
        fwd = cam.to_world[:3, 2]
        assert np.linalg.norm(np.cross(-r / np.linalg.norm(r), fwd)) < 1e-5
        # rotated by k * degrees / (frames - 1) about the up axis
        a, b = r0 - np.dot(r0, up) * up, r - np.dot(r, up) * up
        angle = math.degrees(math.atan2(np.linalg.norm(np.cross(a, b)), np.dot(a, b)))
        assert angle == pytest.approx(k * degrees / (frames - 1), abs=1e-3)
    # and the sensor follows
    setup.set_frame(frames - 1)
    np.testing.assert_allclose(Camera.from_sensor(setup.sensor).to_world,
                               setup.camera(frames - 1).to_world, atol=1e-6)


def test_orbit_does_not_replace_a_builtin_camera_path():
    with pytest.warns(UserWarning, match="animates its own camera: orbit 90.0 is ignored"):
        a = scenes.load("glossy-cornell", size=SIZE, orbit=90.0, frames=4)
    b = scenes.load("glossy-cornell", size=SIZE)
    for k in range(4):
        np.testing.assert_array_equal(a.camera(k).to_world, b.camera(k).to_world)


BSDFS = {
    # plugin -> (XML, expected G-buffer roughness, has diffuse albedo)
    "diffuse": ('<bsdf type="diffuse"><rgb name="reflectance" value="0.6, 0.5, 0.4"/></bsdf>',
                1.0, True),
    "conductor": ('<bsdf type="conductor"><string name="material" value="Au"/></bsdf>', 0.0,
                  False),
    "roughconductor": ('<bsdf type="roughconductor"><string name="material" value="Cu"/>'
                       '<float name="alpha" value="0.2"/></bsdf>', 0.2, False),
    "plastic": ('<bsdf type="plastic"><rgb name="diffuse_reflectance" value="0.1, 0.4, 0.2"/>'
                "</bsdf>", 0.0, True),
    "roughplastic": ('<bsdf type="roughplastic"><float name="alpha" value="0.15"/>'
                     '<rgb name="diffuse_reflectance" value="0.4, 0.1, 0.1"/></bsdf>', 0.15,
                     True),
    "twosided": ('<bsdf type="twosided"><bsdf type="roughconductor">'
                 '<string name="material" value="Al"/><float name="alpha" value="0.3"/>'
                 "</bsdf></bsdf>", 0.3, False),
}


def _check_frame(frame, setup):
    for name in RADIANCE + ("color", "albedo_diffuse", "albedo_specular", "normal", "position",
                            "roughness", "mesh_id", "motion"):
        assert np.all(np.isfinite(frame.numpy(name))), name
    depth = frame.numpy("depth")[..., 0]
    hit = frame.numpy("mesh_id")[..., 0] > 0
    assert np.all(np.isfinite(depth[hit])) and np.all(np.isposinf(depth[~hit]))
    assert frame.meta["nonfinite_samples"] == 0
    assert np.all(frame.numpy("color") >= 0)


def _render_object(tmp_path, body):
    """Render an XML scene body at 1 spp and as a reference, check both frames, and return the
    reference frame with the mask of the shape with id "object" (seen by > 10 pixels)."""
    setup = scenes.load(write(tmp_path, scene_xml(body)), size=SIZE)
    r = Renderer(setup)
    for f in (r.render(0), r.render_reference(0, spp=8)):
        _check_frame(f, setup)
    obj = f.numpy("mesh_id")[..., 0] == setup.shape_index["object"]
    assert obj.sum() > 10
    return f, obj


@pytest.mark.parametrize("plugin", sorted(BSDFS))
def test_xml_bsdf_renders(tmp_path, plugin):
    xml, alpha, has_diffuse = BSDFS[plugin]
    body = FLOOR + sphere(xml) + AREA_LIGHT + CONSTANT
    f, obj = _render_object(tmp_path, body)
    assert f.numpy("color")[obj].mean() > 0  # lit
    np.testing.assert_allclose(f.numpy("roughness")[..., 0][obj], alpha, rtol=1e-6)
    assert bool(np.any(f.numpy("albedo_diffuse")[obj] > 0)) == has_diffuse
    assert np.all(f.numpy("albedo_specular")[obj] > 0) == (plugin not in ("diffuse",))


def test_xml_twosided_is_lit_from_behind(tmp_path):
    # a one-sided diffuse panel seen from its back is black; the twosided one is lit
    def panel(bsdf):
        return ('\n  <shape type="rectangle" id="object"><transform name="to_world">'
                '<rotate y="1" angle="180"/><translate y="0.6"/></transform>'
                f"{bsdf}</shape>")

    diffuse = '<bsdf type="diffuse"><rgb name="reflectance" value="0.7, 0.7, 0.7"/></bsdf>'
    light = ('\n  <emitter type="point"><point name="position" x="0" y="1" z="3"/>'
             '<rgb name="intensity" value="10, 10, 10"/></emitter>')
    means = {}
    for kind, bsdf in (("one", diffuse), ("two", f'<bsdf type="twosided">{diffuse}</bsdf>')):
        setup = scenes.load(write(tmp_path, scene_xml(panel(bsdf) + light), f"{kind}.xml"),
                            size=SIZE)
        f = Renderer(setup).render_reference(0, spp=4)
        _check_frame(f, setup)
        obj = f.numpy("mesh_id")[..., 0] == setup.shape_index["object"]
        assert obj.sum() > 10
        means[kind] = f.numpy("color")[obj].mean()
        # the G-buffer normal faces the camera either way
        n, p = f.numpy("normal")[obj], f.numpy("position")[obj]
        assert np.all(np.sum(n * (f.camera.position - p), -1) > 0)
    assert means["one"] == 0 and means["two"] > 0.05


def _write_envmap(path) -> None:
    h, w = 8, 16
    img = np.zeros((h, w, 3), np.float32)
    img[: h // 2] = (0.5, 0.7, 1.0)  # sky
    img[h // 2:] = (0.2, 0.15, 0.1)  # ground
    img[1, 3] = (50.0, 45.0, 40.0)  # sun
    mi.Bitmap(img).write(str(path))


EMITTERS = {
    "area": AREA_LIGHT,
    "point": ('\n  <emitter type="point"><point name="position" x="1" y="2.5" z="1"/>'
              '<rgb name="intensity" value="8, 8, 8"/></emitter>'),
    "constant": CONSTANT,
    "envmap": ('\n  <emitter type="envmap"><string name="filename" value="sky.exr"/>'
               '<float name="scale" value="1.5"/></emitter>'),
}


@pytest.mark.parametrize("plugin", sorted(EMITTERS))
def test_xml_emitter_renders(tmp_path, plugin):
    _write_envmap(tmp_path / "sky.exr")
    bsdf = ('<bsdf type="roughplastic"><float name="alpha" value="0.3"/>'
            '<rgb name="diffuse_reflectance" value="0.5, 0.5, 0.5"/></bsdf>')
    body = FLOOR + sphere(bsdf) + EMITTERS[plugin]
    f, obj = _render_object(tmp_path, body)
    assert f.numpy("direct_diffuse")[obj].mean() > 0
    assert f.numpy("direct_specular")[obj].mean() > 0
    bg = f.numpy("mesh_id")[..., 0] == 0
    assert bg.sum() > 0
    em = f.numpy("emission")
    if plugin in ("constant", "envmap"):
        assert np.all(em[bg] > 0)  # the environment is seen behind the scene
        if plugin == "constant":
            np.testing.assert_allclose(em[bg], np.broadcast_to((0.2, 0.3, 0.4), em[bg].shape),
                                       rtol=1e-6)
    else:
        assert not np.any(em[bg])
    if plugin == "point":
        assert not np.any(em)  # a point light is never seen directly


# -- errors --------------------------------------------------------------------------------------


@pytest.mark.parametrize("plugin, kind", [("dielectric", "bsdf"), ("principled", "bsdf"),
                                          ("spot", "emitter"), ("projector", "emitter")])
def test_every_rgb_plugin_loads_and_renders(tmp_path, plugin, kind):
    """BSDFs and emitters beyond the analytic ones load and render through Mitsuba's own
    interfaces (they were refused once): the frame is finite and lit."""
    if kind == "bsdf":
        body = FLOOR + sphere(f'<bsdf type="{plugin}"/>') + CONSTANT
    else:
        power = "intensity" if plugin == "spot" else "irradiance"
        body = FLOOR + (f'\n  <emitter type="{plugin}"><transform name="to_world"><lookat '
                        'origin="0, 3, 0.1" target="0, 0, 0" up="0, 1, 0"/></transform>'
                        f'<rgb name="{power}" value="20"/></emitter>')
    f = Renderer(scenes.load(write(tmp_path, scene_xml(body)), size=SIZE), frozen=False).render(0)
    c = f.numpy("color")
    assert np.isfinite(c).all() and c.mean() > 0


def test_a_plugin_mitsuba_cannot_load_in_rgb_is_one_line(tmp_path):
    """A polarized-only plugin Mitsuba refuses in the RGB variant: one SceneError line naming
    the variant and Mitsuba's reason."""
    body = FLOOR + sphere('<bsdf type="measured_polarized"><string name="filename" '
                          'value="missing.pbsdf"/></bsdf>') + CONSTANT
    with pytest.raises(SceneError, match="variant.*measured_polarized|measured_polarized.*"
                                         "variant") as e:
        scenes.load(write(tmp_path, scene_xml(body)))
    assert len(str(e.value).splitlines()) == 1 and "llvm_ad_rgb" in str(e.value)


def test_mitsubas_own_refusal_of_a_nested_dielectric_is_reported(tmp_path):
    """Mitsuba refuses a twosided around a transmitting BSDF: its reason, on one line."""
    body = FLOOR + sphere('<bsdf type="twosided"><bsdf type="roughdielectric"/></bsdf>')
    with pytest.raises(SceneError, match="transmission") as e:
        scenes.load(write(tmp_path, scene_xml(body + CONSTANT)))
    assert len(str(e.value).splitlines()) == 1


def test_unsupported_sensor(tmp_path):
    text = (scene_xml(FLOOR + CONSTANT).replace('type="perspective"', 'type="orthographic"')
            .replace('<float name="fov" value="45"/>', ""))
    with pytest.raises(SceneError, match="orthographic"):
        scenes.load(write(tmp_path, text))


def test_missing_file(tmp_path):
    with pytest.raises(SceneError, match="not found"):
        scenes.load(str(tmp_path / "nope.xml"))
    with pytest.raises(SceneError, match="no-such-scene"):
        scenes.load("no-such-scene")
    with pytest.raises(SceneError):
        scenes.load(str(tmp_path))  # a folder is not a scene


def test_broken_xml(tmp_path):
    path = write(tmp_path, scene_xml(FLOOR + CONSTANT).replace("</scene>", ""))
    with pytest.raises(SceneError, match="XML"):
        scenes.load(path)


def test_xml_that_mitsuba_rejects(tmp_path):
    # well-formed XML, but not a valid scene: Mitsuba's error becomes a SceneError
    body = FLOOR + '\n  <shape type="no_such_shape_plugin"/>'
    with pytest.raises(SceneError, match="Mitsuba could not load"):
        scenes.load(write(tmp_path, scene_xml(body + CONSTANT)))


@pytest.mark.parametrize("size", [(0, 10), (10, 0), (-4, 10), (10, -1)])
def test_bad_size(tmp_path, size):
    with pytest.raises(SceneError, match="positive"):
        scenes.load("glossy-cornell", size=size)
    with pytest.raises(SceneError, match="positive"):
        scenes.load(write(tmp_path, scene_xml(FLOOR + CONSTANT)), size=size)


@pytest.mark.parametrize("text", ["0x10", "10x-3", "abc", "10", "10x10x3", ""])
def test_parse_size_errors(text):
    with pytest.raises(SceneError):
        scenes.parse_size(text)


def test_parse_size():
    assert scenes.parse_size("640x360") == (640, 360)
    assert scenes.parse_size("32X24") == (32, 24)


def test_scene_error_is_a_glossrt_error():
    assert issubclass(SceneError, GlossrtError)


# -- integrator max_depth ------------------------------------------------------------------------


def test_xml_integrator_max_depth_is_used(tmp_path):
    integrator = '\n  <integrator type="path"><integer name="max_depth" value="5"/></integrator>'
    setup = scenes.load(write(tmp_path, scene_xml(FLOOR + CONSTANT, integrator=integrator)),
                        size=SIZE)
    assert setup.max_depth == 5
    r = Renderer(setup)
    assert r.max_depth == 5
    assert r.render(0).meta["max_depth"] == 5
    # an explicit max_depth still wins
    assert Renderer(setup, max_depth=2).max_depth == 2


def test_xml_integrator_max_depth_from_default_parameter(tmp_path):
    """``<default name="max_depth" value="5"/>`` + ``value="$max_depth"`` (as Mitsuba's own
    example scenes write it): Mitsuba's integrator gets 5, so must glossrt."""
    defaults = '\n  <default name="max_depth" value="5"/>'
    integrator = ('\n  <integrator type="path">'
                  '<integer name="max_depth" value="$max_depth"/></integrator>')
    path = write(tmp_path, scene_xml(FLOOR + CONSTANT, integrator=integrator,
                                     defaults=defaults))
    setup = scenes.load(path, size=SIZE)
    assert "max_depth = 5" in str(setup.scene.integrator())  # what Mitsuba itself uses
    assert setup.max_depth == 5


def test_xml_integrator_unbounded_max_depth(tmp_path):
    """Mitsuba's max_depth = -1 means "no limit" (its path integrator's default). glossrt must
    either render such a scene or refuse it with a GlossrtError, not crash with a bare
    ValueError (which the CLI does not catch)."""
    integrator = '\n  <integrator type="path"><integer name="max_depth" value="-1"/></integrator>'
    path = write(tmp_path, scene_xml(FLOOR + CONSTANT, integrator=integrator))
    try:
        setup = scenes.load(path, size=SIZE)
        r = Renderer(setup)
    except GlossrtError:
        return
    f = r.render(0)
    _check_frame(f, setup)


def test_glossy_spheres_roughness_matches_the_phong_exponents():
    """glossy-spheres: three GGX spheres, alpha = sqrt(2 / (s + 2)) for s = 1000, 100, 10,
    each visible, with its alpha in the roughness channel; static camera."""
    from glossrt.scenes.library import GLOSSY_SPHERES_PHONG, phong_to_alpha

    setup = scenes.load("glossy-spheres", size=(32, 24))
    assert setup.max_depth == 3 and not setup.animated
    assert phong_to_alpha(100.0) == pytest.approx(math.sqrt(2.0 / 102.0))
    f = Renderer(setup).render(0)
    mesh = f.numpy("mesh_id")[..., 0]
    rough = f.numpy("roughness")[..., 0]
    xs = []
    for s in GLOSSY_SPHERES_PHONG:
        mask = mesh == setup.shape_index[f"sphere_s{s:g}"]
        assert mask.sum() >= 20, s
        np.testing.assert_allclose(rough[mask], phong_to_alpha(s), rtol=1e-6)
        xs.append(np.nonzero(mask)[1].mean())
        # reflections of diffusely lit surfaces: the sphere's indirect specular is not black
        assert f.numpy("indirect_specular")[mask].mean() > 0.0
    assert xs == sorted(xs)  # side by side, sharpest on the left
    with pytest.raises(ValueError):
        phong_to_alpha(-3.0)


@pytest.mark.parametrize("body, named", [
    (FLOOR + AREA_LIGHT.replace('<translate y="2.5"/>', '<translate x="nan" y="2.5"/>'),
     "area light 'lamp'"),
    (FLOOR.replace('<scale value="3"/>', '<scale value="inf"/>') + AREA_LIGHT, "shape 'floor'"),
    (FLOOR + '\n  <emitter type="point" id="bulb"><point name="position" x="0" y="nan" z="1"/>'
     '</emitter>', "light 'bulb'"),
    (FLOOR + '\n  <emitter type="directional" id="sun"><vector name="direction" x="0" y="inf"'
     ' z="-1"/></emitter>', "light 'sun'"),
])
def test_non_finite_geometry_is_refused(tmp_path, body, named):
    """A NaN / Inf in a light's or an object's placement used to load and render silently
    (an area light with a NaN transform gave a black image, no warning)."""
    with pytest.raises(SceneError, match=f"{named}.*NaN/Inf"):
        scenes.load(write(tmp_path, scene_xml(body + CONSTANT)))


def test_non_finite_camera_is_refused(tmp_path):
    # (Mitsuba itself refuses a NaN lookat, not a NaN translation after it)
    text = scene_xml(FLOOR + CONSTANT).replace('up="0, 1, 0"/>',
                                               'up="0, 1, 0"/><translate x="nan"/>')
    with pytest.raises(SceneError, match="camera.*NaN/Inf"):
        scenes.load(write(tmp_path, text))


def test_non_finite_vertices_of_a_merged_mesh_are_refused(tmp_path):
    """Mitsuba merges id-less shapes sharing a BSDF into one mesh with empty bounds: its
    vertices are checked, not its bounds."""
    floor = FLOOR.replace(' id="floor"', "").replace('<scale value="3"/>',
                                                    '<scale value="3"/><translate x="nan"/>')
    wall = floor.replace('angle="-90"', 'angle="0"').replace("nan", "0")
    with pytest.raises(SceneError, match="shape ''.*NaN/Inf"):
        scenes.load(write(tmp_path, scene_xml(floor + wall + AREA_LIGHT + CONSTANT)))


def test_animation_paths_giving_nan_are_refused():
    """A camera or object path that returns a NaN/Inf matrix for some frame is named at that
    frame (the pose used to be applied: a NaN camera rendered a black frame)."""
    base = scenes.load("glossy-cornell", size=SIZE)
    good_cam, (sid, good_obj) = base.camera_path, next(iter(base.object_paths.items()))

    def bad_at_3(path):
        return lambda f: np.full((4, 4), np.nan) if f == 3 else path(f)

    for cam, obj, named in ((bad_at_3(good_cam), good_obj, "camera path"),
                            (good_cam, bad_at_3(good_obj), f"shape {sid!r}")):
        setup = scenes.SceneSetup(base.name, base.scene, size=SIZE, camera_path=cam,
                                  object_paths={sid: obj})
        setup.set_frame(2)
        with pytest.raises(SceneError, match=f"{named}.*NaN/Inf transform at frame 3"):
            setup.set_frame(3)


# -- <include>d files ----------------------------------------------------------------------------

BOX_WALLS = "".join(
    f"""
  <shape type="rectangle">
    <transform name="to_world">{t}</transform>
    <bsdf type="twosided"><bsdf type="diffuse"><rgb name="reflectance" value="0.8, 0.8, 0.8"/>
    </bsdf></bsdf>
  </shape>"""
    for t in ('<rotate x="1" angle="-90"/><translate y="-1"/>',  # floor
              '<rotate x="1" angle="90"/><translate y="1"/>',  # ceiling
              '<translate z="-1"/>', '<rotate y="1" angle="180"/><translate z="1"/>',
              '<rotate y="1" angle="90"/><translate x="-1"/>',
              '<rotate y="1" angle="-90"/><translate x="1"/>'))

# a closed white box lit by a small ceiling lamp behind the camera: many bounces matter
BOX_SCENE = """<scene version="3.0.0">
  <include filename="{include}"/>
  <sensor type="perspective">
    <float name="fov" value="60"/>
    <transform name="to_world"><lookat origin="0, 0.2, 0.9" target="0, -0.4, -1" up="0, 1, 0"/>
    </transform>
    <film type="hdrfilm"><integer name="width" value="24"/><integer name="height" value="18"/>
    </film>
  </sensor>
  <shape type="rectangle">
    <transform name="to_world">
      <rotate x="1" angle="90"/><scale value="0.15"/><translate y="0.99" z="0.6"/>
    </transform>
    <emitter type="area"><rgb name="radiance" value="20, 20, 20"/></emitter>
  </shape>{walls}
</scene>
"""


def _box(tmp_path, included: str) -> str:
    write(tmp_path, f'<scene version="3.0.0">{included}\n</scene>\n', "base.xml")
    return write(tmp_path, BOX_SCENE.format(include="base.xml", walls=BOX_WALLS), "box.xml")


def test_included_files_are_checked(tmp_path):
    """A bad roughness in an <include>d file is refused like one in the scene file itself
    (the check reads the scene Mitsuba loaded, not the top-level XML text); a glass sphere
    there is rendered."""
    bad = sphere('<bsdf type="roughconductor"><float name="alpha" value="-0.3"/></bsdf>')
    with pytest.raises(SceneError, match="roughness"):
        scenes.load(_box(tmp_path, bad))
    setup = scenes.load(_box(tmp_path, sphere('<bsdf type="dielectric"/>')))
    assert "SmoothDielectric" in {s.bsdf().class_name() for s in setup.shapes}


@pytest.mark.slow
def test_included_integrator_depth_is_used_and_matches_mitsuba(tmp_path):
    """Mitsuba's own Cornell box sets max_depth in an <include>d base.xml; glossrt read only
    the top-level file and rendered such scenes at depth 3, darker than Mitsuba's `path`
    without a word (measured here: half as bright; 10% on Mitsuba's Cornell box). The box
    below gets max_depth 6 from base.xml: glossrt's mean brightness must equal that of
    Mitsuba rendering the loaded scene with its own integrator, within the measured Monte
    Carlo error (4 independent batches each)."""
    path = _box(tmp_path, '<integrator type="path"><integer name="max_depth" value="6"/>'
                          '</integrator>')
    setup = scenes.load(path)
    assert setup.max_depth == 6 and "max_depth = 6" in str(setup.scene.integrator())
    r = Renderer(setup, frozen=False)
    assert r.render(0).meta["max_depth"] == 6
    assert r.render(0).meta["max_depth_from"] == "scene file"
    ours = np.array([r.render_reference(0, spp=32, seed=s).numpy("color").mean()
                     for s in range(4)])
    theirs = np.array([np.array(mi.render(setup.scene, sensor=setup.sensor, spp=32,
                                          seed=1_000_003 * (s + 1))).mean() for s in range(4)])
    se = np.sqrt(ours.var(ddof=1) / 4 + theirs.var(ddof=1) / 4)
    diff = ours.mean() - theirs.mean()
    assert abs(diff) < 5 * se + 0.005 * theirs.mean(), (ours, theirs)  # 0.5%: pixel filter
    # power: depth 3 is far darker than the measured error
    d3 = Renderer(setup, max_depth=3, frozen=False).render_reference(0, spp=32).numpy("color")
    assert theirs.mean() - d3.mean() > 10 * se + 0.05 * theirs.mean()


def test_file_without_integrator_gets_mitsubas_unbounded_depth(tmp_path):
    """No integrator anywhere (the included file sets none): Mitsuba's default max_depth -1
    (no limit, Russian roulette from depth 5), said in the frame header."""
    setup = scenes.load(_box(tmp_path, ""), size=(8, 6))
    assert setup.scene.integrator() is None and setup.max_depth == -1
    f = Renderer(setup, frozen=False).render(0)
    assert f.meta["max_depth"] == -1 and f.meta["rr_depth"] == 5
    assert "Mitsuba's default" in f.meta["max_depth_from"]


# -- bad sizes and roughness ---------------------------------------------------------------------


@pytest.mark.parametrize("size", [(64.5, 48), (64, 48.0), ("64", 48), (True, 48), (64,),
                                  (64, 48, 3), 64, (0, 48), (-2, 48)])
def test_non_integer_or_non_positive_size_is_a_clear_error(tmp_path, size):
    with pytest.raises(SceneError, match="size"):
        scenes.load("glossy-cornell", size=size)
    with pytest.raises(SceneError, match="size"):
        scenes.load(write(tmp_path, scene_xml(FLOOR + CONSTANT)), size=size)


def test_numpy_integer_size_is_accepted():
    setup = scenes.load("glossy-cornell", size=(np.int64(20), np.int32(10)))
    assert setup.size == (20, 10) and all(type(v) is int for v in setup.size)


@pytest.mark.parametrize("alpha", ['<float name="alpha" value="-0.2"/>',
                                   '<float name="alpha_u" value="-0.1"/>'
                                   '<float name="alpha_v" value="0.3"/>',
                                   '<float name="alpha_u" value="0.3"/>'
                                   '<float name="alpha_v" value="-0.1"/>'])
def test_negative_roughness_is_refused_naming_the_bsdf(tmp_path, alpha):
    """Mitsuba's roughconductor takes a negative alpha as it is; glossrt wrote it to the
    roughness channel. Now: one clear error naming the BSDF, at load."""
    bsdf = f'<bsdf type="twosided" id="bad_metal"><bsdf type="roughconductor">{alpha}</bsdf></bsdf>'
    with pytest.raises(SceneError, match="bad_metal.*roughness"):
        scenes.load(write(tmp_path, scene_xml(FLOOR + sphere(bsdf) + CONSTANT)))


def test_negative_roughness_is_refused_by_the_renderer_too():
    """A SceneSetup made without scenes.load (no load-time check) still cannot put a negative
    alpha into the roughness channel: the renderer's material table refuses it."""
    scene = mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "film": {"type": "hdrfilm", "width": 8, "height": 6}},
        "ball": {"type": "sphere", "bsdf": {"type": "roughconductor", "id": "neg", "alpha": -0.3}},
    })
    setup = scenes.SceneSetup("neg", scene)
    with pytest.raises(GlossrtError, match="neg.*roughness"):
        Renderer(setup)


# -- scenes from anywhere: built-in name, XML path, scene dict, mi.Scene -----------------------


def _forms_dict() -> dict:
    """A small scene as a Mitsuba dict; :data:`FORMS_XML` is the same scene as XML."""
    T = mi.ScalarTransform4f
    return {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 3},
        "sensor": {"type": "perspective", "fov": 45.0,
                   "to_world": T().look_at(origin=[0, 1, 4], target=[0, 0.3, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 40, "height": 30}},
        "floor": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(3.0),
                  "bsdf": {"type": "roughplastic", "distribution": "ggx", "alpha": 0.2,
                           "diffuse_reflectance": {"type": "rgb", "value": [0.5, 0.4, 0.3]}}},
        "ball": {"type": "sphere", "center": [0, 0.5, 0], "radius": 0.5,
                 "bsdf": {"type": "roughconductor", "distribution": "ggx", "alpha": 0.1}},
        "lamp": {"type": "rectangle",
                 "to_world": T().translate([0, 2.5, 0]).rotate([1, 0, 0], 90).scale(0.5),
                 "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [10, 10, 10]}}},
    }


FORMS_XML = """<scene version="3.0.0">
  <integrator type="path"><integer name="max_depth" value="3"/></integrator>""" + \
    SENSOR.format(fov=45.0, extra="") + """
  <shape type="rectangle" id="floor">
    <transform name="to_world"><rotate x="1" angle="-90"/><scale value="3"/></transform>
    <bsdf type="roughplastic"><string name="distribution" value="ggx"/>
      <float name="alpha" value="0.2"/>
      <rgb name="diffuse_reflectance" value="0.5, 0.4, 0.3"/></bsdf>
  </shape>
  <shape type="sphere" id="ball">
    <point name="center" x="0" y="0.5" z="0"/><float name="radius" value="0.5"/>
    <bsdf type="roughconductor"><string name="distribution" value="ggx"/>
      <float name="alpha" value="0.1"/></bsdf>
  </shape>
  <shape type="rectangle" id="lamp">
    <transform name="to_world">
      <scale value="0.5"/><rotate x="1" angle="90"/><translate y="2.5"/>
    </transform>
    <emitter type="area"><rgb name="radiance" value="10, 10, 10"/></emitter>
  </shape>
</scene>
"""


def _render_all(setup, **kw) -> dict:
    f = Renderer(setup, frozen=False, **kw).render(0)
    return {name: f.numpy(name) for name in f.names if name != "motion"}


@pytest.mark.slow
def test_scene_forms_render_alike(tmp_path):
    """A scene dict, the same scene loaded by Mitsuba (mi.Scene), and the same scene written
    as XML (a str path and a PathLike) give the same frame, the same name rules and the
    integrator's max_depth."""
    path = tmp_path / "forms.xml"
    path.write_text(FORMS_XML)
    d = _forms_dict()
    setups = {"dict": scenes.load(d, size=SIZE),
              "scene": scenes.load(mi.load_dict(d), size=SIZE),
              "xml": scenes.load(str(path), size=SIZE),
              "pathlike": scenes.load(path, size=SIZE)}
    assert [s.name for s in setups.values()] == ["dict", "scene", "forms", "forms"]
    assert {s.max_depth for s in setups.values()} == {3}
    assert setups["dict"].max_depth_from == "scene dict"
    assert setups["scene"].max_depth_from == "scene object"
    assert not any(s.animated for s in setups.values())
    ref = _render_all(setups["xml"])
    assert ref["color"].max() > 0 and len(np.unique(ref["mesh_id"])) == 3  # floor, ball, sky
    for name, setup in setups.items():
        got = _render_all(setup)
        for ch, v in ref.items():
            np.testing.assert_allclose(got[ch], v, rtol=1e-5, atol=1e-6, err_msg=f"{name} {ch}")
    # the dict is not consumed or changed: it loads again
    assert scenes.load(d, size=SIZE).name == "dict"


@pytest.mark.slow
def test_builtin_dict_renders_like_the_builtin():
    """A built-in's own scene dict (no animation) renders frame 0 like the built-in, at the
    same path depth; mi.cornell_box() loads with its integrator's max_depth."""
    from glossrt.scenes import library  # noqa: F401

    spec = scenes.BUILTIN["glossy-cornell"][0]()
    a = _render_all(scenes.load("glossy-cornell", size=SIZE), max_depth=3)
    b = _render_all(scenes.load(spec.scene_dict, size=SIZE), max_depth=3)
    for ch, v in a.items():  # (frame 0 poses the built-in's moving sphere: float rounding)
        np.testing.assert_allclose(b[ch], v, rtol=1e-4, atol=1e-5, err_msg=ch)
    box = scenes.load(mi.cornell_box(), size=(8, 8))
    assert (box.name, box.max_depth, box.animated) == ("dict", 8, False)


@pytest.mark.parametrize("bad", [3, None, 2.5, b"scene.xml", ["glossy-cornell"],
                                 {"type": "shape"}, {"type": "scene", "x": {"type": "nope"}},
                                 {"type": "scene", "ball": {"type": "sphere"}}])
def test_bad_scene_forms_are_refused(bad):
    """Anything else: one SceneError (a GlossrtError) saying what a scene can be, a dict
    that is not a scene or that Mitsuba cannot load, a scene without a sensor."""
    with pytest.raises(SceneError) as e:
        scenes.load(bad, size=SIZE)
    assert len(str(e.value).splitlines()) == 1


def test_scene_forms_get_the_same_checks():
    """A dict or mi.Scene is checked like an XML file: a glass ball loads in every form, a
    negative roughness is refused."""
    d = _forms_dict()
    d["ball"]["bsdf"] = {"type": "dielectric"}
    for scene in (d, mi.load_dict(d)):
        assert scenes.load(scene).integrator_error is None
    d = _forms_dict()
    d["ball"]["bsdf"]["alpha"] = -0.5
    with pytest.raises(SceneError, match="roughness"):
        scenes.load(d)
