# fleet_torchrl make targets. Every target creates and uses the project's own .venv.
# Hydra overrides go in ARGS, e.g.  make evaluate ARGS="agent=heuristic site=no_closure"
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
ARGS   ?=
PYTEST_ARGS ?=

.PHONY: help install test test-fast lint format table train evaluate grid bench tensorboard clean

help:  ## list the targets
	@grep -E '^[a-z-]+:.*## ' $(MAKEFILE_LIST) | awk -F':.*## ' '{printf "  %-14s %s\n", $$1, $$2}'

install: $(STAMP)  ## create .venv and install the package with its dev tools

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[dev]'
	@touch $(STAMP)

test: $(STAMP)  ## run the whole test suite (slow end-to-end tests included)
	$(PY) -m pytest $(PYTEST_ARGS)

test-fast: $(STAMP)  ## run the tests not marked slow
	$(PY) -m pytest -m "not slow" $(PYTEST_ARGS)

lint: $(STAMP)  ## ruff
	$(PY) -m ruff check fleet_torchrl tests

format: $(STAMP)  ## ruff format + import sort
	$(PY) -m ruff check --fix fleet_torchrl tests

table: $(STAMP)  ## main job: train the learned policies (if missing) and compare all five -> results/table
	$(PY) -m fleet_torchrl.table $(ARGS)

train: $(STAMP)  ## train one policy, e.g. ARGS="agent=dqn state=all"
	$(PY) -m fleet_torchrl.train $(ARGS)

grid: $(STAMP)  ## DQN hyperparameter grid search (Hydra multirun, joblib) + summary -> results/grid
	$(PY) -m fleet_torchrl.train -m +experiment=grid $(ARGS)
	$(PY) -m fleet_torchrl.grid

evaluate: $(STAMP)  ## evaluate a policy (SPEC §4); overrides in ARGS
	$(PY) -m fleet_torchrl.evaluate $(ARGS)

bench: $(STAMP)  ## simulator and evaluation throughput (docs/BENCHMARKS.md)
	$(PY) -m fleet_torchrl.bench $(ARGS)

tensorboard: $(STAMP)  ## open TensorBoard on the training runs
	$(VENV)/bin/tensorboard --logdir_spec outputs:outputs,multirun:multirun

clean:  ## remove Hydra outputs and sweeps (keeps .venv and results/)
	rm -rf outputs multirun/*/ .pytest_cache .ruff_cache
	find . -name __pycache__ -type d -not -path './.venv/*' -exec rm -rf {} +
