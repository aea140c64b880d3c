"""Experiments keep their finished references (render.blocks.references(cache=...)): a
rerun reads them back bit for bit instead of rendering, keyed by job, sample count and path;
``glossrt experiment --which denoisers`` keeps them under ``--out``/references."""

from __future__ import annotations

import numpy as np
import pytest

from glossrt import render, scenes
from glossrt.render import blocks

SIZE = (16, 12)


def _frames(refs):
    return {(f.index, k): f.numpy(k) for f in refs for k in f.names}


def test_references_are_kept_and_read_back(tmp_path, monkeypatch):
    r = render.Renderer(scenes.load("glossy-cornell", size=SIZE, frames=3))
    job = blocks.reference_job("glossy-cornell", SIZE, frames=3)
    first = blocks.references(r, job, [0, 2], 4, cache=tmp_path)
    assert len(list(tmp_path.glob("reference_*.exr"))) == 2

    def boom(*a, **k):
        raise AssertionError("rendered again")

    monkeypatch.setattr(r, "render_reference", boom)
    again = blocks.references(r, job, [0, 2], 4, cache=tmp_path)
    a, b = _frames(first), _frames(again)
    assert a.keys() == b.keys()
    for k in a:
        assert a[k].tobytes() == b[k].tobytes(), k
    # another sample count or another frame is not in the cache: rendered
    with pytest.raises(AssertionError, match="rendered again"):
        blocks.references(r, job, [0], 8, cache=tmp_path)
    with pytest.raises(AssertionError, match="rendered again"):
        blocks.references(r, job, [1], 4, cache=tmp_path)
    # the blocks' path (cluster "none": the same samples, float32 rounding apart) has its own
    monkeypatch.undo()
    blocks.references(r, job, [0], 4, cluster="none", cache=tmp_path)
    assert len(list(tmp_path.glob("reference_*.exr"))) == 3


def test_denoisers_experiment_reuses_its_references(tmp_path, monkeypatch):
    from glossrt.experiments import svgf

    kw = dict(size=SIZE, frames=3, ref_every=2, ref_spp=4, static_frames=2,
              methods=("svgf",), cache=tmp_path / "references")
    res = svgf.denoisers(**kw)
    assert len(list((tmp_path / "references").glob("*.exr"))) == 2
    monkeypatch.setattr(render.Renderer, "render_reference",
                        lambda *a, **k: (_ for _ in ()).throw(AssertionError("rendered")))
    again = svgf.denoisers(**kw)
    assert np.isclose(again.quality["svgf"]["rmse"], res.quality["svgf"]["rmse"], rtol=0,
                      atol=0)
