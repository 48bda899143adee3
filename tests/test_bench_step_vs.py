"""tools/bench/bench_step_vs.py: a bad baseline is a one-line error with exit code 2; against its own tree the
two workers train bitwise the same model (the check that says a change altered no result)."""
import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "tools" / "bench" / "bench_step_vs.py"


def test_a_baseline_that_is_not_a_tree_is_an_error(tmp_path):
    out = subprocess.run([sys.executable, str(SCRIPT), "--baseline", str(tmp_path)], capture_output=True, text=True)
    assert out.returncode == 2
    assert out.stderr.strip().startswith("error: ") and len(out.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "bench_step_vs.json").exists()


@pytest.mark.slow
def test_against_its_own_tree_the_models_are_the_same(tmp_path):
    js, png = tmp_path / "r.json", tmp_path / "r.png"
    out = subprocess.run([sys.executable, str(SCRIPT), "--baseline", str(ROOT), "--quick", "--repeats", "2",
                          "--json", str(js), "--plot", str(png)], capture_output=True, text=True, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    d = json.loads(js.read_text())
    assert len(d["cases"]) == 2 and all(c["same_model_after_steps"] for c in d["cases"])
    for c in d["cases"]:
        r = c["cpu"]["ratio"]
        assert len(c["cpu"]["baseline_all_ms"]) == len(c["cpu"]["new_all_ms"]) == 2
        assert 0 < r["min"] <= r["median"] <= r["max"]
    assert png.stat().st_size > 0


@pytest.mark.slow
def test_raster_workload_against_its_own_tree_gives_the_same_image(tmp_path):
    """--raster: the rasterizer's forward + backward on one 10k cloud at 200x200, the same image bytes from both
    workers (a few seconds: one case, two pairs)."""
    js, png = tmp_path / "r.json", tmp_path / "r.png"
    out = subprocess.run([sys.executable, str(SCRIPT), "--baseline", str(ROOT), "--raster", "--repeats", "2",
                          "--json", str(js), "--plot", str(png)], capture_output=True, text=True, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    d = json.loads(js.read_text())
    assert d["workload"] == "rasterizer forward + backward"
    [c] = d["cases"]
    assert (c["width"], c["height"], c["gaussians"]) == (200, 200, 10_000) and c["same_model_after_steps"]
    assert len(c["cpu"]["new_all_ms"]) == 2


@pytest.mark.parametrize("case", ["346x260", "346x260:zero", "0x260:50000", "346:50000"])
def test_a_malformed_case_is_an_error(tmp_path, case):
    js = tmp_path / "r.json"
    out = subprocess.run([sys.executable, str(SCRIPT), "--baseline", str(ROOT), "--case", case, "--json", str(js)],
                         capture_output=True, text=True, cwd=ROOT)
    assert out.returncode == 2
    assert out.stderr.strip().startswith("error: ") and len(out.stderr.strip().splitlines()) == 1
    assert not js.exists()
