"""Training settings (stored as config.json in the run folder)."""
from __future__ import annotations

import json
import re
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path

from ..config import check, from_dict
from ..errors import ConfigError

# Options a resumed run may change: they do not change the trained model (extending the run, how often it is
# saved, how many threads the rasterizer kernels use: results are bitwise the same for any thread count).
# Extending a run (--iterations on --resume) keeps every schedule as the run started it: schedule_length
# records the length the schedules were made for (learning-rate decays, densification, EDI anneal, pose
# learning rate), and the steps past it run at the schedules' final values (docs/trainer.md, "Resuming").
RESUMABLE_CHANGES = ("iterations", "checkpoint_every", "threads", "readback_every")
# readback_every "auto" (None) per device type the run trains on
READBACK_DEFAULT = {"cpu": 1, "cuda": 100}
# keys added after runs were saved without them, with the value those runs used (not today's default)
LEGACY_VALUES = {"pose_frame": "world", "event_norm": "count", "frame_noise": 0.0, "map_weights": "posterior",
                 "event_floor": "mean", "event_huber": 0.0, "densify_from": "all"}
# keys of config.json that record facts about the run, not settings (TrainConfig.load skips them)
RECORD_KEYS = ("scene_file",)


# the options `ev3dgs train` keeps on its command line; every other setting is a train.toml key (layout.py)
CLI_FLAGS = ("--iterations", "--seed", "--backend", "--threads", "--naive", "--no-event-loss", "--oracle",
             "--refine-poses")


def keys_for_flags(message: str) -> str:
    """A settings message with the former command-line flags it names written as train.toml keys
    (``--event-huber`` -> ``events.huber``, ``--hdr`` -> ``[hdr]``); the flags train still has are kept."""
    from .layout import FIELD_KEY, SWITCHES

    names = {}
    for fld, key in FIELD_KEY.items():
        flag = "--" + fld.replace("_", "-")
        if flag not in CLI_FLAGS:
            names[flag] = f"[{key}]" if key in SWITCHES else key
    names.update({"--learn-response": "[response]", "--edi-prior": "edi_prior.weight",
                  "--threshold-map": "[threshold_map]"})
    pattern = "|".join(re.escape(f) for f in sorted(names, key=len, reverse=True))
    return re.sub(rf"({pattern})(?![a-z-])", lambda m: names[m.group(1)], message)


def with_legacy_values(data: dict) -> dict:
    """A saved config dict with the keys it predates filled in as the run was made."""
    return {**LEGACY_VALUES, **data} if isinstance(data, dict) else data


# default event weight per event norm: "count" is Ev3DGS's 1/625 per squared event; "noise" is per unit of
# chi-square (see losses.noise_event_loss and docs/fidelity.md for how it was set)
EVENT_WEIGHTS = {"noise": 8.0 / 625.0, "count": 1.0 / 625.0}
# what a threshold map (--threshold-map) gives the event term's mismatch variance (see threshold_map.py)
MAP_WEIGHTS = ("prior", "posterior")
FLOOR_STATS = ("mean", "median", "chi2")   # --event-floor (losses.noise_event_loss)
DENSIFY_FROM = ("all", "blur")      # --densify-from
# what --event-floor, --event-huber and --densify-from are where a config leaves them unset (None), per event
# norm: the noise norm's floor at which the penalised chi-square averages as expected, with the blur term
# deciding densification (docs/fidelity.md, "A floor from the chi-square"); the count norm has no floor or
# penalty and densifies from the whole loss, as E2NeRF / Ev3DGS
NORM_DEFAULTS = {"noise": dict(event_floor="chi2", event_huber=3.0, densify_from="blur"),
                 "count": dict(event_floor="mean", event_huber=0.0, densify_from="all")}


SH_STEPS_3DGS = (1000, 30000)   # 3DGS raises the SH degree every 1000 of its 30 000 steps


def sh_interval_for(iterations: int) -> int:
    """--sh-interval auto: the 3DGS schedule scaled to ``iterations`` steps (every iterations / 30 steps,
    at least 1): degree 3 from a tenth of the run, as in 3DGS, and 1000 for a 30 000-step run."""
    every, total = SH_STEPS_3DGS
    return max(1, iterations * every // total)


@dataclass(frozen=True)
class TrainConfig:
    scene: str
    iterations: int = 3000
    subposes: int = 5                 # b + 1 renders across each exposure
    subpose_px: float = 0.0           # > 0: per view the fewest sub-poses (2 to subposes) this many pixels apart
                                      # along its largest image motion (subposes.py); 0: subposes for every view
    event_weight: float | None = None  # omega; None = the event norm's default (EVENT_WEIGHTS)
    event_norm: str = "noise"         # "noise": residual over its expected error (losses.noise_event_loss);
                                      # "count": residual in events, / theta_mean (losses.pose_event_loss)
    event_mismatch: float | None = None  # relative per-pixel threshold spread for the noise norm; None = the
                                      # scene's (simulated) or DEFAULT_REL_MISMATCH
    event_pairs: int = 0              # 0 = all pairs of the b+1 renders, k = k random pairs per step
    event_floor: str | None = None    # the noise norm's model floor per step: the "mean" or the "median" of
                                      # the pixel-pairs' excess squared residual, or "chi2" (the floor at which
                                      # their chi-square averages as expected: losses.chi2_floor); None = the
                                      # norm's (NORM_DEFAULTS: the property floor_stat)
    event_huber: float | None = None  # > 0: the noise norm's residuals beyond this many standard deviations
                                      # pull as |r| (losses.huber); 0 = squared everywhere; None = the norm's
    densify_from: str | None = None   # densification statistics from the gradient of "all" the loss or of
                                      # the "blur" term alone (one more backward pass through it per step);
                                      # None = the norm's
    frame_noise: float | None = None  # the frames' noise sigma in 8-bit levels: the event weight grows as the
                                      # blur term's error comes down to that noise (frame_noise.py); None =
                                      # estimated from the frames; 0 = off
    naive: bool = False               # plain 3DGS on the blurry frame at the mid pose
    event_loss: bool = True
    blur_space: str = "auto"          # "srgb": average stored (image) values; "linear": average in linear light;
                                      # "auto": from the scene's /train transfer (srgb -> linear, else srgb)
    event_domain: str = "auto"        # "linear": events see linear light; "display": events were made from
                                      # display values (v2e); "auto": from the scene's transfer
    oracle: bool = False              # the upper bound: plain 3DGS on the sharp frames at their sharp poses
    learn_thresholds: bool = False
    threshold_map: bool = False       # learn per-pixel ON/OFF thresholds (fixed-pattern mismatch), noise norm
    map_weights: str = "prior"        # with threshold_map, the events' mismatch variance: "prior" = the noise
                                      # norm's (the prior's spread); "posterior" = each pixel's fitted spread
    hdr: bool = False                 # renders above 1 are radiance above full scale; the blur clips after
                                      # the exposure integral (losses.srgb_to_linear_hdr_torch)
    learn_response: bool = False      # learn a monotone camera response before the sRGB decode (response.py)
    edi_prior: float = 0.0            # weight of the EDI prior (edi_prior.py), per unit of chi-square; 0 = off
    edi_anneal: float = 0.5           # the prior's weight falls linearly to 0 at this fraction of the run
    ssim_lambda: float = 0.2
    sh_degree: int = 3
    sh_interval: int | None = None    # raise the active SH degree every this many steps; None = the 3DGS
                                      # schedule scaled to the run (sh_interval_for), fixed when the config
                                      # is made so that extending a run keeps it
    init_points: int = 20000          # random init inside `bounds` when the scene has no /points
    init_opacity: float = 0.1
    densify: bool = True
    checkpoint_every: int = 500
    readback_every: int | None = None  # read the steps' log values and non-finite guard back from the device
                                      # every this many steps (and at every checkpoint), not at every step
                                      # (readback.py); None = READBACK_DEFAULT[device]: 1 on the CPU, where a
                                      # read costs nothing, 100 on CUDA, where each read stalls the queue
    seed: int = 0
    device: str = "auto"
    threads: int | None = None
    backend: str = "auto"
    # exposure-trajectory refinement (pose_refine.py): per-view SE(3) corrections at exposure start and end
    refine_poses: bool = False
    pose_lr: float = 1e-3             # Adam lr of the corrections (rad; translation in scene-scale units)
    pose_lr_final: float = 0.01       # the lr decays exponentially to pose_lr * pose_lr_final at the last step
    pose_start: int = 100             # steps before the poses move (the Gaussians get a first fit)
    pose_warmup: int = 100            # steps of linear lr warm-up after pose_start
    pose_max_rotation: float = 5.0    # clamp of each correction's rotation (degrees)
    pose_max_translation: float = 0.1  # clamp of each correction's translation (fraction of the scene scale)
    pose_gauge: str = "similarity"    # remove the 7-dof similarity component of the corrections, or "none"
    pose_frame: str = "world"         # axes of the corrections: "world" or "camera" (the view's own, z = roll)
    # the run length the schedules are made for; None = iterations (set when a resume extends the run)
    schedule_length: int | None = None
    terms: dict = field(default_factory=dict)   # settings of terms registered outside the package, by table

    def __post_init__(self):
        try:
            self._check()
        except ConfigError as e:
            raise ConfigError(keys_for_flags(str(e))) from None

    def _check(self):
        check(self.iterations >= 1, "--iterations must be >= 1")
        check(1 <= self.subposes <= 64, "--subposes must be in [1, 64]")
        check(isinstance(self.subpose_px, (int, float)) and 0 <= self.subpose_px < float("inf"),
              "--subpose-px must be a number >= 0 (0: every view gets --subposes)")
        check(self.event_weight is None or self.event_weight >= 0, "--event-weight must be >= 0")
        check(self.event_norm in EVENT_WEIGHTS, f"--event-norm must be one of {', '.join(EVENT_WEIGHTS)}")
        check(self.event_mismatch is None or 0 <= self.event_mismatch <= 1, "--event-mismatch must be in [0, 1]")
        check(self.event_floor is None or self.event_floor in FLOOR_STATS,
              f"--event-floor must be one of {', '.join(FLOOR_STATS)}")
        check(self.event_huber is None or (isinstance(self.event_huber, (int, float))
                                           and 0 <= self.event_huber < float("inf")),
              "--event-huber must be a number >= 0 (0: off)")
        check(self.densify_from is None or self.densify_from in DENSIFY_FROM,
              f"--densify-from must be one of {', '.join(DENSIFY_FROM)}")
        for flag, on in ((f"--event-floor {self.event_floor}", self.floor_stat != "mean"),
                         ("--event-huber", self.huber_c)):
            check(not on or self.event_norm == "noise", f"{flag} needs --event-norm noise (it shapes the noise norm)")
        check(self.frame_noise is None or 0 <= self.frame_noise <= 255,
              "--frame-noise must be auto or a sigma in 8-bit levels in [0, 255]")
        check(not self.threshold_map or self.event_norm == "noise",
              "--threshold-map needs --event-norm noise (its prior and weights come from the noise model)")
        check(self.map_weights in MAP_WEIGHTS, f"--map-weights must be one of {', '.join(MAP_WEIGHTS)}")
        n_pairs = self.subposes * (self.subposes - 1) // 2
        check(0 <= self.event_pairs <= n_pairs,
              f"--event-pairs must be in [0, {n_pairs}] ({self.subposes} sub-poses have {n_pairs} pairs)")
        check(self.blur_space in ("auto", "srgb", "linear"), "--blur-space must be auto, srgb or linear")
        for flag, on in (("--hdr", self.hdr), ("--learn-response", self.learn_response)):
            check(not (on and self.blur_space == "srgb"),
                  f"{flag} needs the linear-light blur model, not --blur-space srgb")
        check(not (self.learn_response and (self.oracle or self.naive)),
              "--learn-response needs the blur model (a sharp frame's decode and encode cancel): not with "
              "--oracle or --naive")
        check(not (self.learn_response and self.edi_prior),
              "--learn-response with --edi-prior: the prior's targets come from the frames decoded once, as sRGB")
        check(self.edi_prior >= 0, "--edi-prior must be >= 0")
        check(0 < self.edi_anneal <= 1, "--edi-anneal must be in (0, 1]")
        check(not self.edi_prior or self.event_norm == "noise",
              "--edi-prior needs --event-norm noise (its weights come from the noise model)")
        check(not self.edi_prior or self.uses_events, "--edi-prior needs the event loss (events, not --oracle "
              "or --naive, --event-weight > 0)")
        check(self.event_domain in ("auto", "linear", "display"), "--event-domain must be auto, linear or display")
        check(not (self.oracle and self.naive), "--oracle and --naive are different variants: give one")
        check(0 <= self.ssim_lambda <= 1, "ssim lambda must be in [0, 1]")
        check(0 <= self.sh_degree <= 3, "--sh-degree must be in [0, 3]")
        check(self.sh_interval is None or self.sh_interval >= 1, "--sh-interval must be auto or >= 1")
        if self.sh_interval is None:
            object.__setattr__(self, "sh_interval", sh_interval_for(self.iterations))
        check(self.init_points >= 1, "--init-points must be >= 1")
        check(0 < self.init_opacity < 1, "init opacity must be in (0, 1)")
        check(self.seed >= 0, "--seed must be >= 0")
        check(self.checkpoint_every >= 1, "--checkpoint-every must be >= 1")
        check(self.readback_every is None or self.readback_every >= 1, "readback_every must be >= 1")
        check(self.device in ("auto", "cpu", "cuda"), "--device must be auto, cpu or cuda")
        check(self.threads is None or self.threads >= 1, "--threads must be >= 1")
        check(self.backend in ("auto", "reference", "cpu", "cuda"), "--backend must be auto, reference, cpu or cuda")
        check(not (self.refine_poses and self.oracle), "--refine-poses with --oracle: the oracle's poses are exact")
        check(self.pose_lr > 0 and self.pose_lr < 1, "--pose-lr must be in (0, 1)")
        check(0 < self.pose_lr_final <= 1, "--pose-lr-final must be in (0, 1]")
        check(self.pose_start >= 0 and self.pose_warmup >= 0, "--pose-start and --pose-warmup must be >= 0")
        check(0 < self.pose_max_rotation <= 90, "--pose-max-rotation must be in (0, 90] degrees")
        check(0 < self.pose_max_translation <= 10, "--pose-max-translation must be in (0, 10]")
        check(self.pose_gauge in ("similarity", "none"), "--pose-gauge must be similarity or none")
        check(self.pose_frame in ("world", "camera"), "--pose-frame must be world or camera")
        check(self.schedule_length is None or self.schedule_length >= 1, "schedule_length must be >= 1")
        check(isinstance(self.terms, dict), "terms must be a table of term tables")

    @property
    def schedule_iterations(self) -> int:
        """The run length every schedule is scaled to (RESUMABLE_CHANGES: extending a run keeps it)."""
        return self.schedule_length or self.iterations

    @property
    def uses_events(self) -> bool:
        return (self.event_loss and not self.naive and not self.oracle and self.subposes > 1
                and self.omega > 0)

    def _norm_default(self, key: str):
        value = getattr(self, key)
        return NORM_DEFAULTS.get(self.event_norm, NORM_DEFAULTS["count"])[key] if value is None else value

    @property
    def floor_stat(self) -> str:
        """--event-floor, or the event norm's (NORM_DEFAULTS)."""
        return self._norm_default("event_floor")

    @property
    def huber_c(self) -> float:
        """--event-huber, or the event norm's."""
        return float(self._norm_default("event_huber"))

    @property
    def densify_source(self) -> str:
        """--densify-from, or the event norm's."""
        return self._norm_default("densify_from")

    @property
    def omega(self) -> float:
        """The event loss weight: --event-weight, or the event norm's default."""
        return EVENT_WEIGHTS[self.event_norm] if self.event_weight is None else self.event_weight

    @property
    def variant(self) -> str:
        """naive, blur-only, blur+event or oracle (the evaluation's label)."""
        if self.oracle:
            return "oracle"
        return "naive" if self.naive else ("blur+event" if self.uses_events else "blur-only")

    # ------------------------------------------------------------------ train.toml
    @staticmethod
    def from_toml(data: dict) -> "TrainConfig":
        """From a train.toml dict (layout.py: core keys at the top, one table per term); unknown keys and
        wrong types are one-line ConfigErrors naming the dotted key."""
        from .layout import flat_settings
        from .terms import registered

        return TrainConfig(**flat_settings(data, TrainConfig, registered()))

    @staticmethod
    def default_toml() -> dict:
        """The train.toml dict of the built-in settings (blur + event losses; "auto" left unresolved)."""
        from dataclasses import MISSING
        from types import SimpleNamespace

        from .layout import nested

        values = {f.name: (f.default if f.default is not MISSING else
                           f.default_factory() if f.default_factory is not MISSING else None)
                  for f in fields(TrainConfig)}
        return nested(SimpleNamespace(**values))

    def to_toml(self) -> dict:
        """The train.toml dict of these settings (every key written; "auto" where the trainer resolves it)."""
        from .layout import nested

        return nested(self)

    def resolved_notes(self) -> dict:
        """{dotted key: what "auto" resolves to} for the record in config.toml."""
        notes = {"event_weight": f"{self.omega:g}", "event_floor": self.floor_stat,
                 "event_huber": f"{self.huber_c:g}", "densify_from": self.densify_source,
                 "frame_noise": "estimated from the frames", "event_mismatch": "from the scene's sensor model",
                 "threads": "torch's choice",
                 "readback_every": ", ".join(f"{n} on {d}" for d, n in READBACK_DEFAULT.items())}
        from .layout import FIELD_KEY

        return {FIELD_KEY[k]: v for k, v in notes.items() if getattr(self, k) is None}

    def save(self, path: Path) -> None:
        """config.json: the settings, plus ``scene_file`` (run_scene.scene_record: the scene's path relative
        to the run folder, its absolute path, size and fingerprint), so the run finds its scene from any
        folder and after being moved; and beside it config.toml, the same settings as a train.toml (the
        run's record, read first by --resume; ``ev3dgs train SCENE --config RUN/config.toml`` repeats the
        run)."""
        from ..outputs import atomic_path
        from .layout import dumps
        from .run_scene import scene_record

        path = Path(path)
        data = asdict(self)
        data["scene_file"] = scene_record(self.scene, path.parent)
        with atomic_path(path) as tmp:
            tmp.write_text(json.dumps(data, indent=2))
        with atomic_path(path.with_name("config.toml")) as tmp:
            tmp.write_text("# the resolved settings of this run (ev3dgs train); see docs/trainer.md\n"
                           + dumps(self.to_toml(), self.resolved_notes()))

    @staticmethod
    def load(path: Path) -> "TrainConfig":
        """Read a run's config.json (flat keys, older runs too) or a config.toml/train.toml; a missing key, an
        unknown key or a value of the wrong type (e.g. ``"iterations": "300"``) is a one-line ConfigError naming
        the file and the key."""
        if Path(path).suffix == ".toml":
            from ..config import load_toml

            data = load_toml(path)
            if "scene" not in data:
                raise ConfigError(f"{path}: the run's config has no 'scene'")
            try:
                return TrainConfig.from_toml(data)
            except ConfigError as e:
                raise ConfigError(f"{path}: {e}") from None
        try:
            data = json.loads(Path(path).read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
            raise ConfigError(f"{path}: cannot read the run's config ({e})") from None
        if not isinstance(data, dict):
            raise ConfigError(f"{path}: the run's config must be a JSON object, got {type(data).__name__}")
        if "scene" not in data:
            raise ConfigError(f"{path}: the run's config has no 'scene'")
        data = {k: v for k, v in data.items() if k not in RECORD_KEYS}
        try:
            return from_dict(TrainConfig, with_legacy_values(data))
        except ConfigError as e:
            raise ConfigError(f"{path}: {e}") from None

    def differences(self, other: "TrainConfig", ignore: tuple[str, ...] = RESUMABLE_CHANGES) -> list[tuple]:
        """(key, self's value, other's value) for every field not in ``ignore`` that differs (scene paths are
        compared resolved, so a relative and an absolute path to one file are the same scene, and so is a copy
        or a moved file with the same size, name and creation time: run_scene.same_scene_file)."""
        from .run_scene import same_scene_file

        out = []
        for f in fields(self):
            a, b = getattr(self, f.name), getattr(other, f.name)
            if f.name == "schedule_length":   # None means "the run's iterations": compare what the schedules use
                a, b = self.schedule_iterations, other.schedule_iterations
            if f.name in ignore or a == b:
                continue
            if f.name == "scene" and (Path(a).resolve() == Path(b).resolve() or same_scene_file(a, b)):
                continue
            out.append((f.name, a, b))
        return out


def mismatch_error(path, diffs: list[tuple]) -> ConfigError:
    """The one-line refusal of a resume whose settings differ from the saved run's."""
    listed = "; ".join(f"{k}: saved {a!r} vs given {b!r}" for k, a, b in diffs)
    return ConfigError(f"--resume: {path} was made with other settings ({listed}); only --iterations, "
                       "checkpoint_every, readback_every and --threads may change when resuming (more "
                       "--iterations keep the run's schedules)")


def resume_config(run_dir, opts: dict, given: set[str]) -> TrainConfig:
    """Settings of a resumed run: the run's config.json with the options the user gave (``given``, field
    names) from ``opts`` on top; options not given keep their saved values, whatever the CLI defaults. With a
    checkpoint to resume, a given option that differs from the saved one (other than RESUMABLE_CHANGES) is a
    ConfigError listing every difference. Without config.json: TrainConfig(**opts)."""
    saved_path = Path(run_dir) / "config.json"
    if not saved_path.exists():
        return TrainConfig(**opts)
    saved = TrainConfig.load(saved_path)
    if (Path(run_dir) / "config.toml").exists():   # the run's record; config.json mirrors it for older readers
        saved_path = Path(run_dir) / "config.toml"
        saved = replace(TrainConfig.load(saved_path), scene=saved.scene)
    if "scene" in given and not Path(saved.scene).exists():  # the run and its scene were moved: same file?
        from .run_scene import resolve_run_scene

        try:
            moved = resolve_run_scene(run_dir)
        except Exception:
            moved = None
        if moved is not None and Path(moved).resolve() == Path(opts["scene"]).resolve():
            saved = replace(saved, scene=opts["scene"])
    merged = {**asdict(saved), **{k: v for k, v in opts.items() if k in given}}
    if merged["iterations"] != saved.iterations and saved.schedule_length is None:
        merged["schedule_length"] = saved.iterations   # extending (or cutting) a run keeps its schedules
    cfg = TrainConfig(**merged)
    if (Path(run_dir) / "ckpt.pt").exists():
        diffs = saved.differences(cfg)
        if diffs:
            raise mismatch_error(saved_path, diffs)
    return cfg
