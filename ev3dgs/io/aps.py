"""APS frames from the per-pixel reads of an AEDAT 2.0 (jAER) DAVIS file, global or rolling shutter.

Frame boundaries follow jAER (DavisBaseCamera's extractor, github.com/SensorsINI/jaer): a frame starts at the
reset read of the chip's first pixel address and ends at the signal read of its last one (ev3dgs.io.jaer.chips.Chip).
A ROI readout, which never reaches those corners, starts a new frame at a reset read of a pixel already reset in
the open frame. Pixel = clip(reset - signal, 0, 1023) << 6 (uint16, left-aligned like libcaer frames).
Times, as jAER reports them: frame_start = first reset read, frame_end = last signal read, exposure_end = first
signal read, exposure_start = last reset read (global shutter) or first reset read (rolling shutter, where
reset and signal reads interleave row by row). Every frame also carries row_exposure: per image row, [its last
reset read, its first signal read), so a rolling-shutter frame keeps each row's own exposure window.
"""
from __future__ import annotations

import numpy as np

from .types import FrameData

I64_MAX = np.iinfo(np.int64).max


class FrameBuilder:
    """Accumulates APS reads (state kept across chunks); feed() returns the frames they complete."""

    def __init__(self, width: int, height: int, first=None, last=None):
        self.w, self.h = width, height
        self.first, self.last = first, last           # raw (x, y) of the first / last pixel read, or None
        self.reset = self.signal = None
        self.incomplete = self.orphans = 0

    def open(self) -> bool:
        return self.reset is not None

    def start(self) -> None:
        h, w = self.h, self.w
        self.reset = np.full((h, w), -1, np.int32)
        self.signal = np.full((h, w), -1, np.int32)
        self.row_reset = np.full(h, -1, np.int64)         # last reset read per row
        self.row_signal = np.full(h, I64_MAX, np.int64)   # first signal read per row
        self.t = [None, None, None, None]                 # first reset, last reset, first signal, last signal

    def _add(self, rt, row, x, adc, t) -> None:
        for kind, arr, k in ((0, self.reset, 0), (1, self.signal, 2)):
            m = rt == kind
            if m.any():
                arr[row[m], x[m]] = adc[m]
                tk = t[m]
                if self.t[k] is None:
                    self.t[k] = int(tk[0])
                self.t[k + 1] = int(tk[-1])
                if kind == 0:
                    np.maximum.at(self.row_reset, row[m], tk)
                else:
                    np.minimum.at(self.row_signal, row[m], tk)

    def feed(self, rt, xr, yr, row, adc, t) -> list[FrameData]:
        """APS reads of one chunk: readout type (0 reset, 1 signal), raw x/y, image row, ADC value, time."""
        out = []
        n = len(rt)
        sof = (rt == 0) & (xr == self.first[0]) & (yr == self.first[1]) if self.first else np.zeros(n, bool)
        eof = (rt == 1) & (xr == self.last[0]) & (yr == self.last[1]) if self.last else np.zeros(n, bool)
        pix = row.astype(np.int64) * self.w + self._col(xr)
        i = 0
        while i < n:
            if not self.open():
                nxt = np.flatnonzero(rt[i:] == 0)            # a frame opens at a reset read
                if not len(nxt):
                    self.orphans += n - i
                    break
                self.orphans += int(nxt[0])
                i += int(nxt[0])
                self.start()
                self._seen = np.zeros(self.h * self.w, bool)
                first_in = True
            else:
                first_in = False
            # the open frame ends before the next SOF, before a duplicate reset read, or at (after) the next EOF
            j_end = n
            s = np.flatnonzero(sof[i + (1 if first_in else 0):])
            if len(s):
                j_end = i + (1 if first_in else 0) + int(s[0])
            e = np.flatnonzero(eof[i:j_end])
            stop_after_eof = bool(len(e))
            if stop_after_eof:
                j_end = i + int(e[0]) + 1
            seg = slice(i, j_end)
            r = rt[seg] == 0
            rp = pix[seg][r]
            dup = self._seen[rp]
            if len(rp):
                _, first_idx = np.unique(rp, return_index=True)
                within = np.ones(len(rp), bool)
                within[first_idx] = False
                dup |= within
            if dup.any():
                k = int(np.flatnonzero(r)[np.argmax(dup)])
                if k == 0 and first_in:
                    k = None
                if k is not None:
                    j_end, stop_after_eof = i + k, False
                    seg = slice(i, j_end)
            self._seen[pix[seg][rt[seg] == 0]] = True
            self._add(rt[seg], row[seg], self._col(xr[seg]), adc[seg], t[seg])
            i = j_end
            if stop_after_eof or i < n:
                fr, ok = self.finish()
                if fr is not None:
                    out.append(fr)
                    self.incomplete += not ok
        return out

    def _col(self, xr):
        return xr.astype(np.int64)

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
        fs, last_reset, eoe, fe = self.t
        rows_exp = np.stack([self.row_reset[r0:r1], self.row_signal[r0:r1]], 1)
        rolling = eoe < last_reset                   # signal reads began before the last reset read
        soe = fs if rolling else last_reset
        bad = (rows_exp[:, 0] < 0) | (rows_exp[:, 1] == I64_MAX)
        rows_exp[bad] = (soe, eoe)
        return FrameData(timestamp=(soe + eoe) // 2, exposure_start=soe, exposure_end=eoe, frame_start=fs,
                         frame_end=fe, image=img, position=(int(c0), int(r0)), source="aps",
                         row_exposure=rows_exp), bool(ok.all())
