"""Measured reproductions, one module per paper, behind docs/RESULTS.md, the demo's report
and ``glossrt bench`` / ``glossrt experiment``:

* :mod:`.svgf`: every denoiser against converged references (Schied et al. 2017);
* :mod:`.lobes` and :mod:`.upsampling`: Tokuyoshi 2015's lobe-aware filtering (figs. 4-6) and
  upsampling (one paper: :mod:`.lobes` registers both halves' section and run;
  :mod:`.upsampling` its fig. 7 run, ``--which fig7``);
* :mod:`.ltc`: Heitz et al. 2016's LTC against quadrature and Monte Carlo;
* :mod:`.bspvt`: Okuno & Iwasaki's BSPVT shadows, with the ratio estimator beside them;
* :mod:`.highlights`: Kimura & Tokoi 2004's light-shape highlights;
* :mod:`.specaa`: specular antialiasing (Kaplanyan et al. 2016, Tokuyoshi & Kaplanyan 2021);
* :mod:`.pipeline`: the frame pipeline that composes them (issue 25), every preset against
  converged references;
* :mod:`.scenes`: every preset on scenes no one here wrote (glossrt's trial scenes or a
  folder of Mitsuba XML files), glossrt's path tracer against Mitsuba's;
* :mod:`.paper_scale`: the report's links to the evaluations at the papers' scale (issue 28)
  in docs/RESULTS.md.

Each module registers its report section (:func:`glossrt.report.register_section`), its
benchmark case (:func:`glossrt.report.registry.benchmark`) and its ``glossrt experiment``
run (:func:`glossrt.report.registry.register_experiment`) when it is imported; importing one
picks no backend. The top floor (``demo``, ``bench``, ``cli``) calls :func:`load_all` so that
every registration runs; nothing else imports more than one of these modules.
"""

from __future__ import annotations

import importlib

#: the experiment modules, one per paper (``upsampling`` is the second half of ``lobes``'s)
MODULES = ("svgf", "lobes", "upsampling", "ltc", "bspvt", "highlights", "specaa",
           "pipeline", "scenes", "paper_scale")


def load_all() -> None:
    """Import every experiment module, so that their sections, benchmark cases and
    experiment runs are registered (a no-op once they are)."""
    for name in MODULES:
        importlib.import_module(f"{__name__}.{name}")
