"""Highlights that show the light's shape on rough surfaces (Kimura & Tokoi 2004): ``envmap``
renders the polygon lights into light cube maps, ``render`` shades Frames by sampling them with
microfacet normals (:class:`HighlightRenderer`), with its reference and the paper's baseline
(``shade_plain``: each light as a point light)."""

from .render import HighlightRenderer, reference, shade_plain

__all__ = ["HighlightRenderer", "reference", "shade_plain"]
