"""Polygon lights shaded with linearly transformed cosines (Heitz, Dupuy, Hill, Neubelt 2016):
``fit`` fits the LTC tables to the GGX and Beckmann lobes Mitsuba renders (offline,
``glossrt ltc-fit``), ``table`` reads the shipped tables and looks them up, ``shade`` shades
Frames and polygons with them (and textured lights, sec. 5.3)."""

from .shade import PrefilteredTexture, ltc_frame, polygon_integral, shade_frame, shade_tensor
from .table import LTCTable

__all__ = ["LTCTable", "PrefilteredTexture", "ltc_frame", "polygon_integral", "shade_frame",
           "shade_tensor"]
