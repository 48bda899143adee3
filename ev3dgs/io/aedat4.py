"""AEDAT 4.0 reader (DV / dv-processing recordings): events, frames, IMU and triggers, streamed per packet.

File layout (little-endian): the version line `#!AER-DAT4.0\\r\\n`, a uint32 N and the IOHeader flatbuffer
(compression, dataTablePosition, infoNode XML naming the streams), then packets of int32 streamId, uint32 size
and `size` bytes: one LZ4/zstd frame (or raw bytes) holding a size-prefixed flatbuffer (EVTS, FRME, IMUS,
TRIG). An optional FileDataTable (FTAB, compressed like the packets) at dataTablePosition ends the file and
lists every packet's offset, size, stream, element count and time range; without it (interrupted recording)
or when it is damaged the packets are walked from the header on. Flatbuffers are parsed by `flatbuf` (clean
room); every length and offset is checked against the file or buffer before use, decompression is bounded,
and a truncated tail is salvaged up to the last complete packet with a warning. Errors are AedatError with
the byte offset where reading failed.
"""
from __future__ import annotations

import os
import struct
import warnings as _warnings
import xml.etree.ElementTree as ET

import lz4.frame
import numpy as np
import zstandard

from ..events import Events
from .checks import StreamChecks
from .flatbuf import FlatbufError, gather, root, table_vector
from .types import AedatError, AedatWarning, FrameData, ImuData, RecordingReader, StreamInfo, Triggers

MAGIC = b"#!AER-DAT4.0\r\n"
COMPRESSIONS = {0: "none", 1: "lz4", 2: "lz4-high", 3: "zstd", 4: "zstd-high"}
KINDS = {"EVTS": "events", "FRME": "frames", "IMUS": "imu", "TRIG": "triggers"}
IDENTS = {v: k for k, v in KINDS.items()}
# flatbuffer Event struct: int64 timestamp, int16 x, int16 y, bool polarity, 3 bytes padding (16 bytes)
EVENT_DTYPE = np.dtype({"names": ["t", "x", "y", "p"], "formats": ["<i8", "<i2", "<i2", "u1"],
                        "offsets": [0, 8, 10, 12], "itemsize": 16})
MAX_DECOMPRESSED = 1 << 30          # no packet may claim more than 1 GiB once decompressed
MAX_TABLE_BYTES = 256 << 20         # a stored FileDataTable larger than this is treated as corrupt
_CHUNK = 8 << 20
# Read-ahead pool (packets decompressed ahead of the consumer by WORKERS threads, bounded memory). Off by default:
# on the shared 2-core machine (load ~3.4) it measured slower (1.03-1.20 s vs 0.73 s per 10 M events); set
# READ_AHEAD = 4 where cores are free.
READ_AHEAD = 0
WORKERS = 2
_HDR = struct.Struct("<iI")
_IMU_FIELDS = {"t": (0, "<i8"), "temp": (1, "<f4"), "ax": (2, "<f4"), "ay": (3, "<f4"), "az": (4, "<f4"),
               "gx": (5, "<f4"), "gy": (6, "<f4"), "gz": (7, "<f4")}
_TRIG_FIELDS = {"t": (0, "<i8"), "kind": (1, "i1")}
_FTAB_FIELDS = {"offset": (0, "<i8"), "stream": (1, "<i4", 0), "size": (1, "<u4", 4), "elements": (2, "<i8"),
                "t_start": (3, "<i8"), "t_end": (4, "<i8")}


def _inflate(data: memoryview, comp: int, at: int) -> bytearray:
    """Decompress one LZ4/zstd frame holding a size-prefixed flatbuffer; output bounded by the size prefix,
    MAX_DECOMPRESSED and 1024x the compressed size (16 MiB at least), allocated only as it is produced."""
    cap = min(MAX_DECOMPRESSED, max(16 << 20, 1024 * len(data)))
    if comp in (1, 2) and 256 * len(data) <= cap:
        # LZ4 cannot expand more than ~255x, so one-shot decompression is bounded; the frame header's content
        # size (which lz4 would allocate up front) is checked first.
        if lz4.frame.get_frame_info(data)["content_size"] > 256 * len(data):
            raise AedatError(f"byte {at}: LZ4 frame header claims an impossible content size")
        out = lz4.frame.decompress(data, return_bytearray=True)
        total = 4 + struct.unpack_from("<I", out)[0] if len(out) >= 4 else 4
        if len(out) < total:
            raise AedatError(f"byte {at}: packet decompresses to {len(out)} bytes but its flatbuffer size "
                             f"prefix says {total}")
        return out
    if comp in (1, 2):
        dec, src = lz4.frame.LZ4FrameDecompressor(), [data]

        def read(k: int) -> bytes:
            if dec.eof or (not src and dec.needs_input):
                return b""
            return dec.decompress(src.pop() if src else b"", max_length=k)
    else:
        read = zstandard.ZstdDecompressor().stream_reader(data).read
    out = bytearray()
    while len(out) < 4:
        chunk = read(4 - len(out))
        if not chunk:
            raise AedatError(f"byte {at}: packet decompresses to {len(out)} bytes, too short for a flatbuffer")
        out += chunk
    total = 4 + struct.unpack_from("<I", out)[0]
    if total > cap:
        raise AedatError(f"byte {at}: packet claims {total} decompressed bytes from {len(data)} compressed "
                         f"bytes (limit {cap})")
    while len(out) < total:                   # grow only as output really arrives
        chunk = read(min(total - len(out), _CHUNK))
        if not chunk:
            break
        out += chunk
    if len(out) < total:
        raise AedatError(f"byte {at}: packet decompresses to {len(out)} bytes but its flatbuffer size prefix "
                         f"says {total}")
    return out


def _decompress(data: memoryview, comp: int, at: int):
    if comp == 0:
        return data
    try:
        return _inflate(data, comp, at)
    except AedatError:
        raise
    except Exception as e:  # lz4 raises RuntimeError, zstandard ZstdError: both mean corrupt data
        raise AedatError(f"byte {at}: {COMPRESSIONS[comp]} decompression failed: {e}") from None


class Aedat4Reader(RecordingReader):
    """Reader of one AEDAT 4.0 file. `stream` arguments take a stream id, its name (originalOutputName),
    its source (camera name), "source/name", or a StreamInfo; None picks the first stream of that kind.
    Every decoded packet is checked against what the file states (ev3dgs.io.checks): a corrupt packet is
    skipped, and values the file contradicts are dropped, with a warning naming the stream, packet and byte;
    with strict=True they raise AedatError instead. skip_corrupt=True/False is the older spelling of
    strict=False/True."""

    format = "aedat4"

    def __init__(self, path, *, strict: bool = False, skip_corrupt: bool | None = None) -> None:
        self.path = os.fspath(path)
        self.warnings: list[str] = []
        self.strict = strict if skip_corrupt is None else not skip_corrupt
        self._ahead: dict = {}                       # packet index -> Future of its payload (read-ahead pool)
        try:
            self._f = open(self.path, "rb")
        except OSError as e:
            raise AedatError(f"{self.path}: cannot open: {e.strerror or e}") from None
        try:
            self._open()
        except BaseException:
            self._f.close()
            raise

    # ------------------------------------------------------------------ header and packet index
    def _warn(self, msg: str) -> None:
        self.warnings.append(msg)
        _warnings.warn(f"{self.path}: {msg}", AedatWarning, stacklevel=3)

    def _open(self) -> None:
        f = self._f
        self.file_size = size = os.fstat(f.fileno()).st_size
        head = f.read(18)
        if head[:14] != MAGIC:
            raise AedatError("byte 0: not an AEDAT 4.0 file (no '#!AER-DAT4.0' version line)")
        if len(head) < 18:
            raise AedatError(f"byte 14: file ends inside the IOHeader size ({size} bytes)")
        n = struct.unpack_from("<I", head, 14)[0]
        if 18 + n > size:
            raise AedatError(f"byte 14: IOHeader size {n} runs past the end of the file ({size} bytes)")
        self.data_start = 18 + n
        try:
            hdr, _, _ = root(f.read(n), size_prefixed=False)
            comp = hdr.scalar(0, "i", 0)
            self.table_position = hdr.scalar(1, "q", -1)
            self.info_xml = hdr.string(2)
        except FlatbufError as e:
            raise AedatError(f"byte {18 + e.pos}: corrupt IOHeader: {e.msg}") from None
        if comp not in COMPRESSIONS:
            raise AedatError(f"byte 18: IOHeader names unknown compression {comp}")
        self.compression = comp
        self._streams = self._parse_xml(self.info_xml)
        self.has_table = False
        tp = self.table_position
        if tp == -1:
            self._warn("no FileDataTable (interrupted recording?): walking the packets")
            self._walk(size, truncated_ok=True)
        elif tp >= size or tp < self.data_start:
            kind = "at or past the end of the file" if tp >= size else "before the data"
            self._warn(f"byte 18: FileDataTable position {tp} is {kind} ({size} bytes): the file is truncated "
                       "or its header corrupt; walking the packets")
            self._walk(size, truncated_ok=True)
        elif not self._load_table(tp, size):
            self._walk(tp, truncated_ok=False)
        if not self._streams:    # no usable XML: one stream per id seen, typed from its first packet
            self._streams = {int(i): StreamInfo(int(i), f"stream{int(i)}", "other", compression=COMPRESSIONS[comp])
                             for i in np.unique(self._sid)}
        for s in self._streams.values():
            s.packets = int(np.count_nonzero(self._sid == s.id))
            if s.kind == "other" and s.packets:
                self._guess_kind(s)

    def _parse_xml(self, text: str) -> dict[int, StreamInfo]:
        out: dict[int, StreamInfo] = {}
        try:
            top = ET.fromstring(text)
            outinfo = next((nd for nd in top.iter("node") if nd.get("name") == "outInfo"), None)
            for nd in (outinfo.findall("node") if outinfo is not None else []):
                if not (nd.get("name") or "").isdigit():
                    continue
                sid = int(nd.get("name"))
                attrs = {a.get("key"): (a.text or "") for a in nd.findall("attr")}
                info = nd.find("node[@name='info']")
                iattrs = {a.get("key"): (a.text or "") for a in info.findall("attr")} if info is not None else {}
                tid = attrs.get("typeIdentifier", "")
                dims = [int(v) if v.strip().lstrip("-").isdigit() else 0
                        for v in (iattrs.get("sizeX", "0"), iattrs.get("sizeY", "0"))]
                out[sid] = StreamInfo(sid, attrs.get("originalOutputName", f"stream{sid}"), KINDS.get(tid, "other"),
                                      tid, iattrs.get("source", ""), max(dims[0], 0), max(dims[1], 0),
                                      COMPRESSIONS[self.compression])
        except (ET.ParseError, ValueError, AttributeError) as e:
            self._warn(f"byte 18: unreadable infoNode XML ({e}): stream types are taken from the packets")
            return {}
        return out

    def _guess_kind(self, s: StreamInfo) -> None:
        try:
            ident = root(self._payload(int(np.flatnonzero(self._sid == s.id)[0])))[1].decode("ascii", "replace")
        except (AedatError, FlatbufError):
            return
        if ident in KINDS:
            s.type_identifier, s.kind = ident, KINDS[ident]

    def _walk(self, end: int, truncated_ok: bool) -> None:
        """Index the packets by reading their 8-byte headers from the data start up to `end`."""
        offs, sizes, sids = [], [], []
        pos, f = self.data_start, self._f
        while pos < end:
            if end - pos < 8:
                if not truncated_ok:
                    raise AedatError(f"byte {pos}: {end - pos} stray bytes before the FileDataTable at byte {end}")
                self._warn(f"byte {pos}: file ends inside a packet header: truncated; salvaged {len(offs)} "
                           "complete packets")
                break
            f.seek(pos)
            sid, n = _HDR.unpack(f.read(8))
            if sid < 0 or (self._streams and sid not in self._streams):
                raise AedatError(f"byte {pos}: packet header names stream {sid}, which the IOHeader does not declare")
            if pos + 8 + n > end:
                if truncated_ok and n < 1 << 31:
                    self._warn(f"byte {pos}: packet of stream {sid} claims {n} bytes but only {end - pos - 8} remain: "
                               f"truncated; salvaged {len(offs)} complete packets")
                    break
                what = "file" if end == self.file_size else "data (FileDataTable at byte %d)" % end
                raise AedatError(f"byte {pos}: packet size {n} runs past the end of the {what} ({end} bytes)")
            offs.append(pos + 8)
            sizes.append(n)
            sids.append(sid)
            pos += 8 + n
        self._off = np.array(offs, np.int64)
        self._size = np.array(sizes, np.int64)
        self._sid = np.array(sids, np.int64)
        self._nel = self._t0 = self._t1 = None

    def _load_table(self, tp: int, size: int) -> bool:
        """Index the packets from the FileDataTable; False (with a warning) if it is damaged."""
        try:
            if size - tp > MAX_TABLE_BYTES:
                raise AedatError(f"byte {tp}: FileDataTable of {size - tp} bytes is implausibly large")
            self._f.seek(tp)
            buf = _decompress(memoryview(self._f.read(size - tp)), self.compression, tp)
            tab, ident, body = root(buf)
            if ident != b"FTAB":
                raise AedatError(f"byte {tp}: FileDataTable identifier is {ident!r}, not b'FTAB'")
            start, count = tab.vector(0, 4)
            a = table_vector(body, start, count, _FTAB_FIELDS)
        except (FlatbufError, AedatError) as e:
            self._warn(f"byte {tp}: corrupt FileDataTable ({e}): walking the packets")
            return False
        off, n, sid = a["offset"], a["size"].astype(np.int64), a["stream"].astype(np.int64)
        ends = off + n
        bad = ((off - 8 < self.data_start) | (ends > tp) | (sid < 0) | (a["elements"] < 0)
               | (a["t_end"] < a["t_start"]))
        if count > 1:
            bad[1:] |= off[1:] - 8 < ends[:-1]
        if self._streams:
            bad |= ~np.isin(sid, np.fromiter(self._streams, np.int64))
        if bad.any():
            i = int(np.argmax(bad))
            self._warn(f"byte {tp}: FileDataTable entry {i} (offset {int(off[i])}, {int(n[i])} bytes, stream "
                       f"{int(sid[i])}) is inconsistent: walking the packets")
            return False
        self._off, self._size, self._sid = off, n, sid
        self._nel, self._t0, self._t1 = a["elements"], a["t_start"], a["t_end"]
        self.has_table = True
        return True

    # ------------------------------------------------------------------ packets
    def _payload(self, i: int):
        """Decompressed payload (a size-prefixed flatbuffer) of packet i (read ahead by the pool when queued)."""
        fut = self._ahead.pop(i, None) if self._ahead else None
        if fut is not None:
            return fut.result()
        return self._read_packet(i)

    def _read_packet(self, i: int):
        """Read (positioned read: safe from worker threads) and decompress packet i."""
        off, n, sid = int(self._off[i]), int(self._size[i]), int(self._sid[i])
        if self._f.closed:
            raise AedatError(f"{self.path}: the reader is closed")
        raw = os.pread(self._f.fileno(), n + 8, off - 8)
        if len(raw) < n + 8:
            raise AedatError(f"byte {off - 8}: file ends inside the packet ({n} bytes): was it truncated since opening?")
        if _HDR.unpack_from(raw) != (sid, n):
            hs, hn = _HDR.unpack_from(raw)
            raise AedatError(f"byte {off - 8}: packet header (stream {hs}, {hn} bytes) does not match the "
                             f"FileDataTable (stream {sid}, {n} bytes)")
        return _decompress(memoryview(raw)[8:], self.compression, off)

    def _decode(self, i: int, kind: str):
        """(root table, buffer) of packet i, checked to be a `kind` packet; AedatError names the byte."""
        off = int(self._off[i])
        try:
            tab, ident, body = root(self._payload(i))
        except FlatbufError as e:
            raise AedatError(f"byte {off}: {kind} packet: corrupt flatbuffer ({e} of the decompressed payload)") from None
        name = ident.decode("ascii", "replace")
        if name in KINDS and kind in IDENTS and name != IDENTS[kind]:
            raise AedatError(f"byte {off}: packet identifier {name} in a {kind} stream (expected {IDENTS[kind]})")
        return tab, body

    def _packets(self, kind: str, stream, start_us=None, end_us=None):
        """Yield the decoded and checked packets of the chosen stream, skipping corrupt packets with a warning
        (strict: raising); packets outside [start, end) are skipped using the FileDataTable."""
        s = self._select(stream, kind)
        decode = getattr(self, "_decode_" + kind)
        chk = StreamChecks(self, s)
        check = {"events": lambda i, a: chk.events(i, *a), "frames": lambda i, a: a and chk.frame(i, a),
                 "imu": lambda i, a: chk.samples(i, a, "imu"), "triggers": lambda i, a: chk.samples(i, a, "triggers")}
        todo = [int(i) for i in np.flatnonzero(self._sid == s.id)
                if not (self._t0 is not None and ((start_us is not None and self._t1[i] < start_us)
                                                  or (end_us is not None and self._t0[i] >= end_us)))]
        for i in self._read_ahead(todo):
            try:
                out = check[kind](i, decode(i, s))
            except (AedatError, FlatbufError) as e:
                msg = str(e) if isinstance(e, AedatError) else f"byte {int(self._off[i])}: corrupt {kind} packet ({e})"
                if self.strict:
                    raise AedatError(msg) from None
                self._warn(f"{msg} [{chk.where(i)}]: packet skipped")
                continue
            if out is not None:
                yield out

    def _read_ahead(self, todo: list[int]):
        """Yield the packet indices of `todo` in order while a small thread pool reads and decompresses the next
        READ_AHEAD packets (LZ4/zstd release the GIL, so decompression overlaps decoding and the checks). Memory
        stays bounded by READ_AHEAD decompressed packets; errors surface in order, when a packet is consumed."""
        if self.compression == 0 or len(todo) < 2 or READ_AHEAD < 1:
            yield from todo
            return
        from collections import deque
        from concurrent.futures import ThreadPoolExecutor

        queued: deque = deque()
        with ThreadPoolExecutor(max_workers=WORKERS, thread_name_prefix="aedat4") as pool:
            try:
                nxt = 0
                for k, i in enumerate(todo):
                    while nxt < len(todo) and nxt <= k + READ_AHEAD:
                        j = todo[nxt]
                        if j not in self._ahead:
                            self._ahead[j] = pool.submit(self._read_packet, j)
                            queued.append(j)
                        nxt += 1
                    yield i
                    self._ahead.pop(i, None)
            finally:
                for j in queued:
                    fut = self._ahead.pop(j, None)
                    if fut is not None:
                        fut.cancel()

    def _decode_events(self, i: int, s: StreamInfo):
        """-> (t, x, y, stored polarity byte), checked into Events by StreamChecks.events."""
        tab, body = self._decode(i, "events")
        start, n = tab.vector(0, EVENT_DTYPE.itemsize)
        a = np.frombuffer(body, EVENT_DTYPE, count=n, offset=start)
        # t, x, y stay strided views into the decompressed packet (no copies: the packet buffer lives as long
        # as the chunk); a negative int16 coordinate becomes >= 32768 as uint16, which the checks reject
        return a["t"], a["x"].view(np.uint16), a["y"].view(np.uint16), a["p"]

    def _decode_frames(self, i: int, s: StreamInfo) -> FrameData | None:
        tab, body = self._decode(i, "frames")
        ts = [tab.scalar(k, "q", 0) for k in range(5)]
        code, w, h = tab.scalar(5, "b", 0), tab.scalar(6, "h", 0), tab.scalar(7, "h", 0)
        depth, ch = code & 7, (code >> 3) + 1
        off = int(self._off[i])
        if depth not in (0, 2) or code < 0:
            self._warn(f"byte {off}: frame with unsupported OpenCV type {code} skipped")
            return None
        if w < 0 or h < 0:
            raise AedatError(f"byte {off}: frame size {w}x{h} is negative")
        start, n = tab.vector(10, 1)
        dt = np.dtype(np.uint8 if depth == 0 else "<u2")
        if n != w * h * ch * dt.itemsize:
            raise AedatError(f"byte {off}: frame holds {n} pixel bytes, {w}x{h}x{ch}x{dt.itemsize} expected")
        img = np.frombuffer(body, dt, count=w * h * ch, offset=start).astype(dt.newbyteorder("="))
        img = img.reshape((h, w) if ch == 1 else (h, w, ch))
        return FrameData(timestamp=ts[0], frame_start=ts[1], frame_end=ts[2], exposure_start=ts[3],
                         exposure_end=ts[4], image=img, position=(tab.scalar(8, "h", 0), tab.scalar(9, "h", 0)),
                         source=s.source)

    def _vector(self, i: int, kind: str, fields) -> dict[str, np.ndarray]:
        tab, body = self._decode(i, kind)
        start, n = tab.vector(0, 4)
        return table_vector(body, start, n, fields)

    def _decode_imu(self, i: int, s: StreamInfo):
        return self._vector(i, "imu", _IMU_FIELDS)

    def _decode_triggers(self, i: int, s: StreamInfo):
        return self._vector(i, "triggers", _TRIG_FIELDS)

    # ------------------------------------------------------------------ public API
    def close(self) -> None:
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
        """Iterator of Events, one chunk per packet in file order, restricted to start_us <= t < end_us."""
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
        c = {k: np.concatenate([p[k] for p in parts]) for k in _IMU_FIELDS}
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
        if s.kind not in KINDS.values():
            return 0, -1, -1
        tab, body = self._decode(i, s.kind)
        if s.kind == "frames":
            t = tab.scalar(0, "q", 0)
            return 1, t, t
        start, n = tab.vector(0, 16 if s.kind == "events" else 4)
        if not n:
            return 0, -1, -1
        if s.kind == "events":
            t = gather(np.frombuffer(body, np.uint8), start + 16 * np.arange(n, dtype=np.int64), "<i8")
        else:
            t = table_vector(body, start, n, {"t": (0, "<i8")})["t"]
        return n, int(t.min()), int(t.max())

    def info(self) -> dict:
        """Summary for `ev3dgs-ingest info`: streams with packet/element counts and time ranges, compression,
        file size, FileDataTable state and warnings. Every packet is decoded and checked once (strict: the first
        problem raises); without a FileDataTable the counts and time ranges come from that pass."""
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
                "streams": streams, "t_start": min(ts) if ts else None, "t_end": max(te) if te else None,
                "warnings": list(self.warnings)}


def info(path) -> dict:
    """`Aedat4Reader(path).info()` for a path."""
    with Aedat4Reader(path) as r:
        return r.info()
