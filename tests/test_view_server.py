"""The viser server of `ev3dgs view` without a browser: what its panel holds for a selected view, the live
training hook, and the process as a user runs it (URL printed, 127.0.0.1, a taken port, 0.0.0.0 warning,
Ctrl-C). The page in a real browser: tests/test_view_browser.py (slow)."""
import os
import re
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("viser")

from ev3dgs.event_file import EventFile  # noqa: E402
from ev3dgs.view import data  # noqa: E402
from ev3dgs.view.server import Viewer  # noqa: E402

from view_scene import N, make_scene  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def scene_path(tmp_path_factory):
    return make_scene(tmp_path_factory.mktemp("viewsrv") / "scene.h5")


def test_panel_shows_the_selected_view(scene_path):
    c = data.load_scene(scene_path)
    v = Viewer("127.0.0.1", 0)
    try:
        v.show_scene(c, select=2)
        np.testing.assert_array_equal(v.frame_image.image, c.frame(2))
        np.testing.assert_array_equal(v.sharp_image.image, c.sharp(2))
        v._select(3)
        v.time_slider.value = 50
        v._update_events()
        np.testing.assert_array_equal(v.frame_image.image, c.frame(3))
        with EventFile(scene_path) as r:
            on, off = c.event_counts(r, 3, 0.5)
        np.testing.assert_array_equal(v.event_image.image, data.event_image(on, off))
        assert "**view 3**" in v.caption.content and f"{int(on.sum())} ON" in v.caption.content
        assert v._frusta[3].color == (20, 160, 60) and v._frusta[2].color != (20, 160, 60)
    finally:
        v.stop()


def test_live_update_every_n_steps(scene_path):
    from ev3dgs.view.live import LiveUpdate

    class FakeViewer:
        def __init__(self):
            self.splats, self.status = [], ""

        def show_splats(self, arrays):
            self.splats.append(arrays)

        def set_status(self, text):
            self.status = text

    class FakeTrainer:
        def __init__(self):
            from ev3dgs.splat.model import GaussianModel

            rng = np.random.default_rng(0)
            self.model = GaussianModel.from_points(rng.normal(size=(20, 3)), rng.integers(0, 255, (20, 3)))
            self.step = 0

    fv, tr = FakeViewer(), FakeTrainer()
    hook = LiveUpdate(fv, every=10, iterations=25)
    for step in range(1, 26):
        tr.step = step
        hook(tr, {"loss": 0.5, "psnr_blurry": 20.0})
    assert hook.updates == 3 == len(fv.splats)          # steps 10, 20 and the last one, 25
    assert "step 25/25" in fv.status
    np.testing.assert_array_equal(fv.splats[-1]["centers"], tr.model.means.detach().numpy())


def _start(args):
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.Popen([sys.executable, "-m", "ev3dgs.cli.main", "view", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env)


def _url(proc, timeout=120) -> str:
    """The URL line the viewer prints once it serves."""
    end = time.time() + timeout
    while time.time() < end:
        line = proc.stdout.readline()
        if not line:
            break
        m = re.search(r"(http://\S+)", line)
        if m:
            return m.group(1)
    proc.kill()
    raise AssertionError(f"no URL printed; stderr: {proc.stderr.read()}")


def _stop(proc) -> tuple[int, str]:
    proc.send_signal(signal.SIGINT)
    try:
        proc.wait(timeout=30)
    except subprocess.TimeoutExpired:
        proc.kill()
        raise AssertionError("the viewer did not stop on SIGINT")
    return proc.returncode, proc.stderr.read()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_serves_on_localhost_and_stops_on_ctrl_c(scene_path):
    port = _free_port()
    proc = _start([scene_path, "--port", str(port)])
    url = _url(proc)
    try:
        assert url == f"http://127.0.0.1:{port}"
        with urllib.request.urlopen(url, timeout=30) as r:
            assert r.status == 200 and b"<html" in r.read().lower()
    finally:
        rc, err = _stop(proc)
    assert rc == 0 and "Traceback" not in err and "viewer stopped" in err


def test_taken_port_and_all_interfaces_warning(scene_path):
    with socket.socket() as busy:
        busy.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        busy.bind(("0.0.0.0", 0))
        busy.listen(1)
        port = busy.getsockname()[1]
        proc = _start([scene_path, "--host", "0.0.0.0", "--port", str(port)])
        url = _url(proc)
        rc, err = _stop(proc)
    got = int(url.rsplit(":", 1)[1])
    assert got != port and f"port {port} is in use: using {got}" in err
    assert "warning: --host 0.0.0.0" in err
    assert rc == 0 and "Traceback" not in err


def test_train_with_view_then_view_the_checkpoint(scene_path, tmp_path, capsys):
    """`ev3dgs train --view`: the viewer's URL is printed, training finishes and the viewer stops; a run
    folder with only ckpt.pt (a run still training) is viewable from its checkpoint."""
    from ev3dgs.cli import main as cli

    run = tmp_path / "run"
    rc = cli.main(["train", scene_path, "--out", str(run), "--iterations", "6", "--set", "init_points=200",
                   "--set", "sh_degree=0", "--set", "checkpoint_every=3", "--threads", "1", "--quiet",
                   "--view", "--set", "view.every=3", "--set", "view.port=0"])
    out = capsys.readouterr().out
    assert rc == 0 and re.search(r"ev3dgs view: http://127\.0\.0\.1:\d+", out)
    (run / "model.pt").unlink()
    rc_content = data.load(run)
    assert rc_content.source == "ckpt.pt (step 6)" and len(rc_content.model) > 0
    assert cli.main(["train", scene_path, "--out", str(run), "--view", "--set", "view.port=99999"]) == 2


@pytest.mark.parametrize("host,why", [("256.1.1.1", "not an address or a name that resolves"),
                                      ("192.0.2.1", "no local network interface has that address")])
def test_an_address_that_cannot_be_bound_is_one_line_not_a_hang(scene_path, host, why):
    """Binding is tried on this host alone (no traffic): an invalid address, or one no interface has, fails
    at once with exit 2 instead of leaving the command waiting with no listener."""
    t = time.monotonic()
    r = subprocess.run([sys.executable, "-m", "ev3dgs.cli.main", "view", str(scene_path), "--host", host,
                        "--port", "0"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and why in r.stderr, r.stderr
    assert "Traceback" not in r.stderr and time.monotonic() - t < 60
