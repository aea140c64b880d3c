"""BSPVT builds by vertex chunks (issue 27): work items that a cluster can run anywhere.

* three uneven chunks of polygon-light (R = 8), computed in reversed order and merged, give
  the one-process build (:func:`build_scene_trees` on the loaded scene: one visibility pass,
  one :func:`build_trees` over all vertices) array for array, byte for byte -- also with a
  per-face leaf budget;
* a chunk computed in a fresh Python process from its plain-data item (scene name, vertex
  range, settings as JSON) equals the same chunk computed here;
* bad chunkings and a scene passed as an object are refused with one clear error.
"""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from glossrt import backend

backend.ensure()

from glossrt import scenes  # noqa: E402
from glossrt.errors import GlossrtError  # noqa: E402
from glossrt.lights.bspvt import build  # noqa: E402
from glossrt.lights.bspvt.scene import build_scene_trees  # noqa: E402

SCENE = "polygon-light"
RES = 8
ARRAYS = ("lines", "children", "leaf_value", "roots", "positions", "normals")


def _same_bytes(a: np.ndarray, b: np.ndarray) -> bool:
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


@pytest.fixture(scope="module")
def monolithic():
    return build_scene_trees(scenes.load(SCENE).scene, RES, progress=False)


def _uneven_items(n: int, **settings) -> list[dict]:
    (template,) = build.vertex_chunk_items(SCENE, n, RES, 0.0, "batched", n, **settings)
    cuts = [(0, 1000), (1000, 1001), (1001, n)]  # a big, a single-vertex and the rest
    return [dict(template, start=a, stop=b) for a, b in cuts]


@pytest.mark.slow
@pytest.mark.parametrize("settings", [{}, {"max_leaves": 3}])
def test_uneven_chunks_in_any_order_give_the_monolithic_trees(monolithic, settings):
    mono = monolithic if not settings else build_scene_trees(
        scenes.load(SCENE).scene, RES, progress=False, **settings)
    n = mono.vertex_count
    results = [build.build_vertex_chunk(it) for it in reversed(_uneven_items(n, **settings))]
    merged = build.merge_vertex_chunks(results, n)
    for k in ARRAYS:
        assert _same_bytes(getattr(merged, k), getattr(mono, k)), k
    assert merged.info["leaves_over_epsilon"] == mono.info["leaves_over_epsilon"]
    assert merged.info["depth"] == mono.info["depth"]
    # the entry point by name, chunked in this process, agrees too (and so does its file)
    chunked = build_scene_trees(SCENE, RES, progress=False, chunk_vertices=1700, **settings)
    assert chunked.info["chunks"] == 3
    for k in ARRAYS:
        assert _same_bytes(getattr(chunked, k), getattr(mono, k)), k


@pytest.mark.slow
def test_a_chunk_in_a_fresh_process_equals_the_chunk_here(tmp_path, monolithic):
    item = _uneven_items(monolithic.vertex_count)[0]
    item = dict(item, start=300, stop=340)
    here = build.build_vertex_chunk(item)
    out = tmp_path / "chunk.npz"
    code = (
        "import json, sys, numpy as np\n"
        "from glossrt import backend; backend.ensure()\n"
        "from glossrt.lights.bspvt import build\n"
        "r = build.build_vertex_chunk(json.loads(sys.argv[1]))\n"
        "np.savez(sys.argv[2], **{k: r[k] for k in sys.argv[3].split(',')})\n")
    subprocess.run([sys.executable, "-c", code, json.dumps(item), str(out),
                    ",".join(ARRAYS)], check=True,
                   timeout=300)
    with np.load(out) as there:
        for k in ARRAYS:
            assert _same_bytes(there[k], here[k]), k
    # and it is the monolithic build's vertices 300..339 (vertex-local indices)
    merged = build.merge_vertex_chunks([dict(here, start=0, stop=40)])
    for v in (0, 17, 39):
        np.testing.assert_array_equal(merged.reconstruct(v), monolithic.reconstruct(300 + v))


def test_bad_chunkings_are_refused(monolithic):
    n = monolithic.vertex_count
    items = _uneven_items(n)
    results = [build.build_vertex_chunk(dict(items[0], start=0, stop=2)),
               build.build_vertex_chunk(dict(items[0], start=3, stop=5))]
    with pytest.raises(GlossrtError, match="do not tile"):
        build.merge_vertex_chunks(results)
    with pytest.raises(GlossrtError, match="cover 2 vertices, expected"):
        build.merge_vertex_chunks(results[:1], n)
    with pytest.raises(GlossrtError, match="outside scene"):
        build.build_vertex_chunk(dict(items[0], start=n - 1, stop=n + 1))
    with pytest.raises(GlossrtError, match="by built-in name or XML path"):
        build_scene_trees(scenes.load(SCENE).scene, RES, progress=False, chunk_vertices=100)
    with pytest.raises(GlossrtError, match="chunk_vertices must be a positive integer"):
        build_scene_trees(SCENE, RES, progress=False, chunk_vertices=0)
    with pytest.raises(GlossrtError, match="unknown BSPVT build settings"):
        build_scene_trees(SCENE, RES, progress=False, chunk_vertices=100, bogus=1)


def test_cli_refuses_a_bad_cluster_before_work(tmp_path, capsys):
    from glossrt.cli import main

    out = tmp_path / "t.npz"
    for extra in (["--cluster", "bogus"], ["--chunk-vertices", "0"]):
        assert main(["bspvt", "build", SCENE, "--out", str(out), *extra]) == 2
        err = capsys.readouterr().err
        assert err.startswith("glossrt: error:") and err.count("\n") == 1, err
    assert not out.exists()
