"""Reading a training step's values back to the host in batches, not one `.item()` at a time.

A step leaves its log values on the device: losses as 0-dim tensors, and values that need a host-side formula
(PSNR from a squared error) as :class:`Later`. :func:`read_back` turns every such entry of a list of step
records into a Python float with ONE device-to-host transfer (everything stacked as float64, then `.tolist()`),
in place. A float32 loss widened to float64 is exact, so the floats are those `.item()` would have given.

On a CUDA device every read is a synchronisation: the host waits until the device has run everything queued
before it, so the next step's kernels cannot be queued while this one runs. The trainer reads back every
``readback_every`` steps (train.toml, top level) and at every checkpoint, not at every step (trainer.py)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch


@dataclass(frozen=True)
class Later:
    """A device scalar whose logged value is ``fn(float(value))``, computed when it is read back."""
    value: torch.Tensor
    fn: Callable[[float], float] = float

    def __float__(self) -> float:   # read at once (an on_step callback printing a value before its read-back)
        return float(self.fn(float(self.value)))

    def __format__(self, spec: str) -> str:
        return format(float(self), spec)


def pending(value) -> bool:
    """True for an entry read_back will convert (a tensor or a Later)."""
    return isinstance(value, (torch.Tensor, Later))


def read_back(recs: list[dict]) -> None:
    """Replace every tensor and Later value of ``recs`` (dicts, one level deep) by its float, with one
    device-to-host transfer for all of them (none when there is nothing to read)."""
    where, values = [], []
    for rec in recs:
        for key, v in rec.items():
            if pending(v):
                t = v.value if isinstance(v, Later) else v
                where.append((rec, key, v))
                values.append(t.detach().reshape(()).to(torch.float64))
    if not values:
        return
    host = torch.stack(values).tolist()   # the one read
    for (rec, key, v), x in zip(where, host):
        rec[key] = v.fn(x) if isinstance(v, Later) else x


def to_device(data, dtype: torch.dtype, device) -> torch.Tensor:
    """A small host array (a list, a NumPy array) as a tensor on ``device`` without waiting for the device: a
    blocking host-to-device copy synchronises the stream (as a read does); a non-blocking one from pageable
    memory is staged at once and queued. (A no-op copy on the CPU.)"""
    return torch.as_tensor(data, dtype=dtype).to(device, non_blocking=True)
