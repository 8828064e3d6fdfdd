"""The run spec: everything that decides what one training or evaluation computes.

A :class:`RunSpec` is the site, the state encoding, the decision process, the agent, its
network, the training schedule and the seed of one run, typed and validated. The commands
and the experiment launchers build it once, at their boundary, from the config they composed
(:meth:`RunSpec.of`); the library (the trainer, its checkpoints, the published policies, the
policy store) takes a spec and the few explicit arguments a spec does not hold (the run
folder, whether to resume, where to publish). The library never composes a config itself.
No torch here: a command builds its spec before it imports the heavy packages.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Any

from ..agents.config import AgentConfig, NetworkConfig
from ..env.config import MDPConfig, StateConfig
from ..sim.config import SiteConfig
from .config import TrainConfig

# the groups of the root config a spec holds (besides the seed)
SPEC_GROUPS = ("site", "state", "mdp", "agent", "network", "train")


@dataclass(frozen=True)
class RunSpec:
    """One run's resolved settings (see the module docstring). Frozen: a spec is replaced
    (:func:`dataclasses.replace`), never changed in place; its groups are copies, shared
    with no config."""

    site: SiteConfig
    state: StateConfig
    mdp: MDPConfig
    agent: AgentConfig
    network: NetworkConfig
    train: TrainConfig
    seed: int

    @classmethod
    def of(cls, cfg: Any) -> RunSpec:
        """The spec of a validated root config (:class:`fleet_torchrl.config.Config`, or
        anything with its seven attributes), its groups deep-copied."""
        return cls(**{g: copy.deepcopy(getattr(cfg, g)) for g in SPEC_GROUPS},
                   seed=int(cfg.seed))


__all__ = ["SPEC_GROUPS", "RunSpec"]
