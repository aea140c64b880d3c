"""Figures reproducing plots of the papers glossrt implements.

:func:`plot_fig3`: Tokuyoshi 2015, fig. 3 -- the lobe-aware weight (``beta = 1``) against the
angle between the lobe axes, with eqs. 4-5 evaluated through the exact SG product integral
(eq. 6) and through Iwasaki's approximation (eq. 7), for several sharpnesses.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

FIG3_SHARPNESS = (0.5, 2.0, 8.0, 32.0)


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
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    theta, curves = fig3_curves(sharpness)
    fig = Figure(figsize=(6.0, 4.0), dpi=100)
    FigureCanvasAgg(fig)
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
