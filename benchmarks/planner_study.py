"""The measured study behind the planner's defaults (docs/PLANNER.md); a development tool of
this repository, not part of the package (run it from the repository root).

For each site of a small set (the default site and the sweeps' hardest points) and each
planner setting (futures per action ``K``, horizon ``H``, the energy's terminal value, the
confidence gate ``z``), the planner with the heuristic as base is evaluated on a study set
of sites apart from the test sites (its own evaluation seed), paired with the heuristic and
the rule on the same sites. A row reports the gain over the rule, the paired difference to
the heuristic with its 95 % interval, the failure rate, how often the planner left the
heuristic's action, and the cost: wall time per decision.
"""

from __future__ import annotations

import time
from dataclasses import replace
from typing import Any

from fleet_torchrl.agents.baselines import HeuristicPolicy, RulePolicy
from fleet_torchrl.agents.planner import PlannerPolicy
from fleet_torchrl.evaluation import simulate
from fleet_torchrl.evaluation.results import t95
from fleet_torchrl.sim import SiteConfig

SITES = {"default": {}, "n_vehicles=5": {"n_vehicles": 5}, "t_c=50": {"t_c": 50},
         "p_c=0.2": {"p_c": 0.2}}


def study(settings: list[dict[str, Any]], sites: dict[str, dict] | None = None,
          n_sims: int = 200, ticks: int = 5000, seed: int = 7,
          base: SiteConfig | None = None, log=print) -> list[dict[str, Any]]:
    """Rows of the study (one per site and setting); ``settings``: keyword arguments of
    :class:`PlannerPolicy` besides the base (``rollouts``, ``horizon``, ``energy_value``,
    ``confidence``)."""
    rows = []
    for label, fields in (sites or SITES).items():
        cfg = replace(base or SiteConfig(), **fields, name=label)
        rule = simulate(RulePolicy(), cfg, n_sims, ticks, seed)["trips"].double()
        heur = simulate(HeuristicPolicy(), cfg, n_sims, ticks, seed)["trips"].double()
        r_mean = float(rule.mean())
        log(f"[study] {label}: heuristic {100 * (heur.mean() / r_mean - 1):+.2f} %")
        for s in settings:
            pol = PlannerPolicy(HeuristicPolicy(), **s)
            t0 = time.perf_counter()
            rec = simulate(pol, cfg, n_sims, ticks, seed)
            wall = time.perf_counter() - t0
            trips = rec["trips"].double()
            d = trips - heur
            ci = t95(len(d) - 1) * float(d.std()) / len(d) ** 0.5
            row = {"site": label, **s, "gain_pct": 100 * (float(trips.mean()) / r_mean - 1),
                   "vs_heuristic_pct": 100 * float(d.mean()) / r_mean,
                   "vs_heuristic_ci95": 100 * ci / r_mean,
                   "failure_rate": float(rec["failed"].double().mean()),
                   "changed_share": pol.stats["changed"] / max(pol.stats["decisions"], 1),
                   "us_per_decision": 1e6 * wall / max(pol.stats["decisions"], 1),
                   "wall_s": wall}
            rows.append(row)
            log(f"[study] {label} {s}: {row['gain_pct']:+.2f} % (heuristic "
                f"{row['vs_heuristic_pct']:+.2f} +- {row['vs_heuristic_ci95']:.2f}), fail "
                f"{row['failure_rate']:.3f}, changed {row['changed_share']:.3f}, "
                f"{row['us_per_decision']:.0f} us/decision")
    return rows


def markdown(rows: list[dict[str, Any]]) -> str:
    head = ("| site | K | H | energy value | z | gain % vs rule | vs heuristic (95 %) | "
            "failures | changed | us / decision |\n|---|---:|---:|---:|---:|---:|---:|---:|"
            "---:|---:|")
    lines = [head]
    for r in rows:
        lines.append(f"| {r['site']} | {r['rollouts']} | {r['horizon']} | "
                     f"{r['energy_value']:g} | {r['confidence']:g} | {r['gain_pct']:+.2f} | "
                     f"{r['vs_heuristic_pct']:+.2f} ± {r['vs_heuristic_ci95']:.2f} | "
                     f"{r['failure_rate']:.3f} | {r['changed_share']:.3f} | "
                     f"{r['us_per_decision']:.0f} |")
    return "\n".join(lines)

