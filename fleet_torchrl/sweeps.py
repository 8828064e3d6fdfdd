"""Generalisation sweeps (MODEL §5 item 3): saved policies evaluated on changed sites.

    make sweep-pc      # = fleet-sweeps -m +experiment=sweep_pc   (python -m fleet_torchrl.sweeps)
                       #   then fleet-sweeps-summary name=pc

The command line, and the point's trainings resolved into run specs at this boundary
(:func:`point_settings`); what a point computes is :mod:`fleet_torchrl.experiments.sweeps`.
"""

from __future__ import annotations

import sys
import traceback
from typing import TYPE_CHECKING, Any

from .cli import hydra_command, validated
from .utils.cli import user_errors

if TYPE_CHECKING:
    from omegaconf import DictConfig

    from .config import Config
    from .experiments.sweeps import PointSettings
    from .training.spec import RunSpec


# the groups a sweep point reads
GROUPS = ("site", "state", "mdp", "agent", "network", "train", "eval", "table", "recipes",
          "sweep")


def preflight(cfg: Config, run_dir: str | None) -> None:
    """Before any point is launched: a sweep of one site (not a distribution) whose outputs
    can be written and whose folder is its own."""
    from .experiments.sweeps import check_point_outputs, point_site

    point_site(cfg.sweep, cfg.site)  # a site distribution is refused
    check_point_outputs(cfg.sweep)


def _spec(overrides: list[str], site: Any) -> RunSpec:
    """The run spec ``overrides`` compose to, on the point's ``site``."""
    from dataclasses import replace

    from .config import compose_config
    from .training.spec import RunSpec

    return replace(RunSpec.of(compose_config(overrides)), site=site)


def specialist_spec(cfg: Config, site: Any, recipe: str, seed: int,
                    extra: tuple[str, ...] = ()) -> RunSpec:
    """The training of a specialist: a recipe of ``recipes`` (then ``extra`` overrides) on
    the point's own site (a recipe of a site distribution cannot be a specialist)."""
    from dataclasses import replace

    from .config import compose_config
    from .training.spec import RunSpec
    from .utils.checks import ConfigError

    spec = RunSpec.of(compose_config([*cfg.recipes[recipe].overrides, *extra, f"seed={seed}",
                                      "train.progress=false", "train.tensorboard=false"]))
    if spec.site.randomized:
        raise ConfigError(f"sweep.specialists: the recipe {recipe!r} trains on a site "
                          "distribution; a specialist trains on the point's own site")
    return replace(spec, site=site)


def search_spec(site: Any, overrides: list[str]) -> RunSpec:
    """The training of one of the point's searches (its overrides on the search defaults,
    the point's site)."""
    return _spec(["agent=search", "train.threads=1", *overrides, "train.progress=false",
                  "train.tensorboard=false"], site)


def point_settings(cfg: Config) -> PointSettings:
    """A point's inputs, resolved here: its site, the run specs of its searches and
    specialists (the distilled recipe's also for every state its student may read), the
    planner's settings and the pick set's seed (the searches' selection seed)."""
    from .agents import AGENTS
    from .config import compose_config
    from .experiments.sweeps import (
        DISTILLED,
        PointSettings,
        point_site,
        specialist_seeds,
    )
    from .utils.checks import ConfigError
    from .utils.runinfo import run_info

    s = cfg.sweep
    site = point_site(s, cfg.site)
    seeds = specialist_seeds(s, cfg.seed, site.name)
    searches = {k: search_spec(site, o) for k, o in s.searches.items()} if s.search else {}
    recipes = dict(s.specialists) if s.specialist else {}
    if s.specialist and s.distil is not None:
        recipes[DISTILLED] = s.distil
    specialists = {row: {seed: specialist_spec(cfg, site, recipe, seed) for seed in seeds}
                   for row, recipe in recipes.items()}
    states = {}
    if DISTILLED in specialists:  # the states the student may read instead of its recipe's
        own = specialists[DISTILLED][seeds[0]].state.name
        for enc in (e for e in AGENTS["imitation"].states or () if e != own):
            try:
                states[enc] = {seed: specialist_spec(cfg, site, s.distil, seed,
                                                     (f"state={enc}",)) for seed in seeds}
            except ConfigError:  # a state the recipe cannot read: never its student's
                continue
    return PointSettings(
        sweep=s, eval=cfg.eval, site=site, table=cfg.table, searches=searches,
        specialists=specialists, distil_states=states,
        planner=compose_config(["agent=planner", *s.planner_overrides]).agent,
        pick_seed=compose_config(["agent=search"]).train.eval_seed,
        meta=run_info(cfg, seed=cfg.eval.seed))


def task(dcfg: DictConfig) -> Any:
    """One point of a sweep (one Hydra job); a failure is written beside the point's result
    (``.error``) and the other points go on, but it counts: the job returns
    :class:`~fleet_torchrl.experiments.launch.JobFailed`, so the multirun exits non-zero at
    its end (a single point's run exits 1 at once)."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    from .experiments.launch import JobFailed
    from .experiments.sweeps import point_path, run_point
    from .utils.runinfo import write_text

    with user_errors():
        cfg = validated(dcfg, GROUPS)
    try:
        run_point(point_settings(cfg))
    except Exception as e:  # keep the other points of the multirun going
        path = point_path(cfg.sweep)
        write_text(path.with_suffix(".error"), traceback.format_exc())
        msg = str(e).strip().splitlines()[0] if str(e).strip() else ""
        print(f"error: point {path.stem} failed ({type(e).__name__}: {msg}); see "
              f"{path.with_suffix('.error')}", file=sys.stderr)
        if HydraConfig.get().mode != RunMode.MULTIRUN:
            sys.exit(1)
        return JobFailed(path.stem, f"{type(e).__name__}: {msg}")
    return None


main = hydra_command(task)

if __name__ == "__main__":
    main()
