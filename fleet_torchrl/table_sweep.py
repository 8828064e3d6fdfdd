"""``make table``'s sweeper: the table's trainings resolved into run specs here, at the
command boundary, then launched as jobs of the ``train`` task by Hydra's launcher.

:class:`TableSweep` is what ``hydra/sweeper=table`` runs (``make table``): the table's
trainings are jobs of the ``train`` task launched by the configured launcher
(``hydra/launcher``: two local processes by default, Slurm or Ray like any sweep), and the
evaluation follows in the launching process. Which jobs to launch is decided first: a recipe
and seed whose published policy matches its settings is reused, a run folder holding a
checkpoint of the same settings is resumed, one of other settings is set aside
(:mod:`fleet_torchrl.experiments.table`, which takes the run specs resolved here).

Hydra only loads sweepers from its ``hydra_plugins`` package, so the sweeper class itself is
``hydra_plugins/fleet_torchrl_table/table_sweeper.py``, which hands over to this module.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from .config import Config
    from .training.spec import RunSpec

# groups a table-level override would set for nothing: each recipe sets its own
_RECIPE_GROUPS = ("state", "mdp", "agent", "network")


def check_forwardable(cfg: Config) -> None:
    """Refuse table-level settings that cannot reach the trainings: the learner, state,
    objective and network are each recipe's own (``conf/recipes``), so ``make table
    ARGS="mdp.reward=throughput"`` would change nothing it says. The site is forwarded
    (:func:`~fleet_torchrl.experiments.table.site_overrides`)."""
    from .config import compose_config
    from .experiments.table import site_overrides
    from .utils.checks import ConfigError

    plain = compose_config([])
    for group in _RECIPE_GROUPS:
        mine, default = getattr(cfg, group), getattr(plain, group)
        if mine != default:
            diff = next((f"{group}.{k}={v!r}" for k, v in vars(mine).items()
                         if getattr(default, k, object()) != v), group)
            raise ConfigError(f"{diff} does not reach the table's trainings (each recipe sets "
                              f"its own {group}): put it in a recipe (conf/recipes) or run "
                              "make train")
    site_overrides(cfg)


def table_specs(cfg: Config, wave: int) -> dict[tuple[str, int], RunSpec]:
    """The run spec of every training of the table's ``wave`` (each recipe it trains, each
    training seed): what the job's overrides
    (:func:`~fleet_torchrl.experiments.table.run_overrides`) compose to. Wave 1 (recipes whose
    teachers plan over other recipes' policies) is resolved once wave 0 has trained: its
    teachers' bases are those policy files, checked when the spec is composed."""
    from .config import compose_config
    from .experiments.table import run_overrides, training_seeds
    from .training.spec import RunSpec

    return {(name, seed): RunSpec.of(compose_config(run_overrides(name, seed, cfg)))
            for name in cfg.table.training_names(cfg.recipes)
            if bool(cfg.recipes[name].bases) == bool(wave) for seed in training_seeds(cfg)}


class TableSweep:
    """``make table`` as a Hydra sweep (see the module docstring): plan, launch the trainings
    that are needed, evaluate."""

    def __init__(self, hydra_context: Any, task_function: Any, config: Any) -> None:
        self.hydra_context = hydra_context
        self.task_function = task_function
        self.config = config

    def sweep(self, arguments: list[str]) -> list[Any]:
        from omegaconf import OmegaConf, open_dict, read_write

        from .config import compose_config, to_config, without_hydra
        from .experiments.table import (
            WAVES,
            check_outputs,
            evaluate_table,
            plan_jobs,
            recorded_train_time,
            training_seeds,
        )
        from .utils.cli import user_errors
        from .utils.runinfo import run_info

        with user_errors():
            cfg = to_config(without_hydra(self.config))
            check_forwardable(cfg)
            check_outputs(cfg)
        runs_dir = cfg.table.runs_dir
        with read_write(self.config.hydra), open_dict(self.config.hydra):
            self.config.hydra.sweep.dir = runs_dir  # where the launcher creates its folders
        n_jobs = OmegaConf.select(self.config, "hydra.launcher.n_jobs")
        one_at_a_time = n_jobs == 1 or OmegaConf.select(
            self.config, "hydra.launcher._target_", default="").endswith("BasicLauncher")
        returns = []
        specs: dict[tuple[str, int], RunSpec] = {}
        for wave in range(WAVES):  # recipes whose teachers plan over others' policies last
            with user_errors():
                specs.update(table_specs(cfg, wave))
                jobs = plan_jobs(cfg, specs, progress=cfg.train.progress and one_at_a_time,
                                 wave=wave)
            returns += self._run_jobs(jobs, runs_dir, n_jobs, wave, first_idx=len(returns))
        if cfg.table.evaluate:
            times = {(n, s): recorded_train_time(n, s, cfg)
                     for n in cfg.table.names(cfg.recipes) for s in training_seeds(cfg)}
            with user_errors():
                evaluate_table(cfg, times, specs,
                               compose_config(["agent=planner"]).agent,
                               run_info(cfg, seed=cfg.eval.seed))
        return returns

    def _run_jobs(self, jobs: list[Any], runs_dir: str, n_jobs: Any, wave: int,
                  first_idx: int = 0) -> list[Any]:
        """Launch one wave of the table's trainings; exit 1 if any failed."""
        from hydra.core.plugins import Plugins
        from hydra.core.utils import JobStatus

        from .experiments.launch import progress_callback, torch_threads

        progress = progress_callback(self.hydra_context)
        if progress is not None:
            progress.set_total(len(jobs), name="table" if wave == 0 else "table, wave 2")
        returns = []
        if jobs:
            print(f"[table] {len(jobs)} trainings to run ({n_jobs or 1} at a time), "
                  f"run folders in {runs_dir}/", flush=True)
            launcher = Plugins.instance().instantiate_launcher(
                hydra_context=self.hydra_context, task_function=self.task_function,
                config=self.config)
            threads = torch_threads()
            returns = list(launcher.launch([j.overrides for j in jobs],
                                           initial_job_idx=first_idx))
            torch_threads(threads)  # a job run in this process sets its own
        failed = [(j, r) for j, r in zip(jobs, returns, strict=True)
                  if r.status != JobStatus.COMPLETED]
        for job, r in failed:
            print(f"error: training {job.name} seed {job.seed} failed "
                  f"({type(r._return_value).__name__}: {r._return_value}); see "
                  f"{Path(runs_dir) / job.folder}/train.log; rerun `make table` to resume it "
                  "from its checkpoint", file=sys.stderr)
        if failed:
            sys.exit(1)
        return returns




__all__ = ["TableSweep", "check_forwardable", "table_specs"]
