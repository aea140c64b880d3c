"""The README's viewer screenshot recipe (scripts/screenshot.py) against a running viewer:
Debian's chromium through Playwright (``executable_path``, nothing downloaded), as in
test_view_browser.py; without chromium or Playwright this file skips."""

from __future__ import annotations

import re
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from browser import needs_chromium

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
SCENE, PIPELINE, SIZE = "polygon-light", "schied2017", (64, 48)
#: the address in the README's lines; the test's viewer serves on a free port instead
README_URL = "http://127.0.0.1:8080/"


pytestmark = needs_chromium


def _recipe() -> tuple[str, str]:
    """The README's two lines: the viewer started in the background, the screenshot."""
    lines = [ln.strip() for block in re.findall(r"```sh\n(.*?)```", README.read_text(), re.S)
             for ln in block.splitlines()]
    shot = [ln for ln in lines if ln.startswith("python scripts/screenshot.py ")]
    assert len(shot) == 1, shot
    view = lines[lines.index(shot[0]) - 1]
    return view, shot[0]


def _colours(img: np.ndarray) -> int:
    return len(np.unique(img.reshape(-1, img.shape[-1]), axis=0))


def test_the_readme_screenshot_recipe_waits_for_a_drawn_frame(tmp_path):
    pytest.importorskip("playwright")
    from PIL import Image

    import glossrt.view as gv

    view, shot = _recipe()
    # the README's viewer is the one opened here
    assert view == f"glossrt view {SCENE} --pipeline {PIPELINE} --size {SIZE[0]}x{SIZE[1]} " \
                   "--port 8080 &", view
    args = shlex.split(shot)
    assert args[:3] == ["python", "scripts/screenshot.py", README_URL], args
    v = gv.open(SCENE, pipeline=PIPELINE, size=SIZE, port=0, captures=tmp_path / "caps",
                verbose=False)
    try:
        assert v.wait(1, timeout=240), v.message
        # the README's line, with this viewer's address and the script by its full path
        cmd = [sys.executable, str(ROOT / args[1]), v.url, *args[3:]]
        run = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=400)
    finally:
        v.stop()
    assert run.returncode == 0, run.stdout + run.stderr
    assert "wrote viewer.png" in run.stdout, run.stdout
    img = np.asarray(Image.open(tmp_path / "viewer.png").convert("RGB"))
    w, h = (int(x) for x in args[args.index("--viewport") + 1].split("x"))
    assert img.shape == (h, w, 3)
    # left of the panel, below the notice, above the axes icon: only the canvas, where a
    # blank page shows one flat grey (3 colours with the light's gizmo line; 2898 drawn)
    region = img[int(0.31 * h):int(0.875 * h), int(0.015 * w):int(0.45 * w)]
    assert _colours(region) > 200 and region.std() > 5.0, (_colours(region), region.std())
