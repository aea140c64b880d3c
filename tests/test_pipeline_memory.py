"""Issue 25, memory: the spatio-temporal upsampler of large images runs in row tiles (a
frozen replay keeps every intermediate until it returns), with the same values as the
untiled call and one recording per function across frames."""

import numpy as np
import pytest

from glossrt.denoise import upsampling
from glossrt.denoise.upsampling import SpatioTemporalUpsampler, jitter_sequence
from glossrt.errors import GlossrtError


def test_tile_rows_and_starts():
    assert upsampling.tile_rows(1920, 1080) == (1 << 18) // 1920
    assert upsampling.tile_rows(320, 180) == 180  # untiled: one tile of every row
    starts = upsampling.tile_starts(36, 5)
    assert starts[0] == 0 and starts[-1] == 31 and len(starts) == 8
    covered = set()
    for r in starts:
        covered.update(range(r, r + 5))
    assert covered == set(range(36))


def test_tile_pixels_checked():
    with pytest.raises(GlossrtError, match="tile_pixels"):
        SpatioTemporalUpsampler(tile_pixels=0)


@pytest.mark.slow
@pytest.mark.parametrize("weight", ["lobe", "normal"])
def test_tiled_upsampler_equals_untiled(weight):
    """Five frames (history, moving jitter) of the frozen upsampler with 5-row tiles (the
    last one overlapping) against the untiled frozen call: the same image, frame after
    frame (so the same history), and no new recording after the second frame."""
    from glossrt import render, scenes
    from glossrt.pipeline.stages import ScaledSetup

    w, h = 48, 36
    setup = scenes.load("polygon-light", size=(w, h))
    full = render.Renderer(setup)
    low_r = render.Renderer(ScaledSetup(setup, 2), seed=1)
    ref = SpatioTemporalUpsampler(weight=weight, frozen=True)
    tiled = SpatioTemporalUpsampler(weight=weight, frozen=True, tile_pixels=5 * w + 3)
    counts = []
    for i in range(5):
        setup_frame = full.render(i)
        low = low_r.render(i, jitter=jitter_sequence(2, i))
        a = np.array(ref(setup_frame, low))
        b = np.array(tiled(setup_frame, low))
        assert a.shape == b.shape == (h, w, 3)
        assert np.abs(a).max() > 0
        np.testing.assert_allclose(b, a, rtol=1e-6, atol=1e-7)
        counts.append(tiled.n_recordings)
    assert tiled._tile.n_recordings >= 1  # the tiles ran
    assert counts[1] == counts[-1]
