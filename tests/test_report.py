"""Tests for glossrt.report: the HTML page and the section registry."""

from __future__ import annotations

import re
from pathlib import Path

import matplotlib.image as mpimg
import mitsuba as mi
import numpy as np
import pytest
from matplotlib.figure import Figure

from glossrt import report as rp
from glossrt.errors import GlossrtError


def _img(h=12, w=16, seed=0):
    return np.random.default_rng(seed).uniform(0, 2, (h, w, 3)).astype(np.float32)


def _srcs(page: str) -> list[str]:
    return re.findall(r'<img src="([^"]+)"', page)


def test_tonemap_clamps_and_encodes():
    img = np.array([[[0.0, 0.5, 4.0]], [[np.nan, np.inf, 0.0031308]]], np.float32)
    out = rp.tonemap(img)
    assert out.dtype == np.uint8 and out.shape == (2, 1, 3)
    # sRGB(0.5) = 1.055 * 0.5^(1/2.4) - 0.055 = 0.7354 -> 188
    assert out[0, 0].tolist() == [0, 188, 255]
    assert out[1, 0].tolist() == [0, 255, 10]
    assert rp.tonemap(np.full((1, 1, 3), 0.25), exposure=1.0)[0, 0, 0] == 188


def test_report_writes_page_with_images_table_and_error_map(tmp_path):
    rep = rp.Report(tmp_path / "rep", "Test <report>")
    sec = rep.section("Images & maps", "Intro <b>not bold</b>\n\nsecond paragraph")
    ref = _img(seed=1)
    noisy = ref + np.random.default_rng(2).normal(0, 0.1, ref.shape).astype(np.float32)
    p1 = sec.image("ref", mi.TensorXf(ref), caption="reference <1>")
    rels = sec.images_row([("a", ref), ("b", noisy)], name="row")
    p2 = sec.error_map("err", noisy, ref, caption="relative error")
    sec.table(["metric", "value", "n"], [("rmse", 0.123456789, 3), ("<x>", None, 0)])
    fig = Figure(figsize=(2, 2))
    fig.add_subplot().plot([0, 1], [1, 0])
    p3 = sec.figure("plot", fig)
    sec.raw_html('<p class="raw">raw</p>')
    rep.section("Second").paragraph("a & b")
    index = rep.write()

    assert index == tmp_path / "rep" / "index.html" and index.exists()
    page = index.read_text(encoding="utf-8")
    srcs = _srcs(page)
    assert {p1, p2, p3, *rels} <= set(srcs)
    for s in srcs:
        assert not Path(s).is_absolute() and (index.parent / s).is_file(), s
    png = mpimg.imread(index.parent / p1)
    assert png.shape[:2] == ref.shape[:2]
    # Escaping: user text never becomes markup; raw_html does.
    assert "<b>not bold</b>" not in page and "&lt;b&gt;not bold&lt;/b&gt;" in page
    assert "<title>Test &lt;report&gt;</title>" in page
    assert "reference &lt;1&gt;" in page and "&lt;x&gt;" in page and "a &amp; b" in page
    assert page.count("<p>") >= 2
    assert '<p class="raw">raw</p>' in page
    assert "0.1235" in page
    assert "http" not in page.replace("http-equiv", "")  # no external assets


def test_image_names_are_unique_and_sanitised(tmp_path):
    rep = rp.Report(tmp_path, "t")
    sec = rep.section("s")
    a = sec.image("my img/../x", _img())
    b = sec.image("my img/../x", _img())
    assert a != b and "/" not in a[len("img/") :] and ".." not in a
    assert (tmp_path / a).is_file() and (tmp_path / b).is_file()


def test_error_map_rejects_mismatch(tmp_path):
    sec = rp.Report(tmp_path, "t").section("s")
    with pytest.raises(GlossrtError, match=r"\(12, 16, 3\).*\(12, 15, 3\)"):
        sec.error_map("e", _img(), _img(w=15))
    with pytest.raises(GlossrtError, match="kind"):
        sec.error_map("e", _img(), _img(), kind="squared")


def test_error_image_values():
    ref = np.full((2, 2, 3), 0.5)
    img = ref + 0.1
    assert np.allclose(rp.error_image(img, ref, kind="absolute"), 0.1)
    assert np.allclose(rp.error_image(img, ref, kind="relative", eps=0.0), 0.2)


@pytest.fixture
def clean_registry(monkeypatch):
    """An empty section registry for the test (the demo's and the experiments' sections may
    be registered already when other test modules imported glossrt.demo or an experiment
    module); restored afterwards."""
    from glossrt.report import registry

    monkeypatch.setattr(registry, "_REGISTRY", {})
    yield


def test_build_report_runs_sections_in_order(tmp_path, clean_registry):
    calls = []

    @rp.register_section("test-late", order=900)
    def late(ctx, report):
        calls.append("late")
        report.section("Late").paragraph(ctx.scene)

    @rp.register_section("test-early", order=-900)
    def early(ctx, report):
        calls.append("early")
        report.section("Early").table(["stage", "s"], ctx.timings.items())

    ctx = rp.DemoContext(out_dir=tmp_path, scene="glossy <sphere>", timings={"render": 1.5})
    index = rp.build_report(ctx, "Demo")
    assert calls.index("early") < calls.index("late")
    page = index.read_text(encoding="utf-8")
    assert page.index("Early") < page.index("Late")
    assert "glossy &lt;sphere&gt;" in page and "1.5" in page


def test_failing_section_is_shown_and_raises(tmp_path, clean_registry):
    @rp.register_section("test-ok", order=-800)
    def ok(ctx, report):
        report.section("Fine").paragraph("fine")

    @rp.register_section("test-broken", order=-700)
    def broken(ctx, report):
        raise ValueError("boom <here>")

    @rp.register_section("test-after", order=-600)
    def after(ctx, report):
        report.section("After").paragraph("still runs")

    ctx = rp.DemoContext(out_dir=tmp_path, scene="s")
    with pytest.raises(GlossrtError, match="test-broken") as e:
        rp.build_report(ctx, "Demo")
    assert "boom" in str(e.value)
    page = (tmp_path / "index.html").read_text(encoding="utf-8")
    assert 'class="error"' in page and "boom &lt;here&gt;" in page and "ValueError" in page
    assert "still runs" in page and "Fine" in page


def test_verbose_report_names_each_section_and_its_steps_on_stderr(tmp_path, clean_registry,
                                                                   capsys):
    @rp.register_section("test-steps", order=-500)
    def steps(ctx, report):
        ctx.say("first step ...")
        with ctx.bar("items") as p:
            for k in range(4):
                p(k + 1, 4)
        report.section("Steps").paragraph("done")

    @rp.register_section("test-broken", order=-400)
    def broken(ctx, report):
        raise ValueError("boom")

    ctx = rp.DemoContext(out_dir=tmp_path, scene="s", verbose=True)
    with pytest.raises(GlossrtError, match="test-broken"):
        rp.build_report(ctx, "Demo")
    err = capsys.readouterr().err.splitlines()
    want = ["report section 1/2: test-steps ...", "test-steps: first step ...",
            *(f"test-steps: items: {k}/4 (" for k in range(1, 5)), "test-steps: done (",
            "report section 2/2: test-broken ...", "test-broken: failed (",
            "writing the report page ..."]
    assert len(err) == len(want), err
    assert all(e.startswith(w) for e, w in zip(err, want, strict=True)), err
    assert "ValueError: boom" in err[-2]
    # quiet unless verbose (a context of one's own, as the experiments' tests make)
    quiet = rp.DemoContext(out_dir=tmp_path, scene="s")
    quiet.say("nothing")
    with quiet.bar("nothing", 3) as p:
        p(3)
    assert capsys.readouterr().err == ""


def test_progress_off_a_terminal_writes_a_line_for_a_slow_update(monkeypatch):
    import io

    from glossrt import progress

    clock = [0.0]
    monkeypatch.setattr(progress.time, "perf_counter", lambda: clock[0])
    out = io.StringIO()
    with progress.Progress(100, "work", stream=out) as p:
        p.update(1)  # quarter 0 again, at once: no line
        clock[0] = progress.LINE_EVERY + 0.5
        p.update(2)  # quarter 0, but after LINE_EVERY seconds: a line
        p.update(25)  # a new quarter: a line
    t = f"{progress.LINE_EVERY + 0.5:.1f}s"
    assert out.getvalue().splitlines() == ["work: 0/100 (0.0s)", f"work: 2/100 ({t})",
                                           f"work: 25/100 ({t})"]


def test_register_same_name_replaces(clean_registry):
    @rp.register_section("test-dup", order=1)
    def one(ctx, report):
        pass

    @rp.register_section("test-dup", order=2)
    def two(ctx, report):
        pass

    dup = [(n, o, f) for n, o, f in rp.registered_sections() if n == "test-dup"]
    assert dup == [("test-dup", 2, two)]


def test_montage_writes_a_grid_without_switching_the_backend(tmp_path):
    """report.figures.montage: the experiments' image grids, drawn on an Agg canvas without
    pyplot, so a notebook's backend is left as the user chose it."""
    import matplotlib

    from glossrt.report.figures import Panel, montage

    before = matplotlib.get_backend()
    rng = np.random.default_rng(0)
    img = rng.random((12, 16, 3))
    grid = [[Panel(img, "image"), Panel(img[..., 0], "error", "magma", 0.0, 0.5,
                                        colorbar={"fraction": 0.046, "pad": 0.02})],
            [Panel(img, "short row")]]
    out = montage(tmp_path / "m.png", grid, (4.0, 3.0), dpi=50)
    assert out == tmp_path / "m.png"
    assert mpimg.imread(out).shape[:2] == (150, 200)
    assert matplotlib.get_backend() == before


def test_progress_observer_sees_this_threads_bars_and_can_quiet_them():
    import io
    import threading

    from glossrt import progress

    seen, out = [], io.StringIO()

    def other_thread():  # another thread's bars are not observed
        with progress.Progress(2, "other", stream=out) as p:
            p.update(2)

    with progress.observe(lambda *a: seen.append(a), quiet=True):
        with progress.Progress(4, "trees", stream=out) as p:
            p.update(3)
        t = threading.Thread(target=other_thread)
        t.start()
        t.join()
    assert seen == [("trees", 0, 4), ("trees", 3, 4)]
    assert "trees" not in out.getvalue() and "other: 2/2" in out.getvalue()
    with progress.Progress(4, "after", stream=out) as p:  # outside the block: as before
        p.update(4)
    assert "after: 4/4" in out.getvalue() and len(seen) == 2
