"""``glossrt experiment --cluster`` (issue 27): the experiments' converged references as sample
blocks and their BSPVT builds as vertex chunks on a local Ray cluster of 2 worker slots give
the numbers of the one-process run; a bad cluster is refused before any work.

One local Ray instance serves the module (the CLI's own ``connect`` reuses it) and is shut
down at its end.
"""

from __future__ import annotations

import json
import socket

import numpy as np
import pytest

from glossrt import cluster, scenes
from glossrt.cli import main
from glossrt.errors import GlossrtError
from glossrt.experiments import bspvt as eb
from glossrt.experiments import svgf as es
from glossrt.render import Renderer, blocks

SIZE = (32, 24)
#: the smallest denoiser comparison: 2 frames, a 4 spp reference of each, 2 static frames
ARGS = ["experiment", "--which", "denoisers", "--size", f"{SIZE[0]}x{SIZE[1]}",
        "--frames", "2", "--ref-every", "1", "--spp", "4", "--static-frames", "2"]
#: the JSON's numbers that do not depend on wall time
KEYS = ("quality", "per_frame", "temporal", "skipped")


@pytest.fixture(scope="module")
def local2():
    with cluster.connect("local:2") as c:
        yield c


def test_bad_cluster_refused_before_any_work(tmp_path, capsys, monkeypatch):
    out = tmp_path / "o"
    monkeypatch.delenv(cluster.ENV, raising=False)
    for spec in ("bogus", "local:0", "ray://host"):
        assert main([*ARGS, "--out", str(out), "--cluster", spec]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("glossrt: error:") and "cluster" in err and "\n" not in err
        assert not out.exists()
    monkeypatch.setenv(cluster.ENV, "remote")  # the environment's default, checked the same
    assert main([*ARGS, "--out", str(out)]) == 2
    assert "unknown cluster 'remote'" in capsys.readouterr().err
    assert not out.exists()
    monkeypatch.delenv(cluster.ENV)
    with socket.socket() as s:  # bound, not listening: connections to it are refused
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
        assert main([*ARGS, "--out", str(out), "--cluster", f"ray://127.0.0.1:{port}"]) == 2
    err = capsys.readouterr().err.strip()
    assert "cannot reach Ray cluster" in err and "\n" not in err
    assert not out.exists()


def test_denoisers_same_numbers_with_cluster(local2, tmp_path, monkeypatch):
    monkeypatch.delenv(cluster.ENV, raising=False)
    seen = []
    real = blocks.reference_frames

    def spy(renderer, job, frames, spp, cluster=None, **kw):
        seen.append((type(cluster).__name__, list(frames), spp))
        return real(renderer, job, frames, spp, cluster=cluster, **kw)

    monkeypatch.setattr(blocks, "reference_frames", spy)
    assert main([*ARGS, "--out", str(tmp_path / "one")]) == 0
    assert seen == []  # without --cluster: Renderer.render_reference, as before issue 27
    assert main([*ARGS, "--out", str(tmp_path / "ray"), "--cluster", "local:2"]) == 0
    assert seen == [("Cluster", [0, 1], 4)]  # the references went to the cluster as blocks
    one = json.loads((tmp_path / "one" / "denoisers.json").read_text())
    ray = json.loads((tmp_path / "ray" / "denoisers.json").read_text())
    # the same blocks in this process: bit-identical to the cluster's run
    res = es.denoisers(size=SIZE, frames=2, ref_every=1, ref_spp=4, static_frames=2,
                       cluster="none")
    local = json.loads(json.dumps({k: getattr(res, k) for k in KEYS}))
    assert {k: ray[k] for k in KEYS} == local
    # against the one-process run: the same but for the blocks' float32 rounding (the
    # static sequence's temporal error involves no reference: equal)
    assert ray["temporal"] == one["temporal"] and ray["skipped"] == one["skipped"]
    for m, q in one["quality"].items():
        for k, v in q.items():
            assert ray["quality"][m][k] == pytest.approx(v, rel=1e-5, abs=1e-7), (m, k)


def test_static_reference_job(local2):
    """pipeline's references without motion: the job's ``static`` flag loads the workers'
    scene without its animation (frame 1 differs from the animated scene's)."""
    setup = scenes.load_static("glossy-cornell", size=(16, 12))
    r = Renderer(setup)
    job = blocks.reference_job("glossy-cornell", (16, 12), static=True)
    got = blocks.references(r, job, [1], 4, local2)[0].numpy("color")
    want = r.render_reference(1, 4).numpy("color")
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)
    moving = Renderer(scenes.load("glossy-cornell", size=(16, 12), frames=2))
    assert not np.allclose(moving.render_reference(1, 4).numpy("color"), want, atol=1e-3)


def test_bspvt_trees_on_cluster(local2):
    kw = dict(alphas=(0.25,), frames=(0,), size=(16, 12), resolution=4, ref_spp=2,
              ratio_spp=1)
    one = eb.images(**kw)
    ray = eb.images(**kw, cluster=local2)
    # the trees themselves: the chunks' merge on the cluster is the one-process build
    setup = eb._setup(0.25, (16, 12))
    t1, t2 = eb._trees(setup, 4, 0.0), eb._trees(setup, 4, 0.0, cluster=local2)
    for k in ("lines", "children", "leaf_value", "roots", "positions", "normals"):
        assert np.array_equal(getattr(t1, k), getattr(t2, k)), k
    # the images and errors shaded with them: BSPVT's shading itself varies by an ulp from
    # one call to the next in one process (measured: 1-3 pixels, 4e-9), hence the tolerance
    for r1, r2 in zip(one.rows, ray.rows, strict=True):
        for k in ("mae", "direct"):
            assert r2[k] == pytest.approx(r1[k], rel=1e-6), k
        assert r2["vis_part"] == pytest.approx(r1["vis_part"], rel=1e-6)
    for name, im in one.images.items():
        for m, a in im.items():
            np.testing.assert_allclose(ray.images[name][m], a, rtol=1e-6, atol=1e-8)
    # a density without a built-in name cannot go to the cluster by name: refused
    coarse = eb._setup(0.25, (16, 12), eb.DENSITIES["coarse"])
    with pytest.raises(GlossrtError, match="vertices"):
        eb._trees(coarse, 4, 0.0, cluster="none")
