"""Direct light from the scene's emitters, one package per paper and the pieces they share.

Shared: polygon clipping and edge integrals (``polygon``), shading points and the BRDF
(``shading``), the polygon lights of a scene (``scene``), its point and directional lights
(``analytic``), the Monte Carlo reference (``mc``) and quadrature rules (``quadrature``).
Techniques: linearly transformed cosines (``ltc``: fit, table, shade), BSPVT shadows
(``bspvt``: build, shade, scene), the ratio estimator (``ratio``) and light-shaped highlights
(``highlights``: envmap, render)."""
