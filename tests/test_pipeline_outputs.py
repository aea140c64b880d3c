"""Issue 25, memory: the pipeline's marked outputs (``Pipeline(outputs=...)``, the render
graph's). A channel no later stage reads and the caller did not ask for is freed after its
last reader; the values stay the same, the frame holds only what was asked for, and a frame's
peak memory drops."""

import numpy as np
import pytest

from glossrt import pipeline, scenes
from glossrt.errors import GlossrtError

SIZE = (48, 36)


def _frames(preset: str, scene: str, outputs, frames: int = 2, **choices):
    pipe = pipeline.Pipeline(scenes.load(scene, size=SIZE), preset=preset, progress=False,
                             bspvt_resolution=8, outputs=outputs, **choices)
    return [pipe.render(i) for i in range(frames)]


# every preset, and the choices whose stages read other channels (atrous: position; the
# reduced-resolution light with re-sampling; ratio and highlights direct light; TAA off)
CASES = [
    ("schied2017", "glossy-cornell", {}),
    ("tokuyoshi2015", "glossy-cornell", {}),
    ("okuno-iwasaki", "polygon-light", {}),
    ("kimura-tokoi", "polygon-light", {}),
    ("full", "polygon-light", {}),
    ("full", "glossy-cornell", {"indirect": "atrous", "resample": True}),
    ("full", "polygon-light", {"direct": "ltc+ratio", "taa": False, "indirect_scale": 4,
                               "upsampling": "joint-bilateral"}),
    ("schied2017", "polygon-light", {"indirect": "atrous", "direct": "ltc"}),
    ("reference", "glossy-cornell", {"spp": 2}),
    ("full", "normal-mapped", {"specaa": "avgnormal-eig"}),
    ("schied2017", "glossy-cornell", {"indirect": "oidn"}),
]


@pytest.mark.slow
@pytest.mark.parametrize("preset,scene,choices", CASES,
                         ids=[f"{p}-{s}-{i}" for i, (p, s, _) in enumerate(CASES)])
def test_fewest_outputs_same_color(preset, scene, choices):
    """``outputs=("color",)`` frees every other channel as soon as it is read for the last
    time (and folds emission into the direct light early): frame after frame the composed
    colour is bit-identical to the frames that keep everything, and the frame holds only
    ``color``. A stage that read a channel it does not declare (Stage.reads) would fail
    here with a missing channel, or differ."""
    if choices.get("indirect") == "oidn":
        from glossrt.denoise.oidn import oidn_available

        if not oidn_available():
            pytest.skip("pyoidn is not installed")
    every = _frames(preset, scene, None, **choices)
    fewest = _frames(preset, scene, ("color",), **choices)
    for a, b in zip(every, fewest, strict=True):
        np.testing.assert_array_equal(b.numpy("color"), a.numpy("color"))
        assert b.names == ("color",)
        assert b.meta["pipeline"]["outputs"] == ["color"]
        assert b.meta["pipeline"]["layers"] == ["color"]
        assert {"normal", "direct", "indirect", "composite"} <= set(a.names)
        assert a.meta["pipeline"]["outputs"] == "all"


@pytest.mark.slow
def test_chosen_outputs_same_values():
    """A choice of layers and G-buffer channels: exactly those (and ``color``), each equal
    to the frame that keeps everything; changing the outputs between frames keeps the
    histories (no reset) and the values."""
    setup = scenes.load("polygon-light", size=SIZE)
    pipe_all = pipeline.Pipeline(setup, preset="full", progress=False, bspvt_resolution=8)
    pipe = pipeline.Pipeline(scenes.load("polygon-light", size=SIZE), preset="full",
                             progress=False, bspvt_resolution=8,
                             outputs=("direct", "normal", "emission"))
    want = [("color", "direct", "normal", "emission"), ("color",), ("color", "indirect")]
    for i, names in enumerate(want):
        if i:
            pipe.outputs = names[1:]
        a, b = pipe_all.render(i), pipe.render(i)
        assert set(b.names) == set(names)
        for k in names:
            np.testing.assert_array_equal(b.numpy(k), a.numpy(k))


def test_outputs_refused():
    setup = scenes.load("polygon-light", size=SIZE)
    with pytest.raises(GlossrtError, match="unknown output channel.*nromal.*normal"):
        pipeline.Pipeline(setup, preset="full", progress=False, outputs=("nromal",))
    pipe = pipeline.Pipeline(setup, preset="schied2017", progress=False)
    with pytest.raises(GlossrtError, match="outputs must be channel names"):
        pipe.outputs = 3
    assert pipe.outputs is None
    pipe.outputs = "direct"  # (one name)
    assert pipe.outputs == ("color", "direct")


@pytest.mark.slow
def test_fewest_outputs_lower_peak():
    """The memory the marked outputs save, measured with Dr.Jit's allocator (``full`` at
    128x96 on polygon-light, ``release_memory``, steady frames of one pipeline whose outputs
    alternate between everything and ``color``). What the context holds when the indirect
    stage starts drops by at least what liveness frees before it with ``color`` only: the
    position (no later stage reads it) and one of emission and direct (folded), each a
    3-channel image rounded up to a power of two by the allocator. (The low frame's unread
    channels go with any outputs: it is never one.) The frame's peak drops too."""
    import drjit as dr

    from glossrt.backend import is_gpu

    backend = dr.JitBackend.CUDA if is_gpu() else dr.JitBackend.LLVM
    size = (128, 96)

    def held() -> int:
        dr.sync_thread()
        dr.flush_malloc_cache()
        dr.detail.malloc_clear_statistics()
        return dr.detail.malloc_watermark(backend)

    pipe = pipeline.Pipeline(scenes.load_static("polygon-light", size=size), preset="full",
                             progress=False, bspvt_resolution=8, release_memory=True)
    for i in range(3):
        pipe.render(i)
    stage = pipe.stages["indirect"]
    at_indirect: list[int] = []

    def run(index, ctx, run=stage.run):
        at_indirect.append(held())
        return run(index, ctx)

    stage.run = run
    peaks = []
    for i in range(3, 7):
        pipe.outputs = None if i % 2 else ("color",)
        live = held()
        pipe.render(i)
        dr.sync_thread()
        peaks.append(dr.detail.malloc_watermark(backend) - live)

    def image(w: int, h: int) -> int:  # (the allocator's power of two)
        return 1 << (w * h * 3 * 4 - 1).bit_length()

    freed = 2 * image(*size)
    saved = [at_indirect[k] - at_indirect[k + 1] for k in (0, 2)]
    print(f"\nsteady 128x96 full frames, every output / color only: held at the indirect "
          f"stage's start {[round(b / 2**20, 3) for b in at_indirect]} MiB ({saved} bytes "
          f"less, {freed} expected); allocator peak above the live set "
          f"{[round(b / 2**20, 3) for b in peaks]} MiB")
    assert min(saved) >= freed
    assert peaks[1] < peaks[0] and peaks[3] < peaks[2]


def test_bspvt_vertex_mode_needs_no_material_image():
    """BSPVT's vertex mode reads the vertices' materials, never the pixels': given the
    MaterialImage itself, the frozen shader shades the same values as with the image made,
    and never makes it (no recording of the material kernel)."""
    from glossrt import render
    from glossrt.lights.bspvt.scene import FrozenShader, MaterialImage
    from glossrt.lights.scene import polygon_lights
    from glossrt.pipeline.stages import scene_trees

    setup = scenes.load_static("polygon-light", size=SIZE)
    frame = render.Renderer(setup).render(0)
    lights = polygon_lights(setup, 0)
    trees = scene_trees(setup.scene, 8, progress=False)
    lazy = MaterialImage(setup.scene)
    made = MaterialImage(setup.scene)
    a = np.array(FrozenShader(setup.scene, trees, "vertex")(frame, lights, f0=lazy))
    b = np.array(FrozenShader(setup.scene, trees, "vertex")(frame, lights, f0=made(frame)))
    assert np.abs(b).max() > 0
    np.testing.assert_array_equal(a, b)
    assert lazy._fn.n_recordings == 0 and made._fn.n_recordings == 1
    # pixel mode reads the pixels' materials: the image is made there
    c = np.array(FrozenShader(setup.scene, trees, "pixel")(frame, lights, f0=lazy))
    d = np.array(FrozenShader(setup.scene, trees, "pixel")(frame, lights, f0=made(frame)))
    np.testing.assert_array_equal(c, d)
    assert lazy._fn.n_recordings == 1


@pytest.mark.slow
def test_liveness_frees_after_last_reader():
    """What each stage of ``full`` finds in the context with ``color`` only: the low frame
    without the channels its stage does not read (emission, position) and gone after the
    indirect stage; the position gone after the direct stage; emission and direct folded
    into one entry before the indirect stage; the composite's inputs gone before TAA."""
    pipe = pipeline.Pipeline(scenes.load_static("polygon-light", size=SIZE), preset="full",
                             progress=False, bspvt_resolution=8, outputs=("color",))
    seen: dict[str, tuple] = {}
    for name, stage in pipe.stages.items():
        def run(index, ctx, run=stage.run, name=name):
            low = ctx.get("frame_low")
            seen[name] = (set(ctx), set(ctx["frame"].names) if "frame" in ctx else set(),
                          None if low is None else set(low.names))
            return run(index, ctx)

        stage.run = run
    for i in range(2):
        pipe.render(i)
    keys, names, low = seen["direct"]
    assert "position" in names and "emission" in names
    assert low is not None and not {"emission", "position"} & low
    assert {"normal", "indirect_diffuse", "indirect_specular"} <= low
    keys, names, low = seen["indirect"]
    assert "position" not in names and "emission" not in names
    assert "emission+direct" in keys and "direct" not in keys
    keys, names, low = seen["composite"]
    assert "frame_low" not in keys and low is None
    keys, names, low = seen["taa"]
    assert keys == {"frame", "composite"} and names == {"mesh_id", "motion"}


@pytest.mark.slow
def test_render_cli_outputs(tmp_path, capsys):
    """``glossrt render --pipeline P --outputs NAMES`` writes only those channels (and
    color), the same values as a render that keeps everything; a bad name, or --outputs
    without --pipeline, is one line before anything is written."""
    from glossrt.cli import main
    from glossrt.frame import Frame

    common = ["render", "polygon-light", "--pipeline", "tokuyoshi2015", "--frames", "2", "--size",
              "32x24"]
    assert main(common + ["--out", str(tmp_path / "all")]) == 0
    assert main(common + ["--out", str(tmp_path / "some"), "--outputs", "direct, normal"]) == 0
    a = Frame.load(tmp_path / "all" / "frame_0001.exr")
    b = Frame.load(tmp_path / "some" / "frame_0001.exr")
    assert set(b.names) == {"color", "direct", "normal"}
    assert b.meta["pipeline"]["outputs"] == ["color", "direct", "normal"]
    for k in b.names:
        np.testing.assert_array_equal(b.numpy(k), a.numpy(k))
    capsys.readouterr()
    for extra in (["--pipeline", "full", "--outputs", "color,nromal"],
                  ["--outputs", "color"]):
        bad = tmp_path / "bad"
        assert main(["render", "polygon-light", "--size", "32x24", "--out", str(bad)]
                    + extra) != 0
        assert not bad.exists()
    err = capsys.readouterr().err
    assert "unknown output channel(s) nromal" in err and "goes with --pipeline" in err
    assert "Traceback" not in err
