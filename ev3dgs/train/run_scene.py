"""Where a training run's scene file is, from any working directory and after the run has been moved.

config.json keeps ``scene`` (the absolute path training read) and ``scene_file``: the path relative to the run
folder, the absolute path, the file name, its size and a cheap fingerprint (the root attrs ``name`` and
``created``). ``resolve_scene`` looks, in order, at: the ``--scene`` override; the path relative to the run
folder; the absolute path; the old runs' ``scene`` as given (relative to where training started: the current
folder, then the run folder and its parents); the file name next to the run folder and in its parents. A
candidate whose size or fingerprint differs from the recorded one is used only when nothing else matches
(with a warning). A ``--scene`` override whose name, size or fingerprint differs from the recorded scene's is
refused (``scene_difference`` names what differs) unless ``other_scene`` is given (``--other-scene``)."""
from __future__ import annotations

import json
import os
import warnings
from pathlib import Path

from ..errors import Ev3dgsWarning, InputError

__all__ = ["scene_record", "scene_fingerprint_of", "same_scene_file", "scene_difference", "resolve_scene",
           "resolve_run_scene"]


def scene_fingerprint_of(path: str | os.PathLike) -> dict | None:
    """{"size", "name", "created"} of a scene file, or None when it cannot be read."""
    p = Path(path)
    try:
        size = p.stat().st_size
    except OSError:
        return None
    out = {"size": int(size), "name": None, "created": None}
    try:
        import h5py

        with h5py.File(p, "r") as f:
            for key in ("name", "created"):
                v = f.attrs.get(key)
                out[key] = v.decode() if isinstance(v, bytes) else (None if v is None else str(v))
    except Exception:  # not HDF5, unreadable: the size alone identifies it
        pass
    return out


def scene_record(scene: str | os.PathLike, run_dir: str | os.PathLike) -> dict:
    """What config.json records about the scene file of a run in `run_dir`."""
    absolute = os.path.abspath(scene)
    try:
        relative = os.path.relpath(absolute, os.path.abspath(run_dir))
    except ValueError:  # another drive (Windows)
        relative = None
    fp = scene_fingerprint_of(absolute) or {}
    return {"path": absolute, "relative": relative, "file": os.path.basename(absolute),
            "size": fp.get("size"), "name": fp.get("name"), "created": fp.get("created")}


def _matches(record: dict | None, path: Path) -> bool:
    """True when `path` is the recorded file (or nothing was recorded to tell)."""
    if not record or record.get("size") is None:
        return True
    fp = scene_fingerprint_of(path)
    if fp is None:
        return False
    return all(record.get(k) is None or fp[k] == record.get(k) for k in ("size", "name", "created"))


def scene_difference(record: dict | None, path: str | os.PathLike) -> str | None:
    """What tells the scene file at `path` from the one a run recorded (config.json's ``scene_file``): its
    ``name`` attribute, its size, its creation time (the fingerprint), as one phrase; None when they agree or
    the record holds nothing to compare (an old run)."""
    if not record or all(record.get(k) is None for k in ("size", "name", "created")):
        return None
    fp = scene_fingerprint_of(path)
    if fp is None:
        return "it cannot be read"
    parts = []
    if record.get("name") is not None and fp["name"] != record["name"]:
        parts.append(f"its name is {fp['name']!r}, the run's scene is {record['name']!r}")
    if record.get("size") is not None and fp["size"] != record["size"]:
        parts.append(f"its size is {fp['size']:,} bytes, the run's scene has {record['size']:,}")
    if record.get("created") is not None and fp["created"] != record["created"]:
        parts.append(f"it was created {fp['created']}, the run's scene {record['created']}")
    return "; ".join(parts) or None


def same_scene_file(a: str | os.PathLike, b: str | os.PathLike) -> bool:
    """Two paths to one scene: the same file, or two copies with the same size, name and creation time."""
    pa, pb = Path(a), Path(b)
    try:
        if pa.resolve() == pb.resolve():
            return True
    except OSError:
        pass
    fa, fb = scene_fingerprint_of(pa), scene_fingerprint_of(pb)
    return fa is not None and fa == fb and fa["created"] is not None


def _candidates(run: Path, config: dict) -> list[Path]:
    record = config.get("scene_file") if isinstance(config.get("scene_file"), dict) else {}
    scene = config.get("scene") if isinstance(config.get("scene"), str) else None
    out: list[Path] = []
    if isinstance(record.get("relative"), str):
        out.append(run / record["relative"])
    if isinstance(record.get("path"), str):
        out.append(Path(record["path"]))
    if scene is not None:
        p = Path(scene)
        if p.is_absolute():
            out.append(p)
        else:  # an old run: the path as given where training started
            out.append(p)
            out += [base / p for base in (run.absolute(), *run.absolute().parents)]
    name = record.get("file") if isinstance(record.get("file"), str) else (Path(scene).name if scene else None)
    if name:
        out += [base / name for base in (run.absolute(), *run.absolute().parents)]
    seen, unique = set(), []
    for p in out:
        key = os.path.abspath(p)
        if key not in seen:
            seen.add(key)
            unique.append(p)
    return unique


def resolve_scene(run_dir: str | os.PathLike, config: dict, override: str | os.PathLike | None = None,
                  other_scene: bool = False) -> Path:
    """The scene file of the run in `run_dir` whose config.json holds `config` (a dict); see the module doc.
    InputError (one line, naming where it looked) when none is found, and when the `override` is not the
    scene the run was trained on (unless `other_scene`)."""
    run = Path(run_dir)
    record = config.get("scene_file") if isinstance(config.get("scene_file"), dict) else None
    if override is not None:
        p = Path(override)
        if not p.is_file():
            raise InputError(f"--scene {override}: no such file")
        import h5py

        if not h5py.is_hdf5(p):
            from ..schema import not_a_scene

            raise InputError(not_a_scene(p, "not HDF5"))
        differs = None if other_scene else scene_difference(record, p)
        if differs is not None:
            raise InputError(f"--scene {override} is not the scene the run {run} was trained on ({differs}); "
                             "pass --other-scene to use it anyway")
        return Path(os.path.abspath(p))
    looked = _candidates(run, config)
    existing = [p for p in looked if p.is_file()]
    for p in existing:
        if _matches(record, p):
            return Path(os.path.abspath(p))
    if existing:
        warnings.warn(f"{existing[0]} is not the scene file the run {run} was trained on (its size or "
                      "creation time differs); using it anyway (give --scene FILE to choose another)", Ev3dgsWarning,
                      stacklevel=2)
        return Path(os.path.abspath(existing[0]))
    if not looked:
        raise InputError(f"{run / 'config.json'}: names no scene file (give --scene FILE)")
    shown = ", ".join(os.path.normpath(p) for p in looked[:6]) + (f" and {len(looked) - 6} more" if len(looked) > 6 else "")
    raise InputError(f"{run}: the run's scene file {looked[0].name} is not found (looked at {shown}); "
                     "give --scene FILE")


def resolve_run_scene(run_dir: str | os.PathLike, override: str | os.PathLike | None = None,
                      other_scene: bool = False) -> Path:
    """resolve_scene with the run's config.json read from `run_dir`."""
    path = Path(run_dir) / "config.json"
    try:
        config = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise InputError(f"{path}: not readable ({e})") from None
    if not isinstance(config, dict):
        raise InputError(f"{path}: not a run's config (a JSON object expected)")
    return resolve_scene(run_dir, config, override, other_scene)
