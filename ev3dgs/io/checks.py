"""Checks of decoded recording data against what the file itself states (shared by the AEDAT readers).

A damaged recording must never give silent garbage: every decoded value that the file contradicts is caught,
namely coordinates outside the sensor size the file declares, a polarity byte other than 0/1, a timestamp
outside the FileDataTable's range for its packet, timestamps going backwards within a stream, a duplicated
packet, element counts that disagree with the packet table, and implausible timestamp "wraps" (AEDAT 2.0).
The checks have a fast path for intact data (AEDAT 4: scalar comparisons of statistics gathered while the
packet is unpacked; AEDAT 2.0/3.1: a few vectorised reductions); only a packet that fails them takes the slow
path, which keeps the largest consistent part of it. With strict=True the
reader raises an AedatError naming the byte instead of dropping anything.
"""
from __future__ import annotations

from bisect import bisect_right

import numpy as np

from ..events import Events
from .types import AedatError

I64_MIN, I64_MAX = np.iinfo(np.int64).min, np.iinfo(np.int64).max
TRIGGER_KINDS = 10               # AEDAT 4 TriggerType: 0 (timestamp reset) .. 9 (APS exposure end)
MAX_ACCEL_G, MAX_GYRO_DPS, TEMP_C = 64.0, 8000.0, (-100.0, 200.0)   # beyond any MEMS IMU's range


def lnds_mask(t: np.ndarray) -> np.ndarray:
    """Mask of one longest non-decreasing subsequence of t (O(n log n); used on damaged data only)."""
    vals = t.tolist()
    tails, tail_idx, parent = [], [], [-1] * len(vals)
    for i, v in enumerate(vals):
        k = bisect_right(tails, v)
        if k == len(tails):
            tails.append(v)
            tail_idx.append(i)
        else:
            tails[k], tail_idx[k] = v, i
        parent[i] = tail_idx[k - 1] if k else -1
    keep = np.zeros(len(vals), bool)
    i = tail_idx[-1] if tail_idx else -1
    while i >= 0:
        keep[i] = True
        i = parent[i]
    return keep


def monotonic(t: np.ndarray, last: int | None) -> bool:
    return len(t) == 0 or ((last is None or t[0] >= last) and bool((t[1:] >= t[:-1]).all()))


def time_mask(t: np.ndarray, lo: int, hi: int, last: int | None, bad: np.ndarray, reasons: dict) -> np.ndarray:
    """Keep-mask of samples with lo <= t <= hi, not before `last`, in non-decreasing order (largest consistent
    subsequence); `bad` marks samples already rejected for another reason. Counts go to `reasons`."""
    out = (t < lo) | (t > hi)
    _count(reasons, f"t outside the packet's FileDataTable range [{lo}, {hi}]", out & ~bad)
    bad = bad | out
    if last is not None:
        before = (t < last) & ~bad
        _count(reasons, f"t before the end of the stream's previous packet ({last})", before)
        bad = bad | before
    keep = ~bad
    if not monotonic(t[keep], None):
        sub = lnds_mask(t[keep])
        _count(reasons, "t decreasing within the stream", ~sub)
        keep[np.flatnonzero(keep)[~sub]] = False
    return keep


def _count(reasons: dict, what: str, mask: np.ndarray) -> None:
    n = int(np.count_nonzero(mask))
    if n:
        reasons[what] = reasons.get(what, 0) + n


def describe(reasons: dict) -> str:
    return "; ".join(f"{n} with {what}" for what, n in reasons.items())


class StreamChecks:
    """State of one stream while an AEDAT 4 reader yields its packets: each decoded packet is checked against
    the stream info (sensor size), the FileDataTable entry (element count, time range) and the packets before
    it (time order, duplicates). A failed check raises (strict) or drops what the file contradicts, with a
    warning naming the stream, the packet and its byte offset."""

    def __init__(self, reader, stream) -> None:
        self.r, self.s = reader, stream
        self.last: int | None = None                  # latest timestamp kept so far in this stream
        self.seen: dict[tuple, int] = {}              # (n, first t, last t) -> file packet index
        self.index = {int(i): k for k, i in enumerate(np.flatnonzero(reader._sid == stream.id))}

    def where(self, i: int) -> str:
        return (f"byte {int(self.r._off[i]) - 8}: stream {self.s.id} ({self.s.name}) packet {self.index.get(i, '?')} "
                f"(file packet {i})")

    def _range(self, i: int) -> tuple[int, int]:
        r = self.r
        return (I64_MIN, I64_MAX) if r._t0 is None else (int(r._t0[i]), int(r._t1[i]))

    def _problem(self, i: int, n_bad: int, n: int, reasons: dict, unit: str) -> None:
        msg = f"{self.where(i)}: {describe(reasons)}"
        if self.r.strict:
            raise AedatError(msg)
        self.r._warn(f"{msg}: {n_bad} of {n} {unit} dropped")

    def _pre(self, i: int, t: np.ndarray, reasons: dict) -> bool:
        """Element count against the table, and duplicate detection; True if the whole packet is a duplicate."""
        r, n = self.r, len(t)
        if r._nel is not None and n != int(r._nel[i]):
            reasons[f"{n} elements where the FileDataTable says {int(r._nel[i])}"] = 0
        if n:
            sig = (n, int(t[0]), int(t[-1]))
            if self.last is not None and sig[2] <= self.last and sig in self.seen:
                reasons[f"a duplicate of file packet {self.seen[sig]}"] = n
                return True
            self.seen.setdefault(sig, i)
        return False

    def _finish(self, i, keep, n, reasons, unit, t):
        if keep is not None and not keep.all() or reasons:
            self._problem(i, n - (n if keep is None else int(np.count_nonzero(keep))), n, reasons, unit)
        kt = t if keep is None else t[keep]
        if len(kt):
            self.last = int(kt[-1]) if self.last is None else max(self.last, int(kt[-1]))

    def events(self, i: int, a) -> Events | None:
        """An unpacked events packet (aedat4_packets.EventArrays: arrays and their statistics) -> checked
        Events (None: nothing left). Intact data costs a few scalar comparisons of the statistics."""
        t, x, y, pol = a.t, a.x, a.y, a.pol
        n, (lo, hi), w, h = len(t), self._range(i), self.s.width, self.s.height
        reasons: dict = {}
        if self._pre(i, t, reasons):
            self._problem(i, n, n, reasons, "events")
            return None
        keep = None
        if n and not ((w <= 0 or h <= 0 or (a.max_x < w and a.max_y < h)) and a.bad_polarity == 0
                      and t[0] >= lo and t[-1] <= hi and a.backward == 0
                      and (self.last is None or t[0] >= self.last)):
            bad = np.zeros(n, bool)
            if w > 0 and h > 0:
                bad = (x >= w) | (y >= h)
                _count(reasons, f"x/y outside the {w}x{h} sensor", bad)
            badp = (pol == -128) & ~bad
            _count(reasons, "a polarity byte other than 0/1", badp)
            keep = time_mask(t, lo, hi, self.last, bad | badp, reasons)
        self._finish(i, keep, n, reasons, "events", t)
        if keep is not None:
            t, x, y, pol = t[keep], x[keep], y[keep], pol[keep]
        return Events(t, x, y, pol)

    def samples(self, i: int, d: dict, unit: str) -> dict | None:
        """IMU or trigger samples (a dict of arrays with "t") -> the checked samples."""
        t, n, (lo, hi) = d["t"], len(d["t"]), self._range(i)
        reasons: dict = {}
        if self._pre(i, t, reasons):
            self._problem(i, n, n, reasons, unit)
            return None
        bad = np.zeros(n, bool)
        if unit == "triggers":
            bad = (d["kind"] < 0) | (d["kind"] >= TRIGGER_KINDS)
            _count(reasons, f"a trigger type outside 0..{TRIGGER_KINDS - 1}", bad)
        else:
            bad = ~(imu_plausible(np.stack([d["ax"], d["ay"], d["az"]], 1), np.stack([d["gx"], d["gy"], d["gz"]], 1),
                                  d["temp"]))
            _count(reasons, "non-finite or physically impossible IMU values", bad)
        keep = None
        if bad.any() or not (n == 0 or (t[0] >= lo and t[-1] <= hi and monotonic(t, self.last))):
            keep = time_mask(t, lo, hi, self.last, bad, reasons)
        self._finish(i, keep, n, reasons, unit, t)
        return d if keep is None else {k: v[keep] for k, v in d.items()}

    def frame(self, i: int, fr):
        """A decoded FrameData -> itself, or None if the file contradicts it (size, times)."""
        (lo, hi), w, h = self._range(i), self.s.width, self.s.height
        reasons: dict = {}
        if self.r._nel is not None and int(self.r._nel[i]) != 1:
            reasons[f"1 frame where the FileDataTable says {int(self.r._nel[i])}"] = 0
        fh, fw = fr.image.shape[:2]
        px, py = fr.position
        if px < 0 or py < 0 or (w > 0 and h > 0 and (px + fw > w or py + fh > h)):
            reasons[f"a {fw}x{fh} frame at ({px}, {py}) outside the {w}x{h} sensor"] = 1
        if not lo <= fr.timestamp <= hi:
            reasons[f"timestamp {fr.timestamp} outside the FileDataTable range [{lo}, {hi}]"] = 1
        if fr.exposure_end < fr.exposure_start or fr.frame_end < fr.frame_start:
            reasons["exposure or readout ending before it starts"] = 1
        if self.last is not None and fr.timestamp < self.last:
            reasons[f"timestamp before the previous frame's ({self.last})"] = 1
        elif self.last is not None and fr.timestamp == self.last:   # one stream, one frame per instant
            reasons[f"a second frame at the previous frame's timestamp {self.last} (a duplicated packet?)"] = 1
        bad = any(reasons.values())
        if reasons:
            self._problem(i, int(bad), 1, reasons, "frames")
        if bad:
            return None
        self.last = fr.timestamp
        return fr


def imu_plausible(accel: np.ndarray, gyro: np.ndarray, temp: np.ndarray) -> np.ndarray:
    """Per sample: finite values within any MEMS IMU's range (a flipped exponent bit gives 1e30 g)."""
    with np.errstate(invalid="ignore"):
        return ((np.abs(accel) <= MAX_ACCEL_G).all(1) & (np.abs(gyro) <= MAX_GYRO_DPS).all(1)
                & (temp >= TEMP_C[0]) & (temp <= TEMP_C[1]))


class Wrap32:
    """Unwraps 32-bit (or 31-bit) AEDAT 2.0 timestamps chunk by chunk, taking a backward jump as a wrap only
    when it is plausible: the value before it lies within WRAP_GAP (60 s) of the 2^32 (or 2^31) boundary and the
    value after it within WRAP_GAP of 0, so the unwrapped step is under WRAP_GAP. A backward jump to a small value
    (under RESET_MAX) that is not a wrap and does not come back is a timestamp reset (jAER restarts its clock at 0):
    noted as ("reset", index, (before, after)) and the count restarts from the new value. A run of at most MAX_RUN
    (4096) records that jumps away (by more than 2^30) and comes back to where it left is an outlier run and is
    dropped (one bad timestamp of 0xFFFFFFFF between 10 and 20 must not shift the rest of the file by 2^32).
    A smaller forward jump (over SPIKE_MIN, ~1 s: one flipped bit between 20 and 29) whose run comes back within
    MAX_RUN records to below half of its height is an outlier run too: the records after it are in order with
    the ones before it, so the return is not a clock reset. Other backward jumps are noted and left for the
    monotonic check of each stream."""

    JUMP = 1 << 30
    MAX_RUN = 4096
    WRAP_GAP = 60_000_000
    RESET_MAX = 1 << 24                      # ~16.8 s: a reset restarts the clock at 0
    RESET_MIN_DROP = 1000                    # smaller steps back are jitter, not resets
    SPIKE_MIN = 1 << 20                      # ~1 s forward: checked for a return (a spike) within MAX_RUN
    SPIKE_HOLD = 8                           # records after the return that must stay below the spike

    def __init__(self) -> None:
        self.prev: int | None = None         # raw value of the last kept record
        self.offset = 0
        self.skip = 0                        # records at the start of the next chunk that are outliers

    def feed(self, u: np.ndarray, peek: np.ndarray):
        """u: raw timestamps (int64) of this chunk, peek: up to MAX_RUN raw timestamps that follow it.
        -> (unwrapped t, keep mask, notes [(kind, index, detail)])."""
        n = len(u)
        keep = np.ones(n, bool)
        notes = []
        k0 = min(self.skip, n)
        keep[:k0] = False
        self.skip -= k0
        ext = np.concatenate([u, peek]) if len(peek) else u
        start = self.prev if self.prev is not None else int(ext[0])
        d = np.diff(ext, prepend=start)
        step = np.zeros(n, np.int64)
        resume = k0
        cand = ((np.abs(d[:n]) > self.JUMP) | (d[:n] >= self.SPIKE_MIN)
                | ((d[:n] < -self.RESET_MIN_DROP) & (ext[:n] < self.RESET_MAX)))
        for j in np.flatnonzero(cand).tolist():
            if j < resume:
                continue
            a = int(ext[j - 1]) if j else start
            win = ext[j + 1:j + 1 + self.MAX_RUN] - a
            # a jump away and back: back to within JUMP of where it left, and for a forward jump below half
            # its height (a recording that pauses and goes on never comes back below where it jumped to)
            limit = self.JUMP if d[j] < 0 else min(self.JUMP, int(d[j]) // 2)
            back = np.flatnonzero((win >= 0) & (win < limit))
            if back.size and 0 < d[j] <= self.JUMP:
                # a spike of one flipped bit: the clock must stay back below it after the return, else the
                # 'return' is itself a bad record (a bit cleared) and the forward step was real
                k = j + 1 + int(back[0])
                after = ext[k:k + self.SPIKE_HOLD]      # as many as the run it would drop, up to SPIKE_HOLD
                if len(after) < min(self.SPIKE_HOLD, k - j) or not ((after >= a) & (after < ext[j])).all():
                    back = back[:0]
            if back.size:                                  # jumps away and comes back: outlier run
                k = j + 1 + int(back[0])
                keep[j:min(k, n)] = False
                self.skip = max(0, k - n)
                notes.append(("outlier", j, k - j))
                resume = k + 1
                continue
            if d[j] < 0:
                wrap = 1 << 32 if a >= 1 << 31 else 1 << 31
                if 0 <= int(ext[j]) + wrap - a < self.WRAP_GAP:
                    step[j] = wrap
                elif self.prev is None and j < self.SPIKE_HOLD and k0 == 0 and bool(keep[:j].all()) \
                        and bool((np.diff(ext[j:j + self.SPIKE_HOLD]) >= 0).all()):
                    keep[:j] = False                           # the file's first records alone, far ahead of
                    notes.append(("outlier", 0, j))            # an in-order rest: outliers, not a clock reset
                elif int(ext[j]) < self.RESET_MAX:
                    step[j] = -(self.offset + int(step[:j].sum()))   # the clock restarts: t = raw value again
                    notes.append(("reset", j, (a, int(ext[j]))))
                else:
                    notes.append(("backward", j, int(ext[j]) - a))
        t = u + self.offset + np.cumsum(step)
        self.offset += int(step.sum())
        kept = np.flatnonzero(keep)
        if len(kept):
            self.prev = int(u[kept[-1]])
        return t, keep, notes


class MonotonicFilter:
    """Keeps one stream's timestamps non-decreasing across chunks (legacy readers): the fast path is one
    comparison pass; a chunk that goes backwards keeps its longest non-decreasing part not before `last`."""

    def __init__(self) -> None:
        self.last: int | None = None
        self.dropped = 0
        self.first_bad: int | None = None    # index (in the caller's numbering) of the first dropped sample

    def __call__(self, t: np.ndarray, index: np.ndarray | None = None) -> np.ndarray | None:
        keep = None
        if not monotonic(t, self.last):
            keep = np.ones(len(t), bool) if self.last is None else t >= self.last
            sub = lnds_mask(t[keep])
            keep[np.flatnonzero(keep)[~sub]] = False
            nd = len(t) - int(np.count_nonzero(keep))
            if nd and self.first_bad is None and index is not None:
                self.first_bad = int(index[np.flatnonzero(~keep)[0]])
            self.dropped += nd
        kt = t if keep is None else t[keep]
        if len(kt):
            self.last = int(kt[-1])
        return keep
