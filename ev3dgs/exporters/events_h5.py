"""Export the events in the HDF5 layout of DSEC (uzh-rpg/DSEC), read by its EventSlicer and the many loaders
derived from it, with the frames and their exposure windows beside it.

events.h5 (gzip level 4 + shuffle, readable by any HDF5 build; DSEC itself uses Blosc through hdf5plugin):
  events/x   uint16 (E,)   column, 0 = left
  events/y   uint16 (E,)   row, 0 = top
  events/t   uint32 (E,)   microseconds since t_offset, sorted
  events/p   uint8  (E,)   1 = ON (brighter), 0 = OFF
  t_offset   int64 ()      microseconds; absolute time = t + t_offset (floor of the first event or exposure
                           time to a whole millisecond)
  ms_to_idx  uint64 (T+2,) ms_to_idx[m] = index of the first event with t >= 1000 m (so
                           t[ms_to_idx[m] - 1] < 1000 m <= t[ms_to_idx[m]]), m = 0 .. T+1 with T = t[-1] // 1000;
                           the last entry is E: every event lies before it
  attrs      width, height, pos_threshold, neg_threshold (ours, not DSEC's)
images/NNNNNN.png              blurry frames (RGB PNG, lossless)
images/timestamps.txt          one line per frame: mid-exposure time, absolute us (same clock as t + t_offset)
images/exposure_timestamps.txt "start, end" per frame, absolute us (DSEC's exposure_timestamps_*.txt)
camera.json                    width, height, K (OpenCV pixel centres), distortion (OpenCV k1 k2 p1 p2 k3)
"""
from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np

from ..errors import InputError
from ..event_file import EventFile
from ..outputs import H5Sink
from .common import image_width, progress, write_png
from .notes import sensor_lines

_GZIP = dict(compression="gzip", compression_opts=4, shuffle=True)
_CHUNK_ROWS = 1 << 18


def _t_offset(sc, es: EventFile) -> int:
    starts = []
    if len(es):
        starts.append(int(es.read(0, 1).t[0]))
    if sc.train is not None and len(sc.train):
        starts.append(int(np.min(sc.train.exposure)))
    return (min(starts) // 1000) * 1000 if starts else 0


def _write_events(sink, es, E: int, off: int, n_ms: int, sc, W: int, H: int, quiet: bool) -> None:
    with h5py.File(sink, "w") as f:
        g = f.create_group("events")
        chunks = (max(1, min(_CHUNK_ROWS, E)),)
        ds = {n: g.create_dataset(n, shape=(E,), maxshape=(None,), dtype=dt, chunks=chunks, **_GZIP)
              for n, dt in (("x", np.uint16), ("y", np.uint16), ("t", np.uint32), ("p", np.uint8))}
        ms_to_idx = np.full(n_ms, E, np.uint64)
        bar = progress(E, "events-h5", quiet)
        start, next_ms = 0, 0
        for ev in es.blocks():
            rel = ev.t - off
            j = start + len(ev)
            ds["x"][start:j], ds["y"][start:j] = ev.x, ev.y
            ds["t"][start:j] = rel.astype(np.uint32)
            ds["p"][start:j] = (ev.p > 0).astype(np.uint8)
            # ms m with 1000 m <= this block's last t: its first event at or after 1000 m lies in this block
            # (an earlier one would have settled m with an earlier block), so each m is set exactly once
            last_ms = int(rel[-1]) // 1000
            ms = np.arange(next_ms, last_ms + 1, dtype=np.int64)
            ms_to_idx[next_ms:last_ms + 1] = start + np.searchsorted(rel, ms * 1000, side="left")
            next_ms, start = max(next_ms, last_ms + 1), j
            bar.update(len(ev))
            sink.check()
        bar.close()
        f.create_dataset("ms_to_idx", data=ms_to_idx)
        f.create_dataset("t_offset", data=np.int64(off))
        f.attrs.update(width=W, height=H, pos_threshold=sc.sensor.pos_threshold,
                       neg_threshold=sc.sensor.neg_threshold, source="ev3dgs export-dataset")


def export(sc, ev_path: str, stage: Path, quiet: bool = False) -> dict:
    W, H = sc.camera.width, sc.camera.height
    with EventFile(ev_path) as es:
        E = len(es)
        off = _t_offset(sc, es)
        t_last = int(es.read(E - 1, E).t[0]) - off if E else 0
        if t_last > np.iinfo(np.uint32).max:
            raise InputError(f"the events span {t_last} us, more than uint32 microseconds (71 min) hold: "
                             "DSEC's layout cannot store them")
        n_ms = t_last // 1000 + 2
        # HDF5 writes through H5Sink, never straight to disk: a write that fails inside HDF5 (a full disk)
        # makes a later close segfault; the sink keeps such writes, and check() raises between blocks
        sink = H5Sink(stage / "events.h5")
        try:
            _write_events(sink, es, E, off, n_ms, sc, W, H, quiet)
            sink.fsync()
            sink.check()
        finally:
            sink.close()
    N = len(sc.train) if sc.train is not None else 0
    if N:
        img = stage / "images"
        img.mkdir()
        digits = max(6, image_width(N))
        bar = progress(N, "frames", quiet, unit="img")
        for i in range(N):
            write_png(img / f"{i:0{digits}d}.png", sc.train.images[i])
            bar.update()
        bar.close()
        exp = np.asarray(sc.train.exposure, np.int64)
        (img / "timestamps.txt").write_text("".join(f"{(a + b) // 2}\n" for a, b in exp), encoding="utf-8")
        (img / "exposure_timestamps.txt").write_text(
            "# exposure_start_timestamp_us, exposure_end_timestamp_us\n" + "".join(f"{a}, {b}\n" for a, b in exp),
            encoding="utf-8")
    cam = {"width": W, "height": H, "pixel_convention": "OpenCV: centre of the top-left pixel is (0, 0)"}
    if sc.camera.K is not None:
        cam["K"] = np.asarray(sc.camera.K).tolist()
        cam["distortion_k1_k2_p1_p2_k3"] = np.asarray(sc.camera.distortion).tolist()
    (stage / "camera.json").write_text(json.dumps(cam, indent=1), encoding="utf-8")
    info = {"events": E, "t_offset": off, "frames": N}
    (stage / "README.txt").write_text(_readme(sc, info), encoding="utf-8")
    return info


def _readme(sc, info: dict) -> str:
    L = [f"DSEC-style event HDF5 export of ev3dgs scene '{sc.name}' (source {sc.source}) by `ev3dgs "
         f"export-dataset --format events-h5`: {info['events']} events, {info['frames']} frames.", "",
         "Layout: events.h5 with events/{x,y,t,p}, ms_to_idx, t_offset as DSEC (see the exporter's docstring); "
         "t is uint32 us since t_offset = " + str(info["t_offset"]) + " us, p is 1 for ON and 0 for OFF; "
         "images/ holds the blurry frames with DSEC-style timestamps.txt (mid-exposure) and "
         "exposure_timestamps.txt (start, end), absolute us on the events' clock.", "",
         "Converted exactly: every event (x, y, t, polarity). Compression is gzip (DSEC uses Blosc).", "",
         "Not in this layout:",
         "- poses, test views, sharp frames, points (use --format transforms or e2nerf)."]
    L += sensor_lines(sc, "DSEC's layout (they are written as attributes of events.h5)")
    return "\n".join(L) + "\n"
