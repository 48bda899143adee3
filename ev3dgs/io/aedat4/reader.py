"""AEDAT 4.0 reader (DV / dv-processing recordings): events, frames, IMU and triggers, streamed per packet.

The container (IOHeader, stream XML, packet index from the FileDataTable or by walking the packets, salvage of
a truncated tail) is read by `aedat4_container`; events streams of an indexed file are read by `aedat4_fast`
(C: read, decompress, parse, unpack and check in one pass, no GIL), and any packet it does not find intact, as
well as every other packet, is decompressed and decoded by `aedat4_packets` (optionally with a read-ahead
thread) and checked against what the file states by `checks.StreamChecks`. Flatbuffers are parsed by `flatbuf` (clean room, bounds-checked).
Format: the dv-processing documentation of the AEDAT 4.0 file format and its flatbuffer schemas.
"""
from __future__ import annotations

import os
import warnings as _warnings

import numpy as np

from ...events import Events
from . import fast
from .container import MAGIC, read_container
from .packets import COMPRESSIONS, EVENT_DTYPE, IDENTS, KINDS, IMU_FIELDS, PacketReader, Skip, summary
from ..checks import StreamChecks
from .flatbuf import FlatbufError, root
from ..types import AedatError, AedatWarning, ImuData, RecordingReader, StreamInfo, Triggers

__all__ = ["Aedat4Reader", "AedatWarning", "info", "MAGIC", "EVENT_DTYPE", "COMPRESSIONS", "THREADS"]

# Threads decoding at once by default. Events of an indexed file: the C fast path decodes the packets of a chunk
# on that many threads (each packet into its own place; tools/bench/bench_aedat.py). Everything else: with 2, a worker
# reads and decompresses packets while the calling thread unpacks the previous ones, which only pays where a core
# is idle. THREADS = None picks default_threads(): the cores the 1-minute load average leaves idle, 1 to 4; set
# an int to force.
THREADS: int | None = None


def default_threads() -> int:
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    try:
        load = os.getloadavg()[0]
    except OSError:
        load = float(cores)
    return max(1, min(4, int(cores - load + 0.5)))


class Aedat4Reader(RecordingReader):
    """Reader of one AEDAT 4.0 file. `stream` arguments take a stream id, its name (originalOutputName),
    its source (camera name), "source/name", or a StreamInfo; None picks the first stream of that kind.
    Every decoded packet is checked against what the file states (ev3dgs.io.checks): a corrupt packet is
    skipped, and values the file contradicts are dropped, with a warning naming the stream, packet and byte;
    with strict=True they raise AedatError instead. skip_corrupt=True/False is the older spelling of
    strict=False/True. `threads`: 1 decodes in the calling thread; N > 1 decodes the events packets of an indexed
    file on N C threads (the fast path), and adds N - 1 read-ahead threads that read and decompress other packets
    while the calling thread unpacks them (default: THREADS, or default_threads(): the idle cores, 1 to 4)."""

    format = "aedat4"

    def __init__(self, path, *, strict: bool = False, skip_corrupt: bool | None = None,
                 threads: int | None = None) -> None:
        self.path = os.fspath(path)
        self.warnings: list[str] = []
        self.strict = strict if skip_corrupt is None else not skip_corrupt
        self.threads = (THREADS or default_threads()) if threads is None else int(threads)
        if self.threads < 1:
            raise ValueError(f"threads must be >= 1, got {threads}")
        try:
            self._f = open(self.path, "rb")
        except OSError as e:
            raise AedatError(f"{self.path}: cannot open: {e.strerror or e}") from None
        try:
            c = read_container(self._f, os.fstat(self._f.fileno()).st_size, self._warn)
        except BaseException:
            self._f.close()
            raise
        self.file_size, self.data_start, self.compression = c.file_size, c.data_start, c.compression
        self.table_position, self.info_xml, self.has_table = c.table_position, c.info_xml, c.has_table
        self._streams = c.streams
        self._off, self._size, self._sid, self._nel, self._t0, self._t1 = c.off, c.size, c.sid, c.nel, c.t0, c.t1
        self._reader = PacketReader(self._f, c.off, c.size, c.sid, c.compression, self.path, c.nel)
        for s in self._streams.values():
            if s.kind == "other" and s.packets:
                self._guess_kind(s)

    def _warn(self, msg: str) -> None:
        """A salvaged problem: a warning; with strict=True (any repair or guess fails) an AedatError."""
        if self.strict:
            raise AedatError(f"{self.path}: {msg}")
        self.warnings.append(msg)
        _warnings.warn(f"{self.path}: {msg}", AedatWarning, stacklevel=3)

    def _guess_kind(self, s: StreamInfo) -> None:
        i = int(np.flatnonzero(self._sid == s.id)[0])
        try:
            ident = root(self._reader.payload(i))[1].decode("ascii", "replace")
        except (AedatError, FlatbufError):
            return
        if ident in KINDS:
            s.type_identifier, s.kind = ident, KINDS[ident]

    # ------------------------------------------------------------------ packets
    def _packets(self, kind: str, stream, start_us=None, end_us=None):
        """Yield the decoded and checked packets of the chosen stream, skipping corrupt packets with a warning
        (strict: raising); packets outside [start, end) are skipped using the FileDataTable."""
        s = self._select(stream, kind)
        chk = StreamChecks(self, s)
        check = {"events": chk.events, "frames": chk.frame,
                 "imu": lambda i, a: chk.samples(i, a, "imu"), "triggers": lambda i, a: chk.samples(i, a, "triggers")}
        todo = np.flatnonzero(self._sid == s.id)
        if self._t0 is not None and (start_us is not None or end_us is not None):
            keep = np.ones(len(todo), bool)
            if start_us is not None:
                keep &= self._t1[todo] >= start_us
            if end_us is not None:
                keep &= self._t0[todo] < end_us
            todo = todo[keep]
        if kind == "events" and fast.usable(self):
            for got in fast.iterate(self, s, chk, todo.tolist(), self.threads):
                if type(got) is not int:
                    yield got               # a chunk the fast path read and checked
                    continue
                out = self._checked(got, self._reader._finish(self._reader._attempt(got, kind, s.source), kind),
                                    kind, chk, check)
                if out is not None:
                    yield out
            return
        for i, got in self._reader.iterate(todo.tolist(), kind, s.source, self.threads):
            out = self._checked(i, got, kind, chk, check)
            if out is not None:
                yield out

    def _checked(self, i: int, got, kind: str, chk: StreamChecks, check: dict):
        """Packet i as decoded (or the exception decoding raised) -> its checked content, or None when it was
        skipped (with a warning; strict: raising)."""
        try:
            if isinstance(got, Exception):
                raise got
            return check[kind](i, got)
        except Skip as e:
            self._warn(str(e))
        except (AedatError, FlatbufError) as e:
            msg = str(e) if isinstance(e, AedatError) else f"byte {int(self._off[i])}: corrupt {kind} packet ({e})"
            if self.strict:
                raise AedatError(msg) from None
            self._warn(f"{msg} [{chk.where(i)}]: packet skipped")
        return None

    # ------------------------------------------------------------------ public API
    def close(self) -> None:
        self._reader.close()
        self._f.close()

    def streams(self) -> list[StreamInfo]:
        return [self._streams[k] for k in sorted(self._streams)]

    def _select(self, stream, kind: str) -> StreamInfo:
        ss = self.streams()
        if isinstance(stream, StreamInfo):
            stream = stream.id
        if stream is None:
            found = [s for s in ss if s.kind == kind]
        elif isinstance(stream, (int, np.integer)) and not isinstance(stream, bool):
            found = [s for s in ss if s.id == int(stream)]
        else:
            key = str(stream)
            found = ([s for s in ss if s.name == key] or [s for s in ss if f"{s.source}/{s.name}" == key]
                     or [s for s in ss if s.source == key and s.kind == kind]
                     or [s for s in ss if key.isdigit() and s.id == int(key)])
            found = [s for s in found if s.kind == kind] or found
        names = ", ".join(f"{s.id}:{s.name} ({s.kind})" for s in ss) or "none"
        if not found:
            raise AedatError(f"{self.path}: no {kind} stream {stream if stream is not None else ''} (streams: {names})")
        if found[0].kind != kind:
            raise AedatError(f"{self.path}: stream {found[0].id} '{found[0].name}' holds {found[0].kind}, not {kind}")
        return found[0]

    def sensor_size(self, stream=None) -> tuple[int, int]:
        """(width, height) of the event sensor: from the XML, else the frames stream, else the events seen."""
        s = self._select(stream, "events") if stream is not None or any(
            x.kind == "events" for x in self.streams()) else None
        if s is not None and s.width > 0 and s.height > 0:
            return s.width, s.height
        frm = [x for x in self.streams() if x.kind == "frames" and x.width > 0 and x.height > 0]
        if frm:
            return frm[0].width, frm[0].height
        w = h = 0
        for ev in (self.events(s) if s is not None else ()):
            w, h = max(w, int(ev.x.max()) + 1), max(h, int(ev.y.max()) + 1)
        if not w:
            raise AedatError(f"{self.path}: sensor size unknown (no sizeX/sizeY and no events)")
        return w, h

    def events(self, stream=None, start_us: int | None = None, end_us: int | None = None):
        """Iterator of Events chunks in file order, restricted to start_us <= t < end_us. A chunk holds whole
        packets: consecutive packets merged up to aedat4_fast.CHUNK_EVENTS events on the fast path, one packet
        per chunk on the general path (files without a FileDataTable, FAST off, no C extension)."""
        lo = np.iinfo(np.int64).min if start_us is None else start_us
        hi = np.iinfo(np.int64).max if end_us is None else end_us
        for ev in self._packets("events", stream, start_us, end_us):
            if start_us is not None or end_us is not None:
                keep = (ev.t >= lo) & (ev.t < hi)
                if not keep.all():
                    ev = Events(ev.t[keep], ev.x[keep], ev.y[keep], ev.p[keep])
            if len(ev):
                yield ev

    def frames(self, stream=None):
        for fr in self._packets("frames", stream):
            if fr is not None:
                yield fr

    def imu(self, stream=None) -> ImuData:
        parts = list(self._packets("imu", stream))
        if not parts:
            return ImuData()
        c = {k: np.concatenate([p[k] for p in parts]) for k in IMU_FIELDS}
        return ImuData(c["t"], np.stack([c["ax"], c["ay"], c["az"]], 1), np.stack([c["gx"], c["gy"], c["gz"]], 1),
                       c["temp"])

    def triggers(self, stream=None) -> Triggers:
        parts = list(self._packets("triggers", stream))
        if not parts:
            return Triggers()
        return Triggers(np.concatenate([p["t"] for p in parts]), np.concatenate([p["kind"] for p in parts]))

    def packet_table(self) -> dict[str, np.ndarray]:
        """Per packet in file order: payload offset, size, stream id, and (FileDataTable only, else -1) element
        count and time range."""
        none = np.full(len(self._off), -1, np.int64)
        return {"offset": self._off.copy(), "size": self._size.copy(), "stream": self._sid.copy(),
                "elements": none if self._nel is None else self._nel.copy(),
                "t_start": none if self._t0 is None else self._t0.copy(),
                "t_end": none if self._t1 is None else self._t1.copy()}

    def _summary(self, i: int, s: StreamInfo) -> tuple[int, int, int]:
        """(elements, first t, last t) of packet i, decoding it (used when there is no FileDataTable)."""
        if s.kind not in IDENTS:
            return 0, -1, -1
        return summary(self._reader.payload(i), int(self._off[i]), s.kind)

    def info(self, scan: bool = False) -> dict:
        """Summary for `ev3dgs-ingest info`: streams with packet/element counts and time ranges, compression,
        file size, FileDataTable state and warnings. Cheap by default: the header and the packet index only
        (counts and time ranges from the FileDataTable; without one, each packet is decompressed once to count
        it). scan=True also decodes and checks every packet, as reading does (warnings for what the file
        contradicts; strict: the first problem raises)."""
        if scan:
            for s in self.streams():
                for _ in (self._packets(s.kind, s) if s.kind in IDENTS else ()):
                    pass
        nel, t0, t1 = self._nel, self._t0, self._t1
        if nel is None:
            nel, t0, t1 = (np.full(len(self._off), v, np.int64) for v in (0, -1, -1))
            for s in self.streams():
                for i in np.flatnonzero(self._sid == s.id):
                    try:
                        nel[i], t0[i], t1[i] = self._summary(int(i), s)
                    except (AedatError, FlatbufError) as e:
                        self._warn(f"byte {int(self._off[i])}: packet unreadable ({e})")
        streams = []
        for s in self.streams():
            m = (self._sid == s.id) & (t0 >= 0)
            streams.append({"id": s.id, "name": s.name, "kind": s.kind, "type_identifier": s.type_identifier,
                            "source": s.source, "width": s.width, "height": s.height, "packets": s.packets,
                            "elements": int(nel[self._sid == s.id].sum()),
                            "t_start": int(t0[m].min()) if m.any() else None,
                            "t_end": int(t1[m].max()) if m.any() else None})
        ts = [x for x in (d["t_start"] for d in streams) if x is not None]
        te = [x for x in (d["t_end"] for d in streams) if x is not None]
        return {"path": self.path, "format": self.format, "file_size": self.file_size,
                "compression": COMPRESSIONS[self.compression], "data_start": self.data_start,
                "table_position": self.table_position, "has_table": self.has_table, "packets": len(self._off),
                "scanned": bool(scan), "streams": streams, "t_start": min(ts) if ts else None,
                "t_end": max(te) if te else None, "warnings": list(self.warnings)}


def info(path, scan: bool = False) -> dict:
    """`Aedat4Reader(path).info(scan)` for a path."""
    with Aedat4Reader(path) as r:
        return r.info(scan)
