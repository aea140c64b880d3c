"""Importing glossrt picks no backend; the first call that needs one does (fresh processes:
this test session's own backend was chosen by conftest.py)."""

import json
import os
import subprocess
import sys

import pytest

WALK = r"""
import importlib, json, pkgutil, sys
import mitsuba
import glossrt
from glossrt import backend

chose = []
names = []
for m in pkgutil.walk_packages(glossrt.__path__, "glossrt."):
    importlib.import_module(m.name)
    names.append(m.name)
    if (backend._current or mitsuba.variant()) and not chose:
        chose.append(m.name)
probes = [hasattr(backend.mi, "__version__"), hasattr(backend.mi, "__wrapped__")]
after_imports = [dict(backend._current), mitsuba.variant(), probes]

from glossrt import scenes
setup = scenes.load("glossy-cornell", size=(16, 12))
print(json.dumps({"modules": names, "chose": chose, "after_imports": after_imports,
                  "after_load": [dict(backend._current), mitsuba.variant()]}))
"""

USE_AFTER_IMPORT = r"""
import json
import numpy as np
from glossrt import backend, render, scenes
from glossrt.backend import mi
import mitsuba

before = [dict(backend._current), mitsuba.variant()]
variant = backend.use("cpu")
setup = scenes.load("glossy-cornell", size=(16, 12))
frame = render.Renderer(setup).render(0)
color = frame.numpy("color")
plugin = mi.load_dict({"type": "glossrt", "max_depth": 2})
image = mi.render(setup.scene, integrator=plugin, spp=1)
print(json.dumps({"before": before, "variant": variant, "mitsuba": mitsuba.variant(),
                  "shape": list(color.shape), "finite": bool(np.isfinite(color).all()),
                  "plugin": str(plugin), "aovs": int(image.shape[2]),
                  "float": mi.Float is mitsuba.Float}))
"""


def _run(code: str, device: str | None) -> dict:
    env = {k: v for k, v in os.environ.items() if k != "GLOSSRT_DEVICE"}
    if device is not None:
        env["GLOSSRT_DEVICE"] = device
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                       timeout=900)
    assert r.returncode == 0, r.stderr[-4000:]
    return json.loads(r.stdout.strip().splitlines()[-1])


@pytest.mark.timeout(1200)
def test_importing_every_module_picks_no_backend_and_the_first_call_does():
    out = _run(WALK, "cpu")
    assert len(out["modules"]) > 40 and "glossrt.render.integrator" in out["modules"]
    assert out["chose"] == [], f"importing {out['chose'][0]} picked a backend"
    assert out["after_imports"] == [{}, None, [False, False]]
    # the first real call chose the variant GLOSSRT_DEVICE asks for
    assert out["after_load"] == [{"device": "cpu", "variant": "llvm_ad_rgb"}, "llvm_ad_rgb"]


@pytest.mark.timeout(1200)
def test_backend_use_after_the_imports_then_render_with_the_plugin_registered():
    out = _run(USE_AFTER_IMPORT, None)
    assert out["before"] == [{}, None]
    assert out["variant"] == out["mitsuba"] == "llvm_ad_rgb"
    assert out["shape"] == [12, 16, 3] and out["finite"]
    # "glossrt" exists in the variant chosen after render.integrator was imported
    assert out["plugin"].startswith("GlossrtIntegrator[max_depth=2, rr_depth=5]")
    assert out["aovs"] > 3 and out["float"]


def test_variant_struct_follows_the_variant(monkeypatch):
    import mitsuba

    from glossrt import backend

    builds = []

    class Table:
        DRJIT_STRUCT = backend.VariantStruct(lambda: builds.append(1) or {"data": mitsuba.Float})

    assert Table.DRJIT_STRUCT is Table().DRJIT_STRUCT
    assert Table.DRJIT_STRUCT == {"data": mitsuba.Float} and len(builds) == 1
    monkeypatch.setitem(backend._current, "variant", "another")  # as use() switching would
    assert Table.DRJIT_STRUCT == {"data": mitsuba.Float} and len(builds) == 2


def test_lazy_mitsuba_keeps_names_until_the_variant_changes():
    import mitsuba

    from glossrt import backend

    mi = backend.mi
    assert mi.Point3f is mitsuba.Point3f and "Point3f" in vars(mi)
    mi._forget()
    assert "Point3f" not in vars(mi) and "__getattr__" in vars(mi)
    assert mi.Point3f is mitsuba.Point3f
    ran = []
    fn = backend.on_variant(lambda: ran.append(mitsuba.variant()))  # one is active: at once
    backend._ON_VARIANT.remove(fn)
    assert ran == [backend.ensure()]
