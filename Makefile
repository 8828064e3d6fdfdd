# fleet_torchrl make targets. Every target creates and uses the project's own .venv.
# Hydra overrides go in ARGS, e.g.  make evaluate ARGS="agent=heuristic site=no_closure"
# Each target runs a command that is also a console script after make install
# (python -m fleet_torchrl.train = fleet-train, ...; README "Commands").
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
ARGS   ?=
# optional-dependency groups that make install adds (CI adds ray)
EXTRAS ?= dev,cluster,gym
PYTEST_ARGS ?=
# test workers (pytest-xdist): one per core by default; PYTEST_WORKERS=0 runs in this process
PYTEST_WORKERS ?= auto

.PHONY: help install test test-fast lint format table quick train evaluate grid bench tensorboard clean \
        policies policy-maps sweep-pc sweep-tc sweep-nv sweeps experiments report objective
TIMED  := $(PY) -m fleet_torchrl.utils.timing

help:  ## list the targets
	@grep -E '^[a-z-]+:.*## ' $(MAKEFILE_LIST) | awk -F':.*## ' '{printf "  %-14s %s\n", $$1, $$2}'

install: $(STAMP)  ## create .venv and install the package, its console scripts fleet-<command> and the EXTRAS groups (dev, cluster, gym; CI adds ray)

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[$(EXTRAS)]'
	@touch $(STAMP)

test: $(STAMP)  ## run the whole test suite (slow end-to-end tests included), one worker per core
	$(PY) -m pytest -n $(PYTEST_WORKERS) $(PYTEST_ARGS)

test-fast: $(STAMP)  ## run the tests not marked slow
	$(PY) -m pytest -n $(PYTEST_WORKERS) -m "not slow" $(PYTEST_ARGS)

lint: $(STAMP)  ## ruff
	$(PY) -m ruff check fleet_torchrl tests hydra_plugins benchmarks

format: $(STAMP)  ## apply ruff's automatic lint fixes (import order, modern syntax)
	$(PY) -m ruff check --fix fleet_torchrl tests hydra_plugins benchmarks

table: $(STAMP)  ## main job: train the recipes over 3 seeds (if missing), compare with rule and heuristic -> results/table; some: ARGS="table.only=[dqn_partial,search]"
	$(TIMED) table -- $(PY) -m fleet_torchrl.table $(ARGS)

quick: $(STAMP)  ## a first look at the main comparison in minutes (1 seed, each recipe's preview budget) -> results/quick
	$(TIMED) quick -- $(PY) -m fleet_torchrl.table +experiment=quick $(ARGS)

policies: $(STAMP)  ## train the learned policies that are missing (no evaluation)
	$(PY) -m fleet_torchrl.table table.evaluate=false $(ARGS)

policy-maps: policies  ## action maps of rule, heuristic, tabular, DQN-partial, generalist, search -> results/policy_maps
	$(TIMED) policy-maps -- $(PY) -m fleet_torchrl.policy_maps +experiment=policy_maps $(ARGS)

sweep-pc: policies  ## generalisation sweep over p_c -> results/sweeps/pc.{csv,json,png}
	$(TIMED) sweep-pc -- $(PY) -m fleet_torchrl.sweeps -m +experiment=sweep_pc $(ARGS)
	$(PY) -m fleet_torchrl.sweeps_summary name=pc

sweep-tc: policies  ## generalisation sweep over T_C -> results/sweeps/tc.{csv,json,png}
	$(TIMED) sweep-tc -- $(PY) -m fleet_torchrl.sweeps -m +experiment=sweep_tc $(ARGS)
	$(PY) -m fleet_torchrl.sweeps_summary name=tc

sweep-nv: policies  ## generalisation sweep over N_V -> results/sweeps/nv.{csv,json,png}
	$(TIMED) sweep-nv -- $(PY) -m fleet_torchrl.sweeps -m +experiment=sweep_nv $(ARGS)
	$(PY) -m fleet_torchrl.sweeps_summary name=nv

sweeps: sweep-pc sweep-tc sweep-nv  ## all three generalisation sweeps

experiments: table policy-maps sweeps grid report  ## every experiment of MODEL §5, then the report

report: $(STAMP)  ## assemble docs/report.md from result files (no retraining)
	$(PY) -m fleet_torchrl.report

train: $(STAMP)  ## train one policy, e.g. ARGS="agent=dqn state=all"
	$(PY) -m fleet_torchrl.train $(ARGS)

grid: $(STAMP)  ## DQN hyperparameter grid search (Hydra multirun, joblib) + summary -> results/grid
	$(TIMED) grid -- $(PY) -m fleet_torchrl.train -m +experiment=grid $(ARGS)
	$(PY) -m fleet_torchrl.grid

objective: $(STAMP)  ## how the MDP reward ranks policies vs their trips -> results/objective
	$(PY) -m fleet_torchrl.objective $(ARGS)

evaluate: $(STAMP)  ## evaluate a policy (MODEL §4); overrides in ARGS
	$(PY) -m fleet_torchrl.evaluate $(ARGS)

bench: $(STAMP)  ## simulator, evaluation, environment and the recipes' training throughput (docs/BENCHMARKS.md), e.g. ARGS="bench.repeats=3"
	$(PY) -m fleet_torchrl.bench $(ARGS)

tensorboard: $(STAMP)  ## TensorBoard on the training runs, e.g. ARGS="--port 6007 --bind_all"
	$(VENV)/bin/tensorboard --logdir_spec outputs:outputs,multirun:multirun $(ARGS)

clean:  ## remove Hydra outputs and sweeps (keeps .venv and results/)
	rm -rf outputs multirun/*/ .pytest_cache .ruff_cache
	find . -name __pycache__ -type d -not -path './.venv/*' -exec rm -rf {} +
