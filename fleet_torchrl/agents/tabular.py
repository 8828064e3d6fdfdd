"""Tabular Q-learning on the discretised ``partial`` state (SPEC §3).

State: ``soc_D`` and the lowest other soc in bins of width 10 (10 x 10; soc 100 falls in the
top bin), and the charger ``TC`` as free (0) or busy (> 0): 200 states x 2 actions.
``Q`` starts at 0. A visit of ``(s, a)`` moves ``Q(s, a)`` towards
``r + gamma * max_a' Q(s', a')`` (no bootstrap on failure) with ``alpha = k / (t + k)``,
``t`` = earlier visits of ``(s, a)``. With a batch of sites, the visits of one
``(s, a)`` in the same environment step are averaged into one update with the ``alpha`` of
the first of them -- the sequential rule up to the order of simultaneous visits.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from ..policies import Policy

N_SOC_BINS = 10
N_STATES = N_SOC_BINS * N_SOC_BINS * 2


def state_index(obs: Tensor) -> Tensor:
    """Discretise ``partial`` observations ``[..., 3]`` (normalised) to ``[0, 200)``."""
    # + 1e-4: soc 40 is 0.4 after float32 scaling, which times 10 is 3.9999998, not 4
    soc_bins = (obs[..., :2] * N_SOC_BINS + 1e-4).long().clamp_(0, N_SOC_BINS - 1)
    busy = (obs[..., 2] > 0).long()
    return (soc_bins[..., 0] * N_SOC_BINS + soc_bins[..., 1]) * 2 + busy


class TabularQPolicy(Policy):
    """Greedy policy of a Q-table (ties -> pass). Holds the table and the visit counts."""

    name = "tabular"
    encoding = "partial"

    def __init__(self) -> None:
        super().__init__()
        self.register_buffer("q", torch.zeros(N_STATES, 2))
        self.register_buffer("visits", torch.zeros(N_STATES, 2, dtype=torch.int64))

    def q_values(self, obs: Tensor) -> Tensor:
        return self.q[state_index(obs)]

    def forward(self, obs: Tensor) -> Tensor:
        return self.q_values(obs).argmax(-1)


class TabularLearner(nn.Module):
    """Q-learning updates and epsilon-greedy behaviour around a :class:`TabularQPolicy`."""

    def __init__(self, k: float = 100.0, gamma: float = 0.9) -> None:
        super().__init__()
        self.policy = TabularQPolicy()
        self.k = float(k)
        self.gamma = float(gamma)

    def act(self, obs: Tensor, eps: float, generator: torch.Generator | None = None) -> Tensor:
        greedy = self.policy(obs)
        u = torch.rand(greedy.shape, generator=generator, device=obs.device)
        rand = torch.randint(0, 2, greedy.shape, generator=generator, device=obs.device)
        return torch.where(u < eps, rand, greedy)

    @torch.no_grad()
    def update(self, obs: Tensor, action: Tensor, reward: Tensor, next_obs: Tensor,
               terminated: Tensor, mask: Tensor) -> float:
        """One batched Q-learning update from ``[B]`` transitions selected by ``mask``.

        Returns the mean absolute TD error of the masked transitions.
        """
        q, visits = self.policy.q.view(-1), self.policy.visits.view(-1)
        key = (state_index(obs) * 2 + action)[mask]
        if key.numel() == 0:
            return 0.0
        nxt = self.policy.q[state_index(next_obs)].amax(-1)
        target = reward + self.gamma * nxt * (~terminated).float()
        td = target[mask] - q[key]
        n = q.numel()
        cnt = torch.bincount(key, minlength=n)
        total = torch.zeros(n, dtype=q.dtype, device=q.device).index_add_(0, key, td)
        touched = cnt > 0
        alpha = self.k / (visits[touched].to(q.dtype) + self.k)
        q[touched] += alpha * total[touched] / cnt[touched]
        visits += cnt
        return float(td.abs().mean())
