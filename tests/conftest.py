"""Test set-up: select glossrt's backend once (CPU unless GLOSSRT_DEVICE says otherwise)."""

import os

import pytest

os.environ.setdefault("GLOSSRT_DEVICE", "auto")

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
