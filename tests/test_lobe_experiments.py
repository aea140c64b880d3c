"""glossrt.experiments.lobes: tiny runs of the fig. 4-6 experiments (Tokuyoshi 2015, sec. 5.1,
5.2). Structural checks only (finite MSEs, filtering reduces the 1 spp error on the rough
sphere, optima are the argmins of the recorded curves, the sweep agrees with single filter
calls, the plot is written); the paper's expected outcome is *not* asserted. Run with
``pytest -s`` to see the measured tables.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from glossrt import backend

backend.ensure()

from glossrt.errors import GlossrtError  # noqa: E402
from glossrt.experiments import lobes as le  # noqa: E402

SIZE = (48, 36)
REF_SPP = 32
KW = {"radius": 3}  # a smaller window than the default 6: fewer kernels to compile
BETAS = (1.0, 20.0, 100.0, 1000.0)  # the paper's beta = 20 and 1 / sigma_n^2 = 100 inside


@pytest.fixture(scope="module")
def r4():
    r = le.fig4(SIZE, REF_SPP, filter_kwargs=KW)
    print(f"\nfig4 (roughness-map {SIZE}, ref {REF_SPP} spp, {KW}):\n{r.markdown()}\n"
          f"screen sigma: {r.screen_sigma}")
    return r


@pytest.fixture(scope="module")
def r5():
    r = le.fig5(SIZE, REF_SPP, filter_kwargs=KW)
    print(f"\nfig5 (glossy-spheres {SIZE}, ref {REF_SPP} spp, {KW}):\n{r.markdown()}")
    return r


@pytest.fixture(scope="module")
def r6():
    calls = []
    r = le.fig6(SIZE, REF_SPP, betas=BETAS, filter_kwargs=KW,
                progress=lambda done, total: calls.append((done, total)))
    print(f"\nfig6 (glossy-spheres {SIZE}, ref {REF_SPP} spp, {KW}):\n{r.markdown()}")
    return r, calls


def _positive_finite(values) -> bool:
    a = np.asarray(values, dtype=np.float64)
    return bool(np.all(np.isfinite(a)) and np.all(a > 0))


@pytest.mark.slow
def test_fig4_table_and_images(r4):
    assert list(r4.mse) == list(le.FIG4_METHODS)
    for table in (r4.mse, r4.mse_sharp, r4.mse_rough):
        assert set(table) == set(le.FIG4_METHODS)
        assert _positive_finite(list(table.values()))
    assert r4.pixels["sharp"] > 0 and r4.pixels["rough"] > 0
    w, h = SIZE
    for name in (*le.FIG4_METHODS, "reference"):
        assert r4.images[name].shape == (h, w, 3), name
    # the recorded MSEs are those of the recorded images
    ref = r4.images["reference"].astype(np.float64)
    for m in le.FIG4_METHODS:
        want = np.mean((r4.images[m] - ref) ** 2)
        assert r4.mse[m] == pytest.approx(want, rel=1e-6)
    # every filter reduces the 1 spp error over the image
    for m in ("normal", "screen", "lobe"):
        assert r4.mse[m] < r4.mse["input"], m
    # the screen kernel is narrower on alpha 0.02 than on alpha 0.5
    assert r4.screen_sigma["sharp"] < r4.screen_sigma["rough"]
    md = r4.markdown().splitlines()
    assert len(md) == 2 + len(le.FIG4_METHODS)
    assert all(md[2 + k].startswith(f"| {m} |") for k, m in enumerate(le.FIG4_METHODS))


@pytest.mark.slow
def test_fig5_spheres_and_errors(r5):
    from glossrt.scenes.library import phong_to_alpha

    assert [s.phong for s in r5.spheres] == [1000.0, 100.0, 10.0]
    for s, mask in zip(r5.spheres, r5.masks, strict=True):
        assert s.alpha == pytest.approx(phong_to_alpha(s.phong))
        assert s.pixels == int(mask.sum()) > 0
    assert not np.any(np.sum(r5.masks, axis=0) > 1)  # disjoint
    assert set(r5.mse) == set(le.FIG5_METHODS)
    for m, vals in r5.mse.items():
        assert len(vals) == 3 and _positive_finite(vals), m
    rough = 2  # Phong 10
    assert r5.mse["normal"][rough] < r5.mse["input"][rough]
    assert r5.mse["lobe"][rough] < r5.mse["input"][rough]
    md = r5.markdown().splitlines()
    assert len(md) == 2 + len(le.FIG5_METHODS)
    assert "s=1000" in md[0] and "s=10 " in md[0]


@pytest.mark.slow
def test_fig6_optima_are_the_argmins_of_the_curves(r6):
    r, calls = r6
    n = len(BETAS)
    np.testing.assert_array_equal(r.params, BETAS)
    assert calls[-1] == (2 * n, 2 * n) and len(calls) == 2 * n
    for m in ("normal", "lobe"):
        c = r.curves[m]
        assert c.shape == (3, n) and _positive_finite(c), m
        for k in range(3):
            j = int(np.argmin(c[k]))
            assert r.optimum(m)[k] == BETAS[j]
            assert r.optimum_mse(m)[k] == c[k].min()
            assert r.on_boundary(m)[k] == (j in (0, n - 1))
            lo, hi = r.near_optimal(m)[k]
            assert lo <= BETAS[j] <= hi
        opt = [BETAS[int(np.argmin(c[k]))] for k in range(3)]
        assert r.spread(m) == pytest.approx(math.log10(max(opt) / min(opt)))
        np.testing.assert_allclose(r.mean_curve(m), c.mean(axis=0))
        p, v = r.mean_optimum(m)
        assert v == c.mean(axis=0).min() and p == BETAS[int(np.argmin(c.mean(axis=0)))]
    md = r.markdown().splitlines()
    assert len(md) == 2 + 3
    assert md[2].startswith("| normal |") and md[3].startswith("| lobe |")
    assert md[4].startswith("| input |")


def test_fig6_sweep_agrees_with_single_filter_calls(r5, r6):
    """The sweep (opaque parameters, one compilation) gives the MSE of the plain calls of
    fig5 at the paper's beta = 20 and 1 / sigma_n^2 = 100 (same scene, size and seeds)."""
    r, _ = r6
    assert r.input_mse == r5.mse["input"]  # the same render
    np.testing.assert_allclose(r.curves["lobe"][:, BETAS.index(20.0)], r5.mse["lobe"],
                               rtol=1e-4)
    np.testing.assert_allclose(r.curves["normal"][:, BETAS.index(100.0)], r5.mse["normal"],
                               rtol=1e-4)


def test_fig6_plot_is_written(r6, tmp_path):
    r, _ = r6
    path = tmp_path / "fig6.png"
    assert r.plot(str(path)) == str(path)
    data = path.read_bytes()
    assert len(data) > 10_000 and data[:8] == b"\x89PNG\r\n\x1a\n"


def test_fig6_rejects_bad_parameters():
    with pytest.raises(GlossrtError, match="positive"):
        le.fig6(SIZE, REF_SPP, betas=(1.0, 0.0))
    with pytest.raises(GlossrtError, match="swept"):
        le.fig6(SIZE, REF_SPP, betas=(1.0,), filter_kwargs={"beta": 3.0})
    with pytest.raises(GlossrtError, match="ref_spp"):
        le.fig4(SIZE, 0)
