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

import numpy as np
import torch

from ..errors import ConfigError, Ev3dgsError
from ..splat.model import GaussianModel
from ..splat.rasterize import rasterization
from ..splat.strategy import DefaultStrategy, scaled_schedule
from .checkpoint import load_checkpoint, read_checkpoint, save_checkpoint
from .config import TrainConfig
from .data import TrainData, load_train_data
from .edi_prior import anneal_factor, edi_prior_loss
from .events import pair_list, pose_counts
from .frame_noise import blur_weight, estimate_noise, update_mse
from .init import init_bounds
from .losses import (average_loss, blur_average, log_intensity, noise_event_loss, pose_event_loss,
                     srgb_to_linear_hdr_torch, srgb_to_linear_torch, update_floor)
from .metrics import psnr
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


class Trainer:
    def __init__(self, cfg: TrainConfig, run_dir: str | Path, quiet: bool = False):
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
            print(f"--subpose-px {cfg.subpose_px:g}: {n.min()}-{n.max()} sub-poses per view (mean {n.mean():.1f}) "
                  f"for {mo.min():.1f}-{mo.max():.1f} px of motion per exposure", file=sys.stderr)
        if cfg.hdr and self.data.blur_space != "linear":
            raise ConfigError("--hdr needs the linear-light blur model (--blur-space linear, or a scene whose "
                              "/train transfer is srgb)")
        self.response, self.response_opt = self._response()  # --learn-response (response.py)
        self.model = init_model(self.data, cfg, self.device)
        self.optimizers = self.model.make_optimizers(scene_scale=self.data.scene_scale)
        self.means_lr0 = self.optimizers["means"].param_groups[0]["lr"]
        # densification steps scaled with --iterations (gsplat-style; 30 000 steps = the 3DGS defaults)
        self.strategy = DefaultStrategy(**scaled_schedule(cfg.iterations), scene_scale=self.data.scene_scale,
                                        seed=stream_seed(cfg.seed, "densify"))
        self.strategy_state = self.strategy.initialize_state(len(self.model), device=self.device)
        self.generator = stream_generator(cfg.seed, "views")       # view order
        self.pair_generator = stream_generator(cfg.seed, "pairs")  # --event-pairs draws (train/rng.py)
        self.view_queue: list[int] = []
        self.thresholds = {
            "pos": torch.tensor(math.log(self.data.pos_threshold), device=self.device,
                                requires_grad=cfg.learn_thresholds),
            "neg": torch.tensor(math.log(self.data.neg_threshold), device=self.device,
                                requires_grad=cfg.learn_thresholds)}
        self.threshold_opt = (torch.optim.Adam(list(self.thresholds.values()), lr=1e-3)
                              if cfg.learn_thresholds and cfg.uses_events else None)
        self.step = 0
        self.use_events = cfg.uses_events and self.data.bins is not None
        self.event_floor: float | None = None   # the noise norm's model floor (losses.update_floor)
        self.frame_noise_var = self._frame_noise() if self.use_events else 0.0   # --frame-noise (frame_noise.py)
        self.blur_mse: float | None = None      # the blur term's squared error, tracked over steps
        self.rel_mismatch, self.noise_rate_hz = self._event_noise()
        self.threshold_map = None   # --threshold-map: per-pixel thresholds (threshold_map.py)
        if cfg.threshold_map and self.use_events and self.rel_mismatch > 0:
            from .threshold_map import ThresholdMap

            self.threshold_map = ThresholdMap(self.rel_mismatch, self.data.n_views, self.data.height,
                                              self.data.width, self.device)
        self.edi = self._edi_inputs() if cfg.edi_prior > 0 and self.use_events else None  # --edi-prior
        self.pose_refiner = None  # --refine-poses (issue 16): learnable exposure-trajectory corrections
        if cfg.refine_poses:
            from .pose_refine import PoseRefiner

            self.pose_refiner = PoseRefiner.for_training(self.data, cfg, self.device)

    # ------------------------------------------------------------------ helpers
    def _event_noise(self) -> tuple[float, float]:
        """(relative threshold mismatch, noise events per pixel and second) for the noise norm: --event-mismatch,
        else the scene's simulated settings, else DEFAULT_REL_MISMATCH and no noise events."""
        from .config import DEFAULT_REL_MISMATCH

        d = self.data
        if self.cfg.event_mismatch is not None:
            rel = self.cfg.event_mismatch
        elif d.mismatch_sigma is not None:
            rel = d.mismatch_sigma / (0.5 * (d.pos_threshold + d.neg_threshold))
        else:
            rel = DEFAULT_REL_MISMATCH
        return float(rel), float(d.noise_rate_hz or 0.0)

    def _frame_noise(self) -> float:
        """--frame-noise: the training frames' noise variance (display values, 1 = white), given or estimated
        (log.jsonl records it as sigma in 8-bit levels, with the event weight it sets, where it is above 0)."""
        if self.cfg.frame_noise is not None:
            return (self.cfg.frame_noise / 255.0) ** 2
        return estimate_noise(self.data.images.cpu().numpy(), step=1.0 / 255.0)   # scene files store 8 bits

    def _edi_inputs(self) -> tuple[torch.Tensor, torch.Tensor]:
        """--edi-prior: each view's (N, H, W) log intensity of the blurry frame and where the EDI target holds
        (edi_prior.valid_mask). Refused where the event intensity is not linear in what the blur model averages."""
        from .edi_prior import COMPATIBLE, valid_mask

        d = self.data
        if (d.blur_space, d.event_transfer) not in COMPATIBLE:
            raise ConfigError(f"--edi-prior: the blurry frame's event intensity is not the mean of the sub-poses' "
                              f"with the {d.blur_space} blur model and {d.event_transfer} events (give "
                              f"--blur-space linear for sRGB scenes)")
        with torch.no_grad():
            log_b = log_intensity(d.images, d.color_filter, d.log_knee, d.event_transfer, d.raw_matrix)
        return log_b, valid_mask(d.images, log_b, d.log_knee)

    def _response(self):
        """--learn-response: the curve and its optimizer, refused where the frame is not decoded with sRGB."""
        if not self.cfg.learn_response:
            return None, None
        from .response import RESPONSE_LR, ResponseCurve

        d = self.data
        if d.blur_space != "linear" or (self.cfg.uses_events and d.event_transfer != "srgb"):
            raise ConfigError("--learn-response needs a scene whose frames are decoded with sRGB: the linear-light "
                              f"blur model and sRGB events (this run: {d.blur_space} blur model, "
                              f"{d.event_transfer} events)")
        curve = ResponseCurve(device=self.device)
        return curve, torch.optim.Adam([curve.logits], lr=RESPONSE_LR)

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
        # 3DGS position lr: exponential (log-linear) decay to 1% over the run
        frac = min(1.0, self.step / max(1, self.cfg.iterations))
        self.optimizers["means"].param_groups[0]["lr"] = self.means_lr0 * (0.01 ** frac)

    # ------------------------------------------------------------------ one step
    def train_step(self) -> dict:
        """One optimisation step (bitwise reproducible on the CPU, see :func:`reproducible`)."""
        with reproducible(self.device.type == "cpu"):
            return self._train_step()

    def _train_step(self) -> dict:
        cfg, data = self.cfg, self.data
        self._set_lr()
        if self.step > 0 and self.step % cfg.sh_interval == 0:
            self.model.active_sh_degree = min(self.model.sh_degree, self.model.active_sh_degree + 1)
        v = self._next_view()
        k = data.sub_count(v)  # --subpose-px: this view's own count; the rest of its rows is padding
        poses = data.mid_viewmats[v:v + 1] if cfg.naive else data.viewmats[v][:k]
        if self.pose_refiner is not None:  # the view's corrected sub-poses, differentiable in its corrections
            poses = self.pose_refiner.viewmats(v, poses.dtype)[:k]
        # the b+1 sub-poses in one batched call (one projection, one binning, one kernel over (camera, tile));
        # the densification statistics still count every camera's render separately (info["n_cameras"])
        if self.cfg.backend == "cpu" or (self.cfg.backend == "auto" and self.device.type == "cpu"):
            stack, _, info = self.render(poses)
            infos = [info]
        else:  # reference / gsplat: one render per pose, each with its own means2d for the statistics
            renders, infos = zip(*[(r[0], r[2]) for r in (self.render(pose) for pose in poses)])
            stack = torch.stack(renders)
        for info in infos:
            info["grad_scale"] = float(len(poses))  # each of b+1 renders gets ~1/(b+1) of the gradient
            self.strategy.step_pre_backward(info)
        target = data.images[v]
        # both losses decode the renders to linear light (blur average in linear light, events from linear
        # intensity): decode once, so the decode and its backward run once per step. --hdr: renders above 1
        # decode to radiance above full scale, and the sensor's clip follows the exposure integral
        shown = stack if self.response is None else self.response(stack)  # --learn-response: h(render)
        if cfg.hdr:
            lin = srgb_to_linear_hdr_torch(shown)
        else:
            lin = (srgb_to_linear_torch(shown) if self.response is not None or (
                self.use_events and data.blur_space == "linear" and data.event_transfer == "srgb") else None)
        avg = blur_average(stack, data.blur_space, linear=lin)  # data.blur_space: "auto" resolved from the scene
        if self.response is not None:  # back through h^-1 to the frame's display values
            avg = self.response.inverse(avg)
        l_blur = average_loss(avg, target, cfg.ssim_lambda, clip=cfg.hdr)
        loss = l_blur
        blur_grads = self._blur_grads(l_blur, infos)   # --densify-from blur
        l_event = l_edi = torch.zeros((), device=self.device)
        w_blur = 1.0
        if self.use_events:
            n_pairs = k * (k - 1) // 2  # --event-pairs N: N random pairs, all of them where a view has fewer
            pairs = pair_list(k, cfg.event_pairs if 0 < cfg.event_pairs <= n_pairs else "all", self.pair_generator)
            log_l = log_intensity(stack, data.color_filter, data.log_knee, data.event_transfer, data.raw_matrix,
                                  linear=lin)
            counts = pose_counts(data.bins[v][:k - 1])
            tp, tn = self.thresholds["pos"].exp(), self.thresholds["neg"].exp()
            if cfg.event_norm == "count":
                l_event = pose_event_loss(log_l, counts, pairs, tp, tn, data.count_convention)
            else:
                t = data.sub_times[v][:k].astype(np.float64) * 1e-6
                noise = (torch.tensor([self.noise_rate_hz * abs(t[b] - t[a]) for a, b in pairs],
                                      dtype=log_l.dtype, device=log_l.device) if self.noise_rate_hz > 0 else None)
                tmap = self.threshold_map
                tpm, tnm = (tp, tn) if tmap is None else tmap.thresholds(tp, tn)
                posterior = tmap is not None and cfg.map_weights == "posterior"   # --map-weights
                l_event, estimate = noise_event_loss(log_l, counts, pairs, tpm, tnm, data.count_convention,
                                                     self.rel_mismatch, noise, self.event_floor, data.log_knee,
                                                     tmap.spread if posterior else None, cfg.floor_stat,
                                                     cfg.huber_c)
                self.event_floor = update_floor(self.event_floor, estimate)
                if tmap is not None:  # this view's equations at the current render; the map solved again
                    tmap.update(v, data.bins[v][:k - 1], tp, tn, self.event_floor, log_l, data.log_knee)
                fade = anneal_factor(self.step, cfg.iterations, cfg.edi_anneal) if self.edi is not None else 0.0
                if fade > 0:  # --edi-prior: each sub-pose's EDI target, weighted by its expected error
                    l_edi = edi_prior_loss(log_l, counts, self.edi[0][v], self.edi[1][v], tpm, tnm,
                                           self.event_floor, data.count_convention, self.rel_mismatch,
                                           self.noise_rate_hz, t, data.log_knee,
                                           tmap.spread if posterior else None)   # the map as updated
                    loss = loss + cfg.edi_prior * fade * l_edi
            # --frame-noise: where the frames' noise is most of the blur term's error, the events weigh more
            w_blur = blur_weight(self.frame_noise_var, self.blur_mse)
            loss = loss + (cfg.omega / w_blur) * l_event
        loss.backward()
        self._guard(loss, l_blur, l_event)
        for opt in self.optimizers.values():
            opt.step()
            opt.zero_grad(set_to_none=True)
        for opt in (self.threshold_opt, self.response_opt):
            if opt is not None:
                opt.step()
                opt.zero_grad(set_to_none=True)
        pose_info = self.pose_refiner.step(self.step) if self.pose_refiner is not None else {}
        refined = {}
        if cfg.densify:
            for info, grad in zip(infos, blur_grads or ()):   # the statistics see the blur term's gradient only
                info["means2d"].grad = grad
            refined = self.strategy.step_post_backward(self.model, self.optimizers, self.strategy_state,
                                                       self.step, infos)
        self.step += 1
        with torch.no_grad():  # the blurry frame as the loss saw it (averaged in data.blur_space)
            p = psnr(avg.detach().clamp(0, 1), target)
            if self.frame_noise_var > 0:
                self.blur_mse = update_mse(self.blur_mse, float(torch.mean(
                    (avg.detach().clamp(0, 1) - target.to(avg.dtype)) ** 2)))
        return {"step": self.step, "view": v, "loss": loss.item(), "blur": l_blur.item(), "event": l_event.item(),
                "psnr_blurry": p, "gaussians": len(self.model), **refined, **pose_info,
                **({"edi": l_edi.item()} if self.edi is not None else {}),
                **({"subposes": k} if data.n_sub is not None else {}),
                **({"event_weight": cfg.omega / w_blur, "frame_noise": 255.0 * math.sqrt(self.frame_noise_var)}
                   if self.frame_noise_var > 0 else {})}

    def trained_parameters(self) -> list[torch.Tensor]:
        """Every tensor a step updates: the Gaussians, the learned thresholds and whatever any optimizer of
        the trainer holds (so parameters added later are covered by the NaN guard without listing them). The
        pose corrections of --refine-poses are not listed: PoseRefiner.step skips a non-finite pose gradient
        itself (counted as pose_skipped in log.jsonl) rather than stopping the run."""
        out = {id(p): p for p in self.model.params.values()}
        out.update({id(p): p for p in self.thresholds.values() if p.requires_grad})
        opts = list(self.optimizers.values()) + [o for o in vars(self).values()
                                                  if isinstance(o, torch.optim.Optimizer)]
        for opt in opts:
            for group in opt.param_groups:
                out.update({id(p): p for p in group["params"]})
        return list(out.values())

    def _blur_grads(self, l_blur: torch.Tensor, infos: list[dict]) -> tuple | None:
        """--densify-from blur, while the strategy still densifies: the blur term's gradient at each render's
        screen-space means (the strategy's statistics), so that the event term's weight, which grows with
        the events' precision, does not decide how many Gaussians are split. None: the statistics come from
        the whole loss's gradient, as the backward pass leaves it."""
        if not (self.cfg.densify_source == "blur" and self.use_events and self.cfg.densify
                and self.step < self.strategy.refine_stop):
            return None
        return torch.autograd.grad(l_blur, [info["means2d"] for info in infos], retain_graph=True,
                                   allow_unused=True)

    def _guard(self, loss, l_blur, l_event) -> None:
        bad = not torch.isfinite(loss)
        if not bad:  # a sum is finite only if every term is (inf or NaN anywhere makes it inf or NaN); a finite
            # gradient whose sum overflows is told apart by the element-wise test, which only runs then
            bad = any(p.grad is not None and not torch.isfinite(p.grad.sum()) and not torch.isfinite(p.grad).all()
                      for p in self.trained_parameters())
        if bad:
            ckpt = self.run_dir / "ckpt.pt"
            where = f"the last good checkpoint is {ckpt}" if ckpt.exists() else "no checkpoint was written yet"
            raise TrainingError(f"non-finite loss or gradient at step {self.step + 1} (blur {l_blur.item():.4g}, "
                                f"event {l_event.item():.4g}); stopped, {where}")

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
        rec = {}
        try:
            while self.step < self.cfg.iterations:
                rec = self.train_step()
                rec["seconds"] = time.perf_counter() - t0
                log.write(json.dumps(rec) + "\n")
                bar.update(1)
                bar.set_postfix(loss=f"{rec['loss']:.4f}", psnr=f"{rec['psnr_blurry']:.2f}",
                                gaussians=rec["gaussians"], refresh=False)
                if self.step % self.cfg.checkpoint_every == 0 or self.step == self.cfg.iterations:
                    log.flush()
                    save_checkpoint(ckpt, self)
                if on_step is not None:
                    on_step(self, rec)
        finally:
            bar.close()
            log.close()
        self.save_model()
        plot_curves(self.run_dir / "log.jsonl", self.run_dir / "training.png")
        return rec

    def save_model(self) -> None:
        """model.pt (and config.json) in the run folder: what eval, render and export read."""
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self.cfg.save(self.run_dir / "config.json")
        from ..outputs import atomic_path

        with atomic_path(self.run_dir / "model.pt") as tmp:  # on failure: temporary removed, OutputError
            torch.save({"model": self.model.state_dict(),
                        "thresholds": {k: v.detach().exp().item() for k, v in self.thresholds.items()},
                        # --threshold-map: (2, H, W) ON/OFF multipliers of the thresholds above
                        "threshold_map": (None if self.threshold_map is None
                                          else self.threshold_map.multiplier.clone())}, tmp)
        if self.response is not None:  # --learn-response: the curve, for the user to read
            with atomic_path(self.run_dir / "response.json") as tmp:
                tmp.write_text(json.dumps(self.response.table(), indent=1) + "\n")
        else:
            (self.run_dir / "response.json").unlink(missing_ok=True)
        if self.pose_refiner is not None:  # the refined trajectory, read by eval
            self.pose_refiner.save(self.run_dir / "trajectory.npz")
        else:  # never leave an older run's trajectory beside this model
            (self.run_dir / "trajectory.npz").unlink(missing_ok=True)


# what `ev3dgs train` and `ev3dgs eval` write in a run folder; a fresh run removes them (and nothing else)
RUN_FILES = ("config.json", "model.pt", "ckpt.pt", "log.jsonl", "metrics.json", "trajectory.npz", "training.png",
             "response.json")
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
    ax[0].semilogy(steps, [r["blur"] for r in recs], label="blur loss", lw=0.8)
    if any(r["event"] for r in recs):
        ax[0].semilogy(steps, [max(r["event"], 1e-12) for r in recs], label="event loss (unweighted)", lw=0.8)
    ax[0].legend(fontsize=8)
    ax[0].set_xlabel("step")
    ax[1].plot(steps, [r["psnr_blurry"] for r in recs], lw=0.8)
    ax[1].set_ylabel("PSNR vs blurry input (dB)")
    ax[1].set_xlabel("step")
    fig.tight_layout()
    fig.savefig(png, dpi=100)
    plt.close(fig)
