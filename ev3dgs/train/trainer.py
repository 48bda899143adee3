"""The training loop: blur rendering loss over b+1 poses of each exposure, plus the event rendering loss.

    loss = (1 - lambda) * MSE(mean_k render_k, blurry) + lambda * (1 - SSIM(...))
         + omega * mean(r ** 2 / (v + f g)),   r = (log L_k2 - log L_k1) - E[change | ON, OFF counts]
         (--event-norm noise, the default: losses.noise_event_loss; v = the counts' expected squared error
         from quantisation, threshold mismatch and noise events, f g = the model's own, tracked over steps)
         or + omega * mean((r / theta_mean) ** 2)   (--event-norm count: losses.pose_event_loss)
         E = theta_on * n_on - theta_off * n_off, per the scene's count convention

(added, not subtracted as in the published Ev3DGS code; the binned events are never modified in place.)

Reproducibility: on the CPU a run is bitwise reproducible for a given seed on a given machine, whatever the
thread counts (``--threads``, torch's, NUMBA_NUM_THREADS, OMP_NUM_THREADS). Measured with torch 2.13 (see
tests/test_reliability_training.py): torch's CPU kernels are NOT thread-count independent (element-wise
pow/sigmoid switch between SIMD and scalar code at thread-chunk boundaries, full sums and means split their
partial sums per thread, a matmul's gradient splits its inner sum per thread) and ``index_put_`` with
repeated indices (the backward of ``x[idx]``) adds atomically in a racy order. So every training step runs
under :func:`reproducible`: torch's intra-op thread count pinned to 1 and deterministic algorithms on. The
heavy work on the ``cpu`` backend is the numba rasterizer, which stays parallel (``--threads``): its tiles
write disjoint pixels and per-(tile, Gaussian) gradient slots that one serial pass sums in a fixed order, so
its results do not depend on its thread count either. With CUDA (gsplat) the backward adds gradients with
float atomics: GPU runs are NOT bitwise reproducible (close, not equal).
"""
from __future__ import annotations

import json
import math
import sys
import time
from contextlib import contextmanager
from pathlib import Path

import torch

from ..errors import ConfigError, Ev3dgsError
from ..splat.model import GaussianModel
from ..splat.rasterize import rasterization
from ..splat.strategy import DefaultStrategy, scaled_schedule
from .checkpoint import load_checkpoint, read_checkpoint, save_checkpoint
from .config import READBACK_DEFAULT, TrainConfig
from .data import TrainData, load_train_data
from .init import init_bounds
from .readback import read_back, to_device
from .rng import stream_generator, stream_seed


class TrainingError(Ev3dgsError):
    """Training cannot go on (a non-finite loss or gradient); the last good checkpoint is kept."""


@contextmanager
def reproducible(enabled: bool = True):
    """Run torch CPU maths so that its results do not depend on the thread count or on thread timing:
    intra-op threads pinned to 1 and ``torch.use_deterministic_algorithms(True)`` (warn-only), both restored
    on exit. (Numba kernels are not affected: they are thread-count independent by construction.)"""
    if not enabled:
        yield
        return
    threads = torch.get_num_threads()
    det, warn_only = torch.are_deterministic_algorithms_enabled(), torch.is_deterministic_algorithms_warn_only_enabled()
    torch.set_num_threads(1)
    torch.use_deterministic_algorithms(True, warn_only=True)
    try:
        yield
    finally:
        torch.use_deterministic_algorithms(det, warn_only=warn_only)
        torch.set_num_threads(threads)


def resolve_device(name: str) -> torch.device:
    if name == "cuda" and not torch.cuda.is_available():
        raise Ev3dgsError("--device cuda: CUDA is not available (no CUDA device or no CUDA build of torch)")
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    return torch.device(name)


def init_model(data: TrainData, cfg: TrainConfig, device) -> GaussianModel:
    if data.points is not None and len(data.points[0]) >= 4:
        return GaussianModel.from_points(data.points[0], data.points[1], sh_degree=cfg.sh_degree,
                                         init_opacity=cfg.init_opacity, device=device)
    bounds = data.bounds
    if bounds is None:  # a cube where the cameras look, as wide as their view there (train/init.py)
        forwards = data.mid_viewmats[:, 2, :3].detach().cpu().double().numpy()  # w2c row 2: camera +z in world
        bounds = init_bounds(data.camera_centres, forwards, data.K.detach().cpu().double().numpy(),
                             data.width, data.height)
    return GaussianModel.random_in_bounds(bounds, cfg.init_points, seed=stream_seed(cfg.seed, "init"),
                                          sh_degree=cfg.sh_degree, init_opacity=cfg.init_opacity, device=device)


class Step:
    """One step's shared facts: the view, its cameras, the renders each term asked for, and what terms publish
    for later terms of the same step (``shared``: the blur average, the decoded images, the event floor...)."""

    def __init__(self, trainer: "Trainer", view: int):
        self.trainer, self.view = trainer, view
        data = trainer.data
        self.k = data.sub_count(view)   # --subpose-px: this view's own count; the rest of its rows is padding
        self.target = data.images[view]
        # the view's cameras: its b+1 sub-poses across the exposure (naive: the mid pose)
        self.poses = data.mid_viewmats[view:view + 1] if trainer.cfg.naive else data.viewmats[view][:self.k]
        self.shared: dict = {}
        self.losses: dict = {}   # each term's loss as it entered the sum
        self._index: dict = {}
        self.renders = self.info = None

    def render(self, requests: list) -> None:
        """Render every camera the terms asked for in ONE rasterizer call. ``requests``: (term, (m, 4, 4) or
        None) pairs. A request of the same tensor as an earlier one (the view's sub-poses, asked for by the
        blur and the event terms) shares its renders, and a camera equal to one an earlier request listed is
        rendered once; cameras within one request are all rendered (a static exposure's equal sub-poses are
        each one sample of the blur average and of the densification statistics, as before)."""
        cams, blocks, seen = [], [], {}
        for term, poses in requests:
            if poses is None:
                continue
            if id(poses) not in seen:
                earlier = len(cams)
                idx = []
                for c in poses:
                    j = next((i for i in range(earlier) if torch.equal(cams[i], c)), None)
                    if j is None:
                        cams.append(c)
                        j = len(cams) - 1
                    idx.append(j)
                seen[id(poses)] = idx
                blocks.append(poses)
            self._index[term] = seen[id(poses)]
        stack = blocks[0] if len(blocks) == 1 else torch.stack(cams)
        self.renders, _, self.info = self.trainer.render(stack)

    def images(self, term) -> torch.Tensor:
        """(m, H, W, 3) the renders of the cameras ``term`` asked for, in its order."""
        idx = self._index[term]
        if idx == list(range(len(self.renders))):
            return self.renders
        return self.renders[to_device(idx, torch.long, self.renders.device)]


class Trainer:
    """The core: model, optimiser, densification, schedule, checkpoints and the loop. Everything optional is
    a term (train/terms/), built from the registry where the config turns it on."""

    def __init__(self, cfg: TrainConfig, run_dir: str | Path, quiet: bool = False):
        from .terms import all_terms

        self.cfg = cfg
        self.run_dir = Path(run_dir)
        self.quiet = quiet
        self.device = resolve_device(cfg.device)
        if cfg.threads:
            torch.set_num_threads(cfg.threads)
        torch.manual_seed(cfg.seed)
        self.data = load_train_data(cfg.scene, 1 if cfg.naive or cfg.oracle else cfg.subposes, device=self.device,
                                    blur_space=cfg.blur_space, event_domain=cfg.event_domain, oracle=cfg.oracle,
                                    subpose_px=cfg.subpose_px)
        if self.data.n_sub is not None and not quiet:
            n, mo = self.data.n_sub, self.data.motion_px
            print(f"blur.subpose_px {cfg.subpose_px:g}: {n.min()}-{n.max()} sub-poses per view (mean "
                  f"{n.mean():.1f}) for {mo.min():.1f}-{mo.max():.1f} px of motion per exposure", file=sys.stderr)
        self.model = init_model(self.data, cfg, self.device)
        self.optimizers = self.model.make_optimizers(scene_scale=self.data.scene_scale)
        self.means_lr0 = self.optimizers["means"].param_groups[0]["lr"]
        # densification steps scaled to the run's schedule length (gsplat-style; 30 000 steps = the 3DGS
        # defaults), never starting before MIN_SCHEDULE_STEPS (schedule_floors)
        self.strategy = DefaultStrategy(**densify_schedule(cfg.schedule_iterations),
                                        scene_scale=self.data.scene_scale, seed=stream_seed(cfg.seed, "densify"))
        self.strategy_state = self.strategy.initialize_state(len(self.model), device=self.device)
        self.generator = stream_generator(cfg.seed, "views")       # view order
        self.view_queue: list[int] = []
        self.step = 0
        self._unchecked: list[dict] = []   # records of steps whose non-finite guard is not read back yet
        self._bad_step: int | None = None  # the step whose non-finite loss or gradient stopped the run
        self.terms: list = []   # built in registry order; a term's build may look at those before it
        for cls in all_terms():
            term = cls.build(self)
            if term is not None:
                self.terms.append(term)

    def term(self, table: str):
        """This run's term of that table, or None where it is off."""
        return next((t for t in self.terms if t.table == table), None)

    @property
    def use_events(self) -> bool:
        return self.term("events") is not None

    @property
    def thresholds(self) -> dict:
        """The ON/OFF contrast thresholds (log of, as tensors): the event term's, else the scene's."""
        ev = self.term("events")
        if ev is not None:
            return ev.thresholds
        return {k: torch.tensor(math.log(t), device=self.device)
                for k, t in (("pos", self.data.pos_threshold), ("neg", self.data.neg_threshold))}

    # ------------------------------------------------------------------ helpers
    def _next_view(self) -> int:
        if not self.view_queue:
            self.view_queue = torch.randperm(self.data.n_views, generator=self.generator).tolist()
        return self.view_queue.pop()

    def render(self, viewmat: torch.Tensor):
        m = self.model
        return rasterization(m.means, m.quats_normalised, m.scales, m.opacities, m.sh, viewmat, self.data.K,
                             self.data.width, self.data.height, sh_degree=m.active_sh_degree,
                             background=self.data.background, backend=self.cfg.backend,
                             threads=self.cfg.threads)

    def _set_lr(self) -> None:
        # 3DGS position lr: exponential (log-linear) decay to 1% over the run's schedule length
        frac = min(1.0, self.step / max(1, self.cfg.schedule_iterations))
        self.optimizers["means"].param_groups[0]["lr"] = self.means_lr0 * (0.01 ** frac)
        if self.step > 0 and self.step % self.cfg.sh_interval == 0:
            self.model.active_sh_degree = min(self.model.sh_degree, self.model.active_sh_degree + 1)

    # ------------------------------------------------------------------ one step
    def train_step(self) -> dict:
        """One optimisation step (bitwise reproducible on the CPU, see :func:`reproducible`), read back at once:
        the record's values are floats and a non-finite loss or gradient raises TrainingError before the
        update. (`fit` reads back every ``readback_every`` steps instead: :meth:`step_deferred`.)"""
        rec = self.step_deferred(readback=True)
        read_back([rec])
        return self._public(rec)

    def step_deferred(self, readback: bool = False) -> dict:
        """One optimisation step that reads nothing back from the device unless ``readback``: its record keeps
        device scalars (readback.read_back turns them into floats) and its non-finite guard is a device flag,
        ``rec["_ok"]``, checked at the next read-back. ``readback``: the guard reads back the flags of this
        step and of every earlier step not yet checked (one read) before the update, and raises TrainingError
        at the first non-finite one, as it did at every step."""
        with reproducible(self.device.type == "cpu"):
            return self._train_step(readback)

    def _train_step(self, readback: bool = True) -> dict:
        """Every term's cameras rendered in one call, every term's loss summed, one backward pass, every
        optimiser stepped, densification from the per-camera screen-space gradients."""
        self._set_lr()
        step = Step(self, self._next_view())
        for term in self.terms:   # pose refinement: the view's cameras as corrected
            step.poses = term.adjust_cameras(step, step.poses)
        step.render([(term, term.cameras(step)) for term in self.terms])
        # densification statistics: each of the view's b+1 renders gets ~1/(b+1) of the blur average's gradient
        step.info["grad_scale"] = float(len(step.poses))
        self.strategy.step_pre_backward(step.info)
        loss, logs = None, {}
        for term in self.terms:
            part, log = term.loss(step)
            logs.update(log)
            if part is not None:
                step.losses[term.table] = part
                loss = part if loss is None else loss + part
        stats_grad = self._densify_grad(step)
        loss.backward()
        rec = {"step": self.step + 1, "view": step.view, "loss": loss.detach(), "_ok": self._finite(loss),
               "_losses": {k: v.detach() for k, v in step.losses.items()}}
        self._unchecked.append(rec)
        if readback:
            self._check_guard()
        for opt in self.optimizers.values():
            opt.step()
            opt.zero_grad(set_to_none=True)
        for term in self.terms:
            logs.update(term.after_backward(step))
        refined = {}
        if self.cfg.densify:
            if stats_grad is not None:
                step.info["means2d"].grad = stats_grad
            refined = self.strategy.step_post_backward(self.model, self.optimizers, self.strategy_state,
                                                       self.step, [step.info])
        self.step += 1
        with torch.no_grad():
            for term in self.terms:
                logs.update(term.after_step(step))
        rec.update(logs)
        rec["gaussians"] = len(self.model)
        rec.update(refined)
        return rec

    @staticmethod
    def _public(rec: dict) -> dict:
        """The record as log.jsonl and on_step callers see it (without the guard's private entries)."""
        for key in ("_ok", "_losses"):
            rec.pop(key, None)
        return rec

    def _densify_grad(self, step: Step):
        """densify.from = "blur" while the strategy still densifies and other terms add to the loss: the blur
        term's gradient at the renders' screen-space means (C, N, 2), so that the event term's weight, which
        grows with the events' precision, does not decide how many Gaussians are split. None: the statistics
        come from the whole loss's gradient, as the backward pass leaves it. Either way the strategy sums
        each camera's gradient norm into its statistics and counts each camera once (a per-render mean)."""
        if not (self.cfg.densify_source == "blur" and set(step.losses) - {"blur"} and self.cfg.densify
                and self.step < self.strategy.refine_stop and "blur" in step.losses):
            return None
        parts = step.info.get("means2d_parts")   # a backend that rendered camera by camera (rasterize.py)
        targets = parts if parts is not None else [step.info["means2d"]]
        grads = torch.autograd.grad(step.losses["blur"], targets, retain_graph=True, allow_unused=True)
        if parts is None:
            return grads[0]
        return torch.stack([torch.zeros_like(p) if g is None else g for p, g in zip(parts, grads)])

    def trained_parameters(self) -> list[torch.Tensor]:
        """Every tensor a step updates and the guard checks: the Gaussians and every term's parameters (the
        pose corrections are not listed: the pose term skips a non-finite pose gradient itself, counted as
        pose_skipped in log.jsonl, rather than stopping the run)."""
        out = {id(p): p for p in self.model.params.values()}
        for term in self.terms:
            out.update({id(p): p for p in term.parameters()})
        extra = [o for o in vars(self).values() if isinstance(o, torch.optim.Optimizer)]   # any other optimiser
        for opt in list(self.optimizers.values()) + extra:
            for group in opt.param_groups:
                out.update({id(p): p for p in group["params"]})
        return list(out.values())

    def _finite(self, loss) -> torch.Tensor:
        """A 0-dim bool tensor on the device: the loss and every trained parameter's gradient are finite (a
        sum is finite only if every term is; inf or NaN anywhere in a gradient makes its element test fail).
        Nothing is read back."""
        flags = [torch.isfinite(loss).reshape(())]
        flags += [torch.isfinite(p.grad).all() for p in self.trained_parameters() if p.grad is not None]
        return torch.stack(flags).all() if len(flags) > 1 else flags[0]

    def _first_bad(self) -> dict | None:
        """The record of the first step whose guard flag, not yet read back, says non-finite (one read of all
        the flags), or None; the unchecked list is emptied either way."""
        if not self._unchecked:
            return None
        oks = torch.stack([r["_ok"] for r in self._unchecked]).tolist()   # the one read
        bad = next((r for r, ok in zip(self._unchecked, oks) if not ok), None)
        self._unchecked.clear()
        return bad

    def _check_guard(self) -> None:
        """Read back the guard flags of the steps not yet checked (one read) and raise TrainingError at the
        first non-finite one, naming its step and its terms' losses."""
        bad = self._first_bad()
        if bad is not None:
            losses = dict(bad["_losses"])
            read_back([losses])
            self._raise_bad(bad["step"], losses)

    def _raise_bad(self, step: int, losses: dict) -> None:
        self._bad_step = step
        ckpt = self.run_dir / "ckpt.pt"
        where = f"the last good checkpoint is {ckpt}" if ckpt.exists() else "no checkpoint was written yet"
        parts = ", ".join(f"{k} {float(v):.4g}" for k, v in losses.items())
        raise TrainingError(f"non-finite loss or gradient at step {step} ({parts}); stopped, {where}")

    # ------------------------------------------------------------------ the run
    def fit(self, resume: bool = False, on_step=None) -> dict:
        """Train to cfg.iterations. ``resume``: continue from RUN/ckpt.pt (refused, one line, when it was made
        with other settings; see checkpoint.check_compatible) and roll log.jsonl back to its step, so no
        step is logged twice; a run killed before its first checkpoint restarts from step 0 (and says so).
        Without ``resume`` the run folder's old ckpt.pt and log.jsonl are replaced."""
        self.run_dir.mkdir(parents=True, exist_ok=True)
        ckpt = self.run_dir / "ckpt.pt"
        log_path = self.run_dir / "log.jsonl"
        if resume:
            if ckpt.exists():
                load_checkpoint(ckpt, self, read_checkpoint(ckpt, self.device))
                if self.step > self.cfg.iterations:
                    raise ConfigError(f"--resume: {ckpt} is at step {self.step}, past --iterations "
                                      f"{self.cfg.iterations}")
            elif (self.run_dir / "config.json").exists() or log_path.exists():
                print(f"no checkpoint in {self.run_dir}: starting from step 0", file=sys.stderr)
            else:
                raise Ev3dgsError(f"--resume: no checkpoint in {self.run_dir} (no run was started there)")
        else:
            clear_run(self.run_dir)  # the run they belonged to is being replaced
        rollback_log(log_path, self.step)
        self.cfg.save(self.run_dir / "config.json")
        from tqdm import tqdm

        bar = tqdm(total=self.cfg.iterations, initial=self.step, disable=self.quiet or not sys.stderr.isatty(),
                   unit="it", dynamic_ncols=True)
        log = open(log_path, "a")
        t0 = time.perf_counter()
        rec, queued = {}, []   # queued: records not read back yet
        every = self.cfg.readback_every or READBACK_DEFAULT[self.device.type]

        def flush() -> None:   # read back the queued records (one read) and write them to the log
            read_back(queued)
            for r in queued:
                log.write(json.dumps(self._public(r)) + "\n")
            bar.update(len(queued))
            if queued:
                last = queued[-1]
                bar.set_postfix(loss=f"{last['loss']:.4f}", psnr=f"{last.get('psnr_blurry', float('nan')):.2f}",
                                gaussians=last["gaussians"], refresh=False)
            queued.clear()

        try:
            while self.step < self.cfg.iterations:
                n = self.step + 1
                save = n % self.cfg.checkpoint_every == 0 or n == self.cfg.iterations
                readback = save or n % every == 0
                rec = self.step_deferred(readback=readback)
                rec["seconds"] = time.perf_counter() - t0
                queued.append(rec)
                if readback:
                    flush()
                if save:
                    log.flush()
                    save_checkpoint(ckpt, self)
                if on_step is not None:
                    on_step(self, rec)
        finally:
            try:   # the steps run so far are logged (also when stopped from outside: on_step, Ctrl-C), up to
                # the first one whose non-finite guard stopped the run or, not read back yet, would have
                bad = self._bad_step
                if bad is None:
                    first = self._first_bad()
                    bad = None if first is None else first["step"]
                queued[:] = [r for r in queued if bad is None or r["step"] < bad]
                flush()
            finally:
                bar.close()
                log.close()
        self.save_model()
        plot_curves(self.run_dir / "log.jsonl", self.run_dir / "training.png")
        return rec

    def save_model(self) -> None:
        """model.pt (and config.json, config.toml) in the run folder: what eval, render and export read; and
        every term's own outputs (trajectory.npz, response.json); an older run's term outputs that this run
        does not make are removed."""
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self.cfg.save(self.run_dir / "config.json")
        from ..outputs import atomic_path

        extras = {"thresholds": {k: v.detach().exp().item() for k, v in self.thresholds.items()},
                  "threshold_map": None}   # --threshold-map: (2, H, W) ON/OFF multipliers of the thresholds
        for term in self.terms:
            extras.update(term.model_extras())
        with atomic_path(self.run_dir / "model.pt") as tmp:  # on failure: temporary removed, OutputError
            torch.save({"model": self.model.state_dict(), **extras}, tmp)
        for name in TERM_FILES:   # never leave an older run's trajectory or response beside this model
            (self.run_dir / name).unlink(missing_ok=True)
        for term in self.terms:
            term.write(self.run_dir)


# files a term writes into the run folder (train/terms/)
TERM_FILES = ("trajectory.npz", "response.json", "sensor_model.json")
# Short runs: no schedule starts before a scene has had a first fit, whatever the run length (a 150-step run
# scaled from 3DGS's 30 000 densified from step 2 and reset every opacity every 15 steps, and fell to a white
# blob). Densification starts at step MIN_DENSIFY_START at the earliest, the opacity reset comes at most every
# MIN_RESET_EVERY steps, the EDI prior fades over MIN_EDI_ANNEAL_STEPS at least; pose refinement starts at
# poses.start (100 steps by default), an absolute step. Runs of 1000 steps and more are not affected (the
# scaled schedule of 1000 steps starts densifying at 17 and resets every 100), so the docs' tables stand.
MIN_DENSIFY_START = 15
MIN_RESET_EVERY = 100
MIN_EDI_ANNEAL_STEPS = 100


def densify_schedule(iterations: int) -> dict:
    """The densification steps of a run whose schedules are ``iterations`` long: strategy.scaled_schedule with
    the floors above (a run whose scaled refine_stop comes before MIN_DENSIFY_START is not densified)."""
    sched = scaled_schedule(iterations)
    sched["refine_start"] = max(sched["refine_start"], MIN_DENSIFY_START)
    sched["reset_every"] = max(sched["reset_every"], MIN_RESET_EVERY)
    return sched


# what `ev3dgs train` and `ev3dgs eval` write in a run folder; a fresh run removes them (and nothing else)
RUN_FILES = ("config.json", "config.toml", "model.pt", "ckpt.pt", "log.jsonl", "metrics.json", "trajectory.npz",
             "training.png", "response.json", "sensor_model.json")
RUN_MARKERS = ("config.json", "model.pt", "ckpt.pt", "metrics.json")  # a folder with one of these holds a run


def holds_run(run_dir: str | Path) -> bool:
    """True when `run_dir` holds (part of) a training run."""
    return any((Path(run_dir) / name).exists() for name in RUN_MARKERS)


def clear_eval_images(run_dir: str | Path) -> None:
    """Remove RUN/eval's comparison images (test_NNN.png, train_NNN.png) and the folder when left empty."""
    import re

    folder = Path(run_dir) / "eval"
    if not folder.is_dir():
        return
    for p in folder.iterdir():
        if re.fullmatch(r"(test|train)_\d+\.png", p.name) and p.is_file():
            p.unlink()
    try:
        folder.rmdir()
    except OSError:  # not empty: a user's file is kept
        pass


def clear_run(run_dir: str | Path) -> None:
    """Remove an earlier run's results from `run_dir` (RUN_FILES and the eval images): a fresh run must not sit
    beside a stale model, metrics or trajectory. Other files are kept."""
    for name in RUN_FILES:
        (Path(run_dir) / name).unlink(missing_ok=True)
    clear_eval_images(run_dir)


def rollback_log(log_path: Path, step: int) -> None:
    """Keep the log lines of steps 1..step (those the checkpoint has seen), atomically; a torn last line (a
    run killed mid-write) goes too. step 0 empties the log."""
    if not log_path.exists():
        return
    kept = []
    for line in log_path.read_text(errors="replace").splitlines():
        try:
            rec = json.loads(line)
        except json.JSONDecodeError:
            continue
        if isinstance(rec, dict) and isinstance(rec.get("step"), int) and rec["step"] <= step:
            kept.append(line + "\n")
    from ..outputs import atomic_path

    with atomic_path(log_path) as tmp:
        tmp.write_text("".join(kept))


def plot_curves(log_path: Path, png: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    recs = [json.loads(line) for line in log_path.read_text().splitlines() if line.strip()]
    if not recs:
        return
    steps = [r["step"] for r in recs]
    fig, ax = plt.subplots(1, 2, figsize=(9, 3.2))
    ax[0].semilogy(steps, [r.get("blur", float("nan")) for r in recs], label="blur loss", lw=0.8)
    if any(r.get("event") for r in recs):
        ax[0].semilogy(steps, [max(r.get("event", 0.0), 1e-12) for r in recs], label="event loss (unweighted)",
                       lw=0.8)
    ax[0].legend(fontsize=8)
    ax[0].set_xlabel("step")
    ax[1].plot(steps, [r.get("psnr_blurry", float("nan")) for r in recs], lw=0.8)
    ax[1].set_ylabel("PSNR vs blurry input (dB)")
    ax[1].set_xlabel("step")
    fig.tight_layout()
    fig.savefig(png, dpi=100)
    plt.close(fig)
