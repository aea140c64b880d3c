"""The ``glossrt`` command line: info | render | light | bspvt | ltc-fit | denoise | compare
| experiment | demo | bench | view."""

from __future__ import annotations

import argparse
import errno
import json
import os
import re
import sys
import tempfile
import time
import warnings
import xml.etree.ElementTree as ET
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from .errors import GlossrtError
from .timing import MIN_SAMPLE, steady_median

EXAMPLES = """examples:
  glossrt info
  glossrt render glossy-cornell --out out/cornell --frames 16 --size 320x240
  glossrt render glossy-cornell --out out/cornell-ref --frames 16 --size 320x240 \\
      --reference --spp 1024 --every 4
  glossrt render scene.xml --out out/xml --frames 30 --orbit 20
  glossrt denoise out/cornell --method svgf --out out/cornell-svgf
  glossrt compare out/cornell-svgf out/cornell-ref --json metrics.json
  glossrt demo --out demo-out
  glossrt bench --json bench.json --size 640x360
  glossrt view polygon-light --pipeline full --size 320x180
"""


#: folders this run created (outermost first); :func:`main` removes those left empty when the
#: command fails, so a failed run leaves no empty output folder behind
_CREATED: list[Path] = []

#: peak memory of a render (measured on the 2-core CPU VM, docs/PERFORMANCE.md): the process'
#: base plus bytes per pixel, fitted to the peak RSS (getrusage) of `glossrt render
#: glossy-cornell` at 64x48 .. 1536x1152: 1 spp frames about 1100 B/px, --reference about
#: 1650 B/px over a base of 140-320 MB (a cold kernel cache measured the same: 550 MB at
#: 512x384 --reference); the larger, with a margin, is what every command's size check assumes
#: (a refusal means the render could not fit, not that it would be slow)
MEMORY_BASE = 400e6
MEMORY_PER_PIXEL = 2000.0

#: the largest seed (frame seeds are 32-bit: larger ones would wrap and repeat smaller ones)
SEED_MAX = 2**32 - 1


def memory_estimate(size: tuple[int, int]) -> float:
    """Bytes a render of ``size`` (W, H) needs at its peak (see :data:`MEMORY_PER_PIXEL`)."""
    return MEMORY_BASE + MEMORY_PER_PIXEL * size[0] * size[1]


def _available_memory() -> int | None:
    """Bytes of memory available to a new allocation (``MemAvailable`` of /proc/meminfo, else
    the free physical pages), None when unknown."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def _check_memory(size: tuple[int, int], what: str = "--size") -> None:
    """Refuse, before any work, an image size whose render cannot fit in the memory available."""
    need, avail = memory_estimate(size), _available_memory()
    if avail is not None and need > avail:
        raise GlossrtError(
            f"{what} {size[0]}x{size[1]} needs about {need / 1e9:.1f} GB of memory "
            f"({MEMORY_PER_PIXEL:.0f} bytes per pixel), but only {avail / 1e9:.1f} GB is "
            "available; choose a smaller size")


def _defines(args, remote: bool = False, why: str = "--cluster") -> dict[str, str]:
    """The scene parameters of ``-D NAME=VALUE`` (checked), refused with ``why`` where the
    scene is loaded by other processes (``remote``: they read the file as it is)."""
    from .scenes import parse_defines

    params = parse_defines(getattr(args, "define", None))
    if params and remote:
        raise GlossrtError(f"-D (scene parameters) cannot be combined with {why}: the "
                           "workers load the scene file as it is; give the values defaults "
                           "in the file (<default name=... value=.../>)")
    return params


def _check_seed(seed: int) -> None:
    if not 0 <= seed <= SEED_MAX:
        raise GlossrtError(f"--seed must be in 0..{SEED_MAX} (a 32-bit seed: larger values "
                           f"would wrap around to smaller seeds), got {seed}")


def _path_problem(path: str) -> str | None:
    """What is wrong with ``path`` as an output that ``Path.exists`` hides: a symbolic link loop
    or a link to nothing; None when nothing is."""
    if not os.path.islink(path):
        return None
    try:
        os.stat(path)
    except OSError as e:
        if e.errno == errno.ELOOP:
            return "is a symbolic link loop"
        return f"is a symbolic link to a missing target ({os.readlink(path)!r})"
    return None


def _make_dirs(p: Path) -> None:
    """``mkdir -p p``, remembering the outermost folder it created (for :data:`_CREATED`)."""
    missing = []
    q = p
    while not q.exists() and not os.path.islink(q) and q != q.parent:
        missing.append(q)
        q = q.parent
    for q in reversed(missing):
        try:
            q.mkdir()
        except FileExistsError:
            continue
        if not any(q.is_relative_to(c) for c in _CREATED):
            _CREATED.append(q)


def _writable_dir(path: str, inputs: tuple[str, ...] = ()) -> Path:
    """The output folder ``path``, created if missing and probed for writing; refused when it
    is empty, an existing file, a broken link, or one of the ``inputs`` folders (writing there
    would replace the inputs)."""
    if not path:
        raise GlossrtError("the output folder is an empty path")
    problem = _path_problem(path)
    if problem:
        raise GlossrtError(f"output folder {path!r} {problem}")
    p = Path(path)
    if p.exists():
        if not p.is_dir():
            raise GlossrtError(f"output folder {path!r} exists and is not a folder")
        for src in inputs:
            if os.path.samefile(p, src):
                raise GlossrtError(f"output folder {path!r} is the input folder {src!r}: its "
                                   "frames would be overwritten; choose another --out")
    try:
        _make_dirs(p)
        with tempfile.NamedTemporaryFile(dir=p, prefix=".glossrt-probe-"):
            pass
    except OSError as e:
        raise GlossrtError(f"output folder {path!r} is not writable: {e.strerror or e}") from None
    return p


def _output_file(path: str, what: str, keep: tuple[Path, ...] = ()) -> Path:
    """An output file ``path`` checked before any work: not empty, not a folder, not a broken
    link, not one of the files ``keep`` (inputs), never an existing EXR; its folder is created
    and probed for writing (a write that fails after the work would lose the work)."""
    if not path:
        raise GlossrtError(f"{what}: the output file is an empty path")
    problem = _path_problem(path)
    if problem:
        raise GlossrtError(f"{what}: {path!r} {problem}")
    p = Path(path)
    if p.is_dir():
        raise GlossrtError(f"{what}: {path!r} is a folder, not a file")
    if p.exists() and (p.suffix.lower() == ".exr"
                       or any(k.exists() and os.path.samefile(p, k) for k in keep)):
        raise GlossrtError(f"{what}: {path!r} is an input or an image; refusing to overwrite it")
    try:
        _make_dirs(p.parent)
    except OSError as e:
        raise GlossrtError(f"{what}: cannot create the folder of {path!r}: "
                           f"{e.strerror or e}") from None
    try:
        with tempfile.NamedTemporaryFile(dir=p.parent, prefix=f".{p.name}.probe-"):
            pass
    except OSError as e:
        raise GlossrtError(f"{what}: cannot write into the folder of {path!r} "
                           f"({e.strerror or e})") from None
    return p


def _scene_files(scene: str) -> list[Path]:
    """A scene's input files: an XML scene file and the files it names (``<include>``s,
    meshes, textures; relative names resolved against its folder as Mitsuba does, then the
    working folder), for the checks that no output replaces one. Built-in scenes: none."""
    if not os.path.isfile(scene):
        return []
    files: list[Path] = []
    todo, seen = [Path(scene)], set()
    while todo:
        f = todo.pop()
        real = f.resolve()
        if real in seen:
            continue
        seen.add(real)
        files.append(f)
        if f.suffix.lower() != ".xml":
            continue
        try:
            root = ET.parse(f).getroot()
        except (ET.ParseError, OSError, ValueError):
            continue
        for el in root.iter():
            name = (el.get("filename") if el.tag == "include" else
                    el.get("value") if el.tag == "string" and el.get("name") == "filename"
                    else None)
            if not name or "$" in name:
                continue
            for base in (f.parent, Path.cwd()):
                if (base / name).is_file():
                    todo.append(base / name)
                    break
    return files


def _refuse_overwrite(outputs, inputs, what: str) -> None:
    """Refuse (before any work) when an output path is one of the input files (the same file,
    also through links or another spelling)."""
    inputs = [Path(i) for i in inputs]
    for out in outputs:
        if not os.path.exists(out):
            continue
        for src in inputs:
            try:
                same = os.path.samefile(out, src)
            except OSError:
                continue
            if same:
                raise GlossrtError(f"{what}: {str(out)!r} is the input {str(src)!r}; writing "
                                   "there would replace it; choose another output")


def _refuse_inputs_inside(folder: str, inputs, suffixes: tuple[str, ...], what: str) -> None:
    """Refuse an output folder holding an input file that the command might write over (the
    folder gets files of the given ``suffixes``, in it or in subfolders)."""
    if not os.path.isdir(folder):
        return
    root = Path(folder).resolve()
    for src in inputs:
        real = Path(src).resolve()
        if real.is_relative_to(root) and real.suffix.lower() in suffixes:
            raise GlossrtError(f"{what}: the input {str(src)!r} lies in the output folder "
                               f"{folder!r}, which gets {'/'.join(suffixes)} files; move it "
                               "or choose another --out")


def _write_text(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` atomically (:func:`glossrt.fileio.replacing`)."""
    from .fileio import replacing

    with replacing(path) as tmp:
        Path(tmp).write_text(text)


def _warn_stale(out: Path, written: list[str]) -> None:
    """Warn about frame files in ``out`` that this run did not write (an earlier run's)."""
    new = set(written)
    stale = sorted(p.name for p in out.glob("frame_*.exr") if p.name not in new)
    if stale:
        shown = ", ".join(stale[:4]) + (", ..." if len(stale) > 4 else "")
        print(f"warning: {out} also holds {len(stale)} frame(s) from an earlier run that this "
              f"run did not write ({shown}); a sequence read from it mixes both",
              file=sys.stderr)


def cmd_info(args) -> int:
    from . import backend

    for k, v in backend.info().items():
        print(f"{k:10s} {v}")
    return 0


def cmd_render(args) -> int:
    from . import render, scenes
    from .frame import Frame, frame_filename
    from .progress import Progress

    if args.frames < 1:
        raise GlossrtError(f"--frames must be >= 1, got {args.frames}")
    if args.spp < 1:
        raise GlossrtError(f"--spp must be >= 1, got {args.spp}")
    if args.every < 1:
        raise GlossrtError(f"--every must be >= 1, got {args.every}")
    if args.start < 0:
        raise GlossrtError(f"--start must be >= 0, got {args.start}")
    _check_seed(args.seed)
    size = scenes.parse_size(args.size) if args.size else None
    if size is not None:
        _check_memory(size)
    reference = args.reference or args.mitsuba or args.spp > 1
    if args.max_depth is not None:
        from .render.pathtracer import resolve_max_depth

        try:
            resolve_max_depth(args.max_depth)
        except GlossrtError as e:
            raise GlossrtError(f"--max-depth: {e}") from None
    if args.pipeline is not None:
        return _render_pipeline(args, size)
    if args.set_options:
        raise GlossrtError("--set (pipeline options) goes with --pipeline")
    if args.outputs is not None:
        raise GlossrtError("--outputs (the channels a composed frame keeps) goes with "
                           "--pipeline")
    if args.bspvt is not None:
        raise GlossrtError("--bspvt (prebuilt BSPVT trees) goes with --pipeline")
    if args.bspvt_cache is not None:
        raise GlossrtError("--bspvt-cache (where built BSPVT trees are kept) goes with "
                           "--pipeline")
    if args.specaa is not None:
        from .specaa import parse_method

        parse_method(args.specaa)  # a bad name fails before any rendering
        if reference:
            raise GlossrtError("--specaa shades 1 spp frames; its supersampled reference is "
                               "`glossrt experiment --which specaa`")
    blocks = reference and not args.mitsuba
    if not blocks:
        _refuse_block_flags(args, "")
    else:
        from . import cluster

        cluster.parse(args.cluster)  # a bad spec fails before any work
        if args.block_spp is not None and args.block_spp < 1:
            raise GlossrtError(f"--block-spp must be >= 1, got {args.block_spp}")
    params = _defines(args, blocks and args.cluster is not None)
    todo = list(range(args.start, args.start + args.frames, args.every))
    _refuse_overwrite([Path(args.out) / frame_filename(i) for i in todo],
                      _scene_files(args.scene), "render --out")
    setup = scenes.load(args.scene, size=size, orbit=args.orbit, frames=args.frames,
                        params=params)
    if size is None:
        _check_memory(setup.size, "the scene's film size")
    r = render.Renderer(setup, max_depth=args.max_depth, seed=args.seed)
    spp = args.spp if (args.spp > 1 or not reference) else 256
    if blocks:
        return _render_reference_blocks(args, setup, r, size, todo, spp)
    out = _writable_dir(args.out)
    bad = 0
    tex_cache: dict = {}
    # (converged frames other than --mitsuba's went to the sample blocks above)
    desc = f"{'reference ' if args.mitsuba else ''}{setup.name} {setup.size[0]}x{setup.size[1]}"
    with Progress(len(todo) * (spp if args.mitsuba else 1), desc) as p:
        for k, i in enumerate(todo):
            if args.mitsuba:
                import mitsuba as mi

                img = r.render_mitsuba(i, spp, seed=args.seed)
                cam = setup.camera(i)
                f = Frame(channels={"color": mi.TensorXf(img)}, camera=cam,
                          prev_camera=setup.camera(i - 1) if i > 0 else cam, index=i,
                          meta={"scene": setup.name, "spp": spp, "reference": "mitsuba-path",
                                "max_depth": r.mitsuba_max_depth,
                                "max_depth_from": r.max_depth_from})
                p.update((k + 1) * spp)
            else:
                f = r.render(i)
                if args.specaa is not None:
                    _add_specaa(setup, f, i, args.specaa, tex_cache, r)
                p.update(k + 1)
            bad += int(f.meta.get("nonfinite_samples", 0))
            f.save(out / frame_filename(i))
    print(f"wrote {len(todo)} frame(s) to {out}")
    _warn_stale(out, [frame_filename(i) for i in todo])
    if bad:
        print(f"warning: {bad} non-finite radiance value(s) were replaced by 0 "
              "(counts per frame in the EXR header, meta.nonfinite_samples)", file=sys.stderr)
    return 0


def _render_reference_blocks(args, setup, r, size, todo, spp) -> int:
    """``render --reference``: frames as sample blocks (glossrt.render.blocks) on
    ``--cluster`` or in this process, bit-identical either way; ``--resume`` skips frames
    already written for the same request."""
    from . import cluster
    from .frame import Frame, frame_filename
    from .render import blocks

    plan = blocks.block_plan(spp, setup.size[0], setup.size[1], args.block_spp)
    job = blocks.reference_job(args.scene, size, frames=args.frames, orbit=args.orbit,
                               max_depth=args.max_depth, seed=args.seed)
    want = {"scene": setup.name, "spp": spp, "seed": args.seed,
            "max_depth": r.mitsuba_max_depth, "reference": True,
            "variant": _variant(), "reference_block_spp": plan[0][1]}
    skip = set()
    if args.resume:
        for i in todo:
            path = Path(args.out) / frame_filename(i)
            if not path.exists():
                continue
            f = Frame.load(path)
            have = {k: f.meta.get(k) for k in want}
            diff = [f"{k} {have[k]!r} (asked: {want[k]!r})" for k in want if have[k] != want[k]]
            if f.size != tuple(setup.size):
                diff.append(f"size {f.width}x{f.height} (asked: {setup.size[0]}x"
                            f"{setup.size[1]})")
            if f.index != i or f.camera != setup.camera(i):
                diff.append("its camera or frame index")
            if diff:
                raise GlossrtError(f"--resume: {path} was rendered for another request: "
                                   + "; ".join(diff) + " (another --out, or drop --resume)")
            skip.add(i)
    left = [i for i in todo if i not in skip]
    bad = 0
    desc = f"reference {setup.name} {setup.size[0]}x{setup.size[1]} {spp} spp"
    with cluster.connect(args.cluster) as c:  # an unreachable cluster fails before --out
        out = _writable_dir(args.out)
        for f in blocks.reference_frames(r, job, left, spp, cluster=c or "none",
                                         block_spp=args.block_spp, desc=desc):
            bad += int(f.meta.get("nonfinite_samples", 0))
            f.save(out / frame_filename(f.index))  # whole frames only (atomic)
    print(f"wrote {len(left)} frame(s) to {out}"
          + (f" ({len(skip)} complete one(s) kept: --resume)" if skip else ""))
    _warn_stale(out, [frame_filename(i) for i in todo])
    if bad:
        print(f"warning: {bad} non-finite radiance value(s) were replaced by 0 "
              "(counts per frame in the EXR header, meta.nonfinite_samples)", file=sys.stderr)
    return 0


def _refuse_block_flags(args, why: str) -> None:
    """The flags of ``render --reference``'s sample blocks, refused where no blocks are
    rendered (``why`` ends the line)."""
    for flag, given in (("--cluster", args.cluster), ("--resume", args.resume),
                        ("--block-spp", args.block_spp is not None)):
        if given:
            raise GlossrtError(f"{flag} goes with --reference (glossrt's converged frames, "
                               f"rendered as sample blocks){why}")


def _variant() -> str:
    from . import backend

    return backend.use()


def _bspvt_cache(value: str | None) -> bool | str:
    """``--bspvt-cache``: unset the user's cache folder (True), ``none`` no cache on disk
    (False), else the folder (glossrt.pipeline.Pipeline's ``bspvt_cache``)."""
    return True if value is None else False if value == "none" else value


def _render_pipeline(args, size) -> int:
    """``render --pipeline PRESET|FILE``: composed frames (glossrt.pipeline), every stage's
    layer as channels and the per-stage timings in the header (docs/FORMATS.md)."""
    from . import pipeline, scenes
    from .frame import frame_filename
    from .progress import Progress

    for flag, bad in (("--reference", args.reference), ("--mitsuba", args.mitsuba),
                      ("--specaa", args.specaa is not None)):
        if bad:
            raise GlossrtError(f"--pipeline composes 1 spp frames: {flag} does not apply "
                               "(the reference preset accumulates converged frames; "
                               "specaa: --set specaa=METHOD)")
    _refuse_block_flags(args, "; --pipeline renders its frames in order in this process")
    preset, choices = pipeline.parse(_pipeline_spec(args.pipeline))  # bad name or file
    outputs = (pipeline.check_outputs([k.strip() for k in args.outputs.split(",") if k.strip()])
               if args.outputs is not None else None)
    choices.setdefault("seed", args.seed)
    if args.max_depth is not None:
        choices.setdefault("max_depth", args.max_depth)
    choices.update(_set_options(args))
    if args.spp > 1:
        choices["spp"] = args.spp
    opts = pipeline.resolve(preset, **choices)
    if args.spp > 1 and not opts["accumulate"]:
        raise GlossrtError(f"--spp {args.spp}: pipeline {preset} composes 1 spp frames; "
                           "--spp sets the samples per frame of an accumulating pipeline "
                           "(--pipeline reference, or --set accumulate=true)")
    params = _defines(args)
    todo = list(range(args.start, args.start + args.frames, args.every))
    _refuse_overwrite([Path(args.out) / frame_filename(i) for i in todo],
                      _scene_files(args.scene) + ([Path(args.bspvt)] if args.bspvt else []),
                      "render --out")
    setup = scenes.load(args.scene, size=size, orbit=args.orbit, frames=args.frames,
                        params=params)
    if size is None:
        _check_memory(setup.size, "the scene's film size")
    # every refusal before work (a --bspvt file of another scene too)
    pipe = pipeline.Pipeline(setup, preset=preset, bspvt=args.bspvt, outputs=outputs,
                             bspvt_cache=_bspvt_cache(args.bspvt_cache), **choices)
    out = _writable_dir(args.out)
    desc = f"pipeline {preset} {setup.name} {setup.size[0]}x{setup.size[1]}"
    with Progress(len(todo), desc) as p:
        for k, i in enumerate(todo):
            pipe.render(i).save(out / frame_filename(i))
            p.update(k + 1)
    print(f"wrote {len(todo)} frame(s) to {out}")
    _warn_stale(out, [frame_filename(i) for i in todo])
    return 0


def _add_specaa(setup, frame, index: int, method: str, textures: dict,
                renderer) -> None:
    """Channel ``specaa``: the frame's direct light from the scene's point, directional and
    polygon lights with specular antialiasing ``method`` (glossrt.specaa); ``textures``: the
    prefiltered light textures, kept across frames. A scene without such lights (lit by an
    environment map or emitters glossrt does not shade analytically): the 1 spp path-traced
    direct light (``direct_diffuse + direct_specular``) traced again by ``renderer`` with
    the filtered roughness at the primary hit (``Renderer.render(roughness=...)``; per-pixel
    methods only), ``meta["specaa_source"] = "path-traced"``."""
    from . import specaa
    from .lights.analytic import analytic_lights
    from .lights.scene import polygon_lights
    from .lights.shading import f0_image

    polys = polygon_lights(setup, index)
    lights = analytic_lights(setup, index)
    if not lights and not polys:
        from .pipeline.stages import SpecAAStage

        if specaa.parse_method(method).per_light:
            raise GlossrtError(f"--specaa {method}: scene {setup.name!r} has no point, "
                               "directional or polygon lights, and this method filters per "
                               "light; the path-traced light takes a per-pixel method "
                               "(avgnormal, avgnormal-max, avgnormal-eig, projected)")
        stage = SpecAAStage(method)
        alpha = stage.filter(frame) if stage.filters else frame["roughness"]
        f = renderer.render(index, roughness=alpha)
        frame["specaa"] = f["direct_diffuse"] + f["direct_specular"]
        frame.meta["specaa"] = method
        frame.meta["specaa_source"] = "path-traced"
        return
    img = specaa.shade_tensor(frame, lights, polys, method, f0_image(setup, frame), frozen=True,
                              textures=textures)
    frame["specaa"] = img
    frame.meta["specaa"] = method


def cmd_denoise(args) -> int:
    import shutil

    from . import denoise
    from .frame import RADIANCE, Frame, load_sequence
    from .progress import Progress
    from .timing import timed_eval

    if not os.path.isdir(args.in_dir):
        raise GlossrtError(f"not a folder: {args.in_dir}")
    d = denoise.make(args.method)
    frames = load_sequence(args.in_dir, require=getattr(d, "needs", ()) or ("color",))
    names = [Path(f.source).name for f in frames]
    out = _writable_dir(args.out, inputs=(args.in_dir,))
    # frames go to a hidden folder first and into --out only when every frame is done, so a
    # failure part-way (bad input in a later frame) leaves --out as it was
    tmp = Path(tempfile.mkdtemp(dir=out, prefix=".glossrt-denoise-"))
    seconds = []
    bad_total = {"nonfinite": 0, "negative": 0}
    try:
        with Progress(len(frames), f"{args.method} {frames[0].width}x{frames[0].height}") as p:
            for k, f in enumerate(frames):
                img, secs = timed_eval(d, f)
                seconds.append(secs)
                channels = dict(f.channels)
                channels["color"] = img
                meta = dict(f.meta, denoiser=args.method, denoise_seconds=seconds[-1])
                meta.update(_radiance_problems(f, ("color", *RADIANCE), bad_total))
                g = Frame(channels=channels, camera=f.camera, prev_camera=f.prev_camera,
                          index=f.index, meta=meta)
                g.save(tmp / names[k])
                p.update(k + 1)
        for name in names:
            os.replace(tmp / name, out / name)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    print(f"wrote {len(frames)} frame(s) to {out}; {args.method}: "
          f"{1000 * steady_median(seconds):.1f} ms per frame (median, after the first)")
    _warn_stale(out, names)
    if bad_total["nonfinite"] or bad_total["negative"]:
        print(f"warning: the input frames have {bad_total['nonfinite']} non-finite (NaN/Inf) "
              f"and {bad_total['negative']} negative radiance value(s), which the denoiser "
              "does not take as light (counts per frame and channel in the EXR header, "
              "meta.input_nonfinite and meta.input_negative)", file=sys.stderr)
    return 0


def _radiance_problems(frame, channels, totals: dict) -> dict:
    """Counts of NaN/Inf and of negative values in ``frame``'s radiance ``channels`` (those
    it has), per channel, as output frame metadata (``input_nonfinite``, ``input_negative``:
    only nonzero counts); adds them to ``totals``."""
    import numpy as np

    nonfinite, negative = {}, {}
    for name in channels:
        if name not in frame.channels:
            continue
        a = frame.numpy(name)
        finite = np.isfinite(a)
        n_bad = int(np.count_nonzero(~finite))
        n_neg = int(np.count_nonzero(finite & (a < 0)))
        if n_bad:
            nonfinite[name] = n_bad
        if n_neg:
            negative[name] = n_neg
    totals["nonfinite"] += sum(nonfinite.values())
    totals["negative"] += sum(negative.values())
    meta = {}
    if nonfinite:
        meta["input_nonfinite"] = nonfinite
    if negative:
        meta["input_negative"] = negative
    return meta


def cmd_experiment(args) -> int:
    from .scenes import parse_size

    # which of --size / --spp the command line gave: a --scale paper run takes its paper's
    # values for the others (glossrt.experiments.lobes.run_paper reads args.explicit)
    args.explicit = {o for o in ("size", "spp", "frames") if getattr(args, o) is not None}
    args.size = EXPERIMENT_SIZE if args.size is None else args.size
    args.frames = 30 if args.frames is None else args.frames
    args.spp = EXPERIMENT_SPP if args.spp is None else args.spp
    for opt in ("frames", "spp", "ref_every", "static_frames"):
        if getattr(args, opt) < 1:
            raise GlossrtError(f"--{opt.replace('_', '-')} must be >= 1, got {getattr(args, opt)}")
    if args.published is not None and not os.path.isfile(args.published):
        raise GlossrtError(f"--published: no such file: {args.published}")
    if args.resolution < 1:
        raise GlossrtError(f"--resolution must be >= 1, got {args.resolution}")
    if args.polygons < 0:
        raise GlossrtError(f"--polygons must be >= 0, got {args.polygons}")
    from .report.registry import experiment_scale

    experiment_scale(args)  # a bad --scale: one line, before anything is written
    size = parse_size(args.size)
    _check_memory(size)
    if args.published is not None:
        _refuse_inputs_inside(args.out, [args.published], (".md", ".json", ".png", ".html"),
                              "experiment --out")
    from . import cluster

    spec = cluster.parse(args.cluster)  # a bad spec (or env GLOSSRT_CLUSTER) fails here
    run = {name: fn for name, _, fn in _experiments()}[args.which]
    # one Ray connection for the whole run; an unreachable cluster fails before --out exists.
    # The run reads it as args.cluster (glossrt.report.registry.experiment_cluster)
    with cluster.connect(spec) as c:
        out = _writable_dir(args.out)
        args.cluster = c
        return run(out, size, args)


def cmd_light(args) -> int:
    """Direct light from a scene's polygon lights per frame: LTC or Monte Carlo."""
    import matplotlib.image

    from . import render, scenes
    from .frame import Frame, frame_filename
    from .lights.scene import polygon_lights
    from .lights.shading import check_isotropic, fresnel_image
    from .progress import Progress
    from .report.page import tonemap

    if args.frames < 1:
        raise GlossrtError(f"--frames must be >= 1, got {args.frames}")
    if args.spp is None:
        args.spp = 1 if args.method == "ratio" else 64
    if args.spp < 1:
        raise GlossrtError(f"--spp must be >= 1, got {args.spp}")
    if args.samples < 1:
        raise GlossrtError(f"--samples must be >= 1, got {args.samples}")
    _check_seed(args.seed)
    trees = None
    if args.method == "bspvt":
        from .lights.bspvt import BSPVT

        if not args.bspvt:
            raise GlossrtError("--method bspvt needs --bspvt FILE (glossrt bspvt build)")
        trees = BSPVT.load(args.bspvt)
    size = scenes.parse_size(args.size) if args.size else None
    if size is not None:
        _check_memory(size)
    names = [frame_filename(i) for i in range(args.frames)]
    _refuse_overwrite([Path(args.out) / n for n in names]
                      + [Path(args.out) / (n.rsplit(".", 1)[0] + ".png") for n in names],
                      _scene_files(args.scene) + ([Path(args.bspvt)] if args.bspvt else []),
                      "light --out")
    setup = scenes.load(args.scene, size=size, frames=args.frames, params=_defines(args))
    if size is None:
        _check_memory(setup.size, "the scene's film size")
    if args.method != "mc":  # the Monte Carlo reference shades anisotropic lobes
        check_isotropic(setup)  # before any work or output
    # the G-buffer alone: the scene's integrator (its path depth) plays no part
    r = render.Renderer(setup, seed=args.seed, max_depth=1)
    out = _writable_dir(args.out)
    cache: dict = {}
    hl_state: dict = {}
    work = args.frames * (args.spp if args.method == "mc" else 1)
    desc = f"{args.method} {setup.name} {setup.size[0]}x{setup.size[1]}"
    times = []
    with Progress(work, desc) as p:
        for i in range(args.frames):
            gb = r.render(i)
            # (area lights on other shapes are not this command's: named once, left out)
            lights = polygon_lights(setup, i, skip=True)
            if i == 0:
                areas = sum(1 for e in setup.scene.emitters() if e.get_shape() is not None)
                if areas > len(lights):
                    warnings.warn(f"{setup.name}: {areas - len(lights)} area light(s) are not "
                                  "polygons (spheres, disks, curved meshes) and are left out "
                                  "(glossrt render --pipeline path-traces them)", stacklevel=1)
            if not lights:
                polygon_lights(setup, i)  # (an area light that failed says why, in one line)
                raise GlossrtError(f"{setup.name}: no polygon lights (area emitters on "
                                   "rectangles or small planar meshes) in this scene")
            f0 = fresnel_image(setup, gb)
            t0 = time.perf_counter()
            img = _shade_light(args, setup, i, gb, lights, f0, trees, cache, hl_state, p)
            times.append(time.perf_counter() - t0)
            ch = {k: gb[k] for k in ("albedo_diffuse", "normal", "position", "depth",
                                     "roughness", "distribution", "mesh_id", "motion")
                  if k in gb.names}
            ch["color"] = img
            meta = {"scene": setup.name, "method": args.method, "lights": len(lights),
                    "shadows": (args.method in ("bspvt", "ratio")
                                or (args.method == "mc" and not args.no_shadows)),
                    "spp": args.spp if args.method in ("mc", "ratio") else None,
                    "samples": args.samples if args.method == "highlight" else None,
                    "seconds": times[-1]}
            f = Frame(channels=ch, camera=gb.camera, prev_camera=gb.prev_camera, index=i,
                      meta=meta)
            name = frame_filename(i)
            f.save(out / name)
            matplotlib.image.imsave(out / (name.rsplit(".", 1)[0] + ".png"), tonemap(img))
    print(f"wrote {args.frames} frame(s) to {out}; {args.method}: "
          f"{1000 * steady_median(times):.1f} ms per frame (median)")
    _warn_stale(out, [frame_filename(i) for i in range(args.frames)])
    return 0


def _shade_light(args, setup, i: int, gb, lights, f0, trees, cache: dict, hl_state: dict, p):
    """Frame ``i``'s direct light by ``args.method`` (``glossrt light``), advancing the
    progress ``p``; ``cache``: prefiltered light textures, ``hl_state``: the highlight
    renderer, both kept across frames."""
    if args.method == "ltc":
        from .lights.ltc import shade_frame

        img = shade_frame(gb, lights, f0=f0, textures=cache)
        p.update(i + 1)
    elif args.method == "bspvt":
        from .lights.bspvt import shade_bspvt

        # per vertex the frozen (fused) traversal is fastest; per pixel, on the CPU,
        # the traced one-kernel traversal (docs/PERFORMANCE.md)
        img = shade_bspvt(setup.scene, gb, trees, lights, args.mode, f0=f0,
                          textures=cache, frozen=args.mode == "vertex")
        p.update(i + 1)
    elif args.method == "highlight":
        from .lights.highlights import HighlightRenderer

        if "hl" not in hl_state:
            hl_state["hl"] = HighlightRenderer(args.samples, args.distribution,
                                               args.sampling, not args.no_cull)
        hl = hl_state["hl"]
        img = hl(gb, lights, hl.maps(setup, i, lights), f0, i)
        p.update(i + 1)
    elif args.method == "ratio":
        from .lights.ratio import render_ratio

        img = render_ratio(gb, lights, setup.scene, spp=args.spp, f0=f0,
                           seed=args.seed + 7919 * i).image
        p.update(i + 1)
    else:
        from .lights import mc as lmc

        img = lmc.render_mc(gb, lights, args.spp, f0=f0,
                            scene=None if args.no_shadows else setup.scene,
                            seed=args.seed + 7919 * i,
                            progress=lambda d, n, i=i: p.update(i * n + d))
    return img


def cmd_bspvt(args) -> int:
    """glossrt bspvt build: Okuno & Iwasaki's precomputation for a scene, with Table-1 stats."""
    from . import scenes
    from .lights.bspvt import build_scene_trees

    if args.resolution < 1:
        raise GlossrtError(f"--resolution must be >= 1, got {args.resolution}")
    if args.chunk_vertices is not None and args.chunk_vertices < 1:
        raise GlossrtError(f"--chunk-vertices must be >= 1, got {args.chunk_vertices}")
    out = _output_file(args.out, "bspvt build --out", keep=tuple(_scene_files(args.scene)))
    cluster = _cluster_spec(args)
    chunked = cluster is not None or args.chunk_vertices is not None
    params = _defines(args, chunked, "--cluster or --chunk-vertices")
    # with a cluster (or --chunk-vertices) the build runs as vertex chunks that load the
    # scene by name or path themselves: the same trees, byte for byte
    trees = build_scene_trees(scenes.load(args.scene, params=params).scene if not chunked
                              else args.scene,
                              resolution=args.resolution, epsilon=args.epsilon,
                              method=args.method, progress=True, engine=args.engine,
                              cluster=cluster, chunk_vertices=args.chunk_vertices)
    trees.save(str(out))
    st = trees.stats()
    st["visibility_seconds"] = trees.info.get("visibility_seconds")
    st["file_bytes"] = out.stat().st_size
    print(json.dumps(st, indent=2, default=str))
    print(f"wrote {out}")
    return 0


def _cluster_spec(args) -> str | None:
    """``--cluster``, else the environment's ``GLOSSRT_CLUSTER``, checked
    (:func:`glossrt.cluster.parse`: one clear error for a bad spec); None: this process."""
    from . import cluster

    spec = cluster.parse(getattr(args, "cluster", None))
    return None if spec is None else str(spec)


def cmd_ltc_fit(args) -> int:
    from .lights.ltc import fit as ltc_fit

    if args.size is not None and args.size < 2:
        raise GlossrtError(f"--size must be >= 2, got {args.size}")
    _output_file(args.out, "ltc-fit --out")
    argv = ["--out", args.out, "--distribution", args.distribution, "--metric", args.metric]
    argv += ["--size", str(args.size)] if args.size else []
    cluster = _cluster_spec(args)  # rows as work items: the same table (fit.fit_table)
    argv += ["--cluster", cluster] if cluster is not None else []
    return ltc_fit.main(argv)


def cmd_compare(args) -> int:
    from .compare import compare_dirs, format_table

    for d in (args.out_dir, args.ref_dir):
        if not os.path.isdir(d):
            raise GlossrtError(f"not a folder: {d}")
    js = None
    if args.json is not None:
        # the frames compare reads (load_sequence: *.exr); an earlier run's JSON in a compared
        # folder is not an input and may be rewritten
        inputs = tuple(p for d in (args.out_dir, args.ref_dir) for p in Path(d).glob("*.exr"))
        js = _output_file(args.json, "compare --json", keep=inputs)
    res = compare_dirs(args.out_dir, args.ref_dir, channel=args.channel)
    print(format_table(res))
    if js is not None:
        _write_text(js, json.dumps(res, indent=2))
    return 0


def cmd_demo(args) -> int:
    from . import scenes
    from .demo import check_demo_args, run_demo

    size = scenes.parse_size(args.size)
    check_demo_args(size, args.frames, ref_spp=args.spp)
    _check_memory(size)
    _refuse_inputs_inside(args.out, _scene_files(args.scene), (".exr", ".png", ".html"),
                          "demo --out")
    scenes.load(args.scene, size=(8, 8))  # a bad scene fails before any output
    _writable_dir(args.out)
    path = run_demo(args.out, size=size, frames=args.frames, ref_spp=args.spp,
                    scene=args.scene)
    print(f"report: {path}")
    return 0


def cmd_bench(args) -> int:
    from . import bench
    from .scenes import parse_size

    size = parse_size(args.size)
    options = bench.parse_case_options(args.case_option)
    bench.check_args(repeats=args.repeats, warmup=args.warmup, min_sample=args.min_sample,
                     names=args.only or None, options=options)
    _check_memory(size)
    js = _output_file(args.json, "bench --json") if args.json is not None else None
    res = bench.run(args.only or None, size=size, repeats=args.repeats,
                    warmup=args.warmup, log=lambda s: print(s, file=sys.stderr),
                    min_sample=args.min_sample, options=options)
    text = json.dumps(res, indent=2)
    if js is not None:
        _write_text(js, text + "\n")
    print(text)
    return 0


def _set_options(args) -> dict:
    """The pipeline options of ``--set KEY=VALUE`` (repeatable): VALUE read as a TOML value
    (``2``, ``2.5``, ``true``, ``"svgf"``), a bare word as a string (``direct=ltc+ratio``);
    names and values checked later with the rest of the pipeline's choices."""
    import tomllib

    out: dict = {}
    for item in getattr(args, "set_options", None) or ():
        key, eq, text = item.partition("=")
        key = key.strip()
        if not eq or not key:
            raise GlossrtError(f"--set {item!r}: expected KEY=VALUE, e.g. --set taa=false")
        try:
            value = tomllib.loads(f"v = {text.strip()}")["v"]
        except tomllib.TOMLDecodeError:
            value = text.strip()
        out[key] = value
    return out


def _pipeline_spec(spec: str) -> str:
    """``--pipeline help`` prints the presets and options (``glossrt presets``) and exits."""
    if spec == "help":
        print(_presets_text())
        raise SystemExit(0)
    return spec


def _presets_text() -> str:
    from .pipeline import config

    lines = ["presets (options not named take the defaults below):"]
    for name, settings in config.PRESETS.items():
        lines.append(f"  {name}: " + ", ".join(f"{k}={_toml_value(v)}"
                                                for k, v in settings.items()))
    lines += ["", "options (--set KEY=VALUE, or a TOML file: docs/FORMATS.md; "
                  "examples/pipeline.toml):"]
    for name in config.OPTIONS:
        default = config.DEFAULTS[name]
        shown = "the scene's integrator's" if default is None else _toml_value(default)
        lines.append(f"  {name} = {config.range_text(name)}  (default {shown})")
        lines.append(f"      {config.HELP[name]}")
    return "\n".join(lines)


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    return f'"{v}"' if isinstance(v, str) else f"{v:g}" if isinstance(v, float) else str(v)


def cmd_presets(args) -> int:
    print(_presets_text())
    return 0


def cmd_view(args) -> int:
    """``glossrt view``: the live viewer until Ctrl-C or SIGTERM (glossrt.view)."""
    from . import scenes
    from .view import Viewer, serve

    size = scenes.parse_size(args.size)
    _check_memory(size)
    try:
        # checked first (options, files, host, port, the scene); the pipeline's construction
        # (BSPVT's trees) goes on in the viewer's thread after the URL is printed
        v = Viewer(args.scene, pipeline=_pipeline_spec(args.pipeline), size=size,
                   host=args.host, port=args.port, captures=args.captures, bspvt=args.bspvt,
                   params=_defines(args), bspvt_cache=_bspvt_cache(args.bspvt_cache),
                   **_set_options(args))
        print(f"glossrt view: {v.url}  ({args.scene}, {v.preset}, {size[0]}x{size[1]}; "
              f"captures into {v.captures}; Ctrl-C stops)", flush=True)
        if v.pipe is None:
            print("glossrt view: serving; the pipeline is being built, progress in the panel",
                  file=sys.stderr, flush=True)
        # stopped within 1 s: the render loop ended or was left mid-frame, no capture
        # half-written
        serve(v, timeout=1.0, stop_server=False)
    except KeyboardInterrupt:  # (before serve() took Ctrl-C over: the build may be running)
        print("glossrt: interrupted", file=sys.stderr, flush=True)
        os._exit(130)
    sys.stdout.flush()
    if v.error is not None:
        print(f"glossrt: error: {v.error}", file=sys.stderr, flush=True)
        os._exit(2)
    print("glossrt view: stopped", file=sys.stderr, flush=True)
    # no interpreter teardown: a frame still recording would hold it, and Dr.Jit's and
    # Mitsuba's shutdown alone takes about a second on the 2-core VM (the 2 s promise)
    os._exit(0)


class _Parser(argparse.ArgumentParser):
    """An argument parser whose help can end with text computed only when the help is shown
    (``render --help``'s list of built-in scenes imports the scene library)."""

    def __init__(self, *a, more_help=None, **kw):
        super().__init__(*a, **kw)
        self.more_help = more_help

    def format_help(self) -> str:
        text = super().format_help()
        return text + self.more_help() if self.more_help is not None else text


def _builtin_scenes_help() -> str:
    import textwrap

    from .scenes import BUILTIN, library  # noqa: F401  (library registers the scenes)

    width = max(len(n) for n in BUILTIN)
    return "\nbuilt-in scenes:\n" + "".join(
        textwrap.fill(BUILTIN[n][1], 96, initial_indent=f"  {n:{width}s}  ",
                      subsequent_indent=" " * (width + 4)) + "\n" for n in sorted(BUILTIN))


DEVICE_CHOICES = ["auto", "cpu", "gpu"]
DEVICE_HELP = "backend (default: env GLOSSRT_DEVICE or auto)"


#: ``glossrt experiment``'s --size and --spp when not given (and not --scale paper)
EXPERIMENT_SIZE, EXPERIMENT_SPP = "256x192", 1024


def _experiments() -> list:
    """``(name, help, fn)`` of every ``glossrt experiment --which`` run, each registered by its
    paper's module in :mod:`glossrt.experiments`."""
    from . import experiments
    from .report.registry import registered_experiments

    experiments.load_all()
    return registered_experiments()


def _arg(*flags: str, **kw) -> tuple[tuple[str, ...], dict]:
    """One ``add_argument`` call of the :data:`COMMANDS` table."""
    return flags, kw


def _which_arg() -> tuple[tuple[str, ...], dict]:
    """``experiment --which``: its choices and help from the experiments' registry."""
    runs = _experiments()
    return _arg("--which", choices=[name for name, _, _ in runs], default="denoisers",
                help="; ".join(f"{name}: {help_}" for name, help_, _ in runs))


@dataclass(frozen=True)
class Command:
    """One subcommand: its name, handler ``fn(args) -> int``, one-line help, example, its
    arguments (``_arg(...)`` specs, or a function returning one, called when the parser is
    built) and an optional ``more_help()`` appended to its ``--help``."""

    name: str
    fn: Callable[[argparse.Namespace], int]
    help: str
    example: str
    args: tuple = ()
    more_help: Callable[[], str] | None = None


_SEED = _arg("--seed", type=int, default=0, help=f"random seed, 0..{SEED_MAX}")
_DEFINE = _arg("-D", "--define", action="append", default=None, metavar="NAME=VALUE",
               help="a value for the scene file's $NAME parameter (as Mitsuba's -D), "
                    "repeatable: -D spp=16 -D res=64")
_SET = _arg("--set", action="append", default=None, metavar="KEY=VALUE", dest="set_options",
            help="a pipeline option over the preset or file, repeatable: --set "
                 "direct=ltc+ratio --set svgf_sigma_l=2 --set taa=false (TOML values; "
                 "`glossrt presets` lists every option with its range)")
_CLUSTER = _arg("--cluster", default=None, metavar="SPEC",
                help="run the work on Ray: local, local:N (N worker slots on this machine), "
                     "auto (the cluster `ray start --head` started here) or ray://HOST:PORT; "
                     "none = in this process (default: env GLOSSRT_CLUSTER, else none). "
                     "Same results either way")
_BSPVT_CACHE = _arg("--bspvt-cache", default=None, metavar="DIR|none",
                    help="where built BSPVT trees (direct=ltc+bspvt) are kept and found again "
                         "by later runs, keyed by the scene's geometry (default: "
                         "$XDG_CACHE_HOME/glossrt/bspvt, else ~/.cache/glossrt/bspvt; made "
                         "when first written); none: build them in every run")

#: every subcommand, in the order of ``glossrt --help``
COMMANDS: tuple[Command, ...] = (
    Command("info", cmd_info, "print variant, device, versions and the libLLVM in use",
            "glossrt info"),
    Command("render", cmd_render, "render 1 spp frames (or converged references) to EXR",
            "glossrt render glossy-cornell --out out/cornell --frames 8 --size 320x240", (
                _arg("scene", help="built-in scene name (listed below) or Mitsuba XML path"),
                _DEFINE,
                _arg("--out", required=True, help="output folder (one EXR per frame)"),
                _arg("--frames", type=int, default=1),
                _arg("--start", type=int, default=0, help="first frame index"),
                _arg("--every", type=int, default=1, help="render every k-th frame only"),
                _arg("--spp", type=int, default=1, help="samples per pixel (references)"),
                _arg("--size", help="WxH (default: the scene's film size)"),
                _arg("--orbit", type=float, default=None,
                     help="orbit the camera by DEG degrees in total over the frames "
                          "(scenes without their own animation)"),
                _arg("--max-depth", type=int, default=None,
                     help="Mitsuba max_depth, -1 = no limit (default: the scene file's "
                          "integrator's, <include>d files too; -1, Mitsuba's default, for a "
                          "file without one; 3 for the built-in scenes)"),
                _SEED,
                _arg("--reference", action="store_true",
                     help="converged frames (pixel-centre primary hits), --spp defaults to 256"),
                _arg("--specaa", default=None, metavar="METHOD",
                     help="also write channel 'specaa': direct light from the scene's point, "
                          "directional and polygon lights with specular antialiasing METHOD "
                          "(a scene lit only by an environment map or other emitters: the "
                          "path-traced direct light with the filtered roughness at the "
                          "primary hit) "
                          "(none, halfvector, halfvector-bbox, avgnormal, avgnormal-max, "
                          "avgnormal-eig, projected), optionally METHOD:kappa=K to clamp the "
                          "added roughness (e.g. avgnormal-eig:kappa=0.18; "
                          "projected:kappa=none)"),
                _arg("--mitsuba", action="store_true",
                     help="anti-aliased reference from Mitsuba's own path integrator "
                          "(color only)"),
                _CLUSTER,
                _arg("--resume", action="store_true",
                     help="--reference: keep the frames already in --out that were rendered "
                          "for the same request (refused when their header differs)"),
                _arg("--block-spp", type=int, default=None, metavar="N",
                     help="--reference: samples per work item (default: about 16 blocks per "
                          "frame); part of the result's identity, like --seed"),
                _arg("--pipeline", default=None, metavar="PRESET|FILE",
                     help="composed real-time frames (glossrt.pipeline): a preset "
                          "(schied2017, okuno-iwasaki, kimura-tokoi, tokuyoshi2015, full, "
                          "reference) or a TOML file; writes color plus every stage's layer "
                          "and the per-stage timings (docs/FORMATS.md)"),
                _SET,
                _arg("--bspvt", default=None, metavar="FILE",
                     help="--pipeline with direct=ltc+bspvt: prebuilt trees (`glossrt bspvt "
                          "build`) instead of building them; refused unless they fit the "
                          "scene"),
                _BSPVT_CACHE,
                _arg("--outputs", default=None, metavar="NAMES",
                     help="--pipeline: write only these channels, comma-separated (color "
                          "always; e.g. direct,indirect,normal); the others are freed as "
                          "soon as no later stage reads them (default: every channel and "
                          "layer)"),
            ), more_help=_builtin_scenes_help),
    Command("light", cmd_light,
            "direct light from the scene's polygon lights: LTC or a Monte Carlo reference",
            "glossrt light polygon-light --method ltc --frames 8 --size 320x240 --out out/ltc", (
                _arg("scene", help="built-in scene name or Mitsuba XML path"),
                _DEFINE,
                _arg("--method", choices=["ltc", "mc", "bspvt", "ratio", "highlight"],
                     default="ltc",
                     help="ltc: unshadowed LTC; mc: Monte Carlo reference; bspvt: LTC with "
                          "BSPVT shadows (needs --bspvt); ratio: LTC x denoised ratio of "
                          "shadowed to unshadowed 1-spp-per-sample estimates (Heitz 2018); "
                          "highlight: specular reflection of the lights' shapes through a light "
                          "environment map (Kimura & Tokoi 2004)"),
                _arg("--samples", type=int, default=4,
                     help="highlight: microfacet normals per pixel (the paper: 4)"),
                _arg("--distribution", choices=["ellipsoidal", "ggx"], default="ellipsoidal",
                     help="highlight: the paper's ellipsoidal distribution or GGX visible "
                          "normals with filtered importance sampling"),
                _arg("--sampling", choices=["texture", "hash", "regular"], default="texture",
                     help="highlight (ellipsoidal): normal texture with embedded random "
                          "numbers, per-pixel hash, or the 13-point regular pattern"),
                _arg("--no-cull", action="store_true",
                     help="highlight: no bounding-sphere culling"),
                _arg("--spp", type=int, default=None,
                     help="mc: samples per pixel, default 64 (each one light + one BRDF sample "
                          "per light); ratio: default 1"),
                _arg("--bspvt",
                     help="bspvt: trees built by `glossrt bspvt build` for this scene"),
                _arg("--mode", choices=["vertex", "pixel"], default="vertex",
                     help="bspvt: per-vertex shading (the paper's) or per-pixel"),
                _arg("--no-shadows", action="store_true", help="mc: no visibility (as LTC)"),
                _arg("--frames", type=int, default=1),
                _arg("--size", help="WxH (default: the scene's film size)"),
                _SEED,
                _arg("--out", required=True, help="output folder (EXR + PNG per frame)"),
            )),
    Command("bspvt", cmd_bspvt,
            "build BSPVT shadow trees for a scene (Okuno & Iwasaki; per-vertex cube maps)",
            "glossrt bspvt build polygon-light --out teapot.bspvt.npz --resolution 32", (
                _arg("action", choices=["build"]),
                _arg("scene", help="built-in scene name or Mitsuba XML path"),
                _DEFINE,
                _arg("--out", required=True, help="output .npz"),
                _arg("--resolution", type=int, default=64, help="cube-map face size (texels)"),
                _arg("--epsilon", type=float, default=0.0,
                     help="leaf threshold: misclassified texels per cluster"),
                _arg("--method", choices=["batched", "nelder-mead"], default="batched",
                     help="split-line search: glossrt's exact batched search or the paper's "
                          "Nelder-Mead (slow)"),
                _arg("--engine", choices=["numpy", "drjit"], default="numpy",
                     help="array engine of the batched search: NumPy threads, or Dr.Jit (the "
                          "device of --device; the same trees)"),
                _arg("--cluster", default=None, metavar="SPEC",
                     help="run vertex chunks on a Ray cluster: local[:N], auto or "
                          "ray://HOST:PORT (default: $GLOSSRT_CLUSTER, else this process); "
                          "the same trees"),
                _arg("--chunk-vertices", type=int, default=None, metavar="N",
                     help="vertices per work item of a chunked build (default 256 with "
                          "--cluster)"),
            )),
    Command("ltc-fit", cmd_ltc_fit,
            "fit glossrt's LTC table of a microfacet distribution (minutes)",
            "glossrt ltc-fit --distribution beckmann --out ltc_beckmann.npz", (
                _arg("--out", required=True, help="output .npz"),
                _arg("--size", type=int, default=None, help="table resolution (default 64)"),
                _arg("--distribution", choices=("ggx", "beckmann"), default="ggx",
                     help="the lobe's microfacet distribution (default ggx; Mitsuba's rough "
                          "plugins default to beckmann)"),
                _arg("--metric", choices=("l1", "l3"), default="l1",
                     help="error the fit minimises (default l1; l3: Heitz et al.'s)"),
                _arg("--cluster", default=None, metavar="SPEC",
                     help="fit table rows on a Ray cluster: local[:N], auto or "
                          "ray://HOST:PORT (default: $GLOSSRT_CLUSTER, else this process); "
                          "the same table"),
            )),
    Command("denoise", cmd_denoise,
            "denoise an EXR sequence (writes frames with the denoised color)",
            "glossrt denoise out/cornell --method svgf --out out/cornell-svgf", (
                _arg("in_dir",
                     help="folder of frame EXRs (glossrt's or any following FORMATS.md)"),
                _arg("--method", default="svgf",
                     choices=["svgf", "svgf-lobe", "svgf-spatial-variance", "atrous",
                              "atrous-temporal", "oidn", "optix"]),
                _arg("--out", required=True, help="output folder"),
            )),
    Command("experiment", cmd_experiment,
            "the denoiser comparison behind docs/RESULTS.md (quality, time, temporal error)",
            "glossrt experiment --out results --size 256x192 --frames 30 --spp 1024", (
                _arg("--out", required=True),
                _arg("--size", default=None,
                     help=f"default {EXPERIMENT_SIZE}; with --scale paper the paper's size "
                          "where the experiment has one (lobes: 640x360)"),
                _arg("--frames", type=int, default=None,
                     help="default 30; with --scale paper specaa: 60"),
                _arg("--ref-every", type=int, default=10),
                _arg("--spp", type=int, default=None,
                     help=f"reference samples per pixel, default {EXPERIMENT_SPP}; with "
                          "--scale paper the paper's where the experiment has one "
                          "(lobes: 4096)"),
                _arg("--static-frames", type=int, default=60),
                _which_arg,
                _arg("--scale", default="quick", metavar="{quick,paper}",
                     help="quick (default): the small runs measured on the 2-core machine; "
                          "paper: the papers' sizes (issue 28; bspvt: Table 1 on the "
                          "teapot-17k and teapot-100k scenes and the epsilon sweep)"),
                _arg("--resolution", type=int, default=64,
                     help="bspvt: cube-map face size of the visibility maps"),
                _arg("--polygons", type=int, default=2000,
                     help="ltc: random polygons for the accuracy statistics (0: skip)"),
                _arg("--scenes", default=None, metavar="DIR",
                     help="scenes: every .xml in DIR (e.g. mitsuba-data's docs/scenes; "
                          "default: glossrt's trial scenes)"),
                _DEFINE,
                _arg("--published", default=None,
                     help="ltc: path to ltc_code's fit/results/ltc.js (Heitz et al.'s table, "
                          "not shipped) to score it the same way as glossrt's"),
                _arg("--cluster", default=None, metavar="SPEC",
                     help="render the converged references (denoisers, lobes, pipeline) as "
                          "sample blocks and build the BSPVT trees (bspvt) by vertex chunks "
                          "on Ray: local[:N], auto or ray://HOST:PORT; none = in this "
                          "process as without it (default: env GLOSSRT_CLUSTER, else none)"),
            )),
    Command("compare", cmd_compare, "metrics of frames against references, per frame and mean",
            "glossrt compare out/cornell out/cornell-ref --json metrics.json", (
                _arg("out_dir"),
                _arg("ref_dir"),
                _arg("--channel", default="color",
                     help="the channel to score (default color); depth: background (+inf) "
                          "scores as equal where both frames have it, and each frame's "
                          "background_mismatch counts the pixels where only one has it"),
                _arg("--json", help="also write the results as JSON"),
            )),
    Command("demo", cmd_demo,
            "render a built-in sequence + references and write an HTML report",
            "glossrt demo --out demo-out", (
                _arg("--out", required=True),
                _arg("--scene", default="glossy-cornell"),
                _arg("--size", default="160x120"),
                _arg("--frames", type=int, default=8,
                     help="1 spp frames (at least 2: the report shows the motion from one "
                          "frame to the next)"),
                _arg("--spp", type=int, default=256, help="reference samples per pixel"),
            )),
    Command("view", cmd_view, "live viewer: watch and steer the frame pipeline in a browser",
            "glossrt view polygon-light --pipeline full --size 320x180", (
                _arg("scene", help="built-in scene name (listed below) or Mitsuba XML path"),
                _DEFINE,
                _arg("--pipeline", default="full", metavar="PRESET|FILE",
                     help="a preset (schied2017, okuno-iwasaki, kimura-tokoi, tokuyoshi2015, "
                          "full, reference) or a TOML pipeline file (default full)"),
                _arg("--size", default="320x180", help="WxH rendered (default 320x180)"),
                _arg("--host", default="127.0.0.1",
                     help="address to serve on (default 127.0.0.1, this machine only; "
                          "0.0.0.0 serves every network and prints a warning)"),
                _arg("--port", type=int, default=8080, help="port (default 8080)"),
                _arg("--captures", default="captures",
                     help="folder the Capture and Record buttons write EXRs into "
                          "(default ./captures, made at the first capture)"),
                _SET,
                _arg("--bspvt", default=None, metavar="FILE",
                     help="prebuilt BSPVT trees (glossrt bspvt build) for direct=ltc+bspvt; "
                          "refused unless they fit the scene"),
                _BSPVT_CACHE,
            ), more_help=_builtin_scenes_help),
    Command("presets", cmd_presets,
            "the pipeline presets' settings and every option with its range and default",
            "glossrt presets"),
    Command("bench", cmd_bench, "registered benchmarks (median of repeats), JSON out",
            "glossrt bench --json bench.json --size 640x360", (
                _arg("--json"),
                _arg("--size", default="640x360"),
                _arg("--repeats", type=int, default=9,
                     help="timed samples per case, >= 1 (side-by-side ratios take at least 3)"),
                _arg("--warmup", type=int, default=3, help="untimed calls first, >= 0"),
                _arg("--min-sample", type=float, default=MIN_SAMPLE, metavar="SECONDS",
                     help="time calls shorter than this in back-to-back batches (0: one call "
                          "per sample)"),
                _arg("--only", nargs="*", help="benchmark names"),
                _arg("--case-option", action="append", metavar="KEY=VALUE",
                     help="an option of a benchmark case, repeatable (e.g. pipeline_shrink=10: "
                          "the pipeline case at 1/10 of its sizes; see glossrt.bench."
                          "case_options)"),
            )),
)


def _add_command(sub, cmd: Command) -> argparse.ArgumentParser:
    """The subparser of ``cmd``, with its arguments and ``--device``."""
    p = sub.add_parser(cmd.name, help=cmd.help, description=cmd.help,
                       epilog=f"example:\n  {cmd.example}",
                       formatter_class=argparse.RawDescriptionHelpFormatter,
                       more_help=cmd.more_help)
    p.set_defaults(fn=cmd.fn)
    # also after the command (`glossrt render X --device cpu`); SUPPRESS: an option not
    # given here leaves the one given before the command
    p.add_argument("--device", choices=DEVICE_CHOICES, default=argparse.SUPPRESS,
                   help=DEVICE_HELP + "; also accepted before the command")
    for spec in cmd.args:
        flags, kw = spec() if callable(spec) else spec
        p.add_argument(*flags, **kw)
    return p


def build_parser() -> argparse.ArgumentParser:
    """The ``glossrt`` parser, one subparser per entry of :data:`COMMANDS`."""
    ap = _Parser(
        prog="glossrt", description="Real-time rendering of glossy surfaces (Mitsuba 3 + Dr.Jit).",
        epilog=EXAMPLES, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", choices=DEVICE_CHOICES, default=None, help=DEVICE_HELP)
    sub = ap.add_subparsers(dest="command", required=True, parser_class=_Parser)
    for cmd in COMMANDS:
        _add_command(sub, cmd)
    return ap


def _one_line_warning(message, category, filename, lineno, line=None) -> str:
    return f"glossrt: warning: {message}\n"


#: options whose value may start with "-" and a digit without being a number ("-64x48"):
#: argparse would take it for an option and say only "expected one argument"
_DASH_VALUES = ("--size",)


def _join_dash_values(argv: list[str]) -> list[str]:
    """``--size -64x48`` as ``--size=-64x48``, so the size check names the bad size."""
    out, i = [], 0
    while i < len(argv):
        if argv[i] in _DASH_VALUES and i + 1 < len(argv) and re.match(r"-\d", argv[i + 1]):
            out.append(f"{argv[i]}={argv[i + 1]}")
            i += 2
        else:
            out.append(argv[i])
            i += 1
    return out


def _remove_created() -> None:
    """After a failure: remove the folders this run created that hold no file (frames it
    finished, each written whole, are kept; no empty folder stays behind)."""
    while _CREATED:
        top = _CREATED.pop()
        for folder, _, _ in os.walk(top, topdown=False):
            try:
                os.rmdir(folder)
            except OSError:
                pass


def main(argv: list[str] | None = None) -> int:
    argv = _join_dash_values(list(sys.argv[1:] if argv is None else argv))
    args = build_parser().parse_args(argv)
    warnings.formatwarning = _one_line_warning  # library warnings as one line, no source
    _CREATED.clear()
    ok = False
    try:
        from . import backend

        backend.use(args.device)
        rc = args.fn(args)
        ok = rc == 0
        return rc
    except GlossrtError as e:
        print(f"glossrt: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("glossrt: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # (`glossrt presets | head`): the reader left; no traceback
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141
    finally:
        if not ok:
            _remove_created()
        _CREATED.clear()


if __name__ == "__main__":
    raise SystemExit(main())
