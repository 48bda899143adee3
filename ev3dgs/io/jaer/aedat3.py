"""AEDAT 3.1 (cAER / libcaer) reader: polarity, frame, IMU6/IMU9 and special events.

Layout (docs.inivation.com, "AEDAT 3.1"; libcaer's include/libcaer/events/*.h on gitlab.com/inivation/dv/libcaer),
little-endian: `#` header lines ending with `#!END-HEADER`, then
packets of a 28-byte header (int16 eventType, int16 eventSource, int32 eventSize, eventTSOffset, eventTSOverflow,
eventCapacity, eventNumber, eventValid) followed by eventCapacity x eventSize bytes, of which the first
eventNumber events are decoded. Every event's 64-bit timestamp is (eventTSOverflow << 31) | ts32; events with
the valid bit (bit 0) clear are skipped. Origin is top-left (no flip).

* Polarity (8 B): uint32 data (bit 1 polarity, bits 2-16 y, bits 17-31 x), int32 ts.
* Frame: int32 info (bits 1-3 channels), SOF, EOF, SOE, EOE, lengthX, lengthY, positionX, positionY, then uint16
  pixels (left-aligned 16 bit). RGB/RGBA frames are returned in OpenCV order (BGR/BGRA); timestamp = exposure
  midpoint.
* IMU6 (36 B) / IMU9 (48 B): info, ts, accel xyz (g), gyro xyz (deg/s), temperature (deg C) as float32.
* Special (8 B): data bit 0 valid, bits 1-7 type (libcaer caer_special_event_types), bits 8-31 data; those that
  are triggers (timestamp reset, external inputs/generators, APS frame/exposure markers) come out as Triggers with
  AEDAT 4 TriggerType numbers; the rest (timestamp wrap, row-only, ...) are counted and excluded.

IMU values are stored in g and deg/s by libcaer, already in its camera frame (y down: an upright camera at rest
reads accel y ~ -1 g; x right as DV/jAER converters assume), which is the scene's (OpenCV) frame: no change.
A TIMESTAMP_RESET special event (libcaer restarts the clock and the overflow counter) splits the file into
segments with separate clocks: the longest is read, with a warning (strict=True: AedatError).
Decoded polarity events are kept after the first pass (files up to CACHE_BYTES of polarity packets), and a
per-packet time range makes events(start, end) skip packets outside the window on larger files.

Checks (ev3dgs.io.checks): a packet whose eventTSOverflow goes back, or jumps by more than one and back, is
dropped; events whose 32-bit timestamp has bit 31 set, or that go back in time within their stream, or lie
outside the sensor are dropped; frames outside the sensor or with inverted times and IMU samples with
impossible values are dropped; all with a warning naming the byte (strict=True: AedatError instead).
"""
from __future__ import annotations

import re
import struct

import numpy as np

from ...events import Events
from ..checks import MonotonicFilter, Wrap32, imu_plausible
from ..types import AedatError, events_in_window, FrameData, ImuData, RecordingReader, StreamInfo, Triggers

MAGIC = b"#!AER-DAT3.1"
END = b"#!END-HEADER"
MAX_HEADER = 16 << 20
MAX_EVENT_SIZE = 64 << 20
CHUNK_BYTES = 4 << 20
CACHE_BYTES = 128 << 20
HDR = struct.Struct("<hhiiiiii")
SPECIAL, POLARITY, FRAME, IMU6, IMU9 = 0, 1, 2, 3, 4
SIZES = {SPECIAL: 8, POLARITY: 8, IMU6: 36, IMU9: 48}
KINDS = {POLARITY: "events", FRAME: "frames", IMU6: "imu", IMU9: "imu", SPECIAL: "triggers"}
KIND_ORDER = ["events", "frames", "imu", "triggers"]
# libcaer special type -> AEDAT 4 TriggerType
TRIGGER_KIND = {1: 0, 2: 1, 3: 2, 4: 3, 6: 1, 7: 2, 8: 3, 9: 1, 10: 2, 11: 3, 12: 4, 13: 5, 14: 6, 15: 7, 16: 8,
                17: 9}
SENSORS = [("346", (346, 260)), ("240", (240, 180)), ("640", (640, 480)), ("128", (128, 128))]


class Aedat3Reader(RecordingReader):
    format = "aedat3.1"

    def __init__(self, path, *, sensor_size: tuple[int, int] | None = None, strict: bool = False):
        self.path = str(path)
        self.strict = strict
        self.warnings: list[str] = []
        self._index = None
        self._ev_cache: dict = {}                       # eventSource -> list of Events (whole stream)
        self._ev_range: dict = {}                       # eventSource -> {packet offset: (t0, t1, last before)}
        self._open_with_header(self._read_header)
        self.sources = {int(m.group(1)): m.group(2).strip()
                        for m in re.finditer(r"^#Source (\d+): ?(.*)$", self.header, re.M)}
        self._size = sensor_size or self._guess_size()

    def _read_header(self) -> str:
        f = self._f
        first = f.readline(64)
        self._check_magic(first, MAGIC, "AEDAT 3.1")
        lines, pos = [first], len(first)
        while True:
            line = f.readline(1 << 20)
            if not line.startswith(b"#"):
                raise AedatError(f"{self.path}: byte {pos}: header ends without a {END.decode()} line")
            if not line.endswith(b"\n"):
                raise AedatError(f"{self.path}: byte {pos}: corrupt or truncated header line")
            pos += len(line)
            if pos > MAX_HEADER:
                raise AedatError(f"{self.path}: byte {pos}: header longer than {MAX_HEADER >> 20} MiB")
            lines.append(line)
            if line.startswith(END):
                return b"".join(lines).decode("latin-1")

    def _guess_size(self) -> tuple[int, int]:
        for name in self.sources.values():
            for key, size in SENSORS:
                if key in name:
                    return size
        self._warn(f"unknown camera {list(self.sources.values())!r}: assuming a DAVIS346 (346x260)")
        return (346, 260)

    def close(self) -> None:
        self._f.close()

    def sensor_size(self) -> tuple[int, int]:
        return self._size

    # ----- packet index -----
    def _packets(self):
        """Walk the packet headers once (seeking over payloads): a list of (offset, type, source, size,
        overflow, capacity, number). Corrupt headers raise; a truncated tail is salvaged with a warning."""
        if self._index is not None:
            return self._index
        out, pos, f = [], self.data_start, self._f
        while pos < self.file_size:
            f.seek(pos)
            raw = f.read(HDR.size)
            if len(raw) < HDR.size:
                self._warn(f"truncated file: incomplete packet header at byte {pos} ignored")
                break
            typ, src, size, tso, ovf, cap, num, valid = HDR.unpack(raw)
            bad = None
            if typ < 0 or src < 0:
                bad = f"eventType {typ} / eventSource {src}"
            elif size <= 0 or size > MAX_EVENT_SIZE or (typ in SIZES and size != SIZES[typ]) or \
                    (typ == FRAME and size < 36):
                bad = f"eventSize {size} for eventType {typ}"
            elif not (0 <= tso <= size - 4):
                bad = f"eventTSOffset {tso}"
            elif ovf < 0 or cap < 0 or not (0 <= valid <= num <= cap):
                bad = f"overflow/capacity/number/valid {ovf}/{cap}/{num}/{valid}"
            if bad:
                raise AedatError(f"{self.path}: byte {pos}: corrupt packet header ({bad})")
            payload = cap * size
            avail = self.file_size - pos - HDR.size
            if payload > avail:
                n_ok = min(num, avail // size)
                self._warn(f"truncated file: packet at byte {pos} has {payload} payload bytes, {avail} left; "
                           f"{n_ok} of {num} events kept")
                out.append((pos, typ, src, size, ovf, cap, n_ok))
                break
            out.append((pos, typ, src, size, ovf, cap, num))
            pos += HDR.size + payload
        self._index = self._check_overflow(self._split_resets(out))
        return self._index

    def _edge_time(self, pk, last: bool) -> int:
        """64-bit timestamp of the first (or last) event of a packet."""
        pos, typ, src, size, ovf, cap, num = pk
        if not num:
            return -1 if last else 2**62
        self._f.seek(pos + 8)                       # eventTSOffset
        tso = struct.unpack("<i", self._f.read(4))[0]
        self._f.seek(pos + HDR.size + (num - 1 if last else 0) * size + tso)
        raw = self._f.read(4)
        return (ovf << 31) | (struct.unpack("<I", raw)[0] & 0x7FFFFFFF) if len(raw) == 4 else -1

    def _split_resets(self, index: list) -> list:
        """TIMESTAMP_RESET special events restart the clock: keep the longest run of packets between resets."""
        resets = []
        for k, (pos, typ, src, size, ovf, cap, num) in enumerate(index):
            if typ != SPECIAL or not num:
                continue
            self._f.seek(pos + HDR.size)
            d = np.frombuffer(self._f.read(num * size), "<u4")
            d = d[:len(d) - len(d) % 2].reshape(-1, 2)
            if (((d[:, 0] & 1) == 1) & (((d[:, 0] >> 1) & 0x7F) == 1)).any() and 0 < k < len(index) - 1:
                before, after = self._edge_time(index[k - 1], last=True), self._edge_time(index[k + 1], last=False)
                if after < Wrap32.RESET_MAX and before > after + Wrap32.RESET_MIN_DROP:   # the clock did restart
                    resets.append(k)
        if not resets:
            return index
        bounds = [0] + resets + [len(index)]
        segs = [(a, b) for a, b in zip(bounds[:-1], bounds[1:]) if b > a]
        size = [sum(index[k][5] * index[k][3] for k in range(a, b)) for a, b in segs]
        best = int(np.argmax(size))
        where = ", ".join(f"byte {index[k][0]}" for k in resets)
        msg = f"{len(resets)} TIMESTAMP_RESET event(s) in the packets at {where}: the clock restarts there"
        if self.strict:
            raise AedatError(f"{self.path}: {msg}")
        a, b = segs[best]
        self._warn(f"{msg}; reading only segment {best + 1} of {len(segs)} (packets {a}..{b - 1}, the largest)")
        return index[a:b]

    def _problem(self, msg: str) -> None:
        if self.strict:
            raise AedatError(f"{self.path}: {msg}")
        self._warn(msg)

    def _check_overflow(self, index: list) -> list:
        """Drop packets whose eventTSOverflow goes back, or jumps by more than one and back (a flipped bit)."""
        keep, top = [], None
        for k, pk in enumerate(index):
            ovf, nxt = pk[4], index[k + 1][4] if k + 1 < len(index) else None
            if top is not None and (ovf < top or (ovf > top + 1 and nxt is not None and nxt < ovf)):
                self._problem(f"byte {pk[0]}: packet {k} (eventType {pk[1]}) has eventTSOverflow {ovf} after {top}: "
                              "packet dropped")
                continue
            top = ovf if top is None else max(top, ovf)
            keep.append(pk)
        return keep

    def _ordered(self, filt: MonotonicFilter, t: np.ndarray, pos: int, what: str) -> np.ndarray:
        keep = filt(t)
        if keep is None:
            return np.ones(len(t), bool)
        if not keep.all():
            self._problem(f"byte {pos}: {len(t) - int(keep.sum())} {what} going back in time dropped")
        return keep

    def streams(self) -> list[StreamInfo]:
        found: dict[tuple[str, int], int] = {}
        for _, typ, src, *_rest in self._packets():
            if typ in KINDS:
                key = (KINDS[typ], src)
                found[key] = found.get(key, 0) + 1
        keys = sorted(found, key=lambda k: (KIND_ORDER.index(k[0]), k[1]))
        if not any(k == "events" for k, _ in keys):
            keys.insert(0, ("events", min(self.sources, default=1)))
            found[keys[0]] = 0
        out = []
        for i, (kind, src) in enumerate(keys):
            multi = sum(1 for k, _ in keys if k == kind) > 1
            w, h = self._size if kind in ("events", "frames") else (0, 0)
            out.append(StreamInfo(id=i, name=f"{kind}_{src}" if multi else kind, kind=kind, width=w, height=h,
                                  source=self.sources.get(src, str(src)), packets=found[(kind, src)]))
        self._stream_src = {s.id: src for s, (_, src) in zip(out, keys)}
        return out

    def _select(self, stream, kind: str) -> int:
        """-> the eventSource of the chosen stream."""
        ss = self.streams()
        for s in ss:
            if (stream is None and s.kind == kind) or (stream is not None and stream in (s.id, s.name)):
                if s.kind != kind:
                    raise AedatError(f"{self.path}: stream {stream!r} holds {s.kind}, not {kind}")
                return self._stream_src[s.id]
        if stream is None:
            return -1                                   # no such stream: nothing to read
        raise AedatError(f"{self.path}: no stream {stream!r} (streams: {[s.name for s in ss]})")

    def _payloads(self, types, src, ranges=None, window=None):
        """Yield (packet header tuple, bytes of whole events) in bounded chunks, for packets of `types`/`src`
        (ranges + window: only the packets whose time range overlaps the window)."""
        for pk in self._packets():
            pos, typ, s, size, ovf, cap, num = pk
            if typ not in types or s != src or num == 0:
                continue
            if window is not None and pos in ranges and (ranges[pos][1] < window[0] or ranges[pos][0] >= window[1]):
                continue
            per = max(1, CHUNK_BYTES // size)
            for i in range(0, num, per):
                k = min(per, num - i)
                self._f.seek(pos + HDR.size + i * size)
                buf = self._f.read(k * size)
                if len(buf) < k * size:
                    raise AedatError(f"{self.path}: byte {pos}: file shrank while reading")
                yield pk, buf

    # ----- data -----
    def events(self, stream=None, start_us: int | None = None, end_us: int | None = None):
        src = self._select(stream, "events")
        lo = -2**63 if start_us is None else start_us
        hi = 2**63 - 1 if end_us is None else end_us
        if src not in self._ev_range:                   # the first pass decodes (and checks) every packet
            parts, size = [], 0
            for ev in self._decode_events(src, None):
                size += len(ev) * 13
                if parts is not None:
                    if size <= CACHE_BYTES:
                        parts.append(ev)
                    else:
                        parts = None
            if parts is not None:
                self._ev_cache[src] = parts
        if src in self._ev_cache:
            todo = self._ev_cache[src]
        else:
            todo = self._decode_events(src, (lo, hi))
        yield from events_in_window(todo, lo, hi, start_us is not None or end_us is not None)

    def _decode_events(self, src: int, window):
        """Decode the polarity packets of one source (window=(lo, hi): only packets whose time range, known from
        the first pass, overlaps it)."""
        w, h = self._size
        bad = 0
        mono = MonotonicFilter()
        ranges = self._ev_range.setdefault(src, {}) if window is None else self._ev_range[src]
        for (pos, _, _, _, ovf, _, _), buf in self._payloads((POLARITY,), src, ranges if window else None, window):
            if window is not None:
                mono.last = ranges[pos][2]
            before = mono.last
            d = np.frombuffer(buf, "<u4").reshape(-1, 2)
            data = d[:, 0]
            t = (np.int64(ovf) << 31) | (d[:, 1] & 0x7FFFFFFF).astype(np.int64)
            x = (data >> 17).astype(np.int64)
            y = ((data >> 2) & 0x7FFF).astype(np.int64)
            m = (data & 1).astype(bool)
            inside = (x < w) & (y < h)
            if self.strict and (m & ~inside).any():
                raise AedatError(f"{self.path}: byte {pos}: polarity event outside the {w}x{h} sensor")
            bad += int(np.count_nonzero(m & ~inside))
            m &= inside
            neg = m & (d[:, 1] >= 1 << 31)
            if neg.any():
                self._problem(f"byte {pos}: {int(neg.sum())} polarity events with a negative 32-bit timestamp dropped")
                m &= ~neg
            m[m] = self._ordered(mono, t[m], pos, "polarity events")
            if window is None:
                kept = t[m]
                r0 = ranges.get(pos)
                t0, t1 = (int(kept[0]), int(kept[-1])) if len(kept) else (2**63 - 1, -1)
                ranges[pos] = (t0, t1, before) if r0 is None else (min(r0[0], t0), max(r0[1], t1), r0[2])
            if m.any():
                yield Events(t[m], x[m], y[m], np.where(data[m] & 2, 1, -1).astype(np.int8))
        if bad:
            self._warn(f"{bad} polarity events with coordinates outside the {w}x{h} sensor ignored")

    def frames(self, stream=None):
        src = self._select(stream, "frames")
        w, h = self._size
        last = None
        for (pos, _, _, size, ovf, _, _), buf in self._payloads((FRAME,), src):
            for j in range(len(buf) // size):
                try:
                    fr = self._frame(buf[j * size:(j + 1) * size], ovf, pos, self.sources.get(src, ""))
                except AedatError as e:
                    if self.strict:
                        raise
                    self._warn(f"{str(e).split(': ', 1)[-1]}: frame skipped")
                    continue
                if fr is None:
                    continue
                fh, fw = fr.image.shape[:2]
                why = ("outside the sensor" if fr.position[0] + fw > w or fr.position[1] + fh > h else
                       "with inverted times" if fr.exposure_end < fr.exposure_start or fr.frame_end < fr.frame_start
                       else "going back in time" if last is not None and fr.timestamp < last else None)
                if why:
                    self._problem(f"byte {pos}: frame {j} of the packet ({fw}x{fh} at {fr.position}) {why}: dropped")
                    continue
                last = fr.timestamp
                yield fr

    def _frame(self, ev: bytes, ovf: int, pos: int, source: str):
        info, sof, eof, soe, eoe, lx, ly, px, py = struct.unpack_from("<9i", ev)
        if not info & 1:
            return None
        ch = (info >> 1) & 7
        if ch not in (1, 3, 4) or lx < 0 or ly < 0 or px < 0 or py < 0 or 36 + lx * ly * ch * 2 > len(ev):
            raise AedatError(f"{self.path}: byte {pos}: corrupt frame event ({lx}x{ly}x{ch} at {px},{py} "
                             f"in a {len(ev)}-byte event)")
        img = np.frombuffer(ev, "<u2", lx * ly * ch, 36).astype(np.uint16).reshape(ly, lx, ch)
        img = img[:, :, 0] if ch == 1 else img[:, :, [2, 1, 0] + ([3] if ch == 4 else [])]
        base = np.int64(ovf) << 31
        sof, eof, soe, eoe = (int(base | (v & 0x7FFFFFFF)) for v in (sof, eof, soe, eoe))
        return FrameData(timestamp=(soe + eoe) // 2, exposure_start=soe, exposure_end=eoe, frame_start=sof,
                         frame_end=eof, image=np.ascontiguousarray(img), position=(px, py),
                         source=source)

    def imu(self, stream=None) -> ImuData:
        src = self._select(stream, "imu")
        ts, vals = [], []
        mono = MonotonicFilter()
        for (pos, typ, _, size, ovf, _, _), buf in self._payloads((IMU6, IMU9), src):
            n = len(buf) // size
            rec = np.frombuffer(buf, np.uint8).reshape(n, size)[:, :36]
            head = rec[:, :8].copy().view("<u4")
            v = rec[:, 8:36].copy().view("<f4")
            m = (head[:, 0] & 1).astype(bool)
            bad = m & ~imu_plausible(v[:, 0:3], v[:, 3:6], v[:, 6])
            if bad.any():
                self._problem(f"byte {pos}: {int(bad.sum())} IMU samples with non-finite or impossible values dropped")
                m &= ~bad
            m[m] = self._ordered(mono, (np.int64(ovf) << 31) | (head[m, 1] & 0x7FFFFFFF).astype(np.int64), pos,
                                 "IMU samples")
            ts.append((np.int64(ovf) << 31) | (head[m, 1] & 0x7FFFFFFF).astype(np.int64))
            vals.append(v[m])
        if not ts:
            return ImuData()
        v = np.concatenate(vals).astype(np.float32)
        return ImuData(t=np.concatenate(ts), accel=v[:, 0:3].copy(), gyro=v[:, 3:6].copy(), temperature=v[:, 6].copy())

    def triggers(self, stream=None) -> Triggers:
        src = self._select(stream, "triggers")
        ts, ks = [], []
        mono = MonotonicFilter()
        for (pos, _, _, _, ovf, _, _), buf in self._payloads((SPECIAL,), src):
            d = np.frombuffer(buf, "<u4").reshape(-1, 2)
            typ = (d[:, 0] >> 1) & 0x7F
            kind = np.full(len(d), -1, np.int8)
            for c, k in TRIGGER_KIND.items():
                kind[typ == c] = k
            m = (d[:, 0] & 1).astype(bool) & (kind >= 0)
            m[m] = self._ordered(mono, (np.int64(ovf) << 31) | (d[m, 1] & 0x7FFFFFFF).astype(np.int64), pos,
                                 "triggers")
            ts.append((np.int64(ovf) << 31) | (d[m, 1] & 0x7FFFFFFF).astype(np.int64))
            ks.append(kind[m])
        if not ts:
            return Triggers()
        return Triggers(t=np.concatenate(ts), kind=np.concatenate(ks))

    def info(self) -> dict:
        """Streams, counts, time range and file size (events counted by a full pass)."""
        ss = self.streams()
        counts, t0, t1 = {}, None, None
        for s in ss:
            if s.kind == "events":
                n = on = 0
                for ev in self.events(s.id):
                    n, on = n + len(ev), on + ev.on_count
                    lo, hi = int(ev.t.min()), int(ev.t.max())
                    t0, t1 = (lo, hi) if t0 is None else (min(t0, lo), max(t1, hi))
                counts[s.name] = dict(events=n, on=on, off=n - on)
            elif s.kind == "frames":
                counts[s.name] = dict(frames=sum(1 for _ in self.frames(s.id)))
            elif s.kind == "imu":
                counts[s.name] = dict(imu_samples=len(self.imu(s.id)))
            else:
                counts[s.name] = dict(triggers=len(self.triggers(s.id)))
        first = {k: sum(c.get(k, 0) for c in counts.values()) for k in
                 ("events", "on", "off", "frames", "imu_samples", "triggers")}
        return dict(format=self.format, path=self.path, file_size=self.file_size, sources=dict(self.sources),
                    sensor_size=self._size, header_bytes=self.data_start, packets=len(self._packets()),
                    time_range=(t0, t1), **first, counts=counts, streams=[s.__dict__ for s in ss],
                    warnings=list(self.warnings))
