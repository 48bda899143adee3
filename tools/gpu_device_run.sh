#!/usr/bin/env bash
# The DAVIS346 GPU check (docs/gpu.md) on a machine with a CUDA GPU, torch, nvcc and no network, run from the
# repository root with the folder `make gpu-carry` fills beside it (gpu_carry/: wheels for Python 3.12, the
# 346x260 lego scene when it was made):
#
#   OUT=/some/dir tools/gpu_device_run.sh 1   # install, kernels, the gpu-marked tests, then the davis346 plan
#   OUT=/some/dir tools/gpu_device_run.sh 2   # the same machine: the plan's runs part 1 did not complete
#
# Each part stops training at its deadline (PART1_MINUTES, PART2_MINUTES after its start; the run in progress is
# scored where it stopped) so that it ends inside a 10-minute command (part 2: inside the device time left; its
# JSON is written to $OUT after every run, so a part killed at its limit still returns what it finished).
# Results in $OUT: gpu_partN.json and gpu_partN.log, the trained models (model, settings, log, metrics) as
# models_partN.tgz, in 15 MiB pieces
# (models_partN.tgz.aa, .ab, ...; `cat models_partN.tgz.* | tar xz` joins them). Without the lego scene the
# 346x260 runs train on a synthetic blob scene (gpu_check's default), and the JSON names the scene.
set -uo pipefail
part=${1:?usage: tools/gpu_device_run.sh 1|2}
carry=${GPU_CARRY:-gpu_carry}
out=${OUT:?set OUT to the folder the results go to}
state=${GPU_STATE:-/tmp/ev3dgs_gpu_check}   # kept between the two parts on the same machine
mkdir -p "$out" "$state"
export PYTHONPATH=$PWD MAX_JOBS=${MAX_JOBS:-16} TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0}
export OMP_WAIT_POLICY=PASSIVE
# a system Python that refuses pip (PEP 668, "externally managed") is asked again with --break-system-packages
python3 -m pip install -q --no-index --no-deps "$carry"/wheels/*.whl ||
  python3 -m pip install -q --no-index --no-deps --break-system-packages "$carry"/wheels/*.whl ||
  { echo "error: installing the carried wheels failed" >&2; exit 2; }
if nb=$(python3 -c 'import ninja; print(ninja.BIN_DIR)' 2>/dev/null); then
  export PATH=$nb:$PATH   # gsplat's kernel build needs ninja
fi
scene=()
[ -f "$carry/lego_346x260.h5" ] && scene=(--scene-large "$carry/lego_346x260.h5")
common=(--plan davis346 "${scene[@]}" --workdir "$state/work" --keep-models "$state/models_part$part")
case $part in
  1) args=(--deadline-minutes "${PART1_MINUTES:-8.5}") ;;
  2) args=(--skip-tests --skip-done "$state/gpu_part1.json" --deadline-minutes "${PART2_MINUTES:-2.5}") ;;
  *) echo "error: part must be 1 or 2, got $part" >&2; exit 2 ;;
esac
# GPU_CHECK_ARGS: more gpu_check arguments (tests/test_gpu_check.py runs this script with --dry-run on a CPU)
python3 tools/gpu_check.py "${common[@]}" "${args[@]}" ${GPU_CHECK_ARGS:-} --json "$out/gpu_part$part.json" 2>&1 |
  tee "$out/gpu_part$part.log"
rc=${PIPESTATUS[0]}
cp "$out/gpu_part$part.json" "$state/" 2>/dev/null
if [ -d "$state/models_part$part" ]; then
  tar -czf - -C "$state" "models_part$part" | split -b 15m - "$out/models_part$part.tgz."
fi
ls -la "$out"
exit "$rc"
