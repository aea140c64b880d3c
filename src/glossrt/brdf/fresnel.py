"""The Fresnel terms Mitsuba renders, and their use with split-sum tables.

Mitsuba's ``roughconductor`` weights its lobe with the exact conductor Fresnel term
``fresnel_conductor(wo.h, eta + i k)`` and ``roughplastic`` its specular lobe with the exact
dielectric term ``fresnel(wo.h, eta)`` (both times ``specular_reflectance``). glossrt evaluates
the same functions (Mitsuba's own ``mi.fresnel_conductor`` / ``mi.fresnel``) per lane:
:func:`fresnel_exact`.

A split-sum table (:mod:`glossrt.brdf.ggx`, :mod:`glossrt.lights.ltc.fit`) stores, per view and
roughness, the lobe's mass ``norm = A + B`` and its Schlick moment ``fres = B``
(``integral rho cos (1 - wo.h)^5``). Schlick's form ``F0 (norm - fres) + fres`` is exact for
Schlick's Fresnel only. glossrt instead evaluates the exact term at the *effective* angle whose
Schlick weight equals the lobe's average one:

    (1 - c_eff)^5 = fres / norm,     integral rho F cos  ~=  norm F(c_eff)

It is exact for a mirror (the lobe's ``wo.h`` is the view cosine) and for any ``F`` linear in
``(1 - c)^5``. Measured against a float64 quadrature of the exact conductor term (gold, GGX and
Beckmann, alpha 0.05 / 0.3 / 0.7, views 0.15 / 0.5 / 0.9): largest error 0.0097 (Schlick's
split: 0.026), 0.0012 at alpha 0.05 (Schlick: 0.025).
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import numpy as np

from ..backend import mi

__all__ = ["SCHLICK", "CONDUCTOR", "DIELECTRIC", "NONE", "ROW", "Fresnel", "fresnel_exact",
           "effective_cos", "split_sum"]

#: ``Fresnel.kind``: only F0 is known (Schlick's form), a conductor, a dielectric coating, or
#: no specular lobe at all (Mitsuba's ``diffuse``: ``F = 0`` at every angle, where Schlick's
#: form with ``F0 = 0`` would still leave its grazing ``(1 - cos)^5`` term)
SCHLICK = 0
CONDUCTOR = 1
DIELECTRIC = 2
NONE = 3


@dataclass(frozen=True)
class Fresnel:
    """A BSDF's Fresnel term: ``kind``, RGB ``eta`` and ``k`` (conductor: complex IOR
    ``eta + i k``; dielectric: relative IOR ``eta``), RGB ``scale``
    (``specular_reflectance``) and ``f0``, its value at normal incidence."""

    kind: int = SCHLICK
    eta: tuple[float, float, float] = (1.0, 1.0, 1.0)
    k: tuple[float, float, float] = (0.0, 0.0, 0.0)
    scale: tuple[float, float, float] = (1.0, 1.0, 1.0)
    f0: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def row(self) -> np.ndarray:
        """The 13 numbers of an image row: kind, eta, k, scale, f0 (see :func:`fresnel_exact`)."""
        return np.array([self.kind, *self.eta, *self.k, *self.scale, *self.f0], np.float64)


#: channels of a per-pixel Fresnel image (``Fresnel.row``)
ROW = 13


def fresnel_exact(cos: mi.Float, kind, eta: mi.Color3f, k: mi.Color3f, scale: mi.Color3f,
                  f0: mi.Color3f) -> mi.Color3f:
    """The Fresnel term at ``cos = wo.h`` per lane, as Mitsuba's plugins evaluate it:
    conductors ``mi.fresnel_conductor`` with ``eta + i k``, dielectrics ``mi.fresnel`` with
    ``eta``, both times ``scale``; :data:`SCHLICK` lanes Schlick's form with ``f0``
    (Schlick 1994); :data:`NONE` lanes (no specular lobe) 0. ``kind`` is per lane
    (``mi.UInt32``) or a Python int."""
    c = dr.clip(mi.Float(cos), 0.0, 1.0)
    m = 1.0 - c
    schlick = f0 + (1.0 - f0) * (m * m * m * m * m)
    if isinstance(kind, int) and kind == SCHLICK:
        return mi.Color3f(schlick)
    if isinstance(kind, int) and kind == NONE:
        return dr.zeros(mi.Color3f, dr.width(c))
    cond = mi.Color3f(*(mi.fresnel_conductor(c, mi.Complex2f(eta[i], k[i])) for i in range(3)))
    diel = mi.Color3f(*(mi.fresnel(c, eta[i])[0] for i in range(3)))
    exact = dr.select(kind == CONDUCTOR, cond, diel) * scale
    exact = dr.select(kind == NONE, 0.0, exact)
    return dr.select(kind == SCHLICK, schlick, exact)


def effective_cos(norm: mi.Float, fres: mi.Float) -> mi.Float:
    """``c_eff = 1 - (fres / norm)^(1/5)``: the angle whose Schlick weight is the lobe's mean
    (module docstring); 1 where the lobe has no mass."""
    ratio = dr.select(norm > 0.0, fres / dr.maximum(norm, 1e-30), 0.0)
    return 1.0 - dr.power(dr.clip(ratio, 0.0, 1.0), 0.2)


def split_sum(norm: mi.Float, fres: mi.Float, kind, eta: mi.Color3f, k: mi.Color3f,
              scale: mi.Color3f, f0: mi.Color3f) -> mi.Color3f:
    """``integral rho F cos`` from a split-sum table's ``norm`` and ``fres``: Schlick's exact
    split ``F0 (norm - fres) + fres`` on :data:`SCHLICK` lanes, ``norm F(c_eff)`` with the exact
    term elsewhere (module docstring; 0 on :data:`NONE` lanes)."""
    schlick = f0 * (norm - fres) + fres
    if isinstance(kind, int) and kind == SCHLICK:
        return mi.Color3f(schlick)
    exact = norm * fresnel_exact(effective_cos(norm, fres), kind, eta, k, scale, f0)
    return dr.select(kind == SCHLICK, schlick, exact)
