"""Polygonal and textured area lights: polygon clipping and edge integrals (``polygon``),
linearly transformed cosines fitted by glossrt (``ltc_fit``), LTC shading (``ltc``) and the
polygon lights of a scene (``scene``), and its point and directional lights
(``analytic``)."""
