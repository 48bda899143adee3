"""The trainer as a core plus terms: train.toml, the term registry, one render call per step, explicit resume
semantics, the sensor model read from the scene, and run folders written before the terms existed."""
import dataclasses
import json
import math
import shutil
import tomllib
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

from ev3dgs.blob_scene import blob_scene
from ev3dgs.cli import main as cli
from ev3dgs.errors import ConfigError
from ev3dgs.train.config import TrainConfig
from ev3dgs.train.layout import dumps
from ev3dgs.train.losses import count_variance
from ev3dgs.train.terms import Term, register, unregister
from ev3dgs.train.trainer import Trainer

from cli_exit import exit_code

FIXTURE = Path(__file__).parent / "fixtures" / "old_run"


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return str(blob_scene(tmp_path_factory.mktemp("terms") / "blobs.h5", 24, 18, views=3, subframes=3, n=60,
                          name="blobs", source="test"))


def small(scene, **kw):
    return TrainConfig(**{**dict(scene=scene, iterations=8, init_points=200, checkpoint_every=4, threads=1,
                                 sh_degree=0, subposes=3), **kw})


# ---------------------------------------------------------------------------------------------- a toy term
@dataclasses.dataclass(frozen=True)
class OpacityL1Settings:
    weight: float = 0.1


class OpacityL1(Term):
    """An L1 prior on the opacities, defined in this test file alone."""
    table = "opacity_l1"
    Settings = OpacityL1Settings

    def loss(self, step):
        value = self.trainer.model.opacities.mean()
        return self.settings.weight * value, {"opacity_l1": value.item()}


@pytest.fixture
def toy_term():
    register(OpacityL1)
    yield OpacityL1
    unregister(OpacityL1.table)


def test_a_term_defined_outside_the_package_trains_from_a_toml(scene, tmp_path, toy_term):
    """Registered here, switched on by its table in train.toml: it adds its loss (the log has it) and pulls the
    opacities down against the same run without it (same seed, same everything else)."""
    base = TrainConfig(scene=scene).default_toml()
    base.update(iterations=12, init_points=200, threads=1, sh_degree=0, checkpoint_every=12)
    base.pop("events")
    plain, toy = tmp_path / "plain.toml", tmp_path / "toy.toml"
    plain.write_text(dumps(base))
    toy.write_text(dumps({**base, "opacity_l1": {"weight": 5.0}}))
    for cfg_file, out in ((plain, "a"), (toy, "b")):
        assert cli.main(["train", scene, "--out", str(tmp_path / out), "--config", str(cfg_file), "--quiet"]) == 0
    log = [json.loads(x) for x in (tmp_path / "b" / "log.jsonl").read_text().splitlines()]
    assert all("opacity_l1" in r for r in log) and "opacity_l1" not in (tmp_path / "a" / "log.jsonl").read_text()
    op = {k: torch.sigmoid(torch.load(tmp_path / k / "model.pt", weights_only=True)["model"]["opacity_logits"]).mean()
          for k in ("a", "b")}
    tr = Trainer(TrainConfig.load(tmp_path / "b" / "config.toml"), tmp_path / "c", quiet=True)
    assert tr.term("opacity_l1") is not None and tr.term("events") is None
    saved = tomllib.loads((tmp_path / "b" / "config.toml").read_text())
    assert saved["opacity_l1"] == {"weight": 5.0} and "events" not in saved
    assert op["b"] < op["a"]


def test_a_toy_terms_table_is_checked_by_its_settings(scene, tmp_path, toy_term, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text('[opacity_l1]\nwieght = 1.0\n')
    assert exit_code(cli.main, ["train", scene, "--out", str(tmp_path / "r"), "--config", str(bad)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "opacity_l1.wieght" in err[0]


# ---------------------------------------------------------------------------------------------- train.toml
@pytest.mark.parametrize("text, key", [('iterations = "300"\n', "iterations"),
                                       ('[events]\nhubr = 3\n', "events.hubr"),
                                       ('[evnts]\n', "evnts"),
                                       ('[poses]\nlr = "fast"\n', "poses.lr"),
                                       ('[blur]\nsubposes = 2.5\n', "blur.subposes")])
def test_unknown_keys_and_wrong_types_are_one_line_naming_the_key(scene, tmp_path, capsys, text, key):
    f = tmp_path / "t.toml"
    f.write_text(text)
    assert exit_code(cli.main, ["train", scene, "--out", str(tmp_path / "r"), "--config", str(f)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error:") and key in err[0]


@pytest.mark.parametrize("item, key", [("events.hubr=3", "events.hubr"), ("events.huber=big", "events.huber"),
                                       ("nonsense", "--set nonsense")])
def test_set_errors_are_one_line_naming_the_key(scene, tmp_path, capsys, item, key):
    assert exit_code(cli.main, ["train", scene, "--out", str(tmp_path / "r"), "--set", item]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and key in err[0]


def test_train_help_has_at_most_15_options():
    parser = cli.build_parser()
    train = next(a for a in parser._subparsers._group_actions if a.choices).choices["train"]
    options = [a for a in train._actions if a.option_strings and "--help" not in a.option_strings]
    assert len(options) <= 15, [a.option_strings for a in options]


@pytest.mark.parametrize("kw", [{}, dict(event_norm="count", event_weight=0.01), dict(naive=True, event_loss=False),
                                dict(refine_poses=True, pose_lr=0.002, pose_frame="camera"),
                                dict(edi_prior=0.05, edi_anneal=0.3, blur_space="linear", event_huber=2.0),
                                dict(threshold_map=True, map_weights="posterior", hdr=True, learn_response=True,
                                     blur_space="linear", frame_noise=0.0, densify=False, sh_interval=7)])
def test_the_toml_written_for_a_config_reads_back_as_the_same_config(kw, tmp_path):
    cfg = TrainConfig(scene="s.h5", **kw)
    back = TrainConfig.from_toml(tomllib.loads(dumps(cfg.to_toml(), cfg.resolved_notes())))
    assert back == cfg


def test_set_overrides_the_config_and_a_key_of_an_absent_table_turns_the_term_on(scene, tmp_path):
    f = tmp_path / "t.toml"
    f.write_text('iterations = 2\ninit_points = 50\nsh_degree = 0\nthreads = 1\n[blur]\nsubposes = 3\n')
    assert cli.main(["train", scene, "--out", str(tmp_path / "r"), "--config", str(f), "--quiet",
                     "--set", "events.norm=count", "--set", "blur.ssim_lambda=0.5"]) == 0
    cfg = TrainConfig.load(tmp_path / "r" / "config.toml")
    assert cfg.event_loss and cfg.event_norm == "count" and cfg.ssim_lambda == 0.5 and cfg.subposes == 3
    assert cfg.iterations == 2 and not cfg.refine_poses
    assert cfg == TrainConfig.load(tmp_path / "r" / "config.json")   # the flat mirror for older readers


# ---------------------------------------------------------------------------------------------- the step
@pytest.mark.parametrize("backend", ["reference", "cpu"])
@pytest.mark.parametrize("kw", [{}, dict(refine_poses=True, pose_start=0), dict(naive=True),
                                dict(edi_prior=0.05, blur_space="linear")])
def test_one_render_call_per_step_on_every_backend(scene, tmp_path, monkeypatch, backend, kw):
    """Every term's cameras go through one rasterizer call per step (the event and the EDI terms reuse the
    blur term's renders); on the reference backend the old step rendered each sub-pose on its own."""
    import ev3dgs.train.trainer as trainer_mod

    calls = []
    real = trainer_mod.rasterization

    def counting(*a, **k):
        calls.append(a[5].shape)
        return real(*a, **k)

    monkeypatch.setattr(trainer_mod, "rasterization", counting)
    tr = Trainer(small(scene, backend=backend, iterations=3, **kw), tmp_path / "r", quiet=True)
    for _ in range(3):
        tr.train_step()
    assert len(calls) == 3
    assert all(s == ((1 if kw.get("naive") else 3), 4, 4) for s in calls)


def test_the_step_core_does_not_branch_on_features():
    """_train_step is under 60 lines and names no term; terms are reached through the registry only."""
    import inspect

    import ev3dgs.train.trainer as trainer_mod

    src = inspect.getsource(Trainer._train_step)
    assert len(src.splitlines()) < 60
    for name in ("event", "pose_refiner", "refine_poses", "edi", "hdr", "response", "threshold", "frame_noise",
                 "naive", "oracle"):
        assert name not in src
    module = inspect.getsource(trainer_mod)
    assert "from .terms." not in module and "import terms." not in module


# ---------------------------------------------------------------------------------------------- resume
def test_extending_a_run_keeps_its_schedules(scene, tmp_path, monkeypatch):
    """Resumed with more --iterations, the schedules stay those of the run's original length: the position
    learning rate stays at its final 1 % (it jumped back up before), densification ended where it did."""
    run = tmp_path / "r"
    argv = ["train", scene, "--out", str(run), "--iterations", "8", "--set", "init_points=200", "--set",
            "sh_degree=0", "--threads", "1", "--quiet", "--set", "blur.subposes=3"]
    assert cli.main(argv) == 0
    seen = {}
    set_lr = Trainer._set_lr

    def spy(self):
        set_lr(self)
        seen[self.step] = self.optimizers["means"].param_groups[0]["lr"] / self.means_lr0

    monkeypatch.setattr(Trainer, "_set_lr", spy)
    assert cli.main([*argv[:5], "16", *argv[6:], "--resume"]) == 0
    assert sorted(seen) == list(range(8, 16))
    assert all(v == pytest.approx(0.01, rel=1e-12) for v in seen.values())
    saved = tomllib.loads((run / "config.toml").read_text())
    assert saved["iterations"] == 16 and saved["schedule_length"] == 8
    # a schedule-moving change other than the length is still refused in one line
    with pytest.raises(ConfigError, match="ssim_lambda"):
        from ev3dgs.train.config import resume_config

        resume_config(run, {**dataclasses.asdict(TrainConfig.load(run / "config.toml")), "ssim_lambda": 0.3},
                      {"ssim_lambda"})


# ---------------------------------------------------------------------------------------------- sensor model
def _with_sensor(src, dst, **attrs):
    shutil.copy(src, dst)
    with h5py.File(dst, "a") as f:
        for k, v in attrs.items():
            f["events"].attrs[k] = v
    return str(dst)


@pytest.mark.parametrize("sigma", [0.0, 0.02, 0.06])
def test_the_event_noise_variance_follows_the_scenes_declared_mismatch(scene, tmp_path, sigma):
    """The event term's variance is count_variance's closed form with the scene's /events mismatch_sigma
    (relative to the mean threshold), and the run records where it came from."""
    path = _with_sensor(scene, tmp_path / "s.h5", mismatch_sigma=sigma, leak_rate_hz=0.5, shot_noise_rate_hz=1.5)
    tr = Trainer(small(path), tmp_path / "r", quiet=True)
    ev = tr.term("events")
    theta = 0.5 * (tr.data.pos_threshold + tr.data.neg_threshold)
    assert ev.noise.rel_mismatch == pytest.approx(sigma / theta, rel=1e-12)
    assert ev.noise.noise_rate_hz == pytest.approx(2.0, rel=1e-12)
    assert ev.sensor_record["rel_mismatch_from"] == "scene" and ev.sensor_record["noise_rate_from"] == "scene"
    counts = torch.tensor([[[[0.0]], [[0.0]]], [[[3.0]], [[1.0]]]])   # (K=2, 2, 1, 1): 3 ON, 1 OFF
    tp, tn = torch.tensor(0.2), torch.tensor(0.3)
    v = count_variance(counts, torch.tensor([[0, 1]]), tp, tn, ev.noise.rel_mismatch)
    expect = (0.2 ** 2 + 0.3 ** 2) / 12 + (sigma / theta * (0.2 * 3 + 0.3 * 1)) ** 2
    assert float(v) == pytest.approx(expect, rel=1e-6)   # float32 arithmetic on O(1) values
    tr.save_model()
    record = json.loads((tmp_path / "r" / "sensor_model.json").read_text())
    assert record["rel_mismatch"] == pytest.approx(sigma / theta) and record["rel_mismatch_from"] == "scene"


def test_a_scene_without_the_sensor_model_gets_the_documented_defaults(scene, tmp_path):
    from ev3dgs.train.terms.events import DEFAULT_NOISE_RATE_HZ, DEFAULT_REL_MISMATCH

    tr = Trainer(small(scene), tmp_path / "r", quiet=True)
    rec = tr.term("events").sensor_record
    assert rec == {"rel_mismatch": DEFAULT_REL_MISMATCH, "rel_mismatch_from": "default",
                   "noise_rate_hz": DEFAULT_NOISE_RATE_HZ, "noise_rate_from": "default"}


# ---------------------------------------------------------------------------------------------- old runs
def _old_run(tmp_path):
    shutil.copytree(FIXTURE, tmp_path / "old")
    return tmp_path / "old"


def test_a_run_folder_written_before_the_terms_still_evaluates(tmp_path):
    """tests/fixtures/old_run: written by the trainer before train.toml and the terms existed (flat
    config.json, a scene path that no longer exists: the run was moved with its scene)."""
    old = _old_run(tmp_path)
    assert not (old / "run" / "config.toml").exists()
    assert cli.main(["eval", str(old / "run"), "--quiet"]) == 0
    metrics = json.loads((old / "run" / "metrics.json").read_text())
    assert math.isfinite(metrics["test"]["psnr"])


def test_a_checkpoint_written_before_the_terms_resumes_as_an_uninterrupted_run(tmp_path, monkeypatch):
    """old_run/cut was stopped after its step-3 checkpoint; resumed by today's trainer it ends with the same
    model, bit for bit, as today's trainer running the same settings without a stop. The fixture was trained
    with the numba tile kernels, so both runs use them: the C kernels round differently (their own resume is
    bitwise, tests/test_train.py), and steps 1-3 of the fresh run must be those of the checkpoint."""
    from ev3dgs.splat import cpu_simd

    monkeypatch.setattr(cpu_simd, "KERNEL", "numba")
    old = _old_run(tmp_path)
    scene = str(old / "scene.h5")
    assert cli.main(["train", scene, "--out", str(old / "cut"), "--resume", "--quiet"]) == 0
    log = [json.loads(x)["step"] for x in (old / "cut" / "log.jsonl").read_text().splitlines()]
    assert log == [1, 2, 3, 4, 5, 6]
    cfg = dataclasses.replace(TrainConfig.load(old / "run" / "config.json"), scene=scene)
    fresh = Trainer(cfg, tmp_path / "fresh", quiet=True)
    fresh.fit()
    resumed = torch.load(old / "cut" / "model.pt", weights_only=True)["model"]
    for k, v in fresh.model.state_dict().items():
        assert torch.equal(torch.as_tensor(resumed[k]), torch.as_tensor(v)), k


def test_the_example_train_toml_in_the_docs_is_a_valid_config():
    text = (Path(__file__).parent.parent / "docs" / "trainer.md").read_text()
    block = text.split("```toml\n", 1)[1].split("```", 1)[0]
    cfg = TrainConfig.from_toml({**tomllib.loads(block), "scene": "s.h5"})
    assert cfg.event_loss and cfg.refine_poses and cfg.edi_prior == 0.0128 and not cfg.hdr


@pytest.mark.parametrize("module", ["bench_fidelity", "study_event_term"])
def test_the_studies_variants_are_train_toml_tables(module):
    """The studies write their variants in train.toml's shape; merged onto the built-in settings each one is a
    train.toml giving the same settings as the variant's TrainConfig overrides."""
    import importlib
    import sys

    root = Path(__file__).parent.parent / "tools"
    for sub in ("", "bench", "studies"):
        if str(root / sub) not in sys.path:
            sys.path.insert(0, str(root / sub))
    mod = importlib.import_module(module)
    for name, variant in mod.VARIANTS_TOML.items():
        data = {**TrainConfig.default_toml(), "scene": "s.h5"}
        for k, v in variant.items():
            if v is False:
                data.pop(k, None)
            elif isinstance(v, dict):
                data[k] = {**data.get(k, {}), **v}
            else:
                data[k] = v
        assert TrainConfig.from_toml(data) == TrainConfig(scene="s.h5", **mod.VARIANTS[name]), name


def test_densification_statistics_are_the_same_through_a_per_camera_loop(scene, tmp_path, monkeypatch):
    """A backend without a batched call renders camera by camera inside rasterization() (rasterize.py's loop,
    gradients hooked into the stacked means2d). The trainer's densification statistics, from the whole loss
    and from the blur term alone (densify.from), equal those of the reference backend's batched call."""
    import ev3dgs.splat.rasterize as R
    import ev3dgs.train.trainer as trainer_mod

    def looped(means, quats, scales, opacities, colors, viewmat, K, width, height, **kw):
        threads, backend = kw.pop("threads", None), kw.pop("backend")
        kw.setdefault("near_plane", 0.01), kw.setdefault("far_plane", 1e10), kw.setdefault("eps2d", 0.3)
        kw.setdefault("render_mode", "RGB")
        return R._rasterization_loop(means, quats, scales, opacities, colors, viewmat, K, width, height,
                                     backend=backend, threads=threads, **kw)

    stats = {}
    for name, source in (("batched", "all"), ("batched-blur", "blur"), ("loop", "all"), ("loop-blur", "blur")):
        if name.startswith("loop"):
            monkeypatch.setattr(trainer_mod, "rasterization", looped)
        tr = Trainer(small(scene, backend="reference", iterations=3, densify_from=source), tmp_path / name,
                     quiet=True)
        tr.train_step()   # one step: the same model, so each camera's gradient is the same arithmetic
        stats[name] = {k: v.clone() for k, v in tr.strategy_state.items()}
    for a, b in (("batched", "loop"), ("batched-blur", "loop-blur")):
        assert stats[a]["count"].sum() > 0
        for k in stats[a]:
            assert torch.equal(stats[a][k], stats[b][k]), (a, k)
    assert not torch.equal(stats["batched"]["grad2d"], stats["batched-blur"]["grad2d"])
