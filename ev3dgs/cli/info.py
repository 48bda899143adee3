"""Summaries of a scene file and of a recording (shared by `ev3dgs info` and `ev3dgs-ingest info`).

`scene_summary` / `describe`: a scene file (.h5) as a dict / as one screen of text. `recording_text` renders a
recording reader's info dict as aligned "key: value" lines with its streams one per line; `jsonable` turns any of
these dicts into plain JSON values (numpy scalars and arrays, tuples, paths)."""
from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from .. import schema
from ..errors import SchemaWarning


def _read_scene(path: str):
    """schema.read, with validate's warnings (odd but trainable) returned once each instead of issued; other
    warnings pass on."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", SchemaWarning)
        sc = schema.read(path, require_complete=False)
    found = []
    for w in caught:
        if issubclass(w.category, SchemaWarning):
            if str(w.message) not in found:
                found.append(str(w.message))
        else:  # not ours to summarise: pass it on
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    return sc, found


def scene_summary(path: str) -> dict:
    """What `describe` prints, as a dict of plain values (for --json)."""
    sc, found = _read_scene(path)
    cam, ev, s = sc.camera, sc.events, sc.sensor
    n = len(ev)
    out = {"path": str(path), "format": schema.FORMAT, "version": schema.VERSION, "source": sc.source,
           "name": sc.name, "created": sc.created,
           "camera": {"width": int(cam.width), "height": int(cam.height),
                      "fx": None if cam.K is None else float(cam.K[0, 0])},
           "events": {"count": n, "t_start": int(ev.t[0]) if n else None, "t_end": int(ev.t[n - 1]) if n else None,
                      "pos_threshold": s.pos_threshold, "neg_threshold": s.neg_threshold,
                      "color_filter": s.color_filter, "refractory_us": s.refractory_us}}
    if sc.train is not None:
        out["train"] = {"views": len(sc.train),
                        "exposure_median_us": int(np.median(np.diff(sc.train.exposure, axis=1))),
                        "pose_samples_per_view": None if sc.train.poses is None else int(sc.train.poses.shape[1])}
    for part, label in ((sc.test, "test"), (sc.points, "points"), (sc.imu, "imu")):
        if part is not None:
            out[label] = len(next(iter(vars(part).values())))
    out["warnings"] = found
    return jsonable(out)


def describe(path: str) -> str:
    """The summary; a file validate rejects raises its SchemaError (one line from the CLIs), and validate's
    warnings (odd but trainable) end the summary as `warning` lines instead of Python warnings."""
    d = scene_summary(path)
    cam, ev = d["camera"], d["events"]
    lines = [f"{path}: {d['format']} v{d['version']}, source {d['source']!r}, name {d['name']!r}, "
             f"created {d['created']}",
             f"camera   {cam['width']}x{cam['height']}" + ("" if cam["fx"] is None else f", fx={cam['fx']:.1f}")]
    span = f", t {ev['t_start']}..{ev['t_end']} us" if ev["count"] else ""
    lines.append(f"events   {ev['count']}{span}; thresholds +{ev['pos_threshold']}/-{ev['neg_threshold']}, "
                 f"filter {ev['color_filter']}, refractory {ev['refractory_us']} us")
    if "train" in d:
        tr = d["train"]
        poses = ("no poses" if tr["pose_samples_per_view"] is None
                 else f"{tr['pose_samples_per_view']} pose samples/view")
        lines.append(f"train    {tr['views']} views, exposure median {tr['exposure_median_us']} us, {poses}")
    for label in ("test", "points", "imu"):
        if label in d:
            lines.append(f"{label:8s} {d[label]}")
    lines += [f"warning  {w}" for w in d["warnings"]]
    return "\n".join(lines)


# ------------------------------------------------------------------------------------------ recordings

def jsonable(value):
    """`value` with numpy scalars/arrays, tuples and paths turned into plain JSON values."""
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return jsonable(value.tolist())
    if isinstance(value, np.bool_):
        return bool(value)
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.floating):
        return float(value)
    if isinstance(value, Path):
        return str(value)
    if hasattr(value, "__dict__") and not isinstance(value, type):   # a dataclass such as StreamInfo
        return jsonable(vars(value))
    return value


_FORMATS = {"aedat4": "AEDAT 4.0", "aedat3.1": "AEDAT 3.1", "aedat2": "AEDAT 2.0"}
_UNITS = {"events": "events", "frames": "frames", "imu": "samples", "triggers": "triggers"}
_LABELS = {"file_size": "file size", "data_start": "data start", "table_position": "data table at",
           "has_table": "data table", "header_bytes": "header", "imu_samples": "IMU samples",
           "sensor_size": "sensor", "imu_scale": "IMU scale", "on": "ON events", "off": "OFF events"}
_BYTES = ("file_size", "data_start", "table_position", "header_bytes")
_SKIP = ("path", "format", "streams", "warnings", "t_start", "t_end", "time_range", "counts")


def _count(n) -> str:
    return "unknown" if n is None else f"{int(n):,}"


def _span(t0, t1) -> str:
    """'T0 .. T1 us (D s)', or 'none' without a time range."""
    if t0 is None or t1 is None:
        return "none"
    return f"{int(t0)} .. {int(t1)} us ({(int(t1) - int(t0)) * 1e-6:.3f} s)"


def _value(key: str, v) -> str:
    if isinstance(v, bool):
        return "yes" if v else "no"
    if v is None:
        return "none"
    if key in _BYTES:
        return f"byte {int(v):,}" if key in ("data_start", "table_position") else f"{int(v):,} bytes"
    if key == "sensor_size" and isinstance(v, (list, tuple)) and len(v) == 2:
        return f"{v[0]}x{v[1]}"
    if isinstance(v, dict):
        return ", ".join(f"{k} {_value(k, x)}" for k, x in v.items()) or "none"
    if isinstance(v, (int, np.integer)):
        return f"{int(v):,}"
    if isinstance(v, float):
        return f"{v:g}"
    return str(v)


def _stream_rows(info: dict) -> list[str]:
    counts = info.get("counts") or {}       # AEDAT 3.1: per stream name
    rows = []
    for s in info.get("streams") or []:
        s = jsonable(s)
        kind = s.get("kind", "other")
        n = s.get("elements")
        if n is None:
            c = counts.get(s.get("name"), {})
            n = next((c[k] for k in ("events", "frames", "imu_samples", "triggers") if k in c), None)
        unit = _UNITS.get(kind, "elements")
        what = f"{_count(n)} {unit[:-1] if n == 1 else unit}"
        if s.get("packets"):
            what += f" in {_count(s['packets'])} packet{'' if s['packets'] == 1 else 's'}"
        size = f"{s['width']}x{s['height']}" if s.get("width") and s.get("height") else ""
        ident = s.get("type_identifier") or ""
        rows.append([f"{s.get('id', '')}", str(s.get("name", "")), kind + (f" ({ident})" if ident else ""),
                     str(s.get("source") or ""), size, what,
                     "" if s.get("t_start") is None else "t " + _span(s.get("t_start"), s.get("t_end"))])
    if not rows:
        return []
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    return ["  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip() for r in rows]


def recording_text(path: str, fmt: str, info: dict, warnings_: list[str]) -> str:
    """A recording reader's info dict as aligned lines: scalar fields, the time range, the streams, warnings."""
    items = [(_LABELS.get(k, k.replace("_", " ")), _value(k, v)) for k, v in info.items() if k not in _SKIP]
    t0, t1 = info.get("time_range") or (info.get("t_start"), info.get("t_end"))
    items.append(("time range", _span(t0, t1)))
    width = max(len(k) for k, _ in items) + 1
    lines = [f"{path}: {_FORMATS.get(fmt, fmt)}"]
    lines += [f"  {(k + ':').ljust(width)} {v}" for k, v in items]
    rows = _stream_rows(info)
    if rows:
        lines.append("  streams:")
        lines += [f"    {r}" for r in rows]
    lines += [f"  warning: {w}" for w in warnings_]
    return "\n".join(lines)
