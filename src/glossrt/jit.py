"""Helpers around Dr.Jit that several modules need."""

from __future__ import annotations

import gc
from collections.abc import Iterator
from contextlib import contextmanager

import drjit as dr


@contextmanager
def no_gc() -> Iterator[None]:
    """Keep Python's cyclic garbage collector out of a ``dr.freeze`` call.

    A collection that runs while a frozen function records or replays can free Dr.Jit
    variables of unrelated, unreachable objects (e.g. an earlier filter's history), and
    Dr.Jit 1.5 then aborts the process ("Fatal Python error: Aborted", seen in CI on a cold
    kernel cache). Reference counting still frees objects as usual meanwhile."""
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if enabled:
            gc.enable()


def opaque(values) -> list:
    """Python numbers as opaque Dr.Jit scalars (``mi.Float``): values that change between
    calls (a camera or light position) must not be baked into kernels as literals, or every
    new value compiles new kernels."""
    import mitsuba as mi

    return [dr.opaque(mi.Float, float(v)) for v in values]


def pow_int(x, n: float):
    """``x**n`` by repeated squaring when ``n`` is a small positive integer (128 is 7
    squarings, far cheaper than ``exp(n log x)``); ``dr.power`` otherwise."""
    if float(n).is_integer() and 0 < n <= 1024:
        n = int(n)
        result, base = None, x
        while n:
            if n & 1:
                result = base if result is None else result * base
            n >>= 1
            if n:
                base = base * base
        return result
    return dr.power(x, n)


def owned_float(values):
    """A NumPy array as an evaluated ``mi.Float`` in memory Dr.Jit allocated itself (a kernel
    writes the copy). Arrays built straight from NumPy can keep the NumPy buffer, whose
    alignment varies between calls, and then ``dr.freeze`` re-records now and then (seen as
    a nondeterministic second recording) and the LLVM backend misses its kernel cache:
    inputs of frozen functions and long-lived tables go through this."""
    import mitsuba as mi

    return owned(mi.Float, values)


def owned(t, values):
    """:func:`owned_float` for a flat Dr.Jit type ``t`` (``mi.Float``, ``mi.Int32``,
    ``mi.UInt32``): the data converted to ``t``'s dtype, copied by a kernel into memory
    Dr.Jit allocated, evaluated (empty input: an empty array)."""
    import mitsuba as mi
    import numpy as np

    dt = {mi.Float: np.float32, mi.Int32: np.int32, mi.UInt32: np.uint32}[t]
    a = np.ascontiguousarray(values, dtype=dt).ravel()
    if a.size == 0:
        return t()
    out = t(a) + dr.opaque(t, 0)
    dr.eval(out)
    return out
