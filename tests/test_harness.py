"""make test's own machinery: crashed pytest-xdist workers (tests/crash_rerun.py)."""

import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

pytest.importorskip("xdist")

TESTS = Path(__file__).resolve().parent

#: a test that kills its worker the first time it runs (a marker file remembers)
_CRASH_ONCE = '''
def test_{name}():
    import os, signal
    marker = os.path.join(os.path.dirname(__file__), "{name}.crashed")
    if not os.path.exists(marker):
        open(marker, "w").close()
        os.kill(os.getpid(), signal.SIGKILL)
'''


def _scratch_suite(tmp_path):
    """Seven small test files; test_b.py's middle test and test_z.py's only test kill their
    process the first time they run."""
    for name, n in (("a", 4), ("c", 1), ("d", 2), ("e", 1), ("f", 3)):
        body = "".join(f"\ndef test_{k}():\n    pass\n" for k in range(n))
        (tmp_path / f"test_{name}.py").write_text(body)
    (tmp_path / "test_b.py").write_text(
        "\ndef test_0():\n    pass\n" + textwrap.dedent(_CRASH_ONCE.format(name="b_mid"))
        + "\ndef test_2():\n    pass\n")
    (tmp_path / "test_z.py").write_text(textwrap.dedent(_CRASH_ONCE.format(name="z_only")))


def _run(cmd, cwd, known="", **extra_env):
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(TESTS)] + ([os.environ["PYTHONPATH"]] if os.environ.get("PYTHONPATH") else [])),
        "GLOSSRT_TEST_KNOWN_CRASHES": known, **extra_env}
    run = subprocess.Popen(cmd, cwd=cwd, env=env, stdout=subprocess.PIPE,
                           stderr=subprocess.STDOUT, text=True, start_new_session=True)
    try:
        out, _ = run.communicate(timeout=120)
    except subprocess.TimeoutExpired:
        os.killpg(run.pid, signal.SIGKILL)  # the workers too
        out, _ = run.communicate()
        pytest.fail(f"the run hung after a worker crash:\n{out}")
    return run.returncode, out


_XDIST = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-p", "crash_rerun",
          "-n", "2", "--dist", "loadfile", "--max-worker-restart", "3"]


@pytest.mark.parametrize("known", ["", "test_b.py::test_b_mid,test_z.py::test_z_only"])
def test_crashed_workers_rerun_and_the_run_ends(tmp_path, known):
    """Two workers, one file per worker (make test's ``--dist loadfile``): a worker killed
    in the middle of a file, and one killed on a one-test file after it has finished
    others, each test runs once more and the run ends with everything passed. Without
    crash_rerun's scheduler, pytest-xdist 3.8.0 hangs here with both workers idle (the
    timeout in _run then fails the test). The crashes fail the run unless both are declared
    known upstream crashes; either way the end of the run counts them."""
    _scratch_suite(tmp_path)
    rc, out = _run(_XDIST + [str(tmp_path)], tmp_path, known)
    assert "15 passed, 2 rerun" in out, out
    assert out.count("running it once more") == 2, out
    assert "2 test(s) crashed their worker and were rerun" in out, out
    if known:
        assert rc == 0, out
        assert out.count("known upstream crash") == 2 and "NOT" not in out, out
    else:
        assert rc == 1, out
        assert out.count("NOT a known upstream crash") == 2, out


def test_one_known_crash_does_not_excuse_another(tmp_path):
    _scratch_suite(tmp_path)
    rc, out = _run(_XDIST + [str(tmp_path)], tmp_path, "test_z.py::test_z_only")
    assert rc == 1, out
    assert "test_b.py::test_b_mid: NOT a known upstream crash" in out, out


@pytest.mark.parametrize("known", ["", "tests/test_b.py::test_b_mid"])
def test_one_process_crash_fails_unless_known(tmp_path, known):
    """scripts/run-tests.sh with one process: the process dies in test_b.py's middle test,
    the rest of the suite runs again, and the run fails unless that test is known upstream."""
    (tmp_path / "tests").mkdir()
    _scratch_suite(tmp_path / "tests")  # run-tests.sh lists tests/test_*.py from its folder
    (tmp_path / "tests" / "test_z.py").unlink()
    rc, out = _run(["bash", str(TESTS.parent / "scripts" / "run-tests.sh"), sys.executable,
                    "-p", "no:cacheprovider", "-p", "crash_rerun"], tmp_path, known,
                   GLOSSRT_TEST_WORKERS="1")
    assert "pytest was killed by signal 9" in out, out
    assert "tests/test_b.py::test_b_mid" in out, out
    assert rc == (0 if known else 1), out
