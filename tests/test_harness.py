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


def test_crashed_workers_rerun_and_the_run_ends(tmp_path):
    """Two workers, one file per worker (make test's ``--dist loadfile``): a worker killed
    in the middle of a file, and one killed on a one-test file after it has finished
    others, each test runs once more and the run ends with everything passed. Without
    crash_rerun's scheduler, pytest-xdist 3.8.0 hangs here with both workers idle (the
    timeout below then fails the test)."""
    for name, n in (("a", 4), ("c", 1), ("d", 2), ("e", 1), ("f", 3)):
        body = "".join(f"\ndef test_{k}():\n    pass\n" for k in range(n))
        (tmp_path / f"test_{name}.py").write_text(body)
    (tmp_path / "test_b.py").write_text(
        "\ndef test_0():\n    pass\n" + textwrap.dedent(_CRASH_ONCE.format(name="b_mid"))
        + "\ndef test_2():\n    pass\n")
    (tmp_path / "test_z.py").write_text(textwrap.dedent(_CRASH_ONCE.format(name="z_only")))
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(TESTS)] + ([os.environ["PYTHONPATH"]] if os.environ.get("PYTHONPATH") else []))}
    run = subprocess.Popen(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-p", "crash_rerun",
         "-n", "2", "--dist", "loadfile", "--max-worker-restart", "3", str(tmp_path)],
        cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        start_new_session=True)
    try:
        out, _ = run.communicate(timeout=120)
    except subprocess.TimeoutExpired:
        os.killpg(run.pid, signal.SIGKILL)  # the workers too
        out, _ = run.communicate()
        pytest.fail(f"the run hung after a worker crash:\n{out}")
    assert run.returncode == 0, out
    assert "15 passed, 2 rerun" in out, out
    assert out.count("running it once more") == 2, out
