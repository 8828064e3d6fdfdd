"""Fixtures shared by the whole suite (tests request them by name; nothing imports this)."""

from __future__ import annotations

import pytest
import torch

from fleet_torchrl.config import register_configs
from fleet_torchrl.sim import Site, SiteConfig, SiteState

register_configs()  # tests that call Hydra's compose directly need the schemas


@pytest.fixture(autouse=True)
def _no_launching_pid(monkeypatch):
    """Every test starts without ``FLEET_TORCHRL_RUN_PID``, and what a multirun run in this
    process sets there (``config.mark_multirun``) is undone after it: left set, it would name
    a later test's run folders after this process instead of their own command's."""
    from fleet_torchrl.config import RUN_PID

    monkeypatch.delenv(RUN_PID, raising=False)


@pytest.fixture
def site() -> Site:
    """The default site on the CPU."""
    return Site(SiteConfig())


@pytest.fixture
def make_state():
    """Builder of one site from ``(node, soc[, charging ticks left])`` per vehicle."""

    def build(vehicles: list[tuple], charge: bool = False, tick: int = 0,
              site: Site | None = None) -> SiteState:
        pos = torch.tensor([[v[0]] for v in vehicles], dtype=torch.int64)
        soc = torch.tensor([[float(v[1])] for v in vehicles], dtype=torch.float32)
        left = torch.tensor([[v[2] if len(v) > 2 else 0] for v in vehicles], dtype=torch.int64)
        site = site or Site(SiteConfig(n_vehicles=len(vehicles)))
        return site.state(
            pos, soc, left, torch.tensor([charge]), torch.tensor([tick]))

    return build


@pytest.fixture
def saved_policies(tmp_path):
    """Untrained saved policies ``tabular``, ``dqn_partial``, ``search``, ``imitation``,
    ``generalist`` (imitation on ``partial_site``) and ``generalist_dqn`` (an anchored DQN)
    under ``tmp_path/policies`` (enough for the plumbing of experiments
    that load policies by name)."""
    from fleet_torchrl.agents import save_policy
    from fleet_torchrl.agents.dqn import DQNPolicy, NetworkConfig
    from fleet_torchrl.agents.tabular import TabularQPolicy

    root = tmp_path / "policies"
    save_policy(root / "tabular" / "policy.pt", TabularQPolicy(), "tabular")
    net = NetworkConfig(width=8, depth=1)
    save_policy(root / "dqn_partial" / "policy.pt", DQNPolicy(net, 3, "partial"), "dqn")
    from fleet_torchrl.agents.search import SearchPolicy

    save_policy(root / "search" / "policy.pt", SearchPolicy("table"), "search")
    save_policy(root / "generalist_dqn" / "policy.pt",
                DQNPolicy(net, 3, "partial", "heuristic", 1.0), "dqn")
    from fleet_torchrl.agents.imitation import ImitationPolicy

    save_policy(root / "imitation" / "policy.pt", ImitationPolicy(3, "partial", 8, 1),
                "imitation")
    save_policy(root / "generalist" / "policy.pt", ImitationPolicy(6, "partial_site", 8, 1),
                "imitation")
    return root


@pytest.fixture
def command(monkeypatch):
    """Run a command's entry point (``fleet_torchrl.<command>.main``, what its console script
    calls) in this process with ``args`` as its command line; returns its exit code."""
    import logging
    import sys

    def run(main, *args: str) -> int:
        monkeypatch.setattr(sys, "argv", ["fleet-command", *args])
        # Hydra's job logging gives the root logger handlers on this test's (captured) stderr;
        # left there, a later test's log lines go to a closed stream
        root = logging.getLogger()
        handlers, level = list(root.handlers), root.level
        try:
            main()
        except SystemExit as e:
            return int(e.code or 0)
        finally:
            root.handlers[:] = handlers
            root.setLevel(level)
        return 0

    return run
