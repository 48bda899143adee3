"""The browser viewer: the content of data.py put into a viser server (optional extra ``ev3dgs[view]``).

Scene tree: /world (grid) and /world/axes (thin axes about 15 % of the scene's size, at the corner of the scene
box so they hide none of it; size and place printed in the panel), /train (frusta with thumbnails, exposure
trajectories, start and end markers), /test, /points, /imu (gyro-integrated orientations), /refined (a run's
refined trajectories), /splats (the Gaussians). The panel shows the selected view's blurry frame, its sharp
frame and the events of its exposure up to a time chosen with a slider, and a button that puts the browser's
camera at a training or test camera (its pose and vertical field of view).
"""
from __future__ import annotations

import contextlib
import io
import signal
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from .. import palette
from ..errors import Ev3dgsError
from ..event_file import EventFile
from . import data

TRAIN_COLOUR = (230, 120, 20)      # training frusta and trajectories
SELECTED_COLOUR = (20, 160, 60)
TEST_COLOUR = (80, 80, 200)
REFINED_COLOUR = (200, 30, 160)
START_COLOUR, END_COLOUR = (20, 160, 60), (200, 30, 30)
THUMB_PX = 128
AXES_FRACTION = 0.15               # world axes length / scene extent
AXES_THICKNESS = 0.02              # axes radius / axes length
SELECTED_TRAIN = "selected training view"

# viser's Gaussian-splat mesh draws one quad per Gaussian from a 2-D "position" attribute (its shader reads
# position.xy; WebGL feeds z = 0). three.js reads a z for every vertex when it computes a geometry's bounding
# sphere (for frustum culling and for depth-sorting transparent objects), finds none for the last vertex, and
# logs "computeBoundingSphere(): Computed radius is NaN" on every page with splats. CLIENT_FIX gives such a
# geometry the same corners with z = 0 written out (drawn identically, bounds now finite) and turns culling off
# for its mesh (the quad's bounds say nothing about where the shader places the splats; viser does the same for
# its other shader-placed meshes). It runs before each render of every three.js Scene, which three.js
# announces on window.__THREE_DEVTOOLS__ as it creates it; the script provides that before viser's client loads.
CLIENT_FIX = """<script>(() => {
  const hub = window.__THREE_DEVTOOLS__ || (window.__THREE_DEVTOOLS__ = new EventTarget());
  const fix = (o) => {
    const g = o.isMesh && o.geometry, p = g && g.attributes.position;
    if (!p || p.itemSize !== 2 || p.isInterleavedBufferAttribute) return;
    const xyz = new Float32Array(3 * p.count);
    for (let i = 0; i < p.count; i++) { xyz[3 * i] = p.getX(i); xyz[3 * i + 1] = p.getY(i); }
    g.setAttribute("position", new p.constructor(xyz, 3));
    g.boundingBox = null;
    g.boundingSphere = null;
    o.frustumCulled = false;
  };
  hub.addEventListener("observe", (e) => {
    const scene = e.detail;
    if (!scene || !scene.isScene) return;
    const before = scene.onBeforeRender;
    scene.onBeforeRender = function (...args) {
      scene.traverse(fix);
      return before.apply(this, args);
    };
  });
})();</script>"""


def require_viser():
    try:
        import viser
    except ImportError:
        raise Ev3dgsError("`ev3dgs view` needs the optional package viser, which is not installed: "
                          "pip install ev3dgs[view] (or give --out FILE.png for a static figure)") from None
    return viser


def _thumb(img: np.ndarray) -> np.ndarray:
    h, w = img.shape[:2]
    step = max(1, int(np.ceil(max(h, w) / THUMB_PX)))
    return np.ascontiguousarray(img[::step, ::step])


def _nice_length(extent: float) -> float:
    """A round length (1, 2 or 5 times a power of ten) near a quarter of the scene's size."""
    target = max(extent / 4, 1e-6)
    p = 10 ** np.floor(np.log10(target))
    return float(min((m * p for m in (1, 2, 5, 10)), key=lambda v: abs(np.log(v / target))))


def axes_length(extent: float) -> float:
    """The world axes' length: AXES_FRACTION of the scene's extent."""
    return AXES_FRACTION * max(float(extent), 1e-6)


def axes_origin(c: data.SceneContent) -> np.ndarray:
    """Where the world axes are drawn: the world origin when it lies outside the scene box (the scene's bounds,
    else its points' box, else the camera centres' box), otherwise the box's lowest corner, so the axes run
    along the box's edges and not through what it holds."""
    sc = c.scene
    if sc.bounds is not None:
        box = np.asarray(sc.bounds, np.float64)
    elif sc.points is not None and len(sc.points.xyz):
        xyz = np.asarray(sc.points.xyz, np.float64)
        box = np.stack([xyz.min(axis=0), xyz.max(axis=0)])
    elif c.train_poses is not None:
        centres = c.train_poses[:, :, :3, 3].reshape(-1, 3)
        box = np.stack([centres.min(axis=0), centres.max(axis=0)])
    else:
        return np.zeros(3)
    if not np.isfinite(box).all() or ((box[0] > 0) | (box[1] < 0)).any():
        return np.zeros(3)
    return box[0].copy()


def _target(c: data.SceneContent) -> np.ndarray:
    """The point the opening view looks at: the scene box's centre, else the points' median, else the
    cameras' mean centre."""
    sc = c.scene
    if sc.bounds is not None:
        return np.asarray(sc.bounds, np.float64).mean(axis=0)
    if sc.points is not None and len(sc.points.xyz):
        return np.median(np.asarray(sc.points.xyz, np.float64), axis=0)
    return c.mid_poses()[:, :3, 3].mean(axis=0)


def camera_view(c2w: np.ndarray, K: np.ndarray, width: int, height: int, distance: float) -> dict:
    """The browser camera that looks through a pinhole camera (OpenCV camera-to-world pose: x right, y down,
    z forward): its centre, a look-at point `distance` ahead on its +z axis, up = its -y axis, and the vertical
    field of view of its image (radians)."""
    c2w = np.asarray(c2w, np.float64)
    R, centre = c2w[:3, :3], c2w[:3, 3]
    return {"position": centre.copy(), "look_at": centre + distance * R[:, 2], "up_direction": -R[:, 1],
            "fov": data.frustum(c2w, K, width, height).fov_y}


def _client_root(viser) -> tempfile.TemporaryDirectory | None:
    """A copy of viser's client build with CLIENT_FIX run first; None where the build is not as expected
    (then the stock client is served)."""
    build = Path(viser.__file__).resolve().parent / "client" / "build"
    try:
        html = (build / "index.html").read_text(encoding="utf-8")
    except OSError:
        return None
    if "<head>" not in html:
        return None
    tmp = tempfile.TemporaryDirectory(prefix="ev3dgs-view-")
    root = Path(tmp.name)
    for item in build.iterdir():
        if item.name != "index.html":
            (root / item.name).symlink_to(item, target_is_directory=item.is_dir())
    (root / "index.html").write_text(html.replace("<head>", "<head>" + CLIENT_FIX, 1), encoding="utf-8")
    return tmp


@contextlib.contextmanager
def _serving_from(viser, root: Path | None):
    """While a ViserServer is built: its web server serves the client from `root` (no change when None, nor
    where viser builds its web server otherwise). Viewers are built one at a time (the main thread)."""
    stock = getattr(getattr(viser, "infra", None), "WebsockServer", None)
    if root is None or not isinstance(stock, type):
        yield
        return

    class Server(stock):
        def __init__(self, *args, **kwargs):
            kwargs["http_server_root"] = root
            super().__init__(*args, **kwargs)

    viser.infra.WebsockServer = Server
    try:
        yield
    finally:
        viser.infra.WebsockServer = stock


def _segments(polyline: np.ndarray) -> np.ndarray:
    return np.stack([polyline[:-1], polyline[1:]], axis=1)


def display_url(host: str, port: int) -> str:
    return f"http://{'127.0.0.1' if host in ('0.0.0.0', '::', '') else host}:{port}"


def check_host(host: str) -> None:
    """Fail in one line unless `host` resolves to an address a server can bind (a local interface's, or a
    wildcard): viser's server thread would otherwise fail silently and leave the command waiting."""
    import socket

    try:
        infos = socket.getaddrinfo(host or None, 0, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except (socket.gaierror, UnicodeError) as e:
        raise Ev3dgsError(f"cannot start the viewer on {host!r}: not an address or a name that resolves "
                          f"({getattr(e, 'strerror', None) or e})") from None
    why = None
    for family, kind, proto, _, addr in infos:
        try:
            with socket.socket(family, kind, proto) as probe:
                probe.bind(addr[:2] if family == socket.AF_INET else addr)
            return
        except OSError as e:
            why = e.strerror or str(e)
    raise Ev3dgsError(f"cannot start the viewer on {host!r}: no local network interface has that address ({why})")


class Viewer:
    """A viser server showing one scene (and optionally a model); GUI callbacks run in viser's threads."""

    def __init__(self, host: str = "127.0.0.1", port: int = 8080, label: str = "ev3dgs"):
        viser = require_viser()
        check_host(host)
        self.host, self.requested_port = host, port
        self._client_dir = _client_root(viser)
        try:
            with contextlib.redirect_stdout(io.StringIO()), \
                    _serving_from(viser, None if self._client_dir is None else Path(self._client_dir.name)):
                self.server = viser.ViserServer(host=host, port=port, label=label, verbose=False)
        except OSError as e:
            self._remove_client_dir()
            raise Ev3dgsError(f"cannot start the viewer on {host}:{port} ({e.strerror or e})") from None
        self.port = int(self.server.get_port())
        self.url = display_url(host, self.port)
        self._lock = threading.RLock()
        self._splats = None
        self._content: data.SceneContent | None = None
        self._reader: EventFile | None = None
        self.status = self.server.gui.add_markdown("", order=0)

    # ------------------------------------------------------------------ the scene
    def show_scene(self, c: data.SceneContent, select: int = 0) -> None:
        s = self.server.scene
        self._content = c
        ext = c.extent
        W, H = c.size
        K = c.scene.camera.K
        rots = None if c.train_poses is None else c.train_poses[:, :, :3, :3]
        if rots is not None:
            s.set_up_direction(data.world_up(rots))
        unit = _nice_length(ext)
        s.add_frame("/world", show_axes=False)
        length = axes_length(ext)
        self.axes = s.add_frame("/world/axes", axes_length=length, axes_radius=length * AXES_THICKNESS,
                                position=axes_origin(c))
        up = data.world_up(rots) if rots is not None else np.array([0.0, 0.0, 1.0])
        from ..geometry import matrix_to_quat

        basis = data.top_view_basis(rots) if rots is not None else np.eye(3)[:2]
        s.add_grid("/world/grid", width=unit * 10, height=unit * 10, cell_size=unit, section_size=unit * 5,
                   wxyz=matrix_to_quat(np.stack([basis[0], basis[1], up], axis=1)))
        size = 0.03 * ext
        self._frusta = []
        self._initial_camera(c, up)
        if c.train_poses is not None:
            mids = c.mid_poses()
            lines = c.polylines()
            for i in range(c.n_views):
                f = data.frustum(mids[i], K, W, H)
                h = s.add_camera_frustum(f"/train/view_{i}", f.fov_y, f.aspect, scale=size, color=TRAIN_COLOUR,
                                         thickness=size * 0.04, image=_thumb(c.frame(i)), format="jpeg",
                                         wxyz=f.wxyz, position=f.position)
                h.on_click(lambda _e, i=i: self._select(i))
                self._frusta.append(h)
            segs = np.concatenate([_segments(p) for p in lines]) if lines.shape[1] > 1 else None
            if segs is not None:
                s.add_line_segments("/train/trajectories", segs, TRAIN_COLOUR, thickness=size * 0.05)
            s.add_point_cloud("/train/starts", lines[:, 0], START_COLOUR, point_size=size * 0.08,
                              point_shape="circle")
            s.add_point_cloud("/train/ends", lines[:, -1], END_COLOUR, point_size=size * 0.08,
                              point_shape="diamond")
        if c.test_poses is not None:
            for j, pose in enumerate(c.test_poses):
                f = data.frustum(pose, K, W, H)
                s.add_camera_frustum(f"/test/view_{j}", f.fov_y, f.aspect, scale=size, color=TEST_COLOUR,
                                     thickness=size * 0.04, wxyz=f.wxyz, position=f.position)
        pts = c.scene.points
        if pts is not None and len(pts.xyz):
            s.add_point_cloud("/points", np.asarray(pts.xyz, np.float32), np.asarray(pts.rgb, np.uint8),
                              point_size=size * 0.05)
        if c.imu is not None:
            mid = c.imu.rotations.shape[1] // 2
            good = np.isfinite(c.imu.rotations[:, mid]).all(axis=(1, 2))
            if good.any():
                wxyz = np.stack([matrix_to_quat(r) for r in c.imu.rotations[good, mid]])
                s.add_batched_axes("/imu", wxyz, c.mid_poses()[good, :3, 3], axes_length=size * 0.8,
                                   axes_radius=size * 0.03)
        self._info(c, unit)
        self._panel(c, select)
        self._look_controls(c)

    def _initial_camera(self, c: data.SceneContent, up: np.ndarray) -> None:
        """Open the page looking at the scene from above and outside the cameras."""
        if c.train_poses is None:
            return
        centres = c.mid_poses()[:, :3, 3]
        target = _target(c)
        radius = max(float(np.linalg.norm(centres - target, axis=1).max()), 0.5 * c.extent, 1e-3)
        side = centres[0] - target
        side -= up * (side @ up)
        n = np.linalg.norm(side)
        side = side / n if n > 1e-9 else data.top_view_basis(c.train_poses[:, :, :3, :3])[0]
        cam = self.server.initial_camera
        cam.look_at = target
        cam.up = up
        cam.position = target + radius * (1.3 * side + 1.0 * up)

    def _info(self, c: data.SceneContent, unit: float) -> None:
        sc = c.scene
        lines = [f"**{sc.name or c.path.name}** ({sc.source}): {c.n_views} training views, "
                 f"{0 if sc.test is None else len(sc.test.images)} test views, {len(sc.events)} events, "
                 f"{c.size[0]}x{c.size[1]} px",
                 f"World axes (x red, y green, z blue): {axes_length(c.extent):.3g} units long, drawn at "
                 f"({', '.join(f'{v:.3g}' for v in axes_origin(c))}); grid cells {unit:g}. Training cameras "
                 "orange (trajectory: green start, red end), test cameras blue."]
        if c.train_poses is None:
            lines.append("No poses in this file (ingested without pose estimation).")
        if c.imu is not None and np.isfinite(c.imu.angle_deg).any():
            a = c.imu.angle_deg[np.isfinite(c.imu.angle_deg)]
            lines.append(f"IMU axes at the cameras: gyro integrated from the first pose; it differs from the "
                         f"estimated rotation by median {np.median(a):.2f} deg, max {a.max():.2f} deg.")
        if c.failed:
            lines.append(f"Failed to register ({len(c.failed)}): " + "; ".join(c.failed))
        self.server.gui.add_markdown("\n\n".join(lines), order=1)

    def _panel(self, c: data.SceneContent, select: int) -> None:
        g = self.server.gui
        n = c.n_views
        if n == 0:
            return
        self._reader = EventFile(c.path)
        select = int(min(max(select, 0), n - 1))
        self.view_slider = g.add_slider("view", 0, max(n - 1, 1), 1, select, disabled=n < 2, order=2)
        self.time_slider = g.add_slider("events up to (% of the window)", 0, 100, 1, 100, order=3)
        self.caption = g.add_markdown("", order=4)
        self.frame_image = g.add_image(np.asarray(c.frame(select)), label="blurry frame", format="png", order=5)
        sharp = c.sharp(select)
        self.sharp_image = None if sharp is None else g.add_image(np.asarray(sharp), label="sharp frame",
                                                                  format="png", order=6)
        self.event_image = g.add_image(np.full((c.size[1], c.size[0], 3), 255, np.uint8), format="png",
                                       label=f"events ({palette.legend_text()})", order=7)
        self.view_slider.on_update(lambda _e: self._select(int(self.view_slider.value)))
        self.time_slider.on_update(lambda _e: self._update_events())
        self._select(select)

    def _look_controls(self, c: data.SceneContent) -> None:
        if c.train_poses is None or c.n_views == 0:
            return
        g = self.server.gui
        n_test = 0 if c.test_poses is None else len(c.test_poses)
        self.look_choice = g.add_dropdown("camera", [SELECTED_TRAIN] + [f"test view {j}" for j in range(n_test)],
                                          initial_value=SELECTED_TRAIN, order=2.1,
                                          hint="the camera the button below looks through")
        self.look_button = g.add_button("look through camera", order=2.2,
                                        hint="put the 3D view at that camera: its pose and field of view")
        self.look_button.on_click(lambda _e: self.look_through_choice())

    def look_through_choice(self) -> None:
        """The look-through button: the camera chosen in the dropdown (the selected training view's
        mid-exposure pose, or a test view's pose)."""
        c, choice = self._content, str(self.look_choice.value)
        if choice == SELECTED_TRAIN:
            pose = c.mid_poses()[self.selected]
        else:
            pose = c.test_poses[int(choice.rsplit(" ", 1)[1])]
        self.look_through(pose)

    def look_through(self, c2w: np.ndarray) -> None:
        """Every connected browser's camera to the pinhole camera `c2w` (OpenCV camera-to-world) with the
        scene's intrinsics; its orbit centre is the point ahead of it nearest to the scene's centre."""
        c = self._content
        c2w = np.asarray(c2w, np.float64)
        ahead = float((_target(c) - c2w[:3, 3]) @ c2w[:3, 2])
        distance = ahead if ahead > 0.05 * c.extent else 0.5 * c.extent
        view = camera_view(c2w, c.scene.camera.K, *c.size, distance)
        for client in self.server.get_clients().values():
            cam = client.camera
            try:
                cam.position
            except AssertionError:  # the page has not reported its camera yet (it opens at the initial one)
                continue
            with client.atomic():
                cam.fov = view["fov"]
                cam.position = view["position"]         # moves the look-at point along
                cam.look_at = view["look_at"]
                cam.up_direction = view["up_direction"]

    def _select(self, i: int) -> None:
        c = self._content
        with self._lock:
            if int(self.view_slider.value) != i:
                self.view_slider.value = i  # fires _select again from viser's side; harmless
            self.selected = i
            for j, h in enumerate(self._frusta):
                h.color = SELECTED_COLOUR if j == i else TRAIN_COLOUR
            self.frame_image.image = np.asarray(c.frame(i))
            if self.sharp_image is not None:
                self.sharp_image.image = np.asarray(c.sharp(i))
        self._update_events()

    def _update_events(self) -> None:
        c, i = self._content, self.selected
        frac = float(self.time_slider.value) / 100
        with self._lock:
            on, off = c.event_counts(self._reader, i, frac)
            self.event_image.image = data.event_image(on, off)   # palette's colours (ON red, OFF blue)
            w0, w1, window = c.event_window(self._reader, i)
            t = data.accumulation_time((w0, w1), frac)
            start, end = (int(v) for v in c.exposure[i])
            self.caption.content = (f"**view {i}** of {c.n_views}: exposure {start}-{end} us; events shown: "
                                    f"{window}, up to {t} us: {int(on.sum())} ON, {int(off.sum())} OFF "
                                    f"({palette.legend_text()})")

    # ------------------------------------------------------------------ a model
    def show_splats(self, arrays: dict) -> None:
        with self._lock:
            self._splats = self.server.scene.add_gaussian_splats("/splats", **arrays)

    def show_refined(self, c: data.SceneContent, poses: np.ndarray, pose_t: np.ndarray) -> None:
        lines = data.trajectory_polylines(poses, pose_t)
        size = 0.03 * c.extent
        if lines.shape[1] > 1:
            self.server.scene.add_line_segments("/refined/trajectories",
                                                np.concatenate([_segments(p) for p in lines]),
                                                REFINED_COLOUR, thickness=size * 0.05)
        W, H = c.size
        for i, pose in enumerate(poses[:, poses.shape[1] // 2]):
            f = data.frustum(pose, c.scene.camera.K, W, H)
            self.server.scene.add_camera_frustum(f"/refined/view_{i}", f.fov_y, f.aspect, scale=size,
                                                 color=REFINED_COLOUR, thickness=size * 0.04, wxyz=f.wxyz,
                                                 position=f.position)
        self.server.gui.add_markdown("Refined trajectories (RUN/trajectory.npz) in magenta beside the initial "
                                     "ones (orange).", order=1.5)

    def set_status(self, text: str) -> None:
        self.status.content = text

    # ------------------------------------------------------------------ life cycle
    def announce(self) -> None:
        if self.port != self.requested_port and self.requested_port != 0:
            print(f"port {self.requested_port} is in use: using {self.port}", file=sys.stderr)
        if self.host in ("0.0.0.0", "::", ""):
            print(f"warning: --host {self.host} makes the viewer reachable from other machines on the network, "
                  "with no password; use it only on a network you trust", file=sys.stderr)
        print(f"ev3dgs view: {self.url}  (Ctrl-C to stop)", flush=True)

    def serve(self) -> None:
        """Print the URL and serve until Ctrl-C (SIGINT) or SIGTERM, then stop cleanly. The handlers are set
        here, not inherited (a shell starts background jobs with SIGINT ignored, and a viewer must still stop
        on it), and before the URL is printed, so a signal sent as soon as the URL appears stops it cleanly."""
        def interrupt(signum, frame):
            raise KeyboardInterrupt

        old = {sig: signal.signal(sig, interrupt) for sig in (signal.SIGINT, signal.SIGTERM)}
        try:
            self.announce()
            while True:
                time.sleep(0.2)
        except KeyboardInterrupt:
            pass
        finally:
            for sig, handler in old.items():
                signal.signal(sig, handler)
            self.stop()

    def stop(self) -> None:
        if self._reader is not None:
            self._reader.close()
            self._reader = None
        with contextlib.redirect_stdout(io.StringIO()):  # "(viser) Server stopped"
            self.server.stop()
        self._remove_client_dir()

    def _remove_client_dir(self) -> None:
        if self._client_dir is not None:
            self._client_dir.cleanup()
            self._client_dir = None
