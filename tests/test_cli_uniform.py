"""One behaviour for every `ev3dgs` command that writes: --out names the output, an existing output is refused
(exit 2, one line, the old output untouched) unless --force, --quiet prints nothing, the output type follows the
extension, and outputs are verified before they take their final name."""
import json
import shutil
import subprocess
import sys

import numpy as np
import pytest
import torch

from ev3dgs.cli import main as cli

from cli_exit import exit_code

W, H = 32, 24
FAST = ["--iterations", "5", "--set", "init_points=500", "--threads", "1", "--set", "sh_degree=0",
        "--set", "checkpoint_every=5"]


def make_scene(path) -> str:
    """4 shaky views (3 sub-frames over 100 ms) and 2 test views of a small Gaussian cloud, with simulated
    events; drawn with the plain-torch rasterizer."""
    from ev3dgs.blob_scene import blob_scene

    return str(blob_scene(path, W, H, views=4, subframes=3, n=150, backend="reference", name="tiny", source="test"))


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return make_scene(tmp_path_factory.mktemp("scene") / "tiny.h5")


@pytest.fixture(scope="module")
def trained(scene, tmp_path_factory):
    run = tmp_path_factory.mktemp("runs") / "run"
    assert cli.main(["train", scene, "--out", str(run), *FAST, "--quiet"]) == 0
    return run


@pytest.fixture
def run(trained, tmp_path):
    """A fresh copy of the trained run (not evaluated)."""
    dst = tmp_path / "run"
    shutil.copytree(trained, dst)
    return dst


def one_line_error(capsys) -> str:
    cap = capsys.readouterr()
    assert cap.err.startswith("error: ") and cap.err.count("\n") == 1, cap.err
    return cap.err


def snapshot(path):
    """Bytes of a file, or {name: bytes} of a folder's files."""
    if path.is_dir():
        return {p.name: p.read_bytes() for p in sorted(path.iterdir()) if p.is_file()}
    return path.read_bytes()


# command -> (argv without --force/--quiet, the file or folder whose bytes must survive a refusal)
def _commands(name, scene, run, tmp):
    return {
        "train": (["train", scene, "--out", str(tmp / "r"), *FAST], tmp / "r" / "model.pt"),
        "eval": (["eval", str(run)], run / "metrics.json"),
        "render-png": (["render", str(run), "--out", str(tmp / "frames"), "--frames", "2"], tmp / "frames"),
        "render-gif": (["render", str(run), "--out", str(tmp / "orbit.gif"), "--frames", "2"], tmp / "orbit.gif"),
        "render-mp4": (["render", str(run), "--out", str(tmp / "orbit.mp4"), "--frames", "2"], tmp / "orbit.mp4"),
        "export": (["export", str(run), "--out", str(tmp / "m.ply")], tmp / "m.ply"),
        "view": (["view", str(run), "--out", str(tmp / "fig.png"), "--rows", "2"], tmp / "fig.png"),
    }[name]


@pytest.mark.parametrize("name", ["train", "eval", "render-png", "render-gif", "render-mp4", "export", "view"])
def test_refuses_to_overwrite_without_force(name, scene, run, tmp_path, capsys):
    argv, target = _commands(name, scene, run, tmp_path)
    assert cli.main([*argv, "--quiet"]) == 0
    assert capsys.readouterr().out == ""  # --quiet: no summary
    assert target.exists()
    before = snapshot(target)
    assert cli.main(argv) == 2
    err = one_line_error(capsys)
    assert "--force" in err
    assert snapshot(target) == before  # untouched
    assert cli.main([*argv, "--force", "--quiet"]) == 0
    assert capsys.readouterr().out == ""
    assert target.exists()
    assert not [p for p in target.parent.iterdir() if ".tmp-" in p.name]  # no temporary left
    assert cli.main([*argv, "--force"]) == 0
    assert capsys.readouterr().out.strip() != ""  # without --quiet: a summary


def test_version(capsys):
    from ev3dgs import __version__

    with pytest.raises(SystemExit) as e:
        cli.main(["--version"])
    assert e.value.code == 0 and capsys.readouterr().out.strip() == f"ev3dgs {__version__}"
    out = subprocess.run([sys.executable, "-m", "ev3dgs.cli.main", "--version"], capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == f"ev3dgs {__version__}"


def test_train_force_removes_the_old_runs_files(scene, run, capsys):
    assert cli.main(["eval", str(run), "--quiet"]) == 0
    assert (run / "metrics.json").is_file() and list((run / "eval").glob("*.png"))
    (run / "notes.txt").write_text("mine")
    (run / "trajectory.npz").write_bytes(b"stale")
    assert cli.main(["train", scene, "--out", str(run), *FAST, "--quiet"]) == 2
    assert "--resume" in one_line_error(capsys)
    assert cli.main(["train", scene, "--out", str(run), *FAST, "--resume", "--force"]) == 2
    one_line_error(capsys)
    assert (run / "metrics.json").is_file()
    assert cli.main(["train", scene, "--out", str(run), *FAST, "--force", "--quiet"]) == 0
    assert not (run / "metrics.json").exists() and not (run / "eval").exists()
    assert not (run / "trajectory.npz").exists()
    assert (run / "notes.txt").read_text() == "mine"  # not the run's: kept
    assert {"config.json", "model.pt", "ckpt.pt", "log.jsonl"} <= {p.name for p in run.iterdir()}
    assert len((run / "log.jsonl").read_text().splitlines()) == 5  # a fresh log, not appended to


def test_resume_still_works_on_a_run_folder(scene, run, capsys):
    assert cli.main(["train", scene, "--out", str(run), *FAST[2:], "--iterations", "7", "--resume", "--quiet"]) == 0
    assert json.loads((run / "config.json").read_text())["iterations"] == 7
    assert len((run / "log.jsonl").read_text().splitlines()) == 7


def _video_frames(path):
    import cv2

    cap = cv2.VideoCapture(str(path))
    frames = []
    while True:
        ok, img = cap.read()
        if not ok:
            break
        frames.append(img)
    cap.release()
    return frames


def test_render_gif_and_mp4_read_back(run, tmp_path, capsys):
    from PIL import Image

    assert cli.main(["render", str(run), "--out", str(tmp_path / "o.gif"), "--frames", "4", "--size", "40x30"]) == 0
    assert "GIF" in capsys.readouterr().out
    with Image.open(tmp_path / "o.gif") as im:
        assert im.format == "GIF" and im.n_frames == 4 and im.size == (40, 30)
    assert cli.main(["render", str(run), "--out", str(tmp_path / "o.mp4"), "--frames", "5"]) == 0
    out = capsys.readouterr().out
    assert "mp4, H.264" in out or "MPEG-4 part 2 (fourcc mp4v" in out, out
    frames = _video_frames(tmp_path / "o.mp4")
    assert len(frames) == 5 and frames[0].shape == (H, W, 3)
    assert cli.main(["render", str(run), "--out", str(tmp_path / "f"), "--frames", "3", "--size", "16x12"]) == 0
    import cv2

    files = sorted((tmp_path / "f").iterdir())
    assert [p.name for p in files] == [f"frame_{i:04d}.png" for i in range(3)]
    assert cv2.imread(str(files[0])).shape == (12, 16, 3)


def test_mp4_is_h264_with_the_video_extra_and_says_so_without(run, tmp_path, capsys, monkeypatch):
    """With imageio-ffmpeg (ev3dgs[video]) the mp4 is H.264 (what browsers play; odd sizes padded to even, as
    yuv420p needs); without it, MPEG-4 part 2 and the summary names the extra."""
    import cv2

    from ev3dgs.train import paths

    pytest.importorskip("imageio_ffmpeg")
    assert cli.main(["render", str(run), "--out", str(tmp_path / "a.mp4"), "--frames", "3", "--size", "33x25"]) == 0
    assert "mp4, H.264" in capsys.readouterr().out
    cap = cv2.VideoCapture(str(tmp_path / "a.mp4"))
    code = int(cap.get(cv2.CAP_PROP_FOURCC)).to_bytes(4, "little").decode("ascii", "replace").lower()
    cap.release()
    assert code in ("avc1", "h264"), code
    frames = _video_frames(tmp_path / "a.mp4")
    assert len(frames) == 3 and frames[0].shape == (26, 34, 3)
    monkeypatch.setattr(paths, "_ffmpeg", lambda: None)
    assert cli.main(["render", str(run), "--out", str(tmp_path / "b.mp4"), "--frames", "3"]) == 0
    out = capsys.readouterr().out
    assert "fourcc mp4v" in out and "ev3dgs[video]" in out
    assert len(_video_frames(tmp_path / "b.mp4")) == 3


def test_gif_keeps_identical_frames():
    """Pillow merges a frame equal to the one before: the writer keeps every frame, exact colours."""
    from PIL import Image

    from ev3dgs.train.paths import write_frames

    frames = [np.full((8, 10, 3), v, np.uint8) for v in (10, 10, 10, 200, 200)]
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as d:
        out = Path(d) / "same.gif"
        assert write_frames(frames, out, fps=10) == 5
        with Image.open(out) as im:
            assert im.n_frames == 5
            for i in range(5):
                im.seek(i)
                assert np.array_equal(np.asarray(im.convert("RGB")), frames[i])


def test_broken_writer_output_never_takes_the_final_name(run, tmp_path, monkeypatch, capsys):
    import ev3dgs.train.paths as paths

    monkeypatch.setattr(paths, "_count_video_frames", lambda path: 1)  # as if the file held fewer frames
    out = tmp_path / "o.mp4"
    assert cli.main(["render", str(run), "--out", str(out), "--frames", "3"]) == 2
    assert "broken" in one_line_error(capsys)
    assert not out.exists() and not [p for p in tmp_path.iterdir() if ".tmp-" in p.name]


@pytest.mark.parametrize("argv,match", [
    (["render", "RUN", "--out", "TMP/frames.jpgz"], "unknown output type"),
    (["render", "RUN", "--out", "TMP/o.avi"], "unknown output type"),
    (["render", "RUN", "--out", "TMP/o", "--size", "40by30"], "WIDTHxHEIGHT"),
    (["export", "RUN", "--out", "TMP/m.txt"], r"\.ply"),
    (["export", "RUN"], "--out"),
    (["view", "RUN", "--out", "TMP/fig.jpg"], r"\.png"),
])
def test_bad_output_names_are_refused(run, tmp_path, capsys, argv, match):
    import re

    before = sorted(p.name for p in tmp_path.iterdir())
    assert exit_code(cli.main, [a.replace("RUN", str(run)).replace("TMP", str(tmp_path)) for a in argv]) == 2
    assert re.search(match, one_line_error(capsys))
    assert sorted(p.name for p in tmp_path.iterdir()) == before


def test_old_option_names_still_work(run, tmp_path, capsys):
    from ev3dgs.cli.main import build_parser

    assert cli.main(["export", str(run), "--ply", str(tmp_path / "m.ply"), "--quiet"]) == 0
    assert (tmp_path / "m.ply").is_file()
    assert cli.main(["view", str(run), "--png", str(tmp_path / "f.png"), "--quiet"]) == 0
    assert (tmp_path / "f.png").is_file()
    sub = build_parser()._subparsers._group_actions[0].choices
    assert "--ply" not in sub["export"].format_help() and "--png" not in sub["view"].format_help()
    for name in ("train", "eval", "render", "export", "view"):
        text = sub[name].format_help()
        assert "--force" in text and "--quiet" in text, name


def test_eval_images_are_labelled(run, capsys):
    import cv2

    from ev3dgs.train.evaluate import LABEL_HEIGHT

    assert cli.main(["eval", str(run), "--quiet"]) == 0
    img = cv2.imread(str(run / "eval" / "train_000.png"))
    assert img.shape[0] == H + LABEL_HEIGHT + 2
    strip = img[1:LABEL_HEIGHT + 1]
    assert strip.min() < 100  # dark text in the caption strip
    assert len(list((run / "eval").glob("test_*.png"))) == 2


def test_eval_lpips_without_network_is_one_line_naming_the_file(run, tmp_path, monkeypatch, capsys):
    """`eval --lpips alex` fetches the standard weights; with no network the user learns in one line which
    file to place where, and metrics.json holds PSNR/SSIM without LPIPS."""
    import socket
    import urllib.error

    import torch

    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))
    monkeypatch.setattr(torch.hub, "_hub_dir", None)

    def no_network(url, dst, *a, **k):
        raise urllib.error.URLError(socket.gaierror(-3, "Temporary failure in name resolution"))

    monkeypatch.setattr(torch.hub, "download_url_to_file", no_network)
    (run / "metrics.json").unlink(missing_ok=True)
    assert exit_code(cli.main, ["eval", str(run), "--lpips", "alex"]) == 2
    err = one_line_error(capsys)
    assert "alexnet-owt-7be5be79.pth" in err and str(tmp_path / "torch" / "hub" / "checkpoints") in err
    assert err.startswith("error: LPIPS not computed: ") and "PSNR and SSIM are written to" in err
    m = json.loads((run / "metrics.json").read_text())
    assert m["lpips"] is None and m["lpips_failed"] and "psnr" in m["test"]
    (run / "metrics.json").unlink()
    assert exit_code(cli.main, ["eval", str(run), "--lpips", "alex", "--lpips-weights", "w.pth"]) == 2
    assert "either --lpips" in one_line_error(capsys)
