"""Every check a scene file must pass before anything reads it; `schema.validate` and `schema.read` call it.

A problem that would stop training (or make it produce nonsense) is a SchemaError whose message starts with
the path inside the file. Something merely odd, with which the trainer still runs, is a SchemaWarning: issued
with warnings.warn and returned as a list of messages, so CLIs can print them as one-line `warning:`s.

The events are scanned once, in blocks of schema.CHECK_ROWS rows, every check vectorised over a block: a
100M-event file costs one sequential read of /events and bounded memory.
"""
from __future__ import annotations

import json
import os
import warnings
from typing import Any

import h5py
import numpy as np

from . import schema
from .errors import SchemaError, SchemaWarning, raised_in_h5py
from .sensor import RANGES
from .schema import (_EVENT_DTYPES, _OPTIONAL, _PARTS, COLOR_FILTERS, COUNT_CONVENTIONS, FORMAT, TRANSFERS, VERSION,
                     _is_int, _open, _str)

# Poses are stored as float64 but not all producers compute them in float64: pycolmap's come from unit
# quaternions in float64 (max |R^T R - I| ~ 3e-15), while Blender hands back float32 matrix_world (the simulator's
# pose readback, E2NeRF's transforms JSON) and LLFF poses_bounds.npy files are often float32. Measured on 1e5
# random rotations: one float32 rounding gives 1e-7 (bound ~2*3*2^-24 = 4e-7), 20 chained float32 products
# 9e-7, text rounded to six decimals 1.7e-6. RIGID_TOL = 1e-5 leaves a 6x margin over the worst of these, and
# what it lets through is harmless: a scale or shear of 1e-5 moves a point by 0.01 px at a 1000 px focal
# length. Broken poses (all zeros, a scaled rotation, a 4x4 of random numbers) are off by O(1).
RIGID_TOL = 1e-5
# The trainer renders in float32 (resolution 6e-8 relative): at 1e6 scene units from the origin a position is
# resolved to 0.06 units, coarser than any scene producers write (Blender metres, COLMAP's unit-scale
# reconstructions, DAVIS poses in metres). A larger translation is a unit or parsing error, not a scene.
MAX_COORD = 1e6


def validate(source: str | os.PathLike | h5py.File, require_complete: bool = True,
             warn: bool = True, read_data: bool = False) -> list[str]:
    """Raise SchemaError (message starting with the path inside the file) if the file breaks the schema.

    require_complete=False accepts an events-only file (camera width/height, events, sensor attrs).
    read_data=True also reads every byte of every dataset (the images included, which the checks otherwise
    leave to the reader that needs them), so a damaged compressed chunk anywhere is found now.
    Returns the warnings (odd but trainable: see SchemaWarning), also issued with warnings.warn unless warn=False.
    """
    if isinstance(source, h5py.Group):
        try:
            return check_open(source.file, require_complete, warn, read_data)
        except (OSError, RuntimeError) as e:
            raise SchemaError(f"{source.file.filename}: cannot read HDF5 data ({e})") from None
        except (KeyError, ValueError, TypeError) as e:
            if not raised_in_h5py(e):
                raise
            raise SchemaError(f"{source.file.filename}: cannot read HDF5 object; the file may be corrupt ({e})") \
                from None
    with _open(source) as f:
        return check_open(f, require_complete, warn, read_data)


def check_open(f: h5py.File, complete: bool, warn: bool = True, read_data: bool = False) -> list[str]:
    """`validate` on an open file."""
    notes: list[str] = []
    _validate(f, complete, notes)
    if read_data:
        _read_every_dataset(f)
    if warn:
        for note in notes:
            warnings.warn(note, SchemaWarning, stacklevel=3)
    return notes


# ------------------------------------------------------------------------------------------ helpers

def _read_every_dataset(f: h5py.File) -> None:
    """Read each dataset block by block along its first axis: a damaged chunk is an error naming the
    dataset and the rows, not a failure later in whichever command reads it first."""
    paths: list[str] = []
    f.visititems(lambda name, obj: paths.append("/" + name) if isinstance(obj, h5py.Dataset) else None)
    for path in paths:
        ds = f[path]
        if ds.shape == () or ds.size == 0:
            continue
        row_bytes = max(1, ds.dtype.itemsize * int(np.prod(ds.shape[1:], dtype=np.int64)))
        rows = max(1, (64 << 20) // row_bytes)
        for start in range(0, ds.shape[0], rows):
            try:
                ds[start:start + rows]
            except (OSError, RuntimeError, ValueError) as e:
                raise SchemaError(f"{path}: rows {start}..{min(start + rows, ds.shape[0]) - 1} cannot be read "
                                  f"(damaged data? {' '.join(str(e).split())})") from None


def _real(obj: h5py.HLObject, key: str, where: str, low: float, strict: bool) -> float:
    if key not in obj.attrs:
        raise SchemaError(f"{where}: missing attr {key}")
    v = obj.attrs[key]
    if not (isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, (bool, np.bool_))) \
            or not np.isfinite(v) or (v <= low if strict else v < low):
        raise SchemaError(f"{where}: attr {key} must be a finite number {'>' if strict else '>='} {low}, found {v!r}")
    return float(v)


def _shape(path: str, found: tuple, expected: tuple, dims: dict) -> None:
    new: dict = {}
    ok = len(found) == len(expected)
    for got, want in zip(found, expected) if ok else ():
        if isinstance(want, str):
            bound = dims.get(want, new.get(want))
            if bound is None:
                new[want] = got
            ok = ok and (bound is None or bound == got)
        else:
            ok = ok and got == want
    if not ok:
        shown = [f"{w}={dims[w]}" if isinstance(w, str) and w in dims else str(w) for w in expected]
        text = "(" + ", ".join(shown) + ("," if len(shown) == 1 else "") + ")"
        raise SchemaError(f"{path}: expected shape {text}, found {tuple(found)}")
    dims.update(new)


def _ds(f: h5py.File, path: str, dtype: Any, shape: tuple, dims: dict) -> h5py.Dataset:
    if path not in f:
        raise SchemaError(f"{path}: missing")
    ds = f[path]
    if not isinstance(ds, h5py.Dataset):
        raise SchemaError(f"{path}: expected a dataset, found a group")
    want = np.dtype(dtype)
    if ds.dtype.kind != want.kind or ds.dtype.itemsize != want.itemsize:
        raise SchemaError(f"{path}: expected dtype {want}, found {ds.dtype}")
    _shape(path, ds.shape, shape, dims)
    return ds


def _finite(a: np.ndarray, path: str) -> None:
    bad = np.argwhere(~np.isfinite(a))
    if len(bad):
        raise SchemaError(f"{path}: non-finite value at index {list(map(int, bad[0]))}")


def _pair(f: h5py.File, a: str, b: str) -> bool:
    """True if both exist; SchemaError naming the missing one if only one does."""
    ha, hb = a in f, b in f
    if ha != hb:
        raise SchemaError(f"{b if ha else a}: missing ({a if ha else b} is present; they come together)")
    return ha


def _first(mask: np.ndarray) -> list[int] | None:
    """Index (as a list) of the first True in `mask`, None if there is none."""
    hit = np.argwhere(mask)
    return None if not len(hit) else [int(i) for i in hit[0]]


# ------------------------------------------------------------------------------------ the checks

def _validate(f: h5py.File, complete: bool, notes: list[str]) -> None:
    fmt = _str(f.attrs.get("format"))
    if fmt != FORMAT:
        raise SchemaError(f"/: attr format is {fmt!r}, expected {FORMAT!r} (not an ev3dgs scene file)"
                          if fmt is not None else "/: missing attr format (not an ev3dgs scene file)")
    ver = f.attrs.get("version")
    if not _is_int(ver):
        raise SchemaError(f"/: attr version must be an integer, found {ver!r}")
    if ver > VERSION:
        raise SchemaError(f"/: schema version {int(ver)} is newer than this reader ({VERSION})")
    if ver < 1:
        raise SchemaError(f"/: schema version {int(ver)} is not valid")
    for key in ("source", "name", "created", "config"):
        if key in f.attrs and _str(f.attrs[key]) is None:
            raise SchemaError(f"/: attr {key} must be text, found {f.attrs[key]!r}")
    if "config" in f.attrs:
        try:
            config = json.loads(_str(f.attrs["config"]))
        except ValueError as e:
            raise SchemaError(f"/: attr config is not valid JSON ({e})") from None
        if not isinstance(config, dict):
            raise SchemaError(f"/: attr config must be a JSON object, found {type(config).__name__}")
    if "bounds" in f.attrs:
        b = np.asarray(f.attrs["bounds"])
        if b.shape != (2, 3) or b.dtype.kind not in "iuf" or not np.all(np.isfinite(b)) or np.any(b[0] >= b[1]):
            raise SchemaError(f"/: attr bounds must be finite (2, 3) [min, max] with min < max on every axis (a "
                              f"box with volume), found {b.tolist() if b.size <= 16 else b.shape}")
        if np.abs(b).max() > MAX_COORD:
            raise SchemaError(f"/: attr bounds exceed {MAX_COORD:g} scene units in magnitude, found {b.tolist()}")

    if "camera" not in f:
        raise SchemaError("/camera: missing")
    cam = f["camera"]
    for key in ("width", "height"):
        v = cam.attrs.get(key)
        if not _is_int(v) or v <= 0:
            raise SchemaError(f"/camera: attr {key} must be a positive integer, found {v!r}")
    W, H = int(cam.attrs["width"]), int(cam.attrs["height"])
    if "background" in cam.attrs:
        bg = np.asarray(cam.attrs["background"])
        if bg.shape != (3,) or bg.dtype.kind not in "iuf" or not np.all((bg >= 0) & (bg <= 1)):
            raise SchemaError(f"/camera: attr background must be 3 floats in [0, 1], found {bg!r}")
    if complete or "/camera/K" in f:
        K = _ds(f, "/camera/K", np.float64, (3, 3), {})[()]
        _finite(K, "/camera/K")
        _intrinsics(K)
        _plausible_camera(K, W, H, notes)
    if complete or "/camera/distortion" in f:
        d = _ds(f, "/camera/distortion", np.float64, (5,), {})[()]
        _finite(d, "/camera/distortion")
        _distortion(d, K if complete or "/camera/K" in f else None, W, H)
    if "imu" in f:
        _imu(f)

    exposure = None
    for group, items in _PARTS.items():
        if group not in f and not (complete and group == "train"):
            continue
        dims: dict = {"H": H, "W": W}
        if group == "train":
            _pair(f, "/train/poses", "/train/pose_t")
            _pair(f, "/train/sharp", "/train/sharp_poses")
        for name, dt, shape, _, finite in items:
            path = f"/{group}/{name}"
            if path in _OPTIONAL and path not in f:
                continue
            ds = _ds(f, path, dt, shape, dims)
            if finite:
                a = ds[()]
                _finite(a, path)
                if name.endswith("poses"):
                    _rigid(a, path)
                elif np.abs(a).max(initial=0) > MAX_COORD:
                    raise SchemaError(f"{path}: value at index {_first(np.abs(a) > MAX_COORD)} exceeds "
                                      f"{MAX_COORD:g} scene units in magnitude")
        # Views are what the trainer iterates over and evaluate averages over: none of them is no scene.
        count = {"train": "N", "test": "M"}.get(group)
        if count and dims[count] == 0:
            raise SchemaError(f"/{group}/images: no views ({count} = 0); "
                              + ("a scene needs at least one training view" if group == "train"
                                 else "leave /test out instead"))
    if "train" in f:
        exposure = _validate_times(f, notes)
        if "transfer" in f["train"].attrs:
            tf = _str(f["train"].attrs["transfer"])
            if tf not in TRANSFERS:
                raise SchemaError(f"/train: attr transfer must be one of {TRANSFERS}, found {tf!r}")

    _validate_events(f, W, H, exposure, notes)


MAX_RADIAL_SCALE = 10.0     # OpenCV's radial factor 1 + k1 r^2 + k2 r^4 + k3 r^6 within [1/this, this] on the image
MAX_TANGENTIAL = 1.0        # |p1|, |p2|: decentring of a real lens is under 1e-2


def _distortion(d: np.ndarray, K: np.ndarray | None, W: int, H: int) -> None:
    """OpenCV k1 k2 p1 p2 k3 that describe a lens: over the image's normalised radii (from K; 1 without K) the
    radial map r -> r (1 + k1 r^2 + k2 r^4 + k3 r^6) keeps increasing (a map that folds back shows one scene
    point twice) and scales by at most MAX_RADIAL_SCALE either way; tangential terms below MAX_TANGENTIAL."""
    if not np.any(d):
        return
    k1, k2, p1, p2, k3 = (float(v) for v in d)
    r_max = 1.0
    if K is not None and K[0, 0] > 0 and K[1, 1] > 0:
        xs = (np.array([0.0, W]) - K[0, 2]) / K[0, 0]
        ys = (np.array([0.0, H]) - K[1, 2]) / K[1, 1]
        r_max = float(np.sqrt(np.max(xs ** 2) + np.max(ys ** 2)))
    r = np.linspace(0.0, r_max, 257)
    r2 = r * r
    scale = 1 + k1 * r2 + k2 * r2 ** 2 + k3 * r2 ** 3
    slope = 1 + 3 * k1 * r2 + 5 * k2 * r2 ** 2 + 7 * k3 * r2 ** 3
    what = None
    if np.any(slope <= 0):
        what = f"folds back at normalised radius {r[np.argmax(slope <= 0)]:.3g} (the image reaches {r_max:.3g})"
    elif scale.min() < 1 / MAX_RADIAL_SCALE or scale.max() > MAX_RADIAL_SCALE:
        what = (f"scales the image by {scale.min():.3g}..{scale.max():.3g} (no lens is outside "
                f"1/{MAX_RADIAL_SCALE:g}..{MAX_RADIAL_SCALE:g})")
    elif max(abs(p1), abs(p2)) > MAX_TANGENTIAL:
        what = f"has tangential terms p1 {p1:g}, p2 {p2:g} beyond {MAX_TANGENTIAL:g}"
    if what:
        raise SchemaError(f"/camera/distortion: {d.tolist()} (OpenCV k1 k2 p1 p2 k3) {what}: not a lens")


def _imu(f: h5py.File) -> None:
    """IMU samples: finite values at non-decreasing times."""
    for name in ("t", "accel", "gyro", "temperature"):
        path = f"/imu/{name}"
        if path not in f:
            continue
        a = f[path][()]
        if name == "t":
            back = np.flatnonzero(np.diff(a) < 0)
            if back.size:
                i = int(back[0]) + 1
                raise SchemaError(f"/imu/t: not in time order (t[{i}] = {a[i]} after t[{i - 1}] = {a[i - 1]})")
        elif a.dtype.kind == "f" and not np.all(np.isfinite(a)):
            raise SchemaError(f"/imu/{name}: value at index {_first(~np.isfinite(a))} is not finite")


def _intrinsics(K: np.ndarray) -> None:
    """A pinhole [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0 (finiteness is checked before)."""
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        raise SchemaError(f"/camera/K: focal lengths must be > 0, found fx = K[0, 0] = {K[0, 0]!r}, "
                          f"fy = K[1, 1] = {K[1, 1]!r}")
    # Producers build K from fx, fy, cx, cy and write the constant entries exactly (0 and 1 survive float32).
    if K[1, 0] != 0 or not np.array_equal(K[2], [0.0, 0.0, 1.0]):
        raise SchemaError(f"/camera/K: not a pinhole matrix [[fx, s, cx], [0, fy, cy], [0, 0, 1]]: "
                          f"K[1, 0] = {K[1, 0]!r}, row 2 = {K[2].tolist()}")


# What a pinhole camera allows. A field of view over FOV_ERROR_DEG (or under 1/FOV_NARROW of a pixel's worth)
# is no pinhole: fx = 1e-9 is a unit error, not a lens. Past FOV_WARN_DEG the pinhole model is stretched (a
# fisheye needs its own model). The principal point of a real lens lies near the image centre (decentering of a
# few percent); outside the image it is suspicious, more than one image size outside it is an error.
FOV_ERROR_DEG, FOV_WARN_DEG, FOV_MIN_DEG = 179.0, 160.0, 0.01
ASPECT_ERROR, ASPECT_WARN = 10.0, 1.2      # fx / fy: square-ish pixels on every sensor we read
MAX_EXPOSURE_US = 3_600_000_000            # one hour: no frame of a camera is exposed longer
EXPOSURE_WARN_RATIO = 100.0                # one exposure this many times the median: a unit or clock error?
EVENT_MARGIN_ERROR_US = 10**12             # events 11.6 days away from every frame: a broken timestamp
EXPOSURE_EVENT_RATIO = 100.0               # median exposure over the events' span (>= 1 s): impossible
EVENT_MARGIN_WARN_US = 60_000_000          # a minute away from the frames' span (beyond its own length)


def _plausible_camera(K: np.ndarray, W: int, H: int, notes: list[str]) -> None:
    """Focal lengths against the image size (field of view) and the principal point against the image."""
    fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
    fov_x = float(np.degrees(2 * np.arctan2(W / 2, fx)))
    fov_y = float(np.degrees(2 * np.arctan2(H / 2, fy)))
    for axis, fov, f_, n in (("x", fov_x, fx, W), ("y", fov_y, fy, H)):
        if fov > FOV_ERROR_DEG or fov < FOV_MIN_DEG:
            raise SchemaError(f"/camera/K: f{axis} = {f_:.6g} px gives a {fov:.4g} deg field of view over {n} px; "
                              f"a pinhole camera needs {FOV_MIN_DEG:g}-{FOV_ERROR_DEG:g} deg (focal length in "
                              "pixels, not metres?)")
        if fov > FOV_WARN_DEG:
            notes.append(f"/camera/K: f{axis} = {f_:.6g} px is a {fov:.0f} deg field of view: beyond what the "
                         "pinhole model describes well")
    aspect = fx / fy
    if not 1 / ASPECT_ERROR <= aspect <= ASPECT_ERROR:
        raise SchemaError(f"/camera/K: fx / fy = {aspect:.4g}; pixels that far from square are not a camera")
    if not 1 / ASPECT_WARN <= aspect <= ASPECT_WARN:
        notes.append(f"/camera/K: fx / fy = {aspect:.4g} (pixels far from square)")
    for name, c, n in (("cx", cx, W), ("cy", cy, H)):
        if not -n <= c <= 2 * n:
            raise SchemaError(f"/camera/K: principal point {name} = {c:.6g} lies more than an image size "
                              f"({n} px) outside the image")
        if not 0 <= c <= n:
            notes.append(f"/camera/K: principal point {name} = {c:.6g} lies outside the image (0-{n} px)")


def _rigid(a: np.ndarray, path: str) -> None:
    """Camera-to-world poses (..., 4, 4): rotation orthonormal with det +1 within RIGID_TOL, last row (0, 0, 0, 1),
    translation within MAX_COORD. The trainer inverts them and turns them into quaternions."""
    if not a.size:
        return
    R = a[..., :3, :3]
    err = np.abs(np.swapaxes(R, -1, -2) @ R - np.eye(3)).max(axis=(-2, -1))
    where = _first(err > RIGID_TOL)
    if where is not None:
        raise SchemaError(f"{path}: pose {where} is not rigid: its rotation part is not orthonormal "
                          f"(max |R^T R - I| = {err[tuple(where)]:.3g}, tolerance {RIGID_TOL:g})")
    det = np.linalg.det(R)
    where = _first(det < 0)
    if where is not None:
        raise SchemaError(f"{path}: pose {where} is not rigid: its rotation part is a reflection "
                          f"(det = {det[tuple(where)]:.3g}, expected +1)")
    row = np.abs(a[..., 3, :] - [0.0, 0.0, 0.0, 1.0]).max(axis=-1)
    where = _first(row > RIGID_TOL)
    if where is not None:
        raise SchemaError(f"{path}: pose {where} is not rigid: last row is {a[tuple(where)][3].tolist()}, "
                          f"expected [0, 0, 0, 1]")
    t = np.abs(a[..., :3, 3]).max(axis=-1)
    where = _first(t > MAX_COORD)
    if where is not None:
        raise SchemaError(f"{path}: pose {where} has translation {a[tuple(where)][:3, 3].tolist()}, beyond "
                          f"{MAX_COORD:g} scene units (a unit or parsing error?)")


def _validate_times(f: h5py.File, notes: list[str]) -> np.ndarray:
    """Exposure windows and pose times; returns the (N, 2) exposure."""
    exp = f["/train/exposure"][()]
    bad = np.flatnonzero(exp[:, 0] >= exp[:, 1])
    if bad.size:
        i = int(bad[0])
        raise SchemaError(f"/train/exposure: view {i} has start {exp[i, 0]} >= end {exp[i, 1]}")
    length = exp[:, 1] - exp[:, 0]
    bad = np.flatnonzero(length > MAX_EXPOSURE_US)
    if bad.size:
        i = int(bad[0])
        raise SchemaError(f"/train/exposure: view {i} is exposed for {length[i] / 1e6:.6g} s "
                          f"({exp[i, 0]}..{exp[i, 1]} us); no camera frame lasts over an hour")
    if len(length) > 2:
        med = float(np.median(length))
        bad = np.flatnonzero(length > EXPOSURE_WARN_RATIO * med)
        if bad.size:
            notes.append(f"/train/exposure: view {int(bad[0])} is exposed for {length[bad[0]]} us, over "
                         f"{EXPOSURE_WARN_RATIO:g}x the median {med:.0f} us ({bad.size} such views)")
    if "/train/pose_t" in f:
        pt = f["/train/pose_t"][()]
        if pt.shape[1] < 1:
            raise SchemaError("/train/poses: expected at least one pose sample per view, found S=0")
        # The trainer interpolates between neighbouring samples (searchsorted): times must increase, and two
        # different poses at one instant would be a contradiction.
        where = _first(np.diff(pt, axis=1) <= 0)
        if where is not None:
            n, s = where
            raise SchemaError(f"/train/pose_t: view {n} pose times are not increasing "
                              f"(sample {s + 1} at t={pt[n, s + 1]} follows t={pt[n, s]})")
        out = np.argwhere((pt < exp[:, :1]) | (pt > exp[:, 1:]))
        if len(out):
            n, s = map(int, out[0])
            raise SchemaError(f"/train/pose_t: sample [{n}, {s}] at t={pt[n, s]} is outside the "
                              f"exposure [{exp[n, 0]}, {exp[n, 1]}] of view {n}")
    return exp


def _validate_events(f: h5py.File, W: int, H: int, exposure: np.ndarray | None, notes: list[str]) -> None:
    if "events" not in f:
        raise SchemaError("/events: missing")
    dims: dict = {}
    ds = {name: _ds(f, f"/events/{name}", dt, ("E",), dims) for name, dt in _EVENT_DTYPES}
    ev = f["events"]
    lo, hi = RANGES["threshold"]
    for key in ("pos_threshold", "neg_threshold"):
        v = _real(ev, key, "/events", 0.0, True)
        if not lo <= v <= hi:
            raise SchemaError(f"/events: attr {key} = {v:g} log units is outside the physical range [{lo:g}, {hi:g}]")
    bounded = {"refractory_us": "period_us", "mismatch_sigma": "sigma", "leak_rate_hz": "rate_hz",
               "shot_noise_rate_hz": "rate_hz"}
    for key, kind in bounded.items():  # refractory_us required; the rest an optional sensor model, >= 0
        if key in ev.attrs or key == "refractory_us":
            v = _real(ev, key, "/events", 0.0, False)
            if v > RANGES[kind][1]:
                raise SchemaError(f"/events: attr {key} = {v:g} is outside the physical range [0, {RANGES[kind][1]:g}]")
    if "log_knee" in ev.attrs:  # the trainer takes log(knee) and divides by it: 0 is not a knee
        v = _real(ev, "log_knee", "/events", 0.0, True)
        lo, hi = RANGES["intensity"]
        if not lo <= v <= hi:
            raise SchemaError(f"/events: attr log_knee = {v:g} is outside the physical range [{lo:g}, {hi:g}] "
                              "(a fraction of white)")
    cf = _str(ev.attrs.get("color_filter"))
    if cf not in COLOR_FILTERS:
        raise SchemaError(f"/events: attr color_filter must be one of {COLOR_FILTERS}, found {cf!r}")
    if "count_convention" in ev.attrs:
        cc = _str(ev.attrs["count_convention"])
        if cc not in COUNT_CONVENTIONS:
            raise SchemaError(f"/events: attr count_convention must be one of {COUNT_CONVENTIONS}, found {cc!r}")
    if "camera_raw_matrix" in ev.attrs:  # the trainer takes each Bayer pixel's channel of M @ linear sRGB
        m = np.asarray(ev.attrs["camera_raw_matrix"])
        if m.shape != (3, 3) or m.dtype.kind not in "iuf" or not np.all(np.isfinite(m)) \
                or abs(float(np.linalg.det(m.astype(np.float64)))) < 1e-9:
            raise SchemaError(f"/events: attr camera_raw_matrix must be a finite invertible 3x3 matrix, found "
                              f"{m.tolist() if m.size <= 16 else m.shape}")

    E, rows = dims["E"], schema.CHECK_ROWS
    inside = 0          # events within [start, end] of some exposure (counted until the first block with any)
    last = None
    for start in range(0, E, rows):
        sl = slice(start, start + rows)
        t = ds["t"][sl]
        seq = t if last is None else np.concatenate(([last], t))
        bad = np.flatnonzero(seq[1:] < seq[:-1])
        if bad.size:
            first = (start if last is None else start - 1) + int(bad[0]) + 1
            raise SchemaError(f"/events/t: not sorted (first decrease at index {first})")
        last = t[-1]
        p = ds["p"][sl]
        bad = np.flatnonzero((p != 1) & (p != -1))
        if bad.size:
            raise SchemaError(f"/events/p: value {p[bad[0]]} at index {start + int(bad[0])} is not +1 or -1")
        for name, limit, what in (("x", W, "width"), ("y", H, "height")):
            v = ds[name][sl]
            bad = np.flatnonzero(v >= limit)
            if bad.size:
                raise SchemaError(f"/events/{name}: value {v[bad[0]]} at index {start + int(bad[0])} "
                                  f"is out of range ({what} {limit})")
        if exposure is not None and not inside:
            # t is sorted: the events in [a, b] of this block are t[searchsorted(a):searchsorted(b, right)].
            inside = int((np.searchsorted(t, exposure[:, 1], "right") - np.searchsorted(t, exposure[:, 0])).sum())

    # Warnings, not errors: the trainer runs (blur loss only, or events in one bin); the data are odd enough
    # that a person should look at them (clock offset between frames and events? a stuck timestamp?).
    if exposure is not None and not inside:
        notes.append("/events: no event lies inside any /train/exposure window; the event loss has nothing to "
                     "use" + (" (the file has no events)" if E == 0 else
                              " (are the event and frame clocks the same?)"))
    if exposure is not None and E and len(exposure):
        lo, hi = int(exposure[:, 0].min()), int(exposure[:, 1].max())
        margin = max(EVENT_MARGIN_WARN_US, hi - lo)
        for i, side in ((0, "first"), (E - 1, "last")):
            t = int(ds["t"][i])
            away = max(lo - t, t - hi, 0)
            if away > EVENT_MARGIN_ERROR_US:
                raise SchemaError(f"/events/t: the {side} event (index {i}) at t = {t} us lies {away / 1e6:.6g} s "
                                  f"outside the frames' time span {lo}..{hi} us (a broken timestamp)")
            if away > margin and inside:     # with none inside, the warning below says it once
                notes.append(f"/events/t: the {side} event at t = {t} us lies {away / 1e6:.3g} s outside the "
                             f"frames' time span {lo}..{hi} us")
    if exposure is not None and E > 1 and len(exposure):
        span = max(int(ds["t"][E - 1]) - int(ds["t"][0]), 1_000_000)
        med = float(np.median(exposure[:, 1] - exposure[:, 0]))
        if med > EXPOSURE_EVENT_RATIO * span:
            raise SchemaError(f"/train/exposure: the median view is exposed for {med / 1e6:.6g} s, over "
                              f"{EXPOSURE_EVENT_RATIO:g}x the events' whole span ({span / 1e6:.6g} s, at least 1 s "
                              "counted): wrong exposure times or units")
    if E > 1 and ds["t"][0] == ds["t"][E - 1]:
        notes.append(f"/events/t: all {E} events have the same time {int(ds['t'][0])} us")
