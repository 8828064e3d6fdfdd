"""The site schema (MODEL §1): a plain dataclass with its own range checks."""

from __future__ import annotations

from dataclasses import dataclass

from ..utils.checks import check_range

MAX_NODES = 62  # occupancy of a site is one 64-bit mask


@dataclass
class SiteConfig:
    """The site model of MODEL §1. Defaults are the model's (this project's calibration)."""

    name: str = "default"
    n_nodes: int = 15  # N_N: 0=D decision, 1=C charger, 2=B bypass, 3=M merge, 4..N_N-1 road
    n_vehicles: int = 3  # N_V
    p_c: float = 0.8  # probability that the closed node X is closed in a tick
    t_c: int = 30  # T_C: charging ticks per charge
    soc_low: float = 30.0  # SoC_low: any soc below this after a tick fails the site
    e_move: float = 0.5  # energy lost by a vehicle that moves in a tick
    e_idle: float = 0.02  # energy lost by a vehicle that waits (and is not charging)
    e_charge: float = 40.0  # energy of one full charge (E_charge / T_C per charging tick)
    closed_node: int = 9  # X, a road node
    xi: float = 10.0  # initial soc ~ U[soc_low + xi, 100]
    leave_when_full: bool = True  # a charging vehicle that reaches soc 100 stops charging

    def validate(self, path: str = "site") -> SiteConfig:
        """Raise :class:`~fleet_torchrl.utils.checks.ConfigError` naming the first bad field."""
        check_range(f"{path}.n_nodes", self.n_nodes, 5, MAX_NODES,
                    allowed=f"[5, {MAX_NODES}] (site occupancy is a 64-bit mask)")
        check_range(f"{path}.n_vehicles", self.n_vehicles, 1, self.n_nodes - 2,
                    allowed=f"[1, n_nodes - 2 = {self.n_nodes - 2}] (vehicles start on distinct "
                            "nodes other than C)")
        check_range(f"{path}.p_c", self.p_c, 0.0, 1.0)
        check_range(f"{path}.t_c", self.t_c, 1, 100_000)
        check_range(f"{path}.soc_low", self.soc_low, 0.0, 100.0)
        check_range(f"{path}.xi", self.xi, 0.0, 100.0 - self.soc_low,
                    allowed=f"[0, 100 - soc_low = {100.0 - self.soc_low}]")
        check_range(f"{path}.e_move", self.e_move, 0.0, 100.0)
        check_range(f"{path}.e_idle", self.e_idle, 0.0, 100.0)
        check_range(f"{path}.e_charge", self.e_charge, 0.0, 100.0)
        check_range(f"{path}.closed_node", self.closed_node, 4, self.n_nodes - 1,
                    allowed=f"a road node in [4, n_nodes - 1 = {self.n_nodes - 1}]")
        return self
