"""What each experiment registers, and the top floor (``demo``, ``bench``, ``cli``) runs.

* Report sections: a function ``fn(ctx: DemoContext, report: Report) -> None`` registered
  with :func:`register_section`; it adds one or more sections to the report.
  :func:`build_report` runs all registered sections by ascending ``order`` (ties:
  registration order). A section that raises is shown as an error box in the page and the
  others still run; after writing the page, :func:`build_report` raises
  :class:`GlossrtError` naming the failed sections, so a demo built on it exits non-zero.
  :func:`section_size` and :func:`markdown_table` are the sections' shared helpers.
* Benchmark cases (``glossrt bench``): ``fn(ctx: BenchContext) -> dict`` registered with
  :func:`benchmark` into :data:`BENCHMARKS`, run by :func:`registered_benchmarks` order.
* Experiments (``glossrt experiment --which NAME``): ``fn(out, size, args) -> int``
  registered with :func:`register_experiment`; :func:`finish_experiment` writes their
  Markdown (and JSON) results. ``args.cluster`` is the run's one open Ray connection
  (``glossrt experiment --cluster``, issue 27) or None; a run reads it with
  :func:`experiment_cluster` and passes it to its references and builds.

This module is a library below the experiments: it imports none of them.
"""

from __future__ import annotations

import contextlib
import json
import sys
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from .. import progress
from ..errors import GlossrtError
from ..progress import Progress
from ..timing import MIN_SAMPLE
from .page import Report

__all__ = [
    "BENCHMARKS",
    "BenchContext",
    "DemoContext",
    "EXPERIMENT_SCALES",
    "SectionFn",
    "benchmark",
    "build_report",
    "experiment_cluster",
    "experiment_scale",
    "option_given",
    "finish_experiment",
    "markdown_table",
    "register_experiment",
    "register_section",
    "registered_benchmarks",
    "registered_experiments",
    "registered_sections",
    "section_size",
    "unregister_section",
]


@dataclass
class DemoContext:
    """What a demo hands to its report sections.

    ``frames`` are the rendered (1 spp) glossrt Frames, ``references`` converged Frames for
    the same frame indices or a sparser subset; ``timings`` maps a stage name to seconds;
    ``extra`` holds anything else a section needs. With ``verbose`` (``glossrt demo``) a
    section tells what it is doing on stderr: :meth:`say` writes a line when a step starts,
    :meth:`bar` gives a :class:`~glossrt.progress.Progress` bar for a step of many items;
    both name the section that runs (:attr:`section`, set by :func:`build_report`).
    """

    out_dir: Path
    scene: str
    frames: list = field(default_factory=list)
    references: list = field(default_factory=list)
    timings: dict[str, float] = field(default_factory=dict)
    extra: dict = field(default_factory=dict)
    verbose: bool = False
    section: str = ""

    def say(self, message: str) -> None:
        """``SECTION: message`` on stderr when :attr:`verbose` (a step starts)."""
        if self.verbose:
            sys.stderr.write(f"{self.section}: {message}\n" if self.section else f"{message}\n")
            sys.stderr.flush()

    def bar(self, desc: str, total: int | None = None) -> _Bar:
        """A progress bar ``SECTION: desc``, shown when :attr:`verbose`: ``with
        ctx.bar("filters") as p: fn(progress=p)``, ``p(done, total)`` or ``p(done)`` after
        each item (``total``: given here or by the first call)."""
        return _Bar(f"{self.section}: {desc}" if self.section else desc, total, self.verbose)


class _Bar:
    """:meth:`DemoContext.bar`: a :class:`Progress` made when its total is known (from the
    constructor or the first ``bar(done, total)``)."""

    def __init__(self, desc: str, total: int | None, enabled: bool):
        self.desc, self.enabled = desc, enabled
        self.p = None if total is None else Progress(total, desc, enabled=enabled)

    def __call__(self, done: int, total: int | None = None) -> None:
        if self.p is None or (total is not None and max(int(total), 1) != self.p.total):
            if self.p is not None:
                self.p.close()
            self.p = Progress(1 if total is None else total, self.desc, enabled=self.enabled)
        self.p.update(done)

    def __enter__(self) -> _Bar:
        if self.p is not None:
            self.p.update(0)
        return self

    def __exit__(self, *exc) -> None:
        if self.p is not None:
            self.p.close()


SectionFn = Callable[[DemoContext, Report], None]


@dataclass(frozen=True)
class _Entry:
    name: str
    order: int
    seq: int
    fn: SectionFn


_REGISTRY: dict[str, _Entry] = {}
_seq = 0


def register_section(name: str, order: int = 100) -> Callable[[SectionFn], SectionFn]:
    """Decorator: register ``fn(ctx, report)`` as the report section ``name``.

    Lower ``order`` runs first. Registering a name again replaces the earlier function
    (so reloading a module does not duplicate its sections). Returns ``fn`` unchanged.
    """

    def deco(fn: SectionFn) -> SectionFn:
        global _seq
        if not callable(fn):
            raise GlossrtError(f"report section {name!r} must be a function, got {fn!r}")
        _seq += 1
        _REGISTRY[name] = _Entry(name, int(order), _seq, fn)
        return fn

    return deco


def unregister_section(name: str) -> None:
    """Remove the section ``name`` (no error if it is not registered)."""
    _REGISTRY.pop(name, None)


def registered_sections() -> list[tuple[str, int, SectionFn]]:
    """``(name, order, fn)`` of every registered section, in the order they run."""
    entries = sorted(_REGISTRY.values(), key=lambda e: (e.order, e.seq))
    return [(e.name, e.order, e.fn) for e in entries]


def _run_sections(ctx, report, sections, failures: list[str]) -> None:
    """Each registered section into ``report``; a failing one is named in ``failures`` and
    on the page, and the others still run."""
    for k, (name, _order, fn) in enumerate(sections):
        ctx.section = ""
        ctx.say(f"report section {k + 1}/{len(sections)}: {name} ...")
        ctx.section = name
        t0 = time.perf_counter()
        try:
            fn(ctx, report)
            ctx.say(f"done ({time.perf_counter() - t0:.1f}s)")
        except Exception as e:  # a failing section must not lose the page
            ctx.say(f"failed ({time.perf_counter() - t0:.1f}s): {type(e).__name__}: {e}")
            failures.append(f"{name}: {type(e).__name__}: {e}")
            sec = report.section(f"{name} (failed)")
            sec.error(
                f"Section {name!r} failed: {type(e).__name__}: {e}",
                details="".join(traceback.format_exception(e)),
            )


def build_report(ctx: DemoContext, title: str, out_dir: str | Path | None = None) -> Path:
    """Run every registered section into a :class:`Report` and write it.

    The report goes to ``out_dir`` (default ``ctx.out_dir``); returns the path of
    ``index.html``. If any section raised, its traceback is shown in the page and, after
    the page is written, :class:`GlossrtError` is raised naming the failed sections and
    the report's path. With ``ctx.verbose`` a line on stderr names each section when it
    starts (``report section K/N: NAME ...``) and when it ends (``NAME: done (S s)``).
    """
    report = Report(out_dir if out_dir is not None else ctx.out_dir, title)
    failures: list[str] = []
    sections = registered_sections()
    if not sections:
        report.section("No sections").paragraph("No report sections are registered.")
    # a quiet context keeps the sections' own progress bars (experiments, references) quiet
    # too, wherever they are made
    quiet = (contextlib.nullcontext() if ctx.verbose
             else progress.observe(lambda *_: None, quiet=True))
    with quiet:
        _run_sections(ctx, report, sections, failures)
    ctx.section = ""
    ctx.say("writing the report page ...")
    path = report.write()
    if failures:
        raise GlossrtError(
            f"{len(failures)} report section(s) failed (page written to {path}): "
            + "; ".join(failures)
        )
    return path


def section_size(ctx: DemoContext, base: tuple[int, int], step: int,
                 floor: tuple[int, int]) -> tuple[float, tuple[int, int]]:
    """A paper section's image size: ``base`` scaled like the demo against its default 160
    pixels of width (smaller in the tests' small demos), rounded down to multiples of
    ``step``, at least ``floor``. Returns ``(scale, (w, h))``."""
    scale = min(1.0, ctx.frames[0].width / 160)
    return scale, tuple(max(lo, int(b * scale) // step * step)
                        for b, lo in zip(base, floor, strict=True))


def markdown_table(section, md: str, caption: str = "") -> None:
    """Show a Markdown table (as the experiments write them for docs/RESULTS.md)."""
    lines = [ln for ln in md.strip().splitlines() if ln.startswith("|")]
    cells = [[c.strip() for c in ln.strip("|").split("|")] for ln in lines]
    section.table(cells[0], cells[2:], caption=caption)


# -- benchmark cases (glossrt bench) ------------------------------------------------------------

@dataclass
class BenchContext:
    size: tuple[int, int] = (640, 360)
    warmup: int = 3
    repeats: int = 9
    #: shortest time of one sample (s): faster calls are repeated within it
    #: (see :func:`glossrt.timing.round_robin`)
    min_sample: float = MIN_SAMPLE
    extra: dict = field(default_factory=dict)

    @property
    def turns(self) -> int:
        """Repeats of a :func:`glossrt.timing.round_robin` (at least 3, so a median of ratios
        means something)."""
        return max(3, self.repeats)


#: benchmark name -> ``fn(ctx: BenchContext) -> dict``
BENCHMARKS: dict[str, Callable[[BenchContext], dict]] = {}
_BENCH_ORDER: dict[str, int] = {}


def benchmark(name: str, order: int = 100):
    """Register ``fn(ctx) -> dict`` as benchmark ``name``; lower ``order`` runs first (ties:
    registration order)."""

    def deco(fn):
        BENCHMARKS[name] = fn
        _BENCH_ORDER[name] = int(order)
        return fn

    return deco


def registered_benchmarks() -> list[str]:
    """The names in :data:`BENCHMARKS`, in the order ``glossrt bench`` runs them."""
    return sorted(BENCHMARKS, key=lambda n: _BENCH_ORDER.get(n, 100))


# -- experiments (glossrt experiment --which NAME) ----------------------------------------------

#: ``fn(out: Path, size: (W, H), args: argparse.Namespace) -> int``: one experiment's run
ExperimentFn = Callable[..., int]


@dataclass(frozen=True)
class _Experiment:
    name: str
    help: str
    order: int
    fn: ExperimentFn


_EXPERIMENTS: dict[str, _Experiment] = {}


def register_experiment(name: str, help: str, order: int = 100):
    """Decorator: register ``fn(out, size, args) -> int`` as ``glossrt experiment --which
    name`` (``help``: what it measures and which options it reads); lower ``order`` is listed
    first."""

    def deco(fn: ExperimentFn) -> ExperimentFn:
        _EXPERIMENTS[name] = _Experiment(name, help, int(order), fn)
        return fn

    return deco


def registered_experiments() -> list[tuple[str, str, ExperimentFn]]:
    """``(name, help, fn)`` of every registered experiment, in the order they are listed."""
    return [(e.name, e.help, e.fn) for e in sorted(_EXPERIMENTS.values(), key=lambda e: e.order)]


def experiment_cluster(args):
    """The cluster an experiment run's references and BSPVT builds go to: ``args.cluster``
    (``glossrt experiment`` sets it to its open :class:`glossrt.cluster.Cluster`, or None),
    None when ``args`` has no ``cluster`` (callers that predate the option). None: the
    experiment's one-process path, unchanged."""
    return getattr(args, "cluster", None)


#: ``glossrt experiment --scale``: ``quick`` (the default: the small runs behind the tables
#: measured on the 2-core machine) or ``paper`` (the papers' sizes, issue 28; each experiment
#: that has a paper-scale run reads it with :func:`experiment_scale`, the others run as quick)
EXPERIMENT_SCALES = ("quick", "paper")


def experiment_scale(args) -> str:
    """The scale of an experiment run: ``args.scale`` (``glossrt experiment --scale``, checked
    against :data:`EXPERIMENT_SCALES`), ``"quick"`` when ``args`` has none (callers that
    predate the option)."""
    scale = getattr(args, "scale", None) or "quick"
    if scale not in EXPERIMENT_SCALES:
        raise GlossrtError(f"--scale must be one of {', '.join(EXPERIMENT_SCALES)}, got {scale!r}")
    return scale


def option_given(args, name: str) -> bool:
    """Whether ``glossrt experiment`` was given ``--NAME`` (``args.explicit``, which the CLI
    fills; callers without it: every option counts as given), e.g. so that a paper-scale run
    takes the paper's size unless ``--size`` was given."""
    given = getattr(args, "explicit", None)
    return True if given is None else name in given


def paper_value(args, name: str, value, default):
    """An option's value for this run: the paper's ``default`` in a ``--scale paper`` run
    whose command line did not give ``--NAME``, else ``value`` (the command's)."""
    if experiment_scale(args) == "paper" and not option_given(args, name):
        return default
    return value


def finish_experiment(out: Path, stem: str, md: str, figure: str,
                      data: dict | None = None) -> int:
    """Write an experiment's ``STEM.md`` (and ``STEM.json`` with ``data``), print it."""
    (out / f"{stem}.md").write_text(md + "\n")
    if data is not None:
        (out / f"{stem}.json").write_text(json.dumps(data, indent=2, default=float))
    print(md)
    print(f"wrote {out / (stem + '.md')} and {out / figure}")
    return 0
