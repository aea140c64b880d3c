"""The light-shapes scene (issue 7): its polygon lights are what the docs say, they face the
spheres, the camera does not see them directly, and the spheres span mirror-like to rough."""

from __future__ import annotations

import numpy as np

from glossrt import backend

backend.ensure()

from glossrt import render, scenes  # noqa: E402
from glossrt.lights.scene import polygon_lights  # noqa: E402
from glossrt.scenes.library import LIGHT_SHAPES_ALPHAS  # noqa: E402


def test_light_shapes_lights_and_view():
    setup = scenes.load("light-shapes", size=(96, 54))
    lights = polygon_lights(setup, 0)
    ids = sorted(lt.id for lt in lights)
    assert len(lights) == 18
    assert sum(i.startswith("light_window") for i in ids) == 4
    assert sum(i.startswith("light_ring") for i in ids) == 12
    tri = [lt for lt in lights if lt.id == "light_triangle"][0]
    assert len(tri.vertices) == 3
    tex = [lt for lt in lights if lt.id == "light_textured"][0]
    assert tex.texture is not None and tex.texture.shape[2] == 3
    centre = np.array([0.0, 0.42, 0.0])
    for lt in lights:  # every light faces the spheres' row
        assert lt.normal @ (centre - lt.centroid) > 0
    gb = render.Renderer(setup).render(0)
    seen = set(np.unique(gb.numpy("mesh_id")).astype(int).tolist())
    shapes = scenes.stable_shapes(setup.scene)
    light_ids = {k + 1 for k, s in enumerate(shapes) if s.is_emitter()}
    assert not seen & light_ids  # the camera does not see the lights themselves
    rough = gb.numpy("roughness")[..., 0]
    for a in LIGHT_SHAPES_ALPHAS:
        assert np.any(np.isclose(rough, a, rtol=1e-4))
