"""The viewer's stop while a frame goes on (issue 26), in a file of its own: it opens viewers
one after another, and a process runs one viewer at a time (tests/test_view.py's module
viewer would refuse them)."""

from __future__ import annotations

import threading
import time
import warnings


def test_a_frame_after_stop_writes_nothing_and_the_next_viewer_opens(tmp_path):
    """``stop`` returns within its timeout while a long frame goes on; when that frame ends,
    the loop must not write to the panel or the scene (viser warns of, and never delivers, a
    message queued after the server stopped: the README test showed that warning). A viewer
    opened right after waits for that frame and renders."""
    import glossrt.view as gv

    v = gv.open("polygon-light", pipeline="schied2017", size=(16, 9), port=0,
                captures=tmp_path / "c", verbose=False)
    try:
        assert v.wait(1, timeout=240), v.message
        rendering, render = threading.Event(), v.pipe.render

        def slow(index):  # a frame longer than stop's timeout
            rendering.set()
            time.sleep(5.0)
            return render(index)

        v.pipe.render = slow
        v.inbox.act("step", 1)  # a change: the loop renders again now
        assert rendering.wait(60)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            t0 = time.monotonic()
            v.stop(timeout=1.0)
            assert time.monotonic() - t0 < 3.0  # (1 s, and a loaded machine's slack)
            assert v._thread.is_alive()  # the frame goes on after stop returned
            w = gv.open("polygon-light", pipeline="schied2017", size=(16, 9), port=0,
                        captures=tmp_path / "c", verbose=False)
            assert not v._thread.is_alive()  # (the new viewer waited for it)
            try:
                assert w.wait(2, timeout=240), w.message
            finally:
                w.stop()
        assert not [m for m in caught if "closed connection" in str(m.message)], \
            [str(m.message) for m in caught]
    finally:
        v.stop()
