"""AEDAT 2.0 (jAER) reader for DAVIS cameras: DVS events, APS frames, IMU samples and external-input triggers.

Layout (shared/reference/aedat-formats.md §2.1): `#` header lines, then 8-byte big-endian records
(uint32 address, uint32 timestamp in us). Address bit 31 = 0: DVS (bit 10 = 0: y 30-22, x 21-12, polarity 11)
or external input (bit 10 = 1, low bits 2/3/4 = falling/rising/pulse). Bit 31 = 1: IMU when bits 11-10 = 3
(7 consecutive words, type in 30-28, int16 sample in 27-12), else an APS read (y, x as DVS; bits 11-10 = 0 reset
read, 1 signal read; 10-bit ADC in 9-0).

Conventions chosen here:
* y is flipped to a top-left origin (row = height-1-y; jAER's origin is bottom-left), x unchanged.
* APS frame pixel = clip(reset - signal, 0, 1023) << 6 as uint16 (jAER's reset-minus-signal, left-aligned to 16
  bits like libcaer frames). frame_start = first reset read, exposure_start = last reset read, exposure_end =
  first signal read, frame_end = last signal read, timestamp = exposure midpoint. A frame ends when a reset read
  follows signal reads; its size is the bounding box of its reads (ROI frames keep their position).
* IMU: accel raw/accel_lsb_per_g (default 4096 LSB/g, +-8 g, which fits real jAER files; x negated to DV axes as
  aedat4to2 writes it), gyro raw/65.5 deg/s, temperature raw/340 + 35 deg C.
* Timestamps are read as uint32; a backward jump larger than 2^30 is a wrap (2^32 when the previous value was
  >= 2^31, i.e. an int32 overflow, else 2^31) only when it is plausible (checks.Wrap32: the old value near the
  boundary, the new one near 0, and no return to the old range right after); a short run that jumps away
  and back is dropped as outliers, and DVS events (likewise IMU samples and triggers) that go backwards in
  time are dropped, all with a warning naming the byte (strict=True: AedatError instead).
* Triggers: external-input words; kind in AEDAT 4 TriggerType numbers (rising 1, falling 2, pulse 3), -1 when
  the edge is unknown (jAER usually writes the bare EXTERNAL_INPUT_EVENT_ADDR).
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np

from ..events import Events
from .checks import MonotonicFilter, Wrap32
from .types import AedatError, FrameData, ImuData, RecordingReader, StreamInfo, Triggers

MAGIC = b"#!AER-DAT2.0"
MAX_HEADER = 64 << 20
CHUNK_RECORDS = 1 << 19                       # 4 MiB of records per read
SENSORS = [("346", (346, 260)), ("240", (240, 180)), ("640", (640, 480)), ("128", (128, 128))]
STREAMS = [(0, "events", "events"), (1, "frames", "frames"), (2, "imu", "imu"), (3, "triggers", "triggers")]
EXT_KIND = {2: 2, 3: 1, 4: 3}                 # jAER code -> AEDAT 4 TriggerType


@dataclass
class _Chunk:
    events: Events
    frames: list = field(default_factory=list)
    imu_t: np.ndarray | None = None
    imu_raw: np.ndarray | None = None           # (n, 7) int16: ax ay az temp gx gy gz
    trig_t: np.ndarray | None = None
    trig_kind: np.ndarray | None = None


class _FrameBuilder:
    """Accumulates APS reset/signal reads of the frame being read out (state kept across chunks)."""

    def __init__(self, width: int, height: int):
        self.w, self.h = width, height
        self.reset = self.signal = None
        self.t = [0, 0, 0, 0]                    # first reset, last reset, first signal, last signal
        self.in_signal = False
        self.incomplete = self.orphans = 0

    def open(self) -> bool:
        return self.reset is not None

    def start(self) -> None:
        self.reset = np.full((self.h, self.w), -1, np.int32)
        self.signal = np.full((self.h, self.w), -1, np.int32)
        self.t = [None, None, None, None]
        self.in_signal = False

    def add(self, rt, row, x, adc, t) -> None:
        for kind, arr, k in ((0, self.reset, 0), (1, self.signal, 2)):
            m = rt == kind
            if m.any():
                arr[row[m], x[m]] = adc[m]
                tk = t[m]
                if self.t[k] is None:
                    self.t[k] = int(tk[0])
                self.t[k + 1] = int(tk[-1])
        if (rt == 1).any():
            self.in_signal = True

    def feed(self, rt, row, x, adc, t) -> list[FrameData]:
        """APS reads of one chunk (readout type 0 reset / 1 signal) -> the frames they complete."""
        out = []
        # a reset read after signal reads starts a new frame
        was_sig = np.concatenate([[self.open() and self.in_signal], rt[:-1] == 1])
        cuts = np.nonzero((rt == 0) & was_sig)[0].tolist()
        for lo, hi in zip([0] + cuts, cuts + [len(rt)]):
            if lo == hi:
                continue
            if self.open() and self.in_signal and rt[lo] == 0:
                fr, ok = self.finish()
                if fr is not None:
                    out.append(fr)
                    self.incomplete += not ok
            if not self.open():
                if rt[lo] == 1:                  # a segment starting with a signal read has no reset read
                    self.orphans += hi - lo
                    continue
                self.start()
            self.add(rt[lo:hi], row[lo:hi], x[lo:hi], adc[lo:hi], t[lo:hi])
        return out

    def finish(self):
        """-> (FrameData or None, complete?)."""
        r, s = self.reset, self.signal
        self.reset = self.signal = None
        if self.t[2] is None or self.t[0] is None:
            return None, False
        seen = (r >= 0) | (s >= 0)
        rows, cols = np.nonzero(seen.any(axis=1))[0], np.nonzero(seen.any(axis=0))[0]
        r0, r1, c0, c1 = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
        r, s = r[r0:r1, c0:c1], s[r0:r1, c0:c1]
        ok = (r >= 0) & (s >= 0)
        img = np.where(ok, np.clip(r - s, 0, 1023), 0).astype(np.uint16) << 6
        fs, soe, eoe, fe = self.t
        return FrameData(timestamp=(soe + eoe) // 2, exposure_start=soe, exposure_end=eoe, frame_start=fs,
                         frame_end=fe, image=img, position=(int(c0), int(r0)), source="aps"), bool(ok.all())


class Aedat2Reader(RecordingReader):
    format = "aedat2"

    def __init__(self, path, *, sensor_size: tuple[int, int] | None = None, accel_lsb_per_g: float = 4096.0,
                 gyro_lsb_per_dps: float = 65.5, dv_axes: bool = True, chunk_records: int = CHUNK_RECORDS,
                 strict: bool = False):
        self.path = str(path)
        self.strict = strict
        self.warnings: list[str] = []
        self.accel_lsb_per_g, self.gyro_lsb_per_dps, self.dv_axes = accel_lsb_per_g, gyro_lsb_per_dps, dv_axes
        self.chunk_records = max(1, int(chunk_records))
        self._info = None
        self._open_with_header(self._read_header)
        m = re.search(r"^#\s*AEChip:\s*(\S+)", self.header, re.M)
        self.chip = m.group(1) if m else ""
        self._size = sensor_size or self._guess_size()
        body = self.file_size - self.data_start
        self.n_records = body // 8
        if body % 8:
            self._warn(f"truncated file: {body % 8} trailing bytes at byte {self.data_start + 8 * self.n_records} "
                       "ignored (incomplete record)")

    # ----- header -----
    def _read_header(self) -> str:
        f = self._f
        first = f.readline(64)
        self._check_magic(first, MAGIC, "AEDAT 2.0")
        lines, pos = [first], len(first)
        while True:
            c = f.read(1)
            f.seek(pos)
            if c != b"#":
                break
            line = f.readline(1 << 20)
            if not line.endswith(b"\n") and len(line) >= 1 << 20:
                raise AedatError(f"{self.path}: byte {pos}: header line longer than 1 MiB (corrupt header)")
            pos += len(line)
            if pos > MAX_HEADER:
                raise AedatError(f"{self.path}: byte {pos}: header longer than {MAX_HEADER >> 20} MiB")
            lines.append(line)
        return b"".join(lines).decode("latin-1")

    def _guess_size(self) -> tuple[int, int]:
        for key, size in SENSORS:
            if key in self.chip:
                return size
        if self.chip:
            self._warn(f"unknown AEChip {self.chip!r}: assuming a DAVIS346 (346x260)")
        return (346, 260)

    # ----- interface -----
    def close(self) -> None:
        self._f.close()

    def sensor_size(self) -> tuple[int, int]:
        return self._size

    def streams(self) -> list[StreamInfo]:
        info = self.info()
        counts = {"events": 1, "frames": info["frames"], "imu": info["imu_samples"], "triggers": info["triggers"]}
        w, h = self._size
        return [StreamInfo(id=i, name=n, kind=k, source=self.chip, width=w if k in ("events", "frames") else 0,
                           height=h if k in ("events", "frames") else 0)
                for i, n, k in STREAMS if counts[k]]

    def _check_stream(self, stream, kind: str) -> None:
        if stream is None:
            return
        for i, n, k in STREAMS:
            if stream == i or stream == n:
                if k != kind:
                    raise AedatError(f"{self.path}: stream {stream!r} holds {k}, not {kind}")
                return
        raise AedatError(f"{self.path}: no stream {stream!r} (an AEDAT 2.0 file has events, frames, imu, triggers)")

    def events(self, stream=None, start_us: int | None = None, end_us: int | None = None):
        self._check_stream(stream, "events")
        for ch in self._scan(frames=False):
            ev = ch.events
            if start_us is not None or end_us is not None:
                m = (ev.t >= (-2**63 if start_us is None else start_us)) & (ev.t < (2**63 - 1 if end_us is None
                                                                                   else end_us))
                ev = Events(ev.t[m], ev.x[m], ev.y[m], ev.p[m])
            if len(ev):
                yield ev

    def frames(self, stream=None):
        self._check_stream(stream, "frames")
        for ch in self._scan(frames=True):
            yield from ch.frames

    def imu(self, stream=None) -> ImuData:
        self._check_stream(stream, "imu")
        ts, raws = [], []
        for ch in self._scan(frames=False):
            if ch.imu_t is not None:
                ts.append(ch.imu_t)
                raws.append(ch.imu_raw)
        if not ts:
            return ImuData()
        raw = np.concatenate(raws).astype(np.float64)
        accel = raw[:, 0:3] / self.accel_lsb_per_g
        if self.dv_axes:
            accel[:, 0] = -accel[:, 0]
        return ImuData(t=np.concatenate(ts), accel=accel.astype(np.float32),
                       gyro=(raw[:, 4:7] / self.gyro_lsb_per_dps).astype(np.float32),
                       temperature=(raw[:, 3] / 340.0 + 35.0).astype(np.float32))

    def triggers(self, stream=None) -> Triggers:
        self._check_stream(stream, "triggers")
        ts, ks = [], []
        for ch in self._scan(frames=False):
            if ch.trig_t is not None:
                ts.append(ch.trig_t)
                ks.append(ch.trig_kind)
        if not ts:
            return Triggers()
        return Triggers(t=np.concatenate(ts), kind=np.concatenate(ks).astype(np.int8))

    def info(self) -> dict:
        """Streams, counts, time range and file size (one pass over the file, cached)."""
        if self._info is None:
            c = dict(events=0, on=0, off=0, frames=0, imu_samples=0, triggers=0, special=0)
            t0, t1 = None, None
            for ch in self._scan(frames=True):
                n = len(ch.events)
                c["events"] += n
                c["on"] += ch.events.on_count
                c["frames"] += len(ch.frames)
                c["imu_samples"] += 0 if ch.imu_t is None else len(ch.imu_t)
                c["special"] += 0 if ch.trig_t is None else len(ch.trig_t)
                c["triggers"] += 0 if ch.trig_t is None else len(ch.trig_t)
                if n:
                    lo, hi = int(ch.events.t.min()), int(ch.events.t.max())
                    t0, t1 = (lo, hi) if t0 is None else (min(t0, lo), max(t1, hi))
            c["off"] = c["events"] - c["on"]
            self._info = dict(format=self.format, path=self.path, file_size=self.file_size, chip=self.chip,
                              sensor_size=self._size, header_bytes=self.data_start, records=self.n_records,
                              time_range=(t0, t1), **c)
            self._info["streams"] = [s.__dict__ for s in self.streams()]
            self._info["warnings"] = list(self.warnings)
        return self._info

    # ----- decoding -----
    def _scan(self, frames: bool):
        """Decode the file chunk by chunk; state (timestamp wrap, IMU group, open frame) spans chunks."""
        w, h = self._size
        wrap, mono = Wrap32(), {k: MonotonicFilter() for k in ("events", "imu", "triggers")}
        n_outlier = n_back = 0
        first_bad = {}
        imu_carry = np.zeros((0, 2), np.int64)       # (address, t) of an incomplete IMU sample
        fb = _FrameBuilder(w, h)
        n_bad = n_imu_drop = 0
        self._f.seek(self.data_start)
        left, rec0 = self.n_records, 0
        while left > 0:
            k = min(left, self.chunk_records)
            npk = min(left - k, Wrap32.MAX_RUN)
            buf = self._f.read(8 * (k + npk))
            if len(buf) < 8 * (k + npk):
                raise AedatError(f"{self.path}: byte {self._f.tell()}: file shrank while reading")
            self._f.seek(-8 * npk, 1)
            left -= k
            rec = np.frombuffer(buf, ">u4").reshape(-1, 2)
            t, ok, notes = wrap.feed(rec[:k, 1].astype(np.int64), rec[k:, 1].astype(np.int64))
            for kind, j, detail in notes:
                at = self.data_start + 8 * (rec0 + j)
                what = (f"{detail} record(s) whose timestamp jumps by more than 2^30 us and back (outliers)"
                        if kind == "outlier" else f"timestamp jumping back by {-detail} us (not a plausible wrap)")
                if self.strict:
                    raise AedatError(f"{self.path}: byte {at}: {what}")
                first_bad.setdefault(kind, at)
                n_outlier += detail if kind == "outlier" else 0
                n_back += kind == "backward"
            idx = rec0 + np.flatnonzero(ok)
            rec0 += k
            addr = rec[:k, 0][ok].astype(np.uint32)
            t = t[ok]

            aps = (addr >> 31).astype(bool)
            typ = (addr >> 10) & 3
            x = ((addr >> 12) & 0x3FF).astype(np.int64)
            y = ((addr >> 22) & 0x1FF).astype(np.int64)
            dvs = ~aps & ((typ & 1) == 0)
            special = ~aps & ((typ & 1) == 1)
            inside = (x < w) & (y < h)
            outside = (dvs | (aps & (typ < 2))) & ~inside
            if outside.any():
                if self.strict:
                    raise AedatError(f"{self.path}: byte {self.data_start + 8 * int(idx[np.argmax(outside)])}: "
                                     f"x/y outside the {w}x{h} sensor")
                n_bad += int(np.count_nonzero(outside))
            m = dvs & inside
            m[m] = self._ordered(mono["events"], t[m], idx[m], "DVS event")
            ev = Events(t[m], x[m], h - 1 - y[m], np.where(addr[m] & (1 << 11), 1, -1))
            ch = _Chunk(ev)

            special[special] = self._ordered(mono["triggers"], t[special], idx[special], "trigger")
            if special.any():
                code = addr[special] & 0x3FF
                ch.trig_t = t[special]
                ch.trig_kind = np.full(len(code), -1, np.int8)
                for c, kind in EXT_KIND.items():
                    ch.trig_kind[code == c] = kind

            imu = aps & (typ == 3)
            if imu.any() or len(imu_carry):
                ch.imu_t, ch.imu_raw, imu_carry, dropped = self._imu_groups(imu_carry, addr[imu], t[imu])
                n_imu_drop += dropped
                okt = mono["imu"](ch.imu_t)
                if okt is not None:
                    if self.strict and not okt.all():
                        raise AedatError(f"{self.path}: IMU sample at t={int(ch.imu_t[np.argmin(okt)])} goes back in "
                                         "time")
                    ch.imu_t, ch.imu_raw = ch.imu_t[okt], ch.imu_raw[okt]

            if frames:
                a = aps & (typ < 2) & inside
                if a.any():
                    ch.frames = fb.feed(typ[a], h - 1 - y[a], x[a], (addr[a] & 0x3FF).astype(np.int32), t[a])
            yield ch

        if frames and fb.open():
            fr, ok = fb.finish()
            if fr is not None and ok:
                yield _Chunk(Events(), frames=[fr])
            elif fr is not None:
                self._warn("incomplete APS frame at the end of the file dropped (truncated readout)")
        if len(imu_carry):
            self._warn(f"{len(imu_carry)} dangling IMU words at the end of the file ignored (incomplete sample)")
        if n_imu_drop:
            self._warn(f"{n_imu_drop} IMU words outside complete 7-word samples ignored")
        if n_bad:
            self._warn(f"{n_bad} DVS/APS words with coordinates outside the {w}x{h} sensor ignored")
        if fb.incomplete:
            self._warn(f"{fb.incomplete} APS frames with missing reset or signal reads (missing pixels are 0)")
        if fb.orphans:
            self._warn(f"{fb.orphans} APS signal reads without reset reads ignored")
        if n_outlier:
            self._warn(f"byte {first_bad['outlier']}: {n_outlier} records whose timestamps jump by more than "
                       "2^30 us and back (not a wrap) dropped as outliers")
        if n_back:
            self._warn(f"byte {first_bad['backward']}: {n_back} timestamp jumps back that are not plausible "
                       "wraps (left unwrapped)")
        for kind, f in mono.items():
            if f.dropped:
                self._warn(f"byte {self.data_start + 8 * f.first_bad}: {f.dropped} {kind} going back in time "
                           "dropped" if f.first_bad is not None else f"{f.dropped} {kind} going back in time dropped")

    def _ordered(self, filt: MonotonicFilter, t: np.ndarray, idx: np.ndarray, what: str) -> np.ndarray:
        """Keep-mask of the samples of one stream that do not go back in time (strict: raise at the first)."""
        keep = filt(t, idx)
        if keep is None:
            return np.ones(len(t), bool)
        if self.strict and not keep.all():
            raise AedatError(f"{self.path}: byte {self.data_start + 8 * int(idx[np.argmin(keep)])}: {what} "
                             "going back in time")
        return keep

    @staticmethod
    def _imu_groups(carry, addr, t):
        """IMU words (carry + new) -> (t, raw (n,7) int16, new carry, dropped word count)."""
        a = np.concatenate([carry[:, 0].astype(np.uint32), addr])
        tt = np.concatenate([carry[:, 1], t])
        n = len(a)
        typ = ((a >> 28) & 7).astype(np.int64)
        if n < 7:
            return np.zeros(0, np.int64), np.zeros((0, 7), np.int16), _pack(a, tt), 0
        win_typ = np.lib.stride_tricks.sliding_window_view(typ, 7)
        win_t = np.lib.stride_tricks.sliding_window_view(tt, 7)
        start = np.nonzero((win_typ == np.arange(7)).all(1) & (win_t == win_t[:, :1]).all(1))[0]
        covered = np.zeros(n, bool)
        for k in range(7):
            covered[start + k] = True
        tail = max(int(start[-1]) + 7 if len(start) else 0, n - 6)
        dropped = int(np.count_nonzero(~covered[:tail]))
        idx = start[:, None] + np.arange(7)
        raw = ((a[idx] >> 12) & 0xFFFF).astype(np.uint16).view(np.int16)
        return tt[start], raw, _pack(a[tail:], tt[tail:]), dropped


def _pack(a: np.ndarray, t: np.ndarray) -> np.ndarray:
    return np.stack([a.astype(np.int64), t.astype(np.int64)], 1) if len(a) else np.zeros((0, 2), np.int64)
