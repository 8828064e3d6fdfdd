"""Tabular Q-learning: state bins and the update rule."""

from __future__ import annotations

import pytest
import torch

from fleet_torchrl.agents.tabular import N_STATES, TabularLearner, state_index
from fleet_torchrl.config import compose_config

# ---------------------------------------------------------------------- training


# ---------------------------------------------------------------------- tabular
def test_state_index_bins():
    obs = torch.tensor([[0.0, 0.0, 0.0], [0.35, 0.99, 0.4], [1.0, 1.0, 0.0], [0.099, 0.1, 0.0]])
    assert state_index(obs).tolist() == [0, (3 * 10 + 9) * 2 + 1, (9 * 10 + 9) * 2, 1 * 2]
    # exact multiples of 10 land in their own bin despite float32 scaling (40 -> bin 4)
    from fleet_torchrl.env.encodings import get_encoding
    from fleet_torchrl.sim import Site

    site = Site(compose_config([]).site)
    socs = torch.arange(0, 101, dtype=torch.float32)
    s = site.state(pos=torch.zeros(1, 101, dtype=torch.int64), soc=socs[None, :])
    bins = state_index(get_encoding("partial")(site, s)) // 20
    assert torch.equal(bins, (socs // 10).long().clamp(max=9))
    grid = torch.rand(1000, 3)
    idx = state_index(grid)
    assert idx.min() >= 0 and idx.max() < N_STATES == 200


def test_tabular_update_uses_k_over_t_plus_k():
    lrn = TabularLearner(k=100.0, gamma=0.9)
    obs = torch.tensor([[0.35, 0.8, 0.0]])
    nxt = torch.tensor([[0.75, 0.6, 0.5]])
    s, s2 = state_index(obs).item(), state_index(nxt).item()
    lrn.table.q[s2] = torch.tensor([-2.0, -1.0])
    one = torch.tensor([True])
    lrn.update_q(obs, torch.tensor([1]), torch.tensor([-0.5]), nxt, torch.tensor([False]), one)
    assert lrn.table.q[s, 1].item() == pytest.approx(-0.5 + 0.9 * -1.0)  # alpha = 1 first
    assert lrn.table.visits[s, 1].item() == 1
    lrn.update_q(obs, torch.tensor([1]), torch.tensor([-3.0]), nxt, torch.tensor([True]), one)
    # second visit: alpha = 100/101, no bootstrap on termination
    assert lrn.table.q[s, 1].item() == pytest.approx(-1.4 + 100 / 101 * (-3.0 + 1.4))
    assert lrn.table.q[s, 0].item() == 0.0  # untouched
    lrn.update_q(obs, torch.tensor([0]), torch.tensor([-9.0]), nxt, torch.tensor([False]),
               torch.tensor([False]))  # masked out
    assert lrn.table.q[s, 0].item() == 0.0 and lrn.table.visits[s, 0].item() == 0


def test_tabular_batched_visits_average_into_one_update():
    lrn = TabularLearner(k=100.0, gamma=0.0)
    obs = torch.tensor([[0.55, 0.8, 0.0]] * 3)
    lrn.update_q(obs, torch.tensor([0, 0, 0]), torch.tensor([-1.0, -2.0, -3.0]), obs,
               torch.zeros(3, dtype=torch.bool), torch.ones(3, dtype=torch.bool))
    s = state_index(obs[:1]).item()
    assert lrn.table.q[s, 0].item() == pytest.approx(-2.0)
    assert lrn.table.visits[s, 0].item() == 3
