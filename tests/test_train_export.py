"""PLY export/import, orbit camera paths, frame rendering and frame writing."""
import numpy as np
import pytest
import torch

from ev3dgs.errors import InputError
from ev3dgs.geometry import intrinsics, look_at
from ev3dgs.splat.model import PARAM_NAMES, GaussianModel
from ev3dgs.train.export import load_ply, save_ply
from ev3dgs.train.paths import orbit_path, render_frames, scene_target, write_frames

plyfile = pytest.importorskip("plyfile")


def random_model(n=50, sh_degree=3, seed=0):
    g = torch.Generator().manual_seed(seed)
    k = (sh_degree + 1) ** 2
    params = {
        "means": torch.randn(n, 3, generator=g),
        "log_scales": torch.randn(n, 3, generator=g) - 3,
        "quats": torch.randn(n, 4, generator=g),  # deliberately not unit: stored raw
        "opacity_logits": torch.randn(n, generator=g),
        "sh0": torch.randn(n, 1, 3, generator=g),
        "shN": torch.randn(n, k - 1, 3, generator=g),
    }
    return GaussianModel(params, sh_degree=sh_degree, active_sh_degree=sh_degree)


def expected_names(k1):
    return (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
            + [f"f_rest_{i}" for i in range(3 * k1)]
            + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])


# ------------------------------------------------------------------------------------------------ PLY
@pytest.mark.parametrize("deg", [3, 0])
def test_ply_layout_and_values(tmp_path, deg):
    m = random_model(sh_degree=deg)
    path = tmp_path / "sub" / "point_cloud.ply"
    save_ply(m, path)
    assert [p.name for p in tmp_path.joinpath("sub").iterdir()] == ["point_cloud.ply"]  # no temp left over
    with open(path, "rb") as f:
        head = f.read(300)
    assert head.startswith(b"ply\nformat binary_little_endian 1.0\n")

    ply = plyfile.PlyData.read(str(path))
    assert [e.name for e in ply.elements] == ["vertex"]
    v = ply["vertex"]
    k1 = (deg + 1) ** 2 - 1
    names = [p.name for p in v.properties]
    assert names == expected_names(k1)
    assert len(names) == (62 if deg == 3 else 17)
    assert all(v.data.dtype[n] == np.dtype("<f4") for n in names)
    assert len(v.data) == len(m)

    p = {k: t.detach().numpy() for k, t in m.params.items()}
    col = lambda n: np.asarray(v[n])  # noqa: E731
    np.testing.assert_array_equal(np.stack([col("x"), col("y"), col("z")], 1), p["means"])
    for n in ("nx", "ny", "nz"):
        assert np.all(col(n) == 0)
    for c in range(3):
        np.testing.assert_array_equal(col(f"f_dc_{c}"), p["sh0"][:, 0, c])
        np.testing.assert_array_equal(col(f"scale_{c}"), p["log_scales"][:, c])
        for j in range(k1):  # channel-major: f_rest_{c*(K-1)+j} == shN[:, j, c]
            np.testing.assert_array_equal(col(f"f_rest_{c * k1 + j}"), p["shN"][:, j, c])
    np.testing.assert_array_equal(col("opacity"), p["opacity_logits"])
    for c in range(4):
        np.testing.assert_array_equal(col(f"rot_{c}"), p["quats"][:, c])
    if deg == 3:  # the same ordering as graphdeco's features_rest.transpose(1, 2).flatten(start_dim=1)
        rest = np.stack([col(f"f_rest_{i}") for i in range(45)], 1)
        np.testing.assert_array_equal(rest, m.params["shN"].detach().transpose(1, 2).flatten(start_dim=1).numpy())


@pytest.mark.parametrize("deg", [3, 1, 0])
def test_ply_round_trip(tmp_path, deg):
    m = random_model(sh_degree=deg, seed=deg)
    path = tmp_path / "m.ply"
    save_ply(m, path)
    back = load_ply(path)
    assert back.sh_degree == deg and len(back) == len(m)
    for name in PARAM_NAMES:
        assert back.params[name].dtype == torch.float32
        assert back.params[name].shape == m.params[name].shape
        assert torch.equal(back.params[name], m.params[name]), name
    save_ply(back, path)  # overwrite in place (atomic replace) and read again
    assert torch.equal(load_ply(path).params["shN"], m.params["shN"])


def test_ply_round_trip_float64_and_empty(tmp_path):
    m = random_model(n=7, sh_degree=2)
    m.to(dtype=torch.float64)
    save_ply(m, tmp_path / "a.ply")
    back = load_ply(tmp_path / "a.ply")
    for name in PARAM_NAMES:
        assert torch.equal(back.params[name], m.params[name].float())
    empty = random_model(n=0, sh_degree=1)
    save_ply(empty, tmp_path / "e.ply")
    assert len(load_ply(tmp_path / "e.ply")) == 0


def test_ply_bad_files(tmp_path):
    m = random_model(n=20)
    good = tmp_path / "good.ply"
    save_ply(m, good)
    data = good.read_bytes()

    truncated = tmp_path / "truncated.ply"
    truncated.write_bytes(data[: len(data) - 100])
    garbage = tmp_path / "garbage.ply"
    garbage.write_bytes(b"this is not a ply file\n" + bytes(range(256)))
    header_only = tmp_path / "header.ply"
    header_only.write_bytes(data[: data.index(b"end_header\n") + 4])
    for bad in (truncated, garbage, header_only, tmp_path / "missing.ply"):
        with pytest.raises(InputError) as e:
            load_ply(bad)
        assert "\n" not in str(e.value)

    # a well-formed PLY without the Gaussian properties
    pts = np.zeros(3, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    plain = tmp_path / "points.ply"
    plyfile.PlyData([plyfile.PlyElement.describe(pts, "vertex")]).write(str(plain))
    with pytest.raises(InputError, match="lacks properties") as e:
        load_ply(plain)
    assert "\n" not in str(e.value)

    # f_rest count that is no SH degree
    names = expected_names(3)[:-8] + ["f_rest_9", "opacity", "scale_0", "scale_1", "scale_2",
                                      "rot_0", "rot_1", "rot_2", "rot_3"]
    arr = np.zeros(2, dtype=[(n, "f4") for n in names])
    odd = tmp_path / "odd.ply"
    plyfile.PlyData([plyfile.PlyElement.describe(arr, "vertex")]).write(str(odd))
    with pytest.raises(InputError, match="SH degree"):
        load_ply(odd)


# ------------------------------------------------------------------------------------------- orbit
def ring_poses(n=12, target=(0.3, -0.2, 0.5), radius=4.0, height=1.5, jitter=0.0, seed=0):
    rng = np.random.default_rng(seed)
    t = np.asarray(target)
    out = []
    for i in range(n):
        a = 0.4 + 2 * np.pi * i / n * 0.6  # only part of the circle
        eye = t + np.array([radius * np.cos(a), radius * np.sin(a), height]) + jitter * rng.normal(size=3)
        out.append(look_at(eye, t + jitter * rng.normal(size=3)))
    return np.stack(out)


def axis_distance(pose, point):
    c, d = pose[:3, 3], pose[:3, 2] / np.linalg.norm(pose[:3, 2])
    v = point - c
    return np.linalg.norm(v - np.dot(v, d) * d), np.dot(v, d)


def rot_angle(ra, rb):
    return np.arccos(np.clip((np.trace(ra.T @ rb) - 1) / 2, -1, 1))


@pytest.mark.parametrize("jitter", [0.0, 0.05])
def test_orbit_path(jitter):
    target = np.array([0.3, -0.2, 0.5])
    mid = ring_poses(jitter=jitter)
    est = scene_target(mid)
    if jitter == 0:
        np.testing.assert_allclose(est, target, atol=1e-9)
    else:
        assert np.linalg.norm(est - target) < 0.2
    n = 60
    path = orbit_path(mid, n)
    assert path.shape == (n, 4, 4)
    for pose in path:
        r = pose[:3, :3]
        np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-12)
        assert np.linalg.det(r) == pytest.approx(1.0, abs=1e-12)
        np.testing.assert_array_equal(pose[3], [0, 0, 0, 1])
        off, depth = axis_distance(pose, est)
        assert off < 1e-6 and depth > 0
        assert pose[2, 1] < 0  # image y (down) points down in the world: the horizon stays level
    # same distance and elevation as the input cameras
    d_in = np.linalg.norm(mid[:, :3, 3] - est, axis=1)
    d_out = np.linalg.norm(path[:, :3, 3] - est, axis=1)
    np.testing.assert_allclose(d_out, d_in.mean(), rtol=1e-9)
    elev = np.mean(np.arcsin((mid[:, 2, 3] - est[2]) / d_in))
    np.testing.assert_allclose(path[:, 2, 3] - est[2], d_in.mean() * np.sin(elev), rtol=1e-9)
    # smooth: constant rotation step, constant position step, closed loop
    steps = [rot_angle(path[i][:3, :3], path[(i + 1) % n][:3, :3]) for i in range(n)]  # includes last -> first
    np.testing.assert_allclose(steps, steps[0], rtol=1e-6)
    assert 0 < steps[0] < 2 * np.pi / n + 1e-9
    moves = [np.linalg.norm(path[(i + 1) % n][:3, 3] - path[i][:3, 3]) for i in range(n)]
    np.testing.assert_allclose(moves, moves[0], rtol=1e-6)
    assert np.linalg.norm(path[-1][:3, 3] - path[0][:3, 3]) < 1.01 * moves[0]
    # the relative rotation itself is the same, not only its angle
    rel = [path[i + 1][:3, :3] @ path[i][:3, :3].T for i in range(n - 1)]
    np.testing.assert_allclose(np.stack(rel), np.broadcast_to(rel[0], (n - 1, 3, 3)), atol=1e-9)


def test_orbit_path_explicit_target_and_degenerate_inputs():
    mid = ring_poses()
    tgt = np.array([1.0, 2.0, 0.0])
    path = orbit_path(torch.as_tensor(mid), 8, target=tgt)
    for pose in path:
        assert axis_distance(pose, tgt)[0] < 1e-6
    # parallel (forward-facing) cameras and a single camera still give a finite path looking ahead
    fwd = np.stack([look_at([x, 0.0, 0.0], [x, 5.0, 0.0]) for x in (-1.0, 0.0, 1.0)])
    for poses in (fwd, fwd[:1]):
        t = scene_target(poses)
        assert np.all(np.isfinite(t)) and t[1] > 0
        p = orbit_path(poses, 5)
        assert np.all(np.isfinite(p)) and p.shape == (5, 4, 4)
        for pose in p:
            assert axis_distance(pose, t)[0] < 1e-6
    # cameras straight above the target: elevation is clamped, the path is still a circle
    top = np.stack([look_at([0.0, 0.0, 3.0], [0.0, 0.0, 0.0])] * 2)
    p = orbit_path(top, 6, target=[0.0, 0.0, 0.0])
    assert np.all(np.isfinite(p)) and np.linalg.norm(p[0, :2, 3]) > 0.1
    with pytest.raises(InputError):
        orbit_path(mid, 0)
    with pytest.raises(InputError):
        orbit_path(np.zeros((3, 3, 3)), 4)
    with pytest.raises(InputError):
        orbit_path(mid[:1], 4, target=mid[0, :3, 3])  # the only camera sits on the target


# ------------------------------------------------------------------------------------- frames out
def make_frames(n=5, h=24, w=32):
    rng = np.random.default_rng(1)
    frames = []
    for i in range(n):
        f = np.zeros((h, w, 3), np.uint8)
        f[..., 0] = 40 * i  # R ramps with the frame index
        f[: h // 2, :, 1] = 200  # G on the top half
        f[:, : w // 4, 2] = 255  # B on the left strip
        f[-3:, -3:] = rng.integers(0, 256, (3, 3, 3))
        frames.append(f)
    return frames


def test_write_frames_png_folder(tmp_path):
    import cv2

    frames = make_frames()
    out = tmp_path / "render" / "frames"
    assert write_frames(iter(frames), out) == len(frames)
    files = sorted(p.name for p in out.iterdir())
    assert files == [f"frame_{i:04d}.png" for i in range(len(frames))]
    for i, f in enumerate(frames):
        back = cv2.imread(str(out / f"frame_{i:04d}.png"), cv2.IMREAD_UNCHANGED)
        np.testing.assert_array_equal(back[..., ::-1], f)  # exact, RGB order preserved
    with pytest.raises(InputError):
        write_frames([np.zeros((4, 4), np.uint8)], tmp_path / "bad")
    with pytest.raises(InputError):
        write_frames([frames[0], frames[0][:10]], tmp_path / "bad2")


def test_write_frames_mp4(tmp_path):
    import cv2

    frames = make_frames(n=6, h=48, w=64)
    out = tmp_path / "vid" / "orbit.mp4"
    try:
        n = write_frames(frames, out, fps=10)
    except InputError as e:  # this OpenCV build has no mp4 writer: clean error, nothing left behind
        assert "cannot write mp4 here" in str(e)
        assert not out.exists() and list(out.parent.iterdir()) == []
        return
    assert n == len(frames) and out.is_file()
    assert sorted(p.name for p in out.parent.iterdir()) == ["orbit.mp4"]  # temp renamed away
    cap = cv2.VideoCapture(str(out))
    assert cap.isOpened()
    read = []
    while True:
        ok, img = cap.read()
        if not ok:
            break
        read.append(img[..., ::-1])
    cap.release()
    assert len(read) == len(frames)
    for got, want in zip(read, frames):
        assert got.shape == want.shape
        # lossy codec: compare the block colours away from edges
        np.testing.assert_allclose(got[4:20, 24:56].astype(float).mean((0, 1)),
                                   want[4:20, 24:56].astype(float).mean((0, 1)), atol=20)


def test_write_frames_mp4_no_frames(tmp_path):
    with pytest.raises(InputError):
        write_frames(iter([]), tmp_path / "empty.mp4")
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------------------------------ render
def test_render_frames_tiny_model():
    g = torch.Generator().manual_seed(0)
    n = 30
    m = GaussianModel.from_points(torch.rand(n, 3, generator=g) - 0.5, torch.rand(n, 3, generator=g),
                                  sh_degree=1, init_opacity=0.8)
    with torch.no_grad():
        m.params["shN"].normal_(0, 0.1, generator=g)
    m.active_sh_degree = 1
    w, h = 24, 16
    K = intrinsics(w, h, 60.0)
    poses = orbit_path(np.stack([look_at([3.0, 0.0, 1.0], [0.0, 0.0, 0.0])]), 3, target=[0.0, 0.0, 0.0])
    frames = list(render_frames(m, poses, K, w, h, background=[1.0, 1.0, 1.0], backend="reference"))
    assert len(frames) == 3
    for f in frames:
        assert f.dtype == np.uint8 and f.shape == (h, w, 3)
        assert f.min() < 250  # something was drawn on the white background
    assert not np.array_equal(frames[0], frames[1])  # the views differ
    # an empty view shows exactly the background
    away = np.stack([look_at([3.0, 0.0, 1.0], [6.0, 0.0, 2.0])])
    (bg,) = render_frames(m, away, K, w, h, background=torch.tensor([0.0, 0.5, 1.0]), backend="reference")
    assert np.all(bg == np.array([0, 128, 255], np.uint8))
    # the cpu backend gives the same frames up to rounding
    try:
        cpu = next(render_frames(m, poses[:1], K, w, h, background=[1.0, 1.0, 1.0], backend="cpu", threads=1))
    except ImportError:
        return
    assert np.abs(cpu.astype(int) - frames[0].astype(int)).max() <= 1
