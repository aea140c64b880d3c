"""A screenshot of a running ``glossrt view`` page, taken once the viewer has drawn a frame.

    python scripts/screenshot.py URL OUT.png [--viewport 960x540] [--timeout 120]

Opens URL in Debian's chromium (``$GLOSSRT_CHROMIUM``, else ``chromium`` on the PATH),
headless, driven by Playwright's Python package with ``executable_path`` set (nothing is
downloaded), WebGL through SwiftShader. It waits until the page's 3D canvas holds a drawn
frame: it reads the canvas's pixels every half second (viser draws with
``preserveDrawingBuffer``, so ``toDataURL`` returns what is shown) and waits until they hold
at least ``--min-colours`` distinct colours (a canvas before the first frame is one flat
colour, and the light gizmos alone add about 25). Then it writes the whole page (canvas and
panel) as a PNG and prints how long it waited. Exit status 1, and no file, when the page
cannot be opened or no frame was drawn within ``--timeout`` seconds; 2 when the browser or
Playwright is missing.

``chromium --headless --screenshot`` does not do this: it takes its picture after a fixed
budget of virtual time, before the viewer's first frame has come over the websocket, and
shows an empty canvas.
"""

from __future__ import annotations

import argparse
import base64
import io
import os
import shutil
import sys
import time

#: chromium's flags for a headless machine without a GPU (as the browser tests use them)
ARGS = ["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
        "--disable-background-networking", "--disable-component-update", "--no-first-run",
        "--disable-sync", "--disable-quic"]

#: the page's largest canvas (viser's 3D view) as a PNG data URL, or null before it exists
CANVAS_PNG = """() => {
  const cs = [...document.querySelectorAll("canvas")];
  if (!cs.length) return null;
  const c = cs.reduce((a, b) => (a.width * a.height >= b.width * b.height ? a : b));
  return c.width * c.height > 0 ? c.toDataURL("image/png") : null;
}"""


def find_chromium() -> str | None:
    """``$GLOSSRT_CHROMIUM``, else Debian's chromium, else ``chromium`` on the PATH."""
    for b in (os.environ.get("GLOSSRT_CHROMIUM"), "/usr/bin/chromium",
              "/usr/bin/chromium-browser", shutil.which("chromium")):
        if b and os.path.exists(b):
            return b
    return None


def canvas_colours(data_url: str | None) -> int:
    """The number of distinct RGB colours in a canvas's PNG data URL (0 for None)."""
    import numpy as np
    from PIL import Image

    if not data_url:
        return 0
    png = base64.b64decode(data_url.split(",", 1)[1])
    rgb = np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).reshape(-1, 3)
    return len(np.unique(rgb.astype(np.uint32) @ np.array([65536, 256, 1], np.uint32)))


def screenshot(url: str, out: str, viewport: tuple[int, int] = (960, 540),
               timeout: float = 120.0, min_colours: int = 64,
               chromium: str | None = None) -> dict:
    """Open ``url``, wait for a drawn frame, write the page to ``out`` (PNG). Returns
    ``{"seconds": waited, "colours": distinct colours in the canvas}``; raises
    ``TimeoutError`` (nothing written) when no frame was drawn within ``timeout``."""
    from playwright.sync_api import sync_playwright

    exe = chromium or find_chromium()
    if exe is None:
        raise FileNotFoundError("no chromium: apt-get install chromium, or set "
                                "GLOSSRT_CHROMIUM=/path/to/chromium")
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=exe, headless=True, args=ARGS)
        try:
            page = browser.new_page(viewport={"width": viewport[0], "height": viewport[1]})
            t0 = time.monotonic()
            page.goto(url, wait_until="domcontentloaded", timeout=timeout * 1000)
            colours = 0
            while True:
                colours = canvas_colours(page.evaluate(CANVAS_PNG))
                if colours >= min_colours:
                    break
                if time.monotonic() - t0 > timeout:
                    raise TimeoutError(f"no frame drawn in {timeout:g} s: the canvas of {url} "
                                       f"holds {colours} distinct colours (< {min_colours})")
                page.wait_for_timeout(500)
            page.screenshot(path=out)
            return {"seconds": time.monotonic() - t0, "colours": colours}
        finally:
            browser.close()


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WxH, e.g. 960x540, got {text!r}") from None
    if w < 1 or h < 1:
        raise argparse.ArgumentTypeError(f"the viewport must be positive, got {text!r}")
    return w, h


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("url", help="the viewer's address, as glossrt view prints it")
    ap.add_argument("out", help="the PNG to write")
    ap.add_argument("--viewport", type=_size, default=(960, 540),
                    help="the browser page's WxH in pixels (default 960x540; keep the "
                         "render's aspect ratio)")
    ap.add_argument("--timeout", type=float, default=120.0,
                    help="seconds to wait for a drawn frame (default 120)")
    ap.add_argument("--min-colours", type=int, default=64,
                    help="distinct colours that make the canvas count as drawn (default 64)")
    args = ap.parse_args(argv)
    try:
        from playwright.sync_api import Error as PlaywrightError
    except ImportError:
        print("screenshot: needs Playwright's Python package (pip install playwright; no "
              "browser download needed)", file=sys.stderr)
        return 2
    try:
        got = screenshot(args.url, args.out, args.viewport, args.timeout, args.min_colours)
    except PlaywrightError as e:
        print(f"screenshot: {args.url}: {str(e).splitlines()[0]}", file=sys.stderr)
        return 1
    except ImportError:
        print("screenshot: needs Playwright's Python package (pip install playwright; no "
              "browser download needed)", file=sys.stderr)
        return 2
    except FileNotFoundError as e:
        print(f"screenshot: {e}", file=sys.stderr)
        return 2
    except TimeoutError as e:
        print(f"screenshot: {e}", file=sys.stderr)
        return 1
    print(f"wrote {args.out} (the canvas drew a frame of {got['colours']} colours after "
          f"{got['seconds']:.1f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
