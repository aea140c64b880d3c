"""The pipeline's choices: the stages' options, the presets and TOML descriptions (issue 25).

A pipeline is described by a preset (:data:`PRESETS`) plus stage choices that override it:
``{"direct": "ltc+ratio", "indirect": "svgf-lobe", "taa": True, ...}``. Every name and value
is checked here, before a scene is touched: an unknown option or value is one
:class:`~glossrt.errors.GlossrtError` line listing the choices.

A TOML file describes a pipeline the same way::

    preset = "okuno-iwasaki"      # optional (default schied2017)
    specaa = "avgnormal-eig"      # filtered roughness (glossrt.specaa), default none
    direct = "ltc+ratio"          # any option of OPTIONS, at the top level
    [indirect]                    # or per stage, as a table: method = ... plus its options
    method = "svgf-lobe"
"""

from __future__ import annotations

import os
import tomllib
from collections.abc import Mapping
from typing import Any

from ..errors import GlossrtError

DIRECT = ("pathtraced", "ltc", "ltc+bspvt", "ltc+ratio", "highlights")
INDIRECT = ("svgf", "svgf-lobe", "atrous", "oidn", "none")
TONEMAPS = ("srgb", "filmic")
BSPVT_MODES = ("vertex", "pixel")
#: the path-traced indirect light at full, 1/2 or 1/4 resolution (issue 25), upsampled by
UPSAMPLING = ("joint-bilateral", "spatio-temporal")
UPSAMPLING_WEIGHTS = ("normal", "lobe")
INDIRECT_SCALES = (1, 2, 4)
#: the highlights' microfacet model: Kimura & Tokoi's ellipsoidal NDF (the paper's) or GGX
HIGHLIGHT_DISTRIBUTIONS = ("ellipsoidal", "ggx")
#: the papers' filter parameters (stages.filter_params): SVGF's colour average alpha and
#: edge-stopping sigmas (Schied et al. 2017, secs. 4.1, 4.4), Tokuyoshi 2015's lobe weight
#: beta and kappa (sec. 4.2); a change rebuilds the indirect stage
FILTER_OPTIONS = ("svgf_alpha", "svgf_sigma_z", "svgf_sigma_n", "svgf_sigma_l", "lobe_beta",
                  "lobe_kappa")

#: option -> (allowed values, or a type) ; "auto" of ``direct`` is resolved per scene
OPTIONS: dict[str, Any] = {
    "specaa": str,
    "direct": DIRECT + ("auto",),
    "indirect": INDIRECT,
    "indirect_scale": INDIRECT_SCALES,
    "upsampling": UPSAMPLING,
    "upsampling_weight": UPSAMPLING_WEIGHTS,
    "resample": bool,
    "resample_threshold": float,
    "resample_spp": int,
    "taa": bool,
    "taa_alpha": float,
    "taa_jitter": bool,
    "exposure": float,
    "tonemap": TONEMAPS,
    "bspvt_mode": BSPVT_MODES,
    "bspvt_resolution": int,
    "ratio_spp": int,
    "highlight_samples": int,
    "highlight_probes": int,
    "highlight_distribution": HIGHLIGHT_DISTRIBUTIONS,
    "svgf_alpha": float,
    "svgf_sigma_z": float,
    "svgf_sigma_n": float,
    "svgf_sigma_l": float,
    "lobe_beta": float,
    "lobe_kappa": float,
    "release_memory": bool,
    "accumulate": bool,
    "spp": int,
    "seed": int,
    "max_depth": int,
}

DEFAULTS: dict[str, Any] = {
    "specaa": "none",
    "direct": "pathtraced",
    "indirect": "svgf",
    "indirect_scale": 1,
    "upsampling": "spatio-temporal",
    "upsampling_weight": "lobe",
    "resample": False,
    "resample_threshold": 0.05,
    "resample_spp": 4,
    "taa": False,
    "taa_alpha": 0.1,
    # with taa: the full-resolution primary rays jittered over the pixel (Halton (2, 3), 8
    # frames; glossrt.denoise.taa_jitter), so that TAA resolves geometric edges (Schied 2017,
    # sec. 3: TAA "filters aliasing along the geometric edges" the reconstruction keeps).
    # Off by default: it resolves still edges (docs/RESULTS.md: edge RMSE against the
    # box-filtered image 1.33 against 4.53), but on the animated 1280x720 sequences it did
    # not help (glossy-cornell) or made the frames worse (polygon-light@direct, whose light
    # moves about 20 pixels a frame: RMSE 0.159 against 0.102); the cause is open
    "taa_jitter": False,
    "exposure": 0.0,
    "tonemap": "filmic",
    "bspvt_mode": "vertex",
    "bspvt_resolution": 32,
    "ratio_spp": 1,
    "highlight_samples": 4,
    # light-map probes along the largest object's longest side (direct=highlights; 1: Kimura
    # & Tokoi's one map per object; glossrt.lights.highlights.envmap.probe_grids). On
    # polygon-light's floor the highlights' relative L1 error against a per-pixel reference
    # of the same model is 1.72 (1 probe) / 0.35 (4) / 0.19 (6) / 0.16 (8), for 3 / 19 / 41 /
    # 77 maps (tests/test_pipeline_highlights.py). 4: a frame whose light moved rebuilds
    # 19 maps in about the time the old per-frame rebuild of 3 maps took (~0.1-0.2 s at
    # 96x72, 2-core CPU), a still frame builds none; 6 halves the error again for twice the
    # rebuild
    "highlight_probes": 4,
    "highlight_distribution": "ellipsoidal",
    # the papers' values (denoise.svgf.SVGFParams, denoise.bilateral.BETA / KAPPA)
    "svgf_alpha": 0.2,
    "svgf_sigma_z": 1.0,
    "svgf_sigma_n": 128.0,
    "svgf_sigma_l": 4.0,
    "lobe_beta": 20.0,
    "lobe_kappa": 100.0,
    # hand the blocks Dr.Jit's allocator keeps for reuse back after each stage (and after
    # the low-resolution denoiser): Pipeline.render's docstring
    "release_memory": False,
    "accumulate": False,
    "spp": 1,
    "seed": 0,
    "max_depth": None,
}

#: numeric option -> (lowest, highest, lowest excluded): every value outside is refused before
#: any work. The ends keep each filter's float32 arithmetic finite (tests/test_pipeline_options
#: renders at each end) and bound the work a frame can ask for; more samples come from more
#: frames (``accumulate``), not from one unbounded frame
RANGES: dict[str, tuple[float, float, bool]] = {
    "resample_threshold": (0.0, 1.0, False),
    "resample_spp": (1, 256, False),
    "taa_alpha": (0.0, 1.0, True),
    "exposure": (-20.0, 20.0, False),
    "bspvt_resolution": (1, 128, False),
    "ratio_spp": (1, 256, False),
    "highlight_samples": (1, 64, False),
    "highlight_probes": (1, 16, False),
    "svgf_alpha": (0.0, 1.0, True),
    "svgf_sigma_z": (0.0, 1e4, True),
    "svgf_sigma_n": (0.0, 1e4, True),
    "svgf_sigma_l": (0.0, 1e4, True),
    "lobe_beta": (0.0, 100.0, True),
    "lobe_kappa": (0.0, 1e6, True),
    "spp": (1, 1024, False),
    "seed": (0, 2**32 - 1, False),
    "max_depth": (1, 2**30, False),
}

#: why a range ends where it does, where that is not plain
RANGE_WHY: dict[str, str] = {
    "seed": "frame seeds are 32-bit: larger values would repeat smaller ones",
    "spp": "samples per frame; accumulate=true adds frames for more",
    "bspvt_resolution": "the trees' build time grows with its square: 32 takes about 40 s "
                        "on polygon-light on 2 CPU cores",
    "max_depth": "-1 is no limit",
    "highlight_probes": "light-map probes along the largest object's side",
    "highlight_samples": "each sample is unrolled into the frozen highlight kernel",
    "lobe_beta": "the lobe weight's constant 4^(beta/2) = 2^beta must stay within float32 "
                 "(2^128; measured: 250 gave NaN in 5949 of 9216 values)",
    "lobe_kappa": "measured: 1e30 gave NaN in the composed frame, 1e12 did not",
}

#: one line per option: what it does (``glossrt presets`` prints it with the range and default)
HELP: dict[str, str] = {
    "specaa": "specular antialiasing: filtered roughness at the primary hit (glossrt.specaa)",
    "direct": "direct light: path-traced, LTC, LTC with BSPVT or ratio-estimated shadows, "
              "light-shape highlights; auto: ltc+bspvt where its trees shade something, "
              "else ltc+ratio",
    "indirect": "the reconstruction filter of the 1 spp path-traced light",
    "indirect_scale": "the indirect light traced at 1/1, 1/2 or 1/4 resolution",
    "upsampling": "how the reduced-resolution indirect light is upsampled",
    "upsampling_weight": "the upsampler's weights: normals or Tokuyoshi 2015's lobes",
    "resample": "re-trace the pixels the upsampler cannot fill (adaptive re-sampling)",
    "resample_threshold": "the upsampling weight below which a pixel is re-traced",
    "resample_spp": "samples per re-traced pixel",
    "taa": "temporal antialiasing of the composed frame",
    "taa_alpha": "TAA's exponential average weight of the new frame",
    "taa_jitter": "sub-pixel jitter of the primary rays for TAA",
    "exposure": "exposure in stops before the tonemap",
    "tonemap": "display transform of the composed frame",
    "bspvt_mode": "BSPVT visibility at mesh vertices or per pixel",
    "bspvt_resolution": "the BSPVT trees' cube-map face resolution",
    "ratio_spp": "shadow rays per pixel per light of the ratio estimator",
    "highlight_samples": "samples per pixel of the light-shape highlights",
    "highlight_probes": "light-map probes along the largest object's longest side",
    "highlight_distribution": "the highlights' microfacet distribution",
    "svgf_alpha": "SVGF's temporal average weight of the new frame",
    "svgf_sigma_z": "SVGF's depth edge-stopping sigma",
    "svgf_sigma_n": "SVGF's normal edge-stopping exponent",
    "svgf_sigma_l": "SVGF's luminance edge-stopping sigma",
    "lobe_beta": "Tokuyoshi 2015's lobe-weight exponent beta",
    "lobe_kappa": "Tokuyoshi 2015's lobe-sharpness smoothing kappa",
    "release_memory": "hand Dr.Jit's cached memory back after each stage",
    "accumulate": "average the frames of a still pose (the converged reference)",
    "spp": "samples per pixel per frame when accumulating",
    "seed": "the random seed of the frames",
    "max_depth": "path depth (Mitsuba's convention); unset: the scene's integrator's",
}

#: the presets, named after what they reproduce (issue 25)
PRESETS: dict[str, dict[str, Any]] = {
    # Schied et al. 2017: 1 spp path-traced direct and indirect light, SVGF, TAA
    "schied2017": {"direct": "pathtraced", "indirect": "svgf", "taa": True},
    # Okuno & Iwasaki: LTC with BSPVT shadows for the polygon lights
    "okuno-iwasaki": {"direct": "ltc+bspvt", "indirect": "svgf", "taa": True},
    # Kimura & Tokoi: light shapes in the highlights (specular), LTC diffuse
    "kimura-tokoi": {"direct": "highlights", "indirect": "svgf", "taa": True},
    # Tokuyoshi 2015: the indirect light at 1/2 resolution, filtered with the lobe weights
    # and upsampled spatio-temporally with them (secs. 4.2, 5.3)
    "tokuyoshi2015": {"direct": "pathtraced", "indirect": "svgf-lobe", "taa": False,
                      "indirect_scale": 2, "upsampling": "spatio-temporal",
                      "upsampling_weight": "lobe"},
    # everything but specaa: LTC+BSPVT when the occluders are static, LTC+ratio when one
    # moves; 1/2-resolution indirect light with lobe-aware upsampling and SVGF-lobe. Issue 25
    # puts specaa in too; it stays off (pass specaa="avgnormal-eig") because, measured,
    # avgnormal-eig loses about 70% of the direct light on normal-mapped against the
    # supersampled reference (tests/test_pipeline.py) and the path tracer does not see it
    "full": {"specaa": "none", "direct": "auto", "indirect": "svgf-lobe",
             "taa": True, "indirect_scale": 2, "upsampling": "spatio-temporal",
             "upsampling_weight": "lobe"},
    # progressive accumulation of the converged path-traced frame
    "reference": {"direct": "pathtraced", "indirect": "none", "taa": False,
                  "accumulate": True, "spp": 16},
}

#: what a preset still lacks against issue 25, recorded in the frames' meta
PRESET_NOTES: dict[str, str] = {
    "full": "specaa off by default (avgnormal-eig darkens the direct light on normal-mapped by "
            "about 70% against the supersampled reference); when on, it filters the analytic "
            "shading and the lobe weights, and the path tracer's primary hit keeps the "
            "material roughness",
}


def check_specaa(value: Any) -> str:
    """The ``specaa`` option: ``none`` or a method :func:`glossrt.specaa.parse_method`
    accepts (``:kappa=K`` included) whose roughness is one per pixel (not per light: the
    pipeline's G-buffer has one ``roughness`` channel). Returned as given (stripped)."""
    if not isinstance(value, str):
        raise GlossrtError(f"pipeline option specaa must be a method name, got {value!r}")
    from ..specaa import METHODS, parse_method

    method = parse_method(value)  # GlossrtError listing the methods
    if method.per_light:
        per_pixel = ", ".join(m for m in METHODS if not parse_method(m).per_light)
        raise GlossrtError(f"pipeline option specaa={value!r}: the half-vector methods "
                           "filter per light, but the pipeline's G-buffer holds one "
                           f"roughness per pixel; choose one of {per_pixel} (or "
                           "avgnormal-cov, -bbox; ':kappa=K' allowed)")
    return value.strip()


def _check_value(name: str, value: Any) -> Any:
    kind = OPTIONS[name]
    if value is None and name == "max_depth":
        return None
    if name == "specaa":
        return check_specaa(value)
    if isinstance(kind, tuple):
        if isinstance(value, bool) or value not in kind:
            raise GlossrtError(f"pipeline option {name}={value!r}: choose one of "
                               f"{', '.join(map(str, kind))}")
        return value
    if kind is bool:
        if not isinstance(value, bool):
            raise GlossrtError(f"pipeline option {name} must be true or false, got {value!r}")
        return value
    if kind is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise GlossrtError(f"pipeline option {name} must be an integer, got {value!r}")
    elif isinstance(value, bool) or not isinstance(value, (int, float)):
        raise GlossrtError(f"pipeline option {name} must be a number, got {value!r}")
    else:
        value = float(value)
        if value != value or abs(value) == float("inf"):
            raise GlossrtError(f"pipeline option {name} must be finite, got {value}")
    if name == "max_depth" and value == -1:
        return value  # (Mitsuba's "no limit": Russian roulette ends the paths)
    lo, hi, open_below = RANGES[name]
    if not ((lo < value if open_below else lo <= value) and value <= hi):
        why = f" ({RANGE_WHY[name]})" if name in RANGE_WHY else ""
        raise GlossrtError(f"pipeline option {name} must lie in {range_text(name)}{why}, "
                           f"got {value}")
    return value


def range_text(name: str) -> str:
    """The allowed values of option ``name`` as ``help`` prints them: ``[lo, hi]`` (``(lo,
    hi]`` when ``lo`` itself is not allowed), the choices, or ``true|false``."""
    kind = OPTIONS[name]
    if name == "specaa":
        return "none or a glossrt.specaa method with one roughness per pixel"
    if isinstance(kind, tuple):
        return "|".join(map(str, kind))
    if kind is bool:
        return "true|false"
    lo, hi, open_below = RANGES[name]
    text = f"{'(' if open_below else '['}{_number(lo)}, {_number(hi)}]"
    return f"-1 or {text}" if name == "max_depth" else text


def _number(v: float) -> str:
    return str(v) if isinstance(v, int) else f"{v:g}"


def resolve(preset: str | None = "schied2017", **choices: Any) -> dict[str, Any]:
    """The full option dict of ``preset`` with ``choices`` applied, every name and value
    checked (GlossrtError listing the choices otherwise)."""
    preset = preset or "schied2017"
    if not isinstance(preset, str) or preset not in PRESETS:
        raise GlossrtError(f"unknown pipeline preset {preset!r}; choose one of "
                           f"{', '.join(PRESETS)} (or a .toml file)")
    check_names(choices)
    out = dict(DEFAULTS)
    out.update(PRESETS[preset])
    for k, v in choices.items():
        out[k] = _check_value(k, v)
    out["preset"] = preset
    return out


def check_names(choices: Mapping[str, Any]) -> None:
    unknown = sorted(set(choices) - set(OPTIONS))
    if unknown:
        raise GlossrtError(f"unknown pipeline option(s) {', '.join(unknown)}; the options are "
                           f"{', '.join(OPTIONS)}")


def load_toml(path: str | os.PathLike) -> tuple[str, dict[str, Any]]:
    """``(preset, choices)`` of a TOML pipeline description (module docstring)."""
    try:
        with open(path, "rb") as fh:
            data = tomllib.load(fh)
    except FileNotFoundError:
        raise GlossrtError(f"pipeline file not found: {path}") from None
    except IsADirectoryError:
        raise GlossrtError(f"pipeline file {path} is a folder, not a .toml file") from None
    except OSError as e:
        raise GlossrtError(f"pipeline file {path}: {e.strerror or e}") from None
    except UnicodeDecodeError:
        raise GlossrtError(f"{path}: not a TOML pipeline description (TOML is UTF-8 text; "
                           "this file is not)") from None
    except tomllib.TOMLDecodeError as e:
        raise GlossrtError(f"{path}: not a valid TOML pipeline description ({e})") from None
    preset = data.pop("preset", "schied2017")
    if not isinstance(preset, str):
        raise GlossrtError(f"{path}: preset must be a string, got {preset!r}")
    choices: dict[str, Any] = {}
    for key, value in data.items():
        if isinstance(value, dict):  # [stage] table: method = ..., options
            if key not in ("specaa", "direct", "indirect", "taa", "display"):
                raise GlossrtError(f"{path}: unknown stage table [{key}]; the stages with "
                                   "options are specaa, direct, indirect, taa, display")
            for k, v in value.items():
                if k in ("method", "enabled"):
                    choices[key] = v
                else:
                    choices[k] = v
        else:
            choices[key] = value
    try:
        resolve(preset, **choices)
    except GlossrtError as e:
        raise GlossrtError(f"{path}: {e}") from None
    return preset, choices


def parse(spec: str | os.PathLike | None) -> tuple[str, dict[str, Any]]:
    """``--pipeline PRESET|FILE``: a preset name, or a TOML file (None: the default preset,
    schied2017)."""
    if spec is None:
        return "schied2017", {}
    if not isinstance(spec, (str, os.PathLike)):
        raise GlossrtError(f"pipeline preset must be a preset name ({', '.join(PRESETS)}) or "
                           f"a .toml file, got {type(spec).__name__} {spec!r}")
    spec = os.fspath(spec)
    if spec in PRESETS:
        return spec, {}
    if spec.endswith(".toml") or os.path.exists(spec):
        return load_toml(spec)
    raise GlossrtError(f"unknown pipeline {spec!r}: not a preset ({', '.join(PRESETS)}) "
                       "and not a .toml file")
