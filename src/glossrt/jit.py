"""Helpers around Dr.Jit that several modules need."""

from __future__ import annotations

import gc
import math
from collections.abc import Iterator
from contextlib import contextmanager

import drjit as dr

from .backend import mi


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
    return [dr.opaque(mi.Float, float(v)) for v in values]


#: 2^f on [0, 1): degree-5 polynomial, c0 = 1 (so exp2(0) = 1 exactly), the other
#: coefficients fitted to the relative error (max 1.6e-7 evaluated in float32)
_EXP2_POLY = (1.0, 0.6931513547897339, 0.2401641458272934, 0.05580046772956848,
              0.009016658179461956, 0.0018671966390684247)
_LOG2E = 1.4426950408889634


def exp_weight(x):
    """``exp(x)`` for filter weights, in about a third of ``dr.exp``'s instructions (15 vs 40
    on the LLVM backend, where ``dr.exp`` dominates a tap of an edge-avoiding filter).

    ``2^t`` with ``t = x log2(e)`` split as ``2^floor(t)`` (built in the exponent bits) times
    a polynomial for ``2^frac(t)``; relative error <= 3e-7 for ``|x| <= 1`` and <= 4e-6 up to
    ``|x| = 87`` (the float32 rounding of ``x log2(e)``). Outside that range the result
    saturates at ``2^-126`` (about 1e-38, not 0) and ``2^127``; it is meant for finite
    float32 inputs (a filter's arguments are) and has no derivative: use ``dr.exp`` where
    the tails, NaN propagation or gradients matter. A Python number gives ``math.exp``."""
    if not dr.is_array_v(x):
        return math.exp(x)
    t = dr.clip(x * _LOG2E, -126.0, 127.0)
    i = dr.floor(t)
    f = t - i
    c = _EXP2_POLY
    p = dr.fma(dr.fma(dr.fma(dr.fma(dr.fma(c[5], f, c[4]), f, c[3]), f, c[2]), f, c[1]), f,
               c[0])
    itype = dr.int32_array_t(type(t))
    scale = dr.reinterpret_array(type(t), (itype(i) + 127) << 23)
    return p * scale


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
    return owned(mi.Float, values)


def owned(t, values):
    """:func:`owned_float` for a flat Dr.Jit type ``t`` (``mi.Float``, ``mi.Float64``,
    ``mi.Int32``, ``mi.UInt32``): the data converted to ``t``'s dtype, copied by a kernel
    into memory Dr.Jit allocated, evaluated (empty input: an empty array)."""
    import numpy as np

    dt = {mi.Float: np.float32, mi.Float64: np.float64, mi.Int32: np.int32,
          mi.UInt32: np.uint32}[t]
    a = np.ascontiguousarray(values, dtype=dt).ravel()
    if a.size == 0:
        return t()
    out = t(a) + dr.opaque(t, 0)
    dr.eval(out)
    return out
