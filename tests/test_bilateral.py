"""glossrt.denoise.bilateral: the cross-bilateral filter of Tokuyoshi 2015 (sec. 2.2, 4, 5).

* the Dr.Jit filter against a plain NumPy re-implementation of eq. 1 with the screen, depth,
  normal (sec. 2.2) and lobe (sec. 4.2; eq. 7 and exact eq. 6) weights, on a tiny random frame;
* bookkeeping: a constant demodulated signal stays constant, unlisted components and the
  background pass through;
* a roughness step (alpha 0.02 | 0.5) on a plane: the lobe weight keeps it, the normal
  weight blurs it (sec. 5.1, fig. 4);
* the built-in ``roughness-map`` scene: MSE of indirect_specular against a 256 spp reference.

Run with ``pytest -s`` to see the measured numbers.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from glossrt import backend

backend.ensure()
import mitsuba as mi  # noqa: E402, F401

from glossrt.denoise.bilateral import bilateral  # noqa: E402
from glossrt.frame import RADIANCE, Camera, Frame  # noqa: E402

CAM_POS = np.array([0.3, -0.2, 0.0])
FOV = 45.0


def _camera(w, h):
    m = np.eye(4)
    m[:3, 3] = CAM_POS
    return Camera(to_world=m, fov=FOV, resolution=(w, h))


def random_frame(w=9, h=7, seed=1, background=((0, 0), (4, 3)), jitter=(0.0, 0.0)):
    """Random radiance, albedos, normals and roughness on visible points of the pixels'
    camera rays (through the pixel centres plus ``jitter``, recorded in ``meta``)."""
    rng = np.random.default_rng(seed)
    ch = {}
    for c in RADIANCE:
        ch[c] = rng.uniform(0.0, 2.0, (h, w, 3))
    ch["albedo_diffuse"] = rng.uniform(0.1, 0.9, (h, w, 3))
    ch["albedo_specular"] = rng.uniform(0.1, 0.9, (h, w, 3))
    ch["albedo_specular"][1, 1] = 0.0  # no albedo: filtered as it is
    # visible points on the pixels' camera rays (what a G-buffer holds; the lobe weight's view
    # directions are the rays, glossrt.denoise.common.pixel_view_directions)
    t = math.tan(math.radians(FOV) / 2.0)
    ys, xs = np.mgrid[0:h, 0:w] + 0.5 + np.array(jitter)[::-1, None, None]
    z = rng.uniform(2.9, 3.1, (h, w))
    pos = CAM_POS + np.stack([t * (1 - 2 * xs / w) * z, t * (h - 2 * ys) / w * z, z], -1)
    assert np.allclose(_camera(w, h).project(pos), np.stack([xs, ys], -1))
    n = rng.normal(size=(h, w, 3)) * [0.3, 0.3, 1.0]
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    to_cam = CAM_POS - pos
    n *= np.sign(np.sum(n * to_cam, -1, keepdims=True))  # faces the camera
    ch["normal"] = n
    ch["position"] = pos
    ch["depth"] = pos[..., 2:3].copy()
    ch["roughness"] = rng.uniform(0.05, 0.6, (h, w, 1))
    ch["mesh_id"] = np.ones((h, w, 1))
    for x, y in background:
        ch["mesh_id"][y, x] = 0.0
        ch["depth"][y, x] = np.inf
        ch["normal"][y, x] = 0.0
        ch["position"][y, x] = 0.0
        ch["roughness"][y, x] = 0.0
    ch["color"] = sum(ch[c] for c in RADIANCE)
    meta = {"jitter": [float(v) for v in jitter]} if tuple(jitter) != (0.0, 0.0) else {}
    return Frame(channels={k: v.astype(np.float32) for k, v in ch.items()},
                 camera=_camera(w, h), meta=meta)


# -- NumPy reference (written from the paper's formulas, float64, one pixel at a time) ----------


def np_lobe(n, wo, alpha, beckmann=False):
    """The lobe as an SG (Wang et al.'s warp) with its distribution's NDF sharpness matched
    at the peak: 4 / alpha^2 for GGX, 2 / alpha^2 for Beckmann (Wang et al.'s)."""
    a = max(alpha, 1e-4)
    c = max(abs(np.dot(n, wo)), 1e-6)
    lam = min((2.0 if beckmann else 4.0) / (a * a) / (4.0 * c), 1e12)
    return 2.0 * np.dot(n, wo) * n - wo, lam


def beck(F, y, x) -> bool:
    """Whether pixel (x, y) of the frame arrays ``F`` is Beckmann (its distribution channel)."""
    return "distribution" in F and F["distribution"][y, x, 0] == 1.0


def np_lobe_weight(xi, lam, xj, laj, beta, kappa, approx):
    a = max(lam, 1e-8) * kappa / (max(lam, 1e-8) + kappa)
    b = max(laj, 1e-8) * kappa / (max(laj, 1e-8) + kappa)
    if approx:  # Tokuyoshi 2015, sec. 4.2 (through eq. 7)
        q = 2.0 * math.sqrt(a * b) / (a + b) * math.exp(a * b / (a + b) * (np.dot(xi, xj) - 1))
    else:  # eqs. 4-5 with the exact eq. 6

        def integral(x1, l1, x2, l2):
            r = np.linalg.norm(l1 * x1 + l2 * x2)
            return 4 * math.pi * math.sinh(r) / (math.exp(l1 + l2) * r)

        q = integral(xi, a, xj, b) / math.sqrt(integral(xi, a, xi, a) * integral(xj, b, xj, b))
    return min(q, 1.0) ** beta


def np_bilateral(frame, weight, channels, radius, sigma_s, sigma_n2=0.01, beta=20.0,
                 kappa=100.0, approx=True, sigma_z2=0.01):
    F = {k: frame.numpy(k).astype(np.float64) for k in frame.names}
    h, w = frame.height, frame.width
    hit = F["mesh_id"][..., 0] > 0
    out = sum(F[c] for c in RADIANCE if c not in channels)
    for c in channels:
        alb = F["albedo_specular" if c.endswith("specular") else "albedo_diffuse"]
        ok = alb > 1e-3
        sig = np.where(ok, F[c] / np.maximum(alb, 1e-3), F[c])
        filt = sig.copy()
        for y in range(h):
            for x in range(w):
                if not hit[y, x]:
                    continue
                ni, zi = F["normal"][y, x], F["depth"][y, x, 0]
                wo = CAM_POS - F["position"][y, x]
                li = np_lobe(ni, wo / np.linalg.norm(wo), F["roughness"][y, x, 0],
                             beck(F, y, x))
                num, den = np.zeros(3), 0.0
                for yy in range(max(0, y - radius), min(h, y + radius + 1)):
                    for xx in range(max(0, x - radius), min(w, x + radius + 1)):
                        if not hit[yy, xx]:
                            continue
                        d2 = (xx - x) ** 2 + (yy - y) ** 2
                        wt = math.exp(-d2 / (2 * sigma_s**2))
                        zj = F["depth"][yy, xx, 0]
                        wt *= math.exp(-(((zi - zj) / zi) ** 2) / (2 * sigma_z2))
                        nj = F["normal"][yy, xx]
                        if weight == "lobe" and c.endswith("specular"):
                            wj = CAM_POS - F["position"][yy, xx]
                            lj = np_lobe(nj, wj / np.linalg.norm(wj),
                                         F["roughness"][yy, xx, 0], beck(F, yy, xx))
                            wt *= np_lobe_weight(*li, *lj, beta, kappa, approx)
                        else:
                            wt *= math.exp(-np.sum((ni - nj) ** 2) / (2 * sigma_n2))
                        num += wt * sig[yy, xx]
                        den += wt
                filt[y, x] = num / den
        out = out + np.where(hit[..., None], np.where(ok, filt * alb, filt), F[c])
    return out


@pytest.mark.parametrize("weight,approx", [("normal", True), ("lobe", True), ("lobe", False)])
def test_matches_numpy_reference(weight, approx):
    f = random_frame()
    chans = ("indirect_diffuse", "indirect_specular")
    got = np.array(bilateral(f, weight=weight, channels=chans, radius=3, sigma_s=1.5,
                             approx=approx))
    want = np_bilateral(f, weight, chans, 3, 1.5, approx=approx)
    assert got.shape == (7, 9, 3)
    np.testing.assert_allclose(got, want, rtol=2e-4, atol=2e-5)
    # the filter did something (the weights are not all ~0)
    assert np.max(np.abs(want - f.numpy("color"))) > 1e-2


def test_lobe_differs_from_normal_on_specular_only():
    f = random_frame(seed=3)
    a = np.array(bilateral(f, weight="normal", channels=("indirect_diffuse",), radius=2))
    b = np.array(bilateral(f, weight="lobe", channels=("indirect_diffuse",), radius=2))
    np.testing.assert_array_equal(a, b)  # diffuse components always use w_n


@pytest.mark.parametrize("weight", ["normal", "lobe"])
def test_constant_signal_is_kept(weight):
    f = random_frame(seed=5)
    for c, a in (("indirect_diffuse", "albedo_diffuse"), ("indirect_specular", "albedo_specular")):
        alb = f.numpy(a)
        f[c] = np.where(alb > 1e-3, np.float32(0.7) * alb, np.float32(0.7))
    color = sum(f.numpy(c) for c in RADIANCE)
    got = np.array(bilateral(f, weight=weight, radius=3))
    np.testing.assert_allclose(got, color, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("weight", ["normal", "lobe"])
def test_unlisted_components_and_background_pass_through(weight):
    f = random_frame(seed=7)
    base = np.array(bilateral(f, weight=weight, channels=("indirect_specular",), radius=3))
    rng = np.random.default_rng(0)
    delta = 0.0
    g = Frame(channels=dict(f.channels), camera=f.camera)
    for c in ("emission", "direct_diffuse", "direct_specular", "indirect_diffuse"):
        d = rng.uniform(0, 1, f.numpy(c).shape).astype(np.float32)
        g[c] = f.numpy(c) + d
        delta = delta + d
    moved = np.array(bilateral(g, weight=weight, channels=("indirect_specular",), radius=3))
    np.testing.assert_allclose(moved - base, delta, rtol=1e-5, atol=1e-5)
    # background pixels: the unfiltered sum of the components
    full = np.array(bilateral(f, weight=weight, radius=3))
    color = sum(f.numpy(c) for c in RADIANCE)
    for x, y in ((0, 0), (4, 3)):
        np.testing.assert_array_equal(full[y, x], color[y, x])


def test_background_is_never_a_neighbour():
    # a background pixel with huge radiance must not leak into its neighbours
    f = random_frame(seed=9)
    g = Frame(channels=dict(f.channels), camera=f.camera)
    spec = f.numpy("indirect_specular")
    spec[3, 4] = 1e6
    g["indirect_specular"] = spec
    for weight in ("normal", "lobe"):
        a = np.array(bilateral(f, weight=weight, radius=3))
        b = np.array(bilateral(g, weight=weight, radius=3))
        diff = np.abs(a - b).sum(-1)
        diff[3, 4] = 0.0
        assert diff.max() == 0.0


def step_frame(w=24, h=16):
    """A plane facing the camera; left half alpha 0.02 (signal 1.0), right half alpha 0.5
    (signal 0.2); identical normals and depths everywhere."""
    xs = (np.arange(w) + 0.5 - w / 2) / w
    ys = (np.arange(h) + 0.5 - h / 2) / w
    px, py = np.meshgrid(xs, ys)
    pos = np.stack([px + CAM_POS[0], py + CAM_POS[1], np.full_like(px, 3.0)], -1)
    left = np.arange(w)[None, :].repeat(h, 0) < w // 2
    zero = np.zeros((h, w, 3))
    ch = {c: zero for c in RADIANCE}
    ch["albedo_specular"] = np.full((h, w, 3), 0.5)
    ch["albedo_diffuse"] = np.full((h, w, 3), 0.5)
    ch["indirect_specular"] = 0.5 * np.where(left, 1.0, 0.2)[..., None].repeat(3, -1)
    ch["normal"] = np.broadcast_to([0.0, 0.0, -1.0], (h, w, 3))
    ch["position"] = pos
    ch["depth"] = pos[..., 2:3]
    ch["roughness"] = np.where(left, 0.02, 0.5)[..., None]
    ch["mesh_id"] = np.ones((h, w, 1))
    return Frame(channels={k: np.asarray(v, np.float32) for k, v in ch.items()},
                 camera=_camera(w, h))


def test_lobe_weight_keeps_a_roughness_step():
    f = step_frame()
    inp = f.numpy("indirect_specular")[..., 0]
    step = inp[0, 0] - inp[0, -1]
    lobe = np.array(bilateral(f, weight="lobe"))[..., 0]
    normal = np.array(bilateral(f, weight="normal"))[..., 0]
    cols = [10, 11, 12, 13]  # the two columns each side of the step
    err_l = np.max(np.abs(lobe[:, cols] - inp[:, cols])) / step
    err_n = np.max(np.abs(normal[:, cols] - inp[:, cols])) / step
    print(f"\nroughness step: max error next to the step: lobe {err_l:.3g}, normal {err_n:.3g}"
          " (fraction of the step)")
    assert err_l < 0.01
    assert err_n > 0.2


# -- the built-in roughness-map scene --------------------------------------------------------------

# measured on this code at the defaults (sigma_s 2, radius 6, sigma_z2 0.01, sigma_n2 0.01,
# beta 20, kappa 100, eq. 7), CPU variant, 96x72, frame 0, reference 256 spp
MEASURED = ("normal-aware 0.003169, lobe-aware 0.003289 (ratio 1.04; 1.22 before the scene "
            "declared GGX and the lobes took GGX's own sharpness, 2026-12)")


@pytest.fixture(scope="module")
def roughness_map():
    from glossrt import render, scenes

    setup = scenes.load("roughness-map", size=(96, 72))
    r = render.Renderer(setup)
    f = r.render(0)
    ref = r.render_reference(0, spp=256)
    rest = sum(f.numpy(c) for c in RADIANCE if c != "indirect_specular")
    target = ref.numpy("indirect_specular")
    mse = {"input": float(np.mean((f.numpy("indirect_specular") - target) ** 2))}
    for weight in ("normal", "lobe"):
        out = np.array(bilateral(f, weight=weight, channels=("indirect_specular",)))
        mse[weight] = float(np.mean((out - rest - target) ** 2))
    print(f"\nroughness-map indirect_specular MSE: input {mse['input']:.5g}, "
          f"normal-aware {mse['normal']:.5g}, lobe-aware {mse['lobe']:.5g}, "
          f"ratio {mse['lobe'] / mse['normal']:.3f}")
    return mse


@pytest.mark.slow
def test_roughness_map_both_filters_reduce_error(roughness_map):
    assert roughness_map["normal"] < 0.5 * roughness_map["input"]
    assert roughness_map["lobe"] < 0.5 * roughness_map["input"]


def test_roughness_map_lobe_vs_normal_measured(roughness_map):
    # Tokuyoshi 2015, fig. 4 claims lobe-aware weights (eqs. 2-7) beat normal-aware ones on
    # the roughness map. At this test's 96x72 that does not hold (a negative result, stated in
    # docs/RESULTS.md; issue 28 re-measures at the paper's 640x360): the lobe-aware MSE is
    # 1.04x the normal-aware one (MEASURED). Asserted on the measured side, so the test fails
    # both if the lobe weights get worse and if they start to win (then the claim holds here
    # and this test and RESULTS must say so).
    ratio = roughness_map["lobe"] / roughness_map["normal"]
    assert 0.9 < ratio < 1.15, (ratio, MEASURED)


# -- weight="screen": the sharpness-adapted screen kernel (fig. 4(c) baseline, glossrt's form) ---


def np_screen_sigma(frame, k_s, sigma_min, sigma_s):
    """Per-pixel sigma_s,i = clip(k_s / (sqrt(lambda_i) theta_px), sigma_min, sigma_s)."""
    cam = frame.camera
    theta = 2.0 * math.tan(math.radians(cam.fov) / 2.0) / frame.width
    F = {k: frame.numpy(k).astype(np.float64) for k in ("normal", "position", "roughness")}
    sig = np.full((frame.height, frame.width), sigma_s)
    for y in range(frame.height):
        for x in range(frame.width):
            wo = CAM_POS - F["position"][y, x]
            _, lam = np_lobe(F["normal"][y, x], wo / np.linalg.norm(wo), F["roughness"][y, x, 0],
                             beck(F, y, x))
            sig[y, x] = min(max(k_s / (math.sqrt(lam) * theta), sigma_min), sigma_s)
    return sig


def np_screen_bilateral(frame, channels, radius, sigma_s, k_s, sigma_min, sigma_n2=0.01,
                        sigma_z2=0.01):
    F = {k: frame.numpy(k).astype(np.float64) for k in frame.names}
    h, w = frame.height, frame.width
    hit = F["mesh_id"][..., 0] > 0
    sig_i = np_screen_sigma(frame, k_s, sigma_min, sigma_s)
    out = sum(F[c] for c in RADIANCE if c not in channels)
    for c in channels:
        spec = c.endswith("specular")
        alb = F["albedo_specular" if spec else "albedo_diffuse"]
        ok = alb > 1e-3
        sig = np.where(ok, F[c] / np.maximum(alb, 1e-3), F[c])
        filt = sig.copy()
        for y in range(h):
            for x in range(w):
                if not hit[y, x]:
                    continue
                s_i = sig_i[y, x] if spec else sigma_s
                ni, zi = F["normal"][y, x], F["depth"][y, x, 0]
                num, den = np.zeros(3), 0.0
                for yy in range(max(0, y - radius), min(h, y + radius + 1)):
                    for xx in range(max(0, x - radius), min(w, x + radius + 1)):
                        if not hit[yy, xx]:
                            continue
                        d2 = (xx - x) ** 2 + (yy - y) ** 2
                        wt = math.exp(-d2 / (2 * s_i**2))
                        zj = F["depth"][yy, xx, 0]
                        wt *= math.exp(-(((zi - zj) / zi) ** 2) / (2 * sigma_z2))
                        wt *= math.exp(-np.sum((ni - F["normal"][yy, xx]) ** 2) / (2 * sigma_n2))
                        num += wt * sig[yy, xx]
                        den += wt
                filt[y, x] = num / den
        out = out + np.where(hit[..., None], np.where(ok, filt * alb, filt), F[c])
    return out


def test_screen_matches_numpy_reference():
    f = random_frame(seed=11)
    chans = ("indirect_diffuse", "indirect_specular")
    k_s, sigma_min, sigma_s = 0.5, 0.5, 1.5
    sig = np_screen_sigma(f, k_s, sigma_min, sigma_s)[f.numpy("mesh_id")[..., 0] > 0]
    # all three regimes of the clip occur (the check is not about a constant sigma)
    assert (sig == sigma_min).any() and (sig == sigma_s).any()
    assert ((sig > sigma_min) & (sig < sigma_s)).any()
    got = np.array(bilateral(f, weight="screen", channels=chans, radius=3, sigma_s=sigma_s,
                             k_s=k_s, sigma_min=sigma_min))
    want = np_screen_bilateral(f, chans, 3, sigma_s, k_s, sigma_min)
    np.testing.assert_allclose(got, want, rtol=2e-4, atol=2e-5)
    normal = np.array(bilateral(f, weight="normal", channels=chans, radius=3, sigma_s=sigma_s))
    assert np.max(np.abs(got - normal)) > 1e-2  # the adapted kernel changed the result


def test_screen_reduces_to_normal_when_sigma_is_not_adapted():
    # k_s huge: every adapted sigma clips to sigma_s, so the weight is the normal weight
    f = random_frame(seed=13)
    a = np.array(bilateral(f, weight="screen", radius=3, k_s=1e9))
    b = np.array(bilateral(f, weight="normal", radius=3))
    np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)


def test_screen_keeps_the_normal_weight_on_diffuse_channels():
    f = random_frame(seed=15)
    a = np.array(bilateral(f, weight="screen", channels=("indirect_diffuse",), radius=2))
    b = np.array(bilateral(f, weight="normal", channels=("indirect_diffuse",), radius=2))
    np.testing.assert_array_equal(a, b)


def noisy_step_frame(seed=0):
    """step_frame with independent noise on the demodulated indirect specular (mean 1)."""
    f = step_frame()
    rng = np.random.default_rng(seed)
    h, w = f.height, f.width
    noise = rng.uniform(0.0, 2.0, (h, w, 1)).repeat(3, -1)
    g = Frame(channels=dict(f.channels), camera=f.camera)
    g["indirect_specular"] = (0.5 * noise).astype(np.float32)  # albedo_specular = 0.5
    return g


def test_screen_filters_sharp_pixels_less_than_rough_ones():
    f = noisy_step_frame()
    inp = f.numpy("indirect_specular")[..., 0]
    sharp_cols, rough_cols = slice(0, 5), slice(19, 24)  # >= 7 px from the step (radius 6)

    def reduction(img, cols):
        return float(np.std(img[:, cols]) / np.std(inp[:, cols]))

    scr = np.array(bilateral(f, weight="screen"))[..., 0]
    nrm = np.array(bilateral(f, weight="normal"))[..., 0]
    s_sharp, s_rough = reduction(scr, sharp_cols), reduction(scr, rough_cols)
    n_sharp, n_rough = reduction(nrm, sharp_cols), reduction(nrm, rough_cols)
    sig = np_screen_sigma(f, 1.0, 0.5, 2.0)
    print(f"\nscreen kernel: sigma {sig[:, sharp_cols].mean():.3g} px (alpha 0.02), "
          f"{sig[:, rough_cols].mean():.3g} px (alpha 0.5); remaining noise std: screen "
          f"{s_sharp:.3g} / {s_rough:.3g}, normal {n_sharp:.3g} / {n_rough:.3g} (sharp / rough)")
    assert sig[:, sharp_cols].max() < 1.0 and np.all(sig[:, rough_cols] == 2.0)
    assert s_sharp > 1.5 * s_rough  # less filtering where the lobe is sharp
    assert s_sharp > 1.5 * n_sharp  # ... than the unadapted (normal) kernel there
    assert s_rough == pytest.approx(n_rough, rel=1e-4)  # rough: sigma_s, as weight="normal"


def test_screen_kernel_still_blurs_across_a_roughness_step():
    """Fig. 4(c): the adapted kernel shrinks on the sharp side, but the rough side's wide
    kernel still averages in the sharp side's values (it does not compare the lobes)."""
    f = step_frame()
    inp = f.numpy("indirect_specular")[..., 0]
    step = inp[0, 0] - inp[0, -1]
    out = {w: np.array(bilateral(f, weight=w))[..., 0] for w in ("normal", "screen", "lobe")}
    def rel_err(o, cols):
        return float(np.max(np.abs(o[:, cols] - inp[:, cols])) / step)

    err = {w: (rel_err(o, slice(10, 12)), rel_err(o, slice(12, 14))) for w, o in out.items()}
    print("\nroughness step, max error (fraction of the step) sharp side / rough side: "
          + ", ".join(f"{w} {a:.3g} / {b:.3g}" for w, (a, b) in err.items()))
    assert err["screen"][0] < 0.75 * err["normal"][0]  # the sharp side is blurred less
    assert err["screen"][1] > 0.2
    assert err["screen"][1] == pytest.approx(err["normal"][1], rel=1e-4)


def test_screen_parameter_errors():
    from glossrt.errors import FrameError, GlossrtError

    f = random_frame()
    with pytest.raises(GlossrtError, match="k_s > 0"):
        bilateral(f, weight="screen", k_s=0.0)
    with pytest.raises(GlossrtError, match="sigma_min"):
        bilateral(f, weight="screen", sigma_min=3.0, sigma_s=2.0)
    g = Frame(channels=dict(f.channels), camera=None)
    with pytest.raises(FrameError, match="camera"):
        bilateral(g, weight="screen", radius=1)


def test_exact_lobe_weight_without_depth_weight_runs():
    """``approx=False`` with ``sigma_z2=None``: the screen weight alone is a Python number
    before the exact lobe weight multiplies it (regression: exp_weight once rejected it)."""
    from glossrt import render, scenes

    frame = render.Renderer(scenes.load("roughness-map", size=(16, 12))).render(0)
    a = bilateral(frame, weight="lobe", approx=False, sigma_z2=None, radius=2)
    b = bilateral(frame, weight="lobe", approx=True, sigma_z2=None, radius=2)
    a, b = np.asarray(a), np.asarray(b)
    assert np.all(np.isfinite(a)) and a.shape == (12, 16, 3)
    # eq. 6 exact vs eq. 7 approximate lobe weights: close, not identical
    assert np.abs(a - b).max() <= 0.1 * max(np.abs(b).max(), 1e-6)
