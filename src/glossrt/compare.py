"""Compare a directory of rendered frames with a directory of reference frames.

Frames are matched by file name: every frame in the output directory that has a reference
with the same file name is scored, so a reference set may be sparser than the output (for
example every 10th frame). The temporal error is computed over *all* output frames.

>>> result = compare_dirs("out/frames", "out/reference")      # doctest: +SKIP
>>> print(format_table(result))                                # doctest: +SKIP
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from . import metrics as _m
from .errors import GlossrtError

__all__ = ["METRICS", "compare_dirs", "format_table"]

#: Metrics :func:`compare_dirs` knows, by name: ``fn(image, reference) -> float``.
METRICS: dict[str, Callable[[Any, Any], float]] = {
    "rmse": _m.rmse,
    "relmse": _m.relmse,
    "ssim": _m.ssim,
    "flip": _m.flip,
}


def _load_sequence(directory: Path, channel: str) -> list[Any]:
    from .frame import load_sequence

    return load_sequence(directory, require=(channel,))


def _scored(values: np.ndarray, channel: str) -> np.ndarray:
    """A frame's channel as scored: ``depth``'s background (+inf by docs/FORMATS.md) is 0,
    so pixels that are background in both frames count as equal instead of failing the
    metrics' finite check. NaN, -inf and any other channel's non-finite values are still
    refused by the metrics."""
    if channel == "depth":
        return np.where(np.isposinf(values), np.float32(0.0), values)
    return values


def _file_name(frame: Any) -> str:
    if frame.source is None:
        raise GlossrtError(f"frame {frame.index} has no source file to match by name")
    return Path(frame.source).name


def compare_dirs(
    out_dir: str | Path,
    ref_dir: str | Path,
    channel: str = "color",
    metrics: Sequence[str] = ("rmse", "relmse", "ssim", "flip"),
) -> dict[str, Any]:
    """Score the frames of ``out_dir`` against same-named frames of ``ref_dir``.

    Returns a JSON-serialisable dict::

        {"out_dir": str, "ref_dir": str, "channel": str, "metrics": [names],
         "frames": [{"file": name, "index": int, "rmse": float, ...}, ...],
         "mean": {"rmse": float, ...},
         "temporal_error": float or None,   # over all output frames; None if fewer than 2
         "unmatched": int}                  # output frames without a reference

    ``channel="depth"``: background (+inf, docs/FORMATS.md) scores as 0, so pixels that are
    background in both frames count as equal, and each frame's row also has
    ``"background_mismatch"``: the pixels that are background in only one of the two (a
    silhouette difference, scored as the depth against 0). The SSIM and FLIP of a depth
    channel are those of the values shown as an image; RMSE and relMSE are the meaningful
    ones there.

    Raises :class:`GlossrtError` for an unknown metric, when no file names match (naming both
    directories), or (via the frame loader) when a directory holds no readable frames or
    frames of mismatched size.
    """
    names = list(metrics)
    unknown = [n for n in names if n not in METRICS]
    if unknown:
        raise GlossrtError(f"unknown metric(s) {unknown}; known: {sorted(METRICS)}")
    if not names:
        raise GlossrtError("no metrics requested")
    out_dir, ref_dir = Path(out_dir), Path(ref_dir)
    outs = _load_sequence(out_dir, channel)
    refs = {_file_name(f): f for f in _load_sequence(ref_dir, channel)}

    raws = [f.numpy(channel) for f in outs]  # read once: the rows and the temporal error
    rows: list[dict[str, Any]] = []
    for f, raw in zip(outs, raws, strict=True):
        name = _file_name(f)
        ref = refs.get(name)
        if ref is None:
            continue
        raw_ref = ref.numpy(channel)
        img, ref_img = _scored(raw, channel), _scored(raw_ref, channel)
        row: dict[str, Any] = {"file": name, "index": int(f.index)}
        if channel == "depth":  # background in only one of the two: a silhouette difference
            row["background_mismatch"] = int(np.count_nonzero(
                np.isposinf(raw) != np.isposinf(raw_ref)))
        for n in names:
            try:
                row[n] = float(METRICS[n](img, ref_img))
            except GlossrtError as e:
                raise GlossrtError(f"{name}: {e}") from e
        rows.append(row)
    if not rows:
        raise GlossrtError(
            f"no frame in {out_dir} has a reference with the same file name in {ref_dir}"
        )
    mean = {n: float(sum(r[n] for r in rows) / len(rows)) for n in names}
    temporal = None
    if len(outs) >= 2:
        temporal = _m.temporal_error([_scored(r, channel) for r in raws])
    return {
        "out_dir": str(out_dir),
        "ref_dir": str(ref_dir),
        "channel": channel,
        "metrics": names,
        "frames": rows,
        "mean": mean,
        "temporal_error": temporal,
        "unmatched": len(outs) - len(rows),
    }


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return "nan" if math.isnan(v) else f"{v:.5g}"
    return str(v)


def format_table(result: dict[str, Any]) -> str:
    """A plain-text table of :func:`compare_dirs`'s result: one line per frame, a mean line,
    and the temporal error."""
    names = list(result.get("metrics") or result["mean"].keys())
    extra = ["background_mismatch"] if any("background_mismatch" in r
                                           for r in result["frames"]) else []
    header = ["file", *names, *extra]
    body = [[r["file"], *(_fmt(r[n]) for n in names), *(_fmt(r.get(n, "")) for n in extra)]
            for r in result["frames"]]
    mean_row = [f"mean ({len(result['frames'])} frames)",
                *(_fmt(result["mean"][n]) for n in names), *("" for _ in extra)]
    table = [header, *body, mean_row]
    widths = [max(len(row[i]) for row in table) for i in range(len(header))]

    def line(row: list[str]) -> str:
        cells = [row[0].ljust(widths[0])]
        cells += [c.rjust(w) for c, w in zip(row[1:], widths[1:], strict=True)]
        return "  ".join(cells).rstrip()

    rule = "-" * len(line(header))
    out = [line(header), rule, *(line(r) for r in body), rule, line(mean_row)]
    te = result.get("temporal_error")
    out.append(f"temporal error (all output frames): {_fmt(te) if te is not None else 'n/a'}")
    if result.get("unmatched"):
        out.append(f"output frames without a reference: {result['unmatched']}")
    return "\n".join(out)
