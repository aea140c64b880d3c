"""The papers' filter parameters as pipeline options (issue 26's panel reads them): SVGF's
alpha and sigmas, the lobe weight's beta and kappa, the highlights' distribution."""

from __future__ import annotations

import numpy as np
import pytest

from glossrt.errors import GlossrtError
from glossrt.pipeline import Pipeline, resolve


@pytest.mark.parametrize("kw,msg", [
    ({"svgf_alpha": 0.0}, "svgf_alpha"), ({"svgf_alpha": 1.5}, "svgf_alpha"),
    ({"svgf_sigma_l": -1.0}, "svgf_sigma_l"), ({"lobe_beta": 0}, "lobe_beta"),
    ({"lobe_kappa": "x"}, "lobe_kappa"), ({"highlight_distribution": "phong"}, "ellipsoidal"),
])
def test_bad_filter_options_are_one_line(kw, msg):
    with pytest.raises(GlossrtError, match=msg):
        resolve("full", **kw)


@pytest.mark.slow
def test_filter_options_reach_the_filters_and_change_the_image():
    pipe = Pipeline("polygon-light", preset="tokuyoshi2015", size=(48, 28), progress=False)
    ind = pipe.stages["indirect"]
    assert ind.low_denoiser.params.sigma_l == 4.0 and ind.upsampler.params["beta"] == 20.0
    for i in range(3):
        a = pipe.render(i).numpy("indirect")
    direct = pipe.stages["direct"]
    pipe.configure(svgf_sigma_l=0.5, svgf_alpha=0.5, lobe_beta=5.0, lobe_kappa=30.0)
    assert pipe.stages["direct"] is direct  # only the indirect stage is rebuilt
    ind = pipe.stages["indirect"]
    p = ind.low_denoiser.params
    assert (p.sigma_l, p.alpha, p.beta, p.kappa) == (0.5, 0.5, 5.0, 30.0)
    assert ind.upsampler.params["beta"] == 5.0 and ind.upsampler.params["kappa"] == 30.0
    for i in range(3):
        b = pipe.render(i).numpy("indirect")
    assert np.abs(a - b).mean() > 1e-3 * np.abs(a).mean()


@pytest.mark.slow
def test_highlight_distribution_reaches_the_renderer():
    pipe = Pipeline("polygon-light", preset="kimura-tokoi", size=(32, 18), progress=False,
                    highlight_probes=1, highlight_distribution="ggx")
    assert pipe.stages["direct"].highlights.distribution == "ggx"
    assert np.isfinite(pipe.render(0).numpy("direct")).all()
