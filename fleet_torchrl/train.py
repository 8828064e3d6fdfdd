"""Command line: train a learned policy (MODEL §3).

    python -m fleet_torchrl.train agent=tabular
    python -m fleet_torchrl.train agent=dqn state=partial
    python -m fleet_torchrl.train agent=dqn state=all network.width=128 train.max_episodes=4000

Logs to TensorBoard under the Hydra run directory (``outputs/train/<time>/tb``) and to its
``train.log``, keeps the best policy by periodic evaluation in ``<run dir>/policy.pt``,
checkpoints to ``<run dir>/checkpoint.ckpt``, and at a successful end publishes the policy
with its summary to ``results/policies/<name>/`` (or ``train.out_dir``). A killed run
continues with ``resume=true hydra.run.dir=<its run dir>``.
"""

from __future__ import annotations

import logging
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from .config import Config, check_command_line, register_configs, to_config
from .training import Trainer
from .utils.cli import user_errors
from .utils.runinfo import run_info, write_json

register_configs()
log = logging.getLogger("fleet_torchrl.train")  # Hydra writes it to stdout and <run dir>/train.log


def train(cfg: Config, run_dir: str | Path) -> dict:
    if cfg.train.threads:
        import torch

        torch.set_num_threads(cfg.train.threads)
    write_json(Path(run_dir) / "run_info.json", run_info(cfg, seed=cfg.seed))
    trainer = Trainer(cfg, run_dir)
    summary = trainer.run()
    best = summary["best"] or {}
    log.info(f"{summary['name']}: {summary['rounds']} rounds, {summary['episodes']} episodes, "
          f"{summary['wall_s']:.0f} s; best eval {best.get('trips', float('nan')):.1f} trips "
          f"({best.get('gain_pct', float('nan')):+.2f} % vs rule), failure rate "
          f"{best.get('failure_rate', float('nan')):.3f}; policy -> {summary['policy']}")
    return summary


@hydra.main(version_base="1.3", config_path="conf", config_name="config")
def main(dcfg: DictConfig) -> float:
    with user_errors():
        cfg = to_config(dcfg)
        summary = train(cfg, HydraConfig.get().runtime.output_dir)
    return (summary["best"] or {}).get("trips", float("nan"))


if __name__ == "__main__":
    check_command_line()
    main()
