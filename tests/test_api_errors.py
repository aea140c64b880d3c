"""The Python API reports bad input as glossrt.errors.GlossrtError with a message that names it
(the CLI prints those as one line), never as a bare ValueError / TypeError / KeyError or an
AttributeError from deep inside."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from glossrt.errors import FrameError, GlossrtError

SRC = Path(__file__).resolve().parents[1] / "src" / "glossrt"

#: raises that are not about the user's input: json's default= hook must raise TypeError, and
#: the teapot's patch orientation is an internal consistency check of shipped data
ALLOWED = {
    ("frame.py", 'raise TypeError(f"object of type {type(o).__name__} is not JSON serialisable")'),
    ("teapot.py", 'raise ValueError(f"teapot patches {p} and {q} cannot be oriented alike")'),
}


def test_no_bare_builtin_errors_in_the_package():
    found = []
    for path in sorted(SRC.rglob("*.py")):
        for k, line in enumerate(path.read_text().splitlines(), 1):
            if re.search(r"\braise (ValueError|TypeError|KeyError)\b", line):
                if (path.name, line.strip()) not in ALLOWED:
                    found.append(f"{path.relative_to(SRC)}:{k}: {line.strip()}")
    assert not found, "raise GlossrtError instead:\n" + "\n".join(found)


def test_glossrt_error_is_still_a_value_error():
    assert issubclass(GlossrtError, ValueError) and issubclass(FrameError, GlossrtError)


def test_user_input_errors_are_glossrt_errors():
    from glossrt.brdf.ggx import grid_nodes
    from glossrt.frame import Camera
    from glossrt.render.pathtracer import resolve_max_depth
    from glossrt.scenes.teapot import teapot_mesh

    with pytest.raises(GlossrtError, match=r"points must have shape \(\.\.\., 3\)"):
        Camera(np.eye(4), 45.0, (8, 6)).project(np.zeros((4, 2)))
    with pytest.raises(GlossrtError, match="at least 2 nodes"):
        grid_nodes(1, 8)
    with pytest.raises(GlossrtError, match="max_depth"):
        resolve_max_depth(0)
    with pytest.raises(GlossrtError, match="n >= 2"):
        teapot_mesh(1)


def test_svgf_given_an_array_says_it_takes_a_frame():
    from glossrt.denoise import SVGF, bilateral

    image = np.zeros((4, 6, 3), np.float32)
    with pytest.raises(GlossrtError, match=r"SVGF takes a glossrt\.Frame .*not ndarray"):
        SVGF()(image)
    with pytest.raises(GlossrtError, match=r"glossrt\.Frame.*not ndarray"):
        bilateral(image)
