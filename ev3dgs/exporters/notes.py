"""README.txt lines shared by the exporters: what the scene's sensor, camera and images say that a target
layout may not (thresholds, count convention, transfer curve, intrinsics)."""
from __future__ import annotations

import math

import numpy as np

from .. import schema


def sensor_lines(sc, target: str) -> list[str]:
    s = sc.sensor
    conv = s.count_convention or schema.default_count_convention(sc.source, sc.config)
    lines = [f"- contrast thresholds: ON {s.pos_threshold:g}, OFF {s.neg_threshold:g} (log intensity)"
             + (" - asymmetric" if s.pos_threshold != s.neg_threshold else "")
             + f"; {target} does not store them."]
    if conv == "random_phase":
        lines.append("- count convention: random_phase (each pixel's reference at a random phase when the "
                     "exposure starts, so the expected count over a log change D is D/theta). E2NeRF-style "
                     "losses assume v2e's convention (reference exactly at the first pose, counts truncated "
                     "toward zero, hence their +-0.5 target offset): on this data that offset is a bias of "
                     "half an event.")
    else:
        lines.append("- count convention: exact_reference (reference at each exposure's first pose), as v2e "
                     "and E2NeRF's data.")
    if s.log_knee is not None:
        lines.append(f"- log model: linear below a knee of {s.log_knee:g} (relative intensity); not stored.")
    if s.color_filter != "none":
        lines.append(f"- colour filter {s.color_filter}: events come from one Bayer channel per pixel; not stored.")
    if s.refractory_us:
        lines.append(f"- refractory period {s.refractory_us:g} us: not stored.")
    if s.camera_raw_matrix is not None:
        lines.append("- the sensor's camera-raw colour matrix is not stored.")
    return lines


def transfer_lines(sc) -> list[str]:
    tr = sc.train.transfer or schema.default_transfer(sc.source) if sc.train is not None else None
    if tr == "srgb":
        return ["- images: sRGB-encoded 8-bit values of a blur averaged in linear light, and events of linear "
                "light. E2NeRF/v2e data is display-referred (blur and lin-log of the 8-bit values): a method "
                "that models it that way sees a mismatched transfer curve here (decode sRGB first)."]
    if tr == "linear":
        return ["- images: stored linearly (blur and events in linear light); no transfer curve to undo."]
    if tr == "display":
        return ["- images: display-referred (blur and events of the 8-bit values), as E2NeRF/v2e data."]
    return []


def intrinsics_lines(sc, keeps: str) -> list[str]:
    """What a layout that keeps only `keeps` (e.g. 'one focal length, centred principal point') loses."""
    K = np.asarray(sc.camera.K, dtype=np.float64)
    W, H = sc.camera.width, sc.camera.height
    lost = []
    if not math.isclose(K[0, 0], K[1, 1], rel_tol=1e-12):
        lost.append(f"fy {K[1, 1]:.6g} != fx {K[0, 0]:.6g} (fy dropped)")
    if abs(K[0, 2] - (W - 1) / 2) > 1e-9 or abs(K[1, 2] - (H - 1) / 2) > 1e-9:
        lost.append(f"principal point ({K[0, 2]:.6g}, {K[1, 2]:.6g}) is off-centre (centre assumed)")
    if np.any(np.asarray(sc.camera.distortion) != 0):
        lost.append(f"distortion {np.asarray(sc.camera.distortion).tolist()} dropped (images are not undistorted)")
    head = f"- intrinsics: the layout keeps {keeps}"
    return [head + ("; lost: " + "; ".join(lost) if lost else "; nothing lost for this camera.")]
