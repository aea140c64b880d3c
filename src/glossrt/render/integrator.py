"""glossrt's path tracer as a Mitsuba integrator plugin (``<integrator type="glossrt">``).

Through Mitsuba's own film and sampler (jittered, filtered pixels) it returns the colour and
every other Frame channel as AOVs, so XML workflows and ``mi.render`` can use it directly::

    import glossrt.render.integrator  # registers "glossrt"
    integrator = mi.load_dict({"type": "glossrt", "max_depth": 3})
    img = mi.render(scene, integrator=integrator, spp=64)   # (H, W, 3 + AOVs)

glossrt's own :class:`glossrt.render.Renderer` uses the same ``shade``/``gbuffer`` code with
pixel-centre primary rays instead (noise-free G-buffer), which is what reconstruction
filters want.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from .pathtracer import (
    RADIANCE_OUT,
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


class GlossrtIntegrator(mi.SamplingIntegrator):
    """Separated radiance + G-buffer AOVs. Parameter: ``max_depth`` (int, default 3)."""

    def __init__(self, props: mi.Properties):
        super().__init__(props)
        self.max_depth = resolve_max_depth(int(props.get("max_depth", 3)))
        self._tables: dict[int, ShapeTable] = {}
        self._emitters: dict[int, EmitterTable] = {}
        from ..brdf.ggx import SpecularAlbedoTable

        self.albedo = SpecularAlbedoTable.load()

    def aov_names(self):
        return [f"{name}.{c}" for name, comps in AOV_LAYERS for c in comps]

    def _shapes(self, scene: mi.Scene) -> ShapeTable:
        key = id(scene)
        if key not in self._tables:
            self._tables[key] = ShapeTable(scene)
        return self._tables[key]

    def _emitter_table(self, scene: mi.Scene) -> EmitterTable:
        """Stable emitter order for NEE (built once per scene, not per ``sample`` call)."""
        key = id(scene)
        if key not in self._emitters:
            self._emitters[key] = EmitterTable(scene)
        return self._emitters[key]

    def sample(self, scene, sampler, ray, medium=None, active=True):
        ray = mi.Ray3f(ray)
        r = shade(scene, sampler, ray, self.max_depth, self._emitter_table(scene))
        sensor = scene.sensors()[0]
        gb = gbuffer(r.si, r.bsdf, ray, sensor, self._shapes(scene), self.albedo)
        values = {name: getattr(r, name) for name in RADIANCE_OUT}
        values.update(gb)
        values["depth"] = dr.select(r.si.is_valid(), gb["depth"], 0.0)  # films can't average inf
        aovs = []
        for name, comps in AOV_LAYERS:
            v = values[name]
            aovs += [v] if len(comps) == 1 else [v[i] for i in range(len(comps))]
        color = mi.Color3f(sum((values[n] for n in RADIANCE_OUT), dr.zeros(mi.Color3f)))
        return mi.Spectrum(color), mi.Bool(True), aovs

    def to_string(self):
        return f"GlossrtIntegrator[max_depth={self.max_depth}]"


mi.register_integrator("glossrt", lambda props: GlossrtIntegrator(props))
