"""Issue 13 plumbing: blur space / event domain / count convention from the scene file, the sharp-oracle
variant, and the blur-view / novel-view split of metrics.json."""
import json

import numpy as np
import pytest

from ev3dgs import schema
from ev3dgs.errors import ConfigError
from ev3dgs.events import Events
from ev3dgs.geometry import intrinsics, look_at
from ev3dgs.train.config import TrainConfig
from ev3dgs.train.data import load_train_data, resolve_domains
from ev3dgs.train.evaluate import evaluate
from ev3dgs.train.trainer import Trainer

W, H = 16, 12


def _scene(path, transfer=None, convention=None, sharp=True, source="test", config=None):
    rng = np.random.default_rng(0)
    n, s = 3, 3
    poses, pose_t, exposure = [], [], []
    for v in range(n):
        eye = 3.0 * np.array([np.cos(v), np.sin(v), 0.5])
        poses.append(np.stack([look_at(eye + 0.05 * k, [0, 0, 0]) for k in range(s)]))
        t = v * 200_000 + np.array([0, 50_000, 100_000])
        pose_t.append(t)
        exposure.append((t[0], t[-1]))
    m = 400
    t = np.sort(rng.integers(0, 500_000, m)).astype(np.int64)
    ev = Events(t, rng.integers(0, W, m).astype(np.uint16), rng.integers(0, H, m).astype(np.uint16),
                rng.choice(np.array([-1, 1], np.int8), m))
    imgs = rng.integers(0, 255, (n, H, W, 3)).astype(np.uint8)
    test_poses = np.stack([look_at(3.0 * np.array([np.cos(a), np.sin(a), 0.4]), [0, 0, 0]) for a in (0.3, 1.3, 2.3)])
    sc = schema.Scene(
        name="tiny", source=source, camera=schema.Camera(W, H, K=intrinsics(W, H, 50), background=(1.0, 1.0, 1.0)),
        events=ev, sensor=schema.EventSensor(0.25, 0.18, count_convention=convention),
        bounds=np.array([[-0.5] * 3, [0.5] * 3]),
        train=schema.Train(images=imgs, exposure=np.array(exposure), poses=np.stack(poses), pose_t=np.stack(pose_t),
                           sharp=imgs[::-1].copy() if sharp else None,
                           sharp_poses=np.stack([p[1] for p in poses]) if sharp else None, transfer=transfer),
        test=schema.Test(images=rng.integers(0, 255, (3, H, W, 3)).astype(np.uint8), poses=test_poses),
        config=config or {})
    schema.write(sc, path)
    return str(path)


def test_resolve_domains():
    assert resolve_domains("srgb") == ("linear", "srgb")
    assert resolve_domains("display") == ("srgb", "display")
    assert resolve_domains("linear") == ("srgb", "linear")
    assert resolve_domains("srgb", "srgb", "display") == ("srgb", "display")
    assert resolve_domains("display", "linear", "linear") == ("linear", "srgb")


@pytest.mark.parametrize("transfer,convention,source,want", [
    (None, None, "test", ("linear", "srgb", "random_phase")),          # old file of ours: srgb transfer
    ("display", "exact_reference", "test", ("srgb", "display", "exact_reference")),
    (None, None, "e2nerf", ("srgb", "display", "exact_reference")),     # old E2NeRF import
])
def test_scene_attrs_drive_the_trainer_defaults(tmp_path, transfer, convention, source, want):
    path = _scene(tmp_path / "s.h5", transfer, convention, source=source)
    d = load_train_data(path, 3)
    assert (d.blur_space, d.event_transfer, d.count_convention) == want
    assert d.bins.shape == (3, 2, 2, H, W) and float(d.bins.min()) >= 0
    d2 = load_train_data(path, 3, blur_space="srgb", event_domain="linear")
    assert d2.blur_space == "srgb" and d2.event_transfer == "srgb"


def test_oracle_trains_on_sharp_frames_and_eval_splits_views(tmp_path):
    path = _scene(tmp_path / "s.h5", "srgb", "random_phase")
    d = load_train_data(path, 1, oracle=True)
    sc = schema.read(path)
    assert d.bins is None and d.viewmats.shape == (3, 1, 4, 4)
    np.testing.assert_array_equal((d.images.numpy() * 255).round().astype(np.uint8), np.asarray(sc.train.sharp))
    np.testing.assert_allclose(np.linalg.inv(d.viewmats[:, 0].numpy()), sc.train.sharp_poses, atol=1e-5)
    cfg = TrainConfig(scene=path, iterations=4, init_points=100, threads=1, sh_degree=0, oracle=True,
                      checkpoint_every=4)
    assert not cfg.uses_events and cfg.variant == "oracle"
    Trainer(cfg, tmp_path / "run", quiet=True).fit()
    m = evaluate(tmp_path / "run", write_images=False)
    assert m["variant"] == "oracle" and m["seed"] == 0
    assert m["blur_view"] == m["train_sharp"] and m["blur_view"]["n"] == 3
    assert m["novel_view"] == m["test"] and m["novel_view"]["n"] == 3
    assert json.loads((tmp_path / "run" / "metrics.json").read_text())["blur_view"]["n"] == 3
    with pytest.raises(ConfigError):
        TrainConfig(scene=path, oracle=True, naive=True)


def test_e2nerf_style_test_split(tmp_path):
    """No /train/sharp: the /test views that share a training viewpoint are the blur views, the config's
    test_novel_views the novel ones (E2NeRF's even/odd split)."""
    path = _scene(tmp_path / "s.h5", "display", "exact_reference", sharp=False, source="e2nerf",
                  config={"test_novel_views": [1]})
    cfg = TrainConfig(scene=path, iterations=2, init_points=100, threads=1, sh_degree=0, checkpoint_every=2)
    Trainer(cfg, tmp_path / "run", quiet=True).fit()
    m = evaluate(tmp_path / "run", write_images=False)
    assert m["novel_view"]["n"] == 1 and m["blur_view"]["n"] == 2 and m["test"]["n"] == 3
    assert m["variant"] == "blur+event"


def test_old_run_config_without_new_keys_loads(tmp_path):
    cfg = TrainConfig(scene="x.h5")
    d = json.loads(json.dumps(cfg.__dict__))
    for k in ("event_domain", "oracle"):
        d.pop(k)
    d["blur_space"] = "srgb"
    (tmp_path / "config.json").write_text(json.dumps(d))
    old = TrainConfig.load(tmp_path / "config.json")
    assert old.blur_space == "srgb" and old.event_domain == "auto" and not old.oracle
