"""Shared test set-up.

Tolerance policy (issue 10): a bound must hold on any CPU, BLAS build and thread count, so it comes from the
arithmetic, never from a value one machine printed. With unit round-off u (float64 1.1e-16, float32 6.0e-8):
- closed forms and short elementwise chains on O(1) values (colour curves, Rodrigues, projections): a few u
  per operation, < 100 operations -> 1e-12 (float64), 1e-5 (float32);
- reductions over n terms whose order a library may change with threads or SIMD width (sums, convolutions,
  matmuls): n u |terms| -> the bound scales with n and the magnitudes, and is stated next to the assertion;
- ill-conditioned maps lose digits in proportion to their condition number: arccos near 0/pi (use the atan2
  forms in ev3dgs.geometry), divisions by small denominators (SSIM's C1, C2), T recovered by division in the
  rasterizer backward (bounded by the 1e-4 transmittance cut-off): their bounds carry that factor;
- statistical assertions use several standard errors of the estimate, with fixed seeds.
Where a comparison can be exact (same code, same inputs, deterministic kernels) the tests use equality.
"""
import os
import shutil

import pytest

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
# numba re-reads its config at every compile and refuses a thread count other than the one its pool was
# launched with; without NUMBA_NUM_THREADS it counts os.sched_getaffinity(0), which a test monkeypatches
# (tests/test_aedat4_packets.py). Pinned for the session as a guard; the failure seen on a cold kernel cache
# came from a test importing a benchmark that sets NUMBA_NUM_THREADS=1 (tests/test_calibrate_compare.py).
os.environ.setdefault("NUMBA_NUM_THREADS", str(max(1, len(os.sched_getaffinity(0)))))


@pytest.fixture
def scene_copy(valid_file, tmp_path):
    """A writable copy of the module's ``valid_file`` fixture (a scene file the module's tests corrupt)."""
    path = tmp_path / "scene.h5"
    shutil.copy(valid_file, path)
    return path
