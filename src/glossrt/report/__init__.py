"""Static HTML reports: :class:`Report` / :class:`Section` build a page of text, tone-mapped
images, error maps, tables and figures; :func:`register_section` and :func:`build_report`
assemble a demo's report from registered section functions.

>>> from glossrt.report import DemoContext, Report, build_report, register_section
>>> @register_section("timings", order=10)                       # doctest: +SKIP
... def timings(ctx: DemoContext, report: Report) -> None:
...     report.section("Timings").table(["stage", "s"], ctx.timings.items())
>>> build_report(ctx, "Glossy demo")                              # doctest: +SKIP
"""

from __future__ import annotations

from .page import Report, Section, error_image, tonemap
from .registry import (
    DemoContext,
    SectionFn,
    build_report,
    register_section,
    registered_sections,
    unregister_section,
)

__all__ = [
    "DemoContext",
    "Report",
    "Section",
    "SectionFn",
    "build_report",
    "error_image",
    "register_section",
    "registered_sections",
    "tonemap",
    "unregister_section",
]
