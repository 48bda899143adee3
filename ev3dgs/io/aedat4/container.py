"""AEDAT 4.0 container: the IOHeader, the infoNode XML naming the streams, and the packet index.

File layout (little-endian): the version line `#!AER-DAT4.0\\r\\n`, a uint32 N and the IOHeader flatbuffer
(compression, dataTablePosition, infoNode XML naming the streams), then packets of int32 streamId, uint32 size
and `size` bytes of payload. An optional FileDataTable (FTAB, compressed like the packets) at dataTablePosition
ends the file and lists every packet's offset, size, stream, element count and time range; without it
(interrupted recording) or when it is damaged the packets are walked from the header on, and a truncated tail is
salvaged up to the last complete packet with a warning. Every length and offset is checked against the file
before use; errors are AedatError with the byte offset where reading failed.
"""
from __future__ import annotations

import struct
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field

import numpy as np

from . import fast
from .packets import COMPRESSIONS, HDR, KINDS, decompress
from .flatbuf import FlatbufError, root, table_vector
from ..types import AedatError, StreamInfo

MAGIC = b"#!AER-DAT4.0\r\n"
MAX_TABLE_BYTES = 256 << 20         # a stored FileDataTable larger than this is treated as corrupt
_FTAB_FIELDS = {"offset": (0, "<i8"), "stream": (1, "<i4", 0), "size": (1, "<u4", 4), "elements": (2, "<i8"),
                "t_start": (3, "<i8"), "t_end": (4, "<i8")}


@dataclass
class Container:
    """What the header and the packet index say. Per packet (file order): payload offset `off`, `size`, stream
    `sid`; from the FileDataTable only (else None): element count `nel` and time range `t0`..`t1`."""
    file_size: int
    data_start: int = 0
    compression: int = 0
    table_position: int = -1
    info_xml: str = ""
    streams: dict[int, StreamInfo] = field(default_factory=dict)
    has_table: bool = False
    off: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    size: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    sid: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    nel: np.ndarray | None = None
    t0: np.ndarray | None = None
    t1: np.ndarray | None = None


def read_container(f, file_size: int, warn) -> Container:
    """Parse the header and index the packets of the open file `f`; salvaged problems go to warn(msg)."""
    c = Container(file_size)
    head = f.read(18)
    if head[:14] != MAGIC:
        raise AedatError("byte 0: not an AEDAT 4.0 file (no '#!AER-DAT4.0' version line)")
    if len(head) < 18:
        raise AedatError(f"byte 14: file ends inside the IOHeader size ({file_size} bytes)")
    n = struct.unpack_from("<I", head, 14)[0]
    if 18 + n > file_size:
        raise AedatError(f"byte 14: IOHeader size {n} runs past the end of the file ({file_size} bytes)")
    c.data_start = 18 + n
    try:
        hdr, _, _ = root(f.read(n), size_prefixed=False)
        comp = hdr.scalar(0, "i", 0)
        c.table_position = hdr.scalar(1, "q", -1)
        c.info_xml = hdr.string(2)
    except FlatbufError as e:
        raise AedatError(f"byte {18 + e.pos}: corrupt IOHeader: {e.msg}") from None
    if comp not in COMPRESSIONS:
        raise AedatError(f"byte 18: IOHeader names unknown compression {comp}")
    c.compression = comp
    c.streams = parse_xml(c.info_xml, comp, warn)
    tp = c.table_position
    if tp == -1:
        warn("no FileDataTable (interrupted recording?): walking the packets")
        _walk(f, c, file_size, True, warn)
    elif tp >= file_size or tp < c.data_start:
        kind = "at or past the end of the file" if tp >= file_size else "before the data"
        warn(f"byte 18: FileDataTable position {tp} is {kind} ({file_size} bytes): the file is truncated or its "
             "header corrupt; walking the packets")
        _walk(f, c, file_size, True, warn)
    elif not _load_table(f, c, tp, warn):
        _walk(f, c, tp, False, warn)
    if not c.streams:    # no usable XML: one stream per id seen, typed later from its first packet
        c.streams = {int(i): StreamInfo(int(i), f"stream{int(i)}", "other", compression=COMPRESSIONS[comp])
                     for i in np.unique(c.sid)}
    for s in c.streams.values():
        s.packets = int(np.count_nonzero(c.sid == s.id))
    return c


def parse_xml(text: str, compression: int, warn) -> dict[int, StreamInfo]:
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
            given = [iattrs.get(k) for k in ("sizeX", "sizeY")]
            dims = [int(v) if v is not None and v.strip().isdigit() else 0 for v in given]
            if any(v is not None for v in given) and not all(0 < d < 32768 for d in dims):
                # one damaged key must not give a 346x0 stream: no size, the reader takes it from elsewhere
                warn(f"byte 18: stream {sid} infoNode size sizeX={given[0]!r} sizeY={given[1]!r} is not a size: "
                     "taken from the other streams or the data")
                dims = [0, 0]
            out[sid] = StreamInfo(sid, attrs.get("originalOutputName", f"stream{sid}"), KINDS.get(tid, "other"),
                                  tid, iattrs.get("source", ""), dims[0], dims[1], COMPRESSIONS[compression])
    except (ET.ParseError, ValueError, AttributeError) as e:
        warn(f"byte 18: unreadable infoNode XML ({e}): stream types are taken from the packets")
        return {}
    return out


def _walk(f, c: Container, end: int, truncated_ok: bool, warn) -> None:
    """Index the packets by reading their 8-byte headers from the data start up to `end`."""
    offs, sizes, sids = [], [], []
    pos = c.data_start
    while pos < end:
        if end - pos < 8:
            if not truncated_ok:
                raise AedatError(f"byte {pos}: {end - pos} stray bytes before the FileDataTable at byte {end}")
            warn(f"byte {pos}: file ends inside a packet header: truncated; salvaged {len(offs)} complete packets")
            break
        f.seek(pos)
        sid, n = HDR.unpack(f.read(8))
        if sid < 0 or (c.streams and sid not in c.streams):
            raise AedatError(f"byte {pos}: packet header names stream {sid}, which the IOHeader does not declare")
        if pos + 8 + n > end:
            if truncated_ok and n < 1 << 31:
                warn(f"byte {pos}: packet of stream {sid} claims {n} bytes but only {end - pos - 8} remain: "
                     f"truncated; salvaged {len(offs)} complete packets")
                break
            what = "file" if end == c.file_size else "data (FileDataTable at byte %d)" % end
            raise AedatError(f"byte {pos}: packet size {n} runs past the end of the {what} ({end} bytes)")
        offs.append(pos + 8)
        sizes.append(n)
        sids.append(sid)
        pos += 8 + n
    c.off, c.size, c.sid = (np.array(v, np.int64) for v in (offs, sizes, sids))
    c.nel = c.t0 = c.t1 = None
    c.has_table = False


def _load_table(f, c: Container, tp: int, warn) -> bool:
    """Index the packets from the FileDataTable; False (with a warning) if it is damaged."""
    size = c.file_size
    try:
        if size - tp > MAX_TABLE_BYTES:
            raise AedatError(f"byte {tp}: FileDataTable of {size - tp} bytes is implausibly large")
        f.seek(tp)
        buf = decompress(memoryview(f.read(size - tp)), c.compression, tp)
        tab, ident, body = root(buf)
        if ident != b"FTAB":
            raise AedatError(f"byte {tp}: FileDataTable identifier is {ident!r}, not b'FTAB'")
        start, count = tab.vector(0, 4)
        a = fast.table(body, start, count)      # fresh arrays (buf is a reused scratch buffer)
        if a is None:
            a = table_vector(body, start, count, _FTAB_FIELDS)
    except (FlatbufError, AedatError) as e:
        warn(f"byte {tp}: corrupt FileDataTable ({e}): walking the packets")
        return False
    off, n, sid = a["offset"], a["size"].astype(np.int64), a["stream"].astype(np.int64)
    ends = off + n
    bad = (off - 8 < c.data_start) | (ends > tp) | (sid < 0) | (a["elements"] < 0) | (a["t_end"] < a["t_start"])
    if count > 1:
        bad[1:] |= off[1:] - 8 < ends[:-1]
    if c.streams and not set(np.unique(sid).tolist()) <= set(c.streams):
        bad |= ~np.isin(sid, np.fromiter(c.streams, np.int64))
    if bad.any():
        i = int(np.argmax(bad))
        warn(f"byte {tp}: FileDataTable entry {i} (offset {int(off[i])}, {int(n[i])} bytes, stream {int(sid[i])}) "
             "is inconsistent: walking the packets")
        return False
    c.off, c.size, c.sid = off, n, sid
    c.nel, c.t0, c.t1 = a["elements"], a["t_start"], a["t_end"]
    c.has_table = True
    return True
