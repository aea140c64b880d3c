"""LTC table fits by rows (issue 27): work items that a cluster can run anywhere.

The reference is the fit in HDHN16's order written out here from the public pieces
(:func:`warm_start`, :func:`fit_cell`): rows from rough to smooth, each row from normal
incidence to grazing, every cell started from the cells fitted before it. The warm starts
chain rows only through their normal-incidence cells, so :func:`fit_table` fits that column
first and then every row alone (:func:`fit_row`). Checked on an 8 x 8 table with few samples:

* :func:`fit_table` equals the reference bit for bit;
* one row fitted in a fresh Python process from its plain-data item (JSON) equals the same row
  of the reference.
"""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from glossrt import backend

backend.ensure()

from glossrt.errors import GlossrtError  # noqa: E402
from glossrt.lights.ltc import fit as ltc_fit  # noqa: E402
from glossrt.lights.ltc.table import grid_axes, node_config  # noqa: E402

SIZE, FIT, MOMENTS = 8, 12, 1 << 10
KEYS = ("minv", "params", "err_l3", "err_l1", "nfev")


def _moments():
    r, u = grid_axes(SIZE)
    alpha, cos_o = node_config(r, u)
    aa, cc = np.meshgrid(alpha, cos_o, indexing="ij")
    mo = ltc_fit.brdf_moments(aa.ravel(), cc.ravel(), MOMENTS, "ggx")
    return alpha, cos_o, {k: v.reshape(SIZE, SIZE) for k, v in mo.items()}


@pytest.fixture(scope="module")
def reference():
    """Every cell in HDHN16's order, one after the other (the fit before issue 27)."""
    alpha, cos_o, mo = _moments()
    avg_phi = np.arctan2(mo["dir_x"], mo["dir_z"])
    out = {k: np.zeros((SIZE, SIZE, 4)) for k in ("minv", "params")}
    out.update({k: np.zeros((SIZE, SIZE)) for k in ("err_l3", "err_l1")})
    out["nfev"] = np.zeros((SIZE, SIZE), np.int64)
    for j in range(SIZE - 1, -1, -1):
        for i in range(SIZE):
            start, iso = ltc_fit.warm_start(out["params"], avg_phi, j, i)
            c = ltc_fit.fit_cell(alpha[j], cos_o[i], start, isotropic=iso,
                                 moments={k: float(v[j, i]) for k, v in mo.items()},
                                 fit_samples=FIT, metric="l1")
            out["minv"][j, i], out["params"][j, i] = c.coeffs, c.params
            out["err_l3"][j, i], out["err_l1"][j, i], out["nfev"][j, i] = \
                c.err_l3, c.err_l1, c.nfev
    return out


@pytest.mark.slow
def test_fit_table_by_rows_equals_the_cell_order_fit(reference):
    table = ltc_fit.fit_table(SIZE, progress=False, fit_samples=FIT, moment_samples=MOMENTS)
    for k in KEYS:
        assert table[k].dtype == reference[k].dtype
        assert table[k].tobytes() == reference[k].tobytes(), k
    assert reference["nfev"][:, 1:].sum() > 10 * SIZE  # the rows did real work


@pytest.mark.slow
def test_a_row_fitted_in_a_fresh_process_equals_the_reference_row(tmp_path, reference):
    j = 3
    alpha, cos_o, mo = _moments()
    item = {"j": j, "alpha": float(alpha[j]), "cos_o": cos_o.tolist(),
            "avg_phi": np.arctan2(mo["dir_x"][j], mo["dir_z"][j]).tolist(),
            "moments": {k: v[j].tolist() for k, v in mo.items()},
            "first": reference["params"][j, 0].tolist(), "fit_samples": FIT,
            "distribution": "ggx", "metric": "l1"}
    out = tmp_path / "row.npz"
    code = ("import json, sys, numpy as np\n"
            "from glossrt import backend; backend.ensure()\n"
            "from glossrt.lights.ltc import fit\n"
            "r = fit.fit_row(json.loads(sys.argv[1]))\n"
            "np.savez(sys.argv[2], **{k: r[k] for k in sys.argv[3].split(',')})\n")
    subprocess.run([sys.executable, "-c", code, json.dumps(item), str(out),
                    ",".join(KEYS)], check=True,
                   timeout=300)
    with np.load(out) as row:
        for k in KEYS:
            assert row[k].tobytes() == reference[k][j, 1:].tobytes(), k


def test_bad_settings_are_refused_before_work():
    with pytest.raises(GlossrtError, match="metric must be one of"):
        ltc_fit.fit_table(4, progress=False, metric="l2")
    with pytest.raises(GlossrtError, match="distribution must be one of"):
        ltc_fit.fit_table(4, progress=False, distribution="phong")


def test_cli_refuses_a_bad_cluster_before_work(tmp_path, capsys):
    from glossrt.cli import main

    out = tmp_path / "t.npz"
    assert main(["ltc-fit", "--out", str(out), "--size", "4", "--cluster", "ray://nowhere"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("glossrt: error:") and "cluster" in err and err.count("\n") == 1, err
    assert not out.exists()
