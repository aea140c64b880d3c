"""glossrt.denoise.svgf / atrous: SVGF (Schied et al. 2017) checked piece by piece.

* the a-trous levels (svgf_level, dammertz_level, gaussian3x3) against NumPy implementations
  written from the paper's equations 1-5 and the variance propagation of sec. 4.3;
* temporal accumulation (sec. 4.1) on synthetic flat-plane sequences against closed forms:
  history length, the exponential moving average, disocclusion, NaN hygiene, resets;
* reprojection with motion: 2x2 bilinear taps, renormalisation over consistent taps, the 3x3
  fallback, against a NumPy re-implementation of sec. 4.1;
* frozen (dr.freeze) and plain execution agree;
* rendered glossy-cornell sequences: quality against converged references (sec. 5.2) and
  temporal stability (sec. 5.4) compared with per-frame edge-avoiding a-trous;
* the structured-noise pattern of sec. 5.2 (temporal vs spatial variance estimate);
* disocclusion in a rendered scene: no ghost of a removed object.

Nothing here is compared with stored images: every expectation is computed in the test.
Run with ``pytest -s`` to see the measured numbers.
"""

from __future__ import annotations

import math
import os
import subprocess
import sys

import numpy as np
import pytest

from glossrt import backend

backend.ensure()
import mitsuba as mi  # noqa: E402

from glossrt import metrics, scenes  # noqa: E402
from glossrt.denoise import SVGF  # noqa: E402
from glossrt.denoise import atrous_filter as atrous  # noqa: E402
from glossrt.denoise.atrous import (  # noqa: E402
    EPS_L,
    EPS_Z,
    dammertz_level,
    gaussian3x3,
    svgf_level,
)
from glossrt.denoise.common import GBuffer, Grid, gbuffer  # noqa: E402
from glossrt.frame import Camera, Frame  # noqa: E402
from glossrt.render import Renderer  # noqa: E402

H5 = np.array([1.0, 4.0, 6.0, 4.0, 1.0]) / 16.0  # B3 spline kernel, Schied 2017 eq. 1
LUM = np.array([0.2126, 0.7152, 0.0722])


def _f(a) -> mi.Float:
    return mi.Float(np.ascontiguousarray(a, dtype=np.float32).ravel())


def _np(x, h, w) -> np.ndarray:
    return np.array(x, dtype=np.float64).reshape(h, w)


# =============================================================================================
# 1. the a-trous levels against NumPy implementations of the paper's equations
# =============================================================================================


def _random_gbuffer(rng, h, w):
    """Random G-buffer of a 'scene' with two meshes and background on a W x H grid:
    mesh 1 a tilted plane (1/z affine in the pixel coordinates, plus a little roughness),
    mesh 2 a nearer block, background (depth +inf) in one corner. Normals are perturbed
    around two directions so that w_n = max(0, n.n)^128 takes values between ~0 and 1."""
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    inv_z = 0.45 + 0.03 * xx - 0.02 * yy + 0.004 * rng.standard_normal((h, w))
    mesh = np.ones((h, w))
    block = (xx >= w // 2) & (yy >= h // 2)
    mesh[block] = 2
    inv_z[block] = 0.9 + 0.01 * rng.standard_normal(np.count_nonzero(block))
    n = np.zeros((h, w, 3))
    n[..., 2] = 1.0
    n[block] = (0.0, 0.6, 0.8)
    n += 0.06 * rng.standard_normal((h, w, 3))
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    bg = (xx <= 1) & (yy <= 1)
    mesh[bg] = 0
    depth = 1.0 / inv_z
    depth[bg] = np.inf
    n[bg] = 0.0
    return depth.astype(np.float32), n.astype(np.float32), mesh.astype(np.float32)


def _np_inv_z(depth):
    z = depth.astype(np.float64)
    with np.errstate(divide="ignore"):
        return np.where(np.isfinite(z) & (z > 0), 1.0 / z, 0.0)


def _np_one_sided_gradient(iz):
    """Screen-space gradient of 1/z: of the forward and backward differences, the one of
    smaller magnitude (common.depth_gradient's documented rule). Differences are taken with
    clamp-to-edge addressing, as the implementation does (see test_depth_gradient_border for
    what that means on the border)."""
    h, w = iz.shape
    out = []
    for ax in (1, 0):
        idx = np.arange(iz.shape[ax])
        fwd = np.take(iz, np.minimum(idx + 1, iz.shape[ax] - 1), axis=ax) - iz
        bwd = iz - np.take(iz, np.maximum(idx - 1, 0), axis=ax)
        out.append(np.where(np.abs(fwd) < np.abs(bwd), fwd, bwd))
    return out[0], out[1]


def _np_gauss3(v):
    """3x3 binomial (1/4, 1/2, 1/4)^2 blur with clamp-to-edge addressing."""
    h, w = v.shape
    k = (0.25, 0.5, 0.25)
    out = np.zeros_like(v)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            ys = np.clip(np.arange(h) + dy, 0, h - 1)
            xs = np.clip(np.arange(w) + dx, 0, w - 1)
            out += k[dx + 1] * k[dy + 1] * v[np.ix_(ys, xs)]
    return out


def _np_svgf_level(color, var, n, iz, gx, gy, mesh, step, sigma_z=1.0, sigma_n=128.0,
                   sigma_l=4.0):
    """One level of Schied 2017 eq. 1 with w = w_z w_n w_l (eq. 2-5) and the variance update
    Var = sum h^2 w^2 Var(q) / (sum h w)^2 (sec. 4.3), pixel by pixel in float64.
    Taps outside the image or on background pixels get weight 0; background pixels are
    passed through. Epsilons: those documented in atrous.py (EPS_Z relative to 1/z, EPS_L)."""
    h, w = mesh.shape
    lum = color @ LUM
    std = np.sqrt(np.maximum(_np_gauss3(var), 0.0))
    out_c = color.copy()
    out_v = var.copy()
    for y in range(h):
        for x in range(w):
            if mesh[y, x] <= 0:
                continue
            sw, acc, accv = 0.0, np.zeros(3), 0.0
            for j in range(5):
                for i in range(5):
                    dx, dy = (i - 2) * step, (j - 2) * step
                    qx, qy = x + dx, y + dy
                    if not (0 <= qx < w and 0 <= qy < h) or mesh[qy, qx] <= 0:
                        continue
                    if dx == 0 and dy == 0:
                        wgt = 1.0
                    else:
                        plane = abs(gx[y, x] * dx + gy[y, x] * dy)
                        wz = math.exp(-abs(iz[y, x] - iz[qy, qx]) / (
                            sigma_z * plane + EPS_Z * iz[y, x] + 1e-12))
                        wn = max(0.0, float(n[y, x] @ n[qy, qx])) ** sigma_n
                        wl = math.exp(-abs(lum[y, x] - lum[qy, qx]) / (
                            sigma_l * std[y, x] + EPS_L))
                        wgt = wz * wn * wl
                    hw = H5[i] * H5[j] * wgt
                    sw += hw
                    acc += hw * color[qy, qx]
                    accv += hw * hw * var[qy, qx]
            out_c[y, x] = acc / sw
            out_v[y, x] = accv / (sw * sw)
    return out_c, out_v


def _np_dammertz_level(color, n, pos, mesh, step, sigma_rt, sigma_n, sigma_x):
    """Dammertz et al. 2010: w = exp(-|dc|^2/s_rt^2) exp(-(|dn|^2/step^2)/s_n^2)
    exp(-|dx|^2/s_x^2), the same 5x5 B3 kernel; background taps get weight 0."""
    h, w = mesh.shape
    out = color.copy()
    for y in range(h):
        for x in range(w):
            if mesh[y, x] <= 0:
                continue
            sw, acc = 0.0, np.zeros(3)
            for j in range(5):
                for i in range(5):
                    qx, qy = x + (i - 2) * step, y + (j - 2) * step
                    if not (0 <= qx < w and 0 <= qy < h) or mesh[qy, qx] <= 0:
                        continue
                    dc = np.sum((color[y, x] - color[qy, qx]) ** 2)
                    dn = np.sum((n[y, x] - n[qy, qx]) ** 2) / step**2
                    dp = np.sum((pos[y, x] - pos[qy, qx]) ** 2)
                    wgt = math.exp(-dc / sigma_rt**2) * math.exp(-dn / sigma_n**2) * math.exp(
                        -dp / sigma_x**2)
                    hw = H5[i] * H5[j] * wgt
                    sw += hw
                    acc += hw * color[qy, qx]
            out[y, x] = acc / sw
    return out


def _level_inputs(seed=1, w=9, h=7):
    rng = np.random.default_rng(seed)
    depth, n, mesh = _random_gbuffer(rng, h, w)
    color = rng.uniform(0.0, 2.0, (h, w, 3))
    # a luminance edge through mesh 1, so w_l matters
    color[:, : w // 3] += 1.5
    var = rng.uniform(0.0, 0.5, (h, w)) ** 2
    return depth, n, mesh, color, var


@pytest.mark.parametrize("step", [1, 2])
def test_svgf_level_matches_paper_equations(step):
    h, w = 7, 9
    depth, n, mesh, color, var = _level_inputs(seed=step, w=w, h=h)
    color = color.astype(np.float32).astype(np.float64)
    var = var.astype(np.float32).astype(np.float64)
    # the G-buffer the code gets is float32: the reference uses the same rounded values
    # (an input rounding of 3e-8 in 1/z would otherwise move exp() arguments by up to 1e-4)
    iz = _np_inv_z(depth).astype(np.float32).astype(np.float64)
    gx, gy = (g.astype(np.float32).astype(np.float64) for g in _np_one_sided_gradient(iz))
    grid = Grid(w, h)
    gb = GBuffer(normal=[_f(n[..., k]) for k in range(3)], inv_z=_f(iz), dzdx=_f(gx),
                 dzdy=_f(gy), mesh=_f(mesh))
    out, out_var = svgf_level(grid, [_f(color[..., k]) for k in range(3)], _f(var),
                                         gb, step)
    got_c = np.stack([_np(c, h, w) for c in out], -1)
    got_v = _np(out_var, h, w)
    exp_c, exp_v = _np_svgf_level(color, var, n.astype(np.float64), iz, gx, gy, mesh, step)
    # the weights must be non-trivial for this to test anything: some neighbours are kept,
    # and the output differs from the input by much more than the tolerance
    assert np.max(np.abs(exp_c - color)) > 0.05
    assert np.max(np.abs(exp_v - var)) > 1e-3
    # float32 evaluation: exp() arguments reach ~30 (w_l where the local std is small), so
    # one float32 rounding of the argument (6e-8 relative) moves a weight by ~2e-6; measured
    # worst cases are 4e-6 (colour) and 6e-6 (variance, which uses w^2 and mixes neighbour
    # variances 1000x larger than the centre's). 2e-5 / 5e-5 leave a ~5x margin; a wrong
    # weight or a missing square in the propagation changes the result by >1e-2.
    np.testing.assert_allclose(got_c, exp_c, rtol=2e-5, atol=1e-6)
    np.testing.assert_allclose(got_v, exp_v, rtol=5e-5, atol=1e-9)
    # background is passed through unchanged
    bg = mesh == 0
    np.testing.assert_array_equal(got_c[bg], color[bg].astype(np.float32))


@pytest.mark.parametrize("step", [1, 2])
def test_dammertz_level_matches_reference(step):
    h, w = 7, 9
    depth, n, mesh, color, _ = _level_inputs(seed=10 + step, w=w, h=h)
    rng = np.random.default_rng(5)
    color = (0.3 * color).astype(np.float32).astype(np.float64)
    pos = rng.normal(0.0, 0.2, (h, w, 3)).astype(np.float32).astype(np.float64)
    n = n.astype(np.float64)
    sigma_rt, sigma_n, sigma_x = 0.5, 0.3, 0.3
    grid = Grid(w, h)
    gb = GBuffer(normal=[_f(n[..., k]) for k in range(3)], inv_z=_f(_np_inv_z(depth)),
                 dzdx=_f(np.zeros((h, w))), dzdy=_f(np.zeros((h, w))), mesh=_f(mesh),
                 position=[_f(pos[..., k]) for k in range(3)])
    out = dammertz_level(grid, [_f(color[..., k]) for k in range(3)], gb, step,
                                    sigma_rt, sigma_n, sigma_x)
    got = np.stack([_np(c, h, w) for c in out], -1)
    exp = _np_dammertz_level(color, n, pos, mesh, step, sigma_rt, sigma_n, sigma_x)
    assert np.max(np.abs(exp - color)) > 0.05
    # exponents are O(10) at most: float32 gives ~1e-6 relative, 1e-5 leaves a margin
    np.testing.assert_allclose(got, exp, rtol=1e-5, atol=1e-6)


def test_gaussian3x3_matches_reference():
    h, w = 7, 9
    v = np.random.default_rng(3).uniform(0, 1, (h, w)).astype(np.float32)
    got = _np(gaussian3x3(Grid(w, h), _f(v)), h, w)
    np.testing.assert_allclose(got, _np_gauss3(v.astype(np.float64)), rtol=1e-6, atol=1e-7)
    # a normalised kernel: constants are preserved exactly (up to rounding)
    got1 = _np(gaussian3x3(Grid(w, h), _f(np.full((h, w), 0.7))), h, w)
    np.testing.assert_allclose(got1, 0.7, rtol=1e-6)


def _plane_frame(h, w):
    """G-buffer of a plane tilted in x and y: 1/z is affine in the pixel coordinates."""
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    iz = 0.3 + 0.01 * xx + 0.004 * yy
    normal = np.zeros((h, w, 3), np.float32)
    normal[..., 2] = 1.0
    return Frame(channels={"normal": normal, "depth": (1.0 / iz)[..., None],
                           "mesh_id": np.ones((h, w, 1))}), iz


def test_depth_gradient_of_a_plane_interior():
    """common.depth_gradient (through common.gbuffer): away from the border it is the plane's
    gradient of 1/z, and it equals the documented one-sided rule everywhere."""
    h, w = 12, 16
    frame, iz = _plane_frame(h, w)
    gb = gbuffer(frame, Grid(w, h))
    gx, gy = _np(gb.dzdx, h, w), _np(gb.dzdy, h, w)
    iz32 = _np(gb.inv_z, h, w)
    ex, ey = _np_one_sided_gradient(iz32)
    # (the border, where one of the two differences does not exist: next test)
    np.testing.assert_allclose(gx[:, 1:-1], ex[:, 1:-1], atol=1e-7)
    np.testing.assert_allclose(gy[1:-1, :], ey[1:-1, :], atol=1e-7)
    # 1/z is rounded to float32 (~3e-8): differences of 1e-2 / 4e-3 are good to ~1e-5
    np.testing.assert_allclose(gx[1:-1, 1:-1], 0.01, rtol=1e-4)
    np.testing.assert_allclose(gy[1:-1, 1:-1], 0.004, rtol=1e-4)


def test_depth_gradient_on_image_border():
    """On the image border one of the two one-sided differences does not exist; with
    clamp-to-edge addressing it reads as 0 and, being the 'smaller' one, is chosen, so the
    gradient of a tilted plane is 0 on the border. w_z (eq. 3) then sees no plane slope, and
    border pixels of tilted surfaces reject their neighbours: the corner pixels are not
    filtered at all. Expected: the existing difference is used (the plane's gradient)."""
    h, w = 12, 16
    frame, iz = _plane_frame(h, w)
    grid = Grid(w, h)
    gb = gbuffer(frame, grid)
    gx, gy = _np(gb.dzdx, h, w), _np(gb.dzdy, h, w)
    # impact: variance left after one svgf level on white noise (relative to the input)
    rng = np.random.default_rng(0)
    c = _f(rng.uniform(0, 1, (h, w)))
    var = np.full((h, w), 1 / 12)
    _, ov = svgf_level(grid, [c, c, c], _f(var), gb, 1)
    ratio = _np(ov, h, w) / var
    print(f"\n[depth gradient] border dzdx = {gx[:, 0].min():.4g}..{gx[:, 0].max():.4g} "
          f"(plane 0.01); variance kept by one level: corner {ratio[0, 0]:.2f}, left column "
          f"{ratio[2:-2, 0].mean():.2f}, interior {ratio[2:-2, 2:-2].mean():.2f}")
    np.testing.assert_allclose(gx, 0.01, rtol=1e-3,
                               err_msg="d(1/z)/dx of a tilted plane on the border")
    np.testing.assert_allclose(gy, 0.004, rtol=1e-3,
                               err_msg="d(1/z)/dy of a tilted plane on the border")


# =============================================================================================
# 2. temporal accumulation on synthetic flat-plane sequences (sec. 4.1)
# =============================================================================================

RADIANCE_ZERO = ("emission", "direct_specular", "indirect_diffuse", "indirect_specular")


def _camera(w, h, x=0.0) -> Camera:
    m = np.eye(4)
    m[0, 3] = x
    return Camera(to_world=m, fov=40.0, resolution=(w, h))


def _flat_frame(rad, *, mesh=None, depth=None, normal=None, motion=None, camera=None,
                prev_camera="same", index=0, emission=None) -> Frame:
    """A plane facing the camera: depth 2, normal (0, 0, 1), mesh 1, diffuse albedo 1, zero
    motion; ``rad`` (H, W) or (H, W, 3) is the direct_diffuse radiance, all other radiance
    channels are 0 and the specular albedo is 0 (so only the direct-diffuse signal is
    non-zero, and it is demodulated by 1)."""
    rad = np.asarray(rad, np.float32)
    if rad.ndim == 2:
        rad = np.repeat(rad[..., None], 3, axis=2)
    h, w, _ = rad.shape
    if normal is None:
        normal = np.zeros((h, w, 3), np.float32)
        normal[..., 2] = 1.0
    ch = {
        "direct_diffuse": rad,
        "albedo_diffuse": np.ones((h, w, 3), np.float32),
        "albedo_specular": np.zeros((h, w, 3), np.float32),
        "normal": normal,
        "depth": np.full((h, w, 1), 2.0, np.float32) if depth is None else depth,
        "mesh_id": np.ones((h, w, 1), np.float32) if mesh is None else mesh,
        "motion": np.zeros((h, w, 2), np.float32) if motion is None else motion,
    }
    for name in RADIANCE_ZERO:
        ch[name] = np.zeros((h, w, 3), np.float32)
    if emission is not None:
        ch["emission"] = np.asarray(emission, np.float32)
    cam = _camera(w, h) if camera is None else camera
    prev = cam if prev_camera == "same" else prev_camera
    return Frame(channels=ch, camera=cam, prev_camera=prev, index=index)


def _length(svgf: SVGF) -> np.ndarray:
    h, w = svgf._size[1], svgf._size[0]
    return _np(svgf.history.length, h, w)


def _out(img) -> np.ndarray:
    return np.array(img, dtype=np.float64)


def _ema(xs, alpha=0.2):
    """Schied 2017 sec. 4.1 with the usual warm-up: C'_1 = x_1, C'_n = a_n x_n +
    (1 - a_n) C'_{n-1}, a_n = max(alpha, 1/n) (a plain mean for the first 1/alpha frames)."""
    c = None
    out = []
    for n, x in enumerate(xs, start=1):
        a = max(alpha, 1.0 / n)
        c = x if c is None else a * x + (1 - a) * c
        out.append(c)
    return out


H2, W2 = 24, 32


def _steady_state_run(frozen: bool, n: int = 6):
    """A static flat plane for n frames: from frame 4 on no pixel has a short history."""
    rng = np.random.default_rng(6)
    svgf = SVGF(frozen=frozen)
    outs = [_out(svgf(_flat_frame(rng.exponential(1.0, (H2, W2)), index=i))) for i in range(n)]
    return svgf, outs


FROZEN_PROBES = ("steady-state", "spatial-variance")


def _frozen_probe(kind: str) -> None:
    """What the frozen_guard subprocesses run."""
    if kind == "steady-state":
        _steady_state_run(frozen=True)
    else:
        svgf = SVGF(frozen=True, variance="spatial")
        for i in range(2):
            _out(svgf(_flat_frame(np.ones((H2, W2)), index=i)))
    print(f"{kind} ok", flush=True)


@pytest.fixture(scope="module")
def frozen_guard():
    """Runs frozen SVGF (a steady-state sequence; variance="spatial") in subprocesses first:
    a failure inside dr.freeze can abort the interpreter (std::terminate, "Dr.Jit encountered
    an unrecoverable error"), which would take the whole test session down. Tests that run
    frozen SVGF call ``frozen_guard(*kinds)``, which fails them with the subprocess's message
    instead of letting them crash the session."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in sys.path if p))
    problems = {}
    for kind in FROZEN_PROBES:
        code = ("import sys; sys.path.insert(0, sys.argv[1]); import test_svgf as t; "
                f"t._frozen_probe({kind!r})")
        try:
            r = subprocess.run([sys.executable, "-c", code, os.path.dirname(__file__)],
                               env=env, capture_output=True, text=True, timeout=300)
            if f"{kind} ok" not in r.stdout:
                tail = [ln.strip() for ln in r.stderr.splitlines() if ln.strip()][-2:]
                problems[kind] = f"exit status {r.returncode}: {' | '.join(tail)}"
        except subprocess.TimeoutExpired:
            problems[kind] = "timed out after 300 s"

    def check(*kinds: str):
        bad = [k for k in kinds or ("steady-state",) if k in problems]
        if bad:
            pytest.fail("; ".join(f"frozen SVGF ({k} probe) crashes the interpreter in a "
                                  f"subprocess ({problems[k]})" for k in bad))

    return check


def test_steady_state_without_young_pixels():
    """Once every pixel has >= 4 frames of history no pixel needs the spatial variance
    estimate (sec. 4.2); the filter must still run (plain execution)."""
    svgf, outs = _steady_state_run(frozen=False)
    assert all(np.all(np.isfinite(o)) for o in outs)
    np.testing.assert_array_equal(_length(svgf), len(outs))


@pytest.mark.slow
def test_steady_state_without_young_pixels_frozen(frozen_guard):
    frozen_guard()
    svgf, outs = _steady_state_run(frozen=True)
    _, plain = _steady_state_run(frozen=False)
    for a, b in zip(outs, plain, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("frozen", [False, True])
def test_history_length_and_ema_closed_form(frozen, frozen_guard):
    """levels=0 (no spatial filter): the output is the EMA of the inputs, the history length
    counts the frames."""
    if frozen:
        frozen_guard()
    rng = np.random.default_rng(7)
    xs = [rng.exponential(1.0, (H2, W2, 3)) for _ in range(9)]
    svgf = SVGF(frozen=frozen, levels=0)
    want = _ema(xs)
    for n, x in enumerate(xs, start=1):
        got = _out(svgf(_flat_frame(x, index=n)))
        np.testing.assert_array_equal(_length(svgf), n)
        # float32 recursion of <= 9 steps on values O(1): ~1e-6 relative
        np.testing.assert_allclose(got, want[n - 1], rtol=2e-5, atol=1e-6)


def test_disocclusion_resets_history():
    """Pixels whose mesh id changes cannot reproject (neither the 2x2 nor the 3x3 taps are
    consistent): their output is the current input and their history starts over."""
    rng = np.random.default_rng(8)
    xs = [rng.exponential(1.0, (H2, W2, 3)) for _ in range(7)]
    k = 4  # frames 0..3 see mesh 1 everywhere; from frame 4 on a block is mesh 2
    block = np.zeros((H2, W2), bool)
    block[6:14, 10:20] = True
    mesh = np.ones((H2, W2, 1), np.float32)
    mesh[block] = 2
    svgf = SVGF(frozen=False, levels=0)
    for i, x in enumerate(xs):
        got = _out(svgf(_flat_frame(x, mesh=mesh if i >= k else None, index=i)))
        if i == k:
            np.testing.assert_array_equal(_length(svgf)[block], 1)
            np.testing.assert_array_equal(_length(svgf)[~block], k + 1)
            np.testing.assert_allclose(got[block], xs[k][block], rtol=1e-6)
            np.testing.assert_allclose(got[~block], _ema(xs[: k + 1])[-1][~block], rtol=2e-5)
    # afterwards the block accumulates from frame k on
    np.testing.assert_array_equal(_length(svgf)[block], len(xs) - k)
    np.testing.assert_allclose(got[block], _ema(xs[k:])[-1][block], rtol=2e-5, atol=1e-6)


@pytest.mark.slow
@pytest.mark.parametrize("levels", [0, 5])
def test_nonfinite_input_does_not_poison_history(levels):
    rng = np.random.default_rng(9)
    xs = [rng.exponential(1.0, (H2, W2, 3)).astype(np.float32) for _ in range(8)]
    xs[2][5, 7, 1] = np.nan  # one NaN value
    xs[2][10, 3, :] = np.inf  # three +Inf values
    xs[3][0, 0, 0] = -np.inf  # one -Inf value
    emission = np.zeros((H2, W2, 3), np.float32)
    bad_emission = emission.copy()
    bad_emission[2, 2, 2] = np.nan  # and one NaN in the (unfiltered) emission, frame 4
    clean = [np.nan_to_num(x, nan=0.0, posinf=0.0, neginf=0.0) for x in xs]
    svgf = SVGF(frozen=False, levels=levels)
    ref = SVGF(frozen=False, levels=levels)  # the same sequence with the bad values as 0
    for i, (x, c) in enumerate(zip(xs, clean, strict=True)):
        got = _out(svgf(_flat_frame(x, index=i, emission=bad_emission if i == 4 else emission)))
        want = _out(ref(_flat_frame(c, index=i, emission=emission)))
        assert np.all(np.isfinite(got)), f"frame {i}: non-finite output"
        # documented policy: NaN/Inf values are replaced by 0 before they enter the filter
        np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-7)
    assert svgf.nonfinite == 6  # values, not pixels: 1 + 3 + 1 radiance, 1 emission
    assert ref.nonfinite == 0
    if levels == 0:
        np.testing.assert_allclose(got, _ema(clean)[-1], rtol=2e-5, atol=1e-6)


def test_size_change_and_camera_cut_reset_history():
    rng = np.random.default_rng(10)
    svgf = SVGF(frozen=False, levels=0)
    cam0 = _camera(W2, H2)
    for i in range(3):  # consistent cameras (prev_camera == the previous frame's camera)
        svgf(_flat_frame(rng.random((H2, W2)), camera=cam0, prev_camera=cam0, index=i))
    np.testing.assert_array_equal(_length(svgf), 3)
    # a camera move that is announced (prev_camera is the camera filtered before): kept
    cam1 = _camera(W2, H2, x=1e-3)
    svgf(_flat_frame(rng.random((H2, W2)), camera=cam1, prev_camera=cam0, index=3))
    np.testing.assert_array_equal(_length(svgf), 4)
    # a cut: the frame says its previous camera was somewhere else
    cam2 = _camera(W2, H2, x=5.0)
    x = rng.random((H2, W2))
    got = _out(svgf(_flat_frame(x, camera=cam2, prev_camera=_camera(W2, H2, x=4.9), index=4)))
    np.testing.assert_array_equal(_length(svgf), 1)
    np.testing.assert_allclose(got[..., 0], x, rtol=1e-6)
    svgf(_flat_frame(rng.random((H2, W2)), camera=cam2, prev_camera=cam2, index=5))
    np.testing.assert_array_equal(_length(svgf), 2)
    # a size change
    x = rng.random((H2 + 2, W2 - 4))
    got = _out(svgf(_flat_frame(x, index=6)))
    assert _length(svgf).shape == x.shape
    np.testing.assert_array_equal(_length(svgf), 1)
    np.testing.assert_allclose(got[..., 0], x, rtol=1e-6)


# =============================================================================================
# 3. reprojection with motion: 2x2 bilinear taps, renormalisation, 3x3 fallback (sec. 4.1)
# =============================================================================================


def _np_consistent(cur, prev, y, x, qy, qx):
    """Same surface? Same mesh id (not background), normals within ~25 degrees, 1/z within
    5 %. The synthetic G-buffers below differ either not at all or by far more (a different
    mesh, a 45-degree normal, a 30 % depth step), so any reasonable thresholds agree."""
    h, w = cur["mesh"].shape
    if not (0 <= qx < w and 0 <= qy < h) or cur["mesh"][y, x] <= 0:
        return False
    if prev["mesh"][qy, qx] != cur["mesh"][y, x]:
        return False
    if float(cur["normal"][y, x] @ prev["normal"][qy, qx]) < 0.9:
        return False
    iz_p, iz_q = 1.0 / cur["depth"][y, x], 1.0 / prev["depth"][qy, qx]
    return abs(iz_p - iz_q) <= 0.05 * iz_p


def _np_reproject(prev, cur, motion):
    """Schied 2017 sec. 4.1: fetch the previous frame at p + motion with a 2x2 bilinear
    filter; inconsistent taps are dropped and the weights of the others renormalised; if no
    tap is consistent, a 3x3 box around the nearest pixel over its consistent taps; else a
    disocclusion. Returns (colour, length, kind) with kind 0 = disoccluded, 1 = all four
    taps used, 2 = bilinear with dropped taps, 3 = 3x3 fallback."""
    h, w = cur["mesh"].shape
    col = np.zeros((h, w, 3))
    length = np.zeros((h, w))
    kind = np.zeros((h, w), int)
    for y in range(h):
        for x in range(w):
            px, py = x + motion[y, x, 0], y + motion[y, x, 1]
            x0, y0 = math.floor(px), math.floor(py)
            fx, fy = px - x0, py - y0
            taps = [(x0, y0, (1 - fx) * (1 - fy)), (x0 + 1, y0, fx * (1 - fy)),
                    (x0, y0 + 1, (1 - fx) * fy), (x0 + 1, y0 + 1, fx * fy)]
            good = [(qx, qy, wb) for qx, qy, wb in taps
                    if wb > 0 and _np_consistent(cur, prev, y, x, qy, qx)]
            sw = sum(wb for _, _, wb in good)
            if sw > 0:
                kind[y, x] = 1 if len(good) == sum(wb > 0 for *_, wb in taps) else 2
            else:
                rx, ry = int(np.rint(px)), int(np.rint(py))
                good = [(rx + i, ry + j, 1.0) for j in (-1, 0, 1) for i in (-1, 0, 1)
                        if _np_consistent(cur, prev, y, x, ry + j, rx + i)]
                sw = float(len(good))
                kind[y, x] = 3 if good else 0
            if sw > 0:
                col[y, x] = sum(wb * prev["color"][qy, qx] for qx, qy, wb in good) / sw
                length[y, x] = sum(wb * prev["length"][qy, qx] for qx, qy, wb in good) / sw
    return col, length, kind


def _gb(mesh=None, normal=None, depth=None, h=H2, w=W2):
    g = {"mesh": np.ones((h, w)) if mesh is None else mesh.astype(np.float64)}
    if normal is None:
        normal = np.zeros((h, w, 3))
        normal[..., 2] = 1.0
    g["normal"] = normal.astype(np.float64)
    g["depth"] = np.full((h, w), 2.0) if depth is None else depth.astype(np.float64)
    return g


def _frame_from_gb(x, g, motion, index):
    return _flat_frame(x, mesh=g["mesh"][..., None], normal=g["normal"],
                       depth=g["depth"][..., None], motion=motion, index=index)


@pytest.mark.parametrize("m", [(0.5, 0.5), (1.5, -0.5), (0.25, 0.75), (2.0, 1.0)])
def test_bilinear_reprojection_and_renormalisation(m):
    """Frame 0 holds an image I; frame 1 has zero radiance and a uniform motion m, so its
    output is 0.5 * (I resampled at p + m) (history length 2 -> alpha = 1/2). A few pixels of
    frame 0 are inconsistent with frame 1 (other mesh, tilted normal, other depth): taps on
    them are dropped and the other taps' weights renormalised."""
    rng = np.random.default_rng(11)
    img = rng.uniform(0.5, 2.0, (H2, W2, 3))
    prev = _gb()
    bad = [(5, 6), (9, 14), (15, 20), (17, 8)]  # (y, x): mesh, normal, depth, mesh
    prev["mesh"][5, 6] = prev["mesh"][17, 8] = 2
    prev["normal"][9, 14] = (0.0, math.sqrt(0.5), math.sqrt(0.5))
    prev["depth"][15, 20] = 2.6
    prev["color"], prev["length"] = img, np.ones((H2, W2))
    cur = _gb()
    motion = np.broadcast_to(np.asarray(m, np.float32), (H2, W2, 2)).copy()
    svgf = SVGF(frozen=False, levels=0)
    svgf(_frame_from_gb(img, prev, None, 0))
    got = _out(svgf(_frame_from_gb(np.zeros((H2, W2)), cur, motion, 1)))
    want_h, want_len, kind = _np_reproject(prev, cur, motion)
    ok = kind > 0
    np.testing.assert_allclose(got[ok], 0.5 * want_h[ok], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(got[~ok], 0.0, atol=1e-7)
    np.testing.assert_allclose(_length(svgf), np.where(ok, want_len + 1, 1), rtol=1e-6)
    # the cases this was meant to exercise all occur
    frac = m[0] % 1 or m[1] % 1
    assert np.count_nonzero(kind == 1) > 0.5 * H2 * W2
    assert np.count_nonzero(kind == 2) >= (len(bad) if frac else 0)
    # hand-checked pixel for (0.5, 0.5): the tap (6, 5) of pixel (5, 4) is dropped, the other
    # three taps share the weight equally
    if m == (0.5, 0.5):
        y, x = 4, 5
        expect = (img[4, 5] + img[4, 6] + img[5, 5]) / 3
        np.testing.assert_allclose(got[y, x], 0.5 * expect, rtol=1e-5)
        y, x = 2, 2
        expect = (img[2, 2] + img[2, 3] + img[3, 2] + img[3, 3]) / 4
        np.testing.assert_allclose(got[y, x], 0.5 * expect, rtol=1e-5)


def test_3x3_fallback_keeps_history():
    """All four bilinear taps inconsistent, some 3x3 neighbours consistent: history is kept
    (the mean of the consistent 3x3 taps); nothing consistent in 3x3: disocclusion."""
    rng = np.random.default_rng(12)
    img = rng.uniform(0.5, 2.0, (H2, W2, 3))
    prev = _gb()
    prev["mesh"][6:8, 6:8] = 2  # a 2x2 thin object that has gone
    prev["mesh"][12:16, 20:24] = 3  # a 4x4 one
    prev["color"], prev["length"] = img, np.ones((H2, W2))
    cur = _gb()
    motion = np.full((H2, W2, 2), 0.25, np.float32)
    svgf = SVGF(frozen=False, levels=0)
    svgf(_frame_from_gb(img, prev, None, 0))
    got = _out(svgf(_frame_from_gb(np.zeros((H2, W2)), cur, motion, 1)))
    length = _length(svgf)
    # pixel (6, 6) reads (6.25, 6.25): its 4 taps are the 2x2 object; the 3x3 box around
    # (6, 6) has 5 consistent pixels
    five = [(5, 5), (5, 6), (5, 7), (6, 5), (7, 5)]
    expect = np.mean([img[y, x] for y, x in five], axis=0)
    np.testing.assert_allclose(got[6, 6], 0.5 * expect, rtol=1e-5)
    assert length[6, 6] == pytest.approx(2.0)
    # pixel (13, 21): 4 taps and 3x3 box all inside the 4x4 object -> disoccluded
    np.testing.assert_allclose(got[13, 21], 0.0, atol=1e-7)
    assert length[13, 21] == 1.0
    want_h, want_len, kind = _np_reproject(prev, cur, motion)
    assert kind[6, 6] == 3 and kind[13, 21] == 0
    ok = kind > 0
    np.testing.assert_allclose(got[ok], 0.5 * want_h[ok], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(length, np.where(ok, want_len + 1, 1), rtol=1e-6)


@pytest.mark.parametrize("d", [(2, 1), (1.5, 0.5)])
def test_moving_object_sequence_matches_reference(d):
    """A 6-frame sequence: static plane (mesh 1, depth 2, motion 0) and a block (mesh 2,
    depth 1.5) moving by d pixels per frame (motion -d on it), noisy radiance. Frame by frame
    the output (levels=0) is the EMA over the reprojected history computed by the NumPy
    reference, including disocclusions behind the block and renormalised taps on its edges."""
    rng = np.random.default_rng(13)
    yy, xx = np.mgrid[0:H2, 0:W2] + 0.5
    svgf = SVGF(frozen=False, levels=0)
    prev = None
    kinds = np.zeros(4, int)
    for n in range(6):
        u, v = xx - n * d[0], yy - n * d[1]  # block coordinates of the pixel centres
        on = (u >= 4) & (u < 13) & (v >= 5) & (v < 14)
        g = _gb(mesh=np.where(on, 2, 1), depth=np.where(on, 1.5, 2.0))
        motion = np.zeros((H2, W2, 2), np.float32)
        motion[on] = (-d[0], -d[1])
        x = rng.exponential(1.0, (H2, W2, 3))
        got = _out(svgf(_frame_from_gb(x, g, motion, n)))
        if prev is None:
            want, length = x, np.ones((H2, W2))
        else:
            hist, hlen, kind = _np_reproject(prev, g, motion)
            kinds += np.bincount(kind.ravel(), minlength=4)
            ok = kind > 0
            length = np.where(ok, hlen + 1, 1.0)
            a = np.where(ok, np.maximum(0.2, 1.0 / length), 1.0)[..., None]
            want = a * x + (1 - a) * hist
        # float32 recursion over 6 frames: ~1e-6 relative
        np.testing.assert_allclose(got, want, rtol=2e-5, atol=1e-6, err_msg=f"frame {n}")
        np.testing.assert_allclose(_length(svgf), length, rtol=1e-5, err_msg=f"frame {n}")
        g["color"], g["length"] = want, length
        prev = g
    print(f"\n[moving block d={d}] pixels per case over frames 1-5: disoccluded {kinds[0]}, "
          f"4 taps {kinds[1]}, renormalised {kinds[2]}, 3x3 fallback {kinds[3]}")
    assert kinds[0] > 0  # disocclusion behind the block
    if d[0] % 1:
        assert kinds[2] > 0  # half-pixel motion: taps straddle the block's edge


# =============================================================================================
# 4. frozen and plain execution agree
# =============================================================================================


def test_frozen_matches_unfrozen_on_rendered_sequence(frozen_guard):
    frozen_guard()
    setup = scenes.load("glossy-cornell", size=(48, 36))  # animated: camera sway + sphere
    r = Renderer(setup)
    frames = [r.render(i) for i in range(4)]
    frozen, plain = SVGF(frozen=True), SVGF(frozen=False)
    for f in frames:
        a, b = _out(frozen(f)), _out(plain(f))
        # the same kernels replayed: identical up to float32 rounding of fused operations
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6, err_msg=f"frame {f.index}")
    np.testing.assert_allclose(_np(frozen.history.length, 36, 48),
                               _np(plain.history.length, 36, 48), rtol=1e-6)
    # one recording per frozen stage serves the first frame (empty history) and the later
    # ones (re-recording every frame would cost the Python tracing that freezing avoids)
    stages = {k: v.n_recordings for k, v in vars(frozen).items() if hasattr(v, "n_recordings")}
    print(f"\n[freeze] recordings per frozen stage after 4 frames: {stages}")
    assert stages, "SVGF(frozen=True) has no dr.freeze'd function"
    assert all(n == 1 for n in stages.values()), stages


# =============================================================================================
# 5./6. rendered glossy-cornell: quality (sec. 5.2) and temporal stability (sec. 5.4)
# =============================================================================================

REF_FRAMES = (9, 19)


@pytest.fixture(scope="module")
def animated_sequence():
    """glossy-cornell 96x72, 20 frames (camera sway, moving sphere), 256 spp references at
    frames 9 and 19 (the reference's own RMSE against the 4096-spp limit is ~1/16 of a
    1 spp frame's, below the differences compared)."""
    setup = scenes.load("glossy-cornell", size=(96, 72))
    r = Renderer(setup)
    frames = [r.render(i) for i in range(20)]
    refs = {i: r.render_reference(i, spp=256).numpy("color") for i in REF_FRAMES}
    return frames, refs


@pytest.mark.slow
def test_svgf_beats_per_frame_atrous(animated_sequence, frozen_guard):
    frozen_guard()
    frames, refs = animated_sequence
    svgf = SVGF()
    outs = {f.index: _out(svgf(f)) for f in frames}
    rows = []
    for i in REF_FRAMES:
        ref = refs[i]
        a = _out(atrous(frames[i]))
        noisy = frames[i].numpy("color")
        rows.append((i, metrics.rmse(outs[i], ref), metrics.ssim(outs[i], ref),
                     metrics.rmse(a, ref), metrics.ssim(a, ref), metrics.rmse(noisy, ref),
                     metrics.ssim(noisy, ref)))
    print("\n[quality 96x72] frame: SVGF rmse/ssim | atrous rmse/ssim | 1 spp input rmse/ssim")
    for i, rs, ss, ra, sa, rn, sn in rows:
        print(f"  {i:2d}: {rs:.4f} / {ss:.4f} | {ra:.4f} / {sa:.4f} | {rn:.4f} / {sn:.4f}")
    for i, rs, ss, ra, sa, *_ in rows:
        # Schied 2017 table 1: SVGF is better than EAW in RMSE and SSIM on every scene. The
        # margins measured here are ~40% (RMSE) and ~0.06 (SSIM); the noise of one run moves
        # them by a few %, so strict inequalities are safe.
        assert rs < ra, f"frame {i}: SVGF RMSE {rs:.4f} not below atrous {ra:.4f}"
        assert ss > sa, f"frame {i}: SVGF SSIM {ss:.4f} not above atrous {sa:.4f}"


@pytest.mark.slow
def test_temporal_stability_static_scene(frozen_guard):
    """Sec. 5.4: static camera, lights and scene; temporal error (mean absolute luminance
    change between consecutive outputs) over the last 20 frames of 30. The paper reports
    SVGF ~10x more stable than EAW (fig. 10a); asserted: at least 5x."""
    frozen_guard()
    setup = scenes.load("glossy-cornell", size=(64, 48))
    setup.camera_path = None
    setup.object_paths = {}
    r = Renderer(setup)
    frames = [r.render(i) for i in range(30)]
    svgf = SVGF()
    outs = [_out(svgf(f)) for f in frames]
    tail = frames[-21:]  # 21 outputs -> 20 consecutive differences
    te_svgf = metrics.temporal_error(outs[-21:])
    te_atrous = metrics.temporal_error([_out(atrous(f)) for f in tail])
    te_input = metrics.temporal_error([f.numpy("color") for f in tail])
    ratio = te_svgf / te_atrous
    print(f"\n[temporal error, static 64x48, last 20 frames] SVGF {te_svgf:.5f}, atrous "
          f"{te_atrous:.5f}, 1 spp input {te_input:.5f}; SVGF / atrous = {ratio:.3f}")
    assert ratio <= 0.2


# =============================================================================================
# 7. the structured-noise test pattern (sec. 5.2, fig. 9)
# =============================================================================================


def test_structured_noise_pattern_temporal_vs_spatial_variance(frozen_guard):
    """Per-pixel radiance pattern(x, y) * f(u, alpha(x)) with f = 0 if u < alpha else
    1/(1 - alpha) (mean 1), u uniform per pixel and frame, alpha rising linearly from 0 (left)
    to 0.95 (right); pattern: horizontal stripes 4 pixels wide of 0.5 / 1.5. After 30 frames
    the temporal variance estimate keeps the stripes where the noise is low better than the
    7x7 spatial estimate, which sees the stripes themselves as variance (fig. 9)."""
    frozen_guard("steady-state", "spatial-variance")
    h, w, n_frames = 24, 96, 30
    yy, xx = np.mgrid[0:h, 0:w]
    pattern = np.where((yy // 4) % 2 == 0, 0.5, 1.5)
    alpha = 0.95 * xx / (w - 1)
    col_err = {}
    for variance in ("temporal", "spatial"):
        svgf = SVGF(variance=variance)
        rng = np.random.default_rng(2017)  # the same noise for both
        for i in range(n_frames):
            u = rng.random((h, w))
            f = np.where(u < alpha, 0.0, 1.0 / (1.0 - alpha))
            out = _out(svgf(_flat_frame(pattern * f, index=i)))[..., 0]
        col_err[variance] = np.mean((out - pattern) ** 2, axis=0)  # per column MSE

    def rmse(v, cols):
        return float(np.sqrt(np.mean(col_err[v][cols])))

    thirds = [slice(k * w // 3, (k + 1) * w // 3) for k in range(3)]
    low = alpha[0] < 0.05  # the 5 columns with <5% zero samples
    t3 = [rmse("temporal", s) for s in thirds]
    s3 = [rmse("spatial", s) for s in thirds]
    print(f"\n[structured noise, RMSE vs pattern; 0.5 = pattern lost] thirds (left..right): "
          f"temporal {t3[0]:.3f} {t3[1]:.3f} {t3[2]:.3f}, spatial {s3[0]:.3f} {s3[1]:.3f} "
          f"{s3[2]:.3f}; alpha<0.05: temporal {rmse('temporal', low):.3f}, spatial "
          f"{rmse('spatial', low):.3f}")
    # measured: left third 0.38 vs 0.45 (ratio 0.85, within 0.01 over noise seeds);
    # alpha < 0.05: 0.18 vs 0.43
    assert t3[0] < 0.93 * s3[0]
    assert rmse("temporal", low) < 0.6 * rmse("spatial", low)


# =============================================================================================
# 8. disocclusion in a rendered scene: no ghost of a removed object
# =============================================================================================

JUMP = 8  # the box leaves the view at this frame


def _jump_scene(w, h):
    """A diffuse wall facing the camera and a glossy aluminium box in front of it, lit by a
    small area light just behind the camera (so the box's shadow hides behind the box and its
    departure barely changes the light on the rest of the wall). The box reflects the light
    into the camera: its (specular) illumination is ~5x the wall's, a ghost would show."""
    t = mi.ScalarTransform4f
    d = {
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 40.0, "fov_axis": "x",
                   "to_world": t().look_at(origin=[0, 0, 4], target=[0, 0, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": w, "height": h}},
        "wall": {"type": "rectangle", "to_world": t().translate([0, 0, -1]).scale(3),
                 "bsdf": {"type": "diffuse",
                          "reflectance": {"type": "rgb", "value": [0.7, 0.7, 0.7]}}},
        "box": {"type": "cube",
                "to_world": t().translate([0.2, 0.1, 0.3]).rotate([0, 1, 0], 10).scale(0.45),
                "bsdf": {"type": "roughconductor", "material": "Al", "alpha": 0.25}},
        "light": {"type": "rectangle",
                  "to_world": t().translate([0, 0, 4.3]).rotate([0, 1, 0], 180).scale(0.3),
                  "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0, 0, 0]}},
                  "emitter": {"type": "area",
                              "radiance": {"type": "rgb", "value": [40.0, 38.0, 34.0]}}},
    }
    away = scenes.translation((6.0, 0.0, 0.0))
    still = np.eye(4)
    return scenes.SceneSetup("box-jump", mi.load_dict(d), size=(w, h),
                             object_paths={"box": lambda f: still if f < JUMP else away})


def _with_old_gbuffer(frame, old, region):
    """``frame`` with the G-buffer (mesh_id, depth, normal) of ``old`` pasted into ``region``:
    fakes geometric consistency where the box used to be (a filter that would ghost)."""
    ch = dict(frame.channels)
    for name in ("mesh_id", "depth", "normal"):
        a = frame.numpy(name).copy()
        a[region] = old.numpy(name)[region]
        ch[name] = a
    return Frame(channels=ch, camera=frame.camera, prev_camera=frame.prev_camera,
                 index=frame.index)


@pytest.mark.slow
def test_disocclusion_leaves_no_ghost(frozen_guard):
    frozen_guard()
    w, h, n_after = 64, 48, 5
    setup = _jump_scene(w, h)
    r = Renderer(setup)
    frames = [r.render(i) for i in range(JUMP + n_after)]
    # the scene is static from JUMP on: one converged reference serves frames JUMP..
    ref = r.render_reference(JUMP, spp=256).numpy("color")
    box_id = setup.shape_index["box"]
    before, after = frames[JUMP - 1].numpy("mesh_id")[..., 0], frames[JUMP].numpy("mesh_id")[..., 0]
    revealed = (before == box_id) & (after == setup.shape_index["wall"])
    assert revealed.sum() > 200  # the box covered ~10% of the view
    box_col = frames[JUMP - 1].numpy("color")[revealed].mean(axis=0)  # 1 spp is fine for a mean
    contrast = float(np.abs(box_col - ref[revealed].mean(axis=0)).mean())

    def run(make_frame, start=0):
        svgf = SVGF()
        outs = [_out(svgf(make_frame(f))) for f in frames[start:]]
        return outs[-n_after:]

    def err(img):  # mean absolute error over the revealed pixels and RGB
        return float(np.mean(np.abs(img[revealed] - ref[revealed])))

    keep = run(lambda f: f)
    fresh = run(lambda f: f, start=JUMP)  # a filter that starts at the jump: no history at all
    ghost = run(lambda f: f if f.index < JUMP else _with_old_gbuffer(f, frames[JUMP - 1],
                                                                     revealed))
    e_keep, e_fresh, e_ghost = ([err(o) for o in outs] for outs in (keep, fresh, ghost))
    print(f"\n[disocclusion] {revealed.sum()} revealed pixels, box-wall contrast {contrast:.3f}; "
          "mean |error| in the revealed region at frames "
          f"{JUMP}..{JUMP + n_after - 1}:\n  SVGF   {np.round(e_keep, 4)}\n  reset  "
          f"{np.round(e_fresh, 4)}\n  ghost  {np.round(e_ghost, 4)} (old G-buffer pasted in)")

    def lingering(errs):
        """The excess error over a filter with no history, as a fraction of the box-wall
        contrast: a ghost of the box shows up as a fraction of the contrast left behind.
        5 % is below what is visible next to 1 spp noise."""
        return [(e - f) / contrast for e, f in zip(errs, e_fresh, strict=True)]

    assert max(lingering(e_keep)) < 0.05
    # the check has power: with faked consistency the box's light lingers (EMA 0.8^k)
    assert lingering(e_ghost)[1] > 0.05 * 5
