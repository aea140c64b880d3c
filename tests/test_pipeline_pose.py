"""glossrt.pipeline posing (issue 25): explicit camera and shape transforms against the
scene's own animation and against scenes built with the light elsewhere; motion vectors to
the previous frame rendered; no re-recording across poses; BSPVT trees from files, refused
for another scene, and moving an occluder under BSPVT."""

from __future__ import annotations

import numpy as np
import pytest

from glossrt import pipeline, scenes
from glossrt.errors import GlossrtError
from glossrt.pipeline import stages

SMALL = (32, 24)
BSPVT_RES = 8  # coarse visibility maps: the trees build in about a second


def _rgb(v):
    return {"type": "rgb", "value": list(v)}


def _assert_same_frames(a, b, skip=()):
    assert a.names == b.names
    for n in a.names:
        if n not in skip:
            np.testing.assert_array_equal(a.numpy(n), b.numpy(n), err_msg=n)


# -- explicit poses against the animation ------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize("scene,orbit,preset,choices,moving", [
    # camera path + a moving analytic sphere; path-traced light, SVGF, TAA
    ("glossy-cornell", None, "schied2017", {}, ("sphere",)),
    # a moving polygon light shaded by LTC (and the camera orbiting)
    ("polygon-light", 8.0, "schied2017", {"direct": "ltc"}, ("light",)),
])
def test_explicit_pose_equals_the_animation(scene, orbit, preset, choices, moving):
    """Frames 2 and 3 posed by set_camera / set_transform with the matrices the scene's own
    animation has there are the animated frames 2 and 3, bit for bit, every channel
    (motion vectors, and so the denoiser's and TAA's histories, included)."""
    anim = scenes.load(scene, size=SMALL, orbit=orbit, frames=4)
    posed = scenes.load(scene, size=SMALL, orbit=orbit, frames=4)
    a = pipeline.Pipeline(anim, preset=preset, progress=False, **choices)
    b = pipeline.Pipeline(posed, preset=preset, progress=False, **choices)
    ref = [a.render(i) for i in range(4)]
    b.render(0)
    b.render(1)
    for k in (2, 3):
        b.set_camera(anim.camera_path(k))
        for sid in moving:
            b.set_transform(sid, anim.object_paths[sid](k))
        f = b.render(k)
        assert f.meta["pipeline"]["explicit_pose"]["shapes"] == list(moving)
        _assert_same_frames(ref[k], f)
        assert np.abs(ref[k].numpy("motion")).max() > 0.05  # the frames do move
    # the explicit pose holds: rendering another index keeps frame 3's pose (an index of
    # the same TAA jitter as 3, one cycle later: the jitter moves the primary hits)
    from glossrt.denoise.svgf import TAA_JITTER_COUNT

    f0 = b.render(3 + TAA_JITTER_COUNT)
    np.testing.assert_array_equal(f0.numpy("position"), ref[3].numpy("position"))
    b.clear_pose()
    f0 = b.render(0)
    np.testing.assert_array_equal(f0.numpy("position"), ref[0].numpy("position"))


def _light_scene(light_to_world, size=(32, 24)):
    """A glossy floor and back wall under a quad light (no occluders): a Mitsuba dict."""
    from glossrt.backend import mi

    T = mi.ScalarTransform4f
    glossy = {"type": "roughplastic", "distribution": "ggx", "alpha": 0.3,
              "diffuse_reflectance": _rgb((0.5, 0.45, 0.4))}
    return {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 3},
        "sensor": {"type": "perspective", "fov": 50.0,
                   "to_world": T().look_at(origin=[0, 1.2, 3.0], target=[0, 0.5, 0],
                                           up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": size[0], "height": size[1]}},
        "floor": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale([2, 1, 1]),
                  "bsdf": glossy},
        "wall": {"type": "rectangle", "to_world": T().translate([0, 1.0, -1.0]).scale([2, 1, 1]),
                 "bsdf": glossy},
        "light": {"type": "rectangle", "to_world": light_to_world,
                  "bsdf": {"type": "diffuse", "reflectance": _rgb((0, 0, 0))},
                  "emitter": {"type": "area", "radiance": _rgb((10.0, 9.5, 9.0))}},
    }


@pytest.mark.slow
def test_moved_polygon_light_equals_the_scene_built_with_it_there():
    """set_transform moves a polygon light for the analytic direct stage (LTC) and for the
    path tracer (camera-visible emission, the light at deeper bounces): the converged
    composition equals the pipeline on the same scene built (by Mitsuba, from the dict) with
    the light at the new place."""
    from glossrt.backend import mi

    T = mi.ScalarTransform4f
    rest = T().translate([0.0, 1.4, 0.2]).rotate([1, 0, 0], 70).scale([0.5, 0.3, 1.0])
    move = T().translate([0.45, -0.15, 0.25]).rotate([0, 1, 0], 25)
    opts = {"direct": "ltc", "indirect": "none", "taa": False, "accumulate": True, "spp": 32,
            "progress": False}
    moved = pipeline.Pipeline(_light_scene(rest), **opts)
    before = moved.render(0)
    moved.set_transform("light", scenes.to_matrix(move))
    got = moved.render(0)
    assert got.meta["spp"] == 32  # the accumulation started anew at the new pose
    built = pipeline.Pipeline(_light_scene(move @ rest), **opts).render(0)
    for name in ("direct", "emission"):
        np.testing.assert_allclose(got.numpy(name), built.numpy(name), atol=2e-4, rtol=1e-3,
                                   err_msg=name)
    # the path-traced remainder: same seeds, a light equal to float rounding
    err = float(np.sqrt(np.mean((got.numpy("color") - built.numpy("color")) ** 2)))
    moved_by = float(np.sqrt(np.mean((built.numpy("color") - before.numpy("color")) ** 2)))
    print(f"moved vs built RMSE {err:.2e}; the move itself {moved_by:.3f}")
    assert err < 0.01 * moved_by, (err, moved_by)
    assert got.numpy("indirect").mean() > 0.002


def test_motion_vectors_point_to_the_previous_frame_rendered():
    """The camera moved by set_camera between two frames of the same index: every pixel's
    motion vector lands where its surface point projects in the previous camera (a NumPy
    pinhole projection); a plain renderer would give 0 (same index, static scene)."""
    setup = scenes.load_static("glossy-cornell", size=SMALL)
    pipe = pipeline.Pipeline(setup, indirect="none", taa=False, progress=False)
    prev_cam = pipe.render(0).camera
    pipe.set_camera(position=(0.3, 0.1, 3.7), target=(0.05, 0.0, 0.0), fov=setup.fov * 0.9)
    f = pipe.render(0)
    assert f.prev_camera == prev_cam
    pos = f.numpy("position").reshape(-1, 3)
    hit = f.numpy("mesh_id").reshape(-1) > 0
    w, h = SMALL
    w2c = np.linalg.inv(prev_cam.to_world)
    c = pos @ w2c[:3, :3].T + w2c[:3, 3]
    px = w / 2 - prev_cam.focal_px * c[:, 0] / c[:, 2]  # Mitsuba: camera +x is image left
    py = h / 2 - prev_cam.focal_px * c[:, 1] / c[:, 2]
    ys, xs = np.divmod(np.arange(w * h), w)
    want = np.stack([px - (xs + 0.5), py - (ys + 0.5)], -1)[hit]
    got = f.numpy("motion").reshape(-1, 2)[hit]
    assert np.abs(want).max() > 1.0
    np.testing.assert_allclose(got, want, atol=2e-3)


def test_no_rerecording_across_poses():
    """New camera positions, fields of view and shape transforms (a light, a mesh, an
    analytic sphere) replay every frozen kernel: no stage records again."""
    from glossrt.lights.ltc import shade as ltc_shade

    setup = scenes.load_static("glossy-cornell", size=SMALL)
    pipe = pipeline.Pipeline(setup, direct="ltc", indirect="atrous", taa=True, progress=False)
    for i in range(3):
        pipe.render(i)
    steady = pipe.recordings()
    ltc = ltc_shade._shade_frozen.n_recordings  # (module-wide: LTC's shading kernels)
    for k in range(6, 12):
        pipe.set_camera(position=(0.1 * (k - 8), 0.05, 3.9), target=(0, 0, 0), fov=38.0 + k)
        pipe.set_transform("light", scenes.translation((0.04 * (k - 8), -0.05, 0.0)))
        pipe.set_transform("box", scenes.rotation_about((0.45, -0.7, 0.15), (0, 1, 0), 4 * k))
        pipe.set_transform("sphere", scenes.translation((0.03 * (k - 8), 0.0, 0.0)))
        f = pipe.render(k)
    assert pipe.recordings() == steady
    assert ltc_shade._shade_frozen.n_recordings == ltc
    assert f.meta["pipeline"]["explicit_pose"]["fov"] == 49.0


def test_posing_bad_input_changes_nothing():
    from glossrt.frame import Camera

    setup = scenes.load_static("glossy-cornell", size=SMALL)
    pipe = pipeline.Pipeline(setup, indirect="none", taa=False, progress=False)
    with pytest.raises(GlossrtError, match="no shape 'teapot'.*box.*sphere"):
        pipe.set_transform("teapot", np.eye(4))
    with pytest.raises(GlossrtError, match="'box'.*not rigid"):
        pipe.set_transform("box", np.diag([2.0, 1.0, 1.0, 1.0]))
    with pytest.raises(GlossrtError, match="NaN"):
        pipe.set_transform("box", np.full((4, 4), np.nan))
    with pytest.raises(GlossrtError, match="16x12, the pipeline renders 32x24"):
        pipe.set_camera(Camera(np.eye(4), 40.0, (16, 12)))
    with pytest.raises(GlossrtError, match="up must not be along"):
        pipe.set_camera(position=(0, 2, 0), target=(0, 0, 0))
    with pytest.raises(GlossrtError, match="fov must lie in"):
        pipe.set_camera(fov=180.0)
    assert setup.camera_override is None and setup.fov_override is None
    assert not setup.object_overrides


# -- BSPVT trees ------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def tree_file(tmp_path_factory):
    """polygon-light's trees at BSPVT_RES, written as `glossrt bspvt build` writes them."""
    from glossrt.lights.bspvt import build_scene_trees

    path = tmp_path_factory.mktemp("trees") / "polygon-light.bspvt.npz"
    build_scene_trees(scenes.load("polygon-light").scene, BSPVT_RES, progress=False).save(
        str(path))
    return str(path)


@pytest.fixture
def no_builds(monkeypatch):
    """Any BSPVT tree build fails the test."""
    import glossrt.lights.bspvt as bspvt

    def refuse(*a, **k):
        raise AssertionError("BSPVT trees were built")

    monkeypatch.setattr(bspvt, "build_scene_trees", refuse)
    monkeypatch.setattr(stages, "_TREES", {})


@pytest.mark.slow
def test_prebuilt_tree_file_is_used(tree_file, no_builds):
    pipe = pipeline.Pipeline("polygon-light", preset="okuno-iwasaki", size=SMALL,
                             progress=False, bspvt=tree_file)  # bspvt_resolution 32: unused
    f = pipe.render(0)
    info = f.meta["pipeline"]["bspvt"]
    assert info == {"trees": tree_file, "resolution": BSPVT_RES,
                    "vertices": pipe.bspvt_trees.vertex_count}
    assert f.numpy("direct").mean() > 0.01
    # moving the light keeps the trees (lights are not occluders); the direct stage stays
    direct = pipe.stages["direct"]
    pipe.set_transform("light", scenes.translation((0.2, 0.0, 0.1)))
    g = pipe.render(1)
    assert pipe.stages["direct"] is direct
    assert np.abs(g.numpy("direct") - f.numpy("direct")).max() > 0.01


@pytest.mark.slow
def test_tree_file_of_another_scene_is_refused_before_any_work(tree_file, no_builds,
                                                                 tmp_path):
    from glossrt.cli import main

    other = scenes.load("roughness-map")
    with pytest.raises(GlossrtError, match="bspvt: scene 'roughness-map'.*polygon-light"
                                           ".*vertices.*another scene"):
        pipeline.Pipeline(other, preset="okuno-iwasaki", progress=False, bspvt=tree_file)
    with pytest.raises(GlossrtError, match="direct=pathtraced does not use BSPVT trees"):
        pipeline.Pipeline("polygon-light", preset="schied2017", bspvt=tree_file)
    with pytest.raises(GlossrtError, match="BSPVT file not found"):
        pipeline.Pipeline("polygon-light", preset="full", bspvt=str(tmp_path / "none.npz"))
    out = tmp_path / "frames"
    assert main(["render", "roughness-map", "--pipeline", "okuno-iwasaki", "--bspvt",
                 tree_file, "--size", "32x24", "--out", str(out)]) != 0
    assert not out.exists()  # refused before anything is written
    assert main(["render", "polygon-light", "--pipeline", "okuno-iwasaki", "--bspvt",
                 tree_file, "--size", "32x24", "--frames", "1", "--out", str(out)]) == 0
    from glossrt.frame import Frame

    assert Frame.load(out / "frame_0000.exr").meta["pipeline"]["bspvt"]["trees"] == tree_file


@pytest.mark.slow
def test_tree_file_of_another_scene_is_refused_where_full_would_not_use_trees(
        tree_file, no_builds, tmp_path, capsys):
    """light-shapes has no mesh fine enough for BSPVT's trees, so ``full`` (direct=auto)
    takes ltc+ratio there: polygon-light's trees given for it were accepted and ignored.
    A tree file given is checked against the scene whatever ``direct`` resolves to: one
    line naming the file and the mismatch, from the Python API, ``render`` and the viewer,
    before any work."""
    import glossrt.view as gv
    from glossrt.cli import main

    assert pipeline.Pipeline("light-shapes", preset="full", size=SMALL,
                             progress=False).direct_mode == "ltc+ratio"
    want = "bspvt: scene 'light-shapes': the BSPVT trees in .*polygon-light.*another scene"
    with pytest.raises(GlossrtError, match=want):
        pipeline.Pipeline("light-shapes", preset="full", size=SMALL, progress=False,
                          bspvt=tree_file)
    out = tmp_path / "frames"
    capsys.readouterr()
    assert main(["render", "light-shapes", "--pipeline", "full", "--bspvt", tree_file,
                 "--size", "32x24", "--frames", "1", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "another scene" in err and tree_file in err, err
    assert not out.exists()
    with pytest.raises(GlossrtError, match=want):
        gv.open("light-shapes", pipeline="full", size=SMALL, port=0, verbose=False,
                captures=tmp_path / "c", bspvt=tree_file).stop()
    assert not (tmp_path / "c").exists()


@pytest.mark.slow
def test_built_trees_are_cached_by_geometry(tmp_path, monkeypatch):
    """In memory: a second pipeline on the same geometry builds nothing; on disk
    (bspvt_cache): a new process (the memory cache emptied) reads them back; moving an
    occluder changes the key."""
    monkeypatch.setattr(stages, "_TREES", {})
    n = stages.BUILDS["count"]
    kw = {"preset": "okuno-iwasaki", "size": SMALL, "progress": False,
          "bspvt_resolution": BSPVT_RES, "bspvt_cache": str(tmp_path)}
    a = pipeline.Pipeline("polygon-light", **kw)
    assert stages.BUILDS["count"] == n + 1
    b = pipeline.Pipeline("polygon-light", **kw)
    assert stages.BUILDS["count"] == n + 1 and b.bspvt_trees is None
    assert b.stages["direct"].trees is a.stages["direct"].trees
    monkeypatch.setattr(stages, "_TREES", {})
    c = pipeline.Pipeline("polygon-light", **kw)
    assert stages.BUILDS["count"] == n + 1
    assert c.stages["direct"].trees.source.startswith(str(tmp_path))
    setup = scenes.load("polygon-light")
    key = stages.geometry_key(setup.scene, BSPVT_RES)
    assert key != stages.geometry_key(setup.scene, BSPVT_RES * 2)
    setup.set_object_override("teapot", scenes.translation((0.01, 0, 0)))
    setup.set_frame(0)
    assert stages.geometry_key(setup.scene, BSPVT_RES) != key


@pytest.mark.slow
def test_moving_an_occluder_under_bspvt(tree_file, no_builds):
    """Under direct=ltc+bspvt, moving an occluder makes its polygon lights take the ratio
    estimator while it is away (the meta says which and why) and BSPVT again when it
    returns; under the full preset (direct=auto) the pipeline switches to ltc+ratio while it
    is away and back to ltc+bspvt (the same trees, no build) when it returns."""
    def methods(f):
        return {light["id"]: light["method"] for light in f.meta["pipeline"]["lights"]
                if light["kind"] == "area"}

    pipe = pipeline.Pipeline("polygon-light", preset="okuno-iwasaki", size=SMALL,
                             progress=False, bspvt=tree_file)
    assert set(methods(pipe.render(0)).values()) == {"ltc+bspvt"}
    pipe.set_transform("teapot", scenes.translation((0.1, 0.0, 0.0)))
    f = pipe.render(1)
    assert set(methods(f).values()) == {"ltc+ratio"}
    assert all("'teapot' moves" in light["why"] for light in f.meta["pipeline"]["lights"]
               if light["kind"] == "area")
    pipe.set_transform("teapot", np.eye(4))  # back at rest: BSPVT again
    assert set(methods(pipe.render(2)).values()) == {"ltc+bspvt"}
    full = pipeline.Pipeline("polygon-light", preset="full", size=SMALL, progress=False,
                             bspvt=tree_file)
    assert full.direct_mode == "ltc+bspvt"
    trees = full.stages["direct"].trees
    full.set_transform("teapot", scenes.translation((0.1, 0.0, 0.0)))
    assert full.direct_mode == "ltc+ratio"
    f = full.render(0)
    assert f.meta["pipeline"]["direct"] == "ltc+ratio"
    full.set_transform("teapot", None)
    assert full.direct_mode == "ltc+bspvt"
    assert full.stages["direct"].trees is trees
    full.render(1)
    # an occluder that the animation moves: its lights take the ratio estimator up front
    setup = scenes.load("polygon-light", size=SMALL)
    setup.object_paths["sphere"] = lambda f: scenes.translation((0.01 * f, 0.0, 0.0))
    moving = pipeline.Pipeline(setup, preset="okuno-iwasaki", progress=False, bspvt=tree_file)
    assert all(c.method == "ltc+ratio" and "'sphere' moves" in c.why
               for c in moving.plan.lights if c.kind == "area")
