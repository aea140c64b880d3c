"""Spherical Gaussians and the lobe-aware weight (glossrt.brdf.sg, Tokuyoshi 2015) checked
against independent float64 NumPy quadrature on the sphere / the line."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from glossrt.brdf import sg

mi = sg.mi
dr = sg.dr


# ------------------------------------------------------------------------------ helpers


def _v(a) -> mi.Vector3f:
    a = np.atleast_2d(np.asarray(a, dtype=np.float64))
    return mi.Vector3f(mi.Float(a[:, 0]), mi.Float(a[:, 1]), mi.Float(a[:, 2]))


def _f(x) -> mi.Float:
    return mi.Float(np.atleast_1d(np.asarray(x, dtype=np.float64)))


def _np(x) -> np.ndarray:
    return np.asarray(x, dtype=np.float64)


def _dir(theta, phi=0.0) -> np.ndarray:
    return np.array([math.sin(theta) * math.cos(phi), math.sin(theta) * math.sin(phi),
                     math.cos(theta)])


def _frame(p):
    p = np.asarray(p, float) / np.linalg.norm(p)
    a = np.array([1.0, 0.0, 0.0]) if abs(p[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    t = np.cross(p, a)
    t /= np.linalg.norm(t)
    return t, np.cross(p, t), p


def sphere_quad(f, pole, n_phi=1024, order=12):
    """Integral of ``f(w)`` (w: (..., 3) array) over the sphere: polar angle from ``pole`` with
    composite Gauss-Legendre panels on a geometric grid (dense near the pole, where the sharp
    lobes sit), uniform trapezoid in azimuth (spectrally accurate for periodic integrands)."""
    edges = np.concatenate([[0.0], np.geomspace(1e-4, math.pi, 48)])
    x, wg = np.polynomial.legendre.leggauss(order)
    th, wt = [], []
    for a, b in zip(edges[:-1], edges[1:], strict=True):
        th.append(0.5 * (b - a) * x + 0.5 * (a + b))
        wt.append(0.5 * (b - a) * wg)
    th, wt = np.concatenate(th), np.concatenate(wt)
    phi = (np.arange(n_phi) + 0.5) * (2.0 * math.pi / n_phi)
    t, b, p = _frame(pole)
    st_, ct = np.sin(th)[:, None], np.cos(th)[:, None]
    w = (st_ * np.cos(phi))[..., None] * t + (st_ * np.sin(phi))[..., None] * b + ct[..., None] * p
    vals = f(w)
    return float(np.sum(vals * (wt * np.sin(th))[:, None]) * (2.0 * math.pi / n_phi))


def sg_np(w, xi, lam):
    return np.exp(lam * (w @ np.asarray(xi, float) - 1.0))


# ------------------------------------------------------------------------------ SG integrals


@pytest.mark.parametrize("lam", [0.0, 1e-6, 0.05, 0.5, 3.0, 40.0, 1000.0])
def test_sg_integral_vs_quadrature(lam):
    xi = _dir(0.3, 1.0)
    ref = sphere_quad(lambda w: sg_np(w, xi, lam), xi)
    got = _np(sg.sg_integral(_f(lam)))[0]
    assert got == pytest.approx(ref, rel=2e-6)
    assert _np(sg.sg_eval(_v(xi), _v(xi), _f(lam)))[0] == 1.0


PRODUCT_CASES = [  # (lambda_1, lambda_2, angle between axes)
    (0.5, 0.5, 0.0),
    (0.5, 2.0, 1.0),
    (0.0, 5.0, 1.2),
    (1e-6, 1e-6, 2.0),
    (1.0, 1.0, math.pi - 0.01),  # near-antipodal, equal: r -> 0
    (5.0, 5.0, math.pi - 1e-3),
    (20.0, 10.0, math.pi - 0.05),
    (30.0, 30.0, 2.0),
    (1000.0, 0.5, 0.7),
    (1000.0, 1000.0, 0.05),
    (1000.0, 200.0, 0.1),
    (1000.0, 3.0, math.pi - 0.02),
]


@pytest.mark.parametrize("l1,l2,gamma", PRODUCT_CASES)
def test_sg_product_integral_vs_quadrature(l1, l2, gamma):
    xi1, xi2 = _dir(0.4, 0.2), None
    t, b, p = _frame(xi1)
    xi2 = math.cos(gamma) * p + math.sin(gamma) * (0.6 * t + 0.8 * b)
    pole = xi1 if l1 >= l2 else xi2  # centre the grid on the sharper lobe
    if l1 == l2 and gamma < 0.5:
        pole = (xi1 + xi2) / np.linalg.norm(xi1 + xi2)
    ref = sphere_quad(lambda w: sg_np(w, xi1, l1) * sg_np(w, xi2, l2), pole)
    got = _np(sg.sg_product_integral(_v(xi1), _f(l1), _v(xi2), _f(l2)))[0]
    # float32 evaluation; the exponent (up to ~30 here) amplifies rounding
    assert got == pytest.approx(ref, rel=1e-4)
    # swapping the lobes gives the same value
    got2 = _np(sg.sg_product_integral(_v(xi2), _f(l2), _v(xi1), _f(l1)))[0]
    assert got2 == pytest.approx(got, rel=1e-6)


def _approx_rel_error(lams, n=721):
    theta = np.linspace(0.0, math.pi, n)
    xi2 = np.stack([np.sin(theta), np.zeros(n), np.cos(theta)], 1)
    out = {}
    for l1, l2 in lams:
        a, b = _f(np.full(n, l1)), _f(np.full(n, l2))
        ex = _np(sg.sg_product_integral(_v(np.tile([0, 0, 1.0], (n, 1))), a, _v(xi2), b))
        ap = _np(sg.sg_product_integral_approx(_v(np.tile([0, 0, 1.0], (n, 1))), a, _v(xi2), b))
        peak = ex[0]
        rel_peak = np.max(np.abs(ap - ex)) / peak  # error relative to the peak value
        keep = ex > 1e-2 * peak  # where the product integral is non-negligible
        rel = np.max(np.abs(ap[keep] - ex[keep]) / ex[keep])
        out[(l1, l2)] = (rel_peak, rel)
    return out


def test_iwasaki_approximation_good_for_sharp_lobes():
    """Eq. 7 vs eq. 6: the paper says the error shrinks as the sharpnesses grow."""
    errs = _approx_rel_error([(0.5, 0.5), (2.0, 2.0), (10.0, 10.0), (50.0, 50.0),
                              (100.0, 10.0), (1000.0, 1000.0)])
    for (l1, l2), (rel_peak, rel) in errs.items():
        print(f"eq.7 vs eq.6 l1={l1:g} l2={l2:g}: max|err|/peak={rel_peak:.3g} "
              f"max rel (>1% of peak)={rel:.3g}")
    assert errs[(0.5, 0.5)][0] > 0.1  # poor for broad lobes
    assert errs[(10.0, 10.0)][0] < 2e-2
    assert errs[(50.0, 50.0)][0] < 3e-3 and errs[(50.0, 50.0)][1] < 0.1
    assert errs[(1000.0, 1000.0)][0] < 2e-4 and errs[(1000.0, 1000.0)][1] < 5e-3
    order = [errs[k][0] for k in [(0.5, 0.5), (2.0, 2.0), (10.0, 10.0), (50.0, 50.0)]]
    assert all(x > y for x, y in zip(order, order[1:], strict=False))


# ------------------------------------------------------------------------------ lobes


def _ggx_d_ratio(cos_h, alpha):
    """GGX D(h) / D(n) (Walter et al. 2007, eq. 33)."""
    c2 = cos_h**2
    t2 = (1.0 - c2) / c2
    return 1.0 / (c2 * c2 * (1.0 + t2 / alpha**2) ** 2)


def _beckmann_d_ratio(cos_h, alpha):
    c2 = cos_h**2
    return np.exp(-(1.0 - c2) / c2 / alpha**2) / (c2 * c2)


def _lobe_curvatures(ratio_fn, wo, alpha, delta):
    """In-plane and out-of-plane curvature ``-2 ln(D(h)/D(n)) / delta^2`` of the reflected
    lobe at angle ``delta`` from the mirror direction (n = z)."""
    n = np.array([0.0, 0.0, 1.0])
    r = 2.0 * wo @ n * n - wo
    e_perp = np.cross(n, r)
    e_perp = e_perp / np.linalg.norm(e_perp) if np.linalg.norm(e_perp) > 0 else np.array(
        [0.0, 1.0, 0.0])
    e_par = np.cross(e_perp, r)
    out = []
    for e in (e_par, e_perp):
        vals = []
        for sgn in (1.0, -1.0):
            wi = math.cos(delta) * r + sgn * math.sin(delta) * e
            h = (wo + wi) / np.linalg.norm(wo + wi)
            vals.append(-2.0 * math.log(ratio_fn(h @ n, alpha)) / delta**2)
        out.append(0.5 * sum(vals))
    return out


@pytest.mark.parametrize("theta_o", [0.0, 0.5, 1.0, 1.3])
@pytest.mark.parametrize("alpha", [0.01, 0.05])
def test_lobe_sg_matches_microfacet_lobe_curvature(theta_o, alpha):
    """The isotropic SG's sharpness equals the geometric mean of the reflected NDF lobe's
    curvatures (the Jacobian 1/(4 |n.wo|) is their product); Beckmann with lambda_h = 2/a^2
    (Wang et al. 2009) and GGX with the peak-matching 4/a^2 match it to O(delta, alpha^2);
    the default (Wang) GGX SG is exactly half as sharp as the GGX peak."""
    wo = _dir(theta_o, 0.3)
    delta = 1e-3 * alpha
    n = _v([0, 0, 1.0])
    kb = _lobe_curvatures(_beckmann_d_ratio, wo, alpha, delta)
    kg = _lobe_curvatures(_ggx_d_ratio, wo, alpha, delta)
    ax, lb = sg.beckmann_lobe_to_sg(n, _v(wo), _f(alpha))
    _, lg_peak = sg.ggx_lobe_to_sg(n, _v(wo), _f(alpha), sg.GGX_SG_PEAK)
    _, lg = sg.ggx_lobe_to_sg(n, _v(wo), _f(alpha))
    tol = 1e-2 + 2 * alpha**2
    assert _np(lb)[0] == pytest.approx(math.sqrt(kb[0] * kb[1]), rel=tol)
    assert _np(lg_peak)[0] == pytest.approx(math.sqrt(kg[0] * kg[1]), rel=tol)
    assert _np(lg)[0] == pytest.approx(1.0 / (2 * alpha**2 * math.cos(theta_o)), rel=1e-5)
    assert _np(lg)[0] / _np(lg_peak)[0] == pytest.approx(0.5, rel=1e-6)
    r = 2 * wo[2] * np.array([0, 0, 1.0]) - wo
    assert np.allclose(_np(ax)[:, 0], r, atol=1e-6)
    # values at small angles: SG vs the lobe itself, within the anisotropy of the warp
    w_val = math.exp(-0.5 * _np(lg_peak)[0] * (0.3 * alpha) ** 2)
    lo = math.exp(-0.5 * max(kg) * (0.3 * alpha) ** 2)
    hi = math.exp(-0.5 * min(kg) * (0.3 * alpha) ** 2)
    assert lo * 0.999 <= w_val <= hi * 1.001


def test_phong_and_extreme_lobes_finite():
    n = _v([0, 0, 1.0])
    ax, lam = sg.phong_lobe_to_sg(n, _v(_dir(0.7)), _f(64.0))
    assert _np(lam)[0] == 64.0
    wo = _v(np.array([[math.sin(1.5707963), 0, math.cos(1.5707963)], [1.0, 0, 0], [0, 0, 1.0]]))
    for alpha in (0.0, 1e-4, 0.01, 1.0):
        ax, lam = sg.ggx_lobe_to_sg(mi.Vector3f(0, 0, 1), wo, _f(np.full(3, alpha)))
        lam = _np(lam)
        assert np.all(np.isfinite(lam)) and np.all(lam > 0) and np.all(lam <= sg.LAMBDA_MAX)
        assert np.all(np.isfinite(_np(ax)))


# ------------------------------------------------------------------------------ weights


def _rand_dirs(rng, k):
    v = rng.normal(size=(k, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


@pytest.mark.parametrize("approx", [False, True])
def test_weight_identity_symmetry_range(approx):
    rng = np.random.default_rng(1)
    k = 200
    xp, xq = _rand_dirs(rng, k), _rand_dirs(rng, k)
    lp, lq = 10 ** rng.uniform(-3, 6, k), 10 ** rng.uniform(-3, 6, k)
    wpp = _np(sg.lobe_weight(_v(xp), _f(lp), _v(xp), _f(lp), approx=approx))
    assert np.all(wpp == 1.0)
    wpq = _np(sg.lobe_weight(_v(xp), _f(lp), _v(xq), _f(lq), approx=approx))
    wqp = _np(sg.lobe_weight(_v(xq), _f(lq), _v(xp), _f(lp), approx=approx))
    np.testing.assert_allclose(wpq, wqp, rtol=1e-6, atol=1e-30)
    assert np.all((wpq >= 0) & (wpq <= 1))


@pytest.mark.parametrize("approx", [False, True])
@pytest.mark.parametrize("lam", [1.0, 30.0, 1000.0])
def test_weight_decreases_with_angle_and_mismatch(approx, lam):
    theta = np.linspace(0, math.pi, 200)
    xq = np.stack([np.sin(theta), 0 * theta, np.cos(theta)], 1)
    xp = np.tile([0, 0, 1.0], (200, 1))
    w = _np(sg.lobe_weight(_v(xp), _f(np.full(200, lam)), _v(xq), _f(np.full(200, lam)),
                           beta=1.0, approx=approx))
    assert w[0] == 1.0 and np.all(np.diff(w) <= 1e-7)
    assert w[1] < 1.0
    ratio = np.array([1 / 16, 1 / 4, 1 / 2, 1 / 1.2, 1.0, 1.2, 2, 4, 16])
    wm = _np(sg.lobe_weight(_v(np.tile([0, 0, 1.0], (9, 1))), _f(np.full(9, lam)),
                            _v(np.tile([0, 0, 1.0], (9, 1))), _f(lam * ratio), approx=approx))
    assert wm[4] == 1.0
    assert np.all(np.diff(wm[:5]) > 0) and np.all(np.diff(wm[4:]) < 0)


def test_exact_weight_vs_quadrature():
    """q of eqs. 4-5 by quadrature of the normalised smoothed SG lobes (lambda_bar)."""
    beta, kappa = 20.0, 100.0
    for lp, lq, gamma in [(5.0, 8.0, 0.2), (50.0, 300.0, 0.05), (0.7, 2.0, 0.9)]:
        a, b = lp * kappa / (lp + kappa), lq * kappa / (lq + kappa)
        xp, xq = _dir(0.0), _dir(gamma)
        pole = xp if a > b else xq
        ipq = sphere_quad(lambda w, xp=xp, a=a, xq=xq, b=b: sg_np(w, xp, a) * sg_np(w, xq, b),
                          pole)
        ipp = sphere_quad(lambda w, xp=xp, a=a: sg_np(w, xp, a) ** 2, xp)
        iqq = sphere_quad(lambda w, xq=xq, b=b: sg_np(w, xq, b) ** 2, xq)
        ref = (ipq / math.sqrt(ipp * iqq)) ** beta
        got = _np(sg.lobe_weight(_v(xp), _f(lp), _v(xq), _f(lq), beta, kappa))[0]
        assert got == pytest.approx(ref, rel=1e-4, abs=1e-12)
        apx = _np(sg.lobe_weight(_v(xp), _f(lp), _v(xq), _f(lq), beta, kappa, approx=True))[0]
        if min(a, b) > 20:
            assert apx == pytest.approx(ref, rel=0.1)


_dirs = st.tuples(*[st.floats(-1, 1)] * 3).filter(lambda v: 0.1 < sum(x * x for x in v))


@pytest.mark.slow
@settings(max_examples=60, deadline=None)
@given(
    xp=_dirs, xq=_dirs,
    lp=st.floats(0.0, 1e12), lq=st.floats(0.0, 1e12),
    alpha=st.floats(0.0, 1.0), cos_o=st.floats(-1.0, 1.0),
    beta=st.floats(0.1, 100.0), kappa=st.floats(1e-3, 1e6),
)
def test_no_nan_for_extreme_inputs(xp, xq, lp, lq, alpha, cos_o, beta, kappa):
    xp = np.asarray(xp) / np.linalg.norm(xp)
    xq = np.asarray(xq) / np.linalg.norm(xq)
    xs = [_v(xp), _v(xq)]
    vals = [sg.sg_eval(xs[0], xs[1], _f(lp)), sg.sg_integral(_f(lp)),
            sg.sg_product_integral(xs[0], _f(lp), xs[1], _f(lq)),
            sg.sg_product_integral_approx(xs[0], _f(lp), xs[1], _f(lq))]
    for approx in (False, True):
        w = sg.lobe_weight(xs[0], _f(lp), xs[1], _f(lq), beta, kappa, approx=approx)
        assert 0.0 <= _np(w)[0] <= 1.0
        vals.append(w)
    wo = np.array([math.sqrt(max(1 - cos_o**2, 0.0)), 0.0, cos_o])
    ax, lam = sg.ggx_lobe_to_sg(mi.Vector3f(0, 0, 1), _v(wo), _f(alpha))
    vals += [ax, lam, sg.gaussian_weight(_f(lp), _f(lq), _f(0.0), _f(lq + 1), beta, kappa)]
    for v in vals:
        assert np.all(np.isfinite(_np(v)))


# ------------------------------------------------------------------------------ Gaussian variant


def _q_1d_numeric(mu_p, var_p, mu_q, var_q, v2):
    """Eqs. 3-5 by direct numerical integration on a 1-D grid: c = a * b (discrete
    convolution), p = c / ||c||, q = <p_p, p_q>."""
    x = np.linspace(-30.0, 30.0, 6001)
    dx = x[1] - x[0]

    def smooth(mu, var):
        a = np.exp(-((x - mu) ** 2) / (2 * var)) if var > 0 else (np.abs(x - mu) < dx / 2) / dx
        if v2 == 0:
            return a
        k = np.exp(-(x**2) / (2 * v2))
        return np.convolve(a, k, mode="same") * dx  # eq. 3

    cp, cq = smooth(mu_p, var_p), smooth(mu_q, var_q)
    pp = cp / math.sqrt(np.sum(cp**2) * dx)  # eq. 4
    pq = cq / math.sqrt(np.sum(cq**2) * dx)
    return float(np.sum(pp * pq) * dx)  # eq. 5


@pytest.mark.parametrize("mu_p,var_p,mu_q,var_q,kappa",
                         [(0.0, 1.0, 0.5, 2.0, 100.0), (0.3, 0.2, -0.4, 0.05, 4.0),
                          (1.0, 0.0, 1.2, 0.5, 2.0), (0.0, 1.5, 0.0, 1.5, 10.0),
                          (0.0, 0.5, 2.0, 3.0, None)])
def test_gaussian_weight_vs_numeric(mu_p, var_p, mu_q, var_q, kappa):
    beta = 3.0
    v2 = 0.0 if kappa is None else 1.0 / kappa
    q1 = _q_1d_numeric(mu_p, var_p, mu_q, var_q, v2)
    got1 = sg.gaussian_weight(mu_p, var_p, mu_q, var_q, beta, kappa)  # Python floats
    assert got1 == pytest.approx(q1**beta, rel=1e-4)
    gotf = _np(sg.gaussian_weight(_f(mu_p), _f(var_p), _f(mu_q), _f(var_q), beta, kappa))[0]
    assert gotf == pytest.approx(q1**beta, rel=1e-4)
    # 2-D isotropic Gaussians factorise: q_2d = q_1d(dx) q_1d(dy = 0)
    q0 = _q_1d_numeric(0.0, var_p, 0.0, var_q, v2)
    got2 = sg.gaussian_weight(mu_p, var_p, mu_q, var_q, beta, kappa, dim=2)
    assert got2 == pytest.approx((q1 * q0) ** beta, rel=1e-4)
    # ... which is the paper's printed formula (sec. 3, fig. 2)
    tp, tq = var_p + v2, var_q + v2
    paper = (2 * math.sqrt(tp * tq) / (tp + tq)) ** beta * math.exp(
        -((mu_p - mu_q) ** 2) / (2 * (tp + tq) / beta))
    assert got2 == pytest.approx(paper, rel=1e-9)


# ------------------------------------------------------------------------------ figure


def test_plot_fig3_writes_png(tmp_path):
    from glossrt.report.figures import fig3_curves, plot_fig3

    out = plot_fig3(tmp_path / "fig3.png")
    data = out.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 5000
    theta, curves = fig3_curves((0.5, 32.0), n=91)
    ex, ap = curves[32.0]
    assert ex[0] == 1.0 and ap[0] == 1.0 and np.max(np.abs(ex - ap)) < 0.02
    ex, ap = curves[0.5]
    assert np.max(np.abs(ex - ap)) > 0.05  # the approximation is poor for broad lobes


def _tap_weight(xp, lbp, xq, lbq, beta):
    """The filters' per-tap lobe weight from lambda_bar values (float64 NumPy out)."""
    y_pow, a_g = sg.lobe_tap_terms(_v(xp), sg.lobe_tap_sharpness(_f(lbp), beta), _v(xq),
                                   sg.lobe_tap_sharpness(_f(lbq), beta), beta)
    return np.exp(_np(sg.lobe_tap_log_scale(beta))) * _np(y_pow) * np.exp(-_np(a_g)), a_g


@pytest.mark.parametrize("beta", [20.0, 7.3, 1.0, "opaque"])
def test_lobe_tap_terms_match_the_closed_form(beta):
    """The per-tap form used by the filters (y^(beta/2) by repeated squaring for integer
    beta/2, the constant 4^(beta/2) apart) against the sec. 4.2 closed form in float64, and
    against lobe_weight(approx=True); an opaque Dr.Jit beta takes the exp/log path."""
    rng = np.random.default_rng(7)
    k = 300
    xp, xq = _rand_dirs(rng, k), _rand_dirs(rng, k)
    xq[:100] = xp[:100] + 0.05 * rng.normal(size=(100, 3))  # near neighbours: weights ~ 1
    xq /= np.linalg.norm(xq, axis=1, keepdims=True)
    lp, lq = 10 ** rng.uniform(-1, 5, k), 10 ** rng.uniform(-1, 5, k)
    kappa = 100.0
    a, b = lp * kappa / (lp + kappa), lq * kappa / (lq + kappa)
    cos = np.sum(xp * xq, 1)
    b_np = 12.0 if beta == "opaque" else beta
    b_dr = dr.opaque(mi.Float, 12.0) if beta == "opaque" else beta
    want = (2 * np.sqrt(a * b) / (a + b)) ** b_np * np.exp(b_np * a * b / (a + b) * (cos - 1))
    got, _ = _tap_weight(xp, _np(sg.smoothed_sharpness(_f(lp), kappa)), xq,
                         _np(sg.smoothed_sharpness(_f(lq), kappa)), b_dr)
    assert np.sum(want > 1e-2) > 20  # the comparison covers weights that matter
    np.testing.assert_allclose(got, want, rtol=2e-4, atol=1e-7)
    full = _np(sg.lobe_weight(_v(xp), _f(lp), _v(xq), _f(lq), b_dr, kappa, approx=True))
    np.testing.assert_allclose(got, full, rtol=2e-4, atol=1e-7)
    same, _ = _tap_weight(xp, a, xp, a, b_dr)  # w(p, p) = 1
    np.testing.assert_allclose(same, 1.0, rtol=2e-5)


def test_lobe_tap_terms_sharp_nearly_equal_lobes():
    """Without smoothing (kappa=None) lambda_bar reaches 1e6 and more for mirror-like pixels;
    the filters' per-tap form must stay accurate for two such lobes a hair apart (a packed
    lambda_bar * axis form, xi_p . v_q - lambda_q, loses it to float32 cancellation)."""
    rng = np.random.default_rng(3)
    k = 200
    xp = _rand_dirs(rng, k)
    xq = xp + 1e-4 * rng.normal(size=(k, 3))
    xq /= np.linalg.norm(xq, axis=1, keepdims=True)
    lp, lq = 10 ** rng.uniform(5, 7, k), 10 ** rng.uniform(5, 7, k)
    beta = 20.0
    # float64 closed form (sec. 4.2); cos - 1 as -|a - b|^2 / 2
    cm1 = -0.5 * np.sum((xp - xq) ** 2, 1)
    want = beta * lp * lq / (lp + lq) * cm1
    _, a_g = _tap_weight(xp, lp, xq, lq, beta)
    np.testing.assert_allclose(-_np(a_g), want, rtol=1e-3, atol=1e-3)
