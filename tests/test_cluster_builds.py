"""`glossrt bspvt build --cluster` and `glossrt ltc-fit --cluster` (issue 27) on a local Ray
instance with 2 worker slots: the same trees and the same LTC table, byte for byte, as the
one-process builds (:func:`build_scene_trees` on the loaded scene, :func:`fit_table` without
a cluster). The work items themselves are checked against independent orders and fresh
processes in tests/test_bspvt_chunks.py and tests/test_ltc_rows.py.
"""

from __future__ import annotations

import numpy as np
import pytest

ray = pytest.importorskip("ray")

from glossrt import backend  # noqa: E402

backend.ensure()

from glossrt import cluster, scenes  # noqa: E402
from glossrt.cli import main  # noqa: E402
from glossrt.lights.bspvt import BSPVT  # noqa: E402
from glossrt.lights.bspvt.scene import build_scene_trees  # noqa: E402
from glossrt.lights.ltc import fit as ltc_fit  # noqa: E402

ARRAYS = ("lines", "children", "leaf_value", "roots", "positions", "normals")


@pytest.fixture(scope="module")
def local2():
    with cluster.connect("local:2") as c:  # shut down at the end: no process left behind
        yield c


def test_trees_on_the_cluster_equal_the_one_process_build(local2, tmp_path):
    mono = build_scene_trees(scenes.load("polygon-light").scene, 8, progress=False)
    dist = build_scene_trees("polygon-light", 8, progress=False, cluster=local2,
                             chunk_vertices=1700)
    assert dist.info["chunks"] == 3
    for k in ARRAYS:
        assert getattr(dist, k).tobytes() == getattr(mono, k).tobytes(), k
    # the command line (the open Ray instance is reused)
    out = tmp_path / "t.npz"
    assert main(["bspvt", "build", "polygon-light", "--out", str(out), "--resolution", "8",
                 "--cluster", "local:2", "--chunk-vertices", "2000"]) == 0
    got = BSPVT.load(str(out))
    for k in ARRAYS:
        assert getattr(got, k).tobytes() == getattr(mono, k).tobytes(), k


def test_ltc_table_on_the_cluster_equals_the_one_process_fit(local2, tmp_path):
    kw = dict(progress=False, fit_samples=12, moment_samples=1 << 10)
    mono = ltc_fit.fit_table(5, **kw)
    dist = ltc_fit.fit_table(5, cluster=local2, **kw)
    for k in ("minv", "params", "err_l3", "err_l1", "nfev", "norm", "fres"):
        assert dist[k].tobytes() == mono[k].tobytes(), k
    out = tmp_path / "ltc.npz"
    assert main(["ltc-fit", "--out", str(out), "--size", "3", "--cluster", "local:2"]) == 0
    with np.load(out) as z:
        assert z["minv"].shape == (3, 3, 4) and np.all(np.isfinite(z["minv"]))
