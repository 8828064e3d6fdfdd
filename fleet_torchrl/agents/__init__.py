"""Learned agents (tabular Q-learning, DQN) and their saved-policy files.

A saved policy is one ``policy.pt`` (written atomically) holding a plain dict:
``format``, ``kind`` (``tabular`` | ``dqn``), ``encoding``, ``network`` (DQN), ``n_obs``,
``state_dict`` and ``meta`` (provenance). :func:`load_policy_file` turns it back into a
:class:`~fleet_torchrl.policies.Policy` usable by the evaluation protocol and the environment.
"""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path
from typing import Any

import torch

from ..config import Config, NetworkConfig
from ..policies import HeuristicPolicy, Policy, RulePolicy
from ..runinfo import atomic_write

FORMAT = "fleet_torchrl.policy/1"
POLICY_FILE = "policy.pt"


def run_name(cfg: Config) -> str:
    """Default name of a learned policy: ``tabular``, ``dqn_partial`` or ``dqn_all``."""
    return "tabular" if cfg.agent.name == "tabular" else f"dqn_{cfg.state.name}"


def default_policy_dir(cfg: Config) -> Path:
    if cfg.train.out_dir:
        return Path(cfg.train.out_dir)
    return Path(cfg.table.policies_dir) / run_name(cfg)


def save_policy(path: str | Path, policy: Policy, kind: str, n_obs: int,
                network: NetworkConfig | None = None, meta: dict[str, Any] | None = None) -> Path:
    bundle = {
        "format": FORMAT,
        "kind": kind,
        "encoding": policy.encoding,
        "n_obs": n_obs,
        "network": asdict(network) if network is not None else None,
        "state_dict": {k: v.detach().cpu() for k, v in policy.state_dict().items()},
        "meta": meta or {},
    }
    return atomic_write(path, lambda f: torch.save(bundle, f), mode="wb")


def load_policy_file(path: str | Path, device: str | torch.device = "cpu") -> Policy:
    """Rebuild a policy from ``policy.pt`` (or a folder holding one)."""
    path = Path(path)
    if path.is_dir():
        path = path / POLICY_FILE
    if not path.is_file():
        raise FileNotFoundError(f"no saved policy at {path}; train it first with `make policies` "
                                "or `make train ARGS=\"agent=... state=...\"`")
    try:
        bundle = torch.load(path, map_location=device, weights_only=True)
    except Exception as e:  # truncated or foreign file
        raise ValueError(
            f"{path} is not a readable policy file ({type(e).__name__}: {e})") from None
    if not isinstance(bundle, dict) or bundle.get("format") != FORMAT:
        raise ValueError(f"{path} is not a fleet_torchrl policy file (format {FORMAT} expected)")
    kind = bundle["kind"]
    if kind == "tabular":
        from .tabular import TabularQPolicy

        policy: Policy = TabularQPolicy()
    elif kind == "dqn":
        from .dqn import DQNPolicy, make_qnet

        net = NetworkConfig(**bundle["network"])
        policy = DQNPolicy(make_qnet(net, bundle["n_obs"]), bundle["encoding"])
        policy.name = f"dqn_{bundle['encoding']}"
    else:
        raise ValueError(f"{path}: unknown policy kind {kind!r}")
    try:
        policy.load_state_dict(bundle["state_dict"])
    except RuntimeError as e:
        raise ValueError(f"{path}: weights do not fit the {kind} policy ({e})") from None
    return policy.to(device).eval()


def load_policy(cfg: Config) -> Policy:
    """The saved policy named by ``cfg.agent.policy`` or the default location of its run."""
    path = Path(cfg.agent.policy) if cfg.agent.policy else default_policy_dir(cfg)
    policy = load_policy_file(path, cfg.eval.device)
    if policy.encoding != cfg.state.name:
        raise ValueError(f"{path} was trained on state={policy.encoding}, not "
                         f"state={cfg.state.name}")
    return policy


def load_policies(cfg: Config, names: list[str]) -> dict[str, Policy]:
    """Policies by name: ``rule`` and ``heuristic`` with their default parameters, learned ones
    from ``cfg.table.policies_dir/<name>/policy.pt``."""
    out: dict[str, Policy] = {}
    for name in names:
        if name == "rule":
            out[name] = RulePolicy()
        elif name == "heuristic":
            out[name] = HeuristicPolicy()
        else:
            out[name] = load_policy_file(Path(cfg.table.policies_dir) / name, cfg.eval.device)
            out[name].name = name
    return out
