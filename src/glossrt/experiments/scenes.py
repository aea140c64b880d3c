"""Scenes no one here wrote: glossrt's trial scenes, or a folder of Mitsuba XML files (such
as the documentation scenes of the ``mitsuba-renderer/mitsuba-data`` repository), through
every preset, measured against Mitsuba's own path tracer.

Per scene (:func:`evaluate_scene`):

* whether it loads, and Mitsuba's or glossrt's one line when not;
* **the transport against Mitsuba**: Mitsuba's ``path`` (the scene's ``max_depth`` and
  ``rr_depth``; depth 2 for the ``direct`` integrator) and glossrt's path tracer through the
  same film and sampler (the ``glossrt`` integrator plugin), ``spp`` samples each in
  :data:`BATCHES` independent batches: their image means and the z of the difference (each
  pixel's variance from its batches, pixels independent); the mean of glossrt's own
  renderer (pixel-centre rays) at 4 x 4 the resolution, box-filtered down (the pixel's
  area, as Mitsuba's film integrates it); and the mean of glossrt's converged pixel-centre
  reference, what the ``reference`` preset converges to (which differs from a box filter
  where bright detail is smaller than a pixel: lights seen or reflected at a few pixels);
* **every preset** (:data:`PRESETS`) over ``frames`` frames of the still scene: whether it
  runs, its seconds per frame (the last), its image mean and RMSE against the pixel-centre
  reference, which method took which light and the share of pixels left to the path
  tracer; and the 1 spp path-traced frame's RMSE (the floor a reconstruction must beat).

``glossrt experiment --which scenes [--scenes DIR] [-D NAME=VALUE]`` writes ``scenes.md``,
``scenes.json`` and ``scenes.png`` (per scene: reference, ``full``, 1 spp).
"""

from __future__ import annotations

import gc
import glob
import os
import re
import time
import warnings
from pathlib import Path

import numpy as np

from ..errors import GlossrtError
from ..report.registry import finish_experiment, register_experiment

#: the presets every scene goes through
PRESETS = ("schied2017", "okuno-iwasaki", "kimura-tokoi", "tokuyoshi2015", "full", "reference")
#: independent batches of the Mitsuba comparison
BATCHES = 4


def scene_files(folder: str | None) -> dict[str, str]:
    """The scenes to measure by name: glossrt's trial scenes (``folder`` None), else every
    ``*.xml`` directly in ``folder`` (sorted; ``<include>``d fragments live in subfolders)."""
    from ..scenes import trial_scenes

    if folder is None:
        return trial_scenes()
    if not os.path.isdir(folder):
        raise GlossrtError(f"--scenes: not a folder: {folder}")
    files = sorted(glob.glob(os.path.join(folder, "*.xml")))
    if not files:
        raise GlossrtError(f"--scenes: no .xml files in {folder}")
    return {os.path.splitext(os.path.basename(f))[0]: f for f in files}


def _used_parameters(path: str, seen: set | None = None) -> set[str]:
    """The ``$names`` a scene file and the files it includes use."""
    seen = set() if seen is None else seen
    path = os.path.abspath(path)
    if path in seen or not os.path.isfile(path):
        return set()
    seen.add(path)
    with open(path, errors="replace") as f:
        text = f.read()
    out = set(re.findall(r"\$(\w+)", text))
    for inc in re.findall(r"<include\s+filename=\"([^\"]+)\"", text):
        out |= _used_parameters(os.path.join(os.path.dirname(path), inc), seen)
    return out


def _tonemapped(img) -> np.ndarray:
    from ..report.page import tonemap

    return tonemap(np.nan_to_num(np.asarray(img, np.float32)))


def _mean_z(ours: np.ndarray, theirs: np.ndarray) -> list[float]:
    """z of the difference of two image means per channel from batches (K, H, W, 3)."""
    k = ours.shape[0]
    n = ours.shape[1] * ours.shape[2]
    diff = ours.mean(0).mean((0, 1)) - theirs.mean(0).mean((0, 1))
    var = (ours.var(0, ddof=1).sum((0, 1)) + theirs.var(0, ddof=1).sum((0, 1))) / k
    return [float(v) for v in diff / np.maximum(np.sqrt(var) / n, 1e-12)]


def evaluate_scene(name: str, path: str, size: tuple[int, int], spp: int, frames: int,
                   params: dict | None = None, choices: dict | None = None,
                   presets=PRESETS) -> dict:
    """One scene's row (module docstring) and its images (``_images``: reference, ``full``,
    1 spp; popped before JSON)."""
    from .. import pipeline, render, scenes
    from ..backend import mi
    from ..render import integrator  # noqa: F401  (registers "glossrt")

    row: dict = {"scene": name, "file": path}
    used = _used_parameters(path)
    given = {k: v for k, v in (params or {}).items() if k in used}
    t0 = time.perf_counter()
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            setup = scenes.load(path, size=size, params=given)
        row["warnings"] = [str(w.message) for w in caught]
        r = render.Renderer(setup)
    except GlossrtError as e:
        row.update(status="refused", why=str(e))
        return row
    md = r.mitsuba_max_depth
    row.update(status="ok", integrator=setup.integrator, max_depth=md, rr_depth=r.rr_depth,
               camera=setup.sensor_kind,
               emitters=sorted({kind for _, _, kind, _ in render.emitter_index(setup)}),
               bsdfs=sorted({scenes.bsdf_kind(s.bsdf()) for s in setup.shapes}))
    k = BATCHES
    per = max(1, spp // k)
    ours_i = mi.load_dict({"type": "glossrt", "max_depth": md})
    ours = np.stack([np.array(mi.render(setup.scene, sensor=setup.sensor, integrator=ours_i,
                                        spp=per, seed=11 + b))[..., :3] for b in range(k)])
    theirs = np.stack([np.array(r.render_mitsuba(0, spp=per, seed=101 + b))
                       for b in range(k)])
    ours, theirs = ours.astype(np.float64), theirs.astype(np.float64)
    ref = r.render_reference(0, spp=spp)
    ref_img = ref.numpy("color").astype(np.float64)
    z = _mean_z(ours, theirs)
    # the Renderer's own pixel-centre path at 4 x 4 the resolution, box-filtered down: the
    # pixel's area, as Mitsuba's film integrates it
    w, h = setup.size
    big = render.Renderer(scenes.load(path, size=(4 * w, 4 * h), params=given))
    ss = big.render_reference(0, spp=max(1, spp // 16)).numpy("color").astype(np.float64)
    ss = ss.reshape(h, 4, w, 4, 3).mean((1, 3))
    del big
    row.update(mitsuba_mean=float(theirs.mean()), film_mean=float(ours.mean()),
               film_z=max(z, key=abs), centre_mean=float(ref_img.mean()),
               supersampled_mean=float(ss.mean()),
               nonfinite=int(ref.meta["nonfinite_samples"]))
    one = r.render(0).numpy("color").astype(np.float64)
    row["floor_rmse"] = float(np.sqrt(np.mean((one - ref_img) ** 2)))
    images = {"reference": ref_img, "1 spp": one}
    row["presets"] = {}
    # one copy of the scene alive at a time, as in a user's process (two copies of some
    # scenes keep Dr.Jit from freezing the second one's kernels: docs/RESULTS.md)
    del setup, r, ref, ours_i
    gc.collect()
    for preset in presets:
        t = time.perf_counter()
        try:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                pipe = pipeline.Pipeline(scenes.load(path, size=size, params=given),
                                         preset=preset, progress=False, **(choices or {}))
                for i in range(frames):
                    t = time.perf_counter()
                    f = pipe.render(i)
            img = f.numpy("color").astype(np.float64)
            p = f.meta["pipeline"]
            row["presets"][preset] = {
                "ok": bool(np.isfinite(img).all()), "seconds": time.perf_counter() - t,
                "mean": float(img.mean()),
                "rmse": float(np.sqrt(np.mean((img - ref_img) ** 2))),
                "direct": p["direct"], "lights": pipe.plan.summary(),
                "fallback_share": float(p["fallback_share"]),
                "warnings": sorted({str(w.message) for w in caught
                                    if "thinlens" not in str(w.message)})}
            if preset == "full":
                images["full"] = img
            del pipe, f
        except GlossrtError as e:
            row["presets"][preset] = {"ok": False, "why": str(e)}
        gc.collect()
    row["seconds"] = time.perf_counter() - t0
    row["_images"] = images
    return row


def _fmt(v, spec: str = ".4f") -> str:
    return "-" if v is None else format(v, spec)


def markdown(rows: list[dict], presets=PRESETS) -> str:
    """The table of RESULTS.md: one line per scene."""
    head = ("| scene | loads | integrator (depth) | Mitsuba `path` mean | glossrt via film "
            "(z) | glossrt 4x4 supersampled | pixel-centre reference | presets that run | "
            "`full` RMSE | 1 spp RMSE | `full`: lights | `full`: fallback pixels |")
    lines = [head, "|" + "---|" * 12]
    for r in rows:
        if r["status"] != "ok":
            why = r["why"].replace("|", "/")
            if len(why) > 150:
                why = why[:147] + "..."
            lines.append(f"| {r['scene']} | no: {why} |  |  |  |  |  |  |  |  |  |  |")
            continue
        ran = [p for p in presets if r["presets"].get(p, {}).get("ok")]
        full = r["presets"].get("full", {})
        lines.append(
            f"| {r['scene']} | yes | {r['integrator']} ({r['max_depth']}) | "
            f"{r['mitsuba_mean']:.4f} | {r['film_mean']:.4f} ({r['film_z']:+.1f}) | "
            f"{r['supersampled_mean']:.4f} | {r['centre_mean']:.4f} | {len(ran)}/{len(presets)} | "
            f"{_fmt(full.get('rmse'))} | {r['floor_rmse']:.4f} | {full.get('lights', '-')} | "
            f"{100 * full.get('fallback_share', 0):.0f}% |")
    return "\n".join(lines)


def montage(path: Path, rows: list[dict]) -> Path | None:
    """Per scene that rendered: the pixel-centre reference, ``full`` and the 1 spp frame,
    two scenes per row of the PNG."""
    from ..report.figures import Panel
    from ..report.figures import montage as save

    cells = []
    for r in rows:
        imgs = r.get("_images")
        if not imgs:
            continue
        cells += [Panel(_tonemapped(imgs[k]), f"{r['scene']}: {k}" if k == "reference" else k,
                        fontsize=6) for k in ("reference", "full", "1 spp") if k in imgs]
    if not cells:
        return None
    grid = [cells[i:i + 6] for i in range(0, len(cells), 6)]
    return save(path, grid, figsize=(12.0, 1.5 * len(grid)))


@register_experiment("scenes", "every preset on scenes no one here wrote: glossrt's trial "
                     "scenes or every XML in --scenes DIR (e.g. mitsuba-data's docs/scenes; "
                     "-D NAME=VALUE for their $parameters), against Mitsuba's path (--size, "
                     "--spp, --frames, --resolution for BSPVT's trees)", order=90)
def run_experiment(out, size, args) -> int:
    from ..progress import Progress
    from ..scenes import parse_defines

    files = scene_files(getattr(args, "scenes", None))
    params = parse_defines(getattr(args, "define", None))
    frames = min(int(args.frames), 8)
    # BSPVT's trees at --resolution (the documentation scenes' meshes have up to ~35k
    # vertices: their visibility maps dominate the run otherwise)
    choices = {"bspvt_resolution": int(getattr(args, "resolution", 32))}
    rows = []
    with Progress(len(files), f"scenes {size[0]}x{size[1]}") as p:
        for i, (name, path) in enumerate(files.items()):
            rows.append(evaluate_scene(name, path, size, int(args.spp), frames, params,
                                       choices))
            p.update(i + 1)
    png = montage(out / "scenes.png", rows)
    ok = [r for r in rows if r["status"] == "ok"]
    every = [r for r in ok if all(r["presets"].get(p, {}).get("ok") for p in PRESETS)]
    md = (f"## {len(rows)} scenes at {size[0]}x{size[1]}, {args.spp} spp, {frames} frames, "
          f"BSPVT at resolution {choices['bspvt_resolution']}\n\n"
          f"{len(ok)} load; {len(every)} run in every preset.\n\n{markdown(rows)}")
    data = {"rows": [{k: v for k, v in r.items() if k != "_images"} for r in rows],
            "size": list(size), "spp": int(args.spp), "frames": frames}
    return finish_experiment(out, "scenes", md, png.name if png else "scenes.png", data)


__all__ = ["PRESETS", "evaluate_scene", "markdown", "montage", "scene_files"]
