"""Typed configuration: dataclass schemas, Hydra ConfigStore registration and validation.

Every YAML file under ``conf/`` extends one of the schemas below (``defaults: [base_X, _self_]``),
so a typo in a field name or a wrong type is rejected by Hydra when the config is composed.
Range checks that Hydra cannot express live in :func:`validate`; each failure raises
:class:`ConfigError` with a one-line message naming the field, its value and what is allowed.

This module does not import Hydra at import time: the simulator and the environment use the
dataclasses directly, without any configuration framework.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from omegaconf import MISSING, DictConfig, OmegaConf


class ConfigError(ValueError):
    """A configuration value outside its allowed range (message names the field)."""


# --------------------------------------------------------------------------- schemas
@dataclass
class SiteConfig:
    """The site model of SPEC §1. Defaults are the SPEC's (this project's calibration)."""

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


@dataclass
class StateConfig:
    """State encoding seen by the agents (SPEC §2): ``partial`` (3 features) or ``all``."""

    name: str = "partial"


@dataclass
class MDPConfig:
    """The decision process of SPEC §2."""

    tau_e: int = 3000  # episode tick budget (truncation)
    p_f: float = 50.0  # cost of a failure tick
    p_q: float = 1.0  # cost of a queue tick
    gamma: float = 0.9  # discount
    r_trip: float = 0.0  # reward per completed trip; 0 = SPEC §2 (an extension, see docs)


@dataclass
class AgentConfig:
    name: str = MISSING


@dataclass
class RuleAgentConfig(AgentConfig):
    """Benchmark: charge iff soc_D <= threshold."""

    name: str = "rule"
    threshold: float = 40.0


@dataclass
class HeuristicAgentConfig(AgentConfig):
    """Queue-aware baseline: charge early when the charger is free and the vehicle at D is the
    emptiest one (and below ``upper``); otherwise follow the rule with ``threshold``."""

    name: str = "heuristic"
    threshold: float = 40.0
    upper: float = 60.0
    others_below: float = 100.0  # charge early only if another vehicle is this low; 100 = off


@dataclass
class TabularAgentConfig(AgentConfig):
    """Tabular Q-learning on the discretised ``partial`` state (SPEC §3)."""

    name: str = "tabular"
    num_sites: int = 64  # sites simulated in parallel; one round = one episode per site
    k: float = 100.0  # learning rate k / (t + k), t = visits of the state-action pair
    eps_start: float = 1.0  # epsilon of the first episode
    eps_end: float = 0.3  # epsilon_min
    eps_decay_episodes: int = 40  # episodes (per site) over which epsilon decays to eps_end
    policy: str | None = None  # saved policy for evaluation (default results/policies/tabular)


@dataclass
class DQNAgentConfig(AgentConfig):
    """Deep Q-learning on TorchRL (SPEC §3); the network is the ``network`` group."""

    name: str = "dqn"
    num_sites: int = 8  # sites simulated in parallel; a round resets them all
    steps_per_round: int = 450  # decisions per site and round (one tau_e episode is ~350)
    eps_start: float = 1.0
    eps_end: float = 0.05
    eps_decay_frames: int = 250_000  # frames (decisions, all sites) to anneal epsilon
    double_dqn: bool = False
    prioritized: bool = False  # prioritized replay (alpha 0.6, beta 0.4)
    updates_per_round: int = 400  # gradient steps after each collected round
    policy: str | None = None  # saved policy for evaluation (default results/policies/dqn_<state>)


@dataclass
class NetworkConfig:
    """Q-network and its optimisation (SPEC §3 table; grid-searched by ``make grid``)."""

    name: str = "partial"
    depth: int = 3  # hidden layers
    width: int = 32  # units per hidden layer
    lr: float = 1e-3  # Adam learning rate
    weight_decay: float = 0.01  # Adam L2 regularisation
    batch_size: int = 64
    buffer_size: int = 50_000
    target_update: int = 500  # gradient steps between hard target-network copies
    grad_clip: float = 0.0  # max gradient norm per step; 0 = no clipping


@dataclass
class TrainConfig:
    """Training schedule, periodic evaluation, early stopping, checkpoints, logging."""

    max_episodes: int = 10_000  # N_E: budget of rounds x num_sites (one episode per site/round)
    eval_every: int = 2  # rounds between evaluations of the greedy policy
    eval_sims: int = 200  # evaluation sites (fixed common random numbers)
    eval_ticks: int = 3000
    eval_seed: int = 1_000_003  # distinct from the final evaluation's seed
    patience: int = 15  # evaluations without improvement before stopping (0 = never stop)
    checkpoint_every: int = 5  # rounds between checkpoints
    out_dir: str | None = None  # best policy goes here; default results/policies/<run name>
    device: str = "cpu"
    threads: int = 0  # torch CPU threads; 0 = torch's default
    tensorboard: bool = True
    progress: bool = True


@dataclass
class EvalConfig:
    """Evaluation protocol of SPEC §4 (thesis: 1000 simulations x 10 000 ticks)."""

    n_sims: int = 1000
    ticks: int = 10000
    seed: int = 0
    out: str | None = None  # result JSON path; the per-simulation CSV is written beside it
    device: str = "cpu"
    chunk: int = 256  # ticks of closure draws generated at once
    progress: bool = True


@dataclass
class TableConfig:
    """``make table``: train what is missing, then evaluate all policies (SPEC §5 item 1)."""

    out: str = "results/table"
    policies_dir: str = "results/policies"
    runs_dir: str = "outputs/table"  # Hydra run folders of the trainings (logs, checkpoints)
    retrain: bool = False  # train again even when a saved policy exists
    evaluate: bool = True  # false: only make sure the policies exist (make policies)
    # extra overrides of each training run (the learned policies and their budgets)
    train: dict[str, list[str]] = field(default_factory=lambda: {
        "tabular": ["agent=tabular", "state=partial", "train.max_episodes=7000",
                    "train.patience=40"],
        "dqn_partial": ["agent=dqn", "state=partial", "agent.double_dqn=true",
                        "train.max_episodes=1600", "train.patience=40"],
        "dqn_all": ["agent=dqn", "state=all", "agent.double_dqn=true",
                    "train.max_episodes=1440", "train.patience=40"],
    })


@dataclass
class SweepConfig:
    """One point of a generalisation sweep (SPEC §5 item 3): all policies on a changed site."""

    name: str = "pc"  # sweep name: results/sweeps/<name>.{csv,json,png}
    param: str = "p_c"  # site field varied: p_c | t_c | n_vehicles
    value: float = 0.8  # the point evaluated by this job
    out: str = "results/sweeps"
    policies: list[str] = field(default_factory=lambda: [
        "rule", "heuristic", "tabular", "dqn_partial", "dqn_all"])


SWEEP_PARAMS = ("p_c", "t_c", "n_vehicles")


@dataclass
class MapsConfig:
    """Policy maps (SPEC §5 item 2) of saved policies on the ``partial`` state."""

    out: str = "results/policy_maps"
    policies: list[str] = field(default_factory=lambda: [
        "rule", "heuristic", "tabular", "dqn_partial"])


@dataclass
class ObjectiveConfig:
    """``python -m fleet_torchrl.objective``: the MDP's reward per decision next to trips."""

    n_sites: int = 200  # one episode of mdp.tau_e ticks per site
    seed: int = 7  # training-style sites (rng.training_seed), apart from both eval sets
    out: str = "results/objective"


@dataclass
class Config:
    site: SiteConfig = field(default_factory=SiteConfig)
    state: StateConfig = field(default_factory=StateConfig)
    mdp: MDPConfig = field(default_factory=MDPConfig)
    agent: Any = MISSING
    network: NetworkConfig = field(default_factory=NetworkConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    table: TableConfig = field(default_factory=TableConfig)
    sweep: SweepConfig = field(default_factory=SweepConfig)
    maps: MapsConfig = field(default_factory=MapsConfig)
    objective: ObjectiveConfig = field(default_factory=ObjectiveConfig)
    seed: int = 0
    resume: bool = False


AGENT_SCHEMAS: dict[str, type] = {
    "rule": RuleAgentConfig,
    "heuristic": HeuristicAgentConfig,
    "tabular": TabularAgentConfig,
    "dqn": DQNAgentConfig,
}


def register_configs() -> None:
    """Register the schemas in Hydra's ConfigStore (idempotent)."""
    from hydra.core.config_store import ConfigStore

    cs = ConfigStore.instance()
    cs.store(name="base_config", node=Config)
    cs.store(group="site", name="base_site", node=SiteConfig)
    cs.store(group="state", name="base_state", node=StateConfig)
    cs.store(group="mdp", name="base_mdp", node=MDPConfig)
    cs.store(group="eval", name="base_eval", node=EvalConfig)
    cs.store(group="network", name="base_network", node=NetworkConfig)
    cs.store(group="train", name="base_train", node=TrainConfig)
    for name, schema in AGENT_SCHEMAS.items():
        cs.store(group="agent", name=f"base_{name}", node=schema)


# ------------------------------------------------------------------------ validation
def _fmt(v: Any) -> str:
    return repr(v) if isinstance(v, str) else f"{v}"


def check_range(path: str, value: Any, lo: float | None = None, hi: float | None = None,
                allowed: str | None = None) -> None:
    """Raise :class:`ConfigError` unless ``lo <= value <= hi`` (and finite)."""
    bad = value is None or (isinstance(value, float) and not math.isfinite(value))
    bad = bad or (lo is not None and value < lo) or (hi is not None and value > hi)
    if bad:
        if allowed is None:
            lo_s = "-inf" if lo is None else _fmt(lo)
            hi_s = "inf" if hi is None else _fmt(hi)
            allowed = f"[{lo_s}, {hi_s}]"
        raise ConfigError(f"{path}={_fmt(value)} is invalid: allowed {allowed}")


def check_choice(path: str, value: Any, choices: tuple[str, ...] | list[str]) -> None:
    if value not in choices:
        raise ConfigError(f"{path}={_fmt(value)} is invalid: allowed one of {', '.join(choices)}")


def validate_site(s: SiteConfig, path: str = "site") -> SiteConfig:
    check_range(f"{path}.n_nodes", s.n_nodes, 5, 62,
                allowed="[5, 62] (site occupancy is a 64-bit mask)")
    check_range(f"{path}.n_vehicles", s.n_vehicles, 1, s.n_nodes - 2,
                allowed=f"[1, n_nodes - 2 = {s.n_nodes - 2}] (vehicles start on distinct nodes "
                        "other than C)")
    check_range(f"{path}.p_c", s.p_c, 0.0, 1.0)
    check_range(f"{path}.t_c", s.t_c, 1, 100_000)
    check_range(f"{path}.soc_low", s.soc_low, 0.0, 100.0)
    check_range(f"{path}.xi", s.xi, 0.0, 100.0 - s.soc_low,
                allowed=f"[0, 100 - soc_low = {100.0 - s.soc_low}]")
    check_range(f"{path}.e_move", s.e_move, 0.0, 100.0)
    check_range(f"{path}.e_idle", s.e_idle, 0.0, 100.0)
    check_range(f"{path}.e_charge", s.e_charge, 0.0, 100.0)
    check_range(f"{path}.closed_node", s.closed_node, 4, s.n_nodes - 1,
                allowed=f"a road node in [4, n_nodes - 1 = {s.n_nodes - 1}]")
    return s


def validate_device(path: str, device: str) -> None:
    import torch

    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError):
        raise ConfigError(
            f"{path}={_fmt(device)} is invalid: allowed cpu, cuda, cuda:N, mps") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f"{path}={_fmt(device)} is invalid: CUDA is not available here; use cpu")
    if dev.type not in ("cpu", "cuda", "mps"):
        raise ConfigError(f"{path}={_fmt(device)} is invalid: allowed cpu, cuda, cuda:N, mps")


def validate_agent(a: Any, path: str = "agent") -> Any:
    name = getattr(a, "name", None)
    check_choice(f"{path}.name", name, tuple(AGENT_SCHEMAS))
    if name in ("rule", "heuristic"):
        check_range(f"{path}.threshold", a.threshold, 0.0, 100.0)
    if name == "heuristic":
        check_range(f"{path}.upper", a.upper, 0.0, 100.0)
        check_range(f"{path}.others_below", a.others_below, 0.0, 100.0)
    if name in ("tabular", "dqn"):
        check_range(f"{path}.eps_start", a.eps_start, 0.0, 1.0)
        check_range(f"{path}.eps_end", a.eps_end, 0.0, a.eps_start,
                    allowed=f"[0, eps_start = {a.eps_start}]")
    if name in ("tabular", "dqn"):
        check_range(f"{path}.num_sites", a.num_sites, 1, 1_000_000)
    if name == "tabular":
        check_range(f"{path}.k", a.k, 1e-9, None, allowed="> 0")
        check_range(f"{path}.eps_decay_episodes", a.eps_decay_episodes, 1, None)
    if name == "dqn":
        check_range(f"{path}.eps_decay_frames", a.eps_decay_frames, 1, None)
        check_range(f"{path}.steps_per_round", a.steps_per_round, 1, None)
        check_range(f"{path}.updates_per_round", a.updates_per_round, 0, None)
    return a


def validate_network(n: NetworkConfig, path: str = "network") -> NetworkConfig:
    check_range(f"{path}.depth", n.depth, 0, 64)
    check_range(f"{path}.width", n.width, 1, 65_536)
    check_range(f"{path}.lr", n.lr, 1e-12, 1.0, allowed="(0, 1]")
    check_range(f"{path}.weight_decay", n.weight_decay, 0.0, 10.0)
    check_range(f"{path}.batch_size", n.batch_size, 1, n.buffer_size,
                allowed=f"[1, buffer_size = {n.buffer_size}]")
    check_range(f"{path}.buffer_size", n.buffer_size, 1, 100_000_000)
    check_range(f"{path}.target_update", n.target_update, 1, None)
    check_range(f"{path}.grad_clip", n.grad_clip, 0.0, None)
    return n


def validate_train(t: TrainConfig, path: str = "train") -> TrainConfig:
    check_range(f"{path}.max_episodes", t.max_episodes, 1, None)
    check_range(f"{path}.eval_every", t.eval_every, 1, None)
    check_range(f"{path}.eval_sims", t.eval_sims, 1, 10**7)
    check_range(f"{path}.eval_ticks", t.eval_ticks, 1, 10**8)
    check_range(f"{path}.eval_seed", t.eval_seed, 0, 2**32 - 1)
    check_range(f"{path}.patience", t.patience, 0, None)
    check_range(f"{path}.checkpoint_every", t.checkpoint_every, 1, None)
    check_range(f"{path}.threads", t.threads, 0, 1024)
    validate_device(f"{path}.device", t.device)
    return t


def validate(cfg: Config) -> Config:
    """Check every range; raise :class:`ConfigError` naming the first bad field."""
    validate_site(cfg.site)
    from .encodings import ENCODINGS  # the registry (imported late: it imports the simulator)

    check_choice("state.name", cfg.state.name, tuple(ENCODINGS))
    check_range("mdp.tau_e", cfg.mdp.tau_e, 1, 10**9)
    check_range("mdp.p_f", cfg.mdp.p_f, 0.0, None)
    check_range("mdp.p_q", cfg.mdp.p_q, 0.0, None)
    check_range("mdp.gamma", cfg.mdp.gamma, 0.0, 1.0)
    check_range("mdp.r_trip", cfg.mdp.r_trip, 0.0, None)
    validate_agent(cfg.agent)
    if cfg.agent.name == "tabular" and cfg.state.name != "partial":
        raise ConfigError(f"state.name={cfg.state.name!r} is invalid for agent=tabular: "
                          "allowed partial (the tabular state discretises it)")
    validate_network(cfg.network)
    validate_train(cfg.train)
    check_range("eval.n_sims", cfg.eval.n_sims, 1, 10**8)
    check_range("eval.ticks", cfg.eval.ticks, 1, 10**9)
    check_range("eval.seed", cfg.eval.seed, 0, 2**32 - 1)
    check_range("eval.chunk", cfg.eval.chunk, 1, 1_000_000)
    validate_device("eval.device", cfg.eval.device)
    check_range("seed", cfg.seed, 0, 2**32 - 1)
    check_choice("sweep.param", cfg.sweep.param, SWEEP_PARAMS)
    check_range("objective.n_sites", cfg.objective.n_sites, 1, 10**7)
    check_range("objective.seed", cfg.objective.seed, 0, 2**32 - 1)
    known = ("rule", "heuristic", *cfg.table.train.keys())
    for i, name in enumerate(cfg.sweep.policies):
        check_choice(f"sweep.policies[{i}]", name, known)
    for i, name in enumerate(cfg.maps.policies):
        check_choice(f"maps.policies[{i}]", name, known)
    return cfg


CONF_DIR = Path(__file__).resolve().parents[1] / "conf"


def compose_config(overrides: list[str] | tuple[str, ...] = ()) -> Config:
    """The validated config that ``conf/config.yaml`` plus ``overrides`` composes to.

    Works inside a running Hydra app (which has already initialised Hydra) and outside one.
    """
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    register_configs()
    if GlobalHydra.instance().is_initialized():
        return to_config(compose(config_name="config", overrides=list(overrides)))
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return to_config(compose(config_name="config", overrides=list(overrides)))


def to_config(cfg: DictConfig | Config) -> Config:
    """Turn a composed Hydra config into validated dataclasses."""
    if isinstance(cfg, DictConfig):
        obj = OmegaConf.to_object(cfg)
    else:
        obj = cfg
    if not isinstance(obj, Config):  # composed without the schema (e.g. plain YAML in a test)
        raise ConfigError("config was not composed from the 'base_config' schema")
    return validate(obj)
