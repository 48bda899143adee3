"""AEDAT 2.0 with bytes inserted or removed mid-file (issue 53): the reader finds where the 8-byte records lose
their alignment and where they read as records again, skips the bytes between with a warning that says how many
and where, and returns what the intact file holds except the records at the damage. Fixtures: a DAVIS240C
recording built record by record (tests/aedat2_build.py) and shifted copies of it."""
from __future__ import annotations

import warnings
from collections import Counter

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from aedat2_build import HEADER, build
from ev3dgs.io.jaer.aedat2 import Aedat2Reader
from ev3dgs.io.types import AedatError

DATA, RECS, KINDS = build()
D0 = len(HEADER)


def read(path, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r = Aedat2Reader(path, **kw)
        ev = [e for e in r.events() if len(e)]
        out = dict(ev=np.stack([np.concatenate([getattr(e, k).astype(np.int64) for e in ev]) for k in "txyp"], 1),
                   frames=[(f.exposure_start, f.exposure_end, f.image.copy()) for f in r.frames()],
                   trig=r.triggers().t.tolist(), imu=r.imu().t.tolist(), info=r.info(), warnings=list(r.warnings))
        r.close()
    return out


@pytest.fixture(scope="module")
def intact(tmp_path_factory):
    p = tmp_path_factory.mktemp("a2") / "intact.aedat"
    p.write_bytes(DATA)
    return read(p)


def damage(at: int, k: int, op: str, fill: bytes | None = None) -> bytes:
    if op == "insert":
        return DATA[:at] + (fill if fill is not None else bytes(range(1, k + 1))) + DATA[at:]
    return DATA[:at] + DATA[at + k:]


NEAR = 4          # records each side of the one holding the damage that realigning may lose


def events_of(records) -> set:
    """(t, x, y, p) of the DVS events among these record indices, decoded from the builder's own records."""
    out = set()
    for j in records:
        if 0 <= j < len(RECS) and KINDS[j] == "e":
            a, t = int(RECS[j, 0]), int(RECS[j, 1])
            out.add((t, (a >> 12) & 0x3FF, 179 - ((a >> 22) & 0x1FF), 1 if a & (1 << 11) else -1))
    return out


def check_against_intact(got: dict, ref: dict, at: int, k: int, op: str) -> None:
    """Everything but the records at the damage is the intact file's; nothing is invented."""
    rec = (at - D0) // 8
    t_dmg = int(RECS[min(rec, len(RECS) - 1), 1])
    have = Counter(map(tuple, ref["ev"].tolist()))
    got_c = Counter(map(tuple, got["ev"].tolist()))
    extra = got_c - have
    assert not extra, f"events the intact file does not have: {list(extra)[:3]}"
    missing = have - got_c
    assert set(missing) <= events_of(range(rec - NEAR, rec + NEAR + 1)), "events lost away from the damage"
    assert got["info"]["time_range"] == ref["info"]["time_range"]
    assert got["trig"] == ref["trig"] or (len(ref["trig"]) - len(got["trig"]) == 1
                                          and set(got["trig"]) <= set(ref["trig"]))
    assert set(got["imu"]) <= set(ref["imu"]) and len(ref["imu"]) - len(got["imu"]) <= 1
    # frames: every frame away from the damage is the intact one; the one whose readout holds it may be
    # incomplete (its missing pixels 0) or, at the file's end, dropped as a truncated readout
    got_f = {(s, e): img for s, e, img in got["frames"]}
    assert len(got_f) == len(got["frames"])
    for s0, e0, img0 in ref["frames"]:
        hit = s0 - 2000 <= t_dmg <= e0 + 2000
        assert (s0, e0) in got_f or hit
        if not hit:
            np.testing.assert_array_equal(got_f[(s0, e0)], img0)
    assert set(got_f) <= {(s0, e0) for s0, e0, _ in ref["frames"]}
    # the summary names the bytes skipped and where
    assert got["info"]["skipped_bytes"] >= (k if op == "insert" else 0)
    msg = [w for w in got["warnings"] if w.startswith("skipped ")]
    assert len(msg) == 1 and "do not read as 8-byte records" in msg[0]
    byte = int(msg[0].split(" at byte ")[1].split(")")[0].split(",")[0])
    assert at - 40 <= byte <= at + 8 * Aedat2Reader.RESYNC_WINDOW   # records that read as such by chance go on


# offsets: among events early on, inside an APS frame's readout, beside an IMU sample, near the end
OFFSETS = [D0 + 8 * 300 + 5, D0 + 8 * 6000, D0 + 8 * 7100 + 3, D0 + 8 * 11500 + 7, len(DATA) - 8 * 400 - 2]


@pytest.mark.parametrize("op", ["insert", "remove"])
@pytest.mark.parametrize("k", range(1, 8))
def test_shifted_copies_realign(tmp_path, intact, op, k):
    for at in OFFSETS:
        p = tmp_path / f"{op}{k}-{at}.aedat"
        p.write_bytes(damage(at, k, op))
        check_against_intact(read(p), intact, at, k, op)
        with pytest.raises(AedatError, match="do not read as 8-byte records"):
            Aedat2Reader(p, strict=True)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(rec=st.integers(40, len(RECS) - 200), within=st.integers(0, 7), k=st.integers(1, 7),
       op=st.sampled_from(["insert", "remove"]), fill=st.binary(min_size=7, max_size=7))
def test_any_offset_and_shift_property(tmp_path, intact, rec, within, k, op, fill):
    at = D0 + 8 * rec + within
    p = tmp_path / "h.aedat"
    p.write_bytes(damage(at, k, op, fill[:k]))
    check_against_intact(read(p), intact, at, k, op)


def test_intact_file_untouched_and_two_shifts(tmp_path, intact):
    assert intact["warnings"] == [] and intact["info"]["skipped_bytes"] == 0
    assert len(intact["ev"]) == int((KINDS == "e").sum()) and len(intact["frames"]) == 2
    a, b = OFFSETS[0], OFFSETS[3]
    p = tmp_path / "two.aedat"
    p.write_bytes(DATA[:a] + b"\x07\x07\x07" + DATA[a:b] + DATA[b + 5:])
    got = read(p)
    assert "2 at byte" not in got["warnings"][0] and got["warnings"][0].count(" at byte ") == 2
    assert got["info"]["time_range"] == intact["info"]["time_range"]
    assert not Counter(map(tuple, got["ev"].tolist())) - Counter(map(tuple, intact["ev"].tolist()))


def test_inserted_garbage_is_skipped(tmp_path, intact):
    """Random bytes inserted mid-file (aligned or not) or replacing the file's end: skipped as a whole, nothing
    of them decoded (tools/bench/bench_aedat.py --resync times it)."""
    rng = np.random.default_rng(3)
    at = OFFSETS[1]
    reads = {}
    for n in (1 << 18, 1 << 19, (1 << 19) + 5):
        p = tmp_path / f"g{n}.aedat"
        p.write_bytes(DATA[:at] + rng.integers(0, 256, n, dtype=np.uint8).tobytes() + DATA[at:])
        got = read(p)
        assert got["info"]["time_range"] == intact["info"]["time_range"]
        assert not Counter(map(tuple, got["ev"].tolist())) - Counter(map(tuple, intact["ev"].tolist()))
        assert n <= got["info"]["skipped_bytes"] <= n + 40       # and the records at its two ends
    p = tmp_path / "tail.aedat"
    p.write_bytes(DATA[:at] + rng.integers(0, 256, 1 << 19, dtype=np.uint8).tobytes())
    got = read(p)
    t_at = int(RECS[(at - D0) // 8, 1])
    assert got["info"]["time_range"][1] <= t_at and "no alignment" in got["warnings"][0]
    assert not Counter(map(tuple, got["ev"].tolist())) - Counter(map(tuple, intact["ev"].tolist()))
