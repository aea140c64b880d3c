"""glossrt.jit helpers and the interleaved neighbour reads of the filters."""

import numpy as np
import pytest

mi = pytest.importorskip("mitsuba")
from glossrt import backend  # noqa: E402

backend.ensure()
import drjit as dr  # noqa: E402

from glossrt.denoise.common import Packed  # noqa: E402
from glossrt.jit import exp_weight, pow_int  # noqa: E402


def test_exp_weight_against_numpy():
    xs = np.concatenate([np.linspace(-87.0, 87.0, 400_001), -np.logspace(-12, 1.9, 2001),
                         [0.0]]).astype(np.float32)
    got = exp_weight(mi.Float(xs)).numpy().astype(np.float64)
    want = np.exp(xs.astype(np.float64))
    rel = np.abs(got / want - 1.0)
    # float32 rounding of x log2(e) dominates for large |x| (a few ulp of t ~ 126)
    assert rel.max() < 5e-6
    small = np.abs(xs) <= 1.0
    assert rel[small].max() < 3e-7
    assert got[-1] == 1.0  # exp(0) exactly: the centre-tap weight
    # saturation instead of under/overflow, documented
    sat = exp_weight(mi.Float([-200.0, 200.0])).numpy()
    assert 0 < sat[0] < 1.2e-38 and np.isfinite(sat[1])
    # a Python number (a filter's constant screen weight) stays a Python number
    assert exp_weight(-0.5) == np.exp(-0.5)


def test_pow_int_against_numpy():
    xs = np.linspace(0.0, 1.0, 1001).astype(np.float32)
    for n in (1, 2, 7, 128, 3.5):
        got = pow_int(mi.Float(xs), n).numpy()
        assert np.allclose(got, xs.astype(np.float64) ** n, rtol=2e-5, atol=1e-30), n


@pytest.mark.parametrize("n_channels", [1, 4, 5, 8, 9, 20, 26])
def test_packed_fetch_equals_gathers(n_channels):
    rng = np.random.default_rng(n_channels)
    size = 97
    chs = [mi.Float(rng.normal(size=size).astype(np.float32)) for _ in range(n_channels)]
    q = mi.UInt32(rng.integers(0, size, 300).astype(np.uint32))
    got = Packed(chs).fetch(q)
    assert len(got) == n_channels
    for g, c in zip(got, chs, strict=True):
        assert np.array_equal(g.numpy(), dr.gather(mi.Float, c, q).numpy())


def test_merge_evaluates_its_channels_once():
    """merge() interleaves C channels in one kernel: per-channel scatters launched a kernel
    per channel, each recomputing the channels' shared unevaluated expression."""
    from glossrt.denoise.common import merge

    x = dr.linspace(mi.Float, 0.0, 1.0, 12)
    dr.eval(x)
    y = dr.sin(x) * 2.0 + 1.0  # unevaluated, shared by the channels
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history()
        out = merge([y, y * 2.0, y * 3.0], 3, 4)
        dr.eval(out)
        kernels = [k for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT]
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    assert len(kernels) == 1
    want = np.sin(np.linspace(0.0, 1.0, 12)) * 2.0 + 1.0
    got = out.numpy().reshape(12, 3)
    np.testing.assert_allclose(got, want[:, None] * [1.0, 2.0, 3.0], rtol=1e-6)
