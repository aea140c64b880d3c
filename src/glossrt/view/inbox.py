"""What the browser asked for, coalesced (issue 26): the latest value wins, nothing queues.

The viewer's GUI and camera callbacks run on viser's threads; the render loop runs on its
own. They meet here: a callback :meth:`Inbox.post`s a value under a key (``"camera"``, a
pipeline option, ``"transform:<light>"``, ...), overwriting the one not yet taken, and the
loop :meth:`Inbox.take`s everything at the start of a frame. A burst of a thousand camera
events between two frames leaves one camera. Actions that must not merge away (capture,
step) are counted instead.
"""

from __future__ import annotations

import threading
from collections import Counter
from typing import Any


class Inbox:
    """Latest-value-wins mailbox between event threads and the render loop."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._values: dict[str, Any] = {}
        self._actions: Counter[str] = Counter()

    def post(self, key: str, value: Any) -> None:
        """Set ``key`` to ``value``, replacing a value not yet taken."""
        with self._lock:
            self._values[key] = value
            self._wake.set()

    def act(self, action: str, times: int = 1) -> None:
        """Ask for ``action`` (counted: two clicks before a frame are two captures)."""
        with self._lock:
            self._actions[action] += times
            self._wake.set()

    def take(self, timeout: float = 0.0) -> tuple[dict[str, Any], Counter[str]]:
        """Everything posted since the last take, waiting up to ``timeout`` seconds for
        something when there is nothing."""
        if timeout > 0.0:
            self._wake.wait(timeout)
        with self._lock:
            values, actions = self._values, self._actions
            self._values, self._actions = {}, Counter()
            self._wake.clear()
        return values, actions

    def pending(self) -> int:
        """How many keys and actions wait (never more than the distinct keys posted)."""
        with self._lock:
            return len(self._values) + sum(self._actions.values())

    def wake(self) -> None:
        """End a :meth:`take`'s wait early (stopping)."""
        self._wake.set()
