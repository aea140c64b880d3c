"""The report's index of the evaluations redone at the papers' scale (issue 28): every
subsection of docs/RESULTS.md whose heading says ``(issue 28``, with the command that
measured it and its figures. docs/RESULTS.md stays the one place where these results are
written; the report section links each of them and shows their pictures."""

from __future__ import annotations

import os
import re
import shutil
from dataclasses import dataclass, field
from pathlib import Path

from ..report import DemoContext, Report, register_section

#: docs/RESULTS.md of the source tree this module runs from (absent from an installed wheel)
RESULTS = Path(__file__).resolve().parents[3] / "docs" / "RESULTS.md"
MARK = "(issue 28"
_HEADING = re.compile(r"^(#{2,4}) +(.*)$")
_COMMAND = re.compile(r"`(glossrt (?:experiment|bench|render)[^`]*)`", re.S)
_IMAGE = re.compile(r"!\[([^\]]*)\]\(([^)\s]+)\)")


@dataclass
class PaperRun:
    """One paper-scale subsection of RESULTS.md."""

    title: str
    #: the ``##`` section it belongs to (the paper)
    paper: str
    #: GitHub's anchor of the heading (lower case, punctuation dropped, spaces to hyphens)
    anchor: str
    commands: list[str] = field(default_factory=list)
    #: ``(caption, path relative to RESULTS.md)``
    images: list[tuple[str, str]] = field(default_factory=list)


def anchor(heading: str) -> str:
    """GitHub's anchor of a Markdown heading: lower case, every character but letters,
    digits, spaces, ``-`` and ``_`` dropped, spaces turned into hyphens."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def paper_runs(text: str) -> list[PaperRun]:
    """The subsections of RESULTS.md-style ``text`` whose heading contains :data:`MARK`, in
    order, each with the ``glossrt ...`` commands quoted in it (whitespace joined) and its
    images."""
    runs: list[PaperRun] = []
    paper, cur, level, body = "", None, 0, []

    def close():
        if cur is not None:
            chunk = "\n".join(body)
            cur.commands = [" ".join(c.split()) for c in _COMMAND.findall(chunk)]
            cur.images = _IMAGE.findall(chunk)
            runs.append(cur)

    for line in text.splitlines():
        m = _HEADING.match(line)
        if m and (cur is None or len(m.group(1)) <= level):
            close()
            cur, body = None, []
            if len(m.group(1)) == 2:
                paper = m.group(2).strip()
            if MARK in m.group(2):
                cur, level = PaperRun(m.group(2).strip(), paper, anchor(m.group(2))), \
                    len(m.group(1))
            continue
        body.append(line)
    close()
    return runs


@register_section("paper_scale", order=95)
def section_paper_scale(ctx: DemoContext, report: Report) -> None:
    """Links to every paper-scale evaluation of docs/RESULTS.md, with its command and
    figures (copied next to the report)."""
    sec = report.section(
        "At the papers' scale",
        "The evaluations redone at the sizes, sample counts and sequence lengths the papers "
        "used (issue 28). Each was measured once with the command shown (a cluster makes "
        "them faster: --cluster); the tables, wall times and conclusions are in "
        "docs/RESULTS.md, linked here. This report's own sections above are the small "
        "versions.")
    if not RESULTS.is_file():
        sec.paragraph(f"docs/RESULTS.md is not next to this installation ({RESULTS}); it is "
                      "in the glossrt source tree.")
        return
    runs = paper_runs(RESULTS.read_text(encoding="utf-8"))
    href = Path(os.path.relpath(RESULTS, report.out_dir.resolve())).as_posix()
    sec.links([(f"{r.paper}: {r.title}", f"{href}#{r.anchor}",
                "; ".join(f"`{c}`" for c in r.commands) or "(command in the text)")
               for r in runs])
    for r in runs:
        for caption, rel in r.images:
            src = RESULTS.parent / rel
            if src.is_file():
                sec.saved_figure(f"paper_{Path(rel).stem}",
                                 lambda p, src=src: shutil.copyfile(src, p),
                                 f"{r.title}: {caption}")
