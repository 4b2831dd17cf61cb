# Set-up and the two jobs the README opens with.  `make sitl` flies one SITL episode;
# `make test` runs the test suite (what CI runs through .ci/run).
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
# The model `make sitl` flies: until a trained policy ships as models/default.onnx, the
# goal-seeker plumbing model (it ignores the camera, so it flies the obstacle-free level).
MODEL ?= runs/models/goal-seeker.onnx
LEVEL ?= 0
SEED ?= 0

.PHONY: sitl test install clean

$(BIN)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	# The local CPU build of torch first, so the extras' torch range installs nothing more.
	$(BIN)/python -m pip install --quiet torch==2.13.0
	$(BIN)/python -m pip install --quiet -e '.[sim,train,realsense,dev]'
	touch $@

install: $(BIN)/.installed

runs/models/goal-seeker.onnx: $(BIN)/.installed export/goal_seeker.py
	$(BIN)/cmnav export goal-seeker -o $@

sitl: $(BIN)/.installed $(MODEL)
	$(BIN)/cmnav sitl --model $(MODEL) --level $(LEVEL) --seed $(SEED) --json

test: $(BIN)/.installed
	$(BIN)/python -m pytest -q

clean:
	rm -rf runs .pytest_cache .hypothesis
