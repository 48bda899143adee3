"""Open any supported recording by its magic line: AEDAT 4.0, 3.1 or 2.0."""
from __future__ import annotations

from pathlib import Path

from .types import AedatError, RecordingReader

MAGIC = {b"#!AER-DAT4.0": "aedat4", b"#!AER-DAT3.1": "aedat3.1", b"#!AER-DAT2.0": "aedat2"}


def detect_format(path: str | Path) -> str:
    p = Path(path)
    if not p.is_file():
        raise AedatError(f"{p}: no such file")
    with open(p, "rb") as f:
        head = f.read(16)
    if not head:
        raise AedatError(f"{p}: empty file (0 bytes): not a recording")
    for magic, name in MAGIC.items():
        if head.startswith(magic):
            return name
    raise AedatError(f"{p}: byte 0: not an AEDAT 2.0, 3.1 or 4.0 file (starts with {head[:12]!r})")


def open_recording(path: str | Path, *, strict: bool = False,
                   sensor_size: tuple[int, int] | None = None) -> RecordingReader:
    """The reader for the file's format. strict=False: corrupt packets and values the file contradicts are
    dropped with a warning; strict=True: they raise AedatError naming the byte. sensor_size=(W, H): the sensor of
    an AEDAT 2.0/3.1 file whose header does not name its camera (AEDAT 4 states it)."""
    fmt = detect_format(path)
    if fmt == "aedat4":
        from .aedat4 import Aedat4Reader

        return Aedat4Reader(path, strict=strict)
    if fmt == "aedat3.1":
        from .jaer.aedat3 import Aedat3Reader

        return Aedat3Reader(path, strict=strict, sensor_size=sensor_size)
    from .jaer.aedat2 import Aedat2Reader

    return Aedat2Reader(path, strict=strict, sensor_size=sensor_size)
