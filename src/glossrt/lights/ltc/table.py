"""The LTC tables glossrt ships (``data/ltc_ggx.npz``, ``data/ltc_beckmann.npz``): their axes,
the coefficients of ``M^-1`` they store, reading a table file and the bilinear lookups that
shading does (:class:`LTCTable`). How the tables are fitted, and what each cell holds
(``minv``, ``norm``, ``fres``), is :mod:`glossrt.lights.ltc.fit`'s docstring.

**Table axes** (``size`` nodes per axis, :data:`DEFAULT_SIZE` = 64 for the shipped tables):
rows ``j`` are the perceptual roughness ``r_j = j / (size - 1)``, fitted at
``alpha_j = max(r_j^2, ALPHA_MIN)`` (row 0 at ``alpha = ALPHA_MIN``, where lookups place it);
columns ``i`` are ``u_i = i / (size - 1)`` with ``u = sqrt(1 - cos theta_o)``, fitted at
``cos theta_o = max(1 - u_i^2, COS_O_MIN)`` (:func:`grid_axes`, :func:`node_config`).
``minv`` holds ``(a, b, c, d)`` of ``M^-1 = [[a, 0, b], [0, 1, 0], [c, 0, d]]``, the inverse
matrix divided by its middle element (:func:`minv_matrix`, :func:`coeffs_from_minv`; files of
format 1, divided by the (2, 2) element, are refused by :func:`read_table`).
:class:`LTCTable` interpolates bilinearly in ``(r, u)`` (Dr.Jit: :meth:`LTCTable.lookup`;
NumPy: :meth:`LTCTable.lookup_np`), clamping to the grid.
"""

from __future__ import annotations

import functools
import math
from importlib import resources
from pathlib import Path
from typing import Any

import drjit as dr
import numpy as np

from ...backend import VariantStruct, mi
from ...brdf import microfacet as mf
from ...brdf.ggx import ALPHA_MIN
from ...errors import GlossrtError

__all__ = [
    "COS_O_MIN",
    "DEFAULT_SIZE",
    "TABLE_FORMAT",
    "grid_axes",
    "node_config",
    "minv_matrix",
    "coeffs_from_minv",
    "default_table_path",
    "read_table",
    "LTCTable",
]

#: Smallest view cosine fitted: the ``u = 1`` column is the view at theta_o = 1.57 rad.
COS_O_MIN = math.cos(1.57)
#: Nodes per axis of the shipped table.
DEFAULT_SIZE = 64
#: layout version of the table files: 2 = ``M^-1`` divided by its middle element
TABLE_FORMAT = 2


# ----------------------------------------------------------------------------------------------
# Grid
# ----------------------------------------------------------------------------------------------


def grid_axes(size: int = DEFAULT_SIZE) -> tuple[np.ndarray, np.ndarray]:
    """Nominal node positions ``(r, u)``: ``r_j = u_j = j / (size - 1)``."""
    if size < 2:
        raise GlossrtError("the table needs at least 2 nodes per axis")
    t = np.linspace(0.0, 1.0, size)
    return t.copy(), t.copy()


def node_config(r: Any, u: Any) -> tuple[np.ndarray, np.ndarray]:
    """GGX ``alpha`` and view cosine at which nodes ``(r, u)`` are fitted (module docstring):
    ``alpha = max(r^2, ALPHA_MIN)``, ``cos_o = max(1 - u^2, COS_O_MIN)``."""
    r = np.asarray(r, dtype=np.float64)
    u = np.asarray(u, dtype=np.float64)
    return np.maximum(r * r, ALPHA_MIN), np.maximum(1.0 - u * u, COS_O_MIN)


# ----------------------------------------------------------------------------------------------
# Coefficients of M^-1
# ----------------------------------------------------------------------------------------------


def minv_matrix(coeffs: Any) -> Any:
    """Rebuild ``M^-1 = [[a, 0, b], [0, 1, 0], [c, 0, d]]`` from ``coeffs = (a, b, c, d)``
    (the inverse matrix divided by its middle element, module docstring).

    NumPy: ``(..., 4) -> (..., 3, 3)`` float64. Dr.Jit: a 4-vector (``mi.Vector4f``, ...) ->
    the matching 3x3 matrix type (``mi.Matrix3f``, ...), one matrix per lane.
    """
    if isinstance(coeffs, np.ndarray | list | tuple):
        c = np.asarray(coeffs, dtype=np.float64)
        out = np.zeros(c.shape[:-1] + (3, 3))
        out[..., 0, 0] = c[..., 0]
        out[..., 0, 2] = c[..., 1]
        out[..., 1, 1] = 1.0
        out[..., 2, 0] = c[..., 2]
        out[..., 2, 2] = c[..., 3]
        return out
    mat_t = _matrix3_of(type(coeffs))
    a, b, c, d = coeffs[0], coeffs[1], coeffs[2], coeffs[3]
    return mat_t(a, 0.0, b, 0.0, 1.0, 0.0, c, 0.0, d)


def _matrix3_of(vec_t: type) -> type:
    """The 3x3 matrix type with the scalar type of a Dr.Jit vector type."""
    if dr.type_v(vec_t) == dr.VarType.Float64:
        return dr.float64_array_t(mi.Matrix3f)
    return mi.Matrix3f


def coeffs_from_minv(minv: np.ndarray) -> np.ndarray:
    """``(..., 3, 3)`` inverse matrices in the xz-plane form -> ``(..., 4)`` coefficients
    ``(a, b, c, d)`` of :func:`minv_matrix` after dividing by the middle entry (which must be
    positive: ``1 / m22`` of the fit's parameters)."""
    m = np.asarray(minv, dtype=np.float64)
    e = m[..., 1, 1]
    if np.any(~(e > 0)):
        raise GlossrtError("the middle entry of M^-1 must be positive")
    return np.stack([m[..., 0, 0], m[..., 0, 2], m[..., 2, 0], m[..., 2, 2]], -1) / e[..., None]


# ----------------------------------------------------------------------------------------------
# Table files and lookups
# ----------------------------------------------------------------------------------------------


def default_table_path(distribution: str = "ggx") -> Path:
    """Path of the shipped table of ``distribution``: ``glossrt/data/ltc_ggx.npz`` or
    ``ltc_beckmann.npz``."""
    name = mf.NAMES[mf.code(distribution)]
    return Path(str(resources.files("glossrt") / "data" / f"ltc_{name}.npz"))


class LTCTable:
    """LTC tables on the device, one per distribution, with a Dr.Jit bilinear lookup (and a
    NumPy twin).

    ``minv`` is a flat ``mi.Float`` of ``n_d * n_r * n_u * 4`` coefficients and ``nf`` one of
    ``n_d * n_r * n_u * 2`` (``norm``, ``fres``), both row-major ``[distribution][r][u]``
    (``distributions`` names them: the shipped pair is ``("ggx", "beckmann")``); ``r0`` is
    the roughness at which row 0 was fitted (``sqrt(ALPHA_MIN)``). A Dr.Jit PyTree
    (``DRJIT_STRUCT``): instances can be passed to frozen functions, loops and vcalls.
    ``host`` keeps the float32 NumPy arrays (of the first distribution) for
    :meth:`lookup_np`.
    """

    DRJIT_STRUCT = VariantStruct(lambda: {"minv": mi.Float, "nf": mi.Float, "n_r": int,
                                          "n_u": int, "r0": float, "n_d": int})

    def __init__(self, minv: mi.Float | None = None, nf: mi.Float | None = None, n_r: int = 0,
                 n_u: int = 0, r0: float = 0.0, host: dict[str, np.ndarray] | None = None,
                 n_d: int = 1, distributions: tuple[str, ...] = ("ggx",)) -> None:
        self.minv = minv if minv is not None else mi.Float()
        self.nf = nf if nf is not None else mi.Float()
        self.n_r = int(n_r)
        self.n_u = int(n_u)
        self.r0 = float(r0)
        self.n_d = int(n_d)
        self.distributions = tuple(distributions)
        self.host = host or {}

    @classmethod
    def from_arrays(cls, minv: np.ndarray, norm: np.ndarray, fres: np.ndarray,
                    alpha_min: float = ALPHA_MIN,
                    distributions: tuple[str, ...] = ("ggx",)) -> LTCTable:
        """From ``minv`` ``(n_r, n_u, 4)`` and ``norm``, ``fres`` ``(n_r, n_u)`` (or with a
        leading axis of one table per entry of ``distributions``), fitted at
        ``alpha = max(r^2, alpha_min)`` (:func:`node_config`)."""
        minv = np.asarray(minv, dtype=np.float32)
        if minv.ndim == 3:
            minv, norm, fres = minv[None], np.asarray(norm)[None], np.asarray(fres)[None]
        minv = np.ascontiguousarray(minv)
        norm = np.asarray(norm, dtype=np.float32)
        fres = np.asarray(fres, dtype=np.float32)
        if minv.ndim != 4 or minv.shape[3] != 4 or min(minv.shape[1:3]) < 2:
            raise GlossrtError(f"expected an (n_r, n_u, 4) minv table, got {minv.shape}")
        if norm.shape != minv.shape[:3] or fres.shape != minv.shape[:3]:
            raise GlossrtError("norm and fres must have the shape (n_r, n_u) of minv")
        n_d, n_r, n_u, _ = minv.shape
        if len(distributions) != n_d:
            raise GlossrtError(f"{n_d} tables for distributions {distributions}")
        nf = np.ascontiguousarray(np.stack([norm, fres], -1))
        d_minv = mi.Float(minv.ravel())
        d_nf = mi.Float(nf.ravel())
        dr.make_opaque(d_minv, d_nf)
        r0 = math.sqrt(alpha_min)
        if not 0.0 <= r0 < 1.0 / (n_r - 1):
            raise GlossrtError(f"alpha_min must lie in [0, 1/(n_r-1)^2), got {alpha_min}")
        return cls(d_minv, d_nf, n_r, n_u, r0,
                   {"minv": minv[0], "norm": norm[0], "fres": fres[0]}, n_d, distributions)

    @classmethod
    def load(cls, path: Path | str | None = None) -> LTCTable:
        """The shipped tables of both distributions (GGX and Beckmann), or the one table at
        ``path`` (it shades every pixel with its own distribution); cached per path and
        Mitsuba variant."""
        p = str(Path(path).resolve()) if path is not None else ""
        return _load_cached(p, mi.variant())

    def _coords(self, alpha, cos_o, xp):
        """Continuous grid coordinates ``(y, x)`` of ``(r, u)``, clamped to the grid; row 0
        sits at ``r0`` (where it was fitted), every other row ``j`` at ``j / (n_r - 1)``."""
        r1 = 1.0 / (self.n_r - 1)
        k0 = 1.0 / (r1 - self.r0)
        if xp is np:
            a = np.nan_to_num(np.asarray(alpha, dtype=np.float64), nan=0.0)
            c = np.nan_to_num(np.asarray(cos_o, dtype=np.float64), nan=0.0)
            r = np.sqrt(np.clip(a, 0.0, 1.0))
            u = np.sqrt(1.0 - np.clip(c, 0.0, 1.0))
            y = np.where(r < r1, np.maximum(r - self.r0, 0.0) * k0, r * (self.n_r - 1))
            return y, u * (self.n_u - 1)
        a = dr.minimum(dr.select(alpha > 0.0, alpha, 0.0), 1.0)
        c = dr.minimum(dr.select(cos_o > 0.0, cos_o, 0.0), 1.0)
        r = dr.sqrt(a)
        y = dr.select(r < r1, dr.maximum(r - self.r0, 0.0) * k0, r * (self.n_r - 1))
        return y, dr.sqrt(1.0 - c) * (self.n_u - 1)

    def lookup(self, alpha: mi.Float, cos_o: mi.Float, beckmann: mi.Bool | None = None
               ) -> tuple[mi.Vector4f, mi.Float, mi.Float]:
        """Bilinearly interpolated ``(coeffs, norm, fres)`` at roughness ``alpha`` and view
        cosine ``cos_o``: ``coeffs = (a, b, c, d)`` of ``M^-1`` (:func:`minv_matrix`), from
        the Beckmann table where ``beckmann`` (per lane) and the GGX one elsewhere (a table
        of one distribution ignores ``beckmann``).

        Interpolation is bilinear in ``(r, u) = (sqrt(alpha), sqrt(1 - cos_o))`` between the
        fitted nodes (row 0 at ``r = sqrt(ALPHA_MIN)``, so ``alpha <= ALPHA_MIN`` reads row 0);
        ``alpha`` is clamped to [0, 1] and ``cos_o`` to [0, 1] (NaN reads 0). Only Dr.Jit
        operations, so it runs inside symbolic loops, vcalls and frozen functions.
        """
        y, x = self._coords(mi.Float(alpha), mi.Float(cos_o), dr)
        j0 = dr.minimum(mi.UInt32(y), self.n_r - 2)
        i0 = dr.minimum(mi.UInt32(x), self.n_u - 2)
        ty = y - mi.Float(j0)
        tx = x - mi.Float(i0)
        base = j0 * self.n_u + i0
        if beckmann is not None and self.n_d > 1:
            index = self.distributions.index("beckmann")
            base = base + dr.select(beckmann, index * self.n_r * self.n_u, 0)
        corners = (base, base + 1, base + self.n_u, base + self.n_u + 1)
        c = [dr.gather(mi.Vector4f, self.minv, k) for k in corners]
        n = [dr.gather(mi.Vector2f, self.nf, k) for k in corners]
        coeffs = dr.lerp(dr.lerp(c[0], c[1], tx), dr.lerp(c[2], c[3], tx), ty)
        nf = dr.lerp(dr.lerp(n[0], n[1], tx), dr.lerp(n[2], n[3], tx), ty)
        return coeffs, nf.x, nf.y

    def lookup_np(self, alpha: Any, cos_o: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """NumPy (float64) twin of :meth:`lookup`: ``coeffs`` ``(..., 4)``, ``norm``, ``fres``
        ``(...)`` for broadcast ``alpha`` and ``cos_o``."""
        y, x = self._coords(alpha, cos_o, np)
        y, x = np.broadcast_arrays(y, x)
        j0 = np.minimum(y.astype(np.int64), self.n_r - 2)
        i0 = np.minimum(x.astype(np.int64), self.n_u - 2)
        ty = (y - j0)[..., None]
        tx = (x - i0)[..., None]
        h = self.host
        tab = np.concatenate([h["minv"], h["norm"][..., None], h["fres"][..., None]], -1)
        tab = tab.astype(np.float64)
        v = ((1 - ty) * ((1 - tx) * tab[j0, i0] + tx * tab[j0, i0 + 1])
             + ty * ((1 - tx) * tab[j0 + 1, i0] + tx * tab[j0 + 1, i0 + 1]))
        return v[..., :4], v[..., 4], v[..., 5]

    def numpy(self) -> dict[str, np.ndarray]:
        """The (first) table as float32 arrays ``minv`` ``(n_r, n_u, 4)``, ``norm``,
        ``fres``."""
        return {k: v.copy() for k, v in self.host.items()}

    def __repr__(self) -> str:
        return f"LTCTable(n_r={self.n_r}, n_u={self.n_u}, distributions={self.distributions})"


def read_table(path: Path | str) -> dict[str, Any]:
    """The runtime arrays of one table file (``minv``, ``norm``, ``fres``, ``alpha_min``,
    ``distribution``), checked: a clear :class:`~glossrt.errors.GlossrtError` for a file of
    the earlier layout (``M^-1`` normalised by its (2, 2) element) or of another kind."""
    try:
        with np.load(path, allow_pickle=False) as f:
            if "minv" not in f.files:
                raise GlossrtError(f"{path}: not an LTC table (no 'minv' array)")
            fmt = int(f["format"]) if "format" in f.files else 1
            if fmt != TABLE_FORMAT:
                raise GlossrtError(
                    f"{path}: LTC table format {fmt} (M^-1 normalised by its (2, 2) element), "
                    f"glossrt reads format {TABLE_FORMAT}: refit it with 'glossrt ltc-fit'")
            return {"minv": f["minv"], "norm": f["norm"], "fres": f["fres"],
                    "alpha_min": float(f["alpha_min"]),
                    "distribution": str(f["distribution"])}
    except GlossrtError:
        raise
    except (OSError, ValueError) as e:
        raise GlossrtError(f"{path}: cannot read the LTC table: {e}") from e


@functools.lru_cache(maxsize=8)
def _load_cached(path: str, variant: str) -> LTCTable:
    paths = [path] if path else [str(default_table_path(d)) for d in mf.NAMES]
    tabs = [read_table(p) for p in paths]
    return LTCTable.from_arrays(np.stack([t["minv"] for t in tabs]),
                                np.stack([t["norm"] for t in tabs]),
                                np.stack([t["fres"] for t in tabs]), tabs[0]["alpha_min"],
                                tuple(t["distribution"] for t in tabs))
