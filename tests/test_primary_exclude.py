"""``Renderer(primary_exclude=...)``: emitters whose direct light an analytic stage computes
are removed from the path tracer at the primary hit only (next-event estimation there and
the BSDF-sampled hits from there), and ``render.emitter_index`` numbers the emitters.

References are independent of the exclusion code: the unexcluded render with the same seeds
(indirect light must be bit-identical), glossrt's Monte Carlo of the polygon light
(:func:`glossrt.lights.mc.render_mc`, its own light and BRDF sampling) and LTC
(:func:`glossrt.lights.ltc.shade_frame`, within its measured error, docs/RESULTS.md)."""

from __future__ import annotations

import numpy as np
import pytest

from glossrt import backend

backend.ensure()
import mitsuba as mi  # noqa: E402

from glossrt import scenes  # noqa: E402
from glossrt.errors import GlossrtError  # noqa: E402
from glossrt.render import Renderer, emitter_index  # noqa: E402

SIZE = (24, 18)
RADIANCE = ("emission", "direct_diffuse", "direct_specular", "indirect_diffuse",
            "indirect_specular")
DIRECT = ("direct_diffuse", "direct_specular")
INDIRECT = ("indirect_diffuse", "indirect_specular")


def _check_exclude_all(setup, spp):
    """Excluding every emitter: direct_* is exactly 0; emission, indirect_* and the
    G-buffer are the unexcluded render's with the same seeds (1 spp frame and reference)."""
    n = len(emitter_index(setup))
    full = Renderer(setup, max_depth=4, frozen=False)
    none = Renderer(setup, max_depth=4, frozen=False, primary_exclude=range(n))
    for a, b in ((full.render(0), none.render(0)),
                 (full.render_reference(0, spp), none.render_reference(0, spp))):
        # the scene has direct and indirect light (else the checks say nothing)
        assert sum(a.numpy(ch).max() for ch in DIRECT) > 0
        assert sum(a.numpy(ch).max() for ch in INDIRECT) > 0
        for ch in DIRECT:
            assert not np.any(b.numpy(ch)), ch
        for ch in ("emission", *INDIRECT, "normal", "mesh_id"):
            np.testing.assert_array_equal(b.numpy(ch), a.numpy(ch), err_msg=ch)
        assert b.meta["primary_exclude"] == list(range(n))
        assert len(b.meta["primary_exclude_ids"]) == n
        assert "primary_exclude" not in a.meta


@pytest.mark.slow
def test_excluding_every_emitter_removes_direct_light_only():
    """glossy-cornell (one area light; emission seen by the camera stays)."""
    _check_exclude_all(scenes.load("glossy-cornell", size=SIZE), spp=16)


def test_excluding_every_emitter_of_every_kind():
    """normal-mapped: an area, a point and a directional light; roughness-map: two area
    lights and a constant environment (the BSDF-sampled rays from the primary hit that
    leave the scene must not bring the environment's light either)."""
    for name in ("normal-mapped", "roughness-map"):
        setup = scenes.load(name, size=SIZE)
        assert len(emitter_index(setup)) == 3
        _check_exclude_all(setup, spp=8)


# -- one excluded polygon light + the analytic term = the full render -------------------------

T = mi.ScalarTransform4f


def _two_light_dict(size=(32, 24)) -> dict:
    """A floor of two tiles (Lambert; GGX copper, alpha 0.25, whose BRDF glossrt's Monte
    Carlo models exactly) under two quad lights, nothing between lights and floor: ``lamp_a``
    (the one an analytic stage would take) and ``lamp_b`` (stays path traced)."""
    return {
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 50.0,
                   "to_world": T().look_at(origin=[0, 1.6, 3.2], target=[0, 0, -0.2],
                                           up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": size[0], "height": size[1]}},
        "tile_diffuse": {"type": "rectangle",
                         "to_world": T().translate([-1.0, 0, 0]).rotate([1, 0, 0], -90)
                         .scale([1.0, 2.0, 1.0]),
                         "bsdf": {"type": "diffuse",
                                  "reflectance": {"type": "rgb", "value": [0.6, 0.5, 0.4]}}},
        "tile_glossy": {"type": "rectangle",
                        "to_world": T().translate([1.0, 0, 0]).rotate([1, 0, 0], -90)
                        .scale([1.0, 2.0, 1.0]),
                        "bsdf": {"type": "roughconductor", "distribution": "ggx",
                                 "alpha": 0.25, "material": "Cu"}},
        # behind the tiles, tilted towards them and the camera (its reflection in the copper)
        "lamp_a": {"type": "rectangle",
                   "to_world": T().translate([0.3, 0.9, -2.3]).rotate([1, 0, 0], 20)
                   .scale([0.7, 0.4, 1.0]),
                   "emitter": {"type": "area",
                               "radiance": {"type": "rgb", "value": [6.0, 5.0, 4.0]}}},
        # a large one above the middle, facing down: seen in the copper at angles where light
        # and BSDF sampling are about equally likely (where MIS weights matter most)
        "lamp_b": {"type": "rectangle",
                   "to_world": T().translate([0.4, 1.0, 0.0]).rotate([1, 0, 0], 90)
                   .scale([0.8, 0.6, 1.0]),
                   "emitter": {"type": "area",
                               "radiance": {"type": "rgb", "value": [4.0, 6.0, 8.0]}}},
    }


def _rel_l1(a, b, mask, block: int = 4) -> float:
    """Relative L1 of ``a`` against ``b`` over the ``block`` x ``block`` pixel blocks that lie
    wholly in ``mask`` (H, W), on the blocks' sums: 16x less path-tracing noise than per
    pixel, so what remains is bias."""
    h, w = mask.shape
    k = (h // block) * block, (w // block) * block

    def sums(x):
        x = np.where(mask[..., None], x, 0.0)[:k[0], :k[1]]
        return x.reshape(k[0] // block, block, k[1] // block, block, -1).sum((1, 3))

    full = mask[:k[0], :k[1]].reshape(k[0] // block, block, k[1] // block, block).all((1, 3))
    sa, sb = sums(a)[full], sums(b)[full]
    assert len(sa) >= 20  # enough blocks to say something
    return float(np.abs(sa - sb).sum() / np.abs(sb).sum())


@pytest.fixture(scope="module")
def two_lights():
    setup = scenes.load(_two_light_dict())
    index = emitter_index(setup)
    assert [k for _, _, k, _ in index] == ["area", "area"]
    from glossrt.lights.scene import polygon_lights

    lights = polygon_lights(setup, 0)
    ids = {s.id(): i + 1 for i, s in enumerate(setup.shapes)}
    # the renderer's emitter i is polygon light i, found by its shape index
    assert [sh for _, _, _, sh in index] == [lt.mesh_id for lt in lights]
    a = [i for i, _, _, sh in index if sh == ids["lamp_a"]][0]
    spp = 512
    full = Renderer(setup, max_depth=2, frozen=False).render_reference(0, spp)
    excl = Renderer(setup, max_depth=2, frozen=False, primary_exclude=[a]).render_reference(
        0, spp, seed=1)
    mesh = full.numpy("mesh_id")[..., 0]
    floor = (mesh == ids["tile_diffuse"]) | (mesh == ids["tile_glossy"])
    return setup, full, excl, lights[a], lights[1 - a], floor


def _direct(f) -> np.ndarray:
    return f.numpy("direct_diffuse") + f.numpy("direct_specular")


def test_excluded_light_plus_monte_carlo_equals_full_render(two_lights):
    """Converged direct light with lamp_a excluded + glossrt's Monte Carlo of lamp_a alone
    (unshadowed: nothing occludes it) = the unexcluded converged direct light; and what stays
    (lamp_b, sampled with probability 1 at the primary hit and MIS-weighted with that
    probability) = the Monte Carlo of lamp_b. Measured 2026-12 (32x24, 512 spp each, 4x4
    blocks): 0.010 and 0.013 relative L1 on the floor; 0.15 and 0.18 with the MIS pdf of
    BSDF-sampled hits of lamp_b left at Mitsuba's selection probability (1/2 instead of 1);
    0.23 (lamp_a's share) if the exclusion dropped lamp_a's light without the analytic
    term making up for it."""
    from glossrt.lights.mc import render_mc
    from glossrt.lights.shading import fresnel_image

    setup, full, excl, lamp_a, lamp_b, floor = two_lights
    mat = fresnel_image(setup, full)
    mc_a = render_mc(full, [lamp_a], 512, f0=mat, seed=5)
    mc_b = render_mc(full, [lamp_b], 512, f0=mat, seed=6)
    assert _rel_l1(_direct(excl) + mc_a, _direct(full), floor) < 0.03
    assert _rel_l1(_direct(excl), mc_b, floor) < 0.03
    # lamp_a lights the floor noticeably (else the first check says nothing)
    assert mc_a[floor].sum() > 0.15 * _direct(full)[floor].sum()
    # G-buffer and emission seen directly do not change
    for ch in ("emission", "normal", "albedo_specular"):
        np.testing.assert_array_equal(excl.numpy(ch), full.numpy(ch), err_msg=ch)


def test_excluded_light_plus_ltc_equals_full_render(two_lights):
    """The same with LTC (unshadowed) in place of the Monte Carlo term, within LTC's
    measured error on lamp_a's share of the light (docs/RESULTS.md: 0.092 mean relative
    error at GGX alpha 0.25) plus the Monte Carlo check's noise. Measured 2026-12: 0.019
    (tolerance 0.036); LTC against the Monte Carlo of lamp_a alone: 0.061."""
    from glossrt.lights.ltc import shade_frame
    from glossrt.lights.shading import fresnel_image

    setup, full, excl, lamp_a, _, floor = two_lights
    ltc_a = shade_frame(full, [lamp_a], f0=fresnel_image(setup, full))
    share = ltc_a[floor].sum() / _direct(full)[floor].sum()
    assert _rel_l1(_direct(excl) + ltc_a, _direct(full), floor) < 0.092 * share + 0.015


# -- frozen frames, changes between frames, bad input ------------------------------------------


def test_frozen_frames_replay_with_exclusion():
    """An animated scene with an excluded light renders frozen exactly as traced, recording
    its trace once and replaying it on later frames (no re-tracing per frame). Changing the
    exclusion between frames records at most once per new set, going back to a set used
    before records nothing, and every frame still equals the traced one."""
    setup = scenes.load("roughness-map", size=SIZE)
    frozen = Renderer(setup, primary_exclude=[0])
    plain = Renderer(setup, frozen=False)

    def check(t, exclude):
        plain.primary_exclude = exclude
        a, b = frozen.render(t), plain.render(t)
        for ch in RADIANCE:
            np.testing.assert_array_equal(a.numpy(ch), b.numpy(ch), err_msg=f"{t} {ch}")
        assert a.meta.get("primary_exclude", []) == list(exclude)

    for t in range(3):
        check(t, [0])
    assert frozen._trace_frozen.n_recordings == 1
    sets = [(), (0,), (1, 2), (1, 2), (), (0,), (1, 2)]
    for t, exclude in enumerate(sets, start=3):
        before = frozen._trace_frozen.n_recordings
        frozen.primary_exclude = exclude
        check(t, exclude)
        new = exclude not in sets[:t - 3] and exclude != (0,)
        assert frozen._trace_frozen.n_recordings - before <= int(new), (t, exclude)
    assert frozen._trace_frozen.n_recordings <= 3


@pytest.mark.parametrize("bad", [[3], [-1], [0.5], [True], "0", 0, [None]])
def test_bad_exclusions_are_refused(bad):
    setup = scenes.load("roughness-map", size=(8, 6))
    with pytest.raises(GlossrtError, match="primary_exclude"):
        Renderer(setup, primary_exclude=bad)


def test_emitter_index_kinds_and_shapes():
    """Kinds by plugin; an area light's shape index is the one polygon_lights gives it (the
    mesh_id of its pixels); other emitters have none."""
    from glossrt.lights.scene import polygon_lights

    setup = scenes.load("normal-mapped", size=SIZE)
    index = emitter_index(setup)
    assert [i for i, *_ in index] == [0, 1, 2]
    assert [k for _, _, k, _ in index] == ["area", "point", "directional"]
    assert [e for _, e, _, _ in index][1:] == ["lamp", "sun"]
    assert index[0][3] == polygon_lights(setup, 0)[0].mesh_id
    assert index[1][3] is None and index[2][3] is None
    kinds = {k for _, _, k, _ in emitter_index(scenes.load("roughness-map", size=SIZE))}
    assert kinds == {"area", "constant"}
