"""Separate random streams of one training seed: the view order, the event-pair draws, the random initial
Gaussians and the densification's split noise each have their own generator, so that changing how one of
them is used (e.g. ``--event-pairs``, which draws pairs every step) leaves the others' sequences as they were.

Each stream's seed is numpy's ``SeedSequence(seed, spawn_key=(i,))`` (what ``SeedSequence(seed).spawn()`` gives
its i-th child): the streams' seeds are hashed apart, not ``seed + i`` (seed 1's view stream is not seed 0's
pair stream).
"""
from __future__ import annotations

import numpy as np
import torch

# Stream ids are part of the reproducibility contract: append new streams, never reorder.
STREAMS = ("views", "pairs", "init", "densify")


def stream_seed(seed: int, name: str) -> int:
    """A 63-bit seed for stream ``name`` of the training seed ``seed`` (>= 0)."""
    if name not in STREAMS:
        raise ValueError(f"unknown random stream {name!r} (known: {', '.join(STREAMS)})")
    ss = np.random.SeedSequence(int(seed), spawn_key=(STREAMS.index(name),))
    return int(ss.generate_state(1, np.uint64)[0] >> np.uint64(1))


def stream_generator(seed: int, name: str) -> torch.Generator:
    """A CPU torch.Generator seeded for stream ``name``."""
    return torch.Generator().manual_seed(stream_seed(seed, name))
