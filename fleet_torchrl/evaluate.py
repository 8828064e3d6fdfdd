"""Command line: evaluate one policy with the protocol of MODEL §4.

    fleet-evaluate agent=rule eval.n_sims=1000 eval.ticks=10000 eval.out=results/eval/rule.json

(= ``python -m fleet_torchrl.evaluate ...``.) Prints the summary table and writes the result
JSON (summary, per-simulation records, resolved config, seed, git commit, package versions)
plus a per-simulation CSV beside it. Without ``eval.out`` both go to the Hydra run directory
(``outputs/evaluate/<agent>_<state>_<site>/<time>_<pid>/eval.json``).

An ``eval.out`` that exists is checked before the evaluation starts: a file that is not an
evaluation result (an unrelated JSON, a policy's ``train_summary.json``) or no regular file
at all (a FIFO) is refused and kept; an existing result is replaced only with
``eval.overwrite=true``. Two jobs of a multirun on one ``eval.out`` (``-m agent=rule,heuristic
eval.out=x.json``) are refused before either starts. The CSV is written first and the JSON,
which names it and records its hash, last: an interrupted write never leaves a JSON beside
another run's CSV unnoticed (:func:`~fleet_torchrl.evaluation.results.check_result_pair`), and
its temp files go with the next write of the same result.
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

    from .agents.base import Policy
    from .config import Config

log = logging.getLogger("fleet_torchrl.evaluate")  # to stdout and the Hydra job's log file


# the groups an evaluation reads (train.out_dir, table.policies_dir: where a policy is found)
GROUPS = ("site", "state", "mdp", "agent", "train", "eval", "table")


def preflight(cfg: Config, run_dir: str | Path | None) -> None:
    """Before the run folder exists: the result path (and its CSV beside it) can be
    written and holds nothing it would replace unasked (``eval.overwrite``), and a saved
    policy to evaluate exists and loads (its hash, finite weights, its agent and state)."""
    from .evaluation.results import check_result_path

    if cfg.eval.out:
        check_result_path(cfg.eval.out, overwrite=cfg.eval.overwrite)
    policy_of(cfg, device="cpu")  # a baseline is built from its config: nothing to read


def policy_of(cfg: Config, device: str | None = None) -> Policy:
    """The policy ``cfg.agent`` names (:func:`~fleet_torchrl.store.make_policy` of its run
    spec), on ``device`` (default ``eval.device``): a baseline built, a learned one loaded
    from ``agent.policy``, ``train.out_dir`` or its folder under ``table.policies_dir``."""
    from .store import make_policy

    return make_policy(RunSpec.of(cfg), device or cfg.eval.device, cfg.table.policies_dir,
                       cfg.table.follow_symlinks, cfg.train.out_dir)


def output_paths(cfg: Config) -> list[tuple[str, Path]]:
    """What a run of ``cfg`` writes outside its run folder: ``eval.out`` if set (two jobs of
    a multirun must not share it)."""
    return [("eval.out", Path(cfg.eval.out))] if cfg.eval.out else []


def run(cfg: Config, out: str | Path | None) -> dict:
    from .evaluation import evaluate_with, format_table, save_result
    from .evaluation.results import check_result_path
    from .store import site_label
    from .utils.runinfo import run_info

    if out is not None:  # before the simulation, not after it
        check_result_path(out, overwrite=cfg.eval.overwrite if cfg.eval.out else None)
    policy = policy_of(cfg)
    e = cfg.eval
    result = evaluate_with(policy, cfg.site, e, name=cfg.agent.name)
    result["meta"] = run_info(cfg, seed=e.seed)
    log.info("\n" + format_table([result]))
    log.info(f"({e.n_sims} sims x {e.ticks} ticks on site {site_label(cfg.site)}, seed {e.seed}, "
             f"{result['wall_time_s']:.2f} s)")
    if out is not None:
        js, cs = save_result(result, out)
        log.info(f"wrote {js} and {cs}")
    return result


def task(dcfg: DictConfig) -> None:
    """Evaluate the policy ``agent`` names (a baseline, or a saved policy)."""
    from hydra.core.hydra_config import HydraConfig

    with user_errors():
        cfg = validated(dcfg, GROUPS)
        out = cfg.eval.out or Path(HydraConfig.get().runtime.output_dir) / "eval.json"
        run(cfg, out)


main = hydra_command(task)

if __name__ == "__main__":
    main()
