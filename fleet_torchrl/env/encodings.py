"""State encodings (MODEL §2): what an agent observes when a vehicle is at ``D``.

Features are normalised to [0, 1] so that they mean the same on every site: soc / 100, the
charger's remaining time as a share of the site's own ``T_C`` (per site on a site
distribution), node positions as slots of the site's own ``N_N`` nodes. In both encodings
feature 0 is the soc of the vehicle at ``D``, which lets the rule-based benchmark read either
of them. Parked vehicles (the fleet a site of a distribution does not have) are full and on
no node, so they change no feature.

* ``partial`` (3): ``soc_D``; lowest soc among vehicles neither at ``D`` nor at ``C`` (100 if
  none); ``TC`` = 0 if ``C`` is empty, else ``(ticks left of its occupant + 1) / (T_C + 1)``.
* ``all`` (``N_N + 1``): the soc on every node (0 if empty), then ``TC``.
* ``partial_site`` (6): ``partial``, then the site's own ``N_V / N_N``, ``p_c`` and
  ``T_C / (T_C + N_N)`` (constant on one site; per site on a site distribution).
* ``all_site`` (``N_N + 4``): ``all``, then the same three features of the site.
* ``partial_all_site`` (``N_N + 7``): ``partial``, ``all``, then the site's three features.

Add an encoding by subclassing :class:`Encoding`, registering it in :data:`ENCODINGS` (config
validation reads this registry) and adding a ``fleet_torchrl/conf/state/<name>.yaml``.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..sim import C, D, Site, SiteState
from ..sim.fused import partial_features
from ..utils.checks import lookup


class Encoding:
    name: str = ""

    def size(self, site: Site) -> int:
        raise NotImplementedError

    def __call__(self, site: Site, s: SiteState) -> Tensor:
        raise NotImplementedError


def charger_time(site: Site, s: SiteState) -> Tensor:
    """``TC`` of MODEL §2 for every site: ``[B]`` float32."""
    return _charger_ticks(s).to(torch.float32) / (s.params.t_c + 1).to(torch.float32)


def _charger_ticks(s: SiteState) -> Tensor:
    """``ticks left + 1`` of the vehicle at C, 0 if C is empty: ``[B]`` int64."""
    return ((s.pos == C) * (s.left + 1)).sum(0)


def _inv_charge_span(t_c: Tensor) -> Tensor:
    """Each site's ``1 / (T_C + 1)``, the float32 of the double (cached while ``t_c`` is
    unchanged: sites keep their parameters for a whole episode)."""
    inv = lambda: (1.0 / (t_c.double() + 1.0)).float()  # noqa: E731
    if t_c.is_inference():  # (no version counter to tell a change)
        return inv()
    hit = _INV_CACHE.get(id(t_c))
    if hit is not None and hit[0] is t_c and hit[1] == t_c._version:
        return hit[2]
    inv = inv()
    if len(_INV_CACHE) > 64:
        _INV_CACHE.clear()
    _INV_CACHE[id(t_c)] = (t_c, t_c._version, inv)  # (holding t_c: its id stays its own)
    return inv


_INV_CACHE: dict[int, tuple[Tensor, int, Tensor]] = {}


class Partial(Encoding):
    name = "partial"

    def size(self, site: Site) -> int:
        return 3

    def __call__(self, site: Site, s: SiteState) -> Tensor:
        fast = partial_features(s)  # one compiled pass on the CPU (the same float32 values)
        if fast is not None:
            return fast
        soc = s.soc
        soc_d = (soc * (s.pos == D)).sum(0)
        others = torch.where(s.pos > C, soc, 100.0).amin(0)  # neither D (0) nor C (1)
        tc = _charger_ticks(s).to(torch.float32) * _inv_charge_span(s.params.t_c)
        # (a Python scalar multiplies a float32 tensor as its float32 value does)
        return torch.stack((soc_d * 0.01, others * 0.01, tc), dim=1)


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


class PartialSite(Encoding):
    """``partial`` plus three features of the site itself, each in [0, 1] and comparable
    across sites: fleet density ``N_V / N_N``, the closure probability ``p_c``, and the
    charge's share of a charge-and-lap cycle ``T_C / (T_C + N_N)`` (a lap is at least
    ``N_N`` ticks). On a site distribution they are each site's own draws: a policy that
    reads them can act differently on a crowded or a slow-charging site (the generalist)."""

    name = "partial_site"

    def size(self, site: Site) -> int:
        return 6

    def __call__(self, site: Site, s: SiteState) -> Tensor:
        return torch.cat((ENCODINGS["partial"](site, s), site_features(site, s)), dim=1)


class AllSite(Encoding):
    """``all`` plus the three site features of ``partial_site``: which vehicle comes next
    and how charged it is (what matters on a fast charger, docs/TRAINING.md section 14),
    on every site of a distribution."""

    name = "all_site"

    def size(self, site: Site) -> int:
        return site.n_nodes + 4

    def __call__(self, site: Site, s: SiteState) -> Tensor:
        return torch.cat((ENCODINGS["all"](site, s), site_features(site, s)), dim=1)


class PartialAllSite(Encoding):
    """``partial``, ``all`` and the site's three features: every node, and the summaries a
    network finds hard to compute from them (in ``all`` an empty node reads as an empty
    battery, so the lowest charge of the others is no minimum over its entries). For a
    generalist whose teacher reads every node (docs/TRAINING.md section 15)."""

    name = "partial_all_site"

    def size(self, site: Site) -> int:
        return site.n_nodes + 7

    def __call__(self, site: Site, s: SiteState) -> Tensor:
        return torch.cat((ENCODINGS["partial"](site, s), ENCODINGS["all"](site, s),
                          site_features(site, s)), dim=1)


def site_features(site: Site, s: SiteState) -> Tensor:
    """Each site's ``N_V / N_N``, ``p_c`` and ``T_C / (T_C + N_N)``: ``[B, 3]`` float32."""
    n = float(site.n_nodes)
    n_v = s.params.n_vehicles.to(torch.float32)
    p_c = s.params.p_c.to(torch.float32)
    t_c = s.params.t_c.to(torch.float32)
    return torch.stack((n_v / n, p_c, t_c / (t_c + n)), dim=1)


ENCODINGS: dict[str, Encoding] = {"partial": Partial(), "all": All(),
                                  "partial_site": PartialSite(), "all_site": AllSite(),
                                  "partial_all_site": PartialAllSite()}


def get_encoding(name: str) -> Encoding:
    return lookup(ENCODINGS, name, f"unknown state encoding {name!r}")
