"""Study: how well `ev3dgs-sim calibrate` recovers known sensor settings, and how close `compare` comes on
real recordings.

synthetic: recordings made with ev3dgs.calib.synth (known thresholds, mismatch, leak, shot noise, refractory
period, hot pixels; 25 fps APS frames with read and photon noise) over several seeds; per parameter the
relative error of each seed and the bootstrap standard error calibrate reports for it.

    python tools/studies/study_calibrate.py synthetic [--seeds 6] --json tools/results/study_calibrate.json \\
        --plot tools/results/study_calibrate.png

record: recordings made with `ev3dgs-sim record` (Blender, 250 Hz rendering) of the lego scene with 1.6 deg
shake at 173x130, 25 fps APS frames with 10 ms exposure, for the sensors A, B, C and A without mismatch
(SENSORS); the rendered frames are cached per seed and duration and shared by the four sensors (the
rendering does not depend on the sensor), so each extra sensor costs only its event simulation.

    python tools/studies/study_calibrate.py record --seconds 2 --seeds 1 --sensors A C \\
        --json tools/results/study_calibrate_record.json [--work DIR]

ablate: one sensor factor at a time on the same frames. From the render cache that `record` keeps in --work
(no Blender), re-simulate the events of sensors A, B, C with only their thresholds, with one effect added,
without the mismatch and whole (the whole sensor reproduces the recording's event count), fit the thresholds
at the true APS curve (dark 0, the simulator's knee) without bootstrap; and compare the APS log changes with
the DVS's own log intensity at the exposure midpoints.

    python tools/studies/study_calibrate.py ablate --work DIR --json tools/results/study_calibrate_ablation.json

real: calibrate each real recording, then compare (a) the calibrated config, (b) the simulator's default,
(c) v2e's clean and (d) noisy presets (ev3dgs.sim.presets) on it; the same APS dark level for all four.

    python tools/studies/study_calibrate.py real RECORDING.aedat4 [...] --json tools/results/calibrate_real.json \\
        --figures DIR
"""
from __future__ import annotations

import os
import sys
from pathlib import Path

os.environ.setdefault("NUMBA_NUM_THREADS", "1")
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tools/: pareto.py
from pareto import save_json  # noqa: E402

from ev3dgs.calib.report import calibrate_recording, to_toml  # noqa: E402
from ev3dgs.calib.synth import Truth, make_recording  # noqa: E402
from ev3dgs.errors import InputError  # noqa: E402

PARAMS = [  # (name, truth attribute, getter on a Calibration)
    ("pos_threshold", "pos_threshold", lambda c: c.thresholds.c_on),
    ("neg_threshold", "neg_threshold", lambda c: c.thresholds.c_off),
    ("mismatch_sigma", "sigma", lambda c: c.thresholds.sigma),
    ("leak_hz", "leak_hz", lambda c: c.noise.leak_hz),
    ("shot_noise_hz", "shot_hz", lambda c: c.noise.shot_hz),
    ("white_fraction", "white_fraction", lambda c: c.noise.white_fraction),
    ("refractory_us", "refractory_us", lambda c: c.noise.refractory_us),
    ("aps_dark_dn", "dark_dn", lambda c: c.thresholds.dark),
]
# the sensors: (ON, OFF threshold, mismatch as a share of the mean threshold, refractory us, leak Hz,
# shot noise Hz); the simulator draws both polarities' thresholds with one absolute sigma
RECORD_FPS, RECORD_EXPOSURE_MS, RECORD_RENDER_HZ = 25, 10, 250   # the record mode's camera

SENSORS = {
    "A": (0.15, 0.25, 0.15, 200.0, 0.1, 2.0),
    "B": (0.3, 0.3, 0.25, 500.0, 0.5, 0.5),
    "C": (0.4, 0.2, 0.40, 1000.0, 0.05, 5.0),
    "A0": (0.15, 0.25, 0.0, 200.0, 0.1, 2.0),
}
TOL = {"pos_threshold": 0.10, "neg_threshold": 0.10, "mismatch_sigma": 0.25, "leak_hz": 0.25,
       "shot_noise_hz": 0.25, "white_fraction": None, "refractory_us": 0.20, "aps_dark_dn": None}


def synthetic(args) -> dict:
    truth = Truth()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in range(1, args.seeds + 1):
            t0 = time.perf_counter()
            path = Path(tmp) / f"syn{seed}.aedat4"
            make_recording(path, truth, seed=seed, seconds=args.seconds)
            cal = calibrate_recording(path, boot=args.bootstrap, seed=seed)
            row = {"seed": seed, "seconds": time.perf_counter() - t0}
            for name, attr, get in PARAMS:
                v = get(cal)
                row[name] = {"value": v.value, "se": v.se, "truth": getattr(truth, attr)}
            hot = sorted((x, y) for x, y, _ in cal.noise.hot)
            row["hot_pixels_found"] = hot == sorted(truth.hot)
            rows.append(row)
            print(f"seed {seed}: " + ", ".join(f"{n} {row[n]['value']:.4g}" if row[n]["value"] is not None else
                                                f"{n} -" for n, _, _ in PARAMS), flush=True)
    summary = {}
    for name, attr, _ in PARAMS:
        tv = getattr(truth, attr)
        vals = np.array([r[name]["value"] for r in rows if r[name]["value"] is not None], float)
        ses = np.array([r[name]["se"] for r in rows if r[name]["value"] is not None and r[name]["se"] is not None])
        rel = (vals - tv) / tv if tv else vals - tv
        summary[name] = {"truth": tv, "estimated_in": int(len(vals)), "of": len(rows),
                         "mean": float(vals.mean()) if len(vals) else None,
                         "seed_sd": float(vals.std(ddof=1)) if len(vals) > 1 else None,
                         "mean_rel_error": float(rel.mean()) if len(vals) else None,
                         "max_abs_rel_error": float(np.abs(rel).max()) if len(vals) else None,
                         "mean_bootstrap_se": float(ses.mean()) if len(ses) else None,
                         "bias_in_se": (float((vals.mean() - tv) / ses.mean()) if len(ses) and ses.mean() > 0
                                        else None),
                         "tolerance": TOL[name]}
    return {"truth": {k: v for k, v in vars(truth).items() if k != "hot"}, "seeds": rows, "summary": summary,
            "settings": {"seconds": args.seconds, "bootstrap": args.bootstrap, "fps": 25, "exposure_us": 5000,
                         "size": "64x48"}}


def sensor_dvs(name: str):
    from ev3dgs.sim.config import DVSConfig, Leak, Refractory, ShotNoise, ThresholdMismatch

    on, off, share, refr, leak, shot = SENSORS[name]
    return DVSConfig(pos_threshold=on, neg_threshold=off,
                     threshold_mismatch=ThresholdMismatch(sigma=share * (on + off) / 2) if share else None,
                     refractory=Refractory(period_us=refr), leak=Leak(rate_hz=leak), shot_noise=ShotNoise(rate_hz=shot))


def record_mode(args) -> dict:
    """Record (Blender) and calibrate; per sensor and seed the estimates against the truth."""
    import dataclasses
    import shutil

    from ev3dgs.cli.sim import scene_toml
    from ev3dgs.sim.record import record
    from ev3dgs.sim.scenes import ShakeSpec, load_scene

    work = Path(args.work or tempfile.mkdtemp(prefix="study-calibrate-"))
    work.mkdir(parents=True, exist_ok=True)
    rows = []
    base = load_scene(args.scene)
    for seed in range(1, args.seeds + 1):
        for name in args.sensors:
            t0 = time.perf_counter()
            dvs = sensor_dvs(name)
            spec = dataclasses.replace(base, shake=dataclasses.replace(base.shake, rotation_deg=args.shake_deg),
                                       sensor=dataclasses.replace(base.sensor, dvs=dvs))
            scene = work / f"scene_{name}.toml"
            scene.write_text(scene_toml(spec), encoding="utf-8")
            # one output name per (seed, duration): the render cache beside it is shared by every sensor
            out = work / f"rec_s{seed}_{args.seconds:g}s.aedat4"
            final = work / f"rec_{name}_s{seed}_{args.seconds:g}s.aedat4"
            if not final.exists():
                info = record(str(scene), out, seconds=args.seconds, fps=RECORD_FPS,
                              exposure_ms=RECORD_EXPOSURE_MS, render_rate_hz=RECORD_RENDER_HZ, width=173, height=130,
                              samples=args.samples, seed=seed, keep_cache=True,
                              quiet=False)
                shutil.move(out, final)
                print(f"{name} seed {seed}: recorded {info['events']} events, {info['frames']} frames "
                      f"({info['rendered_now']} rendered now) in {time.perf_counter() - t0:.0f} s", flush=True)
            if args.record_only:
                continue
            t1 = time.perf_counter()
            try:
                cal = calibrate_recording(final, boot=args.bootstrap, seed=seed)
            except InputError as e:   # a recording calibrate refuses is a result, not the end of the study
                rows.append({"sensor": name, "seed": seed, "seconds": args.seconds, "error": str(e)})
                print(f"{name} seed {seed}: calibrate refused: {e}", flush=True)
                continue
            on, off, share, refr, leak, shot = SENSORS[name]
            truth = {"pos_threshold": on, "neg_threshold": off, "mismatch_sigma": share * (on + off) / 2,
                     "refractory_us": refr, "leak_hz": leak, "shot_noise_hz": shot}
            row = {"sensor": name, "seed": seed, "seconds": args.seconds, "events": len(cal.rec.events),
                   "calibrate_s": time.perf_counter() - t1, "hot_pixels": len(cal.noise.hot)}
            for pname, _, get in PARAMS:
                if pname in truth:
                    v = get(cal)
                    row[pname] = {"value": v.value, "se": v.se, "truth": truth[pname], "note": v.note}
            rows.append(row)
            print(f"{name} seed {seed}: " + ", ".join(
                f"{k} {row[k]['value']:.4g} (truth {row[k]['truth']:g})" if row[k]["value"] is not None
                else f"{k} - ({row[k]['note'][:60]})" for k in truth) + f", hot {row['hot_pixels']}", flush=True)
    return {"rows": rows, "settings": {"scene": args.scene, "shake_deg": args.shake_deg, "seconds": args.seconds,
                                       "size": "173x130", "fps": RECORD_FPS, "exposure_ms": RECORD_EXPOSURE_MS,
                                       "render_rate_hz": RECORD_RENDER_HZ,
                                       "samples": args.samples, "bootstrap": args.bootstrap},
            "sensors": {k: dict(zip(("pos", "neg", "mismatch_share", "refractory_us", "leak_hz", "shot_hz"), v))
                        for k, v in SENSORS.items()}}


ABLATIONS = {  # variant -> which effects of the sensor stay on
    "thresholds only": (),
    "refractory only": ("refractory",),
    "shot noise only": ("shot_noise",),
    "leak only": ("leak",),
    "mismatch only": ("threshold_mismatch",),
    "without mismatch": ("refractory", "shot_noise", "leak"),
    "full": ("threshold_mismatch", "refractory", "shot_noise", "leak"),
}


def _fail(message: str):
    print(f"error: {message}", file=sys.stderr)
    raise SystemExit(2)


def _cached_render(work: Path, seed: int, seconds: float):
    """The rendered linear frames `record` cached for (seed, duration) and their times (us, as `record`
    simulates them: 250 Hz over the recording, 25 fps frames of 10 ms)."""
    from ev3dgs.sim.record import EPOCH_US, timeline

    caches = sorted(work.glob(f".rec_s{seed}_{seconds:g}s.cache-*"))
    if not caches:
        _fail(f"no render cache .rec_s{seed}_{seconds:g}s.cache-* in {work} (run record first)")
    files = sorted(caches[0].glob("traj_*.npz"))
    frames = np.concatenate([np.load(f)["frames"] for f in files])
    t_rel = timeline(seconds, RECORD_FPS, RECORD_EXPOSURE_MS, RECORD_RENDER_HZ)[3]
    if len(t_rel) != len(frames):
        _fail(f"the render cache has {len(frames)} frames, the recording needs {len(t_rel)}")
    return frames, EPOCH_US + t_rel


def dvs_vs_aps(rec, frames, t_abs, knee: float) -> dict:
    """The APS log change of each frame pair (well exposed, |change| > 0.1) against the DVS's own: the log of
    the rendered frames' luminance (what the simulator's pixels see, without the camera's ISP and 8-bit
    readout), linear in time between rendered frames as the simulator takes it, at the exposure midpoints."""
    from ev3dgs.calib.thresholds import log_intensity
    from ev3dgs.logmap import safe_log
    from ev3dgs.sim.dvs import luminance

    L = np.stack([safe_log(luminance(f), knee) for f in frames]).reshape(len(frames), -1).astype(np.float64)
    tm = rec.t_mid.astype(np.float64)
    ta = t_abs.astype(np.float64)
    j = np.clip(np.searchsorted(ta, tm) - 1, 0, len(ta) - 2)
    w = ((tm - ta[j]) / (ta[j + 1] - ta[j]))[:, None]
    d_dvs = np.diff(L[j] * (1 - w) + L[j + 1] * w, axis=0)
    d_aps = np.diff(log_intensity(rec.frames.reshape(len(tm), -1), 0.0, knee, rec.full_scale), axis=0)
    v = rec.valid(0.0).reshape(len(tm), -1)
    m = v[1:] & v[:-1] & (np.abs(d_aps) > 0.1)
    return {"pairs": int(m.sum()), "corr": float(np.corrcoef(d_aps[m], d_dvs[m])[0, 1]),
            "dvs_over_aps_up": float(d_dvs[m & (d_aps > 0)].sum() / d_aps[m & (d_aps > 0)].sum()),
            "dvs_over_aps_down": float(d_dvs[m & (d_aps < 0)].sum() / d_aps[m & (d_aps < 0)].sum())}


def ablate(args) -> dict:
    """Thresholds fitted on re-simulations of the same rendered frames with sensor factors switched off."""
    import dataclasses

    from ev3dgs.calib.aps import load_recording, pair_counts
    from ev3dgs.calib.thresholds import fit_thresholds
    from ev3dgs.logmap import DEFAULT_LOG_KNEE
    from ev3dgs.sim.dvs import DVSSimulator
    from ev3dgs.sim.scenes import load_scene

    work = Path(args.work)
    frames, t_abs = _cached_render(work, args.seed, args.seconds)
    isp = load_scene(args.scene).sensor.isp
    out = {"variants": [], "settings": {"seed": args.seed, "seconds": args.seconds, "scene": args.scene,
                                        "curve": [0.0, DEFAULT_LOG_KNEE], "bootstrap": 0}}
    rec = None
    for name in args.sensors:
        path = work / f"rec_{name}_s{args.seed}_{args.seconds:g}s.aedat4"
        if not path.is_file():
            _fail(f"no recording {path} (run record first)")
        if rec is None:
            rec = load_recording(path)          # the APS frames do not depend on the sensor
            out["dvs_vs_aps"] = dvs_vs_aps(rec, frames, t_abs, DEFAULT_LOG_KNEE)
            print(f"DVS vs APS log changes: {out['dvs_vs_aps']}", flush=True)
        full = sensor_dvs(name)
        for variant, keep in ABLATIONS.items():
            if variant == "mismatch only" and full.threshold_mismatch is None:
                continue
            t0 = time.perf_counter()
            dvs = dataclasses.replace(full, **{k: getattr(full, k) if k in keep else None for k in
                                               ("threshold_mismatch", "refractory", "shot_noise", "leak")})
            sim = DVSSimulator(frames.shape[1], frames.shape[2], dvs, seed=args.seed, isp=isp)
            ev = sim.feed(frames, t_abs)
            r = dataclasses.replace(rec, events=ev)
            on, off = pair_counts(r)
            R = dvs.refractory.period_us if dvs.refractory else 0.0
            th = fit_thresholds(r, on, off, boot=0, seed=args.seed, curve=(0.0, DEFAULT_LOG_KNEE), refractory_us=R)
            row = {"sensor": name, "variant": variant, "events": len(ev),
                   "pos_threshold": th.c_on.value, "neg_threshold": th.c_off.value,
                   "pos_error": th.c_on.value / full.pos_threshold - 1,
                   "neg_error": th.c_off.value / full.neg_threshold - 1,
                   "mismatch_sigma": th.sigma.value,
                   "mismatch_truth": dvs.threshold_mismatch.sigma if dvs.threshold_mismatch else 0.0,
                   "seconds": time.perf_counter() - t0}
            if variant == "full":
                row["recording_events"] = len(load_recording(path).events)
            out["variants"].append(row)
            print(f"{name} {variant}: C_on {100 * row['pos_error']:+.1f} %, C_off {100 * row['neg_error']:+.1f} %, "
                  f"mismatch {row['mismatch_sigma']} (truth {row['mismatch_truth']:g}), {len(ev)} events", flush=True)
    return out


def plot_synthetic(res: dict, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [n for n, _, _ in PARAMS]
    fig, ax = plt.subplots(figsize=(11, 4.8))
    for i, n in enumerate(names):
        tv = res["summary"][n]["truth"]
        for j, r in enumerate(res["seeds"]):
            v = r[n]
            if v["value"] is None:
                continue
            scale = tv if tv else 1.0
            x = i + (j - len(res["seeds"]) / 2) * 0.08
            ax.errorbar(x, 100 * (v["value"] - tv) / scale, yerr=100 * (v["se"] or 0) / scale, fmt="o", ms=4,
                        color=f"C{j}", label=f"seed {r['seed']}" if i == 0 else None)
        tol = TOL[n]
        if tol:
            ax.plot([i - 0.4, i + 0.4], [100 * tol] * 2, "k--", lw=0.8)
            ax.plot([i - 0.4, i + 0.4], [-100 * tol] * 2, "k--", lw=0.8)
    ax.axhline(0, color="grey", lw=0.8)
    ax.set_xticks(range(len(names)), [n.replace("_", "\n") for n in names], fontsize=8)
    ax.set_ylabel("error (% of truth; dark level: DN) +- bootstrap s.e.")
    ax.set_title("calibrate on synthetic recordings: error per seed (dashed: the issue's tolerance)")
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def real(args) -> dict:
    from ev3dgs.calib.aps import load_recording
    from ev3dgs.calib.compare import compare, figure, public
    from ev3dgs.sim.config import load_sim_config
    from ev3dgs.sim.presets import PRESETS

    out = {"recordings": {}}
    keys = ("corr_pair_pixel", "corr_pair_block8", "corr_pixel_total", "ratio_sim_real")
    for path in args.recordings:
        name = Path(path).stem
        t0 = time.perf_counter()
        cal = calibrate_recording(path, boot=args.bootstrap)
        text = to_toml(cal)
        rec = load_recording(path)
        with tempfile.TemporaryDirectory() as tmp:
            (Path(tmp) / "s.toml").write_text(text)
            configs = {"calibrated": load_sim_config(Path(tmp) / "s.toml"), **PRESETS}
        dark = float(cal.thresholds.dark.value)
        entry = {"calibration": cal.summary(), "sensor_toml": text, "seconds_calibrate": time.perf_counter() - t0,
                 "configs": {}}
        for cname, cfg in configs.items():
            res = compare(rec, cfg, dark=dark, seed=0)
            if args.figures:
                Path(args.figures).mkdir(parents=True, exist_ok=True)
                figure(res, Path(args.figures) / f"compare_{name}_{cname}.png",
                       title=f"{name}: real vs simulated ({cname})")
            pub = public(res)
            entry["limits"] = pub["limits"]
            entry["configs"][cname] = {
                "count_maps": {pol: {k: pub["count_maps"][pol][k] for k in keys} for pol in ("on", "off", "all")},
                "background": pub["background"], "polarity_on_fraction": pub["polarity_on_fraction"],
                "rate_corr": pub["rate_over_time"]["corr"], "iei_ks": pub["iei"]["ks_log10"],
                "iei_median_us": [pub["iei"]["real_median_us"], pub["iei"]["sim_median_us"]],
                "hot_pixels": pub["hot_pixels"]["real"], "sim_hot_pixels": pub["hot_pixels"]["sim"],
                "real_events": pub["real_events"], "sim_events": pub["sim_events"]}
            c = entry["configs"][cname]
            print(f"{name} {cname}: corr {c['count_maps']['all']['corr_pair_pixel']}, block {c['count_maps']['all']['corr_pair_block8']}, "
                  f"BA real {c['background']['real_hz']:.3g} sim {c['background']['sim_hz']:.3g} Hz, "
                  f"events {c['real_events']} / {c['sim_events']}", flush=True)
        out["recordings"][name] = entry
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="mode", required=True)
    s = sub.add_parser("synthetic")
    s.add_argument("--seeds", type=int, default=6)
    s.add_argument("--seconds", type=float, default=2.0)
    s.add_argument("--bootstrap", type=int, default=100)
    s.add_argument("--json", required=True)
    s.add_argument("--plot")
    c = sub.add_parser("record")
    c.add_argument("--seeds", type=int, default=2)
    c.add_argument("--seconds", type=float, default=2.0)
    c.add_argument("--sensors", nargs="+", default=list(SENSORS), choices=list(SENSORS))
    c.add_argument("--scene", default="lego")
    c.add_argument("--shake-deg", type=float, default=1.6)
    c.add_argument("--samples", type=int, default=8)
    c.add_argument("--bootstrap", type=int, default=100)
    c.add_argument("--record-only", action="store_true", help="record the recordings, calibrate nothing")
    c.add_argument("--work", help="folder for the recordings (kept; default: a new temporary folder)")
    c.add_argument("--json", required=True)
    b = sub.add_parser("ablate")
    b.add_argument("--work", required=True, help="the record mode's folder (recordings and render cache)")
    b.add_argument("--seed", type=int, default=1)
    b.add_argument("--seconds", type=float, default=2.0)
    b.add_argument("--sensors", nargs="+", default=["A", "B", "C"], choices=list(SENSORS))
    b.add_argument("--scene", default="lego")
    b.add_argument("--json", required=True)
    r = sub.add_parser("real")
    r.add_argument("recordings", nargs="+")
    r.add_argument("--bootstrap", type=int, default=100)
    r.add_argument("--json", required=True)
    r.add_argument("--figures", help="folder for one comparison figure per recording and config")
    a = p.parse_args()
    t0 = time.perf_counter()
    if a.mode == "synthetic":
        res = synthetic(a)
        res["seconds_total"] = time.perf_counter() - t0
        save_json(a.json, res)
        if a.plot:
            plot_synthetic(res, a.plot)
    elif a.mode == "ablate":
        res = ablate(a)
        res["seconds_total"] = time.perf_counter() - t0
        save_json(a.json, res)
    elif a.mode == "record":
        res = record_mode(a)
        res["seconds_total"] = time.perf_counter() - t0
        save_json(a.json, res)
    else:
        res = real(a)
        res["seconds_total"] = time.perf_counter() - t0
        save_json(a.json, res)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
