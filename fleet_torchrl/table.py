"""``make table``: the main comparison of MODEL §5 item 1 in one command.

    python -m fleet_torchrl.table                       # defaults: 1000 sims x 10 000 ticks
    python -m fleet_torchrl.table eval.n_sims=200 table.retrain=true

1. For each learned policy (``table.train``: tabular, DQN on ``partial``, DQN on ``all``), reuse
   ``results/policies/<name>/policy.pt`` if it exists, else train it in a subprocess
   (``python -m fleet_torchrl.train``) whose Hydra run directory is
   ``outputs/table/train_<name>``; an interrupted ``make table`` resumes those runs from their
   checkpoints. A checkpoint of another configuration (the budgets or presets changed since)
   or an unreadable one is not resumed: its run directory is moved aside to
   ``train_<name>.stale-<time>``.
2. Evaluate the rule, the heuristic and the learned policies with the protocol of MODEL §4 and
   common random numbers (``eval.*``, same seed for all: every comparison is paired).
3. Write ``results/table/``: ``table.md``, ``table.csv``, ``table.json`` (rows with ``policy``,
   ``trips_mean``, ``trips_std``, ``queue_mean``, ``queue_std``, ``failure_rate``, ``gain_pct``,
   ``gain_ci95`` against the rule, and the same against the heuristic), ``boxplot.png`` (each
   simulation's trips as % over the rule's mean) and one result JSON + CSV per policy.
"""

from __future__ import annotations

import subprocess
import sys

import hydra
from omegaconf import DictConfig

from .config import register_configs, to_config
from .experiments.table import run
from .utils.cli import user_errors

register_configs()


@hydra.main(version_base="1.3", config_path="conf", config_name="config")
def main(dcfg: DictConfig) -> None:
    try:
        with user_errors():
            run(to_config(dcfg))
    except subprocess.CalledProcessError as e:
        print(f"error: training failed ({' '.join(e.cmd[2:4])}...); rerun `make table` to "
              "resume it from its checkpoint", file=sys.stderr)
        sys.exit(1)


if __name__ == "__main__":
    main()
