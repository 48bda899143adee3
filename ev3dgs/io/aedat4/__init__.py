"""AEDAT 4.0 (DV, dv-processing): the reader (`reader`), its container and packet decoding (`container`,
`packets`, `flatbuf`, `codec`), the optional C fast path for events (`fast`, `_fast.c`) and the writer
(`writer`)."""
from .reader import COMPRESSIONS, EVENT_DTYPE, MAGIC, THREADS, Aedat4Reader, AedatWarning, info

__all__ = ["Aedat4Reader", "AedatWarning", "info", "MAGIC", "EVENT_DTYPE", "COMPRESSIONS", "THREADS"]
