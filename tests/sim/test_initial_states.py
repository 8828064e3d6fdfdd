"""Initial states and closure draws: the MODEL §1 distribution, pure functions of the integers."""

from __future__ import annotations

import torch

from fleet_torchrl.sim import C, D, Site, SiteConfig


def test_initial_states_follow_spec(site):
    s, needs = site.init_state(0, torch.arange(2000))
    pos = s.pos
    assert not (pos == C).any()
    srt = pos.sort(0).values
    assert (srt[1:] != srt[:-1]).all()  # distinct nodes per site
    assert (s.soc >= 40.0).all() and (s.soc <= 100.0).all()
    assert torch.equal(needs, (pos == D).any(0))
    # every non-C node is used, roughly uniformly: 3 of 14 nodes per site
    counts = torch.bincount(pos.flatten(), minlength=15).float()
    assert counts[C] == 0
    assert (counts[[k for k in range(15) if k != C]] / (2000 * 3 / 14) - 1).abs().max() < 0.2


def test_initial_states_and_closures_are_pure_functions(site):
    a, _ = site.init_state(7, torch.tensor([3, 4, 5]))
    b, _ = site.init_state(7, torch.tensor([5, 3]))
    assert torch.equal(a.pos[:, 2], b.pos[:, 0]) and torch.equal(a.soc[:, 0], b.soc[:, 1])
    c, _ = site.init_state(8, torch.tensor([3, 4, 5]))
    assert not torch.equal(a.soc, c.soc)
    block = site.closures(7, torch.arange(50), torch.arange(100)[:, None])  # [T, B]
    single = site.closures(7, torch.tensor([13]), torch.tensor([42]))
    assert block[42, 13] == single[0]
    rate = block.float().mean().item()
    assert 0.76 < rate < 0.84
    assert not torch.equal(block, site.closures(8, torch.arange(50), torch.arange(100)[:, None]))
    never = Site(SiteConfig(p_c=0.0))
    assert not never.closures(7, torch.arange(50), torch.arange(9)[:, None]).any()
