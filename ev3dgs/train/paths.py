"""Camera paths and frame output for ``ev3dgs render``.

Poses are 4x4 camera-to-world matrices with OpenCV axes (see ``ev3dgs.geometry``); world up is +z.
"""
from __future__ import annotations

import contextlib
import os
from contextlib import contextmanager
from pathlib import Path
from typing import Iterable, Iterator

import numpy as np
import torch

from ..errors import InputError
from ..outputs import OutputError
from ..geometry import look_at

__all__ = ["orbit_path", "scene_target", "render_frames", "write_frames", "output_kind", "scaled_camera"]

WORLD_UP = np.array([0.0, 0.0, 1.0])
MAX_ELEVATION_DEG = 85.0  # keeps the orbit a real circle and look_at away from its degenerate case


def _as_poses(poses) -> np.ndarray:
    if isinstance(poses, torch.Tensor):
        poses = poses.detach().cpu().numpy()
    p = np.asarray(poses, dtype=np.float64)
    if p.ndim == 2 and p.shape == (4, 4):
        p = p[None]
    if p.ndim != 3 or p.shape[1:] != (4, 4) or len(p) == 0:
        raise InputError(f"poses must be (N, 4, 4) with N >= 1, got {p.shape}")
    if not np.all(np.isfinite(p)):
        raise InputError("poses contain NaN or inf")
    return p


def scene_target(poses) -> np.ndarray:
    """The point closest (least squares) to all the cameras' optical axes.

    Falls back to a point in front of the cameras (the mean centre plus the mean viewing direction times
    the cameras' spread, or 1 unit) when the axes are (nearly) parallel or meet behind the cameras.
    """
    p = _as_poses(poses)
    centres = p[:, :3, 3]
    dirs = p[:, :3, 2] / np.linalg.norm(p[:, :3, 2], axis=1, keepdims=True)
    proj = np.eye(3)[None] - dirs[:, :, None] * dirs[:, None, :]  # (N,3,3) projectors orthogonal to each axis
    a = proj.sum(0)
    b = np.einsum("nij,nj->i", proj, centres)
    eig = np.linalg.eigvalsh(a)
    if eig[0] > 1e-3 * len(p):  # well conditioned: axes are not all parallel
        t = np.linalg.solve(a, b)
        depth = np.einsum("ni,ni->n", t[None] - centres, dirs)
        if np.median(depth) > 0:
            return t
    mean_dir = dirs.mean(0)
    nd = np.linalg.norm(mean_dir)
    mean_dir = mean_dir / nd if nd > 1e-9 else dirs[0]
    spread = float(np.sqrt(((centres - centres.mean(0)) ** 2).sum(1).mean()))
    return centres.mean(0) + mean_dir * (spread if spread > 1e-9 else 1.0)


def orbit_path(mid_poses, n_frames: int, target=None) -> np.ndarray:
    """A closed circular orbit (n_frames, 4, 4) around ``target`` looking at it.

    ``target`` defaults to :func:`scene_target`.  The circle lies at the mean camera distance from the
    target and the mean camera elevation above it (world z up; clamped to +-85 deg), starts at the first
    camera's azimuth and turns counter-clockwise (seen from above) by 2*pi/n_frames per frame, so frame
    n_frames would coincide with frame 0: the path loops seamlessly and consecutive poses differ by the
    same rotation about z.
    """
    p = _as_poses(mid_poses)
    n_frames = int(n_frames)
    if n_frames < 1:
        raise InputError(f"n_frames must be >= 1, got {n_frames}")
    t = scene_target(p) if target is None else np.asarray(
        target.detach().cpu().numpy() if isinstance(target, torch.Tensor) else target, dtype=np.float64
    ).reshape(-1)
    if t.shape != (3,) or not np.all(np.isfinite(t)):
        raise InputError(f"target must be a finite 3-vector, got {t}")
    off = p[:, :3, 3] - t
    dist = np.linalg.norm(off, axis=1)
    radius = float(dist.mean())
    if radius < 1e-9:
        raise InputError("the cameras sit on the orbit target; give another target")
    elev = float(np.mean(np.arctan2(off[:, 2], np.linalg.norm(off[:, :2], axis=1))))  # no division, any distance
    lim = np.deg2rad(MAX_ELEVATION_DEG)
    elev = float(np.clip(elev, -lim, lim))
    # start azimuth: the first camera not straight above/below the target
    horiz = off[:, :2]
    hn = np.linalg.norm(horiz, axis=1)
    i0 = int(np.argmax(hn > 1e-9 * max(radius, 1.0))) if np.any(hn > 1e-9 * max(radius, 1.0)) else -1
    az0 = float(np.arctan2(horiz[i0, 1], horiz[i0, 0])) if i0 >= 0 else 0.0

    r_h, h = radius * np.cos(elev), radius * np.sin(elev)
    out = np.empty((n_frames, 4, 4))
    for i in range(n_frames):
        az = az0 + 2.0 * np.pi * i / n_frames
        eye = t + np.array([r_h * np.cos(az), r_h * np.sin(az), h])
        out[i] = look_at(eye, t, WORLD_UP)
    return out


@torch.no_grad()
def render_frames(model, poses, K, width: int, height: int, background=None, backend: str = "cpu",
                  threads: int | None = None) -> Iterator[np.ndarray]:
    """Render each camera-to-world pose; yields uint8 (height, width, 3) RGB frames.

    Colours come from the model's SH at ``model.active_sh_degree``; ``background`` is an RGB triple in
    [0, 1] (default black).  Lazy: one frame is rendered per ``next``.
    """
    from ..splat.rasterize import rasterization

    p = _as_poses(poses)
    width, height = int(width), int(height)
    dev, dt = model.device, model.dtype
    Kt = torch.as_tensor(np.asarray(K.detach().cpu() if isinstance(K, torch.Tensor) else K, np.float64),
                         dtype=dt, device=dev)
    if Kt.shape != (3, 3):
        raise InputError(f"K must be (3, 3), got {tuple(Kt.shape)}")
    bg = torch.zeros(3, dtype=dt, device=dev) if background is None else torch.as_tensor(
        np.asarray(background.detach().cpu() if isinstance(background, torch.Tensor) else background, np.float64),
        dtype=dt, device=dev).reshape(-1)
    if bg.shape != (3,):
        raise InputError(f"background must be an RGB triple, got shape {tuple(bg.shape)}")
    means, quats, scales, opac = model.means, model.quats_normalised, model.scales, model.opacities
    deg = int(model.active_sh_degree)
    sh = model.sh[:, : (deg + 1) ** 2]
    for c2w in p:
        viewmat = torch.as_tensor(np.linalg.inv(c2w), dtype=dt, device=dev)
        img, _, _ = rasterization(means, quats, scales, opac, sh, viewmat, Kt, width, height,
                                  sh_degree=deg, background=bg, backend=backend, threads=threads)
        yield (img[..., :3].clamp(0.0, 1.0) * 255.0).round().to(torch.uint8).cpu().numpy()


def _check_frame(frame, i: int, size) -> np.ndarray:
    f = np.asarray(frame)
    if f.dtype != np.uint8 or f.ndim != 3 or f.shape[2] != 3:
        raise InputError(f"frame {i}: expected uint8 (H, W, 3), got {f.dtype} {f.shape}")
    if size is not None and f.shape[:2] != size:
        raise InputError(f"frame {i}: size {f.shape[:2]} differs from the first frame's {size}")
    return np.ascontiguousarray(f[..., ::-1])  # RGB -> BGR for OpenCV


def scaled_camera(K, width: int, height: int, new_width: int, new_height: int) -> np.ndarray:
    """K (3, 3) for rendering the same view at new_width x new_height: focal lengths and principal point scaled
    by the ratio of the sizes along each axis, so the image's borders stay where they are (OpenCV pixel
    centres: u' + 0.5 = s (u + 0.5), see ev3dgs.geometry)."""
    K = np.asarray(K, np.float64).copy()
    if new_width < 1 or new_height < 1:
        raise InputError(f"the size must be at least 1x1, got {new_width}x{new_height}")
    sx, sy = new_width / float(width), new_height / float(height)
    K[0, :2] *= sx
    K[1, :2] *= sy
    K[0, 2] = sx * (K[0, 2] + 0.5) - 0.5
    K[1, 2] = sy * (K[1, 2] + 0.5) - 0.5
    return K


FRAME_FORMATS = {".mp4": "mp4", ".gif": "gif", "": "png"}  # extension of --out -> what is written
MP4_FOURCCS = ("avc1", "H264", "mp4v")  # H.264 where this OpenCV can encode it, else MPEG-4 part 2


def output_kind(out: str | os.PathLike) -> str:
    """"mp4", "gif" or "png" (a folder of frames) from the output's extension; InputError for any other."""
    suffix = Path(out).suffix.lower()
    if suffix not in FRAME_FORMATS:
        raise InputError(f"--out {out}: unknown output type {suffix!r}; give a file ending in .mp4 or .gif, or a "
                         "folder name without an extension for PNG frames")
    return FRAME_FORMATS[suffix]


@contextmanager
def _quiet_stderr():
    """Silence the C-level stderr (OpenCV/FFmpeg print their failed encoder probes there)."""
    try:
        saved = os.dup(2)
    except OSError:
        yield
        return
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, 2)
        os.close(devnull)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def _open_mp4(path: Path, fps: float, size) -> tuple:
    """(cv2.VideoWriter, fourcc) of the first codec in MP4_FOURCCS this OpenCV opens."""
    import cv2

    for code in MP4_FOURCCS:
        with _quiet_stderr():
            writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*code), float(fps), (size[1], size[0]))
            ok = writer.isOpened()
        if ok:
            return writer, code
        writer.release()
        with contextlib.suppress(OSError):
            path.unlink()
    raise InputError(f"cannot write {path.suffix} video: the installed OpenCV has no mp4 encoder ("
                     f"{', '.join(MP4_FOURCCS)} tried); give a .gif or a folder for PNG frames")


def _count_video_frames(path: Path) -> int:
    import cv2

    with _quiet_stderr():
        cap = cv2.VideoCapture(str(path))
        try:
            if not cap.isOpened():
                return -1
            n = 0
            while cap.grab():
                n += 1
        finally:
            cap.release()
    return n


def _ffmpeg():
    """imageio-ffmpeg (the `video` extra: an ffmpeg build with libx264), or None."""
    try:
        import imageio_ffmpeg
    except ImportError:
        return None
    return imageio_ffmpeg


def _write_h264(ffmpeg, frames, tmp: Path, fps: float, info: dict) -> int:
    """H.264 (libx264, yuv420p: what browsers and players decode) through ffmpeg; odd sizes are padded by one
    edge row/column, as yuv420p needs even ones."""
    gen, size, n = None, None, 0
    try:
        for i, frame in enumerate(frames):
            rgb = _check_frame(frame, i, size)[..., ::-1]
            size = rgb.shape[:2]
            h, w = size[0] + size[0] % 2, size[1] + size[1] % 2
            if (h, w) != size:
                rgb = np.pad(rgb, ((0, h - size[0]), (0, w - size[1]), (0, 0)), mode="edge")
            if gen is None:
                gen = ffmpeg.write_frames(str(tmp), (w, h), fps=float(fps), codec="libx264", pix_fmt_in="rgb24",
                                          pix_fmt_out="yuv420p", macro_block_size=1, quality=None,
                                          output_params=["-crf", "18"], ffmpeg_log_level="quiet")
                gen.send(None)
            gen.send(np.ascontiguousarray(rgb).tobytes())
            n += 1
        if gen is None:
            raise InputError("no frames to write")
        g, gen = gen, None
        g.close()             # ffmpeg writes the trailer and exits; a failure raises here
    except (OSError, RuntimeError) as e:    # ffmpeg could not write: one line, with the reason when we can tell
        raise OutputError(f"cannot write {tmp.parent / tmp.name}: {_write_failure_reason(tmp, e)}") from None
    finally:
        if gen is not None:
            with contextlib.suppress(Exception):
                gen.close()
    info["fourcc"] = "avc1"
    info["encoder"] = "libx264 (imageio-ffmpeg)"
    return n


def _write_failure_reason(path: Path, e: BaseException) -> str:
    """Why a child process (ffmpeg) failed to write `path`: a full disk when the folder has no room left,
    else its own words."""
    import errno
    import shutil

    try:
        if shutil.disk_usage(path.parent).free < (1 << 20):
            return f"{os.strerror(errno.ENOSPC)} (ENOSPC)"
    except OSError:
        pass
    return "ffmpeg stopped (" + (" ".join(str(e).split())[:200] or type(e).__name__) + ")"


def _write_mp4(frames, tmp: Path, fps: float, info: dict) -> int:
    ffmpeg = _ffmpeg()
    if ffmpeg is not None:
        return _write_h264(ffmpeg, frames, tmp, fps, info)
    writer, size, n = None, None, 0
    try:
        for i, frame in enumerate(frames):
            bgr = _check_frame(frame, i, size)
            if writer is None:
                size = bgr.shape[:2]
                writer, info["fourcc"] = _open_mp4(tmp, fps, size)
            writer.write(bgr)
            n += 1
        if writer is None:
            raise InputError("no frames to write")
    finally:
        if writer is not None:
            writer.release()
    return n


def _gif_frame(rgb: np.ndarray, alt: bool):
    """A palette image of `rgb` whose palette's last entry repeats the colour of pixel (0, 0); `alt` draws that
    pixel with the repeated entry: the same picture with other bytes, so Pillow does not merge a frame
    identical to the one before it (which would leave fewer frames than were rendered)."""
    from PIL import Image

    im = Image.fromarray(rgb).quantize(colors=255, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE)
    pal = (list(im.getpalette() or []) + [0] * 768)[:768]
    i0 = im.getpixel((0, 0))
    pal[765:768] = pal[3 * i0:3 * i0 + 3]
    im.putpalette(pal)
    if alt:
        im.putpixel((0, 0), 255)
    return im


def _write_gif(frames, tmp: Path, fps: float, info: dict) -> int:
    try:
        import PIL.Image  # noqa: F401  (imageio and matplotlib write GIFs through Pillow too)
    except ImportError:
        raise InputError("writing a .gif needs Pillow, which is not installed: pip install pillow; or give "
                         ".mp4 or a folder for PNG frames") from None
    images, size, prev, alt = [], None, None, False
    for i, frame in enumerate(frames):
        f = np.ascontiguousarray(_check_frame(frame, i, size)[..., ::-1])  # back to RGB
        size = f.shape[:2]
        alt = (not alt) if prev is not None and np.array_equal(f, prev) else False
        images.append(_gif_frame(f, alt))
        prev = f
    if not images:
        raise InputError("no frames to write")
    duration = max(20, int(round(1000.0 / fps / 10.0)) * 10)  # GIF delays are in 1/100 s
    images[0].save(tmp, format="GIF", save_all=True, append_images=images[1:], duration=duration, loop=0,
                   optimize=False)
    info["fourcc"] = None
    info["frame_ms"] = duration
    return len(images)


def _count_gif_frames(path: Path) -> int:
    try:
        from PIL import Image

        with Image.open(path) as im:
            if im.format != "GIF":
                return -1
            n = getattr(im, "n_frames", 1)
            im.seek(n - 1)
            im.load()
            return n
    except Exception:
        return -1


def write_frames(frames: Iterable[np.ndarray], out: str | os.PathLike, fps: float = 30,
                 info: dict | None = None) -> int:
    """Write RGB uint8 frames to ``out``; returns the number written. The kind follows the extension
    (output_kind): ``.mp4`` an H.264 video where the installed OpenCV can encode it (fourcc avc1, then H264),
    else MPEG-4 (mp4v); ``.gif`` an animated GIF (Pillow); no extension a folder of ``frame_0000.png``,
    ``frame_0001.png``, ... Files are written to a temporary name beside ``out``, read back (the frames counted)
    and only then renamed into place: a broken file never takes the final name (OutputError). A PNG folder
    that exists already loses its old frame_NNNN.png files (other files are kept). ``info`` (a dict) receives
    "fourcc", the mp4 codec used."""
    from ..outputs import OutputError, publish, remove_stale_temps, temp_name

    out = Path(out)
    kind = output_kind(out)
    info = {} if info is None else info
    if not fps > 0:
        raise InputError(f"fps must be > 0, got {fps}")
    out.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temps(out.parent, out.name)  # left by a killed render of the same output
    if kind == "png":
        return _write_png_folder(frames, out)
    tmp = out.with_name(temp_name(out).name + out.suffix)  # the codec is chosen by the extension
    try:
        n = (_write_mp4 if kind == "mp4" else _write_gif)(frames, tmp, fps, info)
        back = (_count_video_frames if kind == "mp4" else _count_gif_frames)(tmp)
        if back != n:
            how = "it cannot be read back" if back < 0 else f"{back} of {n} frames read back"
            codec = f" (fourcc {info['fourcc']})" if info.get("fourcc") else ""
            raise OutputError(f"the {kind} writer{codec} produced a broken file for {out}: {how}")
        publish(tmp, out)
    finally:
        with contextlib.suppress(OSError):  # missing, or a read-only folder: never hide the real error
            tmp.unlink()
    return n


def _write_png_folder(frames, out: Path) -> int:
    import shutil

    import cv2

    from ..claims import may_replace, pause
    from ..outputs import OutputError, publish, temp_name, write_image

    tmp = temp_name(out)
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    try:
        size, n = None, 0
        for i, frame in enumerate(frames):
            bgr = _check_frame(frame, i, size)
            size = bgr.shape[:2]
            dst = tmp / f"frame_{i:04d}.png"
            write_image(dst, bgr, "PNG")  # a full disk is an OSError naming the file
            n += 1
        written = sorted(tmp.glob("frame_*.png"))
        if len(written) != n or any(cv2.imread(str(p), cv2.IMREAD_UNCHANGED) is None for p in written[-1:]):
            raise OutputError(f"the PNG frames for {out} could not be read back")
        if out.is_dir() and may_replace(out):  # --force: replace the old frames, keep anything else
            pause("publish")
            for old in out.glob("frame_[0-9][0-9][0-9][0-9].png"):
                old.unlink()
            for p in written:
                os.replace(p, out / p.name)
        else:
            publish(tmp, out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return n
