"""State encodings (MODEL §2): what an agent observes when a vehicle is at ``D``.

Features are normalised to [0, 1] (soc / 100) so that one network setting fits every site.
In both encodings feature 0 is the soc of the vehicle at ``D``, which lets the rule-based
benchmark read either of them.

* ``partial`` (3): ``soc_D``; lowest soc among vehicles neither at ``D`` nor at ``C`` (100 if
  none); ``TC`` = 0 if ``C`` is empty, else ``(ticks left of its occupant + 1) / (T_C + 1)``.
* ``all`` (``N_N + 1``): the soc on every node (0 if empty), then ``TC``.

Add an encoding by subclassing :class:`Encoding`, registering it in :data:`ENCODINGS` (config
validation reads this registry) and adding a ``fleet_torchrl/conf/state/<name>.yaml``.
"""

from __future__ import annotations

import functools

import torch
from torch import Tensor

from ..sim import C, D, Site, SiteState


class Encoding:
    name: str = ""

    def size(self, site: Site) -> int:
        raise NotImplementedError

    def __call__(self, site: Site, s: SiteState) -> Tensor:
        raise NotImplementedError


def charger_time(site: Site, s: SiteState) -> Tensor:
    """``TC`` of MODEL §2 for every site: ``[B]`` float32."""
    return _charger_ticks(s).to(torch.float32) / (site.t_c + 1)


def _charger_ticks(s: SiteState) -> Tensor:
    """``ticks left + 1`` of the vehicle at C, 0 if C is empty: ``[B]`` int64."""
    return ((s.pos == C) * (s.left + 1)).sum(0)


@functools.lru_cache(maxsize=64)
def _partial_scale(t_c: int, device: torch.device) -> Tensor:
    return torch.tensor([0.01, 0.01, 1.0 / (t_c + 1)], device=device)


class Partial(Encoding):
    name = "partial"

    def size(self, site: Site) -> int:
        return 3

    def __call__(self, site: Site, s: SiteState) -> Tensor:
        soc = s.soc
        soc_d = (soc * (s.pos == D)).sum(0)
        others = torch.where(s.pos > C, soc, 100.0).amin(0)  # neither D (0) nor C (1)
        raw = torch.stack((soc_d, others, _charger_ticks(s).to(torch.float32)), dim=1)
        return raw * _partial_scale(site.t_c, soc.device)


class All(Encoding):
    name = "all"

    def size(self, site: Site) -> int:
        return site.n_nodes + 1

    def __call__(self, site: Site, s: SiteState) -> Tensor:
        b = s.pos.shape[1]
        out = torch.zeros(site.n_nodes + 1, b, dtype=torch.float32, device=s.pos.device)
        out.scatter_(0, s.pos, s.soc / 100.0)
        out[-1] = charger_time(site, s)
        return out.T.contiguous()


ENCODINGS: dict[str, Encoding] = {"partial": Partial(), "all": All()}


def get_encoding(name: str) -> Encoding:
    try:
        return ENCODINGS[name]
    except KeyError:
        raise ValueError(f"unknown state encoding {name!r}: allowed one of "
                         f"{', '.join(ENCODINGS)}") from None
