"""Device choice: picks the Mitsuba variant (``cuda_ad_rgb`` or ``llvm_ad_rgb``) and finds libLLVM.

The CPU variant loads a system libLLVM at run time; versions before 16 either are not
found or crash on recent CPUs, so glossrt looks for the newest libLLVM >= 16 and points
Dr.Jit at it through ``DRJIT_LIBLLVM_PATH`` before the variant is set.

>>> from glossrt import backend
>>> backend.use("cpu")            # doctest: +SKIP
'llvm_ad_rgb'
"""

from __future__ import annotations

import glob
import os
import re
import types
from collections.abc import Callable
from dataclasses import dataclass

from .errors import BackendError

MIN_LLVM = 16
CPU_VARIANT = "llvm_ad_rgb"
GPU_VARIANT = "cuda_ad_rgb"

_SEARCH = [
    "/usr/lib/llvm-*/lib/libLLVM*.so*",
    "/usr/lib/x86_64-linux-gnu/libLLVM*.so*",
    "/usr/lib/aarch64-linux-gnu/libLLVM*.so*",
    "/usr/lib64/libLLVM*.so*",
    "/usr/lib/libLLVM*.so*",
    "/usr/local/lib/libLLVM*.so*",
    "/opt/homebrew/opt/llvm/lib/libLLVM*.dylib",
    "/usr/local/opt/llvm/lib/libLLVM*.dylib",
]

INSTALL_HINT = (
    f"glossrt's CPU backend needs libLLVM >= {MIN_LLVM}. "
    "On Debian/Ubuntu run (as root): apt-get update && apt-get install -y libllvm19 ; "
    "elsewhere install LLVM >= 16 and set DRJIT_LIBLLVM_PATH=/path/to/libLLVM.so"
)


@dataclass(frozen=True)
class LibLLVM:
    path: str
    version: int


def _version_of(path: str) -> int | None:
    name = os.path.basename(path)
    m = (re.search(r"LLVM-(\d+)", name) or re.search(r"llvm-(\d+)", path)
         or re.search(r"\.so\.(\d+)", name))
    if m:
        return int(m.group(1))
    return None


def find_libllvm() -> LibLLVM | None:
    """The libLLVM glossrt will use: ``DRJIT_LIBLLVM_PATH`` if set, else the newest >= 16 found."""
    env = os.environ.get("DRJIT_LIBLLVM_PATH")
    if env:
        return LibLLVM(env, _version_of(env) or 0) if os.path.exists(env) else None
    best: LibLLVM | None = None
    for pattern in _SEARCH:
        for path in glob.glob(pattern):
            v = _version_of(path)
            if v is None or v < MIN_LLVM or not os.path.isfile(path):
                continue
            if best is None or v > best.version:
                best = LibLLVM(path, v)
    return best


_current: dict[str, str] = {}


def _cuda_works() -> bool:
    import drjit as dr

    try:
        return bool(dr.has_backend(dr.JitBackend.CUDA))
    except Exception:  # pragma: no cover - depends on the driver
        return False


def use(device: str | None = None) -> str:
    """Select the Mitsuba variant for ``device`` ("auto", "cpu" or "gpu"; default: env
    ``GLOSSRT_DEVICE`` or "auto") and return its name. Calling it again with the same device
    is free; "auto" prefers a working CUDA device."""
    device = (device or os.environ.get("GLOSSRT_DEVICE") or "auto").lower()
    if device not in ("auto", "cpu", "gpu"):
        raise BackendError(f"unknown device {device!r}: use auto, cpu or gpu")
    if _current.get("device") == device:
        return _current["variant"]

    lib = find_libllvm()
    if lib is not None and "DRJIT_LIBLLVM_PATH" not in os.environ:
        os.environ["DRJIT_LIBLLVM_PATH"] = lib.path

    import mitsuba

    if device in ("auto", "gpu") and _cuda_works():
        variant = GPU_VARIANT
    elif device == "gpu":
        raise BackendError(
            "device 'gpu' was asked for but no working CUDA device was found "
            "(Dr.Jit could not initialise its CUDA backend); use --device cpu or auto"
        )
    else:
        if lib is None:
            raise BackendError("no usable libLLVM found. " + INSTALL_HINT)
        variant = CPU_VARIANT
    try:
        mitsuba.set_variant(variant)
    except Exception as e:  # pragma: no cover - environment specific
        raise BackendError(f"could not set Mitsuba variant {variant}: {e}. {INSTALL_HINT}") from e
    import drjit as dr

    if variant == CPU_VARIANT and not dr.has_backend(dr.JitBackend.LLVM):
        raise BackendError("Dr.Jit could not load libLLVM. " + INSTALL_HINT)
    changed = _current.get("variant") != variant
    _current.update(device=device, variant=variant)
    if changed:
        mi._forget()
        for fn in list(_ON_VARIANT):
            fn()
    return variant


#: run after a variant is chosen (and again if it changes): see :func:`on_variant`
_ON_VARIANT: list[Callable[[], None]] = []


def on_variant(fn: Callable[[], None]) -> Callable[[], None]:
    """Run ``fn()`` once a variant is chosen, and again whenever :func:`use` switches it (for
    what must exist per variant, such as a registered Mitsuba plugin); at once if one is
    active. Usable as a decorator; returns ``fn``."""
    _ON_VARIANT.append(fn)
    if _current:
        fn()
    return fn


class _LazyMitsuba(types.ModuleType):
    """The ``mitsuba`` module as glossrt's own modules use it (``from ..backend import mi``):
    importing a glossrt module chooses no backend; the first attribute read (``mi.Float``,
    ``mi.load_dict``, ...) calls :func:`ensure` (``GLOSSRT_DEVICE``, else auto) unless
    :func:`use` chose one before. Attributes are the real module's, so ``isinstance`` and type
    identity are unchanged.

    Each name read is kept in the proxy's own ``__dict__``, so later reads are plain module
    attribute reads, as fast as ``mitsuba.X`` (kernels are traced from Python on every
    non-frozen frame; a read through a class-level ``__getattr__`` cost about 1.5 us). Names
    not kept yet reach :meth:`_load` through the module's own ``__getattr__`` (PEP 562).
    :func:`use` forgets them when it switches the variant (a variant set through
    ``mitsuba.set_variant`` directly is not seen)."""

    def __init__(self, name: str, doc: str) -> None:
        super().__init__(name, doc)
        self.__dict__["__getattr__"] = self._load

    def _load(self, name: str):
        if name.startswith("__") and name.endswith("__"):
            raise AttributeError(name)  # copy/pickle/introspection probes choose nothing
        ensure()
        import mitsuba

        value = getattr(mitsuba, name)
        self.__dict__[name] = value
        return value

    def _forget(self) -> None:
        """Drop the names kept from the previous variant."""
        for name in [k for k in self.__dict__ if not k.startswith("__")]:
            del self.__dict__[name]


mi = _LazyMitsuba("mitsuba", "mitsuba, choosing glossrt's backend on first use")


class VariantStruct:
    """A ``DRJIT_STRUCT`` class attribute whose field types are the active variant's::

        class Table:
            DRJIT_STRUCT = VariantStruct(lambda: {"data": mi.Float, "n": int})

    ``build`` runs on the first read (so, like any ``mi.X``, it chooses the backend then, not
    when the class is defined) and again after :func:`use` switches the variant. Reads on the
    class and on its instances give the same ``dict``, which is what Dr.Jit looks for."""

    def __init__(self, build: Callable[[], dict]) -> None:
        self._build = build
        self._variant: str | None = None
        self._fields: dict = {}

    def __get__(self, obj: object, owner: type | None = None) -> dict:
        variant = _current.get("variant") or ensure()
        if variant != self._variant:
            self._fields = self._build()
            self._variant = variant
        return self._fields


def ensure() -> str:
    """Select a variant if none is active yet (respecting ``GLOSSRT_DEVICE``)."""
    if _current:
        return _current["variant"]
    return use()


def is_gpu() -> bool:
    return ensure() == GPU_VARIANT


def info() -> dict[str, str]:
    """Variant, device, versions and the libLLVM in use."""
    variant = ensure()
    import drjit as dr
    import mitsuba as mi
    import numpy as np

    from . import __version__

    out = {
        "glossrt": __version__,
        "variant": variant,
        "device": "gpu (CUDA)" if variant == GPU_VARIANT else f"cpu (LLVM, {os.cpu_count()} cores)",
        "mitsuba": mi.__version__,
        "drjit": dr.__version__,
        "numpy": np.__version__,
    }
    lib = find_libllvm()
    try:
        v = ".".join(str(x) for x in dr.detail.llvm_version())
    except Exception:
        v = "not loaded"
    out["libllvm"] = f"{lib.path if lib else 'not found'} (loaded version {v})"
    return out


def main_check() -> int:
    """Used by the Makefile: exit 0 when a libLLVM >= 16 is usable, else print why and exit 3."""
    lib = find_libllvm()
    if lib is None:
        print("glossrt: " + INSTALL_HINT)
        return 3
    print(f"glossrt: using libLLVM {lib.version} at {lib.path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main_check())
