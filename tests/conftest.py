from __future__ import annotations

import pytest
import torch

from fleet_torchrl.config import CONF_DIR, Config, SiteConfig, compose_config, register_configs
from fleet_torchrl.sim import Site, SiteState

CONF = CONF_DIR
register_configs()  # tests that call Hydra's compose directly need the schemas


def make_cfg(overrides: list[str] | tuple[str, ...] = ()) -> Config:
    """The validated config composed from conf/ with Hydra overrides."""
    return compose_config(overrides)


def make_state(vehicles: list[tuple[int, float] | tuple[int, float, int]], charge: bool = False,
               tick: int = 0) -> SiteState:
    """One site from ``(node, soc[, charging ticks left])`` per vehicle."""
    pos = torch.tensor([[v[0]] for v in vehicles], dtype=torch.int64)
    soc = torch.tensor([[float(v[1])] for v in vehicles], dtype=torch.float32)
    left = torch.tensor([[v[2] if len(v) > 2 else 0] for v in vehicles], dtype=torch.int64)
    return SiteState(pos=pos, soc=soc, left=left, charge=torch.tensor([charge]),
                     tick=torch.tensor([tick]))


OPEN = torch.tensor([False])
CLOSED = torch.tensor([True])


@pytest.fixture
def site() -> Site:
    return Site(SiteConfig())
