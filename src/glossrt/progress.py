"""A small progress bar on stderr (no dependency): live on a terminal, a few lines otherwise
(one at each quarter, and one at any update :data:`LINE_EVERY` seconds or more after the
last line)."""

from __future__ import annotations

import contextlib
import sys
import threading
import time
from collections.abc import Callable, Iterator

#: seconds after which a bar off a terminal writes a line at its next update, quarter or not
LINE_EVERY = 3.0

_local = threading.local()


@contextlib.contextmanager
def observe(show: Callable[[str, int, int], None], quiet: bool = False) -> Iterator[None]:
    """Within the block, every :class:`Progress` update made by this thread also calls
    ``show(desc, done, total)`` (a GUI's progress bar); ``quiet``: those bars write nothing to
    their stream. Exceptions of ``show`` are ignored: a display never stops the work."""
    old = getattr(_local, "observer", None)
    _local.observer = (show, quiet)
    try:
        yield
    finally:
        _local.observer = old


class Progress:
    """``with Progress(total, "rendering") as p: p.update(k)`` (k = items done so far)."""

    def __init__(self, total: int, desc: str, enabled: bool = True, stream=None):
        self.total = max(int(total), 1)
        self.desc = desc
        self.stream = stream or sys.stderr
        self.enabled = enabled
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.t0 = time.perf_counter()
        self._last_quarter = -1
        self._last_line = self.t0
        self.done = 0

    def update(self, done: int) -> None:
        self.done = min(int(done), self.total)
        observer = getattr(_local, "observer", None)
        if observer is not None:
            with contextlib.suppress(Exception):
                observer[0](self.desc, self.done, self.total)
            if observer[1]:
                return
        if not self.enabled:
            return
        frac = self.done / self.total
        elapsed = time.perf_counter() - self.t0
        eta = elapsed / frac - elapsed if frac > 0 else float("nan")
        if self.tty:
            bar = "#" * int(30 * frac)
            self.stream.write(
                f"\r{self.desc}: [{bar:<30}] {self.done}/{self.total} "
                f"{elapsed:5.1f}s elapsed, {eta:5.1f}s left"
            )
            self.stream.flush()
        else:
            quarter = int(4 * frac)
            if quarter != self._last_quarter or time.perf_counter() - self._last_line >= LINE_EVERY:
                self._last_quarter = quarter
                self._last_line = time.perf_counter()
                self.stream.write(f"{self.desc}: {self.done}/{self.total} ({elapsed:.1f}s)\n")
                self.stream.flush()

    def __call__(self, done: int, total: int | None = None) -> None:
        self.update(done)

    def close(self) -> None:
        observer = getattr(_local, "observer", None)
        if self.enabled and self.tty and not (observer is not None and observer[1]):
            self.stream.write("\n")
            self.stream.flush()

    def __enter__(self) -> Progress:
        self.update(0)
        return self

    def __exit__(self, *exc) -> None:
        self.close()
