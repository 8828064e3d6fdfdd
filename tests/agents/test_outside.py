"""Agents from outside the package (docs/ADD_A_POLICY.md): an installed package's entry point,
or a user's conf/agent YAML naming its schema class, adds a policy that evaluates."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from fleet_torchrl.agents.config import AGENT_SCHEMAS, ENTRY_POINT_GROUP
from fleet_torchrl.config import ConfigError, compose_config

ROOT = Path(__file__).resolve().parents[2]

# a baseline written outside the package: its schema (no torch) and its policy
SCHEMA = '''
from dataclasses import dataclass
from typing import ClassVar

from fleet_torchrl.agents.schema import AgentConfig
from fleet_torchrl.utils.checks import ranged


@dataclass
class {cls}(AgentConfig):
    """Charge when the vehicle at D is at most ``below`` percent full."""

    name: str = "{name}"
    below: float = ranged(30.0, 0.0, 100.0)
    policy_type: ClassVar[str] = "{module}.policy:LowPolicy"
'''
POLICY = '''
import torch

from fleet_torchrl.agents import Policy


class LowPolicy(Policy):
    name = "{name}"
    encoding = "partial"

    def __init__(self, below: float = 30.0) -> None:
        super().__init__()
        self.below = below

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return (obs[..., 0] <= self.below / 100.0).long()
'''


def write_package(root: Path, module: str, name: str, cls: str = "LowConfig",
                  entry_point: bool = True) -> Path:
    """The package ``module`` under ``root``: a schema, a policy and, with ``entry_point``,
    the metadata an installation writes (``<module>-0.1.dist-info``)."""
    pkg = root / module
    pkg.mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "config.py").write_text(SCHEMA.format(cls=cls, name=name, module=module))
    (pkg / "policy.py").write_text(POLICY.format(name=name))
    if entry_point:
        info = root / f"{module}-0.1.dist-info"
        info.mkdir()
        (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {module}\nVersion: 0.1\n")
        (info / "entry_points.txt").write_text(
            f"[{ENTRY_POINT_GROUP}]\n{name} = {module}.config:{cls}\n")
    return pkg


def rule_trips(threshold: float, n_sims: int, ticks: int) -> list[float]:
    """What the packaged rule makes, charging at ``threshold`` percent or below."""
    from fleet_torchrl.agents import RulePolicy
    from fleet_torchrl.evaluation.protocol import simulate
    from fleet_torchrl.sim import SiteConfig

    return simulate(RulePolicy(threshold), SiteConfig(), n_sims, ticks, 0)["trips"].tolist()


@pytest.mark.slow
def test_an_installed_package_adds_a_policy_that_evaluates(tmp_path):
    """``pip install`` of a package with an entry point in ``fleet_torchrl.agents`` is all it
    takes: ``agent=<name>`` composes (no YAML), evaluates, and its records are those of the
    rule at the same threshold (a hand check of its decisions), not the default rule's."""
    write_package(tmp_path / "site-packages", "charge_low", "charge_low")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(tmp_path / "site-packages"), str(ROOT), os.environ.get("PYTHONPATH", "")])}
    out = tmp_path / "low.json"
    r = subprocess.run([sys.executable, "-m", "fleet_torchrl.evaluate", "agent=charge_low",
                        "agent.below=30", "eval.n_sims=4", "eval.ticks=300",
                        "eval.progress=false", f"eval.out={out}"],
                       capture_output=True, text=True, timeout=300, cwd=tmp_path, env=env)
    assert r.returncode == 0, r.stderr[-2000:]
    result = json.loads(out.read_text())
    assert result["policy"] == "charge_low" and result["n_sims"] == 4
    assert result["records"]["trips"] == rule_trips(30.0, 4, 300)
    assert result["records"]["trips"] != rule_trips(40.0, 4, 300)
    # a bad value of its own field is refused by its own check, in one line
    r = subprocess.run([sys.executable, "-m", "fleet_torchrl.evaluate", "agent=charge_low",
                        "agent.below=120"], capture_output=True, text=True, timeout=300,
                       cwd=tmp_path, env=env)
    assert r.returncode == 2
    assert r.stderr.strip().splitlines() == [
        "error: agent.below=120.0 is invalid: allowed [0.0, 100.0]"]


@pytest.fixture
def user_agent(tmp_path, monkeypatch):
    """A working directory with a module beside its conf/ and a YAML naming its schema."""
    write_package(tmp_path, "my_low", "my_low", cls="MyLowConfig", entry_point=False)
    (tmp_path / "conf" / "agent").mkdir(parents=True)
    (tmp_path / "conf" / "agent" / "low20.yaml").write_text(
        "_schema_: my_low.config:MyLowConfig\nbelow: 20.0\n")
    monkeypatch.chdir(tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path))
    yield tmp_path
    from fleet_torchrl.agents.registry import AGENTS

    AGENT_SCHEMAS.pop("my_low", None)
    AGENTS.pop("my_low", None)
    for m in [m for m in sys.modules if m.split(".")[0] == "my_low"]:
        del sys.modules[m]


def test_a_user_yaml_naming_its_schema_adds_a_policy(user_agent):
    from fleet_torchrl.evaluation.protocol import simulate
    from fleet_torchrl.sim import SiteConfig
    from fleet_torchrl.store import make_policy

    cfg = compose_config(["agent=low20"])
    assert type(cfg.agent).__name__ == "MyLowConfig" and cfg.agent.name == "my_low"
    assert cfg.agent.below == 20.0  # the YAML's value over the schema's default
    assert compose_config(["agent=low20", "agent.below=25"]).agent.below == 25.0
    policy = make_policy(cfg, "cpu", cfg.table.policies_dir)
    assert type(policy).__name__ == "LowPolicy" and policy.below == 20.0
    trips = simulate(policy, SiteConfig(), 4, 300, 0)["trips"].tolist()
    assert trips == rule_trips(20.0, 4, 300)


def test_a_user_yaml_is_checked_by_its_schema(user_agent):
    with pytest.raises(ConfigError, match=r"^agent\.belo is not a setting of agent "
                                          r"\(allowed: below, name\)$"):
        compose_config(["agent=low20", "+agent.belo=3"])
    with pytest.raises(ConfigError, match=r"agent\.below=101\.0 is invalid"):
        compose_config(["agent=low20", "agent.below=101"])
    with pytest.raises(ConfigError, match=r"^agent\.below='abc' is invalid: Value 'abc' of "
                                          r"type 'str' could not be converted to Float$"):
        compose_config(["agent=low20", "agent.below=abc"])
    (user_agent / "conf" / "agent" / "gone.yaml").write_text("_schema_: my_low.nowhere:X\n")
    with pytest.raises(ConfigError, match=r"gone\.yaml: _schema_='my_low\.nowhere:X' cannot "
                                          r"be imported: No module named 'my_low\.nowhere'"):
        compose_config(["agent=low20"])
