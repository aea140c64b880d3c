"""Built-in procedural scenes (nothing is downloaded). Each is one decorated function."""

from __future__ import annotations

import numpy as np

from . import (
    SceneSpec,
    builtin,
    look_at,
    mi,  # the variant is already selected by the package
    rotation_about,
    translation,
    wobble,
)

T = mi.ScalarTransform4f


def _diffuse(rgb) -> dict:
    return {"type": "diffuse", "reflectance": {"type": "rgb", "value": list(rgb)}}


def _rect(to_world, bsdf: dict, emitter: dict | None = None) -> dict:
    d = {"type": "rectangle", "to_world": to_world, "bsdf": bsdf}
    if emitter is not None:
        d["emitter"] = emitter
    return d


def _sensor(origin, target, fov: float, width: int, height: int) -> dict:
    return {
        "type": "perspective",
        "fov": fov,
        "fov_axis": "x",
        "to_world": T().look_at(origin=origin, target=target, up=[0, 1, 0]),
        "film": {"type": "hdrfilm", "width": width, "height": height},
    }


@builtin(
    "glossy-cornell",
    "Cornell box: GGX gold sphere (alpha 0.05, moving), rough plastic box (alpha 0.3), "
    "quad light; the camera sways left and right",
)
def glossy_cornell() -> SceneSpec:
    white, red, green = (0.73, 0.73, 0.73), (0.63, 0.065, 0.05), (0.14, 0.45, 0.09)
    scene = {
        "type": "scene",
        "sensor": _sensor([0, 0, 3.9], [0, 0, 0], 40.0, 320, 240),
        "floor": _rect(T().translate([0, -1, 0]).rotate([1, 0, 0], -90), _diffuse(white)),
        "ceiling": _rect(T().translate([0, 1, 0]).rotate([1, 0, 0], 90), _diffuse(white)),
        "back": _rect(T().translate([0, 0, -1]), _diffuse(white)),
        "left": _rect(T().translate([-1, 0, 0]).rotate([0, 1, 0], 90), _diffuse(red)),
        "right": _rect(T().translate([1, 0, 0]).rotate([0, 1, 0], -90), _diffuse(green)),
        "light": _rect(
            T().translate([0, 0.995, 0]).rotate([1, 0, 0], 90).scale(0.3),
            _diffuse((0, 0, 0)),
            {"type": "area", "radiance": {"type": "rgb", "value": [12.0, 10.5, 8.0]}},
        ),
        "sphere": {
            "type": "sphere",
            "center": [-0.4, -0.62, -0.2],
            "radius": 0.38,
            "bsdf": {"type": "roughconductor", "material": "Au", "alpha": 0.05},
        },
        "box": {
            "type": "cube",
            "to_world": T().translate([0.45, -0.7, 0.15]).rotate([0, 1, 0], 25).scale(0.3),
            "bsdf": {
                "type": "roughplastic",
                "alpha": 0.3,
                "diffuse_reflectance": {"type": "rgb", "value": [0.15, 0.25, 0.6]},
            },
        },
    }
    sway = wobble(6.0, 60.0)  # degrees
    slide = wobble(0.25, 48.0)  # metres along x
    rest = look_at([0, 0, 3.9], [0, 0, 0], [0, 1, 0])
    return SceneSpec(
        scene,
        camera_path=lambda f: rotation_about((0, 0, 0), (0, 1, 0), sway(f)) @ rest,
        object_paths={"sphere": lambda f: translation((slide(f), 0.0, 0.0))},
        max_depth=3,
    )


def _checker(n_pixels: int, cells: int, low: float, high: float) -> np.ndarray:
    idx = (np.arange(n_pixels) * cells // n_pixels) % 2
    return np.where(idx[:, None] ^ idx[None, :], high, low).astype(np.float32)[..., None]


def _stripes(n_pixels: int, cells: int, low: float, high: float) -> np.ndarray:
    idx = (np.arange(n_pixels) * cells // n_pixels) % 2
    img = np.where(idx[None, :] == 1, high, low) * np.ones((n_pixels, 1))
    return img.astype(np.float32)[..., None]


def _alpha_texture(img: np.ndarray) -> dict:
    return {
        "type": "bitmap",
        "bitmap": mi.Bitmap(img),
        "raw": True,
        "filter_type": "nearest",
        "wrap_mode": "clamp",
    }


@builtin(
    "roughness-map",
    "glossy floor and wall whose GGX roughness texture steps sharply between alpha 0.02 "
    "and 0.5 (Tokuyoshi 2015, fig. 4), coloured blocks and strip lights reflected in them",
)
def roughness_map() -> SceneSpec:
    floor_alpha = _checker(256, 6, 0.02, 0.5)
    wall_alpha = _stripes(256, 8, 0.02, 0.5)
    scene = {
        "type": "scene",
        "sensor": _sensor([0, 1.6, 4.2], [0, 0.2, 0], 50.0, 320, 240),
        "floor": _rect(
            T().rotate([1, 0, 0], -90).scale(2.5),
            {"type": "roughconductor", "material": "Al", "alpha": _alpha_texture(floor_alpha)},
        ),
        "wall": _rect(
            T().translate([0, 1.5, -2.5]).scale([2.5, 1.5, 1]),
            # Mitsuba's roughplastic takes no roughness texture: a conductor does
            {"type": "roughconductor", "material": "Cu", "alpha": _alpha_texture(wall_alpha)},
        ),
        "block_red": {
            "type": "cube",
            "to_world": T().translate([-0.9, 0.35, -0.6]).rotate([0, 1, 0], 20).scale(0.35),
            "bsdf": _diffuse((0.7, 0.12, 0.08)),
        },
        "block_blue": {
            "type": "cube",
            "to_world": T().translate([0.8, 0.25, -1.0]).rotate([0, 1, 0], -30).scale(0.25),
            "bsdf": _diffuse((0.1, 0.2, 0.7)),
        },
        "ball": {
            "type": "sphere",
            "center": [0.1, 0.4, 0.2],
            "radius": 0.4,
            "bsdf": _diffuse((0.8, 0.75, 0.3)),
        },
        "strip_light": _rect(
            T().translate([0, 2.2, -2.3]).rotate([1, 0, 0], 60).scale([1.8, 0.12, 1]),
            _diffuse((0, 0, 0)),
            {"type": "area", "radiance": {"type": "rgb", "value": [30.0, 28.0, 24.0]}},
        ),
        "top_light": _rect(
            T().translate([0, 3.0, 0.5]).rotate([1, 0, 0], 90).scale(0.6),
            _diffuse((0, 0, 0)),
            {"type": "area", "radiance": {"type": "rgb", "value": [4.0, 4.0, 4.0]}},
        ),
        "sky": {"type": "constant", "radiance": {"type": "rgb", "value": [0.05, 0.06, 0.08]}},
    }
    rest = look_at([0, 1.6, 4.2], [0, 0.2, 0], [0, 1, 0])
    sway = wobble(5.0, 60.0)
    return SceneSpec(
        scene,
        camera_path=lambda f: rotation_about((0, 0, 0), (0, 1, 0), sway(f)) @ rest,
        max_depth=3,
    )
