"""DAVIS recording -> scene: the shared real recording ingests exactly (it has only 3 frames: --no-poses)."""
from pathlib import Path

import cv2
import numpy as np
import pytest

from ev3dgs import schema
from ev3dgs.cli import ingest
from ev3dgs.errors import InputError
from ev3dgs.io.calibration import load_calibration
from ev3dgs.io.davis import DavisOptions, ingest_davis, to_rgb8

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data" / "aedat" / "aestream_davis.aedat4"
pytestmark = pytest.mark.skipif(not SHARED.exists(), reason="shared recording not present")


def test_shared_recording_ingests_exactly(tmp_path):
    out = tmp_path / "davis.h5"
    stats = ingest_davis(SHARED, out, DavisOptions(poses=False, events="all"))
    schema.validate(out, require_complete=True)
    sc = schema.read(out)
    assert stats.views == 3 and stats.frames_in_file == 3
    ev = sc.events.load()
    assert len(ev) == 117_667 and ev.on_count == 72_363 and ev.off_count == 45_304
    assert int(ev.t[0]) == 1633953690975950 and int(ev.t[-1]) == 1633953691105949
    assert int(ev.x.astype(np.int64).sum()) == 17_676_033 and int(ev.y.astype(np.int64).sum()) == 10_498_046
    assert tuple(sc.train.exposure[0]) == (1633953690976518, 1633953690981291)
    images = np.asarray(sc.train.images)
    assert images.shape == (3, 260, 346, 3)
    from ev3dgs.io.aedat4 import Aedat4Reader
    from ev3dgs.sim.isp import linear_to_srgb

    with Aedat4Reader(SHARED) as r:
        raw = np.stack([f.image for f in r.frames()])
    assert int(raw[0].astype(np.int64).sum()) == 4_587_151 and int(raw.astype(np.int64).sum()) == 13_809_230
    # the APS frames are linear in light; the scene stores them sRGB-encoded (the schema's images are sRGB)
    lut = np.round(255 * linear_to_srgb(np.arange(256) / 255.0)).astype(np.uint8)
    assert np.array_equal(images[..., 0], lut[raw]) and np.array_equal(images[..., 2], lut[raw])
    assert len(sc.imu.t) == 130 and int(sc.imu.t[0]) == 1633953690976628
    assert sc.imu.temperature[0] == pytest.approx(27.752941, abs=1e-5)
    assert np.allclose(sc.imu.accel[0], [-0.060425, -0.991211, -0.097412], atol=1e-5)
    assert sc.train.poses is None and sc.config["format"] == "aedat4"


def test_margin_keeps_only_events_near_the_used_exposures(tmp_path):
    out = tmp_path / "m.h5"
    ingest_davis(SHARED, out, DavisOptions(poses=False, events="margin", event_margin_ms=1.0, max_views=1))
    sc = schema.read(out)
    ev = sc.events.load()
    start, end = sc.train.exposure[0]
    assert len(ev) > 0 and ev.t.min() >= start - 1000 and ev.t.max() < end + 1000
    assert len(sc.train) == 1


def test_calibration_with_distortion_undistorts_frames_and_events(tmp_path):
    toml = tmp_path / "cal.toml"
    toml.write_text("width = 346\nheight = 260\nfx = 250.0\nfy = 250.0\ncx = 172.5\ncy = 129.5\n"
                    "distortion = [-0.2, 0.05, 0.0, 0.0, 0.0]\n")
    out = tmp_path / "u.h5"
    ingest_davis(SHARED, out, DavisOptions(poses=False, events="all", calibration=str(toml)))
    sc = schema.read(out)
    assert np.allclose(sc.camera.K, [[250, 0, 172.5], [0, 250, 129.5], [0, 0, 1]])
    assert (sc.camera.distortion == 0).all() and sc.config["undistorted"] is True
    assert sc.config["input_distortion"][:2] == [-0.2, 0.05]
    ev = sc.events.load()
    assert 0 < len(ev) <= 117_667 and ev.x.max() < 346 and ev.y.max() < 260
    # an independent check of the event remap: a corner event moves as cv2.undistortPoints says
    K = np.array([[250, 0, 172.5], [0, 250, 129.5], [0, 0, 1.0]])
    d = np.array([-0.2, 0.05, 0, 0, 0])
    p = cv2.undistortPoints(np.array([[[10.0, 10.0]]]), K, d, P=K).ravel()
    assert p[0] < 10 and p[1] < 10  # barrel distortion pulls corners outward when undistorted


def test_calibration_xml_like_dv_writes(tmp_path):
    xml = tmp_path / "calib.xml"
    fs = cv2.FileStorage(str(xml), cv2.FILE_STORAGE_WRITE)
    fs.startWriteStruct("DAVIS346_00000104", cv2.FileNode_MAP)
    fs.write("camera_matrix", np.array([[300.0, 0, 170.0], [0, 301.0, 130.0], [0, 0, 1]]))
    fs.write("distortion_coefficients", np.array([[0.1, -0.01, 0.001, 0.002, 0.0]]))
    fs.write("image_width", 346)
    fs.write("image_height", 260)
    fs.endWriteStruct()
    fs.release()
    cal = load_calibration(xml)
    assert (cal.width, cal.height) == (346, 260) and cal.K[1, 1] == 301.0
    assert np.allclose(cal.distortion, [0.1, -0.01, 0.001, 0.002, 0.0])


def test_to_rgb8_formats():
    g = np.arange(12, dtype=np.uint8).reshape(3, 4)
    assert (to_rgb8(g)[..., 2] == g).all()
    bgr = np.stack([np.full((2, 2), 1), np.full((2, 2), 2), np.full((2, 2), 3)], -1).astype(np.uint8)
    assert tuple(to_rgb8(bgr)[0, 0]) == (3, 2, 1)
    assert to_rgb8(np.full((2, 2), 0xABCD, np.uint16))[0, 0, 0] == 0xAB


@pytest.mark.parametrize("args,match", [
    (["davis", "/nonexistent.aedat4", "--out", "X", "--no-poses"], "no such file"),
    (["davis", "GARBAGE", "--out", "X", "--no-poses"], "not an AEDAT"),
    (["davis", "SHARED", "--out", "X", "--no-poses", "--every", "0"], "--every"),
    (["davis", "SHARED", "--out", "X", "--no-poses", "--color-filter", "RGBW"], "--color-filter"),
    (["davis", "SHARED", "--out", "X", "--calibration", "/nonexistent.toml", "--no-poses"], "calibration file not found"),
    (["info", "GARBAGE"], "not a readable HDF5|not an AEDAT"),
])
def test_bad_input_exit_2(tmp_path, capsys, args, match):
    garbage = tmp_path / "g.aedat4"
    garbage.write_bytes(b"#!AER-DAT9.9\r\njunk")
    args = [a.replace("GARBAGE", str(garbage)).replace("SHARED", str(SHARED)).replace("X", str(tmp_path / "o.h5"))
            for a in args]
    assert ingest.main(args) == 2
    err = capsys.readouterr().err
    import re

    assert err.startswith("error: ") and err.count("\n") == 1 and re.search(match, err), err
    assert not (tmp_path / "o.h5").exists()


def test_options_validation():
    with pytest.raises(InputError):
        DavisOptions(events="some")
