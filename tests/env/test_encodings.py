"""State encodings on a hand-built state."""

from __future__ import annotations

import pytest
import torch

from fleet_torchrl.env.encodings import get_encoding
from fleet_torchrl.sim import C, D, Site, SiteConfig, SiteState


def test_encodings_on_a_hand_built_state():
    site = Site(SiteConfig())
    s = SiteState(pos=torch.tensor([[D, C], [C, 5], [7, 8]]),
                  soc=torch.tensor([[38.0, 50.0], [70.0, 90.0], [60.0, 45.0]]),
                  left=torch.tensor([[0, 0], [9, 0], [0, 0]]),
                  charge=torch.tensor([False, False]), tick=torch.zeros(2, dtype=torch.int64))
    part = get_encoding("partial")(site, s)
    assert torch.allclose(part[0], torch.tensor([0.38, 0.60, 10 / 31]))
    # site 1: nobody at D, finished vehicle stuck at C counts as busy: 1 / (T_C + 1)
    assert torch.allclose(part[1], torch.tensor([0.0, 0.45, 1 / 31]))
    full = get_encoding("all")(site, s)
    assert full.shape == (2, 16)
    assert torch.allclose(full[0, [D, C, 7]], torch.tensor([0.38, 0.70, 0.60]))
    assert full[0, [2, 3, 4, 5, 6, 8]].abs().sum() == 0
    assert full[0, -1] == pytest.approx(10 / 31)
    lone = SiteState(pos=torch.tensor([[D]]), soc=torch.tensor([[50.0]]),
                     left=torch.zeros(1, 1, dtype=torch.int64), charge=torch.tensor([False]),
                     tick=torch.zeros(1, dtype=torch.int64))
    assert torch.allclose(get_encoding("partial")(site, lone), torch.tensor([[0.5, 1.0, 0.0]]))
