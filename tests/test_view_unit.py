"""The live viewer's pieces that need no server (issue 26): event coalescing, the camera
conversion (against Mitsuba's own perspective sensor), light gizmos, layer images."""

from __future__ import annotations

import math
import threading

import numpy as np
import pytest

from glossrt.view import camera as vc
from glossrt.view import layers
from glossrt.view.inbox import Inbox


def test_inbox_latest_value_wins_and_nothing_queues():
    box = Inbox()

    def burst(k: int) -> None:
        for i in range(500):
            box.post("camera", (k, i))
            box.post("option:exposure", float(i))

    threads = [threading.Thread(target=burst, args=(k,)) for k in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert box.pending() == 2  # 4000 events, two keys
    box.act("capture")
    box.act("capture")
    values, actions = box.take()
    assert set(values) == {"camera", "option:exposure"}
    assert values["camera"][1] == 499 and values["option:exposure"] == 499.0
    assert actions["capture"] == 2  # actions are counted, not merged away
    assert box.take() == ({}, {})


def test_inbox_take_waits_and_wakes():
    box = Inbox()
    threading.Timer(0.05, lambda: box.post("layer", "direct")).start()
    values, _ = box.take(timeout=5.0)
    assert values == {"layer": "direct"}


def _mitsuba_ray_angle(fov_x_deg: float, size, film_xy) -> float:
    """Angle between the centre ray and the ray through film point ``film_xy`` (in [0, 1]^2)
    of a Mitsuba perspective sensor: an independent pinhole."""
    import mitsuba as mi

    from glossrt import backend

    backend.ensure()
    s = mi.load_dict({"type": "perspective", "fov": fov_x_deg, "fov_axis": "x",
                      "film": {"type": "hdrfilm", "width": size[0], "height": size[1]}})
    d = []
    for xy in ((0.5, 0.5), film_xy):
        ray, _ = s.sample_ray(0.0, 0.5, mi.ScalarPoint2f(*xy), mi.ScalarPoint2f(0.5, 0.5))
        d.append(np.array([ray.d[0], ray.d[1], ray.d[2]], np.float64).ravel())
    return math.acos(float(np.clip(np.dot(d[0], d[1]), -1.0, 1.0)))


@pytest.mark.parametrize("size,fov_y", [((320, 180), 0.9), ((64, 48), 1.3), ((90, 160), 0.5)])
def test_viser_vertical_fov_is_mitsubas_image_height(size, fov_y):
    # viser states a vertical field of view: the ray through the top edge's centre must make
    # half of it with the view axis in the Mitsuba sensor glossrt builds from it
    fov_x = vc.fov_x_degrees(fov_y, size)
    assert _mitsuba_ray_angle(fov_x, size, (0.5, 0.0)) == pytest.approx(0.5 * fov_y, rel=1e-5)
    assert _mitsuba_ray_angle(fov_x, size, (0.0, 0.5)) == pytest.approx(
        math.radians(0.5 * fov_x), rel=1e-5)
    assert vc.fov_y_radians(fov_x, size) == pytest.approx(fov_y, rel=1e-12)


def test_camera_round_trip_through_a_look_at_matrix():
    from glossrt.scenes import look_at

    cam = vc.ViewerCamera((1.0, 2.0, 5.0), (0.2, 0.5, -1.0), (0.0, 1.0, 0.0), 0.8)
    kw = vc.to_pipeline(cam, (320, 180))
    m = np.asarray(look_at(list(kw["position"]), list(kw["target"]), list(kw["up"])))
    back = vc.from_pipeline(m, kw["fov"], (320, 180), pivot=cam.look_at)
    assert np.allclose(back.position, cam.position, atol=1e-5)
    assert np.allclose(back.look_at, cam.look_at, atol=1e-4)
    assert back.fov_y == pytest.approx(cam.fov_y, rel=1e-9)
    # the up it reports is the camera's own (orthogonal to the view axis), in up's half-space
    fwd = np.subtract(cam.look_at, cam.position)
    assert abs(np.dot(back.up, fwd)) < 1e-5 and back.up[1] > 0.9
    assert back.close_to(vc.ViewerCamera(back.position, back.look_at, back.up, back.fov_y))
    assert not back.close_to(cam) and not back.close_to(None)
    # the orbit point moved along the view axis: the same picture, the same camera
    far = tuple(np.add(cam.position, 3.0 * np.subtract(cam.look_at, cam.position)))
    assert cam.close_to(vc.ViewerCamera(cam.position, far, cam.up, cam.fov_y))


def test_gizmo_matrix_rotates_about_the_light_centre():
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(3)
    centre = np.array([0.3, 1.9, -0.4])
    pos = np.array([1.0, 1.5, 0.2])
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    m = vc.gizmo_matrix(pos, q, centre)
    verts = centre + rng.normal(size=(4, 3)) * 0.2
    moved = (m[:3, :3] @ verts.T).T + m[:3, 3]
    # scipy takes (x, y, z, w); viser states (w, x, y, z)
    r = Rotation.from_quat([q[1], q[2], q[3], q[0]])
    assert np.allclose(moved, pos + r.apply(verts - centre), atol=1e-12)
    assert np.allclose(m @ np.append(centre, 1.0), np.append(pos, 1.0))


def test_layer_images():
    names = layers.names(["color", "emission", "normal", "depth", "direct", "indirect",
                          "composite", "mesh_id", "motion"])
    assert names[:6] == ["color", "composite", "direct", "indirect", "reference", "error"]
    h, w = 6, 8
    n = np.zeros((h, w, 3))
    n[..., 2] = 1.0
    assert (layers.visualise("normal", n)[..., 2] == 255).all()
    assert (layers.visualise("normal", n)[..., 0] == 128).all()
    depth = np.linspace(1.0, 2.0, h * w).reshape(h, w, 1)
    depth[0, 0] = np.inf  # background
    img = layers.visualise("depth", depth)
    assert img[0, 0, 0] == 0 and img[-1, -1, 0] == 255
    ids = layers.visualise("mesh_id", np.arange(h * w, dtype=float).reshape(h, w, 1) % 3)
    assert (ids[0, 0] == 0).all() and not np.array_equal(ids[0, 1], ids[0, 2])
    # the error map: black where equal, the brightest colour at the scale and above
    ref = np.full((h, w, 3), 0.5)
    img = ref.copy()
    img[0, 0] += 10.0
    e = layers.error_map(img, ref, scale=0.25)
    assert e.shape == (h, w, 3) and e.dtype == np.uint8
    assert e[1, 1].sum() < 10 and e[0, 0].sum() > 600


def test_a_client_s_first_reports_are_the_sync_not_a_move(monkeypatch):
    """A client's reports before it echoes the camera the viewer sent are ignored for
    SYNC_SECONDS from its *first* report, however late that comes (a slow page load); after
    the echo, a report that differs is a move."""
    from types import SimpleNamespace

    from glossrt.view import app

    clock = [100.0]
    monkeypatch.setattr(app.time, "monotonic", lambda: clock[0])
    sent = vc.ViewerCamera((0.0, 1.0, 3.0), (0.0, 1.0, 0.0), (0.0, 1.0, 0.0), 0.6)
    posted: list = []
    fake = SimpleNamespace(_syncing_clients={}, _sent_camera=None, _camera=sent,
                           inbox=SimpleNamespace(post=lambda k, v: posted.append((k, v))))
    client = SimpleNamespace(client_id=7, camera=SimpleNamespace(), atomic=lambda: _Null())
    app.Viewer._send_camera(fake, client, sent)

    def report(c: vc.ViewerCamera) -> None:
        app.Viewer._on_camera(fake, 7, SimpleNamespace(position=c.position, look_at=c.look_at,
                                                      up_direction=c.up, fov=c.fov_y))

    default = vc.ViewerCamera((3.0, 3.0, 3.0), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0), 0.6)
    clock[0] += 3 * app.SYNC_SECONDS  # the page took long to load
    report(default)  # an intermediate state of the sync
    clock[0] += 0.5 * app.SYNC_SECONDS
    report(default)
    assert posted == []
    report(sent)  # the echo: in sync
    assert posted == [] and 7 not in fake._syncing_clients
    report(default)  # now a user's move
    assert posted == [("camera", default)]
    # a client that never echoes: its reports count as moves once the window has passed
    app.Viewer._send_camera(fake, client, sent)
    posted.clear()
    report(default)
    clock[0] += 1.01 * app.SYNC_SECONDS
    report(default)
    assert posted == [("camera", default)]


class _Null:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False
