"""Which method shades which light, and on which surfaces (the pipeline's fallbacks).

A direct-light mode (``ltc``, ``ltc+bspvt``, ``ltc+ratio``, ``highlights``) shades the lights
it can represent analytically, on the surfaces whose material it can represent, and leaves
everything else to the path tracer:

* **Lights.** Polygon lights (area emitters on rectangles and on planar convex meshes of at
  most 8 corners: :func:`glossrt.lights.scene.polygon_light`) take the mode's method; point
  and directional lights take one shadow ray each (:class:`glossrt.pipeline.stages.
  PointLights`). Every other emitter (environment maps, constant backgrounds, spot and
  projector lights, area lights on spheres, disks, cylinders or non-planar meshes, spectral
  point lights) is path-traced at the primary hit with next-event estimation and MIS, and its
  noisy light goes through the indirect stage's reconstruction filter with the rest of the
  path-traced light. Under ``ltc+bspvt`` a polygon light with geometry behind it (BSPVT's
  visibility rays through it would read it as occluded), or every polygon light while an
  occluder is away from its rest pose (the trees are precomputed for static occluders),
  takes the ratio estimator instead (:func:`bspvt_light_obstacle`).
* **Surfaces.** The analytic methods shade a pixel only where the primary hit's material is
  one they represent (Lambert plus one isotropic GGX or Beckmann reflection lobe:
  :attr:`glossrt.render.materials.Material.analytic`); under ``highlights`` only on the
  scene's own shapes (the light maps are per object). Every other pixel (glass,
  transmission, blends, masks, bump maps, ``principled``, anisotropic lobes, instanced shapes
  under highlights) takes the path-traced direct light of every emitter. Under ``ltc+bspvt``
  the analytic surfaces BSPVT's trees do not cover (the trees live at the vertices of the
  scene's own non-emitting meshes: analytic spheres, instanced shapes, lamps' own surfaces,
  and meshes too coarse to carry a shadow) take the ratio estimator for the BSPVT lights
  (``DirectPlan.bspvt_ratio``).

The two sides agree by construction: the renderer leaves the analytically shaded lights out
at the primary hit exactly on the shapes the direct stage shades (``Renderer(primary_exclude=
..., exclude_on=...)``), and the direct stage's image is zero on every other pixel, so no
light is counted twice or lost. :class:`DirectPlan` records the choice; the frames' meta
reports it (``meta["pipeline"]["lights"]``, ``["fallback_shapes"]``,
``["fallback_share"]``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..backend import mi
from ..errors import GlossrtError

#: the direct-light modes that shade polygon lights analytically
POLYGON_MODES = ("ltc", "ltc+bspvt", "ltc+ratio", "highlights")
#: ``LightChoice.method`` of a light the path tracer lights at the primary hit
PATH_TRACED = "path-traced"
#: ``LightChoice.method`` of a point or directional light shaded with one shadow ray
ANALYTIC_POINT = "analytic (one shadow ray)"


@dataclass
class LightChoice:
    """How one emitter is shaded: ``index`` in :func:`glossrt.render.emitter_index`'s
    numbering, its ``id`` and plugin ``kind``, the ``method`` (a mode such as ``ltc+bspvt``,
    :data:`ANALYTIC_POINT` or :data:`PATH_TRACED`) and ``why`` it is not shaded by the
    mode's own method (empty when it is)."""

    index: int
    id: str
    kind: str
    method: str
    why: str = ""

    def as_dict(self) -> dict:
        out = {"index": self.index, "id": self.id, "kind": self.kind, "method": self.method}
        if self.why:
            out["why"] = self.why
        return out


@dataclass
class DirectPlan:
    """The direct stage's choices for a scene (:func:`plan`): ``mode``; per emitter a
    :class:`LightChoice` (``lights``); the emitter indices shaded analytically
    (``exclude``, the renderer's ``primary_exclude``); the polygon lights' indices shaded
    with BSPVT's trees (``bspvt``) and with the ratio estimator (``ratio``; under
    ``ltc+bspvt`` only); the point and directional lights' (``points``); the mesh ids the
    analytic methods shade (``shapes``, the renderer's ``exclude_on``) and the shapes left
    to the path tracer with the reason (``fallback_shapes``: id -> why)."""

    mode: str
    lights: list[LightChoice] = field(default_factory=list)
    exclude: tuple[int, ...] = ()
    polygons: tuple[int, ...] = ()
    bspvt: tuple[int, ...] = ()
    ratio: tuple[int, ...] = ()
    points: tuple[int, ...] = ()
    shapes: tuple[int, ...] = ()
    fallback_shapes: dict[str, str] = field(default_factory=dict)
    #: under ``ltc+bspvt``: the mesh ids among ``shapes`` that BSPVT's trees do not cover
    #: (analytic spheres and other non-meshes, instanced shapes, lamps' own surfaces, and
    #: meshes of fewer than :data:`COARSE_VERTICES` vertices),
    #: where the BSPVT lights take the ratio estimator, and why (``ratio_shapes``: id -> why)
    bspvt_ratio: tuple[int, ...] = ()
    ratio_shapes: dict[str, str] = field(default_factory=dict)
    #: under ``ltc+bspvt``: the mesh ids BSPVT's trees shade
    bspvt_shapes: tuple[int, ...] = ()
    #: the number of the scene's shapes (mesh ids 1..n)
    n_shapes: int = 0

    @property
    def path_traced_direct(self) -> bool:
        """Whether the path tracer keeps any direct light at the primary hit (a light not
        shaded analytically, or a surface the analytic methods do not shade)."""
        return (len(self.exclude) < len(self.lights)
                or (bool(self.exclude) and len(self.shapes) < self.n_shapes))

    def key(self) -> tuple:
        """What the stages are built from (two plans with equal keys shade alike)."""
        return (self.mode, self.exclude, self.polygons, self.bspvt, self.ratio, self.points,
                self.shapes, self.bspvt_ratio)

    def report(self) -> dict:
        """The plan as the frames' meta holds it (``meta["pipeline"]``)."""
        out = {"lights": [c.as_dict() for c in self.lights],
               "fallback_shapes": dict(self.fallback_shapes)}
        if self.ratio_shapes:
            out["ratio_shapes"] = dict(self.ratio_shapes)
        return out

    def summary(self) -> str:
        """One line: how many lights take each method (for the viewer and the CLI)."""
        counts: dict[str, int] = {}
        for c in self.lights:
            counts[c.method] = counts.get(c.method, 0) + 1
        return ", ".join(f"{m}: {n}" for m, n in counts.items()) or "no lights"


def bspvt_light_obstacle(setup, light) -> str | None:
    """Why BSPVT's trees cannot shade polygon ``light`` (None: they can): geometry right
    behind its emitting side. A visibility texel is 1 only if its ray escapes the scene
    without the lights (the light moves, so the maps cannot stop at it), so every ray
    through a light with geometry behind it (a ceiling light in a closed room) reads as
    blocked. Found by one ray from the light's centre away from its emitting side."""
    import drjit as dr

    from ..scenes import _registry_id

    v = np.asarray(light.vertices, np.float64)
    centre = v.mean(axis=0)
    n = np.cross(v[1] - v[0], v[2] - v[0])
    n /= np.linalg.norm(n)
    size = float(np.max(np.linalg.norm(v - centre, axis=1)))
    o = centre - n * 1e-4 * max(size, 1e-3)
    ray = mi.Ray3f(mi.Point3f(*(float(x) for x in o)), mi.Vector3f(*(float(-x) for x in n)))
    si = setup.scene.ray_intersect(ray)
    if not bool(si.is_valid()[0]):
        return None
    key = dr.reinterpret_array(mi.UInt32, si.shape)[0]
    hit = next((sh.id() for sh in setup.shapes if _registry_id(mi.ShapePtr, sh) == key),
               "") or "geometry"
    return (f"{hit!r} lies behind it (BSPVT's visibility rays through the light hit it, so "
            "the light would read as occluded)")


def moving_occluders(setup) -> list[str]:
    """Ids of the shapes that are not lights and move: in ``setup``'s animation, or placed
    away from their rest pose explicitly (``SceneSetup.object_overrides``, not identity)."""
    moved = list(setup.object_paths)
    moved += [sid for sid, m in getattr(setup, "object_overrides", {}).items()
              if sid not in moved and not np.array_equal(m, np.eye(4))]
    return [sid for sid in moved if _is_occluder(setup, sid)]


def _is_occluder(setup, sid: str) -> bool:
    shape = next((s for s in setup.shapes if s.id() == sid), None)
    return shape is not None and not shape.is_emitter()


def classify_lights(setup, frame: int | None = None) -> list[tuple]:
    """Every emitter of ``setup`` in :func:`glossrt.render.emitter_index` order as ``(index,
    id, kind, light, why)``: ``light`` a :class:`glossrt.lights.scene.PolygonLight` (area
    emitters on polygons), a point or directional light (:mod:`glossrt.lights.analytic`), or
    None with ``why`` it has no analytic form here (posed for ``frame`` first when given)."""
    from ..lights.analytic import analytic_light
    from ..lights.scene import polygon_light
    from ..scenes import _registry_id, emitter_kind, stable_emitters

    if frame is not None:
        setup.set_frame(int(frame))
    rank = {_registry_id(mi.ShapePtr, s): i + 1 for i, s in enumerate(setup.shapes)}
    out = []
    for k, e in enumerate(stable_emitters(setup.scene)):
        kind = emitter_kind(e)
        shape = e.get_shape()
        name = e.id() if shape is None else (shape.id() or e.id())
        light, why = None, ""
        try:
            if shape is not None and kind != "area":
                why = f"{kind} emitters have no analytic form here"
            elif shape is not None:
                light = polygon_light(e, rank.get(_registry_id(mi.ShapePtr, shape), 0),
                                      f"emitter {k}")
            else:
                light = analytic_light(e)
                if light is None:
                    why = f"{kind} emitters have no analytic form here"
        except GlossrtError as err:
            why = str(err)
        out.append((k, name, kind, light, why))
    return out


def reflects_nothing(bsdf) -> bool:
    """Whether ``bsdf`` reflects no light at all: no glossy or delta lobe, and every
    reflectance it has a constant 0 (the black BSDF scenes give their lamps)."""
    flags = int(bsdf.flags())
    if flags & (int(mi.BSDFFlags.Glossy) | int(mi.BSDFFlags.Delta)):
        return False
    params = mi.traverse(bsdf)
    keys = [k for k in params.keys() if "reflectance" in k]
    if not keys or any(not k.endswith("reflectance.value") for k in keys):
        return False
    return all(not np.any(np.asarray(params[k], np.float64)) for k in keys)


class LightsAt:
    """The lights of chosen emitters (:func:`glossrt.render.emitter_index` numbering, each
    one a polygon, point or directional light in :func:`classify_lights`) in their pose at a
    frame: what the direct stage shades each frame. The scene's emitter order and the shapes'
    mesh ids are read once, when it is made."""

    def __init__(self, setup) -> None:
        from ..scenes import _registry_id, stable_emitters

        self.setup = setup
        self.emitters = stable_emitters(setup.scene)
        #: per emitter: its shape's mesh id (0 without a shape)
        rank = {_registry_id(mi.ShapePtr, s): i + 1 for i, s in enumerate(setup.shapes)}
        self.mesh_ids = [0 if e.get_shape() is None
                         else rank.get(_registry_id(mi.ShapePtr, e.get_shape()), 0)
                         for e in self.emitters]

    def __call__(self, indices, frame: int | None = None) -> dict:
        """Emitter index -> its light at ``frame`` (posed first when given), for
        ``indices``."""
        from ..lights.analytic import analytic_light
        from ..lights.scene import polygon_light

        if frame is not None:
            self.setup.set_frame(int(frame))
        out = {}
        for k in indices:
            e = self.emitters[k]
            out[k] = (analytic_light(e) if e.get_shape() is None
                      else polygon_light(e, self.mesh_ids[k], f"emitter {k}"))
        return out


#: a receiver mesh with fewer vertices than this takes the ratio estimator for the BSPVT
#: lights: the visibility BSPVT interpolates between so few vertices (per vertex, and per
#: pixel from its triangle's vertices) cannot carry a shadow (a 2-triangle floor shaded from
#: its 4 corners came out uniformly lit, 0.0033 against 0.079 path-traced under one quad
#: light)
COARSE_VERTICES = 64


def plan(setup, mode: str, shapes_table, trees_ok: bool = True,
         frame: int = 0, why: str = "direct=pathtraced") -> DirectPlan:
    """The :class:`DirectPlan` of direct-light ``mode`` (``pathtraced`` or one of
    :data:`POLYGON_MODES`) for ``setup`` at ``frame``. ``shapes_table``: the renderer's
    :class:`glossrt.render.pathtracer.ShapeTable` (which materials are analytic);
    ``trees_ok``: under ``ltc+bspvt``, whether the scene has BSPVT trees at all (False: every
    polygon light takes the ratio estimator); ``why``: the reason every light is path-traced
    under ``pathtraced``."""
    from ..lights.bspvt.scene import scene_meshes
    from ..lights.scene import PolygonLight
    from ..scenes import _registry_id, bsdf_kind, stable_shapes

    out = DirectPlan(mode=mode, n_shapes=len(setup.shapes))
    # (an instance is never a primary hit: the shapes of its group are)
    instances = {i for i, s in enumerate(setup.shapes, start=1)
                 if s.class_name() == "Instance"}
    classified = classify_lights(setup, frame)
    if mode == "pathtraced":
        out.lights = [LightChoice(k, name, kind, PATH_TRACED, why)
                      for k, name, kind, _, _ in classified]
        return out
    moving = moving_occluders(setup) if mode == "ltc+bspvt" else []
    bspvt, ratio, polys, points = [], [], [], []
    for k, name, kind, light, why in classified:
        if light is None:
            out.lights.append(LightChoice(k, name, kind, PATH_TRACED, why))
        elif not isinstance(light, PolygonLight):
            points.append(k)
            out.lights.append(LightChoice(k, name, kind, ANALYTIC_POINT))
        elif mode != "ltc+bspvt":
            polys.append(k)
            out.lights.append(LightChoice(k, name, kind, mode))
        else:
            polys.append(k)
            obstacle = (f"object {moving[0]!r} moves (BSPVT's visibility is precomputed for "
                        "static occluders)" if moving else
                        "the scene has no triangle meshes to precompute visibility at"
                        if not trees_ok else bspvt_light_obstacle(setup, light))
            if obstacle:
                ratio.append(k)
                out.lights.append(LightChoice(k, name, kind, "ltc+ratio", obstacle))
            else:
                bspvt.append(k)
                out.lights.append(LightChoice(k, name, kind, "ltc+bspvt"))
    out.polygons, out.bspvt, out.ratio, out.points = (tuple(polys), tuple(bspvt),
                                                      tuple(ratio), tuple(points))
    out.exclude = tuple(sorted(polys + points))
    # the surfaces: analytic materials, and what the mode's data covers
    own = len(stable_shapes(setup.scene))
    trees = ({_registry_id(mi.ShapePtr, m): m for m in scene_meshes(setup.scene)}
             if bspvt else None)
    analytic = set(shapes_table.analytic_ids)
    keep, ratio_shapes, tree_shapes = [], [], []
    for i, s in enumerate(setup.shapes, start=1):
        label = s.id() or f"shape {i} ({s.class_name()})"
        if i in instances or (s.is_emitter() and reflects_nothing(s.bsdf())):
            keep.append(i)  # (no pixel of it reflects light: nothing to fall back for)
            continue
        if i not in analytic:
            b = s.bsdf()
            out.fallback_shapes[label] = (
                f"its BSDF ({bsdf_kind(b)}) is not one the analytic methods represent "
                "(Lambert plus one isotropic GGX or Beckmann reflection lobe)")
            continue
        if i > own and mode == "highlights":
            out.fallback_shapes[label] = ("it is instanced (the highlights' light maps cover "
                                          "the scene's own shapes)")
            continue
        keep.append(i)
        if trees is None:
            continue
        mesh = trees.get(_registry_id(mi.ShapePtr, s))
        why = ("it is instanced (BSPVT's trees cover the scene's own meshes)" if i > own else
               "it emits light (BSPVT's trees live at the vertices of the non-emitting "
               "meshes)" if s.is_emitter() else
               f"it is not a triangle mesh ({s.class_name()}): BSPVT's trees live at mesh "
               "vertices" if mesh is None else
               f"its {mesh.vertex_count()} vertices are too few to carry a shadow (fewer "
               f"than {COARSE_VERTICES}: BSPVT interpolates visibility between them)"
               if mesh.vertex_count() < COARSE_VERTICES else None)
        if why is not None:
            ratio_shapes.append(i)
            out.ratio_shapes[label] = why
        else:
            tree_shapes.append(i)
    out.shapes = tuple(keep)
    out.bspvt_ratio = tuple(ratio_shapes)
    out.bspvt_shapes = tuple(tree_shapes)
    if bspvt and not tree_shapes:  # the trees would shade no pixel: the ratio estimator
        for c in out.lights:
            if c.method == "ltc+bspvt":
                c.method = "ltc+ratio"
                c.why = ("BSPVT's trees cover none of the surfaces the analytic methods shade "
                         "(see ratio_shapes)")
        out.ratio = tuple(sorted(out.ratio + out.bspvt))
        out.bspvt = out.bspvt_ratio = ()
    return out


__all__ = ["ANALYTIC_POINT", "DirectPlan", "LightChoice", "PATH_TRACED", "POLYGON_MODES",
           "bspvt_light_obstacle", "classify_lights", "LightsAt", "moving_occluders", "plan",
           "reflects_nothing"]
