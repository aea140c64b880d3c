"""glossrt.lights.highlights.envmap: light environment cube maps (Kimura & Tokoi 2004, issue 7).

* rendering against independent computations: the solid angle of a quad (Van Oosterom &
  Strackee's formula, exact where the quad's edges fall on texel boundaries, within a
  rigorous discretisation bound otherwise), radiance x solid angle, one-sided back faces,
  and texel by texel against a float64 NumPy ray caster with the same sample positions
  (several lights, occlusion, a textured light); a two-colour texture where expected;
* exact texel solid angles against quadrature; mip levels keep the solid-angle integral;
* lookups: stored values at texel centres, NumPy == Dr.Jit, bilinear midpoints, linear
  (monotone) in ``lod``; ``fis_lod`` against its formula;
* bounding spheres against a numerical minimisation, the cone test of ``cull_mask``;
* probes and per-mesh maps on a small Mitsuba scene; clear errors on bad input.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from glossrt import backend

backend.ensure()

import mitsuba as mi  # noqa: E402

from glossrt.errors import GlossrtError  # noqa: E402
from glossrt.lights.bspvt.build import cube_dir, cube_directions, texel_centres  # noqa: E402
from glossrt.lights.highlights.envmap import (  # noqa: E402
    SPHERE_EPS,
    CubeMapSet,
    LightCubeMap,
    cull_mask,
    fis_lod,
    level_resolutions,
    light_spheres,
    lobe_spread,
    mip_chain,
    probe_points,
    texel_solid_angles,
)
from glossrt.lights.scene import PolygonLight  # noqa: E402

#: a 2 x 2 square at z = 2 facing the origin (counter-clockwise seen from below)
SQUARE = np.array([[-1.0, -1.0, 2.0], [-1.0, 1.0, 2.0], [1.0, 1.0, 2.0], [1.0, -1.0, 2.0]])
SQUARE_UV = (SQUARE[:, :2] + 1.0) / 2.0


def vec(a: np.ndarray) -> mi.Vector3f:
    a = np.asarray(a, np.float64).reshape(-1, 3)
    return mi.Vector3f(*(mi.Float(np.ascontiguousarray(a[:, c], np.float32)) for c in range(3)))


def col_np(c) -> np.ndarray:
    return np.stack([np.asarray(c[k], np.float64) for k in range(3)], -1)


def polygon_solid_angle(verts: np.ndarray, p: np.ndarray) -> float:
    """Van Oosterom & Strackee (1983): solid angle of a planar convex polygon seen from
    ``p``, summed over the fan triangles."""
    r = verts - p
    total = 0.0
    for k in range(1, len(r) - 1):
        a, b, c = r[0], r[k], r[k + 1]
        la, lb, lc = (np.linalg.norm(x) for x in (a, b, c))
        num = a @ np.cross(b, c)
        den = la * lb * lc + (a @ b) * lc + (a @ c) * lb + (b @ c) * la
        total += 2.0 * math.atan2(num, den)
    return abs(total)


def sample_directions(r: int, ss: int) -> np.ndarray:
    """(6, R, R, ss*ss, 3) unit directions of the texel samples (centres of the ss x ss
    sub-squares of each texel), written from the stated convention."""
    sub = (np.arange(ss) + 0.5) / ss
    e = -1.0 + 2.0 * (np.arange(r)[:, None] + sub[None, :]) / r  # [texel, sample]
    s = e[None, None, :, None, :]  # [face, j, i, b, a]: i and a along s
    t = e[None, :, None, :, None]  # j and b along t
    face = np.arange(6)[:, None, None, None, None]
    d = cube_dir(face, s, t).reshape(6, r, r, ss * ss, 3)  # sample a + ss b
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def texture_bilinear(tex: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear, clamped: u across columns, v down rows, texel centres at (i + 1/2)/W."""
    h, w = tex.shape[:2]
    x = np.clip(u * w - 0.5, 0.0, w - 1.0)
    y = np.clip(v * h - 0.5, 0.0, h - 1.0)
    i0, j0 = np.floor(x).astype(int), np.floor(y).astype(int)
    i1, j1 = np.minimum(i0 + 1, w - 1), np.minimum(j0 + 1, h - 1)
    fx, fy = (x - i0)[..., None], (y - j0)[..., None]
    return ((tex[j0, i0] * (1 - fx) + tex[j0, i1] * fx) * (1 - fy)
            + (tex[j1, i0] * (1 - fx) + tex[j1, i1] * fx) * fy)


def reference_map(lights, probe, r: int, ss: int) -> np.ndarray:
    """Float64 NumPy ray caster: nearest light per sample, black from behind unless
    two-sided, texture by least-squares uv of the first three vertices; averaged."""
    d = sample_directions(r, ss).reshape(-1, 3)
    best = np.full(len(d), np.inf)
    out = np.zeros((len(d), 3))
    for lt in lights:
        v = np.asarray(lt.vertices, np.float64)
        n = np.cross(v[1] - v[0], v[2] - v[0])
        n /= np.linalg.norm(n)
        den = d @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((v[0] - probe) @ n) / den
        y = probe + d * t[:, None]
        inside = (t > 0) & (np.abs(den) > 1e-12)
        for k in range(len(v)):
            a, b = v[k], v[(k + 1) % len(v)]
            inside &= np.cross(b - a, y - a) @ n >= 0.0
        hit = inside & (t < best)
        le = np.broadcast_to(np.asarray(lt.radiance, np.float64), (len(d), 3)).copy()
        if lt.texture is not None:
            basis = np.stack([v[1] - v[0], v[2] - v[0]], 1)  # (3, 2)
            st, *_ = np.linalg.lstsq(basis, (y - v[0]).T, rcond=None)
            uv = lt.uv[0] + st.T @ np.stack([lt.uv[1] - lt.uv[0], lt.uv[2] - lt.uv[0]])
            le = le * texture_bilinear(lt.texture.astype(np.float64), uv[:, 0], uv[:, 1])
        front = den < 0
        le = np.where((front | lt.two_sided)[:, None], le, 0.0)
        best = np.where(hit, t, best)
        out = np.where(hit[:, None], le, out)
    return out.reshape(6, r, r, ss * ss, 3).mean(3)


# -- solid angles and rendering ---------------------------------------------------------------


def test_texel_solid_angles_against_quadrature():
    from scipy.integrate import dblquad

    for r in (1, 5, 16):
        om = texel_solid_angles(r)
        assert om.shape == (r, r)
        assert abs(6 * om.sum() - 4 * math.pi) < 1e-12
    om = texel_solid_angles(5)
    e = -1.0 + 2.0 * np.arange(6) / 5
    for j, i in [(0, 0), (1, 3), (2, 2), (4, 1)]:
        q, _ = dblquad(lambda t, s: (1 + s * s + t * t) ** -1.5, e[i], e[i + 1], e[j], e[j + 1],
                       epsabs=1e-13)
        assert abs(om[j, i] - q) < 1e-10
    assert np.allclose(om, om.T) and np.allclose(om, om[::-1])


def test_aligned_square_solid_angle_is_exact():
    """The square's gnomonic image is s, t in [-1/2, 1/2] on +Z: whole texels at R = 32, so
    the map's solid-angle integral is the analytic solid angle up to rounding."""
    radiance = np.array([1.0, 2.0, 0.5])
    light = PolygonLight(vertices=SQUARE, radiance=radiance)
    m = LightCubeMap.render([light], [0.0, 0.0, 0.0], resolution=32, supersample=2)
    exact = polygon_solid_angle(SQUARE, np.zeros(3))
    assert abs(exact - 4 * math.asin(1 / 5)) < 1e-12  # rectangle formula
    assert np.allclose(m.integral(0), radiance * exact, rtol=2e-6)
    base = m.levels[0]
    assert np.all(base[[0, 1, 2, 3, 5]] == 0.0)
    assert np.all(base[4, 8:24, 8:24] == radiance.astype(np.float32))


def edges_near_texels(verts: np.ndarray, probe: np.ndarray, r: int) -> np.ndarray:
    """(6, R, R) int: how many of the polygon's edges (great-circle arcs seen from
    ``probe``) come within a texel's angular circumradius of its centre direction: only
    these texels can be crossed by the polygon's outline."""
    c = cube_directions(r)  # (6, R, R, 3) unit
    e = -1.0 + 2.0 * np.arange(r + 1) / r
    corners = []
    for dj in (0, 1):
        for di in (0, 1):
            s = e[di:r + di][None, None, :]
            t = e[dj:r + dj][None, :, None]
            k = cube_dir(np.arange(6)[:, None, None], s, t)
            corners.append(k / np.linalg.norm(k, axis=-1, keepdims=True))
    radius = np.max([np.arccos(np.clip((c * k).sum(-1), -1, 1)) for k in corners], 0)
    u = verts - probe
    u = u / np.linalg.norm(u, axis=1, keepdims=True)
    count = np.zeros((6, r, r), np.int64)
    for a, b in zip(u, np.roll(u, -1, axis=0), strict=True):
        n = np.cross(a, b)
        n /= np.linalg.norm(n)
        dn = c @ n
        proj = c - dn[..., None] * n
        within = (np.cross(a, proj) @ n >= 0) & (np.cross(proj, b) @ n >= 0)
        to_circle = np.arcsin(np.clip(np.abs(dn), 0, 1))
        to_ends = np.minimum(np.arccos(np.clip(c @ a, -1, 1)), np.arccos(np.clip(c @ b, -1, 1)))
        dist = np.where(within, to_circle, to_ends)
        count += dist <= radius * (1 + 1e-9)
    return count


@pytest.mark.parametrize("ss", [1, 3])
def test_tilted_quad_solid_angle_within_discretisation_bound(ss):
    """A tilted quad across two faces. A texel that no edge comes near is wholly in or out
    (exact). In a texel near ``k`` edges, each straight edge (great circles are straight in
    (s, t)) crosses at most ``2 ss - 1`` of the ``ss^2`` sub-squares, each misjudged by at
    most its solid angle; the other sub-squares are right but weighted ``Omega / ss^2``
    instead of their own solid angle (relative spread ``sp`` within a texel): a rigorous
    bound on the error of the map's solid angle."""
    rot = np.array([[0.8, 0.0, 0.6], [0.0, 1.0, 0.0], [-0.6, 0.0, 0.8]])
    rz = np.array([[math.cos(0.4), -math.sin(0.4), 0], [math.sin(0.4), math.cos(0.4), 0],
                   [0, 0, 1]])
    verts = (SQUARE * [1.3, 0.7, 1.0]) @ (rot @ rz).T + [0.9, 0.2, 0.0]
    probe = np.array([0.1, -0.2, 0.3])
    radiance = np.array([3.0, 1.0, 0.25])
    light = PolygonLight(vertices=verts, radiance=radiance)
    assert light.normal @ (probe - light.centroid) > 0  # the probe sees the front
    r = 24
    m = LightCubeMap.render([light], probe, resolution=r, supersample=ss)
    exact = polygon_solid_angle(verts, probe)
    om = texel_solid_angles(r)
    near = edges_near_texels(verts, probe, r)
    cover = m.levels[0][..., 0].astype(np.float64) / radiance[0]
    partial = (cover > 1e-6) & (cover < 1 - 1e-6)
    assert np.all(near[partial] > 0)  # partly covered texels are near the outline
    assert len(np.unique(np.nonzero(near)[0])) >= 2  # the outline crosses face edges
    sub = texel_solid_angles(r * ss).reshape(r, ss, r, ss).transpose(0, 2, 1, 3)
    sp = np.max(np.abs(sub * ss * ss / om[:, :, None, None] - 1.0))
    per_texel = np.minimum(1.0, near * (2 * ss - 1) / ss**2) * (1 + sp) + sp
    bound = float((np.where(near > 0, per_texel, 0.0) * om[None]).sum())
    got = m.integral(0)
    err = got[0] / radiance[0] - exact
    print(f"ss={ss}: solid angle {got[0] / radiance[0]:.6f} vs {exact:.6f}, error {err:.2e} "
          f"(bound {bound:.2e}, {int((near > 0).sum())} outline texels)")
    assert abs(err) <= bound
    assert np.allclose(got / radiance, got[0] / radiance[0], rtol=1e-6)  # radiance x angle
    # the same texel by texel as an independent float64 ray caster
    ref = reference_map([light], probe, r, ss)
    assert np.abs(m.levels[0] - ref).max() < 1e-5


def test_one_sided_back_is_black_two_sided_is_not():
    behind = np.array([0.0, 0.0, 4.0])
    one = PolygonLight(vertices=SQUARE, radiance=[1.0, 1.0, 1.0])
    m = LightCubeMap.render([one], behind, resolution=16)
    assert np.all(m.levels[0] == 0.0) and np.all(m.integral(0) == 0.0)
    two = PolygonLight(vertices=SQUARE, radiance=[1.0, 1.0, 1.0], two_sided=True)
    m2 = LightCubeMap.render([two], behind, resolution=32)
    assert np.allclose(m2.integral(0), polygon_solid_angle(SQUARE, behind), rtol=2e-6)
    assert np.all(m2.levels[0][5, 8:24, 8:24] == 1.0)  # seen on -Z


def test_several_lights_match_numpy_ray_caster():
    """Overlapping lights at different depths (the nearer hides the farther, a one-sided
    one seen from behind hides them in black), a textured pentagon, a two-sided triangle."""
    rng = np.random.default_rng(3)
    tex = rng.uniform(0.0, 2.0, (5, 7, 3)).astype(np.float32)
    ang = np.linspace(0, 2 * np.pi, 6)[:-1] + 0.1
    penta = np.c_[0.8 * np.cos(ang), 0.6 * np.sin(ang), np.full(5, -1.5)]  # CCW from +z side
    penta_uv = np.c_[0.5 + 0.6 * np.cos(ang), 0.5 - 0.5 * np.sin(ang)]
    lights = [  # in an order where "the last light hit" would be wrong
        PolygonLight(vertices=SQUARE[:, [0, 1, 2]] * [0.3, 0.4, 1.0] + [-0.1, 0.1, 0.0],
                     radiance=[0.1, 2.0, 0.3]),  # z = 2, nearest
        PolygonLight(vertices=SQUARE[::-1] * [0.25, 0.2, 1.25] + [-0.5, 0, 0],
                     radiance=[5.0, 5.0, 5.0]),  # z = 2.5, faces away: a black occluder
        PolygonLight(vertices=SQUARE * [1, 1, 1.5], radiance=[1.0, 0.5, 0.2]),  # z = 3, far
        PolygonLight(vertices=penta, radiance=[1.0, 1.0, 1.0], texture=tex, uv=penta_uv),
        PolygonLight(vertices=[[2.0, -0.5, -0.5], [2.5, 0.6, 0.0], [1.8, 0.3, 0.9]],
                     radiance=[0.7, 0.8, 0.9], two_sided=True),
    ]
    probe = np.array([0.013, -0.021, 0.017])
    r, ss = 16, 2
    m = LightCubeMap.render(lights, probe, resolution=r, supersample=ss)
    ref = reference_map(lights, probe, r, ss)
    diff = np.abs(m.levels[0] - ref)
    print("max |map - reference|:", diff.max())
    assert diff.max() < 1e-4 * (1.0 + ref.max())
    base = m.levels[0]
    assert np.any(np.all(base[4] == np.float32([0.1, 2.0, 0.3]), -1))  # the near light
    assert np.any(np.all(base[4] == 0.0, -1) & (ref[4, ..., 0] == 0.0))


def test_two_colour_texture_where_expected():
    tex = np.zeros((1, 2, 3), np.float32)
    tex[0, 0] = [1.0, 0.0, 0.0]  # u < 1/4: pure red (clamped bilinear)
    tex[0, 1] = [0.0, 1.0, 0.0]  # u > 3/4: pure green
    light = PolygonLight(vertices=SQUARE, radiance=[2.0, 2.0, 2.0], texture=tex, uv=SQUARE_UV)
    r, ss = 32, 2
    m = LightCubeMap.render([light], np.zeros(3), resolution=r, supersample=ss)
    # on +Z, s = x / 2 and u = (x + 1) / 2 = s + 1/2: texel i spans u in [lo, hi]
    lo = -1.0 + 2.0 * np.arange(r) / r + 0.5
    hi = lo + 2.0 / r
    c = texel_centres(r)
    rows = np.abs(c) < 0.5  # texel rows inside the light
    red = (lo >= 0.0) & (hi <= 0.25)
    green = (lo >= 0.75) & (hi <= 1.0)
    face = m.levels[0][4]
    assert red.sum() >= 3 and green.sum() >= 3
    assert np.all(face[np.ix_(rows, red)] == np.float32([2.0, 0.0, 0.0]))
    assert np.all(face[np.ix_(rows, green)] == np.float32([0.0, 2.0, 0.0]))
    mid = (lo > 0.3) & (hi < 0.7)
    blend = face[np.ix_(rows, mid)]
    assert np.all((blend[..., 0] > 0) & (blend[..., 1] > 0))  # bilinear between the two
    # looked up towards points of the light at u = 0.1 and u = 0.9 (v = 0.5)
    dirs = np.array([[2 * 0.1 - 1, 0.0, 2.0], [2 * 0.9 - 1, 0.0, 2.0]])
    got = col_np(m.lookup(vec(dirs)))
    assert np.allclose(got, [[2.0, 0.0, 0.0], [0.0, 2.0, 0.0]], atol=1e-6)


def test_no_lights_is_black_and_bad_input_is_clear():
    m = LightCubeMap.render([], [0.0, 0.0, 0.0], resolution=4)
    assert m.n_levels == 3 and all(np.all(lv == 0) for lv in m.levels)
    light = PolygonLight(vertices=SQUARE, radiance=[1.0, 1.0, 1.0])
    for bad, match in [
        (dict(probe=[0.0, np.nan, 0.0]), "NaN"),
        (dict(probe=[0.0, 0.0]), r"shape \(3,\)"),
        (dict(resolution=0), "resolution"),
        (dict(resolution=2.5), "resolution"),
        (dict(supersample=0), "supersample"),
        (dict(resolution=8, levels=5), "levels"),
        (dict(levels=0), "levels"),
    ]:
        kw = dict(probe=[0.0, 0.0, 0.0], resolution=8)
        kw.update(bad)
        with pytest.raises(GlossrtError, match=match):
            LightCubeMap.render([light], **kw)
    bad_light = PolygonLight(vertices=SQUARE, radiance=[1.0, 1.0, 1.0])
    bad_light.vertices = bad_light.vertices.copy()
    bad_light.vertices[0, 0] = np.inf
    with pytest.raises(GlossrtError, match="NaN or Inf"):
        LightCubeMap.render([bad_light], [0.0, 0.0, 0.0], resolution=4)
    with pytest.raises(GlossrtError, match="NaN or Inf"):
        light_spheres([bad_light])
    with pytest.raises(GlossrtError, match="shape"):
        mip_chain(np.zeros((5, 4, 4, 3)))
    with pytest.raises(GlossrtError, match="NaN"):
        LightCubeMap.from_faces(np.full((6, 2, 2, 3), np.nan))


# -- levels and lookups ----------------------------------------------------------------------


def random_map(r: int, seed: int = 0, levels=None) -> LightCubeMap:
    rng = np.random.default_rng(seed)
    return LightCubeMap.from_faces(rng.uniform(0.0, 4.0, (6, r, r, 3)), levels)


def test_level_resolutions():
    assert level_resolutions(16) == [16, 8, 4, 2, 1]
    assert level_resolutions(12) == [12, 6, 3, 2, 1]
    assert level_resolutions(1) == [1]
    assert level_resolutions(16, 2) == [16, 8]


def test_mip_levels_keep_the_integral():
    m = random_map(16)
    ref = m.integral(0)
    for lv in range(1, m.n_levels):
        assert np.allclose(m.integral(lv), ref, rtol=1e-6), lv
    # a coarse texel is the solid-angle-weighted mean of its 2 x 2 children
    om = texel_solid_angles(16)
    f, j, i = 3, 5, 2
    kids = m.levels[0][f, 2 * j:2 * j + 2, 2 * i:2 * i + 2].astype(np.float64)
    w = om[2 * j:2 * j + 2, 2 * i:2 * i + 2, None]
    assert np.allclose(m.levels[1][f, j, i], (w * kids).sum((0, 1)) / w.sum(), rtol=1e-6)
    assert np.allclose(m.levels[-1][:, 0, 0], (om[..., None] * m.levels[0]).sum((1, 2))
                       / om.sum(), rtol=1e-6)
    # odd sizes (12 -> 6 -> 3 -> 2 -> 1): a constant map stays constant
    const = LightCubeMap.from_faces(np.full((6, 12, 12, 3), 0.7))
    assert [lv.shape[1] for lv in const.levels] == [12, 6, 3, 2, 1]
    for lv in const.levels:
        assert np.allclose(lv, 0.7, rtol=1e-6)
    odd = random_map(12, 1)
    for lv in range(1, odd.n_levels):  # approximate: split texels by covered fraction
        assert np.allclose(odd.integral(lv), odd.integral(0), rtol=2e-2)


def test_lookup_at_texel_centres_returns_stored_values():
    m = random_map(8, 2)
    for lv, r in enumerate(m.resolutions):
        d = cube_directions(r).reshape(-1, 3)
        stored = m.levels[lv].reshape(-1, 3)
        got = col_np(m.lookup(vec(d), float(lv)))
        assert np.allclose(got, stored, rtol=1e-5, atol=1e-6), lv
        assert np.allclose(m.lookup_np(d, lv), stored, rtol=1e-5, atol=1e-6), lv
        assert m.solid_angle_texel(lv) == pytest.approx(4 * math.pi / (6 * r * r))


def test_lookup_bilinear_and_clamped():
    m = random_map(8, 3)
    c = texel_centres(8)
    face = m.levels[0][2]  # +Y: u = z, v = x
    # half-way between texel centres (i=2, j=5) and (i=3, j=5)
    d = cube_dir(2, 0.5 * (c[2] + c[3]), c[5])
    got = col_np(m.lookup(vec(d)))[0]
    assert np.allclose(got, 0.5 * (face[5, 2] + face[5, 3]), rtol=1e-5)
    # a quarter of the way diagonally: bilinear weights (3/4, 1/4) x (3/4, 1/4)
    d = cube_dir(2, 0.75 * c[2] + 0.25 * c[3], 0.75 * c[5] + 0.25 * c[6])
    want = (0.75 * (0.75 * face[5, 2] + 0.25 * face[5, 3])
            + 0.25 * (0.75 * face[6, 2] + 0.25 * face[6, 3]))
    assert np.allclose(col_np(m.lookup(vec(d)))[0], want, rtol=1e-5)
    # beyond the last texel centre (within half a texel of the face edge): clamped
    d = cube_dir(2, 0.99, c[5])
    assert np.allclose(col_np(m.lookup(vec(d)))[0], face[5, 7], rtol=1e-5)
    # zero / NaN directions read 0
    bad = col_np(m.lookup(mi.Vector3f(mi.Float([0.0, np.nan]), mi.Float([0.0, 1.0]),
                                      mi.Float([0.0, 0.0]))))
    assert np.all(bad == 0.0)


def test_lookup_np_equals_lookup():
    m = random_map(16, 4)
    rng = np.random.default_rng(5)
    d = rng.normal(size=(4000, 3))
    lod = rng.uniform(-1.0, 6.0, 4000)
    a = m.lookup_np(d, lod)
    b = col_np(m.lookup(vec(d), mi.Float(lod)))
    assert np.abs(a - b).max() < 1e-4
    b0 = col_np(m.lookup(vec(d)))
    assert np.abs(m.lookup_np(d) - b0).max() < 1e-4


def test_trilinear_lod_is_linear_and_monotone():
    m = random_map(16, 6)
    rng = np.random.default_rng(7)
    d = rng.normal(size=(50, 3))
    lods = np.linspace(0.0, m.n_levels - 1, 8 * (m.n_levels - 1) + 1)
    vals = np.stack([col_np(m.lookup(vec(d), float(x))) for x in lods])  # (L, 50, 3)
    for lv in range(m.n_levels - 1):
        seg = vals[8 * lv:8 * lv + 9]
        step = np.diff(seg, axis=0)
        up, down = np.all(step >= -1e-5, 0), np.all(step <= 1e-5, 0)
        assert np.all(up | down)  # monotone between consecutive levels
        lin = seg[0] + (seg[-1] - seg[0]) * (np.arange(9) / 8)[:, None, None]
        assert np.allclose(seg, lin, atol=1e-5)
    # beyond the last level: clamped
    top = col_np(m.lookup(vec(d), 100.0))
    assert np.allclose(top, vals[-1], atol=1e-6)


def test_fis_lod_formula():
    w, n = 64, 16
    pdf = np.array([1e-4, 0.01, 0.3, 2.0, 50.0, 1e6])
    omega_p = 4 * math.pi / (6 * w * w)
    want = np.maximum(0.5 * np.log2((1.0 / (n * pdf)) / omega_p), 0.0)
    assert np.allclose(fis_lod(pdf, n, w), want, rtol=1e-12)
    got = np.asarray(fis_lod(mi.Float(pdf), n, w), np.float64)
    assert np.allclose(got, want, rtol=1e-5, atol=1e-5)
    assert want[-1] == 0.0 and fis_lod(1e6, n, w) == 0.0  # large pdf: the base level
    # the chapter's +1 bias: one level coarser where unclamped
    assert np.allclose(fis_lod(pdf[:2], n, w, bias=1.0), want[:2] + 1.0)
    assert fis_lod(0.0, n, w) == math.inf
    m = random_map(8, 8)
    d = np.array([[0.3, -0.2, 0.9]])
    coarse = col_np(m.lookup(vec(d), fis_lod(mi.Float(0.0), n, 8)))
    assert np.allclose(coarse, m.lookup_np(d, m.n_levels - 1), rtol=1e-5)
    with pytest.raises(GlossrtError, match="n_samples"):
        fis_lod(1.0, 0, w)


# -- bounding spheres and culling ------------------------------------------------------------


def test_light_spheres_are_smallest_enclosing():
    from scipy.optimize import minimize

    rect = PolygonLight(vertices=SQUARE * [1.5, 1.0, 1.0], radiance=[1, 1, 1])
    c, r = light_spheres([rect])
    assert np.allclose(c[0], rect.centroid) and r[0] == pytest.approx(math.hypot(1.5, 1.0))
    rng = np.random.default_rng(9)
    for _ in range(5):
        ang = np.sort(rng.uniform(0, 2 * np.pi, rng.integers(3, 9)))
        rad = rng.uniform(0.5, 2.0, len(ang))
        p2 = np.c_[rad * np.cos(ang), rad * np.sin(ang)]
        from scipy.spatial import ConvexHull

        hull = ConvexHull(p2)
        if len(hull.vertices) < 3:
            continue
        p2 = p2[hull.vertices]
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        verts = np.c_[p2, np.zeros(len(p2))] @ q.T + rng.normal(size=3)
        lt = PolygonLight(vertices=verts, radiance=[1, 1, 1])
        c, r = light_spheres([lt])
        assert np.all(np.linalg.norm(verts - c[0], axis=1) <= r[0])
        # the convex program min rho s.t. |v_k - x|^2 <= rho, solved by SLSQP
        x0 = np.r_[verts.mean(0), np.max(np.sum((verts - verts.mean(0)) ** 2, 1))]
        res = minimize(lambda x: x[3], x0, method="SLSQP", constraints=[dict(
            type="ineq", fun=lambda x, v=verts: x[3] - np.sum((v - x[:3]) ** 2, 1))],
            options=dict(ftol=1e-12, maxiter=500))
        assert np.sum((verts - res.x[:3]) ** 2, 1).max() <= res.x[3] * (1 + 1e-9)  # feasible
        assert r[0] == pytest.approx(math.sqrt(res.fun), rel=1e-6)
        # no sphere about the solver's centre is smaller (r carries a 1e-9 relative margin)
        assert r[0] / (1 + SPHERE_EPS) <= np.linalg.norm(verts - res.x[:3], axis=1).max() + 1e-12
    c, r = light_spheres([])
    assert c.shape == (0, 3) and r.shape == (0,)


def test_cull_mask_cone_test():
    centre, radius = np.array([[0.0, 0.0, 5.0]]), np.array([1.0])
    p = mi.Point3f(0.0, 0.0, 0.0)
    half = math.asin(1.0 / 5.0)
    delta = 0.1
    outside = half + delta  # a direction just outside the sphere's cone
    dirs = np.array([[0, 0, 1.0], [0, 0, -1.0], [math.sin(outside), 0, math.cos(outside)],
                     [math.sin(outside), 0, math.cos(outside)],
                     [math.sin(outside), 0, math.cos(outside)]])
    spread = mi.Float([0.0, 1.0, 0.0, 0.99 * delta, 1.01 * delta])
    got = np.asarray(cull_mask(p, vec(dirs), centre, radius, spread))
    assert got.tolist() == [True, False, False, False, True]
    # scalar spread: the opposite direction needs pi - half
    opp = vec([[0, 0, -1.0]])
    assert not np.asarray(cull_mask(p, opp, centre, radius, math.pi - half - 0.01))[0]
    assert np.asarray(cull_mask(p, opp, centre, radius, math.pi - half + 0.01))[0]
    # inside the sphere: never culled; no lights: everything culled
    inside = np.asarray(cull_mask(mi.Point3f(0.0, 0.3, 4.5), opp, centre, radius, 0.0))
    assert inside.all()
    assert not np.asarray(cull_mask(p, vec(dirs), np.zeros((0, 3)), np.zeros(0), 0.5)).any()
    # a second sphere behind: the opposite direction is kept
    two = np.asarray(cull_mask(p, opp, np.r_[centre, [[0, 0, -3.0]]], np.array([1.0, 0.5]),
                               0.0))
    assert two.all()
    with pytest.raises(GlossrtError, match="spread"):
        cull_mask(p, opp, centre, radius, -0.1)


def test_lobe_spread_doubles_the_angle():
    """Reflecting a fixed view about a normal tilted by delta turns the mirror direction by
    2 delta (checked with an actual reflection)."""
    v = np.array([0.3, 0.0, 1.0]) / np.linalg.norm([0.3, 0.0, 1.0])
    n = np.array([0.0, 0.0, 1.0])
    delta = 0.2
    h = np.array([math.sin(delta), 0.0, math.cos(delta)])
    r0 = 2 * (v @ n) * n - v
    r1 = 2 * (v @ h) * h - v
    assert math.acos(np.clip(r0 @ r1, -1, 1)) == pytest.approx(lobe_spread(delta))
    assert np.allclose(lobe_spread(np.array([0.1, 0.3])), [0.2, 0.6])
    assert np.allclose(np.asarray(lobe_spread(mi.Float([0.25]))), [0.5])
    with pytest.raises(GlossrtError):
        lobe_spread(-0.1)


# -- probes and per-mesh maps -------------------------------------------------------------


def small_scene():
    t = mi.ScalarTransform4f
    return mi.load_dict({
        "type": "scene",
        "ball": {"type": "sphere", "center": [0.5, 0.0, 0.0], "radius": 0.3},
        "box": {"type": "cube", "to_world": t().translate([-1.0, 0.2, 0.1]).scale(0.2)},
        "lamp": {"type": "rectangle", "to_world": t().translate([0.0, 0.0, 2.0])
                 .rotate([1, 0, 0], 180).scale(0.5),
                 "emitter": {"type": "area", "radiance": {"type": "rgb",
                                                          "value": [2.0, 1.0, 0.5]}}},
    })


def test_probe_points_and_cube_map_set():
    from glossrt.lights.scene import polygon_lights
    from glossrt.scenes import stable_shapes

    scene = small_scene()
    shapes = stable_shapes(scene)
    probes = probe_points(scene)
    emitter_ids = [k + 1 for k, s in enumerate(shapes) if s.is_emitter()]
    assert len(emitter_ids) == 1 and emitter_ids[0] not in probes
    assert sorted(probes) == [k + 1 for k, s in enumerate(shapes) if not s.is_emitter()]
    by_id = {s.id(): k + 1 for k, s in enumerate(shapes)}
    assert np.allclose(probes[by_id["ball"]], [0.5, 0.0, 0.0], atol=1e-6)
    assert np.allclose(probes[by_id["box"]], [-1.0, 0.2, 0.1], atol=1e-6)

    lights = polygon_lights(scene)
    cms = CubeMapSet.render(lights, probes, resolution=8, supersample=2)
    assert len(cms) == 2 and cms.n_levels == 4
    rng = np.random.default_rng(11)
    n = 600
    d = rng.normal(size=(n, 3))
    d[: n // 2] = [0.0, 0.0, 1.0] + 0.3 * rng.normal(size=(n // 2, 3))  # towards the lamp
    ids = rng.integers(-1, 6, n)
    lod = rng.uniform(0.0, 3.0, n)
    got = col_np(cms.lookup(mi.Float(ids.astype(np.float64)), vec(d), mi.Float(lod)))
    got_u = col_np(cms.lookup(mi.UInt32(np.maximum(ids, 0).astype(np.uint32)), vec(d),
                              mi.Float(lod)))
    want = np.zeros((n, 3))
    for k, m in cms.maps.items():
        sel = ids == k
        want[sel] = m.lookup_np(d[sel], lod[sel])
        assert np.allclose(m.probe, probes[k])
    assert np.abs(got - want).max() < 1e-4
    assert np.abs(got_u[ids >= 0] - want[ids >= 0]).max() < 1e-4
    assert want[np.isin(ids, list(probes))].max() > 0  # the lamp is seen
    nan = col_np(cms.lookup(mi.Float([np.nan]), vec([[0, 0, 1.0]])))
    assert np.all(nan == 0.0)
    # maps of different sizes cannot be stacked
    with pytest.raises(GlossrtError, match="levels"):
        CubeMapSet({1: random_map(8), 2: random_map(4)})
