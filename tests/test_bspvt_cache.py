"""BSPVT trees kept on disk between processes: by default in the user's cache folder
(``$XDG_CACHE_HOME/glossrt/bspvt``; tests/conftest.py points it at a temporary folder), in
another folder or nowhere (``bspvt_cache``, ``--bspvt-cache``); a damaged or stale file is
built anew, a file is written whole or not at all, and a folder that cannot be written
costs one warning, never the render."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

from glossrt import pipeline, scenes
from glossrt.errors import GlossrtError
from glossrt.pipeline import stages

SMALL = (32, 24)
BSPVT_RES = 8  # coarse visibility maps: polygon-light's trees build in about a second
#: a pipeline file: the full preset with those coarse trees
FULL = 'preset = "full"\nbspvt_resolution = 8\n'


@pytest.fixture
def cache(tmp_path, monkeypatch):
    """A user cache folder of this test alone (``XDG_CACHE_HOME``), the trees in memory
    forgotten and the unwritable folders not yet warned about: every pipeline below reads
    the disk or builds. Returns where the trees go."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    monkeypatch.setattr(stages, "_TREES", {})
    monkeypatch.setattr(stages, "_UNWRITABLE", set())
    return tmp_path / "xdg" / "glossrt" / "bspvt"


def _pipe(**kw):
    kw = {"bspvt_resolution": BSPVT_RES, **kw}
    return pipeline.Pipeline("polygon-light", preset="okuno-iwasaki", size=SMALL,
                             progress=False, **kw)


def _toml(tmp_path) -> str:
    path = tmp_path / "full.toml"
    path.write_text(FULL)
    return str(path)


def test_the_default_cache_is_the_users_cache_folder(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert stages.default_bspvt_cache() == str(tmp_path / "glossrt" / "bspvt")
    for unset in ("", "relative/cache"):  # (the XDG specification: absolute paths only)
        monkeypatch.setenv("XDG_CACHE_HOME", unset)
        assert stages.default_bspvt_cache() == os.path.join(
            os.path.expanduser("~"), ".cache", "glossrt", "bspvt")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert stages.bspvt_cache_dir(True) == stages.default_bspvt_cache()
    assert stages.bspvt_cache_dir(False) is None and stages.bspvt_cache_dir(None) is None
    assert stages.bspvt_cache_dir(tmp_path / "mine") == str(tmp_path / "mine")
    (tmp_path / "file").write_text("x")
    for bad, msg in ((tmp_path / "file", "exists and is not a folder"), (3, "got 3"),
                     ("", "got ''")):
        with pytest.raises(GlossrtError, match=msg):
            pipeline.Pipeline("polygon-light", preset="full", bspvt_cache=bad)


def test_trees_built_in_one_process_are_read_in_the_next(cache, tmp_path):
    """The first pipeline builds the trees and keeps them in the user's cache folder; a new
    process rendering the same scene through the CLI (``full``, 64x48) reads them from there
    and builds none."""
    n = stages.BUILDS["count"]
    pipe = _pipe()
    assert stages.BUILDS["count"] == n + 1
    assert pipe.bspvt_cache == str(cache)
    files = sorted(cache.glob("bspvt-*.npz"))
    assert len(files) == 1 and pipe.stages["direct"].trees.source == str(files[0])
    assert not [p for p in cache.iterdir() if p.suffix == ".tmp"]
    out = tmp_path / "frames"
    code = ("import json, sys\nfrom glossrt.cli import main\nfrom glossrt.pipeline import "
            "stages\nrc = main(sys.argv[1:])\nprint(json.dumps({'rc': rc, 'builds': "
            "stages.BUILDS['count']}))\n")
    args = ["render", "polygon-light", "--pipeline", _toml(tmp_path), "--size", "64x48",
            "--frames", "1", "--out", str(out)]
    r = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True,
                       timeout=600, env=dict(os.environ))
    assert r.returncode == 0, r.stderr[-2000:]
    assert json.loads(r.stdout.strip().splitlines()[-1]) == {"rc": 0, "builds": 0}, r.stdout
    from glossrt.frame import Frame

    meta = Frame.load(out / "frame_0000.exr").meta["pipeline"]
    assert meta["direct"] == "ltc+bspvt"
    assert meta["bspvt"]["trees"] == str(files[0])
    assert sorted(cache.glob("bspvt-*.npz")) == files


def test_bspvt_cache_none_writes_nothing(cache, tmp_path):
    from glossrt.cli import main

    n = stages.BUILDS["count"]
    out = tmp_path / "frames"
    assert main(["render", "polygon-light", "--pipeline", _toml(tmp_path), "--bspvt-cache",
                 "none", "--size", "32x24", "--frames", "1", "--out", str(out)]) == 0
    assert stages.BUILDS["count"] == n + 1  # (built: nothing was found, nothing kept)
    assert (out / "frame_0000.exr").is_file()
    assert not (tmp_path / "xdg").exists()
    stages._TREES.clear()
    pipe = _pipe(bspvt_cache=False)
    assert pipe.bspvt_cache is None and stages.BUILDS["count"] == n + 2
    assert not (tmp_path / "xdg").exists()
    # a folder of one's own, made when the trees are first written
    stages._TREES.clear()
    mine = tmp_path / "a" / "b"
    assert main(["render", "polygon-light", "--pipeline", _toml(tmp_path), "--bspvt-cache",
                 str(mine), "--size", "32x24", "--frames", "1", "--out",
                 str(tmp_path / "f2")]) == 0
    assert len(list(mine.glob("bspvt-*.npz"))) == 1 and not (tmp_path / "xdg").exists()
    assert main(["render", "polygon-light", "--bspvt-cache", str(mine), "--size", "16x12",
                 "--out", str(tmp_path / "f3")]) == 2  # (no --pipeline: no trees)


def test_an_unwritable_cache_folder_warns_once_and_renders(cache, tmp_path, monkeypatch,
                                                          capsys):
    """A cache folder that cannot be made (its parent is a file: refused even to root) costs
    one warning per process, and the frames are rendered with the trees kept in memory."""
    from glossrt.cli import main

    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    monkeypatch.setenv("XDG_CACHE_HOME", str(blocker))
    out = tmp_path / "frames"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert main(["render", "polygon-light", "--pipeline", _toml(tmp_path), "--size",
                     "32x24", "--frames", "1", "--out", str(out)]) == 0
        # another geometry (resolution): built, again not kept, no second warning
        pipe = _pipe(bspvt_resolution=4)
    said = [str(w.message) for w in caught if "not cached on disk" in str(w.message)]
    assert len(said) == 1, said
    assert str(blocker) in said[0] and "--bspvt-cache" in said[0]
    assert (out / "frame_0000.exr").is_file()
    assert pipe.stages["direct"].trees.source == ""  # (in memory)
    assert blocker.read_text() == "not a folder"


def test_a_damaged_or_stale_cache_file_is_built_anew(cache, tmp_path):
    """Garbage, a truncated file, or trees of another resolution or geometry under the
    scene's key: the pipeline builds the trees and replaces the file with good ones."""
    from glossrt.lights.bspvt import BSPVT, build_scene_trees

    _pipe()
    path = next(cache.glob("bspvt-*.npz"))
    good = path.read_bytes()
    other = build_scene_trees(scenes.load("roughness-map").scene, BSPVT_RES, progress=False)
    coarser = build_scene_trees(scenes.load("polygon-light").scene, 4, progress=False)
    for name, write in (("garbage", lambda: path.write_bytes(b"PK\x03\x04 not a zip")),
                        ("truncated", lambda: path.write_bytes(good[: len(good) // 2])),
                        ("another scene", lambda: other.save(str(path))),
                        ("another resolution", lambda: coarser.save(str(path)))):
        write()
        stages._TREES.clear()
        n = stages.BUILDS["count"]
        pipe = _pipe()
        assert stages.BUILDS["count"] == n + 1, name
        trees = BSPVT.load(str(path))  # whole again
        assert trees.resolution == BSPVT_RES, name
        assert trees.vertex_count == pipe.stages["direct"].trees.vertex_count, name
    stages._TREES.clear()
    n = stages.BUILDS["count"]
    _pipe()
    assert stages.BUILDS["count"] == n  # (and read back)


def test_a_failed_write_leaves_no_file(cache, monkeypatch):
    """A write that fails half-way (a full disk) leaves neither a cache file nor a temporary
    one: readers never see half a file; the render goes on with a warning."""
    import glossrt.lights.bspvt.build as build

    def full_disk(f, **arrays):
        f.write(b"PK\x03\x04" + b"\0" * 1000)
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(build.np, "savez_compressed", full_disk)
    with pytest.warns(UserWarning, match="not cached on disk.*No space left"):
        pipe = _pipe()
    assert list(Path(cache).iterdir()) == []
    assert np.isfinite(pipe.render(0).numpy("direct")).all()
