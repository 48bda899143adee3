"""--event-floor median|chi2, --event-huber and --densify-from blur in the trainer: densification statistics from
the blur term alone are those of a run without the event loss (a second computation of the same gradient);
the three together train, stay finite and are bitwise reproducible; bad values are refused."""
from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from test_train import cfg, scene_path  # noqa: E402,F401  (the small blob scene and its settings)

from ev3dgs.errors import ConfigError  # noqa: E402
from ev3dgs.train.trainer import Trainer  # noqa: E402


def _first_step_stats(scene, out, **kw) -> torch.Tensor:
    tr = Trainer(cfg(scene, **kw), out, quiet=True)
    tr.train_step()
    return tr.strategy_state["grad2d"].clone()


def test_blur_densification_sees_only_the_blur_gradient(scene_path, tmp_path):
    """After one step from the same start (same seed: same Gaussians, same view), the accumulated screen-space
    gradient norms with --densify-from blur (the noise norm's default) equal a blur-only run's, whose backward
    holds nothing else; with "all" the event term adds to them. Float32 sums of the same terms in the same
    order: equal to a few ulps at most."""
    blur_only = _first_step_stats(scene_path, tmp_path / "b", event_loss=False)
    from_blur = _first_step_stats(scene_path, tmp_path / "e", densify_from="blur")
    default = _first_step_stats(scene_path, tmp_path / "d")
    from_all = _first_step_stats(scene_path, tmp_path / "a", densify_from="all")
    assert float(blur_only.abs().sum()) > 0
    torch.testing.assert_close(from_blur, blur_only, rtol=1e-6, atol=0)
    assert torch.equal(default, from_blur)
    assert not torch.allclose(from_all, blur_only, rtol=1e-3, atol=0)


@pytest.mark.parametrize("floor", ["median", "chi2"])
def test_robust_event_options_train_finite_and_reproducible(scene_path, tmp_path, floor):
    opts = dict(iterations=40, event_floor=floor, event_huber=3.0, densify_from="blur")
    runs = []
    for name in ("a", "b"):
        tr = Trainer(cfg(scene_path, **opts), tmp_path / name, quiet=True)
        tr.fit()
        runs.append({k: p.detach().clone() for k, p in tr.model.params.items()})
    for k, p in runs[0].items():
        assert torch.isfinite(p).all(), k
        assert torch.equal(p, runs[1][k]), k
    plain = Trainer(cfg(scene_path, iterations=40, event_floor="mean", event_huber=0.0, densify_from="all"),
                    tmp_path / "plain", quiet=True)
    plain.fit()
    assert any(p.shape != runs[0][k].shape or not torch.equal(p.detach(), runs[0][k])
               for k, p in plain.model.params.items())


@pytest.mark.parametrize("bad", [dict(event_floor="mode"), dict(event_huber=-1.0),
                                 dict(event_huber=float("inf")), dict(densify_from="event"),
                                 dict(event_floor="median", event_norm="count"),
                                 dict(event_floor="chi2", event_norm="count"),
                                 dict(event_huber=3.0, event_norm="count")])
def test_bad_robust_event_options_are_refused(scene_path, bad):
    with pytest.raises(ConfigError):
        cfg(scene_path, **bad)


def test_the_defaults_follow_the_norm_and_a_config_saved_without_them_keeps_its_own(scene_path, tmp_path):
    """Unset, the floor, penalty and densification source are the noise norm's chi2 / 3 / blur and the count
    norm's mean / 0 / all; a config.json written before the three keys existed loads with the values its run
    used (config.LEGACY_VALUES), not today's."""
    import json
    from dataclasses import asdict

    from ev3dgs.train.config import TrainConfig

    noise, count = cfg(scene_path), cfg(scene_path, event_norm="count")
    assert (noise.floor_stat, noise.huber_c, noise.densify_source) == ("chi2", 3.0, "blur")
    assert (count.floor_stat, count.huber_c, count.densify_source) == ("mean", 0.0, "all")
    saved = {k: v for k, v in asdict(noise).items() if k not in ("event_floor", "event_huber", "densify_from")}
    (tmp_path / "config.json").write_text(json.dumps(saved))
    old = TrainConfig.load(tmp_path / "config.json")
    assert (old.floor_stat, old.huber_c, old.densify_source) == ("mean", 0.0, "all")


def test_the_default_noise_norm_run_is_the_explicit_one_bit_for_bit(scene_path, tmp_path):
    params = []
    for name, kw in (("d", {}), ("e", dict(event_floor="chi2", event_huber=3.0, densify_from="blur"))):
        tr = Trainer(cfg(scene_path, iterations=30, **kw), tmp_path / name, quiet=True)
        tr.fit()
        params.append({k: p.detach().clone() for k, p in tr.model.params.items()})
    assert all(torch.equal(p, params[1][k]) for k, p in params[0].items())


def test_bench_event_weighting_times_the_three_settings_before_any_split(scene_path, tmp_path):
    """tools/bench/bench_event_weighting.py: the three settings timed, ratios against the default's median,
    and a run long enough to reach the first split (step 500 of a 30 000-step schedule) refused."""
    import json

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools" / "bench"))
    from bench_event_weighting import VARIANTS, main

    out = tmp_path / "w.json"
    assert main(["--scene", scene_path, "--rounds", "2", "--init-points", "200", "--json", str(out),
                 "--plot", str(tmp_path / "w.png")]) == 0
    res = json.loads(out.read_text())
    assert set(res["ms_per_step"]) == set(VARIANTS) and res["ratio_to_default"]["default"] == 1.0
    assert all(v > 0 for v in res["ms_per_step"].values()) and (tmp_path / "w.png").stat().st_size > 1000
    with pytest.raises(SystemExit, match="no Gaussian may be split"):
        main(["--scene", scene_path, "--rounds", "495", "--json", str(tmp_path / "x.json")])
