"""Converged references as sample blocks: work items for :mod:`glossrt.cluster`.

A reference frame of ``spp`` samples is split into blocks of consecutive sample indices
(:func:`block_plan`, which depends only on ``spp`` and the image size). Sample ``s`` of pixel
``p`` is seeded ``tea(s, frame_seed(frame, seed, REFERENCE_SALT))``, the seeds of
:meth:`Renderer.render_reference`, so a block's samples depend only on the frame's seed and
the block's index. A block returns its per-pixel mean (accumulated in float64 on the worker,
NumPy's pairwise sum over a fixed shape); :class:`BlockMerge` merges the blocks of a frame
by sample-weighted mean in block order, in float64. The result is therefore bit-identical
whatever the number of workers (none included) and whatever the order in which the blocks
finish; it differs from :meth:`Renderer.render_reference` only by float32 rounding (that
one sums the same samples in float32 on the device).

Items and results are plain data (dicts of numbers, strings and NumPy arrays): the scene
travels as its built-in name, or as its XML and the files it references
(:func:`glossrt.scenefiles.bundle`, put once into the cluster's object store by
:func:`reference_frames`, unpacked once per node by :func:`glossrt.scenefiles.materialise`:
no shared folder needed), plus the load arguments; every worker process loads it once
(:func:`render_reference_block` keeps the last renderer). Without a cluster nothing is
packed: the driver's renderer serves the blocks.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable, Iterator, Sequence

import numpy as np

from ..backend import mi
from ..errors import GlossrtError
from ..frame import Frame
from ..progress import Progress
from . import (
    COMPONENTS,
    GBUFFER_OUT,
    MAX_LANES,
    RADIANCE_OUT,
    REFERENCE_SALT,
    Renderer,
    frame_seed,
)

#: blocks per frame :func:`block_plan` aims at when the lane budget allows
TARGET_BLOCKS = 16

_CACHE: dict = {}


def block_plan(spp: int, width: int, height: int,
               block_spp: int | None = None) -> list[tuple[int, int]]:
    """``(first sample, sample count)`` of each block of a ``spp`` reference at
    ``width x height``: blocks of ``block_spp`` samples (default: about
    :data:`TARGET_BLOCKS` blocks, one device launch of at most :data:`MAX_LANES` lanes
    each), the last one shorter."""
    if spp < 1:
        raise GlossrtError(f"spp must be >= 1, got {spp}")
    cap = max(1, MAX_LANES // max(width * height, 1))
    if block_spp is None:
        block_spp = min(cap, math.ceil(spp / TARGET_BLOCKS))
    elif block_spp < 1:
        raise GlossrtError(f"block spp must be >= 1, got {block_spp}")
    return [(s, min(block_spp, spp - s)) for s in range(0, spp, block_spp)]


def _job_key(job: dict) -> tuple:
    """What identifies a job's renderer (the cached one is reused when it matches)."""
    return tuple(sorted((k, repr(v)) for k, v in job.items()))


def _renderer(job: dict) -> Renderer:
    key = _job_key(job)
    if _CACHE.get("key") != key:
        from .. import scenes

        _CACHE.clear()
        size = tuple(job["size"]) if job.get("size") else None
        scene = job["scene"]
        if job.get("scene_files") is not None:  # the XML and its files, shipped
            from ..cluster import local_scene

            scene = local_scene(job["scene_files"])
        if job.get("static"):  # the animation removed (scenes.load_static)
            setup = scenes.load_static(scene, size=size)
        else:
            setup = scenes.load(scene, size=size, orbit=job.get("orbit"),
                                frames=job.get("frames", 1))
        _CACHE["renderer"] = Renderer(setup, max_depth=job.get("max_depth"),
                                      seed=job.get("seed", 0), frozen=False)
        _CACHE["key"] = key
    return _CACHE["renderer"]


def render_reference_block(item: dict) -> dict:
    """One block of a reference frame (a work item, see the module). ``item``: ``job`` (the
    scene: ``scene``, ``size``, ``orbit``, ``frames``, ``max_depth``, ``seed``, and
    ``static``: true for :func:`glossrt.scenes.load_static`'s setup; see
    :func:`reference_job`; on a cluster also ``scene_files``, see :func:`shipped_job`),
    ``frame``, ``start`` and ``count`` (its samples). Returns
    ``count``, ``nonfinite`` (samples replaced by 0), ``mean`` (name -> (H, W, 3) float32
    per-pixel mean of each radiance channel) and, for the block of sample 0, ``gbuffer``
    (sample 0's G-buffer channels)."""
    import drjit as dr

    r = _renderer(item["job"])
    frame, start, count = int(item["frame"]), int(item["start"]), int(item["count"])
    w, h = r.width, r.height
    n_pix = w * h
    base = frame_seed(frame, r.seed, REFERENCE_SALT)
    k = max(1, min(count, MAX_LANES // max(n_pix, 1)))
    sums: dict[str, np.ndarray] = {}
    gbuf: dict[str, np.ndarray] = {}
    bad = 0
    done = 0
    while done < count:
        kk = min(k, count - done)
        lane = dr.arange(mi.UInt32, n_pix * kk)
        sample = lane % kk + (start + done)
        seeds = mi.sample_tea_32(sample, dr.opaque(mi.UInt32, base), 4)[0]
        out = r.trace(frame, lane // kk, seeds, frozen=False)
        bad += int(out["nonfinite"][0])
        for name in RADIANCE_OUT:  # lanes are pixel-major: pixel p owns lanes p*kk..
            part = np.array(out[name], dtype=np.float32).reshape(n_pix, kk, 3)
            s = part.sum(axis=1, dtype=np.float64)
            sums[name] = sums[name] + s if name in sums else s
        if start == 0 and not gbuf:
            for name in GBUFFER_OUT:
                c = COMPONENTS.get(name, 3)
                a = np.array(out[name], dtype=np.float32).reshape(n_pix, kk, c)[:, 0]
                gbuf[name] = np.ascontiguousarray(a.reshape(h, w, c))
        done += kk
    res = {"count": count, "nonfinite": bad,
           "mean": {n: (v / count).astype(np.float32).reshape(h, w, 3) for n, v in sums.items()}}
    if gbuf:
        res["gbuffer"] = gbuf
    return res


class BlockMerge:
    """The blocks of one reference frame, merged in block order (float64)."""

    def __init__(self) -> None:
        self.sums: dict[str, np.ndarray] = {}
        self.count = 0
        self.nonfinite = 0
        self.gbuffer: dict[str, np.ndarray] = {}

    def add(self, block: dict) -> None:
        c = int(block["count"])
        for name, m in block["mean"].items():
            s = m.astype(np.float64) * c
            self.sums[name] = self.sums[name] + s if name in self.sums else s
        self.count += c
        self.nonfinite += int(block["nonfinite"])
        self.gbuffer.update(block.get("gbuffer") or {})

    def frame(self, renderer: Renderer, index: int, seconds: float,
              block_spp: int) -> Frame:
        """The merged Frame (the header of :meth:`Renderer.render_reference`'s, plus
        ``meta["reference_block_spp"]``)."""
        n = self.count
        channels = {k: (v / n).astype(np.float32) for k, v in self.sums.items()}
        channels["color"] = (sum(self.sums[k] for k in RADIANCE_OUT) / n).astype(np.float32)
        channels.update(self.gbuffer)
        f = renderer._frame(index, {k: mi.TensorXf(v) for k, v in channels.items()}, n,
                            self.nonfinite, seconds, reference=True)
        f.meta["reference_block_spp"] = block_spp
        return f


def reference_frames(renderer: Renderer, job: dict, frames: Sequence[int], spp: int,
                     cluster=None, block_spp: int | None = None, desc: str = "",
                     stats: list | None = None) -> Iterator[Frame]:
    """The reference frames ``frames`` of ``spp`` samples, yielded in order as each one's
    blocks are merged; the blocks run on ``cluster`` (:func:`glossrt.cluster.map_items`;
    None: env ``GLOSSRT_CLUSTER``, else in this process). ``renderer``: the driver's (frame
    headers; its scene is ``job``'s, see :func:`render_reference_block`)."""
    from .. import cluster as _cluster

    plan = block_plan(spp, renderer.width, renderer.height, block_spp)
    bs = plan[0][1]
    with _cluster.connect(cluster) as c:
        job = shipped_job(job, c)
        items = [{"job": job, "frame": int(i), "start": s, "count": n}
                 for i in frames for s, n in plan]
        # in this process the driver's renderer serves the blocks (no second scene load)
        _CACHE.clear()
        _CACHE["key"] = _job_key(job)
        _CACHE["renderer"] = renderer
        merge = BlockMerge()
        t0 = time.perf_counter()
        try:
            for k, block in enumerate(_cluster.imap_items(
                    render_reference_block, items, cluster=c, desc=desc,
                    weights=[n for _, n in plan] * len(frames), stats=stats)):
                merge.add(block)
                if (k + 1) % len(plan) == 0:
                    yield merge.frame(renderer, int(frames[k // len(plan)]),
                                      time.perf_counter() - t0, bs)
                    merge = BlockMerge()
                    t0 = time.perf_counter()
        finally:
            _CACHE.clear()


def shipped_job(job: dict, cluster=None) -> dict:
    """``job`` as the workers of the open ``cluster`` get it: an XML scene's files packed
    (:func:`glossrt.scenefiles.bundle`) and their bytes put once into the cluster's object
    store (:func:`glossrt.cluster.share`) under ``scene_files``, so that a node without the
    driver's folders renders the same scene. Without a cluster, or for a built-in scene,
    ``job`` as it is."""
    from .. import cluster as _cluster

    if job.get("scene_files") is not None:
        return job
    shipped = _cluster.ship_scene(job["scene"], cluster)
    return job if shipped is job["scene"] else dict(job, scene_files=shipped)


def reference_job(scene, size: Sequence[int] | None = None, *, frames: int = 1, orbit=None,
        max_depth: int | None = None, seed: int = 0, static: bool = False) -> dict:
    """The ``job`` of :func:`reference_frames` for a renderer of ``scenes.load(scene,
    size=size, orbit=orbit, frames=frames)`` (``static``: ``scenes.load_static(scene,
    size=size)``) and ``Renderer(setup, max_depth=max_depth, seed=seed)``: plain data a
    worker loads the same scene from (an XML path made absolute: workers start in folders
    of their own; on a cluster :func:`reference_frames` ships the file and what it
    references, :func:`shipped_job`)."""
    import os

    if not isinstance(scene, (str, os.PathLike)):
        raise GlossrtError("reference blocks need the scene by built-in name or XML path "
                           f"(each worker loads it itself), got {type(scene).__name__}")
    scene = os.fspath(scene)
    if os.path.isfile(scene):
        scene = os.path.abspath(scene)
    return {"scene": scene, "size": [int(x) for x in size] if size else None,
            "orbit": orbit, "frames": int(frames), "max_depth": max_depth, "seed": int(seed),
            "static": bool(static)}


def _cache_path(cache, job: dict, spp: int, blocks: bool, frame: int):
    """Where :func:`references` keeps reference ``frame`` of ``job`` at ``spp`` samples (the
    key: the job's plain fields, the sample count and the path, blocks or one process)."""
    import hashlib
    from pathlib import Path

    plain = {k: v for k, v in job.items() if k != "scene_files"}
    key = repr((sorted((k, repr(v)) for k, v in plain.items()), int(spp), bool(blocks)))
    digest = hashlib.sha1(key.encode()).hexdigest()[:16]
    return Path(cache) / f"reference_{digest}_{int(frame):04d}.exr"


def references(renderer: Renderer, job: dict, frames: Sequence[int], spp: int,
               cluster=None, desc: str = "", cache=None) -> list[Frame]:
    """The reference frames ``frames`` of ``spp`` samples for the experiments (issue 27).
    ``cluster`` None: :meth:`Renderer.render_reference` of each frame in this process, the
    path the experiments had before (about 1.1-2x faster in one process than blocks, and
    no block kernels to compile); otherwise (an open :class:`glossrt.cluster.Cluster`, or a
    spec, ``"none"`` for the blocks in this process) :func:`reference_frames`, whose result
    is the same whatever the cluster and differs from :meth:`Renderer.render_reference` only
    by float32 rounding (measured: at most 2.4e-7 relative on ``glossy-cornell``).
    ``job``: :func:`reference_job` of ``renderer``'s scene. ``cache``: a folder where each
    reference frame is written as soon as it is complete (atomically, :meth:`Frame.save`)
    and read back by a later call for the same job, sample count and path, so that a killed
    experiment keeps the references it had finished. ``desc`` names a progress bar of the
    samples on stderr (:class:`glossrt.progress.Progress`; in this process and on a cluster
    alike); ``""``: none."""
    frames = [int(i) for i in frames]
    paths = ({i: _cache_path(cache, job, spp, cluster is not None, i) for i in frames}
             if cache is not None else None)

    def make(todo: list[int]) -> Iterator[Frame]:
        if cluster is None:
            with Progress(len(todo) * spp, desc, enabled=bool(desc)) as bar:
                for k, i in enumerate(todo):
                    yield renderer.render_reference(
                        i, spp, progress=lambda d, _n, k=k: bar.update(k * spp + d))
            return
        if job.get("size") and tuple(job["size"]) != (renderer.width, renderer.height):
            raise GlossrtError(f"reference job size {job['size']} is not the renderer's "
                               f"{renderer.width}x{renderer.height}")
        yield from reference_frames(renderer, job, todo, spp, cluster=cluster, desc=desc)

    return cached_frames(frames, paths, make)


def cached_frames(frames: Sequence[int], paths: dict | None,
                  make: Callable[[list[int]], Iterable[Frame]]) -> list[Frame]:
    """Frames ``frames`` read from their files ``paths[i]`` where those exist, the others
    made by ``make(todo)`` (it yields them in ``todo``'s order) and each written to its file
    as soon as it is made (atomically, :meth:`Frame.save`), so that a killed run keeps what
    it had finished. ``paths`` None: nothing read or kept."""
    frames = [int(i) for i in frames]
    out = {i: Frame.load(p) for i, p in (paths or {}).items() if p.is_file()}
    todo = [i for i in frames if i not in out]
    if todo:
        for i, f in zip(todo, make(todo), strict=True):
            out[i] = f
            if paths is not None:
                paths[i].parent.mkdir(parents=True, exist_ok=True)
                f.save(paths[i])
    return [out[i] for i in frames]
