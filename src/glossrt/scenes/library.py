"""Built-in procedural scenes (nothing is downloaded). Each is one decorated function."""

from __future__ import annotations

import functools
import math

import numpy as np

from ..backend import mi
from ..errors import GlossrtError
from . import (
    SceneSpec,
    builtin,
    look_at,
    rotation_about,
    translation,
    wobble,
)


def T(*args) -> mi.ScalarTransform4f:
    """``mi.ScalarTransform4f(*args)`` (the backend is chosen when a scene is built)."""
    return mi.ScalarTransform4f(*args)


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
            "bsdf": {"type": "roughconductor", "distribution": "ggx", "material": "Au",
                     "alpha": 0.05},
        },
        "box": {
            "type": "cube",
            "to_world": T().translate([0.45, -0.7, 0.15]).rotate([0, 1, 0], 25).scale(0.3),
            "bsdf": {
                "type": "roughplastic",
                "distribution": "ggx",
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
            {"type": "roughconductor", "distribution": "ggx", "material": "Al",
             "alpha": _alpha_texture(floor_alpha)},
        ),
        "wall": _rect(
            T().translate([0, 1.5, -2.5]).scale([2.5, 1.5, 1]),
            # Mitsuba's roughplastic takes no roughness texture: a conductor does
            {"type": "roughconductor", "distribution": "ggx", "material": "Cu",
             "alpha": _alpha_texture(wall_alpha)},
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
        raise GlossrtError(f"Phong exponent must be > -2, got {s}")
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
            "bsdf": {"type": "roughconductor", "distribution": "ggx", "material": "Ag",
                     "alpha": phong_to_alpha(s)},
        }
    return SceneSpec(scene, max_depth=3)


# -- polygon-light: a teapot and a sphere under a moving, rotating quad light --------------------

#: GGX roughness of the ``polygon-light-a*`` variants (``polygon-light`` is 0.25)
POLYGON_LIGHT_ALPHAS = (0.1, 0.25, 0.5, 1.0)
#: teapot tessellation of the built-ins (``teapot_mesh(n)``: 2082 vertices, 4032 triangles)
POLYGON_LIGHT_TEAPOT_N = 8
#: floor grid (quads per side) and sphere rings of the polygon-light scenes (meshes throughout)
POLYGON_LIGHT_FLOOR_N = 48
POLYGON_LIGHT_SPHERE_N = 16
#: frames of one period of the light's animation
POLYGON_LIGHT_PERIOD = 96
#: the quad light at rest (frame 0): centre, half extents, downward tilt (degrees) of its
#: emitting side from facing the camera (+z), constant radiance
POLYGON_LIGHT_CENTRE = (0.0, 1.3, -1.5)
POLYGON_LIGHT_HALF = (0.9, 0.45)
POLYGON_LIGHT_TILT = 50.0
POLYGON_LIGHT_RADIANCE = (12.0, 11.4, 10.8)


def stained_glass(height: int = 96, width: int = 160, cells: int = 28, seed: int = 7,
                  peak: float = 30.0) -> np.ndarray:
    """(H, W, 3) float32 linear radiance: a stained-glass window -- Voronoi cells of
    saturated glass colours separated by dark lead lines, inside a dark frame. ``peak`` is
    the brightest channel value (the built-in's: mean luminance 8.6, against 11.4 for the
    constant light)."""
    rng = np.random.default_rng(seed)
    palette = np.array([(0.9, 0.12, 0.08), (0.1, 0.3, 0.95), (0.95, 0.75, 0.1),
                        (0.15, 0.75, 0.25), (0.6, 0.15, 0.8), (0.95, 0.95, 0.85),
                        (0.1, 0.75, 0.8), (0.95, 0.45, 0.1)])
    sites = rng.uniform(0.0, 1.0, (cells, 2)) * (width, height)
    colour = palette[rng.integers(0, len(palette), cells)] * rng.uniform(0.6, 1.0, (cells, 1))
    yy, xx = np.mgrid[0:height, 0:width] + 0.5
    d = np.hypot(xx[..., None] - sites[:, 0], yy[..., None] - sites[:, 1])  # (H, W, cells)
    order = np.argsort(d, axis=-1)
    d1 = np.take_along_axis(d, order[..., :1], -1)[..., 0]
    d2 = np.take_along_axis(d, order[..., 1:2], -1)[..., 0]
    img = colour[order[..., 0]]
    lead = (d2 - d1) < 1.6
    border = max(2, min(height, width) // 24)
    frame = np.zeros((height, width), bool)
    frame[:border], frame[-border:], frame[:, :border], frame[:, -border:] = True, True, True, True
    img[lead | frame] = 0.02
    return (img * peak).astype(np.float32)


def polygon_light_path(frame: int) -> np.ndarray:
    """Rigid motion of ``polygon-light``'s quad light at ``frame`` (applied on top of its rest
    pose; identity at frame 0), periodic over :data:`POLYGON_LIGHT_PERIOD` frames: its centre
    sweeps 0.9 m left and right above and behind the objects, bobbing +-0.2 m and coming
    0.6 m closer half-way, while the quad rolls about its normal (+-45 degrees) and turns
    about the vertical (+-30 degrees) to follow the objects."""
    theta = 2.0 * math.pi * frame / POLYGON_LIGHT_PERIOD
    c0 = np.array(POLYGON_LIGHT_CENTRE)
    c = c0 + np.array([0.9 * math.sin(theta), 0.2 * math.sin(2.0 * theta),
                       0.3 * (1.0 - math.cos(theta))])
    tilt = math.radians(POLYGON_LIGHT_TILT)
    normal = (0.0, -math.sin(tilt), math.cos(tilt))
    roll = rotation_about((0, 0, 0), normal, 45.0 * math.sin(theta))
    yaw = rotation_about((0, 0, 0), (0, 1, 0), -30.0 * math.sin(theta))
    return translation(c) @ yaw @ roll @ translation(-c0)


def polygon_light_scene(alpha: float = 0.25, textured: bool = False,
                        teapot_n: int = POLYGON_LIGHT_TEAPOT_N,
                        floor_n: int = POLYGON_LIGHT_FLOOR_N,
                        sphere_n: int = POLYGON_LIGHT_SPHERE_N) -> SceneSpec:
    """The ``polygon-light`` scenes (Heitz et al. 2016, figs. 1, 6, 7): a Utah teapot (GGX
    ``roughplastic``: orange diffuse + GGX specular, ``alpha``) and a copper sphere (GGX
    ``roughconductor``, ``alpha``) on a grey glossy floor (GGX ``roughplastic``, ``alpha``)
    under one quad light (``rectangle`` with an ``area`` emitter, id ``light``; at rest
    behind the objects, facing them and the camera, tilted down) that moves and rotates
    (:func:`polygon_light_path`), seen directly and in the floor. ``textured``:
    the light's radiance is a :func:`stained_glass` bitmap instead of a constant. The teapot
    is :func:`glossrt.scenes.teapot.teapot_shape` with ``teapot_n`` x ``teapot_n`` quads per
    patch, 0.3 units per data unit (0.945 m tall), turned z-up to y-up. Every object is a
    triangle mesh with vertex normals, so that per-vertex methods (BSPVT shadows) have
    vertices everywhere: the floor a ``floor_n`` x ``floor_n`` grid, the sphere
    ``sphere_n`` rings of ``2 sphere_n`` quads."""
    from .teapot import grid_mesh, mesh_shape, sphere_mesh, teapot_shape

    alpha = float(alpha)
    if not 0.0 < alpha <= 1.0:
        raise GlossrtError(f"GGX alpha must lie in (0, 1], got {alpha}")
    teapot_to_world = (T().translate([-0.45, 0.0, -0.1]).rotate([0, 1, 0], 25)
                       .rotate([1, 0, 0], -90).scale(0.3))
    cx, cy, cz = POLYGON_LIGHT_CENTRE
    hx, hz = POLYGON_LIGHT_HALF
    if textured:
        radiance = mi.load_dict({"type": "bitmap", "bitmap": mi.Bitmap(stained_glass()),
                                 "raw": True, "filter_type": "bilinear", "wrap_mode": "clamp"})
        # (Mitsuba builds its sampling table lazily; glossrt's Renderer samples every emitter
        # once before recording its frozen kernels, see render._warm_emitters)
    else:
        radiance = {"type": "rgb", "value": list(POLYGON_LIGHT_RADIANCE)}
    scene = {
        "type": "scene",
        "sensor": _sensor([0, 1.25, 3.4], [0.05, 0.5, -0.4], 55.0, 320, 240),
        "floor": mesh_shape(
            "floor", *grid_mesh(floor_n), T().rotate([1, 0, 0], -90).scale(3.0),
            # a stronger coat than the default (eta 1.9: F0 = 0.097) for clear reflections
            {"type": "roughplastic", "distribution": "ggx", "alpha": alpha, "int_ior": 1.9,
             "diffuse_reflectance": {"type": "rgb", "value": [0.25, 0.25, 0.27]}},
        ),
        "teapot": teapot_shape(
            teapot_n, teapot_to_world,
            {"type": "roughplastic", "distribution": "ggx", "alpha": alpha,
             "diffuse_reflectance": {"type": "rgb", "value": [0.75, 0.32, 0.1]}}),
        "sphere": mesh_shape(
            "sphere", *sphere_mesh(sphere_n),
            T().translate([0.85, 0.32, -0.25]).rotate([1, 0, 0], -90).scale(0.32),
            {"type": "roughconductor", "distribution": "ggx", "material": "Cu", "alpha": alpha}),
        # rest pose: behind the objects, the rectangle's +z normal (its emitting side) turned
        # POLYGON_LIGHT_TILT degrees down from +z, towards the objects and the camera
        "light": _rect(
            T().translate([cx, cy, cz]).rotate([1, 0, 0], POLYGON_LIGHT_TILT)
            .scale([hx, hz, 1.0]),
            _diffuse((0, 0, 0)),
            {"type": "area", "radiance": radiance},
        ),
    }
    return SceneSpec(scene, object_paths={"light": polygon_light_path}, max_depth=3)


@builtin(
    "polygon-light",
    "Utah teapot (GGX rough plastic) and copper sphere on a glossy floor under a moving, "
    "rotating quad light, GGX alpha 0.25 (Heitz et al. 2016, figs. 1, 6); variants "
    "polygon-light-a0.1 / -a0.25 / -a0.5 / -a1.0 and polygon-light-textured",
)
def polygon_light() -> SceneSpec:
    return polygon_light_scene(0.25)


def _register_polygon_light_alphas() -> None:
    for a in POLYGON_LIGHT_ALPHAS:
        builtin(
            f"polygon-light-a{a}",
            f"polygon-light with GGX alpha {a} on the teapot, sphere and floor",
        )(functools.partial(polygon_light_scene, a))


_register_polygon_light_alphas()


@builtin(
    "polygon-light-textured",
    "polygon-light (GGX alpha 0.25) whose moving quad light shows a stained-glass texture "
    "(Heitz et al. 2016, fig. 7: textured polygon light)",
)
def polygon_light_textured() -> SceneSpec:
    return polygon_light_scene(0.25, textured=True)


#: (teapot quads per patch side, floor grid, sphere rings) of the paper-size polygon-light
#: meshes (issue 28): the default density's 8 / 48 / 16 proportions scaled to about 17K
#: vertices (Okuno & Iwasaki, Table 1: the fig. 6 teapot scene has 17K) and past 100K (their
#: figs. 1 and 7 meshes have 506K and 138K). Vertices: teapot ``32 n^2 + 4 n + 2``, floor
#: ``(m + 1)^2``, sphere ``2 k (k - 1) + 2``: 7262 + 8281 + 1742 = 17285 and
#: 43958 + 49729 + 10806 = 104493.
PAPER_SIZE_DENSITIES = {"teapot-17k": (15, 90, 30), "teapot-100k": (37, 222, 74)}


@builtin(
    "teapot-17k",
    "polygon-light (GGX alpha 0.25) tessellated to 17285 vertices (teapot 15, floor 90, "
    "sphere 30): the size of Okuno & Iwasaki's Table 1 teapot scene (17K vertices)",
)
def teapot_17k() -> SceneSpec:
    t, f, sph = PAPER_SIZE_DENSITIES["teapot-17k"]
    return polygon_light_scene(0.25, teapot_n=t, floor_n=f, sphere_n=sph)


@builtin(
    "teapot-100k",
    "polygon-light (GGX alpha 0.25) tessellated to 104493 vertices (teapot 37, floor 222, "
    "sphere 74): a mesh past 100K vertices, as Okuno & Iwasaki's 138K and 506K scenes",
)
def teapot_100k() -> SceneSpec:
    t, f, sph = PAPER_SIZE_DENSITIES["teapot-100k"]
    return polygon_light_scene(0.25, teapot_n=t, floor_n=f, sphere_n=sph)


#: GGX alpha of the light-shapes spheres, left to right: mirror-like to rough
LIGHT_SHAPES_ALPHAS = (0.01, 0.05, 0.15, 0.4)


def _planar_mesh_light(name: str, pts2: np.ndarray, to_world, radiance) -> object:
    """A convex polygon light (2D points ``pts2`` counter-clockwise in its xy plane, emitting
    towards +z) as a triangle-fan mesh with an ``area`` emitter."""
    from .teapot import mesh_shape

    pts2 = np.asarray(pts2, np.float64)
    v = np.c_[pts2, np.zeros(len(pts2))]
    f = np.array([[0, k, k + 1] for k in range(1, len(pts2) - 1)], np.uint32)
    return mesh_shape(name, v, f, None, to_world, _diffuse((0, 0, 0)),
                      {"type": "area", "radiance": {"type": "rgb", "value": list(radiance)}})


@builtin(
    "light-shapes",
    "four GGX spheres from mirror-like to rough (alpha 0.01 / 0.05 / 0.15 / 0.4) on a glossy "
    "floor, reflecting lights of recognisable shapes: a window of four panes, a triangle, a "
    "ring of twelve quads and a textured light (Kimura & Tokoi, fig. 8)",
)
def light_shapes() -> SceneSpec:
    """The highlight-shape scene (issue 7): dark rough-plastic spheres (diffuse 0.03, so the
    highlights dominate) in a row; the lights (a 2 x 2 block: window, triangle / ring,
    stained glass) hang above the camera's view, in front of the spheres and facing them, so
    each sphere shows all four shapes, sharp on the left, blurred on the right."""
    lights_to = (T().look_at(origin=[0.0, 2.0, 1.25], target=[0.0, 0.42, 0.0], up=[0, 1, 0])
                 @ T().scale([1.5, 1.5, 1.0]))
    scene: dict = {
        "type": "scene",
        "sensor": _sensor([0, 1.0, 3.6], [0, 0.42, 0], 50.0, 320, 180),
        "floor": _rect(T().rotate([1, 0, 0], -90).scale(4.0),
                       {"type": "roughplastic", "distribution": "ggx", "alpha": 0.2,
                        "diffuse_reflectance": {"type": "rgb", "value": [0.2, 0.2, 0.21]}}),
    }
    for k, a in enumerate(LIGHT_SHAPES_ALPHAS):
        scene[f"sphere{k}"] = {
            "type": "sphere", "center": [-1.5 + k, 0.42, 0.0], "radius": 0.42,
            "bsdf": {"type": "roughplastic", "distribution": "ggx", "alpha": a, "int_ior": 1.6,
                     "diffuse_reflectance": {"type": "rgb", "value": [0.03, 0.03, 0.03]}}}
    radiance = (20.0, 20.0, 18.0)
    area = {"type": "area", "radiance": {"type": "rgb", "value": list(radiance)}}
    # in the lights' plane (look_at frame: x, y), a 2 x 2 block of shapes ~0.7 m each
    # window: 2 x 2 panes of 0.3 with 0.08 frame bars
    for i in range(2):
        for j in range(2):
            cx, cy = -0.45 + (i - 0.5) * 0.38, 0.42 + (j - 0.5) * 0.38
            scene[f"light_window{2 * i + j}"] = _rect(
                lights_to @ T().translate([cx, cy, 0.0]).scale([0.15, 0.15, 1.0]),
                _diffuse((0, 0, 0)), area)
    tri = np.array([[-0.36, -0.3], [0.36, -0.3], [0.0, 0.34]])
    scene["light_triangle"] = _planar_mesh_light(
        "light_triangle", tri, lights_to @ T().translate([0.45, 0.42, 0.0]), radiance)
    # ring of 12 quads (annulus 0.2 - 0.34)
    for q in range(12):
        a0, a1 = 2 * math.pi * q / 12, 2 * math.pi * (q + 0.8) / 12
        quad = np.array([[0.2 * math.cos(a0), 0.2 * math.sin(a0)],
                         [0.34 * math.cos(a0), 0.34 * math.sin(a0)],
                         [0.34 * math.cos(a1), 0.34 * math.sin(a1)],
                         [0.2 * math.cos(a1), 0.2 * math.sin(a1)]])
        scene[f"light_ring{q:02d}"] = _planar_mesh_light(
            f"light_ring{q:02d}", quad, lights_to @ T().translate([-0.45, -0.42, 0.0]),
            radiance)
    tex = mi.load_dict({"type": "bitmap", "bitmap": mi.Bitmap(stained_glass(peak=40.0)),
                        "raw": True, "filter_type": "bilinear", "wrap_mode": "clamp"})
    scene["light_textured"] = _rect(
        lights_to @ T().translate([0.45, -0.42, 0.0]).scale([0.36, 0.26, 1.0]),
        _diffuse((0, 0, 0)), {"type": "area", "radiance": tex})
    return SceneSpec(scene, max_depth=3)


# -- normal-mapped: specular aliasing of a glossy, normal-mapped floor and sphere ----------------

#: GGX alpha of the ``normal-mapped`` floor and sphere (``roughconductor``, aluminium)
NORMAL_MAPPED_ALPHA_FLOOR = 0.05
NORMAL_MAPPED_ALPHA_SPHERE = 0.08
#: the normal map's resolution and seed (:func:`glossrt.scenes.normalmap.procedural_normal_map`)
NORMAL_MAPPED_MAP_SIZE = 1024
NORMAL_MAPPED_MAP_SEED = 3
#: metres per tile of the normal map on the floor (texel: 4 mm)
NORMAL_MAPPED_TILE = 4.0
#: the floor: normal-mapped for x >= NORMAL_MAPPED_SPLIT_X, flat (``floor_flat``) to its left
NORMAL_MAPPED_FLOOR_X = (-8.0, 8.0)
NORMAL_MAPPED_FLOOR_Z = (-30.0, 4.0)
NORMAL_MAPPED_SPLIT_X = -0.4
NORMAL_MAPPED_SPHERE = ((0.35, 0.5, -2.4), 0.5)  # centre, radius (resting on the floor)
NORMAL_MAPPED_EYE = (0.0, 0.42, 3.2)
NORMAL_MAPPED_TARGET = (0.15, -0.2, -1.6)


def normal_mapped_path(frame: int) -> np.ndarray:
    """Camera of ``normal-mapped`` at ``frame``: a slow dolly forward (3 mm per frame, level)
    while turning 0.06 degrees per frame to the left about the vertical through the eye
    (0.34 pixels per frame at 320 x 180): over 16 frames the view shifts by a few pixels."""
    rest = look_at(NORMAL_MAPPED_EYE, NORMAL_MAPPED_TARGET, (0, 1, 0))
    forward = rest[:3, 2] * np.array([1.0, 0.0, 1.0])
    forward /= np.linalg.norm(forward)
    turn = rotation_about(NORMAL_MAPPED_EYE, (0, 1, 0), 0.06 * frame)
    return translation(0.003 * frame * forward) @ turn @ rest


def _normal_mapped_bsdf(normal_map: np.ndarray, to_uv, alpha: float) -> dict:
    """Mitsuba ``normalmap`` (bilinear, repeating, raw bitmap) over a GGX aluminium
    ``roughconductor``."""
    return {
        "type": "normalmap",
        "normalmap": {"type": "bitmap", "bitmap": mi.Bitmap(normal_map), "raw": True,
                      "filter_type": "bilinear", "wrap_mode": "repeat", "to_uv": to_uv},
        "bsdf": {"type": "roughconductor", "distribution": "ggx", "material": "Al",
                 "alpha": alpha},
    }


@builtin(
    "normal-mapped",
    "glossy GGX aluminium floor and sphere with a high-frequency procedural normal map (bumps "
    "and scratches) seen at grazing angles, lit by a point, a directional and a small area "
    "light; slow camera motion; a flat floor strip (floor_flat) on the left (specular "
    "aliasing, Tokuyoshi & Kaplanyan 2016, figs. 1-3)",
)
def normal_mapped() -> SceneSpec:
    """Shape ids ``floor`` (normal-mapped, GGX alpha :data:`NORMAL_MAPPED_ALPHA_FLOOR`),
    ``floor_flat`` (the same conductor without normal map, the left strip
    x < :data:`NORMAL_MAPPED_SPLIT_X`), ``sphere`` (normal-mapped, alpha
    :data:`NORMAL_MAPPED_ALPHA_SPHERE`) and ``light`` (a small quad light high on the left,
    outside the view); emitters ``sun`` (directional) and ``lamp`` (point). The map
    (:func:`~glossrt.scenes.normalmap.procedural_normal_map`, 1 mm texels on the floor and
    the sphere; bumps of 5-35 mm) is partly resolved at the bottom of the image (pixels of
    ~3 x 8 mm on the floor) and far below a pixel in the distance, where its highlights
    sparkle; the camera is 0.42 m above the floor. The sphere's map has its
    green channel mirrored: Mitsuba's sphere parametrisation is left-handed (shading frame
    ``t`` runs along ``-dp/dv``), so the mirrored map is the normal field of a height field
    there too."""
    from .normalmap import procedural_normal_map

    nmap = procedural_normal_map(NORMAL_MAPPED_MAP_SIZE, NORMAL_MAPPED_MAP_SEED)
    nmap_sphere = nmap.copy()
    nmap_sphere[..., 1] = 1.0 - nmap_sphere[..., 1]
    (x0, x1), (z0, z1), xs = NORMAL_MAPPED_FLOOR_X, NORMAL_MAPPED_FLOOR_Z, NORMAL_MAPPED_SPLIT_X
    centre, radius = NORMAL_MAPPED_SPHERE

    def floor_rect(xa: float, xb: float) -> mi.ScalarTransform4f:
        # rectangle [-1, 1]^2 (normal +z) -> floor x in [xa, xb], z in [z0, z1]; u along +x,
        # v along -z
        return (T().translate([(xa + xb) / 2, 0.0, (z0 + z1) / 2]).rotate([1, 0, 0], -90)
                .scale([(xb - xa) / 2, (z1 - z0) / 2, 1.0]))

    tiles_u, tiles_v = (x1 - xs) / NORMAL_MAPPED_TILE, (z1 - z0) / NORMAL_MAPPED_TILE
    # a whole number of tiles around the equator (no seam), as close as that allows to the
    # floor's texel size; half as many from pole to pole (square texels at the equator)
    sphere_tiles = max(1, round(2.0 * math.pi * radius / NORMAL_MAPPED_TILE))
    scene = {
        "type": "scene",
        "sensor": _sensor(list(NORMAL_MAPPED_EYE), list(NORMAL_MAPPED_TARGET), 50.0, 320, 180),
        "floor": _rect(floor_rect(xs, x1), _normal_mapped_bsdf(
            nmap, T().scale([tiles_u, tiles_v, 1.0]), NORMAL_MAPPED_ALPHA_FLOOR)),
        "floor_flat": _rect(floor_rect(x0, xs), {
            "type": "roughconductor", "distribution": "ggx", "material": "Al",
            "alpha": NORMAL_MAPPED_ALPHA_FLOOR}),
        "sphere": {"type": "sphere", "center": list(centre), "radius": radius,
                   "bsdf": _normal_mapped_bsdf(
                       nmap_sphere, T().scale([sphere_tiles, sphere_tiles / 2.0, 1.0]),
                       NORMAL_MAPPED_ALPHA_SPHERE)},
        # low sun ahead on the right (11 degrees up): sparkly glare on the right half
        "sun": {"type": "directional", "direction": [-0.3, -0.2, 1.0],
                "irradiance": {"type": "rgb", "value": [0.6, 0.57, 0.5]}},
        # right, beyond the sphere: glints on the near floor and on the sphere's rim
        "lamp": {"type": "point", "position": [2.2, 1.2, -5.0],
                 "intensity": {"type": "rgb", "value": [6.0, 6.0, 6.6]}},
        # small quad light high on the left, beyond the view: its glossy reflection on the
        # flat strip, glints on the normal-mapped floor
        "light": _rect(
            T().look_at(origin=[-1.5, 2.4, -6.0], target=[0.0, 0.0, -1.0], up=[0, 1, 0])
            .scale([0.35, 0.2, 1.0]),
            _diffuse((0, 0, 0)),
            {"type": "area", "radiance": {"type": "rgb", "value": [30.0, 28.0, 25.0]}},
        ),
    }
    return SceneSpec(scene, camera_path=normal_mapped_path, max_depth=3)


#: the normal map's mip level of ``normal-mapped-toksvig`` (a box filter of 2^level texels
#: per side; glossrt's choice)
NORMAL_MAPPED_TOKSVIG_LEVEL = 3


@builtin(
    "normal-mapped-toksvig",
    "normal-mapped with each normal map replaced by its Toksvig-filtered mip level 3 and the "
    "matching per-texel GGX roughness (Toksvig 2005; the scene of Tokuyoshi 2015's fig. 7 "
    "analogue)",
)
def normal_mapped_toksvig() -> SceneSpec:
    """``normal-mapped`` with Toksvig-filtered normal maps and roughness textures
    (:func:`~glossrt.scenes.normalmap.toksvig` at :data:`NORMAL_MAPPED_TOKSVIG_LEVEL`)."""
    from .normalmap import toksvig

    spec = normal_mapped()
    d = spec.scene_dict
    for sid, alpha in (("floor", NORMAL_MAPPED_ALPHA_FLOOR),
                       ("sphere", NORMAL_MAPPED_ALPHA_SPHERE)):
        bsdf = d[sid]["bsdf"]
        tex = bsdf["normalmap"]
        # the bitmap the scene built (the sphere's green channel mirrored already)
        nmap = np.array(tex["bitmap"], dtype=np.float32)
        filtered, rough = toksvig(nmap, alpha, NORMAL_MAPPED_TOKSVIG_LEVEL)
        tex["bitmap"] = mi.Bitmap(filtered)
        bsdf["bsdf"]["alpha"] = {"type": "bitmap", "bitmap": mi.Bitmap(rough), "raw": True,
                                 "filter_type": "bilinear", "wrap_mode": "repeat",
                                 "to_uv": tex["to_uv"]}
    spec.description = f"normal-mapped, Toksvig mip level {NORMAL_MAPPED_TOKSVIG_LEVEL}"
    return spec
