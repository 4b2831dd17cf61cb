# Set-up and the two jobs the README opens with.  `make sitl` flies one SITL episode;
# `make test` runs the test suite (what CI runs through .ci/run).
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
# The model `make sitl` flies: models/default.onnx, exported from the committed encoder and
# policy checkpoints (the ONNX file itself, about 60 MB, is built here rather than committed), at
# a cluttered level.  `make sitl MODEL=runs/models/goal-seeker.onnx LEVEL=0` flies the plumbing
# model instead.
MODEL ?= models/default.onnx
LEVEL ?= 3
SEED ?= 0

.PHONY: sitl test install clean

$(BIN)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	# The local CPU build of torch first, so the extras' torch range installs nothing more.
	$(BIN)/python -m pip install --quiet torch==2.13.0
	$(BIN)/python -m pip install --quiet -e '.[sim,train,realsense,report,dev]'
	touch $@

install: $(BIN)/.installed

runs/models/goal-seeker.onnx: $(BIN)/.installed export/goal_seeker.py
	$(BIN)/cmnav export goal-seeker -o $@

models/default.onnx: $(BIN)/.installed models/cmwae-stereo/model.json models/student-stereo/model.json
	$(BIN)/cmnav export --encoder models/cmwae-stereo --policy models/student-stereo -o $@

# Exit code 1 is an outcome (crash or timeout, in the JSON summary), not a failure to run.
sitl: $(BIN)/.installed $(MODEL)
	$(BIN)/cmnav sitl --model $(MODEL) --level $(LEVEL) --seed $(SEED) --json || [ $$? -eq 1 ]

# Two workers: first the tests that compute (6.2 min on 2 cores with OpenMP threads passive,
# tests/conftest.py; 11.6 in one process), then the
# real-time SITL flights (marker `flight`, ~0.5 core each, mostly waiting on the clock), kept
# apart so that no flight shares the cores with training tests; `pytest -q` alone runs
# everything in one process.
test: $(BIN)/.installed
	$(BIN)/python -m pytest -q -m "not flight" -n 2
	$(BIN)/python -m pytest -q -m flight -n 2

clean:
	rm -rf runs .pytest_cache .hypothesis
