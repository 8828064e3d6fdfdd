"""The objectives of the decision process (MODEL §2): rewards from the simulator's events.

The simulator (both backends) reports per step *events*: the ticks the step ran, its trips
and queue ticks, and what its last tick brought (an arrival, a failure, a queue tick); see
:class:`fleet_torchrl.sim.fused.Events`. An :class:`Objective` turns them into the step's
reward, says how a learner discounts the step, and gives the long-run reward per tick of a
whole episode's totals. Everything that depends on ``mdp.reward`` lives here, in one torch
function per objective, shared by the environment (fused and eager) and ``make objective``;
a new objective is one subclass and one :func:`register` call.

Rewards are bit-identical to accumulating the ticks' costs one by one in float32 (as the
ticks happen): within a step only the last tick can bring a trip or a failure, so the sum
over the earlier ticks is a function of their number alone, read from a table of the
running float32 sums (:class:`_RunningSums`) and completed by the last tick's term.

* ``thesis`` (default): a tick costs ``-p_f`` if the site failed in it, else ``-p_q`` if it
  was a queue tick; the reward is the mean cost of the step's ticks, discounted by
  ``mdp.gamma`` per decision.
* ``throughput``: tick ``k`` of the step (``k = 0`` right after the decision) earns
  ``trip_k - rho - p_f * fail_k``, discounted within the step by ``gamma_tick^k``; the next
  state is discounted by ``gamma_tick^dt`` (a semi-Markov decision process). Its long-run
  average per tick, ``trips/tick - rho - p_f * failures/tick``, ranks failure-free policies
  exactly by their trips; ``rho`` only centres the values near 0.
"""

from __future__ import annotations

from typing import Any, Protocol

import numpy as np
import torch
from torch import Tensor

from ..utils.checks import lookup


class MDPConfig(Protocol):
    """The settings of the decision process an objective reads: what an
    :class:`fleet_torchrl.env.config.MDPConfig` has (not imported here: its ``validate``
    imports this module)."""

    @property
    def p_f(self) -> float: ...
    @property
    def p_q(self) -> float: ...
    @property
    def gamma(self) -> float: ...
    @property
    def gamma_tick(self) -> float: ...
    @property
    def rho(self) -> float: ...


class StepEvents(Protocol):
    """What an objective reads of a step (``[B]`` tensors): see ``sim.fused.Events``."""

    ticks: Tensor
    trips: Tensor
    queue: Tensor
    arrived: Tensor
    failed: Tensor
    queued: Tensor


def _f32(x: float) -> float:
    """The float32 value of ``x`` as a Python float (exact in float32 arithmetic)."""
    return float(np.float32(x))


class _RunningSums:
    """``sums[k]``: the float32 running sum of ``k`` terms ``term(j)``, ``j = 0 .. k-1``
    (``sums[0] = 0``), and ``factors[k]``: the float32 running product ``f^k``; grown on
    demand, one table per objective and settings."""

    def __init__(self, term: float, factor: float = 1.0) -> None:
        self.term, self.factor = np.float32(term), np.float32(factor)
        self.sums = np.zeros(1, dtype=np.float32)
        self.factors = np.ones(1, dtype=np.float32)

    def upto(self, k: int, device: torch.device) -> tuple[Tensor, Tensor]:
        n = self.sums.shape[0]
        if k >= n:
            size = max(k + 1, 2 * n, 1024)
            sums = np.empty(size, dtype=np.float32)
            facs = np.empty(size, dtype=np.float32)
            sums[:n], facs[:n] = self.sums, self.factors
            acc, f = self.sums[-1], self.factors[-1]
            for j in range(n, size):  # acc + f * term: the order the ticks add in
                acc = np.float32(acc + np.float32(f * self.term))
                f = np.float32(f * self.factor)
                sums[j], facs[j] = acc, f
            self.sums, self.factors = sums, facs
        return (torch.from_numpy(self.sums).to(device), torch.from_numpy(self.factors).to(device))


class Objective:
    """One objective: the step reward, the learners' discount, the long-run rate."""

    name: str = ""

    def reward(self, ev: StepEvents, mdp: MDPConfig) -> Tensor:
        """The reward of each step, float32 ``[B]`` (sites with 0 ticks: 0)."""
        raise NotImplementedError

    def discount(self, mdp: MDPConfig) -> float:
        """The learners' discount base (per decision, or per tick)."""
        raise NotImplementedError

    def exponent(self, ticks: Tensor) -> Tensor:
        """The exponent of :meth:`discount` for steps of ``ticks`` ticks (float32)."""
        raise NotImplementedError

    def rate(self, trips: Tensor, queue: Tensor, failures: Tensor, ticks: Tensor,
             mdp: MDPConfig) -> Tensor:
        """The long-run reward per tick of totals over whole episodes (what a learner
        discounting per tick maximises as the discount goes to 1)."""
        raise NotImplementedError

    def ranks_by_decision(self) -> bool:
        """Whether a learner of this objective maximises the reward per decision (per
        decision discounting) rather than per tick (``make objective`` sorts by it)."""
        return False

    def snapshot_score(self, summary: dict[str, Any]) -> float:
        """What ranks two evaluations of a learner of this objective with the same failure
        rate (``train.select=objective``): higher is better. Default: the mean trips."""
        return float(summary["trips_mean"])

    def _table(self, key: tuple, term: float, factor: float = 1.0) -> _RunningSums:
        tables = self.__dict__.setdefault("_tables", {})
        if key not in tables:
            tables[key] = _RunningSums(term, factor)
        return tables[key]


class ThesisCost(Objective):
    """MODEL §2.2: the mean cost per tick of the step; queue ticks and failures cost."""

    name = "thesis"

    def reward(self, ev: StepEvents, mdp: MDPConfig) -> Tensor:
        # the running sum of the queue ticks before the last one, then the last tick's cost
        sums, _ = self._table(("q", mdp.p_q), -_f32(mdp.p_q)).upto(
            int(ev.queue.max()) if ev.queue.numel() else 0, ev.queue.device)
        before = sums[ev.queue - ev.queued.long()]  # (the last tick's queue is in the count)
        last = torch.where(ev.failed, _f32(mdp.p_f), torch.where(ev.queued, _f32(mdp.p_q), 0.0))
        # a site that ran no tick: 0 / 1 (no queue, no failure)
        return (before - last.to(torch.float32)) / ev.ticks.clamp(min=1)

    def discount(self, mdp: MDPConfig) -> float:
        return mdp.gamma

    def exponent(self, ticks: Tensor) -> Tensor:
        return torch.ones_like(ticks, dtype=torch.float32)

    def rate(self, trips, queue, failures, ticks, mdp):
        return -(mdp.p_q * queue + mdp.p_f * failures) / ticks

    def ranks_by_decision(self) -> bool:
        return True

    def snapshot_score(self, summary: dict[str, Any]) -> float:
        return -float(summary["queue_mean"])  # the thesis reward costs queue ticks


class Throughput(Objective):
    """MODEL §2.3: discounted trips minus a reference rate, failures heavily penalised."""

    name = "throughput"

    def reward(self, ev: StepEvents, mdp: MDPConfig) -> Tensor:
        table = self._table(("t", mdp.rho, mdp.gamma_tick), -_f32(mdp.rho), mdp.gamma_tick)
        sums, factors = table.upto(int(ev.ticks.max()) if ev.ticks.numel() else 0,
                                   ev.ticks.device)
        k = (ev.ticks - 1).clamp(min=0)  # the ticks before the last one
        # the last tick's term: (arrived - rho) - p_f * failed, as float32 in that order
        r = (ev.arrived.to(torch.float32) - _f32(mdp.rho)) \
            - ev.failed.to(torch.float32) * _f32(mdp.p_f)
        out = sums[k] + factors[k] * r
        return torch.where(ev.ticks > 0, out, 0.0)

    def discount(self, mdp: MDPConfig) -> float:
        return mdp.gamma_tick

    def exponent(self, ticks: Tensor) -> Tensor:
        return ticks.to(torch.float32)

    def rate(self, trips, queue, failures, ticks, mdp):
        return (trips - mdp.rho * ticks - mdp.p_f * failures) / ticks


OBJECTIVES: dict[str, Objective] = {}


def register(objective: Objective) -> Objective:
    OBJECTIVES[objective.name] = objective
    return objective


register(ThesisCost())
register(Throughput())


def get_objective(name: str) -> Objective:
    return lookup(OBJECTIVES, name, f"mdp.reward={name!r} is invalid")


__all__ = ["OBJECTIVES", "Objective", "StepEvents", "get_objective", "register"]
