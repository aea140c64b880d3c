"""glossrt.pipeline posing of point lights (issue 25): ``set_transform`` moves a point light
by its emitter id for the analytic direct stage and for the path tracer's deeper bounces,
against a scene loaded with the light at the moved place; no re-recording; bad names."""

from __future__ import annotations

import numpy as np
import pytest

from glossrt import pipeline, scenes
from glossrt.errors import GlossrtError

SIZE = (24, 18)
REST = (0.0, 1.5, 0.0)


def _rgb(v):
    return {"type": "rgb", "value": list(v)}


def _scene(lamp=REST):
    """A glossy floor, a glossy back wall and a box (occluder, casting the lamp's shadow)
    under a point light ``lamp`` (the dict key, so the emitter's id)."""
    from glossrt.backend import mi

    T = mi.ScalarTransform4f
    glossy = {"type": "roughplastic", "distribution": "ggx", "alpha": 0.3,
              "diffuse_reflectance": _rgb((0.5, 0.45, 0.4))}
    return {"type": "scene",
            "sensor": {"type": "perspective", "fov": 50.0,
                       "to_world": T().look_at(origin=[0, 2.0, 3.0], target=[0, 0.3, 0],
                                               up=[0, 1, 0]),
                       "film": {"type": "hdrfilm", "width": SIZE[0], "height": SIZE[1]}},
            "floor": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(2.0),
                      "bsdf": glossy},
            "wall": {"type": "rectangle",
                     "to_world": T().translate([0, 1.0, -1.0]).scale([2.0, 1.0, 1.0]),
                     "bsdf": glossy},
            "box": {"type": "cube", "to_world": T().translate([0.2, 0.4, 0]).scale(0.2),
                    "bsdf": {"type": "diffuse", "reflectance": _rgb((0.4, 0.4, 0.4))}},
            "lamp": {"type": "point", "position": [float(x) for x in lamp],
                     "intensity": _rgb((3.0, 2.8, 2.6))}}


OPTS = {"direct": "ltc", "indirect": "none", "taa": False, "max_depth": 3, "progress": False}


def _assert_same(a, b, skip=()):
    assert a.names == b.names
    for n in a.names:
        if n not in skip:
            np.testing.assert_array_equal(a.numpy(n), b.numpy(n), err_msg=n)


@pytest.mark.slow
def test_moved_point_light_equals_the_scene_loaded_with_it_there():
    """Frame 2 with the lamp moved by set_transform (a translation by exact binary
    fractions, so the moved position is the same float32 as the loaded one) is the frame 2
    of the pipeline on the scene Mitsuba loaded with the lamp there, bit for bit in every
    channel: the analytic direct layer (the lamp shaded with its shadow ray) and the path
    tracer's 1 spp layers, whose deeper bounces carry the lamp's light (excluded at the
    primary hit only). The move replays every frozen kernel."""
    move = scenes.translation((0.5, -0.25, 0.25))
    moved = pipeline.Pipeline(_scene(), **OPTS)
    rest = [moved.render(i) for i in range(3)]
    steady = moved.recordings()
    assert moved.setup.movable_lights() == ["lamp"]
    moved.set_transform("lamp", move)
    got = moved.render(2)
    assert moved.recordings() == steady  # the lamp's position is an input of the frame
    assert got.meta["pipeline"]["explicit_pose"]["point_lights"] == ["lamp"]
    built = pipeline.Pipeline(_scene((0.5, 1.25, 0.25)), **OPTS).render(2)
    _assert_same(got, built)
    # the move does change both layers (direct light and the path tracer's indirect light)
    for name in ("direct", "indirect"):
        change = np.abs(got.numpy(name) - rest[2].numpy(name)).max()
        assert change > 0.05, (name, change)
    assert got.numpy("indirect").mean() > 0.002
    # back to the rest position: the rest frame again
    moved.clear_pose()
    _assert_same(moved.render(2), rest[2])


@pytest.mark.slow
def test_rotated_point_light_and_the_accumulation_restarts():
    """A rotation about a point moves the lamp to R (p - c) + c (an isotropic light has no
    orientation): the converged frame equals the scene loaded there (float rounding of the
    rotated position aside); a moved light is a new pose, so the accumulation starts anew."""
    m = scenes.rotation_about((0.3, 0.0, 0.2), (0.0, 1.0, 0.0), 35.0)
    where = m[:3, :3] @ np.array(REST) + m[:3, 3]
    opts = dict(OPTS, accumulate=True, spp=8)
    moved = pipeline.Pipeline(_scene(), **opts)
    moved.render(0)
    assert moved.render(0).meta["spp"] == 16
    moved.set_transform("lamp", m)
    got = moved.render(0)
    assert got.meta["spp"] == 8  # started anew at the new pose
    built = pipeline.Pipeline(_scene(where), **opts).render(0)
    for name in ("direct", "color"):
        np.testing.assert_allclose(got.numpy(name), built.numpy(name), rtol=1e-4, atol=1e-5,
                                   err_msg=name)


XML = """<scene version="3.0.0">
  <sensor type="perspective">
    <float name="fov" value="45"/>
    <transform name="to_world"><lookat origin="0, 2, 5" target="0, 0.3, 0" up="0, 1, 0"/>
    </transform>
    <film type="hdrfilm"><integer name="width" value="16"/><integer name="height" value="12"/>
    </film>
  </sensor>
  <shape type="cube" id="floor">
    <transform name="to_world"><scale x="3" y="0.05" z="3"/></transform>
    <bsdf type="diffuse"/>
  </shape>
  <emitter type="point" id="bulb"><point name="position" x="0" y="1.5" z="0"/>
    <rgb name="intensity" value="2, 2, 2"/></emitter>
  <emitter type="directional"><vector name="direction" x="0" y="-1" z="0"/>
    <rgb name="irradiance" value="0.5, 0.5, 0.5"/></emitter>
</scene>
"""


def test_point_light_names_and_bad_input(tmp_path):
    """An XML point light is addressed by its id; an unknown name lists the movable shapes
    and point lights; a matrix that is not rigid is refused naming the light; nothing
    changes on a refusal."""
    path = tmp_path / "bulb.xml"
    path.write_text(XML)
    pipe = pipeline.Pipeline(str(path), **OPTS)
    assert pipe.setup.movable_lights() == ["bulb"]  # the directional light has no position
    with pytest.raises(GlossrtError, match="no shape 'lamp'.*shapes that can move are floor; "
                                           "the point lights bulb"):
        pipe.set_transform("lamp", np.eye(4))
    with pytest.raises(GlossrtError, match="'bulb'.*not rigid"):
        pipe.set_transform("bulb", np.diag([2.0, 1.0, 1.0, 1.0]))
    with pytest.raises(GlossrtError, match="NaN"):
        pipe.set_transform("bulb", np.full((4, 4), np.nan))
    assert not pipe.setup.light_overrides
    before = pipe.render(0)
    pipe.set_transform("bulb", scenes.translation((0.5, 0.0, 0.0)))
    after = pipe.render(0)
    assert np.abs(after.numpy("direct") - before.numpy("direct")).max() > 0.01
    pipe.set_transform("bulb", None)
    np.testing.assert_array_equal(pipe.render(0).numpy("direct"), before.numpy("direct"))
