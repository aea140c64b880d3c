"""Tokuyoshi 2015 fig. 7 (sec. 5.3): ``SpatioTemporalUpsampler(history="herzog")``, Herzog
et al. 2010's confidence-weighted temporal accumulation, against an independent NumPy model
of its recurrence on a static view; the default history unchanged (bit for bit against the
committed module); reset; the Toksvig filter against a direct computation; and
``glossrt.experiments.upsampling.fig7`` at a tiny size.

Run with ``pytest -s`` to see the measured numbers."""

from __future__ import annotations

import json

import numpy as np
import pytest

from glossrt import backend

backend.ensure()

from glossrt import render, scenes  # noqa: E402
from glossrt.denoise import upsampling as up  # noqa: E402
from glossrt.errors import GlossrtError  # noqa: E402
from glossrt.frame import RADIANCE  # noqa: E402

IND = ("indirect_diffuse", "indirect_specular")
FULL, LOW = (32, 24), (16, 12)


@pytest.fixture(scope="module")
def cornell():
    return (render.Renderer(scenes.load("glossy-cornell", size=FULL)),
            render.Renderer(scenes.load("glossy-cornell", size=LOW)))


def _ind(img, full):
    return np.array(img) - sum(full.numpy(c) for c in RADIANCE if c not in IND)


def _np_confidence(jitter, sigma=up.HERZOG_SIGMA, floor=up.HERZOG_FLOOR, f=2):
    """c_s of the documented formula, in NumPy: distance (full pixels) from each full pixel
    centre to the nearest jittered low-resolution sample."""
    w, h = FULL
    x = (np.arange(w) + 0.5) / f - 0.5 - jitter[0]
    y = (np.arange(h) + 0.5) / f - 0.5 - jitter[1]
    dx = np.abs(x - np.floor(x + 0.5))  # ties are 0.5 either way
    dy = np.abs(y - np.floor(y + 0.5))
    d2 = (dy[:, None] ** 2 + dx[None, :] ** 2) * f * f
    return np.maximum(floor, np.exp(-d2 / (2 * sigma**2)))[..., None]


def test_herzog_matches_a_numpy_model_and_reduces_the_variance(cornell):
    """Noisy 1 spp jittered frames of a still view: the output is the recurrence
    y_t = (c_s x_t + g c_{t-1} y_{t-1}) / (c_s + g c_{t-1}), c_t = c_s + g c_{t-1} run in
    NumPy on the spatial upsamples x_t (upsample()), and its error against a reference
    falls with frames (the spatial one's does not)."""
    full_r, low_r = cornell
    ref = full_r.render_reference(0, spp=128)
    tgt = sum(ref.numpy(c) for c in IND)
    st = up.SpatioTemporalUpsampler(weight="lobe", history="herzog")
    g = up.HERZOG_DECAY
    y = c = None
    errs, spatial = [], []
    for k in range(12):
        full = full_r.render(0, seed=k)
        jit = up.jitter_sequence(2, k)
        low = low_r.render(0, seed=100 + k, jitter=jit)
        out = _ind(st(full, low), full)
        x = _ind(up.upsample(full, low, weight="lobe"), full)
        cs = _np_confidence(jit)
        if y is None:
            y, c = x, cs
        else:
            y = (cs * x + g * c * y) / (cs + g * c)
            c = cs + g * c
        np.testing.assert_allclose(out, y, rtol=2e-4, atol=2e-6)
        # median squared error: 1 spp fireflies would dominate a mean at this size
        errs.append(np.median((out - tgt) ** 2))
        spatial.append(np.median((x - tgt) ** 2))
    print(f"\nHerzog median sq. error by frame {np.round(errs, 6)}; spatial "
          f"{np.round(spatial, 6)}")
    assert np.mean(errs[8:]) < 0.5 * np.mean(spatial)
    assert np.mean(errs[8:]) < 0.7 * errs[0]  # measured ~0.55 (bias and reference noise stay)
    # reset: the next frame is the spatial upsample alone
    st.reset()
    np.testing.assert_allclose(_ind(st(full, low), full), x, rtol=1e-5, atol=1e-7)


def test_herzog_converges_to_a_noise_free_input(cornell):
    """One noisy frame, then the same input every frame: the output tends to that input,
    the first frame's weight decaying as the model says (g^t c / c_t)."""
    full_r, low_r = cornell
    full = full_r.render(0, seed=0)
    a, b = low_r.render(0, seed=1), low_r.render(0, seed=2)
    xa = _ind(up.upsample(full, a, weight="normal"), full)
    xb = _ind(up.upsample(full, b, weight="normal"), full)
    st = up.SpatioTemporalUpsampler(weight="normal", history="herzog")
    st(full, a)
    for _ in range(30):
        out = _ind(st(full, b), full)
    cs = _np_confidence((0.0, 0.0))
    g = up.HERZOG_DECAY
    wa = g**30 * cs / (cs * sum(g**i for i in range(31)))
    np.testing.assert_allclose(out, wa * xa + (1 - wa) * xb, rtol=2e-4, atol=2e-6)
    assert np.max(np.abs(out - xb)) <= 0.01 * np.max(np.abs(xa - xb)) + 1e-6


def test_bad_history_options():
    with pytest.raises(GlossrtError, match="unknown history"):
        up.SpatioTemporalUpsampler(history="svgf")
    with pytest.raises(GlossrtError, match="frozen"):
        up.SpatioTemporalUpsampler(history="herzog", frozen=True)
    with pytest.raises(GlossrtError, match="decay"):
        up.SpatioTemporalUpsampler(history="herzog", decay=1.5)


def test_toksvig_filter_against_a_direct_computation():
    from glossrt.scenes.normalmap import toksvig

    rng = np.random.default_rng(0)
    n = rng.normal(size=(8, 8, 3))
    n[..., 2] = np.abs(n[..., 2]) + 0.5
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    nmap, alpha = toksvig((n + 1) / 2, 0.1, 2)
    assert nmap.shape == (2, 2, 3) and alpha.shape == (2, 2, 1)
    block = n[4:8, 0:4].reshape(-1, 3).mean(0)  # row block 1, column block 0
    length = np.linalg.norm(block)
    np.testing.assert_allclose(2 * nmap[1, 0] - 1, block / length, atol=1e-6)
    np.testing.assert_allclose(alpha[1, 0, 0] ** 2, min(1.0, 0.01 + (1 - length) / length),
                               rtol=1e-5)
    flat = np.zeros((4, 4, 3))
    flat[..., 2] = 1.0
    assert np.allclose(toksvig((flat + 1) / 2, 0.3, 1)[1], 0.3)  # no variance: alpha kept
    with pytest.raises(GlossrtError, match="level"):
        toksvig(flat, 0.1, 3)


def test_fig7_runs_tiny():
    from glossrt.experiments import upsampling as ue

    res = ue.fig7(size=(24, 14), frames=3, ref_spp=4)
    modes = [m for m, _ in ue.FIG7_MODES]
    assert list(res.mse) == [(w, m) for w in ("normal", "lobe") for m in modes]
    assert all(len(v) == 2 and np.all(np.isfinite(v)) for v in res.mse.values())
    md = res.markdown()
    for m in modes:
        assert md.count(f"| {m} |") == 2
    assert "Toksvig" in md and "Differences from the paper" in md
    with pytest.raises(GlossrtError, match="multiple"):
        ue.fig7(size=(25, 14), frames=2, ref_spp=1)


def test_fig7_bias_variance_over_independent_sequences():
    """``inputs`` >= 2: K sequences with distinct seeds; the MSE is their mean and equals
    bias^2 + variance of the split (an identity of the estimator, computed here by two
    routes: each sequence's own MSE against the accumulated per-pixel sums); independent
    noise gives a positive variance; one sequence gives no split."""
    from glossrt.experiments import upsampling as ue

    res = ue.fig7(size=(24, 14), frames=3, ref_spp=4, inputs=3)
    assert res.inputs == 3 and set(res.split) == set(res.mse)
    for key, per_frame in res.split.items():
        assert len(per_frame) == len(res.ref_frames)
        for e, mse in zip(per_frame, res.mse[key], strict=True):
            assert len(e.per_input) == 3
            assert np.isclose(np.mean(e.per_input), mse, rtol=1e-6)
            assert np.isclose(e.bias2 + e.variance, mse, rtol=1e-6)
            assert e.variance > 0
    md = res.markdown()
    assert "seeds 1-3" in md and "bias^2" in md
    assert md.count("| lobe | Herzog confidence |") == 2
    assert ue.fig7(size=(24, 14), frames=3, ref_spp=4).split == {}
    with pytest.raises(GlossrtError, match="inputs"):
        ue.fig7(size=(24, 14), frames=3, ref_spp=4, inputs=0)


def test_fig7_experiment_command(tmp_path, monkeypatch):
    """``glossrt experiment --which fig7``: the paper scale takes 640x360, 16 frames and 4096
    spp where the option was not given (checked on the arguments fig7 receives), and the
    references are kept under OUT/references (a rerun renders none)."""
    from types import SimpleNamespace

    from glossrt.experiments import upsampling as ue
    from glossrt.render import Renderer

    seen = {}
    real = ue.fig7

    def spy(**kw):
        seen.update(kw)
        return real(**{**kw, "size": (24, 14), "frames": 3, "ref_spp": 4,
                       "inputs": min(kw["inputs"], 2)})

    monkeypatch.setattr(ue, "fig7", spy)
    paper = SimpleNamespace(scale="paper", explicit=set(), size="1x1", frames=30, spp=1)
    assert ue.run_fig7(tmp_path, (1, 1), paper) == 0
    assert (seen["size"], seen["frames"], seen["ref_spp"]) == ((640, 360), 16, 4096)
    assert seen["inputs"] == ue.FIG7_PAPER_INPUTS
    assert seen["cache"] == tmp_path / "references"
    given = SimpleNamespace(scale="paper", explicit={"frames"}, frames=5, spp=1)
    ue.run_fig7(tmp_path, (24, 14), given)
    assert (seen["size"], seen["frames"], seen["ref_spp"]) == ((640, 360), 5, 4096)
    quick = SimpleNamespace(scale="quick", explicit={"spp"}, frames=3, spp=4)
    monkeypatch.setattr(Renderer, "render_reference",
                        lambda *a, **k: pytest.fail("reference rendered again"))
    assert ue.run_fig7(tmp_path, (24, 14), quick) == 0  # its references are in the cache
    assert (seen["size"], seen["frames"], seen["ref_spp"]) == ((24, 14), 3, 4)
    assert seen["inputs"] == 1
    data = json.loads((tmp_path / "fig7.json").read_text())
    assert set(data["mse"]) == {f"{w} / {m}" for w in ("normal", "lobe")
                                for m, _ in ue.FIG7_MODES}
    assert "| lobe | Herzog confidence |" in (tmp_path / "fig7.md").read_text()
