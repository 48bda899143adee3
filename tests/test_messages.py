"""The messages a new user meets (issue 52, item 6): each states what happened and what to do, in our words.

calibrate's bootstrap no longer lets numpy warn; other libraries' warnings are worded as such; view without
viser names --out; the LPIPS notes point to the docs, and LPIPS that cannot be computed leaves PSNR/SSIM
written; an unknown option points to the sub-command's help; Ctrl-C in training prints the command that
resumes; a recording given where a scene file is expected names `ev3dgs-ingest davis`; `ev3dgs info RUN`
summarises the run."""
import json
import shlex
import shutil
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ev3dgs.cli import main as cli
from ev3dgs.cli import sim as sim_cli
from ev3dgs.cli.common import run as run_cli, warning_text
from ev3dgs.errors import Ev3dgsWarning

from cli_exit import exit_code
from test_cli_uniform import FAST, make_scene, one_line_error

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    d = tmp_path_factory.mktemp("messages")
    scene = make_scene(d / "tiny.h5")
    assert cli.main(["train", scene, "--out", str(d / "run"), *FAST, "--quiet"]) == 0
    return d / "tiny.h5", d / "run"


@pytest.fixture
def run(trained, tmp_path):
    dst = tmp_path / "run"
    shutil.copytree(trained[1], dst)
    return dst


# ------------------------------------------------------------------------------- warnings

@settings(max_examples=60, deadline=None)
@given(st.lists(st.lists(st.one_of(st.floats(-1e3, 1e3), st.just(float("nan"))), min_size=4, max_size=4),
                min_size=0, max_size=12))
def test_bootstrap_se_is_the_std_of_the_finite_values_without_warning(rows):
    from ev3dgs.calib.noise import bootstrap_se

    bs = np.array(rows, np.float64).reshape(len(rows), 4)
    with warnings.catch_warnings():
        warnings.simplefilter("error")          # numpy's "Degrees of freedom <= 0 for slice" would raise
        se = bootstrap_se(bs)
    for j in range(4):
        v = [r[j] for r in rows if np.isfinite(r[j])]
        if len(v) < 2:
            assert np.isnan(se[j])
        else:   # the textbook formula, in plain Python
            m = sum(v) / len(v)
            ref = (sum((x - m) ** 2 for x in v) / (len(v) - 1)) ** 0.5
            assert se[j] == pytest.approx(ref, rel=1e-9, abs=1e-9)


def test_calibrate_quiet_prints_nothing_when_a_fit_is_not_possible(tmp_path, capsys, monkeypatch):
    """A recording whose shot-noise fit fails (every bootstrap replicate NaN for two quantities): calibrate
    --quiet used to print numpy's `Degrees of freedom <= 0 for slice.`."""
    from ev3dgs.calib import noise
    from ev3dgs.calib.synth import make_recording

    make_recording(tmp_path / "r.aedat4", seed=4, seconds=1.0)
    monkeypatch.setattr(noise, "_shot_fit", lambda *a, **k: None)    # the fit finds no usable intensity span
    capsys.readouterr()
    assert sim_cli.main(["calibrate", str(tmp_path / "r.aedat4"), "--out", str(tmp_path / "s.toml"),
                         "--bootstrap", "8", "--quiet"]) == 0
    cap = capsys.readouterr()
    assert cap.err == "" and cap.out == ""
    assert "[dvs.shot_noise]" in (tmp_path / "s.toml").read_text()


def test_third_party_warnings_are_worded_ours_are_not(capsys):
    def main(argv):
        warnings.warn_explicit("Degrees of freedom <= 0 for slice.", RuntimeWarning,
                               "/venv/lib/python3.11/site-packages/numpy/lib/_nanfunctions_impl.py", 2000)
        warnings.warn("scene looks odd", Ev3dgsWarning)
        return 0

    assert run_cli(main, []) == 0
    err = capsys.readouterr().err.splitlines()
    assert err == ["warning: the library numpy warned: 'Degrees of freedom <= 0 for slice.' (RuntimeWarning; "
                   "unexpected: the results may be affected, please report it with the command line)",
                   "warning: scene looks odd"]
    # a numerical warning raised on a line of ours (numpy's stacklevel) is still numpy's, not a message of ours
    assert warning_text("x", RuntimeWarning, "/somewhere/ev3dgs/train/trainer.py").startswith(
        "a library ev3dgs uses warned: 'x' (RuntimeWarning;")
    # a plain warnings.warn of ours, from the source tree or an installed copy, is printed as it is
    for where in ("/somewhere/ev3dgs/train/trainer.py", "/venv/lib/python3.11/site-packages/ev3dgs/schema.py"):
        assert warning_text("x", UserWarning, where) == "x"
    assert warning_text("x", UserWarning, "/venv/lib/python3.11/site-packages/torch/nn/init.py").startswith(
        "the library torch warned: 'x' (UserWarning;")


# ------------------------------------------------------------------------------------ view

def test_view_without_viser_names_the_out_option(monkeypatch, trained, capsys):
    monkeypatch.setitem(sys.modules, "viser", None)
    assert cli.main(["view", str(trained[0])]) == 2
    err = one_line_error(capsys)
    assert "(or give --out FILE.png for a static figure)" in err and "--png" not in err


# ----------------------------------------------------------------------------------- LPIPS

def test_lpips_notes_point_to_the_docs_and_the_docs_hold_the_recipe():
    from ev3dgs.train.lpips import FILE_HINT
    from ev3dgs.train.metrics import lpips_unavailable_reason

    for text in (FILE_HINT, lpips_unavailable_reason(None)):
        assert "docs/commands/ev3dgs-eval.md" in text and "ev3dgs/train/lpips.py" not in text
    page = (ROOT / "docs" / "commands" / "ev3dgs-eval.md").read_text()
    assert "torch.save(lpips.LPIPS(net='alex', version='0.1').state_dict(), 'lpips_alex.pth')" in page


def test_missing_lpips_weights_leave_psnr_ssim_written(run, tmp_path, capsys):
    missing = tmp_path / "lpips_alex.pth"
    assert cli.main(["eval", str(run), "--lpips-weights", str(missing)]) == 2
    cap = capsys.readouterr()
    assert cap.err == (f"error: LPIPS not computed: {missing}: no such LPIPS weights file (or name a network: "
                       f"alex or vgg); PSNR and SSIM are written to {run}/metrics.json\n")
    m = json.loads((run / "metrics.json").read_text())
    assert m["lpips"] is None and m["lpips_failed"] and "PSNR" in cap.out
    assert m["test"]["n"] == 2 and np.isfinite(m["test"]["psnr"]) and np.isfinite(m["blur_view"]["ssim"])
    assert f"{m['test']['psnr']:6.2f} dB" in cap.out


# ------------------------------------------------------------------------------- argv, Ctrl-C

@pytest.mark.parametrize("main,argv,prog", [
    (cli.main, ["train", "x.h5", "--out", "r", "--bogus-flag"], "ev3dgs train"),
    (cli.main, ["eval", "r", "--bogus-flag"], "ev3dgs eval"),
    (sim_cli.main, ["list-scenes", "--bogus-flag"], "ev3dgs-sim list-scenes"),
])
def test_unknown_option_points_to_the_subcommands_help(main, argv, prog, capsys):
    assert exit_code(main, argv) == 2
    err = one_line_error(capsys)
    assert err == f"error: unrecognized arguments: --bogus-flag (see {prog} --help)\n"


def test_ctrl_c_in_training_prints_the_command_that_resumes(trained, tmp_path, monkeypatch, capsys):
    scene, _ = trained
    out = tmp_path / "r"
    argv = ["train", str(scene), "--out", str(out), *FAST, "--force"]

    checkpoint = {"written": True}

    def interrupted(args):
        out.mkdir(exist_ok=True)
        if checkpoint["written"]:
            (out / "ckpt.pt").write_bytes(b"checkpoint")
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "_train", interrupted)
    assert cli.main(argv) == 130
    err = one_line_error(capsys)
    head = f"error: interrupted; the run keeps its last checkpoint, {out / 'ckpt.pt'}; continue it with: "
    assert err.startswith(head)
    command = shlex.split(err[len(head):])
    assert command == ["ev3dgs", *[a for a in argv if a != "--force"], "--resume"]
    (out / "ckpt.pt").unlink()
    checkpoint["written"] = False         # interrupted before the first checkpoint
    assert cli.main(argv) == 130
    assert one_line_error(capsys) == ("error: interrupted; no checkpoint was written yet (one every "
                                      "checkpoint_every steps), so there is nothing to resume: run the same "
                                      "command again to start over\n")


def test_ctrl_c_elsewhere_is_the_plain_line(trained, tmp_path, monkeypatch, capsys):
    def interrupted(args):
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "_info", interrupted)
    assert cli.main(["info", str(trained[0])]) == 130
    assert capsys.readouterr().err == "error: interrupted\n"


# ------------------------------------------------------------------------ recordings, runs

def _recording(path):
    from ev3dgs.events import Events
    from ev3dgs.io.aedat4.writer import write_aedat4

    t = np.arange(0, 10_000, 100, dtype=np.int64)
    write_aedat4(path, 32, 24, events=Events(t, np.full(len(t), 3), np.full(len(t), 4), np.ones(len(t))))
    return path


@pytest.mark.parametrize("command", ["train", "info", "validate", "view", "eval-scene"])
def test_a_recording_where_a_scene_is_expected_names_ingest(command, trained, tmp_path, capsys):
    rec = _recording(tmp_path / "x.aedat4")
    argv = {"train": ["train", str(rec), "--out", str(tmp_path / "r"), *FAST],
            "info": ["info", str(rec)], "validate": ["validate", str(rec)],
            "view": ["view", str(rec), "--out", str(tmp_path / "v.png")],
            "eval-scene": ["eval", str(trained[1]), "--scene", str(rec), "--force"]}[command]
    assert exit_code(cli.main, argv) == 2
    err = one_line_error(capsys)
    assert (f"{rec}: an AEDAT 4.0 recording, not a scene file (.h5); convert it first with "
            f"`ev3dgs-ingest davis {rec} --out SCENE.h5`") in err
    assert "signature" not in err


def test_a_recording_by_extension_alone(tmp_path, capsys):
    rec = tmp_path / "cut.aedat4"
    rec.write_bytes(b"\x00" * 64)      # damaged: no magic line, but named as a recording
    assert cli.main(["info", str(rec)]) == 2
    assert "an AEDAT recording, not a scene file (.h5)" in one_line_error(capsys)


def test_info_of_a_run_folder_summarises_it(run, trained, capsys):
    assert cli.main(["info", str(run)]) == 0
    out = capsys.readouterr().out
    log = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    lines = out.splitlines()
    assert lines[0] == f"{run}: training run, variant blur+event"
    assert lines[1].startswith(f"progress {log[-1]['step']} of 5 steps (finished: model.pt); last step: "
                               f"loss {log[-1]['loss']:.5f}")
    assert f"{log[-1]['gaussians']} Gaussians" in lines[1]
    assert lines[2].startswith(f"scene    {trained[0]} (name 'tiny', {trained[0].stat().st_size:,} bytes")
    assert "init_points 500" in out and "sh_degree 0" in out and "iterations 5" in out
    assert "metrics  not evaluated" in out
    assert cli.main(["eval", str(run), "--quiet"]) == 0
    assert cli.main(["info", str(run)]) == 0
    out = capsys.readouterr().out
    m = json.loads((run / "metrics.json").read_text())
    assert (f"metrics  novel views                PSNR {m['novel_view']['psnr']:6.2f} dB  "
            f"SSIM {m['novel_view']['ssim']:.4f}  (2 views)") in out
    assert "eval/ (" in out


def test_info_of_a_folder_that_is_no_run(tmp_path, capsys):
    assert cli.main(["info", str(tmp_path)]) == 2
    assert "not a training run" in one_line_error(capsys)
