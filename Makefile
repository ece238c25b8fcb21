# make demo: create .venv, install, run the main job on the shipped defaults.
# make test: create .venv, install with dev extras, run the test suite.
PYTHON ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
# A CPU build of torch is enough for everything here; override with `make TORCH_SPEC=torch ...` for a CUDA build.
TORCH_SPEC ?= torch==2.13.0
export MUJOCO_GL ?= egl

.PHONY: demo test test-hardware test-gpu lint bench clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV) || python3 -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip

$(VENV)/.installed: pyproject.toml | $(BIN)/python
	$(BIN)/python -c "import torch" 2>/dev/null || $(BIN)/pip install --quiet "$(TORCH_SPEC)" || $(BIN)/pip install --quiet "torch>=2.4"
	$(BIN)/pip install --quiet -e ".[dev]"
	touch $@

demo: $(VENV)/.installed
	$(BIN)/rotate demo --out demo_out

# The suite ends with the skipped tests' reasons (-rs) and what -m deselected, with the command that runs it.
test: $(VENV)/.installed
	$(BIN)/ruff check .
	$(BIN)/python -m pytest -q -x -rs --durations=15

# Tests against real devices (a hand on its bus, Digit 360 or Xela sensors): see tests/hardware/test_hw_real_devices.py
# for the environment variables that name them.
test-hardware: $(VENV)/.installed
	$(BIN)/python -m pytest -q -rs -m hardware

# Tests that need a CUDA GPU (the MuJoCo Warp backend at scale): a CUDA build of torch and the [warp] extra.
test-gpu: $(VENV)/.installed
	$(BIN)/pip install --quiet -e ".[warp]"
	$(BIN)/python -m pytest -q -rs -m gpu

lint: $(VENV)/.installed  # ruff's rules (pyproject.toml); the code is wrapped by hand at 120 columns, not by ruff format
	$(BIN)/ruff check .

bench: $(VENV)/.installed
	$(BIN)/python scripts/bench_env.py

clean:
	rm -rf $(VENV) demo_out .pytest_cache
