"""Measurements behind docs/RESULTS.md for polygon lights with LTC (issue 5).

* :func:`accuracy`: :func:`glossrt.lights.ltc.shade.polygon_integral` against the float64 area
  quadrature of the same BRDF (:mod:`glossrt.lights.quadrature`) for random quads and
  triangles, views and roughnesses: median / 90th / 99th percentile relative error;
* :func:`images`: LTC shading of ``polygon-light`` (per GGX alpha) against an unshadowed Monte
  Carlo reference of the same BRDF (:mod:`glossrt.lights.mc`): error, time per frame, and the
  Monte Carlo sample count that reaches LTC's error, with its time (side by side, one run).

The paper's report section (``ltc``), benchmark case (``ltc``) and ``glossrt experiment
--which ltc`` are registered here.
"""

from __future__ import annotations

import json
import math
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..report import DemoContext, Report, register_section
from ..report.registry import (
    BenchContext,
    benchmark,
    finish_experiment,
    register_experiment,
    section_size,
)
from ..timing import paired_ratio, round_robin

ALPHAS = (0.1, 0.25, 0.5, 1.0)


def random_polygons(rng: np.random.Generator, k: int) -> list[tuple]:
    """``k`` random (vertices, wo, n, alpha) cases: one-sided quads (parallelograms) and
    triangles facing the shading point, mostly above its horizon, views from 3 to 87
    degrees, alpha around 0.1, 0.25, 0.5 and 1 (at most 1, the table's range)."""
    cases = []
    while len(cases) < k:
        n = np.array([0, 0, 1.0])
        th = math.acos(rng.uniform(0.05, 1.0))
        ph = rng.uniform(0, 2 * math.pi)
        wo = np.array([math.sin(th) * math.cos(ph), math.sin(th) * math.sin(ph), math.cos(th)])
        alpha = float(min(rng.choice(ALPHAS) * rng.uniform(0.8, 1.2), 1.0))  # table: <= 1
        c = rng.normal(size=3)
        c[2] = abs(c[2]) + 0.3
        c *= rng.uniform(0.5, 3.0) / np.linalg.norm(c)
        e1, e2 = rng.normal(size=3), rng.normal(size=3)
        size = rng.uniform(0.1, 1.0)
        e1 *= size / np.linalg.norm(e1)
        e2 *= size / np.linalg.norm(e2)
        if rng.uniform() < 0.5:
            verts = np.array([c - e1 - e2, c + e1 - e2, c + e1 + e2, c - e1 + e2])
        else:
            verts = np.array([c - e1, c + e1, c + e2])
        nl = np.cross(verts[1] - verts[0], verts[2] - verts[0])
        if np.linalg.norm(nl) < 1e-3:
            continue
        if nl @ (-verts[0]) < 0:
            verts = verts[::-1].copy()
        cases.append((verts, wo, n, alpha))
    return cases


#: lobe-share groups of :func:`accuracy`: the part of the lobe's mass a polygon catches
SHARES = ((0.0, 0.01, "< 1%"), (0.01, 0.1, "1-10%"), (0.1, 0.5, "10-50%"), (0.5, 2.0, "> 50%"))
#: view-angle groups of :func:`accuracy` (degrees)
VIEWS = ((0.0, 30.0), (30.0, 60.0), (60.0, 80.0), (80.0, 90.0))


def accuracy(n: int = 2000, seed: int = 5, m: int = 400, table=None,
             distribution: str = "ggx") -> dict:
    """Error statistics of LTC's polygon integral for ``distribution``'s lobe (see the
    module docstring), grouped by roughness, by the share of the lobe's mass the polygon
    catches (``exact / norm``) and by view angle. Per group: the relative error's median /
    p90 / p99 over cases whose exact value is at least 1e-3 of the largest (relative error
    of nothing is meaningless), and the mass error ``|LTC - exact| / norm``'s median and
    max over all cases (bounded by half the fit's L1 error). Returns {"all": stats,
    0.1: stats, ..., "share": {label: stats}, "view": {label: stats}}. ``table``: the LTC
    table to score (default glossrt's, see :func:`load_published_table`)."""
    from ..lights.ltc import polygon_integral
    from ..lights.ltc.fit import brdf_moments
    from ..lights.quadrature import polygon_quadrature

    cases = random_polygons(np.random.default_rng(seed), n)
    want = np.array([polygon_quadrature(v, wo, nn, a, m=m, distribution=distribution)
                     for v, wo, nn, a in cases])
    got = np.zeros(len(cases))
    groups: dict[int, list[int]] = {}
    for i, c in enumerate(cases):
        groups.setdefault(len(c[0]), []).append(i)
    for idx in groups.values():
        got[idx] = polygon_integral(np.array([cases[i][0] for i in idx]),
                                    np.array([cases[i][2] for i in idx]),
                                    np.array([cases[i][1] for i in idx]),
                                    np.array([cases[i][3] for i in idx]), two_sided=False,
                                    table=table, distribution=distribution)
    alphas = np.array([c[3] for c in cases])
    cos_o = np.array([float(c[1] @ c[2]) for c in cases])
    norm = brdf_moments(alphas, cos_o, 1 << 12, distribution)["norm"]
    share = want / norm
    view = np.degrees(np.arccos(np.clip(cos_o, -1.0, 1.0)))
    sig = want > 1e-3 * want.max()
    rel = np.abs(got / np.where(sig, want, 1.0) - 1)
    mass = np.abs(got - want) / norm

    def stats(mask):
        r = rel[mask & sig]
        med, p90, p99 = np.percentile(r, [50, 90, 99]) if r.size else (np.nan,) * 3
        ms = mass[mask]
        return {"median": float(med), "p90": float(p90), "p99": float(p99),
                "count": int(r.size), "cases": int(mask.sum()),
                "mass_median": float(np.median(ms)) if ms.size else float("nan"),
                "mass_max": float(ms.max()) if ms.size else float("nan")}

    out: dict = {"all": stats(np.ones(len(cases), bool))}
    for a in ALPHAS:
        out[a] = stats((alphas > 0.75 * a) & (alphas < 1.25 * a))
    out["share"] = {lab: stats((share >= lo) & (share < hi)) for lo, hi, lab in SHARES}
    out["view"] = {f"{lo:g}-{hi:g} deg": stats((view >= lo) & (view < hi)) for lo, hi in VIEWS}
    return out


def accuracy_markdown(acc: dict) -> str:
    """The tables of :func:`accuracy`: by roughness, by lobe share, by view angle."""
    head = ("| {} | cases (rel.) | median rel. error | p90 | p99 | mass error median | "
            "mass error max |\n|---|---|---|---|---|---|---|")

    def row(k, v):
        return (f"| {k} | {v['cases']} ({v['count']}) | {v['median']:.3f} | {v['p90']:.3f} | "
                f"{v['p99']:.3f} | {v['mass_median']:.2e} | {v['mass_max']:.3f} |")

    parts = [head.format("alpha") + "\n" + "\n".join(
        row(k, v) for k, v in acc.items() if k not in ("share", "view"))]
    parts.append(head.format("share of the lobe") + "\n" + "\n".join(
        row(k, v) for k, v in acc["share"].items()))
    parts.append(head.format("view angle") + "\n" + "\n".join(
        row(k, v) for k, v in acc["view"].items()))
    return "\n\n".join(parts)


# Heitz et al.'s fit (selfshadow/ltc_code, fitLTC.cpp): rows at alpha = max(r^2, 1e-5)
PUBLISHED_ALPHA_MIN = 1e-5


def load_published_table(path: str | Path):
    """The published GGX LTC table of Heitz et al. 2016 from a copy of ``fit/results/ltc.js``
    of https://github.com/selfshadow/ltc_code (BSD 2-clause; the user supplies the file,
    glossrt does not ship it), as an :class:`~glossrt.lights.ltc.table.LTCTable` in glossrt's
    layout, for :func:`compare_with_published`.

    The file holds ``g_ltc_1`` (per cell ``M^-1`` normalised by its middle element, as glm's
    column-major ``[0][0], [0][2], [2][0], [2][2]``, i.e. elements (0,0), (2,0), (0,2),
    (2,2)) and ``g_ltc_2`` (``norm``, ``fresnel``, 0, sphere), ``N x N`` cells with the
    roughness index fastest, over the same ``(sqrt(alpha), sqrt(1 - cos theta))`` grid as
    glossrt's table."""
    import re

    from ..errors import GlossrtError
    from ..lights.ltc.table import LTCTable

    text = Path(path).read_text()
    num = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?")
    parts = {}
    for name in ("g_ltc_1", "g_ltc_2"):
        m = re.search(name + r"\s*=\s*\[([^\]]*)\]", text)
        if m is None:
            raise GlossrtError(f"{path}: no array {name} (expected ltc_code's fit/results/ltc.js)")
        parts[name] = np.array([float(x) for x in num.findall(m.group(1))])
    size = parts["g_ltc_1"].size // 4
    n = int(round(math.sqrt(size)))
    if n < 2 or n * n * 4 != parts["g_ltc_1"].size or parts["g_ltc_2"].size != size * 4:
        raise GlossrtError(f"{path}: g_ltc_1 / g_ltc_2 must hold N*N*4 numbers each, got "
                           f"{parts['g_ltc_1'].size} and {parts['g_ltc_2'].size}")
    # file order [theta][roughness] -> glossrt's [roughness][theta]
    t1 = parts["g_ltc_1"].reshape(n, n, 4).transpose(1, 0, 2)
    t2 = parts["g_ltc_2"].reshape(n, n, 4).transpose(1, 0, 2)
    m00, m20, m02, m22 = (t1[..., k] for k in range(4))
    if not np.all(np.isfinite(t1)):
        raise GlossrtError(f"{path}: non-finite or singular matrices in g_ltc_1")
    # glossrt's canonical M^-1 = [[a, 0, b], [0, 1, 0], [c, 0, d]]: the same normalisation
    coeffs = np.stack([m00, m02, m20, m22], -1)
    return LTCTable.from_arrays(coeffs, t2[..., 0], t2[..., 1], PUBLISHED_ALPHA_MIN)


def _cell_l1(table, norm: np.ndarray, cells: list[tuple[int, int]]) -> np.ndarray:
    """The fit error L1 (:func:`glossrt.lights.ltc.fit.lobe_errors`) of ``table``'s matrices
    at glossrt's nodes ``cells`` (lobe norms from glossrt's table, the same for both)."""
    from ..lights.ltc.fit import _Objective
    from ..lights.ltc.table import grid_axes, minv_matrix, node_config

    alpha, cos_o = node_config(*grid_axes(table.n_r))
    coeffs = table.host["minv"].astype(np.float64)
    out = np.full(len(cells), np.nan)
    for k, (j, i) in enumerate(cells):
        obj = _Objective(float(alpha[j]), float(cos_o[i]), float(norm[j, i]), False)
        try:
            out[k] = obj.errors_of(np.linalg.inv(minv_matrix(coeffs[j, i])))[1]
        except np.linalg.LinAlgError:
            pass
    return out


def compare_with_published(path: str | Path, polygons: int = 2000, cell_step: int = 1,
                           seed: int = 5, m: int = 400,
                           progress: Callable[[str], None] | None = None) -> dict:
    """glossrt's LTC table against the published one (:func:`load_published_table`), scored
    the same way: the fit error L1 = int |LTC - normalised lobe| per cell (glossrt's samples,
    BRDF and lobe norms, every ``cell_step``-th row and column of glossrt's 64 x 64 nodes) and
    :func:`accuracy` on ``polygons`` random polygons against the float64 quadrature.
    Returns {"cells", "l1": {"glossrt": stats, "published": stats, "glossrt_better": n},
    "polygons": {"glossrt": accuracy, "published": accuracy}, "norm_max_diff"}."""
    from ..lights.ltc.table import LTCTable

    say = progress or (lambda _m: None)
    ours = LTCTable.load()
    theirs = load_published_table(path)
    if (theirs.n_r, theirs.n_u) != (ours.n_r, ours.n_u):
        from ..errors import GlossrtError

        raise GlossrtError(f"{path}: published table is {theirs.n_r}x{theirs.n_u}, glossrt's "
                           f"{ours.n_r}x{ours.n_u}: not comparable cell by cell")
    norm = ours.host["norm"].astype(np.float64)
    idx = range(0, ours.n_r, max(1, int(cell_step)))
    cells = [(j, i) for j in idx for i in range(0, ours.n_u, max(1, int(cell_step)))]
    say(f"fit error of {len(cells)} cells, both tables")
    l1 = {"glossrt": _cell_l1(ours, norm, cells), "published": _cell_l1(theirs, norm, cells)}

    def st(x):
        x = x[np.isfinite(x)]
        return {"median": float(np.median(x)), "mean": float(np.mean(x)),
                "p95": float(np.percentile(x, 95)), "max": float(np.max(x)), "count": int(x.size)}

    out = {"cells": len(cells),
           "l1": {k: st(v) for k, v in l1.items()},
           "norm_max_diff": float(np.max(np.abs(norm - theirs.host["norm"])))}
    out["l1"]["glossrt_better"] = int(np.sum(l1["glossrt"] < l1["published"]))
    if polygons > 0:
        say(f"{polygons} random polygons against the quadrature, both tables")
        out["polygons"] = {"glossrt": accuracy(polygons, seed, m),
                           "published": accuracy(polygons, seed, m, table=theirs)}
    return out


def published_markdown(res: dict) -> str:
    """:func:`compare_with_published`'s result as a markdown table."""
    rows = ["| table | L1 median | L1 mean | L1 p95 | polygons: median rel. error | p90 | p99 |",
            "|---|---|---|---|---|---|---|"]
    for k in ("glossrt", "published"):
        l1 = res["l1"][k]
        p = res.get("polygons", {}).get(k, {}).get("all")
        tail = (f"{p['median']:.3f} | {p['p90']:.3f} | {p['p99']:.3f}" if p else "- | - | -")
        rows.append(f"| {k} | {l1['median']:.4f} | {l1['mean']:.4f} | {l1['p95']:.4f} | {tail} |")
    rows.append(f"\nglossrt's fit error is lower in {res['l1']['glossrt_better']} of "
                f"{res['cells']} cells; largest |norm difference| {res['norm_max_diff']:.3g}.")
    return "\n".join(rows)


@dataclass
class LTCImageResults:
    size: tuple[int, int]
    ref_spp: int
    rows: list[dict] = field(default_factory=list)
    images: dict[str, np.ndarray] = field(default_factory=dict)
    labels: list[str] = field(default_factory=list)

    COLUMNS = ["alpha", "LTC RMSE", "LTC mean rel. error", "LTC ms / frame",
               "MC spp for LTC's RMSE", "MC ms / frame at that spp", "MC time / LTC time",
               "reference (with shadows) vs Mitsuba direct, mean rel. error"]

    def table(self) -> list[list]:
        return [[r["alpha"], r["rmse"], r["rel"], r["ltc_ms"], r["mc_spp"], r["mc_ms"],
                 r["mc_ms"] / r["ltc_ms"] if r["mc_ms"] else None, r.get("vs_direct")]
                for r in self.rows]

    def montage(self, path: str | Path, eps: float = 1e-2) -> Path:
        """One PNG: a row per run (LTC | Monte Carlo reference | relative error
        ``|LTC - MC| / (MC + eps)`` on a 0-50% colour scale), paper fig. 8, lower row."""
        from ..report.figures import Panel, montage
        from ..report.page import tonemap

        n = len(self.labels)
        h, w = self.size[1], self.size[0]
        lum = np.array([0.2126, 0.7152, 0.0722])
        grid = []
        for label in self.labels:
            ltc = self.images[f"{label}: LTC"]
            ref = self.images[f"{label}: Monte Carlo {self.ref_spp} spp"]
            rel = np.abs(ltc @ lum - ref @ lum) / (ref @ lum + eps)
            grid.append([
                Panel(tonemap(ltc), f"{label}: LTC"),
                Panel(tonemap(ref), f"Monte Carlo, {self.ref_spp} spp (no shadows)"),
                Panel(rel, "relative error (0 to 50%)", "magma", 0.0, 0.5,
                      colorbar={"fraction": 0.046, "pad": 0.02})])
        return montage(path, grid, (9.6, 9.6 * n * h / (3 * w) + 0.6 * n), dpi=110)

    def markdown(self) -> str:
        lines = ["| " + " | ".join(self.COLUMNS) + " |", "|" + "---|" * len(self.COLUMNS)]
        for row in self.table():
            cells = ["-" if v is None else (str(v) if isinstance(v, int | str) else f"{v:.4g}")
                     for v in row]
            lines.append("| " + " | ".join(cells) + " |")
        return "\n".join(lines)


def _timed(fn, repeats: int = 3):
    fn()  # warm the kernel cache
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        ts.append(time.perf_counter() - t0)
    return out, 1000 * float(np.median(ts))


def images(alphas: tuple[float, ...] = ALPHAS, size: tuple[int, int] = (160, 120),
           ref_spp: int = 1024, frame: int = 0, max_spp: int = 256, textured: bool = False,
           progress: Callable[[str], None] | None = None) -> LTCImageResults:
    """LTC vs unshadowed Monte Carlo on ``polygon-light-a<alpha>`` (module docstring), and on
    ``polygon-light-textured`` (alpha 0.25, row label ``"textured 0.25"``) if ``textured``."""
    from .. import render, scenes
    from ..lights.ltc import shade_frame
    from ..lights.mc import render_mc
    from ..lights.scene import polygon_lights
    from ..lights.shading import fresnel_image

    say = progress or (lambda _m: None)
    res = LTCImageResults(tuple(size), ref_spp)
    runs = [(a, f"polygon-light-a{a:.2g}" if a != 1.0 else "polygon-light-a1.0", f"alpha {a:g}")
            for a in alphas]
    if textured:
        runs.append(("textured 0.25", "polygon-light-textured", "textured light, alpha 0.25"))
    for a, name, label in runs:
        say(f"{name}: G-buffer, LTC, unshadowed Monte Carlo reference ({ref_spp} spp)")
        setup = scenes.load(name, size=size)
        gb = render.Renderer(setup).render(frame)
        lights = polygon_lights(setup, frame)
        f0 = fresnel_image(setup, gb)
        cache: dict = {}
        ltc, ltc_ms = _timed(lambda gb=gb, lights=lights, f0=f0, cache=cache:
                             shade_frame(gb, lights, f0=f0, textures=cache))
        ref = render_mc(gb, lights, ref_spp, f0=f0, seed=1)
        hit = gb.numpy("mesh_id")[..., 0] > 0
        # the reference's BRDF against Mitsuba's own direct integrator: the same Monte Carlo
        # with shadows (direct has them) on the pixels that see a non-emitting surface
        r = render.Renderer(setup)
        say(f"{name}: Mitsuba's direct integrator and shadowed Monte Carlo ({ref_spp} spp)")
        direct = np.array(r.render_mitsuba(frame, ref_spp, integrator="direct"))
        shadowed = render_mc(gb, lights, ref_spp, f0=f0, scene=setup.scene, seed=1)
        surf = hit & ~(gb.numpy("emission").max(-1) > 0)
        vs_direct = float(np.mean(np.abs(shadowed - direct)[surf])
                          / max(np.mean(np.abs(direct[surf])), 1e-12))
        err = (ltc - ref)[hit]
        rmse = float(np.sqrt(np.mean(err**2)))
        rel = float(np.mean(np.abs(err)) / max(np.mean(np.abs(ref[hit])), 1e-12))
        mc_spp, mc_ms = None, None
        say(f"{name}: the Monte Carlo samples per pixel that reach LTC's RMSE (up to "
            f"{max_spp})")
        spp = 1
        while spp <= max_spp:
            img, ms = _timed(lambda spp=spp, gb=gb, lights=lights, f0=f0:
                             render_mc(gb, lights, spp, f0=f0, seed=7), repeats=1)
            if float(np.sqrt(np.mean(((img - ref)[hit]) ** 2))) <= rmse:
                mc_spp, mc_ms = spp, ms
                break
            spp *= 2
        res.rows.append({"alpha": a, "rmse": rmse, "rel": rel, "ltc_ms": ltc_ms,
                         "mc_spp": mc_spp, "mc_ms": mc_ms, "vs_direct": vs_direct})
        res.labels.append(label)
        res.images[f"{label}: LTC"] = ltc
        res.images[f"{label}: Monte Carlo {ref_spp} spp"] = ref
        res.images[f"{label}: |LTC - MC|"] = np.abs(ltc - ref)
    return res


# -- textured lights: the prefiltered lookup's footprint scale (issue 23) -------------------

#: footprint scales tried by :func:`texture_footprint` (log-spaced)
FOOTPRINT_SCALES = tuple(float(x) for x in np.round(np.geomspace(0.0625, 2.0, 16), 4))


def footprint_textures(n: int = 64) -> dict[str, np.ndarray]:
    """The light textures of :func:`texture_footprint`, (n, n, 3) float32: an 8 x 8
    ``checker`` (0.05 / 1, tinted), a ``gradient`` (red along u, green along v, blue
    constant) and ``blobs`` (three coloured Gaussian spots of different sizes on a dark
    ground)."""
    s = (np.arange(n) + 0.5) / n
    u, v = np.meshgrid(s, s)
    cells = ((u * 8).astype(int) + (v * 8).astype(int)) % 2
    checker = np.where(cells[..., None] == 1, [1.0, 0.9, 0.7], [0.05, 0.05, 0.08])
    gradient = np.stack([u, v, np.full_like(u, 0.5)], -1)
    blobs = np.full((n, n, 3), 0.03)
    for cu, cv, r, col in ((0.25, 0.3, 0.08, (1.0, 0.2, 0.1)), (0.7, 0.65, 0.15, (0.1, 0.4, 1.0)),
                           (0.6, 0.2, 0.04, (0.9, 0.9, 0.2))):
        blobs = blobs + np.exp(-((u - cu) ** 2 + (v - cv) ** 2) / (2 * r * r))[..., None] * col
    return {k: np.asarray(x, np.float32) for k, x in
            (("checker", checker), ("gradient", gradient), ("blobs", blobs))}


#: materials of :func:`texture_footprint`: (label, GGX alpha, diffuse albedo, F0)
FOOTPRINT_MATERIALS = (("spec a0.1", 0.1, 0.0, 1.0), ("spec a0.25", 0.25, 0.0, 1.0),
                       ("spec a0.5", 0.5, 0.0, 1.0), ("spec a1", 1.0, 0.0, 1.0),
                       ("diffuse", 0.5, 0.8, 0.0))


@dataclass
class _FpLight:
    vertices: np.ndarray
    radiance: tuple
    two_sided: bool = False
    texture: object = None
    uv: object = None


def footprint_frame(w: int, h: int, alpha: float, albedo: float):
    """The G-buffer of :func:`texture_footprint`: a floor (z = 0, x in [-1, 1], y in
    [-0.6, 1.2]) seen from (0, -2, 1.2), every pixel a floor point (position grid, normal +z,
    GGX ``alpha``, diffuse ``albedo``)."""
    from ..frame import RADIANCE, Camera, Frame

    px, py = np.meshgrid(np.linspace(-1.0, 1.0, w), np.linspace(-0.6, 1.2, h))
    ch = {c: np.zeros((h, w, 3)) for c in RADIANCE}
    ch["position"] = np.stack([px, py, np.zeros_like(px)], -1)
    ch["normal"] = np.broadcast_to([0, 0, 1.0], (h, w, 3))
    ch["albedo_diffuse"] = np.full((h, w, 3), albedo)
    ch["albedo_specular"] = np.zeros((h, w, 3))
    ch["roughness"] = np.full((h, w, 1), alpha)
    ch["mesh_id"] = np.ones((h, w, 1))
    ch["depth"] = np.ones((h, w, 1))
    cam = np.eye(4)
    cam[:3, 3] = [0.0, -2.0, 1.2]
    return Frame(channels={k: np.asarray(x, np.float32) for k, x in ch.items()},
                 camera=Camera(cam, 45.0, (w, h)))


#: the light of :func:`texture_footprint`: a 1.2 x 0.72 quad centred at (0, 1.0, 0.55),
#: facing down and towards the camera (counter-clockwise seen from the floor); the camera
#: sees its mirror image in the floor around y = 0
FOOTPRINT_LIGHT = np.array([[-0.6, 0.7, 0.75], [-0.6, 1.3, 0.35], [0.6, 1.3, 0.35],
                            [0.6, 0.7, 0.75]])
FOOTPRINT_UV = np.array([[0.0, 0.0], [0.0, 1.0], [1.0, 1.0], [1.0, 0.0]])


def texture_footprint(size: tuple[int, int] = (32, 24), ref_spp: int = 4096,
                      scales: tuple[float, ...] = FOOTPRINT_SCALES,
                      textures: dict[str, np.ndarray] | None = None,
                      materials: tuple = FOOTPRINT_MATERIALS, seed: int = 3,
                      progress: Callable[[str], None] | None = None) -> dict:
    """Calibrate the textured-light lookup's footprint scale ``c`` (``sigma_uv = c d /
    sqrt(A)``, :mod:`glossrt.lights.ltc`) against Monte Carlo.

    For each texture of ``textures`` (default :func:`footprint_textures`) and each material
    (GGX alpha, diffuse albedo, F0) a floor under the textured quad
    :data:`FOOTPRINT_LIGHT` (:func:`footprint_frame`) is shaded by LTC with the prefiltered
    texture at each scale of ``scales`` and each ``blend`` (``"log"``, ``"linear"``), and by
    unshadowed Monte Carlo (:func:`glossrt.lights.mc.render_mc`, ``ref_spp`` per pixel, the
    full-resolution texture, bilinear) with the texture and with a plain light of radiance
    1. The error isolates the texture lookup from LTC's own error of the lobe's integral:
    LTC's texture factor ``LTC_tex / LTC_plain`` applied to the reference's plain light,
    against the reference's textured light, as a relative L1 error ``sum |f_LTC MC_plain -
    MC_tex| / sum MC_tex`` over the pixels and channels. Returns ``{"errors": {blend: array
    (texture, material, scale)}, "total": {blend: the same for sum |LTC_tex - MC_tex| / sum
    MC_tex}, "scales", "textures", "materials", "best": {blend: scale of the least mean
    error}, "noise": the reference's own relative L1 noise (two halves of its samples)}``."""
    from ..lights.ltc import PrefilteredTexture, shade_frame
    from ..lights.mc import render_mc

    textures = footprint_textures() if textures is None else textures
    w, h = size
    plain_light = _FpLight(FOOTPRINT_LIGHT, (1.0, 1.0, 1.0))
    names = list(textures)
    err = {b: np.zeros((len(names), len(materials), len(scales))) for b in ("log", "linear")}
    tot = {b: np.zeros_like(err[b]) for b in err}
    noise = np.zeros((len(names), len(materials)))
    for j, (label, alpha, albedo, f0v) in enumerate(materials):
        frame = footprint_frame(w, h, alpha, albedo)
        f0 = np.full((h, w, 3), f0v, np.float32)
        mc_plain = render_mc(frame, [plain_light], ref_spp, f0=f0, seed=seed)
        ltc_plain = shade_frame(frame, [plain_light], f0=f0)
        for i, name in enumerate(names):
            img = textures[name]
            light = _FpLight(FOOTPRINT_LIGHT, (1.0, 1.0, 1.0), texture=img, uv=FOOTPRINT_UV)
            half = ref_spp // 2
            a = render_mc(frame, [light], half, f0=f0, seed=seed + 1)
            b = render_mc(frame, [light], ref_spp - half, f0=f0, seed=seed + 2)
            mc_tex = 0.5 * (a + b)
            noise[i, j] = 0.5 * np.abs(a - b).sum() / mc_tex.sum()
            for blend in ("log", "linear"):
                pre = PrefilteredTexture(img, blend=blend)
                for k, c in enumerate(scales):
                    pre.scale = float(c)
                    ltc_tex = shade_frame(frame, [light], f0=f0, textures={id(img): pre})
                    factor = ltc_tex / np.maximum(ltc_plain, 1e-12)
                    err[blend][i, j, k] = (np.abs(factor * mc_plain - mc_tex).sum()
                                           / mc_tex.sum())
                    tot[blend][i, j, k] = np.abs(ltc_tex - mc_tex).sum() / mc_tex.sum()
            if progress is not None:
                progress(f"{name}, {label}: best scale (log blend) "
                         f"{scales[int(np.argmin(err['log'][i, j]))]}")
    best = {b: float(scales[int(np.argmin(e.mean(axis=(0, 1))))]) for b, e in err.items()}
    return {"errors": err, "total": tot, "scales": tuple(scales), "textures": names,
            "materials": [m[0] for m in materials], "best": best, "noise": noise}


def footprint_markdown(res: dict, at: tuple[tuple[str, float], ...]) -> str:
    """A table of :func:`texture_footprint`'s texture-lookup error per texture and material
    for the (blend, scale) pairs of ``at`` (each scale must be one of ``res["scales"]``)."""
    cols = [f"{b}, c = {c:g}" for b, c in at]
    lines = ["| texture | material | " + " | ".join(cols) + " | reference noise |",
             "|---|---|" + "---|" * (len(cols) + 1)]
    idx = [(b, res["scales"].index(c)) for b, c in at]
    for i, t in enumerate(res["textures"]):
        for j, m in enumerate(res["materials"]):
            vals = " | ".join(f"{res['errors'][b][i, j, k]:.4f}" for b, k in idx)
            lines.append(f"| {t} | {m} | {vals} | {res['noise'][i, j]:.4f} |")
    means = " | ".join(f"**{res['errors'][b][..., k].mean():.4f}**" for b, k in idx)
    lines.append(f"| mean | | {means} | {res['noise'].mean():.4f} |")
    return "\n".join(lines)


@register_section("ltc", order=60)
def section_ltc(ctx: DemoContext, report: Report) -> None:
    t0 = time.perf_counter()
    _, size = section_size(ctx, (96, 72), 4, (16, 12))
    spp = min(512, int(ctx.references[0].meta.get("spp", 256)) * 2) if ctx.references else 512
    res = images(alphas=ALPHAS, size=size, ref_spp=spp, max_spp=64, textured=True,
                 progress=ctx.say)
    s = report.section(
        "Polygon lights: LTC",
        "Heitz et al. 2016 with glossrt's own GGX LTC fit: direct light of polygon-light "
        f"(teapot, sphere, glossy floor, one quad light) at {size[0]}x{size[1]}, LTC against an "
        f"unshadowed Monte Carlo reference of the same BRDF ({spp} spp), per GGX alpha and with "
        "the textured light (prefiltered texture); the Monte Carlo column gives the samples per "
        "pixel that reach LTC's RMSE (up to 64) and their time, measured in the same run. See "
        "docs/RESULTS.md for a larger run.")
    s.table(LTCImageResults.COLUMNS, res.table())
    for k, label in enumerate(res.labels):
        ltc = res.images[f"{label}: LTC"]
        ref = res.images[f"{label}: Monte Carlo {spp} spp"]
        s.images_row([(f"{label}: LTC", ltc), (f"{label}: Monte Carlo", ref)], name=f"ltc_{k}")
        s.error_map(f"ltc_error_{k}", ltc, ref, caption=f"{label}: relative error of "
                    "LTC against Monte Carlo (fig. 8 lower row analogue)")
    ctx.timings["LTC section"] = time.perf_counter() - t0


@benchmark("ltc", order=40)
def bench_ltc(ctx: BenchContext) -> dict:
    """Deferred LTC shading of ``polygon-light``'s G-buffer by its quad light (Heitz et al.
    2016) at the bench size, the light moving between calls: traced anew and frozen
    (``dr.freeze``, the real-time path), with unshadowed Monte Carlo of the same BRDF at 1 spp
    for scale, interleaved in one run; the result stays on the device (no NumPy copy).
    GPU target (issue 5): frozen, 1920x1080, at most 0.5 ms."""
    import drjit as dr

    from .. import render, scenes
    from ..lights.ltc import shade_tensor
    from ..lights.mc import render_mc
    from ..lights.scene import polygon_lights
    from ..lights.shading import fresnel_image

    w, h = ctx.size
    setup = scenes.load("polygon-light", size=(w, h), frames=4)
    r = render.Renderer(setup)
    inputs = []
    for i in range(4):
        gb = r.render(i)
        inputs.append((gb, polygon_lights(setup, i), fresnel_image(setup, gb)))
    state = {"k": 0}

    def step(frozen):
        gb, lights, f0 = inputs[state["k"] % 4]
        state["k"] += 1
        dr.eval(shade_tensor(gb, lights, f0=f0, frozen=frozen))

    gb0, lights0, f00 = inputs[0]
    cases = {"ltc-traced": lambda: step(False), "ltc-frozen": lambda: step(True),
             "mc-1spp": lambda: render_mc(gb0, lights0, 1, f0=f00)}
    times = round_robin(cases, 1, ctx.turns, ctx.min_sample)
    med = {k: statistics.median(v) for k, v in times.items()}
    return {"scene": "polygon-light", "size": [w, h], "lights": 1, "seconds": med,
            "frozen_vs_traced": paired_ratio(times["ltc-frozen"], times["ltc-traced"]),
            "gpu_target_s_at_1920x1080": 0.5e-3}


@register_experiment("ltc", "Heitz et al. 2016 accuracy and images (uses --size, --spp, "
                     "--polygons, --published)", order=30)
def run_experiment(out, size, args) -> int:
    """Heitz et al. 2016 measurements (RESULTS.md): polygon_integral against the quadrature,
    LTC images against Monte Carlo per alpha and textured (montage with error maps), and the
    published table when its ltc.js is given (--published; --polygons random polygons)."""
    spp, polygons, published = args.spp, args.polygons, args.published
    parts = []
    cmp = None
    if published:
        print(f"published table {published}: fit error per cell and {polygons} random "
              "polygons, both tables ...", flush=True)
        cmp = compare_with_published(published, polygons=polygons, progress=print)
        (out / "ltc_published.json").write_text(json.dumps(cmp, indent=2, default=str))
        parts.append("## glossrt's fit vs the published table\n\n" + published_markdown(cmp))
    if polygons > 0:
        for dist in ("beckmann", "ggx"):
            print(f"accuracy ({dist}): {polygons} random polygons against the quadrature ...",
                  flush=True)
            acc = (cmp["polygons"]["glossrt"] if cmp and dist == "ggx"
                   else accuracy(polygons, distribution=dist))
            (out / f"ltc_accuracy_{dist}.json").write_text(json.dumps(acc, indent=2,
                                                                      default=str))
            parts.insert(0, f"## polygon_integral vs quadrature, {dist}\n\n"
                         + accuracy_markdown(acc))
    print(f"images at {size[0]}x{size[1]}, references {spp} spp ...", flush=True)
    res = images(size=size, ref_spp=spp, textured=True, progress=print)
    res.montage(out / "ltc_images.png")
    parts.append(f"## LTC vs Monte Carlo ({size[0]}x{size[1]}, {spp} spp)\n\n{res.markdown()}")
    return finish_experiment(out, "ltc", "\n\n".join(parts), "ltc_images.png")
