"""Study: how well `ev3dgs-sim calibrate` recovers known sensor settings, and how close `compare` comes on
real recordings.

synthetic: recordings made with ev3dgs.calib.synth (known thresholds, mismatch, leak, shot noise, refractory
period, hot pixels; 25 fps APS frames with read and photon noise) over several seeds; per parameter the
relative error of each seed and the bootstrap standard error calibrate reports for it.

    python tools/studies/study_calibrate.py synthetic [--seeds 6] --json tools/results/study_calibrate.json \\
        --plot tools/results/study_calibrate.png

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
    else:
        res = real(a)
        res["seconds_total"] = time.perf_counter() - t0
        save_json(a.json, res)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
