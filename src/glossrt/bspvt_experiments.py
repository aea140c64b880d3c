"""Measurements behind docs/RESULTS.md for BSPVT shadows (Okuno & Iwasaki; issue 6).

* :func:`images`: on ``polygon-light`` per GGX alpha and frame of the moving light, the
  shadowed direct light of BSPVT per vertex and per pixel, the ratio estimator (Heitz, Hill &
  McGuire 2018) and unshadowed LTC against a shadowed Monte Carlo reference of the same BRDF:
  mean absolute error, times, and the error split into the LTC part (unshadowed LTC against
  unshadowed Monte Carlo) and the visibility part (BSPVT against unshadowed LTC times the
  reference's shadowed / unshadowed ratio: what is left once LTC's BRDF error is factored
  out), the paper's fig. 8; and each method and the Monte Carlo reference against Mitsuba's
  own ``direct`` integrator on the same scene (the yardstick users trust; it filters each
  pixel with a box, so the Monte Carlo column is the comparison's floor);
* :func:`table1`: the paper's Table 1 for a few mesh densities: vertices, precomputation
  time (visibility rays + trees), data size, leaves per vertex.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

ALPHAS = (0.1, 0.25, 0.5, 1.0)
#: (teapot quads per patch side, floor grid, sphere rings) of the Table-1 densities
DENSITIES = {"coarse": (4, 24, 8), "default": (8, 48, 16), "fine": (12, 72, 24)}
METHODS = ("bspvt-vertex", "bspvt-pixel", "ratio", "ltc (no shadows)")


def _setup(alpha: float, size, density=DENSITIES["default"]):
    from . import scenes
    from .scenes.library import polygon_light_scene

    spec = polygon_light_scene(alpha, teapot_n=density[0], floor_n=density[1],
                               sphere_n=density[2])
    return scenes.from_spec(f"polygon-light-a{alpha:g}", spec, size=size)


def _timed(fn):
    t0 = time.perf_counter()
    out = fn()
    return out, 1000.0 * (time.perf_counter() - t0)


@dataclass
class ShadowResults:
    size: tuple[int, int]
    ref_spp: int
    resolution: int
    rows: list[dict] = field(default_factory=list)
    images: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)

    COLUMNS = ["alpha", "frame", "method", "mean abs. error", "ms / frame"]

    def markdown(self) -> str:
        lines = ["| alpha | frame | " + " | ".join(METHODS) + " | LTC part | visibility part |",
                 "|" + "---|" * (len(METHODS) + 4)]
        for r in self.rows:
            cells = [f"{r['mae'][m]:.4f} ({r['ms'][m]:.0f} ms)" for m in METHODS]
            lines.append(f"| {r['alpha']:g} | {r['frame']} | " + " | ".join(cells)
                         + f" | {r['ltc_part']:.4f} | {r['vis_part']:.4f} |")
        return "\n".join(lines)

    def direct_markdown(self) -> str:
        """Every method and the Monte Carlo reference against Mitsuba's ``direct``
        integrator: mean absolute error over the pixels that see a non-emitting surface."""
        lines = ["| alpha | frame | Monte Carlo reference | " + " | ".join(METHODS) + " |",
                 "|" + "---|" * (len(METHODS) + 3)]
        for r in self.rows:
            d = r["direct"]
            lines.append(f"| {r['alpha']:g} | {r['frame']} | {d['mc']:.4f} | "
                         + " | ".join(f"{d[m]:.4f}" for m in METHODS) + " |")
        return "\n".join(lines)

    def montage(self, path: str | Path, eps: float = 1e-2) -> Path:
        """Per run: reference, BSPVT per pixel, its absolute error, unshadowed LTC's absolute
        error (paper fig. 8: upper row, and the lower row's error)."""
        from .report.figures import Panel, montage
        from .report.page import tonemap

        keys = list(self.images)
        w, h = self.size
        lum = np.array([0.2126, 0.7152, 0.0722])
        grid = []
        for k in keys:
            im = self.images[k]
            ref = im["reference"]
            vmax = max(float(np.percentile(ref, 99)), 1e-6) * 0.25
            grid.append([
                Panel(tonemap(ref), f"{k}: Monte Carlo {self.ref_spp} spp (shadows)",
                      fontsize=7),
                Panel(tonemap(im["bspvt-pixel"]), "BSPVT per pixel", fontsize=7),
                Panel(np.abs(im["bspvt-pixel"] - ref) @ lum, "|BSPVT - MC|", "magma", 0, vmax,
                      fontsize=7),
                Panel(np.abs(im["ltc (no shadows)"] - ref) @ lum, "|LTC without shadows - MC|",
                      "magma", 0, vmax, fontsize=7)])
        return montage(path, grid, (12, 12 * len(keys) * h / (4 * w) + 0.6 * len(keys)),
                       dpi=100)


def images(alphas=ALPHAS, frames=(0, 24), size=(128, 96), resolution: int = 32,
           epsilon: float = 0.0, ref_spp: int = 1024, ratio_spp: int = 4,
           progress: Callable[[str], None] | None = None) -> ShadowResults:
    """BSPVT, ratio estimator and unshadowed LTC against shadowed Monte Carlo (module
    docstring), ``frames`` of the moving light; trees built once per alpha (visibility does
    not depend on the material: built once, shared)."""
    from . import render
    from .lights.bspvt import build_scene_trees, shade_bspvt
    from .lights.ltc import shade_frame
    from .lights.mc import render_mc
    from .lights.ratio import render_ratio
    from .lights.scene import polygon_lights
    from .lights.shading import fresnel_image

    say = progress or (lambda _m: None)
    res = ShadowResults(tuple(size), ref_spp, resolution)
    trees = None
    for a in alphas:
        setup = _setup(a, size)
        if trees is None:
            say(f"building trees (R = {resolution}) ...")
            trees = build_scene_trees(setup.scene, resolution, epsilon, progress=False)
        r = render.Renderer(setup)
        for fi in frames:
            say(f"alpha {a:g}, frame {fi}: references ({ref_spp} spp) and methods")
            gb = r.render(fi)
            lights = polygon_lights(setup, fi)
            f0 = fresnel_image(setup, gb)
            ref = render_mc(gb, lights, ref_spp, f0=f0, scene=setup.scene, seed=11)
            ref_u = render_mc(gb, lights, ref_spp, f0=f0, seed=11)
            shade_bspvt(setup.scene, gb, trees, lights, "pixel", f0=f0)  # warm kernels
            runs = {
                "bspvt-vertex": lambda s=setup, g=gb, lt=lights, f=f0, t=trees: shade_bspvt(
                    s.scene, g, t, lt, "vertex", f0=f),
                "bspvt-pixel": lambda s=setup, g=gb, lt=lights, f=f0, t=trees: shade_bspvt(
                    s.scene, g, t, lt, "pixel", f0=f),
                "ratio": lambda s=setup, g=gb, lt=lights, f=f0, k=fi: render_ratio(
                    g, lt, s.scene, spp=ratio_spp, f0=f, seed=k).image,
                "ltc (no shadows)": lambda g=gb, lt=lights, f=f0: shade_frame(g, lt, f0=f)}
            out, ms = {}, {}
            for m, fn in runs.items():
                out[m], ms[m] = _timed(fn)
            hit = gb.numpy("mesh_id")[..., 0] > 0
            mae = {m: float(np.abs(out[m] - ref)[hit].mean()) for m in METHODS}
            # the yardstick: Mitsuba's own direct integrator (emitters' own pixels left out)
            direct = np.array(r.render_mitsuba(fi, ref_spp, integrator="direct"))
            surf = hit & ~(gb.numpy("emission").max(-1) > 0)
            vs_direct = {m: float(np.abs(out[m] - direct)[surf].mean()) for m in METHODS}
            vs_direct["mc"] = float(np.abs(ref - direct)[surf].mean())
            ltc = out["ltc (no shadows)"]
            frac = np.where(ref_u > 1e-4, ref / np.maximum(ref_u, 1e-4), 1.0)
            res.rows.append({
                "alpha": a, "frame": fi, "mae": mae, "ms": ms, "direct": vs_direct,
                "ltc_part": float(np.abs(ltc - ref_u)[hit].mean()),
                "vis_part": float(np.abs(out["bspvt-pixel"] - ltc * frac)[hit].mean())})
            res.images[f"alpha {a:g}, frame {fi}"] = {"reference": ref, **out}
    return res


def table1(densities: dict | None = None, resolution: int = 64, epsilon: float = 0.0,
           progress: Callable[[str], None] | None = None) -> list[dict]:
    """The paper's Table 1 for ``polygon-light`` at each density (module docstring)."""
    from .lights.bspvt import build_scene_trees

    say = progress or (lambda _m: None)
    rows = []
    for name, dens in (densities or DENSITIES).items():
        setup = _setup(0.25, (32, 24), dens)
        say(f"{name} {dens}: building (R = {resolution}) ...")
        trees = build_scene_trees(setup.scene, resolution, epsilon, progress=False)
        st = trees.stats()
        rows.append({"density": name, "vertices": st["vertices"],
                     "visibility_s": trees.info["visibility_seconds"],
                     "trees_s": trees.info["tree_seconds"],
                     "ms_per_vertex": 1000 * trees.info["total_seconds"] / st["vertices"],
                     "data_mb": st["data_mb"], "leaves_per_vertex": st["leaves_per_vertex"]})
    return rows


def table1_markdown(rows: list[dict], resolution: int) -> str:
    out = ["| mesh | vertices | visibility rays (s) | trees (s) | ms / vertex | data (MB) | "
           "leaves / vertex |", "|---|---|---|---|---|---|---|"]
    out += [f"| {r['density']} | {r['vertices']} | {r['visibility_s']:.1f} | {r['trees_s']:.1f} "
            f"| {r['ms_per_vertex']:.2f} | {r['data_mb']:.1f} | {r['leaves_per_vertex']:.1f} |"
            for r in rows]
    return "\n".join(out) + f"\n\n(cube maps {resolution} x {resolution} per face)"
