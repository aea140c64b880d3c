"""Shadows of polygon lights with binary space partitioning visibility trees (Okuno & Iwasaki):
``build`` precomputes the visibility cube maps and their trees (Algorithm 1), ``shade``
integrates the visible pieces of a light (eq. 2), ``scene`` is the entry point for a scene
and its Frames (build the trees, check that they match the scene, shade)."""

from .build import BSPVT, build_trees, scene_vertices, visibility_cubemaps
from .scene import (
    build_scene_trees,
    check_trees_match,
    match_scene,
    pixel_triangles,
    shade_bspvt,
)

__all__ = ["BSPVT", "build_scene_trees", "build_trees", "check_trees_match", "match_scene",
           "pixel_triangles", "scene_vertices", "shade_bspvt", "visibility_cubemaps"]
