"""The site schema (MODEL §1): a plain dataclass with its own range checks."""

from __future__ import annotations

from dataclasses import dataclass

from ..utils.checks import (
    ConfigError,
    as_number,
    check_fields,
    check_range,
    coerce_schema,
    ranged,
    validate_on_init,
)
from ..utils.paths import check_label

MAX_NODES = 62  # occupancy of a site is one 64-bit mask


@dataclass
class SiteRanges:
    """A distribution of sites (MODEL §1.6): each parameter given as ``[low, high]`` is drawn
    per site, uniformly (integers: every value of the range equally likely), as a pure
    function of ``(seed, site index)``; a parameter left ``None`` keeps the site's value."""

    n_vehicles: list[int] | None = None  # N_V, integers in [1, n_nodes - 2]
    p_c: list[float] | None = None  # closure probability in [0, 1]
    t_c: list[int] | None = None  # T_C, integers >= 1

    def __post_init__(self) -> None:
        validate_on_init(self)

    def validate(self, site: SiteConfig | None = None, path: str = "site.ranges"
                 ) -> SiteRanges:
        """Each range ``[low, high]`` within its parameter's bounds (``n_vehicles``: those of
        ``site``'s nodes; without a site, of the largest site)."""
        n_nodes = site.n_nodes if site is not None else MAX_NODES
        bounds = {"n_vehicles": (1, n_nodes - 2), "p_c": (0.0, 1.0), "t_c": (1, 100_000)}
        for name, (lo, hi) in bounds.items():
            r = getattr(self, name)
            if r is None:
                continue
            if not isinstance(r, (list, tuple)) or len(r) != 2 or \
                    any(as_number(v) is None for v in r):
                raise ConfigError(f"{path}.{name}={r!r} is invalid: allowed [low, high] "
                                  "with low <= high, or null (the site's own value)")
            # an integer parameter takes integers, not floats (3.0 would reach torch's
            # integer draws as a float)
            if name != "p_c" and not all(isinstance(as_number(v), int) for v in r):
                raise ConfigError(f"{path}.{name}={list(r)} is invalid: allowed integers")
            for k, v in enumerate(r):
                check_range(f"{path}.{name}[{k}]", v, lo, hi)
            if r[0] > r[1]:
                raise ConfigError(f"{path}.{name}={list(r)} is invalid: allowed [low, high] "
                                  "with low <= high, or null (the site's own value)")
        return self

    def varied(self) -> list[str]:
        """The names of the parameters that are drawn."""
        return [n for n in ("n_vehicles", "p_c", "t_c") if getattr(self, n) is not None]


@dataclass
class SiteConfig:
    """The site model of MODEL §1. Defaults are the model's (this project's calibration)."""

    name: str = "default"
    # N_N: 0=D decision, 1=C charger, 2=B bypass, 3=M merge, 4..N_N-1 road
    n_nodes: int = ranged(15, 5, MAX_NODES,
                          allowed=f"[5, {MAX_NODES}] (site occupancy is a 64-bit mask)")
    n_vehicles: int = 3  # N_V
    p_c: float = ranged(0.8, 0.0, 1.0)  # probability that the closed node X is closed in a tick
    t_c: int = ranged(30, 1, 100_000)  # T_C: charging ticks per charge
    soc_low: float = ranged(30.0, 0.0, 100.0)  # SoC_low: any soc below this after a tick fails
    e_move: float = ranged(0.5, 0.0, 100.0)  # energy lost by a vehicle that moves in a tick
    # energy lost by a vehicle that waits (and is not charging)
    e_idle: float = ranged(0.02, 0.0, 100.0)
    # energy of one full charge (E_charge / T_C per charging tick)
    e_charge: float = ranged(40.0, 0.0, 100.0)
    closed_node: int = 9  # X, a road node
    xi: float = 10.0  # initial soc ~ U[soc_low + xi, 100]
    leave_when_full: bool = True  # a charging vehicle that reaches soc 100 stops charging
    ranges: SiteRanges | None = None  # a site distribution (site=randomized); None = one site

    def __post_init__(self) -> None:
        validate_on_init(self)

    @classmethod
    def coerce(cls, value: SiteConfig | dict | None, path: str = "site") -> SiteConfig:
        """``value`` as a validated site: a :class:`SiteConfig` (checked as it stands now: it
        may have been changed since it was built), a dict of its fields (``ranges`` a dict
        too; what ``gymnasium.make(..., site={...})`` passes) or None (the default site)."""

        def from_dict(values: dict) -> SiteConfig:
            ranges = values.get("ranges")
            if isinstance(ranges, dict):
                bad = sorted(str(k) for k in ranges if k not in ("n_vehicles", "p_c", "t_c"))
                if bad:
                    raise ConfigError(f"{path}.ranges.{bad[0]} is not a setting of "
                                      f"{path}.ranges (allowed: n_vehicles, p_c, t_c)")
                values["ranges"] = SiteRanges(**ranges)
            return cls(**values)

        return coerce_schema(cls, value, path, from_dict)

    @property
    def max_vehicles(self) -> int:
        """Vehicles per site in the state tensors: ``n_vehicles``, or the top of its range."""
        r = self.ranges
        return r.n_vehicles[1] if r is not None and r.n_vehicles is not None else self.n_vehicles

    @property
    def randomized(self) -> bool:
        return self.ranges is not None and bool(self.ranges.varied())

    def validate(self, path: str = "site") -> SiteConfig:
        """Raise :class:`~fleet_torchrl.utils.checks.ConfigError` naming the first bad field.
        The name may become part of a path (policy names, run folders): one part, never
        ``/`` or ``..`` (the root config asks more of ``site.name``: a plain name)."""
        check_label(f"{path}.name", self.name)
        check_fields(self, path)
        check_range(f"{path}.n_vehicles", self.n_vehicles, 1, self.n_nodes - 2,
                    allowed=f"[1, n_nodes - 2 = {self.n_nodes - 2}] (vehicles start on distinct "
                            "nodes other than C)")
        check_range(f"{path}.xi", self.xi, 0.0, 100.0 - self.soc_low,
                    allowed=f"[0, 100 - soc_low = {100.0 - self.soc_low}]")
        check_range(f"{path}.closed_node", self.closed_node, 4, self.n_nodes - 1,
                    allowed=f"a road node in [4, n_nodes - 1 = {self.n_nodes - 1}]")
        if self.ranges is not None:
            if not isinstance(self.ranges, SiteRanges):
                raise ConfigError(f"{path}.ranges={self.ranges!r} is invalid: allowed a "
                                  "SiteRanges or null")
            self.ranges.validate(self, f"{path}.ranges")
        return self


def site_bytes(site: SiteConfig) -> int:
    """Memory of one simulated site in flight, on the high side: its state and parameters,
    the per-site counters of a run, and the transient tensors of its initial draw (one
    value per node) and of a kernel call (measured: about 500 bytes for the default site in
    an evaluation, 800 in the environment). What :mod:`fleet_torchrl.utils.resources`
    multiplies by the sites a setting asks for."""
    return 400 + 24 * site.n_nodes + 64 * site.max_vehicles
