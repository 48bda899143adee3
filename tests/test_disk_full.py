"""A disk that fills while a command writes (issue 31): the command fails with one line and exit 2, and
nothing undecodable is left under the final name. The disk is a small tmpfs mounted for the test (root and a
kernel that allows it, as in CI; skipped with the reason elsewhere); the commands' up-front free-space
estimate is switched off, as when another process fills the disk after the check."""
from __future__ import annotations

import os
import subprocess
import uuid

import pytest

from ev3dgs import outputs
from ev3dgs.cli import main as cli

from cli_exit import exit_code
from test_cli_uniform import scene, trained  # noqa: F401  (fixtures: a tiny scene and a trained run)


@pytest.fixture
def full_disk(tmp_path, monkeypatch):
    mnt = tmp_path / f"tmpfs-{uuid.uuid4().hex[:6]}"
    mnt.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=24k", "tmpfs", str(mnt)], capture_output=True, text=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({(r.stderr or r.stdout).strip()})")
    monkeypatch.setattr(outputs, "_check_space", lambda *a, **k: None)
    try:
        yield mnt
    finally:
        subprocess.run(["umount", "-l", str(mnt)], capture_output=True)


def _one_line(capfd) -> str:
    err = capfd.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1, err      # no libpng line, no traceback
    return err


def _leftovers(folder) -> list[str]:
    return sorted(os.listdir(folder))


@pytest.mark.parametrize("out", ["o.mp4", "o.gif", "frames"])
def test_render_to_a_full_disk_leaves_nothing_under_the_final_name(trained, full_disk, capfd, out):  # noqa: F811
    assert exit_code(cli.main, ["render", str(trained), "--out", str(full_disk / out), "--frames", "200",
                                "--size", "320x240"]) == 2
    err = _one_line(capfd)
    assert "No space left on device" in err or "ENOSPC" in err or "broken file" in err, err
    assert _leftovers(full_disk) == [], _leftovers(full_disk)


@pytest.mark.parametrize("fmt", ["e2nerf", "events-h5", "aedat4", "transforms"])
@pytest.mark.parametrize("free_kb", [4, 12])
def test_export_dataset_to_a_full_disk(scene, full_disk, capfd, fmt, free_kb):  # noqa: F811
    """In a child process: a write failing inside HDF5 used to end in a segfault (exit 139) at a later close."""
    import sys

    (full_disk / "filler").write_bytes(b"\0" * ((24 - free_kb) << 10))
    code = ("import sys; from ev3dgs import outputs; outputs._check_space = lambda *a, **k: None; "
            "from ev3dgs.cli.main import main; sys.exit(main(sys.argv[1:]))")
    r = subprocess.run([sys.executable, "-c", code, "export-dataset", scene, "--format", fmt, "--out",
                        str(full_disk / "ds"), "--quiet"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 2, (r.returncode, r.stderr[-2000:])
    assert r.stderr.startswith("error: ") and r.stderr.count("\n") == 1, r.stderr[-2000:]
    assert _leftovers(full_disk) == ["filler"]


def test_render_cache_entry_on_a_full_disk_is_one_error_and_nothing_more(full_disk, capfd, monkeypatch):
    """make-dataset's per-view cache entry: a full disk is one OutputError; no 'Exception ignored in
    ZipFile.__del__' follows, and no temporary is left (issue 31, item 9)."""
    import gc

    import numpy as np

    from ev3dgs.outputs import OutputError
    from ev3dgs.sim.dataset import _save_npz

    import sys

    unraisable = []
    monkeypatch.setattr(sys, "unraisablehook", unraisable.append)   # what Python prints as 'Exception ignored'
    frames = np.random.default_rng(0).random((4, 64, 64, 3), dtype=np.float32)   # ~200 KB, over the 24 KB disk
    with pytest.raises(OutputError):
        _save_npz(full_disk / "view.npz", frames=frames, poses=np.eye(4)[None])
    gc.collect()
    assert unraisable == [] and "Exception ignored" not in capfd.readouterr().err
    assert _leftovers(full_disk) == []
