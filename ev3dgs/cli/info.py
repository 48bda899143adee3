"""Summaries of a scene file, a training run and a recording (`ev3dgs info`, `ev3dgs-ingest info`).

`scene_summary` / `describe`: a scene file (.h5) as a dict / as one screen of text; `run_summary` /
`describe_run`: a run folder written by `ev3dgs train` the same way. `recording_text` renders a
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


# ------------------------------------------------------------------------------------------ runs

_METRIC_GROUPS = (("novel_view", "novel views"), ("novel_view_unaligned", "novel views, unaligned"),
                  ("blur_view", "deblurred training views"), ("blur_view_given_poses", "deblurred, at given poses"),
                  ("blurry_input", "blurry input (baseline)"))


def _json(path: Path):
    """The JSON in `path`, or None when it is missing; a damaged file is a one-line InputError."""
    import json

    from ..errors import InputError

    if not path.is_file():
        return None
    try:
        return json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as e:
        raise InputError(f"{path}: not readable JSON ({e})") from None


def _last_log_record(path: Path) -> dict | None:
    import json

    last = None
    try:
        lines = path.read_text(errors="replace").splitlines()
    except OSError:
        return None
    for line in reversed(lines):
        try:
            rec = json.loads(line)
        except ValueError:
            continue   # a torn last line (a run killed mid-write)
        if isinstance(rec, dict) and isinstance(rec.get("step"), int):
            last = rec
            break
    return last


def run_summary(run_dir: str | Path) -> dict:
    """A training run folder as a dict of plain values: its settings (those that differ from the defaults),
    its progress (steps logged, the last loss, Gaussians), its scene (recorded and where it is found now), its
    metrics when it was evaluated, and which of the run's files are there."""
    import dataclasses

    from ..errors import InputError
    from ..train.config import RECORD_KEYS, TrainConfig

    run = Path(run_dir)
    config = _json(run / "config.json")
    if not isinstance(config, dict) or not isinstance(config.get("scene"), str):
        raise InputError(f"{run}: not a training run (no config.json naming a scene; `ev3dgs info` takes a scene "
                         "file or a run folder written by `ev3dgs train`)")
    defaults = {f.name: f.default for f in dataclasses.fields(TrainConfig)
                if f.default is not dataclasses.MISSING}
    settings = {k: v for k, v in config.items()
                if k not in RECORD_KEYS and k != "scene" and k in defaults and v != defaults[k]}
    unknown = sorted(k for k in config if k not in defaults and k not in RECORD_KEYS and k != "scene")
    try:
        variant = TrainConfig.load(run / "config.json").variant
    except Exception:  # noqa: BLE001 - an old or edited config: the summary still shows what it holds
        variant = None
    last = _last_log_record(run / "log.jsonl")
    record = config.get("scene_file") if isinstance(config.get("scene_file"), dict) else {}
    try:
        from ..train.run_scene import resolve_scene

        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            found = str(resolve_scene(run, config))
        scene_note = "; ".join(str(w.message) for w in caught) or None
    except InputError as e:
        found, scene_note = None, str(e)
    metrics = _json(run / "metrics.json")
    files = [n for n in ("config.toml", "model.pt", "ckpt.pt", "log.jsonl", "metrics.json", "trajectory.npz", "training.png",
                         "response.json") if (run / n).is_file()]
    evals = len(list((run / "eval").glob("*.png"))) if (run / "eval").is_dir() else 0
    out = {"path": str(run), "variant": variant, "iterations": config.get("iterations"),
           "steps_logged": None if last is None else last["step"],
           "finished": ((run / "model.pt").is_file() and last is not None
                        and last["step"] == config.get("iterations")),
           "last": None if last is None else {k: last.get(k) for k in ("loss", "psnr_blurry", "gaussians", "seconds")},
           "settings": settings, "unknown_settings": unknown,
           "scene": {"recorded": config["scene"], "name": record.get("name"), "size": record.get("size"),
                     "created": record.get("created"), "found": found, "note": scene_note},
           "metrics": None, "files": files, "eval_images": evals}
    if isinstance(metrics, dict):
        out["metrics"] = {key: {k: metrics[key].get(k) for k in ("psnr", "ssim", "lpips", "n")}
                          for key, _ in _METRIC_GROUPS if isinstance(metrics.get(key), dict)}
        out["metrics_lpips"] = metrics.get("lpips_reason") if metrics.get("lpips") is None else (
            f"LPIPS v{metrics['lpips'].get('version')} ({metrics['lpips'].get('net')})")
    return jsonable(out)


def describe_run(run_dir: str | Path) -> str:
    """`run_summary` as one screen of text."""
    d = run_summary(run_dir)
    it = d["iterations"]
    if d["steps_logged"] is None:
        progress = "no step logged yet"
    else:
        progress = f"{d['steps_logged']} of {it} steps" + (" (finished: model.pt)" if d["finished"] else
                                                          " (model.pt)" if "model.pt" in d["files"] else
                                                          " (unfinished: ckpt.pt, continue with --resume)"
                                                          if "ckpt.pt" in d["files"] else " (no checkpoint)")
        last = d["last"]
        bits = [f"loss {last['loss']:.5f}" if isinstance(last.get("loss"), (int, float)) else None,
                f"PSNR vs blurry {last['psnr_blurry']:.2f} dB" if isinstance(last.get("psnr_blurry"),
                                                                             (int, float)) else None,
                f"{last['gaussians']} Gaussians" if last.get("gaussians") is not None else None,
                f"{last['seconds']:.0f} s" if isinstance(last.get("seconds"), (int, float)) else None]
        progress += "; last step: " + ", ".join(b for b in bits if b)
    lines = [f"{d['path']}: training run, variant {d['variant'] or 'unknown'}", f"progress {progress}"]
    sc = d["scene"]
    ident = ", ".join(x for x in (f"name {sc['name']!r}" if sc["name"] else None,
                                  f"{sc['size']:,} bytes" if isinstance(sc["size"], int) else None,
                                  f"created {sc['created']}" if sc["created"] else None) if x)
    lines.append(f"scene    {sc['recorded']}" + (f" ({ident})" if ident else ""))
    if sc["found"] is None:
        lines.append(f"         not found: {sc['note']}")
    elif sc["found"] != sc["recorded"] or sc["note"]:
        lines.append(f"         found at {sc['found']}" + (f" ({sc['note']})" if sc["note"] else ""))
    shown = ", ".join(f"{k} {v}" for k, v in d["settings"].items())
    lines.append(f"settings {shown or 'all defaults'}"
                 + (f"; unknown keys {', '.join(d['unknown_settings'])}" if d["unknown_settings"] else ""))
    if d["metrics"] is None:
        lines.append("metrics  not evaluated (ev3dgs eval RUN writes metrics.json)")
    else:
        labels = dict(_METRIC_GROUPS)
        for key, m in d["metrics"].items():
            lp = f"  LPIPS {m['lpips']:.4f}" if isinstance(m.get("lpips"), (int, float)) else ""
            lines.append(f"metrics  {labels[key]:26s} PSNR {m['psnr']:6.2f} dB  SSIM {m['ssim']:.4f}{lp}  "
                         f"({m['n']} views)")
        if d.get("metrics_lpips"):
            lines.append(f"         {d['metrics_lpips']}")
    files = ", ".join(d["files"]) + (f", eval/ ({d['eval_images']} PNGs)" if d["eval_images"] else "")
    lines.append(f"files    config.json, {files}" if files else "files    config.json")
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
           "sensor_size": "sensor", "imu_scale": "IMU scale", "on": "ON events", "off": "OFF events",
           "skipped_bytes": "bytes skipped (realigned)"}
_BYTES = ("file_size", "data_start", "table_position", "header_bytes", "skipped_bytes")
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
