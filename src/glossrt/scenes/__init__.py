"""Scenes: built-in procedural scenes and Mitsuba 3 XML files, with their animation.

A :class:`SceneSetup` wraps a loaded ``mi.Scene`` together with glossrt's own pinhole
sensor (so any output size can be asked for), a camera path and rigid object motion.
``setup.set_frame(i)`` poses camera and objects for frame ``i``; the renderer reads
``setup.camera(i)`` and ``setup.object_transforms(i)`` to build motion vectors.

Adding a built-in scene is one decorated function in :mod:`glossrt.scenes.library`::

    @builtin("my-scene", "one line shown by `glossrt render --help`")
    def my_scene() -> SceneSpec:
        return SceneSpec(scene_dict, camera_path=..., object_paths={"shape_id": path})
"""

from __future__ import annotations

import functools
import hashlib
import math
import os
import re
import warnings
import xml.etree.ElementTree as ET
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import drjit as dr
import numpy as np

from ..backend import mi
from ..errors import SceneError
from ..jit import owned_float

Matrix = np.ndarray
#: the cameras glossrt renders: Mitsuba's class name -> plugin name (``thinlens`` as a
#: pinhole of the same pose and field of view, with a warning: no depth of field)
SUPPORTED_SENSORS = {"PerspectiveCamera": "perspective", "ThinLensCamera": "thinlens"}


@dataclass
class SceneSpec:
    """What a built-in scene builder returns: a Mitsuba scene dict and its animation.

    ``camera_path(frame) -> 4x4`` gives the sensor's to_world per frame (None: static);
    ``object_paths[shape_id](frame) -> 4x4`` gives a rigid transform applied on top of the
    shape's rest pose (None entries / missing ids: static)."""

    scene_dict: dict
    camera_path: Callable[[int], Matrix] | None = None
    object_paths: dict[str, Callable[[int], Matrix]] = field(default_factory=dict)
    max_depth: int | None = None
    description: str = ""


BUILTIN: dict[str, tuple[Callable[[], SceneSpec], str]] = {}


@dataclass(eq=False)
class Pose:
    """Where a frame's camera and moving shapes are (:meth:`SceneSetup.pose`): the camera's
    ``to_world`` (4x4) and horizontal ``fov`` (degrees), and ``objects``: mesh index (as in
    the ``mesh_id`` channel) -> the rigid transform applied on top of that shape's rest pose
    (shapes not listed are at rest). What motion vectors point back to
    (:attr:`glossrt.render.Renderer.previous_pose`). ``lights``: point-light id -> the rigid
    transform applied to its rest position (:meth:`SceneSetup.set_light_override`; invisible
    to the camera, so no motion vectors, but a moved light is another pose)."""

    camera: Matrix
    fov: float
    objects: dict[int, Matrix]
    lights: dict[str, Matrix] = field(default_factory=dict)

    def same(self, other: Pose | None) -> bool:
        """Whether ``other`` is the same pose (exact values; shapes and lights at identity
        count as unlisted)."""
        if other is None or self.fov != other.fov:
            return False
        if not np.array_equal(self.camera, other.camera):
            return False
        eye = np.eye(4)
        for mine, theirs in ((self.objects, other.objects), (self.lights, other.lights)):
            for m in set(mine) | set(theirs):
                if not np.array_equal(mine.get(m, eye), theirs.get(m, eye)):
                    return False
        return True


#: how far a shape transform's 3x3 part may be from a rotation (``R^T R = I``, ``det R =
#: 1``) and its last row from (0, 0, 0, 1) to count as rigid
RIGID_TOL = 1e-5


def check_rigid(matrix, what: str) -> Matrix:
    """``matrix`` as a 4x4 float64 rigid transform (rotation + translation), or one
    :class:`SceneError` naming ``what`` and the problem."""
    try:
        m = np.array(matrix, dtype=np.float64)
        if m.shape == (3, 4):
            m = np.vstack([m, [0.0, 0.0, 0.0, 1.0]])
        m = m.reshape(4, 4)
    except (TypeError, ValueError):
        raise SceneError(f"{what}: a transform must be a 4x4 (or 3x4) matrix, got "
                         f"{np.shape(matrix)}") from None
    if not np.isfinite(m).all():
        raise SceneError(f"{what}: the transform has NaN/Inf entries")
    r = m[:3, :3]
    if (np.abs(m[3] - [0.0, 0.0, 0.0, 1.0]).max() > RIGID_TOL
            or np.abs(r.T @ r - np.eye(3)).max() > RIGID_TOL or np.linalg.det(r) < 0):
        raise SceneError(f"{what}: the transform is not rigid (rotation + translation; no "
                         "scaling, shearing, mirroring or projection)")
    return m




def builtin(name: str, description: str):
    """Register a built-in scene builder under ``name``."""

    def deco(fn: Callable[[], SceneSpec]):
        BUILTIN[name] = (fn, description)
        return fn

    return deco


def to_matrix(t) -> Matrix:
    """4x4 float64 NumPy matrix of a Mitsuba transform (scalar or width-1 vectorised)."""
    m = np.array(t.matrix, dtype=np.float64)
    if m.ndim == 3:
        m = m[..., 0]
    return m.reshape(4, 4)


def look_at(origin, target, up) -> Matrix:
    return to_matrix(mi.ScalarTransform4f().look_at(origin, target, up))


def rotation_about(point, axis, degrees: float) -> Matrix:
    """4x4 rotation by ``degrees`` about the line through ``point`` along ``axis``."""
    t = (
        mi.ScalarTransform4f().translate(list(point))
        @ mi.ScalarTransform4f().rotate(list(axis), degrees)
        @ mi.ScalarTransform4f().translate([-p for p in point])
    )
    return to_matrix(t)


def translation(v) -> Matrix:
    m = np.eye(4)
    m[:3, 3] = v
    return m


def stable_shapes(scene: mi.Scene) -> list:
    """``scene.shapes()`` in an order that does not change between loads of the same scene
    (Mitsuba's own order varies from load to load), so ``mesh_id`` is reproducible."""

    def key(s):
        b = s.bbox()
        return (s.id(), s.class_name(), tuple(float(b.min[i]) for i in range(3)),
                tuple(float(b.max[i]) for i in range(3)))

    return sorted(scene.shapes(), key=key)


def _registry_id(ptr_type, obj) -> int:
    """Dr.Jit registry id of a Mitsuba object (what ``mi.ShapePtr``/``mi.EmitterPtr`` hold)."""
    return int(dr.reinterpret_array(mi.UInt32, ptr_type(obj))[0])


def _param_digest(obj) -> str:
    """Digest of an object's parameters (``mi.traverse``): tells apart emitters of the same
    plugin and id (Mitsuba gives many emitters the same id, e.g. '' or 'emitter')."""
    params = mi.traverse(obj)
    h = hashlib.sha1()
    for k in sorted(params.keys()):
        v = params[k]
        v = getattr(v, "matrix", v)
        try:
            a = np.ascontiguousarray(np.asarray(v, dtype=np.float64))
            data = a.tobytes() + repr(a.shape).encode()
        except (TypeError, ValueError):
            data = repr(v).encode()
        h.update(k.encode() + b"\0" + data + b"\0")
    return h.hexdigest()


def _finite(values) -> bool:
    return bool(np.isfinite(np.asarray(values, dtype=np.float64)).all())


def _bad_bounds(b) -> bool:
    """A NaN anywhere, or an Inf in non-empty bounds (empty bounds, +inf .. -inf, are those
    of environment and directional lights)."""
    v = np.asarray([*b.min, *b.max], dtype=np.float64)
    return bool(np.isnan(v).any() or (b.valid() and not np.isfinite(v).all()))


def check_finite_geometry(scene: mi.Scene, name: str = "scene") -> None:
    """Raise :class:`SceneError` naming the first shape or emitter whose placement has a NaN
    or Inf (a NaN in a transform or in vertices: such a light or object silently renders
    nothing). Shapes (area lights included): a mesh's vertices (the mesh Mitsuba merges
    id-less shapes into has empty bounds), other shapes' bounds; other emitters: their bounds
    where they have any (point lights) and their ``to_world``, ``position`` and ``direction``
    parameters."""
    for shape in stable_shapes(scene):
        # a mesh's vertices are tested where they are (one Bool comes back, not the array)
        bad = (not dr.all(dr.isfinite(shape.vertex_positions_buffer()), axis=None)
               if shape.is_mesh() else _bad_bounds(shape.bbox()))
        if bad:
            kind = "area light" if shape.is_emitter() else "shape"
            raise SceneError(f"{name}: {kind} {shape.id()!r} has NaN/Inf geometry: check "
                             "its transform and vertices")
    for e in scene.emitters():
        if e.get_shape() is not None:
            continue  # checked with its shape
        params = mi.traverse(e)
        placement = [getattr(params[k], "matrix", params[k]) for k in params.keys()
                     if k.endswith(("to_world", "position", "direction"))]
        if _bad_bounds(e.bbox()) or not all(_finite(v) for v in placement):
            raise SceneError(f"{name}: {e.class_name()} light {e.id()!r} has a NaN/Inf "
                             "position, direction or transform")


def stable_emitters(scene: mi.Scene) -> list:
    """``scene.emitters()`` in an order that does not change between loads of the same scene
    (Mitsuba's own order varies from load to load): area emitters first, in the order of their
    shapes in :func:`stable_shapes`, then the others by id, plugin and parameters. glossrt's
    next-event estimation picks emitters in this order, so a seed gives the same image on
    every load."""
    rank = {_registry_id(mi.ShapePtr, s): i for i, s in enumerate(stable_shapes(scene))}

    def key(e):
        shape = e.get_shape()
        if shape is not None:
            r = rank.get(_registry_id(mi.ShapePtr, shape))
            if r is not None:
                return (0, r, "", "")
        return (1, 0, e.id(), e.class_name())

    emitters = list(scene.emitters())
    keys = [key(e) for e in emitters]
    ties = {k for k in keys if keys.count(k) > 1}
    # the parameters' digest only where id and plugin tie (an environment map's digest reads
    # all its texels, and the pipeline orders the emitters every frame)
    order = sorted(range(len(emitters)), key=lambda i: keys[i] + (
        _param_digest(emitters[i]) if keys[i] in ties else "",))
    return [emitters[i] for i in order]


class SceneSetup:
    """A loaded scene, glossrt's sensor for it, and its animation."""

    def __init__(
        self,
        name: str,
        scene: mi.Scene,
        *,
        size: tuple[int, int] | None = None,
        camera_path: Callable[[int], Matrix] | None = None,
        object_paths: dict[str, Callable[[int], Matrix]] | None = None,
        max_depth: int | None = None,
        max_depth_from: str | None = None,
        source: str | None = None,
        rr_depth: int | None = None,
        integrator: str | None = None,
        integrator_error: str | None = None,
    ):
        self.name = name
        self.scene = scene
        self.source = source
        #: path depth in Mitsuba's convention (-1: no limit), None: the renderer's default
        self.max_depth = max_depth
        #: where ``max_depth`` comes from (the frames' ``meta["max_depth_from"]``)
        self.max_depth_from = max_depth_from if max_depth is not None else None
        #: the depth Russian roulette starts at (the integrator's ``rr_depth``), None: the
        #: renderer's default (Mitsuba's 5)
        self.rr_depth = rr_depth
        #: the scene's integrator plugin (``path``, ``direct``, ...; None: a built-in scene)
        self.integrator = integrator
        #: why glossrt cannot render the scene's integrator (None: it can): raised by a
        #: renderer that traces with the scene's path depth, never by commands that do not
        #: trace (:class:`IntegratorDepth`)
        self.integrator_error = integrator_error
        sensors = scene.sensors()
        if not sensors:
            raise SceneError(f"{name}: the scene has no sensor (camera)")
        s0 = sensors[0]
        p0 = mi.traverse(s0)
        kind = SUPPORTED_SENSORS.get(s0.class_name())
        if kind is None or "x_fov" not in p0.keys():
            cls = s0.class_name()
            plugin = cls[:-len("Camera")].lower() if cls.endswith("Camera") else cls.lower()
            raise SceneError(
                f"{name}: sensor {plugin} ({cls}) is not supported: glossrt renders pinhole "
                "cameras (its G-buffer, motion vectors and analytic shading project through "
                "one eye point); use <sensor type=\"perspective\"> (thinlens is rendered as "
                "a pinhole)")
        #: the scene's camera plugin (``perspective``, or ``thinlens`` rendered as a pinhole)
        self.sensor_kind = kind
        self.fov = float(p0["x_fov"][0])
        self.rest_camera = to_matrix(p0["to_world"])
        if not (np.isfinite(self.rest_camera).all() and math.isfinite(self.fov)):
            raise SceneError(f"{name}: the camera has a NaN/Inf transform or field of view")
        check_finite_geometry(scene, name)
        film_size = tuple(int(v) for v in s0.film().size())
        self.size = check_size(size) if size is not None else film_size
        w, h = self.size
        near = float(p0["near_clip"]) if "near_clip" in p0.keys() else 1e-2
        far = float(p0["far_clip"]) if "far_clip" in p0.keys() else 1e4
        self.sensor = mi.load_dict(
            {
                "type": "perspective",
                "fov": self.fov,
                "fov_axis": "x",
                "near_clip": near,
                "far_clip": far,
                "to_world": mi.ScalarTransform4f(self.rest_camera),
                "film": {
                    "type": "hdrfilm",
                    "width": w,
                    "height": h,
                    "rfilter": {"type": "box"},
                    "pixel_format": "rgb",
                },
            }
        )
        self.sensor_params = mi.traverse(self.sensor)
        self.camera_path = camera_path
        self.object_paths = dict(object_paths or {})
        self.params = mi.traverse(scene)
        self._rest: dict[str, tuple[str, object]] = {}
        self._rest_normals: dict[str, np.ndarray] = {}
        #: moved meshes' rest vertex positions on the host (read once, not per pose)
        self._rest_positions: dict[str, np.ndarray] = {}
        #: shapes in mesh_id order (1-based); stable across loads of the same scene
        self.shapes = render_shapes(scene)
        # (the scene's own shapes: those inside instanced groups cannot be moved one by one)
        own = len(stable_shapes(scene))
        shapes = {s.id(): s for s in self.shapes[:own]}
        for sid in self.object_paths:
            if sid not in shapes:
                raise SceneError(f"{name}: animated shape {sid!r} is not in the scene")
            self._keep_rest(sid)
        self.shape_index = {s.id(): i + 1 for i, s in enumerate(self.shapes[:own]) if s.id()}
        #: the frame index last posed by :meth:`set_frame`
        self.frame = None
        #: explicit pose (the viewer moves things): see :meth:`set_camera_override` and
        #: :meth:`set_object_override`; they replace the animation's camera and shape paths
        self.camera_override: Matrix | None = None
        self.fov_override: float | None = None
        self.object_overrides: dict[str, Matrix] = {}
        #: point-light id -> rigid transform of its rest position (:meth:`set_light_override`)
        self.light_overrides: dict[str, Matrix] = {}
        self._light_rest: dict[str, np.ndarray] = {}  # point-light id -> rest position (3,)
        self._lights_applied: dict[str, Matrix] = {}  # point-light id -> transform written
        self._pose_version = 0
        self._posed: tuple | None = None  # (frame, pose version) last set by set_frame
        self._applied: dict[str, Matrix] = {}  # shape id -> transform last written
        self._fov_applied = self.fov

    def _keep_rest(self, sid: str) -> None:
        """Remember shape ``sid``'s rest-pose parameter (its ``to_world`` or vertices)."""
        if sid in self._rest:
            return
        for key in (f"{sid}.vertex_positions", f"{sid}.to_world"):
            if key in self.params.keys():
                val = self.params[key]
                self._rest[sid] = (key, type(val)(val))
                if key.endswith("vertex_positions"):
                    self._rest_positions[sid] = np.array(val, dtype=np.float64).reshape(-1, 3)
                normals = f"{sid}.vertex_normals"
                if key.endswith("vertex_positions") and normals in self.params.keys():
                    # written with the positions: Mitsuba would recompute them otherwise
                    # (a mesh's own normals replaced by face-averaged ones)
                    self._rest_normals[sid] = np.array(self.params[normals],
                                                       dtype=np.float64).reshape(-1, 3)
                return
        raise SceneError(f"{self.name}: shape {sid!r} cannot be moved (no transform parameter)")

    # -- animation -------------------------------------------------------------------
    def camera_matrix(self, frame: int) -> Matrix:
        """The camera's ``to_world`` at ``frame``: the explicit one when set
        (:meth:`set_camera_override`), else the camera path's, else the scene's."""
        if self.camera_override is not None:
            return self.camera_override
        return self.rest_camera if self.camera_path is None else self.camera_path(frame)

    @property
    def current_fov(self) -> float:
        """The horizontal field of view in degrees (the explicit one when set)."""
        return self.fov if self.fov_override is None else self.fov_override

    def camera(self, frame: int):
        """The :class:`glossrt.frame.Camera` of ``frame`` (None for frame < 0)."""
        from ..frame import Camera

        if frame < 0:
            return None
        return Camera(to_world=self.camera_matrix(frame), fov=self.current_fov,
                      resolution=self.size)

    def _shape_transform(self, sid: str, frame: int) -> Matrix:
        if sid in self.object_overrides:
            return self.object_overrides[sid]
        path = self.object_paths.get(sid)
        return np.eye(4) if path is None else path(frame)

    def object_transforms(self, frame: int) -> dict[int, Matrix]:
        """Mesh index (1-based, as in the ``mesh_id`` channel) -> rigid transform at ``frame``
        (explicit transforms, :meth:`set_object_override`, replace the paths')."""
        return {self.shape_index[sid]: self._shape_transform(sid, frame)
                for sid in {**self.object_paths, **self.object_overrides}}

    def pose(self, frame: int) -> Pose:
        """The :class:`Pose` of ``frame`` (camera, field of view, moved shapes and point
        lights)."""
        return Pose(np.array(self.camera_matrix(frame), dtype=np.float64), self.current_fov,
                    self.object_transforms(frame), dict(self.light_overrides))

    @property
    def animated(self) -> bool:
        return self.camera_path is not None or bool(self.object_paths)

    # -- explicit pose (issue 25: the viewer moves things) -----------------------------
    def movable_shapes(self) -> list[str]:
        """Ids of the shapes :meth:`set_object_override` can move (those with a transform
        or vertex parameter)."""
        keys = set(self.params.keys())
        return [sid for sid in self.shape_index
                if f"{sid}.to_world" in keys or f"{sid}.vertex_positions" in keys]

    def movable_lights(self) -> list[str]:
        """Ids of the point lights :meth:`set_light_override` can move: ``point`` emitters
        whose id (the XML ``id``, the scene dict's key) names no shape and no other emitter
        and has a ``<id>.position`` parameter (``mi.traverse``). Spot lights are not
        supported by glossrt's renderer (:data:`SUPPORTED_EMITTERS`); directional lights
        have no position."""
        keys = set(self.params.keys())
        ids = [e.id() for e in self.scene.emitters()]
        return sorted(e.id() for e in self.scene.emitters()
                      if emitter_kind(e) == "point" and e.id() and ids.count(e.id()) == 1
                      and e.id() not in self.shape_index and f"{e.id()}.position" in keys)

    def _keep_light_rest(self, eid: str) -> None:
        if eid not in self._light_rest:
            self._light_rest[eid] = np.array(self.params[f"{eid}.position"],
                                             dtype=np.float64).reshape(3)

    def prepare_to_move(self) -> None:
        """Write every movable shape's rest pose (and point light's rest position) once (the
        next :meth:`set_frame`), so that frozen kernels recorded from then on already take
        those shapes' placement as evaluated inputs: moving a shape for the first time later
        replays them (a shape first moved after the recording was measured to record the
        trace once more)."""
        for sid in self.movable_shapes():
            self._keep_rest(sid)
        for eid in self.movable_lights():
            self._keep_light_rest(eid)
        self._posed = None

    def set_camera_override(self, to_world=None, fov: float | None = None) -> None:
        """Pose the camera explicitly in every frame from now on: ``to_world`` (4x4, rigid;
        None: the animation's) and ``fov`` (horizontal, degrees; None: the scene's). Checked
        first (:class:`SceneError`; nothing changes then)."""
        m = None if to_world is None else check_rigid(to_world, f"{self.name}: camera")
        if fov is not None:
            fov = float(fov)
            if not 0.0 < fov < 180.0:
                raise SceneError(f"{self.name}: camera fov must lie in (0, 180) degrees, "
                                 f"got {fov}")
        self.camera_override, self.fov_override = m, fov
        self._pose_version += 1

    def set_object_override(self, sid: str, matrix) -> None:
        """Place shape ``sid`` (an object or a polygon light) by ``matrix`` (4x4, rigid,
        applied on top of its rest pose, as the animation's paths are) in every frame from
        now on; None: back to its animation (or rest pose). Checked first
        (:class:`SceneError`; nothing changes then)."""
        if sid not in self.shape_index:
            raise SceneError(f"{self.name}: no shape {sid!r} to move; the shapes are "
                             f"{', '.join(sorted(self.movable_shapes())) or 'none'}")
        if matrix is None:
            if self.object_overrides.pop(sid, None) is not None:
                self._pose_version += 1
            return
        m = check_rigid(matrix, f"{self.name}: shape {sid!r}")
        self._keep_rest(sid)
        self.object_overrides[sid] = m
        self._pose_version += 1

    def set_light_override(self, eid: str, matrix) -> None:
        """Place point light ``eid`` (an id of :meth:`movable_lights`) at ``matrix`` applied
        to its rest position (4x4, rigid: ``p = R p_rest + t``; the rotation turns the
        position about the origin, an isotropic light has no orientation) in every frame
        from now on; None: back to its rest position. Written to the emitter's ``position``
        parameter (``mi.traverse``), which the path tracer and the analytic direct stage
        both read. Checked first (:class:`SceneError`; nothing changes then)."""
        movable = self.movable_lights()
        if eid not in movable:
            raise SceneError(f"{self.name}: no point light {eid!r} to move; the point lights "
                             f"are {', '.join(movable) or 'none'}")
        if matrix is None:
            if self.light_overrides.pop(eid, None) is not None:
                self._pose_version += 1
            return
        m = check_rigid(matrix, f"{self.name}: point light {eid!r}")
        self._keep_light_rest(eid)
        self.light_overrides[eid] = m
        self._pose_version += 1

    def clear_overrides(self) -> None:
        """Back to the animation: no explicit camera, field of view, shape transforms or
        light positions."""
        if self.camera_override is None and self.fov_override is None \
                and not self.object_overrides and not self.light_overrides:
            return
        self.camera_override = self.fov_override = None
        self.object_overrides = {}
        self.light_overrides = {}
        self._pose_version += 1

    def set_frame(self, frame: int) -> None:
        """Pose camera and moving objects for ``frame`` (explicit overrides included)."""
        if (frame, self._pose_version) == self._posed:
            return
        cam = self.camera_matrix(frame)
        if not _finite(cam):
            raise SceneError(f"{self.name}: the camera path gives a NaN/Inf transform at "
                             f"frame {frame}")
        self.sensor_params["to_world"] = mi.Transform4f(cam)
        if self.current_fov != self._fov_applied:
            self.sensor_params["x_fov"] = self.current_fov
            self._fov_applied = self.current_fov
        self.sensor_params.update()
        changed = False
        for sid, (key, rest) in self._rest.items():  # every shape ever moved
            m = self._shape_transform(sid, frame)
            if not _finite(m):
                raise SceneError(f"{self.name}: the path of shape {sid!r} gives a NaN/Inf "
                                 f"transform at frame {frame}")
            last = self._applied.get(sid)
            if last is not None and np.array_equal(last, m):
                continue
            if key.endswith("to_world"):
                self.params[key] = mi.Transform4f(m) @ rest
            else:
                v = self._rest_positions[sid] @ m[:3, :3].T + m[:3, 3]
                # in memory Dr.Jit allocated: a NumPy-backed buffer's alignment varies, and
                # dr.freeze then re-records now and then (glossrt.jit.owned_float)
                self.params[key] = owned_float(v)
                n = self._rest_normals.get(sid)
                if n is not None:  # normals transform by the inverse transpose
                    r = m[:3, :3]
                    if np.allclose(r.T @ r, np.eye(3), atol=RIGID_TOL):
                        n = n @ r.T  # a rotation: itself (and the rest pose exact)
                    else:
                        n = n @ np.linalg.inv(r)
                        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)
                    self.params[f"{sid}.vertex_normals"] = owned_float(n)
            self._applied[sid] = np.array(m, dtype=np.float64)
            changed = True
        for eid, rest in self._light_rest.items():  # every point light ever moved
            m = self.light_overrides.get(eid, np.eye(4))
            last = self._lights_applied.get(eid)
            if last is not None and np.array_equal(last, m):
                continue
            p = m[:3, :3] @ rest + m[:3, 3]
            # opaque: a new position replays the frozen kernels that read it
            self.params[f"{eid}.position"] = mi.Point3f(*(dr.opaque(mi.Float, float(x))
                                                          for x in p))
            self._lights_applied[eid] = np.array(m, dtype=np.float64)
            changed = True
        if changed:
            self.params.update()
        self.frame = frame
        self._posed = (frame, self._pose_version)

    def look_at_point(self) -> np.ndarray:
        """The point the camera orbits: on its view axis, level with the scene's centre."""
        m = self.rest_camera
        origin, forward = m[:3, 3], m[:3, 2] / np.linalg.norm(m[:3, 2])
        bbox = self.scene.bbox()
        centre = np.array([bbox.center()[i] for i in range(3)], dtype=np.float64)
        d = float(np.dot(centre - origin, forward))
        if not np.isfinite(d) or d <= 1e-3:
            d = 1.0
        return origin + d * forward

    def set_orbit(self, degrees: float, frames: int) -> None:
        """Camera path: rotate about the look-at point around the camera's up axis, spanning
        ``degrees`` in total over ``frames`` frames (frame 0 is the scene's own camera)."""
        if self.camera_path is not None:
            return
        pivot = self.look_at_point()
        up = self.rest_camera[:3, 1]
        rest = self.rest_camera
        step = degrees / max(frames - 1, 1)
        self.camera_path = lambda f: rotation_about(pivot, up, step * f) @ rest


# -- loading ------------------------------------------------------------------------------


#: Mitsuba class names (``obj.class_name()``) of emitters -> their plugin names (another
#: class: its name in lower case)
_EMITTER_CLASSES = {"AreaLight": "area", "PointLight": "point",
                    "ConstantBackgroundEmitter": "constant", "EnvironmentMapEmitter": "envmap",
                    "DirectionalEmitter": "directional", "SpotLight": "spot",
                    "Projector": "projector", "DirectionalArea": "directionalarea"}
#: Mitsuba class names of BSDFs -> their plugin names (another class: its name in lower case)
_BSDF_CLASSES = {"SmoothDiffuse": "diffuse", "SmoothConductor": "conductor",
                 "RoughConductor": "roughconductor", "SmoothPlastic": "plastic",
                 "RoughPlastic": "roughplastic", "TwoSidedBRDF": "twosided",
                 "NormalMap": "normalmap", "BumpMap": "bumpmap", "SmoothDielectric": "dielectric",
                 "RoughDielectric": "roughdielectric", "ThinDielectric": "thindielectric",
                 "BlendBSDF": "blendbsdf", "MaskBSDF": "mask", "Null": "null",
                 "Principled": "principled", "PrincipledThin": "principledthin",
                 "PolarizedPlastic": "pplastic", "LinearPolarizer": "polarizer"}


def emitter_kind(emitter) -> str:
    """The plugin name of a Mitsuba emitter (``"area"``, ``"point"``, ``"spot"``,
    ``"projector"``, ``"directional"``, ``"envmap"``, ``"constant"``; another class's name in
    lower case)."""
    cls = emitter.class_name()
    return _EMITTER_CLASSES.get(cls, cls.lower())


def bsdf_kind(bsdf) -> str:
    """The plugin name of a Mitsuba BSDF (another class's name in lower case)."""
    cls = bsdf.class_name()
    return _BSDF_CLASSES.get(cls, cls.lower())


#: what a scene file without an integrator gets: Mitsuba's ``path`` default, max_depth -1
#: (unbounded; Russian roulette ends the paths from depth 5)
MITSUBA_DEFAULT_MAX_DEPTH = -1
#: Mitsuba's default Russian-roulette depth (``rr_depth``)
MITSUBA_DEFAULT_RR_DEPTH = 5

#: Mitsuba integrators whose image glossrt's path tracer renders, by the first word of their
#: string form (Python-implemented integrators share one class name) -> plugin name. The
#: path tracers take their ``max_depth`` and ``rr_depth``; the direct-light ones render
#: direct light only (path depth 2: emission, next-event estimation and the BSDF-sampled
#: emitter hit at the primary vertex)
PATH_INTEGRATORS = {"PathIntegrator": "path", "VolumetricSimplePathIntegrator": "volpath",
                    "VolumetricMisPathIntegrator": "volpathmis",
                    "ParticleTracerIntegrator": "ptracer", "PRBIntegrator": "prb",
                    "BasicPRBIntegrator": "prb_basic", "PRBVolpathIntegrator": "prbvolpath",
                    "PathProjectiveIntegrator": "prb_projective",
                    "GlossrtIntegrator": "glossrt"}
DIRECT_INTEGRATORS = {"DirectIntegrator": "direct",
                      "DirectProjectiveIntegrator": "direct_projective"}
#: the volumetric path tracers: they render participating media, which glossrt does not
VOLUME_INTEGRATORS = {"volpath", "volpathmis", "prbvolpath"}


@functools.cache
def _children_class(variant: str) -> type:
    """The :class:`_Children` callback of ``variant`` (the active one; Mitsuba's base classes
    are per variant)."""

    class _Children(mi.TraversalCallback):
        """Collects the Mitsuba objects an object hands to ``traverse`` (twosided's sides, a
        normalmap's nested BSDF, an instance's shape group, a shape group's shapes), by
        name."""

        def __init__(self):
            super().__init__()
            self.objects = {}

        def put(self, name, value, *flags):
            if isinstance(value, mi.Object):
                self.objects[name] = value

    return _Children


def children(obj) -> dict:
    """The Mitsuba objects ``obj`` hands to ``traverse``, by name (a wrapper BSDF's nested
    BSDFs, an instance's shape group, a shape group's shapes)."""
    cb = _children_class(mi.variant())()
    obj.traverse(cb)
    return cb.objects


def _nested_bsdfs(bsdf) -> list:
    """``bsdf`` and every BSDF nested in it, depth first."""
    out = [bsdf]
    for child in children(bsdf).values():
        if isinstance(child, mi.BSDF):
            out += _nested_bsdfs(child)
    return out


def instanced_shapes(scene: mi.Scene) -> list:
    """The shapes inside the shape groups that the scene's ``instance`` shapes place, each
    once (several instances of one group share its shapes: a ray that hits an instance
    reports the group's shape), in a load-independent order."""
    out, seen = [], set()
    if not any(s.class_name() == "Instance" for s in scene.shapes()):
        return out
    # (an instance does not hand its group to ``traverse``; the scene hands its groups)
    for group in children(scene).values():
        if not (isinstance(group, mi.Shape) and group.class_name().startswith("ShapeGroup")):
            continue
        for s in children(group).values():
            if isinstance(s, mi.Shape) and _registry_id(mi.ShapePtr, s) not in seen:
                seen.add(_registry_id(mi.ShapePtr, s))
                out.append(s)
    b = [s.bbox() for s in out]
    order = sorted(range(len(out)), key=lambda i: (
        out[i].id(), out[i].class_name(), tuple(float(b[i].min[k]) for k in range(3)),
        tuple(float(b[i].max[k]) for k in range(3))))
    return [out[i] for i in order]


def render_shapes(scene: mi.Scene) -> list:
    """The shapes a ray can report (``si.shape``), in ``mesh_id`` order (1-based position):
    :func:`stable_shapes` (the scene's own shapes), then :func:`instanced_shapes` (those
    inside instanced shape groups, shared by all instances of a group). Appending keeps the
    scene's own shapes' indices whether or not it instances anything."""
    return stable_shapes(scene) + instanced_shapes(scene)


_ROUGHNESS_KEYS = ("alpha", "alpha.value", "alpha_u", "alpha_u.value", "alpha_v",
                   "alpha_v.value", "alpha.data")


def check_roughness(bsdf, where: str = "") -> None:
    """Raise :class:`SceneError` naming ``bsdf`` (and ``where`` it is) when its microfacet
    roughness (``alpha``, ``alpha_u``, ``alpha_v``, constant or a texture's values) is
    negative or not finite. Mitsuba's ``roughconductor`` takes such values as they are
    (``roughplastic`` clamps them to 1e-4 itself, so they never reach here)."""
    params = mi.traverse(bsdf)
    for key in params.keys():
        if not any(key == k or key.endswith("." + k) for k in _ROUGHNESS_KEYS):
            continue
        v = np.asarray(params[key], dtype=np.float64).ravel()
        if v.size and (not np.isfinite(v).all() or v.min() < 0):
            bad = v[~np.isfinite(v) | (v < 0)][0]
            prefix = f"{where}: " if where else ""
            raise SceneError(f"{prefix}BSDF {bsdf.id()!r} ({bsdf.class_name()}): roughness "
                             f"{key} = {bad:g}; microfacet roughness must be >= 0")


def check_plugins(scene: mi.Scene, name: str) -> None:
    """Raise :class:`SceneError` for a BSDF (nested ones included) with a negative or
    non-finite roughness (:func:`check_roughness`). Every BSDF and emitter Mitsuba loads in
    the RGB variant is rendered (through Mitsuba's own ``sample`` / ``eval`` / ``pdf``);
    what Mitsuba loaded is checked, so ``<include>``d files, ``$parameters`` and built-in
    scene dicts are covered alike."""
    for shape in render_shapes(scene):
        bsdf = shape.bsdf()
        if bsdf is None:
            continue
        for b in _nested_bsdfs(bsdf):
            check_roughness(b, f"{name}: shape {shape.id()!r}")


def media(scene: mi.Scene) -> list[str]:
    """Where the scene has participating media: ``"shape 'x' (interior)"`` per medium
    attached to a shape, ``"the sensor"`` for a camera inside one."""
    out = []
    for s in render_shapes(scene):
        for side, m in (("interior", s.interior_medium()), ("exterior", s.exterior_medium())):
            if m is not None:
                out.append(f"shape {s.id()!r} ({side}: {m.class_name()})")
    for sensor in scene.sensors():
        if sensor.get_medium() is not None:
            out.append("the sensor")
    return out


_INT_FIELD = r"{}\s*=\s*(-?\d+)"


@dataclass(frozen=True)
class IntegratorDepth:
    """How glossrt renders a scene's integrator: ``max_depth`` and ``rr_depth`` in Mitsuba's
    convention (-1: no limit), the Mitsuba plugin it comes from (``integrator``) and
    ``error``: why glossrt cannot render it (then the depths are None): the renderer raises
    it when it traces with the scene's depth (commands that do not trace never do)."""

    max_depth: int | None
    rr_depth: int | None
    integrator: str
    error: str | None = None


def _read_int(field: str, text: str) -> int | None:
    m = re.search(_INT_FIELD.format(field), text)
    if m is None:
        return None
    v = int(m.group(1))
    return -1 if v >= 2**31 - 1 else v  # an unsigned -1 (``volpath`` prints 4294967295)


def integrator_depth(scene: mi.Scene, name: str) -> IntegratorDepth:
    """What glossrt renders for the loaded scene's integrator (:class:`IntegratorDepth`).

    * none: Mitsuba's default ``path`` (max_depth -1, rr_depth 5);
    * ``path`` and the path tracers that estimate the same image (``ptracer``, ``prb``,
      ``prb_basic``, ``prb_projective``, and ``volpath`` / ``volpathmis`` / ``prbvolpath``
      in a scene without media): their ``max_depth`` and ``rr_depth``, read from the
      integrator's string form (``mi.traverse`` gives no parameters);
    * ``direct`` and ``direct_projective``: direct light only, path depth 2;
    * ``aov``: the first integrator nested in it of the kinds above;
    * anything else (``depth``, ``moment``, an ``aov`` without one of these, a volumetric
      path tracer in a scene with media): ``error`` names it and what to use."""
    integrator = scene.integrator()
    if integrator is None:
        return IntegratorDepth(MITSUBA_DEFAULT_MAX_DEPTH, MITSUBA_DEFAULT_RR_DEPTH, "none")
    text = str(integrator)
    first = re.match(r"\s*(\w+)", text)
    word = first.group(1) if first else integrator.class_name()
    if word == "AOVIntegrator":  # its nested integrators: the first one glossrt renders
        inner = re.findall(r"\b(\w+Integrator)\[", text)
        word = next((w for w in inner if w in PATH_INTEGRATORS or w in DIRECT_INTEGRATORS),
                    word)
        if word == "AOVIntegrator":
            return IntegratorDepth(None, None, "aov", (
                f"{name}: integrator aov nests no path tracer, so the scene says no path "
                "depth to render light with; add <integrator type=\"path\"/> inside it, or "
                "use <integrator type=\"path\"> (\"direct\" for direct light only)"))
    if word in DIRECT_INTEGRATORS:
        return IntegratorDepth(2, MITSUBA_DEFAULT_RR_DEPTH, DIRECT_INTEGRATORS[word])
    if word in PATH_INTEGRATORS:
        plugin = PATH_INTEGRATORS[word]
        where = media(scene) if plugin in VOLUME_INTEGRATORS else []
        if where:
            return IntegratorDepth(None, None, plugin, (
                f"{name}: integrator {plugin} renders participating media ({where[0]}), "
                "which glossrt's path tracer does not (it renders surfaces only); use "
                "<integrator type=\"path\"> to render the scene without them, as Mitsuba's "
                "path does"))
        depth = _read_int("max_depth", text)
        rr = _read_int("rr_depth", text)
        return IntegratorDepth(MITSUBA_DEFAULT_MAX_DEPTH if depth is None else depth,
                               MITSUBA_DEFAULT_RR_DEPTH if rr is None else rr, plugin)
    plugin = word[:-len("Integrator")].lower() if word.endswith("Integrator") else word.lower()
    return IntegratorDepth(None, None, plugin, (
        f"{name}: integrator {plugin} is not one glossrt renders (it renders the light of "
        "Mitsuba's path tracer); use <integrator type=\"path\"> (with its max_depth), "
        "\"direct\" for direct light only, or none for Mitsuba's default path tracer"))


_LOAD_ERROR = re.compile(r"^\s*\[[\w.]+:\d+\]\s*")
_UNDEFINED = re.compile(r"undefined parameter:?\s*\$?(\w+)")


def _load_error(what: str, e: Exception) -> str:
    """One line for a scene Mitsuba refused: Mitsuba's message on one line, without its
    source locations; an undefined ``$parameter`` says how to give it; a plugin Mitsuba cannot
    instantiate in this variant (polarized or spectral-only plugins in an RGB variant) is
    named with the variant."""
    lines = [_LOAD_ERROR.sub("", ln).strip() for ln in str(e).strip().splitlines()]
    msg = " ".join(ln for ln in lines if ln) or repr(e)
    m = _UNDEFINED.search(msg)
    if m:
        return (f"{what}: the scene uses the parameter ${m.group(1)} without a default: give "
                f"it (glossrt render -D {m.group(1)}=VALUE, scenes.load(..., "
                f"params={{{m.group(1)!r}: VALUE}}))")
    if "polarized" in msg.lower() or "spectral" in msg.lower():
        return (f"{what}: Mitsuba cannot load the scene in the {mi.variant()} variant "
                f"glossrt renders with (a polarized or spectral-only plugin): {msg}")
    return f"{what}: Mitsuba could not load the scene: {msg}"


def check_size(size) -> tuple[int, int] | None:
    """``size`` as ``(W, H)`` positive integers (at most :data:`MAX_SIDE`), or a
    :class:`SceneError` saying what is wrong with it; None stays None."""
    if size is None:
        return None
    try:
        w, h = size
    except (TypeError, ValueError):
        raise SceneError(f"image size must be (width, height), got {size!r}") from None
    for v in (w, h):
        if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)):
            raise SceneError(f"image size must be two positive integers, got {size!r}")
    w, h = int(w), int(h)
    if w <= 0 or h <= 0:
        raise SceneError(f"image size must be positive, got {w}x{h}")
    if max(w, h) > MAX_SIDE:
        raise SceneError(f"image size {w}x{h}: at most {MAX_SIDE} pixels a side")
    return w, h


#: what :func:`load` takes (besides a built-in name): described in its errors
SCENE_FORMS = ("a built-in scene name", "a Mitsuba XML file path", "a Mitsuba scene dict",
               "a loaded mi.Scene")


def load(
    scene,
    *,
    size: tuple[int, int] | None = None,
    orbit: float | None = None,
    frames: int = 1,
    params: Mapping | None = None,
) -> SceneSetup:
    """Load a scene from any of:

    * a built-in scene's name (``glossrt render --help`` lists them), with its animation;
      the setup's ``name`` is that name;
    * a Mitsuba 3 XML file's path (``str`` or ``os.PathLike``); ``name``: the file name
      without ``.xml``;
    * a Mitsuba scene dict as ``mi.load_dict`` takes it (``{"type": "scene", ...}``, e.g.
      ``mi.cornell_box()``); ``name``: ``"dict"``;
    * an already loaded ``mi.Scene`` (of the active variant; glossrt renders it as it is,
      with a sensor of its own); ``name``: ``"scene"``.

    Every form gets the same checks on what Mitsuba loaded (supported plugins, roughness,
    finite geometry, the integrator's ``max_depth``). A dict or ``mi.Scene`` has no animation:
    the camera is the scene's first sensor, static (a :class:`SceneError` when it has none).

    ``size`` (W, H) overrides the scene's film size; ``orbit`` (degrees over all
    ``frames``) adds a camera orbit to a scene without its own animation; ``params``: values
    of an XML file's ``$parameters`` (``mi.load_file``'s keyword arguments, Mitsuba's
    ``-D name=value``).

    Every BSDF and emitter Mitsuba loads in the RGB variant is rendered; a ``thinlens``
    camera is rendered as a pinhole (with a warning), other non-pinhole cameras are refused.
    An integrator glossrt does not render is refused by the renderer that would trace with
    it (:attr:`SceneSetup.integrator_error`), not here."""
    size = check_size(size)
    params = check_params(params)
    if params and not (isinstance(scene, (str, os.PathLike)) and os.fspath(scene) not in BUILTIN):
        raise SceneError("scene params are for XML files' $parameters; this scene is "
                         f"{type(scene).__name__ if not isinstance(scene, str) else 'built in'}")
    if orbit is not None and not math.isfinite(float(orbit)):
        raise SceneError(f"orbit must be a finite number of degrees, got {orbit}")
    from . import library  # noqa: F401  (registers the built-in scenes)

    if isinstance(scene, Mapping):
        setup = _from_dict(scene, size)
    elif isinstance(scene, (str, os.PathLike)):
        name_or_path = os.fspath(scene)
        if not isinstance(name_or_path, str):  # a bytes path
            raise SceneError(f"scene path must be text, got {name_or_path!r}")
        if name_or_path in BUILTIN:
            setup = from_spec(name_or_path, BUILTIN[name_or_path][0](), size=size)
        else:
            setup = _from_file(name_or_path, size, params)
    elif isinstance(scene, mi.Scene):
        setup = _from_scene(scene, "scene", size, "scene object")
    else:
        raise SceneError(f"a scene must be {', '.join(SCENE_FORMS[:-1])} or {SCENE_FORMS[-1]}"
                         f" (of variant {mi.variant()}), got {type(scene).__name__}")
    if setup.sensor_kind == "thinlens":
        warnings.warn(f"{setup.name}: the thinlens camera is rendered as a pinhole of the same "
                      "pose and field of view: depth of field is not rendered", stacklevel=2)
    if orbit:
        if setup.camera_path is not None:
            warnings.warn(f"scene {setup.name!r} animates its own camera: orbit {orbit} "
                          "is ignored", stacklevel=2)
        setup.set_orbit(float(orbit), frames)
    return setup


def _from_scene(scene: mi.Scene, name: str, size, what: str, source: str | None = None,
                label: str | None = None) -> SceneSetup:
    """A static :class:`SceneSetup` named ``name`` of a loaded scene, checked like any scene
    (errors say ``label``, default ``name``); ``what`` ("scene file", ...) is where its
    integrator comes from, for ``meta["max_depth_from"]``. An integrator glossrt does not
    render is not refused here (:attr:`SceneSetup.integrator_error`)."""
    label = name if label is None else label
    check_plugins(scene, label)  # what Mitsuba loaded (``<include>``d files too)
    d = integrator_depth(scene, label)
    if scene.integrator() is None:
        origin = f"Mitsuba's default (the {what} sets no integrator)"
    elif d.integrator in DIRECT_INTEGRATORS.values():
        origin = f"{what} ({d.integrator} integrator: direct light only)"
    else:
        origin = what
    return SceneSetup(name, scene, size=size, max_depth=d.max_depth, max_depth_from=origin,
                      source=source, rr_depth=d.rr_depth, integrator=d.integrator,
                      integrator_error=d.error)


def _from_dict(d: Mapping, size) -> SceneSetup:
    if d.get("type") != "scene":
        raise SceneError("a Mitsuba scene dict needs \"type\": \"scene\", got \"type\": "
                         f"{d.get('type')!r}")
    try:
        scene = mi.load_dict(dict(d))
    except Exception as e:
        raise SceneError(_load_error("dict", e)) from None
    return _from_scene(scene, "dict", size, "scene dict")


def check_params(params) -> dict[str, str]:
    """``params`` (a mapping of XML ``$parameter`` names to values, or None) as the strings
    ``mi.load_file`` takes, or one :class:`SceneError` naming a bad entry."""
    if params is None:
        return {}
    if not isinstance(params, Mapping):
        raise SceneError(f"scene params must be a mapping of names to values, got {params!r}")
    out = {}
    for k, v in params.items():
        if not isinstance(k, str) or not re.fullmatch(r"[A-Za-z_]\w*", k):
            raise SceneError(f"scene parameter name {k!r}: use letters, digits and _")
        if isinstance(v, bool):
            v = str(v).lower()
        if not isinstance(v, (str, int, float)) or (isinstance(v, float)
                                                     and not math.isfinite(v)):
            raise SceneError(f"scene parameter {k}: a value must be text or a finite number, "
                             f"got {v!r}")
        out[k] = str(v)
    return out


def parse_defines(items) -> dict[str, str]:
    """``-D NAME=VALUE`` command-line items as scene parameters, or one :class:`SceneError`."""
    out = {}
    for item in items or ():
        name, eq, value = str(item).partition("=")
        if not eq or not name:
            raise SceneError(f"-D {item!r}: give a scene parameter as NAME=VALUE")
        out[name.strip()] = value
    return check_params(out)


def _from_file(path: str, size, params: dict | None = None) -> SceneSetup:
    if not path.endswith(".xml") and not os.path.exists(path):
        raise SceneError(
            f"unknown scene {path!r}: not a built-in scene ({', '.join(sorted(BUILTIN))}) "
            "and no such file"
        )
    if os.path.isdir(path):
        raise SceneError(f"{path} is a folder, not a scene file")
    if not os.path.isfile(path):
        raise SceneError(f"scene file not found: {path}")
    try:
        ET.parse(path)
    except ET.ParseError as e:
        raise SceneError(f"{path}: not a valid XML scene ({e})") from None
    try:
        scene = mi.load_file(path, **(params or {}))
    except Exception as e:
        raise SceneError(_load_error(path, e)) from None
    return _from_scene(scene, os.path.splitext(os.path.basename(path))[0], size, "scene file",
                       source=path, label=path)


def load_static(scene, *, size: tuple[int, int] | None = None) -> SceneSetup:
    """:func:`load` (any of its scene forms) with the animation removed: the camera and every
    object stay at their rest pose in all frames, so consecutive frames differ only in their
    noise (temporal-error and steady-state timing sequences)."""
    setup = load(scene, size=size)
    setup.camera_path = None
    setup.object_paths = {}
    return setup


def from_spec(name: str, spec: SceneSpec, *, size: tuple[int, int] | None = None) -> SceneSetup:
    """A :class:`SceneSetup` from a scene description (what a built-in's function returns,
    e.g. :func:`glossrt.scenes.library.polygon_light_scene` with non-default options), with
    its animation and path depth."""
    try:
        scene = mi.load_dict(spec.scene_dict)
    except Exception as e:  # pragma: no cover - a bug in a built-in scene
        raise SceneError(f"scene {name!r} failed to load: {e}") from e
    check_plugins(scene, name)
    return SceneSetup(name, scene, size=check_size(size), camera_path=spec.camera_path,
                      object_paths=spec.object_paths, max_depth=spec.max_depth,
                      max_depth_from="built-in scene")


#: the trial scenes shipped with glossrt (``src/glossrt/data/scenes``): small Mitsuba XML
#: files that use the plugins beyond the analytic methods (transmission, principled, blends,
#: masks, bump maps, spot and projector lights, curved area lights, the ``direct``
#: integrator, a thin-lens camera, instancing), by name
TRIAL_SCENES = ("glass", "materials", "lights", "direct", "thinlens", "instances")


def trial_scenes() -> dict[str, str]:
    """The paths of glossrt's trial scenes (:data:`TRIAL_SCENES`), by name: scenes written
    for the fallback paths (the pipeline renders them with the papers' methods where they
    apply and the path tracer elsewhere; ``glossrt experiment --which scenes``)."""
    folder = os.path.join(os.path.dirname(os.path.dirname(__file__)), "data", "scenes")
    return {name: os.path.join(folder, f"{name}.xml") for name in TRIAL_SCENES}


#: the largest image side: a G-buffer channel of 16384^2 RGB pixels still fits Dr.Jit's 2^32
#: array entries
MAX_SIDE = 16384


def parse_size(text: str) -> tuple[int, int]:
    """'640x360' -> (640, 360), with a clear error for anything else."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise SceneError(f"--size must look like 640x360, got {text!r}") from None
    if w <= 0 or h <= 0:
        raise SceneError(f"--size must be positive, got {text!r}")
    if max(w, h) > MAX_SIDE:
        raise SceneError(f"--size {text!r}: at most {MAX_SIDE} pixels a side")
    return w, h


def wobble(amplitude: float, period: float) -> Callable[[int], float]:
    """A smooth periodic scalar path, handy for built-in animation."""
    return lambda f: amplitude * math.sin(2.0 * math.pi * f / period)
