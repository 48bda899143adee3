"""Camera intrinsics from a calibration file: DV's camera-calibration XML (OpenCV FileStorage, as written by
DV's calibration module and by cv2.FileStorage), or a small TOML/JSON:

    width = 346
    height = 260
    fx = 320.0
    fy = 320.0
    cx = 172.5          # OpenCV pixel convention: centre of the top-left pixel at (0, 0)
    cy = 129.5
    distortion = [k1, k2, p1, p2, k3]     # optional, OpenCV order
"""
from __future__ import annotations

import json
import tomllib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError


@dataclass
class Calibration:
    width: int
    height: int
    K: np.ndarray            # (3,3)
    distortion: np.ndarray   # (5,)


def _from_mapping(d: dict, path: Path) -> Calibration:
    try:
        K = np.array([[float(d["fx"]), 0.0, float(d["cx"])], [0.0, float(d["fy"]), float(d["cy"])], [0, 0, 1.0]])
        dist = np.zeros(5)
        given = np.asarray(d.get("distortion", []), dtype=float).ravel()
        dist[: min(5, len(given))] = given[:5]
        return Calibration(int(d["width"]), int(d["height"]), K, dist)
    except KeyError as e:
        raise InputError(f"{path}: calibration needs {e.args[0]!r} (width, height, fx, fy, cx, cy)") from None
    except (TypeError, ValueError) as e:
        raise InputError(f"{path}: bad calibration value ({e})") from None


def _from_xml(path: Path) -> Calibration:
    import cv2

    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    if not fs.isOpened():
        raise InputError(f"{path}: not a readable OpenCV/DV calibration XML")
    try:
        root = fs.root()
        # DV nests the camera under its name; plain OpenCV files keep the keys at the root
        node = root
        if root.getNode("camera_matrix").empty():
            for key in root.keys():
                sub = root.getNode(key)
                if sub.isMap() and not sub.getNode("camera_matrix").empty():
                    node = sub
                    break
        K = node.getNode("camera_matrix").mat()
        dist = node.getNode("distortion_coefficients").mat()
        w = node.getNode("image_width").real()
        h = node.getNode("image_height").real()
    finally:
        fs.release()
    if K is None or K.shape != (3, 3):
        raise InputError(f"{path}: no 3x3 camera_matrix found")
    d = np.zeros(5)
    if dist is not None:
        flat = np.asarray(dist, float).ravel()
        d[: min(5, len(flat))] = flat[:5]
    return Calibration(int(w), int(h), np.asarray(K, float), d)


def load_calibration(path: str | Path) -> Calibration:
    p = Path(path)
    if not p.is_file():
        raise InputError(f"calibration file not found: {p}")
    suffix = p.suffix.lower()
    try:
        if suffix == ".toml":
            return _from_mapping(tomllib.loads(p.read_text()), p)
        if suffix == ".json":
            return _from_mapping(json.loads(p.read_text()), p)
    except (tomllib.TOMLDecodeError, json.JSONDecodeError, UnicodeDecodeError, RecursionError) as e:
        raise InputError(f"{p}: cannot parse calibration ({e})") from None
    return _from_xml(p)
