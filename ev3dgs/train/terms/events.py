"""[events]: the event rendering loss. From the log intensity of the view's sub-pose renders, each pair's
change against what the exposure's ON/OFF counts say, weighted by the event noise model (norm "noise", the
default: losses.noise_event_loss) or in events (norm "count", E2NeRF/Ev3DGS: losses.pose_event_loss).

The noise model is one object (EventNoise): the sensor's relative threshold mismatch and its noise-event rate,
read from the scene's declared sensor model (/events attrs, schema.SENSOR_MODEL_ATTRS) or events.mismatch,
the floor statistic and the Huber corner. It also holds the learned global thresholds (events.learn_thresholds)
and the frames' noise weighting (events.frame_noise: the event weight grows as the blur term's error comes
down to the frames' noise; frame_noise.py). A [threshold_map] term, where there is one, gives it per-pixel
thresholds and their spread."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from ..events import pair_list, pose_counts
from ..frame_noise import blur_weight, estimate_noise, update_mse
from ..losses import log_intensity, noise_event_loss, pose_event_loss, update_floor
from ..readback import to_device
from . import Term, register

# sigma / theta assumed when the scene does not declare its sensor's mismatch (DAVIS346: a few hundredths of
# log units for thresholds 0.1-0.3)
DEFAULT_REL_MISMATCH = 0.1
DEFAULT_NOISE_RATE_HZ = 0.0   # noise events per pixel and second assumed when the scene does not say


@dataclass(frozen=True)
class EventNoise:
    """What the noise norm expects of the counts (losses.count_variance) and how it shapes the residuals."""
    rel_mismatch: float        # per-pixel threshold spread / the mean threshold
    noise_rate_hz: float       # noise events per pixel and second (leak + shot noise)
    floor_stat: str            # "mean", "median" or "chi2" (losses.noise_event_loss)
    huber_c: float             # > 0: residuals beyond this many standard deviations pull as |r|
    knee: float | None         # the log model's linear floor (linear intensity)
    convention: str            # the scene's count convention

    def noise_events(self, times_s: np.ndarray, pairs, like: torch.Tensor) -> torch.Tensor | None:
        """(P,) expected noise events per pixel in each pair's window, or None without noise events."""
        if not self.noise_rate_hz > 0:
            return None
        return to_device([self.noise_rate_hz * abs(times_s[b] - times_s[a]) for a, b in pairs], like.dtype,
                         like.device)

    @property
    def device_floor(self) -> bool:
        """The floor is tracked on the device (a 0-dim float64 tensor, nothing read back per step): the mean and
        median statistics; chi2 is solved on the host (losses.chi2_floor reads a few scalars per step)."""
        return self.floor_stat != "chi2"

    def loss(self, log_l, counts, pairs, tp, tn, times_s, floor, spread=None):
        """(loss, this step's floor estimate): losses.noise_event_loss with this model."""
        return noise_event_loss(log_l, counts, pairs, tp, tn, self.convention, self.rel_mismatch,
                                self.noise_events(times_s, pairs, log_l), floor, self.knee, spread,
                                self.floor_stat, self.huber_c, self.device_floor)


def sensor_model(cfg, data) -> tuple[float, float, dict]:
    """(relative mismatch, noise rate, record): events.mismatch, else the scene's declared sensor model
    (/events mismatch_sigma, leak_rate_hz, shot_noise_rate_hz), else (files made before the sensor model was
    declared) the simulator's provenance (a legacy path, data.legacy_sensor_noise), else DEFAULT_REL_MISMATCH
    and no noise events. The record says which values were used and where each came from (log.jsonl's first
    line and metrics: ``sensor_model``)."""
    d = data
    theta = 0.5 * (d.pos_threshold + d.neg_threshold)
    if cfg.event_mismatch is not None:
        rel, rel_from = cfg.event_mismatch, "events.mismatch"
    elif d.mismatch_sigma is not None:
        rel, rel_from = d.mismatch_sigma / theta, d.sensor_source["mismatch_sigma"]
    else:
        rel, rel_from = DEFAULT_REL_MISMATCH, "default"
    if d.noise_rate_hz is not None:
        rate, rate_from = d.noise_rate_hz, d.sensor_source["noise_rate_hz"]
    else:
        rate, rate_from = DEFAULT_NOISE_RATE_HZ, "default"
    record = {"rel_mismatch": float(rel), "rel_mismatch_from": rel_from, "noise_rate_hz": float(rate),
              "noise_rate_from": rate_from}
    return float(rel), float(rate), record


@register
class Events(Term):
    table = "events"
    builtin = True
    wants_linear = True   # the blur term decodes the renders once for both

    @classmethod
    def build(cls, trainer):
        if not (trainer.cfg.uses_events and trainer.data.bins is not None):
            return None
        return cls(trainer)

    def __init__(self, trainer):
        super().__init__(trainer)
        from ..rng import stream_generator

        cfg, d, dev = trainer.cfg, trainer.data, trainer.device
        self.pair_generator = stream_generator(cfg.seed, "pairs")   # events.pairs draws (train/rng.py)
        self.thresholds = {
            "pos": torch.tensor(math.log(d.pos_threshold), device=dev, requires_grad=cfg.learn_thresholds),
            "neg": torch.tensor(math.log(d.neg_threshold), device=dev, requires_grad=cfg.learn_thresholds)}
        self.threshold_opt = (torch.optim.Adam(list(self.thresholds.values()), lr=1e-3)
                              if cfg.learn_thresholds else None)
        # the noise norm's model floor (losses.update_floor) and the blur term's squared error tracked over
        # steps: 0-dim float64 tensors on the device where nothing needs them on the host (floor: see
        # EventNoise.device_floor), else floats; the ``floor`` and ``blur_mse`` properties read them back
        self._floor = None
        self.frame_noise_var = self._frame_noise()
        self._blur_mse = None
        self.rel_mismatch, self.noise_rate_hz, self.sensor_record = sensor_model(cfg, d)
        self.noise = EventNoise(self.rel_mismatch, self.noise_rate_hz, cfg.floor_stat, cfg.huber_c, d.log_knee,
                                d.count_convention)

    def _frame_noise(self) -> float:
        """events.frame_noise: the training frames' noise variance (display values, 1 = white), given or
        estimated (log.jsonl records it as sigma in 8-bit levels, with the event weight it sets, where > 0)."""
        cfg = self.trainer.cfg
        if cfg.frame_noise is not None:
            return (cfg.frame_noise / 255.0) ** 2
        return estimate_noise(self.trainer.data.images.cpu().numpy(), step=1.0 / 255.0)  # files store 8 bits

    def cameras(self, step):
        return step.poses   # the same renders as the blur term's

    def loss(self, step):
        cfg, data, v, k = self.trainer.cfg, self.trainer.data, step.view, step.k
        n_pairs = k * (k - 1) // 2  # events.pairs N: N random pairs, all of them where a view has fewer
        pairs = pair_list(k, cfg.event_pairs if 0 < cfg.event_pairs <= n_pairs else "all", self.pair_generator)
        log_l = log_intensity(step.images(self), data.color_filter, data.log_knee, data.event_transfer,
                              data.raw_matrix, linear=step.shared.get("linear"))
        counts = pose_counts(data.bins[v][:k - 1])
        tp, tn = self.thresholds["pos"].exp(), self.thresholds["neg"].exp()
        tmap = self.trainer.term("threshold_map")
        if cfg.event_norm == "count":
            l_event = pose_event_loss(log_l, counts, pairs, tp, tn, data.count_convention)
        else:
            t = data.sub_times[v][:k].astype(np.float64) * 1e-6
            tpm, tnm = (tp, tn) if tmap is None else tmap.map.thresholds(tp, tn)
            spread = tmap.posterior_spread() if tmap is not None else None   # threshold_map.weights
            l_event, estimate = self.noise.loss(log_l, counts, pairs, tpm, tnm, t, self._floor, spread)
            self._floor = update_floor(self._floor, estimate)
            if tmap is not None:  # this view's equations at the current render; the map solved again
                tmap.map.update(v, data.bins[v][:k - 1], tp, tn, self._floor, log_l, data.log_knee)
            # what the EDI prior of this step reads (the map as updated)
            step.shared.update(log_l=log_l, counts=counts, thresholds=(tpm, tnm), times_s=t, event_floor=self._floor,
                               spread=tmap.posterior_spread() if tmap is not None else None)
        # events.frame_noise: where the frames' noise is most of the blur term's error, the events weigh more
        w_blur = blur_weight(self.frame_noise_var, self._blur_mse)
        logs = {"event": l_event.detach()}   # read back with the step's record (readback.py)
        if self.frame_noise_var > 0:
            logs.update(frame_noise=255.0 * math.sqrt(self.frame_noise_var))
        # omega / w: a tensor w divides as a tensor (a Python float over a tensor is its reciprocal times it)
        weight = (torch.div(torch.full_like(w_blur, cfg.omega), w_blur) if torch.is_tensor(w_blur)
                  else cfg.omega / w_blur)
        if self.frame_noise_var > 0:
            logs["event_weight"] = weight
        # a 0-dim float64 weight times the 0-dim float32 loss would be float64: cast first, as a Python float is
        return (weight.to(l_event.dtype) if torch.is_tensor(weight) else weight) * l_event, logs

    def parameters(self):
        return [p for p in self.thresholds.values() if p.requires_grad]

    def after_backward(self, step):
        if self.threshold_opt is not None:
            self.threshold_opt.step()
            self.threshold_opt.zero_grad(set_to_none=True)
        return {}

    def after_step(self, step):
        if self.frame_noise_var > 0:
            avg = step.shared["average"].detach().clamp(0, 1)
            mse = torch.mean((avg - step.target.to(avg.dtype)) ** 2).to(torch.float64)   # exact widening
            self._blur_mse = update_mse(self._blur_mse, mse)
        return {}

    def save(self, payload):
        payload["rng"]["pairs"] = self.pair_generator.get_state()
        payload["thresholds"] = {k: v.detach().clone() for k, v in self.thresholds.items()}
        payload["threshold_opt"] = None if self.threshold_opt is None else self.threshold_opt.state_dict()
        payload["event_floor"] = self.floor          # floats (read back: a checkpoint is a read-back step)
        payload["blur_mse"] = self.blur_mse

    def load(self, payload, path):
        if "pairs" in payload["rng"]:
            self.pair_generator.set_state(payload["rng"]["pairs"])
        for k, v in (payload.get("thresholds") or {}).items():
            self.thresholds[k].data.copy_(v)
        if self.threshold_opt is not None and payload.get("threshold_opt") is not None:
            self.threshold_opt.load_state_dict(payload["threshold_opt"])
        floor = payload.get("event_floor")   # absent in checkpoints of the count norm, which has none
        self._floor = None if floor is None else self._tracked(float(floor), self.noise.device_floor)
        mse = payload.get("blur_mse")        # absent without frame noise and in older checkpoints
        self._blur_mse = None if mse is None else self._tracked(float(mse), True)

    def _tracked(self, value: float, on_device: bool):
        return torch.tensor(value, dtype=torch.float64, device=self.trainer.device) if on_device else value

    @property
    def floor(self) -> float | None:
        """The noise norm's model floor as a float (reads it back from the device; None before the first step)."""
        return None if self._floor is None else float(self._floor)

    @property
    def blur_mse(self) -> float | None:
        """The blur term's tracked squared error as a float (reads it back; None before the first step)."""
        mse = None if self._blur_mse is None else float(self._blur_mse)
        return None if mse is None or math.isnan(mse) else mse   # NaN: nothing tracked yet (update_mse)

    def model_extras(self):
        return {"thresholds": {k: v.detach().exp().item() for k, v in self.thresholds.items()}}

    def write(self, run_dir):
        """RUN/sensor_model.json: the event noise model this run used and where each value came from."""
        import json

        from ...outputs import atomic_path

        record = {**self.sensor_record, "floor_stat": self.noise.floor_stat, "huber_c": self.noise.huber_c,
                  "norm": self.trainer.cfg.event_norm}
        with atomic_path(run_dir / "sensor_model.json") as tmp:
            tmp.write_text(json.dumps(record, indent=1) + "\n")
