"""What --strict means for the readers: any repair or guess fails. Each kind of damage below is read with a
warning by default (the data that survives, nothing invented) and is an AedatError with strict=True. The
recordings are made by the tests (ev3dgs.io.aedat4.writer; the jAER builder of test_aedat_legacy), so the
counts are known."""
from __future__ import annotations

import struct
import warnings

import numpy as np
import pytest

from ev3dgs.events import Events
from ev3dgs.io.aedat4 import Aedat4Reader
from ev3dgs.io.aedat4.writer import write_aedat4
from ev3dgs.io.jaer.aedat2 import Aedat2Reader
from ev3dgs.io.types import AedatError, FrameData

from test_aedat_legacy import A2_HEADER

W, H, N = 40, 30, 6000


@pytest.fixture(scope="module")
def intact(tmp_path_factory):
    rng = np.random.default_rng(0)
    t = 1_000_000 + 100 * np.arange(N, dtype=np.int64)
    ev = Events(t, rng.integers(0, W, N).astype(np.uint16), rng.integers(0, H, N).astype(np.uint16),
                rng.choice(np.array([-1, 1], np.int8), N))
    frames = [FrameData(timestamp=s, exposure_start=s, exposure_end=s + 5000, frame_start=s, frame_end=s + 5000,
                        image=np.full((H, W), 40 * k, np.uint8)) for k, s in enumerate((1_100_000, 1_300_000, 1_500_000))]
    path = tmp_path_factory.mktemp("strict") / "rec.aedat4"
    write_aedat4(path, W, H, ev, frames, None, packet_events=1000)
    with Aedat4Reader(path, strict=True) as r:
        table, tp = r.packet_table(), r.table_position
        xml = r.info_xml
    return path.read_bytes(), table, tp, xml


def _read(path, strict):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with Aedat4Reader(path, strict=strict) as r:
            ev = list(r.events())
            n = sum(len(e) for e in ev)
            return n, len(list(r.frames())), list(r.warnings), r.sensor_size(), \
                [(s.kind, s.width, s.height) for s in r.streams()]


def _truncate(data, table, tp, xml):
    return data[:tp - 37]                                     # inside the last packet before the table


def _broken_xml(data, table, tp, xml):
    k = data.find(b'<node name="outInfo"')                     # same length, no longer well-formed XML
    return data[:k] + b'<node name=<outInfo"' + data[k + 20:]


def _no_table(data, table, tp, xml):
    """An interrupted recording: the header's table position is -1 and the data ends without a table."""
    k = data.find(struct.pack("<q", tp), 0, int(table["offset"][0]))
    return (data[:k] + struct.pack("<q", -1) + data[k + 8:])[:tp]


def _damaged_table(data, table, tp, xml):
    b = bytearray(data)
    b[tp + 8:tp + 24] = b"\xff" * 16
    return bytes(b)


def _duplicated_frames_packet(data, table, tp, xml):
    i = int(np.flatnonzero(table["stream"] == 1)[0])            # the first frames packet, once more after it
    a, b = int(table["offset"][i]) - 8, int(table["offset"][i]) + int(table["size"][i])
    k = data.find(struct.pack("<q", tp), 0, int(table["offset"][0]))
    head = data[:k] + struct.pack("<q", -1) + data[k + 8:]      # no table: the copy shifts every later offset
    return head[:b] + head[a:b] + head[b:tp]



DAMAGE = {"truncated": _truncate, "broken infoNode XML": _broken_xml, "no FileDataTable": _no_table,
          "damaged FileDataTable": _damaged_table, "duplicated frames packet": _duplicated_frames_packet}


def test_a_duplicated_frames_packet_is_dropped(intact, tmp_path):
    p = tmp_path / "dup.aedat4"
    p.write_bytes(_duplicated_frames_packet(*intact))
    n, frames, warns, _, _ = _read(p, strict=False)
    assert (n, frames) == (N, 3) and any("a second frame at the previous frame's timestamp" in w for w in warns)


@pytest.mark.parametrize("name", DAMAGE)
def test_damage_is_a_warning_by_default_and_an_error_when_strict(intact, tmp_path, name):
    data, table, tp, xml = intact
    p = tmp_path / "damaged.aedat4"
    p.write_bytes(DAMAGE[name](data, table, tp, xml))
    n, frames, warns, size, _ = _read(p, strict=False)
    assert warns, "a repair without a warning"
    assert n <= N and frames <= 3 and size == (W, H)
    with pytest.raises(AedatError):
        _read(p, strict=True)


def test_intact_recording_reads_strictly(intact, tmp_path):
    p = tmp_path / "ok.aedat4"
    p.write_bytes(intact[0])
    assert _read(p, strict=True)[:3] == (N, 3, [])


@pytest.mark.parametrize("value", ["00", "-3", "ab", "3e", " 0"])
def test_a_damaged_size_key_gives_no_half_size(intact, tmp_path, value):
    """A sizeY that is not a size (same length as the intact "30", so nothing else moves) leaves the stream
    without one (never 40x0): the sensor size comes from the frames stream, with a warning; strict fails."""
    data, table, tp, xml = intact
    old = f'<attr key="sizeY" type="int">{H}</attr>'.encode()
    k = data.find(old)
    assert k > 0 and len(value) == len(str(H))
    p = tmp_path / "size.aedat4"
    p.write_bytes(data[:k] + f'<attr key="sizeY" type="int">{value}</attr>'.encode() + data[k + len(old):])
    n, frames, warns, size, streams = _read(p, strict=False)
    assert size == (W, H) and n == N and frames == 3
    assert all((w > 0 and h > 0) or (w, h) == (0, 0) for _, w, h in streams), streams
    assert any("is not a size" in w for w in warns)
    with pytest.raises(AedatError, match="is not a size"):
        _read(p, strict=True)


def test_aedat2_cut_inside_its_header(tmp_path):
    p = tmp_path / "cut.aedat"
    p.write_bytes(A2_HEADER[:A2_HEADER.index(b"#End Of")])          # every header line but the last, no data
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with Aedat2Reader(p) as r:
            assert list(r.events()) == []
    assert any("ends inside its header" in str(w.message) for w in caught)
    with pytest.raises(AedatError, match="ends inside its header"):
        Aedat2Reader(p, strict=True)
