"""``make test``'s handling of crashed test processes (loaded by tests/conftest.py;
``-p crash_rerun`` with tests/ on the path loads it elsewhere, as tests/test_harness.py
does).

* A test whose pytest-xdist worker died runs once more on a fresh worker, loudly (so the log
  says whether the crash repeats), and the ``--dist loadfile`` scheduler is repaired so that
  a crash cannot leave the run hanging.
* A crash **fails the run** unless the crashed test is in :data:`KNOWN_UPSTREAM`, which names
  a crash shown to be an upstream bug (with a minimal reproduction in docs/ARCHITECTURE.md,
  "Crashed tests"). The end of the run prints how many tests crashed and were rerun.
* ``GLOSSRT_TEST_KNOWN_CRASHES`` (comma-separated node ids) adds to the list; only
  tests/test_harness.py uses it, on its scratch suite.
"""

import os
import sys

import pytest

#: crashes shown to be upstream's: test node id -> the upstream bug and where its minimal
#: reproduction is written down. Empty: no crash seen in this suite has been reproduced
#: outside glossrt yet (docs/ARCHITECTURE.md, "Crashed tests"), so every crash fails the run.
KNOWN_UPSTREAM: dict[str, str] = {}

#: tests whose pytest-xdist worker crashed once (see pytest_handlecrashitem)
_CRASHED: set[str] = set()


def known_upstream(nodeid: str) -> bool:
    """Whether a crash of ``nodeid`` is a known upstream bug (see :data:`KNOWN_UPSTREAM`)."""
    extra = os.environ.get("GLOSSRT_TEST_KNOWN_CRASHES", "")
    return nodeid in KNOWN_UPSTREAM or nodeid in {s.strip() for s in extra.split(",") if s}


@pytest.hookimpl(optionalhook=True)
def pytest_handlecrashitem(crashitem, report, sched):
    """pytest-xdist (``make test``'s default, two workers): a test whose worker process
    died is run once more on a fresh worker, loudly; a second crash of the same test fails
    it, and :func:`pytest_sessionfinish` fails the run for any crash not known upstream."""
    if crashitem in _CRASHED:
        return
    _CRASHED.add(crashitem)
    sys.stderr.write(f"\n!! {report.longrepr}; running it once more\n")
    try:
        sched.mark_test_pending(crashitem)
    except NotImplementedError:
        pass  # --dist loadfile puts the crashed file's unfinished tests back in the queue itself
    report.outcome = "rerun"


#: scripts/run-tests.sh sets this (one pytest process): a file that records each test started
#: and finished (and each failure), so that after a crash of the whole process the crashed test
#: is known and only the rest of the suite is run again
_PROGRESS = os.environ.get("GLOSSRT_TEST_PROGRESS")


def _progress(line: str) -> None:
    if _PROGRESS:
        with open(_PROGRESS, "a") as f:
            f.write(line + "\n")


def pytest_runtest_logstart(nodeid, location):
    _progress(f"start {nodeid}")  # the last test started and never done is the one that crashed


def pytest_runtest_logreport(report):
    if report.failed:
        _progress(f"FAILED {report.nodeid}")
    if report.when == "teardown":
        _progress(f"done {report.nodeid}")


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    if not _CRASHED:
        return
    tr = terminalreporter
    tr.section("crashed tests", sep="!", red=True)
    tr.line(f"{len(_CRASHED)} test(s) crashed their worker and were rerun:")
    for nodeid in sorted(_CRASHED):
        why = KNOWN_UPSTREAM.get(nodeid, "known upstream crash") if known_upstream(nodeid) \
            else "NOT a known upstream crash: fails the run"
        tr.line(f"  {nodeid}: {why}")


@pytest.hookimpl(trylast=True)
def pytest_sessionfinish(session, exitstatus):
    unknown = sorted(t for t in _CRASHED if not known_upstream(t))
    if unknown and session.exitstatus == 0:
        session.exitstatus = pytest.ExitCode.TESTS_FAILED


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config, log):
    """``--dist loadfile`` (``make test``) with two repairs of pytest-xdist 3.8.0's
    ``LoadFileScheduling`` after a worker crash, without which the run can hang for ever
    with every worker idle (seen once in CI, 2026-12-01, after a crash in test_shadows;
    upstream pytest-xdist issues 1323, 1327 and 1378, fixed after 3.8.0, the newest release
    here): the crashed worker's *finished* files are put back in the queue as empty work
    units that no worker ever reports done, and a replacement worker handed a single test
    waits for a second one or a shutdown that never comes. A third: a replacement worker that
    has not finished collecting is left alone by ``schedule()`` (3.8.0 raised KeyError in the
    controller when another worker's collection arrived first: INTERNALERROR, seen once in a
    loaded run of tests/test_harness.py); and work sent to a worker that died just after
    reporting its last test is left for remove_node to requeue (3.8.0: INTERNALERROR
    "cannot send (already closed?)", seen once in CI)."""
    if config.getvalue("dist") != "loadfile":
        return None
    from xdist.scheduler import LoadFileScheduling

    class CrashSafeLoadFile(LoadFileScheduling):
        def remove_node(self, node):
            workload = self.assigned_work.get(node, {})
            for scope in [s for s, unit in workload.items() if all(unit.values())]:
                del workload[scope]  # finished files stay finished
            return super().remove_node(node)

        def _reschedule(self, node):
            if node not in self.registered_collections:
                # a replacement worker still collecting (another worker's collection can
                # trigger schedule() meanwhile; 3.8.0 then raises KeyError): it is scheduled
                # when its own collection arrives
                return
            try:
                super()._reschedule(node)
                # a worker holding one test runs it only once a second one or a shutdown comes
                if not node.shutting_down and \
                        self._pending_of(self.assigned_work.get(node, {})) == 1:
                    if self.workqueue:
                        self._assign_work_unit(node)
                    else:
                        node.shutdown()
            except OSError:
                # the worker died after reporting its last test (its channel is closed; 3.8.0
                # raised INTERNALERROR): the work just given to it is still recorded as its
                # own, and remove_node puts it back in the queue when the crash is reported
                pass

    return CrashSafeLoadFile(config, log)


def pytest_report_teststatus(report, config):
    if report.outcome == "rerun":
        return "rerun", "R", "RERUN"
    return None
