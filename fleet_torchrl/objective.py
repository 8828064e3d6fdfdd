"""How the MDP's reward ranks policies, next to the trips they make.

    python -m fleet_torchrl.objective                 # thesis reward
    python -m fleet_torchrl.objective mdp.r_trip=10   # with the optional trip reward

The learners optimise the reward of MODEL §2; the evaluation reports trips. This command
measures both for the same policies: every policy plays one episode (``mdp.tau_e`` ticks or
until failure) on each of ``objective.n_sites`` training-style sites drawn under
``objective.seed`` through :class:`~fleet_torchrl.env.FleetChargingEnv`, and the table lists
the mean reward per decision (the quantity a discounted learner maximises on average, since
``V = r / (1 - gamma)`` for a constant per-step reward) beside trips, queue ticks and failures.
The policies are the rule, the heuristic at several upper limits (the "charge early" family
whose trips peak near 60), one that charges early only while another vehicle is at most 75
(``heuristic_65_75``), and every saved learned policy found in ``table.policies_dir``.
If a policy with a higher reward makes fewer trips, a perfect learner of that reward
ends up below the best trips gain (docs/TRAINING.md).
"""

from __future__ import annotations

from pathlib import Path

import hydra
from omegaconf import DictConfig

from .config import register_configs, to_config
from .experiments.objective import candidate_policies, mdp_score, score_table
from .utils.cli import user_errors
from .utils.runinfo import run_info, write_json, write_text

register_configs()


@hydra.main(version_base="1.3", config_path="conf", config_name="config")
def main(dcfg: DictConfig) -> None:
    with user_errors():
        cfg = to_config(dcfg)
        o = cfg.objective
        scores = {name: mdp_score(p, cfg.site, cfg.mdp, o.n_sites, o.seed, cfg.eval.device)
                  for name, p in candidate_policies(cfg).items()}
        text = score_table(scores)
        print(text)
        print(f"({o.n_sites} episodes of {cfg.mdp.tau_e} ticks, seed {o.seed}, "
              f"r_trip={cfg.mdp.r_trip:g}; sorted by reward)")
        out = Path(o.out)
        write_json(out / "objective.json", {"scores": scores,
                                            "meta": run_info(cfg, seed=o.seed)})
        write_text(out / "objective.md", text + "\n")
        print(f"wrote {out / 'objective.md'}")


if __name__ == "__main__":
    main()
