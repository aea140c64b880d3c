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
    a nondeterministic second recording): inputs of frozen functions go through this."""
    import mitsuba as mi
    import numpy as np

    out = mi.Float(np.ascontiguousarray(values, dtype=np.float32).ravel()) + \
        dr.opaque(mi.Float, 0.0)
    dr.eval(out)
    return out


def owned(t, values):
    """:func:`owned_float` for any flat Dr.Jit type ``t`` (``mi.UInt32``, ``mi.Float``, ...):
    NumPy data copied by a kernel into memory Dr.Jit allocated, evaluated."""
    import numpy as np

    out = t(np.ascontiguousarray(values).ravel()) + dr.opaque(t, 0)
    dr.eval(out)
    return out
