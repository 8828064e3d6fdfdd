"""``make table``: the main comparison of MODEL §5 item 1 in one command.

    fleet-table                       # 1000 sims x 10 000 ticks (python -m fleet_torchrl.table)
    fleet-table eval.n_sims=200 table.seeds=1 table.retrain=true
    fleet-table table.only=[dqn_partial,search]    # some of the recipes
    fleet-table hydra/launcher=slurm  # the trainings as Slurm jobs, like any sweep

``fleet-table ARGS`` is ``fleet-train hydra/sweeper=table hydra.mode=MULTIRUN
hydra.sweep.dir='${table.runs_dir}' ARGS`` (:data:`TABLE`): a Hydra multirun of the ``train``
task whose sweeper (``conf/hydra/sweeper/table.yaml``,
:class:`~fleet_torchrl.table_sweep.TableSweep`) decides which trainings are needed,
launches them with the configured launcher and then evaluates; what it trains, evaluates and
writes is :mod:`fleet_torchrl.experiments.table`.
"""

from __future__ import annotations

import sys
from typing import Any

from .cli import hydra_command
from .train import task

_train_app = hydra_command(task)
# the groups the table reads (its trainings, jobs of the train task, read train.GROUPS)
GROUPS = ("site", "state", "mdp", "agent", "network", "train", "eval", "table", "recipes")
# what makes the train app the table (a primary config of its own could not include
# conf/config.yaml: Hydra takes hydra.searchpath, the users' conf/, from a primary only)
TABLE = ["hydra/sweeper=table", "hydra.mode=MULTIRUN", "hydra.sweep.dir=${table.runs_dir}",
         "hydra.help.app_name=fleet-table"]


def main() -> Any:
    """The train app with the table's sweeper; the command line's overrides come after
    :data:`TABLE` (a ``hydra.sweep.dir`` of yours wins)."""
    sys.argv = [sys.argv[0], *TABLE, *sys.argv[1:]]
    return _train_app()


if __name__ == "__main__":
    main()
