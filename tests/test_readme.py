"""The README's Python examples run as written (in order, in a scratch folder)."""

import os
import re
from pathlib import Path

README = Path(__file__).resolve().parents[1] / "README.md"


def test_readme_python_examples_run(tmp_path, monkeypatch):
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), re.S)
    assert blocks, "README has no Python examples"
    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    exec(compile("\n".join(blocks), str(README), "exec"), namespace)  # noqa: S102
    assert os.path.exists("frame_0000.exr")
    assert namespace["image"].shape == (120, 160, 3)


def _python_blocks() -> str:
    return "\n".join(re.findall(r"```python\n(.*?)```", README.read_text(), re.S))


def test_readme_imports_pick_no_device_and_backend_use_comes_before_the_first_call(tmp_path):
    """Importing what the README imports leaves the device unchosen (backend.use() may come
    after the imports), and the README calls backend.use() before its first scene load."""
    import subprocess
    import sys

    lines = _python_blocks().splitlines()
    first_use = next(k for k, line in enumerate(lines) if "backend.use(" in line)
    first_load = next(k for k, line in enumerate(lines) if "scenes.load(" in line)
    assert first_use < first_load
    imports = [line.split("#")[0].rstrip() for line in lines
               if line.startswith(("from glossrt", "import glossrt"))]
    assert any("render" in line for line in imports) and any("denoise" in line for line in imports)
    check = "\n".join(imports) + (
        "\nimport glossrt.backend, mitsuba\n"
        "print('chosen:', dict(glossrt.backend._current), mitsuba.variant())\n")
    env = {k: v for k, v in os.environ.items() if k != "GLOSSRT_DEVICE"}
    r = subprocess.run([sys.executable, "-c", check], capture_output=True, text=True,
                       cwd=tmp_path, env=env, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "chosen: {} None" in r.stdout, f"the README's imports pick a device: {r.stdout}"


ROOT = README.parent
DOCS = [README, *sorted((ROOT / "docs").glob("*.md"))]


def _repo_files() -> list[str]:
    skip = {".git", ".venv", "__pycache__", ".pytest_cache", ".ruff_cache", ".hypothesis"}
    out = []
    for dirpath, dirnames, filenames in os.walk(ROOT):
        dirnames[:] = [d for d in dirnames if d not in skip and not d.endswith(".egg-info")]
        rel = os.path.relpath(dirpath, ROOT)
        out += [os.path.normpath(os.path.join(rel, f)) for f in filenames]
        out += [os.path.normpath(os.path.join(rel, d)) + "/" for d in dirnames]
    return out


def test_relative_links_in_readme_and_docs_resolve():
    bad = []
    for doc in DOCS:
        for target in re.findall(r"\]\(([^)\s]+)\)", doc.read_text()):
            if re.match(r"[a-z]+:", target) or target.startswith("#"):
                continue  # a web address or an anchor in the same file
            path = (doc.parent / target.split("#")[0]).resolve()
            if not path.exists():
                bad.append(f"{doc.relative_to(ROOT)}: ({target})")
    assert not bad, "links to files that do not exist:\n" + "\n".join(bad)


def test_files_named_in_architecture_exist():
    """docs/ARCHITECTURE.md's map names files and folders (``frame.py``, ``denoise/``,
    ``DRJIT.md``): each must be a file or folder of the repository."""
    files = _repo_files()
    text = (ROOT / "docs" / "ARCHITECTURE.md").read_text()
    names = set(re.findall(r"(?<![\w./-])((?:[\w-]+/)*[\w-]+\.(?:py|md|sh|npz|css|png))\b", text))
    names |= set(re.findall(r"(?<![\w./-])((?:[\w-]+/)*[\w-]+/)(?=[\s,)]|$)", text, re.M))
    assert {"frame.py", "denoise/", "tests/test_distributions.py"} <= names  # the parser works
    missing = sorted(n for n in names if not any(f == n or f.endswith("/" + n) for f in files))
    assert not missing, f"docs/ARCHITECTURE.md names files that do not exist: {missing}"
