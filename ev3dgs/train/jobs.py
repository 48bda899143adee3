"""Independent trainings side by side: each in its own spawned process with one thread.

CPU training gives bitwise the same result for any thread count (trainer.reproducible), and on a small scene
one training scales sublinearly past one thread (the demo scene: ~1.5x from 1 to 2 threads), so N trainings at once
on N cores finish sooner than N one after the other with N threads each, with the same numbers.
"""
from __future__ import annotations

import multiprocessing as mp
import os
from concurrent.futures import ProcessPoolExecutor, as_completed

ONE_THREAD = {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "NUMBA_NUM_THREADS": "1"}


def default_jobs() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def run_parallel(fn, items: list, n_jobs: int, on_done=None) -> list:
    """[fn(item) for item in items], n_jobs at a time in one-thread worker processes (n_jobs <= 1: here, in
    order); results in item order. `fn` must be importable (module level); on_done(result) is called as each
    finishes. Items are submitted in the given order: put the longest first."""
    if n_jobs <= 1 or len(items) <= 1:
        out = []
        for it in items:
            out.append(fn(it))
            if on_done:
                on_done(out[-1])
        return out
    old = {k: os.environ.get(k) for k in ONE_THREAD}
    os.environ.update(ONE_THREAD)          # inherited by the spawned workers before they import torch/numba
    try:
        with ProcessPoolExecutor(min(n_jobs, len(items)), mp_context=mp.get_context("spawn")) as pool:
            futures = {pool.submit(fn, it): i for i, it in enumerate(items)}
            done = [None] * len(items)
            for f in as_completed(futures):
                done[futures[f]] = f.result()
                if on_done:
                    on_done(done[futures[f]])
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    return done
