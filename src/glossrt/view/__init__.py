"""Live viewer: watch and steer the frame pipeline in a browser (issue 26).

>>> import glossrt.view                                              # doctest: +SKIP
>>> v = glossrt.view.open("polygon-light", pipeline="full", size=(320, 180))  # doctest: +SKIP
>>> v.url                       # open it; a notebook embeds the handle  # doctest: +SKIP
>>> v.configure(direct="ltc+ratio")                                  # doctest: +SKIP
>>> v.capture()                 # the next frame, every layer, into ./captures  # doctest: +SKIP
>>> v.stop()                                                         # doctest: +SKIP

Built on viser (its websocket server, camera callbacks, GUI widgets and streamed background
images): :mod:`glossrt.view.app` runs the server and the render loop,
:mod:`~glossrt.view.inbox` coalesces the browser's events, :mod:`~glossrt.view.camera`
converts cameras and light gizmos, :mod:`~glossrt.view.layers` turns layers into images.

One viewer runs per process (a second is refused until the first is stopped: two render
loops in one process deadlock in Dr.Jit). Its frames' Dr.Jit work holds :data:`DRJIT_LOCK`;
hold it too for Dr.Jit work of your own while the viewer runs.
"""

from .app import DRJIT_LOCK, Viewer, open, serve

__all__ = ["DRJIT_LOCK", "Viewer", "open", "serve"]
