"""AEDAT 2.0 (jAER) reader: DVS events, APS frames, IMU samples and external-input triggers of DAVIS cameras,
and DVS events of the DVS128.

Layout (docs.inivation.com, "AEDAT 2.0"; jAER's DavisChip.java and DVS128.java on github.com/SensorsINI/jaer):
printable `#` header lines (jAER ends them with `#End Of ASCII Header`), then 8-byte big-endian records
(uint32 address, uint32 timestamp in us). The header's `# AEChip:` line names the chip and so the address layout
(ev3dgs.io.jaer); an unknown chip is refused, a missing line is inferred from the address ranges with a warning
(or given with sensor_size). DAVIS address bit 31 = 0: DVS (bit 10 = 0: y 30-22, x 21-12, polarity 11) or external
input (bit 10 = 1, low bits 2/3/4 = falling/rising/pulse). Bit 31 = 1: IMU when bits 11-10 = 3 (7 consecutive words,
type in 30-28, int16 sample in 27-12), else an APS read (bits 11-10 = 0 reset read, 1 signal read; ADC in 9-0).

Conventions chosen here:
* y is flipped to a top-left origin (row = height-1-y; jAER's origin is bottom-left); x as jAER extracts it.
* APS frames: ev3dgs.io.aps (jAER's first/last pixel address boundaries, rolling shutter with per-row exposure).
* IMU: full scale from the header (jAER's defaults +-8 g / +-1000 deg/s with a warning when it is not stated),
  axes turned into the camera frame (OpenCV: x right, y down, z forward) for both sensors, temperature
  raw/340 + 35 deg C (ev3dgs.io.jaer).
* Timestamps are read as uint32 and unwrapped by checks.Wrap32 (plausible wraps only). A timestamp reset (the
  clock restarting near 0) splits the file into segments: the longest is read, with a warning naming the byte
  (strict=True: AedatError). Outlier runs and DVS events / IMU samples / triggers going back in time are dropped
  with a warning naming the byte (strict=True: AedatError).
* Triggers: external-input words; kind in AEDAT 4 TriggerType numbers (rising 1, falling 2, pulse 3), -1 when
  the edge is unknown (jAER usually writes the bare EXTERNAL_INPUT_EVENT_ADDR).
* Decoding happens once: the first pass keeps the events, IMU samples and triggers (up to CACHE_RECORDS records;
  beyond that a per-chunk time index lets events(start, end) decode only the chunks it needs).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ...events import Events
from . import chips as jaer
from ..aps import FrameBuilder
from ..checks import MonotonicFilter, Wrap32
from ..types import AedatError, events_in_window, ImuData, RecordingReader, StreamInfo, Triggers

MAGIC = b"#!AER-DAT2.0"
END_OF_HEADER = b"#End Of ASCII Header"
MAX_HEADER = 64 << 20
CHUNK_RECORDS = 1 << 19                       # 4 MiB of records per read
CACHE_RECORDS = 1 << 24                       # files up to 128 MiB are decoded once and kept in memory
STREAMS = [(0, "events", "events"), (1, "frames", "frames"), (2, "imu", "imu"), (3, "triggers", "triggers")]
EXT_KIND = {2: 2, 3: 1, 4: 3}                 # jAER code -> AEDAT 4 TriggerType
_PRINTABLE = np.zeros(256, bool)
_PRINTABLE[32:127] = True
_PRINTABLE[[9, 10, 13]] = True
_PRINTABLE[160:] = True                       # latin-1 letters in user comments


@dataclass
class _Chunk:
    events: Events
    frames: list = field(default_factory=list)
    imu_t: np.ndarray | None = None
    imu_raw: np.ndarray | None = None           # (n, 7) int16: ax ay az temp gx gy gz
    trig_t: np.ndarray | None = None
    trig_kind: np.ndarray | None = None


class Aedat2Reader(RecordingReader):
    format = "aedat2"

    def __init__(self, path, *, sensor_size: tuple[int, int] | None = None, accel_lsb_per_g: float | None = None,
                 gyro_lsb_per_dps: float | None = None, chunk_records: int = CHUNK_RECORDS, strict: bool = False,
                 cache_records: int = CACHE_RECORDS):
        self.path = str(path)
        self.strict = strict
        self.warnings: list[str] = []
        self.chunk_records = max(1, int(chunk_records))
        self.cache_records = cache_records
        self._info = self._cache = self._index = None
        self.resync: list[dict] = []                 # mid-file realignments: byte and bytes skipped
        self._open_with_header(self._read_header)
        self._align()
        body = self.file_size - self.data_start
        self.n_records = body // 8
        self._pieces, self._starts = [(self.data_start, self.n_records)], [0]
        if not self.n_records and END_OF_HEADER.decode("latin-1") not in self.header:
            self._warn(f"byte {self.data_start}: the file ends inside its header (no end-of-header line, no "
                       "data): truncated")
        self.chip, spec = jaer.chip_from_header(self.header, self.path)
        if sensor_size is not None:
            spec = jaer.chip_for_size(tuple(sensor_size)) if spec is None else \
                jaer.Chip(spec.name, spec.layout, tuple(sensor_size), spec.first, spec.last)
        elif spec is None:
            self._f.seek(self.data_start)
            sample = np.frombuffer(self._f.read(8 * min(self.n_records, 1 << 20)), ">u4").reshape(-1, 2)[:, 0]
            spec, why = jaer.infer_chip(sample, self.path)
            self._warn(f"no AEChip line in the header: sensor taken as {spec.name} {spec.size[0]}x{spec.size[1]} "
                       f"({why}); pass --sensor-size WxH if that is wrong")
        self.spec = spec
        self._size = spec.size
        acc, gyr, self._imu_note = jaer.imu_scales(self.header)
        self.accel_lsb_per_g = accel_lsb_per_g or acc
        self.gyro_lsb_per_dps = gyro_lsb_per_dps or gyr
        if accel_lsb_per_g and gyro_lsb_per_dps:
            self._imu_note = None
        self._resync()
        self._rec_lo, self._rec_hi = 0, self.n_records
        self._timeline()

    # ----- where the 8-byte records start -----
    ALIGN_RECORDS = 4096                     # records whose timestamps judge an alignment
    ALIGN_MIN_RECORDS = 64                   # fewer: too little to judge, the header's end is taken as it is
    ALIGN_ORDERED = 0.9                      # fraction of non-decreasing steps of a plausible alignment
    ALIGN_INTACT = 0.99                      # at the header's end and this ordered: intact, nothing to search
    ALIGN_MARGIN = 0.02                      # another offset must beat the header's end by this much

    def _in_order(self, raw: bytes) -> float:
        """How plausible `raw` is as records: the fraction of timestamp steps in order, times (for a DAVIS chip
        the header names) the fraction of DVS addresses inside the sensor. A shifted read mixes address bytes
        into the timestamps; where an address's low byte is always 0 its shifted timestamps stay in order, but
        then the timestamp bytes land in the address, whose x and y fall outside the sensor."""
        rec = np.frombuffer(raw[:len(raw) // 8 * 8], ">u4").reshape(-1, 2)
        t = rec[:, 1].astype(np.int64)
        ordered = float(np.mean(np.diff(t) >= 0)) if len(t) > 1 else 1.0
        chip = getattr(self, "_header_chip", None)
        if chip is None or chip.layout != "davis":
            return ordered
        a = rec[:, 0]
        dvs = (a >> 31) == 0
        if not dvs.any():
            return ordered
        inside = (((a >> 12) & 0x3FF) < chip.size[0]) & (((a >> 22) & 0x1FF) < chip.size[1])
        return ordered * float(np.mean(inside[dvs]))

    def _align(self) -> None:
        """Bytes inserted or removed where the header meets the data shift every record: its timestamps then
        decode as noise. Keep the header's end when its records are in time order; else take the offset of
        0-7 bytes whose records are (a warning; strict: an error), and refuse when none is."""
        try:
            self._header_chip = jaer.chip_from_header(self.header, self.path)[1]
        except AedatError:       # an unsupported chip is refused with its own message later
            self._header_chip = None
        self._f.seek(self.data_start)
        raw = self._f.read(8 * self.ALIGN_RECORDS + 8)
        tail = (self.file_size - self.data_start) % 8
        if len(raw) < 8 * self.ALIGN_MIN_RECORDS or (not tail and self._in_order(raw) >= self.ALIGN_INTACT):
            return
        if self._in_order(raw[:8 * self.RESYNC_RUN]) == 1.0:
            return               # the first records read as records: a shift is further on (_resync finds it)
        # a shifted record's 'timestamp' mixes address bytes into it: measured 49-95 % of steps in order at the
        # seven wrong offsets of a DAVIS346 file, 99.7 % at the right one
        scores = [self._in_order(raw[k:]) for k in range(8)]
        best = max(range(8), key=lambda k: scores[k])
        if tail and scores[tail] >= self.ALIGN_ORDERED and scores[tail] >= scores[best] - self.ALIGN_MARGIN \
                and scores[tail] >= scores[0] + self.ALIGN_MARGIN:
            best = tail          # the file's end agrees: bytes were inserted or removed at its start
        if best == 0 or scores[best] < scores[0] + self.ALIGN_MARGIN:
            if scores[0] >= self.ALIGN_ORDERED:
                return
            best = 0
        if scores[best] < self.ALIGN_ORDERED:
            raise AedatError(f"{self.path}: byte {self.data_start}: no 8-byte record alignment of the data gives "
                             f"timestamps in order (at most {100 * max(scores):.0f} % of steps; damaged data?)")
        msg = (f"byte {self.data_start}: the records start {best} bytes after the header's end (bytes inserted or "
               f"removed at the header/data boundary): {100 * scores[best]:.0f} % of timestamp steps in order there, "
               f"{100 * scores[0]:.0f} % at the header's end")
        if self.strict:
            raise AedatError(f"{self.path}: {msg}")
        self._warn(f"{msg}; reading from byte {self.data_start + best}")
        self.data_start += best

    # ----- mid-file: bytes inserted or removed shift every record after them -----
    RESYNC_WINDOW = 64                       # records judged together: below RESYNC_VALID of them valid = a break
    RESYNC_VALID = 0.8
    RESYNC_RUN = 32                          # consecutive valid records that confirm an alignment after a break
    RESYNC_STEP = 1 << 28                    # us: a forward timestamp step above this (4.5 min) is not a record's
    RESYNC_SEARCH = 1 << 16                  # bytes searched per try after a break (doubling up to a chunk)
    RESYNC_CONTINUOUS = 1 << 18              # bytes searched for an alignment continuing the break's time
    RESYNC_BACK = 8                          # records before a break where the search for the next run starts
    RESYNC_NEAR = 1 << 20                    # us: records this close before a realigned run are kept (~1 s)
    RESYNC_MAX = 64                          # realignments in one file: more is damage, not a few slips
    RESYNC_MAX_BREAKS = 4096                 # breaks searched at all (each search reads at most ~2 MiB)

    def _addr_ok(self, a: np.ndarray) -> np.ndarray:
        """Which uint32 words are addresses the chip can write (x/y inside the sensor, a known word type)."""
        if self.spec.layout == "dvs128":
            return (a & 0x7FFF0000) == 0
        w, h = self._size
        aps = (a >> 31) == 1
        typ = (a >> 10) & 3
        inside = (((a >> 12) & 0x3FF) < w) & (((a >> 22) & 0x1FF) < h)
        special = ~aps & ((typ & 1) == 1) & ((a & 0x7FFFF000) == 0)
        imu = aps & (typ == 3) & (((a >> 28) & 7) < 7)
        return (~aps & ((typ & 1) == 0) & inside) | special | imu | (aps & (typ != 3) & inside)

    def _valid(self, rec: np.ndarray, anchor: int | None):
        """Records that read as records at this alignment: a valid address and a timestamp at most RESYNC_STEP
        ahead of the latest valid one before it, never behind it (32-bit wraps unwrapped step by step).
        -> (valid mask, the reference time before each record (unwrapped, int64), the offset to raw values)."""
        a = rec[:, 0]
        u = rec[:, 1].astype(np.int64)
        start = int(u[0]) if anchor is None else anchor
        d = np.diff(u, prepend=start)
        d = ((d + (1 << 31)) & 0xFFFFFFFF) - (1 << 31)
        tu = start + np.cumsum(d)
        addr = self._addr_ok(a)
        ok = addr & (d >= 0) & (d < self.RESYNC_STEP)
        if ok.all():             # in order throughout (intact data): the reference is the previous record
            return ok, tu
        ref = np.maximum.accumulate(np.where(ok, tu, np.iinfo(np.int64).min))
        ref = np.maximum(np.concatenate([[start], ref[:-1]]), start)
        valid = addr & (tu >= ref) & (tu - ref < self.RESYNC_STEP)
        return valid, tu

    def _first_run(self, valid: np.ndarray, run: int) -> int:
        """Index of the first `run` consecutive True in valid, -1 if none."""
        if len(valid) < run:
            return -1
        c = np.concatenate([[0], np.cumsum(valid)])
        hit = np.flatnonzero(c[run:] - c[:-run] == run)
        return int(hit[0]) if hit.size else -1

    def _search(self, start: int, last_t: int | None, home: int):
        """The first byte >= start from which RESYNC_RUN consecutive records are valid at some alignment ->
        (byte, raw t there, whether t continues last_t) or None. One whose time continues last_t (within
        RESYNC_STEP) is preferred while one is found within RESYNC_CONTINUOUS bytes; else the earliest (a clock
        reset). The current alignment (byte % 8 == home) wins when its run starts within RESYNC_RUN records of
        the earliest: data that repeats one address reads as records at a second alignment too."""
        def pick(cands: dict):
            first = min(cands.values())
            own = cands.get(home)
            return own if own is not None and own[0] <= first[0] + 8 * self.RESYNC_RUN else first

        span, first_any = self.RESYNC_SEARCH, {}
        pos = start
        while pos + 8 * self.RESYNC_RUN <= self.file_size:
            self._f.seek(pos)
            raw = self._f.read(span + 8 * (self.RESYNC_RUN + 1))
            cont_c = {}
            for k in range(8):
                n = (len(raw) - k) // 8
                if n < self.RESYNC_RUN:
                    continue
                rec = np.frombuffer(raw[k:k + 8 * n], ">u4").reshape(-1, 2)
                u = rec[:, 1].astype(np.int64)
                d = ((np.diff(u, prepend=u[0]) + (1 << 31)) & 0xFFFFFFFF) - (1 << 31)
                ok = self._addr_ok(rec[:, 0]) & (d >= 0) & (d < self.RESYNC_STEP)
                ok[0] = bool(self._addr_ok(rec[:1, 0])[0])
                c = np.concatenate([[0], np.cumsum(ok)])
                runs = np.flatnonzero(c[self.RESYNC_RUN:] - c[:-self.RESYNC_RUN] == self.RESYNC_RUN)
                runs = runs[8 * runs + k < span]             # starts inside this span: the next try goes on
                if not runs.size:
                    continue
                a = (pos + k) % 8
                j = int(runs[0])
                first_any.setdefault(a, (pos + k + 8 * j, int(u[j])))
                if last_t is not None:
                    step = ((u[runs] - last_t + (1 << 31)) & 0xFFFFFFFF) - (1 << 31)
                    cont = np.flatnonzero((step >= -self.RESYNC_STEP) & (step < self.RESYNC_STEP))
                    if cont.size:
                        j = int(runs[cont[0]])
                        cont_c[a] = (pos + k + 8 * j, int(u[j]))
            if cont_c:
                return (*pick(cont_c), True)
            if first_any and (last_t is None or pos + span - start >= self.RESYNC_CONTINUOUS):
                return (*pick(first_any), False)
            pos += span
            span = min(2 * span, max(8 * self.chunk_records, self.RESYNC_SEARCH))
        return (*pick(first_any), False) if first_any else None

    def _resync(self) -> None:
        """One pass over the data: where the records stop reading as records (a run of RESYNC_WINDOW with under
        RESYNC_VALID valid) and another alignment reads as records again, bytes were inserted or removed: the
        records before and after are kept as separate pieces and the bytes between are skipped, with a warning
        naming them (strict: AedatError). A break after which the same alignment reads on (outliers, a clock
        reset) is left to the per-record checks of the decoding pass."""
        pieces, skipped, breaks = [], [], 0
        pos = self.data_start                              # start of the current piece
        scan, anchor = pos, None                           # next record to judge, reference time before it
        win = self.RESYNC_WINDOW
        cap = 8 * max(self.chunk_records, 16 * win)
        while self.file_size - scan >= 8 * win:
            self._f.seek(scan)
            raw = self._f.read(min(cap, (self.file_size - scan) // 8 * 8))
            rec = np.frombuffer(raw, ">u4").reshape(-1, 2)
            valid, tu = self._valid(rec, anchor)
            if valid.all():
                low = valid[:0]
            else:
                c = np.concatenate([[0], np.cumsum(valid)])
                low = np.flatnonzero(c[win:] - c[:-win] < self.RESYNC_VALID * win)
            if not low.size:
                if len(rec) >= (self.file_size - scan) // 8:
                    break
                keep = max(1, len(rec) - win)              # judge the last window again with the next chunk
                anchor = self._anchor(valid[:keep], tu[:keep], anchor)
                scan += 8 * keep
                continue
            i = int(low[0])
            f = i + int(np.argmin(valid[i:]))              # the first record that does not read as one
            last = self._anchor(valid[:f], tu[:f], anchor)
            last_raw = None if last is None else last & 0xFFFFFFFF
            # the first records past the damage can read as records by chance: search from a little before
            hit = self._search(max(pos, scan + 8 * (f - self.RESYNC_BACK)), last_raw, pos % 8)
            if hit is None:
                if self.file_size - (scan + 8 * f) >= 8 * 4 * self.RESYNC_RUN:   # garbage to the end
                    end = scan + 8 * f
                    pieces.append((pos, (end - pos) // 8))
                    skipped.append((end, self.file_size))
                    pos = None
                break
            at, t_raw, continuous = hit
            breaks += 1
            garbage = continuous and at - (scan + 8 * f) >= 8 * win     # a long run overwritten or inserted
            if (at - pos) % 8 == 0 and not garbage:        # the same alignment reads on: left to the decoding
                scan, anchor = (at, None) if at > scan or anchor is not None else (scan + 8, None)
                if breaks > self.RESYNC_MAX_BREAKS:        # records that keep breaking: the decoding pass judges
                    break
                continue
            if len(pieces) >= self.RESYNC_MAX:
                raise AedatError(f"{self.path}: byte {at}: the 8-byte records lose their alignment more than "
                                 f"{self.RESYNC_MAX} times: damaged data")
            # the run found starts at the first whole record after the damage or one record later, and the
            # damage ends at most 15 bytes before that record: nothing within 23 bytes before the run is kept
            end = min(scan + 8 * f, pos + 8 * max((at - 23 - pos) // 8, 0))
            end = self._trim(max(end, pos), pos, t_raw)
            at = min(at + 16, self.file_size)  # the first records after the damage may hold its bytes yet read as ones
            pieces.append((pos, (end - pos) // 8))
            skipped.append((end, at))
            pos = scan = at
            anchor = None
        tail = 0 if pos is None else (self.file_size - pos) % 8
        if pos is not None:
            pieces.append((pos, (self.file_size - pos) // 8))
        if tail:
            body = self.file_size - pos
            self._warn(f"{tail} trailing bytes at byte {self.file_size - tail} ignored: the data ({body} bytes from "
                       f"byte {pos}) is not a whole number of 8-byte records (truncated file, or a damaged header)")
        if not skipped:
            return
        where = ", ".join(f"{b - a} at byte {a}" for a, b in skipped)
        total = sum(b - a for a, b in skipped)
        msg = (f"skipped {total} bytes that do not read as 8-byte records ({where}): bytes inserted, removed or "
               "overwritten mid-file; the records after them realigned")
        if pos is None:
            msg += "; the last run reads as records at no alignment (damaged to the end of the file)"
        if self.strict:
            raise AedatError(f"{self.path}: {msg}")
        self._warn(msg)
        self.resync = [dict(byte=a, skipped=b - a) for a, b in skipped]
        self._pieces = [p for p in pieces if p[1] > 0]
        self._starts = np.cumsum([0] + [n for _, n in self._pieces[:-1]]).tolist()
        self.n_records = sum(n for _, n in self._pieces)

    def _trim(self, end: int, pos: int, t_next: int) -> int:
        """Records just before a break that read as records by chance (a shifted read's timestamp can land
        within RESYNC_STEP): drop those, up to RESYNC_RUN of them, whose time is not within RESYNC_NEAR before
        the first record after the break."""
        n = min((end - pos) // 8, self.RESYNC_RUN)
        if n <= 0:
            return end
        self._f.seek(end - 8 * n)
        u = np.frombuffer(self._f.read(8 * n), ">u4")[1::2].astype(np.int64)
        step = ((t_next - u + (1 << 31)) & 0xFFFFFFFF) - (1 << 31)
        near = (step >= 0) & (step < self.RESYNC_NEAR)
        last = np.flatnonzero(near)
        return end - 8 * (n - (int(last[-1]) + 1 if last.size else n))

    @staticmethod
    def _anchor(valid: np.ndarray, tu: np.ndarray, anchor: int | None) -> int | None:
        idx = np.flatnonzero(valid)
        return int(tu[idx[-1]]) if idx.size else anchor

    def _piece(self, v: int) -> int:
        from bisect import bisect_right
        return max(0, bisect_right(self._starts, v) - 1)

    def _byte(self, v: int) -> int:
        """File byte of (virtual) record v."""
        i = self._piece(v)
        return self._pieces[i][0] + 8 * (v - self._starts[i])

    def _read_records(self, v: int, n: int) -> bytes:
        """The bytes of records v .. v+n-1, across the pieces the realignment left."""
        out = []
        i = self._piece(v)
        while n > 0 and i < len(self._pieces):
            b0, pn = self._pieces[i]
            off = v - self._starts[i]
            take = min(n, pn - off)
            self._f.seek(b0 + 8 * off)
            out.append(self._f.read(8 * take))
            v, n, i = v + take, n - take, i + 1
        return out[0] if len(out) == 1 else b"".join(out)

    # ----- header -----
    def _read_header(self) -> str:
        f = self._f
        first = f.readline(64)
        self._check_magic(first, MAGIC, "AEDAT 2.0")
        lines, pos = [first], len(first)
        while not lines[-1].startswith(END_OF_HEADER):
            f.seek(pos)
            line = f.readline(1 << 20)
            if not line.startswith(b"#"):
                break
            ok = _PRINTABLE[np.frombuffer(line, np.uint8)]
            if ok.all() and line.endswith(b"\n"):
                pos += len(line)
                if pos > MAX_HEADER:
                    raise AedatError(f"{self.path}: byte {pos}: header longer than {MAX_HEADER >> 20} MiB")
                lines.append(line)
                continue
            # a '#' that starts binary data (an address whose first byte is 0x23), or a damaged header line
            text = int(np.argmin(ok)) if not ok.all() else len(line)
            if text >= 16 or (ok.all() and not line.endswith(b"\n")):
                what = "the file ends inside the header" if ok.all() else \
                    f"a header line cut after {text} bytes (binary data follows without a line end)"
                raise AedatError(f"{self.path}: byte {pos}: {what}: truncated or damaged header")
            break
        f.seek(pos)
        return b"".join(lines).decode("latin-1")

    # ----- timestamps: resets split the file -----
    def _timeline(self) -> None:
        """One pass over the timestamps: find timestamp resets and pick the segment to read."""
        resets = []
        wrap = Wrap32()
        left, rec0 = self.n_records, 0
        while left > 0:
            k = min(left, self.chunk_records)
            npk = min(left - k, Wrap32.MAX_RUN)
            buf = self._read_records(rec0, k + npk)
            ts = np.frombuffer(buf, ">u4")[1::2].astype(np.int64)
            for kind, j, detail in wrap.feed(ts[:k], ts[k:])[2]:
                if kind == "reset":
                    resets.append((rec0 + j, detail))
            rec0 += k
            left -= k
        if not resets:
            return
        bounds = [0] + [r for r, _ in resets] + [self.n_records]
        segs = list(zip(bounds[:-1], bounds[1:]))
        best = max(range(len(segs)), key=lambda i: segs[i][1] - segs[i][0])
        where = ", ".join(f"byte {self._byte(r)} (t {a} -> {b} us)" for r, (a, b) in resets)
        msg = (f"{len(resets)} timestamp reset(s) at {where}: the file holds {len(segs)} segments with separate "
               "clocks")
        if self.strict:
            raise AedatError(f"{self.path}: {msg}")
        self._rec_lo, self._rec_hi = segs[best]
        self._warn(f"{msg}; reading only segment {best + 1} (records {segs[best][0]}..{segs[best][1] - 1}, "
                   f"{segs[best][1] - segs[best][0]} of {self.n_records}, the longest)")

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

    def _decoded(self) -> dict:
        """Events, IMU and triggers of the whole file, decoded once (a frames pass fills it on the way)."""
        if self._cache is None:
            for _ in self._scan(frames=False):
                pass
        return self._cache

    def events(self, stream=None, start_us: int | None = None, end_us: int | None = None):
        self._check_stream(stream, "events")
        lo = -2**63 if start_us is None else start_us
        hi = 2**63 - 1 if end_us is None else end_us
        if self._cache is None and self._index is None:
            self._decoded()
        if self._cache is not None and self._cache["events"] is not None:
            parts = self._cache["events"]
            todo = parts
        else:                                      # a large file: decode only the chunks that overlap [lo, hi)
            todo = (ch.events for ch in self._scan(False, window=(lo, hi)))
        yield from events_in_window(todo, lo, hi, start_us is not None or end_us is not None)

    def frames(self, stream=None):
        self._check_stream(stream, "frames")
        for ch in self._scan(frames=True):
            yield from ch.frames

    def imu(self, stream=None) -> ImuData:
        self._check_stream(stream, "imu")
        c = self._decoded()
        if not c["imu_t"]:
            return ImuData()
        if self._imu_note:
            self._warn(self._imu_note)
        accel, gyro, temp = jaer.imu_to_camera(np.concatenate(c["imu_raw"]), self.accel_lsb_per_g,
                                               self.gyro_lsb_per_dps)
        return ImuData(t=np.concatenate(c["imu_t"]), accel=accel, gyro=gyro, temperature=temp)

    def triggers(self, stream=None) -> Triggers:
        self._check_stream(stream, "triggers")
        c = self._decoded()
        if not c["trig_t"]:
            return Triggers()
        return Triggers(t=np.concatenate(c["trig_t"]), kind=np.concatenate(c["trig_kind"]).astype(np.int8))

    def info(self) -> dict:
        """Chip, sensor, counts, time range and file size (the one decoding pass, cached)."""
        if self._info is None:
            c = dict(events=0, on=0, off=0, frames=0, imu_samples=0, triggers=0)
            t0, t1 = None, None
            for ch in self._scan(frames=self.spec.layout == "davis"):
                n = len(ch.events)
                c["events"] += n
                c["on"] += ch.events.on_count
                c["frames"] += len(ch.frames)
                c["imu_samples"] += 0 if ch.imu_t is None else len(ch.imu_t)
                c["triggers"] += 0 if ch.trig_t is None else len(ch.trig_t)
                if n:
                    lo, hi = int(ch.events.t.min()), int(ch.events.t.max())
                    t0, t1 = (lo, hi) if t0 is None else (min(t0, lo), max(t1, hi))
            if c["imu_samples"] and self._imu_note:
                self._warn(self._imu_note)
            c["off"] = c["events"] - c["on"]
            w, h = self._size
            self._info = dict(format=self.format, path=self.path, file_size=self.file_size, chip=self.chip or None,
                              layout=self.spec.layout, sensor_size=self._size, header_bytes=self.data_start,
                              records=self.n_records, time_range=(t0, t1), **c,
                              skipped_bytes=sum(r["skipped"] for r in self.resync),
                              imu_scale={"accel_lsb_per_g": self.accel_lsb_per_g,
                                         "gyro_lsb_per_dps": self.gyro_lsb_per_dps})
            counts = {"events": c["events"], "frames": c["frames"], "imu": c["imu_samples"],
                      "triggers": c["triggers"]}
            self._info["streams"] = [dict(id=i, name=n, kind=k, elements=counts[k],
                                          **({"width": w, "height": h} if k in ("events", "frames") else {}))
                                     for i, n, k in STREAMS if counts[k] or k == "events"]
            self._info["warnings"] = list(self.warnings)
        return self._info

    # ----- decoding -----
    def _scan(self, frames: bool, window: tuple[int, int] | None = None):
        """Decode the chosen segment chunk by chunk; state (timestamp wrap, IMU group, open frame) spans chunks.
        The first complete pass keeps the decoded events/IMU/triggers (small files) or a per-chunk time index
        (large ones). window=(lo, hi): events only, decoding just the chunks the index says overlap it."""
        w, h = self._size
        fill = self._cache is None and self._index is None and window is None
        small = (self._rec_hi - self._rec_lo) <= self.cache_records
        store = {"events": [], "imu_t": [], "imu_raw": [], "trig_t": [], "trig_kind": []} if fill else None
        index = [] if fill and not small else None
        wrap, mono = Wrap32(), {k: MonotonicFilter() for k in ("events", "imu", "triggers")}
        n_outlier = n_back = 0
        first_bad = {}
        imu_carry = np.zeros((0, 2), np.int64)       # (address, t) of an incomplete IMU sample
        spec = self.spec
        fb = FrameBuilder(w, h, spec.first, spec.last)
        n_bad = n_imu_drop = 0
        rec0 = self._rec_lo
        if window is not None:
            todo = [c for c in self._index if c["t1"] >= window[0] and c["t0"] < window[1]]
            if not todo:
                return
            rec0 = todo[0]["rec0"]
            wrap.prev, wrap.offset, wrap.skip = todo[0]["wrap"]
            mono["events"].last = todo[0]["mono"]
            stop = todo[-1]["rec0"] + todo[-1]["k"]
        else:
            stop = self._rec_hi
        left = stop - rec0
        while left > 0:
            k = min(left, self.chunk_records)
            npk = min(self._rec_hi - rec0 - k, Wrap32.MAX_RUN)
            state = (wrap.prev, wrap.offset, wrap.skip), mono["events"].last
            buf = self._read_records(rec0, k + npk)
            if len(buf) < 8 * (k + npk):
                raise AedatError(f"{self.path}: byte {self._byte(rec0)}: file shrank while reading")
            left -= k
            rec = np.frombuffer(buf, ">u4").reshape(-1, 2)
            t, ok, notes = wrap.feed(rec[:k, 1].astype(np.int64), rec[k:, 1].astype(np.int64))
            for kind, j, detail in notes:
                if kind == "reset":              # only at the segment's very start (the pass chose the segment)
                    continue
                at = self._byte(rec0 + j)
                what = (f"{detail} record(s) whose timestamp jumps away by more than 1 s and back (outliers)"
                        if kind == "outlier" else f"timestamp jumping back by {-detail} us (not a plausible wrap)")
                if self.strict:
                    raise AedatError(f"{self.path}: byte {at}: {what}")
                first_bad.setdefault(kind, at)
                n_outlier += detail if kind == "outlier" else 0
                n_back += kind == "backward"
            idx = rec0 + np.flatnonzero(ok)
            chunk_rec0 = rec0
            rec0 += k
            addr = rec[:k, 0][ok].astype(np.uint32)
            t = t[ok]
            ch = self._decode_chunk(addr, t, idx, mono, frames, fb)
            n_bad += ch.n_bad
            if spec.layout == "davis":
                imu = ch.imu_mask
                if imu.any() or len(imu_carry):
                    ch.imu_t, ch.imu_raw, imu_carry, dropped = self._imu_groups(imu_carry, addr[imu], t[imu])
                    n_imu_drop += dropped
                    okt = mono["imu"](ch.imu_t)
                    if okt is not None:
                        if self.strict and not okt.all():
                            raise AedatError(f"{self.path}: IMU sample at t={int(ch.imu_t[np.argmin(okt)])} goes "
                                             "back in time")
                        ch.imu_t, ch.imu_raw = ch.imu_t[okt], ch.imu_raw[okt]
            if store is not None:
                if index is None:
                    store["events"].append(ch.events)
                else:
                    ev = ch.events
                    index.append(dict(rec0=chunk_rec0, k=k, wrap=state[0], mono=state[1],
                                      t0=int(ev.t[0]) if len(ev) else 2**63 - 1, t1=int(ev.t[-1]) if len(ev) else -1))
                if ch.imu_t is not None and len(ch.imu_t):
                    store["imu_t"].append(ch.imu_t)
                    store["imu_raw"].append(ch.imu_raw)
                if ch.trig_t is not None and len(ch.trig_t):
                    store["trig_t"].append(ch.trig_t)
                    store["trig_kind"].append(ch.trig_kind)
            yield ch
        if window is not None:
            return
        if store is not None:                    # a complete pass: keep what it decoded
            if index is not None:
                store["events"] = None
                self._index = index
            self._cache = store
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
            self._warn(f"{fb.orphans} APS reads outside a frame readout ignored")
        if n_outlier:
            self._warn(f"byte {first_bad['outlier']}: {n_outlier} records whose timestamps jump away by more than "
                       "1 s and back (neither a wrap nor a reset) dropped as outliers")
        if n_back:
            self._warn(f"byte {first_bad['backward']}: {n_back} timestamp jumps back that are neither plausible "
                       "wraps nor resets (left unwrapped)")
        for kind, f in mono.items():
            if f.dropped:
                self._warn(f"byte {self._byte(f.first_bad)}: {f.dropped} {kind} going back in time "
                           "dropped" if f.first_bad is not None else f"{f.dropped} {kind} going back in time dropped")

    def _decode_chunk(self, addr, t, idx, mono, frames: bool, fb: FrameBuilder) -> _Chunk:
        """Addresses of one chunk -> its events, triggers, APS frames (IMU words are marked in imu_mask)."""
        w, h = self._size
        if self.spec.layout == "dvs128":
            dvs, special, x, row, p = jaer.decode_dvs128(addr)
            inside = np.ones(len(addr), bool)
            aps = imu = np.zeros(len(addr), bool)
            code = None
        else:
            aps = (addr >> 31).astype(bool)
            typ = (addr >> 10) & 3
            x = ((addr >> 12) & 0x3FF).astype(np.int64)
            yr = ((addr >> 22) & 0x1FF).astype(np.int64)
            row = h - 1 - yr
            dvs = ~aps & ((typ & 1) == 0)
            special = ~aps & ((typ & 1) == 1)
            inside = (x < w) & (yr < h)
            imu = aps & (typ == 3)
            p = np.where(addr & (1 << 11), 1, -1).astype(np.int8)
            code = addr & 0x3FF
        outside = (dvs | (aps & ~imu)) & ~inside
        if outside.any() and self.strict:
            raise AedatError(f"{self.path}: byte {self._byte(int(idx[np.argmax(outside)]))}: "
                             f"x/y outside the {w}x{h} sensor")
        m = dvs & inside
        m[m] = self._ordered(mono["events"], t[m], idx[m], "DVS event")
        ch = _Chunk(Events(t[m], x[m], row[m], p[m]))
        ch.n_bad = int(np.count_nonzero(outside))
        ch.imu_mask = imu
        special[special] = self._ordered(mono["triggers"], t[special], idx[special], "trigger")
        if special.any():
            ch.trig_t = t[special]
            if code is None:                                 # DVS128 sync input: falling edges
                ch.trig_kind = np.full(int(special.sum()), 2, np.int8)
            else:
                c = code[special]
                ch.trig_kind = np.full(len(c), -1, np.int8)
                for cc, kind in EXT_KIND.items():
                    ch.trig_kind[c == cc] = kind
        if frames and self.spec.layout == "davis":
            a = aps & ~imu & inside
            if a.any():
                ch.frames = fb.feed(typ[a], x[a], yr[a], row[a], (code[a]).astype(np.int32), t[a])
        return ch

    def _ordered(self, filt: MonotonicFilter, t: np.ndarray, idx: np.ndarray, what: str) -> np.ndarray:
        """Keep-mask of the samples of one stream that do not go back in time (strict: raise at the first)."""
        keep = filt(t, idx)
        if keep is None:
            return np.ones(len(t), bool)
        if self.strict and not keep.all():
            raise AedatError(f"{self.path}: byte {self._byte(int(idx[np.argmin(keep)]))}: {what} "
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
