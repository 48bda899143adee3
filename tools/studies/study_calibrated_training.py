"""Study: does training with the calibrated sensor help? A 40 % threshold-mismatch sensor, calibrated, and
blur+event trained with the calibrated sensor model against the trainer's defaults.

1. The scene (default: lego, the demo's --quick dataset at 96x72: 10 shaky views of 17 sub-frames, 3 sharp
   test views) is made once with the TRUTH sensor (symmetric thresholds, a per-pixel threshold spread of
   40 % of the threshold, leak and shot noise, a refractory period): its events are what a camera with that
   sensor would give.
2. The same sensor is calibrated the way a user calibrates a camera: a calibration recording with APS frames
   (ev3dgs.calib.synth: a static ramp, a moving texture, a flash; 2 s, 64x48) made with it, fitted by
   `ev3dgs-sim calibrate` (ev3dgs.calib.report), and its TOML read as `ev3dgs-ingest davis --sensor` reads it
   (ev3dgs.calib.sensor.load_sensor_toml).
3. Three copies of the scene file differ only in the /events sensor attrs the trainer reads:
   * "calibrated": thresholds, mismatch, leak, shot noise and refractory period from the calibration;
   * "default": the noise-model attrs (mismatch_sigma, leak_rate_hz, shot_noise_rate_hz) absent and no
     simulator provenance of them, as a real recording ingested without --sensor: the trainer's defaults
     (10 % relative mismatch, no noise events); thresholds the sensor's nominal ones (a generous default: a
     user without calibration does not know them);
   * "truth": the simulator's own sensor (the file as made).
   Each is trained with blur+event (the noise norm, the studies' SH schedule and floor,
   bench_fidelity.study_overrides) on every seed; the sharp-frame oracle (trained on the sharp frames, it
   does not read the events) once per seed, as the upper bound.

    python tools/studies/study_calibrated_training.py --json tools/results/study_calibrated_training.json \\
        --plot tools/results/study_calibrated_training.png [--seeds 0 1] [--iterations 1000]

Options are this study's (the study config below and its command line), not product settings. Runs are
cached by settings and trainer code in --cache (bench_fidelity.run_one), so an interrupted study resumes.
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tools"))
sys.path.insert(0, str(ROOT / "tools" / "bench"))

from pareto import save_json  # noqa: E402


@dataclass(frozen=True)
class StudyConfig:
    """The truth sensor and the study's sizes."""

    scene: str = "lego"
    theta: float = 0.2                 # symmetric contrast threshold (the lego scene's)
    mismatch_share: float = 0.4        # per-pixel threshold spread as a share of theta
    leak_hz: float = 0.1
    shot_hz: float = 1.0
    refractory_us: float = 500.0
    calib_seconds: float = 2.0         # the calibration recording
    calib_bootstrap: int = 50
    calib_seed: int = 1
    init_points: int = 5000

    def dvs(self, base):
        from ev3dgs.sim.config import Leak, Refractory, ShotNoise, ThresholdMismatch

        return replace(base, pos_threshold=self.theta, neg_threshold=self.theta,
                       threshold_mismatch=ThresholdMismatch(sigma=self.mismatch_share * self.theta),
                       refractory=Refractory(period_us=self.refractory_us), leak=Leak(rate_hz=self.leak_hz),
                       shot_noise=ShotNoise(rate_hz=self.shot_hz))

    def truth(self):
        from ev3dgs.calib.synth import Truth

        return Truth(pos_threshold=self.theta, neg_threshold=self.theta, sigma=self.mismatch_share * self.theta,
                     leak_hz=self.leak_hz, shot_hz=self.shot_hz, refractory_us=self.refractory_us, hot=())


def make_scene(sc: StudyConfig, cache: Path) -> Path:
    """The scene made with the truth sensor (render cache kept beside it)."""
    from ev3dgs.sim.dataset import make_dataset
    from ev3dgs.sim.scenes import load_scene, resolve_render

    path = cache / "truth" / "scene.h5"
    if path.exists():
        return path
    path.parent.mkdir(parents=True, exist_ok=True)
    spec = load_scene(sc.scene)
    spec = replace(spec, sensor=replace(spec.sensor, dvs=sc.dvs(spec.sensor.dvs)))
    t = time.perf_counter()
    make_dataset(spec, resolve_render(spec, quick=True), path, seed=0, quiet=True, keep_cache=True)
    print(f"scene: {time.perf_counter() - t:.0f} s", flush=True)
    return path


def calibrate(sc: StudyConfig, cache: Path) -> tuple[Path, dict]:
    """Record the calibration recording with the truth sensor, calibrate it; (sensor TOML, summary)."""
    from ev3dgs.calib.report import calibrate_recording, to_toml
    from ev3dgs.calib.synth import make_recording

    rec, toml = cache / "calib.aedat4", cache / "calibrated.sensor.toml"
    if not rec.exists():
        make_recording(rec, sc.truth(), seed=sc.calib_seed, seconds=sc.calib_seconds)
    t = time.perf_counter()
    cal = calibrate_recording(rec, boot=sc.calib_bootstrap, seed=sc.calib_seed)
    toml.write_text(to_toml(cal), encoding="utf-8")
    s = cal.summary()
    s["calibrate_s"] = time.perf_counter() - t
    return toml, s


def with_sensor(src: Path, dst: Path, sensor) -> Path:
    """A copy of the scene file whose /events sensor attrs are `sensor`'s (an EventSensor; None: the noise
    model's attrs absent and the simulator provenance of the sensor removed, as in a real recording ingested
    without --sensor)."""
    import h5py

    from ev3dgs.schema import SENSOR_MODEL_ATTRS

    dst.parent.mkdir(parents=True, exist_ok=True)
    tmp = dst.with_suffix(".tmp.h5")
    shutil.copyfile(src, tmp)
    with h5py.File(tmp, "r+") as f:
        ea = f["events"].attrs
        if sensor is None:
            for k in SENSOR_MODEL_ATTRS:
                if k in ea:
                    del ea[k]
            config = json.loads(f.attrs["config"])
            config.get("sim", {}).pop("dvs", None)   # else the trainer reads the simulator's provenance
            f.attrs["config"] = json.dumps(config)
        else:
            ea["pos_threshold"], ea["neg_threshold"] = float(sensor.pos_threshold), float(sensor.neg_threshold)
            ea["refractory_us"] = float(sensor.refractory_us)
            for k in SENSOR_MODEL_ATTRS:
                ea[k] = float(getattr(sensor, k))
    tmp.replace(dst)
    return dst


def noise_model(scene: Path) -> dict:
    """The event noise model the trainer builds from the file (terms/events.sensor_model's record)."""
    from types import SimpleNamespace

    from ev3dgs import schema
    from ev3dgs.train.config import TrainConfig
    from ev3dgs.train.data import sensor_model as declared
    from ev3dgs.train.terms.events import sensor_model

    sc = schema.read(scene)
    d = SimpleNamespace(pos_threshold=sc.sensor.pos_threshold, neg_threshold=sc.sensor.neg_threshold,
                        **declared(sc.sensor, sc.config))
    return sensor_model(TrainConfig(scene=str(scene)), d)[2]


def _job(job: dict) -> dict:
    import torch

    from bench_fidelity import run_one

    torch.set_num_threads(1)
    t = time.perf_counter()
    m = run_one(Path(job["scene_path"]), job["overrides"], job["seed"], job["iterations"], job["init_points"],
                Path(job["out"]))
    return {"variant": job["variant"], "seed": job["seed"], "wall": time.perf_counter() - t,
            "blur_view": m["blur_view"]["psnr"], "novel_view": m["novel_view"]["psnr"]}


def summarise(runs: list[dict]) -> dict:
    out = {}
    for v in dict.fromkeys(r["variant"] for r in runs):
        rs = [r for r in runs if r["variant"] == v]
        out[v] = {}
        for view in ("blur_view", "novel_view"):
            x = np.array([r[view] for r in rs])
            out[v][view] = {"mean": float(x.mean()), "min": float(x.min()), "max": float(x.max()),
                            "sd": float(x.std(ddof=1)) if len(x) > 1 else None, "seeds": [float(y) for y in x]}
    return out


def plot(summary: dict, png: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
    names = list(summary)
    for ax, view in zip(axes, ("blur_view", "novel_view")):
        for i, n in enumerate(names):
            s = summary[n][view]
            ax.plot([i] * len(s["seeds"]), s["seeds"], "o", color=f"C{i}", alpha=0.6)
            ax.plot([i - 0.2, i + 0.2], [s["mean"]] * 2, "-", color=f"C{i}", lw=2)
        ax.set_xticks(range(len(names)), names, fontsize=8)
        ax.set_ylabel(f"{view.replace('_', ' ')} PSNR (dB)")
        ax.grid(alpha=0.3)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(png, dpi=100)
    plt.close(fig)


def main(argv=None) -> int:
    from bench_fidelity import study_overrides
    from study_event_term import VARIANTS

    from ev3dgs.calib.sensor import load_sensor_toml
    from ev3dgs.train.jobs import run_parallel

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--iterations", type=int, default=1000)
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--no-oracle", action="store_true", help="skip the sharp-frame oracle runs")
    ap.add_argument("--cache", default=str(ROOT / "tools/results/calibrated_training_cache"))
    ap.add_argument("--json", required=True)
    ap.add_argument("--plot")
    a = ap.parse_args(argv)
    sc = StudyConfig()
    cache = Path(a.cache)
    cache.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    truth = make_scene(sc, cache)
    toml, cal = calibrate(sc, cache)
    print("calibrated: " + ", ".join(f"{k} {cal[k]['value']}" for k in
                                     ("pos_threshold", "neg_threshold", "mismatch_sigma", "leak_hz",
                                      "shot_noise_hz", "refractory_us")), flush=True)
    files = {"calibrated": with_sensor(truth, cache / "calibrated" / "scene.h5", load_sensor_toml(toml)),
             "default": with_sensor(truth, cache / "default" / "scene.h5", None), "truth": truth}
    models = {k: noise_model(p) for k, p in files.items()}
    for k, m in models.items():
        print(f"{k}: {m}", flush=True)
    assert models["default"]["rel_mismatch_from"] == "default", models["default"]
    jobs = []
    for seed in a.seeds:
        for name, path in files.items():
            jobs.append(dict(variant=name, seed=seed, scene_path=str(path),
                             overrides=study_overrides(VARIANTS["blur+event"]), iterations=a.iterations,
                             init_points=sc.init_points, out=str(cache / "runs" / f"{name}_s{seed}")))
        if not a.no_oracle:
            jobs.append(dict(variant="sharp oracle", seed=seed, scene_path=str(truth),
                             overrides=study_overrides(VARIANTS["oracle"]), iterations=a.iterations,
                             init_points=sc.init_points, out=str(cache / "runs" / f"oracle_s{seed}")))

    def report(r):
        print(f"  {r['variant']:12s} seed {r['seed']}: blur view {r['blur_view']:.2f}, novel {r['novel_view']:.2f} "
              f"dB ({r['wall']:.0f} s)", flush=True)

    runs = run_parallel(_job, jobs, a.jobs, report)
    summary = summarise(runs)
    for v, s in summary.items():
        print(f"{v:12s} blur view {s['blur_view']['mean']:.2f} [{s['blur_view']['min']:.2f}, "
              f"{s['blur_view']['max']:.2f}], novel {s['novel_view']['mean']:.2f} [{s['novel_view']['min']:.2f}, "
              f"{s['novel_view']['max']:.2f}]", flush=True)
    res = {"settings": {**vars(a), "study": vars(sc)}, "calibration": cal, "noise_models": models,
           "summary": summary, "runs": runs, "seconds": time.perf_counter() - t0,
           "machine": "x86_64, 2 cores shared, one thread per run"}
    save_json(a.json, res)
    if a.plot:
        plot(summary, Path(a.plot), f"{sc.scene} 96x72, 40 % mismatch sensor, blur+event, {a.iterations} steps, "
                                    f"seeds {a.seeds}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
