"""`ev3dgs-sim compare`: re-simulate a recording's events from its own APS frames and hold them against the
real events.

Re-simulation. The APS frames, their noise taken out of static stretches (denoise_frames), as linear
intensity (DN - dark) / (full scale - dark), are fed to the DVS simulator at their exposure midpoints; the
simulator moves each pixel's log intensity linearly between two frames, so the scene is interpolated in log
space between exposure midpoints. The frame rate limits what can be compared: whatever happens between two
frames (a reversal, an edge crossing several pixels, flicker) is replaced by a straight line in log
intensity, event timing inside a frame interval is the interpolation's, not the scene's. So the comparison
is made per frame pair (counts), on static regions (noise), and in distributions (polarity, inter-event
intervals), not event by event.

Metrics (real vs simulated), all between the first and last exposure midpoint:

* count maps: per pixel and frame pair ON and OFF counts; Pearson correlation over all (pair, pixel) cells,
  pixels and 8x8 blocks, and the ratio of the totals (simulated / real). Hot pixels of the real recording are
  left out of both (the simulator has no hot-pixel model; they are listed apart).
* background activity: the ON and OFF rate of static pixels (APS log intensity spans less than 0.1 plus 6
  frame-noise standard deviations, with all 8 neighbours; one mask for every config), and the relative error
  of the simulated total rate.
* polarity balance: ON / (ON + OFF).
* event rate over time, per frame interval, and its correlation.
* inter-event-interval histograms (same pixel, log bins 10 us - 10 s) and the Kolmogorov-Smirnov distance of
  log intervals.
* hot pixels: found in the real and in the simulated events with the same test (ev3dgs.calib.noise).
"""
from __future__ import annotations

import re
from dataclasses import replace

import numpy as np

from ..errors import InputError
from ..events import Events
from .aps import Recording, load_recording, pair_counts, pixel_index

STATIC_C = 0.2          # the static mask: APS log span below 0.5 * STATIC_C (+ frame noise)
BLOCK = 8
IEI_BINS = np.logspace(1, 7, 49)
_DARK = re.compile(r"^#\s*aps_dark_dn\s*=\s*([-+0-9.eE]+)", re.M)


def dark_from_toml(path, cfg=None) -> float | None:
    """The APS dark level of a sensor TOML: its [aps] dark_dn (`cfg`, the loaded SimConfig), else, in files
    `calibrate` wrote before that key, the comment `# aps_dark_dn = X` (with a note; a value that is not a
    finite number in the key's range is a ConfigError), else None."""
    import math
    import warnings

    from ..errors import ConfigError
    from ..sensor import RANGES

    if cfg is not None and cfg.aps is not None:
        return cfg.aps.dark_dn
    try:
        with open(path, encoding="utf-8") as f:
            m = _DARK.search(f.read())
    except (OSError, UnicodeDecodeError):
        return None                      # load_sim_config has read it already: nothing more to find
    if not m:
        return None
    try:
        v = float(m.group(1))
    except ValueError:
        v = math.nan
    lo, hi = RANGES["dn"]
    if not lo <= v <= hi:
        raise ConfigError(f"{path}: '# aps_dark_dn = {m.group(1)}' is not a dark level in DN in [{lo:g}, {hi:g}]; "
                          "write it as [aps] dark_dn = X")
    warnings.warn(f"{path}: the APS dark level ({v:g} DN) is read from the '# aps_dark_dn' comment of an older "
                  "calibrate file; [aps] dark_dn = X is the key now")
    return v


HOLD_SIGMAS = 4.0       # denoise_frames: a change below this many frame-noise s.d. is not a change


def denoise_frames(rec: Recording, sigmas: float = HOLD_SIGMAS) -> np.ndarray:
    """(F, H, W) DN with the APS frame noise taken out of static stretches, so that the re-simulation's
    static pixels do not fire on frame noise (the real sensor never sees it).

    Method: per pixel, consecutive frames form one stretch while each new frame lies within `sigmas` frame-
    noise standard deviations of the stretch's running mean (the noise of the mean included: sigma
    sqrt(1 + 1/n)); every frame of a stretch is replaced by the stretch's mean. The noise is the measured one
    (thresholds.frame_noise, by intensity). Why this and not a temporal low-pass: a low-pass also smooths
    real changes and spreads an edge's events over several frame intervals; here a change larger than the
    noise passes at once and whole, a static pixel becomes exactly constant (no event but the sensor's own
    noise), and a slow drift still arrives, in steps of a few noise s.d. At 4 s.d. a static pixel breaks its
    stretch by noise alone with probability 6e-5 per frame."""
    from .thresholds import frame_noise

    F = rec.frames
    n_f = len(F)
    X = F.reshape(n_f, -1)
    centres, noise = frame_noise(rec)
    label = np.zeros(X.shape, np.int64)
    s, n = X[0].copy(), np.ones(X.shape[1])
    for f in range(1, n_f):
        m = s / n
        brk = np.abs(X[f] - m) > sigmas * np.interp(m, centres, noise) * np.sqrt(1 + 1 / n)
        label[f] = label[f - 1] + brk
        s = np.where(brk, X[f], s + X[f])
        n = np.where(brk, 1.0, n + 1)
    P = X.shape[1]
    key = label * P + np.arange(P)[None, :]
    u, inv = np.unique(key.ravel(), return_inverse=True)
    means = np.bincount(inv, weights=X.ravel()) / np.bincount(inv)
    return means[inv].reshape(F.shape)


def resimulate(rec: Recording, cfg, dark: float = 0.0, seed: int = 0, denoise: bool = True) -> Events:
    """The simulator's events from the recording's APS frames (linear, fed at the exposure midpoints), the
    frames' noise taken out of static stretches first (denoise_frames; denoise=False: as recorded)."""
    from dataclasses import replace as _replace

    from ..sim.dvs import simulate_events

    if denoise:
        rec = _replace(rec, frames=denoise_frames(rec))
    frames = rec.intensity(dark).astype(np.float32)
    ev = simulate_events(frames, rec.t_mid, cfg.dvs, seed=seed, isp=cfg.isp)
    return Events(ev.t, ev.x, ev.y, ev.p)


def _corr(a: np.ndarray, b: np.ndarray) -> float | None:
    a, b = np.asarray(a, float).ravel(), np.asarray(b, float).ravel()
    if len(a) < 3 or a.std() == 0 or b.std() == 0:
        return None
    return float(np.corrcoef(a, b)[0, 1])


def _blocks(x: np.ndarray, H: int, W: int) -> np.ndarray:
    """(..., P) -> (..., blocks) sums over BLOCK x BLOCK tiles (edges cropped)."""
    h, w = H // BLOCK, W // BLOCK
    y = x.reshape(*x.shape[:-1], H, W)[..., :h * BLOCK, :w * BLOCK]
    return y.reshape(*x.shape[:-1], h, BLOCK, w, BLOCK).sum((-3, -1)).reshape(*x.shape[:-1], h * w)


def _iei(ev: Events, width: int, exclude: np.ndarray) -> np.ndarray:
    pix = pixel_index(ev, width)
    keep = ~exclude[pix]
    pix, t = pix[keep], ev.t[keep]
    o = np.lexsort((t, pix))
    pix, t = pix[o], t[o]
    same = pix[1:] == pix[:-1]
    return np.diff(t)[same]


def _ks(a: np.ndarray, b: np.ndarray) -> float | None:
    if len(a) < 10 or len(b) < 10:
        return None
    from scipy.stats import ks_2samp

    return float(ks_2samp(np.log10(np.maximum(a, 1)), np.log10(np.maximum(b, 1))).statistic)


def _hot(rec: Recording, ev: Events, dark: float, knee: float, c_on: float, c_off: float, static) -> list:
    from .noise import hot_pixels, window_counts

    r = replace(rec, events=ev)
    on, off, T = window_counts(r)
    return hot_pixels(r, on, off, T, (dark, knee), c_on, c_off, static)


def compare(rec: Recording, cfg, dark: float = 0.0, seed: int = 0, sim: Events | None = None,
            denoise: bool = True) -> dict:
    """Numbers of the comparison (see the module doc); `sim` = already re-simulated events."""
    from .noise import static_mask

    if not 0 <= dark < rec.full_scale - 1:
        raise InputError(f"APS dark level {dark} DN is outside [0, {rec.full_scale - 1:g})")
    if rec.width < BLOCK or rec.height < BLOCK:
        raise InputError(f"{rec.path}: a {rec.width}x{rec.height} sensor is too small to compare: the count maps "
                         f"are compared in {BLOCK}x{BLOCK} blocks")
    sim = resimulate(rec, cfg, dark, seed, denoise) if sim is None else sim
    srec = replace(rec, events=sim)
    H, W, P = rec.height, rec.width, rec.width * rec.height
    T = (rec.t_mid[-1] - rec.t_mid[0]) * 1e-6
    dt_ms = float(np.median(np.diff(rec.t_mid))) / 1e3
    from ..logmap import DEFAULT_LOG_KNEE

    static = static_mask(rec, (dark, DEFAULT_LOG_KNEE), STATIC_C)
    hot_mask, hot_list = _hot(rec, rec.events, dark, cfg.dvs.log_knee, cfg.dvs.pos_threshold,
                              cfg.dvs.neg_threshold, static)
    sim_hot_mask, sim_hot = _hot(rec, sim, dark, cfg.dvs.log_knee, cfg.dvs.pos_threshold, cfg.dvs.neg_threshold,
                                 static)
    keep = ~hot_mask
    static = static & keep
    r_on, r_off = pair_counts(rec)
    s_on, s_off = pair_counts(srec)
    out: dict = {"recording": rec.path, "width": W, "height": H, "frames": int(len(rec.t_mid)),
                 "frame_interval_ms": dt_ms, "seconds": float(T), "aps_dark_dn": float(dark),
                 "real_events": int(r_on.sum() + r_off.sum()), "sim_events": int(s_on.sum() + s_off.sum()),
                 "limits": (f"the simulation sees the scene only through {len(rec.t_mid)} APS frames, one every "
                            f"{dt_ms:.1f} ms, interpolated linearly in log intensity between exposure midpoints: "
                            "changes between frames (reversals, fast edges, flicker) are not simulated, event "
                            "times inside a frame interval are the interpolation's (APS frame noise is taken out of "
                            "static stretches first); so counts are compared per frame pair, not event by event")}
    cm = {}
    for name, r, s in (("on", r_on, s_on), ("off", r_off, s_off), ("all", r_on + r_off, s_on + s_off)):
        r, s = r[:, keep], s[:, keep]
        full_r = np.zeros((len(r), P))
        full_s = np.zeros((len(s), P))
        full_r[:, keep], full_s[:, keep] = r, s
        rb, sb = _blocks(full_r, H, W), _blocks(full_s, H, W)
        cm[name] = {"corr_pair_pixel": _corr(r, s), "corr_pixel_total": _corr(r.sum(0), s.sum(0)),
                    "corr_pair_block8": _corr(rb, sb), "real": int(r.sum()), "sim": int(s.sum()),
                    "ratio_sim_real": float(s.sum() / r.sum()) if r.sum() else None}
    out["count_maps"] = cm
    ns = int(static.sum())
    ev_r, ev_s = rec.events, sim

    def rates(ev):
        m = (ev.t >= rec.t_mid[0]) & (ev.t < rec.t_mid[-1])
        pix = pixel_index(ev, W)[m]
        on = np.bincount(pix[ev.p[m] > 0], minlength=P)[static].sum()
        off = np.bincount(pix[ev.p[m] < 0], minlength=P)[static].sum()
        return float(on / max(ns, 1) / T), float(off / max(ns, 1) / T)

    ron, roff = rates(ev_r)
    son, soff = rates(ev_s)
    real_ba = ron + roff
    out["background"] = {"static_pixels": ns, "real_on_hz": ron, "real_off_hz": roff, "sim_on_hz": son,
                         "sim_off_hz": soff, "real_hz": real_ba, "sim_hz": son + soff,
                         "rel_error": float((son + soff - real_ba) / real_ba) if real_ba > 0 else None,
                         "abs_log10_ratio": (float(abs(np.log10((son + soff) / real_ba)))
                                             if real_ba > 0 and son + soff > 0 else None)}

    def balance(on, off):
        n = on.sum() + off.sum()
        return float(on.sum() / n) if n else None

    out["polarity_on_fraction"] = {"real": balance(r_on[:, keep], r_off[:, keep]),
                                   "sim": balance(s_on[:, keep], s_off[:, keep])}
    rr = (r_on[:, keep].sum(1) + r_off[:, keep].sum(1)) / (np.diff(rec.t_mid) * 1e-6)
    sr = (s_on[:, keep].sum(1) + s_off[:, keep].sum(1)) / (np.diff(rec.t_mid) * 1e-6)
    out["rate_over_time"] = {"t_s": (((rec.t_mid[:-1] + rec.t_mid[1:]) / 2 - rec.t_mid[0]) * 1e-6).tolist(),
                             "real_hz": rr.tolist(), "sim_hz": sr.tolist(), "corr": _corr(rr, sr)}
    ir, is_ = _iei(ev_r, W, hot_mask), _iei(ev_s, W, hot_mask)
    hr = np.histogram(ir, IEI_BINS)[0]
    hs = np.histogram(is_, IEI_BINS)[0]
    out["iei"] = {"bins_us": IEI_BINS.tolist(), "real": hr.tolist(), "sim": hs.tolist(),
                  "real_median_us": float(np.median(ir)) if len(ir) else None,
                  "sim_median_us": float(np.median(is_)) if len(is_) else None,
                  "ks_log10": _ks(ir, is_)}
    out["hot_pixels"] = {"real": len(hot_list), "sim": len(sim_hot), "real_list": [list(h) for h in hot_list[:100]]}
    tot_r = np.where(keep, r_on.sum(0) + r_off.sum(0), 0)
    tot_s = np.where(keep, s_on.sum(0) + s_off.sum(0), 0)
    out["_maps"] = (r_on.sum(0) - r_off.sum(0), s_on.sum(0) - s_off.sum(0), keep,
                    _blocks(tot_r[None], H, W)[0], _blocks(tot_s[None], H, W)[0])
    return out


def figure(res: dict, path, title: str = "") -> None:
    """One figure, real vs simulated: net count maps, per-pixel counts, rate over time, IEI histograms,
    background rates (`draw`), written to `path`."""
    import matplotlib.pyplot as plt

    fig = draw(res, title)
    fig.savefig(path, dpi=90)
    plt.close(fig)


def draw(res: dict, title: str = ""):
    """The matplotlib Figure (Agg) `figure` writes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .. import palette   # the polarity colours of every figure: ON red, OFF blue

    H, W = res["height"], res["width"]
    net_r, net_s, keep, blk_r, blk_s = res["_maps"]
    fig, ax = plt.subplots(2, 3, figsize=(15, 8.5), constrained_layout=True)
    lim = max(1.0, float(np.percentile(np.abs(net_r[keep]), 99.5)))
    for a, m, name in ((ax[0, 0], net_r, "real"), (ax[0, 1], net_s, "simulated")):
        im = a.imshow(np.where(keep, m, 0).reshape(H, W), cmap=palette.net_colormap(), vmin=-lim, vmax=lim,
                      interpolation="nearest")
        a.set_title(f"{name}: ON - OFF events per pixel")
        a.axis("off")
    bar = fig.colorbar(im, ax=ax[0, 1], shrink=0.8)
    bar.set_label(f"ON - OFF events ({palette.ON_NAME}: more ON, {palette.OFF_NAME}: more OFF)")
    cm = res["count_maps"]["all"]
    a = ax[0, 2]
    a.loglog(blk_r + 1, blk_s + 1, ".", ms=3, alpha=0.5)
    top = max(float(blk_r.max()), float(blk_s.max()), 1.0) + 1
    a.plot([1, top], [1, top], "k:", lw=1)
    a.set_xlabel(f"real events + 1 per {BLOCK}x{BLOCK} block")
    a.set_ylabel("simulated events + 1")
    cpp, cb = cm["corr_pair_pixel"], cm["corr_pair_block8"]
    a.set_title("count maps per frame pair:\nr = " + (f"{cpp:.2f} (pixels), " if cpp is not None else "- , ") +
                (f"{cb:.2f} ({BLOCK}x{BLOCK} blocks)" if cb is not None else "-"), fontsize=10)
    rt = res["rate_over_time"]
    a = ax[1, 0]
    ts = np.asarray(rt["t_s"])
    a.plot(ts, np.asarray(rt["real_hz"]) / 1e3, label="real")
    a.plot(ts, np.asarray(rt["sim_hz"]) / 1e3, label="simulated")
    a.set_xlabel("time (s)")
    a.set_ylabel("event rate (k events/s), per frame interval")
    a.legend()
    c = rt["corr"]
    a.set_title(f"event rate: r = {c:.2f}" if c is not None else "event rate")
    ie = res["iei"]
    a = ax[1, 1]
    b = np.asarray(ie["bins_us"])
    for key, lab in (("real", "real"), ("sim", "simulated")):
        h = np.asarray(ie[key], float)
        a.stairs(h / max(h.sum(), 1), b, label=lab)
    a.set_xscale("log")
    a.axvline(res["frame_interval_ms"] * 1e3, color="k", ls=":", lw=1, label="frame interval")
    a.set_xlabel("same-pixel inter-event interval (us)")
    a.set_ylabel("fraction")
    ks = ie["ks_log10"]
    a.set_title(f"inter-event intervals: KS = {ks:.2f}" if ks is not None else "inter-event intervals")
    a.legend()
    bg = res["background"]
    a = ax[1, 2]
    x = np.arange(2)
    a.bar(x - 0.2, [bg["real_on_hz"], bg["real_off_hz"]], 0.4, label="real")
    a.bar(x + 0.2, [bg["sim_on_hz"], bg["sim_off_hz"]], 0.4, label="simulated")
    a.set_xticks(x, ["ON", "OFF"])
    a.set_ylabel("Hz per static pixel")
    a.set_title(f"background activity ({bg['static_pixels']} static pixels)")
    a.legend()
    palette.fit_suptitle(fig, title or res["recording"], fontsize=10)
    return fig


def public(res: dict) -> dict:
    return {k: v for k, v in res.items() if not k.startswith("_")}


def compare_recording(path, cfg, dark: float = 0.0, seed: int = 0, rec: Recording | None = None) -> dict:
    rec = load_recording(path) if rec is None else rec
    return compare(rec, cfg, dark=dark, seed=seed)
