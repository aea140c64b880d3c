"""The pipeline's direct stage replays one frozen function per frame (issue 25's speed
part): the frozen BSPVT shading equals the traced one (lights.bspvt.shade_bspvt with
NumPy's fresnel_image) to float rounding, its recordings stay put over frames and poses,
and per-stage kernel timing read every Nth frame adds no recordings."""

from __future__ import annotations

import numpy as np
import pytest

from glossrt import scenes as scn
from glossrt.errors import GlossrtError


@pytest.fixture(scope="module", params=["vertex", "pixel"])
def bspvt_pipe(request):
    from glossrt.pipeline import Pipeline

    pipe = Pipeline(scn.load_static("polygon-light", size=(32, 18)), preset="full",
                    progress=False, direct="ltc+bspvt", bspvt_mode=request.param,
                    bspvt_resolution=8, indirect="none", indirect_scale=1, taa=False)
    for i in range(2):
        pipe.render(i)
    return pipe


@pytest.mark.slow
def test_frozen_bspvt_matches_traced_and_keeps_recordings(bspvt_pipe):
    from glossrt.lights.bspvt import shade_bspvt
    from glossrt.lights.scene import polygon_lights
    from glossrt.lights.shading import fresnel_image

    pipe = bspvt_pipe
    rec = pipe.recordings()
    poses = [((0.4, 1.3, 4.2), (0.0, 0.4, 0.0)), ((-0.6, 1.0, 3.5), (0.1, 0.5, 0.0))]
    for k, (pos, tgt) in enumerate(poses):
        pipe.set_camera(position=pos, target=tgt)
        f = pipe.render(2 + k)
        direct = pipe.stages["direct"]
        assert direct.bspvt is not None
        # the independent path: traced anew, NumPy material rows
        ref = shade_bspvt(pipe.setup.scene, f, direct.trees, polygon_lights(pipe.setup, 2 + k),
                          pipe.opts["bspvt_mode"], f0=fresnel_image(pipe.setup, f))
        got = f.numpy("direct")
        assert ref.max() > 0.1
        np.testing.assert_allclose(got, ref, rtol=1e-5, atol=1e-5 * ref.max())
    assert pipe.recordings() == rec  # new poses replay
    pipe.clear_pose()


def test_material_image_matches_fresnel_image(bspvt_pipe):
    from glossrt.lights.shading import fresnel_image

    pipe = bspvt_pipe
    f = pipe.render(5)
    got = np.array(pipe.stages["direct"].materials(f))
    ref = fresnel_image(pipe.setup, f)
    np.testing.assert_allclose(got, ref, rtol=1e-5, atol=1e-6)


def test_timing_every_n_frames_adds_no_recordings(bspvt_pipe):
    pipe = bspvt_pipe
    pipe.timing_every = 3
    pipe.timing = "kernels"
    metas = [pipe.render(10 + i).meta["pipeline"] for i in range(3)]
    rec = pipe.recordings()
    for i in range(3, 9):
        metas.append(pipe.render(10 + i).meta["pipeline"])
    assert pipe.recordings() == rec
    # every frame names the frame whose history it reports: one read per three frames
    idx = [10 + i for i in range(3, 9)]
    read = [m["stage_ms_frame"] for m in metas[3:]]
    assert all(i - 3 < r <= i for i, r in zip(idx, read, strict=True))
    assert sum(r == i for i, r in zip(idx, read, strict=True)) == 2
    assert all(m["stage_ms"] is not None and "direct" in m["stage_ms"] for m in metas)
    assert all(set(m["stage_host_ms"]) == set(pipe.stages) for m in metas)
    with pytest.raises(GlossrtError, match="timing_every"):
        pipe.timing_every = 0
        pipe.render(30)
    pipe.timing_every = 8


@pytest.mark.slow
def test_textured_light_prefiltered_once_across_frames():
    """light-shapes' textured light: polygon_lights reads a new texture array every frame;
    the direct stage keeps one prefiltered mip chain for the same texels (before: one build
    per frame, twice per light group under ltc+ratio: the 673 ms frames)."""
    from glossrt.pipeline import Pipeline

    pipe = Pipeline(scn.load_static("light-shapes", size=(16, 12)), preset="full",
                    progress=False, direct="ltc", indirect="none", taa=False)
    for i in range(3):
        pipe.render(i)
    direct = pipe.stages["direct"]
    assert len(direct._textures) == 1 and len(direct._stable) == 1


@pytest.mark.slow
def test_oidn_time_counted_in_its_stage():
    """``indirect=oidn`` filters on the host, where Dr.Jit's kernel history sees nothing: the
    stage's ``stage_ms`` (``timing="kernels"``) holds the filter's own time
    (``stage_external_ms``), measured inside ``oidn_denoise``; before, the stage read about
    0 ms while OIDN took most of the frame."""
    from glossrt.denoise.oidn import oidn_available
    from glossrt.pipeline import Pipeline

    if not oidn_available():
        pytest.skip("pyoidn is not installed")
    pipe = Pipeline(scn.load_static("glossy-cornell", size=(64, 48)), preset="schied2017",
                    progress=False, indirect="oidn", timing_every=1)
    for i in range(3):
        meta = pipe.render(i).meta["pipeline"]
    external = meta["stage_external_ms"]
    assert set(external) == {"indirect"} and external["indirect"] > 0
    kernels = meta["stage_ms"]["indirect"] - external["indirect"]
    assert 0 <= kernels < meta["stage_ms"]["indirect"]
    # no host time is invented: below the stage's wall time, which includes it
    assert external["indirect"] <= meta["stage_host_ms"]["indirect"]
    plain = Pipeline(scn.load_static("glossy-cornell", size=(64, 48)), preset="schied2017",
                     progress=False, timing_every=1)
    assert "stage_external_ms" not in plain.render(0).meta["pipeline"]
