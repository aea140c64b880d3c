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


#: scripts/run-tests.sh sets this: a file that records each finished test (and each failure),
#: so that after a crash of the whole process only the rest of the suite is run again
_PROGRESS = os.environ.get("GLOSSRT_TEST_PROGRESS")


def pytest_runtest_logreport(report):
    if not _PROGRESS:
        return
    lines = []
    if report.failed:
        lines.append(f"FAILED {report.nodeid}")
    if report.when == "teardown":
        lines.append(f"done {report.nodeid}")
    if lines:
        with open(_PROGRESS, "a") as f:
            f.write("".join(line + "\n" for line in lines))


# make test's crash handling under pytest-xdist (a plugin module of its own, so that
# tests/test_harness.py can load it into a scratch run: ``-p crash_rerun``)
from crash_rerun import (  # noqa: E402, F401
    pytest_handlecrashitem,
    pytest_report_teststatus,
    pytest_xdist_make_scheduler,
)
