"""The live viewer: :class:`Viewer` serves a :class:`glossrt.pipeline.Pipeline` to browsers
through viser (issue 26).

Start-up. What can be checked without work (options, size, captures folder, host and port)
is checked first. The render loop's thread then loads the scene and constructs the pipeline
(BSPVT's trees can take a minute); as soon as the pipeline's own checks have passed (the
scene, a trees file, the options against the scene) the server starts and the URL is known,
while the construction goes on. The panel shows its progress; an error of the construction
is shown there in one line and ends the render loop (:attr:`Viewer.error`). A refusal before
the server starts raises from the constructor.

Threads. viser runs its websocket server and calls the GUI and camera callbacks on its own
threads; those callbacks only post to an :class:`~glossrt.view.inbox.Inbox` (latest value
wins). One render loop, on its own thread, owns every Dr.Jit call after start-up (the
pipeline's construction included): at the start of each frame it takes what was posted,
applies it to the pipeline (a refusal is shown in the panel and the previous state kept),
renders, and broadcasts the chosen layer as a JPEG background image to every connected
client. A client that connects gets the current camera and image; one that leaves changes
nothing. At the interpreter's exit the loop is stopped and waited for (a Dr.Jit call still
running while the interpreter finalizes aborts the process).

Ground truth on pause: after :data:`STILL_FRAMES` frames without a change of camera,
lights, options or animation time, a second pipeline with the ``reference`` preset
accumulates the converged frame of the same pose, :data:`REFERENCE_SPP` samples per pixel
per frame, and the panel shows the live image's RMSE and FLIP against it.

Captures go through :meth:`glossrt.frame.Frame.save` (a temporary file renamed into place)
into the captures folder only; names are made here, never taken from the browser.
"""

from __future__ import annotations

import atexit
import collections
import errno
import math
import os
import re
import sys
import threading
import time
import traceback
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from .. import progress
from ..errors import GlossrtError
from . import layers
from .camera import ViewerCamera, from_pipeline, gizmo_matrix, to_pipeline
from .inbox import Inbox
from .meter import ErrorMeter

#: the stats measured against the reference (ErrorMeter.measure), kept in a capture's meta
ERROR_KEYS = ("rmse", "flip", "flip_spp")
#: frames without any change before the reference starts accumulating
STILL_FRAMES = 2
#: samples per pixel the reference adds per loop iteration, and where it stops
REFERENCE_SPP = 4
REFERENCE_MAX_SPP = 4096
LOOPBACK = ("127.0.0.1", "localhost", "::1")
#: seconds a client's camera reports are ignored from its first report after the viewer set its
#: camera, unless it reports that camera back sooner (see Viewer._send_camera); counted from
#: the first report, not from the send, so that a slow page load does not use the window up
SYNC_SECONDS = 10.0
#: a client camera within this of the viewer's (position relative to the scene's scale;
#: direction, up and fov in radians) is an echo, not a move: a user's drag moves it by far
#: more, and clients report our camera back through float32 and their own orbit maths
ECHO_TOL = 1e-3
_IN_SYNC = object()  # a client absent from Viewer._syncing_clients
#: the viewer's Dr.Jit work in this process: a frame of its render loop, its start-up; hold it
#: for Dr.Jit work of your own while a viewer runs (a thread running frozen kernels holds
#: Dr.Jit's lock and waits for the GIL; another thread's Dr.Jit call waits for that lock with
#: the GIL held: a deadlock, or a crash)
DRJIT_LOCK = threading.RLock()
#: the viewer of this process (one at a time: two render loops deadlocked even with each
#: frame under DRJIT_LOCK, since any thread's freeing of a Dr.Jit array takes Dr.Jit's lock)
_CURRENT: list[Viewer] = []
_CURRENT_LOCK = threading.Lock()


def _claim(viewer: Viewer) -> None:
    """Make ``viewer`` this process' viewer: refused while another one runs; one that was
    stopped may still be finishing a frame, which is waited for."""
    with _CURRENT_LOCK:
        for old in _CURRENT:
            if not old._stop.is_set():
                raise GlossrtError(f"a viewer already runs in this process ({old.url}): stop "
                                   "it first (two render loops in one process deadlock)")
            if old._thread.is_alive():
                old._thread.join()
        _CURRENT[:] = [viewer]
        if not _EXIT_HOOK:
            # threading's exit hooks run before every atexit one (Mitsuba's variant modules
            # register theirs when first imported, maybe later than this, by the loop)
            getattr(threading, "_register_atexit", atexit.register)(_stop_at_exit)
            _EXIT_HOOK.append(True)


#: whether :func:`_stop_at_exit` is registered
_EXIT_HOOK: list[bool] = []


def _stop_at_exit() -> None:
    """At the interpreter's exit, before the atexit hooks (Mitsuba's and Dr.Jit's shutdown
    among them): stop this process' viewer (if it still runs) and wait for its render loop to
    end. ``stop()`` returns within its timeout while a frame (or the pipeline's construction)
    goes on; a Dr.Jit call still running in that thread while the interpreter finalized
    aborted the process ("terminate called without an active exception"), crashed it or hung
    it."""
    with _CURRENT_LOCK:
        viewers = list(_CURRENT)
    for v in viewers:
        v._stop.set()  # (the loop's panel writes end; viser's own exit hook stops its server)
        inbox = getattr(v, "inbox", None)
        if inbox is not None:
            inbox.wake()
        if v._thread.is_alive():
            v._thread.join()

#: GUI ranges of the numeric pipeline options (slider: min, max, step); others are numbers
SLIDERS: dict[str, tuple[float, float, float]] = {
    "exposure": (-8.0, 8.0, 0.1),
    "taa_alpha": (0.01, 1.0, 0.01),
    "resample_threshold": (0.0, 1.0, 0.01),
    "svgf_alpha": (0.01, 1.0, 0.01),
}
#: the panel's folders; options not named here go to "Parameters"
FOLDERS: dict[str, tuple[str, ...]] = {
    "Stages": ("direct", "indirect", "indirect_scale", "upsampling", "upsampling_weight",
               "specaa", "taa"),
    "Display": ("exposure", "tonemap"),
    "Advanced": ("spp", "accumulate", "seed", "max_depth", "release_memory"),
}


def _check_size(size) -> tuple[int, int]:
    from ..scenes import check_size, parse_size

    if isinstance(size, str):
        return parse_size(size)
    try:
        w, h = (int(v) for v in size)
    except (TypeError, ValueError):
        raise GlossrtError(f"size must be WxH or (width, height), got {size!r}") from None
    return check_size((w, h))


def _check_port(port) -> int:
    if isinstance(port, bool) or not isinstance(port, int) or not 0 <= port <= 65535:
        raise GlossrtError(f"port must be an integer in 0..65535, got {port!r}")
    return port


def _check_host(host: str, port: int) -> None:
    """Refuse a host this machine cannot serve on, as the server would bind it: the name
    resolved, and a socket bound to each of its addresses at ``port`` (one in use is fine: the
    server takes the next free port, and the URL names it)."""
    import socket

    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM,
                                   flags=socket.AI_PASSIVE)
    except (OSError, UnicodeError) as e:
        why = e.strerror if isinstance(e, OSError) and e.strerror else str(e)
        raise GlossrtError(f"host {host!r} cannot be resolved ({why}): give an address of "
                           "this machine, e.g. 127.0.0.1 or 0.0.0.0") from None
    for family, kind, proto, _, addr in dict.fromkeys(infos):
        with socket.socket(family, kind, proto) as s:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            if family == socket.AF_INET6:
                s.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_V6ONLY, 1)
            try:
                s.bind(addr)
            except OSError as e:
                if e.errno == errno.EADDRINUSE:
                    continue
                if e.errno == errno.EACCES:
                    raise GlossrtError(f"port {port}: not allowed to serve on it (ports below "
                                       "1024 need root); choose another --port") from None
                raise GlossrtError(f"host {host!r} ({addr[0]}): cannot serve on it "
                                   f"({e.strerror or e}): give an address of this machine, "
                                   "e.g. 127.0.0.1 or 0.0.0.0") from None


def _free_port(host: str) -> int:
    import socket

    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def _check_captures(path) -> Path:
    """The captures folder, made absolute: a relative one is the folder under the working
    directory at open time (the render loop may still write a capture after ``stop``
    returns, when the caller may have changed directory). It may not exist yet (made at the
    first capture), but what is there must be a writable folder, and its parent must exist."""
    p = Path(os.fspath(path)).expanduser().absolute()
    if p.exists():
        if not p.is_dir():
            raise GlossrtError(f"captures: {p} exists and is not a folder")
        if not os.access(p, os.W_OK):
            raise GlossrtError(f"captures: folder {p} is not writable")
    else:
        parent = p.parent
        if not parent.is_dir():
            raise GlossrtError(f"captures: the folder above {p} does not exist")
        if not os.access(parent, os.W_OK):
            raise GlossrtError(f"captures: cannot create {p} (folder {parent} not writable)")
    return p


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", Path(str(text)).stem)[:60] or "scene"


#: a line of :class:`glossrt.progress.Progress` (on a terminal or not): description, done, total
class Viewer:
    """A live view of a frame pipeline in the browser. Start with :func:`open`; stop with
    :meth:`stop` (or use it as a context manager).

    ``scene``: anything :func:`glossrt.scenes.load` takes (a built-in name, an XML path, a
    Mitsuba scene dict or an ``mi.Scene``; ``params``: an XML file's ``$parameters``).
    ``pipeline``: a preset or a TOML file (:func:`glossrt.pipeline.parse`), ``choices``
    override its options; ``bspvt`` and ``bspvt_cache``: as :class:`glossrt.pipeline.Pipeline`'s
    (prebuilt trees; where built trees are kept, by default the user's cache folder).
    Everything is checked before the server starts (the options, the host and port, the scene
    and the pipeline's checks against it): a
    :class:`~glossrt.errors.GlossrtError` means nothing was started and nothing written. The
    server starts once those checks have passed; the pipeline's construction (BSPVT's trees)
    goes on in the render loop's thread, with its progress in the panel, and :attr:`pipe` is
    None until it ends. An error of that construction ends the render loop: :attr:`error`
    holds it in one line, the panel shows it and :meth:`wait` raises it. The stats say which
    method shades which light and what share of the pixels takes the path tracer's direct
    light (``stats["lights"]``, ``stats["fallback_share"]``)."""

    def __init__(self, scene, pipeline: str = "full", size=(320, 180),
                 host: str = "127.0.0.1", port: int = 8080, captures="captures",
                 verbose: bool = True, bspvt=None, params=None, bspvt_cache=True,
                 **choices: Any):
        from .. import pipeline as pl

        if not isinstance(host, str) or not host:
            raise GlossrtError(f"host must be a host name or address, got {host!r}")
        port = _check_port(port)
        size = _check_size(size)
        preset, file_choices = pl.parse(pipeline)
        choices = {**file_choices, **choices}
        self._opts = pl.resolve(preset, **choices)  # names and values, before the scene loads
        self.captures = _check_captures(captures)
        _check_host(host, port)
        self.verbose = verbose
        self._bspvt_cache = bspvt_cache
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="glossrt-view", daemon=True)
        _claim(self)
        try:
            self._start(scene, preset, choices, size, host, port, verbose, bspvt, params)
        except BaseException:
            self._stop.set()  # (the claim is given up: nothing runs)
            raise

    def _start(self, scene, preset, choices, size, host, port, verbose, bspvt,
               params=None) -> None:
        import drjit as dr

        #: the pipeline, once constructed (None until then)
        self.pipe = None
        #: why the pipeline's construction failed, in one line (None: it did not)
        self.error: str | None = None
        self._build_exc: BaseException | None = None
        self._build = (scene, preset, choices, size, bspvt, params)
        # set by the render loop's thread when the pipeline's checks have passed (the scene
        # loaded, the pose known) or the construction ended
        self._checked = threading.Event()
        self._panel = threading.Event()  # the panel exists: the loop's writes go to it (_gui)
        self.inbox = Inbox()
        self._lock = threading.Lock()  # the snapshot the API reads (stats, last images)
        self._save_lock = threading.Lock()
        # the render loop's writes to the panel and the scene (see _gui), and stop()
        self._gui_lock = threading.RLock()
        self._syncing = False
        self.index = 0
        self.playing = False
        self.layer = "color"
        self.message = ""
        self.status = "building the pipeline"
        #: the last statuses shown (what a person saw: "recording kernels", "live", ...)
        self.status_log: collections.deque[str] = collections.deque(maxlen=64)
        self.status_log.append(self.status)
        #: the construction's progress: (what, done, total) of its current step, or None
        self.progress: tuple[str, int, int] | None = None
        self._rebuilt = False
        self.stats: dict[str, Any] = {"frames": 0, "fps": 0.0, "reference_spp": 0}
        self.last_image: np.ndarray | None = None
        self.last_frame = None
        self.captured: list[Path] = []
        self._record_left = 0
        self._record_dir: Path | None = None
        self._record_count = 0
        self._reference = None
        self._ref_color: np.ndarray | None = None
        self._ref_spp = 0
        self._meter = ErrorMeter()  # the loop's: RMSE per frame, FLIP in a helper process
        self._still = 0
        self._sent_camera: ViewerCamera | None = None
        self._syncing_clients: dict[int, float | None] = {}
        with DRJIT_LOCK:  # (the caller's own Dr.Jit work may run meanwhile)
            dr.sync_thread()  # the render loop's thread takes over every Dr.Jit array
        self._thread.start()
        while not self._checked.wait(0.1):  # (Ctrl-C stays responsive)
            pass
        if self.error is not None:  # refused before anything was served
            self._thread.join()
            raise self._build_exc
        self._start_server(host, port)
        self._build_gui()

    # -- start-up -------------------------------------------------------------------------
    def _construct(self) -> bool:
        """The render loop's first work: load the scene and construct the pipeline; True
        when it is ready. Sets :attr:`_checked` once the pipeline's checks have passed (the
        server may start) or the construction ended."""
        from .. import pipeline as pl
        from ..scenes import load

        scene, preset, choices, size, bspvt, params = self._build
        viewer = self

        class _Checked(pl.Pipeline):
            """The pipeline, telling the viewer when its checks have passed."""

            def _check(self, *args, **kwargs):
                plan = super()._check(*args, **kwargs)
                if not viewer._checked.is_set():
                    viewer._posed(self.setup)
                return plan

        try:
            with DRJIT_LOCK, progress.observe(self._show_progress, quiet=not self.verbose):
                setup = load(scene, size=size, params=params)
                pipe = _Checked(setup, preset=preset, progress=True, bspvt=bspvt,
                                bspvt_cache=self._bspvt_cache, **choices)
                if not self._checked.is_set():  # (a pipeline that checked nothing here)
                    self._posed(pipe.setup)
        except Exception as e:  # noqa: BLE001 - one line for the user, the loop ends
            self._build_exc = e
            if isinstance(e, GlossrtError):
                self.error = str(e)
            else:  # (a fault of glossrt's: its traceback, here or raised by the constructor)
                if self._checked.is_set():
                    traceback.print_exc(file=sys.stderr)
                self.error = f"the pipeline's construction failed: {type(e).__name__}: {e}"
            self.error = " ".join(self.error.split())
            if self._checked.is_set():  # (served: the panel says it)
                self._set_message(f"error: {self.error}")
                self._set_status("stopped: the pipeline's construction failed")
                self._gui(lambda: setattr(self._progress_bar, "animated", False))
            self._checked.set()
            return False
        self.pipe = pipe
        return True

    def _posed(self, setup) -> None:
        """What the server and the panel need of the scene (its size, camera, movable
        lights), from the render loop's thread; then the server may start."""
        self.size = tuple(setup.size)
        self._lights = self._light_rests(setup)
        self._camera = self._scene_camera(setup)
        self._up = np.asarray(setup.rest_camera, np.float64)[:3, 1]
        self._checked.set()

    def _show_progress(self, desc: str, done: int, total: int) -> None:
        """A progress line of the pipeline's construction: in the status and the bar."""
        self.progress = (desc, done, total)
        self._set_status(f"building the pipeline: {desc} {done}/{total}")
        value = 100.0 * min(done, total) / max(total, 1)
        self._gui(lambda: setattr(self._progress_bar, "value", value))

    def _start_server(self, host: str, port: int) -> None:
        import viser

        if host not in LOOPBACK:
            warnings.warn(f"glossrt view serves on {host}: anyone who can reach this "
                          "machine's port can watch and steer the session", stacklevel=3)
        if port == 0:
            port = _free_port(host)
        import contextlib
        import io

        with contextlib.redirect_stdout(io.StringIO()):  # viser's banner: glossrt prints the URL
            self.server = viser.ViserServer(host=host, port=port, label="glossrt",
                                            verbose=False)
        self.host = host
        self.port = int(self.server.get_port())
        self.server.scene.set_up_direction(tuple(float(v) for v in self._up))
        # a client starts from (and its "Reset View" returns to) viser's initial camera: make
        # it the scene's, or the client reports viser's default camera as a move once the
        # page has loaded (seen under load in the browser tests)
        init, cam = self.server.initial_camera, self._camera
        init.fov = cam.fov_y
        init.up = cam.up
        init.position = cam.position
        init.look_at = cam.look_at
        self.server.on_client_connect(self._on_connect)

    def _scene_camera(self, setup=None) -> ViewerCamera:
        s = self.pipe.setup if setup is None else setup
        return from_pipeline(s.camera_matrix(0), s.current_fov, self.size,
                             pivot=s.look_at_point())

    def _light_rests(self, setup) -> dict[str, tuple[np.ndarray, float]]:
        """The polygon lights that can move: shape id -> (rest centre, size)."""
        from ..lights.scene import polygon_lights

        movable = set(setup.movable_shapes())
        out = {}
        for light in polygon_lights(setup, 0, skip=True):
            if light.id in movable:
                v = np.asarray(light.vertices, np.float64)
                c = v.mean(axis=0)
                out[light.id] = (c, float(np.max(np.linalg.norm(v - c, axis=1))))
        return out

    @property
    def preset(self) -> str:
        """The pipeline's preset (the one asked for while the pipeline is constructed)."""
        return self._opts["preset"] if self.pipe is None else self.pipe.preset

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        if host in ("0.0.0.0", "[::]"):
            host = "127.0.0.1"
        return f"http://{host}:{self.port}/"

    # -- the panel --------------------------------------------------------------------------
    def _widget(self, gui, name: str, value: Any):
        from ..pipeline import OPTIONS
        from ..pipeline.config import HELP, RANGES, range_text
        from ..specaa import METHODS, parse_method

        kind = OPTIONS[name]
        if name == "specaa":
            opts = list(dict.fromkeys(["none"] + [m for m in METHODS
                                                   if not parse_method(m).per_light]))
            return gui.add_dropdown("specaa", opts, initial_value=str(value).split(":")[0]
                                    if str(value).split(":")[0] in opts else "none")
        if name == "direct":
            return gui.add_dropdown(name, list(kind), initial_value=str(value))
        if isinstance(kind, tuple):
            return gui.add_dropdown(name, [str(v) for v in kind], initial_value=str(value))
        if kind is bool:
            return gui.add_checkbox(name, bool(value))
        if name in SLIDERS:
            lo, hi, step = SLIDERS[name]
            return gui.add_slider(name, min=lo, max=hi, step=step,
                                  initial_value=float(min(max(value, lo), hi)))
        # the option's range (glossrt.pipeline.config.RANGES) bounds the input; its line of
        # help is the hint
        lo, hi, _ = RANGES[name]
        if kind is int:
            init = 0 if value is None else int(value)
            if name == "max_depth":  # (0: the scene's; -1: no limit)
                return gui.add_number(name + " (0: scene's)", init, min=-1, max=int(hi),
                                      step=1, hint=HELP[name])
            return gui.add_number(name, init, min=int(lo), max=int(hi), step=1,
                                  hint=HELP[name])
        return gui.add_number(name, float(value), min=float(lo), max=float(hi),
                              hint=f"{HELP[name]}; {range_text(name)}")

    def _build_gui(self) -> None:
        with self._gui_lock:  # (the loop's writes wait for the panel, then go to it)
            self._add_widgets()
            self._panel.set()

    def _add_widgets(self) -> None:
        from ..pipeline import OPTIONS, PRESETS

        gui = self.server.gui
        self._status_md = gui.add_markdown(f"**{self.status}**")
        # the pipeline's construction (BSPVT's trees: its steps' progress), then hidden
        done = self.progress[1] / max(self.progress[2], 1) if self.progress else 0.0
        self._progress_bar = gui.add_progress_bar(100.0 * min(done, 1.0),
                                                  animated=self.error is None,
                                                  visible=self.last_image is None)
        self._message_md = gui.add_markdown(self.message)
        self._stats_md = gui.add_markdown("")  # fps, stage ms, errors: at the top
        self._widgets: dict[str, Any] = {}
        opts = self._opts if self.pipe is None else self.pipe.opts
        with gui.add_folder("Pipeline"):
            self._preset = gui.add_dropdown("preset", list(PRESETS),
                                            initial_value=opts["preset"])
            self._preset.on_update(self._on_preset)
        placed = {n for names in FOLDERS.values() for n in names}
        folders = dict(FOLDERS)
        folders["Parameters"] = tuple(n for n in OPTIONS if n not in placed)
        for title in ("Stages", "Parameters", "Display", "Advanced"):
            with gui.add_folder(title, expand_by_default=title != "Advanced"):
                for name in folders[title]:
                    if name not in OPTIONS:
                        continue
                    w = self._widget(gui, name, opts[name])
                    self._widgets[name] = w
                    w.on_update(lambda ev, n=name: self._on_option(n, ev))
                    if name == "specaa":
                        self._kappa = gui.add_number("specaa kappa (0: method's)", 0.0,
                                                     min=0.0, step=0.01)
                        self._kappa.on_update(lambda ev: self._on_option("specaa", ev))
                if title == "Display":
                    self._layer = gui.add_dropdown("layer", layers.names(
                        ("color", "composite", "direct", "indirect")), initial_value="color")
                    self._layer.on_update(self._on_layer)
        with gui.add_folder("Camera"):
            self._fov = gui.add_slider("vertical fov (deg)", min=5.0, max=120.0, step=0.5,
                                       initial_value=round(math.degrees(self._camera.fov_y), 1))
            self._fov.on_update(self._on_fov)
        with gui.add_folder("Animation"):
            self._play = gui.add_button("Play / pause")
            self._play.on_click(lambda ev: self.inbox.act("play"))
            self._step = gui.add_button("Step")
            self._step.on_click(lambda ev: self.inbox.act("step"))
            self._reset_pose = gui.add_button("Reset camera and lights")
            self._reset_pose.on_click(lambda ev: self.inbox.act("reset_pose"))
        with gui.add_folder("Capture"):
            self._capture = gui.add_button("Capture EXR")
            self._capture.on_click(lambda ev: self.inbox.act("capture"))
            self._record_n = gui.add_number("frames to record", 8, min=1, max=10000, step=1)
            self._record = gui.add_button("Record")
            self._record.on_click(lambda ev: self.inbox.post("record",
                                                              int(self._record_n.value)))
        self._gizmos = {}
        for sid, (centre, extent) in self._lights.items():
            g = self.server.scene.add_transform_controls(
                f"/lights/{_slug(sid)}", scale=max(0.2, 1.5 * extent),
                position=tuple(float(v) for v in centre))
            g.on_update(lambda ev, sid=sid: self._on_gizmo(sid, ev))
            self._gizmos[sid] = g

    # -- callbacks (viser's threads: post only) ----------------------------------------------
    def _on_connect(self, client) -> None:
        self._send_camera(client, self._camera)
        if self.last_image is not None:
            client.scene.set_background_image(self.last_image, format="jpeg", jpeg_quality=90)
        client.camera.on_update(lambda cam, cid=client.client_id: self._on_camera(cid, cam))

    def _send_camera(self, client, cam: ViewerCamera) -> None:
        """Put ``client``'s camera where the pipeline's is. Until the client reports that
        camera back (or :data:`SYNC_SECONDS` pass after its first report), its camera reports
        are the intermediate states of this update (its default camera with our up and field
        of view, ...): they are not the user's and are ignored."""
        self._sent_camera = cam
        self._syncing_clients[client.client_id] = None  # the window opens at the first report
        with client.atomic():
            client.camera.fov = cam.fov_y
            client.camera.up_direction = cam.up
            client.camera.position = cam.position
            client.camera.look_at = cam.look_at

    def _on_camera(self, client_id: int, cam) -> None:
        new = ViewerCamera(tuple(map(float, cam.position)), tuple(map(float, cam.look_at)),
                           tuple(map(float, cam.up_direction)), float(cam.fov))
        until = self._syncing_clients.get(client_id, _IN_SYNC)
        if until is not _IN_SYNC:
            if new.close_to(self._sent_camera, tol=ECHO_TOL):
                self._syncing_clients.pop(client_id, None)  # in sync from now on
                return
            if until is None:
                until = self._syncing_clients[client_id] = time.monotonic() + SYNC_SECONDS
            if time.monotonic() < until:
                return
            self._syncing_clients.pop(client_id, None)
        if new.close_to(self._camera, tol=ECHO_TOL):
            return  # nothing moved
        self.inbox.post("camera", new)

    def _on_fov(self, ev) -> None:
        """The field of view slider: every client's camera and the pipeline's."""
        if self._syncing:
            return
        cam = self._camera
        new = ViewerCamera(cam.position, cam.look_at, cam.up, math.radians(self._fov.value))
        self._send_cameras(new)
        self.inbox.post("camera", new)

    def _on_preset(self, ev) -> None:
        if not self._syncing:
            self.inbox.post("preset", self._preset.value)

    def _on_option(self, name: str, ev) -> None:
        if self._syncing:
            return
        w = self._widgets[name]
        value = w.value
        from ..pipeline import OPTIONS

        kind = OPTIONS[name]
        if name == "specaa":
            k = float(self._kappa.value)
            value = value if value == "none" or k <= 0 else f"{value}:kappa={k:g}"
        elif name == "max_depth":
            value = None if int(value) == 0 else int(value)
        elif isinstance(kind, tuple):
            value = next((v for v in kind if str(v) == value), value)
        elif kind is int:
            value = int(value)
        elif kind is float:
            value = float(value)
        self.inbox.post(f"option:{name}", value)

    def _on_layer(self, ev) -> None:
        self.inbox.post("layer", self._layer.value)

    def _on_gizmo(self, sid: str, ev) -> None:
        g = self._gizmos[sid]
        self.inbox.post(f"transform:{sid}", (np.array(g.position, np.float64),
                                             np.array(g.wxyz, np.float64)))

    # -- the API a script or notebook uses (any thread: posts too) -----------------------------
    def configure(self, **choices: Any) -> None:
        """Change pipeline options from code, as the panel does (applied at the next
        frame; a refusal shows in :attr:`message` and keeps the previous state)."""
        from ..pipeline import config

        config.check_names(choices)
        for k, v in choices.items():
            self.inbox.post(f"option:{k}", v)

    def set_camera(self, position, look_at, up=None, fov_y: float | None = None) -> None:
        """Move the camera as a browser does (``fov_y`` vertical, radians)."""
        cam = self._camera
        self.inbox.post("camera", ViewerCamera(
            tuple(map(float, position)), tuple(map(float, look_at)),
            tuple(map(float, cam.up if up is None else up)),
            cam.fov_y if fov_y is None else float(fov_y)))

    def move_light(self, name: str, position, wxyz=(1.0, 0.0, 0.0, 0.0)) -> None:
        """Move polygon light ``name`` as its gizmo does (``position`` of its centre)."""
        if name not in self._lights:
            raise GlossrtError(f"move_light: no movable polygon light {name!r}; the lights are "
                               f"{', '.join(self._lights) or 'none'}")
        self.inbox.post(f"transform:{name}", (np.asarray(position, np.float64),
                                              np.asarray(wxyz, np.float64)))

    def capture(self) -> None:
        """Write the next frame as one multi-layer EXR into the captures folder."""
        self.inbox.act("capture")

    def record(self, frames: int) -> None:
        """Write the next ``frames`` frames into a new folder of the captures folder."""
        if isinstance(frames, bool) or not isinstance(frames, int) or frames < 1:
            raise GlossrtError(f"record: frames must be an integer >= 1, got {frames!r}")
        self.inbox.post("record", frames)

    def wait(self, frames: int = 1, timeout: float = 60.0, until=None) -> bool:
        """Wait until ``frames`` more frames were rendered (or ``until()`` is true); False
        when ``timeout`` seconds passed first or the render loop ended. The first frame
        comes after the pipeline's construction; an error of that raises here
        (:class:`~glossrt.errors.GlossrtError`, :attr:`error`)."""
        start = self.stats["frames"]
        t_end = time.monotonic() + timeout
        while time.monotonic() < t_end and self._thread.is_alive():
            if (until() if until is not None else self.stats["frames"] >= start + frames):
                return True
            time.sleep(0.02)
        if self.error is not None:
            raise GlossrtError(self.error) from self._build_exc
        return False

    def stop(self, timeout: float = 2.0, stop_server: bool = True) -> None:
        """Stop the render loop and the server within ``timeout`` seconds. A capture being
        written is finished first (it is written whole or not at all). ``stop_server=False``:
        leave the server to the process' exit (the CLI ends with ``os._exit``)."""
        t_end = time.monotonic() + timeout
        self._stop.set()
        self.inbox.wake()
        self._thread.join(max(0.0, t_end - time.monotonic() - 0.3))
        got = self._save_lock.acquire(timeout=max(0.0, t_end - time.monotonic() - 0.2))
        # a write of the loop (still finishing a frame) in progress ends first; later ones are
        # skipped, as _stop is set (see _gui)
        got_gui = self._gui_lock.acquire(timeout=max(0.0, t_end - time.monotonic() - 0.1))
        try:
            if stop_server:
                self.server.stop()
        finally:
            if got_gui:
                self._gui_lock.release()
            if got:
                self._save_lock.release()

    @property
    def running(self) -> bool:
        return self._thread.is_alive() and not self._stop.is_set()

    def __enter__(self) -> Viewer:
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    def _repr_html_(self) -> str:  # Jupyter: the live viewer embedded in the output cell
        return (f'<iframe src="{self.url}" width="100%" height="540" '
                'style="border:none"></iframe>')

    def show(self, height: int = 540) -> None:
        """Embed the live viewer in a Jupyter notebook's output (IPython's IFrame)."""
        try:
            from IPython.display import IFrame, display
        except ImportError:
            print(f"glossrt view: open {self.url}")
            return
        display(IFrame(self.url, width="100%", height=height))

    # -- the render loop (its own thread: every Dr.Jit call) ---------------------------------------
    def _set_status(self, text: str) -> None:
        if text == self.status:
            return  # (every frame sets it: no GUI update, no repeats in the log)
        self.status = text
        self.status_log.append(text)
        self._gui(lambda: setattr(self._status_md, "content", f"**{text}**"))

    def _set_message(self, text: str) -> None:
        self.message = text
        self._gui(lambda: setattr(self._message_md, "content", text))

    def _gui(self, write, *args, **kwargs) -> None:
        """The render loop's every write to the panel or the scene: ``write(*args,
        **kwargs)``, once the panel exists (it is built from the state of the moment) and
        unless :meth:`stop` has begun (viser warns of, and never delivers, a message queued
        after its server stopped; stop() waits for a write in progress)."""
        with self._gui_lock:
            if self._panel.is_set() and not self._stop.is_set():
                write(*args, **kwargs)

    def _send_cameras(self, cam: ViewerCamera) -> None:
        for client in self.server.get_clients().values():
            self._send_camera(client, cam)

    def _sync_widgets(self) -> None:
        """Show the pipeline's options in the panel (after a refusal or a preset change)."""
        self._gui(self._write_widgets)

    def _write_widgets(self) -> None:
        self._syncing = True
        try:
            self._preset.value = self.pipe.preset
            for name, w in self._widgets.items():
                v = self.pipe.opts[name]
                if name == "specaa":
                    method, _, kappa = str(v).partition(":kappa=")
                    w.value = method
                    self._kappa.value = float(kappa) if kappa and kappa != "none" else 0.0
                elif name == "max_depth":
                    w.value = 0 if v is None else int(v)
                elif isinstance(w.value, str):
                    w.value = str(v)
                else:
                    w.value = type(w.value)(v)
        finally:
            self._syncing = False

    def _reset_gizmo(self, sid: str) -> None:
        """Light ``sid``'s gizmo back at the light's rest pose."""
        g = self._gizmos.get(sid)
        if g is not None:
            self._gui(setattr, g, "position", tuple(float(v) for v in self._lights[sid][0]))
            self._gui(setattr, g, "wxyz", (1.0, 0.0, 0.0, 0.0))

    def _apply(self, values: dict[str, Any], actions) -> bool:
        """Apply what was posted; True when the pose or the pipeline changed."""
        from .. import pipeline as pl

        changed = False
        if "layer" in values:
            self.layer = values.pop("layer")
        if "preset" in values:
            preset = values.pop("preset")
            try:
                new = pl.Pipeline(self.pipe.setup, preset=preset, progress=False,
                                  bspvt_cache=self.pipe.bspvt_cache)
            except GlossrtError as e:
                self._set_message(f"refused: {e}")
            else:
                self.pipe = new
                self._set_message(f"preset {preset}")
                changed = self._rebuilt = True
            self._sync_widgets()
        options = {k.split(":", 1)[1]: v for k, v in values.items() if k.startswith("option:")}
        if options:
            try:
                self.pipe.configure(**options)
                self._set_message("")
                changed = self._rebuilt = True
            except GlossrtError as e:
                self._set_message(f"refused: {e}")
            self._sync_widgets()
        if "camera" in values:
            cam = values["camera"]
            try:
                self.pipe.set_camera(**to_pipeline(cam, self.size))
                self._camera = cam
                changed = True
            except GlossrtError as e:
                self._set_message(f"refused: {e}")
        for key, (pos, wxyz) in ((k, v) for k, v in values.items()
                                  if k.startswith("transform:")):
            sid = key.split(":", 1)[1]
            try:
                self.pipe.set_transform(sid, gizmo_matrix(pos, wxyz, self._lights[sid][0]))
                changed = True
            except GlossrtError as e:
                self._set_message(f"refused: {e}")
                self._reset_gizmo(sid)  # the gizmo back where the light is
        if actions.get("reset_pose"):
            self.pipe.clear_pose()
            self._camera = self._scene_camera()
            for sid in self._gizmos:
                self._reset_gizmo(sid)
            self._gui(self._send_cameras, self._camera)
            changed = True
        if actions.get("play", 0) % 2:
            self.playing = not self.playing
        if actions.get("step"):
            self.index += actions["step"]
            changed = True
        if "record" in values:
            self._record_left = int(values["record"])
            self._record_dir, self._record_count = None, 0
        return changed

    def _reference_step(self, index: int) -> None:
        from ..pipeline import Pipeline

        if self._reference is None:
            self._reference = Pipeline(self.pipe.setup, preset="reference", progress=False,
                                       spp=REFERENCE_SPP, seed=self.pipe.opts["seed"] + 7919,
                                       max_depth=self.pipe.opts["max_depth"],
                                       outputs=("color",))  # (its colour is all it shows)
            self._reference.reset()
        f = self._reference.render(index)
        self._ref_color = f.numpy("color")
        self._ref_spp += REFERENCE_SPP

    def _reference_reset(self) -> None:
        self._ref_color, self._ref_spp, self._still = None, 0, 0
        self._meter.reset()
        if self._reference is not None:
            self._reference.reset()

    def _image(self, frame) -> np.ndarray:
        name = self.layer
        ex, tm = self.pipe.opts["exposure"], self.pipe.opts["tonemap"]
        if name == "reference":
            if self._ref_color is None:
                return np.zeros((self.size[1], self.size[0], 3), np.uint8)
            return layers.visualise("reference", self._ref_color, ex, tm)
        if name == "error":
            if self._ref_color is None:
                return np.zeros((self.size[1], self.size[0], 3), np.uint8)
            ref = self._ref_color
            return layers.error_map(frame.numpy("color"), ref,
                                    scale=max(float(np.nanmean(ref)), 1e-3))
        if name not in frame.names:
            name = "color"
        return layers.visualise(name, frame.numpy(name), ex, tm)

    def _with_reference(self, frame):
        """``frame`` plus the viewer's ``reference`` layer (when accumulated) and meta."""
        from ..frame import Frame

        channels = {k: frame[k] for k in frame.names}
        if self._ref_color is not None:
            channels["reference"] = self._ref_color.astype(np.float32)
        meta = dict(frame.meta)
        meta["viewer"] = {"layer": self.layer, "reference_spp": self._ref_spp,
                          **{k: v for k, v in self.stats.items() if k in ERROR_KEYS}}
        return Frame(channels=channels, camera=frame.camera, prev_camera=frame.prev_camera,
                     index=frame.index, meta=meta)

    def _next_capture(self) -> Path:
        stem = f"{_slug(self.pipe.setup.name)}-{self.pipe.preset}-f{self.index:05d}"
        k = 0
        while (self.captures / f"{stem}-{k:03d}.exr").exists():
            k += 1
        return self.captures / f"{stem}-{k:03d}.exr"

    def _save(self, frame, path: Path) -> None:
        with self._save_lock:
            path.parent.mkdir(parents=True, exist_ok=True)
            self._with_reference(frame).save(path)
        self.captured.append(path)

    def _captures(self, frame, actions) -> None:
        from ..frame import frame_filename

        for _ in range(actions.get("capture", 0)):
            path = self._next_capture()
            self._save(frame, path)
            self._set_message(f"wrote {path}")
        if self._record_left > 0:
            if self._record_dir is None:
                stamp = time.strftime("%Y%m%d-%H%M%S")
                k = 0
                while (self.captures / f"record-{stamp}-{k}").exists():
                    k += 1
                self._record_dir = self.captures / f"record-{stamp}-{k}"
            # numbered in recording order (a paused animation repeats its index)
            self._save(frame, self._record_dir / frame_filename(self._record_count))
            self._record_count += 1
            self._record_left -= 1
            if self._record_left == 0:
                self._set_message(f"recorded into {self._record_dir}")

    def _show_stats(self, frame, seconds: float) -> None:
        p = frame.meta["pipeline"]
        s = dict(self.stats)
        s["frames"] += 1
        fps = 1.0 / max(seconds, 1e-6)
        s["fps"] = fps if s["frames"] == 1 else 0.8 * s["fps"] + 0.2 * fps
        s["frame_ms"] = 1000.0 * seconds
        s["stage_ms"] = dict(p["stage_ms"])
        s["recordings"] = self.pipe.recordings()
        s["reference_spp"] = self._ref_spp
        for k in ERROR_KEYS:
            s.pop(k, None)
        if self._ref_color is not None:
            s.update(self._meter.measure(frame.numpy("color"), self._ref_color, self._ref_spp))
        s["index"] = self.index
        s["direct"] = p["direct"]
        s["lights"] = [dict(light) for light in p.get("lights", ())]
        s["fallback_share"] = float(p.get("fallback_share", 0.0))
        self.stats = s
        methods = self.pipe.plan.summary()
        fallback = (f"; {100 * s['fallback_share']:.0f}% of the pixels path-traced for every "
                    "light (materials the analytic methods do not represent)"
                    if s["fallback_share"] > 0 else "")
        rows = "\n".join(f"| {k} | {v:.1f} |" for k, v in s["stage_ms"].items())
        if "rmse" not in s:
            err = "reference: accumulates when the view stands still"
        else:
            err = f"RMSE **{s['rmse']:.4g}** against {self._ref_spp} spp; " + (
                f"FLIP **{s['flip']:.4g}** against {s['flip_spp']} spp" if "flip" in s else
                (self._meter.error or "FLIP: measuring"))
        self._gui(setattr, self._stats_md, "content", (
            f"**{s['fps']:.1f} fps** ({s['frame_ms']:.0f} ms), frame {self.index}, "
            f"{s['frames']} rendered, {s['recordings']} recordings, direct: {p['direct']}\n\n"
            f"lights: {methods}{fallback}\n\n"
            f"{err}\n\n| stage | ms |\n|---|---|\n{rows}"))

    def _loop(self) -> None:
        try:
            if not self._construct():
                return
            while not self._panel.wait(0.05):  # (the server starts meanwhile)
                if self._stop.is_set():
                    return
            self._frames()
        finally:
            self._meter.close()

    def _frames(self) -> None:
        failures = 0
        self._set_status("recording kernels")
        while not self._stop.is_set():
            idle = self._still >= STILL_FRAMES and not self.playing
            values, actions = self.inbox.take(
                timeout=0.05 if idle and self._ref_spp >= REFERENCE_MAX_SPP else 0.0)
            if self._stop.is_set():
                break
            try:
                with DRJIT_LOCK:
                    self._frame(values, actions)
                failures = 0
            except Exception as e:  # noqa: BLE001 - shown in the panel, the loop goes on
                failures += 1
                traceback.print_exc(file=sys.stderr)
                self._set_message(f"render failed: {type(e).__name__}: {e}")
                if failures >= 3:
                    self._set_status("stopped after 3 failed frames")
                    return
                time.sleep(0.5)

    def _frame(self, values: dict[str, Any], actions) -> None:
        """One iteration of the loop: apply what was posted, render, show, capture."""
        self._rebuilt = False
        if self._apply(values, actions) or self.playing:
            self._reference_reset()
        if self._rebuilt:  # a rebuilt stage records its kernels on this frame
            self._set_status("recording kernels")
        t0 = time.perf_counter()
        rec0 = self.pipe.recordings()
        frame = self.pipe.render(self.index)
        seconds = time.perf_counter() - t0
        self._still += 1
        if self._still > STILL_FRAMES and self._ref_spp < REFERENCE_MAX_SPP:
            self._reference_step(self.index)
        shown = layers.names(frame.names)
        if list(self._layer.options) != shown:  # every channel of this pipeline's frame
            self._gui(setattr, self._layer, "options", shown)
        img = self._image(frame)
        self.last_frame, self.last_image = frame, img
        self._gui(self.server.scene.set_background_image, img, format="jpeg", jpeg_quality=90)
        if self._progress_bar.visible:  # (the construction's, until the first image)
            self._gui(setattr, self._progress_bar, "visible", False)
        self._captures(frame, actions)
        recorded = self.pipe.recordings() - rec0
        # the status first: once the stats show the new state, the status says so too
        self._set_status(f"recorded {recorded} kernel(s)" if recorded else
                         ("playing" if self.playing else
                          "converging reference" if self._ref_spp else "live"))
        self._show_stats(frame, seconds)
        if self.playing:
            self.index += 1


def open(scene, pipeline: str = "full", size=(320, 180), host: str = "127.0.0.1",
         port: int = 8080, captures="captures", device: str | None = None,
         verbose: bool = True, **choices: Any) -> Viewer:
    """Start a live viewer of ``scene`` through ``pipeline`` and return its handle (see
    :class:`Viewer`). In a notebook the handle shows itself as the embedded viewer; from a
    script, open :attr:`Viewer.url`. ``device``: ``cpu``/``gpu`` (None: as chosen before)."""
    from .. import backend

    if device is not None:
        backend.use(device)
    return Viewer(scene, pipeline=pipeline, size=size, host=host, port=port,
                  captures=captures, verbose=verbose, **choices)


def serve(viewer: Viewer, timeout: float = 1.8, stop_server: bool = True) -> None:
    """Block until Ctrl-C or SIGTERM (or the render loop ends: :attr:`Viewer.error` says
    why when the pipeline's construction failed), then stop ``viewer`` within ``timeout``
    seconds (see :meth:`Viewer.stop`)."""
    import signal

    done = threading.Event()

    def _handler(signum, frame) -> None:
        done.set()

    old = {s: signal.signal(s, _handler) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        while not done.wait(0.05) and viewer._thread.is_alive():
            pass
        if viewer.error is not None and not done.is_set():
            viewer.server.flush()  # (the panel's error on its way to the open pages)
            done.wait(0.5)
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        viewer.stop(timeout=timeout, stop_server=stop_server)


__all__ = ["Viewer", "open", "serve"]
