"""The layers of docs/ARCHITECTURE.md hold: import-linter's contracts in pyproject.toml.

A module imports only from its own layer or the ones below (top floor: cli, demo, bench;
experiments; report; techniques; scenes/render/brdf; ground floor), each paper's experiment
stands alone, and the papers' techniques do not import each other.
"""

from __future__ import annotations

import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

pytest.importorskip("importlinter")

ROOT = Path(__file__).resolve().parents[1]


def _lint(config: Path, cwd: Path) -> subprocess.CompletedProcess:
    code = "import sys; from importlinter.cli import lint_imports_command; lint_imports_command()"
    return subprocess.run(
        [sys.executable, "-c", code, "--no-cache", str(config)], cwd=cwd, capture_output=True,
        text=True, timeout=300, env={"PYTHONPATH": str(ROOT / "src"), "PATH": "/usr/bin:/bin"})


def test_the_contracts_hold():
    run = _lint(ROOT / "pyproject.toml", ROOT)
    assert run.returncode == 0, run.stdout[-4000:] + run.stderr[-2000:]
    assert "3 kept, 0 broken" in run.stdout, run.stdout[-2000:]


def test_a_reversed_layer_order_is_reported_broken(tmp_path):
    """The same analysis with the layers upside down must fail: the contracts look at real
    imports (the command line does import the experiments, the experiments the techniques)."""
    contracts = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]
    layers = next(c for c in contracts["contracts"] if c["type"] == "layers")["layers"]
    lines = ["[importlinter]", "root_package = glossrt", "",
             "[importlinter:contract:upside-down]", "name = upside down", "type = layers",
             "layers ="] + [f"    {layer}" for layer in reversed(layers)]
    cfg = tmp_path / ".importlinter"
    cfg.write_text("\n".join(lines) + "\n")
    run = _lint(cfg, tmp_path)
    assert run.returncode != 0, run.stdout[-2000:]
    assert "BROKEN" in run.stdout and "glossrt.cli" in run.stdout, run.stdout[-2000:]
