"""Per-frame G-buffer and radiance channels, and their on-disk form: one multi-layer OpenEXR.

A :class:`Frame` holds named channels (``H x W x C`` float32 :class:`mitsuba.TensorXf`), the
:class:`Camera` it was rendered with, the previous frame's camera (for reprojection) and free
JSON metadata. :meth:`Frame.save` writes one float32 OpenEXR file whose layers are the channels
(``color.R``, ``normal.X``, ``depth.Z``, ...), plus a root ``R, G, B`` copy of ``color`` for generic
viewers, and whose header carries the cameras and metadata as a JSON string attribute named
``glossrt``; :meth:`Frame.load` reads it back bit-exactly. Both go through the ``openexr``
package and NumPy, so frames load and save without a Dr.Jit backend. The layout is documented
in ``docs/FORMATS.md``.

>>> frame = Frame.load("out/frame_0000.exr", require=("color", "normal"))  # doctest: +SKIP
>>> frame.numpy("color").shape                                              # doctest: +SKIP
(720, 1280, 3)
"""

from __future__ import annotations

import json
import math
import os
import re
import sys
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .backend import mi  # chooses the backend on first use (frames load and save without one)
from .errors import FrameError, GlossrtError
from .fileio import FolderNotWritable, replacing

__all__ = [
    "CHANNELS",
    "RADIANCE",
    "DENOISER_CHANNELS",
    "HEADER_ATTRIBUTE",
    "FORMAT_VERSION",
    "Camera",
    "Frame",
    "component_names",
    "load_sequence",
    "check_same_size",
    "frame_filename",
]

_RGB = ("R", "G", "B")
_XYZ = ("X", "Y", "Z")

#: The channel schema, in canonical order: channel name -> OpenEXR component suffixes.
#: The EXR channel for component ``c`` of channel ``name`` is ``f"{name}.{c}"``.
CHANNELS: dict[str, tuple[str, ...]] = {
    "color": _RGB,
    "emission": _RGB,
    "direct_diffuse": _RGB,
    "direct_specular": _RGB,
    "indirect_diffuse": _RGB,
    "indirect_specular": _RGB,
    "albedo_diffuse": _RGB,
    "albedo_specular": _RGB,
    "normal": _XYZ,
    "position": _XYZ,
    "depth": ("Z",),
    "roughness": ("Y",),
    "roughness_uv": ("X", "Y"),
    "tangent": _XYZ,
    "distribution": ("Y",),
    "mesh_id": ("Y",),
    "motion": ("X", "Y"),
}

#: The radiance components; ``color`` is their sum (linear, not demodulated).
RADIANCE: tuple[str, ...] = (
    "emission",
    "direct_diffuse",
    "direct_specular",
    "indirect_diffuse",
    "indirect_specular",
)

#: What a temporal denoiser / reconstruction filter reads.
DENOISER_CHANNELS: tuple[str, ...] = (
    "color",
    "albedo_diffuse",
    "albedo_specular",
    "normal",
    "depth",
    "mesh_id",
    "motion",
)

#: Name of the EXR header string attribute holding glossrt's JSON header.
HEADER_ATTRIBUTE = "glossrt"
#: Version of the JSON header layout (``"format"`` key of the header).
FORMAT_VERSION = 1

_EXR_MAGIC = b"\x76\x2f\x31\x01"
_IN_MEMORY = "<in-memory frame>"


def component_names(name: str, count: int) -> tuple[str, ...]:
    """EXR component suffixes of channel ``name`` with ``count`` components.

    Schema channels use :data:`CHANNELS`; other (extra) channels use ``Y`` for one component,
    ``R, G`` / ``R, G, B`` / ``R, G, B, A`` for two to four, and ``0, 1, ...`` beyond that.
    """
    if name in CHANNELS:
        return CHANNELS[name]
    if count < 1:
        raise FrameError(f"channel {name!r} has no components")
    if count == 1:
        return ("Y",)
    if count <= 4:
        return ("R", "G", "B", "A")[:count]
    return tuple(str(i) for i in range(count))


# --------------------------------------------------------------------------------------------
# Camera
# --------------------------------------------------------------------------------------------


@dataclass(eq=False)
class Camera:
    """A Mitsuba ``perspective`` camera: enough to project world points to pixels.

    Attributes:
        to_world: 4x4 float64 camera-to-world matrix (Mitsuba's sensor ``to_world``). In camera
            space the camera looks down +Z, +Y is up in the image and +X points *left*.
        fov: horizontal field of view in degrees (Mitsuba's ``x_fov``).
        resolution: image size ``(W, H)`` in pixels.
    """

    to_world: np.ndarray
    fov: float
    resolution: tuple[int, int]

    def __post_init__(self) -> None:
        try:
            m = np.array(self.to_world, dtype=np.float64).reshape(4, 4)
        except (TypeError, ValueError) as e:
            raise FrameError(f"camera to_world must be a 4x4 matrix: {e}") from e
        if not np.all(np.isfinite(m)):
            raise FrameError("camera to_world contains NaN or Inf")
        self.to_world = m
        self.fov = float(self.fov)
        if not 0.0 < self.fov < 180.0:
            raise FrameError(f"camera fov must be in (0, 180) degrees, got {self.fov}")
        try:
            w, h = (int(v) for v in self.resolution)
        except (TypeError, ValueError) as e:
            raise FrameError(f"camera resolution must be (W, H), got {self.resolution!r}") from e
        if w < 1 or h < 1:
            raise FrameError(f"camera resolution must be positive, got {w}x{h}")
        self.resolution = (w, h)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Camera):
            return NotImplemented
        return (
            np.array_equal(self.to_world, other.to_world)
            and self.fov == other.fov
            and self.resolution == other.resolution
        )

    @property
    def position(self) -> np.ndarray:
        """Camera centre in world space, shape (3,)."""
        return self.to_world[:3, 3].copy()

    @property
    def world_to_camera(self) -> np.ndarray:
        """Inverse of :attr:`to_world` (4x4 float64)."""
        return np.linalg.inv(self.to_world)

    @property
    def tan_half_fov(self) -> float:
        """``tan(fov / 2)`` of the horizontal field of view: half the image plane's width at
        unit distance (float64)."""
        return math.tan(math.radians(self.fov) / 2.0)

    @property
    def focal_px(self) -> float:
        """The focal length in pixels, ``(W / 2) / tan(fov / 2)`` (float64): a camera-space
        point ``(x, y, z)`` lands ``focal_px * (x, y) / z`` pixels from the image centre."""
        return (self.resolution[0] / 2) / self.tan_half_fov

    def pixel_angle(self, width: int | None = None) -> float:
        """``2 tan(fov / 2) / W``: the angle (radians) one pixel subtends at the image centre,
        for an image ``width`` pixels wide (default: the camera's ``W``)."""
        return 2.0 * self.tan_half_fov / (self.resolution[0] if width is None else width)

    def to_dict(self) -> dict[str, Any]:
        """JSON-able form; :meth:`from_dict` restores it exactly (floats are written by repr)."""
        return {
            "to_world": self.to_world.tolist(),
            "fov": self.fov,
            "resolution": list(self.resolution),
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Camera:
        """Inverse of :meth:`to_dict`; raises FrameError on missing or malformed fields."""
        if not isinstance(d, Mapping):
            raise FrameError(f"camera must be a JSON object, got {type(d).__name__}")
        missing = [k for k in ("to_world", "fov", "resolution") if k not in d]
        if missing:
            raise FrameError(f"camera is missing field(s): {', '.join(missing)}")
        return cls(to_world=np.asarray(d["to_world"]), fov=d["fov"], resolution=d["resolution"])

    @classmethod
    def from_sensor(cls, sensor: Any) -> Camera:
        """The camera of a loaded Mitsuba ``perspective`` sensor (``fov_axis`` is resolved by
        Mitsuba into ``x_fov``). Raises GlossrtError for principal-point offsets or film crops,
        which :meth:`project` does not model."""
        params = mi.traverse(sensor)
        if "x_fov" not in params:
            raise GlossrtError(f"sensor {sensor.class_name()} is not a perspective camera")
        for k in ("principal_point_offset_x", "principal_point_offset_y"):
            if k in params and float(np.asarray(params[k]).ravel()[0]) != 0.0:
                raise GlossrtError(f"sensor has a non-zero {k}, which glossrt does not support")
        film = sensor.film()
        size = tuple(int(v) for v in film.size())
        crop = tuple(int(v) for v in film.crop_size())
        if crop != size:
            raise GlossrtError(f"sensor film is cropped ({crop} of {size}); glossrt needs no crop")
        m = np.asarray(sensor.world_transform().matrix, dtype=np.float64)
        if m.ndim == 3:  # JIT variants hold a width-1 array per entry
            m = m[..., 0]
        fov = float(np.asarray(params["x_fov"]).ravel()[0])
        return cls(to_world=m, fov=fov, resolution=(size[0], size[1]))

    def project(self, points: np.ndarray) -> np.ndarray:
        """Continuous pixel coordinates of world-space ``points`` (shape ``(..., 3)``).

        Returns shape ``(..., 2)`` float64: x to the right, y down, pixel ``(i, j)`` covering
        ``[i, i+1) x [j, j+1)`` so its centre is at ``(i + 0.5, j + 0.5)``. This matches
        Mitsuba's perspective sensor: ``sample_ray(.., uv, ..)`` shoots through
        ``uv * (W, H)``. Points on or behind the camera plane (camera-space z <= 0) give NaN.
        """
        p = np.asarray(points, dtype=np.float64)
        if p.shape[-1:] != (3,):
            raise FrameError(f"points must have shape (..., 3), got {p.shape}")
        inv = self.world_to_camera
        c = p @ inv[:3, :3].T + inv[:3, 3]
        x, y, z = c[..., 0], c[..., 1], c[..., 2]
        w, h = self.resolution
        t, focal = self.tan_half_fov, self.focal_px
        with np.errstate(divide="ignore", invalid="ignore"):
            zs = np.where(z > 0.0, z, np.nan)
            px = 0.5 * w * (1.0 - (x / zs) / t)
            py = 0.5 * h - (y / zs) * focal
        return np.stack([px, py], axis=-1)


# --------------------------------------------------------------------------------------------
# Frame
# --------------------------------------------------------------------------------------------


def _json_default(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"object of type {type(o).__name__} is not JSON serialisable")


class Frame:
    """One rendered frame: named channels plus the cameras and metadata needed to use them.

    Attributes:
        channels: channel name -> ``H x W x C`` float32 :class:`mitsuba.TensorXf`. Schema
            channels (:data:`CHANNELS`) must have the schema's component count; other names
            are allowed with any count. All channels share one ``H x W``.
        camera: the camera the frame was rendered with (None for foreign EXRs without a
            glossrt header).
        prev_camera: the previous frame's camera (None for the first frame of a sequence).
        index: frame number in its sequence.
        meta: free JSON-able metadata (scene, spp, seed, nan_count, ...).
        source: the file the frame was loaded from, if any (used in error messages).

    Channels given as NumPy arrays (and every channel of a loaded frame) stay NumPy arrays
    until a tensor is asked for (``frame[name]``, :meth:`require`, :attr:`channels`): only then
    is the Dr.Jit backend chosen. :meth:`load`, :meth:`save`, :meth:`numpy`, :attr:`names`,
    :attr:`size` and :meth:`nonfinite_counts` work without Mitsuba, Dr.Jit or libLLVM.
    """

    def __init__(
        self,
        channels: Mapping[str, Any] | None = None,
        camera: Camera | None = None,
        prev_camera: Camera | None = None,
        index: int = 0,
        meta: Mapping[str, Any] | None = None,
        source: str | None = None,
    ) -> None:
        self.camera = camera
        self.prev_camera = prev_camera
        self.source = source
        self._store: dict[str, Any] = {}
        for name, value in dict(channels or {}).items():
            self[name] = value
        try:
            self.index = int(index)
        except (TypeError, ValueError) as e:
            raise FrameError(f"frame index must be an integer, got {index!r}") from e
        if meta is not None and not isinstance(meta, Mapping):
            raise FrameError(f"frame meta must be a dict, got {type(meta).__name__}")
        self.meta: dict[str, Any] = dict(meta or {})
        self._check_camera()

    def __repr__(self) -> str:
        w, h = self.size
        return (
            f"Frame({self.where}, {w}x{h}, index={self.index}, "
            f"channels=({', '.join(self._store)}))"
        )

    # -- basic access --------------------------------------------------------------------------

    @property
    def channels(self) -> dict[str, mi.TensorXf]:
        """Channel name -> ``H x W x C`` :class:`mitsuba.TensorXf` (chooses the backend on first
        use). The dict is the frame's own: deleting an entry removes the channel."""
        for name in self._store:
            self._tensor(name)
        return self._store

    @channels.setter
    def channels(self, value: Mapping[str, Any]) -> None:
        self._store = {}
        for name, v in dict(value).items():
            self[name] = v

    @property
    def where(self) -> str:
        """The source file, or ``"<in-memory frame>"``: used to name the frame in errors."""
        return _shown(self.source) if self.source is not None else _IN_MEMORY

    @property
    def names(self) -> tuple[str, ...]:
        """Channel names, in order."""
        return tuple(self._store)

    @property
    def size(self) -> tuple[int, int]:
        """``(W, H)``: from the channels, else the camera's resolution, else ``(0, 0)``."""
        for t in self._store.values():
            return int(t.shape[1]), int(t.shape[0])
        if self.camera is not None:
            return self.camera.resolution
        return 0, 0

    @property
    def width(self) -> int:
        """Image width in pixels."""
        return self.size[0]

    @property
    def height(self) -> int:
        """Image height in pixels."""
        return self.size[1]

    def __contains__(self, name: object) -> bool:
        return name in self._store

    def _tensor(self, name: str) -> mi.TensorXf:
        value = self._store[name]
        if isinstance(value, np.ndarray):
            value = mi.TensorXf(value)
            self._store[name] = value
        return value

    def __getitem__(self, name: str) -> mi.TensorXf:
        if name not in self._store:
            have = ", ".join(self._store) or "none"
            raise FrameError(f"channel {name!r} missing from {self.where} (has: {have})")
        return self._tensor(name)

    def require(self, *names: str) -> tuple[mi.TensorXf, ...]:
        """Check that all ``names`` are present (FrameError naming every missing one and the
        source) and return their tensors in that order."""
        names = _names_arg(names)
        self._require_names(names)
        return tuple(self._tensor(n) for n in names)

    def numpy(self, name: str) -> np.ndarray:
        """Channel ``name`` as a new ``(H, W, C)`` float32 numpy array."""
        if name not in self._store:
            self[name]  # raises FrameError naming the channel and the frame
        value = self._store[name]
        if isinstance(value, np.ndarray):
            return value.copy()
        return np.array(value, dtype=np.float32).reshape(self.height, self.width, -1)

    def __setitem__(self, name: str, value: Any) -> None:
        """Set channel ``name`` from a TensorXf or array of shape ``(H, W, C)`` (or ``(H, W)``
        for one component), checking its size against the other channels and its component
        count against the schema. NumPy input is copied and kept as NumPy until a tensor is
        asked for."""
        if not isinstance(name, str) or not name or name.endswith(".") or name != name.strip():
            raise FrameError(f"invalid channel name {name!r} in {self.where}")
        stored: Any
        dr = sys.modules.get("drjit")
        if dr is not None and isinstance(value, dr.ArrayBase):
            if isinstance(value, mi.TensorXf) and len(value.shape) == 3:
                stored = value
                shape = tuple(int(s) for s in value.shape)
            else:
                stored = None
                value = np.asarray(value)
        else:
            stored = None
        if stored is None:
            try:
                arr = np.array(value, dtype=np.float32)
            except (TypeError, ValueError) as e:
                raise FrameError(
                    f"channel {name!r} in {self.where} is not an array of numbers: {e}"
                ) from e
            if arr.ndim == 2:
                arr = arr[:, :, None]
            if arr.ndim != 3:
                raise FrameError(
                    f"channel {name!r} in {self.where} must be H x W x C, got shape {arr.shape}"
                )
            stored = np.ascontiguousarray(arr)
            shape = arr.shape
        h, w, c = shape
        if name in CHANNELS and c != len(CHANNELS[name]):
            raise FrameError(
                f"channel {name!r} in {self.where} has {c} component(s); the schema needs "
                f"{len(CHANNELS[name])} ({', '.join(CHANNELS[name])})"
            )
        if c < 1 or h < 1 or w < 1:
            raise FrameError(f"channel {name!r} in {self.where} is empty (shape {shape})")
        for other, t in self._store.items():
            if other != name and (int(t.shape[0]), int(t.shape[1])) != (h, w):
                raise FrameError(
                    f"channel {name!r} in {self.where} is {w}x{h} but channel {other!r} is "
                    f"{int(t.shape[1])}x{int(t.shape[0])}"
                )
        self._store[name] = stored
        self._check_camera()

    def _check_camera(self) -> None:
        for cam in (self.camera, self.prev_camera):
            if cam is not None and not isinstance(cam, Camera):
                raise FrameError(
                    f"{self.where}: camera must be a glossrt.Camera, got {type(cam).__name__}"
                )
        if self.camera is None or not self._store:
            return
        t = next(iter(self._store.values()))
        size = (int(t.shape[1]), int(t.shape[0]))
        if self.camera.resolution != size:
            r = self.camera.resolution
            raise FrameError(
                f"{self.where}: channels are {size[0]}x{size[1]} but the camera resolution is "
                f"{r[0]}x{r[1]}"
            )

    # -- checks --------------------------------------------------------------------------------

    def nonfinite_counts(self) -> dict[str, int]:
        """Number of pixels with any NaN or +-Inf component, for every channel.

        ``depth = +inf`` is the background marker and is not counted where ``mesh_id == 0``
        (or anywhere, when the frame has no ``mesh_id`` channel).
        """
        out: dict[str, int] = {}
        background: np.ndarray | None = None
        if "mesh_id" in self._store:
            background = self.numpy("mesh_id")[..., 0] == 0
        for name in self._store:
            a = self.numpy(name)
            bad = ~np.isfinite(a)
            if name == "depth":
                ok = np.isposinf(a[..., 0])
                if background is not None:
                    ok &= background
                bad[..., 0] &= ~ok
            out[name] = int(np.count_nonzero(bad.any(axis=-1)))
        return out

    # -- disk ------------------------------------------------------------------------------------

    def header(self) -> dict[str, Any]:
        """The JSON header :meth:`save` writes into the EXR attribute ``glossrt``."""
        return {
            "format": FORMAT_VERSION,
            "index": self.index,
            "camera": self.camera.to_dict() if self.camera is not None else None,
            "prev_camera": self.prev_camera.to_dict() if self.prev_camera is not None else None,
            "channels": {
                n: list(component_names(n, int(t.shape[2]))) for n, t in self._store.items()
            },
            "meta": self.meta,
        }

    def save(self, path: str | bytes | os.PathLike[Any]) -> Path:
        """Write the frame as one float32 multi-layer OpenEXR file and return its path.

        Written with the ``openexr`` package (no Dr.Jit backend needed). Besides the layers
        (``color.R``, ``normal.X``, ...) the file has a root ``R, G, B`` layer equal to
        ``color`` (when the frame has one), which generic EXR viewers show as the image. The
        file is written to a temporary file in the same folder and renamed into place, so an
        interrupted save never leaves a partial ``path`` behind. Raises FrameError when the
        folder does not exist or is not writable, or when :attr:`meta` is not JSON-able.
        """
        path = _as_path(path)
        shown = _shown(path)
        folder = path.parent if str(path.parent) else Path(".")
        if not self._store:
            raise FrameError(f"cannot save {shown}: the frame has no channels")
        self._check_camera()
        try:
            header = json.dumps(self.header(), default=_json_default, allow_nan=True)
        except (TypeError, ValueError) as e:
            raise FrameError(
                f"cannot save {shown}: frame meta is not JSON-serialisable: {e}"
            ) from e
        if not folder.is_dir():
            raise FrameError(f"cannot save {shown}: folder {_shown(folder)} does not exist")
        OpenEXR = _openexr()

        pixels: dict[str, np.ndarray] = {}
        for n in self._store:
            a = self.numpy(n)
            for k, c in enumerate(component_names(n, a.shape[2])):
                pixels[f"{n}.{c}"] = np.ascontiguousarray(a[:, :, k])
        if "color" in self._store:  # the root layer generic viewers show
            for c in _RGB:
                pixels[c] = pixels[f"color.{c}"]
        from . import __version__

        attrs = {
            "compression": OpenEXR.PIZ_COMPRESSION,
            "type": OpenEXR.scanlineimage,
            HEADER_ATTRIBUTE: header,
            "generatedBy": f"glossrt {__version__}",
        }
        try:
            exr = OpenEXR.File(attrs, pixels)
            with replacing(path) as tmp, open(tmp, "wb") as fh:
                exr.write(fh)
        except FolderNotWritable as e:
            raise FrameError(
                f"cannot save {shown}: folder {_shown(folder)} is not writable "
                f"({e.strerror or e})"
            ) from e
        except (OSError, RuntimeError, ValueError, TypeError) as e:
            raise FrameError(f"cannot save {shown} in folder {_shown(folder)}: {e}") from e
        return path

    @classmethod
    def load(
        cls, path: str | bytes | os.PathLike[Any], require: str | Iterable[str] = ()
    ) -> Frame:
        """Read a frame written by :meth:`save` (bit-exact) or any float OpenEXR file.

        Read with the ``openexr`` package into NumPy: no Dr.Jit backend is needed until a
        tensor is asked for. ``require`` is a channel name or several. Channels are grouped
        into layers by the part of the EXR channel name before its last dot; unprefixed
        ``R, G, B`` are the ``color`` layer when the file has none (in glossrt's files they are
        a copy of ``color`` and are not loaded twice; see ``docs/FORMATS.md``) and other
        unprefixed channels become one-component channels of their own name. The parts of a
        multi-part file are merged (part names prefix the channels when two parts share a
        channel name). Files without a glossrt header load with ``camera = prev_camera =
        None``. Raises FrameError naming the file when it is missing, not an OpenEXR file,
        unreadable, has a malformed header, or lacks ``require`` channels.
        """
        req = _names_arg(require)
        p = _as_path(path)
        src = _shown(p)
        if not p.exists():
            raise FrameError(f"frame file {src} does not exist")
        if not p.is_file():
            raise FrameError(f"frame file {src} is not a regular file")
        try:
            with open(p, "rb") as f:
                magic = f.read(4)
        except OSError as e:
            raise FrameError(f"cannot read frame file {src}: {e.strerror or e}") from e
        if magic != _EXR_MAGIC:
            raise FrameError(f"{src} is not an OpenEXR file")
        OpenEXR = _openexr()
        try:
            with open(p, "rb") as fh:
                exr = OpenEXR.File(fh, separate_channels=True)
            parts = list(exr.parts)
        except OSError as e:
            raise FrameError(f"cannot read frame file {src}: {e.strerror or e}") from e
        except Exception as e:  # the openexr package raises RuntimeError and others
            raise FrameError(f"cannot read OpenEXR file {src} (corrupt or truncated?): {e}") from e

        planes, attrs = _read_parts(parts, src)
        header: dict[str, Any] = {}
        if HEADER_ATTRIBUTE in attrs:
            raw = attrs[HEADER_ATTRIBUTE]
            try:
                header = json.loads(raw)
            except (TypeError, ValueError) as e:
                raise FrameError(f"{src}: malformed glossrt header attribute: {e}") from e
            if not isinstance(header, dict):
                raise FrameError(f"{src}: malformed glossrt header attribute (not an object)")

        _resolve_root_rgb(planes, src)
        fields = list(planes)
        layers = _group_layers(fields, src)
        order: dict[str, list[str]] = {}
        stored = header.get("channels")
        if isinstance(stored, dict):
            for n, comps in stored.items():
                if n in layers and isinstance(comps, list) and set(comps) == set(layers[n]):
                    order[n] = [str(c) for c in comps]
        for n in CHANNELS:
            if n in layers and n not in order:
                order[n] = _order_components(n, layers[n], src)
        for n in sorted(layers):
            if n not in order:
                order[n] = _order_components(n, layers[n], src)

        channels: dict[str, np.ndarray] = {}
        for n, comps in order.items():
            channels[n] = np.stack([planes[layers[n][c]] for c in comps], axis=-1)

        try:
            camera = _camera_or_none(header.get("camera"))
            prev = _camera_or_none(header.get("prev_camera"))
        except FrameError as e:
            raise FrameError(f"{src}: bad camera in glossrt header: {e}") from e
        meta = header.get("meta") or {}
        if not isinstance(meta, dict):
            raise FrameError(f"{src}: glossrt header 'meta' is not an object")
        try:
            index = int(header.get("index", 0))
        except (TypeError, ValueError) as e:
            raise FrameError(f"{src}: glossrt header 'index' is not an integer") from e

        frame = cls(
            channels=channels,
            camera=camera,
            prev_camera=prev,
            index=index,
            meta=meta,
            source=str(p),
        )
        frame._require_names(req)
        return frame

    def _require_names(self, names: Sequence[str]) -> None:
        missing = [n for n in names if n not in self._store]
        if missing:
            have = ", ".join(self._store) or "none"
            raise FrameError(
                f"{self.where} lacks required channel(s) {', '.join(missing)} (has: {have})"
            )


def _names_arg(names: Any) -> tuple[str, ...]:
    """``require=`` as a tuple of names: one str is one name (not its letters)."""
    if isinstance(names, str):
        return (names,)
    try:
        out = tuple(names)
    except TypeError as e:
        raise FrameError(f"channel names must be a str or strs, got {names!r}") from e
    if len(out) == 1 and not isinstance(out[0], str) and isinstance(out[0], Iterable):
        return _names_arg(out[0])  # require(("a", "b")) as well as require("a", "b")
    bad = [n for n in out if not isinstance(n, str)]
    if bad:
        raise FrameError(f"channel names must be str, got {bad[0]!r}")
    return out


def _as_path(path: Any) -> Path:
    """A user's path (str, bytes or PathLike; any bytes, UTF-8 or not) as a Path."""
    try:
        return Path(os.fsdecode(path))
    except TypeError as e:
        raise FrameError(f"a frame path must be a str, bytes or path, got {path!r}") from e


def _shown(path: Any) -> str:
    """``path`` for messages: bytes that are not UTF-8 (surrogate escapes) as ``\\xff``, so the
    message can be printed."""
    return os.fsencode(path).decode("utf-8", "backslashreplace")


def _openexr() -> Any:
    try:
        import OpenEXR
    except ImportError as e:  # pragma: no cover - a declared dependency
        raise GlossrtError(
            "glossrt reads and writes frames with the 'openexr' package: pip install openexr"
        ) from e
    return OpenEXR


def _read_parts(parts: Sequence[Any], src: str) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """EXR channel name -> (H, W) float32 plane, merged over all parts, and the first part's
    header attributes (plus the glossrt attribute of whichever part has it)."""
    if not parts:
        raise FrameError(f"{src}: the OpenEXR file has no parts")
    OpenEXR = _openexr()
    windows = []
    per_part: list[tuple[str, dict[str, np.ndarray]]] = []
    attrs: dict[str, Any] = dict(parts[0].header)
    for k, part in enumerate(parts):
        name = part.name() or ""
        label = f"part {k}" + (f" ({name!r})" if name else "")
        kind = part.type()
        if kind not in (OpenEXR.scanlineimage, OpenEXR.tiledimage):
            raise FrameError(f"{src}: {label} holds deep data, which glossrt cannot read")
        hdr = part.header
        if HEADER_ATTRIBUTE in hdr and HEADER_ATTRIBUTE not in attrs:
            attrs[HEADER_ATTRIBUTE] = hdr[HEADER_ATTRIBUTE]
        lo, hi = (tuple(int(v) for v in np.asarray(c).ravel()) for c in hdr["dataWindow"])
        windows.append((lo, hi))
        planes: dict[str, np.ndarray] = {}
        for cname, ch in part.channels.items():
            if ch.xSampling != 1 or ch.ySampling != 1:
                raise FrameError(
                    f"{src}: channel {cname!r} of {label} is subsampled "
                    f"({ch.xSampling}x{ch.ySampling}), which glossrt cannot read"
                )
            px = np.asarray(ch.pixels)
            if px.ndim != 2:
                raise FrameError(f"{src}: channel {cname!r} of {label} is not a 2D image")
            planes[cname] = np.ascontiguousarray(px, dtype=np.float32)
        per_part.append((name, planes))
    for k, win in enumerate(windows[1:], 1):
        if win != windows[0]:
            raise FrameError(
                f"{src}: part {k} covers pixels {win[0]}-{win[1]} but part 0 covers "
                f"{windows[0][0]}-{windows[0][1]}; glossrt needs parts of one size"
            )
    seen: dict[str, int] = {}
    clash = False
    for _, planes in per_part:
        for cname in planes:
            clash |= cname in seen
            seen[cname] = 1
    merged: dict[str, np.ndarray] = {}
    if not clash:
        for _, planes in per_part:
            merged.update(planes)
        return merged, attrs
    names = [n for n, _ in per_part]
    if any(not n for n in names) or len(set(names)) != len(names):
        raise FrameError(
            f"{src}: its {len(parts)} parts share channel names and have no distinct part "
            "names to tell them apart"
        )
    for pname, planes in per_part:  # the part name prefixes its channels
        for cname, plane in planes.items():
            merged[f"{pname}.{cname}"] = plane
    return merged, attrs


def _resolve_root_rgb(planes: dict[str, np.ndarray], src: str) -> None:
    """Root ``R, G, B`` next to a ``color`` layer: glossrt's copy for viewers, dropped when it
    equals ``color`` bit for bit; otherwise kept as a layer named ``rgb``."""
    has_color = any(f.rsplit(".", 1)[0] == "color" for f in planes if "." in f)
    if not has_color or not all(c in planes for c in _RGB):
        return
    same = all(
        f"color.{c}" in planes
        and np.array_equal(planes[c].view(np.uint32), planes[f"color.{c}"].view(np.uint32))
        for c in _RGB
    )
    if not same:
        if any(f.rsplit(".", 1)[0] == "rgb" for f in planes if "." in f):
            raise FrameError(
                f"{src}: root R, G, B differ from the 'color' layer and 'rgb' is taken"
            )
        for c in _RGB:
            planes[f"rgb.{c}"] = planes[c]
    for c in _RGB:
        del planes[c]


def _camera_or_none(d: Any) -> Camera | None:
    return None if d is None else Camera.from_dict(d)


def _group_layers(fields: Sequence[str], src: str) -> dict[str, dict[str, str]]:
    """EXR channel names -> {layer: {component suffix: full EXR channel name}}."""
    unprefixed = [f for f in fields if "." not in f]
    rgb_root = all(c in unprefixed for c in _RGB)
    layers: dict[str, dict[str, str]] = {}

    def add(layer: str, comp: str, full: str) -> None:
        comps = layers.setdefault(layer, {})
        if comp in comps:
            raise FrameError(f"{src}: EXR channel {full!r} clashes with {comps[comp]!r}")
        comps[comp] = full

    for f in fields:
        if "." in f:
            layer, comp = f.rsplit(".", 1)
            if not layer or not comp:
                raise FrameError(f"{src}: cannot interpret EXR channel name {f!r}")
            add(layer, comp, f)
        elif rgb_root and f in _RGB:
            add("color", f, f)
        else:
            single = f in CHANNELS and len(CHANNELS[f]) == 1
            add(f, CHANNELS[f][0] if single else "Y", f)
    return layers


def _natural_key(s: str) -> list[Any]:
    return [(0, int(t), "") if t.isdigit() else (1, 0, t) for t in re.split(r"(\d+)", s) if t]


def _order_components(name: str, comps: Mapping[str, str], src: str) -> list[str]:
    """Component order of a layer whose order the header does not record."""
    have = set(comps)
    if name in CHANNELS:
        want = CHANNELS[name]
        if have != set(want):
            raise FrameError(
                f"{src}: channel {name!r} has EXR components {', '.join(sorted(have))}; "
                f"glossrt expects {', '.join(want)}"
            )
        return list(want)
    for convention in (("R", "G", "B", "A"), ("X", "Y", "Z", "W"), ("U", "V", "W")):
        if have <= set(convention):
            return [c for c in convention if c in have]
    return sorted(have, key=_natural_key)


def frame_filename(index: int) -> str:
    """File name of frame ``index`` in a sequence: ``frame_0000.exr``, ``frame_0001.exr``..."""
    if int(index) < 0:
        raise FrameError(f"frame index must be >= 0, got {index}")
    return f"frame_{int(index):04d}.exr"


def check_same_size(frames: Sequence[Frame]) -> tuple[int, int]:
    """Return the common ``(W, H)`` of ``frames``; FrameError naming the first frame whose size
    differs from the first one (and both sizes), or when ``frames`` is empty."""
    if not frames:
        raise FrameError("no frames given")
    first = frames[0]
    size = first.size
    for f in frames[1:]:
        if f.size != size:
            raise FrameError(
                f"{f.where} is {f.width}x{f.height} but {first.where} is {size[0]}x{size[1]}; "
                "all frames of a sequence must have the same size"
            )
    return size


def load_sequence(
    directory: str | bytes | os.PathLike[Any], require: str | Iterable[str] = ()
) -> list[Frame]:
    """Load every ``*.exr`` in ``directory``, in natural file-name order (equal to plain name
    order for the zero-padded :func:`frame_filename` names). FrameError if the folder is
    missing or has no EXR files, if a file fails :meth:`Frame.load`, or if sizes differ."""
    req = _names_arg(require)
    d = _as_path(directory)
    if not d.is_dir():
        raise FrameError(f"frame folder {_shown(d)} does not exist")
    files = sorted((p for p in d.glob("*.exr") if p.is_file()), key=lambda p: _natural_key(p.name))
    if not files:
        raise FrameError(f"no *.exr frames in {_shown(d)}")
    frames = [Frame.load(p, require=req) for p in files]
    check_same_size(frames)
    return frames
