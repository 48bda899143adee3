"""An AEDAT 4.0 writer (clean room, from the documented byte layout; no flatbuffers package).

File layout (little-endian): the version line `#!AER-DAT4.0\\r\\n`, a uint32 size + the IOHeader flatbuffer
(identifier IOHE: compression, dataTablePosition, infoNode XML describing the streams), then packets
(int32 stream id, int32 size, payload = a size-prefixed flatbuffer, compressed as one LZ4/zstd frame when the
file is compressed) and, last, the FileDataTable (FTAB, compressed the same way, no packet header) whose
position is patched into the header once known.

The flatbuffers are laid out front to back: size prefix, root uoffset, identifier, vtable, root table, then
the vectors the table points to (uoffsets are unsigned and point forward; a table's soffset to its vtable
may point either way). Every scalar is aligned to its size relative to the start of the size-prefixed
buffer, int64 fields and the 16-byte Event struct to 8, as a flatbuffers verifier requires.

Schemas written (slot order as in DV's .fbs files):
  EVTS EventPacket{elements:[Event]}, Event struct (int64 t, int16 x, int16 y, bool polarity, pad 3)
  FRME Frame{timestamp, startOfFrame, endOfFrame, startOfExposure, endOfExposure: int64, format: int8
       (OpenCV type: 0 = CV_8UC1 GRAY, 16 = CV_8UC3 BGR, 24 = CV_8UC4 BGRA, 2 = CV_16UC1), sizeX, sizeY,
       positionX, positionY: int16, pixels:[uint8], exposure: int64 (us), source: int8 (1 = SENSOR)}
  IMUS IMUPacket{elements:[IMU]}, IMU{timestamp int64, temperature, accelerometer xyz (g), gyroscope xyz
       (deg/s), magnetometer xyz: float32}
  TRIG TriggerPacket{elements:[Trigger]}, Trigger{timestamp int64, type int8}
  FTAB FileDataTable{Table:[FileDataDefinition{ByteOffset int64, PacketInfo struct(int32 streamId, int32
       size), NumElements int64, TimestampStart int64, TimestampEnd int64}]}
"""
from __future__ import annotations

import os
import struct
from collections.abc import Iterable
from pathlib import Path
from xml.sax.saxutils import escape

import numpy as np

from ...errors import InputError
from ...events import Events
from ..types import FrameData, ImuData, Triggers

VERSION_LINE = b"#!AER-DAT4.0\r\n"
COMPRESSION = {"none": 0, "lz4": 1, "lz4-high": 2, "zstd": 3, "zstd-high": 4}
COMPRESSION_XML = {"none": "NONE", "lz4": "LZ4", "lz4-high": "LZ4_HIGH", "zstd": "ZSTD", "zstd-high": "ZSTD_HIGH"}
FORMAT_GRAY, FORMAT_BGR, FORMAT_BGRA, FORMAT_GRAY16 = 0, 16, 24, 2   # OpenCV type codes (DV FrameFormat)
FRAME_SOURCE_SENSOR = 1
EVENT_DTYPE = np.dtype({"names": ["t", "x", "y", "p"], "formats": ["<i8", "<i2", "<i2", "u1"],
                        "offsets": [0, 8, 10, 12], "itemsize": 16})
# inline tables of the table vectors, each starting 4 bytes past an 8-byte boundary (soffset first)
IMU_DTYPE = np.dtype({"names": ["soff", "t", "f"], "formats": ["<i4", "<i8", ("<f4", 10)],
                      "offsets": [0, 4, 12], "itemsize": 56})
TRIG_DTYPE = np.dtype({"names": ["soff", "t", "type"], "formats": ["<i4", "<i8", "i1"],
                       "offsets": [0, 4, 12], "itemsize": 16})
FTAB_DTYPE = np.dtype({"names": ["soff", "offset", "n", "t0", "t1", "sid", "size"],
                       "formats": ["<i4", "<i8", "<i8", "<i8", "<i8", "<i4", "<i4"],
                       "offsets": [0, 4, 12, 20, 28, 36, 40], "itemsize": 48})
STREAMS = {  # kind -> (stream name, identifier, DV type description)
    "events": ("events", "EVTS", "Array of events (polarity ON/OFF)."),
    "frames": ("frames", "FRME", "Standard frame (8-bit image)."),
    "imu": ("imu", "IMUS", "Inertial Measurement Unit data samples."),
    "triggers": ("triggers", "TRIG", "External triggers and special signals."),
}


class _Builder:
    """A size-prefixed flatbuffer written front to back: [u32 size][u32 root][4-char identifier]..."""

    def __init__(self, ident: str) -> None:
        self.b = bytearray(12)
        self.b[8:12] = ident.encode("ascii")

    def pad_to(self, align: int, extra: int = 0) -> None:
        """Pad so that the next write + `extra` bytes is `align`-aligned."""
        self.b += bytes((-(len(self.b) + extra)) % align)

    def vtable(self, field_offsets: list[int], table_size: int) -> int:
        self.pad_to(2)
        pos = len(self.b)
        self.b += struct.pack(f"<HH{len(field_offsets)}H", 4 + 2 * len(field_offsets), table_size, *field_offsets)
        return pos

    def table(self, vt: int, layout: bytes) -> int:
        """A table (`layout` = its inline bytes after the soffset) starting 4 past an 8-byte boundary."""
        self.pad_to(8, 4)
        pos = len(self.b)
        self.b += struct.pack("<i", pos - vt) + layout
        return pos

    def patch_ref(self, at: int) -> None:
        """Point the uoffset at `at` to the current end (the next thing written)."""
        struct.pack_into("<I", self.b, at, len(self.b) - at)

    def vector(self, at: int, data: bytes, count: int, elem_align: int = 4) -> int:
        """A vector of `count` elements (raw `data`), referenced from the uoffset field at `at`."""
        self.pad_to(elem_align, 4)
        self.patch_ref(at)
        pos = len(self.b)
        self.b += struct.pack("<I", count) + data
        return pos

    def root(self, table_pos: int) -> bytes:
        struct.pack_into("<I", self.b, 4, table_pos - 4)
        self.pad_to(8)
        struct.pack_into("<I", self.b, 0, len(self.b) - 4)
        return bytes(self.b)


def _vector_table(ident: str, vt_offsets: list[int], table_size: int, rows: np.ndarray) -> bytes:
    """A root table with one slot, a vector of tables (rows of an inline-table dtype), all sharing a vtable."""
    fb = _Builder(ident)
    root_vt = fb.vtable([4], 8)
    root = fb.table(root_vt, bytes(4))
    elem_vt = fb.vtable(vt_offsets, table_size)
    n = len(rows)
    # the vector of uoffsets, then the tables, each 4 past an 8-byte boundary
    fb.pad_to(4)
    fb.patch_ref(root + 4)
    vec = len(fb.b)
    fb.b += bytes(4 + 4 * n)
    fb.pad_to(8, 4)
    first = len(fb.b)
    stride = rows.dtype.itemsize
    slots = vec + 4 + 4 * np.arange(n, dtype=np.int64)
    tables = first + stride * np.arange(n, dtype=np.int64)
    # a fresh zeroed array, filled field by field: the rows' padding bytes are written as zeros whatever the
    # caller's array holds there (numpy's copy of a structured array need not carry them), so the same
    # recording always gives the same file
    packed = np.zeros(n, rows.dtype)
    for name in rows.dtype.names:
        packed[name] = rows[name]
    rows = packed
    rows["soff"] = tables - elem_vt
    struct.pack_into("<I", fb.b, vec, n)
    fb.b[vec + 4:vec + 4 + 4 * n] = (tables - slots).astype("<u4").tobytes()
    fb.b += rows.tobytes()
    return fb.root(root)


def event_packet(t: np.ndarray, x: np.ndarray, y: np.ndarray, p: np.ndarray) -> bytes:
    rows = np.zeros(len(t), EVENT_DTYPE)
    rows["t"], rows["x"], rows["y"], rows["p"] = t, x, y, np.asarray(p) > 0
    fb = _Builder("EVTS")
    root = fb.table(fb.vtable([4], 8), bytes(4))
    fb.vector(root + 4, rows.tobytes(), len(rows), elem_align=8)
    return fb.root(root)


def _frame_format(image: np.ndarray) -> int:
    channels = 1 if image.ndim == 2 else image.shape[2]
    if image.dtype == np.uint8 and channels in (1, 3, 4):
        return {1: FORMAT_GRAY, 3: FORMAT_BGR, 4: FORMAT_BGRA}[channels]
    if image.dtype == np.uint16 and channels == 1:
        return FORMAT_GRAY16
    raise InputError(f"frame images must be uint8 GRAY/BGR/BGRA or uint16 GRAY, got {image.dtype} {image.shape}")


def frame_packet(f: FrameData) -> bytes:
    img = np.asarray(f.image)
    fmt = _frame_format(img)
    h, w = img.shape[:2]
    fb = _Builder("FRME")
    # inline: 6 int64 at 4..52 (ts, sof, eof, soe, eoe, exposure), pixels uoffset 52, 4 int16 at 56..64,
    # format 64, source 65
    vt = fb.vtable([4, 12, 20, 28, 36, 64, 56, 58, 60, 62, 52, 44, 65], 66)
    layout = struct.pack("<6qI4hbb", f.timestamp, f.frame_start, f.frame_end, f.exposure_start, f.exposure_end,
                         f.exposure_end - f.exposure_start, 0, w, h, int(f.position[0]), int(f.position[1]),
                         fmt, FRAME_SOURCE_SENSOR)
    root = fb.table(vt, layout)
    data = np.ascontiguousarray(img.astype(img.dtype.newbyteorder("<"), copy=False)).tobytes()
    fb.vector(root + 52, data, len(data))
    return fb.root(root)


def imu_packet(imu: ImuData, i: int, j: int) -> bytes:
    rows = np.zeros(j - i, IMU_DTYPE)
    rows["t"] = imu.t[i:j]
    rows["f"][:, 0] = imu.temperature[i:j]
    rows["f"][:, 1:4] = imu.accel[i:j]
    rows["f"][:, 4:7] = imu.gyro[i:j]
    return _vector_table("IMUS", [4, 12, 16, 20, 24, 28, 32, 36, 40, 44, 48], 52, rows)


def trigger_packet(trig: Triggers, i: int, j: int) -> bytes:
    rows = np.zeros(j - i, TRIG_DTYPE)
    rows["t"], rows["type"] = trig.t[i:j], trig.kind[i:j]
    return _vector_table("TRIG", [4, 12], 13, rows)


def file_data_table(entries: list[tuple[int, int, int, int, int, int]]) -> bytes:
    """entries: (payload offset, stream id, payload size, elements, t start, t end)."""
    rows = np.zeros(len(entries), FTAB_DTYPE)
    if entries:
        e = np.asarray(entries, np.int64)
        rows["offset"], rows["sid"], rows["size"], rows["n"], rows["t0"], rows["t1"] = e.T
    return _vector_table("FTAB", [4, 36, 12, 20, 28], 44, rows)


def info_xml(streams: list[tuple[int, str]], width: int, height: int, compression: str, camera_name: str,
             ts_offset: int | None = None) -> str:
    """The infoNode XML, laid out as DV's recorder writes it (one node per stream id)."""
    base = "/mainloop/Recorder/outInfo/"
    lines = ['<dv version="2.0">', f'    <node name="outInfo" path="{base}">']
    for sid, kind in streams:
        name, ident, description = STREAMS[kind]
        path = f"{base}{sid}/"
        lines += [f'        <node name="{sid}" path="{path}">',
                  f'            <attr key="compression" type="string">{COMPRESSION_XML[compression]}</attr>',
                  '            <attr key="originalModuleName" type="string">capture</attr>',
                  f'            <attr key="originalOutputName" type="string">{name}</attr>',
                  f'            <attr key="typeDescription" type="string">{escape(description)}</attr>',
                  f'            <attr key="typeIdentifier" type="string">{ident}</attr>',
                  f'            <node name="info" path="{path}info/">']
        if kind in ("events", "frames"):
            lines += [f'                <attr key="sizeX" type="int">{width}</attr>',
                      f'                <attr key="sizeY" type="int">{height}</attr>']
        lines.append(f'                <attr key="source" type="string">{escape(camera_name)}</attr>')
        if ts_offset is not None:
            lines.append(f'                <attr key="tsOffset" type="long">{int(ts_offset)}</attr>')
        lines += ["            </node>", "        </node>"]
    lines += ["    </node>", "</dv>"]
    return "\n".join(lines) + "\n"


def io_header(compression: str, data_table_position: int, xml: str) -> bytes:
    fb = _Builder("IOHE")
    vt = fb.vtable([12, 4, 16], 20)   # compression int32 @12, dataTablePosition int64 @4, infoNode @16
    root = fb.table(vt, struct.pack("<qiI", data_table_position, COMPRESSION[compression], 0))
    fb.vector(root + 16, xml.encode() + b"\0", len(xml.encode()))
    return fb.root(root)


def _compressor(compression: str):
    if compression == "none":
        return lambda b: b
    if compression.startswith("lz4"):
        import lz4.frame

        level = 9 if compression == "lz4-high" else 0
        return lambda b: lz4.frame.compress(b, compression_level=level)
    import zstandard

    z = zstandard.ZstdCompressor(level=19 if compression == "zstd-high" else 3)
    return z.compress


def _event_chunks(events) -> Iterable[Events]:
    if events is None:
        return ()
    if isinstance(events, Events):
        return (events,)
    return events


def write_aedat4(path, width: int, height: int, events=None, frames: list[FrameData] | None = None,
                 imu: ImuData | None = None, compression: str = "lz4", camera_name: str = "DAVIS346_SIM",
                 packet_events: int = 20000, triggers: Triggers | None = None, imu_packet_samples: int = 50,
                 ts_offset: int | None = None) -> dict:
    """Write an AEDAT 4.0 file atomically (a temp file beside `path`, then os.replace).

    `events` is an Events or an iterable of time-ordered Events chunks (streamed; packets of
    `packet_events`); frames are FrameData with GRAY/BGR(A) uint8 or GRAY uint16 images; the imu and
    trigger streams are written when given (the events/frames/imu streams always exist). Packets of the
    different streams are interleaved in time order. Returns {stream: packets, ..., "bytes": size}."""
    compression = compression.lower()
    if compression not in COMPRESSION:
        raise InputError(f"compression must be one of {sorted(COMPRESSION)}, got {compression!r}")
    if not (0 < width < 32768 and 0 < height < 32768) or packet_events < 1 or imu_packet_samples < 1:
        raise InputError("width/height must be in [1, 32767] and packet sizes >= 1")
    frames = list(frames or [])
    kinds = ["events", "frames", "imu"] + (["triggers"] if triggers is not None else [])
    sid = {k: i for i, k in enumerate(kinds)}
    compress = _compressor(compression)
    # non-event packets, queued by start time: (t start, t end, kind, elements, builder)
    queue = [(f.timestamp, f.timestamp, "frames", 1, (lambda f=f: frame_packet(f))) for f in frames]
    if imu is not None and len(imu):
        for i in range(0, len(imu), imu_packet_samples):
            j = min(i + imu_packet_samples, len(imu))
            queue.append((int(imu.t[i]), int(imu.t[j - 1]), "imu", j - i, (lambda i=i, j=j: imu_packet(imu, i, j))))
    if triggers is not None and len(triggers):
        for i in range(0, len(triggers), imu_packet_samples):
            j = min(i + imu_packet_samples, len(triggers))
            queue.append((int(triggers.t[i]), int(triggers.t[j - 1]), "triggers", j - i,
                          (lambda i=i, j=j: trigger_packet(triggers, i, j))))
    queue.sort(key=lambda q: (q[0], kinds.index(q[2])))
    header = io_header(compression, 0, info_xml([(sid[k], k) for k in kinds], width, height, compression,
                                                 camera_name, ts_offset))
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    table: list[tuple[int, int, int, int, int, int]] = []
    counts = dict.fromkeys(kinds, 0)

    try:
        with open(tmp, "wb") as out:
            out.write(VERSION_LINE + header)   # the header's size prefix is the file's header size
            pos = len(VERSION_LINE) + len(header)

            def put(kind: str, payload: bytes, n: int, t0: int, t1: int) -> None:
                nonlocal pos
                data = compress(payload)
                out.write(struct.pack("<ii", sid[kind], len(data)))
                out.write(data)
                table.append((pos + 8, sid[kind], len(data), n, t0, t1))
                pos += 8 + len(data)
                counts[kind] += 1

            qi = 0

            def flush_until(t: int | None) -> None:
                nonlocal qi
                while qi < len(queue) and (t is None or queue[qi][0] <= t):
                    t0, t1, kind, n, build = queue[qi]
                    put(kind, build(), n, t0, t1)
                    qi += 1

            pending: list[Events] = []
            npend = 0
            last_t = None

            def emit(ev: Events) -> None:
                flush_until(int(ev.t[0]))
                put("events", event_packet(ev.t, ev.x, ev.y, ev.p), len(ev), int(ev.t[0]), int(ev.t[-1]))

            for chunk in _event_chunks(events):
                if not len(chunk):
                    continue
                if (last_t is not None and chunk.t[0] < last_t) or (len(chunk) > 1 and (np.diff(chunk.t) < 0).any()):
                    raise InputError("events must be sorted by time")
                if int(chunk.x.max()) >= width or int(chunk.y.max()) >= height:
                    raise InputError(f"event coordinates outside the {width}x{height} sensor")
                last_t = int(chunk.t[-1])
                pending.append(chunk)
                npend += len(chunk)
                if npend >= packet_events:
                    merged = Events.concatenate(pending)
                    k = (len(merged) // packet_events) * packet_events
                    for i in range(0, k, packet_events):
                        emit(Events(merged.t[i:i + packet_events], merged.x[i:i + packet_events],
                                    merged.y[i:i + packet_events], merged.p[i:i + packet_events]))
                    rest = Events(merged.t[k:], merged.x[k:], merged.y[k:], merged.p[k:])
                    pending, npend = ([rest] if len(rest) else []), len(rest)
            if npend:
                emit(Events.concatenate(pending))
            flush_until(None)
            data_table_position = pos
            out.write(compress(file_data_table(table)))
            # patch dataTablePosition (the int64 at the root table's offset 4) into the header
            root = struct.unpack_from("<I", header, 4)[0] + 4
            out.seek(len(VERSION_LINE) + root + 4)
            out.write(struct.pack("<q", data_table_position))
            out.flush()
            os.fsync(out.fileno())
        from ...outputs import publish

        publish(tmp, path)   # never over an output another process made meanwhile (ev3dgs.claims)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return {**counts, "bytes": path.stat().st_size}
