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
    experiment_scale,
    finish_experiment,
    markdown_table,
    paper_value,
    register_experiment,
    section_size,
)
from ..timing import frozen_on_frames, paired_ratio, round_robin
from . import upsampling as ue

__all__ = [
    "DEFAULT_BETAS",
    "PAPER_INPUT_SPP",
    "PAPER_K",
    "PAPER_REF_SPP",
    "PAPER_SIZE",
    "BiasVariance",
    "ErrorSplit",
    "PaperStudy",
    "Rendered",
    "claims",
    "fig4_paper",
    "fig5_paper",
    "load_paper_json",
    "paper_json",
    "noisy_input",
    "render_scene",
    "roughness_band",
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


@dataclass
class Rendered:
    """One scene's frame 0 as the experiments use it: ``setup``, its ``renderer``, the 1 spp
    ``frame`` (seed 0), the ``reference`` of ``ref_spp`` samples and the render's ``seconds``.
    Pass it to another experiment on the same scene to render the reference once."""

    scene: str
    size: tuple[int, int]
    ref_spp: int
    setup: Any
    renderer: Any
    frame: Any
    reference: Any
    seconds: float


def render_scene(scene: str, size: tuple[int, int], ref_spp: int, cluster=None,
                 cache=None) -> Rendered:
    """Render ``scene``'s frame 0 at ``size``: the 1 spp frame and the reference of
    ``ref_spp`` samples, on ``cluster`` (:func:`glossrt.render.blocks.references`: None, in
    this process), kept in the folder ``cache`` (None: not kept) and read back from it."""
    from .. import render, scenes
    from ..render import blocks

    if ref_spp < 1:
        raise GlossrtError(f"ref_spp must be >= 1, got {ref_spp}")
    t0 = time.perf_counter()
    setup = scenes.load(scene, size=tuple(size))
    r = render.Renderer(setup)
    frame = r.render(0)
    ref = blocks.references(r, blocks.reference_job(scene, size), [0], int(ref_spp), cluster,
                            desc=f"reference {scene} {ref_spp} spp", cache=cache)[0]
    return Rendered(scene, tuple(size), int(ref_spp), setup, r, frame, ref,
                    time.perf_counter() - t0)


def _reuse(rendered: Rendered | None, scene: str, size, ref_spp: int, cluster,
           cache=None) -> Rendered:
    """``rendered`` when it is ``scene`` at ``size`` and ``ref_spp``, else a new render."""
    if rendered is None:
        return render_scene(scene, size, ref_spp, cluster, cache=cache)
    want = (scene, tuple(size), int(ref_spp))
    if (rendered.scene, tuple(rendered.size), rendered.ref_spp) != want:
        raise GlossrtError(f"rendered is {rendered.scene} {rendered.size} {rendered.ref_spp} "
                           f"spp, wanted {want[0]} {want[1]} {want[2]} spp")
    return rendered


def _render(scene: str, size: tuple[int, int], ref_spp: int, cluster=None):
    """(setup, 1 spp frame 0, reference frame 0, seconds): :func:`render_scene`'s."""
    r = render_scene(scene, size, ref_spp, cluster)
    return r.setup, r.frame, r.reference, r.seconds


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
    #: how many independent inputs each curve is the mean MSE over, and their spp
    inputs: int = 1
    input_spp: int = 1

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
         progress: Progress | None = None, cluster=None, inputs: int = 1,
         input_spp: int = 1, rendered: Rendered | None = None) -> Fig6Result:
    """Tokuyoshi 2015, sec. 5.2 / fig. 6: on ``glossy-spheres`` frame 0, the MSE of each
    sphere's ``indirect_specular`` for the lobe weight at every ``beta`` in ``betas`` and for
    the normal weight at every ``1 / sigma_n^2`` in ``betas`` (the same values; end of sec.
    4.2: ``G(n_i, n_j, 1 / sigma_n^2)`` is the lobe weight of a diffuse lobe). The other
    parameters are the paper's (kappa 100) and glossrt's (sigma_s 2, radius 6), or
    ``filter_kwargs``. The scene is rendered once; ``progress(done, total)`` after each
    filter run. ``cluster``: where the reference is rendered
    (:func:`glossrt.render.blocks.references`).

    ``inputs`` / ``input_spp``: the curves are the mean MSE over ``inputs`` independent
    inputs of ``input_spp`` samples (seeds :data:`INPUT_SEED0` + i, :func:`noisy_input`);
    the default 1 / 1 is the seed-0 frame of the quick runs. ``rendered``: a
    :func:`render_scene` of ``glossy-spheres`` at ``size`` and ``ref_spp`` to reuse."""
    params = np.asarray(betas, dtype=np.float64).ravel()
    if params.size < 1 or not np.all(np.isfinite(params)) or np.any(params <= 0):
        raise GlossrtError("fig6: betas must be positive finite values (at least one)")
    kw = dict(filter_kwargs or {})
    for swept in ("beta", "sigma_n2"):
        if swept in kw:
            raise GlossrtError(f"fig6: {swept!r} is swept; do not pass it in filter_kwargs")
    _check_counts(inputs=inputs, input_spp=input_spp)
    rd = _reuse(rendered, "glossy-spheres", size, ref_spp, cluster)
    spheres, masks = _spheres(rd.setup, rd.frame)
    target = rd.reference.numpy(CHANNEL)
    t0 = time.perf_counter()
    if inputs == 1 and input_spp == 1:
        frames = [rd.frame]
    else:
        frames = [noisy_input(rd.renderer, input_spp, INPUT_SEED0 + i) for i in range(inputs)]
    seconds = {"render": rd.seconds if rendered is None else 0.0,
               "inputs": time.perf_counter() - t0}
    curves = {m: np.zeros((len(spheres), params.size)) for m in ("normal", "lobe")}
    total, done = 2 * params.size * len(frames), 0
    for m in ("normal", "lobe"):
        t0 = time.perf_counter()
        for j, p in enumerate(params):
            # opaque: one compilation of the filter's kernels for the whole sweep
            if m == "lobe":
                extra = {"beta": dr.opaque(mi.Float, float(p))}
            else:
                extra = {"sigma_n2": dr.opaque(mi.Float, float(1.0 / p))}
            for frame in frames:
                img = _specular(frame, m, **kw, **extra)
                curves[m][:, j] += [_mse(img, target, mask) / len(frames) for mask in masks]
                done += 1
                _tick(progress, done, total)
        seconds[m] = time.perf_counter() - t0
    input_mse = [float(np.mean([_mse(f.numpy(CHANNEL), target, mask) for f in frames]))
                 for mask in masks]
    return Fig6Result(scene="glossy-spheres", size=tuple(size), ref_spp=int(ref_spp),
                      filter_kwargs=kw, spheres=spheres, params=params, curves=curves,
                      input_mse=input_mse, seconds=seconds, inputs=len(frames),
                      input_spp=int(input_spp))


# --------------------------------------------------------------------------------------------
# paper scale (issue 28): bias / variance over K independent inputs, band vs interiors


#: Tokuyoshi 2015, fig. 5's caption: 640x360 (the paper writes 360 x 640)
PAPER_SIZE = (640, 360)
#: issue 28: references of at least 4096 spp
PAPER_REF_SPP = 4096
#: issue 28: the input at 1 and at 4 spp
PAPER_INPUT_SPP = (1, 4)
#: independent inputs per noise level (glossrt's choice: the paper filters one input)
PAPER_K = 16
#: independent inputs fig. 6's curves are averaged over at paper scale (glossrt's choice)
PAPER_FIG6_INPUTS = 4
#: seed of the first independent input (the quick runs' one input is seed 0)
INPUT_SEED0 = 1
#: relative roughness difference that counts as a step (:func:`roughness_band`)
STEP_TOL = 1e-3


def _check_counts(**counts: int) -> None:
    for name, v in counts.items():
        if int(v) < 1:
            raise GlossrtError(f"{name} must be >= 1, got {v}")


def noisy_input(renderer, spp: int, seed: int):
    """An independent noisy frame 0 of ``spp`` samples per pixel: :meth:`Renderer.render`
    (1 spp, the real-time input) or :meth:`Renderer.render_reference` (``spp`` > 1: ``spp``
    independent 1 spp estimates averaged, the same pixel-centre primary hits) with ``seed``
    (distinct seeds: independent noise; the references use seed 0 with their own salt)."""
    _check_counts(spp=spp)
    if spp == 1:
        return renderer.render(0, seed=int(seed))
    return renderer.render_reference(0, int(spp), seed=int(seed))


def roughness_band(alpha: np.ndarray, hit: np.ndarray, radius: int,
                   tol: float = STEP_TOL) -> np.ndarray:
    """The band around roughness steps: the hit pixels whose filter window (the (2 radius +
    1)^2 pixels the cross-bilateral filter reads) holds hit pixels of different roughness
    (``max - min > tol * max`` over the window's hit pixels of the G-buffer's ``alpha``).
    The other hit pixels are the cells' interiors: their whole window has one roughness."""
    if radius < 0:
        raise GlossrtError(f"radius must be >= 0, got {radius}")
    alpha = np.asarray(alpha, dtype=np.float64)
    hit = np.asarray(hit, dtype=bool)
    h, w = alpha.shape
    pad = np.pad(np.where(hit, alpha, np.nan), radius, constant_values=np.nan)
    lo = np.full((h, w), np.inf)
    hi = np.full((h, w), -np.inf)
    for dy in range(2 * radius + 1):
        for dx in range(2 * radius + 1):
            win = pad[dy:dy + h, dx:dx + w]
            lo, hi = np.fmin(lo, win), np.fmax(hi, win)  # fmin / fmax skip the NaNs
    with np.errstate(invalid="ignore"):
        return hit & (hi - lo > tol * np.abs(hi))


@dataclass
class ErrorSplit:
    """MSE of one method over one region, split over K independent inputs (x_k, reference
    r, per pixel and RGB channel, then the mean over the region's pixels and channels):

    * ``variance`` = mean of s^2 = sum_k (x_k - mean_k x)^2 / (K - 1) (unbiased);
    * ``bias2`` = mean of (mean_k x - r)^2 - s^2 / K (unbiased for (E[x] - r)^2: the mean
      over K inputs still holds variance / K);
    * ``mse`` = ``bias2`` + ``variance`` = the mean over k of each input's MSE (an identity);
    * ``per_input``: each input's MSE (for paired comparisons between methods).

    r is itself a ``ref_spp`` estimate: its variance (about the 1 spp variance / ref_spp,
    :attr:`PaperStudy.ref_noise`) is inside ``bias2``."""

    mse: float
    bias2: float
    variance: float
    per_input: list[float]


class BiasVariance:
    """Accumulates K filtered inputs of one method against ``reference`` (H, W, 3) and
    splits their error per region (``masks``: name -> (H, W) bool, or None for all pixels)
    into :class:`ErrorSplit`. Sums in float64 of d = x - r and d^2 per pixel."""

    def __init__(self, reference: np.ndarray, masks: Mapping[str, np.ndarray | None]):
        self.ref = np.asarray(reference, dtype=np.float64)
        self.masks = {k: (None if m is None else np.asarray(m, dtype=bool))
                      for k, m in masks.items()}
        for k, m in self.masks.items():
            if m is not None and not m.any():
                raise GlossrtError(f"region {k!r} has no pixel")
        self.s1 = np.zeros_like(self.ref)
        self.s2 = np.zeros_like(self.ref)
        self.k = 0
        self.per_input: dict[str, list[float]] = {k: [] for k in self.masks}

    def add(self, image: np.ndarray) -> None:
        d = np.asarray(image, dtype=np.float64) - self.ref
        if d.shape != self.ref.shape:
            raise GlossrtError(f"image shape {d.shape} is not the reference's {self.ref.shape}")
        self.s1 += d
        self.s2 += d * d
        self.k += 1
        for name, m in self.masks.items():
            self.per_input[name].append(float(np.mean(d * d if m is None else (d * d)[m])))

    def split(self, region: str) -> ErrorSplit:
        if self.k < 2:
            raise GlossrtError(f"a bias / variance split needs K >= 2 inputs, got {self.k}")
        k, m = self.k, self.masks[region]
        mean_d = self.s1 / k
        var = np.maximum((self.s2 - self.s1 * mean_d) / (k - 1), 0.0)
        bias2 = mean_d * mean_d - var / k
        sel = (lambda a: a) if m is None else (lambda a: a[m])
        return ErrorSplit(mse=float(np.mean(sel(self.s2)) / k), bias2=float(np.mean(sel(bias2))),
                          variance=float(np.mean(sel(var))),
                          per_input=list(self.per_input[region]))


@dataclass
class PaperStudy:
    """One scene at paper scale: ``split[spp][method][region]`` (:class:`ErrorSplit`) for the
    input and each filter over ``k`` independent inputs (seeds ``seeds``) per noise level
    ``spp``; ``pixels[region]``; ``ref_noise[region]``: the reference's own variance, about
    the 1 spp variance / ``ref_spp`` (from the lowest input spp's measured variance), a floor
    under every ``bias2``. ``images``: the reference and, per spp, the first input and its
    filtered versions (``"{method} {spp} spp"``); ``samples[(spp, method)]``: all K filtered
    images (K, H, W, 3) when asked for (tests). A region without pixels is left out of
    ``regions``."""

    scene: str
    size: tuple[int, int]
    ref_spp: int
    input_spp: tuple[int, ...]
    k: int
    seeds: tuple[int, ...]
    params: dict[str, Any]
    regions: list[str]
    pixels: dict[str, int]
    split: dict[int, dict[str, dict[str, ErrorSplit]]]
    ref_noise: dict[str, float]
    images: dict[str, np.ndarray] = field(repr=False)
    samples: dict[tuple[int, str], np.ndarray] = field(repr=False, default_factory=dict)
    seconds: dict[str, float] = field(default_factory=dict)

    def compare(self, spp: int, a: str, b: str, region: str) -> tuple[float, float, float]:
        """``(MSE a / MSE b, mean paired difference a - b, its standard error)`` over the K
        inputs (both methods filter the same K inputs)."""
        ea, eb = self.split[spp][a][region], self.split[spp][b][region]
        d = np.asarray(ea.per_input) - np.asarray(eb.per_input)
        se = float(np.std(d, ddof=1) / math.sqrt(d.size)) if d.size > 1 else math.inf
        return ea.mse / eb.mse, float(d.mean()), se

    def markdown(self) -> str:
        cols = ["input spp", "method"]
        for reg in self.regions:
            cols += [f"{reg} ({self.pixels[reg]} px): MSE", "bias^2", "variance"]
        cols += [f"/ normal ({self.regions[0]})"]
        rows = []
        for spp, per in self.split.items():
            for m, regs in per.items():
                row: list[Any] = [str(spp), m]
                for reg in self.regions:
                    e = regs[reg]
                    row += [e.mse, e.bias2, e.variance]
                row.append(regs[self.regions[0]].mse / per["normal"][self.regions[0]].mse
                           if "normal" in per else None)
                rows.append(row)
        noise = ", ".join(f"{r} {_fmt(v)}" for r, v in self.ref_noise.items())
        return (f"{self.scene} {self.size[0]}x{self.size[1]}, reference {self.ref_spp} spp, "
                f"K = {self.k} independent inputs per noise level (seeds {self.seeds[0]}.."
                f"{self.seeds[-1]}), filters {self.params or 'at the defaults'}. MSE = bias^2 + "
                "variance; variance: unbiased over K (1/(K-1)); bias^2: (mean over K - "
                "reference)^2 - variance/K. The reference's own noise (inside bias^2, about "
                f"var(1 spp) / {self.ref_spp}): {noise}.\n\n" + _table(cols, rows))


def _study(scene: str, size, ref_spp: int, input_spp: Sequence[int], k: int,
           regions: Callable[[Rendered], dict[str, np.ndarray | None]], methods: Sequence[str],
           kw: dict, progress: Progress | None, cluster, seeds, keep_samples: bool,
           rendered: Rendered | None, cache=None) -> PaperStudy:
    input_spp = tuple(int(s) for s in input_spp)
    _check_counts(k=k, **{f"input_spp[{i}]": s for i, s in enumerate(input_spp)})
    seeds = tuple(range(INPUT_SEED0, INPUT_SEED0 + int(k))) if seeds is None else \
        tuple(int(s) for s in seeds)
    if len(seeds) < 2 or not input_spp:
        raise GlossrtError(f"need >= 2 inputs per noise level and >= 1 noise level, got "
                           f"{len(seeds)} seeds and input_spp {input_spp}")
    rd = _reuse(rendered, scene, size, ref_spp, cluster, cache)
    target = rd.reference.numpy(CHANNEL)
    # a region without pixels (no interior at a tiny size and a wide window) is left out
    masks = {k_: m for k_, m in regions(rd).items() if m is None or m.any()}
    filters = [m for m in methods if m != "input"]
    split: dict[int, dict[str, dict[str, ErrorSplit]]] = {}
    images: dict[str, np.ndarray] = {"reference": target}
    samples: dict[tuple[int, str], np.ndarray] = {}
    seconds = {"render": rd.seconds if rendered is None else 0.0, "inputs": 0.0,
               **{m: 0.0 for m in filters}}
    total, done = len(input_spp) * len(seeds) * len(filters), 0
    for spp in input_spp:
        acc = {m: BiasVariance(target, masks) for m in ["input", *filters]}
        kept: dict[str, list] = {m: [] for m in acc}
        for j, seed in enumerate(seeds):
            t0 = time.perf_counter()
            frame = noisy_input(rd.renderer, spp, seed)
            seconds["inputs"] += time.perf_counter() - t0
            imgs = {"input": frame.numpy(CHANNEL)}
            for m in filters:
                t0 = time.perf_counter()
                imgs[m] = _specular(frame, m, **kw)
                seconds[m] += time.perf_counter() - t0
                done += 1
                _tick(progress, done, total)
            for m, img in imgs.items():
                acc[m].add(img)
                if keep_samples:
                    kept[m].append(img)
                if j == 0:
                    images[f"{m} {spp} spp"] = img
        split[spp] = {m: {reg: a.split(reg) for reg in masks} for m, a in acc.items()}
        if keep_samples:
            samples.update({(spp, m): np.stack(v) for m, v in kept.items()})
    lo = min(input_spp)
    ref_noise = {reg: split[lo]["input"][reg].variance * lo / rd.ref_spp for reg in masks}
    return PaperStudy(scene=scene, size=tuple(size), ref_spp=int(ref_spp),
                      input_spp=input_spp, k=len(seeds), seeds=seeds, params=dict(kw),
                      regions=list(masks),
                      pixels={r: int(rd.frame.width * rd.frame.height) if m is None
                              else int(m.sum()) for r, m in masks.items()},
                      split=split, ref_noise=ref_noise, images=images, samples=samples,
                      seconds=seconds)


def fig4_paper(size: tuple[int, int] = PAPER_SIZE, ref_spp: int = PAPER_REF_SPP,
               input_spp: Sequence[int] = PAPER_INPUT_SPP, k: int = PAPER_K,
               filter_kwargs: Mapping[str, Any] | None = None,
               progress: Progress | None = None, cluster=None, seeds=None,
               keep_samples: bool = False, rendered: Rendered | None = None,
               cache=None) -> PaperStudy:
    """Tokuyoshi 2015, fig. 4 at paper scale (issue 28): ``roughness-map`` frame 0 at
    ``size``, the reference of ``ref_spp`` samples rendered once (on ``cluster``; kept in the
    folder ``cache`` and read back from it), ``k``
    independent inputs (seeds ``INPUT_SEED0``.., or ``seeds``) per noise level in
    ``input_spp``, each filtered by every method of :data:`FIG4_METHODS`; the error of
    each split into bias^2 and variance (:class:`ErrorSplit`) over the image, the band around
    roughness steps (:func:`roughness_band` at the filter's radius) and the cells'
    interiors (the other hit pixels)."""
    kw = dict(filter_kwargs or {})
    radius = int(kw.get("radius", _default_radius()))

    def regions(rd: Rendered) -> dict[str, np.ndarray | None]:
        hit = rd.frame.numpy("mesh_id")[..., 0] > 0
        band = roughness_band(rd.frame.numpy("roughness")[..., 0], hit, radius)
        return {"image": None, "band": band, "interior": hit & ~band}

    return _study("roughness-map", size, ref_spp, input_spp, k, regions, FIG4_METHODS, kw,
                  progress, cluster, seeds, keep_samples, rendered, cache)


def fig5_paper(size: tuple[int, int] = PAPER_SIZE, ref_spp: int = PAPER_REF_SPP,
               input_spp: Sequence[int] = PAPER_INPUT_SPP, k: int = PAPER_K,
               filter_kwargs: Mapping[str, Any] | None = None,
               progress: Progress | None = None, cluster=None, seeds=None,
               keep_samples: bool = False, rendered: Rendered | None = None) -> PaperStudy:
    """Tokuyoshi 2015, fig. 5 at paper scale: as :func:`fig4_paper` on ``glossy-spheres``,
    one region per sphere (``"s=1000"``, ``"s=100"``, ``"s=10"``: Phong exponents)."""
    def regions(rd: Rendered) -> dict[str, np.ndarray | None]:
        infos, masks = _spheres(rd.setup, rd.frame)
        return {f"s={s.phong:g}": m for s, m in zip(infos, masks, strict=True)}

    return _study("glossy-spheres", size, ref_spp, input_spp, k, regions, FIG5_METHODS,
                  dict(filter_kwargs or {}), progress, cluster, seeds, keep_samples, rendered)


def _default_radius() -> int:
    from ..denoise.bilateral import RADIUS

    return RADIUS


_LABEL = {"input": "input", "normal": "normal-aware", "screen": "screen kernel",
          "lobe": "lobe-aware"}


def _verdict(ratio: float, diff: float, se: float, greater: bool = False) -> str:
    """Whether "a < b" (``greater``: "a > b") holds for the paired difference ``diff`` = a -
    b with standard error ``se``: HOLDS / DOES NOT HOLD when it is more than 2 standard
    errors from 0 on that side / the other, else UNDECIDED (within the K inputs' noise)."""
    nums = f"ratio {ratio:.3g}, difference {diff:.3g} +- {se:.2g}"
    signed = -diff if greater else diff
    if signed < -2.0 * se:
        return f"HOLDS ({nums})"
    if signed > 2.0 * se:
        return f"DOES NOT HOLD ({nums})"
    return f"UNDECIDED ({nums}: within 2 s.e.)"


def claims(f4: PaperStudy | None = None, f5: PaperStudy | None = None,
           f6: Mapping[int, Fig6Result] | None = None) -> list[str]:
    """Which of Tokuyoshi 2015's claims (secs. 5.1-5.2) hold, one line each, computed from
    the measured numbers: a paired comparison over the K inputs (:meth:`PaperStudy.compare`,
    "a < b" holds when the mean paired MSE difference is below -2 standard errors; it
    does not hold when above +2; else undecided) for figs. 4-5, the optima and curves for
    fig. 6 (deterministic comparisons of the measured curves)."""
    out = []
    if f4 is not None:
        at = f"fig. 4, roughness-map {f4.size[0]}x{f4.size[1]}"
        for spp in f4.input_spp:
            for a, b, reg in (("lobe", "normal", "image"), ("lobe", "normal", "band"),
                              ("lobe", "normal", "interior"), ("lobe", "screen", "image"),
                              ("lobe", "screen", "band")):
                if reg in f4.regions and b in f4.split[spp]:
                    out.append(f"{at}, {spp} spp: {_LABEL[a]} < {_LABEL[b]} MSE ({reg}): "
                               + _verdict(*f4.compare(spp, a, b, reg)))
    if f5 is not None:
        at = f"fig. 5, glossy-spheres {f5.size[0]}x{f5.size[1]}"
        sharp = f5.regions[0]
        for spp in f5.input_spp:
            out.append(f"{at}, {spp} spp: normal-aware > input MSE on the sharpest sphere "
                       f"({sharp}; the normal weight at sigma_n^2 0.01 over-blurs it): "
                       + _verdict(*f5.compare(spp, "normal", "input", sharp), greater=True))
            for reg in f5.regions:
                out.append(f"{at}, {spp} spp: lobe-aware < input MSE ({reg}): "
                           + _verdict(*f5.compare(spp, "lobe", "input", reg)))
                out.append(f"{at}, {spp} spp: lobe-aware < normal-aware MSE ({reg}): "
                           + _verdict(*f5.compare(spp, "lobe", "normal", reg)))
    for spp, r in (f6 or {}).items():
        at = (f"fig. 6, glossy-spheres {r.size[0]}x{r.size[1]}, {spp} spp (mean of "
              f"{r.inputs} input{'s' if r.inputs > 1 else ''})")
        sl, sn = r.spread("lobe"), r.spread("normal")
        edge = " (an optimum on the sweep's end: spreads are lower bounds)" \
            if r.on_boundary("lobe").any() or r.on_boundary("normal").any() else ""
        out.append(f"{at}: the lobe weight's optima are closer together than the normal "
                   f"weight's: {'HOLDS' if sl < sn else 'DOES NOT HOLD'} ({sl:.2f} vs "
                   f"{sn:.2f} decades){edge}")
        q = r.optimum_mse("lobe") / r.optimum_mse("normal")
        same = "HOLDS" if np.all(np.abs(q - 1) <= 0.1) else "DOES NOT HOLD"
        out.append(f"{at}: at each sphere's own optimum the two weights' MSEs are almost the "
                   f"same (within 10%): {same} (lobe / normal "
                   f"{', '.join(f'{v:.3g}' for v in q)})")
        pl, vl = r.mean_optimum("lobe")
        pn, vn = r.mean_optimum("normal")
        out.append(f"{at}: one common parameter gives a lower mean MSE with the lobe weight "
                   f"(the purple line): {'HOLDS' if vl < vn else 'DOES NOT HOLD'} (lobe "
                   f"{vl:.4g} at beta {pl:.3g}, normal {vn:.4g} at 1/sigma_n^2 {pn:.3g})")
    return out


def run_paper(out, size, args) -> int:
    """``glossrt experiment --which lobes --scale paper``: figs. 4-6 at :data:`PAPER_SIZE`
    (or ``--size`` when given), references of ``--spp`` (default :data:`PAPER_REF_SPP`, kept
    in ``OUT/references`` and read back by a rerun),
    inputs at :data:`PAPER_INPUT_SPP`, :data:`PAPER_K` inputs per noise level, fig. 6 over
    :data:`PAPER_FIG6_INPUTS` inputs per noise level. Writes ``lobes-paper.md`` / ``.json``
    and ``fig6-{spp}spp.png``."""
    from ..progress import Progress as Bar

    size = tuple(paper_value(args, "size", size, PAPER_SIZE))
    spp = int(paper_value(args, "spp", args.spp, PAPER_REF_SPP))
    cluster = experiment_cluster(args)
    t0 = time.perf_counter()
    parts = [f"# Tokuyoshi 2015 figs. 4-6 at paper scale ({size[0]}x{size[1]}, reference "
             f"{spp} spp, inputs {' and '.join(map(str, PAPER_INPUT_SPP))} spp, K = {PAPER_K})"]

    class bar:  # a progress bar made at the first tick, when the total is known
        def __init__(self, desc: str):
            self.desc, self.p = desc, None

        def __call__(self, done: int, total: int) -> None:
            self.p = self.p or Bar(total, self.desc)
            self.p.update(done)

        def close(self) -> None:
            if self.p is not None:
                self.p.close()

    print("fig. 4 (roughness-map) ...", flush=True)
    b = bar("fig. 4 filters")
    cache = out / "references"  # (a rerun reads the references back)
    f4 = fig4_paper(size, spp, k=PAPER_K, progress=b, cluster=cluster, cache=cache)
    b.close()
    print("fig. 5 (glossy-spheres) ...", flush=True)
    spheres = render_scene("glossy-spheres", size, spp, cluster, cache=cache)
    b = bar("fig. 5 filters")
    f5 = fig5_paper(size, spp, k=PAPER_K, progress=b, rendered=spheres)
    b.close()
    f6 = {}
    for s in PAPER_INPUT_SPP:
        print(f"fig. 6 ({s} spp) ...", flush=True)
        b = bar(f"fig. 6 sweep {s} spp")
        f6[s] = fig6(size, spp, inputs=PAPER_FIG6_INPUTS, input_spp=s, progress=b,
                     rendered=spheres)
        b.close()
        f6[s].plot(str(out / f"fig6-{s}spp.png"))
    parts += [f"## fig. 4 analogue (roughness-map): band = hit pixels within the filter "
              f"radius of a roughness step\n\n{f4.markdown()}",
              f"## fig. 5 analogue (glossy-spheres)\n\n{f5.markdown()}"]
    parts += [f"## fig. 6 analogue, {s} spp input (mean over {r.inputs} inputs)\n\n"
              f"{r.markdown()}" for s, r in f6.items()]
    parts.append("## Which claims hold\n\n" + "\n".join(f"- {c}" for c in claims(f4, f5, f6)))
    wall = time.perf_counter() - t0
    parts.append(f"Wall time {wall:.0f} s (reference renders {f4.seconds['render']:.0f} + "
                 f"{spheres.seconds:.0f} s).")
    data = paper_json(f4, f5, f6, size=list(size), ref_spp=spp, k=PAPER_K, wall_s=wall)
    return finish_experiment(out, "lobes-paper", "\n\n".join(parts),
                             f"fig6-{PAPER_INPUT_SPP[0]}spp.png", data)


def study_to_json(s: PaperStudy) -> dict:
    """:class:`PaperStudy` as JSON data (without images), for :func:`study_from_json`."""
    return {"scene": s.scene, "size": list(s.size), "ref_spp": s.ref_spp,
            "input_spp": list(s.input_spp), "k": s.k, "seeds": list(s.seeds),
            "params": s.params, "regions": s.regions, "pixels": s.pixels,
            "ref_noise": s.ref_noise, "seconds": s.seconds,
            "split": {str(spp): {m: {reg: {"mse": e.mse, "bias2": e.bias2,
                                           "variance": e.variance, "per_input": e.per_input}
                                     for reg, e in regs.items()}
                                 for m, regs in per.items()}
                      for spp, per in s.split.items()}}


def study_from_json(d: Mapping[str, Any]) -> PaperStudy:
    """The :class:`PaperStudy` of :func:`study_to_json`'s data (no images)."""
    split = {int(spp): {m: {reg: ErrorSplit(e["mse"], e["bias2"], e["variance"],
                                            list(e["per_input"])) for reg, e in regs.items()}
                        for m, regs in per.items()} for spp, per in d["split"].items()}
    return PaperStudy(scene=d["scene"], size=tuple(d["size"]), ref_spp=int(d["ref_spp"]),
                      input_spp=tuple(d["input_spp"]), k=int(d["k"]), seeds=tuple(d["seeds"]),
                      params=dict(d["params"]), regions=list(d["regions"]),
                      pixels=dict(d["pixels"]), split=split, ref_noise=dict(d["ref_noise"]),
                      images={}, seconds=dict(d.get("seconds", {})))


def fig6_to_json(r: Fig6Result) -> dict:
    """:class:`Fig6Result` as JSON data, for :func:`fig6_from_json`."""
    return {"scene": r.scene, "size": list(r.size), "ref_spp": r.ref_spp,
            "filter_kwargs": r.filter_kwargs, "inputs": r.inputs, "input_spp": r.input_spp,
            "spheres": [vars(sp) for sp in r.spheres], "params": r.params.tolist(),
            "curves": {m: c.tolist() for m, c in r.curves.items()},
            "input_mse": list(r.input_mse), "seconds": r.seconds}


def fig6_from_json(d: Mapping[str, Any]) -> Fig6Result:
    """The :class:`Fig6Result` of :func:`fig6_to_json`'s data."""
    return Fig6Result(scene=d["scene"], size=tuple(d["size"]), ref_spp=int(d["ref_spp"]),
                      filter_kwargs=dict(d["filter_kwargs"]),
                      spheres=[SphereInfo(**sp) for sp in d["spheres"]],
                      params=np.asarray(d["params"], dtype=np.float64),
                      curves={m: np.asarray(c, dtype=np.float64)
                              for m, c in d["curves"].items()},
                      input_mse=list(d["input_mse"]), seconds=dict(d.get("seconds", {})),
                      inputs=int(d["inputs"]), input_spp=int(d["input_spp"]))


def paper_json(f4: PaperStudy, f5: PaperStudy, f6: Mapping[int, Fig6Result],
               **extra: Any) -> dict:
    """``lobes-paper.json``'s data: the three studies and the claims computed from them."""
    return {**extra, "fig4": study_to_json(f4), "fig5": study_to_json(f5),
            "fig6": {str(s): fig6_to_json(r) for s, r in f6.items()},
            "claims": claims(f4, f5, f6)}


def load_paper_json(path) -> tuple[PaperStudy, PaperStudy, dict[int, Fig6Result]]:
    """``(fig4, fig5, {spp: fig6})`` of a ``lobes-paper.json`` (:func:`run_paper`), so the
    claims (:func:`claims`) can be recomputed and asserted from stored measurements."""
    import json
    from pathlib import Path

    d = json.loads(Path(path).read_text())
    return (study_from_json(d["fig4"]), study_from_json(d["fig5"]),
            {int(s): fig6_from_json(r) for s, r in d["fig6"].items()})


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
    ctx.say(f"fig. 4 analogue: roughness-map {size[0]}x{size[1]}, reference {spp} spp ...")
    with ctx.bar("fig. 4 filters") as p:
        f4 = fig4(size=size, ref_spp=spp, progress=p)
    markdown_table(s, f4.markdown(), "fig. 4 analogue: roughness-map, indirect specular")
    s.images_row([(k, v) for k, v in f4.images.items()], name="fig4")
    ctx.say(f"fig. 5 analogue: glossy-spheres {size[0]}x{size[1]}, reference {spp} spp ...")
    with ctx.bar("fig. 5 filters") as p:
        f5 = fig5(size=size, ref_spp=spp, progress=p)
    markdown_table(s, f5.markdown(), "fig. 5 analogue: glossy-spheres, one parameter set")
    s.images_row([(k, v) for k, v in f5.images.items()], name="fig5")
    ctx.say(f"fig. 6 analogue: glossy-spheres, reference {spp} spp, then the sweeps ...")
    with ctx.bar("fig. 6 sweeps") as p:
        f6 = fig6(size=size, ref_spp=spp, progress=p)
    markdown_table(s, f6.markdown(), "fig. 6 analogue: optima per sphere")
    s.saved_figure("fig6.png", lambda p: f6.plot(str(p)), "fig. 6 analogue: MSE vs beta "
                   "(lobe) and vs 1/sigma_n^2 (normal), one line per Phong exponent")
    ctx.say("joint bilateral upsampling (roughness-map) ...")
    up = ue.upsampling(size=size, ref_spp=spp, low_spp=spp, progress=ctx.say)
    markdown_table(s, up.markdown(), "joint bilateral upsampling of converged 1/2 and 1/4 "
                   "resolution indirect light (roughness-map); adaptive re-sampling where the "
                   f"normalised weight sum < {up.threshold}")
    s.images_row([(k, v) for k, v in up.images.items()], name="upsampling")
    ctx.say("spatio-temporal upsampling (glossy-cornell, 8 frames) ...")
    st = ue.spatio_temporal(size=size, frames=8, ref_spp=spp, ref_frames=(3, 7),
                            progress=ctx.say)
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
                     "--spp); --scale paper: figs. 4-6 at 640x360, 4096 spp references, "
                     "16 inputs at 1 and at 4 spp, bias / variance, band vs interiors",
                     order=20)
def run_experiment(out, size, args) -> int:
    """Tokuyoshi 2015 figs. 4-6 analogues and the upsampling measurements (RESULTS.md);
    ``--scale paper``: :func:`run_paper`."""
    if experiment_scale(args) == "paper":
        return run_paper(out, size, args)
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
    print("fig. 7 analogue (normal-mapped, Toksvig) ...", flush=True)
    f7 = ue.fig7(size=size, frames=args.frames, ref_spp=spp, cluster=cluster)
    parts.append(f"## fig. 7 analogue: spatio-temporal upsampling, simplified history vs "
                 f"Herzog 2010 (normal-mapped, Toksvig)\n\n{f7.markdown()}")
    return finish_experiment(out, "lobes", "\n\n".join(parts), "fig6.png")
