"""The Utah teapot: Martin Newell's 32 bicubic Bezier patches (1975), tessellated.

Data: the public-domain control points as distributed in Steve Baker's ``teaset.tgz``
(http://www.sjbaker.org/teapot/, "teapot" file; here with 0-based indices, as reproduced in
github.com/markkilgard/opengl4_examples, ``tessellation/teapot.cpp``). The numbers are the
classic data set unchanged: z up, the body a surface of revolution of radius 2 at z = 0.9,
the lid knob's top at z = 3.15, the handle reaching x = -3 and the spout's tip x = 3.434
(bounding box [-3, 3.434] x [-2, 2] x [0, 3.15]). Four control points of the list (at
(0, +-0.002, 3.15) and (+-0.002, 0, 3.15)) are used by no patch; they are kept so that the
indices match the source.

Parts (patch indices): rim 0-3, body 4-11, handle 12-15, spout 16-19, lid knob 20-23, lid
24-27, bottom 28-31 (Crow's addition: not flat, it bulges down to z = 0 at the centre).

What the tessellated mesh is (and is not), see :func:`teapot_mesh`:

* the lid's rim (radius 1.3 at z = 2.4) does not meet the body's opening (radius 1.4): the
  classic gap, through which the inside of the rim shows;
* the spout and the handle are separate tubes pushed into the body: their ends are open
  but lie inside the body (the handle's lower end touches the body's surface at one point,
  (-2, 0, 0.9)), and the spout's tip is open;
* the lid knob's top and the bottom's centre are patch rows that collapse to one point
  (degenerate triangles there are removed; the welded centre vertex gets the normal of
  its fan, +z / -z).

So the mesh is closed along every patch seam but has 6 boundary loops (7 without the
bottom): body opening, lid rim, spout base and tip, handle's two ends.
"""

from __future__ import annotations

import numpy as np

from ..errors import GlossrtError

_PATCH_TEXT = """
    0,1,2,3,4,5,6,7,8,9,10,11,12,13,14,15,
    3,16,17,18,7,19,20,21,11,22,23,24,15,25,26,27,
    18,28,29,30,21,31,32,33,24,34,35,36,27,37,38,39,
    30,40,41,0,33,42,43,4,36,44,45,8,39,46,47,12,
    12,13,14,15,48,49,50,51,52,53,54,55,56,57,58,59,
    15,25,26,27,51,60,61,62,55,63,64,65,59,66,67,68,
    27,37,38,39,62,69,70,71,65,72,73,74,68,75,76,77,
    39,46,47,12,71,78,79,48,74,80,81,52,77,82,83,56,
    56,57,58,59,84,85,86,87,88,89,90,91,92,93,94,95,
    59,66,67,68,87,96,97,98,91,99,100,101,95,102,103,104,
    68,75,76,77,98,105,106,107,101,108,109,110,104,111,112,113,
    77,82,83,56,107,114,115,84,110,116,117,88,113,118,119,92,
    120,121,122,123,124,125,126,127,128,129,130,131,132,133,134,135,
    123,136,137,120,127,138,139,124,131,140,141,128,135,142,143,132,
    132,133,134,135,144,145,146,147,148,149,150,151,68,152,153,154,
    135,142,143,132,147,155,156,144,151,157,158,148,154,159,160,68,
    161,162,163,164,165,166,167,168,169,170,171,172,173,174,175,176,
    164,177,178,161,168,179,180,165,172,181,182,169,176,183,184,173,
    173,174,175,176,185,186,187,188,189,190,191,192,193,194,195,196,
    176,183,184,173,188,197,198,185,192,199,200,189,196,201,202,193,
    203,203,203,203,206,207,208,209,210,210,210,210,211,212,213,214,
    203,203,203,203,209,216,217,218,210,210,210,210,214,219,220,221,
    203,203,203,203,218,223,224,225,210,210,210,210,221,226,227,228,
    203,203,203,203,225,229,230,206,210,210,210,210,228,231,232,211,
    211,212,213,214,233,234,235,236,237,238,239,240,241,242,243,244,
    214,219,220,221,236,245,246,247,240,248,249,250,244,251,252,253,
    221,226,227,228,247,254,255,256,250,257,258,259,253,260,261,262,
    228,231,232,211,256,263,264,233,259,265,266,237,262,267,268,241,
    269,269,269,269,278,279,280,281,274,275,276,277,270,271,272,273,
    269,269,269,269,281,288,289,290,277,285,286,287,273,282,283,284,
    269,269,269,269,290,297,298,299,287,294,295,296,284,291,292,293,
    269,269,269,269,299,304,305,278,296,302,303,274,293,300,301,270,"""

_VERTEX_TEXT = """
    1.4,0,2.4, 1.4,-0.784,2.4, 0.784,-1.4,2.4, 0,-1.4,2.4,
    1.3375,0,2.53125, 1.3375,-0.749,2.53125, 0.749,-1.3375,2.53125, 0,-1.3375,2.53125,
    1.4375,0,2.53125, 1.4375,-0.805,2.53125, 0.805,-1.4375,2.53125, 0,-1.4375,2.53125,
    1.5,0,2.4, 1.5,-0.84,2.4, 0.84,-1.5,2.4, 0,-1.5,2.4,
    -0.784,-1.4,2.4, -1.4,-0.784,2.4, -1.4,0,2.4, -0.749,-1.3375,2.53125,
    -1.3375,-0.749,2.53125, -1.3375,0,2.53125, -0.805,-1.4375,2.53125, -1.4375,-0.805,2.53125,
    -1.4375,0,2.53125, -0.84,-1.5,2.4, -1.5,-0.84,2.4, -1.5,0,2.4,
    -1.4,0.784,2.4, -0.784,1.4,2.4, 0,1.4,2.4, -1.3375,0.749,2.53125,
    -0.749,1.3375,2.53125, 0,1.3375,2.53125, -1.4375,0.805,2.53125, -0.805,1.4375,2.53125,
    0,1.4375,2.53125, -1.5,0.84,2.4, -0.84,1.5,2.4, 0,1.5,2.4,
    0.784,1.4,2.4, 1.4,0.784,2.4, 0.749,1.3375,2.53125, 1.3375,0.749,2.53125,
    0.805,1.4375,2.53125, 1.4375,0.805,2.53125, 0.84,1.5,2.4, 1.5,0.84,2.4,
    1.75,0,1.875, 1.75,-0.98,1.875, 0.98,-1.75,1.875, 0,-1.75,1.875,
    2,0,1.35, 2,-1.12,1.35, 1.12,-2,1.35, 0,-2,1.35,
    2,0,0.9, 2,-1.12,0.9, 1.12,-2,0.9, 0,-2,0.9,
    -0.98,-1.75,1.875, -1.75,-0.98,1.875, -1.75,0,1.875, -1.12,-2,1.35,
    -2,-1.12,1.35, -2,0,1.35, -1.12,-2,0.9, -2,-1.12,0.9,
    -2,0,0.9, -1.75,0.98,1.875, -0.98,1.75,1.875, 0,1.75,1.875,
    -2,1.12,1.35, -1.12,2,1.35, 0,2,1.35, -2,1.12,0.9,
    -1.12,2,0.9, 0,2,0.9, 0.98,1.75,1.875, 1.75,0.98,1.875,
    1.12,2,1.35, 2,1.12,1.35, 1.12,2,0.9, 2,1.12,0.9,
    2,0,0.45, 2,-1.12,0.45, 1.12,-2,0.45, 0,-2,0.45,
    1.5,0,0.225, 1.5,-0.84,0.225, 0.84,-1.5,0.225, 0,-1.5,0.225,
    1.5,0,0.15, 1.5,-0.84,0.15, 0.84,-1.5,0.15, 0,-1.5,0.15,
    -1.12,-2,0.45, -2,-1.12,0.45, -2,0,0.45, -0.84,-1.5,0.225,
    -1.5,-0.84,0.225, -1.5,0,0.225, -0.84,-1.5,0.15, -1.5,-0.84,0.15,
    -1.5,0,0.15, -2,1.12,0.45, -1.12,2,0.45, 0,2,0.45,
    -1.5,0.84,0.225, -0.84,1.5,0.225, 0,1.5,0.225, -1.5,0.84,0.15,
    -0.84,1.5,0.15, 0,1.5,0.15, 1.12,2,0.45, 2,1.12,0.45,
    0.84,1.5,0.225, 1.5,0.84,0.225, 0.84,1.5,0.15, 1.5,0.84,0.15,
    -1.6,0,2.025, -1.6,-0.3,2.025, -1.5,-0.3,2.25, -1.5,0,2.25,
    -2.3,0,2.025, -2.3,-0.3,2.025, -2.5,-0.3,2.25, -2.5,0,2.25,
    -2.7,0,2.025, -2.7,-0.3,2.025, -3,-0.3,2.25, -3,0,2.25,
    -2.7,0,1.8, -2.7,-0.3,1.8, -3,-0.3,1.8, -3,0,1.8,
    -1.5,0.3,2.25, -1.6,0.3,2.025, -2.5,0.3,2.25, -2.3,0.3,2.025,
    -3,0.3,2.25, -2.7,0.3,2.025, -3,0.3,1.8, -2.7,0.3,1.8,
    -2.7,0,1.575, -2.7,-0.3,1.575, -3,-0.3,1.35, -3,0,1.35,
    -2.5,0,1.125, -2.5,-0.3,1.125, -2.65,-0.3,0.9375, -2.65,0,0.9375,
    -2,-0.3,0.9, -1.9,-0.3,0.6, -1.9,0,0.6, -3,0.3,1.35,
    -2.7,0.3,1.575, -2.65,0.3,0.9375, -2.5,0.3,1.125, -1.9,0.3,0.6,
    -2,0.3,0.9, 1.7,0,1.425, 1.7,-0.66,1.425, 1.7,-0.66,0.6,
    1.7,0,0.6, 2.6,0,1.425, 2.6,-0.66,1.425, 3.1,-0.66,0.825,
    3.1,0,0.825, 2.3,0,2.1, 2.3,-0.25,2.1, 2.4,-0.25,2.025,
    2.4,0,2.025, 2.7,0,2.4, 2.7,-0.25,2.4, 3.3,-0.25,2.4,
    3.3,0,2.4, 1.7,0.66,0.6, 1.7,0.66,1.425, 3.1,0.66,0.825,
    2.6,0.66,1.425, 2.4,0.25,2.025, 2.3,0.25,2.1, 3.3,0.25,2.4,
    2.7,0.25,2.4, 2.8,0,2.475, 2.8,-0.25,2.475, 3.525,-0.25,2.49375,
    3.525,0,2.49375, 2.9,0,2.475, 2.9,-0.15,2.475, 3.45,-0.15,2.5125,
    3.45,0,2.5125, 2.8,0,2.4, 2.8,-0.15,2.4, 3.2,-0.15,2.4,
    3.2,0,2.4, 3.525,0.25,2.49375, 2.8,0.25,2.475, 3.45,0.15,2.5125,
    2.9,0.15,2.475, 3.2,0.15,2.4, 2.8,0.15,2.4, 0,0,3.15,
    0,-0.002,3.15, 0.002,0,3.15, 0.8,0,3.15, 0.8,-0.45,3.15,
    0.45,-0.8,3.15, 0,-0.8,3.15, 0,0,2.85, 0.2,0,2.7,
    0.2,-0.112,2.7, 0.112,-0.2,2.7, 0,-0.2,2.7, -0.002,0,3.15,
    -0.45,-0.8,3.15, -0.8,-0.45,3.15, -0.8,0,3.15, -0.112,-0.2,2.7,
    -0.2,-0.112,2.7, -0.2,0,2.7, 0,0.002,3.15, -0.8,0.45,3.15,
    -0.45,0.8,3.15, 0,0.8,3.15, -0.2,0.112,2.7, -0.112,0.2,2.7,
    0,0.2,2.7, 0.45,0.8,3.15, 0.8,0.45,3.15, 0.112,0.2,2.7,
    0.2,0.112,2.7, 0.4,0,2.55, 0.4,-0.224,2.55, 0.224,-0.4,2.55,
    0,-0.4,2.55, 1.3,0,2.55, 1.3,-0.728,2.55, 0.728,-1.3,2.55,
    0,-1.3,2.55, 1.3,0,2.4, 1.3,-0.728,2.4, 0.728,-1.3,2.4,
    0,-1.3,2.4, -0.224,-0.4,2.55, -0.4,-0.224,2.55, -0.4,0,2.55,
    -0.728,-1.3,2.55, -1.3,-0.728,2.55, -1.3,0,2.55, -0.728,-1.3,2.4,
    -1.3,-0.728,2.4, -1.3,0,2.4, -0.4,0.224,2.55, -0.224,0.4,2.55,
    0,0.4,2.55, -1.3,0.728,2.55, -0.728,1.3,2.55, 0,1.3,2.55,
    -1.3,0.728,2.4, -0.728,1.3,2.4, 0,1.3,2.4, 0.224,0.4,2.55,
    0.4,0.224,2.55, 0.728,1.3,2.55, 1.3,0.728,2.55, 0.728,1.3,2.4,
    1.3,0.728,2.4, 0,0,0, 1.5,0,0.15, 1.5,0.84,0.15,
    0.84,1.5,0.15, 0,1.5,0.15, 1.5,0,0.075, 1.5,0.84,0.075,
    0.84,1.5,0.075, 0,1.5,0.075, 1.425,0,0, 1.425,0.798,0,
    0.798,1.425,0, 0,1.425,0, -0.84,1.5,0.15, -1.5,0.84,0.15,
    -1.5,0,0.15, -0.84,1.5,0.075, -1.5,0.84,0.075, -1.5,0,0.075,
    -0.798,1.425,0, -1.425,0.798,0, -1.425,0,0, -1.5,-0.84,0.15,
    -0.84,-1.5,0.15, 0,-1.5,0.15, -1.5,-0.84,0.075, -0.84,-1.5,0.075,
    0,-1.5,0.075, -1.425,-0.798,0, -0.798,-1.425,0, 0,-1.425,0,
    0.84,-1.5,0.15, 1.5,-0.84,0.15, 0.84,-1.5,0.075, 1.5,-0.84,0.075,
    0.798,-1.425,0, 1.425,-0.798,0,"""

#: (32, 16) control point indices per patch, row-major 4 x 4 (0-based)
PATCHES = np.array(_PATCH_TEXT.replace("\n", "").strip(",").split(","), dtype=np.int64).reshape(
    32, 16)
#: (306, 3) control points (z up)
CONTROL_POINTS = np.array(
    _VERTEX_TEXT.replace("\n", "").replace(" ", "").strip(",").split(","), dtype=np.float64
).reshape(306, 3)

#: patch indices of each part
PARTS = {
    "rim": range(0, 4),
    "body": range(4, 12),
    "handle": range(12, 16),
    "spout": range(16, 20),
    "knob": range(20, 24),
    "lid": range(24, 28),
    "bottom": range(28, 32),
}

#: bounding box of the full teapot surface (the handle's outer corner, the body's radius,
#: the bottom's centre, the knob's top; the spout's lip bulges out to x = 3.43408, inside
#: its patches, so tessellations approach it from below)
BBOX_MIN = (-3.0, -2.0, 0.0)
BBOX_MAX = (3.434075, 2.0, 3.15)
#: surface area of the 32 patches (64 x 64-point Gauss-Legendre quadrature of |P_u x P_v|;
#: the spout and handle parts inside the body included); tessellations approach it from
#: below, -0.65 % at n = 8, -0.17 % at n = 16
PATCH_AREA = 52.8833


def patch_control_points() -> np.ndarray:
    """(32, 4, 4, 3) control points of every patch (row index first)."""
    return CONTROL_POINTS[PATCHES].reshape(32, 4, 4, 3)


def _bernstein(t: np.ndarray) -> np.ndarray:
    s = 1.0 - t
    return np.stack([s * s * s, 3.0 * s * s * t, 3.0 * s * t * t, t * t * t], axis=-1)


def _weld_groups(lid: bool, bottom: bool) -> list[list[int]]:
    """Patches welded together: rim + body (+ bottom), handle, spout, knob + lid. The handle
    and the spout only touch the body (a control point in common at the handle's lower
    end): welding them would give body vertices normals bent towards the handle."""
    body = list(PARTS["rim"]) + list(PARTS["body"]) + (list(PARTS["bottom"]) if bottom else [])
    groups = [body, list(PARTS["handle"]), list(PARTS["spout"])]
    if lid:
        groups.append(list(PARTS["knob"]) + list(PARTS["lid"]))
    return groups


def _orient_patches(faces: np.ndarray, patch_of_face: np.ndarray, patches: list[int]) -> dict:
    """Flip flag per patch so that every edge shared by two patches is traversed in opposite
    directions (a consistent orientation of the welded surface)."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    owner = np.tile(patch_of_face, 3)
    key = np.sort(e, axis=1)
    forward = e[:, 0] < e[:, 1]
    order = np.lexsort((key[:, 1], key[:, 0]))
    key, forward, owner = key[order], forward[order], owner[order]
    same = np.all(key[1:] == key[:-1], axis=1) & (owner[1:] != owner[:-1])
    # constraint: flip[p] ^ flip[q] == (both traverse the shared edge the same way)
    links: dict[int, list[tuple[int, bool]]] = {p: [] for p in patches}
    for i in np.flatnonzero(same):
        p, q, parity = int(owner[i]), int(owner[i + 1]), bool(forward[i] == forward[i + 1])
        links[p].append((q, parity))
        links[q].append((p, parity))
    flip: dict[int, bool] = {}
    for start in patches:
        if start in flip:
            continue
        flip[start] = False
        stack = [start]
        while stack:
            p = stack.pop()
            for q, parity in links[p]:
                want = flip[p] ^ parity
                if q not in flip:
                    flip[q] = want
                    stack.append(q)
                elif flip[q] != want:  # pragma: no cover - the data set is orientable
                    raise ValueError(f"teapot patches {p} and {q} cannot be oriented alike")
    return flip


def _closed_volume(v: np.ndarray, faces: np.ndarray) -> float:
    """Signed volume of the surface with each boundary loop closed by a fan from the loop's
    centroid (positive: faces wound counter-clockwise seen from outside)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    def det_sum(a, b, c):
        return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum()) / 6.0

    vol = det_sum(v[faces[:, 0]], v[faces[:, 1]], v[faces[:, 2]])
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    key = np.sort(e, axis=1)
    _, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    boundary = e[counts[inv.ravel()] == 1]  # directed as in their face
    if len(boundary):
        n = len(v)
        graph = coo_matrix((np.ones(len(boundary)), (boundary[:, 0], boundary[:, 1])),
                           shape=(n, n))
        _, label = connected_components(graph, directed=False)
        loops = label[boundary[:, 0]]
        for lab in np.unique(loops):
            edges = boundary[loops == lab]
            c = v[np.unique(edges)].mean(axis=0)
            vol += det_sum(v[edges[:, 1]], v[edges[:, 0]], np.broadcast_to(c, (len(edges), 3)))
    return vol


def _vertex_normals(v: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted smooth normals; a vertex whose weighted sum vanishes (cannot happen
    on the teapot, but guards against NaN) takes the mean of its faces' unit normals, or
    +z."""
    fn = np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]])
    acc = np.zeros_like(v)
    for k in range(3):
        np.add.at(acc, faces[:, k], fn)
    length = np.linalg.norm(acc, axis=1)
    bad = ~(length > 1e-12 * max(1.0, float(np.max(length, initial=0.0))))
    if np.any(bad):
        unit = fn / np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-300)
        acc2 = np.zeros_like(v)
        for k in range(3):
            np.add.at(acc2, faces[:, k], unit)
        acc[bad] = acc2[bad]
        length = np.linalg.norm(acc, axis=1)
        still = ~(length > 1e-12)
        acc[still] = (0.0, 0.0, 1.0)
        length[still] = 1.0
    return acc / length[:, None]


def teapot_mesh(n: int = 8, lid: bool = True, bottom: bool = True):
    """Tessellate the teapot: each patch on an ``n`` x ``n`` grid of quads (two triangles
    each, ``n >= 2``), vertices welded along patch seams.

    Returns ``(vertices (V, 3) float32, faces (F, 3) uint32, normals (V, 3) float32)`` in
    the data's own frame (z up, units of the data: 3.15 tall). Faces are wound counter-
    clockwise seen from outside (the side the normals point to); normals are unit, area-
    weighted averages of the faces around each vertex (for ``n < 6`` a few faces on the
    spout's sharply curled lip, and at ``n = 2`` on the rim's, tilt past one of their
    vertices' normals).

    Counts: with lid and bottom ``V = 32 n^2 + 4 n + 2`` and ``F = 64 n^2 - 8 n`` (the
    ``8 n`` degenerate triangles at the knob's top and the bottom's centre are dropped).
    Without the bottom the body has ``(3 n + 1) 4 n`` vertices instead of ``16 n^2 + 1``
    and ``8 n^2 - 4 n`` faces fewer; without the lid ``8 n^2 + 1`` vertices and
    ``16 n^2 - 4 n`` faces fewer. The handle and the spout are welded separately from the
    body (see :func:`_weld_groups`), so their vertices where they meet the body are not
    shared with it."""
    n = int(n)
    if n < 2:
        # n = 1 flattens the spout's and the handle's half-tubes (their four corners lie
        # on the symmetry plane y = 0) into zero-area triangles
        raise GlossrtError(f"teapot tessellation needs n >= 2, got {n}")
    ctrl = patch_control_points()
    basis = _bernstein(np.linspace(0.0, 1.0, n + 1))
    grids = np.einsum("ia,jb,pabk->pijk", basis, basis, ctrl)  # (32, n+1, n+1, 3)
    # quads (i, j) -> triangles (a, b, c), (a, c, d) in grid indices
    idx = np.arange((n + 1) * (n + 1)).reshape(n + 1, n + 1)
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    c, d = idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    grid_faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])

    all_v, all_f, all_n = [], [], []
    offset = 0
    for group in _weld_groups(lid, bottom):
        pts = grids[group].reshape(-1, 3)
        # exact welding: seams share control points, so their samples are bit-identical
        # (Bernstein weights are exactly 0 / 1 at the patch edges); +0.0 folds -0.0 into 0.0
        key = np.round(pts, 9) + 0.0
        _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
        inverse = inverse.ravel()
        # keep first-occurrence order (patch by patch, row by row)
        rank = np.empty(len(first), np.int64)
        rank[np.argsort(first, kind="stable")] = np.arange(len(first))
        remap = rank[inverse]
        verts = pts[np.sort(first)]
        m = (n + 1) * (n + 1)
        faces = np.concatenate([remap[grid_faces + k * m] for k in range(len(group))])
        patch_of_face = np.repeat(np.asarray(group), len(grid_faces))
        keep = ((faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2])
                & (faces[:, 2] != faces[:, 0]))
        faces, patch_of_face = faces[keep], patch_of_face[keep]
        flip = _orient_patches(faces, patch_of_face, group)
        flipped = np.array([flip[int(p)] for p in patch_of_face], dtype=bool)
        faces[flipped] = faces[flipped][:, ::-1]
        if _closed_volume(verts, faces) < 0.0:
            faces = faces[:, ::-1]
        all_v.append(verts)
        all_f.append(faces + offset)
        all_n.append(_vertex_normals(verts, faces))
        offset += len(verts)
    vertices = np.concatenate(all_v)
    return (vertices.astype(np.float32), np.concatenate(all_f).astype(np.uint32),
            np.concatenate(all_n).astype(np.float32))


def _as_matrix(to_world) -> np.ndarray:
    if to_world is None:
        return np.eye(4)
    m = getattr(to_world, "matrix", to_world)
    m = np.array(m, dtype=np.float64)
    if m.ndim == 3:
        m = m[..., 0]
    return m.reshape(4, 4)


def mesh_shape(name: str, v: np.ndarray, f: np.ndarray, nrm: np.ndarray | None = None,
               to_world=None, bsdf=None, emitter=None):
    """A Mitsuba mesh (``mi.Mesh``) from vertices ``v`` (V, 3), counter-clockwise faces ``f``
    (F, 3) and optional vertex normals ``nrm`` (V, 3), transformed by ``to_world`` (4x4 matrix
    or ``mi.ScalarTransform4f``: vertices transformed, normals by the inverse transpose, the
    winding reversed under a mirroring transform so it stays counter-clockwise from outside),
    to put as a value in a scene dict for ``mi.load_dict`` (the dict key becomes its id).
    ``bsdf``: a BSDF dict (or object); Mitsuba's default diffuse when None. ``emitter``: an
    emitter dict (or object), e.g. ``{"type": "area", ...}``, for a mesh light."""
    from ..backend import mi

    m = _as_matrix(to_world)
    v = np.asarray(v, np.float64) @ m[:3, :3].T + m[:3, 3]
    f = np.asarray(f)
    if np.linalg.det(m[:3, :3]) < 0.0:
        f = f[:, ::-1]
    props = mi.Properties("mesh")
    if bsdf is not None:
        props["bsdf"] = mi.load_dict(bsdf) if isinstance(bsdf, dict) else bsdf
    if emitter is not None:
        props["emitter"] = mi.load_dict(emitter) if isinstance(emitter, dict) else emitter
    mesh = mi.Mesh(name, len(v), len(f), props, has_vertex_normals=nrm is not None)
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(v.astype(np.float32).ravel())
    params["faces"] = mi.UInt32(np.ascontiguousarray(f, dtype=np.uint32).ravel())
    params.update()
    if nrm is not None:
        nrm = np.asarray(nrm, np.float64) @ np.linalg.inv(m[:3, :3])  # (M^-T n) as rows
        nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
        # after the positions: an update of vertex_positions may recompute the normals
        params["vertex_normals"] = mi.Float(nrm.astype(np.float32).ravel())
        params.update()
    return mesh


def teapot_shape(n: int = 8, to_world=None, bsdf=None, *, lid: bool = True,
                 bottom: bool = True, name: str = "teapot"):
    """A Mitsuba mesh (``mi.Mesh``) of :func:`teapot_mesh` (see :func:`mesh_shape` for
    ``to_world`` and ``bsdf``)."""
    v, f, nrm = teapot_mesh(n, lid=lid, bottom=bottom)
    return mesh_shape(name, v, f, nrm, to_world, bsdf)


def grid_mesh(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The square [-1, 1]^2 at z = 0 as an ``n`` x ``n`` grid of quads (two triangles each,
    counter-clockwise seen from +z): ``(vertices, faces, normals)`` -- a floor that can carry
    per-vertex data (BSPVT shadows), where Mitsuba's ``rectangle`` has no vertices."""
    if n < 1:
        raise GlossrtError(f"grid resolution must be >= 1, got {n}")
    t = np.linspace(-1.0, 1.0, n + 1)
    x, y = np.meshgrid(t, t, indexing="xy")
    v = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], -1)
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="xy")
    a = (j * (n + 1) + i).ravel()
    b, c, d = a + 1, a + n + 2, a + n + 1
    f = np.concatenate([np.stack([a, b, c], -1), np.stack([a, c, d], -1)])
    return v, f.astype(np.uint32), np.tile([0.0, 0.0, 1.0], (len(v), 1))


def sphere_mesh(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The unit sphere as a latitude-longitude mesh: ``n`` rings of ``2 n`` quads (triangles
    at the poles), seams welded, counter-clockwise seen from outside; normals = positions."""
    if n < 2:
        raise GlossrtError(f"sphere resolution must be >= 2, got {n}")
    m = 2 * n
    th = np.linspace(0.0, np.pi, n + 1)[1:-1]
    ph = np.arange(m) * (2 * np.pi / m)
    ring = np.stack([np.outer(np.sin(th), np.cos(ph)), np.outer(np.sin(th), np.sin(ph)),
                     np.outer(np.cos(th), np.ones(m))], -1).reshape(-1, 3)
    v = np.concatenate([[[0.0, 0.0, 1.0]], ring, [[0.0, 0.0, -1.0]]])
    south = len(v) - 1
    k = np.arange(m)
    k1 = (k + 1) % m
    faces = [np.stack([np.zeros(m, int), 1 + k, 1 + k1], -1)]
    for r in range(n - 2):
        a, b = 1 + r * m + k, 1 + r * m + k1
        c, d = a + m, b + m
        faces += [np.stack([a, c, d], -1), np.stack([a, d, b], -1)]
    last = 1 + (n - 2) * m
    faces.append(np.stack([last + k, np.full(m, south), last + k1], -1))
    return v, np.concatenate(faces).astype(np.uint32), v.copy()
