"""Tabular Q-learning on the discretised ``partial`` state (MODEL §3).

State: ``soc_D`` and the lowest other soc in bins of width 10 (10 x 10; soc 100 falls in the
top bin), and the charger ``TC`` as free (0) or busy (> 0): 200 states x 2 actions.
``Q`` starts at 0. A visit of ``(s, a)`` moves ``Q(s, a)`` towards
``r + gamma * max_a' Q(s', a')`` (no bootstrap on failure) with ``alpha = k / (t + k)``,
``t`` = earlier visits of ``(s, a)``. With a batch of sites, the visits of one
``(s, a)`` in the same environment step are averaged into one update with the ``alpha`` of
the first of them -- the sequential rule up to the order of simultaneous visits.
"""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDictBase
from torch import Tensor

from ...env import MDPConfig, discount_exponent
from ...sim.fused import TABLE, KernelPolicy
from ..base import Learner, Policy
from .config import TabularAgentConfig

N_SOC_BINS = 10
N_STATES = N_SOC_BINS * N_SOC_BINS * 2


def n_cells(n_tc: int = 2) -> int:
    """Cells of the discretised ``partial`` state with ``n_tc`` charger bins."""
    return N_SOC_BINS * N_SOC_BINS * n_tc


def state_index(obs: Tensor, n_tc: int = 2) -> Tensor:
    """Discretise ``partial`` observations ``[..., 3]`` (normalised) to ``[0, 100 n_tc)``:
    ``(soc_D bin * 10 + others bin) * n_tc + TC bin``. TC bin 0 is a free charger; with
    ``n_tc = 2`` (the tabular learner's 200 states) bin 1 is busy, with more bins the busy
    range ``(0, 1]`` is cut into ``n_tc - 1`` equal shares (the kernel's table policies use
    the same float32 arithmetic: :mod:`fleet_torchrl.sim.kernel`)."""
    # + 1e-4: soc 40 is 0.4 after float32 scaling, which times 10 is 3.9999998, not 4
    soc_bins = (obs[..., :2] * N_SOC_BINS + 1e-4).long().clamp_(0, N_SOC_BINS - 1)
    tc = obs[..., 2]
    busy = tc > 0
    if n_tc == 2:
        tc_bin = busy.long()
    else:
        tc_bin = torch.where(busy, 1 + (tc * (n_tc - 1)).long().clamp(max=n_tc - 2), 0)
    return (soc_bins[..., 0] * N_SOC_BINS + soc_bins[..., 1]) * n_tc + tc_bin


class TabularQPolicy(Policy):
    """Greedy policy of a Q-table (ties -> pass). Holds the table and the visit counts."""

    name = "tabular"
    encoding = "partial"

    def __init__(self) -> None:
        super().__init__()
        self.register_buffer("q", torch.zeros(N_STATES, 2))
        self.register_buffer("visits", torch.zeros(N_STATES, 2, dtype=torch.int64))

    def check_loaded(self) -> str | None:
        """Its table has two actions (pass, charge) by its shape; its visit counts are
        counts."""
        bad = (self.visits < 0).nonzero()
        if bad.numel():
            s, a = (int(v) for v in bad[0])
            return f"visits[{s}, {a}] = {int(self.visits[s, a])}: a visit count is >= 0"
        return None

    def q_values(self, obs: Tensor) -> Tensor:
        return self.q[state_index(obs)]

    def forward(self, obs: Tensor) -> Tensor:
        return self.q_values(obs).argmax(-1)

    def kernel_policy(self) -> KernelPolicy:
        """The greedy action of every cell as an action table (ties -> pass, as argmax)."""
        return KernelPolicy(TABLE, table=self.q.argmax(-1).to(torch.int8)[None].cpu())


class TabularLearner(Learner):
    """Q-learning updates and epsilon-greedy behaviour around a :class:`TabularQPolicy`.

    A round plays one episode per site (``steps_per_round = None``) and updates the table
    online after every environment step.
    """

    steps_per_round = None

    @classmethod
    def from_context(cls, c: Any) -> TabularLearner:
        return cls(k=c.agent.k, gamma=c.mdp.discount, agent=c.agent, mdp=c.mdp).to(c.device)

    def __init__(self, k: float = 100.0, gamma: float = 0.9,
                 agent: TabularAgentConfig | None = None, mdp: MDPConfig | None = None) -> None:
        super().__init__()
        self.table = TabularQPolicy()
        self.k = float(k)
        self.gamma = float(gamma)  # discount base; ** the transition's exponent (mdp)
        self.agent = agent or TabularAgentConfig()
        self.mdp = mdp or MDPConfig(gamma=self.gamma)
        self.eps = self.agent.eps_start
        self._td_sum, self._td_n = 0.0, 0

    # ------------------------------------------------------------------ Learner
    def policy(self) -> TabularQPolicy:
        return self.table

    def exploration(self) -> float:
        return self.eps

    def start_round(self, round_idx: int) -> None:
        self.eps = self.agent.epsilon(round_idx)

    def act(self, td: TensorDictBase) -> TensorDictBase:
        return td.set("action", self.explore(td["observation"], self.eps))

    def observe(self, td: TensorDictBase, learn: Tensor) -> None:
        nxt = td["next"]
        expo = discount_exponent(td, self.mdp).squeeze(-1)
        self._td_sum += self.update_q(td["observation"], td["action"],
                                      nxt["reward"].squeeze(-1), nxt["observation"],
                                      nxt["terminated"].squeeze(-1), learn, expo)
        self._td_n += 1

    def update(self) -> dict[str, float]:
        """Tabular learning is online (in :meth:`observe`); reports the round's mean |TD|."""
        out = {"loss/td": self._td_sum / max(self._td_n, 1)}
        self._td_sum, self._td_n = 0.0, 0
        return out

    # ------------------------------------------------------------------ Q-learning
    def explore(self, obs: Tensor, eps: float,
                generator: torch.Generator | None = None) -> Tensor:
        """Epsilon-greedy actions for ``[B, 3]`` observations."""
        greedy = self.table(obs)
        u = torch.rand(greedy.shape, generator=generator, device=obs.device)
        rand = torch.randint(0, 2, greedy.shape, generator=generator, device=obs.device)
        return torch.where(u < eps, rand, greedy)

    @torch.no_grad()
    def update_q(self, obs: Tensor, action: Tensor, reward: Tensor, next_obs: Tensor,
               terminated: Tensor, mask: Tensor, expo: Tensor | None = None) -> float:
        """One batched Q-learning update from ``[B]`` transitions selected by ``mask``.

        ``expo``: each transition's discount exponent (``gamma ** expo``; default 1, i.e.
        per decision; the ticks of the step for the throughput objective).

        Returns the mean absolute TD error of the masked transitions.
        """
        q, visits = self.table.q.view(-1), self.table.visits.view(-1)
        key = (state_index(obs) * 2 + action)[mask]
        if key.numel() == 0:
            return 0.0
        nxt = self.table.q[state_index(next_obs)].amax(-1)
        disc = self.gamma if expo is None else torch.pow(self.gamma, expo.to(reward.dtype))
        target = reward + disc * nxt * (~terminated).float()
        td = target[mask] - q[key]
        n = q.numel()
        cnt = torch.bincount(key, minlength=n)
        total = torch.zeros(n, dtype=q.dtype, device=q.device).index_add_(0, key, td)
        touched = cnt > 0
        alpha = self.k / (visits[touched].to(q.dtype) + self.k)
        q[touched] += alpha * total[touched] / cnt[touched]
        visits += cnt
        return float(td.abs().mean())
