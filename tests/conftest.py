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


def pytest_collection_modifyitems(config, items):
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
