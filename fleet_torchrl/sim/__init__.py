"""The charging site, tick by tick (MODEL §1): pure torch, no TorchRL, no config framework.

``Site`` holds the tick rules for a batch of independent sites, ``SiteState`` their state,
``rng`` the counter-based common random numbers, ``SiteConfig`` the site's schema
(``SiteRanges`` a distribution of sites, whose per-site draws are ``SiteParams``). The schema
imports at once; the rest on first use (:mod:`fleet_torchrl.utils.lazy`: no torch for
``--help``).
"""

from typing import TYPE_CHECKING

from ..utils.lazy import lazy_exports
from .config import MAX_NODES, SiteConfig, SiteRanges

__getattr__, __dir__ = lazy_exports(__name__, {
    name: ".site" for name in ("BYPASS", "C", "D", "M", "Site", "SiteParams", "SiteState",
                               "TickOutcome")})

if TYPE_CHECKING:
    from .site import BYPASS, C, D, M, Site, SiteParams, SiteState, TickOutcome

__all__ = ["BYPASS", "C", "D", "M", "MAX_NODES", "Site", "SiteConfig", "SiteParams",
           "SiteRanges", "SiteState", "TickOutcome"]
