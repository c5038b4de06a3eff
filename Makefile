# make train: set up .venv and run the mission (learners taught by a simulated trainer and the game at once,
# against the game alone; a few minutes); make test: set up and run lint + tests.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: train test test-parallel test-serial lint bench clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[test]"
	touch $(STAMP)

MISSION ?= multirun/mission/$(shell date +%Y-%m-%d_%H-%M-%S)

train: $(STAMP)
	$(PY) train.py -m +experiment=mission hydra.sweep.dir=$(MISSION)
	$(PY) evaluate.py runs=$(MISSION) last=20

lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

# The suite on both cores (pytest-xdist), then the latency and browser tests alone.
test: lint test-parallel test-serial

test-parallel: $(STAMP)
	$(VENV)/bin/pytest -q -n 2 --dist worksteal -m "not serial"

test-serial: $(STAMP)
	$(VENV)/bin/pytest -q -m serial

bench: $(STAMP)
	$(PY) -m pip install --quiet -e ".[test,bench]"
	$(PY) benchmarks/tetris_throughput.py

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache
