"""Runs find their scene file from any working folder, after the run and its scene have been moved together,
with --scene, and in old runs whose config.json has only the relative `scene`."""
import json
import os
import shutil
import subprocess
import sys

import pytest

from ev3dgs.cli import main as cli
from ev3dgs.train.run_scene import resolve_run_scene, scene_record

from test_cli_uniform import FAST, make_scene, one_line_error


@pytest.fixture(scope="module")
def project(tmp_path_factory):
    """proj/scene.h5 and proj/run, trained from inside proj with relative paths."""
    proj = tmp_path_factory.mktemp("proj")
    make_scene(proj / "scene.h5")
    cwd = os.getcwd()
    os.chdir(proj)
    try:
        assert cli.main(["train", "scene.h5", "--out", "run", *FAST, "--quiet"]) == 0
    finally:
        os.chdir(cwd)
    return proj


@pytest.fixture
def proj(project, tmp_path):
    """A copy of the project, its run's config recording the copy's scene (as if trained there)."""
    dst = tmp_path / "proj"
    shutil.copytree(project, dst)
    cfg = json.loads((dst / "run" / "config.json").read_text())
    cfg["scene"] = cfg["scene_file"]["path"] = str(dst / "scene.h5")
    (dst / "run" / "config.json").write_text(json.dumps(cfg))
    return dst


def _use_all(run, out_dir, extra=()):
    """eval, render, view and export of `run`, from the current folder; all must succeed."""
    out_dir.mkdir(exist_ok=True)
    assert cli.main(["eval", str(run), "--quiet", "--force", *extra]) == 0
    assert json.loads((run / "metrics.json").read_text())["test"]["n"] == 2
    assert cli.main(["render", str(run), "--out", str(out_dir / "o.gif"), "--frames", "2", "--quiet", "--force",
                     *extra]) == 0
    assert cli.main(["view", str(run), "--out", str(out_dir / "v.png"), "--quiet", "--force", *extra]) == 0
    assert cli.main(["export", str(run), "--out", str(out_dir / "m.ply"), "--quiet", "--force"]) == 0
    assert (out_dir / "o.gif").is_file() and (out_dir / "v.png").is_file()


def test_config_records_the_scene(project):
    cfg = json.loads((project / "run" / "config.json").read_text())
    rec = cfg["scene_file"]
    assert os.path.isabs(cfg["scene"]) and cfg["scene"] == rec["path"]
    assert rec["relative"] == os.path.join("..", "scene.h5") and rec["file"] == "scene.h5"
    assert rec["size"] == (project / "scene.h5").stat().st_size and rec["name"] == "tiny" and rec["created"]


def test_from_another_folder(proj, tmp_path, monkeypatch):
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    _use_all(proj / "run", tmp_path / "out")


def test_subprocess_from_another_folder(proj, tmp_path):
    out = subprocess.run([sys.executable, "-m", "ev3dgs.cli.main", "eval", str(proj / "run"), "--quiet"],
                         cwd=tmp_path, capture_output=True, text=True, timeout=300,
                         env={**os.environ, "PYTHONPATH": os.getcwd()})
    assert out.returncode == 0, out.stderr
    assert out.stdout == "" and (proj / "run" / "metrics.json").is_file()


def test_after_moving_run_and_scene_together(proj, tmp_path, monkeypatch, capsys):
    new = tmp_path / "newplace"
    new.mkdir()
    moved = shutil.move(str(proj), str(new))
    assert not proj.exists()
    monkeypatch.chdir(tmp_path)
    _use_all(new / "proj" / "run", tmp_path / "out")
    assert resolve_run_scene(new / "proj" / "run") == new / "proj" / "scene.h5"
    # and training resumes there, given the moved scene
    assert cli.main(["train", str(new / "proj" / "scene.h5"), "--out", str(new / "proj" / "run"),
                     *FAST[2:], "--iterations", "6", "--resume", "--quiet"]) == 0, moved
    assert json.loads((new / "proj" / "run" / "config.json").read_text())["scene_file"]["relative"] == \
        os.path.join("..", "scene.h5")


def test_run_moved_alone_needs_scene(proj, tmp_path, monkeypatch, capsys):
    away = tmp_path / "away"
    away.mkdir()
    shutil.move(str(proj / "run"), str(away / "run"))
    shutil.move(str(proj / "scene.h5"), str(tmp_path / "kept.h5"))  # not where the run recorded it, other name
    monkeypatch.chdir(away)
    assert cli.main(["eval", str(away / "run"), "--quiet"]) == 2
    err = one_line_error(capsys)
    assert "scene.h5 is not found" in err and "looked at" in err and "--scene" in err
    _use_all(away / "run", tmp_path / "out", extra=("--scene", str(tmp_path / "kept.h5")))
    assert json.loads((away / "run" / "metrics.json").read_text())["scene"] == str(tmp_path / "kept.h5")
    assert cli.main(["eval", str(away / "run"), "--force", "--scene", str(tmp_path / "nope.h5")]) == 2
    assert "--scene" in one_line_error(capsys)


def test_found_by_name_in_a_parent_folder(proj, tmp_path, monkeypatch):
    deep = proj / "runs" / "a"
    deep.parent.mkdir()
    shutil.move(str(proj / "run"), str(deep))  # the relative path no longer leads to it; the name does
    cfg = json.loads((deep / "config.json").read_text())
    cfg["scene"] = cfg["scene_file"]["path"] = str(tmp_path / "gone" / "scene.h5")
    (deep / "config.json").write_text(json.dumps(cfg))
    monkeypatch.chdir(tmp_path)
    assert resolve_run_scene(deep) == proj / "scene.h5"
    assert cli.main(["eval", str(deep), "--quiet"]) == 0


def test_old_config_with_only_a_relative_scene(proj, tmp_path, monkeypatch):
    cfg = json.loads((proj / "run" / "config.json").read_text())
    del cfg["scene_file"]
    cfg["scene"] = "scene.h5"  # as the run was started inside proj
    (proj / "run" / "config.json").write_text(json.dumps(cfg))
    monkeypatch.chdir(proj)
    _use_all(proj / "run", tmp_path / "out1")
    monkeypatch.chdir(tmp_path)  # elsewhere: found beside the run folder
    _use_all(proj / "run", tmp_path / "out2")


def test_a_different_file_at_the_recorded_path_warns(proj, tmp_path, capsys):
    other = make_scene(tmp_path / "other.h5")
    rec = scene_record(other, proj / "run")
    assert rec["relative"] == os.path.join("..", "..", "other.h5")
    cfg = json.loads((proj / "run" / "config.json").read_text())
    cfg["scene_file"]["created"] = "1999-01-01T00:00:00+00:00"  # the file there now is not the recorded one
    (proj / "run" / "config.json").write_text(json.dumps(cfg))
    assert cli.main(["eval", str(proj / "run"), "--quiet"]) == 0
    err = capsys.readouterr().err
    assert err.startswith("warning: ") and "not the scene file" in err
