"""The scene file (HDF5, schema version 1): dataclasses, atomic `write`, lazy `read`, `validate`.

The layout is specified in docs/schema.md. `read` returns the large arrays (events,
train images and sharp frames, test images) as `LazyArray` objects that open the file on access; the
events come as a `LazyEvents` (same t/x/y/p attribute names as `Events`, `load()` reads them all).
Small arrays (K, distortion, exposure, poses, points, imu) are read eagerly as numpy arrays.
`write` accepts numpy arrays or `LazyArray`s (copied chunk-wise) and an `Events` or `LazyEvents`.
Every problem with a file is a `SchemaError` whose message starts with the path inside the file.
"""
from __future__ import annotations

import datetime
import json
import os
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

import h5py
import numpy as np

from .errors import SchemaError, raised_in_h5py
from .events import Events

FORMAT = "ev3dgs-scene"
VERSION = 1
COLOR_FILTERS = ("none", "RGGB", "BGGR", "GRBG", "GBRG")
# /events attr count_convention: where each pixel's reference stood when its exposure began.
#   "random_phase": at a uniformly random phase within one threshold (a real sensor that has been running; our
#     simulator's default), so the expected count over a change D is D / theta;
#   "exact_reference": exactly at the log intensity of the exposure's first pose (v2e / ESIM restarted per view:
#     E2NeRF's data, our simulator with reference = "exact"), so counts are truncated toward zero.
COUNT_CONVENTIONS = ("random_phase", "exact_reference")
# /train attr transfer: what the stored uint8 images encode and in which domain the blur happened.
#   "srgb": sRGB-encoded images of linear-light blur (our Blender data, DAVIS APS frames); events see linear light
#   "display": blur and events both computed on display values (E2NeRF / v2e): no sRGB decode before the log
#   "linear": images stored linearly (blur and events in linear light, no decode)
TRANSFERS = ("srgb", "linear", "display")
CHECK_ROWS = 1 << 20        # events scanned per step by validate
EVENT_CHUNK = 1 << 18       # HDF5 chunk length of the event datasets
_COPY_BYTES = 64 << 20      # bytes per block when copying a large array into the file
_GZIP = dict(compression="gzip", compression_opts=4, shuffle=True)
_EVENT_DTYPES = (("t", np.int64), ("x", np.uint16), ("y", np.uint16), ("p", np.int8))


class LazyArray:
    """One dataset of a scene file, read on access: `a[i:j]`, `a[[1, 5]]`, `np.asarray(a)`, `a.read()`."""

    def __init__(self, path: str | os.PathLike, name: str, shape: tuple[int, ...], dtype: Any) -> None:
        self.path = str(path)
        self.name = name
        self.shape = tuple(int(s) for s in shape)
        self.dtype = np.dtype(dtype)

    @property
    def ndim(self) -> int:
        return len(self.shape)

    def __len__(self) -> int:
        return self.shape[0]

    def __repr__(self) -> str:
        return f"LazyArray({self.path!r}, {self.name!r}, shape={self.shape}, dtype={self.dtype})"

    @contextmanager
    def _dataset(self) -> Iterator[h5py.Dataset]:
        try:
            with h5py.File(self.path, "r") as f:
                yield f[self.name]
        except (OSError, RuntimeError) as e:
            raise SchemaError(f"{self.name}: cannot read from {self.path} ({e})") from None

    def __getitem__(self, key: Any) -> np.ndarray:
        with self._dataset() as ds:
            return ds[key]

    def read(self) -> np.ndarray:
        """The whole array in memory."""
        return self[()]

    def __array__(self, dtype: Any = None, copy: Any = None) -> np.ndarray:
        a = self.read()
        return a if dtype is None else a.astype(dtype, copy=False)

    def iter_blocks(self, rows: int) -> Iterator[tuple[int, np.ndarray]]:
        """(start row, block) pairs of at most `rows` rows, with the file opened once."""
        with self._dataset() as ds:
            for start in range(0, self.shape[0], rows):
                yield start, ds[start:start + rows]


@dataclass
class LazyEvents:
    """The events of a scene file as LazyArrays (attributes t, x, y, p like `Events`); `load()` reads them."""

    t: LazyArray
    x: LazyArray
    y: LazyArray
    p: LazyArray

    def __len__(self) -> int:
        return len(self.t)

    def load(self) -> Events:
        return Events(self.t.read(), self.x.read(), self.y.read(), self.p.read())


@dataclass
class Camera:
    width: int
    height: int
    K: np.ndarray | None = None                      # f8 (3,3); None in an events-only file
    distortion: np.ndarray = field(default_factory=lambda: np.zeros(5))   # OpenCV k1 k2 p1 p2 k3
    background: tuple[float, float, float] | None = None


# optional /events attrs of the sensor model (see EventSensor); absent: unknown
SENSOR_MODEL_ATTRS = ("mismatch_sigma", "leak_rate_hz", "shot_noise_rate_hz")


@dataclass
class EventSensor:
    pos_threshold: float = 0.2                        # log units, nominal
    neg_threshold: float = 0.2
    color_filter: str = "none"                        # "none" or RGGB/BGGR/GRBG/GBRG
    refractory_us: float = 0
    log_knee: float | None = None                     # optional, for the trainer's log model
    count_convention: str | None = None               # COUNT_CONVENTIONS; None (absent): default_count_convention
    camera_raw_matrix: np.ndarray | None = None       # f8 (3,3) camera raw = M @ linear sRGB; None: identity
    # the sensor model the trainer's event noise model reads; None (absent): unknown, the trainer's defaults
    mismatch_sigma: float | None = None               # log units, std of the per-pixel thresholds around nominal
    leak_rate_hz: float | None = None                 # Hz per pixel, leak (background ON) events
    shot_noise_rate_hz: float | None = None           # Hz per pixel, shot-noise events (ON+OFF) at intensity 0


@dataclass
class Train:
    images: Any                                       # u1 (N,H,W,3), np.ndarray or LazyArray
    exposure: np.ndarray                              # i8 (N,2) [start, end)
    poses: np.ndarray | None = None                   # f8 (N,S,4,4) camera-to-world
    pose_t: np.ndarray | None = None                  # i8 (N,S)
    sharp: Any = None                                 # u1 (N,H,W,3)
    sharp_poses: np.ndarray | None = None             # f8 (N,4,4)
    transfer: str | None = None                       # attr, TRANSFERS; None: default_transfer

    def __len__(self) -> int:
        return len(self.images)


@dataclass
class Test:
    __test__ = False  # not a pytest test class, despite the name
    images: Any                                       # u1 (M,H,W,3)
    poses: np.ndarray                                 # f8 (M,4,4)


@dataclass
class Points:
    xyz: np.ndarray                                   # f4 (P,3)
    rgb: np.ndarray                                   # u1 (P,3)


@dataclass
class Imu:
    """IMU samples in the camera frame the scene uses (OpenCV: x right, y down, z forward, right-handed; both
    sensors in the same frame, so an upright camera at rest reads accel ~ (0, -1, 0) g and a positive gyro z is a
    clockwise roll seen from behind the camera)."""
    t: np.ndarray                                     # i8 (I,)
    accel: np.ndarray                                 # f4 (I,3) g
    gyro: np.ndarray                                  # f4 (I,3) deg/s
    temperature: np.ndarray                           # f4 (I,)


@dataclass
class Scene:
    name: str
    source: str
    camera: Camera
    events: Events | LazyEvents
    sensor: EventSensor
    train: Train | None = None
    test: Test | None = None
    points: Points | None = None
    imu: Imu | None = None
    bounds: np.ndarray | None = None                  # f8 (2,3) AABB min, max
    config: dict = field(default_factory=dict)        # provenance, stored as JSON text
    created: str = ""                                 # ISO 8601 UTC, set by write when empty


# group -> (dataset, dtype, shape, large: lazy + compressed, must be finite); H, W are the camera's size.
_U1, _I8, _F4, _F8 = (np.dtype(c) for c in ("u1", "i8", "f4", "f8"))
_PARTS = {
    "train": (("images", _U1, ("N", "H", "W", 3), True, False), ("exposure", _I8, ("N", 2), False, False),
              ("poses", _F8, ("N", "S", 4, 4), False, True), ("pose_t", _I8, ("N", "S"), False, False),
              ("sharp", _U1, ("N", "H", "W", 3), True, False), ("sharp_poses", _F8, ("N", 4, 4), False, True)),
    "test": (("images", _U1, ("M", "H", "W", 3), True, False), ("poses", _F8, ("M", 4, 4), False, True)),
    "points": (("xyz", _F4, ("P", 3), False, True), ("rgb", _U1, ("P", 3), False, False)),
    "imu": (("t", _I8, ("I",), False, False), ("accel", _F4, ("I", 3), False, False),
            ("gyro", _F4, ("I", 3), False, False), ("temperature", _F4, ("I",), False, False)),
}
_OPTIONAL = ("/train/poses", "/train/pose_t", "/train/sharp", "/train/sharp_poses")
_CLASSES = {"train": Train, "test": Test, "points": Points, "imu": Imu}


# ----------------------------------------------------------------------------------------- write

def _blocks(src: Any, rows: int) -> Iterator[tuple[int, np.ndarray]]:
    if isinstance(src, LazyArray):
        yield from src.iter_blocks(rows)
        return
    a = src if isinstance(src, h5py.Dataset) else np.asarray(src)
    for start in range(0, len(a), rows):
        yield start, a[start:start + rows]


def _cast(a: Any, dtype: Any, where: str) -> np.ndarray:
    """`a` as `dtype`, refusing lossy kinds (float into int) and out-of-range integers."""
    a = np.asarray(a)
    dt = np.dtype(dtype)
    if a.dtype == dt:
        return a
    ok = a.dtype.kind in ("biu" if dt.kind in "iu" else "biuf")
    if ok and dt.kind in "iu" and a.size and a.dtype.kind != "b":
        info = np.iinfo(dt)
        ok = info.min <= int(a.min()) and int(a.max()) <= info.max
    if not ok:
        raise SchemaError(f"{where}: expected dtype {dt}, found {a.dtype} (cannot convert safely)")
    return a.astype(dt)


def _put_large(g: h5py.Group, name: str, src: Any, dtype: Any, chunk_rows: int, check=None) -> None:
    shape = tuple(int(s) for s in src.shape)
    row_bytes = max(1, int(np.prod(shape[1:], dtype=np.int64)) * np.dtype(dtype).itemsize)
    ds = g.create_dataset(name, shape=shape, dtype=dtype, chunks=(chunk_rows,) + shape[1:],
                          maxshape=(None,) + shape[1:], **_GZIP)
    for start, block in _blocks(src, max(1, _COPY_BYTES // row_bytes)):
        ds[start:start + len(block)] = _cast(block, dtype, ds.name)
        if check is not None:
            check()  # stop at the first failed write (see write)


def _put(g: h5py.Group, name: str, a: Any, dtype: Any) -> None:
    g.create_dataset(name, data=_cast(a, dtype, f"{g.name.rstrip('/')}/{name}"))


def _json_default(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (Path, datetime.datetime)):
        return str(o)
    raise TypeError(f"{type(o).__name__} is not JSON serialisable")


def _check_sorted(t: Any, where: str) -> None:
    last = None
    for start, tc in _blocks(t, CHECK_ROWS):
        seq = tc if last is None else np.concatenate(([last], tc))
        bad = np.flatnonzero(seq[1:] < seq[:-1])
        if bad.size:
            offset = start if last is None else start - 1
            raise SchemaError(f"{where}: not sorted (first decrease at index {offset + int(bad[0]) + 1})")
        if len(tc):
            last = tc[-1]


def write(scene: Scene, path: str | os.PathLike) -> Path:
    """Write `scene` to `path` atomically (temporary file beside it, then rename); returns the path.

    Raises SchemaError (the target untouched) if the scene breaks the schema.
    """
    path = Path(path)
    _check_sorted(scene.events.t, "/events/t")
    try:
        config = json.dumps(scene.config or {}, sort_keys=True, default=_json_default)
    except (TypeError, ValueError) as e:
        raise SchemaError(f"/: config is not JSON serialisable ({e})") from None
    created = scene.created or datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
    from .outputs import H5Sink, OutputError, os_error_message, publish, remove_stale_temps, temp_name

    tmp, sink = temp_name(path), None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        remove_stale_temps(path.parent, path.name)  # left by killed writers of the same file
        # HDF5 writes through H5Sink, never straight to disk: a failed write (ENOSPC) inside HDF5 makes the
        # next close of the file or of one of its datasets segfault (see ev3dgs.outputs.H5Sink)
        sink = H5Sink(tmp, target=path)
        with h5py.File(sink, "w") as f:
            _write_contents(f, scene, config, created, sink.check)
        sink.fsync()
        sink.check()
        sink.close()
        validate(tmp, require_complete=False)
        publish(tmp, path)
    except BaseException as e:
        if sink is not None:
            sink.close()
        try:
            os.unlink(tmp)
        except OSError:  # missing, or a read-only folder: never hide the real error
            pass
        if isinstance(e, OSError):
            raise OutputError(f"cannot write {os_error_message(e, path)}", e.errno) from None
        raise
    return path


def _write_contents(f: h5py.File, s: Scene, config: str, created: str, check=None) -> None:
    f.attrs.update(format=FORMAT, version=VERSION, source=str(s.source), name=str(s.name),
                   created=created, config=config)
    if s.bounds is not None:
        f.attrs["bounds"] = _cast(s.bounds, np.float64, "/")
    cam = f.create_group("camera")
    cam.attrs["width"], cam.attrs["height"] = int(s.camera.width), int(s.camera.height)
    if s.camera.background is not None:
        cam.attrs["background"] = _cast(s.camera.background, np.float64, "/camera")
    if s.camera.K is not None:
        _put(cam, "K", s.camera.K, np.float64)
    if s.camera.K is not None or np.any(np.asarray(s.camera.distortion) != 0):
        _put(cam, "distortion", s.camera.distortion, np.float64)
    ev = f.create_group("events")
    for name, dt in _EVENT_DTYPES:
        _put_large(ev, name, getattr(s.events, name), dt, max(1, min(EVENT_CHUNK, len(s.events))), check)
    sn = s.sensor
    ev.attrs.update(pos_threshold=float(sn.pos_threshold), neg_threshold=float(sn.neg_threshold),
                    color_filter=str(sn.color_filter), refractory_us=sn.refractory_us)
    if sn.log_knee is not None:
        ev.attrs["log_knee"] = float(sn.log_knee)
    if sn.count_convention is not None:
        ev.attrs["count_convention"] = str(sn.count_convention)
    if sn.camera_raw_matrix is not None:
        ev.attrs["camera_raw_matrix"] = _cast(sn.camera_raw_matrix, np.float64, "/events")
    for key in SENSOR_MODEL_ATTRS:
        if getattr(sn, key) is not None:
            ev.attrs[key] = float(getattr(sn, key))
    for group, items in _PARTS.items():
        part = getattr(s, group)
        g = None if part is None else f.create_group(group)
        for name, dt, _, large, _ in items if part is not None else ():
            if getattr(part, name) is not None:
                if large:
                    _put_large(g, name, getattr(part, name), dt, 1, check)
                else:
                    _put(g, name, getattr(part, name), dt)
        if group == "train" and part is not None and part.transfer is not None:
            g.attrs["transfer"] = str(part.transfer)


# -------------------------------------------------------------------------------------- validate

_RECORDINGS = {b"#!AER-DAT4.0": "an AEDAT 4.0", b"#!AER-DAT3.1": "an AEDAT 3.1", b"#!AER-DAT2.0": "an AEDAT 2.0"}
_RECORDING_SUFFIXES = (".aedat4", ".aedat", ".aedat2", ".aedat3")


def not_a_scene(path: str | os.PathLike, error: BaseException | str) -> str:
    """Why `path` cannot be opened as a scene file, in one line: an event-camera recording (by its magic line,
    or its extension) is named as such with the command that converts it; a run folder, any folder and
    anything else as what they are."""
    p = Path(path)
    if p.is_dir():
        if (p / "config.json").is_file():
            return f"{p}: a training run folder, not a scene file (.h5); `ev3dgs info {p}` summarises the run"
        return f"{p}: a folder, not a scene file (.h5)"
    try:
        with open(p, "rb") as f:
            head = f.read(12)
    except OSError:
        head = b""
    kind = next((k for magic, k in _RECORDINGS.items() if head.startswith(magic)), None)
    if kind is None and p.suffix.lower() in _RECORDING_SUFFIXES and not head.startswith(b"\x89HDF"):
        kind = "an AEDAT"
    if kind is not None:
        return (f"{p}: {kind} recording, not a scene file (.h5); convert it first with "
                f"`ev3dgs-ingest davis {p} --out SCENE.h5` (`ev3dgs-ingest info` summarises it as it is)")
    return f"{p}: not a readable HDF5 file ({error})"


@contextmanager
def _open(path: str | os.PathLike) -> Iterator[h5py.File]:
    p = Path(path)
    if not p.is_file():
        raise SchemaError(f"{p}: no such file" if not p.exists() else not_a_scene(p, "not a file"))
    try:
        f = h5py.File(p, "r")
    except (OSError, RuntimeError) as e:
        raise SchemaError(not_a_scene(p, e)) from None
    try:
        with f:
            yield f
    except (OSError, RuntimeError) as e:
        raise SchemaError(f"{p}: cannot read HDF5 data; the file may be truncated or corrupt ({e})") from None
    except (KeyError, ValueError, TypeError) as e:
        if not raised_in_h5py(e):  # ours: a bug, keep its traceback
            raise
        # a damaged object header or attribute surfaces from h5py as KeyError/ValueError/TypeError
        raise SchemaError(f"{p}: cannot read HDF5 object; the file may be corrupt ({e})") from None


def _str(v: Any) -> str | None:
    if isinstance(v, (bytes, np.bytes_)):
        return v.decode("utf-8", "replace")
    return str(v) if isinstance(v, (str, np.str_)) else None


def _is_int(v: Any) -> bool:
    return isinstance(v, (int, np.integer)) and not isinstance(v, (bool, np.bool_))


def validate(source: str | os.PathLike | h5py.File, require_complete: bool = True, warn: bool = True,
             read_data: bool = False) -> list[str]:
    """Raise SchemaError (message starting with the path inside the file) if the file breaks the schema.

    require_complete=False accepts an events-only file (camera width/height, events, sensor attrs).
    read_data=True reads every dataset in full (a damaged compressed chunk is found now, not by a later reader).
    Returns the warnings (odd but trainable), also issued as SchemaWarning unless warn=False.
    The checks live in schema_validate.py.
    """
    from . import schema_validate  # here, not at the top: schema_validate imports the layout from this module

    return schema_validate.validate(source, require_complete, warn, read_data)


# ------------------------------------------------------------------------------------------ read

def read(path: str | os.PathLike, require_complete: bool = True) -> Scene:
    """Validate, then load the scene: large arrays as LazyArray, events as LazyEvents, the rest numpy."""
    path = Path(path).absolute()
    from . import schema_validate

    with _open(path) as f:
        schema_validate.check_open(f, require_complete)

        def lazy(name: str) -> LazyArray:
            return LazyArray(path, name, f[name].shape, f[name].dtype)

        def get(name: str) -> np.ndarray | None:
            return f[name][()] if name in f else None

        cam = f["camera"]
        bg = cam.attrs.get("background")
        camera = Camera(int(cam.attrs["width"]), int(cam.attrs["height"]), get("/camera/K"),
                        np.zeros(5) if "/camera/distortion" not in f else get("/camera/distortion"),
                        None if bg is None else tuple(float(v) for v in bg))
        ea = f["events"].attrs
        refr = ea["refractory_us"]
        source = _str(f.attrs.get("source", "")) or ""
        config = json.loads(_str(f.attrs.get("config", "{}")))
        sensor = EventSensor(float(ea["pos_threshold"]), float(ea["neg_threshold"]), _str(ea["color_filter"]),
                             int(refr) if _is_int(refr) else float(refr),
                             float(ea["log_knee"]) if "log_knee" in ea else None,
                             _str(ea["count_convention"]) if "count_convention" in ea else None,
                             np.asarray(ea["camera_raw_matrix"], np.float64) if "camera_raw_matrix" in ea else None,
                             **{k: float(ea[k]) for k in SENSOR_MODEL_ATTRS if k in ea})
        events = LazyEvents(*(lazy(f"/events/{n}") for n, _ in _EVENT_DTYPES))
        parts = {group: _CLASSES[group](*(None if f"/{group}/{n}" not in f else
                                          lazy(f"/{group}/{n}") if large else get(f"/{group}/{n}")
                                          for n, _, _, large, _ in items))
                 for group, items in _PARTS.items() if group in f}
        if "train" in parts and "transfer" in f["train"].attrs:  # absent: None (see default_transfer)
            parts["train"].transfer = _str(f["train"].attrs["transfer"])
        bounds = np.asarray(f.attrs["bounds"], np.float64) if "bounds" in f.attrs else None
        return Scene(name=_str(f.attrs.get("name", "")) or "", source=source,
                     camera=camera, events=events, sensor=sensor, **parts, bounds=bounds,
                     config=config,
                     created=_str(f.attrs.get("created", "")) or "")


def default_count_convention(source: str, config: dict) -> str:
    """count_convention of a file without the attr (read() gives None; the trainer uses this):
    "exact_reference" for E2NeRF imports (v2e restarted per view) and for simulated files whose settings carry
    no dvs.reference (our simulator before it had one started each view at an exact reference); a simulated
    file that records dvs.reference follows it; anything else (real recordings) "random_phase"."""
    if source == "e2nerf":
        return "exact_reference"
    dvs = config.get("sim", {}).get("dvs") if isinstance(config.get("sim"), dict) else None
    if isinstance(dvs, dict):
        ref = dvs.get("reference")
        return "random_phase" if ref == "random" else "exact_reference"
    return "random_phase"


def default_transfer(source: str) -> str:
    """/train transfer of a file without the attr (read() gives None; the trainer uses this): "display" for E2NeRF
    imports (v2e events and ISP blur of display values), "srgb" otherwise (our simulator and DAVIS ingest
    store sRGB-encoded images of linear-light blur)."""
    return "display" if source == "e2nerf" else "srgb"
