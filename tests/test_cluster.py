"""Scale-out on Ray (glossrt.cluster, glossrt.render.blocks, `render --reference --cluster`).

One local Ray instance with 2 worker slots serves the module (started once: a few seconds);
the last test shuts it down and checks that no process it started is left.
"""

import os
import shutil
import signal
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import ray

from glossrt import cluster, scenes
from glossrt.cli import main
from glossrt.errors import GlossrtError
from glossrt.frame import Frame
from glossrt.render import Renderer, blocks

# this module's work functions travel by value (workers cannot import a test module)
ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])

W, H, SPP = 32, 24, 6
JOB = {"scene": "glossy-cornell", "size": [W, H], "orbit": None, "frames": 2,
       "max_depth": None, "seed": 3}


def _descendants(pid: int) -> set[int]:
    children: dict[int, list[int]] = {}
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                ppid = int(Path(f"/proc/{d}/stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            children.setdefault(ppid, []).append(int(d))
    out, todo = set(), [pid]
    while todo:
        for c in children.get(todo.pop(), []):
            out.add(c)
            todo.append(c)
    return out


class _Session:
    def __init__(self):
        self.cm = cluster.connect("local:2")
        t0 = time.perf_counter()
        self.c = self.cm.__enter__()
        self.startup_s = time.perf_counter() - t0
        self.procs = _descendants(os.getpid())

    def close(self):
        if self.cm is not None:
            self.cm.__exit__(None, None, None)
            self.cm = None


@pytest.fixture(scope="module")
def local2():
    s = _Session()
    yield s
    s.close()


@pytest.fixture(scope="module")
def renderer():
    setup = scenes.load("glossy-cornell", size=(W, H), frames=2)
    return Renderer(setup, seed=JOB["seed"], frozen=False)


def _items(frame=1, block_spp=1):
    plan = blocks.block_plan(SPP, W, H, block_spp)
    return [{"job": JOB, "frame": frame, "start": s, "count": c} for s, c in plan]


def _merge(renderer, results, frame=1):
    m = blocks.BlockMerge()
    for r in results:
        m.add(r)
    return m.frame(renderer, frame, 0.0, 1)


def _same(a: Frame, b: Frame) -> None:
    assert a.names == b.names
    for n in a.names:
        assert np.array_equal(a.numpy(n), b.numpy(n)), n


def _sleepy(i):  # later items finish first
    time.sleep(0.03 * (8 - i))
    return i * i


def _threads(_):
    import drjit as dr

    return dr.thread_count()


def _reversed_block(item):
    time.sleep(0.15 * (SPP - item["start"]))
    return blocks.render_reference_block(item)


def _die_once(item):
    """Kills its own worker process the first time block 2 runs."""
    marker = Path(item["marker"])
    if item["start"] == 2 and not marker.exists():
        marker.write_text(str(os.getpid()))
        os.kill(os.getpid(), signal.SIGKILL)
    return blocks.render_reference_block(item)


def _fails(item):
    raise GlossrtError(f"bad item {item}")


# -- specs ----------------------------------------------------------------------------------
def test_parse(monkeypatch):
    assert cluster.parse("local") == cluster.Spec("local")
    assert cluster.parse("local:3") == cluster.Spec("local", cpus=3)
    assert cluster.parse("auto").kind == "auto"
    assert cluster.parse("ray://10.0.0.1:10001").address == "ray://10.0.0.1:10001"
    assert cluster.parse("") is None and cluster.parse("none") is None
    monkeypatch.setenv("GLOSSRT_CLUSTER", "local:2")
    assert cluster.parse(None) == cluster.Spec("local", cpus=2)
    monkeypatch.delenv("GLOSSRT_CLUSTER")
    assert cluster.parse(None) is None
    for bad in ("local:0", "local:x", "remote", "ray://host", "ray://host:99999", "http://a:1"):
        with pytest.raises(GlossrtError, match="cluster"):
            cluster.parse(bad)


def test_bad_address_fails_fast(tmp_path, capsys, monkeypatch):
    with socket_port() as port:  # a port nothing listens on
        t0 = time.perf_counter()
        with pytest.raises(GlossrtError, match="cannot reach Ray cluster"):
            with cluster.connect(f"ray://127.0.0.1:{port}"):
                pass
        rc = main(["render", "glossy-cornell", "--reference", "--spp", "2", "--size", "8x6",
                   "--out", str(tmp_path / "o"), "--cluster", f"ray://127.0.0.1:{port}"])
        # `auto` where a dead cluster's address is recorded (Ray alone waits a minute)
        monkeypatch.setenv("RAY_ADDRESS", f"127.0.0.1:{port}")
        with pytest.raises(GlossrtError, match="cannot reach Ray cluster auto"):
            with cluster.connect("auto"):
                pass
        assert time.perf_counter() - t0 < 15
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "cannot reach Ray cluster" in err[0]
    assert not (tmp_path / "o").exists()
    rc = main(["render", "glossy-cornell", "--reference", "--out", str(tmp_path / "o"),
               "--cluster", "local:0"])
    assert rc == 2 and not (tmp_path / "o").exists()


class socket_port:
    def __enter__(self):
        import socket

        s = socket.socket()
        s.bind(("127.0.0.1", 0))
        self.port = s.getsockname()[1]
        s.close()
        return self.port

    def __exit__(self, *exc):
        return False


# -- map_items ------------------------------------------------------------------------------
def test_map_items_order_threads_and_stats(local2):
    stats = []
    t0 = time.perf_counter()
    assert cluster.map_items(_sleepy, range(8), cluster=local2.c, stats=stats) == \
        [i * i for i in range(8)]
    assert sum(s.items for s in stats) == 8 and len({s.pid for s in stats}) <= 2
    assert time.perf_counter() - t0 < 30
    assert cluster.map_items(_sleepy, range(3)) == [0, 1, 4]  # no cluster: in process
    # Dr.Jit's thread count is the CPUs Ray gave the task
    assert cluster.map_items(_threads, range(2), cluster=local2.c) == [1, 1]
    assert cluster.map_items(_threads, range(1), cluster=local2.c, num_cpus=2) == [2]
    assert local2.c.nodes and all(n["variant"] == local2.c.variant for n in local2.c.nodes)


def test_worker_error_names_node(local2):
    with pytest.raises(GlossrtError, match=r"item 0 failed: .*on node .*bad item"):
        cluster.map_items(_fails, [5], cluster=local2.c)


def test_version_mismatch_refused(local2, monkeypatch):
    import glossrt

    monkeypatch.setattr(glossrt, "__version__", "0.0.0-other")
    with pytest.raises(GlossrtError, match="refusing to mix versions"):
        with cluster.connect(local2.c.spec):
            pass


def test_node_without_libllvm_refused(local2):
    # a worker whose libLLVM cannot be found: the run fails at once, naming the node
    bad = {"DRJIT_LIBLLVM_PATH": "/nonexistent/libLLVM-19.so"}
    with pytest.raises(GlossrtError, match=r"node \S+ cannot run glossrt: .*libLLVM"):
        with cluster.connect(local2.c.spec, worker_env=bad):
            pass


# -- references -----------------------------------------------------------------------------
def test_block_plan():
    assert blocks.block_plan(6, W, H, 4) == [(0, 4), (4, 2)]
    assert blocks.block_plan(1000, W, H) == [(s, min(63, 1000 - s)) for s in range(0, 1000, 63)]
    assert blocks.block_plan(64, 2048, 2048) == [(s, 1) for s in range(64)]  # lane budget
    with pytest.raises(GlossrtError):
        blocks.block_plan(0, W, H)


def test_blocks_equal_render_reference(renderer):
    # the same samples (seeds) as Renderer.render_reference, which sums them in float32 on
    # the device: equal up to float32 rounding
    ref = renderer.render_reference(1, SPP)
    got = _merge(renderer, cluster.map_items(blocks.render_reference_block, _items()))
    assert got.names == ref.names and got.meta["spp"] == SPP
    for n in ref.names:
        np.testing.assert_allclose(got.numpy(n), ref.numpy(n), rtol=2e-6, atol=2e-7,
                                   err_msg=n)
    assert np.abs(got.numpy("color")).max() > 0


def test_reference_bit_identical_0_and_2_workers(local2, renderer):
    solo = _merge(renderer, cluster.map_items(blocks.render_reference_block, _items()))
    two = _merge(renderer, cluster.map_items(blocks.render_reference_block, _items(),
                                             cluster=local2.c))
    _same(solo, two)
    # finishing in reverse order (last block first) changes nothing
    _same(solo, _merge(renderer, cluster.map_items(_reversed_block, _items(),
                                                   cluster=local2.c)))


def test_killed_worker_rerun(local2, renderer, tmp_path):
    marker = tmp_path / "killed"
    items = [dict(it, marker=str(marker)) for it in _items()]
    solo = _merge(renderer, cluster.map_items(blocks.render_reference_block, _items()))
    got = _merge(renderer, cluster.map_items(_die_once, items, cluster=local2.c))
    assert marker.exists()  # a worker was killed mid-run, its block rerun elsewhere
    _same(solo, got)


def _cli(out, *extra):
    return main(["render", "glossy-cornell", "--reference", "--spp", str(SPP), "--size",
                 f"{W}x{H}", "--frames", "3", "--seed", "3", "--block-spp", "2",
                 "--out", str(out), *extra])


def test_cli_resume_after_killed_driver(local2, tmp_path, capsys):
    full = tmp_path / "full"
    assert _cli(full) == 0  # in this process
    part = tmp_path / "part"
    part.mkdir()
    shutil.copy(full / "frame_0000.exr", part / "frame_0000.exr")  # the driver died then
    kept = (part / "frame_0000.exr").stat().st_mtime_ns
    assert _cli(part, "--resume", "--cluster", "local:2") == 0
    assert "1 complete one(s) kept" in capsys.readouterr().out
    assert (part / "frame_0000.exr").stat().st_mtime_ns == kept
    for i in range(3):
        _same(Frame.load(full / f"frame_000{i}.exr"), Frame.load(part / f"frame_000{i}.exr"))
    # a header of another request is refused, nothing written
    before = {p.name: p.stat().st_mtime_ns for p in part.iterdir()}
    (part / "frame_0002.exr").unlink()
    capsys.readouterr()
    for extra in (("--seed", "4"), ("--spp", "8"), ("--block-spp", "3")):
        args = {"--seed": "3", "--spp": str(SPP), "--block-spp": "2"}
        args[extra[0]] = extra[1]
        assert main(["render", "glossy-cornell", "--reference", "--size", f"{W}x{H}",
                     "--frames", "3", "--resume", "--out", str(part),
                     *(x for kv in args.items() for x in kv)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "--resume" in err[0] and "another request" in err[0], err
    assert not (part / "frame_0002.exr").exists()
    assert all(p.stat().st_mtime_ns == before[p.name] for p in part.iterdir())


def test_shutdown_leaves_no_process(local2):
    assert local2.startup_s < 60
    procs = _descendants(os.getpid()) | local2.procs
    assert procs  # Ray's own processes (gcs, raylet, workers) were children of the test
    local2.close()
    assert not ray.is_initialized()
    deadline = time.time() + 20
    while time.time() < deadline:
        left = [p for p in procs if Path(f"/proc/{p}").exists()
                and "ray" in Path(f"/proc/{p}/cmdline").read_bytes().decode(errors="replace")]
        if not left:
            break
        time.sleep(0.2)
    assert not left, left
