"""Test set-up: select glossrt's backend once (CPU unless GLOSSRT_DEVICE says otherwise);
point the user's cache folder (``XDG_CACHE_HOME``: built BSPVT trees,
glossrt.pipeline.stages.default_bspvt_cache) at a temporary folder of this test process,
removed at exit, so that no test reads or writes the real one (subprocesses inherit it)."""

import atexit
import os
import shutil
import tempfile

import pytest

os.environ.setdefault("GLOSSRT_DEVICE", "auto")
USER_CACHE = tempfile.mkdtemp(prefix="glossrt-test-cache-")
os.environ["XDG_CACHE_HOME"] = USER_CACHE
atexit.register(shutil.rmtree, USER_CACHE, True)

from glossrt import backend  # noqa: E402

VARIANT = backend.use()


#: whole files in the slow tier (docs/TESTING.md; `make check` runs ``-m "not slow"``): the
#: ones that start processes (CLI runs, Ray, viewers, browsers), render end to end or at paper
#: scale; single heavy tests elsewhere carry ``@pytest.mark.slow`` themselves
SLOW_FILES = frozenset({
    "test_any_scene.py", "test_bspvt_cache.py", "test_bspvt_paper_scale.py", "test_cli.py",
    "test_cluster.py", "test_cluster_builds.py", "test_cluster_docs.py", "test_cluster_gpus.py",
    "test_cluster_scenes.py", "test_experiment_cluster.py", "test_fig7_upsampling.py",
    "test_harness.py", "test_import_side_effects.py", "test_lobes_paper_scale.py",
    "test_pipeline_experiment.py", "test_readme.py", "test_references_cache.py",
    "test_screenshot.py", "test_specaa_paper_scale.py", "test_view.py", "test_view_browser.py",
    "test_view_meter.py", "test_view_start.py", "test_view_stop.py", "test_view_unit.py",
})


def pytest_collection_modifyitems(config, items):
    slow = pytest.mark.slow
    for item in items:
        if item.path.name in SLOW_FILES:
            item.add_marker(slow)
    if VARIANT == backend.GPU_VARIANT:
        return
    skip = pytest.mark.skip(reason="needs a CUDA device")
    for item in items:
        if "gpu" in item.keywords:
            item.add_marker(skip)


# make test's crash handling (a plugin module of its own, so that tests/test_harness.py can
# load it into a scratch run: ``-p crash_rerun``)
from crash_rerun import (  # noqa: E402, F401
    pytest_handlecrashitem,
    pytest_report_teststatus,
    pytest_runtest_logreport,
    pytest_runtest_logstart,
    pytest_sessionfinish,
    pytest_terminal_summary,
    pytest_xdist_make_scheduler,
)
