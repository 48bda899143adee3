"""What every recording reader returns, whatever the file format (AEDAT 4.0, 3.1, 2.0).

Timestamps are int64 microseconds as stored in the file (AEDAT 4 uses Unix-epoch us). Frames keep the
file's pixels and channel order (OpenCV order: GRAY, BGR or BGRA; 8 or 16 bit); `ev3dgs.io.davis` converts
them to RGB for the scene file. Events come as `ev3dgs.events.Events` chunks (t, x, y with row 0 at the
top, p +1/-1), streamed so that memory stays bounded by a few packets.
"""
from __future__ import annotations

import os
import re
import warnings as _warnings
from dataclasses import dataclass, field

import numpy as np

from ..errors import Ev3dgsError, Ev3dgsWarning


class AedatError(Ev3dgsError):
    """A corrupt or unsupported recording; the message names the byte offset where reading failed."""


class AedatWarning(Ev3dgsWarning):
    """A recoverable problem in a recording (truncated tail, damaged FileDataTable, skipped packet, dropped
    values that the file contradicts)."""


@dataclass
class StreamInfo:
    id: int
    name: str                      # e.g. "events", "frames", "imu", "triggers"
    kind: str                      # "events" | "frames" | "imu" | "triggers" | "other"
    type_identifier: str = ""      # AEDAT 4 flatbuffer identifier: EVTS, FRME, IMUS, TRIG
    source: str = ""               # camera / module that produced it
    width: int = 0
    height: int = 0
    compression: str = "none"      # none | lz4 | lz4-high | zstd | zstd-high
    packets: int = 0


@dataclass
class FrameData:
    timestamp: int                 # the frame's own timestamp
    exposure_start: int
    exposure_end: int
    frame_start: int               # start / end of the readout
    frame_end: int
    image: np.ndarray              # (H, W) or (H, W, C) uint8 or uint16, file channel order (OpenCV: BGR/BGRA)
    position: tuple[int, int] = (0, 0)   # ROI offset (x, y) on the sensor
    source: str = ""
    # per image row: [start, end) of its exposure (int64 us, shape (H, 2)); set by readers that see per-pixel reads
    # (AEDAT 2.0 APS); on a rolling-shutter frame every row has its own window, exposure_start/end are the first
    # row's (as jAER reports them)
    row_exposure: np.ndarray | None = None

    @property
    def rolling_shutter(self) -> bool:
        r = self.row_exposure
        return r is not None and len(r) > 1 and bool((r[:, 0] != r[0, 0]).any())


@dataclass
class ImuData:
    t: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    # camera frame (OpenCV: x right, y down, z forward) for both sensors; see ev3dgs.io.jaer.chips.IMU_AXES
    accel: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float32))       # g
    gyro: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float32))        # deg/s
    temperature: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))      # deg C

    def __len__(self) -> int:
        return len(self.t)


@dataclass
class Triggers:
    t: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    kind: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int8))

    def __len__(self) -> int:
        return len(self.t)


def events_in_window(parts, lo: int, hi: int, sliced: bool):
    """Yield the non-empty parts of a time-sorted Events stream with lo <= t < hi (each part sliced by binary
    search when `sliced`, i.e. when the caller asked for a window; parts wholly outside are skipped)."""
    from ..events import Events

    for ev in parts:
        if not len(ev) or ev.t[-1] < lo or ev.t[0] >= hi:
            continue
        if sliced:
            a, b = np.searchsorted(ev.t, lo), np.searchsorted(ev.t, hi)
            ev = Events(ev.t[a:b], ev.x[a:b], ev.y[a:b], ev.p[a:b])
        if len(ev):
            yield ev


class RecordingReader:
    """The interface every format's reader implements (aedat4.Aedat4Reader, aedat3.Aedat3Reader,
    aedat2.Aedat2Reader). Use as a context manager. `stream` arguments take a stream id or name; None picks
    the first stream of that kind. Problems that were salvaged (a truncated tail, a skipped corrupt packet)
    are appended to `warnings` and also issued with warnings.warn; unrecoverable ones raise AedatError."""

    path: str
    warnings: list[str]
    format: str                    # "aedat4" | "aedat3.1" | "aedat2"

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        raise NotImplementedError

    def _open_with_header(self, read_header) -> None:
        """Open self.path, read its text header with read_header() (closing the file if that fails), and
        note where the binary data starts."""
        try:
            self._f = open(self.path, "rb")
        except OSError as e:
            raise AedatError(f"{self.path}: cannot open: {e}") from e
        try:
            self.file_size = os.fstat(self._f.fileno()).st_size
            self.header = read_header()
        except BaseException:
            self._f.close()
            raise
        self.data_start = self._f.tell()

    def _check_magic(self, first_line: bytes, magic: bytes, label: str) -> None:
        if not first_line.startswith(magic):
            other = re.match(rb"#!AER-DAT(\d\.\d)", first_line)
            what = f"AEDAT {other.group(1).decode()}" if other else f"starts with {first_line[:12]!r}"
            raise AedatError(f"{self.path}: byte 0: not an {label} file ({what})")

    def _warn(self, msg: str) -> None:
        """Record a salvaged problem once, and issue it as a Python warning. With strict=True every repair
        or guess is an error instead: a strict read returns what the file says, or fails."""
        if getattr(self, "strict", False):
            raise AedatError(f"{self.path}: {msg}")
        if msg not in self.warnings:
            self.warnings.append(msg)
            _warnings.warn(f"{self.path}: {msg}", AedatWarning, stacklevel=3)

    def streams(self) -> list[StreamInfo]:
        raise NotImplementedError

    def sensor_size(self) -> tuple[int, int]:
        """(width, height) of the event sensor."""
        raise NotImplementedError

    def events(self, stream=None, start_us: int | None = None, end_us: int | None = None):
        """Iterator of Events chunks (a packet or a few), in file order, restricted to [start, end)."""
        raise NotImplementedError

    def frames(self, stream=None):
        """Iterator of FrameData in file order."""
        raise NotImplementedError

    def imu(self, stream=None) -> ImuData:
        raise NotImplementedError

    def triggers(self, stream=None) -> Triggers:
        raise NotImplementedError
