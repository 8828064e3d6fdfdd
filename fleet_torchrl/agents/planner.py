"""A simulation-based lookahead policy (``agent=planner``): one step of policy improvement.

At each decision the planner simulates, for both actions, ``rollouts`` sampled futures of
``horizon`` ticks from the site's current state, every later decision taken by a base policy
(``agent.base``: the heuristic by default, any baseline, or a saved policy file), and picks
the better action:

* **Common random numbers.** Future ``k`` of both actions sees the same closures, so the
  comparison is paired: the difference of their scores has far less noise than either.
* **Its own streams.** A future's closures are drawn from the planner's stream
  (``rng.STREAM_PLANNER``: planner seed, the site's index, the decision's tick, ``k``),
  never from the evaluated site's: the planner does not know the site's own future, and its
  decision at tick ``t`` depends on the state at ``t`` alone (tests/agents/test_planner.py).
* **Score.** Failures dominate (fewer failed futures wins); then the mean over futures of
  trips in the horizon plus ``energy_value`` trips per unit of charge left in the fleet's
  batteries at the horizon (trips alone over a short horizon favour never charging; the
  value is a measured choice, docs/PLANNER.md).
* **Confidence.** The planner leaves the base policy's action only when the other one
  scores better by ``confidence`` standard errors of the paired difference (or fails in
  fewer futures): where the futures cannot tell the actions apart, it acts as the base.
  Without this gate the noise of a few futures made the planner worse than its base.
* **Safety line.** It never turns the base's charge into a pass for a vehicle below
  :meth:`Site.reserve_floor` (one more lap and a full queue at ``D``): a failure that is
  likely but not certain shows in none of a few futures (measured: the planner failed 0.5-
  1.5 % of the study's sites at ``N_V`` = 5 without it, each time after passing a vehicle
  at about 38 % that did not finish its lap).

So the planner with base ``P`` is one step of policy improvement over ``P``: where it
gains significantly over ``P``, ``P`` was not optimal (``make table`` and the sweeps report
what this step adds, MODEL §3.6).

Cost: ``2 x rollouts x horizon`` site-ticks per decision, all decisions of an epoch in one
batch: with the base policy inside the compiled kernel (the heuristic, threshold policies,
tables) one kernel call per decision epoch; a network base decides its rollouts' arrivals
with batched forward passes.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..sim import D, Site, SiteState, rng
from ..sim.rollout import DecisionContext, advance
from .base import Policy
from .config import BASELINE_BASES, PlannerAgentConfig


class PlannerPolicy(Policy):
    """The rollout planner around a base policy (module docstring). It decides from the
    site's state (:meth:`decide`), not from an encoded observation."""

    name = "planner"

    def __init__(self, base: Policy, rollouts: int = 32, horizon: int = 200,
                 energy_value: float = 0.02, confidence: float = 1.5, seed: int = 0) -> None:
        super().__init__()
        if isinstance(base, PlannerPolicy):
            raise ValueError("a planner's base policy cannot be a planner")
        self.base = base
        self.encoding = base.encoding
        self.rollouts, self.horizon = int(rollouts), int(horizon)
        self.energy_value, self.confidence = float(energy_value), float(confidence)
        self.seed = int(seed)
        self.stats = {"decisions": 0, "changed": 0}  # how often it left the base's action

    def forward(self, obs: Tensor) -> Tensor:
        raise TypeError("the planner decides from the site's state, not from an observation: "
                        "call decide(site, state, ctx) (the evaluation protocol does)")

    @torch.no_grad()
    def decide(self, site: Site, state: SiteState, ctx: DecisionContext) -> Tensor:
        act = self.base.decide(site, state, ctx)
        d = ctx.need.nonzero().squeeze(1)
        n, k = d.numel(), self.rollouts
        if n == 0:
            return act
        dev = state.pos.device
        rep = d.repeat(2 * k)  # rollout (a, j, i) at (a * k + j) * n + i
        rs = state.select(rep)
        rs.charge = torch.arange(2, device=dev).repeat_interleave(k * n).bool()
        future = torch.arange(k, device=dev).repeat_interleave(n).repeat(2)
        h = rng.hash_ints(self.seed, ctx.index[rep], rs.tick, future, rng.STREAM_PLANNER,
                          device=dev)
        ev = advance(site, rs, h, rs.tick + self.horizon, self.base.decide,
                     self.base.kernel_policy(), ctx.index[rep], ctx.fused)
        real = rs.pos != site.park  # the vehicles a site of a distribution does not have
        energy = (rs.soc.double() * real).sum(0)
        score = (ev.trips.double() + self.energy_value * energy).view(2, k, n)
        fails = ev.failed.view(2, k, n).sum(1)
        base_a = act[d].long()
        diff = score[1] - score[0]  # paired over common futures: charge minus pass
        gain = torch.where(base_a == 1, -diff, diff)  # the other action minus the base's
        se = gain.std(0) / k ** 0.5
        f_base = torch.where(base_a == 1, fails[1], fails[0])
        f_other = torch.where(base_a == 1, fails[0], fails[1])
        switch = (f_other < f_base) | ((f_other == f_base)
                                       & (gain.mean(0) > self.confidence * se + 1e-9))
        # never turn a charge into a pass for a battery that might not last another lap and
        # a full queue: a few futures cannot show a failure that is merely likely
        soc_d = (state.soc[:, d] * (state.pos[:, d] == D)).sum(0)
        switch &= ~((base_a == 1) & (soc_d < site.reserve_floor(state.params.select(d))))
        self.stats["decisions"] += n
        self.stats["changed"] += int(switch.sum())
        out = act.clone()
        out[d] = torch.where(switch, 1 - base_a, base_a).to(act.dtype)
        return out

    @classmethod
    def from_config(cls, agent: PlannerAgentConfig, base: Policy) -> PlannerPolicy:
        return cls(base, agent.rollouts, agent.horizon, agent.energy_value, agent.confidence,
                   agent.seed)


__all__ = ["BASELINE_BASES", "PlannerAgentConfig", "PlannerPolicy"]
