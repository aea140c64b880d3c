"""glossrt.frame: channel schema, EXR round trip, camera projection and error messages."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from glossrt import backend
from glossrt.errors import FrameError
from glossrt.frame import (
    CHANNELS,
    HEADER_ATTRIBUTE,
    RADIANCE,
    Camera,
    Frame,
    check_same_size,
    component_names,
    frame_filename,
    load_sequence,
)

backend.ensure()
import mitsuba as mi  # noqa: E402

W, H = 7, 5
EXTRAS = {"denoised": 3, "variance": 1, "aux4": 4, "features": 11}


def look_at(origin=(1.0, 2.0, 3.0), target=(0.0, 0.3, 0.0)) -> np.ndarray:
    t = mi.ScalarTransform4f().look_at(origin=list(origin), target=list(target), up=[0, 1, 0])
    return np.array(t.matrix, dtype=np.float64)


def make_frame(w: int = W, h: int = H, seed: int = 0, extras: bool = True) -> Frame:
    rng = np.random.default_rng(seed)
    ch: dict[str, np.ndarray] = {}
    for name, comps in CHANNELS.items():
        ch[name] = rng.standard_normal((h, w, len(comps))).astype(np.float32)
    mesh = rng.integers(0, 4, (h, w, 1)).astype(np.float32)
    mesh[0, 0, 0] = 0.0
    ch["mesh_id"] = mesh
    depth = rng.uniform(0.1, 100.0, (h, w, 1)).astype(np.float32)
    depth[mesh == 0] = np.inf
    ch["depth"] = depth
    ch["color"] = sum(ch[n] for n in RADIANCE).astype(np.float32)
    # awkward bit patterns that must survive the round trip
    ch["roughness"][0, 0, 0] = -0.0
    ch["roughness"][0, 1, 0] = np.float32(1e-45)  # denormal
    ch["position"][0, 0, 0] = np.float32(3.4e38)
    if extras:
        for name, n in EXTRAS.items():
            ch[name] = rng.standard_normal((h, w, n)).astype(np.float32)
    cam = Camera(look_at(), 45.0, (w, h))
    prev = Camera(look_at(origin=(1.1, 2.0, 3.0)), 45.0, (w, h))
    meta = {"scene": "cornell", "spp": 1, "seed": np.int64(7), "nan_count": 0, "x": 1 / 3}
    return Frame(ch, camera=cam, prev_camera=prev, index=3, meta=meta)


def bits(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.float32).view(np.uint32)


# -- schema ------------------------------------------------------------------------------------


def test_schema_order_and_components():
    assert list(CHANNELS) == [
        "color", "emission", "direct_diffuse", "direct_specular", "indirect_diffuse",
        "indirect_specular", "albedo_diffuse", "albedo_specular", "normal", "position",
        "depth", "roughness", "roughness_uv", "tangent", "distribution", "mesh_id", "motion",
    ]  # fmt: skip
    assert set(RADIANCE) < set(CHANNELS)
    assert CHANNELS["normal"] == ("X", "Y", "Z") and CHANNELS["motion"] == ("X", "Y")
    assert component_names("extra", 1) == ("Y",)
    assert component_names("extra", 4) == ("R", "G", "B", "A")
    assert component_names("extra", 6) == tuple("012345")
    assert frame_filename(12) == "frame_0012.exr"


# -- round trip --------------------------------------------------------------------------------


def test_round_trip_bit_exact(tmp_path: Path):
    f = make_frame()
    feat = f.numpy("features")
    feat[1, 2, 5] = np.nan
    f["features"] = mi.TensorXf(feat)
    path = f.save(tmp_path / frame_filename(f.index))
    assert path.name == "frame_0003.exr"
    g = Frame.load(path)
    assert g.source == str(path)
    assert g.names == f.names
    for name in f.names:
        assert isinstance(g[name], mi.TensorXf)
        assert tuple(g[name].shape) == tuple(f[name].shape)
        np.testing.assert_array_equal(bits(g.numpy(name)), bits(f.numpy(name)), err_msg=name)
    assert np.isposinf(g.numpy("depth")).sum() == (f.numpy("mesh_id") == 0).sum()
    assert g.camera == f.camera and g.prev_camera == f.prev_camera
    assert g.camera.to_world.dtype == np.float64
    assert g.index == 3
    assert g.meta == {"scene": "cornell", "spp": 1, "seed": 7, "nan_count": 0, "x": 1 / 3}
    assert (g.width, g.height) == (W, H)
    assert sorted(os.listdir(tmp_path)) == ["frame_0003.exr"]


def test_round_trip_without_cameras(tmp_path: Path):
    f = Frame({"depth": np.full((H, W), np.inf, np.float32)})
    g = Frame.load(f.save(tmp_path / "d.exr"))
    assert g.camera is None and g.prev_camera is None and g.names == ("depth",)
    assert g.numpy("depth").shape == (H, W, 1)


def test_exr_readable_by_plain_bitmap(tmp_path: Path):
    f = make_frame()
    path = f.save(tmp_path / "f.exr")
    bmp = mi.Bitmap(str(path))
    expected = {f"{n}.{c}" for n, comps in CHANNELS.items() for c in comps}
    expected |= {f"{n}.{c}" for n, k in EXTRAS.items() for c in component_names(n, k)}
    expected |= {"R", "G", "B"}  # the root layer generic viewers show: a copy of color
    assert {fld.name for fld in bmp.struct_()} == expected
    assert "depth.Z" in expected and "roughness.Y" in expected and "color.R" in expected
    assert HEADER_ATTRIBUTE in bmp.metadata()
    # a standard OpenEXR string attribute: name, NUL, type name, NUL, size, JSON text
    assert HEADER_ATTRIBUTE.encode() + b"\0string\0" in path.read_bytes()[:20000]
    layers = dict(bmp.split())
    assert set(layers) == set(CHANNELS) | set(EXTRAS) | {"<root>"}
    np.testing.assert_array_equal(np.array(layers["color"]), f.numpy("color"))
    np.testing.assert_array_equal(np.array(layers["<root>"]), f.numpy("color"))
    np.testing.assert_array_equal(np.array(layers["normal"]), f.numpy("normal"))


def test_foreign_exr_loads_without_camera(tmp_path: Path):
    rgb = np.random.default_rng(1).random((H, W, 3)).astype(np.float32)
    mi.Bitmap(rgb, mi.Bitmap.PixelFormat.RGB).write(str(tmp_path / "ref.exr"))
    g = Frame.load(tmp_path / "ref.exr", require=("color",))
    assert g.camera is None and g.names == ("color",)
    np.testing.assert_array_equal(g.numpy("color"), rgb)


def test_meta_must_be_json(tmp_path: Path):
    f = make_frame(extras=False)
    f.meta["bad"] = object()
    with pytest.raises(FrameError, match="JSON"):
        f.save(tmp_path / "x.exr")
    assert os.listdir(tmp_path) == []


# -- camera --------------------------------------------------------------------------------------


def test_camera_dict_round_trip():
    cam = Camera(look_at(), 39.5, (640, 360))
    assert Camera.from_dict(cam.to_dict()) == cam
    np.testing.assert_array_equal(cam.position, np.array(look_at())[:3, 3])
    with pytest.raises(FrameError, match="resolution"):
        Camera.from_dict({"to_world": np.eye(4).tolist(), "fov": 40})
    with pytest.raises(FrameError, match="fov"):
        Camera(np.eye(4), 180.0, (4, 4))


def test_camera_focal_length_and_pixel_angle():
    """One place for the focal-length arithmetic: ``focal_px = (W / 2) / tan(fov / 2)``, a
    point ``(x, y, z)`` in camera space lands ``focal_px * y / z`` pixels above the centre,
    and one pixel subtends ``2 tan(fov / 2) / W`` at the centre."""
    cam = Camera(np.eye(4), 60.0, (640, 360))
    t = np.tan(np.radians(60.0) / 2.0)
    assert cam.tan_half_fov == pytest.approx(t, rel=1e-15)
    assert cam.focal_px == pytest.approx(320.0 / t, rel=1e-15)
    assert cam.pixel_angle() == pytest.approx(2.0 * t / 640, rel=1e-15)
    assert cam.pixel_angle(320) == pytest.approx(2.0 * t / 320, rel=1e-15)
    px = cam.project(np.array([0.0, 0.25, 2.0]))  # identity to_world: camera space
    assert px[1] == pytest.approx(180.0 - cam.focal_px * 0.125, rel=1e-12)


@pytest.mark.parametrize("fov,res", [(45.0, (64, 40)), (80.0, (31, 57))])
def test_project_matches_mitsuba_sample_ray(fov: float, res: tuple[int, int]):
    to_world = mi.ScalarTransform4f().look_at(origin=[1, 2, 3], target=[0, 0.3, 0], up=[0, 1, 0])
    sensor = mi.load_dict({
        "type": "perspective", "fov": fov, "to_world": to_world,
        "film": {"type": "hdrfilm", "width": res[0], "height": res[1]},
    })  # fmt: skip
    cam = Camera(np.array(to_world.matrix, dtype=np.float64), fov, res)
    assert Camera.from_sensor(sensor) == Camera(
        np.array(mi.traverse(sensor)["to_world"].matrix, dtype=np.float64)[..., 0], fov, res
    )
    uvs = np.array([[0.5, 0.5], [0.1, 0.2], [0.9, 0.7], [0.0, 1.0], [1.0, 0.0], [0.33, 0.81]])
    u, v = (mi.Float(uvs[:, k].astype(np.float32)) for k in (0, 1))
    ray, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f(u, v), mi.Point2f(0.5, 0.5))
    o = np.array(ray.o, dtype=np.float64).T  # Dr.Jit arrays convert as (3, N)
    d = np.array(ray.d, dtype=np.float64).T
    pts = o + np.array([[0.7], [2.7], [9.0], [1.0], [3.3], [5.0]]) * d
    px = cam.project(pts)
    np.testing.assert_allclose(px, uvs * np.array(res), atol=1e-3)  # pixels
    assert cam.project(np.array(pts[0])).shape == (2,)
    behind = 2 * cam.position - pts[0]
    assert np.isnan(cam.project(behind[None])).all()


# -- errors --------------------------------------------------------------------------------------


def test_missing_channel_names_channel_and_file(tmp_path: Path):
    f = Frame({"color": np.zeros((H, W, 3), np.float32)})
    with pytest.raises(FrameError, match=r"'emission'.*<in-memory frame>"):
        f["emission"]
    path = f.save(tmp_path / "frame_0000.exr")
    g = Frame.load(path)
    with pytest.raises(FrameError) as e:
        g["motion"]
    assert "motion" in str(e.value) and str(path) in str(e.value)
    with pytest.raises(FrameError) as e:
        Frame.load(path, require=("color", "normal", "motion"))
    msg = str(e.value)
    assert "normal" in msg and "motion" in msg and str(path) in msg
    with pytest.raises(FrameError, match="depth"):
        g.require("color", "depth")
    (c,) = g.require("color")
    assert tuple(c.shape) == (H, W, 3)


def test_corrupt_and_missing_files(tmp_path: Path):
    bad = tmp_path / "bad.exr"
    bad.write_bytes(b"not an exr at all" * 10)
    with pytest.raises(FrameError, match="bad.exr"):
        Frame.load(bad)
    good = make_frame(extras=False).save(tmp_path / "good.exr")
    trunc = tmp_path / "trunc.exr"
    trunc.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    with pytest.raises(FrameError, match="trunc.exr"):
        Frame.load(trunc)
    with pytest.raises(FrameError, match="nope.exr"):
        Frame.load(tmp_path / "nope.exr")


def test_unwritable_folder(tmp_path: Path):
    f = make_frame(extras=False)
    with pytest.raises(FrameError, match="missing_dir"):
        f.save(tmp_path / "missing_dir" / "f.exr")
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(FrameError, match="file"):
        f.save(blocker / "f.exr")
    if os.geteuid() != 0:  # root ignores directory permissions
        ro = tmp_path / "ro"
        ro.mkdir()
        ro.chmod(0o500)
        try:
            with pytest.raises(FrameError, match="ro"):
                f.save(ro / "f.exr")
            assert os.listdir(ro) == []
        finally:
            ro.chmod(0o700)


@pytest.mark.parametrize("exc", [OSError("disk full"), KeyboardInterrupt()])
def test_interrupted_save_leaves_nothing(tmp_path: Path, monkeypatch, exc: BaseException):
    f = make_frame(extras=False)
    old = f.save(tmp_path / "f.exr").read_bytes()

    def boom(*args, **kwargs):
        raise exc

    monkeypatch.setattr(os, "replace", boom)
    with pytest.raises(FrameError if isinstance(exc, OSError) else KeyboardInterrupt):
        make_frame(seed=5, extras=False).save(tmp_path / "f.exr")
    monkeypatch.undo()
    assert os.listdir(tmp_path) == ["f.exr"]
    assert (tmp_path / "f.exr").read_bytes() == old


def test_component_and_size_mismatch():
    f = make_frame(extras=False)
    with pytest.raises(FrameError, match=r"'normal'.*2 component.*3"):
        f["normal"] = np.zeros((H, W, 2), np.float32)
    with pytest.raises(FrameError, match=r"'albedo_diffuse' .* 8x5"):
        f["albedo_diffuse"] = np.zeros((H, W + 1, 3), np.float32)
    with pytest.raises(FrameError, match="camera resolution"):
        Frame({"depth": np.zeros((H + 1, W, 1), np.float32)}, camera=f.camera)
    with pytest.raises(FrameError, match="H x W x C"):
        f["extra"] = np.zeros(5, np.float32)
    f["extra"] = np.ones((H, W, 6), np.float32)  # extras take any component count
    assert f.numpy("extra").shape == (H, W, 6)
    f["normal"] = mi.TensorXf(np.zeros((H, W, 3), np.float32))
    assert "normal" in f


def test_load_sequence(tmp_path: Path):
    with pytest.raises(FrameError, match="no"):
        load_sequence(tmp_path)
    for i in (2, 0, 1):
        make_frame(seed=i, extras=False).save(tmp_path / frame_filename(i))
    (tmp_path / "notes.txt").write_text("ignored")
    frames = load_sequence(tmp_path, require=("color",))
    assert [Path(fr.source).name for fr in frames] == [frame_filename(i) for i in range(3)]
    assert check_same_size(frames) == (W, H)
    make_frame(w=W + 1, extras=False).save(tmp_path / frame_filename(3))
    with pytest.raises(FrameError) as e:
        load_sequence(tmp_path)
    msg = str(e.value)
    assert "frame_0003.exr" in msg and f"{W + 1}x{H}" in msg and f"{W}x{H}" in msg
    with pytest.raises(FrameError, match="motion"):
        load_sequence(tmp_path, require=("motion", "foo"))


def test_nonfinite_counts():
    f = make_frame(extras=False)
    counts = f.nonfinite_counts()
    assert set(counts) == set(f.names) and sum(counts.values()) == 0
    c = f.numpy("color")
    c[1, 2] = [np.nan, 0, np.inf]
    c[2, 2, 0] = -np.inf
    f["color"] = c
    mesh = f.numpy("mesh_id")
    d = f.numpy("depth")
    fg = np.argwhere(mesh[..., 0] != 0)[0]
    d[fg[0], fg[1], 0] = np.inf  # +inf on a mesh pixel is a bug
    f["depth"] = d
    counts = f.nonfinite_counts()
    assert counts["color"] == 2 and counts["depth"] == 1


# -- I/O without a JIT backend, the viewers' root layer, multi-part files, odd paths -----------

_NO_JIT = r"""
import sys


class _NoJit:
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in ("mitsuba", "drjit"):
            raise ImportError(f"{name} is blocked in this test")
        return None


sys.meta_path.insert(0, _NoJit())
import numpy as np
from glossrt.frame import Frame

f = Frame.load(sys.argv[1], require="color")
np.savez(sys.argv[2], **{n: f.numpy(n) for n in f.names})
f.save(sys.argv[3])
assert "mitsuba" not in sys.modules and "drjit" not in sys.modules
print("names", ",".join(f.names), f.index)
"""


def test_load_and_save_without_mitsuba_or_drjit(tmp_path: Path):
    import subprocess
    import sys

    f = make_frame()
    src = f.save(tmp_path / "in.exr")
    script = tmp_path / "nojit.py"
    script.write_text(_NO_JIT)
    env = {k: v for k, v in os.environ.items() if k != "DRJIT_LIBLLVM_PATH"}
    r = subprocess.run(
        [sys.executable, str(script), str(src), str(tmp_path / "ch.npz"), str(tmp_path / "o.exr")],
        capture_output=True, text=True, env=env, timeout=120,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert f"names {','.join(f.names)} 3" in r.stdout
    with np.load(tmp_path / "ch.npz") as z:
        for name in f.names:
            np.testing.assert_array_equal(bits(z[name]), bits(f.numpy(name)), err_msg=name)
    g = Frame.load(tmp_path / "o.exr")  # written there without a backend: still bit-exact
    assert g.names == f.names and g.camera == f.camera and g.meta == Frame.load(src).meta
    for name in f.names:
        np.testing.assert_array_equal(bits(g.numpy(name)), bits(f.numpy(name)), err_msg=name)


def test_root_rgb_layer_equals_color_for_viewers(tmp_path: Path):
    import OpenEXR  # an independent reader

    f = make_frame()
    path = f.save(tmp_path / "f.exr")
    exr = OpenEXR.File(str(path), separate_channels=True)
    header = exr.parts[0].header
    chans = {n: np.array(c.pixels) for n, c in exr.parts[0].channels.items()}
    assert {"R", "G", "B"} <= set(chans)
    color = f.numpy("color")
    for k, c in enumerate("RGB"):
        assert chans[c].dtype == np.float32
        np.testing.assert_array_equal(bits(chans[c]), bits(color[..., k]), err_msg=c)
        np.testing.assert_array_equal(bits(chans[f"color.{c}"]), bits(color[..., k]))
    assert HEADER_ATTRIBUTE in header
    # loading does not show the viewers' copy as a second layer
    assert Frame.load(path).names == f.names
    # a frame without color has no root layer
    p2 = Frame({"depth": np.ones((H, W), np.float32)}).save(tmp_path / "d.exr")
    with OpenEXR.File(str(p2), separate_channels=True) as exr:
        assert set(exr.channels()) == {"depth.Z"}


def test_root_rgb_that_differs_from_color_is_kept_as_rgb(tmp_path: Path):
    import OpenEXR

    rng = np.random.default_rng(4)
    planes = {n: rng.random((H, W)).astype(np.float32)
              for n in ("R", "G", "B", "color.R", "color.G", "color.B")}  # fmt: skip
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION}, dict(planes)).write(
        str(tmp_path / "x.exr"))
    g = Frame.load(tmp_path / "x.exr")
    assert set(g.names) == {"color", "rgb"}
    np.testing.assert_array_equal(g.numpy("rgb")[..., 1], planes["G"])
    np.testing.assert_array_equal(g.numpy("color")[..., 2], planes["color.B"])


def _write_parts(path: Path, *parts: tuple[str, dict], header: dict | None = None) -> None:
    """A multi-part EXR written by the openexr package (Part() consumes its dict: copies)."""
    import OpenEXR

    OpenEXR.File([OpenEXR.Part(dict(header or {}), dict(ch), name) for name, ch in parts]).write(
        str(path))


def test_multipart_exr_parts_are_all_read(tmp_path: Path):
    rng = np.random.default_rng(2)

    def plane():
        return rng.standard_normal((H, W)).astype(np.float32)

    beauty = {"R": plane(), "G": plane(), "B": plane()}
    aux = {"depth.Z": plane(), "normal.X": plane(), "normal.Y": plane(), "normal.Z": plane()}
    _write_parts(tmp_path / "two.exr", ("beauty", beauty), ("aux", aux))
    g = Frame.load(tmp_path / "two.exr", require=("color", "depth", "normal"))
    assert set(g.names) == {"color", "depth", "normal"}
    np.testing.assert_array_equal(g.numpy("color"), np.stack([beauty[c] for c in "RGB"], -1))
    np.testing.assert_array_equal(g.numpy("depth")[..., 0], aux["depth.Z"])
    np.testing.assert_array_equal(g.numpy("normal")[..., 2], aux["normal.Z"])

    # parts that share channel names: the part names prefix them
    left, right = {"R": plane(), "G": plane(), "B": plane()}, {"R": plane(), "G": plane(),
                                                               "B": plane()}
    _write_parts(tmp_path / "stereo.exr", ("left", left), ("right", right))
    s = Frame.load(tmp_path / "stereo.exr")
    assert set(s.names) == {"left", "right"}
    np.testing.assert_array_equal(s.numpy("right")[..., 0], right["R"])
    np.testing.assert_array_equal(s.numpy("left")[..., 2], left["B"])

    # parts of different sizes are refused by name
    small = {"Z": np.zeros((H - 1, W), np.float32)}
    display = {"displayWindow": (np.array([0, 0], np.int32), np.array([W - 1, H - 1], np.int32))}
    _write_parts(tmp_path / "sizes.exr", ("beauty", beauty), ("z", small), header=display)
    with pytest.raises(FrameError, match=r"sizes\.exr: part 1"):
        Frame.load(tmp_path / "sizes.exr")


def test_paths_with_non_utf8_bytes(tmp_path: Path):
    folder = tmp_path / os.fsdecode(b"dir\xff")
    folder.mkdir()
    path = folder / os.fsdecode(b"fr\xfe.exr")
    f = make_frame(extras=False)
    assert f.save(path) == path
    assert os.listdir(os.fsencode(folder)) == [b"fr\xfe.exr"]
    for p in (path, os.fsencode(path), str(path)):
        g = Frame.load(p, require="color")
        np.testing.assert_array_equal(bits(g.numpy("color")), bits(f.numpy("color")))
    assert load_sequence(folder)[0].names == f.names
    with pytest.raises(FrameError) as e:
        Frame.load(folder / os.fsdecode(b"missing\xfd.exr"))
    msg = str(e.value)
    msg.encode("utf-8")  # printable: the odd byte is shown, not a lone surrogate
    assert "missing\\xfd.exr" in msg
    with pytest.raises(FrameError) as e:
        f.save(folder / os.fsdecode(b"no\xfc") / "f.exr")
    str(e.value).encode("utf-8")
    assert "no\\xfc" in str(e.value)


def test_require_takes_one_name_or_several(tmp_path: Path):
    f = make_frame(extras=False)
    path = f.save(tmp_path / "f.exr")
    assert Frame.load(path, require="color").names == f.names
    with pytest.raises(FrameError) as e:
        Frame.load(path, require="denoised")
    assert "lacks required channel(s) denoised " in str(e.value)  # not d, e, n, ...
    assert len(load_sequence(tmp_path, require="motion")) == 1
    (c,) = f.require("color")
    (d,) = f.require(["depth"])
    assert tuple(d.shape) == (H, W, 1) and tuple(c.shape) == (H, W, 3)
    with pytest.raises(FrameError, match="must be str"):
        Frame.load(path, require=[3])


def test_openexr_is_a_declared_dependency():
    import tomllib

    pyproject = Path(__file__).resolve().parents[1] / "pyproject.toml"
    deps = tomllib.loads(pyproject.read_text())["project"]["dependencies"]
    assert any(d.lower().startswith("openexr") for d in deps), deps
