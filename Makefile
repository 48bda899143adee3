# Everything runs from a virtual environment inside the repo (.venv); `make setup` builds it.
PY ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
export OMP_WAIT_POLICY := PASSIVE

.PHONY: setup test test-slow demo bench study-quick study clean

setup: $(STAMP)

$(STAMP): pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/pip install --upgrade pip
	# torch first and pinned: an unpinned torch pulls several GB of CUDA packages.
	$(BIN)/pip install torch==2.13.0
	$(BIN)/pip install -e '.[dev]'
	touch $(STAMP)

test: setup
	$(BIN)/python -m pytest -q

test-slow: setup
	# pytest exits 5 when no test is marked slow: that is not a failure
	$(BIN)/python -m pytest -q -m slow || [ $$? -eq 5 ]

demo: setup
	$(BIN)/python -m ev3dgs.demo --out demo_out

bench: setup
	$(BIN)/python tools/bench_sim.py --json tools/results/bench_sim.json --plot tools/results/bench_sim.png

# accuracy against time: reduced studies in well under 15 minutes on 2 cores; `make study` for the full ones
study-quick: setup
	$(BIN)/python tools/study_sim.py --quick
	$(BIN)/python tools/study_render.py --quick
	$(BIN)/python tools/study_train.py --quick

study: setup
	$(BIN)/python tools/study_sim.py
	$(BIN)/python tools/study_render.py
	$(BIN)/python tools/study_train.py

clean:
	rm -rf $(VENV) demo_out .pytest_cache
