"""What `ev3dgs-ingest` says about a recording: `davis` reports how many events it kept and why, `info` prints
aligned "key: value" lines (and --json the same as JSON). Checked on a recording the test writes (counts known by
construction) and, when the shared real recordings are present, against their independently read counts."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from ev3dgs import schema
from ev3dgs.cli import ingest as ingest_cli
from ev3dgs.events import Events
from ev3dgs.io.aedat4.writer import write_aedat4
from ev3dgs.io.davis import DavisOptions, events_in_file, ingest_davis
from ev3dgs.io.types import FrameData

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data" / "aedat"
AESTREAM = SHARED / "aestream_davis.aedat4"          # EXPECTED.md: 117,667 events, 3 frames, 130 IMU, 15 triggers
TEST_DATA = SHARED / "aedat_test_data.aedat4"        # EXPECTED.md: 78,830 events, 59 frames of 500 us
needs_shared = pytest.mark.skipif(not (AESTREAM.is_file() and TEST_DATA.is_file()),
                                  reason="the shared real recordings are not present")

W, H = 40, 30
T0, STEP, N = 1_000_000, 100, 20_000            # one event every 100 us for 2 s
EXPOSURES = [(T0 + 100_000 + 400_000 * k, T0 + 100_000 + 400_000 * k + 20_000) for k in range(4)]


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> Path:
    """Events every STEP us from T0; 4 full-size frames exposed 20 ms each, 400 ms apart."""
    rng = np.random.default_rng(0)
    t = T0 + STEP * np.arange(N, dtype=np.int64)
    ev = Events(t, rng.integers(0, W, N).astype(np.uint16), rng.integers(0, H, N).astype(np.uint16),
                rng.choice(np.array([-1, 1], np.int8), N))
    frames = [FrameData(timestamp=s, exposure_start=s, exposure_end=e, frame_start=s - 500, frame_end=e + 500,
                        image=np.full((H, W), 60 + 20 * k, np.uint8)) for k, (s, e) in enumerate(EXPOSURES)]
    path = tmp_path_factory.mktemp("rec") / "small.aedat4"
    write_aedat4(path, W, H, ev, frames, None, packet_events=1500)
    return path


def kept_analytically(margin_ms: float, exposures) -> int:
    """Events on the STEP grid inside the windows [start - margin, end + margin)."""
    t = T0 + STEP * np.arange(N)
    m = int(margin_ms * 1000)
    keep = np.zeros(N, bool)
    for s, e in exposures:
        keep |= (t >= s - m) & (t < e + m)
    return int(keep.sum())


@pytest.mark.parametrize("margin,every,kept", [
    (10.0, 1, 4 * (20_000 + 2 * 10_000) // STEP),      # 4 disjoint windows of 40 ms
    (2.5, 1, 4 * (20_000 + 2 * 2_500) // STEP),
    (10.0, 2, 2 * (20_000 + 2 * 10_000) // STEP),      # --every 2: exposures 0 and 2
    (250.0, 1, (1_320_000 + 250_000) // STEP),          # the windows merge into [T0 - 150 ms, T0 + 1.57 s)
])
def test_davis_reports_the_events_it_kept(recording, tmp_path, capsys, margin, every, kept):
    out = tmp_path / "s.h5"
    assert ingest_cli.main(["davis", str(recording), "--out", str(out), "--no-poses",
                            "--event-margin-ms", str(margin), "--every", str(every)]) == 0
    used = EXPOSURES[::every]
    assert kept == kept_analytically(margin, used)
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == (f"kept {kept:,} of {N:,} events (--events margin: {margin:g} ms either side of the "
                        f"{len(used)} selected exposures; --events all keeps every event)")
    assert lines[1] == f"{len(used)} views (of 4 frames), {kept:,} events -> {out}"
    assert len(schema.read(out).events) == kept


def test_davis_events_all(recording, tmp_path, capsys):
    out = tmp_path / "a.h5"
    assert ingest_cli.main(["davis", str(recording), "--out", str(out), "--no-poses", "--events", "all"]) == 0
    assert capsys.readouterr().out.splitlines()[0] == f"kept {N:,} of {N:,} events (--events all keeps every event)"
    assert ingest_cli.main(["davis", str(recording), "--out", str(out), "--no-poses", "--force", "--quiet"]) == 0
    assert capsys.readouterr().out == ""


def test_counting_pass_matches_the_windowed_read(recording, tmp_path, monkeypatch):
    """Without a count from the reader, one pass counts every event and keeps the same events as reading the
    windows does."""
    import ev3dgs.io.davis as davis

    opts = DavisOptions(poses=False, event_margin_ms=7.0)
    a = ingest_davis(recording, tmp_path / "a.h5", opts)
    monkeypatch.setattr(davis, "events_in_file", lambda reader, stream=None: None)
    b = ingest_davis(recording, tmp_path / "b.h5", opts)
    assert a.events_in_file == b.events_in_file == N and a.events == b.events == kept_analytically(7.0, EXPOSURES)
    ea, eb = schema.read(tmp_path / "a.h5").events.load(), schema.read(tmp_path / "b.h5").events.load()
    for k in "txyp":
        assert np.array_equal(getattr(ea, k), getattr(eb, k))


def test_jaer_readers_know_their_event_count_after_the_first_pass(tmp_path):
    from test_aedat_legacy import build_aedat2, build_aedat3

    from ev3dgs.io.jaer.aedat2 import Aedat2Reader
    from ev3dgs.io.jaer.aedat3 import Aedat3Reader

    (tmp_path / "a.aedat").write_bytes(build_aedat2()[0])
    (tmp_path / "a.aedat3").write_bytes(build_aedat3()[0])
    with Aedat2Reader(tmp_path / "a.aedat") as r:
        assert events_in_file(r) is None            # nothing decoded yet
        list(r.frames())                            # the pass davis makes to select its views
        n = events_in_file(r)
        assert n == sum(len(e) for e in r.events()) > 0
    with Aedat3Reader(tmp_path / "a.aedat3") as r:
        assert events_in_file(r) is None
        total = sum(len(e) for e in r.events())
        assert events_in_file(r) == total > 0


def _info(args, capsys) -> str:
    assert ingest_cli.main(["info", *args]) == 0
    return capsys.readouterr().out


def test_info_text_and_json(recording, capsys):
    text = _info([str(recording)], capsys)
    lines = text.splitlines()
    assert lines[0] == f"{recording}: AEDAT 4.0"
    fields = {ln.split(":")[0].strip(): ln.split(":", 1)[1].strip() for ln in lines[1:] if not ln.startswith("    ")
              and ":" in ln}
    assert fields["file size"] == f"{recording.stat().st_size:,} bytes" and fields["scanned"] == "no"
    # the values of the key lines start in one column
    keyed = [ln for ln in lines[1:lines.index("  streams:")]]
    assert len({len(ln) - len(ln.split(":", 1)[1].lstrip()) for ln in keyed}) == 1 and len(keyed) >= 8
    streams = [ln.split() for ln in lines[lines.index("  streams:") + 1:]]
    ev_row = " ".join(streams[0])
    assert f"{N:,} events in 14 packets" in ev_row and f"t {T0} .. {T0 + STEP * (N - 1)} us (2.000 s)" in ev_row
    assert "4 frames in 4 packets" in " ".join(streams[1])
    got = json.loads(_info([str(recording), "--json"], capsys))
    assert got["format"] == "aedat4" and got["file_size"] == recording.stat().st_size and got["warnings"] == []
    ev = next(s for s in got["streams"] if s["kind"] == "events")
    assert ev["elements"] == N and ev["packets"] == 14 and ev["t_start"] == T0
    assert next(s for s in got["streams"] if s["kind"] == "frames")["elements"] == 4


def test_info_of_a_scene_file(recording, tmp_path, capsys):
    out = tmp_path / "s.h5"
    ingest_davis(recording, out, DavisOptions(poses=False, events="all"))
    assert f"events   {N}" in _info([str(out)], capsys)
    got = json.loads(_info([str(out), "--json"], capsys))
    assert got["events"]["count"] == N and got["train"]["views"] == 4 and got["camera"]["width"] == W
    assert got["train"]["exposure_median_us"] == 20_000 and got["events"]["t_start"] == T0


@needs_shared
def test_real_recordings_davis_counts(tmp_path, capsys):
    out = tmp_path / "a.h5"
    assert ingest_cli.main(["davis", str(AESTREAM), "--out", str(out), "--no-poses", "--events", "all"]) == 0
    assert capsys.readouterr().out.startswith("kept 117,667 of 117,667 events (--events all")
    sc = schema.read(out)
    ev = sc.events.load()
    # the margin windows over the same 3 exposures, counted here from the --events all scene
    keep = np.zeros(len(ev), bool)
    for s, e in sc.train.exposure:
        keep |= (ev.t >= s - 10_000) & (ev.t < e + 10_000)
    assert ingest_cli.main(["davis", str(AESTREAM), "--out", str(out), "--no-poses", "--force"]) == 0
    assert capsys.readouterr().out.splitlines()[0] == (
        f"kept {int(keep.sum()):,} of 117,667 events (--events margin: 10 ms either side of the 3 selected "
        "exposures; --events all keeps every event)")
    assert ingest_cli.main(["davis", str(TEST_DATA), "--out", str(out), "--no-poses", "--force",
                            "--events", "all"]) == 0
    assert capsys.readouterr().out.splitlines() == [
        "kept 78,830 of 78,830 events (--events all keeps every event)",
        f"59 views (of 59 frames), 78,830 events -> {out}"]


@needs_shared
def test_real_recording_info(capsys):
    text = _info([str(AESTREAM)], capsys)
    assert "  file size:     1,191,471 bytes" in text.splitlines()
    rows = [" ".join(ln.split()) for ln in text.splitlines() if ln.startswith("    ")]
    assert rows == [
        "0 events events (EVTS) DAVIS346_00000104 346x260 117,667 events in 13 packets "
        "t 1633953690975950 .. 1633953691105949 us (0.130 s)",
        "1 frames frames (FRME) DAVIS346_00000104 346x260 3 frames in 3 packets "
        "t 1633953690978904 .. 1633953691058904 us (0.080 s)",
        "2 imu imu (IMUS) DAVIS346_00000104 130 samples in 13 packets "
        "t 1633953690976628 .. 1633953691105605 us (0.129 s)",
        "3 triggers triggers (TRIG) DAVIS346_00000104 15 triggers in 11 packets "
        "t 1633953690976518 .. 1633953691110744 us (0.134 s)"]
    got = json.loads(_info([str(TEST_DATA), "--json", "--scan"], capsys))
    counts = {s["kind"]: (s["elements"], s["packets"]) for s in got["streams"]}
    assert counts["events"] == (78_830, 236) and counts["frames"] == (59, 59) and counts["imu"] == (2_363, 236)
    assert counts["triggers"][1] == 177
    assert got["scanned"] is True and got["data_start"] == 3126 and got["table_position"] == 6_122_043
    ev = next(s for s in got["streams"] if s["kind"] == "events")
    assert (ev["t_start"], ev["t_end"]) == (1589163147368868, 1589163149728813)
