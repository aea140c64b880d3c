"""Measured reproductions of Tokuyoshi 2015's denoising experiments (sec. 5.1 and 5.2,
figs. 4-6) with glossrt's cross-bilateral filter (:func:`glossrt.denoise.bilateral`).

Reference: Y. Tokuyoshi, "Specular Lobe-Aware Filtering and Upsampling for Interactive
Indirect Illumination", IPSJ Journal 56(8), 2015.

* :func:`fig4`: the ``roughness-map`` scene (sec. 5.1, fig. 4): MSE of the indirect specular
  buffer against a converged reference for the 1 spp input, the normal-aware weight
  (fig. 4(b)), the sharpness-adapted screen kernel (fig. 4(c), glossrt's form, see
  :mod:`glossrt.denoise.bilateral`) and the lobe-aware weight (fig. 4(d)), at the paper's
  parameters;
* :func:`fig5`: the ``glossy-spheres`` scene (sec. 5.1, fig. 5): one parameter set for
  spheres of Phong exponent 1000, 100 and 10; MSE per sphere (mask = the sphere's
  ``mesh_id``);
* :func:`fig6`: MSE per sphere against the parameter (sec. 5.2, fig. 6): the lobe weight
  sweeping ``beta``, the normal weight sweeping ``1 / sigma_n^2`` over the same values (the
  normal weight ``G(n_i, n_j, 1 / sigma_n^2)`` is the lobe weight of a diffuse lobe, end of
  sec. 4.2, so ``1 / sigma_n^2`` plays the role of ``beta``), the optimum per sphere and how
  far the optima spread (decades).

Everything is measured on the ``indirect_specular`` component only (the filter is given
``channels=("indirect_specular",)``; the filtered component is the filter's output minus the
unfiltered other components). MSE = mean over pixels (and RGB) of the squared difference to
the reference's ``indirect_specular``. Each function renders its scene once (frame 0: the 1
spp frame and a reference of ``ref_spp`` samples with the same primary hits) and reuses it for
every filter / parameter. Sweeps pass the swept value as an opaque Dr.Jit scalar so the
filter's kernels compile once per method (results equal the Python-float call to float32
rounding).

The numbers are whatever they are: nothing here is tuned to reproduce the paper.

The paper's report section (``lobes``: figs. 3-6 and :mod:`.upsampling`), benchmark case
(``lobe-weights``) and ``glossrt experiment --which lobes`` are registered here.
"""

from __future__ import annotations

import math
import statistics
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import drjit as dr
import numpy as np

from ..backend import mi
from ..errors import GlossrtError
from ..frame import RADIANCE
from ..report import DemoContext, Report, register_section
from ..report.registry import (
    BenchContext,
    benchmark,
    experiment_cluster,
    finish_experiment,
    markdown_table,
    register_experiment,
    section_size,
)
from ..timing import frozen_on_frames, paired_ratio, round_robin
from . import upsampling as ue

__all__ = [
    "DEFAULT_BETAS",
    "FIG4_METHODS",
    "FIG5_METHODS",
    "Fig4Result",
    "Fig5Result",
    "Fig6Result",
    "SphereInfo",
    "fig4",
    "fig5",
    "fig6",
]

Progress = Callable[[int, int], None]

CHANNEL = "indirect_specular"
#: fig. 4: the input and the three filters (weight names of glossrt.denoise.bilateral)
FIG4_METHODS = ("input", "normal", "screen", "lobe")
#: fig. 5: the paper's input / normal / lobe, plus the screen-kernel baseline
FIG5_METHODS = ("input", "normal", "screen", "lobe")
#: fig. 6: the swept parameter (beta for the lobe weight, 1 / sigma_n^2 for the normal
#: weight), 4 values per decade from 0.1 to 10^4 (the paper's beta = 20 and 1 / sigma_n^2 =
#: 100 inside)
DEFAULT_BETAS = np.logspace(-1.0, 4.0, 21)
#: roughness-map's two GGX roughness values (scenes.library.roughness_map)
SHARP_ALPHA, ROUGH_ALPHA = 0.02, 0.5


# --------------------------------------------------------------------------------------------
# helpers


def _render(scene: str, size: tuple[int, int], ref_spp: int, cluster=None):
    """(setup, 1 spp frame 0, reference frame 0, seconds); the reference rendered on
    ``cluster`` (:func:`glossrt.render.blocks.references`: None, in this process)."""
    from .. import render, scenes
    from ..render import blocks

    if ref_spp < 1:
        raise GlossrtError(f"ref_spp must be >= 1, got {ref_spp}")
    t0 = time.perf_counter()
    setup = scenes.load(scene, size=tuple(size))
    r = render.Renderer(setup)
    frame = r.render(0)
    ref = blocks.references(r, blocks.reference_job(scene, size), [0], int(ref_spp), cluster,
                            desc=f"reference {scene} {ref_spp} spp")[0]
    return setup, frame, ref, time.perf_counter() - t0


def _specular(frame, weight: str, **kwargs) -> np.ndarray:
    """The filtered ``indirect_specular`` (H, W, 3) of ``frame``."""
    from ..denoise.bilateral import bilateral

    out = np.array(bilateral(frame, weight=weight, channels=(CHANNEL,), **kwargs))
    rest = sum(frame.numpy(c) for c in RADIANCE if c != CHANNEL)
    return (out - rest).astype(np.float32)


def _mse(img: np.ndarray, ref: np.ndarray, mask: np.ndarray | None = None) -> float:
    d = (img.astype(np.float64) - ref.astype(np.float64)) ** 2
    if mask is not None:
        if not mask.any():
            raise GlossrtError("MSE over an empty mask")
        d = d[mask]
    return float(np.mean(d))


def _fmt(v: float | None) -> str:
    return "-" if v is None or not np.isfinite(v) else f"{v:.4g}"


def _table(columns: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    for row in rows:
        cells = [c if isinstance(c, str) else _fmt(c) for c in row]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _tick(progress: Progress | None, done: int, total: int) -> None:
    if progress is not None:
        progress(done, total)


# --------------------------------------------------------------------------------------------
# fig. 4: roughness map


@dataclass
class Fig4Result:
    """Tokuyoshi 2015, fig. 4 on ``roughness-map``: MSE of ``indirect_specular``.

    ``mse[method]``: whole image; ``mse_sharp`` / ``mse_rough``: over the pixels of GGX alpha
    0.02 / 0.5 (the two values of the roughness texture). ``images[name]``: (H, W, 3)
    ``indirect_specular`` of ``"input"``, each filter and ``"reference"``.
    ``screen_sigma``: mean adapted screen sigma (pixels) of ``weight="screen"`` over the
    sharp and the rough pixels (``"sharp"``, ``"rough"``)."""

    scene: str
    size: tuple[int, int]
    ref_spp: int
    params: dict[str, Any]
    mse: dict[str, float]
    mse_sharp: dict[str, float]
    mse_rough: dict[str, float]
    pixels: dict[str, int]
    screen_sigma: dict[str, float]
    images: dict[str, np.ndarray] = field(repr=False)
    seconds: dict[str, float] = field(default_factory=dict)

    def markdown(self) -> str:
        """MSE table (one row per method) in Markdown."""
        base = self.mse["input"]
        rows = [[m, self.mse[m], self.mse_sharp[m], self.mse_rough[m], self.mse[m] / base]
                for m in self.mse]
        cols = ["method", "MSE (image)", f"MSE (alpha {SHARP_ALPHA:g}, {self.pixels['sharp']} px)",
                f"MSE (alpha {ROUGH_ALPHA:g}, {self.pixels['rough']} px)", "/ input"]
        return _table(cols, rows)


def _screen_sigma_image(frame, **kwargs) -> np.ndarray:
    """Per-pixel adapted sigma of ``weight="screen"`` (H, W) with ``kwargs``' parameters."""
    from ..brdf.sg import lobe_to_sg
    from ..denoise.bilateral import (
        K_S,
        SIGMA_MIN,
        SIGMA_S,
        pixel_angle,
        screen_sigma,
        view_directions,
    )
    from ..denoise.common import split

    n = mi.Vector3f(*split(frame["normal"]))
    pos = split(frame["position"])
    alpha = split(frame["roughness"])[0]
    from ..denoise.common import beckmann_mask

    _, lam = lobe_to_sg(n, view_directions(frame, pos), alpha, beckmann_mask(frame),
                        kwargs.get("ndf_sharpness"))
    sig = screen_sigma(lam, pixel_angle(frame), kwargs.get("k_s", K_S),
                       kwargs.get("sigma_min", SIGMA_MIN), kwargs.get("sigma_s", SIGMA_S))
    return np.array(sig).reshape(frame.height, frame.width)


def _filter_all(frame, target, t_render: float, methods: list, kw: dict, progress) -> tuple:
    """The input, the reference and each filter's ``indirect_specular`` of ``frame``, and
    each one's seconds (``progress(done, total)`` after each filter)."""
    images = {"input": frame.numpy(CHANNEL), "reference": target}
    seconds = {"render": t_render}
    for k, m in enumerate(methods):
        t0 = time.perf_counter()
        images[m] = _specular(frame, m, **kw)
        seconds[m] = time.perf_counter() - t0
        _tick(progress, k + 1, len(methods))
    return images, seconds


def fig4(size: tuple[int, int] = (96, 72), ref_spp: int = 256,
         filter_kwargs: Mapping[str, Any] | None = None,
         progress: Progress | None = None, cluster=None) -> Fig4Result:
    """Tokuyoshi 2015, sec. 5.1 / fig. 4: denoise the ``indirect_specular`` of
    ``roughness-map`` frame 0 (``size`` = (W, H)) with the normal-aware, the screen-kernel and
    the lobe-aware weights at the paper's parameters (beta 20, kappa 100, sigma_n^2 0.01;
    glossrt's sigma_s 2, radius 6, k_s 1) and measure the MSE against a ``ref_spp`` reference.

    ``filter_kwargs``: extra :func:`~glossrt.denoise.bilateral` arguments for all three
    filters (e.g. ``{"ndf_sharpness": 4.0}``). ``progress(done, total)`` after each filter.
    ``cluster``: where the reference is rendered (:func:`glossrt.render.blocks.references`)."""
    kw = dict(filter_kwargs or {})
    setup, frame, ref, t_render = _render("roughness-map", size, ref_spp, cluster)
    target = ref.numpy(CHANNEL)
    alpha = frame.numpy("roughness")[..., 0]
    hit = frame.numpy("mesh_id")[..., 0] > 0
    sharp = hit & np.isclose(alpha, SHARP_ALPHA, rtol=1e-3)
    rough = hit & np.isclose(alpha, ROUGH_ALPHA, rtol=1e-3)
    methods = [m for m in FIG4_METHODS if m != "input"]
    images, seconds = _filter_all(frame, target, t_render, methods, kw, progress)
    names = ["input", *methods]
    sig = _screen_sigma_image(frame, **kw)
    return Fig4Result(
        scene="roughness-map", size=tuple(size), ref_spp=int(ref_spp), params=kw,
        mse={m: _mse(images[m], target) for m in names},
        mse_sharp={m: _mse(images[m], target, sharp) for m in names},
        mse_rough={m: _mse(images[m], target, rough) for m in names},
        pixels={"sharp": int(sharp.sum()), "rough": int(rough.sum())},
        screen_sigma={"sharp": float(sig[sharp].mean()), "rough": float(sig[rough].mean())},
        images=images, seconds=seconds)


# --------------------------------------------------------------------------------------------
# glossy spheres (figs. 5-6)


@dataclass
class SphereInfo:
    """One sphere of ``glossy-spheres``: shape id, Phong exponent, GGX alpha, ``mesh_id`` and
    its pixel count in the image."""

    shape_id: str
    phong: float
    alpha: float
    mesh_id: int
    pixels: int


def _spheres(setup, frame) -> tuple[list[SphereInfo], list[np.ndarray]]:
    """The spheres of ``glossy-spheres`` (sharpest first) and their pixel masks."""
    from ..scenes.library import GLOSSY_SPHERES_PHONG, phong_to_alpha

    mesh = frame.numpy("mesh_id")[..., 0]
    infos, masks = [], []
    for s in GLOSSY_SPHERES_PHONG:
        sid = f"sphere_s{s:g}"
        if sid not in setup.shape_index:
            raise GlossrtError(f"{setup.name}: no shape {sid!r} (has {sorted(setup.shape_index)})")
        mid = setup.shape_index[sid]
        mask = mesh == mid
        if not mask.any():
            raise GlossrtError(f"{setup.name}: sphere {sid!r} covers no pixel at {frame.size}")
        infos.append(SphereInfo(sid, float(s), phong_to_alpha(s), int(mid), int(mask.sum())))
        masks.append(mask)
    return infos, masks


@dataclass
class Fig5Result:
    """Tokuyoshi 2015, fig. 5 on ``glossy-spheres``: one parameter set for all spheres.

    ``mse[method][k]``: MSE of ``indirect_specular`` over sphere ``k`` (``spheres[k]``,
    sharpest first); ``images``: (H, W, 3) ``indirect_specular`` of the input, each filter and
    the reference; ``masks[k]``: sphere ``k``'s pixels."""

    scene: str
    size: tuple[int, int]
    ref_spp: int
    params: dict[str, Any]
    spheres: list[SphereInfo]
    mse: dict[str, list[float]]
    images: dict[str, np.ndarray] = field(repr=False)
    masks: list[np.ndarray] = field(repr=False)
    seconds: dict[str, float] = field(default_factory=dict)

    def markdown(self) -> str:
        """MSE per sphere (columns) and method (rows), with the ratio to the input."""
        cols = ["method"]
        for s in self.spheres:
            cols += [f"MSE s={s.phong:g} (alpha {s.alpha:.3f})", "/ input"]
        rows = []
        for m, vals in self.mse.items():
            row: list[Any] = [m]
            for k, v in enumerate(vals):
                row += [v, v / self.mse["input"][k]]
            rows.append(row)
        return _table(cols, rows)


def fig5(size: tuple[int, int] = (96, 72), ref_spp: int = 256,
         filter_kwargs: Mapping[str, Any] | None = None,
         progress: Progress | None = None, cluster=None) -> Fig5Result:
    """Tokuyoshi 2015, sec. 5.1 / fig. 5: filter ``glossy-spheres`` frame 0 with one
    parameter set (the paper's: beta 20, kappa 100, sigma_n^2 0.01; glossrt's screen kernel)
    and measure the ``indirect_specular`` MSE on each sphere (Phong exponent 1000, 100, 10).

    ``filter_kwargs``: extra :func:`~glossrt.denoise.bilateral` arguments for every filter.
    ``progress(done, total)`` after each filter. ``cluster``: where the reference is
    rendered (:func:`glossrt.render.blocks.references`)."""
    kw = dict(filter_kwargs or {})
    setup, frame, ref, t_render = _render("glossy-spheres", size, ref_spp, cluster)
    spheres, masks = _spheres(setup, frame)
    target = ref.numpy(CHANNEL)
    methods = [m for m in FIG5_METHODS if m != "input"]
    images, seconds = _filter_all(frame, target, t_render, methods, kw, progress)
    mse = {m: [_mse(images[m], target, mask) for mask in masks] for m in ["input", *methods]}
    return Fig5Result(scene="glossy-spheres", size=tuple(size), ref_spp=int(ref_spp),
                      params=kw, spheres=spheres, mse=mse, images=images, masks=masks,
                      seconds=seconds)


@dataclass
class Fig6Result:
    """Tokuyoshi 2015, fig. 6 on ``glossy-spheres``: MSE against the weight's parameter.

    ``params``: the swept values (``beta`` for ``"lobe"``, ``1 / sigma_n^2`` for
    ``"normal"``); ``curves[method]``: (n_spheres, n_params) MSE over each sphere (sharpest
    first); ``input_mse[k]``: the unfiltered MSE of sphere ``k``. Derived (see the
    methods): the optimum per sphere (the argmin of its recorded curve), whether it lies on
    the end of the sweep, the spread of the optima in decades (``log10(max / min)`` over the
    spheres), the mean over the spheres (the paper's purple line) and its optimum."""

    scene: str
    size: tuple[int, int]
    ref_spp: int
    filter_kwargs: dict[str, Any]
    spheres: list[SphereInfo]
    params: np.ndarray
    curves: dict[str, np.ndarray]
    input_mse: list[float]
    seconds: dict[str, float] = field(default_factory=dict)

    #: the swept parameter's name per method
    LABELS = {"normal": "1 / sigma_n^2", "lobe": "beta"}

    def optimum_index(self, method: str) -> np.ndarray:
        """Index into :attr:`params` of each sphere's lowest MSE."""
        return np.argmin(self.curves[method], axis=1)

    def optimum(self, method: str) -> np.ndarray:
        """Each sphere's optimal parameter value."""
        return self.params[self.optimum_index(method)]

    def optimum_mse(self, method: str) -> np.ndarray:
        """Each sphere's MSE at its optimum."""
        c = self.curves[method]
        return c[np.arange(c.shape[0]), self.optimum_index(method)]

    def spread(self, method: str) -> float:
        """How far the spheres' optima lie apart: ``log10(max / min)`` (decades). A lower
        bound when an optimum lies on the end of the sweep (:meth:`on_boundary`)."""
        opt = self.optimum(method)
        return float(math.log10(opt.max() / opt.min()))

    def on_boundary(self, method: str) -> np.ndarray:
        """Per sphere: whether its optimum is the first or last swept value (the true
        optimum may lie beyond the sweep)."""
        i = self.optimum_index(method)
        n = self.params.size
        return (n > 1) & ((i == 0) | (i == n - 1))

    def near_optimal(self, method: str, tol: float = 0.05) -> list[tuple[float, float]]:
        """Per sphere: the smallest and largest swept value whose MSE is within ``1 + tol``
        of the sphere's minimum (how flat the optimum is)."""
        out = []
        for k, c in enumerate(self.curves[method]):
            ok = np.nonzero(c <= (1.0 + tol) * self.optimum_mse(method)[k])[0]
            out.append((float(self.params[ok.min()]), float(self.params[ok.max()])))
        return out

    def mean_curve(self, method: str) -> np.ndarray:
        """MSE averaged over the spheres, per parameter value (the paper's purple line)."""
        return self.curves[method].mean(axis=0)

    def mean_optimum(self, method: str) -> tuple[float, float]:
        """``(parameter, mean MSE)`` at the minimum of :meth:`mean_curve`: the best single
        parameter for all spheres."""
        i = int(np.argmin(self.mean_curve(method)))
        return float(self.params[i]), float(self.mean_curve(method)[i])

    def markdown(self) -> str:
        """Optima per sphere and method, spread of the optima, best common parameter."""
        cols = ["method", "parameter"]
        for s in self.spheres:
            cols += [f"s={s.phong:g}: optimum", "MSE"]
        cols += ["spread (decades)", "common optimum", "mean MSE there"]
        rows = []
        n = self.params.size
        for m in self.curves:
            opt, omse = self.optimum(m), self.optimum_mse(m)
            edge, idx = self.on_boundary(m), self.optimum_index(m)
            row: list[Any] = [m, self.LABELS.get(m, "?")]
            for k in range(len(self.spheres)):
                cell = _fmt(float(opt[k]))
                if edge[k]:  # the sweep's end: the optimum may lie beyond
                    cell = ("<= " if idx[k] == 0 and n > 1 else ">= ") + cell
                row += [cell, float(omse[k])]
            p, v = self.mean_optimum(m)
            spread = _fmt(self.spread(m))
            row += [(">= " + spread) if edge.any() else spread, p, v]
            rows.append(row)
        inp: list[Any] = ["input", "-"]
        for v in self.input_mse:
            inp += ["-", v]
        inp += ["-", "-", float(np.mean(self.input_mse))]
        rows.append(inp)
        return _table(cols, rows)

    def plot(self, path: str, logy: bool = False) -> str:
        """Save a figure like the paper's fig. 6: one panel per method (normal, lobe), MSE
        against the parameter (log x), one line per sphere, the mean over the spheres in
        purple, optima marked. Returns ``path``."""
        from ..report.figures import subplots

        methods = [m for m in ("normal", "lobe") if m in self.curves]
        fig, axes = subplots(1, len(methods), (5.2 * len(methods), 4.0), sharey=True)
        colours = ["tab:blue", "tab:orange", "tab:green", "tab:red", "tab:brown"]
        for ax, m in zip(axes[0], methods, strict=True):
            c = self.curves[m]
            for k, s in enumerate(self.spheres):
                col = colours[k % len(colours)]
                ax.plot(self.params, c[k], "-", color=col, lw=1.5,
                        label=f"Phong {s.phong:g} (alpha {s.alpha:.3f})")
                i = self.optimum_index(m)[k]
                ax.plot(self.params[i], c[k, i], "o", color=col, ms=7, mfc="none", mew=2)
            mean = self.mean_curve(m)
            p, v = self.mean_optimum(m)
            ax.plot(self.params, mean, "-", color="purple", lw=2.5, label="mean")
            ax.plot(p, v, "D", color="purple", ms=7)
            ax.set_xscale("log")
            if logy:
                ax.set_yscale("log")
            ax.set_xlabel(self.LABELS.get(m, "parameter"))
            bound = ">= " if self.on_boundary(m).any() else ""
            ax.set_title(f"{m}-aware: optima spread {bound}{self.spread(m):.2f} decades")
            ax.grid(True, which="both", alpha=0.3)
        axes[0][0].set_ylabel("MSE (indirect specular, per sphere)")
        axes[0][-1].legend(fontsize=8)
        fig.suptitle(f"{self.scene} {self.size[0]}x{self.size[1]}, reference {self.ref_spp} spp "
                     "(cf. Tokuyoshi 2015, fig. 6)", fontsize=10)
        fig.tight_layout()
        fig.savefig(path, dpi=110)
        return path


def fig6(size: tuple[int, int] = (96, 72), ref_spp: int = 256,
         betas: Sequence[float] | np.ndarray = DEFAULT_BETAS,
         filter_kwargs: Mapping[str, Any] | None = None,
         progress: Progress | None = None, cluster=None) -> Fig6Result:
    """Tokuyoshi 2015, sec. 5.2 / fig. 6: on ``glossy-spheres`` frame 0, the MSE of each
    sphere's ``indirect_specular`` for the lobe weight at every ``beta`` in ``betas`` and for
    the normal weight at every ``1 / sigma_n^2`` in ``betas`` (the same values; end of sec.
    4.2: ``G(n_i, n_j, 1 / sigma_n^2)`` is the lobe weight of a diffuse lobe). The other
    parameters are the paper's (kappa 100) and glossrt's (sigma_s 2, radius 6), or
    ``filter_kwargs``. The scene is rendered once; ``progress(done, total)`` after each
    filter run. ``cluster``: where the reference is rendered
    (:func:`glossrt.render.blocks.references`)."""
    params = np.asarray(betas, dtype=np.float64).ravel()
    if params.size < 1 or not np.all(np.isfinite(params)) or np.any(params <= 0):
        raise GlossrtError("fig6: betas must be positive finite values (at least one)")
    kw = dict(filter_kwargs or {})
    for swept in ("beta", "sigma_n2"):
        if swept in kw:
            raise GlossrtError(f"fig6: {swept!r} is swept; do not pass it in filter_kwargs")
    setup, frame, ref, t_render = _render("glossy-spheres", size, ref_spp, cluster)
    spheres, masks = _spheres(setup, frame)
    target = ref.numpy(CHANNEL)
    curves = {m: np.zeros((len(spheres), params.size)) for m in ("normal", "lobe")}
    seconds = {"render": t_render}
    total, done = 2 * params.size, 0
    for m in ("normal", "lobe"):
        t0 = time.perf_counter()
        for j, p in enumerate(params):
            # opaque: one compilation of the filter's kernels for the whole sweep
            if m == "lobe":
                extra = {"beta": dr.opaque(mi.Float, float(p))}
            else:
                extra = {"sigma_n2": dr.opaque(mi.Float, float(1.0 / p))}
            img = _specular(frame, m, **kw, **extra)
            curves[m][:, j] = [_mse(img, target, mask) for mask in masks]
            done += 1
            _tick(progress, done, total)
        seconds[m] = time.perf_counter() - t0
    return Fig6Result(scene="glossy-spheres", size=tuple(size), ref_spp=int(ref_spp),
                      filter_kwargs=kw, spheres=spheres, params=params, curves=curves,
                      input_mse=[_mse(frame.numpy(CHANNEL), target, mask) for mask in masks],
                      seconds=seconds)


@register_section("lobes", order=50)
def section_lobes(ctx: DemoContext, report: Report) -> None:
    from ..report.figures import plot_fig3

    t0 = time.perf_counter()
    # 96x72 at 256 spp for the demo's 160x120; smaller when the demo itself is (tests)
    _, size = section_size(ctx, (96, 72), 4, (16, 12))
    spp = min(256, int(ctx.references[0].meta.get("spp", 256))) if ctx.references else 256
    s = report.section(
        "Specular-lobe-aware filtering and upsampling",
        "Tokuyoshi 2015: cross-bilateral filtering of the demodulated indirect light with the "
        "normal-aware weight, glossrt's sharpness-adapted screen kernel (the fig. 4(c) "
        "baseline) and the lobe-aware weight (beta 20, kappa 100, sigma_n^2 0.01; screen "
        f"kernel sigma_s 2 px, radius 6), at {size[0]}x{size[1]} against {spp} spp "
        "references; MSE of the indirect specular component. See docs/RESULTS.md for the "
        "full discussion; nothing is tuned to match the paper.")
    s.saved_figure("fig3.png", plot_fig3, "fig. 3 analogue: the lobe weight vs the angle "
                   "between lobe axes, exact (eq. 6) and approximate (eq. 7)")
    f4 = fig4(size=size, ref_spp=spp)
    markdown_table(s, f4.markdown(), "fig. 4 analogue: roughness-map, indirect specular")
    s.images_row([(k, v) for k, v in f4.images.items()], name="fig4")
    f5 = fig5(size=size, ref_spp=spp)
    markdown_table(s, f5.markdown(), "fig. 5 analogue: glossy-spheres, one parameter set")
    s.images_row([(k, v) for k, v in f5.images.items()], name="fig5")
    f6 = fig6(size=size, ref_spp=spp)
    markdown_table(s, f6.markdown(), "fig. 6 analogue: optima per sphere")
    s.saved_figure("fig6.png", lambda p: f6.plot(str(p)), "fig. 6 analogue: MSE vs beta "
                   "(lobe) and vs 1/sigma_n^2 (normal), one line per Phong exponent")
    up = ue.upsampling(size=size, ref_spp=spp, low_spp=spp)
    markdown_table(s, up.markdown(), "joint bilateral upsampling of converged 1/2 and 1/4 "
                   "resolution indirect light (roughness-map); adaptive re-sampling where the "
                   f"normalised weight sum < {up.threshold}")
    s.images_row([(k, v) for k, v in up.images.items()], name="upsampling")
    st = ue.spatio_temporal(size=size, frames=8, ref_spp=spp, ref_frames=(3, 7))
    markdown_table(s, st.markdown(), "spatial vs spatio-temporal upsampling (1/2, jittered "
                   "1 spp low-resolution frames, animated glossy-cornell), indirect light MSE")
    ctx.timings["specular-lobe section (figs. 3-6, upsampling)"] = time.perf_counter() - t0


@benchmark("lobe-weights", order=30)
def bench_lobe_weights(ctx: BenchContext) -> dict:
    """Cost of Tokuyoshi 2015's lobe weight over the normal weight at the same footprint,
    interleaved in one run on ``roughness-map``: the cross-bilateral filter (13x13 window) and
    joint bilateral upsampling from 1/2 and 1/4 resolution (4x4 samples), each for the
    specular channel alone (``spec``: the weight function is swapped) and for both indirect
    channels (``both``: the diffuse one keeps the normal weight, so lobe mode computes both
    weights); each traced anew per call and frozen (``frozen_on_frames``: kernels replayed,
    no Python tracing, the real-time path). Target: lobe / normal <= 1.15."""
    from .. import render, scenes
    from ..denoise import bilateral, upsample

    w, h = ctx.size
    full = render.Renderer(scenes.load("roughness-map", size=(w, h))).render(0)
    lows = {f: render.Renderer(scenes.load("roughness-map", size=(w // f, h // f))).render(0)
            for f in (2, 4) if w % f == 0 and h % f == 0}
    sets = {"spec": ("indirect_specular",), "both": ("indirect_diffuse", "indirect_specular")}
    cases = {}
    for cname, ch in sets.items():
        for weight in ("normal", "lobe"):
            fns = {"bilateral": (lambda fr, wt=weight, ch=ch: bilateral(
                fr, weight=wt, channels=ch), (full,))}
            for f, low in lows.items():
                fns[f"upsample-1/{f}"] = (lambda fr, lo, wt=weight, ch=ch: upsample(
                    fr, lo, weight=wt, channels=ch), (full, low))
            for op, (fn, frames) in fns.items():
                cases[f"{op}-{cname}-traced-{weight}"] = (
                    lambda fn=fn, frames=frames: dr.eval(fn(*frames)))
                cases[f"{op}-{cname}-frozen-{weight}"] = frozen_on_frames(fn, *frames)
    times = round_robin(cases, 2, ctx.turns, ctx.min_sample)
    med = {k: statistics.median(v) for k, v in times.items()}
    ratios = {k.replace("-normal", ""): paired_ratio(times[k.replace("-normal", "-lobe")], v)
              for k, v in times.items() if k.endswith("-normal")}
    return {"scene": "roughness-map", "size": [w, h], "seconds": med,
            "ratio_lobe_vs_normal": ratios, "target_ratio": 1.15,
            "repeats": ctx.turns}


@register_experiment("lobes", "Tokuyoshi 2015 figs. 4-6 and upsampling (uses --size and "
                     "--spp)", order=20)
def run_experiment(out, size, args) -> int:
    """Tokuyoshi 2015 figs. 4-6 analogues and the upsampling measurements (RESULTS.md)."""
    spp, cluster = args.spp, experiment_cluster(args)
    if size[0] % 4 or size[1] % 4:
        raise GlossrtError(f"--size must be a multiple of 4 in both axes for the 1/4 "
                           f"upsampling, got {size[0]}x{size[1]}")
    parts = []
    for title, fn in (("fig. 4 analogue (roughness-map)", fig4),
                      ("fig. 5 analogue (glossy-spheres)", fig5),
                      ("fig. 6 analogue (glossy-spheres)", fig6)):
        print(f"{title} ...", flush=True)
        res = fn(size=size, ref_spp=spp, cluster=cluster)
        parts.append(f"## {title}\n\n{res.markdown()}")
        if fn is fig6:
            res.plot(str(out / "fig6.png"))
    print("upsampling ...", flush=True)
    up = ue.upsampling(size=size, ref_spp=spp, low_spp=spp, cluster=cluster)
    parts.append(f"## upsampling (roughness-map)\n\n{up.markdown()}")
    print("spatio-temporal upsampling ...", flush=True)
    st = ue.spatio_temporal(size=size, ref_spp=spp, cluster=cluster)
    parts.append(f"## spatio-temporal upsampling (glossy-cornell)\n\n{st.markdown()}")
    return finish_experiment(out, "lobes", "\n\n".join(parts), "fig6.png")
