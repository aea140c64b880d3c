"""glossrt's path tracer as a Mitsuba integrator plugin, against Mitsuba's own `path`.

Both go through the same film and sampler (jittered, box-filtered pixels), so every pixel is
comparable, edges included. The noise level is measured, not assumed: two independent
`path` renders give the RMS difference that Monte Carlo noise alone produces.
"""

import mitsuba as mi
import numpy as np
import pytest

from glossrt import render, scenes  # noqa: F401  (importing render registers "glossrt")
from glossrt.render.integrator import AOV_LAYERS

BATCHES, SPP = 12, 32


def _batches(setup, integrator, offset):
    """Independent renders (seeds far apart: nearby seeds give overlapping sample streams)."""
    out = [np.array(mi.render(setup.scene, sensor=setup.sensor, integrator=integrator, spp=SPP,
                              seed=1_000_003 * (k + 1) + offset))
           for k in range(BATCHES)]
    return np.stack(out)


@pytest.fixture(scope="module")
def renders():
    setup = scenes.load("glossy-cornell", size=(40, 30))
    ours = _batches(setup, mi.load_dict({"type": "glossrt", "max_depth": 3}), 0)
    path = _batches(setup, mi.load_dict({"type": "path", "max_depth": 3}), 500_009)
    return ours, path


def _z(a, b):
    """Per pixel and channel: difference of batch means in units of its standard error."""
    se2 = a.var(0, ddof=1) / len(a) + b.var(0, ddof=1) / len(b)
    ok = se2 > 0
    return (a.mean(0) - b.mean(0))[ok] / np.sqrt(se2[ok]), (a.mean(0) == b.mean(0))[~ok]


def test_aov_layout(renders):
    ours = renders[0][0]
    n = 3 + sum(len(c) for _, c in AOV_LAYERS)
    assert ours.shape == (30, 40, n)
    names = mi.load_dict({"type": "glossrt"}).aov_names()
    assert names[:3] == ["emission.R", "emission.G", "emission.B"] and len(names) == n - 3


def test_components_sum_to_color(renders):
    ours = renders[0]
    comp = sum(ours[..., 3 + 3 * i: 6 + 3 * i] for i in range(5))
    np.testing.assert_allclose(comp, ours[..., :3], rtol=1e-5, atol=1e-5)


def _check_same_expectation(ours_rgb, path_rgb):
    z, zero_var_equal = _z(ours_rgb, path_rgb)
    assert zero_var_equal.all()  # pixels without noise (background) must agree exactly
    # with 12 batches z is roughly Student-t (heavier tails: radiance is skewed), so |z| > 5
    # is rare for unbiased estimators; a bias shows as many large |z| and a shifted mean z
    return z


def test_agrees_with_mitsuba_path(renders):
    ours, path = renders
    z = _check_same_expectation(ours[..., :3], path)
    assert np.mean(np.abs(z) > 5) < 2e-3
    assert abs(z.mean()) < 5 / np.sqrt(z.size) * z.std()


def test_comparison_has_power(renders):
    """Dropping one component (glossy indirect light) must be caught by the same check."""
    ours, path = renders
    without = ours[..., :3] - ours[..., 12:15]  # indirect_specular
    z = _check_same_expectation(without, path)
    assert not (abs(z.mean()) < 5 / np.sqrt(z.size) * z.std() and np.mean(np.abs(z) > 5) < 2e-3)
