"""Export events and frames as an AEDAT 4.0 file (DV / dv-processing) through ev3dgs.io.aedat4.writer.

recording.aedat4: the events stream (packets of 20000, streamed from the scene file) and the frames stream (the
blurry training frames as BGR, timestamp = exposure start, with startOfExposure / endOfExposure = the
exposure window), LZ4-compressed by default. Frames are read from the scene file one at a time, when the
writer reaches their timestamp.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError
from ..io.aedat4.writer import COMPRESSION, write_aedat4
from ..event_file import EventFile
from .common import progress
from .notes import sensor_lines


class _LazyFrame:
    """A FrameData look-alike whose image is read from the scene file only when the writer packs it."""

    def __init__(self, images, i: int, start: int, end: int) -> None:
        self._images, self._i = images, i
        self.timestamp = self.exposure_start = self.frame_start = int(start)
        self.exposure_end = self.frame_end = int(end)
        self.position = (0, 0)

    @property
    def image(self) -> np.ndarray:
        return np.ascontiguousarray(np.asarray(self._images[self._i])[..., ::-1])   # RGB -> BGR


def export(sc, ev_path: str, stage: Path, quiet: bool = False, compression: str = "lz4") -> dict:
    W, H = sc.camera.width, sc.camera.height
    if compression not in COMPRESSION:
        raise InputError(f"--compression must be one of {sorted(COMPRESSION)}, found {compression!r}")
    if not (W < 32768 and H < 32768):
        raise InputError(f"AEDAT 4 stores coordinates as int16: a {W}x{H} sensor does not fit")
    frames = []
    if sc.train is not None:
        exp = np.asarray(sc.train.exposure, np.int64)
        frames = [_LazyFrame(sc.train.images, i, a, b) for i, (a, b) in enumerate(exp)]
    with EventFile(ev_path) as es:
        bar = progress(len(es), "aedat4", quiet)

        def chunks():
            for ev in es.blocks():
                yield ev
                bar.update(len(ev))

        counts = write_aedat4(stage / "recording.aedat4", W, H, events=chunks(), frames=frames,
                              compression=compression, camera_name=f"ev3dgs:{sc.name}")
        bar.close()
        n = len(es)
    info = {"events": n, "frames": len(frames), "bytes": counts["bytes"], "compression": compression}
    L = [f"AEDAT 4.0 export of ev3dgs scene '{sc.name}' (source {sc.source}) by `ev3dgs export-dataset "
         f"--format aedat4`: {n} events, {len(frames)} frames, {compression} compression.", "",
         "Converted exactly: events (t us, x, y, polarity) and the blurry frames (BGR 8-bit) with their "
         "exposure windows (startOfExposure / endOfExposure; timestamp = exposure start).", "",
         "Not in this layout:", "- poses, intrinsics, test views, sharp frames, points.",
         "- frames overlapping in time are written in timestamp order; DV assumes one exposure at a time."]
    L += sensor_lines(sc, "AEDAT 4")
    (stage / "README.txt").write_text("\n".join(L) + "\n", encoding="utf-8")
    return info
