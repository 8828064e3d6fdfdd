"""``hydra/sweeper=table``: the trainings of ``make table`` as jobs of Hydra's launcher.

Hydra imports every module of ``hydra_plugins`` in every app it runs, so this one imports
nothing of fleet_torchrl until a table actually sweeps.
"""

from __future__ import annotations

from typing import Any

from hydra.plugins.sweeper import Sweeper


class TableSweeper(Sweeper):
    """Plans the table's trainings, launches the needed ones, evaluates
    (:class:`fleet_torchrl.table_sweep.TableSweep`)."""

    def __init__(self) -> None:
        self.sweep_impl: Any = None

    def setup(self, *, hydra_context: Any, task_function: Any, config: Any) -> None:
        from fleet_torchrl.table_sweep import TableSweep

        self.sweep_impl = TableSweep(hydra_context, task_function, config)

    def sweep(self, arguments: list[str]) -> Any:
        return self.sweep_impl.sweep(arguments)
