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

* **Several bases** (``agent.bases``: parallel rollout). The same futures run under every
  base; the reference is the first base, unless another base's own action fails in fewer
  futures or scores better by the confidence bound (then the best such base), and the
  other action is scored under whichever base scores it best (``agent.other_under=best``;
  ``gated``: under the reference's base unless another scores it better by the confidence
  bound; ``reference``: always under the reference's base). The best of several noisy means
  may be biased upwards: at ``N_V`` = 1 the four-base planner of the generalist left the
  reference's action in 23 % of the decisions and lost 0.66 points to the heuristic, 0.13
  scored under the reference (``gated`` 0.63: there the other bases' horizon scores, not
  their noise, mislead). The gate and
  the safety line then apply to that pair: one step of improvement over the best base at
  each decision, at one set of futures per base. With one base, or the base repeated, the
  decisions are the one-base planner's (tests/agents/test_planner.py).
* **Stakes.** After each :meth:`decide`, ``last_gap`` (``[B]``, float64) holds for every
  deciding site the absolute difference between the mean scores of the two actions (the
  pair compared above), ``inf`` where one fails in more futures, and 0 for the sites that
  did not decide: what taking the wrong action is estimated to cost, which the distilled
  student can weight its labels by (``agent.label_weight=gap``, agents/imitation/learner.py).

So the planner with base ``P`` is one step of policy improvement over ``P``: where it
gains significantly over ``P``, ``P`` was not optimal (``make table`` and the sweeps report
what this step adds, MODEL §3.6).

Cost: ``2 x rollouts x horizon`` site-ticks per decision and base (``other_under=reference``
with ``m`` bases: ``(m + 1) x rollouts x horizon``, each base running its own action only),
all decisions of an epoch in one batch: with the base policy inside the compiled kernel
(the heuristic, threshold policies, tables) one kernel call per decision epoch; a network
base decides its rollouts' arrivals with batched forward passes.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import torch
from torch import Tensor, nn

from ...sim import D, Site, SiteState, rng
from ...sim.rollout import DecisionContext, advance
from ..base import Policy
from .config import BASELINE_BASES, OTHER_UNDER, PlannerAgentConfig


class PlannerPolicy(Policy):
    """The rollout planner around a base policy (module docstring). It decides from the
    site's state (:meth:`decide`), not from an encoded observation."""

    name = "planner"
    decides_from_state = True

    def __init__(self, base: Policy, rollouts: int = 32, horizon: int = 200,
                 energy_value: float = 0.02, confidence: float = 1.5, seed: int = 0,
                 bases: Sequence[Policy] = (), other_under: str = "best") -> None:
        super().__init__()
        if any(isinstance(b, PlannerPolicy) for b in (base, *bases)):
            raise ValueError("a planner's base policy cannot be a planner")
        self.base = base
        if bases:  # registered only when there are any: a one-base planner's fingerprint stays
            self.more_bases = nn.ModuleList(bases)
        self.encoding = base.encoding
        self.rollouts, self.horizon = int(rollouts), int(horizon)
        self.energy_value, self.confidence = float(energy_value), float(confidence)
        self.seed = int(seed)
        if other_under not in OTHER_UNDER:
            raise ValueError(f"other_under={other_under!r}: allowed one of "
                             f"{', '.join(OTHER_UNDER)}")
        self.other_under = other_under
        # how often it left the reference base's action; with several bases, how often the
        # reference was another than the first
        self.stats = {"decisions": 0, "changed": 0, "other_base": 0}
        # what the last decide() estimated each decision to be worth (None before the first)
        self.last_gap: Tensor | None = None

    @property
    def bases(self) -> list[Policy]:
        """The base policies: ``base`` first, then the parallel rollout's others."""
        more = self._modules.get("more_bases")
        return [self.base, *(more if more is not None else ())]

    def forward(self, obs: Tensor) -> Tensor:
        raise TypeError("the planner decides from the site's state, not from an observation: "
                        "call decide(site, state, ctx) (the evaluation protocol does)")

    def _futures(self, site: Site, state: SiteState, ctx: DecisionContext, base: Policy,
                 d: Tensor, charge: Tensor) -> tuple[Tensor, Tensor]:
        """Scores ``[k, n]`` and failed futures ``[n]`` of the deciding sites ``d`` ([n],
        a site may repeat) taking action ``charge`` ([n]) under ``base``. Future ``j`` of a
        site is the same whatever the action, the base or the other rows of the batch (its
        closures hash the planner's seed, the site's index, the tick and ``j``)."""
        k, n = self.rollouts, d.numel()
        rep = d.repeat(k)  # rollout (j, i) at j * n + i
        future = torch.arange(k, device=d.device).repeat_interleave(n)
        h = rng.hash_ints(self.seed, ctx.index[rep], state.tick[rep], future,
                          rng.STREAM_PLANNER, device=d.device)
        rs = state.select(rep)
        rs.charge = charge.repeat(k).bool()
        ev = advance(site, rs, h, rs.tick + self.horizon, base.decide, base.kernel_policy(),
                     ctx.index[rep], ctx.fused)
        real = rs.pos != site.park  # the vehicles a site of a distribution does not have
        energy = (rs.soc.double() * real).sum(0)
        score = (ev.trips.double() + self.energy_value * energy).view(k, n)
        return score, ev.failed.view(k, n).sum(0)

    def _both(self, site: Site, state: SiteState, ctx: DecisionContext, base: Policy,
              d: Tensor) -> tuple[Tensor, Tensor]:
        """Scores ``[2, k, n]`` and failed futures ``[2, n]`` of both actions of the
        deciding sites ``d`` under ``base``, on common futures."""
        n = d.numel()
        act = torch.arange(2, device=d.device).repeat_interleave(n)
        score, failed = self._futures(site, state, ctx, base, d.repeat(2), act)
        return score.view(-1, 2, n).transpose(0, 1), failed.view(2, n)

    def _reference(self, own: Tensor, score: Tensor, fails: Tensor) -> Tensor:
        """For each deciding site, the base whose own action is the planner's reference:
        the first base, unless another one's own action fails in fewer futures or scores
        better by ``confidence`` standard errors of the paired difference (then the best
        such base). Taking the best mean alone would follow noise: with bases about equal,
        a few futures pick a base that is worse in truth (measured: at ``T_C`` = 20 the
        reference became another base in 77 % of the decisions, and the planner lost a
        third of its gain)."""
        m, n = own.shape
        col = torch.arange(n, device=own.device)
        mine = score[torch.arange(m, device=own.device)[:, None], own, :, col]  # [m, n, k]
        f = fails.gather(1, own.unsqueeze(1)).squeeze(1)  # [m, n]
        return self._gate(mine, f, torch.zeros(n, dtype=torch.long, device=own.device))

    def _gated(self, a: Tensor, start: Tensor, score: Tensor, fails: Tensor) -> Tensor:
        """For each deciding site, the base under which action ``a`` ([n]) is scored: base
        ``start`` ([n]) unless another base scores it in fewer failed futures or better by
        ``confidence`` standard errors of the paired difference (then the best such base)."""
        col = torch.arange(a.numel(), device=a.device)
        return self._gate(score[:, a, :, col].transpose(0, 1), fails[:, a, col], start)

    def _gate(self, mine: Tensor, f: Tensor, start: Tensor) -> Tensor:
        """Per site, base ``start`` ([n]) unless another base fails in fewer futures (``f``,
        [m, n]) or scores better (``mine``, [m, n, k]) by ``confidence`` standard errors of
        the paired difference over the common futures; then the best such base."""
        col = torch.arange(f.shape[1], device=f.device)
        diff = mine - mine[start, col].unsqueeze(0)  # each base minus the start's, paired
        mean, se = diff.mean(2), diff.std(2) / self.rollouts ** 0.5
        f0 = f[start, col]
        better = (f < f0) | ((f == f0) & (mean > self.confidence * se + 1e-9))
        key = torch.where(better, mean - 1e6 * (f - f0), -math.inf)
        key[start, col] = torch.where(better.any(0), -math.inf, 0.0).to(key.dtype)
        return torch.argmax(key, dim=0)

    def _under_any(self, site: Site, state: SiteState, ctx: DecisionContext, d: Tensor,
                   own: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        """Both actions under every base (``other_under`` best or gated, or one base): the
        paired gain ``[k, n]`` of the other action (under its base) over the reference's,
        both actions' failed futures ``[n]``, the reference base and its action ``[n]``."""
        bases, n = self.bases, d.numel()
        runs = [self._both(site, state, ctx, b, d) for b in bases]
        score = torch.stack([r[0] for r in runs])  # [m, 2, k, n]
        fails = torch.stack([r[1] for r in runs])  # [m, 2, n]
        col = torch.arange(n, device=d.device)

        def best(a: Tensor) -> Tensor:
            """For each site, the base under which action ``a`` ([n]) fails in fewest
            futures, then scores highest on average (the first of equals)."""
            a = a.expand(len(bases), n)
            f = fails.gather(1, a.unsqueeze(1)).squeeze(1)
            v = score.mean(2).gather(1, a.unsqueeze(1)).squeeze(1)
            return torch.argmax(torch.where(f == f.min(0).values, v, -math.inf), dim=0)

        ref = self._reference(own, score, fails) if len(bases) > 1 else \
            torch.zeros(n, dtype=torch.long, device=d.device)
        base_a = own[ref, col]  # the reference: the first base's action, or a better base's
        other = 1 - base_a
        if len(bases) == 1 or self.other_under == "reference":
            alt = ref
        elif self.other_under == "gated":
            alt = self._gated(other, ref, score, fails)
        else:
            alt = best(other)
        # paired over common futures: the other action (under base alt) minus the reference's
        gain = (score[alt, other, :, col] - score[ref, base_a, :, col]).T  # [k, n]
        return gain, fails[ref, base_a, col], fails[alt, other, col], ref, base_a

    def _under_reference(self, site: Site, state: SiteState, ctx: DecisionContext,
                         d: Tensor, own: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor,
                                                          Tensor]:
        """:meth:`_under_any` for ``other_under=reference`` at ``m + 1`` sets of futures
        per decision instead of ``2 m``: each base runs its own action only (all the
        reference's gate compares), then the other action runs under the reference's base
        alone. The same decisions and stakes as scoring both actions under every base."""
        bases, n, k = self.bases, d.numel(), self.rollouts
        runs = [self._futures(site, state, ctx, b, d, own[i]) for i, b in enumerate(bases)]
        mine = torch.stack([r[0] for r in runs]).permute(0, 2, 1)  # [m, n, k]
        fails = torch.stack([r[1] for r in runs])  # [m, n]
        col = torch.arange(n, device=d.device)
        ref = self._gate(mine, fails, torch.zeros(n, dtype=torch.long, device=d.device))
        base_a = own[ref, col]
        gain = torch.empty(k, n, dtype=mine.dtype, device=d.device)
        f_other = torch.empty(n, dtype=fails.dtype, device=d.device)
        for b in torch.unique(ref).tolist():  # a loop over bases, each a batch of sites
            s = (ref == b).nonzero().squeeze(1)
            score, failed = self._futures(site, state, ctx, bases[b], d[s], 1 - base_a[s])
            gain[:, s] = score - mine[b, s].T
            f_other[s] = failed
        return gain, fails[ref, col], f_other, ref, base_a

    @torch.no_grad()
    def decide(self, site: Site, state: SiteState, ctx: DecisionContext) -> Tensor:
        bases = self.bases
        act = self.base.decide(site, state, ctx)
        d = ctx.need.nonzero().squeeze(1)
        n, k = d.numel(), self.rollouts
        if n == 0:
            return act
        dev = state.pos.device
        own = torch.stack([act[d].long()] + [b.decide(site, state, ctx)[d].long()
                                             for b in bases[1:]])  # [m, n]: each base's action
        if len(bases) > 1 and self.other_under == "reference":
            gain, f_base, f_other, ref, base_a = self._under_reference(site, state, ctx, d,
                                                                       own)
        else:
            gain, f_base, f_other, ref, base_a = self._under_any(site, state, ctx, d, own)
        other = 1 - base_a
        se = gain.std(0) / k ** 0.5
        switch = (f_other < f_base) | ((f_other == f_base)
                                       & (gain.mean(0) > self.confidence * se + 1e-9))
        # never turn a charge into a pass for a battery that might not last another lap and
        # a full queue: a few futures cannot show a failure that is merely likely
        soc_d = (state.soc[:, d] * (state.pos[:, d] == D)).sum(0)
        switch &= ~((base_a == 1) & (soc_d < site.reserve_floor(state.params.select(d))))
        self.stats["decisions"] += n
        self.stats["changed"] += int(switch.sum())
        self.stats["other_base"] += int((ref != 0).sum())
        # the stake of each decision: the estimated difference between the two actions'
        # mean scores, infinite where one fails in more futures (a failure ends the site)
        stake = torch.where(f_other != f_base, math.inf, gain.mean(0).abs())
        self.last_gap = torch.zeros(act.shape, dtype=torch.float64, device=dev)
        self.last_gap[d] = stake
        out = act.clone()
        out[d] = torch.where(switch, other, base_a).to(act.dtype)
        return out

    @classmethod
    def from_config(cls, agent: PlannerAgentConfig, base: Policy,
                    bases: Sequence[Policy] = ()) -> PlannerPolicy:
        return cls(base, agent.rollouts, agent.horizon, agent.energy_value, agent.confidence,
                   agent.seed, bases, agent.other_under)

    @classmethod
    def from_agent(cls, agent: PlannerAgentConfig) -> PlannerPolicy:
        """The planner over the bases ``agent`` names (baselines or saved policies)."""
        from ..registry import base_policy

        for b in agent.all_bases():
            assert b in BASELINE_BASES or Path(b).exists(), b
        return cls.from_config(agent, base_policy(agent.base),
                               [base_policy(b) for b in agent.bases])


__all__ = ["BASELINE_BASES", "OTHER_UNDER", "PlannerAgentConfig", "PlannerPolicy"]
