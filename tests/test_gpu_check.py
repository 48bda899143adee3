"""tools/gpu_check.py's CPU dry-run path: environment report, the gpu-marked tests run (and skip without CUDA),
synthetic scenes, a few training steps of each variant, the JSON marked as a dry run."""
import json
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tools"))
import gpu_check  # noqa: E402


def test_dry_run_writes_the_json(tmp_path, capsys):
    out = tmp_path / "gpu_dry.json"
    rc = gpu_check.main(["--dry-run", "--steps", "2", "--json", str(out), "--workdir", str(tmp_path / "work")])
    assert rc == 0
    r = json.loads(out.read_text())
    assert r["dry_run"] is True and r["device"] == "cpu" and r["backend"] == "cpu" and r["steps"] == [2]
    assert r["gpu"] == "none (dry run)" and r["environment"]["python"]
    assert r["gpu_tests"]["returncode"] in (0, 5) and "-m gpu" in r["gpu_tests"]["command"]
    if r["environment"]["gsplat"]:  # the gpu-marked parity tests were collected and skipped (no CUDA here)
        assert r["gpu_tests"]["counts"].get("skipped", 0) >= 2 and not r["gpu_tests"]["counts"].get("failed")
    runs = r["runs"]
    assert {(x["size"], x["variant"]) for x in runs} == {(s, v) for s in gpu_check.SIZES for v in gpu_check.VARIANTS}
    for x in runs:
        assert x["steps"] == 2 and x["ms_per_step"] > 0 and x["gaussians"] > 0 and x["test_psnr"] > 5
    assert {(x["width"], x["height"]) for x in runs} == {(24, 18), (86, 65)}  # a quarter of 96x72, 346x260


def test_install_command_never_reaches_the_network():
    cmd = gpu_check.install_command("/wheels")
    assert "--no-index" in cmd and cmd[cmd.index("--find-links") + 1] == "/wheels" and cmd[-1] == "ev3dgs[cuda]"


def test_without_cuda_the_real_run_refuses(capsys):
    import torch

    if torch.cuda.is_available():
        pytest.skip("a CUDA device is present")
    assert gpu_check.main(["--skip-tests"]) == 2
    assert "--dry-run" in capsys.readouterr().err


def test_gpu_slug():
    assert gpu_check.gpu_slug("NVIDIA H100 80GB HBM3") == "nvidia_h100_80gb_hbm3"
