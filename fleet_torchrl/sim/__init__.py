"""The charging site, tick by tick (MODEL §1): pure torch, no TorchRL, no config framework.

``Site`` holds the tick rules for a batch of independent sites, ``SiteState`` their state,
``rng`` the counter-based common random numbers, ``SiteConfig`` the site's schema.
"""

from .config import MAX_NODES, SiteConfig
from .site import BYPASS, C, D, M, Site, SiteState, TickOutcome

__all__ = ["BYPASS", "C", "D", "M", "MAX_NODES", "Site", "SiteConfig", "SiteState",
           "TickOutcome"]
