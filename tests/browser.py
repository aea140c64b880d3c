"""The browser tests' chromium, from one place: scripts/screenshot.py's finder
(``$GLOSSRT_CHROMIUM``, else Debian's chromium) and its flags for a headless machine without a
GPU. Nothing downloads a browser: without one, the browser tests skip."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

_SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "screenshot.py"
_spec = importlib.util.spec_from_file_location("glossrt_screenshot_script", _SCRIPT)
screenshot = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(screenshot)

#: the chromium executable, None when there is none
CHROMIUM: str | None = screenshot.find_chromium()
#: chromium's flags (headless, WebGL through SwiftShader)
ARGS: list[str] = screenshot.ARGS

#: a file's marker: skip it without chromium
needs_chromium = pytest.mark.skipif(CHROMIUM is None,
                                    reason="no chromium (apt-get install chromium)")
