"""The AEDAT 4.0 writer (checked against dv-processing's reader) and the DAVIS346 recording simulator.
The writer tests and one small end-to-end recording are fast; the other Blender runs are slow."""
import importlib.util
import struct
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from ev3dgs.errors import InputError
from ev3dgs.outputs import OutputError
from ev3dgs.events import Events
from ev3dgs.io.aedat4.writer import write_aedat4
from ev3dgs.io.types import FrameData, ImuData, Triggers

dv = pytest.importorskip("dv_processing")
HAS_BPY = importlib.util.find_spec("bpy") is not None
needs_bpy = pytest.mark.skipif(not HAS_BPY, reason="bpy is not installed")
REAL = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "aedat" / "aestream_davis.aedat4"
T0 = 1_700_000_000_000_000


# ---------------------------------------------------------------- helpers: dv-processing and a raw walk
def read_dv(path):
    r = dv.io.MonoCameraRecording(str(path))
    ev, frames, imu, trig = [], [], [], []
    while r.isEventStreamAvailable() and (b := r.getNextEventBatch()) is not None:
        ev.append(b.numpy())
    while r.isFrameStreamAvailable() and (f := r.getNextFrame()) is not None:
        frames.append(f)
    while r.isImuStreamAvailable() and (b := r.getNextImuBatch()) is not None:
        imu += b
    while r.isTriggerStreamAvailable() and (b := r.getNextTriggerBatch()) is not None:
        trig += b
    ev = np.concatenate(ev) if ev else None
    return r, ev, frames, imu, trig


def _decompress(data, compression):
    if compression == 1 or compression == 2:
        import lz4.frame
        return lz4.frame.decompress(data)
    if compression in (3, 4):
        import zstandard
        return zstandard.ZstdDecompressor().decompressobj().decompress(data)
    return data


def _table(buf, pos):
    vt = pos - struct.unpack_from("<i", buf, pos)[0]
    vt_size = struct.unpack_from("<H", buf, vt)[0]
    offs = struct.unpack_from(f"<{(vt_size - 4) // 2}H", buf, vt + 4)
    return lambda slot, fmt: (struct.unpack_from(fmt, buf, pos + offs[slot])[0]
                              if slot < len(offs) and offs[slot] else None)


def raw_walk(path):
    """Independent minimal parse: header fields, XML, packets by a linear walk, FTAB entries, raw frames."""
    b = open(path, "rb").read()
    assert b[:14] == b"#!AER-DAT4.0\r\n"
    n = struct.unpack_from("<I", b, 14)[0]
    h = b[18:18 + n]
    assert h[4:8] == b"IOHE"
    root = struct.unpack_from("<I", h, 0)[0]
    get = _table(h, root)
    comp, dtp = get(0, "<i") or 0, get(1, "<q")
    xpos = root + struct.unpack_from("<H", h, root - struct.unpack_from("<i", h, root)[0] + 8)[0]
    xpos += struct.unpack_from("<I", h, xpos)[0]
    xml = h[xpos + 4:xpos + 4 + struct.unpack_from("<I", h, xpos)[0]].decode()
    packets, pos = [], 18 + n
    while pos < dtp:
        sid, size = struct.unpack_from("<ii", b, pos)
        buf = _decompress(b[pos + 8:pos + 8 + size], comp)
        assert struct.unpack_from("<I", buf, 0)[0] == len(buf) - 4
        packets.append((pos + 8, sid, size, buf[4:]))   # the flatbuffer without its size prefix
        pos += 8 + size
    assert pos == dtp
    ftab = _decompress(b[dtp:], comp)[4:]
    assert ftab[4:8] == b"FTAB"
    r = struct.unpack_from("<I", ftab, 0)[0]
    vec = r + struct.unpack_from("<H", ftab, r - struct.unpack_from("<i", ftab, r)[0] + 4)[0]
    vec += struct.unpack_from("<I", ftab, vec)[0]
    entries = []
    for i in range(struct.unpack_from("<I", ftab, vec)[0]):
        p = vec + 4 + 4 * i
        e = _table(ftab, p + struct.unpack_from("<I", ftab, p)[0])
        entries.append((e(0, "<q"), e(1, "<i"), e(1, "<4xi"), e(2, "<q"), e(3, "<q"), e(4, "<q")))
    frames = []
    for _, _, _, fb in packets:
        if fb[4:8] == b"FRME":
            f = _table(fb, struct.unpack_from("<I", fb, 0)[0])
            frames.append(dict(t=f(0, "<q"), sof=f(1, "<q"), eof=f(2, "<q"), soe=f(3, "<q"), eoe=f(4, "<q"),
                               format=f(5, "<b"), w=f(6, "<h"), h=f(7, "<h"), exposure=f(11, "<q")))
    return dict(compression=comp, dtp=dtp, xml=xml, packets=packets, entries=entries, frames=frames, size=len(b))


def sample_data(seed=0, n=45_000):
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(T0, T0 + 800_000, n))
    ev = Events(t, rng.integers(0, 346, n), rng.integers(0, 260, n), rng.choice(np.array([-1, 1], np.int8), n))
    frames = []
    for i in range(4):
        s = T0 + 5_000 + 200_000 * i
        shape = (260, 346) if i % 2 == 0 else (260, 346, 3)      # GRAY and BGR
        frames.append(FrameData(timestamp=s, exposure_start=s, exposure_end=s + 20_000 + i, frame_start=s - 1000,
                                frame_end=s + 21_000 + i, image=rng.integers(0, 256, shape, dtype=np.uint8)))
    m = 800
    imu = ImuData(T0 + 1000 * np.arange(m), rng.normal(0, 1, (m, 3)).astype(np.float32),
                  rng.normal(0, 100, (m, 3)).astype(np.float32), rng.uniform(20, 40, m).astype(np.float32))
    return ev, frames, imu


def chunks(ev, sizes=(1, 9000, 13000, 333, 30000)):
    i = 0
    for s in sizes:
        yield Events(ev.t[i:i + s], ev.x[i:i + s], ev.y[i:i + s], ev.p[i:i + s])
        i += s
    if i < len(ev):
        yield Events(ev.t[i:], ev.x[i:], ev.y[i:], ev.p[i:])


# ---------------------------------------------------------------- writer
@pytest.mark.parametrize("compression, code", [("none", 0), ("lz4", 1), ("zstd", 3)])
def test_writer_round_trip_dv_processing(tmp_path, compression, code):
    ev, frames, imu = sample_data()
    trig = Triggers(np.array([T0 + 5_000, T0 + 25_000], np.int64), np.array([8, 9], np.int8))
    path = tmp_path / "a.aedat4"
    stats = write_aedat4(path, 346, 260, chunks(ev), frames, imu, compression=compression, packet_events=7000,
                         triggers=trig)
    assert stats["events"] == 7 and stats["frames"] == 4 and stats["triggers"] == 1
    assert not [p for p in tmp_path.iterdir() if p.name != "a.aedat4"]      # no temp file left

    r, got, gf, gi, gt = read_dv(path)
    assert r.getCameraName() == "DAVIS346_SIM" and r.getEventResolution() == (346, 260)
    assert set(r.getStreamNames()) == {"events", "frames", "imu", "triggers"}
    np.testing.assert_array_equal(got["timestamp"], ev.t)
    np.testing.assert_array_equal(got["x"], ev.x)
    np.testing.assert_array_equal(got["y"], ev.y)
    np.testing.assert_array_equal(got["polarity"], ev.p > 0)
    assert len(gf) == len(frames)
    for f, g in zip(gf, frames):
        np.testing.assert_array_equal(f.image, g.image)
        assert f.timestamp == g.timestamp
        assert f.exposure.total_seconds() * 1e6 == pytest.approx(g.exposure_end - g.exposure_start)
    assert len(gi) == len(imu)
    arr = lambda attr: np.array([getattr(s, attr) for s in gi])  # noqa: E731
    np.testing.assert_array_equal(arr("timestamp"), imu.t)
    for k, a in enumerate("XYZ"):
        np.testing.assert_array_equal(arr(f"accelerometer{a}").astype(np.float32), imu.accel[:, k])
        np.testing.assert_array_equal(arr(f"gyroscope{a}").astype(np.float32), imu.gyro[:, k])
        assert not arr(f"magnetometer{a}").any()
    np.testing.assert_array_equal(arr("temperature").astype(np.float32), imu.temperature)
    assert [(t.timestamp, int(t.type)) for t in gt] == [(T0 + 5_000, 8), (T0 + 25_000, 9)]
    t_end = max(int(ev.t[-1]), int(imu.t[-1]), frames[-1].timestamp)
    assert r.getTimeRange() == (min(int(ev.t[0]), int(imu.t[0])), t_end)

    raw = raw_walk(path)
    assert raw["compression"] == code
    # every packet is in the FileDataTable, with its payload offset, stream, size and time range
    assert [(e[0], e[1], e[2]) for e in raw["entries"]] == [(p[0], p[1], p[2]) for p in raw["packets"]]
    idents = {p[1]: p[3][4:8] for p in raw["packets"]}
    assert idents == {0: b"EVTS", 1: b"FRME", 2: b"IMUS", 3: b"TRIG"}
    assert sum(e[3] for e in raw["entries"] if e[1] == 0) == len(ev)
    assert min(e[4] for e in raw["entries"] if e[1] == 0) == ev.t[0]
    assert max(e[5] for e in raw["entries"] if e[1] == 0) == ev.t[-1]
    # raw frame fields: all five timestamps, OpenCV format code, size, exposure
    for rf, g in zip(raw["frames"], frames):
        assert (rf["t"], rf["sof"], rf["eof"], rf["soe"], rf["eoe"]) == (
            g.timestamp, g.frame_start, g.frame_end, g.exposure_start, g.exposure_end)
        assert rf["format"] == (0 if g.image.ndim == 2 else 16) and (rf["w"], rf["h"]) == (346, 260)
        assert rf["exposure"] == g.exposure_end - g.exposure_start
    # the description XML has DV's structure
    root = ET.fromstring(raw["xml"])
    assert root.tag == "dv" and root.get("version") == "2.0"
    (out_info,) = root.findall("node")
    assert out_info.get("name") == "outInfo"
    streams = {n.get("name"): {a.get("key"): a.text for a in n.findall("attr")} for n in out_info.findall("node")}
    assert {k: (v["originalOutputName"], v["typeIdentifier"]) for k, v in streams.items()} == {
        "0": ("events", "EVTS"), "1": ("frames", "FRME"), "2": ("imu", "IMUS"), "3": ("triggers", "TRIG")}
    assert {v["compression"] for v in streams.values()} == {compression.upper()}
    info = {a.get("key"): a.text for a in out_info.find("node[@name='0']/node[@name='info']").findall("attr")}
    assert info["sizeX"] == "346" and info["sizeY"] == "260" and info["source"] == "DAVIS346_SIM"


def test_writer_data_table_is_checked(tmp_path):
    """dv-processing reads the FileDataTable: a damaged one makes it refuse the file."""
    ev, frames, imu = sample_data(n=5000)
    path = tmp_path / "a.aedat4"
    write_aedat4(path, 346, 260, ev, frames, imu, compression="none", packet_events=1000)
    read_dv(path)
    b = path.read_bytes()
    dtp = raw_walk(path)["dtp"]

    def moved_table(delta):
        c = bytearray(b)
        struct.pack_into("<q", c, 18 + struct.unpack_from("<I", b, 18)[0] + 4, dtp + delta)
        return bytes(c)

    for bad in (b[:-12], b[:-1], moved_table(8), moved_table(-8)):
        p = tmp_path / "bad.aedat4"
        p.write_bytes(bad)
        with pytest.raises(Exception):
            read_dv(p)


def test_writer_empty_and_errors(tmp_path):
    path = tmp_path / "e.aedat4"
    write_aedat4(path, 96, 72, Events(), [], None)
    raw = raw_walk(path)
    assert raw["packets"] == [] and raw["entries"] == []
    assert set(dv.io.MonoCameraRecording(str(path)).getStreamNames()) == {"events", "frames", "imu"}
    before = path.read_bytes()
    with pytest.raises(InputError):
        write_aedat4(path, 96, 72, Events([5, 3], [0, 0], [0, 0], [1, 1]), [], None)
    with pytest.raises(InputError):
        write_aedat4(path, 96, 72, Events([5], [96], [0], [1]), [], None)
    with pytest.raises(InputError):
        write_aedat4(path, 96, 72, None, [], None, compression="gzip")
    assert path.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == ["e.aedat4"]


@pytest.mark.skipif(not REAL.is_file(), reason="shared sample recording not present")
def test_writer_rewrites_real_recording(tmp_path):
    """The real DV recording's values, written by us, parse the same way in dv-processing."""
    r, ev, frames, imu, trig = read_dv(REAL)
    raw_frames = raw_walk(REAL)["frames"]
    fd = [FrameData(timestamp=rf["t"], exposure_start=rf["soe"], exposure_end=rf["eoe"], frame_start=rf["sof"],
                    frame_end=rf["eof"], image=f.image) for rf, f in zip(raw_frames, frames)]
    arr = lambda attr: np.array([getattr(s, attr) for s in imu])  # noqa: E731
    imu_d = ImuData(arr("timestamp"), np.stack([arr(f"accelerometer{a}") for a in "XYZ"], 1).astype(np.float32),
                    np.stack([arr(f"gyroscope{a}") for a in "XYZ"], 1).astype(np.float32),
                    arr("temperature").astype(np.float32))
    tr = Triggers(np.array([t.timestamp for t in trig]), np.array([int(t.type) for t in trig], np.int8))
    out = tmp_path / "copy.aedat4"
    write_aedat4(out, 346, 260, Events(ev["timestamp"], ev["x"], ev["y"], np.where(ev["polarity"], 1, -1)), fd,
                 imu_d, camera_name=r.getCameraName(), triggers=tr)
    r2, ev2, frames2, imu2, trig2 = read_dv(out)
    assert len(ev2) == 117_667 and r2.getCameraName() == "DAVIS346_00000104"
    for k in ("timestamp", "x", "y", "polarity"):
        np.testing.assert_array_equal(ev2[k], ev[k])
    assert [(f.timestamp, f.exposure) for f in frames2] == [(f.timestamp, f.exposure) for f in frames]
    assert frames2[0].timestamp == 1633953690976518          # dv-processing's value: start of exposure
    assert all((a.image == b.image).all() for a, b in zip(frames2, frames))
    assert sum(int(f.image.sum()) for f in frames2) == 13_809_230
    assert [(s.timestamp, s.temperature, s.accelerometerY, s.gyroscopeX) for s in imu2] == \
        [(s.timestamp, s.temperature, s.accelerometerY, s.gyroscopeX) for s in imu]
    assert [(t.timestamp, t.type) for t in trig2] == [(t.timestamp, t.type) for t in trig]
    assert r2.getTimeRange() == r.getTimeRange()


# ---------------------------------------------------------------- record (Blender)
def _omega_cam(c2w, t_us):
    from ev3dgs.sim.record import rotation_log

    R = c2w[:, :3, :3]
    dt = np.diff(t_us) * 1e-6
    w = rotation_log(np.swapaxes(R[:-1], 1, 2) @ R[1:]) / dt[:, None]
    return np.rad2deg(w), (t_us[:-1] + t_us[1:]) / 2


@needs_bpy
def test_record_small_end_to_end(tmp_path):
    from ev3dgs.sim.record import record

    out = tmp_path / "rec.aedat4"
    s = record("lego", out, seconds=0.6, fps=10, exposure_ms=50, render_rate_hz=100, width=96, height=72,
               samples=4)
    assert s["frames"] == 6 and s["imu"] == 601 and s["events"] > 0 and s["rendered"] == 61
    assert set(s["seconds"]) >= {"render", "events", "frames", "imu", "write"}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rec.aedat4", "rec.calibration.toml", "rec.sensor.toml",
                                                          "rec.trajectory.npz"]   # cache removed
    from ev3dgs.calib.sensor import load_sensor_toml
    from ev3dgs.sim.scenes import load_scene

    sensor = load_sensor_toml(tmp_path / "rec.sensor.toml")          # what `ingest davis --sensor` reads
    dvs = load_scene("lego").sensor.dvs
    assert (sensor.pos_threshold, sensor.neg_threshold) == (dvs.pos_threshold, dvs.neg_threshold)

    r, ev, frames, imu, _ = read_dv(out)
    assert r.getEventResolution() == (96, 72) and r.getFrameResolution() == (96, 72)
    z = np.load(out.with_suffix(".trajectory.npz"))
    t_us, c2w, K = z["t_us"], z["c2w"], z["K"]
    assert t_us.shape == (61,) and c2w.shape == (61, 4, 4) and K.shape == (3, 3)
    np.testing.assert_allclose(c2w[:, 3], np.tile([0, 0, 0, 1.0], (61, 1)))
    assert K[0, 2] == pytest.approx(47.5) and K[1, 2] == pytest.approx(35.5)
    assert t_us[0] == 1_700_000_000_000_000 and np.all(np.diff(t_us) == 10_000)
    start, end = r.getTimeRange()
    assert start == t_us[0] and end == t_us[-1]

    # events: present and within the rendered span (the first frame only initialises the simulator)
    assert len(ev) == s["events"] and ev["timestamp"][0] > t_us[0] and ev["timestamp"][-1] <= t_us[-1]
    assert np.all(np.diff(ev["timestamp"]) >= 0) and (ev["polarity"] == 1).any() and (ev["polarity"] == 0).any()
    # frames: fps * seconds, exposure windows inside the recording, as in the trajectory file
    assert len(frames) == 6 and all(f.image.shape == (72, 96) and f.image.dtype == np.uint8 for f in frames)
    exp = z["exposure"]
    assert exp.shape == (6, 2) and np.all(exp[:, 1] - exp[:, 0] == 50_000)
    assert np.all(exp[:, 0] >= start) and np.all(exp[:, 1] <= end)
    assert [f.timestamp for f in frames] == list(exp[:, 0])
    assert all(f.exposure.total_seconds() == pytest.approx(0.05) for f in frames)
    assert all(5 < f.image.mean() < 250 and f.image.std() > 5 for f in frames)   # the object is in view
    raw = raw_walk(out)
    assert all(rf["sof"] < rf["soe"] < rf["eoe"] < rf["eof"] and rf["format"] == 0 for rf in raw["frames"])
    # IMU: 1 kHz; gyro = camera-frame angular velocity of the saved trajectory (finite differences)
    it = np.array([x.timestamp for x in imu])
    assert len(imu) == 601 and np.all(np.diff(it) == 1000) and it[0] == start and it[-1] == end
    gyro = np.array([[x.gyroscopeX, x.gyroscopeY, x.gyroscopeZ] for x in imu])
    accel = np.array([[x.accelerometerX, x.accelerometerY, x.accelerometerZ] for x in imu])
    w_fd, t_mid = _omega_cam(c2w, t_us)
    w_imu = np.stack([np.interp(t_mid, it, gyro[:, k]) for k in range(3)], 1)
    scale = np.abs(w_fd).max()
    assert scale > 10                                          # the camera really turns
    assert np.abs(w_imu - w_fd).max() < 0.01 * scale
    assert np.all(np.abs(np.linalg.norm(accel, axis=1)) < 20) and np.all(np.array([x.temperature for x in imu]) == 30)
    # accel = specific force (acceleration + g world-up) in the camera frame, in g: second differences
    p, dt = c2w[:, :3, 3], 0.01
    f_world = (p[2:] - 2 * p[1:-1] + p[:-2]) / dt**2 + [0, 0, 9.80665]
    a_fd = np.einsum("nji,nj->ni", c2w[1:-1, :3, :3], f_world) / 9.80665
    a_imu = accel[np.searchsorted(it, t_us[1:-1])]
    assert np.abs(a_imu - a_fd).max() < 0.03 * np.abs(a_fd).max() + 0.01


@needs_bpy
@pytest.mark.slow
def test_record_resumes_from_cache_and_is_deterministic(tmp_path):
    from ev3dgs.sim.record import record

    kw = dict(seconds=0.4, fps=5, exposure_ms=100, render_rate_hz=80, width=64, height=48, samples=2, seed=3)
    a = record("ficus", tmp_path / "a.aedat4", keep_cache=True, **kw)
    caches = [p for p in tmp_path.iterdir() if p.name.startswith(".a.cache-")]
    assert len(caches) == 1 and a["rendered_now"] == 2
    b = record("ficus", tmp_path / "a.aedat4", **kw)
    assert b["rendered_now"] == 0 and b["events"] == a["events"]
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".a.cache-")]
    _, ev, frames, imu, _ = read_dv(tmp_path / "a.aedat4")
    assert len(frames) == 2 and len(imu) == 401 and len(ev) == a["events"]


def test_record_rejects_bad_arguments(tmp_path):
    from ev3dgs.sim.record import record

    with pytest.raises(InputError):
        record("lego", tmp_path / "x.h5")
    with pytest.raises(InputError):
        record("lego", tmp_path / "x.aedat4", fps=20, exposure_ms=60)   # exposure longer than the period
    not_a_folder = tmp_path / "file"
    not_a_folder.write_text("x")
    with pytest.raises(OutputError, match="is not a folder"):   # a missing folder is made; one under a file not
        record("lego", not_a_folder / "sub" / "x.aedat4")
