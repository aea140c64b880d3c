"""Point and directional lights of a Mitsuba scene, for deferred shading (no visibility).

Conventions (checked against Mitsuba 3.9 by ``tests/test_analytic_lights.py``):

* A ``point`` emitter is a position and an RGB *radiant intensity* ``I`` (W/sr, Mitsuba's
  ``intensity``): at distance ``d`` it delivers the irradiance ``E = I / d^2`` on a surface
  facing it. Mitsuba keeps only the position (``mi.traverse`` key ``position``), whether the
  scene gave ``position`` or a ``to_world`` (its translation; rotation and scale do nothing).
* A ``directional`` emitter is a direction and an RGB *irradiance* ``E`` (W/m^2, Mitsuba's
  ``irradiance``) on a surface facing the light. Its ``to_world`` maps local +z to the
  direction the light *travels* (``direction`` in the scene description), so the direction
  towards the light is ``-direction``.
* Both are delta lights: direct light from them is ``sum_lights E f(wo, wi) cos(theta_i)``
  with ``wi`` towards the light -- what :func:`shade_unfiltered` evaluates with the BRDF of
  :func:`glossrt.lights.shading.brdf_cos`.

Mitsuba itself refuses a textured (spatially varying) ``intensity`` / ``irradiance`` on these
plugins; a spectral one (``regular``, ``irregular``, ``blackbody``: parameters other than a
single ``value``) raises :class:`GlossrtError` naming the emitter. Other emitter types
(``area``, ``constant``, ``envmap``, ``spot``, ...) are left out.
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import numpy as np

from ..backend import mi
from ..errors import GlossrtError
from ..jit import opaque
from ..scenes import stable_emitters, to_matrix
from .shading import ShadingPoints, brdf_cos

#: Mitsuba class names of the plugins this module reads
POINT_CLASS = "PointLight"
DIRECTIONAL_CLASS = "DirectionalEmitter"


@dataclass
class PointLight:
    """An isotropic point light: world ``position`` (3,) and RGB radiant ``intensity`` (3,)
    (W/sr; Mitsuba's ``intensity``). ``id``: the emitter's Mitsuba id ('' when none)."""

    position: np.ndarray
    intensity: np.ndarray
    id: str = ""

    def __post_init__(self):
        self.position = _vec3(self.position, "position", self.id)
        self.intensity = _vec3(self.intensity, "intensity", self.id, broadcast=True)


@dataclass
class DirectionalLight:
    """A distant light: unit ``direction`` (3,) the light *travels* in (Mitsuba: its
    ``to_world`` applied to +z) and RGB ``irradiance`` (3,) (W/m^2) on a surface facing it.
    ``id``: the emitter's Mitsuba id ('' when none)."""

    direction: np.ndarray
    irradiance: np.ndarray
    id: str = ""

    def __post_init__(self):
        d = _vec3(self.direction, "direction", self.id)
        n = float(np.linalg.norm(d))
        if not n > 0.0:
            raise GlossrtError(f"directional light {self.id!r}: its direction is zero")
        self.direction = d / n
        self.irradiance = _vec3(self.irradiance, "irradiance", self.id, broadcast=True)


def _vec3(value, what: str, name: str, broadcast: bool = False) -> np.ndarray:
    a = np.asarray(value, dtype=np.float64).ravel()
    if broadcast and a.size == 1:
        a = np.repeat(a, 3)
    if a.size != 3 or not np.all(np.isfinite(a)):
        raise GlossrtError(f"light {name!r}: {what} must be 3 finite numbers, got {value!r}")
    return a


def _emitter_name(emitter) -> str:
    return emitter.id() or f"<unnamed {emitter.class_name()}>"


def _rgb_param(emitter, params, key: str) -> np.ndarray:
    """The constant RGB value of the spectrum parameter ``key`` (``intensity`` /
    ``irradiance``) of an emitter; a GlossrtError for anything but one constant value."""
    keys = sorted(k for k in params.keys() if k.startswith(key + "."))
    if keys != [key + ".value"]:
        raise GlossrtError(
            f"{emitter.class_name()} {_emitter_name(emitter)!r}: its {key} is not a constant "
            f"RGB value (parameters {', '.join(keys) or 'none'}); spectral or textured "
            f"{key} is not supported -- use an rgb value")
    a = np.array(params[key + ".value"], dtype=np.float64).ravel()
    if a.size == 1:
        a = np.repeat(a, 3)
    if a.size != 3 or not np.all(np.isfinite(a)):
        raise GlossrtError(f"{emitter.class_name()} {_emitter_name(emitter)!r}: {key} "
                           f"{a.tolist()} is not 3 finite numbers")
    return a


def analytic_light(emitter) -> PointLight | DirectionalLight | None:
    """The light of one Mitsuba emitter in its current pose: a :class:`PointLight` for a
    ``point`` emitter, a :class:`DirectionalLight` for a ``directional`` one, ``None`` for
    any other type."""
    cls = emitter.class_name()
    if cls not in (POINT_CLASS, DIRECTIONAL_CLASS):
        return None
    params = mi.traverse(emitter)
    if cls == POINT_CLASS:
        pos = np.array(params["position"], dtype=np.float64).ravel()
        return PointLight(pos, _rgb_param(emitter, params, "intensity"), id=emitter.id())
    m = to_matrix(params["to_world"])
    return DirectionalLight(m[:3, 2], _rgb_param(emitter, params, "irradiance"),
                            id=emitter.id())


def analytic_lights(setup, frame: int | None = None) -> list[PointLight | DirectionalLight]:
    """Every ``point`` and ``directional`` emitter of ``setup`` (a
    :class:`glossrt.scenes.SceneSetup`, posed for ``frame`` first when given; or a bare
    ``mi.Scene``), in the scene's stable emitter order
    (:func:`glossrt.scenes.stable_emitters`: the same on every load). Other emitter types are
    left out; a spectral intensity / irradiance raises :class:`GlossrtError` naming the
    emitter."""
    if frame is not None and hasattr(setup, "set_frame"):
        setup.set_frame(int(frame))
    scene = getattr(setup, "scene", setup)
    lights = []
    for e in stable_emitters(scene):
        light = analytic_light(e)
        if light is not None:
            lights.append(light)
    return lights


def device_lights(lights) -> list[tuple]:
    """The lights as Dr.Jit values for :func:`incident` / :func:`shade_unfiltered`: per light
    ``("point", position: mi.Point3f, intensity: mi.Color3f)`` or ``("directional",
    direction: mi.Vector3f, irradiance: mi.Color3f)``, every number an opaque width-1 array
    (:func:`glossrt.jit.opaque`), so moving or dimming a light reuses the compiled kernels
    (only the number and kinds of lights are part of a kernel)."""
    out = []
    for light in lights:
        if isinstance(light, PointLight):
            out.append(("point", mi.Point3f(*opaque(light.position)),
                        mi.Color3f(*opaque(light.intensity))))
        elif isinstance(light, DirectionalLight):
            out.append(("directional", mi.Vector3f(*opaque(light.direction)),
                        mi.Color3f(*opaque(light.irradiance))))
        else:
            raise GlossrtError(f"not a point or directional light: {light!r}")
    return out


def incident(dev_light: tuple, p: mi.Point3f) -> tuple[mi.Vector3f, mi.Color3f]:
    """Unit direction ``wi`` from ``p`` (world space) towards the light and the irradiance
    ``E`` the light delivers at ``p`` on a surface facing it: ``I / d^2`` for a point light
    at distance ``d`` (``wi`` 0 and ``E`` 0 at the light's own position), the light's
    irradiance and ``wi = -direction`` for a directional light. Visibility is not tested.
    ``dev_light``: one entry of :func:`device_lights`."""
    kind, a, value = dev_light
    if kind == "point":
        d = mi.Vector3f(a - p)
        dist2 = dr.squared_norm(d)
        ok = dist2 > 0
        inv = dr.select(ok, dr.rcp(dist2), 0.0)
        wi = d * dr.select(ok, dr.rsqrt(dist2), 0.0)
        return wi, mi.Color3f(value * inv)
    if kind == "directional":
        zero = dr.zeros(mi.Float, dr.width(p))
        wi = mi.Vector3f(zero - a.x, zero - a.y, zero - a.z)
        return wi, mi.Color3f(value.x + zero, value.y + zero, value.z + zero)
    raise GlossrtError(f"unknown light kind {kind!r} (expected 'point' or 'directional')")


def shade_unfiltered(sp: ShadingPoints, lights_dev) -> tuple[mi.Color3f, mi.Color3f]:
    """Diffuse and specular direct light per lane (outgoing radiance towards ``sp.wo``):
    ``sum over lights of E f cos(theta_i)`` with ``E`` and ``wi`` from :func:`incident` and
    ``f cos(theta_i)`` from :func:`glossrt.lights.shading.brdf_cos` (Lambert and GGX; 0 below
    either horizon and on lanes without a surface). No shadows. ``lights_dev``: from
    :func:`device_lights`."""
    n = dr.width(sp.p)
    diff = dr.zeros(mi.Color3f, n)
    spec = dr.zeros(mi.Color3f, n)
    for light in lights_dev:
        wi, e = incident(light, sp.p)
        d, s = brdf_cos(sp, wi)
        diff = diff + e * d
        spec = spec + e * s
    return diff, spec
