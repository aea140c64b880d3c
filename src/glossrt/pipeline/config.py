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
        if name in ("bspvt_resolution", "ratio_spp", "highlight_samples", "spp",
                    "resample_spp") and value < 1:
            raise GlossrtError(f"pipeline option {name} must be >= 1, got {value}")
        if name == "highlight_probes" and not 1 <= value <= 16:
            raise GlossrtError(f"pipeline option highlight_probes must be in 1..16 (probes "
                               f"along the largest object's side), got {value}")
        return value
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise GlossrtError(f"pipeline option {name} must be a number, got {value!r}")
    value = float(value)
    if name == "resample_threshold" and not 0.0 <= value <= 1.0:
        raise GlossrtError(f"pipeline option resample_threshold must lie in [0, 1], got {value}")
    if name == "svgf_alpha" and not 0.0 < value <= 1.0:
        raise GlossrtError(f"pipeline option svgf_alpha must lie in (0, 1], got {value}")
    if name in FILTER_OPTIONS and name != "svgf_alpha" and not value > 0.0:
        raise GlossrtError(f"pipeline option {name} must be > 0, got {value}")
    if name == "taa_alpha" and not 0.0 < value <= 1.0:
        raise GlossrtError(f"pipeline option taa_alpha must lie in (0, 1], got {value}")
    if value != value or abs(value) == float("inf"):
        raise GlossrtError(f"pipeline option {name} must be finite, got {value}")
    return value


def resolve(preset: str | None = "schied2017", **choices: Any) -> dict[str, Any]:
    """The full option dict of ``preset`` with ``choices`` applied, every name and value
    checked (GlossrtError listing the choices otherwise)."""
    preset = preset or "schied2017"
    if preset not in PRESETS:
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


def parse(spec: str) -> tuple[str, dict[str, Any]]:
    """``--pipeline PRESET|FILE``: a preset name, or a TOML file."""
    if spec in PRESETS:
        return spec, {}
    if spec.endswith(".toml") or os.path.exists(spec):
        return load_toml(spec)
    raise GlossrtError(f"unknown pipeline {spec!r}: not a preset ({', '.join(PRESETS)}) "
                       "and not a .toml file")
