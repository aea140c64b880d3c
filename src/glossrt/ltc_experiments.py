"""Measurements behind docs/RESULTS.md for polygon lights with LTC (issue 5).

* :func:`accuracy`: :func:`glossrt.lights.ltc.polygon_integral` against the float64 area
  quadrature of the same BRDF (:mod:`glossrt.lights.quadrature`) for random quads and
  triangles, views and roughnesses: median / 90th / 99th percentile relative error;
* :func:`images`: LTC shading of ``polygon-light`` (per GGX alpha) against an unshadowed Monte
  Carlo reference of the same BRDF (:mod:`glossrt.lights.mc`): error, time per frame, and the
  Monte Carlo sample count that reaches LTC's error, with its time (side by side, one run).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

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


def accuracy(n: int = 2000, seed: int = 5, m: int = 400) -> dict:
    """Relative error statistics of LTC's polygon integral (see the module docstring);
    cases whose exact value is below 1e-3 of the largest are left out (relative error of
    nothing). Returns {"all": stats, 0.1: stats, ...} with stats median / p90 / p99 / count."""
    from .lights.ltc import polygon_integral
    from .lights.quadrature import polygon_quadrature

    cases = random_polygons(np.random.default_rng(seed), n)
    want = np.array([polygon_quadrature(v, wo, nn, a, m=m) for v, wo, nn, a in cases])
    got = np.zeros(len(cases))
    groups: dict[int, list[int]] = {}
    for i, c in enumerate(cases):
        groups.setdefault(len(c[0]), []).append(i)
    for idx in groups.values():
        got[idx] = polygon_integral(np.array([cases[i][0] for i in idx]),
                                    np.array([cases[i][2] for i in idx]),
                                    np.array([cases[i][1] for i in idx]),
                                    np.array([cases[i][3] for i in idx]), two_sided=False)
    alphas = np.array([c[3] for c in cases])
    sig = want > 1e-3 * want.max()
    rel = np.abs(got / np.where(sig, want, 1.0) - 1)

    def stats(mask):
        r = rel[mask & sig]
        med, p90, p99 = np.percentile(r, [50, 90, 99]) if r.size else (np.nan,) * 3
        return {"median": float(med), "p90": float(p90), "p99": float(p99),
                "count": int(r.size)}

    out = {"all": stats(np.ones(len(cases), bool))}
    for a in ALPHAS:
        out[a] = stats((alphas > 0.75 * a) & (alphas < 1.25 * a))
    return out


@dataclass
class LTCImageResults:
    size: tuple[int, int]
    ref_spp: int
    rows: list[dict] = field(default_factory=list)
    images: dict[str, np.ndarray] = field(default_factory=dict)

    COLUMNS = ["alpha", "LTC RMSE", "LTC mean rel. error", "LTC ms / frame",
               "MC spp for LTC's RMSE", "MC ms / frame at that spp", "MC time / LTC time"]

    def table(self) -> list[list]:
        return [[r["alpha"], r["rmse"], r["rel"], r["ltc_ms"], r["mc_spp"], r["mc_ms"],
                 r["mc_ms"] / r["ltc_ms"] if r["mc_ms"] else None] for r in self.rows]

    def markdown(self) -> str:
        lines = ["| " + " | ".join(self.COLUMNS) + " |", "|" + "---|" * len(self.COLUMNS)]
        for row in self.table():
            cells = ["-" if v is None else (str(v) if isinstance(v, int) else f"{v:.4g}")
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
           ref_spp: int = 1024, frame: int = 0, max_spp: int = 256,
           progress: Callable[[str], None] | None = None) -> LTCImageResults:
    """LTC vs unshadowed Monte Carlo on ``polygon-light-a<alpha>`` (module docstring)."""
    from . import render, scenes
    from .lights.ltc import shade_frame
    from .lights.mc import render_mc
    from .lights.scene import polygon_lights
    from .lights.shading import f0_image

    say = progress or (lambda _m: None)
    res = LTCImageResults(tuple(size), ref_spp)
    for a in alphas:
        name = f"polygon-light-a{a:.2g}" if a != 1.0 else "polygon-light-a1.0"
        say(f"{name}: G-buffer, LTC, Monte Carlo reference ({ref_spp} spp)")
        setup = scenes.load(name, size=size)
        gb = render.Renderer(setup).render(frame)
        lights = polygon_lights(setup, frame)
        f0 = f0_image(setup, gb)
        ltc, ltc_ms = _timed(lambda gb=gb, lights=lights, f0=f0: shade_frame(gb, lights, f0=f0))
        ref = render_mc(gb, lights, ref_spp, f0=f0, seed=1)
        hit = gb.numpy("mesh_id")[..., 0] > 0
        err = (ltc - ref)[hit]
        rmse = float(np.sqrt(np.mean(err**2)))
        rel = float(np.mean(np.abs(err)) / max(np.mean(np.abs(ref[hit])), 1e-12))
        mc_spp, mc_ms = None, None
        spp = 1
        while spp <= max_spp:
            img, ms = _timed(lambda spp=spp, gb=gb, lights=lights, f0=f0:
                             render_mc(gb, lights, spp, f0=f0, seed=7), repeats=1)
            if float(np.sqrt(np.mean(((img - ref)[hit]) ** 2))) <= rmse:
                mc_spp, mc_ms = spp, ms
                break
            spp *= 2
        res.rows.append({"alpha": a, "rmse": rmse, "rel": rel, "ltc_ms": ltc_ms,
                         "mc_spp": mc_spp, "mc_ms": mc_ms})
        res.images[f"alpha {a:g}: LTC"] = ltc
        res.images[f"alpha {a:g}: Monte Carlo {ref_spp} spp"] = ref
        res.images[f"alpha {a:g}: |LTC - MC|"] = np.abs(ltc - ref)
    return res
