"""glossrt.pipeline, direct=ltc+bspvt on a static scene (issue 25): the converged composed
image is within LTC's measured error plus BSPVT's (plus the references' own disagreement) of
the converged path-traced image, and unshadowed LTC on the same scene is not."""

from __future__ import annotations

import numpy as np
import pytest

from glossrt import pipeline, render, scenes
from glossrt.pipeline import stages

SIZE = (48, 36)
SPP = 256
BSPVT_RES = 8  # coarse visibility maps: polygon-light's trees build in about a second


def _rmse(a, b) -> float:
    return float(np.sqrt(np.mean((np.asarray(a, np.float64) - b) ** 2)))


@pytest.fixture(scope="module")
def static_scene():
    """The built-in polygon-light without its animation (the light at rest behind the teapot
    and sphere, tilted down: their shadows fall on the floor towards the camera). BSPVT
    accepts it (triangle meshes only, nothing behind the light): checked by the pipeline
    (``pipeline.bspvt_obstacles``), which would refuse the scene otherwise."""
    setup = scenes.load_static("polygon-light", size=SIZE)
    # two independent converged path-traced references (pixel-centre primary hits, as the
    # pipeline's accumulated G-buffer, so the primary-hit emission is the same in all three)
    refs = [render.Renderer(setup).render_reference(0, spp=SPP, seed=s) for s in (11, 12)]
    return setup, refs


def _composed(setup, direct: str, **kw):
    pipe = pipeline.Pipeline(setup, direct=direct, indirect="none", taa=False,
                             accumulate=True, spp=SPP, progress=False,
                             bspvt_resolution=BSPVT_RES, **kw)
    f = pipe.render(0)
    assert pipe.direct_mode == direct and f.meta["spp"] == SPP
    return f


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["vertex", "pixel"])
def test_ltc_bspvt_composition_is_within_ltc_plus_bspvt_error(static_scene, mode):
    """Composed = emission + BSPVT direct (B) + the path tracer's light with the polygon light
    left out at the primary hit; reference R = the converged path-traced image. With the
    unshadowed LTC term A, and S and U the converged Monte Carlo direct light with and
    without shadow rays from the SAME samples (glossrt.lights.ratio.stochastic_pair: the
    G-buffer BRDF, shadow rays through the Mitsuba scene; S <= U sample by sample):

        C - R = (B - A S/U) + (A S/U - S) + (S - R_direct) + (C_pt - R_pt)

    and |A S/U - S| = |A - U| S/U <= |A - U| per pixel and channel, so

        RMSE(C - R) <= e_bspvt + e_ltc + e_model + e_noise, each measured apart:

    * e_ltc = RMSE(A - U): LTC's error, unshadowed (Heitz et al. 2016 against Monte Carlo of
      the same BRDF at the same shading points; includes U's noise). Measured 0.026.
    * e_bspvt = RMSE(B - A S/U): BSPVT against LTC weighted by the exact ray-traced
      visibility ratio (Heitz, Hill & McGuire 2018's split, unfiltered, 256 spp): its
      visibility maps at 8x8 texels per cube face and the vertex interpolation. Measured
      0.019 (vertex), 0.017 (pixel).
    * e_model = RMSE(S - R_direct): the two references of the shadowed direct light
      (glossrt's Monte Carlo of the G-buffer BRDF, the path tracer's next-event estimation
      with Mitsuba's BSDFs) against each other: their noise and the BRDF model. 0.011.
    * e_noise = RMSE(R1 - R2): two path-traced references with other seeds; the composed
      image's path-traced part (indirect light only) is no noisier than a reference. 0.009.

    Measured: RMSE(C - R) 0.029 (vertex) / 0.028 (pixel) against a sum of 0.065 / 0.063
    (48x36, 256 spp). Unshadowed LTC on the same scene (direct=ltc) is 0.117 from the
    reference: the bound fails it by 1.8x (the shadows remove half the direct light)."""
    setup, (ref, ref2) = static_scene
    builds = stages.BUILDS["count"]
    f = _composed(setup, "ltc+bspvt", bspvt_mode=mode)
    assert stages.BUILDS["count"] <= builds + 1  # cached by geometry: at most one build
    unshadowed = _composed(setup, "ltc")

    from glossrt.lights.ratio import stochastic_pair
    from glossrt.lights.scene import polygon_lights
    from glossrt.lights.shading import fresnel_image

    polys = polygon_lights(setup, 0)
    pair = stochastic_pair(f, polys, scene=setup.scene, spp=SPP, f0=fresnel_image(setup, f),
                           seed=5)
    s = pair["shadowed_diffuse"].astype(np.float64) + pair["shadowed_specular"]
    u = pair["unshadowed_diffuse"].astype(np.float64) + pair["unshadowed_specular"]
    ratio = np.where(u > 0, s / np.where(u > 0, u, 1.0), 1.0)  # no sample: no shadow evidence
    assert (s <= u + 1e-6).all()
    a = unshadowed.numpy("direct")  # LTC (pixel), the same G-buffer
    b = f.numpy("direct")
    r_direct = ref.numpy("direct_diffuse") + ref.numpy("direct_specular")
    e_ltc = _rmse(a, u)
    e_bspvt = _rmse(b, a * ratio)
    e_model = _rmse(s, r_direct)
    e_noise = _rmse(ref.numpy("color"), ref2.numpy("color"))
    tol = e_ltc + e_bspvt + e_model + e_noise
    err = _rmse(f.numpy("color"), ref.numpy("color"))
    err_unshadowed = _rmse(unshadowed.numpy("color"), ref.numpy("color"))
    print(f"{mode}: composed-vs-reference RMSE {err:.5f} <= e_ltc {e_ltc:.5f} + e_bspvt "
          f"{e_bspvt:.5f} + e_model {e_model:.5f} + e_noise {e_noise:.5f} = {tol:.5f}; "
          f"unshadowed LTC {err_unshadowed:.5f}")
    assert err <= tol, (err, e_ltc, e_bspvt, e_model, e_noise)
    # the bound can fail: the same composition without shadows is far outside it
    assert err_unshadowed > 1.5 * tol, (err_unshadowed, tol)
    # the shadows are a large part of the direct light, and BSPVT finds most of them
    assert _rmse(a, s) > 4 * e_bspvt
    assert abs(b.mean() - r_direct.mean()) < 0.1 * r_direct.mean()
    assert f.numpy("indirect").mean() > 0.001  # the floor and objects light each other
