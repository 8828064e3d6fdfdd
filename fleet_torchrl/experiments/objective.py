"""How the MDP's reward ranks policies, next to the trips they make.

    python -m fleet_torchrl.objective                         # mdp.reward=thesis
    python -m fleet_torchrl.objective mdp.reward=throughput   # the trip-aligned objective

The learners optimise the reward of MODEL §2; the evaluation reports trips. This command
measures both for the same policies: every policy plays one episode (``mdp.tau_e`` ticks or
until failure) on each of ``objective.n_sites`` training-style sites drawn under
``objective.seed`` through :class:`~fleet_torchrl.env.FleetChargingEnv`, and the table lists
the mean reward per decision (the quantity a learner discounting per decision maximises on
average, since ``V = r / (1 - gamma)`` for a constant per-step reward) and the long-run reward
per tick (what a learner discounting per tick maximises as ``gamma_tick -> 1``:
``-(p_q * queue + p_f * failures) / ticks`` for ``thesis``, ``(trips - rho * ticks - p_f *
failures) / ticks`` for ``throughput``) beside trips, queue ticks and failures. The table is
sorted by the criterion of the objective: per decision for ``thesis``, per tick for
``throughput`` (:func:`criterion`).
The policies are the rule, the heuristic at several upper limits (the "charge early" family
whose trips peak near 60), one that charges early only while another vehicle is at most 75
(``heuristic_65_75``), and every saved learned policy found in ``table.policies_dir``.
If a policy with a higher reward makes fewer trips, a perfect learner of that reward
ends up below the best trips gain (docs/TRAINING.md).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch

from ..agents import HeuristicPolicy, Policy, RulePolicy
from ..env import FleetChargingEnv, MDPConfig
from ..sim import SiteConfig
from ..store import load_policies, saved_policy_path

if TYPE_CHECKING:
    from collections.abc import Iterable

    from .config import TableConfig


@torch.no_grad()
def mdp_score(policy: Policy, site_cfg: SiteConfig, mdp_cfg: MDPConfig, n_sites: int = 200,
              seed: int = 7, device: str | torch.device = "cpu") -> dict[str, float]:
    """One episode per site: mean reward per decision, trips, queue ticks, failure rate."""
    env = FleetChargingEnv(site_cfg, policy.encoding, n_sites, mdp_cfg, seed=seed, device=device)
    policy = policy.to(env.device).eval()
    td = env.reset()
    reward = torch.zeros(n_sites, device=env.device)
    steps = torch.zeros(n_sites, device=env.device)
    done = torch.zeros(n_sites, dtype=torch.bool, device=env.device)
    trips = torch.zeros(n_sites, device=env.device)
    queue = torch.zeros_like(trips)
    ticks = torch.zeros_like(trips)
    failed = torch.zeros_like(done)
    while not bool(done.all()):
        td = td.set("action", policy(td["observation"])).set("_step", ~done)
        nxt = env.step(td)["next"]  # a finished site stays as it is
        live = ~done
        reward += nxt["reward"].squeeze(-1) * live
        steps += live
        # counters of a finished site are frozen at its episode's end
        trips = torch.where(live, nxt["trips"].squeeze(-1).float(), trips)
        queue = torch.where(live, nxt["queue_ticks"].squeeze(-1).float(), queue)
        ticks = torch.where(live, nxt["ticks"].squeeze(-1).float(), ticks)
        failed |= live & nxt["terminated"].squeeze(-1)
        done |= nxt["done"].squeeze(-1)
        td = nxt.clone()
    m = mdp_cfg
    per_tick = m.objective.rate(trips.sum(), queue.sum(), failed.float().sum(), ticks.sum(), m)
    return {"reward_per_decision": float(reward.sum() / steps.sum()),
            "reward_per_tick": float(per_tick),
            "decisions": float(steps.mean()), "trips": float(trips.mean()),
            "queue": float(queue.mean()), "failure_rate": float(failed.float().mean())}


def candidate_policies(table: TableConfig, recipes: Iterable[str], device: str
                       ) -> dict[str, Policy]:
    """Rule, heuristic family, and the learned policies of ``recipes`` saved under
    ``table.policies_dir``."""
    pols: dict[str, Policy] = {"rule": RulePolicy()}
    for upper in (50.0, 55.0, 60.0, 65.0, 70.0, 75.0, 80.0):
        pols[f"heuristic_{upper:g}"] = HeuristicPolicy(40.0, upper)
    # early charging only while another vehicle is at most 75: as little queueing, more trips
    pols["heuristic_65_75"] = HeuristicPolicy(40.0, 65.0, others_below=75.0)
    root = table.policies_dir
    saved = [name for name in recipes
             if saved_policy_path(root, name, table.follow_symlinks).is_file()]
    return {**pols, **load_policies(root, saved, device, table.follow_symlinks)}


def criterion(mdp_cfg: MDPConfig) -> str:
    """The score a learner of this objective maximises: per decision (``thesis``, discounted
    per decision) or per tick (``throughput``, discounted per tick)."""
    return ("reward_per_decision" if mdp_cfg.objective.ranks_by_decision()
            else "reward_per_tick")


def score_table(scores: dict[str, dict[str, float]], key: str = "reward_per_decision") -> str:
    """Markdown table of the scores, best first by ``key``."""
    base = scores["rule"]["trips"]
    lines = ["| policy | reward / decision | reward / tick | trips | gain vs rule | queue ticks "
             "| failures |", "|---|---:|---:|---:|---:|---:|---:|"]
    for name, s in sorted(scores.items(), key=lambda kv: -kv[1][key]):
        lines.append(f"| {name} | {s['reward_per_decision']:.5f} | {s['reward_per_tick']:.6f} | "
                     f"{s['trips']:.1f} | "
                     f"{(s['trips'] / base - 1) * 100:+.2f} % | {s['queue']:.1f} | "
                     f"{s['failure_rate']:.3f} |")
    return "\n".join(lines)
