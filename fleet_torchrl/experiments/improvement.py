"""What one step of policy improvement adds to a policy (MODEL §3.6, ``make table``).

The rollout planner with base policy ``P`` decides each arrival by simulating both actions
under ``P`` and keeping ``P``'s action unless the other is clearly better: one step of policy
improvement over ``P``. If that step gains significantly, ``P`` was not optimal on the site,
and the gain measures by how much at least. The check runs the planner over ``P`` on the
first ``n_sims`` sites of the evaluation (simulation ``i`` is site ``i`` of the seed, so they
pair with ``P``'s own records of the main evaluation) and reports the paired difference of
trips in points of the gain over the rule, with its 95 % interval (Student's t).
"""

from __future__ import annotations

from typing import Any

import torch

from ..agents.base import Policy
from ..agents.planner import PlannerAgentConfig, PlannerPolicy
from ..evaluation import simulate
from ..evaluation.results import t95
from ..sim import SiteConfig


def improvement(policy: Policy, own: dict[str, Any], rule: dict[str, Any], site: SiteConfig,
                n_sims: int, ticks: int, seed: int, planner: PlannerAgentConfig,
                device: str = "cpu") -> dict[str, Any]:
    """The one-step improvement of ``policy``: ``own`` and ``rule`` are its and the rule's
    results of the main evaluation (their per-simulation records, same seed and ticks)."""
    n = min(n_sims, len(own["records"]["trips"]))
    pol = PlannerPolicy.from_config(planner, policy)
    rec = simulate(pol, site, n, ticks, seed, device)
    pct, ci = paired_points(rec["trips"], own["records"]["trips"][:n],
                            rule["records"]["trips"][:n])
    return {"improvement_pct": pct, "improvement_ci95": ci, "sims": n,
            "planner_failure_rate": float(rec["failed"].double().mean()),
            "changed_share": pol.stats["changed"] / max(pol.stats["decisions"], 1)}


def paired_points(mine: Any, base: Any, rule: Any) -> tuple[float, float]:
    """Mean and 95 % half-interval (Student's t) of the per-site difference of trips
    ``mine - base``, in points of gain over the rule's mean trips on the same sites (NaN
    interval for one site)."""
    f64 = torch.float64
    d = 100.0 * (torch.as_tensor(mine, dtype=f64) - torch.as_tensor(base, dtype=f64)) \
        / float(torch.as_tensor(rule, dtype=f64).mean())
    n = d.numel()
    ci = t95(n - 1) * float(d.std()) / n ** 0.5 if n > 1 else float("nan")
    return float(d.mean()), ci


__all__ = ["improvement", "paired_points"]
