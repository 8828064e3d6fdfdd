"""Calibrating a classifier's deferral to the heuristic on validation sites (``train.defer``).

A student that imitates a planner across a site distribution can be slightly worse than the
heuristic on a part of it where the heuristic is near the best policy and the student's
labels carry little (docs/TRAINING.md §15: the generalist at ``p_c`` = 0, on two of three
seeds, by about 0.1 point). With ``train.defer=heuristic`` the published policy takes the
heuristic's action wherever the student's logit lies within ``[-m, m]``
(:func:`~fleet_torchrl.agents.imitation.defer_to_heuristic`): the baseline decides where the
network is least sure, as in safe policy improvement with a baseline. The margin ``m`` is
calibrated once, after training, on the best snapshot:

* the *validation points* (:func:`validation_points`): the training site itself, or for a site
  distribution each drawn parameter at ``train.defer_points`` evenly spaced values of its range
  with the others at the site's own values (one parameter at a time, as the sweeps vary them);
* at each point, ``train.defer_sims`` sites x ``train.defer_ticks`` ticks from the selection's
  own evaluation seed ``train.eval_seed`` (never the final evaluation's seed), paired against
  the heuristic on the same sites;
* ``m`` is the first of ``0`` and then ``train.defer_margins`` (ascending) at which the policy
  is significantly below the heuristic (paired 95 %, :func:`~fleet_torchrl.evaluation.
  strata_below`) at no validation point; if every candidate is below somewhere, the one
  below at the fewest points (the smaller on a tie), reported as such.

The margin changes no training: the run, its checkpoint and its snapshot selection are the
plain student's, so a finished run is calibrated again by resuming it with other deferral
settings (the checkpoint's fingerprint leaves them out; the published policy's summary
records them and the calibration).
"""

from __future__ import annotations

import copy
import logging
from dataclasses import replace
from typing import Any

import torch

from ..agents.baselines import HeuristicPolicy
from ..evaluation import evaluate_policy, strata_below
from ..sim import SiteConfig

log = logging.getLogger(__name__)


def validation_points(site: SiteConfig, k: int) -> list[tuple[str, SiteConfig]]:
    """The sites a deferral margin is validated on: ``site`` itself when it is one site; for a
    distribution, each drawn parameter at ``k`` evenly spaced values of its range (integers
    rounded, repeats dropped), the others at the site's own values; named ``"p_c=0.225"``."""
    if not site.randomized:
        return [(site.name or "site", site)]
    fixed = replace(site, ranges=None)
    out: list[tuple[str, SiteConfig]] = []
    for param in site.ranges.varied():
        lo, hi = getattr(site.ranges, param)
        values = [lo + (hi - lo) * i / (k - 1) for i in range(k)] if k > 1 else [lo]
        if param != "p_c":
            values = [int(round(v)) for v in values]
        seen = []
        for v in values:
            v = round(float(v), 6) if param == "p_c" else v
            if v not in seen:
                seen.append(v)
                out.append((f"{param}={v:g}", replace(fixed, **{param: v})))
    return out


def calibrate_deferral(policy: Any, site: SiteConfig, margins: list[float], sims: int,
                       ticks: int, seed: int, points: int, device: str = "cpu"
                       ) -> dict[str, Any]:
    """The deferral margin of ``policy`` (an :class:`~fleet_torchrl.agents.imitation.
    ImitationPolicy`, left unchanged) and the record of how it was chosen (module docstring):
    ``margin``, ``clear`` (whether no validation point is below the heuristic at it) and per
    candidate the points where it is below and its mean gain over the heuristic (%)."""
    sites = validation_points(site, points)
    args = dict(n_sims=sims, ticks=ticks, seed=seed, device=device)
    heuristic = {name: evaluate_policy(HeuristicPolicy(), s, **args) for name, s in sites}
    everything = torch.ones(sims, dtype=torch.bool)
    trial = copy.deepcopy(policy).cpu()
    candidates = [0.0, *sorted(float(m) for m in margins if m > 0)]
    record: dict[str, Any] = {"points": [name for name, _ in sites], "sims": sims,
                              "ticks": ticks, "seed": seed, "candidates": []}
    for m in candidates:
        trial.set_defer_margin(m)
        below, gains = [], []
        for name, s in sites:
            res = evaluate_policy(trial, s, name=f"defer {m:g} {name}", **args)
            h = heuristic[name]
            gains.append(100.0 * (res["trips_mean"] / max(h["trips_mean"], 1e-9) - 1.0))
            if strata_below(res, h, {"all": everything}):
                below.append(name)
        mean_gain = sum(gains) / len(gains)
        record["candidates"].append({"margin": m, "below": below,
                                     "mean_gain_vs_heuristic_pct": mean_gain})
        log.info("deferral margin %g: below the heuristic at %s; mean %+.3f %% over it",
                 m, ", ".join(below) or "no validation point", mean_gain)
        if not below:
            return {**record, "margin": m, "clear": True}
    best = min(record["candidates"], key=lambda c: (len(c["below"]), c["margin"]))
    log.warning("every deferral margin is below the heuristic somewhere: keeping %g (below at "
                "%s)", best["margin"], ", ".join(best["below"]))
    return {**record, "margin": best["margin"], "clear": False}


__all__ = ["calibrate_deferral", "validation_points"]
