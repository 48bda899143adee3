"""`ev3dgs view ... --out FILE.png`: the viewer's content as one static figure (no server, no browser).

Left: a contact sheet, one row per selected training view: the blurry frame, the sharp frame (where the scene
has one), the view's events (colours from ev3dgs/palette.py, ON red, OFF blue, with a legend; the window is
the exposure, or the interval to the next frame when the exposure holds too few events, and each panel says
which) and, for a run, the model rendered at the mid-exposure pose. Right: a top view of the camera centres and exposure trajectories (looking down the cameras' mean up
vector), and every view's exposure trajectory relative to its start, in its own camera axes.
"""
from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from .. import palette
from ..event_file import EventFile
from . import data

TRAIN, TEST, REFINED, IMU = "#e6781e", "#5050c8", "#c81ea0", "#2a9d8f"


def pick_rows(n: int, rows: int) -> list[int]:
    """`rows` view indices spread evenly over 0..n-1 (all of them when n <= rows)."""
    if n <= rows:
        return list(range(n))
    return sorted({int(round(v)) for v in np.linspace(0, n - 1, rows)})


def _renders(run: data.RunContent, poses: np.ndarray) -> list[np.ndarray]:
    import torch

    from ..train.evaluate import render_views

    c = run.scene
    model = run.model
    K = torch.as_tensor(c.scene.camera.K, dtype=model.dtype)
    bg = torch.as_tensor(c.scene.camera.background or (0, 0, 0), dtype=model.dtype)
    return render_views(model, poses, K, c.size[0], c.size[1], bg, backend="auto")


def _top_view(ax, c: data.SceneContent, refined: np.ndarray | None, refined_t: np.ndarray | None) -> None:
    rots = c.train_poses[:, :, :3, :3]
    basis = data.top_view_basis(rots)
    lines = c.polylines()
    arrow = 0.08 * c.extent
    pts = c.scene.points
    if pts is not None and len(pts.xyz):
        xyz = np.asarray(pts.xyz, np.float64)[:: max(1, len(pts.xyz) // 4000)]
        p2 = xyz @ basis.T
        ax.scatter(p2[:, 0], p2[:, 1], s=1, c="0.8", lw=0, label="/points")
    for i, line in enumerate(lines):
        p2 = line @ basis.T
        ax.plot(p2[:, 0], p2[:, 1], color=TRAIN, lw=1.2, label="training views" if i == 0 else None)
        ax.plot(*p2[0], "o", ms=3, color="#14a03c")
        ax.plot(*p2[-1], "x", ms=4, color="#c81e1e")
    mids = c.mid_poses()
    d = (mids[:, :3, 2] @ basis.T) * arrow
    c2 = mids[:, :3, 3] @ basis.T
    ax.quiver(c2[:, 0], c2[:, 1], d[:, 0], d[:, 1], color=TRAIN, angles="xy", scale_units="xy", scale=1,
              width=0.004)
    if c.imu is not None:
        mid = c.imu.rotations.shape[1] // 2
        good = np.isfinite(c.imu.rotations[:, mid]).all(axis=(1, 2))
        di = (c.imu.rotations[good, mid][:, :, 2] @ basis.T) * arrow
        ax.quiver(c2[good, 0], c2[good, 1], di[:, 0], di[:, 1], color=IMU, angles="xy", scale_units="xy",
                  scale=1, width=0.003, label="IMU-integrated view direction")
    if c.test_poses is not None and len(c.test_poses):
        t2 = c.test_poses[:, :3, 3] @ basis.T
        ax.plot(t2[:, 0], t2[:, 1], "^", color=TEST, ms=5, ls="none", label="test views")
    if refined is not None:
        for i, line in enumerate(data.trajectory_polylines(refined, refined_t)):
            p2 = line @ basis.T
            ax.plot(p2[:, 0], p2[:, 1], color=REFINED, lw=1, ls="--", label="refined" if i == 0 else None)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_title("top view (o start, x end; arrows: view direction)", fontsize=8)
    ax.tick_params(labelsize=6)
    ax.legend(fontsize=6, loc="best")


def _shake(ax, c: data.SceneContent, refined: np.ndarray | None, refined_t: np.ndarray | None) -> None:
    """Each view's sub-pose centres relative to its first one, in that camera's axes (x right, y up)."""
    def rel(poses, pose_t):
        order = np.argsort(pose_t, axis=1, kind="stable")
        p = np.take_along_axis(poses, order[:, :, None, None], axis=1)
        d = p[:, :, :3, 3] - p[:, :1, :3, 3]
        local = np.einsum("nji,nsj->nsi", p[:, 0, :3, :3], d)   # R0^T d
        return local[..., 0], -local[..., 1]

    x, y = rel(c.train_poses, c.pose_t)
    for i in range(len(x)):
        ax.plot(x[i], y[i], color=TRAIN, lw=0.8, alpha=0.8)
        ax.plot(x[i, -1], y[i, -1], "x", ms=3, color="#c81e1e")
    if refined is not None:
        rx, ry = rel(refined, refined_t)
        for i in range(len(rx)):
            ax.plot(rx[i], ry[i], color=REFINED, lw=0.8, ls="--")
    ax.plot(0, 0, "o", ms=3, color="#14a03c")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_title("camera motion in each exposure (own axes)", fontsize=8)
    ax.set_xlabel("right (scene units)", fontsize=7)
    ax.set_ylabel("up", fontsize=7)
    ax.tick_params(labelsize=6)


def draw(content: data.SceneContent | data.RunContent, rows: int = 4):
    """The figure (matplotlib Figure, Agg)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    run = content if isinstance(content, data.RunContent) else None
    c = run.scene if run is not None else content
    n = c.n_views
    idx = pick_rows(n, rows)
    events_col = f"events ({palette.legend_text()})"
    cols = ["blurry frame"] + (["sharp frame"] if c.scene.train is not None and c.scene.train.sharp is not None
                               else []) + [events_col] + (["model render"] if run else [])
    has_poses = c.train_poses is not None
    W, H = c.size
    cell = 1.9
    fig_w = cell * len(cols) * max(1.0, W / H) + (4.2 if has_poses else 0)
    fig = plt.figure(figsize=(fig_w, max(cell * max(len(idx), 2) + 0.6, 4.5)))
    gs = fig.add_gridspec(max(len(idx), 2), len(cols) + (2 if has_poses else 0),
                          width_ratios=[1] * len(cols) + ([1.4, 1.4] if has_poses else []))
    renders = _renders(run, c.mid_poses()[idx]) if run is not None and has_poses else None
    with EventFile(c.path) as reader:
        for r, i in enumerate(idx):
            on, off = c.event_counts(reader, i)
            _, _, window = c.event_window(reader, i)
            imgs = [np.asarray(c.frame(i))]
            if "sharp frame" in cols:
                imgs.append(np.asarray(c.sharp(i)))
            imgs.append(data.event_image(on, off))
            if run is not None:
                imgs.append(renders[r] if renders is not None else np.zeros((H, W, 3), np.uint8))
            for k, img in enumerate(imgs):
                ax = fig.add_subplot(gs[r, k])
                ax.imshow(img, interpolation="nearest")
                ax.set_xticks([])
                ax.set_yticks([])
                if r == 0:
                    ax.set_title(cols[k], fontsize=8)
                if k == 0:
                    ax.set_ylabel(f"view {i}", fontsize=8)
                if k == cols.index(events_col):
                    ax.set_xlabel(_wrap(f"{int(on.sum())} ON, {int(off.sum())} OFF; {window}", 44), fontsize=6)
    refined = (run.refined_poses, run.refined_t) if run is not None else (None, None)
    if has_poses:
        half = max(len(idx), 2) // 2
        _top_view(fig.add_subplot(gs[:half, len(cols):]), c, *refined)
        _shake(fig.add_subplot(gs[half:, len(cols):]), c, *refined)
    sc = c.scene
    title = f"{sc.name or c.path.name} ({sc.source}): {n} training views"
    if run is not None:
        title += f"; run {run.path.name}, {len(run.model)} Gaussians from {run.source}"
    if not has_poses:
        title += " (no poses in the file: ingested without pose estimation)"
    if c.failed:
        shown = ", ".join(c.failed[:3]) + (f" and {len(c.failed) - 3} more" if len(c.failed) > 3 else "")
        title += f"; {len(c.failed)} failed to register: {shown}"
    palette.fit_suptitle(fig, title, fontsize=9)
    fig.legend(handles=palette.legend_handles(), loc="lower left", fontsize=6, ncol=2, frameon=False,
               bbox_to_anchor=(0.0, 0.0))
    fig.tight_layout(rect=(0, 0.04, 1, 1))   # the legend's row at the bottom
    return fig


def _wrap(text: str, width: int) -> str:
    import textwrap

    return "\n".join(textwrap.wrap(text, width))


def write_png(content: data.SceneContent | data.RunContent, out: str | Path, rows: int = 4, dpi: int = 120) -> Path:
    """Draw and write the figure atomically (temporary file beside `out`, then rename)."""
    import matplotlib.pyplot as plt

    from ..outputs import atomic_path, check_output_file, remove_stale_temps

    out = Path(out)
    check_output_file(out, 2 << 20, make_parents=True, option="--out")
    fig = draw(content, rows)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    plt.close(fig)
    out.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temps(out.parent, out.name)
    with atomic_path(out) as tmp:
        tmp.write_bytes(buf.getvalue())
    return out
