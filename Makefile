# Everything runs from a virtual environment inside the repo (.venv); `make setup` builds it.
PY ?= python3.11
TORCH_PIP_ARGS ?=
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
export OMP_WAIT_POLICY := PASSIVE

.PHONY: setup test test-slow demo docs bench study-quick study study-event-term study-attribution study-response bench-fidelity bench-fidelity-quick clean

setup: $(STAMP)

$(STAMP): pyproject.toml setup.py ev3dgs/io/aedat4/_fast.c ev3dgs/splat/_raster.c
	$(PY) -m venv $(VENV)
	$(BIN)/pip install --upgrade pip
	# torch first and pinned: an unpinned torch pulls several GB of CUDA packages. On a machine whose pip
	# resolves torch==2.13.0 to a CUDA build, TORCH_PIP_ARGS='--index-url https://download.pytorch.org/whl/cpu'
	# gets the CPU build instead.
	$(BIN)/pip install torch==2.13.0 $(TORCH_PIP_ARGS)
	$(BIN)/pip install -e '.[blender,view,video,docs,cuda,dev]'
	# the reference LPIPS package, for tests/test_lpips.py only; --no-deps: its torchvision would replace our torch
	$(BIN)/pip install --no-deps lpips==0.1.4
	touch $(STAMP)

test: setup
	$(BIN)/python -m pytest -q --durations=15

test-slow: setup
	# the browser test (tests/test_view_browser.py) drives the system's Chromium; it skips when there is none
	command -v chromium >/dev/null || (apt-get update && apt-get install -y chromium) || echo "no chromium: the browser test will skip"
	# pytest exits 5 when no test is marked slow: that is not a failure
	$(BIN)/python -m pytest -q -m slow || [ $$? -eq 5 ]

# the documentation site into site/ (tests/test_docs.py builds it with --strict in `make test`)
docs: setup
	$(BIN)/python -m mkdocs build --strict -d site

# what a GPU machine without network needs beside the repository for tools/gpu_device_run.sh (docs/gpu.md), in
# gpu_carry/ (ignored): wheels for its Python 3.12 (gsplat, ninja and the dependencies training imports that such
# machines lacked; not the AEDAT readers' lz4, cramjam and zstandard, which training does not import) and the lego
# scene at DAVIS346 size (24 training views of 17 sub-frames, 8 test views; Blender on one core, resumable: a
# second run keeps the views already rendered). Carry gpu_carry/wheels and gpu_carry/lego_346x260.h5, not the
# folder (an interrupted render leaves its cache there).
GPU_CARRY := gpu_carry
.PHONY: gpu-carry
gpu-carry: setup
	$(BIN)/pip download --no-deps -d $(GPU_CARRY)/wheels --python-version 3.12 --only-binary=:all: \
		--platform manylinux_2_28_x86_64 --platform manylinux2014_x86_64 --platform manylinux_2_17_x86_64 \
		gsplat==1.5.3 plyfile==1.1.5 colour-science==0.4.7 ninja==1.13.2
	test -f $(GPU_CARRY)/lego_346x260.h5 || $(BIN)/ev3dgs-sim make-dataset --scene lego --size 346x260 --views 24 \
		--test-views 8 --subframes 17 --samples 16 --seed 0 --out $(GPU_CARRY)/lego_346x260.h5
	du -sh $(GPU_CARRY)/wheels $(GPU_CARRY)/lego_346x260.h5

demo: setup
	$(BIN)/python -m ev3dgs.demo --out demo_out

bench: setup
	$(BIN)/python tools/bench/bench_sim.py --json tools/results/bench_sim.json --plot tools/results/bench_sim.png

# accuracy against time: reduced studies in well under 15 minutes on 2 cores; `make study` for the full ones
study-quick: setup
	$(BIN)/python tools/studies/study_sim.py --quick
	$(BIN)/python tools/studies/study_render.py --quick
	$(BIN)/python tools/studies/study_train.py --quick

study: setup
	$(BIN)/python tools/studies/study_sim.py
	$(BIN)/python tools/studies/study_render.py
	$(BIN)/python tools/studies/study_train.py

# the event term against the contrast threshold and its mismatch on one scene (all thirteen steps about 7 h on 2 cores)
study-event-term: setup
	$(BIN)/python tools/studies/study_event_term.py --variants blur+event-count --seeds 0 \
		--json tools/results/study_event_term_count.json
	$(BIN)/python tools/studies/study_event_term.py --variants blur-only blur+event oracle \
		--merge tools/results/study_event_term_count.json \
		--json tools/results/study_event_term.json --plot tools/results/study_event_term.png
	$(BIN)/python tools/studies/study_event_term.py --variants blur+event-map --mismatch 0.1 0.4 \
		--merge tools/results/study_event_term.json \
		--json tools/results/study_event_term_map.json --plot tools/results/study_event_term_map.png
	$(BIN)/python tools/studies/study_event_term.py --variants blur-only blur+event blur-only-hdr blur+event-hdr \
		blur+event-sh --thresholds 0.05 --mismatch 0.1 --blur-fit --json tools/results/study_event_term_hdr05.json
	$(BIN)/python tools/studies/study_event_term.py --variants blur+event-hdr-sh blur-only-hdr-sh oracle-sh \
		--blur-fit --merge tools/results/study_event_term.json tools/results/study_event_term_hdr05.json \
		--json tools/results/study_event_term_hdr.json --plot tools/results/study_event_term_hdr.png
	$(BIN)/python tools/studies/study_event_term.py --variants blur+event-edi blur+event-hdr-sh-edi --mismatch 0.1 \
		--merge tools/results/study_event_term_hdr.json \
		--json tools/results/study_event_term_edi.json --plot tools/results/study_event_term_edi.png
	$(BIN)/python tools/studies/study_event_term.py --variants blur+event-hdr-sh-map --mismatch 0.1 0.4 \
		--merge tools/results/study_event_term_edi.json tools/results/study_event_term_map.json \
		--json tools/results/study_event_term_hdr_map.json --plot tools/results/study_event_term_hdr_map.png
	$(BIN)/python tools/studies/study_event_term.py --variants blur+event-px2 blur+event-hdr-sh-map-px2 \
		--thresholds 0.05 --mismatch 0.1 --json tools/results/study_event_term_px2.json
	$(BIN)/python tools/studies/study_event_term.py --variants blur+event-hdr-sh-map@17 --mismatch 0.1 \
		--merge tools/results/study_event_term_px2.json tools/results/study_event_term_hdr_map.json \
		--json tools/results/study_event_term_subposes.json --plot tools/results/study_event_term_subposes.png \
		--plot-variants blur+event blur+event-px2 blur+event-hdr-sh-map blur+event-hdr-sh-map-px2 \
		blur+event-hdr-sh-map@17
	$(BIN)/python tools/studies/study_event_term.py --variants blur-only-sh blur+event-sh oracle-sh \
		--json tools/results/study_event_term_sh.json --plot tools/results/study_event_term_sh.png
	$(BIN)/python tools/studies/study_event_term.py --variants blur+event-sh-mapprior --mismatch 0.1 0.4 \
		--merge tools/results/study_event_term_sh.json \
		--json tools/results/study_event_term_sh_mapprior.json --plot tools/results/study_event_term_sh_mapprior.png
	$(BIN)/python tools/studies/study_event_term.py --variants blur+event-sh-robust \
		--merge tools/results/study_event_term_sh.json --plot-variants blur+event-sh blur+event-sh-robust \
		--json tools/results/study_event_term_robust.json --plot tools/results/study_event_term_robust.png
	$(BIN)/python tools/studies/study_event_term.py --variants blur+event-hdr-sh-map@17-robust --thresholds 0.05 \
		--mismatch 0.1 --seeds 0 1 2 --merge tools/results/study_event_term_subposes.json \
		tools/results/study_event_term_subposes_seed2.json tools/results/study_event_term_robust.json \
		--json tools/results/study_event_term_all_options.json

# where the gap to the sharp oracle comes from: heldout_shake (shares study-event-term's renders and runs; ~2 h
# on 2 cores after study-event-term) and lowlight (frame noise), two seeds
study-attribution: setup
	$(BIN)/python tools/studies/study_attribution.py --variants info-oracle oracle blur-ideal@17 blur-only@17 \
		blur-only blur+event blur+event@17 blur+event@4pairs oracle@3000 blur-only@3000 blur+event@3000 \
		--json tools/results/study_attribution.json --plot tools/results/study_attribution.png
	$(BIN)/python tools/studies/study_attribution.py --variants info-oracle-sh oracle-sh --seeds 0 1 2 \
		--json tools/results/study_attribution_sh.json
	$(BIN)/python tools/studies/study_attribution.py --scene lowlight --theta 0.2 --mismatch 0.15 --samples 16 \
		--variants naive blur-only blur+event oracle oracle-noisy info-oracle blur-clean naive-clean \
		blur+event-fn0 blur+event-w4 --cache tools/results/attribution_cache_lowlight \
		--json tools/results/study_attribution_lowlight.json --plot tools/results/study_attribution_lowlight.png

# a camera with a tone curve the scene does not declare, and --learn-response (heldout_shake at theta 0.05; shares
# study-event-term's renders; ~20 min on 2 cores after them)
study-response: setup
	$(BIN)/python tools/studies/study_response.py --variants blur-only blur+event blur+event-response oracle \
		blur+event-hdr blur+event-hdr-response --json tools/results/study_response.json \
		--plot tools/results/study_response.png

# naive / blur-only / blur+event / sharp oracle on the built-in scenes, 3 seeds (~1 h on 2 cores);
# the quick one is lego, one seed, small size (<= 10 minutes)
bench-fidelity: setup
	$(BIN)/python tools/bench/bench_fidelity.py

bench-fidelity-quick: setup
	$(BIN)/python tools/bench/bench_fidelity.py --quick

clean:
	rm -rf $(VENV) demo_out site .pytest_cache
