"""Adaptive density control (clone / split / prune / opacity reset), gsplat DefaultStrategy style.

The running statistics live in a plain ``state`` dict owned by the caller, not in the model.
Every structural change goes through :func:`_update_param_and_optimizer`, which replaces the
Parameter in ``model.params`` *and* in every optimizer param group holding it, carrying the Adam
moments (``exp_avg``, ``exp_avg_sq``, ...) row by row; the scalar ``step`` is kept as is.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Iterable

import torch
from torch import Tensor, nn

from .model import LOG_SCALE_MAX, LOG_SCALE_MIN, GaussianModel

__all__ = ["DefaultStrategy", "quat_to_rotmat", "scaled_schedule", "REFERENCE_STEPS"]

# The DefaultStrategy step defaults (refine 500..15000 every 100, opacity reset every 3000) are inria 3DGS's for
# a 30 000-step run; gsplat's trainer multiplies all four by steps / 30 000 (its --steps_scaler).
REFERENCE_STEPS = 30_000
# Floor on the refinement interval of a scaled schedule: the screen-gradient statistic is a mean over the
# renders since the last refinement, and over fewer than ~10 views it is mostly the noise of one view.
MIN_REFINE_EVERY = 10


def scaled_schedule(iterations: int, reference: int = REFERENCE_STEPS,
                    min_refine_every: int = MIN_REFINE_EVERY) -> dict[str, int]:
    """The densification steps for a run of ``iterations`` steps: DefaultStrategy's defaults times
    ``iterations / reference`` (rounded; so ``iterations == reference`` gives exactly the defaults), with
    refine_every >= min(min_refine_every, 100) and reset_every >= refine_every. The oversized-Gaussian prune,
    which starts after the first opacity reset, moves with reset_every. E.g. 600 steps: refine from step 10
    to 300 every 10, opacity reset at 60, 120, 180, 240."""
    if iterations < 1 or reference < 1:
        raise ValueError(f"iterations and reference must be >= 1, got {iterations}, {reference}")
    d = DefaultStrategy
    f = iterations / reference
    every = max(min(min_refine_every, d.refine_every), round(d.refine_every * f), 1)
    return {"refine_start": max(1, round(d.refine_start * f)),
            "refine_stop": max(2, round(d.refine_stop * f)),
            "refine_every": every,
            "reset_every": max(every, round(d.reset_every * f))}

ParamFn = Callable[[str, Tensor], Tensor]
OptFn = Callable[[str, str, Tensor], Tensor]


def quat_to_rotmat(q: Tensor) -> Tensor:
    """(N, 4) wxyz (normalised here) -> (N, 3, 3)."""
    q = q / torch.sqrt((q * q).sum(-1, keepdim=True).clamp_min(1e-24))
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(q.shape[:-1] + (3, 3))


@torch.no_grad()
def _update_param_and_optimizer(
    model: GaussianModel,
    optimizers: dict[str, torch.optim.Optimizer],
    param_fn: ParamFn,
    optimizer_fn: OptFn,
    names: Iterable[str] | None = None,
) -> None:
    """Replace ``model.params[name]`` by ``Parameter(param_fn(name, old))`` for each name, and swap
    it in every optimizer that holds the old one.  Per-row optimizer state tensors (same leading
    size as the parameter, e.g. Adam's exp_avg / exp_avg_sq) become ``optimizer_fn(name, key, v)``;
    everything else (``step``) is carried over unchanged."""
    for name in list(names) if names is not None else list(model.params.keys()):
        old = model.params[name]
        new = nn.Parameter(param_fn(name, old.detach()), requires_grad=old.requires_grad)
        for opt in optimizers.values():
            for group in opt.param_groups:
                for i, p in enumerate(group["params"]):
                    if p is not old:
                        continue
                    st = opt.state.pop(old, None)
                    if st is not None:
                        for key, v in list(st.items()):
                            if key != "step" and isinstance(v, Tensor) and v.shape == old.shape:
                                st[key] = optimizer_fn(name, key, v)
                        opt.state[new] = st
                    group["params"][i] = new
        model.params[name] = new


def _update_state(state: dict, fn: Callable[[Tensor], Tensor]) -> None:
    for k, v in list(state.items()):
        if isinstance(v, Tensor) and v.dim() >= 1:
            state[k] = fn(v)


@dataclass
class DefaultStrategy:
    """3DGS densification with gsplat / inria defaults (grad threshold in NDC-like units)."""

    grow_grad2d: float = 2e-4
    grow_scale3d: float = 0.01
    prune_opa: float = 0.005
    prune_scale3d: float = 0.1
    prune_scale2d: float = 0.15
    refine_start: int = 500
    refine_stop: int = 15_000
    refine_every: int = 100
    reset_every: int = 3000
    reset_value: float = 0.01
    n_split: int = 2
    scene_scale: float = 1.0
    seed: int | None = 0
    verbose: bool = False

    def __post_init__(self) -> None:
        self._gen: torch.Generator | None = None

    # ---------------------------------------------------------------- state
    def initialize_state(self, n: int, device=None) -> dict:
        z = lambda: torch.zeros(n, dtype=torch.float32, device=device)  # noqa: E731
        return {"grad2d": z(), "count": z(), "max_radius2d": z()}

    def step_pre_backward(self, info: dict) -> None:
        m2d = info["means2d"]
        if m2d.requires_grad:
            m2d.retain_grad()

    # ---------------------------------------------------------- accumulation
    @torch.no_grad()
    def accumulate(self, state: dict, info: dict) -> None:
        """Add one render's screen-space gradient norms (pixels * (W/2, H/2) -> NDC-like units).

        ``info['grad_scale']`` (optional, default 1) multiplies the gradient, e.g. the number
        of renders averaged into one image by a blur loss."""
        m2d = info["means2d"]
        grad = m2d.grad
        if grad is None:
            return
        n = state["count"].shape[0]
        w, h = float(info["width"]), float(info["height"])
        g = grad.detach().reshape(-1, n, 2).to(state["grad2d"])
        g = g * self._ndc_scale(w, h, g.dtype, g.device)
        g = g * float(info.get("grad_scale", 1.0))
        radii = info["radii"].detach()
        if radii.shape[-1] == 2 and radii.dim() >= 2 and radii.numel() == 2 * n * g.shape[0]:
            radii = radii.max(dim=-1).values  # gsplat >= 1.5 per-axis radii
        radii = radii.reshape(-1, n).to(state["grad2d"])
        # masked element-wise adds, one camera row at a time in a fixed order: no index_add_ / scatter
        # (whose CPU kernels may accumulate in a thread-dependent order), so the sums are bitwise
        # reproducible for any thread count
        zero = state["grad2d"].new_zeros(())
        norms = g.norm(dim=-1)
        for c in range(radii.shape[0]):
            sel = radii[c] > 0
            state["grad2d"] += torch.where(sel, norms[c], zero)
            state["count"] += sel.to(state["count"].dtype)
            r = torch.where(sel, radii[c] / float(max(w, h)), zero)
            torch.maximum(state["max_radius2d"], r, out=state["max_radius2d"])

    # --------------------------------------------------------------- main hook
    def step_post_backward(
        self,
        model: GaussianModel,
        optimizers: dict[str, torch.optim.Optimizer],
        state: dict,
        step: int,
        infos: list[dict] | dict,
    ) -> dict:
        if isinstance(infos, dict):
            infos = [infos]
        if step >= self.refine_stop:
            return {}
        if state["count"].shape[0] != len(model):
            raise ValueError(f"state has {state['count'].shape[0]} rows, model {len(model)}")
        for info in infos:
            self.accumulate(state, info)
        out: dict = {}
        if step >= self.refine_start and step % self.refine_every == 0:
            n_clone, n_split = self._grow(model, optimizers, state)
            n_prune = self._prune(model, optimizers, state, step)
            for v in state.values():
                if isinstance(v, Tensor):
                    v.zero_()
            out = {"cloned": n_clone, "split": n_split, "pruned": n_prune}
            if self.verbose:
                print(f"step {step}: cloned {n_clone} split {n_split} pruned {n_prune} -> {len(model)}")
        if step > 0 and step % self.reset_every == 0:
            self.reset_opacity(model, optimizers)
            out["reset"] = True
        return out

    # ------------------------------------------------------------- operations
    @torch.no_grad()
    def _grow(self, model, optimizers, state) -> tuple[int, int]:
        avg = state["grad2d"] / state["count"].clamp_min(1)
        is_high = avg > self.grow_grad2d
        is_small = model.scales.max(dim=-1).values <= self.grow_scale3d * self.scene_scale
        is_clone = is_high & is_small
        is_split = is_high & ~is_small
        n_clone, n_split = int(is_clone.sum()), int(is_split.sum())
        if n_clone:
            self.clone(model, optimizers, state, is_clone)
            # clones are appended at the end and are not split in this densification step
            is_split = torch.cat([is_split, is_split.new_zeros(n_clone)])
        if n_split:
            self.split(model, optimizers, state, is_split)
        return n_clone, n_split

    @torch.no_grad()
    def _prune(self, model, optimizers, state, step) -> int:
        mask = model.opacities < self.prune_opa
        if step > self.reset_every:
            mask |= model.scales.max(dim=-1).values > self.prune_scale3d * self.scene_scale
            mask |= state["max_radius2d"] > self.prune_scale2d
        n = int(mask.sum())
        if n:
            self.prune(model, optimizers, state, mask)
        return n

    @torch.no_grad()
    def clone(self, model, optimizers, state, mask: Tensor) -> None:
        """Append copies of the selected Gaussians; Adam rows are copied with them."""
        sel = torch.where(mask)[0]
        _update_param_and_optimizer(
            model, optimizers,
            lambda name, p: torch.cat([p, p[sel]]),
            lambda name, key, v: torch.cat([v, v[sel]]),
        )
        _update_state(state, lambda v: torch.cat([v, v[sel]]))

    @torch.no_grad()
    def split(self, model, optimizers, state, mask: Tensor) -> None:
        """Replace each selected Gaussian by ``n_split`` children sampled from N(mean, Sigma),
        scales / (0.8 * n_split); children get zero Adam moments.  Kept rows come first."""
        sel = torch.where(mask)[0]
        rest = torch.where(~mask)[0]
        ns = self.n_split
        scales = model.scales[sel]
        rot = quat_to_rotmat(model.params["quats"][sel])
        noise = torch.randn((ns, len(sel), 3), generator=self._generator(), dtype=torch.float32)
        noise = noise.to(device=scales.device, dtype=scales.dtype)
        offsets = torch.einsum("nij,nj,snj->sni", rot, scales, noise)  # (ns, n, 3)
        new_log = torch.log(scales / (0.8 * ns)).clamp(LOG_SCALE_MIN, LOG_SCALE_MAX)

        def param_fn(name: str, p: Tensor) -> Tensor:
            if name == "means":
                child = (p[sel][None] + offsets).reshape(-1, 3)
            elif name == "log_scales":
                child = new_log.repeat(ns, 1)
            elif name == "quats":
                q = p[sel]
                child = (q / torch.sqrt((q * q).sum(-1, keepdim=True).clamp_min(1e-24))).repeat(ns, 1)
            else:
                child = p[sel].repeat((ns,) + (1,) * (p.dim() - 1))
            return torch.cat([p[rest], child])

        def opt_fn(name: str, key: str, v: Tensor) -> Tensor:
            return torch.cat([v[rest], v.new_zeros((ns * len(sel),) + tuple(v.shape[1:]))])

        _update_param_and_optimizer(model, optimizers, param_fn, opt_fn)
        _update_state(state, lambda v: torch.cat([v[rest], v[sel].repeat((ns,) + (1,) * (v.dim() - 1))]))

    @torch.no_grad()
    def prune(self, model, optimizers, state, mask: Tensor) -> None:
        keep = torch.where(~mask)[0]
        _update_param_and_optimizer(
            model, optimizers, lambda name, p: p[keep], lambda name, key, v: v[keep]
        )
        _update_state(state, lambda v: v[keep])

    @torch.no_grad()
    def reset_opacity(self, model, optimizers) -> None:
        """opacity <- min(opacity, reset_value) (via the logit); opacity Adam moments zeroed."""
        # a hair below logit(reset_value) so that float32 sigmoid never exceeds reset_value
        cap = math.log(self.reset_value / (1.0 - self.reset_value)) - 1e-5
        _update_param_and_optimizer(
            model, optimizers,
            lambda name, p: torch.clamp_max(p, cap),
            lambda name, key, v: torch.zeros_like(v),
            names=["opacity_logits"],
        )

    def _ndc_scale(self, w: float, h: float, dtype, device) -> Tensor:
        """(W/2, H/2) on the device, made once per size (a copy to the device at every step would wait for it)."""
        key = (w, h, dtype, device)
        cache = self.__dict__.setdefault("_scales", {})
        if key not in cache:
            cache[key] = torch.tensor([w / 2.0, h / 2.0], dtype=dtype).to(device)
        return cache[key]

    def _generator(self) -> torch.Generator | None:
        if self.seed is None:
            return None
        if self._gen is None:
            self._gen = torch.Generator().manual_seed(int(self.seed))
        return self._gen
