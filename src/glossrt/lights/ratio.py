"""Analytic direct light with stochastic shadows by the ratio estimator of Heitz, Hill and
McGuire 2018 ("Combining Analytic Direct Illumination and Stochastic Shadows", I3D 2018;
``glossrt light --method ratio``): a peer of the Monte Carlo reference
(:mod:`glossrt.lights.mc`) and of the unshadowed LTC shading (:mod:`glossrt.lights.ltc`).

The paper's split of the shadowed direct light (``V`` the binary visibility, ``L f cos`` the
unshadowed integrand)::

    int L f cos V dw = int L f cos dw * (int L f cos V dw / int L f cos dw)

is exact whatever computes each factor. Here the first factor (the unshadowed light ``A``)
is analytic, by LTC (:func:`glossrt.lights.ltc.shade.shade_frame`), and the second, the
*illumination-weighted shadow*, is the ratio ``S / U`` of two Monte Carlo estimates made with
the **same** samples: ``S`` with shadow rays, ``U`` without (the paper's ratio estimator).
Both are denoised with the **same** filter weights (the paper filters the two stochastic
images alike, so the ratio of the filtered images is again a ratio of weighted sums of the
same samples) and the result is ``A * S~ / U~``.

glossrt's choices:

* **Same rays, one pass.** :func:`estimate_pair` is :func:`glossrt.lights.mc.estimate`
  (two-strategy MIS, balance heuristic) drawing its random numbers in the same order, but it
  keeps every sample's unshadowed contribution ``u`` and gates a copy by the shadow ray:
  ``s = u V``. So ``S <= U`` sample by sample (the ratio lies in ``[0, 1]`` before any
  clamping), ``S == U`` bit for bit wherever no shadow ray is blocked, and ``S`` / ``U`` are
  what ``render_mc`` gives with / without ``scene`` for the same ``seed`` (up to the float
  rounding of summing diffuse and specular apart). Half the work of two calls.
* **Diffuse and specular apart** (``split=True``, the default): ``A_d S_d / U_d + A_s S_s /
  U_s``. The ratio is visibility weighted by the lobe that integrates it (the paper's
  "illumination-weighted shadow"), and on a glossy surface the two lobes weight the light
  very differently: the cosine lobe sees all of the polygon, a sharp GGX lobe only the part
  around the mirror direction, so an occluder hiding that part darkens the highlight
  (``S_s / U_s ~ 0``) but only some of the diffuse light (``S_d / U_d ~ 0.5``). One mixed
  ratio is exact only in expectation and only if LTC were exact; in practice it moves
  LTC's specular error (LTC is exact for the diffuse term) and each lobe's shadow into the
  other, and after filtering it mixes neighbours whose diffuse / specular proportions
  differ. Split, each ratio is the paper's estimator applied to one integrand, filtered by
  the bilateral filter with that component's albedo demodulation and weights.
  ``split=False`` (one ratio of the sums, filtered without demodulation) is kept for
  comparison.
* **0 / 0.** Where the filtered unshadowed estimate is 0 (no sample of the window reached
  the light: the light is below the horizon, or every sample missed a small or sharply
  reflected light), the ratio is **1**: without any sample there is no evidence of a
  shadow, and the analytic term is then the best estimate (it is exact for an unoccluded
  light, the common case); a ratio of 0 would punch black holes into lit regions wherever
  the few samples missed, i.e. bring the noise back into unshadowed light, which the method
  exists to avoid. As the sample count grows ``U~ > 0`` wherever ``A > 0`` (the MIS
  strategies cover the integrand), so the choice only matters at low sample counts. Where
  ``A`` is 0 as well, the result is 0 either way.
* **Clamp** every ratio to ``[0, 1]`` per channel (it is there already, see above; the clamp
  guards against float rounding in the filter's demodulation).
* **One ratio per light** (``per_light=True``, the default; Heitz, Hill & McGuire 2018,
  sec. 5, multiple lights: ``L = sum_l A_l S_l / U_l``): each light ``l`` gets its own
  analytic term ``A_l`` and its own pair ``S_l`` / ``U_l`` (the same samples: every light
  draws its own light and BRDF sample, as in :func:`glossrt.lights.mc.estimate`), filtered
  alike and divided per light. One ratio shared by all lights, ``(sum_l A_l) (sum_l S_l) /
  (sum_l U_l)``, is right only where every light is shadowed alike, or where each ``A_l``
  equals its ``U_l`` (then the sums cancel); it is wrong wherever the analytic terms err
  differently per light (LTC's specular error, a textured light's prefiltered lookup) and
  wherever the filter averages over pixels whose mix of lights differs (near one light and
  far from another): a light that is hidden then darkens the visible one's contribution, or
  the visible one lightens the hidden one's shadow. ``per_light=False`` (one ratio of the
  sums over lights, per component) is kept for comparison. The cost is one pair of images
  and one filtering per light.

Denoising: :func:`glossrt.denoise.bilateral` (cross-bilateral, weights from the G-buffer
only: screen distance, depth, normals and, with ``weight="lobe"``, the specular lobes), run
on ``S`` and on ``U`` with the same parameters (``filter_params`` are passed through, e.g.
``radius``, ``sigma_s``, ``weight``), so both see identical weights
(:func:`filtered_ratio`).
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from dataclasses import dataclass, field

import drjit as dr
import numpy as np

from ..backend import mi
from ..errors import GlossrtError
from ..frame import RADIANCE, Frame
from .ltc import shade_frame
from .mc import _Light, _spec_weight, _visible, sample_batches, strategies
from .shading import MATERIAL_ROW, ShadingPoints

__all__ = ["COMPONENTS", "RatioImages", "estimate_pair", "filtered_ratio", "render_ratio",
           "stochastic_pair"]

#: the radiance channel each component is filtered as (its albedo demodulates it)
COMPONENTS = {"diffuse": "direct_diffuse", "specular": "direct_specular"}


@dataclass
class Pair:
    """Per-lane shadowed (``s``) and unshadowed (``u``) estimates from the same samples,
    diffuse (``_d``) and specular (``_s``) apart."""

    s_d: mi.Color3f
    s_s: mi.Color3f
    u_d: mi.Color3f
    u_s: mi.Color3f


def estimate_pair(sp: ShadingPoints, lights: list, rng: mi.PCG32, scene=None) -> list[Pair]:
    """One two-strategy MIS sample per lane of the direct light of each of ``lights``
    (``_Light`` objects of :mod:`glossrt.lights.mc`), with and without shadow rays through
    ``scene``, from the same samples (:func:`glossrt.lights.mc.strategies`, the ones
    :func:`glossrt.lights.mc.estimate` draws; ``scene=None``: ``s`` is ``u``): one
    :class:`Pair` per light, in order (sum them for the whole light)."""
    frame = mi.Frame3f(sp.n)
    wo_l = frame.to_local(sp.wo)
    q = _spec_weight(sp)
    out = []
    for lt in lights:
        s1, s2 = strategies(sp, lt, frame, wo_l, q, rng)
        # Veach 1997, balance heuristic: f L / p_l * p_l / (p_l + p_b)
        scale = dr.select(s1.ok, s1.le / s1.denom, 0.0)
        scale2 = dr.select(s2.ok, s2.le / s2.denom, 0.0)
        # Heitz, Hill & McGuire 2018, ratio estimator: the same sample, with and without V
        c_d, c_s = s1.fd * scale, s1.fs * scale
        c_d2, c_s2 = s2.fd * scale2, s2.fs * scale2
        u_d, u_s = c_d + c_d2, c_s + c_s2
        if scene is None:
            out.append(Pair(mi.Color3f(u_d), mi.Color3f(u_s), u_d, u_s))
            continue
        vis = _visible(scene, sp.p, sp.n, s1.y, s1.ok)
        vis2 = _visible(scene, sp.p, sp.n, s2.y, s2.ok)
        s_d = dr.select(vis, c_d, 0.0) + dr.select(vis2, c_d2, 0.0)
        s_s = dr.select(vis, c_s, 0.0) + dr.select(vis2, c_s2, 0.0)
        out.append(Pair(s_d, s_s, u_d, u_s))
    return out


def _check_spp(spp) -> int:
    if isinstance(spp, bool) or not isinstance(spp, int | np.integer) or spp < 1:
        raise GlossrtError(f"spp must be an integer >= 1, got {spp!r}")
    return int(spp)


def _check_f0(frame, f0):
    if f0 is None:
        return None
    try:
        arr = np.asarray(f0, np.float32)
    except (TypeError, ValueError) as e:
        raise GlossrtError(f"f0 must be a numeric (H, W, 3) array: {e}") from e
    wants = [(frame.height, frame.width, c) for c in (3, MATERIAL_ROW)]
    if arr.shape not in wants:
        raise GlossrtError(f"f0 has shape {arr.shape} but the frame needs {wants[0]} "
                           f"({frame.width}x{frame.height} pixels, RGB F0) or {wants[1]} "
                           f"(fresnel_image)")
    if not np.all(np.isfinite(arr)):
        raise GlossrtError("f0 contains NaN or Inf")
    return arr


def _scene_of(scene):
    if scene is None:
        return None
    if hasattr(scene, "ray_test"):
        return scene
    inner = getattr(scene, "scene", None)  # a glossrt SceneSetup
    if inner is not None and hasattr(inner, "ray_test"):
        return inner
    raise GlossrtError(f"scene must be a Mitsuba scene (or a glossrt SceneSetup) for the shadow "
                       f"rays, or None; got {type(scene).__name__}")


def stochastic_pair(frame, lights: list, scene=None, spp: int = 1,
                    f0: np.ndarray | None = None, seed: int = 0,
                    progress: Callable[[int, int], None] | None = None,
                    per_light: bool = False) -> dict | list[dict]:
    """The noisy shadowed and unshadowed Monte Carlo images of ``frame`` from the same
    samples, ``spp`` per pixel (sampled and seeded like :func:`glossrt.lights.mc.render_mc`):
    a dict of (H, W, 3) float32 arrays ``shadowed_diffuse``, ``shadowed_specular``,
    ``unshadowed_diffuse``, ``unshadowed_specular`` for all lights together, or with
    ``per_light=True`` a list of such dicts, one per light (they sum to the former).
    ``scene``: the Mitsuba scene for the shadow rays (``None``: the shadowed images are the
    unshadowed ones)."""
    spp = _check_spp(spp)
    f0 = _check_f0(frame, f0)
    scene = _scene_of(scene)
    h, w = frame.height, frame.width
    lts = [_Light(lt) for lt in lights]
    groups = len(lts) if per_light else 1
    acc = [[dr.zeros(mi.Color3f, w * h) for _ in range(4)] for _ in range(groups)]
    done = 0
    for sp, rng, k in sample_batches(ShadingPoints.of(frame, f0), spp, seed):
        pairs = estimate_pair(sp, lts, rng, scene)
        if not per_light and pairs:
            total = pairs[0]
            for p in pairs[1:]:
                total = Pair(total.s_d + p.s_d, total.s_s + p.s_s, total.u_d + p.u_d,
                             total.u_s + p.u_s)
            pairs = [total] if pairs else []
        for g, pair in enumerate(pairs):
            ests = []
            for s, u in ((pair.s_d, pair.u_d), (pair.s_s, pair.u_s)):
                ok = dr.isfinite(u)  # s is u or 0: drop both together
                ests += [dr.select(ok, s, 0.0), dr.select(ok, u, 0.0)]
            for j, est in enumerate(ests):
                acc[g][j] = acc[g][j] + mi.Color3f(*(dr.block_sum(est[c], k)
                                                     for c in range(3)))
        dr.eval(acc)
        done += k
        if progress is not None:
            progress(done, spp)
    names = ("shadowed_diffuse", "unshadowed_diffuse", "shadowed_specular",
             "unshadowed_specular")
    out = [{name: (np.stack([np.array(a[c]) for c in range(3)], -1) / spp)
            .reshape(h, w, 3).astype(np.float32) for name, a in zip(names, ag, strict=True)}
           for ag in acc]
    return out if per_light else out[0]


def _filter_frame(frame, channel: str, image: np.ndarray, demodulate: bool) -> Frame:
    """A copy of ``frame`` whose only radiance is ``image`` in ``channel`` (the other
    radiance channels zero); ``demodulate=False`` zeroes that channel's albedo, which the
    bilateral filter then leaves out of its demodulation."""
    zeros = np.zeros((frame.height, frame.width, 3), np.float32)
    chans = dict(frame.channels)
    for c in RADIANCE:
        chans[c] = zeros
    chans[channel] = image
    if not demodulate:
        chans["albedo_specular" if channel.endswith("specular") else "albedo_diffuse"] = zeros
    return Frame(channels=chans, camera=frame.camera, prev_camera=frame.prev_camera,
                 index=frame.index, meta=frame.meta, source=frame.source)


def _bilateral_params(filter_params: dict) -> dict:
    from ..denoise.bilateral import bilateral

    allowed = set(inspect.signature(bilateral).parameters) - {"frame", "channels"}
    bad = sorted(set(filter_params) - allowed)
    if bad:
        raise GlossrtError(f"unknown denoiser parameter(s) {', '.join(bad)}; the bilateral "
                           f"filter takes {', '.join(sorted(allowed))}")
    return filter_params


def _safe_ratio(s: np.ndarray, u: np.ndarray) -> np.ndarray:
    """``s / u`` clamped to [0, 1], 1 where ``u`` is 0 (module docstring, "0 / 0")."""
    s64, u64 = np.asarray(s, np.float64), np.asarray(u, np.float64)
    pos = u64 > 0.0
    r = np.ones_like(u64)
    np.divide(s64, u64, out=r, where=pos)
    return np.clip(np.nan_to_num(r, nan=1.0), 0.0, 1.0).astype(np.float32)


def filtered_ratio(frame, shadowed: np.ndarray, unshadowed: np.ndarray,
                   component: str = "diffuse", denoise: bool = True, demodulate: bool = True,
                   **filter_params) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(ratio, S~, U~)``: the shadowed and unshadowed images (H, W, 3) filtered by
    :func:`glossrt.denoise.bilateral` with identical weights (same G-buffer, same
    parameters, filtered as the ``component``'s radiance channel, see :data:`COMPONENTS`)
    and their ratio ``S~ / U~`` (1 where ``U~`` is 0, clamped to [0, 1] per channel).
    ``denoise=False``: the images as they are."""
    if component not in COMPONENTS:
        raise GlossrtError(f"unknown component {component!r}; choose one of "
                           f"{', '.join(COMPONENTS)}")
    want = (frame.height, frame.width, 3)
    imgs = []
    for name, img in (("shadowed", shadowed), ("unshadowed", unshadowed)):
        arr = np.asarray(img, np.float32)
        if arr.shape != want:
            raise GlossrtError(f"{name} image has shape {arr.shape}, the frame needs {want}")
        if not np.all(np.isfinite(arr)):
            raise GlossrtError(f"{name} image contains NaN or Inf")
        imgs.append(arr)
    if denoise:
        from ..denoise.bilateral import bilateral

        params = _bilateral_params(filter_params)
        channel = COMPONENTS[component]
        # Heitz, Hill & McGuire 2018: S and U denoised by the same filter; the bilateral
        # weights depend on the G-buffer only, identical for both
        imgs = [np.array(bilateral(_filter_frame(frame, channel, img, demodulate),
                                   channels=(channel,), **params), np.float32)
                .reshape(want) for img in imgs]
    elif filter_params:
        raise GlossrtError(f"denoiser parameter(s) {', '.join(sorted(filter_params))} given "
                           "with denoise=False")
    s, u = imgs
    # Heitz, Hill & McGuire 2018, ratio estimator: int L f V / int L f ~ S~ / U~
    return _safe_ratio(s, u), s, u


@dataclass
class RatioImages:
    """What :func:`render_ratio` computed, all (H, W, 3) float32: ``image`` the result;
    ``analytic`` the unshadowed LTC image (:func:`glossrt.lights.ltc.shade.shade_frame`),
    ``analytic_diffuse`` / ``analytic_specular`` its two terms; the noisy
    ``shadowed_*`` / ``unshadowed_*`` Monte Carlo estimates (same samples); their filtered
    versions ``shadowed_*_denoised`` / ``unshadowed_*_denoised`` (the noisy ones when
    ``denoise=False``), all summed over the lights, and the ratios ``ratio_diffuse`` /
    ``ratio_specular`` (with ``split=False`` both are the one ratio of the sums, and the
    ``*_diffuse`` estimates hold the sums, the ``*_specular`` ones zeros). With one light (or
    ``per_light=False``) the ratios are the ones applied; with several, each light has its
    own (``per_light``: one dict per light of its ``analytic_*``, ``ratio_*`` and noisy and
    filtered estimates, keyed as here) and ``ratio_*`` is their effective ratio ``sum_l A_l
    r_l / sum_l A_l`` (1 where no light reaches)."""

    image: np.ndarray
    analytic: np.ndarray
    analytic_diffuse: np.ndarray
    analytic_specular: np.ndarray
    shadowed_diffuse: np.ndarray
    shadowed_specular: np.ndarray
    unshadowed_diffuse: np.ndarray
    unshadowed_specular: np.ndarray
    shadowed_diffuse_denoised: np.ndarray
    shadowed_specular_denoised: np.ndarray
    unshadowed_diffuse_denoised: np.ndarray
    unshadowed_specular_denoised: np.ndarray
    ratio_diffuse: np.ndarray
    ratio_specular: np.ndarray
    per_light: list = field(default_factory=list)

    @property
    def shadowed(self) -> np.ndarray:
        """The noisy shadowed Monte Carlo image (diffuse + specular)."""
        return self.shadowed_diffuse + self.shadowed_specular

    @property
    def unshadowed(self) -> np.ndarray:
        """The noisy unshadowed Monte Carlo image (diffuse + specular)."""
        return self.unshadowed_diffuse + self.unshadowed_specular


def _analytic_terms(frame, lights: list, f0, textures: dict | None = None
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(total, diffuse, specular)`` unshadowed LTC images of ``lights``: the specular term
    shaded without diffuse albedo, the diffuse term the rest. ``textures``: the prefiltered
    light textures, kept between calls (:func:`glossrt.lights.ltc.shade.prefiltered`)."""
    total = shade_frame(frame, lights, f0=f0, textures=textures)
    no_diffuse = dict(frame.channels)
    no_diffuse["albedo_diffuse"] = np.zeros((frame.height, frame.width, 3), np.float32)
    a_s = shade_frame(Frame(channels=no_diffuse, camera=frame.camera), lights, f0=f0,
                      textures=textures)
    return total, np.maximum(total - a_s, 0.0), a_s


def _ratios(frame, noisy: dict, split: bool, denoise: bool, filter_params: dict) -> dict:
    """One light group's (or all lights') filtered ratios: ``r_d``, ``r_s`` and the noisy
    and filtered estimates, keyed as in :class:`RatioImages`."""
    zeros = np.zeros_like(noisy["shadowed_diffuse"])
    if split:
        r_d, sd_f, ud_f = filtered_ratio(frame, noisy["shadowed_diffuse"],
                                         noisy["unshadowed_diffuse"], "diffuse", denoise,
                                         **filter_params)
        r_s, ss_f, us_f = filtered_ratio(frame, noisy["shadowed_specular"],
                                         noisy["unshadowed_specular"], "specular", denoise,
                                         **filter_params)
    else:
        noisy = {"shadowed_diffuse": noisy["shadowed_diffuse"] + noisy["shadowed_specular"],
                 "unshadowed_diffuse": noisy["unshadowed_diffuse"]
                 + noisy["unshadowed_specular"],
                 "shadowed_specular": zeros, "unshadowed_specular": zeros}
        r_d, sd_f, ud_f = filtered_ratio(frame, noisy["shadowed_diffuse"],
                                         noisy["unshadowed_diffuse"], "diffuse", denoise,
                                         demodulate=False, **filter_params)
        r_s, ss_f, us_f = r_d, zeros, zeros
    return {**noisy, "shadowed_diffuse_denoised": sd_f, "shadowed_specular_denoised": ss_f,
            "unshadowed_diffuse_denoised": ud_f, "unshadowed_specular_denoised": us_f,
            "ratio_diffuse": r_d, "ratio_specular": r_s}


def render_ratio(frame, lights: list, scene=None, spp: int = 1, f0: np.ndarray | None = None,
                 seed: int = 0, denoise: bool = True, split: bool = True,
                 progress: Callable[[int, int], None] | None = None,
                 per_light: bool = True, textures: dict | None = None,
                 **filter_params) -> RatioImages:
    """Shadowed direct light of ``frame``'s G-buffer from the polygon ``lights`` by the ratio
    estimator (module docstring): unshadowed LTC (:func:`glossrt.lights.ltc.shade.shade_frame`,
    ``f0`` per pixel as there) times the ratio of shadowed to unshadowed Monte Carlo
    estimates from the same ``spp`` samples per pixel (``seed``; shadow rays through
    ``scene``, a Mitsuba scene or SceneSetup, ``None``: no shadows, ratio 1), denoised with
    the same bilateral weights (``denoise``; ``filter_params`` go to
    :func:`glossrt.denoise.bilateral`). ``split``: one ratio per component (diffuse,
    specular; default) or one for their sum. ``per_light``: one ratio per light (default,
    Heitz, Hill & McGuire 2018) or one shared by all lights. ``textures``: a cache
    {id(light texture): PrefilteredTexture} reused across calls (a textured light's
    prefiltered mip chain takes ~0.1-0.7 s to build: without it every call builds each one
    twice per light group). Returns :class:`RatioImages`; the image is ``.image``."""
    spp = _check_spp(spp)
    f0 = _check_f0(frame, f0)
    scene = _scene_of(scene)
    if denoise:
        _bilateral_params(filter_params)
    elif filter_params:
        raise GlossrtError(f"denoiser parameter(s) {', '.join(sorted(filter_params))} given "
                           "with denoise=False")
    # analytic, unshadowed: all lights, then (several lights, one ratio each) light by light
    cache = {} if textures is None else textures  # one build per texture in this call
    total, a_d, a_s = _analytic_terms(frame, lights, f0, cache)
    groups = per_light and len(lights) > 1
    terms = ([_analytic_terms(frame, [lt], f0, cache)[1:] for lt in lights] if groups
             else [(a_d, a_s)])
    noisy = stochastic_pair(frame, lights, scene, spp, f0, seed, progress, per_light=groups)
    noisy = noisy if groups else [noisy]
    parts = [_ratios(frame, nz, split, denoise, filter_params) for nz in noisy]
    # Heitz, Hill & McGuire 2018, sec. 5: L = sum_l A_l S_l / U_l (one ratio per light),
    # shadowed = unshadowed (analytic) x weighted shadow (ratio), written as
    # A - sum_l (A_d,l (1 - r_d,l) + A_s,l (1 - r_s,l)) so that ratio 1 returns A bit for bit
    image = np.array(total, np.float64)
    for (ad, as_), part in zip(terms, parts, strict=True):
        image -= ad * (1.0 - part["ratio_diffuse"]) + as_ * (1.0 - part["ratio_specular"])
    image = np.maximum(image, 0.0).astype(np.float32)
    summed = {k: sum(p[k] for p in parts).astype(np.float32) for k in parts[0]
              if not k.startswith("ratio_")}
    if groups:
        rat = {}
        for comp, k in (("diffuse", 0), ("specular", 1)):
            num = sum(t[k] * p[f"ratio_{comp}"] for t, p in zip(terms, parts, strict=True))
            den = sum(t[k] for t in terms)
            r = np.ones_like(den)
            np.divide(num, den, out=r, where=den > 0)
            rat[f"ratio_{comp}"] = np.clip(r, 0.0, 1.0).astype(np.float32)
        each = [{"analytic_diffuse": t[0].astype(np.float32),
                 "analytic_specular": t[1].astype(np.float32), **p}
                for t, p in zip(terms, parts, strict=True)]
    else:
        rat = {k: parts[0][k] for k in ("ratio_diffuse", "ratio_specular")}
        each = []
    return RatioImages(image=image, analytic=total, analytic_diffuse=a_d.astype(np.float32),
                       analytic_specular=a_s.astype(np.float32), **summed, **rat,
                       per_light=each)
