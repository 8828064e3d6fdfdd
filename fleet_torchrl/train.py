"""Command line: train a learned policy (MODEL §3).

    fleet-train agent=tabular                 # = python -m fleet_torchrl.train agent=tabular
    fleet-train agent=dqn state=partial
    fleet-train agent=dqn state=all network.width=128 train.max_episodes=4000

Logs to TensorBoard under the Hydra run directory
(``outputs/train/<agent>_<state>_<site>/<time>_<pid>/tb``) and to its ``train.log``, keeps the
best policy by periodic evaluation in ``<run dir>/policy.pt``, checkpoints to
``<run dir>/checkpoint.ckpt``, and at a successful end publishes the policy with its summary
(``policy.pt``, ``train_summary.json``) to ``results/policies/<name>/seed<seed>/`` (or
``train.out_dir``), so ``fleet-train -m seed=0,1`` publishes each seed to its own folder.

Nothing published is replaced: a publish folder that already holds a policy (of this same
training or another) is refused before the run starts, unless ``train.overwrite=true``
(:mod:`fleet_torchrl.training.publish`); two jobs of a multirun that would publish to one
folder are refused before either starts (:class:`~fleet_torchrl.cli.ValidateFirst`). A run
whose best policy failed sites (failure rate above 0 on its evaluation set) publishes nothing
to the default folder: its policy stays in ``<run dir>/policy.pt`` and the log says so in one
line (an explicit ``train.out_dir``, such as each of ``make table``'s trainings, gets it with
its failure rate in the summary). The run folder is held (``<run dir>/.lock``) before Hydra
writes its ``.hydra/``, so a second training, or a resume, started in a folder where one runs
is refused without touching it. A killed run continues with ``resume=true
hydra.run.dir=<its run dir>``. The trainings of ``make table`` are jobs of this task too
(:mod:`fleet_torchrl.table`).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING

from .cli import hydra_command, validated
from .training.spec import RunSpec
from .utils.cli import user_errors

if TYPE_CHECKING:
    from omegaconf import DictConfig

    from .config import Config

log = logging.getLogger("fleet_torchrl.train")  # Hydra writes it to stdout and <run dir>/train.log


# the groups a training reads (table: policies_dir, follow_symlinks: where it publishes)
GROUPS = ("site", "state", "mdp", "agent", "network", "train", "table")


def preflight(cfg: Config, run_dir: str | Path | None) -> None:
    """What is checked before Hydra writes the run folder (:class:`~fleet_torchrl.cli.
    ValidateFirst`) and again before a job trains: the agent is a learner, the folder its
    policy is published to can be written (not only after the whole training), no policy file
    is named for it to ignore (``agent.policy``), a resume finds its checkpoint, of the same
    settings (a refused resume writes nothing), and the publish folder holds no policy this
    run would replace (:func:`~fleet_torchrl.training.publish.check_publish`)."""
    from .agents.registry import AGENTS, get_agent
    from .training.checkpoint import CHECKPOINT, check_resumable
    from .training.publish import check_publish
    from .utils.checks import ConfigError
    from .utils.paths import check_output

    if not get_agent(cfg.agent.name).trainable:
        raise ConfigError(f"agent={cfg.agent.name} is invalid for train: it is not trained; "
                          "allowed one of "
                          + ", ".join(n for n, s in AGENTS.items() if s.trainable))
    if getattr(cfg.agent, "policy", None):  # what evaluate loads; a training would ignore it
        raise ConfigError(
            f"agent.policy={cfg.agent.policy} is invalid for train: it names the saved policy "
            "that evaluate loads, and a training starts from its own seed, not from a file; "
            "drop it (continue a run with resume=true hydra.run.dir=<its run folder>; choose "
            "where the trained policy goes with train.out_dir)")
    spec, folder = RunSpec.of(cfg), publish_folder(cfg)
    check_output("train.out_dir" if cfg.train.out_dir else "table.policies_dir", folder, "dir")
    if cfg.resume and run_dir is not None:
        check_resumable(Path(run_dir) / CHECKPOINT, spec)
    check_publish(spec, folder, run_dir, cfg.resume)
    check_training_sites(cfg)


def publish_folder(cfg: Config) -> Path:
    """Where a training of ``cfg`` publishes its policy: ``train.out_dir``, else its folder
    under ``table.policies_dir`` (:func:`~fleet_torchrl.training.publish.publish_dir`)."""
    from .training.publish import publish_dir

    return publish_dir(RunSpec.of(cfg), cfg.table.policies_dir, cfg.table.follow_symlinks)


def output_paths(cfg: Config) -> list[tuple[str, Path]]:
    """What a run of ``cfg`` writes outside its run folder: its publish folder (two jobs of
    a multirun must not share it)."""
    return [("publish folder", publish_folder(cfg))]


def claim(cfg: Config, run_dir: str | Path) -> None:
    """Hold the run folder for this process (:func:`~fleet_torchrl.utils.paths.hold_run_dir`)
    before Hydra writes its ``.hydra/`` into it: a second training there, or a resume of a
    run that still trains, is refused before it writes anything."""
    from .utils.paths import hold_run_dir

    Path(run_dir).mkdir(parents=True, exist_ok=True)
    hold_run_dir(run_dir)




def check_training_sites(cfg: Config) -> None:
    """The training's sites can start their episodes: a site whose initial states keep
    failing is refused in one line before the run folder is made (on at most 1024 of
    ``agent.num_sites``: what fails there fails in the run)."""
    from .env.fleet_env import check_site_starts

    n = min(int(getattr(cfg.agent, "num_sites", 1)), 1024)
    check_site_starts(cfg.site, n, cfg.mdp, cfg.seed, cfg.state.name)


def train(cfg: Config, run_dir: str | Path) -> dict:
    """Train ``cfg`` in ``run_dir`` (checked first, then its provenance written); the run's
    summary."""
    import torch

    from .training import Trainer
    from .utils.paths import release_run_dir
    from .utils.runinfo import run_info, write_json

    try:
        preflight(cfg, run_dir)  # a refused resume must not overwrite the run's run_info.json
        claim(cfg, run_dir)  # held already when ValidateFirst checked this run
        if cfg.train.threads:
            torch.set_num_threads(cfg.train.threads)
        write_json(Path(run_dir) / "run_info.json", run_info(cfg, seed=cfg.seed))
        trainer = Trainer(RunSpec.of(cfg), run_dir, publish_folder(cfg), cfg.resume)
        summary = trainer.run()
    finally:
        release_run_dir(run_dir)
    best = summary["best"] or {}
    log.info(f"{summary['name']}: {summary['rounds']} rounds, {summary['episodes']} episodes, "
             f"{summary['wall_s']:.0f} s; best eval {best.get('trips', float('nan')):.1f} trips "
             f"({best.get('gain_pct', float('nan')):+.2f} % vs rule), failure rate "
             f"{best.get('failure_rate', float('nan')):.3f}; policy -> {summary['policy']}")
    return summary


def task(dcfg: DictConfig) -> float:
    """One training run in its Hydra run folder; returns its best evaluation trips (what a
    Hydra sweeper would optimise)."""
    from hydra.core.hydra_config import HydraConfig

    with user_errors():
        cfg = validated(dcfg, GROUPS)
        summary = train(cfg, HydraConfig.get().runtime.output_dir)
    return (summary["best"] or {}).get("trips", float("nan"))


main = hydra_command(task)

if __name__ == "__main__":
    main()
