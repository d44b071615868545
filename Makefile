# bid-sim: every target wraps the `bid` command line.
PYTHON ?= python3.11
VENV := .venv
BID := $(VENV)/bin/bid
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

TOWN ?= 02
DENSITY ?= normal

EPISODES ?= 48
WORKERS ?= 2
# Share of driving time with steering noise (recovery data; labels stay the expert's).
PERTURB ?= 0.2
# `make record` records Town01 unless TOWN is given (the demo's default is Town02).
RECORD_TOWN = $(if $(filter command line environment,$(origin TOWN)),$(TOWN),01)

AGENT ?= bid
CHECKPOINT ?= runs/small/best.pt
WEATHERS ?= test
SEEDS ?= 3

.PHONY: demo test bench towns clean lint record evaluate train

$(STAMP): pyproject.toml
	@command -v $(PYTHON) >/dev/null 2>&1 || { echo "error: $(PYTHON) not found; install Python 3.11 or run 'make PYTHON=python3 ...'"; exit 2; }
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q -e '.[dev,cluster]'
	touch $(STAMP)

demo: $(STAMP)
	$(BID) towns
	$(BID) episode --town $(TOWN) --density $(DENSITY) --route 0 --seed 0 --agent expert

test: $(STAMP)
	$(PY) -m pytest tests

bench: $(STAMP)
	$(PY) benchmarks/bench_world.py
	$(BID) bench render
	$(BID) bench record
	$(PY) benchmarks/bench_reader.py
	$(PY) benchmarks/bench_model.py

# The BID model, `small` preset, on the recordings of `make record`.
train: $(STAMP)
	$(BID) train --preset small --data data/town01 --name small

# The closed-loop benchmark; AGENT=expert needs no checkpoint.
evaluate: $(STAMP)
	$(BID) evaluate --town $(TOWN) --density $(DENSITY) --weathers $(WEATHERS) --seeds $(SEEDS) \
		--agent $(AGENT) $(if $(filter bid,$(AGENT)),--checkpoint $(CHECKPOINT)) --workers $(WORKERS) \
		--out results/town$(TOWN)_$(AGENT)_$(DENSITY)

# Demonstrations: the expert over random routes, four train weathers, three densities.
record: $(STAMP)
	$(BID) record --town $(RECORD_TOWN) --episodes $(EPISODES) --perturb $(PERTURB) --workers $(WORKERS) \
		--out data/town$(RECORD_TOWN)

towns: $(STAMP)
	$(BID) towns

lint: $(STAMP)
	$(VENV)/bin/ruff check bid_sim bid_model tests benchmarks

clean:
	rm -rf build results runs .pytest_cache
