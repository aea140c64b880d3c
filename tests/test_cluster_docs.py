"""docs/CLUSTER.md, run (issue 27): every shell block of the how-to against a Ray cluster of
two nodes on this machine, started by the page's own ``ray start`` commands, and the SLURM
script with stand-ins for ``srun`` / ``scontrol`` / ``sbatch``.

The ``ray start`` lines get ``--block`` and run in a session of their own, so that the test
ends exactly the processes it started (the page's ``ray stop`` would stop every Ray instance
on the machine, other tests' included); at the end no process of those sessions is left.
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("ray")

from glossrt.frame import Frame  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "CLUSTER.md"
SBATCH = ROOT / "scripts" / "slurm" / "glossrt-ray.sbatch"
BIN = Path(sys.executable).parent


def _blocks() -> list[str]:
    return re.findall(r"```bash\n(.*?)```", DOC.read_text(), flags=re.S)


def _role(block: str) -> str:
    if "ray start --head" in block:
        return "head"
    if "ray start --address" in block:
        return "worker"
    if "sbatch" in block:
        return "slurm"
    if block.strip() == "ray stop":
        return "stop"
    if "--cluster local" in block:
        return "local"
    return "driver"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _session(sid: int) -> list[int]:
    """The processes of session ``sid`` (Ray's processes stay in the session of the
    ``ray start`` that started them)."""
    out = []
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                fields = Path(f"/proc/{d}/stat").read_text().rsplit(")", 1)[1].split()
            except (OSError, IndexError):
                continue
            if int(fields[3]) == sid and fields[0] != "Z":
                out.append(int(d))
    return out


def _end(sessions: list[int]) -> None:
    for sid in sessions:
        for pid in _session(sid):
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline and any(_session(s) for s in sessions):
        time.sleep(0.2)


def _wait_log(path: Path, text: str, proc, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if path.exists() and text in path.read_text(errors="replace"):
            return
        if proc.poll() is not None:
            break
        time.sleep(0.25)
    raise AssertionError(f"{path.name}: no {text!r}:\n{path.read_text(errors='replace')[-2000:]}")


def _env(tmp: Path, **extra) -> dict:
    env = dict(os.environ, PATH=f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}",
               HEAD_IP="127.0.0.1", CPUS="1", **extra)
    for k in ("RAY_ADDRESS", "GLOSSRT_CLUSTER"):
        env.pop(k, None)
    return env


def _start(block: str, env: dict, log: Path) -> subprocess.Popen:
    """A head or worker block: its lines as written, ``ray start`` with ``--block`` and in
    a session of its own."""
    lines = [("exec " + ln + " --block") if ln.startswith("ray start") else ln
             for ln in block.strip().splitlines()]
    return subprocess.Popen(["bash", "-ec", "\n".join(lines)], env=env, cwd=log.parent,
                            stdout=log.open("w"), stderr=subprocess.STDOUT,
                            start_new_session=True)


def _run(script: str, env: dict, cwd: Path, timeout: float = 300) -> str:
    r = subprocess.run(["bash", "-ec", script], env=env, cwd=cwd, capture_output=True,
                       text=True, timeout=timeout)
    assert r.returncode == 0, f"{script}\n--- stdout\n{r.stdout[-3000:]}\n--- stderr\n" \
                              f"{r.stderr[-3000:]}"
    return r.stdout + r.stderr


def _frames(folder: Path) -> dict[str, np.ndarray]:
    out = {}
    for p in sorted(folder.glob("*.exr")):
        f = Frame.load(p)
        for k in f.names:
            out[f"{p.name}:{k}"] = f.numpy(k)
    return out


def test_every_command_of_the_cluster_howto(tmp_path):
    roles = [_role(b) for b in _blocks()]
    assert sorted(roles) == sorted(["local", "head", "worker", "driver", "slurm", "stop"]), roles
    blocks = dict(zip(roles, _blocks(), strict=True))
    port = _free_port()
    env = _env(tmp_path, PORT=str(port))
    # one machine: --cluster local:2
    _run(blocks["local"], env, tmp_path)
    head = worker = None
    sessions = []
    try:
        head = _start(blocks["head"], env, tmp_path / "head.log")
        sessions.append(head.pid)
        _wait_log(tmp_path / "head.log", "Ray runtime started", head)
        worker = _start(blocks["worker"], env, tmp_path / "worker.log")
        sessions.append(worker.pid)
        _wait_log(tmp_path / "worker.log", "Ray runtime started", worker)
        out = _run(blocks["driver"], env, tmp_path)
    finally:
        _end(sessions)
    assert not any(_session(s) for s in sessions), "Ray processes left behind"
    # the reference through two Ray nodes: bit-identical to the local cluster's, resumed
    # without new work; the trees, the table and the experiment written
    local = _frames(tmp_path / "refs-local")
    assert len(local) > 0
    for folder in ("refs", "refs-client"):  # as a Ray driver, through Ray Client
        remote = _frames(tmp_path / folder)
        assert local.keys() == remote.keys(), folder
        for k in local:
            assert local[k].tobytes() == remote[k].tobytes(), (folder, k)
    assert "wrote 0 frame(s)" in out and "(2 complete one(s) kept: --resume)" in out, out[-2000:]
    nodes = set(re.findall(r"worker \S+ \(node ([0-9a-f]{8})\) pid", out))
    assert len(nodes) == 2, out[-3000:]  # the blocks ran on both nodes
    assert "wrote 2 frame(s) to refs-client" in out, out[-2000:]
    for f in ("trees.npz", "ltc.npz"):
        assert (tmp_path / f).stat().st_size > 0
    assert any((tmp_path / "exp").iterdir())


def test_the_slurm_script_runs_a_command_on_its_cluster(tmp_path):
    """scripts/slurm/glossrt-ray.sbatch as the page submits it, with stand-ins: ``sbatch``
    runs the script, ``srun`` runs its step's command here, ``scontrol show hostnames``
    names two nodes. The reference it renders is the local cluster's, bit for bit."""
    block = next(b for b in _blocks() if _role(b) == "slurm").strip()
    shims = tmp_path / "shims"
    shims.mkdir()
    (shims / "sbatch").write_text(
        "#!/bin/bash\n# stand-in: drop sbatch's options, run the script here\n"
        "while [[ $1 == -* ]]; do shift; done\nexec bash \"$@\"\n")
    (shims / "srun").write_text(
        "#!/bin/bash\n# stand-in: drop srun's options (-w takes a value), run the command\n"
        "while [[ $1 == -* ]]; do [[ $1 == -w ]] && shift; shift; done\nexec \"$@\"\n")
    (shims / "scontrol").write_text("#!/bin/bash\nprintf 'node1\\nnode2\\n'\n")
    for f in shims.iterdir():
        f.chmod(0o755)
    env = _env(tmp_path, SLURM_JOB_NODELIST="node[1-2]", SLURM_CPUS_PER_TASK="1",
               GLOSSRT_RAY_PORT=str(_free_port()), GLOSSRT_RAY_WAIT="6")
    env["PATH"] = f"{shims}{os.pathsep}{env['PATH']}"
    shutil.copytree(ROOT / "scripts", tmp_path / "scripts")
    proc = subprocess.Popen(["bash", "-ec", block], env=env, cwd=tmp_path,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            start_new_session=True)
    try:
        out, _ = proc.communicate(timeout=300)
    finally:
        _end([proc.pid])
    assert proc.returncode == 0, out[-3000:]
    assert not _session(proc.pid), "Ray processes left behind"
    assert len(set(re.findall(r"worker \S+ \(node ([0-9a-f]{8})\) pid", out))) == 2, out[-3000:]
    env = _env(tmp_path)
    _run(next(b for b in _blocks() if _role(b) == "local"), env, tmp_path)
    local, slurm = _frames(tmp_path / "refs-local"), _frames(tmp_path / "refs-slurm")
    assert len(local) > 0 and local.keys() == slurm.keys()
    for k in local:
        assert local[k].tobytes() == slurm[k].tobytes(), k
