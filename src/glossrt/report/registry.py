"""Registered report sections for the demo, and :func:`build_report` which runs them.

A section is a function ``fn(ctx: DemoContext, report: Report) -> None`` registered with
:func:`register_section`; it adds one or more sections to the report. :func:`build_report`
runs all registered sections by ascending ``order`` (ties: registration order). A section
that raises is shown as an error box in the page and the others still run; after writing
the page, :func:`build_report` raises :class:`GlossrtError` naming the failed sections, so a
demo built on it exits non-zero.
"""

from __future__ import annotations

import traceback
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import GlossrtError
from .page import Report

__all__ = [
    "DemoContext",
    "SectionFn",
    "build_report",
    "register_section",
    "registered_sections",
    "unregister_section",
]


@dataclass
class DemoContext:
    """What a demo hands to its report sections.

    ``frames`` are the rendered (1 spp) glossrt Frames, ``references`` converged Frames for
    the same frame indices or a sparser subset; ``timings`` maps a stage name to seconds;
    ``extra`` holds anything else a section needs.
    """

    out_dir: Path
    scene: str
    frames: list = field(default_factory=list)
    references: list = field(default_factory=list)
    timings: dict[str, float] = field(default_factory=dict)
    extra: dict = field(default_factory=dict)


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


def build_report(ctx: DemoContext, title: str, out_dir: str | Path | None = None) -> Path:
    """Run every registered section into a :class:`Report` and write it.

    The report goes to ``out_dir`` (default ``ctx.out_dir``); returns the path of
    ``index.html``. If any section raised, its traceback is shown in the page and, after
    the page is written, :class:`GlossrtError` is raised naming the failed sections and
    the report's path.
    """
    report = Report(out_dir if out_dir is not None else ctx.out_dir, title)
    failures: list[str] = []
    sections = registered_sections()
    if not sections:
        report.section("No sections").paragraph("No report sections are registered.")
    for name, _order, fn in sections:
        try:
            fn(ctx, report)
        except Exception as e:  # a failing section must not lose the page
            failures.append(f"{name}: {type(e).__name__}: {e}")
            sec = report.section(f"{name} (failed)")
            sec.error(
                f"Section {name!r} failed: {type(e).__name__}: {e}",
                details="".join(traceback.format_exception(e)),
            )
    path = report.write()
    if failures:
        raise GlossrtError(
            f"{len(failures)} report section(s) failed (page written to {path}): "
            + "; ".join(failures)
        )
    return path
