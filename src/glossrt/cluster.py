"""Scale-out on Ray: run independent work items on a cluster, results in item order.

>>> from glossrt import cluster
>>> cluster.map_items(abs, [-1, 2, -3])                    # no cluster: in this process
[1, 2, 3]
>>> with cluster.connect("local:2") as c:                   # doctest: +SKIP
...     out = cluster.map_items(work, items, cluster=c, desc="blocks")

Cluster specs (``--cluster``; env ``GLOSSRT_CLUSTER`` is the default): ``local`` (a Ray
instance on this machine with one worker slot per CPU), ``local:N`` (N slots), ``auto`` (the
cluster ``ray start --head`` started on this machine), ``ray://HOST:PORT`` (a remote cluster's
Ray Client server, ``ray start --head`` opens port 10001), ``none`` or the empty string (no
cluster: the same items run in this process, in order).

What travels: ``fn`` is a module-level function, pickled by reference (workers import its
module, so glossrt must be installed there); items and results are plain picklable data
(NumPy arrays, strings, numbers), never Dr.Jit objects. A scene travels as its built-in
name, or as its XML and the files it references (:func:`glossrt.scenefiles.bundle`), put
once per run into Ray's object store (:func:`share`) and unpacked once per node
(:func:`resolve` + :func:`glossrt.scenefiles.materialise`): no shared folder is needed.
Scheduling, retries of a killed worker's items (``max_retries``) and GPU assignment
(``CUDA_VISIBLE_DEVICES`` per task) are Ray's. Every worker process is set up before its
first item: Dr.Jit's thread count is the number of CPUs Ray gave the task, the Mitsuba
variant is the driver's, and on remote clusters Dr.Jit's kernel cache is a node-local folder
(``DRJIT_CACHE_DIR``, default ``/tmp/glossrt-drjit-cache``; env
``GLOSSRT_WORKER_KERNEL_CACHE`` on the driver chooses another): shared kernel caches on
network file systems are a known source of failures. Connecting probes every node once: a
node whose glossrt cannot be imported, whose libLLVM is missing, or whose glossrt version or
Mitsuba variant differs from the driver's fails the run at once with a message naming the
node.

Ground floor: this module imports Ray, Mitsuba and Dr.Jit only inside functions.
"""

from __future__ import annotations

import os
import re
import socket
import sys
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field

from .backend import GPU_VARIANT as _GPU
from .errors import GlossrtError
from .progress import Progress

ENV = "GLOSSRT_CLUSTER"
#: seconds to reach a ``ray://`` address or an ``auto`` cluster before giving up
CONNECT_TIMEOUT_S = 5.0
#: seconds the per-node start-up probe may take (worker start, glossrt import, variant)
PROBE_TIMEOUT_S = 180.0
REMOTE_KERNEL_CACHE = "/tmp/glossrt-drjit-cache"

_CLIENT = re.compile(r"^ray://(?P<host>[A-Za-z0-9_.\-]+|\[[0-9A-Fa-f:]+\]):(?P<port>\d{1,5})$")


class ClusterError(GlossrtError):
    """A cluster spec that cannot be parsed or reached, or a cluster unfit for the run."""


@dataclass(frozen=True)
class Spec:
    """A parsed cluster spec: ``kind`` is ``"local"``, ``"auto"`` or ``"client"``."""

    kind: str
    cpus: int | None = None
    address: str | None = None

    def __str__(self) -> str:
        if self.kind == "local":
            return "local" if self.cpus is None else f"local:{self.cpus}"
        return self.address or self.kind


def parse(spec: str | None) -> Spec | None:
    """The cluster ``spec`` (see the module) as a :class:`Spec`, or None for no cluster.
    ``None`` reads env ``GLOSSRT_CLUSTER``; ``""`` and ``"none"`` mean no cluster. A bad spec
    raises :class:`ClusterError` (one line)."""
    if spec is None:
        spec = os.environ.get(ENV, "")
    if not isinstance(spec, str):
        raise ClusterError(f"cluster spec must be a string, got {spec!r}")
    s = spec.strip()
    if s.lower() in ("", "none"):
        return None
    if s.lower() == "local":
        return Spec("local")
    if s.lower().startswith("local:"):
        n = s[6:]
        if not n.isdigit() or int(n) < 1:
            raise ClusterError(f"cluster {spec!r}: local:N needs a number of worker slots "
                               "N >= 1 (e.g. local:2)")
        return Spec("local", cpus=int(n))
    if s.lower() == "auto":
        return Spec("auto", address="auto")
    m = _CLIENT.match(s)
    if m:
        port = int(m.group("port"))
        if not 0 < port < 65536:
            raise ClusterError(f"cluster {spec!r}: port {port} is out of range")
        return Spec("client", address=s)
    raise ClusterError(f"unknown cluster {spec!r}: use local, local:N, auto or "
                       "ray://HOST:PORT (none: run in this process)")


def _ray():
    try:
        import ray
    except ImportError as e:  # pragma: no cover - ray is a dependency
        raise ClusterError(f"--cluster needs Ray (pip install 'ray[client]'): {e}") from None
    return ray


def _driver_variant() -> str:
    from . import backend

    return backend.use()


def _device_of(variant: str) -> str:
    return "gpu" if variant == _GPU else "cpu"


@dataclass
class Cluster:
    """An open connection to a Ray cluster (from :func:`connect`)."""

    spec: Spec
    variant: str
    owned: bool
    nodes: list[dict] = field(default_factory=list)
    #: a runtime environment each task is given (``worker_env`` on a Ray glossrt did not
    #: start); None when the job's own carries it
    task_env: dict | None = None

    @property
    def cpus(self) -> int:
        """CPUs in the cluster (worker slots of one CPU each)."""
        return max(int(_ray().cluster_resources().get("CPU", 1)), 1)


def _auto_address() -> str | None:
    """``host:port`` of the cluster ``auto`` means (env RAY_ADDRESS, else the last
    ``ray start`` on this machine), or None when none is known (Ray then says so at once)."""
    try:
        from ray._private.services import canonicalize_bootstrap_address

        return canonicalize_bootstrap_address("auto")
    except Exception:  # Ray's own message follows from ray.init
        return None


def _probe_address(spec: Spec) -> None:
    """Fail within :data:`CONNECT_TIMEOUT_S` when the cluster's address does not answer (Ray
    Client retries for about a minute, and ``auto`` waits as long for a dead cluster that
    ``ray start`` left recorded)."""
    if spec.kind == "auto":
        addr = _auto_address()
        if not addr or ":" not in addr:
            return
        host, port = addr.rsplit(":", 1)[0].strip("[]"), int(addr.rsplit(":", 1)[1])
    else:
        m = _CLIENT.match(spec.address or "")
        assert m is not None
        host, port = m.group("host").strip("[]"), int(m.group("port"))
    try:
        with socket.create_connection((host, port), timeout=CONNECT_TIMEOUT_S):
            pass
    except OSError as e:
        raise ClusterError(f"cannot reach Ray cluster {spec.address} ({host}:{port}): "
                           f"{e.strerror or e} (is `ray start --head` running there"
                           + (", with its client port open?)" if spec.kind == "client" else "?)")
                           ) from None


@contextmanager
def connect(spec: str | Spec | Cluster | None = None,
            worker_env: dict[str, str] | None = None,
            local_gpus: int | None = None) -> Iterator[Cluster | None]:
    """Open the cluster ``spec`` for a run: ``with connect("local:2") as c: ...``. Yields
    None for no cluster (see :func:`parse`), a :class:`Cluster` otherwise. A local Ray
    instance glossrt started is shut down at the end (no process left behind); a Ray that
    was already initialised in this process is used as it is and left running.
    ``worker_env``: more environment variables for the worker processes (e.g.
    ``DRJIT_LIBLLVM_PATH`` where nodes keep libLLVM elsewhere). ``local_gpus``: the GPUs a
    ``local`` instance offers (default: Ray's detection), e.g. one per device of a
    multi-GPU workstation."""
    if isinstance(spec, Cluster):
        yield spec
        return
    parsed = spec if isinstance(spec, Spec) else parse(spec)
    if parsed is None:
        yield None
        return
    if parsed.kind in ("client", "auto"):
        _probe_address(parsed)
    ray = _ray()
    variant = _driver_variant()
    owned = False
    if not ray.is_initialized():
        env = {"GLOSSRT_DEVICE": _device_of(variant), **(worker_env or {})}
        cache = os.environ.get("GLOSSRT_WORKER_KERNEL_CACHE")
        if cache or parsed.kind != "local":
            env["DRJIT_CACHE_DIR"] = cache or REMOTE_KERNEL_CACHE
        kw = dict(runtime_env={"env_vars": env}, log_to_driver=False,
                  logging_level="ERROR", include_dashboard=False)
        try:
            if parsed.kind == "local":
                # "local": a new instance even where `ray start` left one running
                gpus = {} if local_gpus is None else {"num_gpus": int(local_gpus)}
                ray.init(address="local", num_cpus=parsed.cpus or os.cpu_count() or 1,
                         **gpus, **kw)
            elif parsed.kind == "client":
                try:
                    ray.init(address=parsed.address, **kw)
                except Exception as e:
                    # Ray 2.60's client server may fail the first session after the head
                    # started (seen once: a gRPC check failure in its SpecificServer);
                    # a second attempt connects
                    if "Initialization failure from server" not in str(e):
                        raise
                    ray.init(address=parsed.address, **kw)
            else:
                ray.init(address=parsed.address, **kw)
        except Exception as e:
            msg = str(e).splitlines()[0] if str(e) else type(e).__name__
            chain = f"{e} {e.__cause__} {e.__context__}"
            if "AuthToken" in chain or "Authentication" in chain:
                msg += (" (the cluster requires Ray's token: set RAY_AUTH_MODE=token here "
                        "and copy the head's ~/.ray/auth_token to this machine, "
                        "docs/CLUSTER.md)")
            elif parsed.kind == "client" and "timeout" in msg:
                msg += (" (recent Ray clusters require a token: set RAY_AUTH_MODE=token "
                        "and RAY_AUTH_TOKEN, or copy the head's ~/.ray/auth_token here)")
            raise ClusterError(f"cannot connect to Ray cluster {parsed}: {msg}") from None
        owned = True
    try:
        c = Cluster(parsed, variant, owned,
                    task_env={"env_vars": dict(worker_env)} if worker_env and not owned
                    else None)
        c.nodes = _probe_nodes(variant, c.task_env)
        yield c
    finally:
        if owned:
            ray.shutdown()


# -- worker side ---------------------------------------------------------------------------
_WORKER: dict = {}


def _setup_worker(variant: str) -> dict:
    """Once per worker process: the driver's Mitsuba variant (libLLVM found), Dr.Jit's
    thread count = the CPUs Ray assigned to the task. Returns the worker's description."""
    ray = _ray()
    ctx = ray.get_runtime_context()
    cpus = ctx.get_assigned_resources().get("CPU", 1.0)
    info = _WORKER.get("info")
    if info is None:  # (the node's address once: asking opens a socket)
        from . import __version__, backend

        node = ray.util.get_node_ip_address()
        try:
            got = backend.use(_device_of(variant))
        except GlossrtError as e:
            raise ClusterError(f"node {node}: {e}") from None
        info = {"node": node, "node_id": ctx.get_node_id(), "pid": os.getpid(),
                "version": __version__, "variant": got,
                "kernel_cache": os.environ.get("DRJIT_CACHE_DIR", "~/.drjit"),
                "cuda_visible_devices": os.environ.get("CUDA_VISIBLE_DEVICES")}
        _WORKER["info"] = info
    elif (info["variant"] == _GPU and
          os.environ.get("CUDA_VISIBLE_DEVICES") != info["cuda_visible_devices"]):
        # Ray lent this reused worker another GPU, but its CUDA context stays on the first
        # one: end the process, so that Ray reruns the item on a fresh worker (a worker
        # death is retried, see max_retries)
        os._exit(75)
    if _WORKER.get("cpus") != cpus:
        import drjit as dr

        dr.set_thread_count(max(int(cpus), 1))
        _WORKER["cpus"] = cpus
    return dict(info, threads=max(int(cpus), 1))


def _run(fn: Callable, item, variant: str):
    """One item on a worker: ``(fn(item), worker description, seconds)``."""
    info = _setup_worker(variant)
    t0 = time.perf_counter()
    try:
        out = fn(item)
    except GlossrtError as e:
        raise ClusterError(f"on node {info['node']} (pid {info['pid']}): {e}") from None
    return out, info, time.perf_counter() - t0


_REMOTE: dict = {}


def _remote(name: str):
    """The Ray remote function of ``name`` (made once per process: importing this module
    must not import Ray)."""
    if name not in _REMOTE:
        _REMOTE[name] = _ray().remote(globals()[name])
    return _REMOTE[name]


def _probe_nodes(variant: str, task_env: dict | None = None) -> list[dict]:
    """Run :func:`_setup_worker` once on every alive node; refuse a node that cannot run glossrt or
    differs from the driver (glossrt version, Mitsuba variant)."""
    ray = _ray()
    from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

    from . import __version__

    gpu = _device_of(variant) == "gpu"
    nodes = [n for n in ray.nodes() if n.get("Alive")
             and n.get("Resources", {}).get("GPU" if gpu else "CPU", 0) > 0]
    if not nodes:
        raise ClusterError("the Ray cluster has no alive node with a "
                           f"{'GPU' if gpu else 'CPU'} (driver variant {variant})")
    refs = {}
    for n in nodes:
        opts = dict(num_cpus=1, num_gpus=1 if gpu else 0, max_retries=0,
                    scheduling_strategy=NodeAffinitySchedulingStrategy(n["NodeID"], soft=False))
        if task_env:
            opts["runtime_env"] = task_env
        refs[n.get("NodeManagerAddress", n["NodeID"])] = _remote("_setup_worker").options(
            **opts).remote(variant)
    out = []
    for name, ref in refs.items():
        try:
            info = ray.get(ref, timeout=PROBE_TIMEOUT_S)
        except ray.exceptions.GetTimeoutError:
            raise ClusterError(f"node {name}: no worker started within {PROBE_TIMEOUT_S:.0f} s"
                               ) from None
        except Exception as e:
            raise ClusterError(f"node {name} cannot run glossrt: {_cause(e)}") from None
        if info["version"] != __version__:
            raise ClusterError(f"node {name} has glossrt {info['version']}, the driver "
                               f"{__version__}: refusing to mix versions")
        if info["variant"] != variant:
            raise ClusterError(f"node {name} runs Mitsuba variant {info['variant']}, the "
                               f"driver {variant}: refusing to mix variants")
        out.append(info)
    return out


def _cause(e: BaseException) -> str:
    """The last line of a (remote) exception: the original error, without Ray's trace."""
    cause = getattr(e, "cause", None)
    if isinstance(cause, BaseException):
        return f"{type(cause).__name__}: {cause}".splitlines()[-1].strip()
    lines = [ln.strip() for ln in str(e).splitlines() if ln.strip()]
    return lines[-1] if lines else type(e).__name__


# -- driver side ---------------------------------------------------------------------------
@dataclass
class WorkerStats:
    """Items a worker process finished and the seconds they took (its throughput)."""

    node: str
    pid: int
    items: int = 0
    seconds: float = 0.0
    #: Ray's id of the node (several nodes may share an address)
    node_id: str = ""

    def __str__(self) -> str:
        rate = self.items / self.seconds if self.seconds > 0 else float("inf")
        nid = f" (node {self.node_id[:8]})" if self.node_id else ""
        return (f"worker {self.node}{nid} pid {self.pid}: {self.items} item(s) in "
                f"{self.seconds:.1f} s ({rate:.2f}/s)")


def imap_items(fn: Callable, items: Sequence, *, cluster=None, desc: str = "",
               weights: Sequence[float] | None = None, num_gpus: int | None = None,
               num_cpus: int = 1, max_retries: int = 3, progress: bool = True,
               stats: list[WorkerStats] | None = None) -> Iterator:
    """:func:`map_items` as an iterator: yields ``fn(item)`` in item order as soon as the
    results up to it are in (at most a few times the cluster's slots are held at once)."""
    items = list(items)
    w = [1.0] * len(items) if weights is None else [float(x) for x in weights]
    if len(w) != len(items):
        raise GlossrtError(f"map_items: {len(w)} weights for {len(items)} items")
    if num_gpus not in (None, 0, 1):
        raise GlossrtError(f"map_items: num_gpus must be 0 or 1, got {num_gpus}")
    with connect(cluster) as c:
        yield from _imap(fn, items, w, c, desc, num_gpus, num_cpus, max_retries, progress,
                         stats)


def _imap(fn, items, weights, c, desc, num_gpus, num_cpus, max_retries, show, stats):
    per: dict[tuple[str, int], WorkerStats] = {}
    total = sum(weights)
    done = 0.0
    bar = Progress(max(int(round(total)), 1), desc or "items", enabled=show and bool(desc))
    scale = bar.total / total if total > 0 else 0.0

    def account(info, seconds):
        key = (info["node"], info["pid"])
        s = per.setdefault(key, WorkerStats(*key, node_id=info.get("node_id", "")))
        s.items += 1
        s.seconds += seconds

    with bar:
        if c is None:
            local = {"node": "local", "pid": os.getpid()}
            for i, item in enumerate(items):
                t0 = time.perf_counter()
                out = fn(item)
                account(local, time.perf_counter() - t0)
                done += weights[i]
                bar.update(int(done * scale))
                yield out
        else:
            if "<" in getattr(fn, "__qualname__", "<") or fn.__module__ == "__main__":
                raise GlossrtError("map_items: fn must be a module-level function of an "
                                   f"importable module (workers import it), got {fn!r}")
            ray = _ray()
            if num_gpus is None:  # the driver's variant decides
                num_gpus = 1 if c.variant == _GPU else 0
            # SPREAD: blocks go round the nodes from the start. Ray's default packs them on
            # the driver's node first, and short blocks all finished there before another
            # node's worker process had started (seen in CI: 32 blocks on one of two nodes)
            opts = dict(num_cpus=num_cpus, num_gpus=num_gpus, max_retries=max_retries,
                        scheduling_strategy="SPREAD")
            if c.task_env:
                opts["runtime_env"] = c.task_env
            task = _remote("_run").options(**opts)
            window = max(4 * c.cpus // max(num_cpus, 1), 8)
            pending: dict = {}  # ObjectRef -> item index
            ready: dict[int, object] = {}
            nxt = 0
            for want in range(len(items)):
                while nxt < len(items) and len(pending) + len(ready) < window:
                    pending[task.remote(fn, items[nxt], c.variant)] = nxt
                    nxt += 1
                while want not in ready:
                    finished, _ = ray.wait(list(pending), num_returns=1)
                    for ref in finished:
                        i = pending.pop(ref)
                        try:
                            out, info, seconds = ray.get(ref)
                        except Exception as e:
                            for r in pending:
                                ray.cancel(r, force=True)
                            raise ClusterError(f"{desc or 'map_items'}: item {i} failed: "
                                               f"{_cause(e)}") from None
                        account(info, seconds)
                        ready[i] = out
                        done += weights[i]
                        bar.update(int(done * scale))
                yield ready.pop(want)
    rows = sorted(per.values(), key=lambda s: (s.node, s.pid))
    if stats is not None:
        stats.extend(rows)
    if show and desc and c is not None:
        for s in rows:
            print(f"{desc}: {s}", file=sys.stderr)


def map_items(fn: Callable, items: Iterable, *, cluster=None, desc: str = "",
              weights: Sequence[float] | None = None, num_gpus: int | None = None,
              num_cpus: int = 1, max_retries: int = 3, progress: bool = True,
              stats: list[WorkerStats] | None = None) -> list:
    """``[fn(item) for item in items]``, the items spread over ``cluster`` (a spec for
    :func:`parse`, None = env ``GLOSSRT_CLUSTER``, or an open :class:`Cluster` from
    :func:`connect`); results in item order whatever the order the items finish in.

    ``fn``: a module-level function (workers import its module); items and results: plain
    picklable data. Each item is one Ray task of ``num_cpus`` CPUs (Dr.Jit's thread count on
    the worker) and ``num_gpus`` GPUs (0 or 1; default 1 when the driver runs the CUDA
    variant, else 0; Ray sets ``CUDA_VISIBLE_DEVICES``); a task
    whose worker dies is rerun up to ``max_retries`` times (an exception ``fn`` raises is not
    retried: it fails the run naming the node). ``weights``: each item's share of the
    progress bar (default 1; e.g. its samples); ``desc`` names the bar, and with a cluster
    the per-worker throughput is printed to stderr at the end. ``stats``: a list that gets
    one :class:`WorkerStats` per worker process. Without a cluster the items run in this
    process in order."""
    return list(imap_items(fn, list(items), cluster=cluster, desc=desc, weights=weights,
                           num_gpus=num_gpus, num_cpus=num_cpus, max_retries=max_retries,
                           progress=progress, stats=stats))


# -- data shared with the workers (issue 27: scenes travel as XML and files) ----------------
def share(value, cluster=None):
    """``value`` put once into the object store of the open ``cluster`` (a :class:`Cluster`
    from :func:`connect`): the returned reference travels inside work items at no cost and
    each worker fetches the value with :func:`resolve` (e.g. a scene bundle's bytes,
    :mod:`glossrt.scenefiles`). Without a cluster (None) ``value`` is returned as it is."""
    if cluster is None:
        return value
    return _ray().put(value)


def resolve(value):
    """On a worker: the value a :func:`share` reference stands for (Ray resolves references
    only when they are a task's own arguments, not inside an item's dict); anything else is
    returned as it is."""
    ray = sys.modules.get("ray")
    if ray is not None and isinstance(value, ray.ObjectRef):
        return ray.get(value)
    return value


def ship_scene(scene, cluster=None):
    """``scene`` as the workers of the open ``cluster`` get it: an XML file packed with the
    files it references (:func:`glossrt.scenefiles.bundle`), its bytes put once into the
    object store (:func:`share`); a built-in name, a scene without a cluster, or one already
    shipped, as it is. Workers turn either form into a path with :func:`local_scene`."""
    from . import scenefiles

    if cluster is None or not isinstance(scene, str) or not os.path.isfile(scene):
        return scene
    b = scenefiles.bundle(scene)
    return dict(b, data=share(b["data"], cluster))


def local_scene(scene) -> str:
    """On a worker: the path (or built-in name) of a scene from :func:`ship_scene`, a shipped
    bundle unpacked once per node (:func:`glossrt.scenefiles.materialise`)."""
    from . import scenefiles

    return scenefiles.materialise(scene, fetch=resolve)
