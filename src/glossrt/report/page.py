"""A small static HTML report: sections of text, tone-mapped images, error maps and tables.

The page is one ``index.html`` with inline CSS; images are PNG files under ``img/`` next to
it and are referenced by relative paths, so the directory can be moved or zipped as a whole.
All text passed in is HTML-escaped, except :meth:`Section.raw_html`.
"""

from __future__ import annotations

import html
import re
import sys
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import GlossrtError
from ..metrics import as_array, srgb_encode

__all__ = ["Report", "Section", "tonemap", "error_image"]

_CSS_FILE = Path(__file__).with_name("style.css")


def tonemap(img: Any, exposure: float = 0.0) -> np.ndarray:
    """Linear HDR image -> 8-bit sRGB, shape (H, W, 3), dtype uint8.

    The radiance is scaled by ``2**exposure``, clamped to [0, 1] and sRGB-encoded (no
    filmic curve, so what is clipped is visibly clipped). NaN becomes 0 and +Inf 1. One
    channel is shown as grey; channels after the third (alpha) are dropped.
    """
    a = as_array(img, "image", check_finite=False)
    c = a.shape[2]
    if c == 1:
        a = np.repeat(a, 3, axis=2)
    elif c == 2:
        raise GlossrtError("cannot display an image with 2 channels")
    else:
        a = a[:, :, :3]
    a = np.nan_to_num(a * (2.0**exposure), nan=0.0, posinf=1.0, neginf=0.0)
    return np.round(srgb_encode(a) * 255.0).astype(np.uint8)


def error_image(img: Any, ref: Any, kind: str = "relative", eps: float = 1e-2) -> np.ndarray:
    """Per-pixel error of ``img`` against ``ref``, shape (H, W).

    ``kind="absolute"``: mean over channels of ``|x - r|``.
    ``kind="relative"``: that divided by ``mean over channels of |r| + eps``.
    Raises :class:`GlossrtError` for mismatched sizes or non-finite values.
    """
    x = as_array(img, "image")
    r = as_array(ref, "reference")
    if x.shape != r.shape:
        raise GlossrtError(
            f"image and reference differ in size: image {x.shape} vs reference {r.shape}"
        )
    err = np.mean(np.abs(x - r), axis=2)
    if kind == "absolute":
        return err
    if kind == "relative":
        return err / (np.mean(np.abs(r), axis=2) + eps)
    raise GlossrtError(f"error map kind must be 'relative' or 'absolute', got {kind!r}")


def _esc(text: Any) -> str:
    return html.escape(str(text), quote=True)


def _text_html(text: str) -> str:
    """Escaped text; blank lines separate paragraphs, single newlines become <br>."""
    paras = [p.strip() for p in re.split(r"\n\s*\n", str(text)) if p.strip()]
    return "\n".join("<p>" + _esc(p).replace("\n", "<br>\n") + "</p>" for p in paras)


def _cell(v: Any) -> str:
    if v is None:
        return "<td>&ndash;</td>"
    if isinstance(v, bool | np.bool_):
        return f"<td>{_esc(v)}</td>"
    if isinstance(v, int | np.integer):
        return f'<td class="num">{int(v)}</td>'
    if isinstance(v, float | np.floating):
        return f'<td class="num">{float(v):.4g}</td>'
    return f"<td>{_esc(v)}</td>"


def _figure(src: str, caption: str) -> str:
    cap = f"<figcaption>{_esc(caption)}</figcaption>" if caption else ""
    return f'<figure><img src="{_esc(src)}" alt="{_esc(caption)}">{cap}</figure>'


class Section:
    """A titled part of a :class:`Report`; made by :meth:`Report.section`.

    Content appears in the order the methods are called.
    """

    def __init__(self, report: Report, title: str, anchor: str) -> None:
        self.report = report
        self.title = title
        self.anchor = anchor
        self._blocks: list[str] = []
        self.failed = False

    def paragraph(self, text: str) -> None:
        """Add text (escaped; blank lines start new paragraphs)."""
        self._blocks.append(_text_html(text))

    def links(self, items: Sequence[tuple[str, str, str]]) -> None:
        """Add a list of ``(label, href, note)``: each label a link to ``href`` (a path
        relative to the report, or a URL), then its note (escaped text; text in backticks is
        shown as code)."""
        lis = []
        for label, href, note in items:
            parts = re.split(r"`([^`]*)`", _esc(note))
            text = "".join(f"<code>{p}</code>" if i % 2 else p for i, p in enumerate(parts))
            lis.append(f'<li><a href="{_esc(href)}">{_esc(label)}</a>'
                       + (f": {text}" if note else "") + "</li>")
        self._blocks.append("<ul>\n" + "\n".join(lis) + "\n</ul>")

    def image(self, name: str, img: Any, caption: str = "", exposure: float = 0.0) -> str:
        """Add a linear image, tone-mapped by :func:`tonemap`; returns its path relative to the
        report (``img/<name>.png``, with a suffix if the name is already taken)."""
        rel = self._write_image(name, img, exposure)
        self._blocks.append(_figure(rel, self._note_nonfinite(img, caption)))
        return rel

    def images_row(
        self, items: Sequence[tuple[str, Any]], name: str | None = None, exposure: float = 0.0
    ) -> list[str]:
        """Add ``(caption, image)`` pairs side by side; returns their relative paths. Files are
        named ``<name>_<i>`` (``name`` defaults to the section title)."""
        base = name or self.title
        rels, figs = [], []
        for i, (caption, img) in enumerate(items):
            rel = self._write_image(f"{base}_{i}", img, exposure)
            rels.append(rel)
            figs.append(_figure(rel, self._note_nonfinite(img, caption)))
        self._blocks.append('<div class="row">\n' + "\n".join(figs) + "\n</div>")
        return rels

    def error_map(
        self,
        name: str,
        img: Any,
        ref: Any,
        caption: str = "",
        kind: str = "relative",
        vmax: float | None = None,
        eps: float = 1e-2,
    ) -> str:
        """Add a false-colour map of the per-pixel error of ``img`` against ``ref`` (see
        :func:`error_image`; relative by default) with a colour bar; returns its path.

        The colour scale runs from 0 to ``vmax`` (default: the 99th percentile of the error,
        so a few outliers do not wash out the map; the value is printed on the bar).
        """
        from matplotlib.figure import Figure

        err = error_image(img, ref, kind=kind, eps=eps)
        if vmax is None:
            vmax = float(np.percentile(err, 99.0))
        vmax = vmax if vmax > 0 else 1.0
        h, w = err.shape
        scale = max(1.0, 320.0 / max(h, w)) / 100.0  # inches per pixel at dpi 100
        fig = Figure(figsize=(w * scale + 1.2, h * scale), dpi=100)
        ax = fig.add_subplot()
        im = ax.imshow(err, cmap="inferno", vmin=0.0, vmax=vmax, interpolation="nearest")
        ax.set_axis_off()
        label = f"|x - r| / (|r| + {eps:g})" if kind == "relative" else "|x - r| (channel mean)"
        fig.colorbar(im, ax=ax, label=label, fraction=0.08, pad=0.03)
        rel = self._save_figure(name, fig)
        caption = caption or f"{kind} error, scale 0..{vmax:.3g}"
        self._blocks.append(_figure(rel, caption))
        return rel

    def table(
        self, columns: Sequence[str], rows: Iterable[Sequence[Any]], caption: str = ""
    ) -> None:
        """Add a table; floats are shown with 4 significant digits, None as a dash."""
        columns = list(columns)
        out = ["<table>"]
        if caption:
            out.append(f"<caption>{_esc(caption)}</caption>")
        out.append("<tr>" + "".join(f"<th>{_esc(c)}</th>" for c in columns) + "</tr>")
        for i, row in enumerate(rows):
            row = list(row)
            if len(row) != len(columns):
                raise GlossrtError(
                    f"table row {i} has {len(row)} cells, expected {len(columns)} ({columns})"
                )
            out.append("<tr>" + "".join(_cell(v) for v in row) + "</tr>")
        out.append("</table>")
        self._blocks.append("\n".join(out))

    def figure(self, name: str, fig: Any, caption: str = "") -> str:
        """Add a matplotlib figure saved as PNG; returns its path. A figure made with pyplot
        is closed afterwards."""
        rel = self._save_figure(name, fig)
        if "matplotlib.pyplot" in sys.modules:
            sys.modules["matplotlib.pyplot"].close(fig)
        self._blocks.append(_figure(rel, caption))
        return rel

    def saved_figure(self, name: str, write: Callable[[Path], Any], caption: str = "") -> str:
        """Add a picture that ``write(path)`` saves itself (e.g. a plotting function taking a
        file name); returns its path relative to the report."""
        rel, path = self.report._new_file(name)
        write(path)
        self._blocks.append(_figure(rel, caption))
        return rel

    def raw_html(self, html_text: str) -> None:
        """Add HTML as it is (not escaped)."""
        self._blocks.append(str(html_text))

    def error(self, message: str, details: str = "") -> None:
        """Add a red error box with ``message`` and optional preformatted ``details``."""
        self.failed = True
        det = f"<pre>{_esc(details)}</pre>" if details else ""
        self._blocks.append(f'<div class="error"><strong>{_esc(message)}</strong>{det}</div>')

    # -- helpers -----------------------------------------------------------------------------

    def _note_nonfinite(self, img: Any, caption: str) -> str:
        a = as_array(img, "image", check_finite=False)
        bad = int(a.size - np.count_nonzero(np.isfinite(a)))
        if bad:
            note = f"({bad} NaN/Inf values, shown black/white)"
            return f"{caption} {note}" if caption else note
        return caption

    def _write_image(self, name: str, img: Any, exposure: float) -> str:
        from matplotlib.image import imsave

        rgb = tonemap(img, exposure)
        rel, path = self.report._new_file(name)
        imsave(path, rgb)
        return rel

    def _save_figure(self, name: str, fig: Any) -> str:
        rel, path = self.report._new_file(name)
        fig.savefig(path, dpi=fig.dpi, bbox_inches="tight")
        return rel

    def _html(self) -> str:
        parts = [f'<section id="{_esc(self.anchor)}">', f"<h2>{_esc(self.title)}</h2>"]
        parts += self._blocks
        parts.append("</section>")
        return "\n".join(parts)


class Report:
    """A static HTML report written to ``out_dir/index.html`` (images in ``out_dir/img/``).

    >>> rep = Report("out/report", "Glossy sphere")                   # doctest: +SKIP
    >>> sec = rep.section("Result", "1 spp, filtered.")               # doctest: +SKIP
    >>> sec.image("filtered", frame["color"], caption="filtered")    # doctest: +SKIP
    >>> rep.write()                                                   # doctest: +SKIP
    """

    def __init__(self, out_dir: str | Path, title: str) -> None:
        self.out_dir = Path(out_dir)
        self.title = title
        self.sections: list[Section] = []
        self._files: set[str] = set()
        self._anchors: set[str] = set()

    def section(self, title: str, text: str = "") -> Section:
        """Start a new section (shown in creation order), optionally with introductory text."""
        anchor = _unique(_slug(title) or "section", self._anchors)
        sec = Section(self, title, anchor)
        if text:
            sec.paragraph(text)
        self.sections.append(sec)
        return sec

    def write(self) -> Path:
        """Write ``index.html`` (may be called again after adding content); returns its path."""
        self.out_dir.mkdir(parents=True, exist_ok=True)
        css = _CSS_FILE.read_text(encoding="utf-8") if _CSS_FILE.exists() else ""
        from .. import __version__

        toc = ""
        if len(self.sections) > 1:
            items = "".join(
                f'<li><a href="#{_esc(s.anchor)}">{_esc(s.title)}</a>'
                + (" (failed)" if s.failed else "")
                + "</li>"
                for s in self.sections
            )
            toc = f"<nav><ul>{items}</ul></nav>"
        body = "\n".join(s._html() for s in self.sections)
        page = (
            '<!DOCTYPE html>\n<html lang="en">\n<head>\n<meta charset="utf-8">\n'
            f"<title>{_esc(self.title)}</title>\n<style>\n{css}</style>\n</head>\n<body>\n"
            f"<h1>{_esc(self.title)}</h1>\n{toc}\n{body}\n"
            f"<footer>generated by glossrt {_esc(__version__)}</footer>\n</body>\n</html>\n"
        )
        path = self.out_dir / "index.html"
        path.write_text(page, encoding="utf-8")
        return path

    def _new_file(self, name: str) -> tuple[str, Path]:
        stem = name[:-4] if name.lower().endswith(".png") else name
        fname = _unique(_slug(stem) or "image", self._files) + ".png"
        (self.out_dir / "img").mkdir(parents=True, exist_ok=True)
        return f"img/{fname}", self.out_dir / "img" / fname


def _slug(text: str) -> str:
    """File-name/anchor-safe version of ``text``: letters, digits, ``_``, ``-``, single dots."""
    s = re.sub(r"[^A-Za-z0-9_.-]+|\.{2,}", "_", str(text))
    return re.sub(r"_{2,}", "_", s).strip("._-")


def _unique(base: str, taken: set[str]) -> str:
    name, i = base, 2
    while name.lower() in taken:
        name = f"{base}_{i}"
        i += 1
    taken.add(name.lower())
    return name
