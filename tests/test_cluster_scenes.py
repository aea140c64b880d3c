"""Scenes travel with the work (issue 27): an XML scene and the files it references reach
the workers as a bundle (glossrt.scenefiles) through Ray's object store, not as a path.

* a reference of an XML scene with a PLY mesh and a bitmap texture in sub-folders, rendered
  through 2 workers after the scene's folder was renamed away (the driver had loaded and
  packed it), is bit-identical to the same blocks computed in this process beforehand; so
  is a chunked BSPVT build of that scene;
* bundle(): referenced files found (includes, recursively), ``$parameters`` and absolute
  paths left alone, a missing file is one error naming it, the size cap, equal scenes give
  equal digests;
* materialise(): unpacks once per node (a second call fetches nothing), uses the folder of
  a worker that won the race, refuses tar members that leave the folder.
"""

from __future__ import annotations

import hashlib
import io
import os
import shutil
import struct
import tarfile
import time

import numpy as np
import pytest

from glossrt import backend

backend.ensure()
import mitsuba as mi  # noqa: E402

from glossrt import cluster, scenefiles, scenes  # noqa: E402
from glossrt.errors import GlossrtError  # noqa: E402
from glossrt.lights.bspvt.scene import build_scene_trees  # noqa: E402
from glossrt.render import Renderer, blocks  # noqa: E402

W, H, SPP = 32, 24, 4
ARRAYS = ("lines", "children", "leaf_value", "roots", "positions", "normals")

XML = """<scene version="3.0.0">
  <sensor type="perspective">
    <float name="fov" value="50"/>
    <transform name="to_world"><lookat origin="0, 2, 3" target="0, 0, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm">
      <integer name="width" value="40"/><integer name="height" value="30"/>
    </film>
  </sensor>
  <shape type="ply" id="floor">
    <string name="filename" value="meshes/floor.ply"/>
    <bsdf type="diffuse">
      <texture type="bitmap" name="reflectance">
        <string name="filename" value="tex/checker.png"/>
        <string name="filter_type" value="nearest"/>
      </texture>
    </bsdf>
  </shape>
  <shape type="sphere" id="ball">
    <point name="center" x="0" y="0.4" z="0"/><float name="radius" value="0.3"/>
    <bsdf type="roughconductor"><float name="alpha" value="0.2"/></bsdf>
  </shape>
  <shape type="rectangle" id="lamp">
    <transform name="to_world"><rotate x="1" angle="90"/><scale value="0.4"/>
      <translate y="2"/></transform>
    <emitter type="area"><rgb name="radiance" value="8, 8, 8"/></emitter>
  </shape>
  <!-- {tag} -->
</scene>
"""


def _write_ply(path, n: int = 3) -> None:
    """An n x n vertex grid on y = 0 (side 2) with uv, as binary PLY written with NumPy."""
    g = np.linspace(-1.0, 1.0, n, dtype=np.float32)
    x, z = np.meshgrid(g, g)
    u, v = np.meshgrid(np.linspace(0, 1, n, dtype=np.float32),
                       np.linspace(0, 1, n, dtype=np.float32))
    verts = np.zeros(n * n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("nx", "<f4"),
                                   ("ny", "<f4"), ("nz", "<f4"), ("u", "<f4"), ("v", "<f4")])
    verts["x"], verts["z"], verts["ny"] = x.ravel(), z.ravel(), 1.0
    verts["u"], verts["v"] = u.ravel(), v.ravel()
    faces = []
    for j in range(n - 1):
        for i in range(n - 1):
            a = j * n + i
            faces += [(a, a + n, a + 1), (a + 1, a + n, a + n + 1)]
    head = ("ply\nformat binary_little_endian 1.0\n"
            f"element vertex {n * n}\n"
            + "".join(f"property float {p}\n" for p in ("x", "y", "z", "nx", "ny", "nz",
                                                       "u", "v"))
            + f"element face {len(faces)}\nproperty list uchar int vertex_indices\n"
            "end_header\n")
    body = b"".join(struct.pack("<B3i", 3, *f) for f in faces)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(head.encode() + verts.tobytes() + body)


def _scene(folder, tag: str = "") -> str:
    _write_ply(folder / "meshes" / "floor.ply")
    (folder / "tex").mkdir(parents=True, exist_ok=True)
    checker = np.kron(np.indices((4, 4)).sum(0) % 2, np.ones((2, 2)))[..., None]
    img = (np.array([0.9, 0.2, 0.1]) * checker + 0.05).astype(np.float32)
    mi.Bitmap(img).convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.UInt8, True).write(
        str(folder / "tex" / "checker.png"))
    (folder / "scene.xml").write_text(XML.format(tag=tag))
    return str(folder / "scene.xml")


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("node-scenes")


@pytest.fixture(scope="module")
def local2(scene_dir):
    cm = cluster.connect("local:2", worker_env={scenefiles.ENV: str(scene_dir)})
    c = cm.__enter__()
    yield c
    cm.__exit__(None, None, None)


@pytest.fixture
def vanishing(monkeypatch, tmp_path):
    """Packing a scene renames its folder away right after (undone at the end): from then
    on only the bundle has the files."""
    moved = []
    original = scenefiles.bundle

    def bundle_then_rename(path):
        b = original(path)
        folder = os.path.dirname(os.path.abspath(path))
        os.rename(folder, folder + "-gone")
        moved.append(folder)
        return b

    monkeypatch.setattr(scenefiles, "bundle", bundle_then_rename)
    yield moved
    for folder in moved:
        os.rename(folder + "-gone", folder)


def test_reference_of_a_moved_scene_through_workers(local2, scene_dir, tmp_path, vanishing):
    path = _scene(tmp_path / "room")
    r = Renderer(scenes.load(path, size=(W, H)), seed=5, frozen=False)
    job = blocks.reference_job(path, (W, H), seed=5)
    (here,) = blocks.reference_frames(r, job, [0], SPP, cluster="none", block_spp=1)
    assert not vanishing  # in this process nothing is packed
    stats = []
    (there,) = blocks.reference_frames(r, job, [0], SPP, cluster=local2, block_spp=1,
                                       stats=stats)
    assert vanishing and not os.path.exists(path)  # the workers had only the bundle
    assert stats and all(s.node != "local" for s in stats)
    assert here.names == there.names
    for n in here.names:
        assert np.array_equal(here.numpy(n), there.numpy(n)), n
    color = here.numpy("color")
    assert np.isfinite(color).all() and color.mean() > 0
    # the texture is seen: its red checks make the floor redder than it is green
    assert color[..., 0].mean() > 1.5 * color[..., 1].mean()
    (unpacked,) = [d for d in scene_dir.iterdir() if not d.name.startswith(".")]
    assert sorted(str(p.relative_to(unpacked)) for p in unpacked.rglob("*") if p.is_file()) \
        == ["meshes/floor.ply", "scene.xml", "tex/checker.png"]


def test_chunked_bspvt_build_of_a_moved_scene(local2, tmp_path, vanishing):
    path = _scene(tmp_path / "room", tag="bspvt")  # another digest than the test above
    here = build_scene_trees(path, 8, progress=False, chunk_vertices=4)
    assert here.info["chunks"] == 3 and not vanishing
    there = build_scene_trees(path, 8, progress=False, cluster=local2, chunk_vertices=4)
    assert vanishing and not os.path.exists(path)
    for k in ARRAYS:
        a, b = getattr(here, k), getattr(there, k)
        assert a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes(), k
    assert there.vertex_count == 9


# -- bundle() / materialise() ----------------------------------------------------------------
def _tree(tmp_path):
    (tmp_path / "parts" / "deeper").mkdir(parents=True)
    (tmp_path / "tex").mkdir()
    (tmp_path / "tex" / "a.png").write_bytes(b"png-a")
    (tmp_path / "tex" / "b.exr").write_bytes(b"exr-b")
    (tmp_path / "unused.ply").write_bytes(b"not referenced")
    (tmp_path / "main.xml").write_text(
        '<scene version="3.0.0"><include filename="parts/inc.xml"/>'
        '<shape type="ply"><string name="filename" value="$mesh"/></shape>'
        '<shape type="obj"><string name="filename" value="/abs/elsewhere.obj"/></shape>'
        "</scene>")
    (tmp_path / "parts" / "inc.xml").write_text(
        '<scene version="3.0.0"><include filename="deeper/nested.xml"/></scene>')
    (tmp_path / "parts" / "deeper" / "nested.xml").write_text(
        '<scene version="3.0.0"><texture type="bitmap">'
        '<string name="filename" value="../../tex/a.png"/></texture>'
        '<emitter type="envmap"><string name="filename" value="tex/b.exr"/></emitter>'
        "</scene>")
    return tmp_path / "main.xml"


def test_bundle_finds_the_referenced_files(tmp_path):
    main = _tree(tmp_path / "s")
    b = scenefiles.bundle(main)
    assert b["xml"] == "main.xml"
    assert b["files"] == ["main.xml", "parts/deeper/nested.xml", "parts/inc.xml",
                          "tex/a.png", "tex/b.exr"]
    assert b["digest"] == hashlib.sha256(b["data"]).hexdigest()
    with tarfile.open(fileobj=io.BytesIO(b["data"])) as tar:
        assert tar.extractfile("tex/a.png").read() == b"png-a"
    time.sleep(0.01)
    other = _tree(tmp_path / "t")  # the same files elsewhere, later: the same bytes
    assert scenefiles.bundle(other)["digest"] == b["digest"]


def test_bundle_refuses_a_missing_file_and_a_huge_scene(tmp_path, monkeypatch):
    main = _tree(tmp_path)
    (tmp_path / "tex" / "a.png").unlink()
    with pytest.raises(GlossrtError, match=r"nested\.xml references '\.\./\.\./tex/a\.png'"):
        scenefiles.bundle(main)
    with pytest.raises(GlossrtError, match="scene file not found"):
        scenefiles.bundle(tmp_path / "nope.xml")
    (tmp_path / "tex" / "a.png").write_bytes(b"png-a")
    monkeypatch.setattr(scenefiles, "MAX_BYTES", 100)
    with pytest.raises(GlossrtError, match="more than"):
        scenefiles.bundle(main)


def test_materialise_once_per_node_and_a_lost_race(tmp_path, monkeypatch):
    monkeypatch.setenv(scenefiles.ENV, str(tmp_path / "node"))
    b = scenefiles.bundle(_tree(tmp_path / "s"))
    first = scenefiles.materialise(b)
    assert first == str(tmp_path / "node" / b["digest"] / "main.xml")
    assert (tmp_path / "node" / b["digest"] / "tex" / "b.exr").read_bytes() == b"exr-b"

    def no_fetch(_):
        raise AssertionError("fetched although the node has the bundle")

    assert scenefiles.materialise(dict(b, data="a-handle"), fetch=no_fetch) == first
    assert scenefiles.materialise("glossy-cornell") == "glossy-cornell"
    # another worker unpacks the same bundle while this one fetches: the winner's folder
    shutil.rmtree(tmp_path / "node")

    def racing_fetch(_):
        scenefiles.materialise(b)
        return b["data"]

    assert scenefiles.materialise(dict(b, data="h"), fetch=racing_fetch) == first
    assert [p.name for p in (tmp_path / "node").iterdir()] == [b["digest"]]  # no leftovers


def _evil(member: tarfile.TarInfo, data: bytes = b"x") -> dict:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w") as tar:
        ok = tarfile.TarInfo("scene.xml")
        ok.size = 4
        tar.addfile(ok, io.BytesIO(b"<a/>"))
        member.size = len(data) if member.isfile() else 0
        tar.addfile(member, io.BytesIO(data) if member.isfile() else None)
    raw = buf.getvalue()
    return {"xml": "scene.xml", "digest": hashlib.sha256(raw).hexdigest(), "data": raw}


@pytest.mark.parametrize("kind", ["dotdot", "absolute", "symlink", "hardlink"])
def test_materialise_refuses_escaping_members(tmp_path, monkeypatch, kind):
    node = tmp_path / "node"
    monkeypatch.setenv(scenefiles.ENV, str(node))
    m = tarfile.TarInfo({"dotdot": "../../escaped.txt", "absolute": str(tmp_path / "abs.txt"),
                         "symlink": "link", "hardlink": "hard"}[kind])
    if kind == "symlink":
        m.type, m.linkname = tarfile.SYMTYPE, str(tmp_path / "target")
    elif kind == "hardlink":
        m.type, m.linkname = tarfile.LNKTYPE, "../../etc/passwd"
    with pytest.raises(GlossrtError, match="leaves the bundle's folder|not a plain file"):
        scenefiles.materialise(_evil(m))
    assert not (tmp_path / "escaped.txt").exists() and not (tmp_path / "abs.txt").exists()
    assert list(node.iterdir()) == []  # the temporary folder is gone, nothing in place
    with pytest.raises(GlossrtError, match="does not match its digest"):
        scenefiles.materialise(dict(_evil(tarfile.TarInfo("fine.txt")), digest="0" * 64))
    with pytest.raises(GlossrtError, match="XML path"):
        scenefiles.materialise(dict(_evil(tarfile.TarInfo("fine.txt")), xml="../x.xml"))
