"""Test set-up: select glossrt's backend once (CPU unless GLOSSRT_DEVICE says otherwise)."""

import os
import sys

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


#: tests whose pytest-xdist worker crashed once (see pytest_handlecrashitem)
_CRASHED: set[str] = set()


@pytest.hookimpl(optionalhook=True)
def pytest_handlecrashitem(crashitem, report, sched):
    """pytest-xdist (``make test``'s default, two workers): a test whose worker process
    died is run once more on a fresh worker, loudly; a second crash of the same test fails
    it (the safety net of scripts/run-tests.sh, per test)."""
    if crashitem in _CRASHED:
        return
    _CRASHED.add(crashitem)
    sys.stderr.write(f"\n!! {report.longrepr}; running it once more\n")
    try:
        sched.mark_test_pending(crashitem)
    except NotImplementedError:
        pass  # --dist loadfile puts the crashed file's unfinished tests back in the queue itself
    report.outcome = "rerun"


def pytest_report_teststatus(report, config):
    if report.outcome == "rerun":
        return "rerun", "R", "RERUN"
    return None
