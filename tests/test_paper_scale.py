"""The report's index of the paper-scale evaluations (issue 28): parsing RESULTS.md-style
Markdown, GitHub's heading anchors, the section on the real docs/RESULTS.md, and every
command it lists being one the CLI accepts."""

from __future__ import annotations

import shlex
from pathlib import Path

import pytest

from glossrt.experiments import paper_scale as ps

SAMPLE = """# Results

## Paper A (issue 3)

Small table.

### At 1280x720 (issue 28; references of 512 spp)

`glossrt experiment --which denoisers --size 1280x720
--spp 512 --out x`, 8 min. Also `ls -l` and `glossrt bench --only pipeline`.

![curve](images/a.png)

#### Detail inside the paper-scale part

more text ![inner](images/b.png)

### Fig. 4 analogue

`glossrt experiment --which lobes` (not paper scale)

## Paper B (issue 6)

### Table 1 at the paper's size (issue 28)

`glossrt experiment --which bspvt --scale paper`
"""


def test_paper_runs_of_a_sample():
    runs = ps.paper_runs(SAMPLE)
    assert [r.title for r in runs] == ["At 1280x720 (issue 28; references of 512 spp)",
                                       "Table 1 at the paper's size (issue 28)"]
    a, b = runs
    assert a.paper == "Paper A (issue 3)" and b.paper == "Paper B (issue 6)"
    # a command split over two lines is joined; other code spans are not commands; the
    # #### subsection belongs to the ### one, the next ### ends it
    assert a.commands == ["glossrt experiment --which denoisers --size 1280x720 --spp 512 "
                          "--out x", "glossrt bench --only pipeline"]
    assert a.images == [("curve", "images/a.png"), ("inner", "images/b.png")]
    assert b.commands == ["glossrt experiment --which bspvt --scale paper"]


@pytest.mark.parametrize("heading, want", [
    # GitHub's anchors (as github.com renders these headings of docs/RESULTS.md)
    ("At the paper's scale (issue 28): 640x360, 4096 spp references, bias and variance",
     "at-the-papers-scale-issue-28-640x360-4096-spp-references-bias-and-variance"),
    ("Table 1 at the paper's size (issue 28)", "table-1-at-the-papers-size-issue-28"),
    ("Fig. 4 analogue: `roughness-map` (GGX alpha 0.02 | 0.5 checker floor, striped wall)",
     "fig-4-analogue-roughness-map-ggx-alpha-002--05-checker-floor-striped-wall"),
])
def test_anchor_is_githubs(heading, want):
    assert ps.anchor(heading) == want


def test_section_links_every_paper_scale_result(tmp_path):
    from glossrt.cli import build_parser
    from glossrt.report import DemoContext, Report

    runs = ps.paper_runs(ps.RESULTS.read_text(encoding="utf-8"))
    # each paper whose evaluation the issue asks for at scale has at least one entry
    papers = " ".join(r.paper for r in runs)
    for name in ("Denoisers", "lobe-aware", "BSPVT", "Specular antialiasing"):
        assert name in papers, (name, papers)
    parser = build_parser()
    for r in runs:
        assert r.commands, r.title
        for cmd in r.commands:  # every listed command is one the CLI accepts
            argv = shlex.split(cmd)
            assert argv[0] == "glossrt"
            parser.parse_args(argv[1:])
    rep = Report(tmp_path / "report", "t")
    ps.section_paper_scale(DemoContext(out_dir=tmp_path, scene="glossy-cornell"), rep)
    html = rep.write().read_text()
    assert html.count('<li><a href="') == len(runs)
    for r in runs:
        assert f"#{r.anchor}\"" in html
    href = html.split('<li><a href="')[1].split("#")[0]
    assert (tmp_path / "report" / href).resolve() == ps.RESULTS.resolve()
    figures = [img for r in runs for _, img in r.images]
    assert figures and len(list((tmp_path / "report" / "img").glob("paper_*.png"))) == \
        len(figures)
    for _, img in [i for r in runs for i in r.images]:
        assert (ps.RESULTS.parent / img).is_file(), img


def test_section_without_the_source_tree(tmp_path, monkeypatch):
    from glossrt.report import DemoContext, Report

    monkeypatch.setattr(ps, "RESULTS", Path(tmp_path / "missing" / "RESULTS.md"))
    rep = Report(tmp_path / "report", "t")
    ps.section_paper_scale(DemoContext(out_dir=tmp_path, scene="glossy-cornell"), rep)
    assert "source tree" in rep.write().read_text()
