"""A one-screen summary of a scene file (shared by `ev3dgs info` and `ev3dgs-ingest info`)."""
from __future__ import annotations

import warnings

import numpy as np

from .. import schema
from ..errors import SchemaWarning


def describe(path: str) -> str:
    """The summary; a file validate rejects raises its SchemaError (one line from the CLIs), and validate's
    warnings (odd but trainable) end the summary as `warning` lines instead of Python warnings."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", SchemaWarning)
        sc = schema.read(path, require_complete=False)
    cam, ev = sc.camera, sc.events
    lines = [f"{path}: {schema.FORMAT} v{schema.VERSION}, source {sc.source!r}, name {sc.name!r}, "
             f"created {sc.created}",
             f"camera   {cam.width}x{cam.height}" + ("" if cam.K is None else f", fx={cam.K[0, 0]:.1f}")]
    n = len(ev)
    span = f", t {int(ev.t[0])}..{int(ev.t[n - 1])} us" if n else ""
    s = sc.sensor
    lines.append(f"events   {n}{span}; thresholds +{s.pos_threshold}/-{s.neg_threshold}, "
                 f"filter {s.color_filter}, refractory {s.refractory_us} us")
    if sc.train is not None:
        poses = "no poses" if sc.train.poses is None else f"{sc.train.poses.shape[1]} pose samples/view"
        lines.append(f"train    {len(sc.train)} views, exposure median "
                     f"{int(np.median(np.diff(sc.train.exposure, axis=1)))} us, {poses}")
    for part, label in ((sc.test, "test"), (sc.points, "points"), (sc.imu, "imu")):
        if part is not None:
            first = next(iter(vars(part).values()))
            lines.append(f"{label:8s} {len(first)}")
    seen = set()
    for w in caught:
        if issubclass(w.category, SchemaWarning):
            if str(w.message) not in seen:          # each warning once
                seen.add(str(w.message))
                lines.append(f"warning  {w.message}")
        else:  # not ours to summarise: pass it on
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    return "\n".join(lines)
