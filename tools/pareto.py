"""Shared by the benchmarks and studies: JSON results with the machine noted, and a Pareto plot (accuracy
against seconds, Pareto front marked)."""
from __future__ import annotations

import json
import os
import platform
from pathlib import Path


def machine() -> str:
    return f"{platform.machine()}, {os.cpu_count()} cores"


def save_json(path: str, payload: dict, machine_note: str = "") -> None:
    """payload as JSON at path (folders created), with "machine" (plus an optional note, e.g. threads)."""
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text(json.dumps({"machine": machine() + machine_note, **payload}, indent=2))


def pareto_front(points: list[tuple[float, float]], higher_is_better: bool = True) -> list[int]:
    """Indices of the points no other point beats on both time (lower) and accuracy."""
    front = []
    for i, (t, a) in enumerate(points):
        dominated = any((t2 <= t and (a2 >= a if higher_is_better else a2 <= a)) and (t2, a2) != (t, a)
                        for t2, a2 in points)
        if not dominated:
            front.append(i)
    return front


def pareto_plot(path: str, series: dict[str, list[dict]], x: str, y: str, xlabel: str, ylabel: str, title: str,
                label_key: str = "label", higher_is_better: bool = True, logx: bool = True) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 3.8))
    allpts = []
    for name, rows in series.items():
        xs, ys = [r[x] for r in rows], [r[y] for r in rows]
        ax.plot(xs, ys, "o-", ms=4, lw=1, label=name)
        for r in rows:
            ax.annotate(str(r[label_key]), (r[x], r[y]), fontsize=7, xytext=(3, 3), textcoords="offset points")
        allpts += list(zip(xs, ys))
    front = sorted((allpts[i] for i in pareto_front(allpts, higher_is_better)))
    if front:
        ax.plot([p[0] for p in front], [p[1] for p in front], "k--", lw=0.8, label="Pareto front")
    if logx:
        ax.set_xscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=10)
    ax.legend(fontsize=7)
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
