"""Built-in procedural scenes (nothing is downloaded). Each is one decorated function."""

from __future__ import annotations

import math

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


#: Phong exponents of the three spheres of ``glossy-spheres`` (Tokuyoshi 2015, fig. 6: three
#: materials of different Phong exponent), left to right: sharpest to roughest
GLOSSY_SPHERES_PHONG = (1000.0, 100.0, 10.0)


def phong_to_alpha(s: float) -> float:
    """GGX / Beckmann roughness matching a Phong exponent: ``alpha = sqrt(2 / (s + 2))``
    (Walter et al. 2007's Phong-Beckmann correspondence; the NDF sharpness ``2 / alpha^2``
    of Wang et al.'s SG is then ``s + 2``)."""
    if not s > -2.0:
        raise ValueError(f"Phong exponent must be > -2, got {s}")
    return math.sqrt(2.0 / (s + 2.0))


def _bands(n_pixels: int, colours) -> np.ndarray:
    """Vertical colour bands (an RGB bitmap, ``len(colours)`` bands across)."""
    idx = np.arange(n_pixels) * len(colours) // n_pixels
    row = np.asarray(colours, dtype=np.float32)[idx]  # (n, 3)
    return np.ascontiguousarray(np.broadcast_to(row[None], (n_pixels // 4, n_pixels, 3)))


@builtin(
    "glossy-spheres",
    "three GGX silver spheres side by side, alpha = sqrt(2 / (s + 2)) for Phong exponents "
    "s = 1000, 100, 10 (left to right; Tokuyoshi 2015, figs. 5-6), in a closed room with "
    "red / green side walls, a colour-banded wall behind the camera, coloured blocks and a "
    "ceiling light (a rich indirect_specular channel); static camera",
)
def glossy_spheres() -> SceneSpec:
    """Shape ids ``sphere_s1000``, ``sphere_s100``, ``sphere_s10`` (GGX ``roughconductor``,
    material ``Ag``, ``alpha = sqrt(2 / (s + 2))`` = 0.0447, 0.140, 0.408): the spheres of
    Tokuyoshi 2015, fig. 6's three Phong exponents. The room (4 x 2.6 x 5 m) is closed so
    every reflected ray sees a diffusely lit surface. One emitter only: Mitsuba orders a
    scene's emitters differently from load to load, so with several emitters the same seed
    gives a different noise realisation per load (the experiments compare a frame rendered
    once with filters, but tests compare separate loads)."""
    red, green, white = (0.7, 0.06, 0.05), (0.08, 0.55, 0.1), (0.7, 0.7, 0.7)
    bands = _bands(256, [(0.8, 0.1, 0.1), (0.9, 0.8, 0.1), (0.1, 0.6, 0.15),
                         (0.1, 0.3, 0.85), (0.85, 0.85, 0.85), (0.6, 0.1, 0.7)])
    front_bsdf = {
        "type": "diffuse",
        "reflectance": {"type": "bitmap", "bitmap": mi.Bitmap(bands), "raw": True,
                        "filter_type": "nearest", "wrap_mode": "clamp"},
    }
    scene = {
        "type": "scene",
        "sensor": _sensor([0, 1.0, 2.3], [0, 0.5, -0.5], 45.0, 320, 240),
        "floor": _rect(T().rotate([1, 0, 0], -90).scale([2, 2.5, 1]), _diffuse(white)),
        "ceiling": _rect(T().translate([0, 2.6, 0]).rotate([1, 0, 0], 90).scale([2, 2.5, 1]),
                         _diffuse(white)),
        "back": _rect(T().translate([0, 1.3, -2.5]).scale([2, 1.3, 1]),
                      _diffuse((0.15, 0.25, 0.7))),
        # behind the camera, seen in the spheres: vertical colour bands
        "front": _rect(T().translate([0, 1.3, 2.5]).rotate([0, 1, 0], 180).scale([2, 1.3, 1]),
                       front_bsdf),
        "left": _rect(T().translate([-2, 1.3, 0]).rotate([0, 1, 0], 90).scale([2.5, 1.3, 1]),
                      _diffuse(red)),
        "right": _rect(T().translate([2, 1.3, 0]).rotate([0, 1, 0], -90).scale([2.5, 1.3, 1]),
                       _diffuse(green)),
        "light": _rect(
            T().translate([0, 2.59, 0.6]).rotate([1, 0, 0], 90).scale([0.8, 0.5, 1]),
            _diffuse((0, 0, 0)),
            {"type": "area", "radiance": {"type": "rgb", "value": [9.0, 8.5, 8.0]}},
        ),
        "block_yellow": {
            "type": "cube",
            "to_world": T().translate([-1.2, 0.3, 0.9]).rotate([0, 1, 0], 30).scale(0.3),
            "bsdf": _diffuse((0.85, 0.75, 0.1)),
        },
        "block_cyan": {
            "type": "cube",
            "to_world": T().translate([1.2, 0.25, 1.1]).rotate([0, 1, 0], -20).scale(0.25),
            "bsdf": _diffuse((0.1, 0.7, 0.75)),
        },
    }
    for k, s in enumerate(GLOSSY_SPHERES_PHONG):
        scene[f"sphere_s{s:g}"] = {
            "type": "sphere",
            "center": [-0.75 + 0.75 * k, 0.35, -0.5],
            "radius": 0.33,
            "bsdf": {"type": "roughconductor", "material": "Ag", "alpha": phong_to_alpha(s)},
        }
    return SceneSpec(scene, max_depth=3)
