"""How the MDP's reward ranks policies, next to the trips they make.

    fleet-objective                         # mdp.reward=thesis (python -m fleet_torchrl.objective)
    fleet-objective mdp.reward=throughput   # the trip-aligned objective

Scores the rule, the heuristic family and every saved learned policy by the objective's
reward beside their trips (:mod:`fleet_torchrl.experiments.objective`) and writes
``results/objective/objective.{md,json}``.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from .cli import hydra_command, validated
from .utils.cli import user_errors

if TYPE_CHECKING:
    from omegaconf import DictConfig

    from .config import Config


# the groups make objective reads
GROUPS = ("site", "mdp", "eval", "table", "recipes", "objective")


def preflight(cfg: Config, run_dir: str | None) -> None:
    """Before the run folder exists: ``objective.out`` can be written, and the folder of
    saved policies exists (without it the table would show the baselines only, as if no
    policy had been trained)."""
    from .utils.paths import check_input_dir, check_output

    check_output("objective.out", cfg.objective.out, "dir")
    check_input_dir("table.policies_dir", cfg.table.policies_dir)


def task(dcfg: DictConfig) -> None:
    """Score every candidate policy by the objective's reward and by its trips."""
    from .experiments.objective import candidate_policies, criterion, mdp_score, score_table
    from .utils.runinfo import run_info, write_json, write_text

    with user_errors():
        cfg = validated(dcfg, GROUPS)
        preflight(cfg, None)
        o = cfg.objective
        scores = {name: mdp_score(p, cfg.site, cfg.mdp, o.n_sites, o.seed, cfg.eval.device)
                  for name, p in candidate_policies(cfg.table, cfg.recipes,
                                                    cfg.eval.device).items()}
        key = criterion(cfg.mdp)
        text = score_table(scores, key)
        print(text)
        print(f"({o.n_sites} episodes of {cfg.mdp.tau_e} ticks, seed {o.seed}, "
              f"reward={cfg.mdp.reward}, leave_when_full={cfg.site.leave_when_full}; "
              f"sorted by {key})")
        out = Path(o.out)
        write_json(out / "objective.json", {"scores": scores,
                                            "meta": run_info(cfg, seed=o.seed)})
        write_text(out / "objective.md", text + "\n")
        print(f"wrote {out / 'objective.md'}")


main = hydra_command(task)

if __name__ == "__main__":
    main()
