"""The viewer's world axes and its "look through camera" button, at server level (no browser): the axes follow
the scene's extent and stay clear of the scene box; the button puts each connected page's camera at the chosen
camera's centre, looking down its +z axis with its -y axis up and its vertical field of view. A page is stood in
for by a plain websocket client that reports a camera, as viser's page does when it connects."""
import dataclasses
import threading
import time
from pathlib import Path

import numpy as np
import pytest

viser = pytest.importorskip("viser")

from ev3dgs.view import data  # noqa: E402
from ev3dgs.view.server import CLIENT_FIX, Viewer, axes_origin, camera_view  # noqa: E402

from view_scene import D, EXPOSURE_US, H, PERIOD_US, S, make_scene, pose_at  # noqa: E402

F32 = np.finfo(np.float32).eps


@pytest.fixture(scope="module")
def scene_path(tmp_path_factory):
    return make_scene(tmp_path_factory.mktemp("viewcam") / "scene.h5")


@pytest.fixture(scope="module")
def content(scene_path):
    return data.load_scene(scene_path)


@pytest.mark.parametrize("scale", [0.01, 1.0, 250.0])
def test_axes_follow_the_extent_and_stay_thin(content, scale):
    extent = 2.0 * scale
    c = dataclasses.replace(content, extent=extent)
    v = Viewer("127.0.0.1", 0)
    try:
        v.show_scene(c)
        assert 0.10 * extent <= v.axes.axes_length <= 0.20 * extent
        assert 0 < v.axes.axes_radius <= 0.03 * v.axes.axes_length
    finally:
        v.stop()


def test_axes_sit_at_the_corner_of_the_scene_box(content):
    # the test scene's box is [-0.6, 0.6]^3: it holds the origin, so the axes go to its lowest corner
    np.testing.assert_allclose(axes_origin(content), [-0.6, -0.6, -0.6])
    outside = dataclasses.replace(content, scene=dataclasses.replace(
        content.scene, bounds=np.array([[1.0, 1.0, 1.0], [2.0, 2.0, 2.0]])))
    np.testing.assert_array_equal(axes_origin(outside), [0, 0, 0])  # the origin is clear: true world axes


def test_camera_view_of_a_pinhole():
    # a camera at (1, 2, 3) looking along world +x (its z axis), its x axis world -y, its y axis (down) world -z
    R = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    c2w = np.eye(4)
    c2w[:3, :3], c2w[:3, 3] = R, [1, 2, 3]
    K = np.array([[50.0, 0, 24], [0, 50.0, 16], [0, 0, 1]])
    v = camera_view(c2w, K, 48, 32, 2.0)
    np.testing.assert_allclose(v["position"], [1, 2, 3])
    np.testing.assert_allclose(v["look_at"], [3, 2, 3])
    np.testing.assert_allclose(v["up_direction"], [0, 0, 1])
    assert v["fov"] == pytest.approx(2 * np.arctan(16 / 50))


class FakePage:
    """A websocket client that speaks viser's protocol far enough to be a connected page: it reports one
    camera and drains what the server sends."""

    def __init__(self, port: int):
        from websockets.sync.client import connect

        self.ws = connect(f"ws://127.0.0.1:{port}", subprotocols=[f"viser-v{viser.__version__}"],
                          max_size=None)
        self.reader = threading.Thread(target=self._drain, daemon=True)
        self.reader.start()

    def _drain(self):
        try:
            while True:
                self.ws.recv()
        except Exception:
            pass

    def report_camera(self):
        import msgspec

        from viser import _messages

        m = _messages.ViewerCameraMessage(wxyz=(1.0, 0.0, 0.0, 0.0), position=(0.0, 0.0, -5.0), fov=1.0,
                                          near=0.01, far=1000.0, image_height=800, image_width=1280,
                                          look_at=(0.0, 0.0, 0.0), up_direction=(0.0, -1.0, 0.0))
        self.ws.send(msgspec.msgpack.encode(m.as_serializable_dict()))

    def close(self):
        self.ws.close()


def _connected_client(v: Viewer, page: FakePage, timeout=20.0):
    end = time.time() + timeout
    while time.time() < end:
        for client in v.server.get_clients().values():
            try:
                client.camera.position
                return client
            except AssertionError:
                pass
        time.sleep(0.05)
    raise AssertionError("the page's camera never reached the server")


def _check_looks_through(cam, c2w, K, tol):
    R, centre = c2w[:3, :3], c2w[:3, 3]
    np.testing.assert_allclose(cam.position, centre, atol=tol)
    look = np.asarray(cam.look_at) - np.asarray(cam.position)
    np.testing.assert_allclose(look / np.linalg.norm(look), R[:, 2], atol=tol)
    up = np.asarray(cam.up_direction)
    np.testing.assert_allclose(up / np.linalg.norm(up), -R[:, 1], atol=tol)
    Rq = viser.transforms.SO3(np.asarray(cam.wxyz)).as_matrix()  # the page's camera-to-world rotation
    np.testing.assert_allclose(Rq, R, atol=tol)
    assert cam.fov == pytest.approx(2 * np.arctan(0.5 * H / K[1, 1]), abs=tol)


def test_look_through_training_and_test_cameras(content):
    v = Viewer("127.0.0.1", 0)
    page = FakePage(v.port)
    try:
        v.show_scene(content, select=1)
        page.report_camera()
        client = _connected_client(v, page)
        K = content.scene.camera.K
        # the scene file stores float32 poses: agreement to a few float32 roundings of the scene's size
        tol = 16 * F32 * max(1.0, D)
        press = v.look_button._impl.update_cb
        assert len(press) == 1
        v._select(3)
        press[0](None)
        mid_t = 3 * PERIOD_US + (S // 2) * EXPOSURE_US // (S - 1)   # view 3's middle pose sample
        _check_looks_through(client.camera, pose_at(mid_t), K, tol)
        v.look_choice.value = "test view 1"
        press[0](None)
        _check_looks_through(client.camera, content.test_poses[1], K, tol)
    finally:
        page.close()
        v.stop()


def test_served_page_carries_the_client_fix(scene_path):
    import urllib.request

    v = Viewer("127.0.0.1", 0)
    try:
        with urllib.request.urlopen(v.url, timeout=30) as r:
            html = r.read().decode()
        stock = (Path(viser.__file__).parent / "client" / "build" / "index.html").read_text(encoding="utf-8")
        # the fix runs first in <head>, before viser's client script; the rest is viser's page unchanged
        assert html == stock.replace("<head>", "<head>" + CLIENT_FIX, 1) and html != stock
    finally:
        v.stop()
