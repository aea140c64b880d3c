"""glossrt's path tracer as a Mitsuba integrator plugin (``<integrator type="glossrt">``).

Through Mitsuba's own film and sampler (jittered, filtered pixels) it returns the colour and
every other Frame channel as AOVs, so XML workflows and ``mi.render`` can use it directly::

    import glossrt.render.integrator  # registers "glossrt" (in every variant glossrt picks)
    integrator = mi.load_dict({"type": "glossrt", "max_depth": 3})
    img = mi.render(scene, integrator=integrator, spp=64)   # (H, W, 3 + AOVs)

glossrt's own :class:`glossrt.render.Renderer` uses the same ``shade``/``gbuffer`` code with
pixel-centre primary rays instead (noise-free G-buffer), which is what reconstruction
filters want.
"""

from __future__ import annotations

import functools

import drjit as dr

from .. import backend
from ..backend import mi
from .pathtracer import (
    RADIANCE_OUT,
    RR_DEPTH,
    EmitterTable,
    ShapeTable,
    gbuffer,
    resolve_max_depth,
    shade,
)

#: AOV layers in output order, with their components (Mitsuba names them layer.component)
AOV_LAYERS = (
    [(n, "RGB") for n in RADIANCE_OUT]
    + [("albedo_diffuse", "RGB"), ("albedo_specular", "RGB"), ("normal", "XYZ"),
       ("position", "XYZ"), ("depth", "Z"), ("roughness", "Y"), ("roughness_uv", "XY"),
       ("tangent", "XYZ"), ("distribution", "Y"),
       ("mesh_id", "Y")]
)


@functools.cache
def _integrator_class(variant: str) -> type:
    """The plugin's class for ``variant`` (the active one): Mitsuba's base classes are per
    variant, so the class is built once a variant is chosen, not at import."""

    class GlossrtIntegrator(mi.SamplingIntegrator):
        """Separated radiance + G-buffer AOVs. Parameters: ``max_depth`` (int, default 3) and
        ``rr_depth`` (int, default 5, Mitsuba's).

        ``depth`` is measured along the axis of the sensor being rendered (the one ``render``
        gets, e.g. ``mi.render(scene, sensor=posed_sensor)``), not ``scene.sensors()[0]``. The
        scene's shape and emitter tables are built for each ``render`` call and dropped after it
        (about 10 ms), so a later scene can never be served another scene's tables (a cache keyed
        by ``id(scene)`` could be, once a new scene took a freed one's address)."""

        def __init__(self, props: mi.Properties):
            super().__init__(props)
            self.max_depth = resolve_max_depth(int(props.get("max_depth", 3)))
            self.rr_depth = int(props.get("rr_depth", RR_DEPTH))
            #: (scene, sensor, ShapeTable, EmitterTable) while ``render`` runs, else None
            self._current = None
            from ..brdf.ggx import SpecularAlbedoTable

            self.albedo = SpecularAlbedoTable.load()

        def aov_names(self):
            return [f"{name}.{c}" for name, comps in AOV_LAYERS for c in comps]

        def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
            if isinstance(sensor, int):
                sensor = scene.sensors()[sensor]
            self._current = (scene, sensor, ShapeTable(scene), EmitterTable(scene))
            try:
                return super().render(scene, sensor, seed, spp, develop, evaluate)
            finally:
                self._current = None

        def _tables(self, scene: mi.Scene):
            """(sensor, ShapeTable, EmitterTable) of the ``render`` call under way; outside one
            (``sample`` called directly) the scene's first sensor and fresh tables."""
            cur = self._current
            if cur is not None and cur[0] is scene:
                return cur[1:]
            return scene.sensors()[0], ShapeTable(scene), EmitterTable(scene)

        def sample(self, scene, sampler, ray, medium=None, active=True):
            ray = mi.Ray3f(ray)
            sensor, shapes, emitters = self._tables(scene)
            r = shade(scene, sampler, ray, self.max_depth, emitters, shapes=shapes,
                      rr_depth=self.rr_depth)
            # depth along the axis of the sensor being rendered (the posed camera)
            gb = gbuffer(r.si, r.bsdf, ray, sensor, shapes, self.albedo, r.albedo)
            # a non-finite sample is 0, as in the Renderer's frames (which count them)
            values = {name: dr.select(dr.isfinite(getattr(r, name)), getattr(r, name), 0.0)
                      for name in RADIANCE_OUT}
            values.update(gb)
            # films can't average inf
            values["depth"] = dr.select(r.si.is_valid(), gb["depth"], 0.0)
            aovs = []
            for name, comps in AOV_LAYERS:
                v = values[name]
                aovs += [v] if len(comps) == 1 else [v[i] for i in range(len(comps))]
            color = mi.Color3f(sum((values[n] for n in RADIANCE_OUT), dr.zeros(mi.Color3f)))
            return mi.Spectrum(color), mi.Bool(True), aovs

        def to_string(self):
            return (f"GlossrtIntegrator[max_depth={self.max_depth}, "
                    f"rr_depth={self.rr_depth}]")

    return GlossrtIntegrator


def integrator_class() -> type:
    """The plugin's class in the active variant (a subclass of its ``mi.SamplingIntegrator``)."""
    return _integrator_class(mi.variant())


def __getattr__(name: str):
    if name == "GlossrtIntegrator":
        return integrator_class()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


@backend.on_variant
def _register() -> None:
    """Register ``"glossrt"`` in the variant glossrt just chose (and in each one it switches to)."""
    cls = integrator_class()
    mi.register_integrator("glossrt", lambda props: cls(props))
