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
  time (visibility rays + trees), data size, leaves per vertex;
* at the paper's scale (issue 28, ``--scale paper``): :func:`paper_table1` (the built-ins
  ``teapot-17k`` built in full, ``teapot-100k`` from a random sample of vertex chunks,
  :func:`sample_build`, extrapolated by :func:`extrapolate_build`) and :func:`epsilon_sweep`
  (leaves against visibility error; glossrt's quantitative analogue of the paper's fig. 4).

The paper's report section (``bspvt``), benchmark case (``bspvt``) and ``glossrt experiment
--which bspvt`` are registered here.
"""

from __future__ import annotations

import functools
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import GlossrtError
from ..report import DemoContext, Report, register_section
from ..report.registry import (
    BenchContext,
    benchmark,
    experiment_cluster,
    experiment_scale,
    finish_experiment,
    markdown_table,
    register_experiment,
    section_size,
)
from ..timing import round_robin

ALPHAS = (0.1, 0.25, 0.5, 1.0)
#: (teapot quads per patch side, floor grid, sphere rings) of the Table-1 densities
DENSITIES = {"coarse": (4, 24, 8), "default": (8, 48, 16), "fine": (12, 72, 24)}
METHODS = ("bspvt-vertex", "bspvt-pixel", "ratio", "ltc (no shadows)")


def _setup(alpha: float, size, density=DENSITIES["default"]):
    from .. import scenes
    from ..scenes.library import polygon_light_scene

    spec = polygon_light_scene(alpha, teapot_n=density[0], floor_n=density[1],
                               sphere_n=density[2])
    return scenes.from_spec(f"polygon-light-a{alpha:g}", spec, size=size)


#: the built-in scene with the default density's geometry (the alpha changes materials only)
_DEFAULT_SCENE = "polygon-light"


def _trees(setup, resolution: int, epsilon: float, cluster=None, progress: bool = False):
    """BSPVT trees of the default-density ``polygon-light`` ``setup``: in this process
    (``cluster`` None), or by vertex chunks on ``cluster`` (issue 27: the chunk items load the
    built-in :data:`_DEFAULT_SCENE` by name, whose vertices are checked to be ``setup``'s;
    the same trees as the one-process build). ``progress``: the build's progress bars on
    stderr."""
    from ..lights.bspvt import build_scene_trees, scene_vertices

    if cluster is None:
        return build_scene_trees(setup.scene, resolution, epsilon, progress=progress)
    trees = build_scene_trees(_DEFAULT_SCENE, resolution, epsilon, progress=progress,
                              cluster=cluster)
    if not np.array_equal(trees.positions, scene_vertices(setup.scene)[0].astype(np.float32)):
        raise GlossrtError(f"{_DEFAULT_SCENE!r} does not have {setup.name}'s vertices: "
                           "its trees cannot be built on a cluster by name")
    return trees


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
        from ..report.figures import Panel, montage
        from ..report.page import tonemap

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
           progress: Callable[[str], None] | None = None, cluster=None) -> ShadowResults:
    """BSPVT, ratio estimator and unshadowed LTC against shadowed Monte Carlo (module
    docstring), ``frames`` of the moving light; trees built once per alpha (visibility does
    not depend on the material: built once, shared). ``cluster``: the trees are built by
    vertex chunks there (:func:`_trees`); None: in this process, as before."""
    from .. import render
    from ..lights.bspvt import shade_bspvt
    from ..lights.ltc import shade_frame
    from ..lights.mc import render_mc
    from ..lights.ratio import render_ratio
    from ..lights.scene import polygon_lights
    from ..lights.shading import fresnel_image

    say = progress or (lambda _m: None)
    res = ShadowResults(tuple(size), ref_spp, resolution)
    trees = None
    for a in alphas:
        setup = _setup(a, size)
        if trees is None:
            say(f"building trees (R = {resolution}) ...")
            trees = _trees(setup, resolution, epsilon, cluster, progress is not None)
        r = render.Renderer(setup)
        for fi in frames:
            say(f"alpha {a:g}, frame {fi}: shadowed and unshadowed Monte Carlo references "
                f"({ref_spp} spp)")
            gb = r.render(fi)
            lights = polygon_lights(setup, fi)
            f0 = fresnel_image(setup, gb)
            ref = render_mc(gb, lights, ref_spp, f0=f0, scene=setup.scene, seed=11)
            ref_u = render_mc(gb, lights, ref_spp, f0=f0, seed=11)
            say(f"alpha {a:g}, frame {fi}: {', '.join(METHODS)}")
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
            say(f"alpha {a:g}, frame {fi}: Mitsuba's direct integrator ({ref_spp} spp)")
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
    """The paper's Table 1 for ``polygon-light`` at each density (module docstring). Always
    built in this process, also under ``glossrt experiment --cluster``: the table is one
    machine's precomputation time per vertex, and the coarse and fine meshes have no
    built-in name a cluster's workers could load them by."""
    from ..lights.bspvt import build_scene_trees

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


@register_section("bspvt", order=70)
def section_bspvt(ctx: DemoContext, report: Report) -> None:
    t0 = time.perf_counter()
    scale, size = section_size(ctx, (96, 72), 4, (16, 12))
    spp = min(512, int(ctx.references[0].meta.get("spp", 256)) * 2) if ctx.references else 512
    res = max(8, int(16 * scale))
    small = scale < 1.0  # (tests run the demo tiny)
    out = images(alphas=(0.1,) if small else (0.1, 1.0), frames=(0,) if small else (0, 24),
                 size=size, resolution=res, ref_spp=spp, progress=ctx.say)
    s = report.section(
        "Polygon-light shadows: BSPVT",
        "Okuno & Iwasaki's binary space partitioning visibility trees on polygon-light "
        f"({size[0]}x{size[1]}, {res}x{res} cube maps per vertex, the moving light at frames "
        f"{', '.join(str(r['frame']) for r in out.rows[:2])}): mean absolute error against a "
        f"shadowed Monte Carlo reference ({spp} spp) of "
        "BSPVT per vertex (the paper's mode) and per pixel, the ratio estimator (Heitz, Hill & "
        "McGuire 2018, 4 spp, cross-bilateral denoised) and LTC without shadows, with the time "
        "per frame; the error split as in the paper's fig. 8 into LTC's (unshadowed LTC vs "
        "unshadowed Monte Carlo) and the visibility's. See docs/RESULTS.md for 64x64 maps.")
    markdown_table(s, out.markdown(), "mean absolute error (ms per frame)")
    markdown_table(s, out.direct_markdown(),
                   "against Mitsuba's own direct integrator (mean absolute error)")
    for k, im in out.images.items():
        s.images_row([(f"{k}: Monte Carlo", im["reference"]),
                      ("BSPVT per pixel", im["bspvt-pixel"]),
                      ("ratio estimator", im["ratio"]),
                      ("LTC, no shadows", im["ltc (no shadows)"])],
                     name=f"bspvt_{k.replace(' ', '_').replace(',', '')}")
        s.error_map(f"bspvt_err_{k.replace(' ', '_').replace(',', '')}", im["bspvt-pixel"],
                    im["reference"], caption=f"{k}: relative error of BSPVT per pixel")
    ctx.timings["BSPVT section"] = time.perf_counter() - t0


@benchmark("bspvt", order=70)
def bench_bspvt(ctx: BenchContext) -> dict:
    """Okuno & Iwasaki's BSPVT shadows on ``polygon-light`` (4965 vertices): precomputation
    (visibility rays and trees, 32x32 cube maps, 8x8 below 320 pixels wide: the 64x64
    default is in ``glossrt experiment --which bspvt``) per vertex, and shadowed shading of a
    frame at the bench size per vertex (the paper's mode) and per pixel, each with the
    one-kernel traversal (default), the per-level wavefront and frozen (the fused traversal
    replayed), with unshadowed LTC and the ratio estimator at 1 spp beside them, interleaved
    in one run; and the tree build alone with each array engine (NumPy, Dr.Jit) at 64x64 on
    512 vertices (``tree_engines``). GPU targets (issue 6): build 50x faster than the
    paper's 2.7 min for 17K vertices; per-vertex shading of 512x512 at 200 fps or more."""
    from .. import render, scenes
    from ..lights.bspvt import build_scene_trees, shade_bspvt
    from ..lights.ltc import shade_frame
    from ..lights.ratio import render_ratio
    from ..lights.scene import polygon_lights
    from ..lights.shading import fresnel_image

    w, h = ctx.size
    setup = scenes.load("polygon-light", size=(w, h))
    res = 32 if w >= 320 else 8  # tiny bench sizes (tests) build tiny maps
    t0 = time.perf_counter()
    trees = build_scene_trees(setup.scene, res, progress=False)
    build_s = time.perf_counter() - t0
    engines = _bench_engines(setup.scene, 64 if w >= 320 else 8, 512 if w >= 320 else 16)
    gb = render.Renderer(setup).render(0)
    lights = polygon_lights(setup, 0)
    f0 = fresnel_image(setup, gb)
    cases = {}
    for mode in ("vertex", "pixel"):
        for kind, kw in (("", {}), ("-wavefront", {"traversal": "wavefront"}),
                         ("-frozen", {"frozen": True})):
            cases[f"bspvt-{mode}{kind}"] = functools.partial(
                shade_bspvt, setup.scene, gb, trees, lights, mode,
                f0=f0 if mode == "pixel" else None, **kw)
    cases |= {"ltc": lambda: shade_frame(gb, lights, f0=f0),
              "ratio-1spp": lambda: render_ratio(gb, lights, setup.scene, spp=1, f0=f0)}
    times = round_robin(cases, 1, ctx.turns, ctx.min_sample)
    med = {k: statistics.median(v) for k, v in times.items()}
    st = trees.stats()
    return {"scene": "polygon-light", "size": [w, h], "vertices": st["vertices"],
            "resolution": res, "build_s": build_s,
            "build_ms_per_vertex": 1000 * build_s / st["vertices"],
            "visibility_s": trees.info["visibility_seconds"],
            "leaves_per_vertex": st["leaves_per_vertex"], "data_mb": st["data_mb"],
            "tree_engines": engines, "seconds": med}


def _bench_engines(scene, res: int, count: int) -> dict:
    """The tree build alone (visibility computed once) with each array engine on ``count``
    vertices spread over the scene at ``res`` x ``res`` maps: ms per vertex, the time
    extrapolated to the paper's 17K-vertex model (issue 6's GPU target: 2.7 min / 50 =
    3.24 s), and whether the engines' trees are identical."""
    from ..lights.bspvt import build as bspvt

    pos, nrm, _ = bspvt.scene_vertices(scene)
    sel = np.linspace(0, len(pos) - 1, min(count, len(pos))).astype(int)
    vis = bspvt.visibility_cubemaps(bspvt.occluders(scene), pos[sel], nrm[sel], res,
                                    progress=False)
    out, built = {"resolution": res, "vertices": len(sel), "target_s_17k": 2.7 * 60 / 50}, {}
    for engine in bspvt.ENGINES:
        bspvt.build_trees(vis[:2], progress=False, engine=engine)  # compile / warm up
        t0 = time.perf_counter()
        built[engine] = bspvt.build_trees(vis, progress=False, engine=engine)
        dt = time.perf_counter() - t0
        out[engine] = {"seconds": dt, "ms_per_vertex": 1000 * dt / len(sel),
                       "extrapolated_17k_s": dt / len(sel) * 17000}
    a, b = built["numpy"], built["drjit"]
    out["identical"] = all(np.array_equal(getattr(a, k), getattr(b, k))
                           for k in ("lines", "children", "leaf_value", "roots"))
    return out


@register_experiment("bspvt", "Okuno & Iwasaki shadows and Table 1 (--size, --spp, "
                     "--resolution; --scale paper: Table 1 on teapot-17k / teapot-100k and "
                     "the epsilon sweep)", order=40)
def run_experiment(out, size, args) -> int:
    """Okuno & Iwasaki measurements (RESULTS.md): shadow error per alpha and light position
    for BSPVT per vertex / per pixel, the ratio estimator and unshadowed LTC, and Table 1;
    ``--scale paper``: :func:`run_paper_scale` instead."""
    if experiment_scale(args) == "paper":
        return run_paper_scale(out, args)
    spp, resolution = args.spp, args.resolution
    res = images(size=size, ref_spp=spp, resolution=resolution, progress=print,
                 cluster=experiment_cluster(args))
    res.montage(out / "bspvt_images.png")
    rows = table1(resolution=resolution, progress=print)
    md = (f"## shadows vs Monte Carlo ({size[0]}x{size[1]}, {spp} spp, R = {resolution})\n\n"
          f"mean absolute error (time per frame)\n\n{res.markdown()}\n\n"
          f"## against Mitsuba's direct integrator ({spp} spp)\n\n{res.direct_markdown()}\n\n"
          f"## Table 1\n\n{table1_markdown(rows, resolution)}")
    return finish_experiment(out, "bspvt", md, "bspvt_images.png",
                             {"rows": res.rows, "table1": rows})


# -- paper scale (issue 28: Table 1 on meshes of the paper's size, the epsilon sweep) -----------

#: Okuno & Iwasaki, Table 1 (512x512 images, 64x64 maps, Xeon E5-2650 v4, multi-threaded CPU):
#: per scene, vertices, rendering speed, precomputation time, data size, leaves per vertex
PAPER_TABLE1 = (
    {"scene": "fig. 6 teapot", "vertices": "17K", "fps": "43.5", "build": "2.7 min",
     "data_mb": 23.1, "leaves_per_vertex": 105.8},
    {"scene": "fig. 7 bunny", "vertices": "138K", "fps": "1.8-10.0", "build": "1.2 h",
     "data_mb": 177.0, "leaves_per_vertex": 99.9},
    {"scene": "fig. 1 dragon", "vertices": "506K", "fps": "2.5", "build": "14.4 h",
     "data_mb": 837.8, "leaves_per_vertex": 127.9},
)
#: glossrt's built-in paper-size scenes (:data:`glossrt.scenes.library.PAPER_SIZE_DENSITIES`)
PAPER_SCENES = ("teapot-17k", "teapot-100k")
#: cluster start (``ray.init`` + node probe, about 5 s) plus a cold kernel compile per node
#: (about 10 s): ``t_start`` of docs/PERFORMANCE.md's model ``T = W / C + t_start + t_tail``
CLUSTER_START_S = 15.0
SWEEP_EPSILONS = (0.0, 1.0, 2.0, 4.0, 8.0, 16.0)


def sample_build(scene: str, n_sample: int, resolution: int = 64, epsilon: float = 0.0,
                 chunk_vertices: int = 100, seed: int = 0, cluster=None,
                 progress: bool = False) -> dict:
    """Build the trees of a seeded random sample of about ``n_sample`` vertices of the
    built-in ``scene``: ``ceil(n_sample / chunk_vertices)`` of its vertex chunks of
    ``chunk_vertices``, drawn without replacement (a cluster sample: each chunk loads the
    scene by name, on ``cluster``'s workers or in this process), and return the per-vertex
    means: ``seconds_per_vertex`` (the items' summed visibility + tree seconds: core-seconds
    on a cluster's one-CPU workers, this process's wall time without one), leaves, data bytes,
    plus the longest item's seconds per vertex and the totals. Each chunk is a contiguous
    vertex range, so many small chunks spread the sample over the mesh's parts."""
    from ..lights.bspvt import build as bspvt
    from ..lights.bspvt.scene import _map_items
    from ..scenes import load

    if not isinstance(scene, str):
        raise GlossrtError("sample_build needs a built-in scene name (the chunks load it)")
    if int(n_sample) != n_sample or n_sample < 1:
        raise GlossrtError(f"n_sample must be a positive integer, got {n_sample}")
    n_total = len(bspvt.scene_vertices(load(scene).scene)[0])
    items = bspvt.vertex_chunk_items(scene, n_total, resolution, epsilon, "batched",
                                     chunk_vertices)
    k = min(len(items), -(-int(n_sample) // int(chunk_vertices)))
    pick = np.sort(np.random.default_rng(seed).choice(len(items), k, replace=False))
    chosen = [items[i] for i in pick]
    if cluster is None:
        # load the scene into the items' per-process cache first, so the items' seconds are
        # the build's alone; a cluster's workers each load it once within their first item
        # (counted: a slight overestimate, as in the full build)
        bspvt._item_scene(scene)
    t0 = time.perf_counter()
    results = _map_items(bspvt.build_vertex_chunk, chosen, cluster, progress,
                         f"BSPVT sample {resolution}x{resolution}")
    wall = time.perf_counter() - t0
    n = sum(r["stop"] - r["start"] for r in results)
    item_s = [r["info"]["visibility_seconds"] + r["info"]["tree_seconds"] for r in results]
    per_item_v = [s / (r["stop"] - r["start"]) for s, r in zip(item_s, results, strict=True)]
    data = sum(sum(r[a].nbytes for a in ("lines", "children", "leaf_value", "roots"))
               for r in results)
    return {"scene": scene, "vertices_total": n_total, "vertices_sampled": n,
            "chunks_sampled": k, "chunk_vertices": int(chunk_vertices), "seed": seed,
            "resolution": resolution, "epsilon": float(epsilon), "wall_s": wall,
            "item_seconds": float(sum(item_s)),
            "seconds_per_vertex": float(sum(item_s)) / n,
            "max_item_seconds_per_vertex": max(per_item_v),
            "visibility_s": float(sum(r["info"]["visibility_seconds"] for r in results)),
            "leaves_per_vertex": sum(len(r["leaf_value"]) for r in results) / n,
            "bytes_per_vertex": data / n}


def extrapolate_build(sample: dict, workers: int = 1, chunk_vertices: int | None = None,
                      start_s: float | None = None) -> dict:
    """The full build of ``sample["vertices_total"]`` vertices from a :func:`sample_build`:
    leaves and data size scale with the vertices; the wall time follows docs/PERFORMANCE.md's
    cluster model ``T = W / C + t_start + t_tail`` with ``W`` = seconds per vertex x vertices,
    ``C`` = ``workers``, ``t_tail`` the slowest sampled item's seconds per vertex times
    ``chunk_vertices`` (default the chunked build's
    :data:`~glossrt.lights.bspvt.build.CHUNK_VERTICES`) and ``t_start``
    :data:`CLUSTER_START_S` on a cluster (``workers > 1``), 0 in one process."""
    from ..lights.bspvt.build import CHUNK_VERTICES

    v = sample["vertices_total"]
    c = max(int(workers), 1)
    chunk = CHUNK_VERTICES if chunk_vertices is None else int(chunk_vertices)
    work = sample["seconds_per_vertex"] * v
    tail = sample["max_item_seconds_per_vertex"] * min(chunk, v) if c > 1 else 0.0
    start = (CLUSTER_START_S if c > 1 else 0.0) if start_s is None else float(start_s)
    return {"vertices": v, "workers": c, "work_core_s": work,
            "build_s": work / c + start + tail,
            "ms_per_vertex": 1000 * sample["seconds_per_vertex"],
            "leaves_per_vertex": sample["leaves_per_vertex"],
            "leaves": sample["leaves_per_vertex"] * v,
            "data_mb": sample["bytes_per_vertex"] * v / 1e6}


def shading_ms(scene: str, trees, size=(512, 512), frames: int = 5) -> float:
    """Median ms of ``frames`` calls of frozen per-vertex BSPVT shading
    (``shade_bspvt(..., "vertex", frozen=True)``) of frame 0 of ``scene`` at ``size``, after
    two warm-up calls (recording and first replay); the G-buffer is rendered once."""
    from .. import render, scenes
    from ..lights.bspvt import shade_bspvt
    from ..lights.scene import polygon_lights

    setup = scenes.load(scene, size=tuple(size))
    gb = render.Renderer(setup).render(0)
    lights = polygon_lights(setup, 0)
    run = functools.partial(shade_bspvt, setup.scene, gb, trees, lights, "vertex",
                            frozen=True)
    for _ in range(2):
        run()
    return statistics.median(_timed(run)[1] for _ in range(max(1, frames)))


def paper_table1(resolution: int = 64, epsilon: float = 0.0, sample_vertices: int = 2000,
                 shade_size=(512, 512), cluster=None, seed: int = 0,
                 scenes=PAPER_SCENES, progress: Callable[[str], None] | None = None,
                 ) -> list[dict]:
    """Table 1 at the paper's sizes: ``scenes[0]`` (``teapot-17k``) built in full (by vertex
    chunks on ``cluster``, else in this process) with its frozen per-vertex shading time at
    ``shade_size``; ``scenes[1]`` (``teapot-100k``) from a :func:`sample_build` of
    ``sample_vertices`` vertices, extrapolated (:func:`extrapolate_build`, marked
    ``extrapolated``; its shading needs the full trees and is not measured)."""
    from ..lights.bspvt import build_scene_trees

    say = progress or (lambda _m: None)
    workers = cluster.cpus if cluster is not None else 1
    rows = []
    full, sampled = scenes[0], scenes[1:]
    say(f"{full}: full build (R = {resolution}, {workers} worker(s)) ...")
    t0 = time.perf_counter()
    trees = build_scene_trees(full, resolution, epsilon, progress=False, cluster=cluster)
    wall = time.perf_counter() - t0
    st = trees.stats()
    say(f"{full}: shading {shade_size[0]}x{shade_size[1]} ...")
    rows.append({"scene": full, "vertices": st["vertices"], "build_s": wall,
                 "workers": workers, "ms_per_vertex": 1000 * wall * workers / st["vertices"],
                 "leaves_per_vertex": st["leaves_per_vertex"], "data_mb": st["data_mb"],
                 "shade_ms": shading_ms(full, trees, shade_size), "extrapolated": False})
    del trees
    for name in sampled:
        say(f"{name}: sample build of {sample_vertices} vertices ...")
        s = sample_build(name, sample_vertices, resolution, epsilon, seed=seed,
                         cluster=cluster)
        ex = extrapolate_build(s, workers)
        rows.append({"scene": name, "vertices": s["vertices_total"], "build_s": ex["build_s"],
                     "workers": workers, "ms_per_vertex": ex["ms_per_vertex"],
                     "leaves_per_vertex": ex["leaves_per_vertex"], "data_mb": ex["data_mb"],
                     "shade_ms": None, "extrapolated": True, "sample": s})
    return rows


def _duration(s: float) -> str:
    return f"{s:.0f} s" if s < 120 else (f"{s / 60:.1f} min" if s < 7200 else f"{s / 3600:.1f} h")


def paper_table1_markdown(rows: list[dict], resolution: int, shade_size) -> str:
    out = ["| scene | vertices | build (wall) | workers | worker-ms / vertex | leaves / vertex | "
           f"data (MB) | shading {shade_size[0]}x{shade_size[1]} (ms / frame) |",
           "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        x = "*" if r["extrapolated"] else ""
        shade = "not measured" if r["shade_ms"] is None else f"{r['shade_ms']:.1f}"
        out.append(f"| {r['scene']} | {r['vertices']} | {x}{_duration(r['build_s'])}{x} | "
                   f"{r['workers']} | {r['ms_per_vertex']:.1f} | "
                   f"{x}{r['leaves_per_vertex']:.1f}{x} | {x}{r['data_mb']:.1f}{x} | {shade} |")
    for p in PAPER_TABLE1:
        out.append(f"| paper: {p['scene']} | {p['vertices']} | {p['build']} | multi-core CPU | "
                   f"- | {p['leaves_per_vertex']} | {p['data_mb']} | "
                   f"{p['fps']} fps (512x512) |")
    notes = [f"cube maps {resolution} x {resolution} per face, epsilon 0; worker-ms / vertex: "
             "build wall time x workers / vertices (one process with its own threads counts as "
             "one worker); per-vertex shading frozen (`shade_bspvt(..., frozen=True)`), frame "
             "0, median of 5 frames."]
    samp = [r for r in rows if r["extrapolated"]]
    if samp:
        s = samp[0]["sample"]
        notes.append(f"`*` extrapolated from a sample of {s['vertices_sampled']} vertices "
                     f"({s['chunks_sampled']} random chunks of {s['chunk_vertices']}, seed "
                     f"{s['seed']}): leaves and data scale with the vertices, build time by "
                     "docs/PERFORMANCE.md's model T = W / C + t_start + t_tail (W = measured "
                     "seconds per vertex x vertices); shading needs the full trees.")
    return "\n".join(out) + "\n\n" + "\n".join(notes)


def epsilon_sweep(scene: str = "teapot-17k", n_vertices: int = 300, epsilons=SWEEP_EPSILONS,
                  resolution: int = 64, seed: int = 0) -> list[dict]:
    """Leaves against error for several leaf thresholds ``epsilon`` (texels of eq. 3's
    one-sided error ``e(P) = min(ones, zeros)``; glossrt's analogue of the paper's fig. 4,
    which shows the original and the BSPVT maps of one dragon vertex): the visibility cube
    maps of ``n_vertices`` seeded random vertices of ``scene`` computed once, trees built at
    each epsilon, and against the exact maps: the fraction of texels the trees misclassify
    (leaf mean thresholded at 1/2) and the mean absolute visibility error (leaf mean
    against 0/1). With epsilon 0 both are 0 (exact reconstruction); a larger epsilon prunes
    the epsilon-0 tree (a cluster's split depends on the cluster alone), so leaves do not
    grow and the misclassified texels do not shrink (``min`` is subadditive)."""
    from .. import scenes
    from ..lights.bspvt import build as bspvt

    eps = [float(e) for e in epsilons]
    if not eps or any(not (e >= 0.0 and np.isfinite(e)) for e in eps):
        raise GlossrtError(f"epsilons must be finite and >= 0, got {list(epsilons)}")
    sc = scenes.load(scene).scene
    pos, nrm, _ = bspvt.scene_vertices(sc)
    k = min(int(n_vertices), len(pos))
    if k < 1:
        raise GlossrtError(f"n_vertices must be >= 1, got {n_vertices}")
    sel = np.sort(np.random.default_rng(seed).choice(len(pos), k, replace=False))
    vis = bspvt.visibility_cubemaps(bspvt.occluders(sc), pos[sel], nrm[sel], resolution,
                                    progress=False)
    exact = np.asarray(vis, np.float32).reshape(k, 6, resolution, resolution)
    bspvt.build_trees(vis[:1], progress=False)  # warm up (threads, first-call costs)
    rows = []
    for e in eps:
        t0 = time.perf_counter()
        trees = bspvt.build_trees(vis, e, positions=pos[sel], normals=nrm[sel],
                                  progress=False)
        dt = time.perf_counter() - t0
        rec = np.stack([trees.reconstruct(v) for v in range(k)])
        st = trees.stats()
        rows.append({"epsilon": e, "vertices": k, "leaves_per_vertex": st["leaves_per_vertex"],
                     "data_bytes_per_vertex": st["data_bytes"] / k,
                     "misclassified": float(np.mean((rec >= 0.5) != (exact >= 0.5))),
                     "mean_abs_error": float(np.mean(np.abs(rec - exact))),
                     "tree_ms_per_vertex": 1000 * dt / k})
    return rows


def epsilon_sweep_markdown(rows: list[dict], scene: str, resolution: int, seed: int) -> str:
    out = ["| epsilon (texels) | leaves / vertex | data (bytes / vertex) | misclassified texels | "
           "mean abs. visibility error | trees (ms / vertex) |", "|---|---|---|---|---|---|"]
    out += [f"| {r['epsilon']:g} | {r['leaves_per_vertex']:.1f} | "
            f"{r['data_bytes_per_vertex']:.0f} | {100 * r['misclassified']:.3f}% | "
            f"{r['mean_abs_error']:.5f} | {r['tree_ms_per_vertex']:.1f} |" for r in rows]
    return "\n".join(out) + (f"\n\n({rows[0]['vertices']} random vertices of {scene}, seed "
                             f"{seed}, cube maps {resolution} x {resolution}; errors against "
                             "the exact visibility maps at the texel centres)")


def plot_epsilon_sweep(path: str | Path, rows: list[dict]) -> Path:
    """Leaves per vertex against the misclassified texel fraction, one point per epsilon."""
    from ..report.figures import subplots

    fig, ax = subplots(1, 1, (5, 3.6))
    ax = ax[0, 0]
    x = [100 * r["misclassified"] for r in rows]
    y = [r["leaves_per_vertex"] for r in rows]
    ax.plot(x, y, "o-")
    for r, xi, yi in zip(rows, x, y, strict=True):
        ax.annotate(f"eps {r['epsilon']:g}", (xi, yi), textcoords="offset points",
                    xytext=(5, 4), fontsize=8)
    ax.set_xlabel("misclassified texels (%)")
    ax.set_ylabel("leaves per vertex")
    ax.set_title("BSPVT: leaves against visibility error (epsilon sweep)", fontsize=9)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=120)
    return path


def run_paper_scale(out: Path, args) -> int:
    """``glossrt experiment --which bspvt --scale paper``: :func:`paper_table1` (at
    ``--resolution``, on ``--cluster`` when given) and :func:`epsilon_sweep` on
    ``teapot-17k``."""
    resolution = args.resolution
    cluster = experiment_cluster(args)
    shade_size = (512, 512)
    sweep = epsilon_sweep(resolution=resolution, seed=0)
    print(epsilon_sweep_markdown(sweep, "teapot-17k", resolution, 0))
    plot_epsilon_sweep(out / "bspvt_epsilon_sweep.png", sweep)
    rows = paper_table1(resolution=resolution, shade_size=shade_size, cluster=cluster,
                        progress=print)
    md = (f"## Table 1 at the paper's size\n\n"
          f"{paper_table1_markdown(rows, resolution, shade_size)}\n\n"
          f"## epsilon sweep (leaves against error)\n\n"
          f"{epsilon_sweep_markdown(sweep, 'teapot-17k', resolution, 0)}")
    return finish_experiment(out, "bspvt_paper", md, "bspvt_epsilon_sweep.png",
                             {"table1": rows, "epsilon_sweep": sweep})
