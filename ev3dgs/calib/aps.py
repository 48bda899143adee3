"""A recording with APS frames -> what calibration and comparison need.

* frames as float DN (GRAY; colour frames are averaged to luminance), their exposure midpoints (the events
  between two midpoints belong to that frame pair; a frame without a valid exposure window is refused);
* the saturation level (the format's full scale) and the dark level (estimated in ev3dgs.calib.thresholds);
* all events of the recording's event stream (the readers stream them; recordings of a few seconds fit in
  memory).

Errors a user can act on are InputError, one line: no frames, one frame, every pixel saturated or under-exposed,
events without frames, frames without events, frames of another size than the event sensor.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from ..events import Events

UNDER_DN = 3.0          # a pixel within this many DN (8-bit scale) of the dark level is under-exposed
SAT_MARGIN = 2.0        # ... within this many DN of full scale is saturated


@dataclass
class Recording:
    path: str
    width: int
    height: int
    frames: np.ndarray          # (F, H, W) float64 DN, 8-bit scale (16-bit frames are divided by 256)
    t_mid: np.ndarray           # (F,) int64 exposure midpoints (us)
    exposure_us: np.ndarray     # (F,) int64
    full_scale: float           # DN of a saturated pixel
    events: Events

    @property
    def pairs(self) -> int:
        return len(self.t_mid) - 1

    def saturated(self) -> np.ndarray:
        return self.frames >= self.full_scale - SAT_MARGIN

    def intensity(self, dark: float) -> np.ndarray:
        """Linear intensity, 1.0 = full scale above the dark level (the simulator's input)."""
        return np.clip((self.frames - dark) / (self.full_scale - dark), 0.0, None)

    def valid(self, dark: float) -> np.ndarray:
        """(F, H, W): neither saturated nor under-exposed (less than UNDER_DN above the dark level, or above
        0 DN when the dark level is negative: a readout that clips at 0 has no signal there)."""
        return (~self.saturated()) & (self.frames - max(dark, 0.0) >= UNDER_DN)


def _gray(img: np.ndarray) -> tuple[np.ndarray, float]:
    img = np.asarray(img)
    scale = 1.0
    if img.dtype == np.uint16:
        scale = 1.0 / 256.0
    elif img.dtype != np.uint8:
        raise InputError(f"APS frames of dtype {img.dtype} are not supported (uint8 or uint16)")
    x = img.astype(np.float64) * scale
    if x.ndim == 3:  # OpenCV channel order BGR(A): luminance of B, G, R
        x = x[..., 2] * 0.2126 + x[..., 1] * 0.7152 + x[..., 0] * 0.0722
    return x, 255.0


def pixel_index(ev: Events, width: int) -> np.ndarray:
    return ev.y.astype(np.int64) * width + ev.x.astype(np.int64)


def load_recording(path) -> Recording:
    """Read frames and events of an AEDAT 4.0/3.1/2.0 recording; refuse what cannot be calibrated."""
    from ..io.recording import open_recording

    with open_recording(path) as rec:
        kinds = {s.kind for s in rec.streams()}
        frames = list(rec.frames()) if "frames" in kinds else []
        width, height = rec.sensor_size()
        events = Events.concatenate([e for e in rec.events()]) if "events" in kinds else Events()
    if not frames:
        what = "events but no APS frames" if len(events) else "no APS frames"
        raise InputError(f"{path}: the recording has {what}: calibration needs at least two frames")
    if len(frames) < 2:
        raise InputError(f"{path}: the recording has one APS frame: calibration needs at least two (a frame pair)")
    if not len(events):
        raise InputError(f"{path}: the recording has frames but no events")
    from .checks import check_exposures

    check_exposures(path, [int(f.exposure_start) for f in frames], [int(f.exposure_end) for f in frames], events.t)
    imgs, t_mid, expo = [], [], []
    full = 255.0
    for i, f in enumerate(frames):
        if f.image.shape[:2] != (height, width) or tuple(f.position) != (0, 0):
            raise InputError(f"{path}: frame {i} is {f.image.shape[1]}x{f.image.shape[0]} at {tuple(f.position)}, "
                             f"not the full {width}x{height} sensor (ROI frames are not supported)")
        if f.exposure_end <= f.exposure_start:
            raise InputError(f"{path}: frame {i} has no exposure window (start {f.exposure_start}, end "
                             f"{f.exposure_end}): events cannot be assigned to frame pairs")
        g, full = _gray(f.image)
        imgs.append(g)
        t_mid.append((int(f.exposure_start) + int(f.exposure_end)) // 2)
        expo.append(int(f.exposure_end) - int(f.exposure_start))
    t_mid = np.asarray(t_mid, np.int64)
    order = np.argsort(t_mid, kind="stable")
    keep = np.concatenate([[True], np.diff(t_mid[order]) > 0])
    order = order[keep]
    if len(order) < 2:
        raise InputError(f"{path}: all APS frames have the same exposure midpoint: no frame pair")
    frames_a = np.stack(imgs)[order]
    rec = Recording(str(path), int(width), int(height), frames_a, t_mid[order], np.asarray(expo)[order], full,
                    events)
    sat = rec.saturated()
    if sat.all():
        raise InputError(f"{path}: every pixel of every APS frame is saturated: no log intensity to fit")
    if (frames_a.max() - frames_a.min()) == 0 or (frames_a - frames_a.min() < UNDER_DN).all():
        raise InputError(f"{path}: every APS frame is uniform (all pixels {frames_a.flat[0]:.0f} DN): "
                         "no usable intensity")
    ok = ~sat & (frames_a - np.percentile(frames_a, 0.5) >= UNDER_DN)
    if ok.mean() < 1e-3:
        raise InputError(f"{path}: fewer than 0.1 % of the APS pixels are neither saturated nor under-exposed")
    inside = (events.t >= t_mid[0]) & (events.t < t_mid[-1])
    if not inside.any():
        raise InputError(f"{path}: no event lies between the first and last APS frame")
    return rec


def pair_counts(rec: Recording, weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(pairs, P) ON and OFF counts per pixel between consecutive exposure midpoints (int32); with per-event
    `weights` (held_weights) the sums of the weights instead (float64)."""
    ev = rec.events
    P = rec.width * rec.height
    k = np.searchsorted(rec.t_mid, ev.t, side="right") - 1
    inside = (k >= 0) & (k < rec.pairs)
    pix = pixel_index(ev, rec.width)
    out = []
    for sign in (1, -1):
        m = inside & (ev.p == sign)
        if weights is None:
            c = np.bincount(k[m] * P + pix[m], minlength=rec.pairs * P).astype(np.int32)
        else:
            c = np.bincount(k[m] * P + pix[m], weights=weights[m], minlength=rec.pairs * P)
        out.append(c.reshape(rec.pairs, P))
    return out[0], out[1]


def held_weights(rec: Recording, refractory_us: float) -> np.ndarray:
    """Per event (in the recording's order) the thresholds' worth of log change it stands for, counting the
    change lost while the pixel is held after it (refractory period R): dt / (dt - R), dt the interval to the
    pixel's next event if that has the same polarity, else 1 (the slope after a last event is unknown; a
    reversal's is small).

    Derivation (the simulator's refractory semantics, ev3dgs.sim.kernel): after an event the pixel is held
    for R with its reference following the input, so at release d = 0, and the next event of the same
    polarity fires when the input has moved a whole threshold C further. At a slope g that is steady between
    the two events the interval is dt = R + C / g, and the change lost in the hold is g R = C R / (dt - R): the
    event stands for C (1 + R / (dt - R)) = C dt / (dt - R). Events crowd where the slope is steep, so a
    correction that assumes the pair's mean slope (dL (1 - N R / dt_pair)) misses most of the loss: on the
    lego `record` recordings of a 1 ms sensor, thresholds read +24 / +41 % with it (+10 / +6 % without a
    refractory period) and +15 / +17 % with these weights. dt - R is floored at 1 us (the timestamps'
    resolution), an interval below R counts 1; fit_thresholds caps what a pair's weights can add (the lost
    change cannot exceed the pair's)."""
    ev = rec.events
    n = len(ev.t)
    if refractory_us <= 0 or n == 0:
        return np.ones(n)
    pix = pixel_index(ev, rec.width)
    o = np.lexsort((ev.t, pix))
    ps, ts, pp = pix[o], ev.t[o].astype(np.float64), ev.p[o]
    w = np.ones(n)
    same = (ps[1:] == ps[:-1]) & (pp[1:] == pp[:-1])
    dt = ts[1:][same] - ts[:-1][same]
    # an interval below R (an early outlier: R is the histogram's onset) says nothing about a hold: 1
    w[:-1][same] = np.where(dt > refractory_us, dt / np.maximum(dt - refractory_us, 1.0), 1.0)
    out = np.empty(n)
    out[o] = w
    return out


def last_polarity(rec: Recording) -> np.ndarray:
    """(F, P) int8: the polarity of each pixel's last event before each exposure midpoint (0: none yet)."""
    ev = rec.events
    P = rec.width * rec.height
    pix = pixel_index(ev, rec.width)
    out = np.zeros((len(rec.t_mid), P), np.int8)
    cur = np.zeros(P, np.int8)
    bounds = np.searchsorted(ev.t, rec.t_mid, side="left")
    prev = 0
    for k, b in enumerate(bounds):
        if b > prev:   # events are time-sorted: keep each pixel's last one
            seg_pix = pix[prev:b][::-1]
            u, first = np.unique(seg_pix, return_index=True)
            cur[u] = ev.p[prev:b][::-1][first]
        out[k] = cur
        prev = b
    return out
