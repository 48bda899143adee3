"""eval, render and view refuse a --scene that is not the scene the run was trained on (its name, size or
creation time differs from what config.json records), in one line naming the difference, unless
--other-scene; the run's own scene, or a copy of it, is accepted as --scene."""
import json
import shutil

import h5py
import pytest

from ev3dgs.cli import main as cli
from ev3dgs.blob_scene import blob_scene

from test_cli_uniform import FAST, H, W, make_scene, one_line_error


@pytest.fixture(scope="module")
def project(tmp_path_factory):
    """A run trained on tiny.h5 (name 'tiny'), and a second small scene, other.h5 (name 'other')."""
    d = tmp_path_factory.mktemp("mismatch")
    scene = make_scene(d / "tiny.h5")
    other = blob_scene(d / "other.h5", W, H, views=3, subframes=3, n=120, seed=1, backend="reference",
                       name="other", source="test")
    assert cli.main(["train", scene, "--out", str(d / "run"), *FAST, "--quiet"]) == 0
    return d, d / "run", other


def _commands(run, scene, out):
    return {"eval": ["eval", str(run), "--scene", str(scene), "--force", "--quiet"],
            "render": ["render", str(run), "--scene", str(scene), "--out", str(out / "o.gif"), "--frames", "2",
                       "--force", "--quiet"],
            "view": ["view", str(run), "--scene", str(scene), "--out", str(out / "v.png"), "--force", "--quiet"]}


@pytest.mark.parametrize("command", ["eval", "render", "view"])
def test_another_scene_is_refused_naming_the_difference(project, tmp_path, capsys, command):
    d, run, other = project
    before = (run / "metrics.json").read_bytes() if (run / "metrics.json").exists() else None
    assert cli.main(_commands(run, other, tmp_path)[command]) == 2
    err = one_line_error(capsys)
    assert f"--scene {other} is not the scene the run {run} was trained on" in err
    assert "its name is 'other', the run's scene is 'tiny'" in err
    assert "pass --other-scene to use it anyway" in err
    # nothing written, nothing replaced
    assert not (tmp_path / "o.gif").exists() and not (tmp_path / "v.png").exists()
    assert ((run / "metrics.json").read_bytes() if (run / "metrics.json").exists() else None) == before


def test_same_name_but_another_file_names_size_or_creation(project, tmp_path, capsys):
    """A re-made scene under the same name: the size or the creation time tells it apart."""
    d, run, _ = project
    twin = tmp_path / "tiny.h5"
    shutil.copy(d / "tiny.h5", twin)
    with h5py.File(twin, "r+") as f:
        f.attrs["created"] = "1999-01-01T00:00:00+00:00"
    assert cli.main(_commands(run, twin, tmp_path)["eval"]) == 2
    err = one_line_error(capsys)
    assert "it was created 1999-01-01T00:00:00+00:00, the run's scene" in err
    assert "its name is" not in err


@pytest.mark.parametrize("command", ["eval", "render", "view"])
def test_other_scene_option_accepts_it(project, tmp_path, capsys, command):
    d, run, other = project
    copy = tmp_path / "run"
    shutil.copytree(run, copy)
    assert cli.main(_commands(copy, other, tmp_path)[command] + ["--other-scene"]) == 0
    if command == "eval":
        m = json.loads((copy / "metrics.json").read_text())
        assert m["scene"] == str(other) and m["test"]["n"] == 2   # other.h5's two test views


def test_the_runs_own_scene_and_a_copy_are_accepted(project, tmp_path, capsys):
    d, run, _ = project
    copy = tmp_path / "copy.h5"
    shutil.copy(d / "tiny.h5", copy)    # another path, the same name, size and creation time
    for scene in (d / "tiny.h5", copy):
        assert cli.main(_commands(run, scene, tmp_path)["eval"]) == 0


def test_other_scene_without_a_run_is_refused(project, tmp_path, capsys):
    d, _, _ = project
    assert cli.main(["view", str(d / "tiny.h5"), "--other-scene", "--out", str(tmp_path / "v.png")]) == 2
    assert "--other-scene is for a run folder" in one_line_error(capsys)
