"""``make test``'s handling of crashed pytest-xdist workers (loaded by tests/conftest.py;
``-p crash_rerun`` with tests/ on the path loads it elsewhere, as tests/test_harness.py
does): a test whose worker died runs once more on a fresh worker, loudly, and the
``--dist loadfile`` scheduler is repaired so that a crash cannot leave the run hanging."""

import sys

import pytest

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


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config, log):
    """``--dist loadfile`` (``make test``) with two repairs of pytest-xdist 3.8.0's
    ``LoadFileScheduling`` after a worker crash, without which the run can hang for ever
    with every worker idle (seen once in CI, 2026-12-01, after a crash in test_shadows;
    upstream pytest-xdist issues 1323, 1327 and 1378, fixed after 3.8.0, the newest release
    here): the crashed worker's *finished* files are put back in the queue as empty work
    units that no worker ever reports done, and a replacement worker handed a single test
    waits for a second one or a shutdown that never comes."""
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
            super()._reschedule(node)
            # a worker holding one test runs it only once a second one or a shutdown comes
            if not node.shutting_down and self._pending_of(self.assigned_work.get(node, {})) == 1:
                if self.workqueue:
                    self._assign_work_unit(node)
                else:
                    node.shutdown()

    return CrashSafeLoadFile(config, log)


def pytest_report_teststatus(report, config):
    if report.outcome == "rerun":
        return "rerun", "R", "RERUN"
    return None
