"""Figures of the experiments and reproductions of the papers' plots.

Every figure is a :class:`matplotlib.figure.Figure` drawn by the Agg canvas
(:func:`new_figure`), never through ``pyplot``: glossrt switches no global matplotlib backend,
so a notebook keeps its own.

:func:`montage`: a grid of image panels (tone-mapped images, false-colour error maps, optional
colour bars) saved as one PNG; the experiments' ``montage()`` methods describe their panels
with :class:`Panel`.

:func:`plot_fig3`: Tokuyoshi 2015, fig. 3 -- the lobe-aware weight (``beta = 1``) against the
angle between the lobe axes, with eqs. 4-5 evaluated through the exact SG product integral
(eq. 6) and through Iwasaki's approximation (eq. 7), for several sharpnesses.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

FIG3_SHARPNESS = (0.5, 2.0, 8.0, 32.0)


def new_figure(figsize: tuple[float, float], dpi: float | None = None) -> Any:
    """A matplotlib ``Figure`` of ``figsize`` inches with an Agg canvas attached (``dpi``:
    matplotlib's default when None). No ``pyplot``, so no global backend is chosen or
    switched, and nothing needs closing."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize) if dpi is None else Figure(figsize=figsize, dpi=dpi)
    FigureCanvasAgg(fig)
    return fig


def subplots(rows: int, cols: int, figsize: tuple[float, float], **kw: Any) -> tuple[Any, Any]:
    """``(fig, axes)`` as ``pyplot.subplots(rows, cols, figsize=figsize, squeeze=False,
    **kw)`` gives them, on a :func:`new_figure` (axes: a ``rows x cols`` array)."""
    fig = new_figure(figsize)
    return fig, fig.subplots(rows, cols, squeeze=False, **kw)


@dataclass
class Panel:
    """One image of a :func:`montage`: ``image`` (an RGB image already tone-mapped, or a
    scalar map shown in ``cmap`` from ``vmin`` to ``vmax``), its ``title`` (in ``fontsize``
    points) and, with ``colorbar`` (keyword arguments of ``Figure.colorbar``, e.g.
    ``{"fraction": 0.046, "pad": 0.02}``), a colour bar beside it."""

    image: Any
    title: str
    cmap: str | None = None
    vmin: float | None = None
    vmax: float | None = None
    fontsize: float = 8
    colorbar: dict | None = None


def montage(path: str | Path, grid: Sequence[Sequence[Panel | None]],
            figsize: tuple[float, float], dpi: float = 100) -> Path:
    """Save ``grid`` (rows of :class:`Panel`; None or a short row leaves a cell empty) as one
    PNG of ``figsize`` inches at ``dpi``: every axis hidden, images drawn pixel for pixel
    (nearest interpolation), the layout tightened. Returns ``Path(path)``."""
    rows = len(grid)
    cols = max(len(row) for row in grid)
    fig, axes = subplots(rows, cols, figsize)
    for r, row in enumerate(grid):
        for c in range(cols):
            ax = axes[r, c]
            ax.axis("off")
            p = row[c] if c < len(row) else None
            if p is None:
                continue
            im = ax.imshow(p.image, cmap=p.cmap, vmin=p.vmin, vmax=p.vmax,
                           interpolation="nearest")
            ax.set_title(p.title, fontsize=p.fontsize)
            if p.colorbar is not None:
                fig.colorbar(im, ax=ax, **p.colorbar)
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    return Path(path)


def fig3_curves(
    sharpness: Sequence[float] = FIG3_SHARPNESS, n: int = 181
) -> tuple[np.ndarray, dict[float, tuple[np.ndarray, np.ndarray]]]:
    """Angles (radians, ``0..pi``) and, per sharpness ``lambda`` (both lobes, no smoothing
    kernel, ``beta = 1``), the weights ``(exact eq. 6, approx eq. 7)`` of
    :func:`glossrt.brdf.sg.lobe_weight`."""
    from glossrt.brdf import sg

    mi = sg.mi  # mitsuba, imported after glossrt's backend set-up

    theta = np.linspace(0.0, math.pi, n)
    zeros = np.zeros_like(theta)
    xi_p = mi.Vector3f(mi.Float(zeros), mi.Float(zeros), mi.Float(zeros + 1.0))
    xi_q = mi.Vector3f(mi.Float(np.sin(theta)), mi.Float(zeros), mi.Float(np.cos(theta)))
    curves = {}
    for lam in sharpness:
        lf = mi.Float(float(lam))
        ex = sg.lobe_weight(xi_p, lf, xi_q, lf, beta=1.0, kappa=None, approx=False)
        ap = sg.lobe_weight(xi_p, lf, xi_q, lf, beta=1.0, kappa=None, approx=True)
        curves[float(lam)] = (np.asarray(ex, dtype=np.float64), np.asarray(ap, dtype=np.float64))
    return theta, curves


def plot_fig3(path: str | Path, sharpness: Sequence[float] = FIG3_SHARPNESS) -> Path:
    """Write Tokuyoshi 2015's fig. 3 (weight vs angle between axes; exact eq. 6 solid,
    Iwasaki's eq. 7 dashed; ``beta = 1``) as a PNG to ``path``; returns the path."""
    theta, curves = fig3_curves(sharpness)
    fig = new_figure((6.0, 4.0), dpi=100)
    ax = fig.add_subplot()
    deg = np.degrees(theta)
    for k, (lam, (ex, ap)) in enumerate(curves.items()):
        color = f"C{k}"
        ax.plot(deg, ex, color=color, label=f"λ = {lam:g}, exact (eq. 6)")
        ax.plot(deg, ap, color=color, linestyle="--", label=f"λ = {lam:g}, approx. (eq. 7)")
    ax.set_xlabel("angle between ξ_i and ξ_j [deg]")
    ax.set_ylabel("w_ω(i, j)  (β = 1)")
    ax.set_xlim(0.0, 180.0)
    ax.set_ylim(0.0, 1.05)
    ax.set_title("Tokuyoshi 2015, fig. 3: Iwasaki's approximation")
    ax.legend(fontsize=7)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, format="png")
    return path
