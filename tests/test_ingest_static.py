"""`ev3dgs-ingest davis` and a camera that did not move: refused in seconds, before EDI and pose estimation,
with a message that says why and what works instead; progress, --min-registered and the failure message of
pose estimation; SIGTERM and Ctrl-C during pose estimation end with one line and leave no temporary file."""
from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from ev3dgs.cli import ingest as ingest_cli
from ev3dgs.cli import main as ev3dgs_cli
from ev3dgs.events import Events
from ev3dgs.io import colmap, davis, edi
from ev3dgs.io.aedat4.writer import write_aedat4
from ev3dgs.io.motion import MotionCheck, frame_motion, imu_motion, imu_ratio_limit
from ev3dgs.io.types import FrameData, ImuData

REPO = Path(__file__).resolve().parents[1]
STREET = REPO.parent / "shared" / "data" / "aedat" / "aedat_test_data.aedat4"   # EXPECTED.md: the static street
EPOCH = 1_700_000_000_000_000


def _texture(h, w, seed=0):
    rng = np.random.default_rng(seed)
    t = np.zeros((h, w))
    for sigma, amp in ((8, 0.5), (3, 0.35), (1.2, 0.25)):
        n = cv2.GaussianBlur(rng.random((h, w)), (0, 0), sigma)
        t += amp * (n - n.mean()) / (n.std() + 1e-9)
    return np.clip(0.45 + 0.15 * t, 0.02, 1.0)


def make_davis(path, *, shift_px_per_frame=0.0, frames=12, w=160, h=120, imu="noise", seed=0, fps=20):
    """A DAVIS-like recording: a textured plane seen by a camera translating sideways at `shift_px_per_frame`
    (0: a static camera), APS frames with read noise, a few noise events, and an IMU at 1 kHz whose readings
    are bias + white noise (a camera at rest) or, with imu="shake", a 2 Hz rotation of 20 deg/s on top."""
    rng = np.random.default_rng(seed)
    big = _texture(h, w + int(abs(shift_px_per_frame) * frames) + 8, seed)
    period, exp = int(1e6 / fps), 5000
    aps = []
    for k in range(frames):
        m = np.float32([[1, 0, -shift_px_per_frame * k], [0, 1, 0]])
        img = cv2.warpAffine(big.astype(np.float32), m, (w, h), flags=cv2.INTER_LINEAR)
        dn = np.clip(np.round(255 * img + rng.normal(0, 1.0, img.shape)), 0, 255).astype(np.uint8)
        s = EPOCH + k * period
        aps.append(FrameData(timestamp=s, exposure_start=s, exposure_end=s + exp, frame_start=s - 100,
                             frame_end=s + exp + 100, image=dn, source="TEST"))
    n_ev = 2000
    t = np.sort(rng.integers(EPOCH, EPOCH + frames * period, n_ev))
    ev = Events(t, rng.integers(0, w, n_ev).astype(np.uint16), rng.integers(0, h, n_ev).astype(np.uint16),
                rng.choice(np.array([1, -1], np.int8), n_ev))
    data = None
    if imu:
        ti = np.arange(EPOCH, EPOCH + frames * period, 1000, dtype=np.int64)
        gyro = np.array([0.7, -0.5, 0.1]) + rng.normal(0, 0.05, (len(ti), 3))
        accel = np.array([0.02, -0.99, 0.25]) + rng.normal(0, 0.0015, (len(ti), 3))
        if imu == "shake":
            gyro[:, 1] += 20.0 * np.sin(2 * np.pi * 2.0 * (ti - EPOCH) * 1e-6)
        data = ImuData(ti, accel.astype(np.float32), gyro.astype(np.float32), np.full(len(ti), 30.0, np.float32))
    write_aedat4(path, w, h, events=ev, frames=aps, imu=data)
    return path


@pytest.fixture
def no_pose_work(monkeypatch):
    """EDI and pycolmap raise if entered: a refusal must come before them."""
    def boom(*a, **k):
        raise AssertionError("entered EDI or pose estimation")

    monkeypatch.setattr(edi, "edi_latent_frames", boom)
    monkeypatch.setattr(colmap, "estimate_poses", boom)


def _one_line(capsys, rc):
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert rc == 2 and len(lines) == 1 and lines[0].startswith("error: "), (rc, err)
    return lines[0]


@pytest.mark.parametrize("imu", ["noise", None])
def test_static_camera_is_refused_before_edi_and_pose_estimation(tmp_path, capsys, no_pose_work, imu):
    rec = make_davis(tmp_path / "static.aedat4", imu=imu)
    out = tmp_path / "s.h5"
    line = _one_line(capsys, ingest_cli.main(["davis", str(rec), "--out", str(out)]))
    assert "the camera did not move" in line and "moving camera" in line and "--no-poses" in line
    assert ("IMU samples" in line) == (imu is not None) and "image motion" in line
    assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == ["static.aedat4"]
    assert "export-dataset --format events-h5 or aedat4" in line
    # --no-poses gives the file (no pose estimation involved)
    assert ingest_cli.main(["davis", str(rec), "--out", str(out), "--no-poses", "--quiet"]) == 0 and out.is_file()
    # what the message says the file is for works on it
    assert ev3dgs_cli.main(["info", str(out)]) == 0
    assert ev3dgs_cli.main(["view", str(out), "--out", str(tmp_path / "v.png"), "--quiet"]) == 0
    for fmt in ("events-h5", "aedat4"):
        assert ev3dgs_cli.main(["export-dataset", str(out), "--format", fmt, "--out", str(tmp_path / fmt),
                                "--quiet"]) == 0
    capsys.readouterr()
    # and train on it does not send the user back to ingest in a loop
    line = _one_line(capsys, ev3dgs_cli.main(["train", str(out), "--out", str(tmp_path / "run"), "--quiet"]))
    assert "moving camera" in line and "--no-poses" in line and "export-dataset" in line


@pytest.mark.parametrize("imu", ["noise", "shake", None])
def test_moving_camera_goes_on_to_pose_estimation(tmp_path, monkeypatch, imu):
    """A camera translating 3 px per frame (33 px over the recording, above the 1.5-degree limit of 3.0 px at
    this 70-degree lens): pose estimation is entered whatever the IMU says (a constant velocity reads as rest)."""
    rec = make_davis(tmp_path / "moving.aedat4", shift_px_per_frame=3.0, imu=imu)

    class Entered(Exception):
        pass

    def entered(*a, **k):
        raise Entered

    monkeypatch.setattr(colmap, "estimate_poses", entered)
    with pytest.raises(Entered):
        davis.ingest_davis(rec, tmp_path / "m.h5", davis.DavisOptions())


def test_imu_shake_alone_counts_as_motion(tmp_path, monkeypatch):
    """With an IMU that moves, the frames are not even looked at."""
    rec = make_davis(tmp_path / "shake.aedat4", imu="shake")
    import ev3dgs.io.motion as motion

    monkeypatch.setattr(motion, "frame_motion", lambda *a, **k: pytest.fail("frames looked at"))
    monkeypatch.setattr(colmap, "estimate_poses", lambda *a, **k: (_ for _ in ()).throw(KeyError("entered")))
    with pytest.raises(KeyError, match="entered"):
        davis.ingest_davis(rec, tmp_path / "m.h5", davis.DavisOptions())


def test_imu_ratio_limit_matches_low_passed_noise():
    """The limit is the std / first-difference sigma of first-order low-passed white noise: simulate AR(1)
    noise at several bandwidths and compare (n = 200 000 samples: the ratio's relative standard error is
    below 1 %, so 5 % is several standard errors)."""
    rng = np.random.default_rng(0)
    fs = 1000.0
    for bw in (10.0, 40.0, 200.0):
        rho = math.exp(-2 * math.pi * bw / fs)
        e = rng.normal(size=200_000)
        x = np.empty_like(e)
        x[0] = e[0]
        for i in range(1, len(e)):          # plain loop: 200k steps
            x[i] = rho * x[i - 1] + e[i]
        d = np.diff(x)
        ratio = x.std() / (1.4826 * np.median(np.abs(d - np.median(d))) / math.sqrt(2))
        assert ratio == pytest.approx(imu_ratio_limit(fs, bw), rel=0.05)


def test_imu_witness_rest_and_motion():
    rng = np.random.default_rng(1)
    t = np.arange(0, 2_000_000, 1000, dtype=np.int64)
    rest = imu_motion(t, rng.normal(0, 1e-3, (len(t), 3)) + [0, -1, 0], rng.normal(0, 0.05, (len(t), 3)) + 0.7)
    assert rest["static"] and rest["gyro_ratio"] < 1.2 and rest["accel_ratio"] < 1.2   # white noise: ~1
    g = rng.normal(0, 0.05, (len(t), 3))
    g[:, 0] += 1.0 * np.sin(2 * np.pi * 1.0 * t * 1e-6)       # 1 deg/s at 1 Hz: 14 x the noise std
    moving = imu_motion(t, rng.normal(0, 1e-3, (len(t), 3)), g)
    assert not moving["static"] and moving["gyro_ratio"] > 10
    # a noise-free IMU (a simulator's): at rest it is static, any motion is motion
    assert imu_motion(t, np.zeros((len(t), 3)), np.zeros((len(t), 3)))["static"]
    assert imu_motion(t, np.zeros((len(t), 3)), g - rng.normal(0, 0.05, g.shape) * 0)["static"] is False
    assert imu_motion(t[:10], np.zeros((10, 3)), np.zeros((10, 3))) is None


def test_frame_witness_measures_a_known_shift():
    """A texture shifted by a known amount: the median flow is that shift (Farneback is sub-pixel accurate
    on smooth texture; 0.2 px)."""
    tex = (255 * _texture(120, 200, 3)).astype(np.uint8)
    frames = [tex[:, 20 - k:180 - k] for k in range(0, 8, 2)]      # 0, 2, 4, 6 px to the right
    r = frame_motion(frames, 200.0, MotionCheck())
    assert r["median_px"] == pytest.approx(6.0, abs=0.2)
    assert r["limit_px"] == pytest.approx(200.0 * math.tan(math.radians(1.5)))
    assert not r["static"]
    assert frame_motion([tex, tex], 200.0)["median_px"] < 0.05 and frame_motion([tex], 200.0) is None


@pytest.mark.skipif(not STREET.exists(), reason="the DAVIS346 street recording (../shared/data/aedat) is absent")
def test_street_recording_is_refused_in_seconds(tmp_path, capsys, no_pose_work):
    """The real DAVIS346 street recording (static camera, moving cars): refused with the static-camera message,
    EDI and pycolmap never entered (they took 6 min 24 s to fail before)."""
    out = tmp_path / "street.h5"
    line = _one_line(capsys, ingest_cli.main(["davis", str(STREET), "--out", str(out)]))
    assert "the camera did not move" in line and "2,363 IMU samples" in line and "--no-poses" in line
    assert not out.exists()


def test_pose_failure_names_sub_frames_and_what_to_try(tmp_path, capsys, monkeypatch):
    """Featureless frames (the motion check off): the message counts sub-frames and frames, and suggests what
    was not tried; a terminal sees the stages as they go, a pipe sees nothing but the error."""
    rec = tmp_path / "flat.aedat4"
    frames = [FrameData(timestamp=EPOCH + k * 50_000, exposure_start=EPOCH + k * 50_000,
                        exposure_end=EPOCH + k * 50_000 + 5000, frame_start=EPOCH + k * 50_000,
                        frame_end=EPOCH + k * 50_000 + 5000, image=np.full((48, 64), 100, np.uint8), source="T")
              for k in range(4)]
    write_aedat4(rec, 64, 48, events=Events.concatenate([]), frames=frames)
    args = ["davis", str(rec), "--out", str(tmp_path / "f.h5"), "--no-motion-check", "--subposes", "3",
            "--min-registered", "0.25"]
    line = _one_line(capsys, ingest_cli.main(args))
    assert "only 0 of 12 sub-frames (4 frames x 3) registered (need 3, min_registered=0.25)" in line, line
    assert "--calibration" in line and "--no-poses" in line and "EDI-deblurred" not in line

    class Tty:     # stderr as a terminal: the progress line goes there
        def __init__(self):
            self.text = ""

        def write(self, s):
            self.text += s

        def flush(self):
            pass

        def isatty(self):
            return True

    tty = Tty()
    monkeypatch.setattr(sys, "stderr", tty)
    assert ingest_cli.main(args + ["--force"]) == 2
    assert "EDI: 0 of 12 sub-frames (4 frames x 3)" in tty.text and "pose estimation: SIFT features" in tty.text
    tty.text = ""
    assert ingest_cli.main(args + ["--force", "--quiet"]) == 2
    assert "EDI" not in tty.text and tty.text.startswith("error: ")


@pytest.mark.parametrize("value", ["1.5", "-0.1", "x"])
def test_min_registered_option(tmp_path, capsys, value):
    rec = make_davis(tmp_path / "r.aedat4", frames=2, w=64, h=48)
    try:
        rc = ingest_cli.main(["davis", str(rec), "--out", str(tmp_path / "o.h5"), "--min-registered", value])
    except SystemExit as e:     # argparse's refusal of a non-number
        rc = e.code
    assert "min-registered" in _one_line(capsys, rc)


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_signal_during_pose_estimation_ends_with_one_line(tmp_path, sig):
    """A real `ev3dgs-ingest davis` process stopped while pycolmap works: one line on stderr (no native stack
    dump from glog's handler), no temporary folder and no output."""
    rec = make_davis(tmp_path / "r.aedat4", frames=30, w=346, h=260, imu=None)
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    env = dict(os.environ, TMPDIR=str(tmp), PYTHONPATH=str(REPO), OMP_NUM_THREADS="1")
    p = subprocess.Popen([sys.executable, "-m", "ev3dgs.cli.ingest", "davis", str(rec), "--out",
                          str(tmp_path / "o.h5"), "--no-motion-check"], cwd=tmp_path, env=env,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while not list(tmp.glob("ev3dgs_colmap_*/job.json")):   # pycolmap's child has its job: pose estimation runs
        assert p.poll() is None and time.monotonic() < deadline, p.communicate()
        time.sleep(0.05)
    time.sleep(0.5)
    p.send_signal(sig)
    out, err = p.communicate(timeout=60)
    assert err.strip().splitlines() == ["error: interrupted"], err
    assert p.returncode == 130 and list(tmp.iterdir()) == [] and not (tmp_path / "o.h5").exists()
