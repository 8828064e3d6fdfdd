"""Where policies are published and found: policy names, run folders, saved-policy lookup.

A training run publishes its policy under ``<table.policies_dir>/<name>/seed<s>/`` (``make
train`` and ``make table`` alike), ``name`` being unique to what was trained
(:func:`policy_name`: agent, state, objective, variant, site) and ``s`` its seed, so that no
run replaces the policy of another recipe or seed (and a folder that already holds one is
refused: :mod:`fleet_torchrl.training.publish`). Folders ``<name>/policy.pt`` of earlier
versions are still found. Evaluations and experiments find them
again by name (:func:`saved_policy_path`, :func:`load_policies`, :func:`make_policy`).
Every such path computed from a name stays inside ``table.policies_dir``: a policy folder
there that is a symbolic link out of it is neither read nor written unless
``table.follow_symlinks=true`` (:func:`inside`); ``agent.policy=<path>`` and
``train.out_dir=<path>`` name a place outside on purpose and are taken as they are.

This module sits above the agents and below the training and the root config, which it
never imports: a function takes what it reads, a run's settings (:class:`Run`, which a
:class:`~fleet_torchrl.training.spec.RunSpec` is) and the policies' folder, the device, the
symlink setting, each as an argument.
"""

from __future__ import annotations

import functools
import hashlib
import json
from dataclasses import asdict
from importlib import resources
from pathlib import Path
from typing import Protocol

import torch
import yaml

from .agents.base import Policy
from .agents.config import AgentConfig
from .agents.policy_files import POLICY_FILE
from .agents.registry import AGENTS, check_policy_fits_site, get_agent, load_policy_file
from .env.config import MDPConfig, StateConfig
from .sim import SiteConfig, SiteRanges
from .utils.paths import check_inside, is_name

# the packaged site presets, wherever in the package this module lives
_SITE_PRESETS = resources.files(__name__.split(".")[0]).joinpath("conf", "site")


class Run(Protocol):
    """What names a run's policy and what it is evaluated on: its site, state encoding,
    decision process and agent (a :class:`~fleet_torchrl.training.spec.RunSpec` is one)."""

    @property
    def site(self) -> SiteConfig: ...
    @property
    def state(self) -> StateConfig: ...
    @property
    def mdp(self) -> MDPConfig: ...
    @property
    def agent(self) -> AgentConfig: ...


def policy_name(cfg: Run) -> str:
    """Name of the policy a run of ``cfg`` makes, and so of the folder ``make train``
    publishes it to: one name per agent, state, objective and site, so that no run
    replaces the policy of another recipe (``tabular``, ``dqn_all_throughput``,
    ``search_mlp_five_vehicles``, ``dqn_partial_throughput_anchored_randomized``)."""
    spec = get_agent(cfg.agent.name)
    name = spec.name if spec.states is not None and len(spec.states) == 1 \
        else f"{spec.name}_{cfg.state.name}"
    # what else tells two runs apart: tabular vs tabular_throughput, search vs
    # search_mlp, then the site (a DQN of the site distribution is not the default
    # site's, whose folder it used to overwrite)
    return name + cfg.agent.run_suffix(cfg.mdp) + site_suffix(cfg.site)


@functools.cache
def site_preset(name: str) -> SiteConfig | None:
    """The site ``conf/site/<name>.yaml`` defines (its ``defaults`` chain followed), or None
    if the package has no such preset. Plain YAML, no Hydra (tests/agents/test_registry.py
    checks it against Hydra's composition). A name that is no plain name (``../eval/default``)
    names no preset."""
    if not is_name(name):
        return None
    path = _SITE_PRESETS.joinpath(f"{name}.yaml")
    if not path.is_file():
        return None
    node = yaml.safe_load(path.read_text()) or {}
    values: dict = {}
    for parent in node.pop("defaults", []):
        if parent == "_self_" or parent.startswith("/schema_"):
            continue
        base = site_preset(parent)
        if base is None:
            return None
        values.update(asdict(base))
    values.update(node)
    ranges = values.pop("ranges", None)
    return SiteConfig(**values, ranges=SiteRanges(**ranges) if ranges else None)


def site_suffix(site: SiteConfig) -> str:
    """What a policy name adds for the site it was trained on: nothing for the default site,
    ``_<preset>`` for a packaged preset as it stands (``_five_vehicles``, ``_randomized``),
    and ``_<name>-<8 hex digits of its settings>`` for any other site (a preset with a
    field changed, ``site.p_c=0.6``), which would otherwise publish into the folder of the
    preset's policy."""
    preset = site_preset(site.name)
    if preset is not None and preset == site:
        return "" if site.name == "default" else f"_{site.name}"
    fields = asdict(site)
    del fields["name"]
    digest = hashlib.sha256(json.dumps(fields, sort_keys=True).encode()).hexdigest()[:8]
    return f"_{site.name}-{digest}"


def site_label(site: SiteConfig) -> str:
    """How logs name a site: ``'<name>'`` for a preset as it stands (or a site the package
    has no preset of), ``'<name>' with p_c=0.5, t_c=20`` for a packaged preset with fields
    changed (each changed field as an override writes it; ``ranges.t_c=[20, 40]``)."""
    preset = site_preset(site.name)
    if preset is None or preset == site:
        return f"'{site.name}'"
    have, want = asdict(site), asdict(preset)
    changed = []
    for key, value in have.items():
        if key == "ranges" and value is not None and want[key] is not None:
            changed += [f"ranges.{k}={v}" for k, v in value.items() if v != want[key][k]]
        elif value != want[key]:
            changed.append(f"{key}={value}")
    return f"'{site.name}' with {', '.join(changed)}"


FOLLOW = "set table.follow_symlinks=true, or pass the policy as agent.policy=<path>"


def inside(root: str | Path, path: str | Path, follow_symlinks: bool = False) -> Path:
    """``path``, computed under the policies' folder ``root``, if it resolves inside it or
    ``follow_symlinks`` is set; else :class:`~fleet_torchrl.utils.checks.ConfigError`
    saying how to allow it."""
    return Path(path) if follow_symlinks else \
        check_inside("table.policies_dir", path, root, FOLLOW)


def seed_dir(root: str | Path, name: str, seed: int, follow_symlinks: bool = False) -> Path:
    """Folder of the policy ``name`` trained with ``seed`` (``make train`` and ``make table``
    publish there), inside ``root`` (:func:`inside`)."""
    return inside(root, Path(root) / name / f"seed{seed}", follow_symlinks)


def saved_policy_path(root: str | Path, name: str, follow_symlinks: bool = False) -> Path:
    """The saved policy a name stands for: ``<root>/<name>/policy.pt`` if there is one, else
    the policy of the lowest training seed, ``<root>/<name>/seed<k>/policy.pt``; inside
    ``root`` (:func:`inside`)."""
    folder = inside(root, Path(root) / name, follow_symlinks)
    if (folder / POLICY_FILE).is_file():
        return inside(root, folder / POLICY_FILE, follow_symlinks)
    seeds = sorted((int(p.parent.name[4:]), p) for p in folder.glob(f"seed*/{POLICY_FILE}")
                   if p.parent.name[4:].isdigit())
    return inside(root, seeds[0][1], follow_symlinks) if seeds else folder / POLICY_FILE


def make_policy(cfg: Run, device: str | torch.device, policies_dir: str | Path,
                follow_symlinks: bool = False, out_dir: str | Path | None = None) -> Policy:
    """The policy ``cfg.agent`` names, on ``device``: baselines from their config, learned
    ones from disk: ``agent.policy``, else ``out_dir`` (a training's ``train.out_dir``), else
    where its run published it under ``policies_dir`` (:func:`saved_policy_path`)."""
    spec = get_agent(cfg.agent.name)
    if not spec.trainable:
        return spec.make_policy(cfg.agent).to(device)
    if cfg.agent.policy:  # type: ignore[attr-defined]  (every learner's schema has it)
        path = Path(cfg.agent.policy)  # type: ignore[attr-defined]
    elif out_dir:
        path = Path(out_dir)
    else:  # <name>/policy.pt of earlier versions, else the lowest seed trained
        path = saved_policy_path(policies_dir, policy_name(cfg), follow_symlinks)
        other = site_suffix(cfg.site)
        if other and not path.is_file():  # names carry the site: say how to cross sites
            home = Path(policies_dir) / policy_name(cfg).removesuffix(other)
            raise FileNotFoundError(
                f"no saved policy at {path} (a policy trained on this site); to evaluate "
                f"one trained on another site here, pass agent.policy=<its folder>, "
                f"e.g. agent.policy={home}")
    policy = load_policy_file(path, device)
    if not isinstance(policy, spec.policy_class):
        raise ValueError(f"{path} holds a {type(policy).__name__}, not a policy of "
                         f"agent={spec.name}: pass the matching agent= with agent.policy=")
    if policy.encoding != cfg.state.name:
        raise ValueError(f"{path} was trained on state={policy.encoding}, not "
                         f"state={cfg.state.name}")
    check_policy_fits_site(policy, cfg.site, path)
    return policy


def load_policies(root: str | Path, names: list[str], device: str | torch.device,
                  follow_symlinks: bool = False) -> dict[str, Policy]:
    """Policies by name, on ``device``: baselines (``rule``, ``heuristic``) with their default
    parameters, learned ones from the policies' folder ``root`` (:func:`saved_policy_path`)."""
    out: dict[str, Policy] = {}
    for name in names:
        spec = AGENTS.get(name)
        if spec is not None and not spec.trainable:
            out[name] = spec.make_policy(spec.schema()).to(device)
        else:
            out[name] = load_policy_file(saved_policy_path(root, name, follow_symlinks),
                                         device)
            out[name].name = name
    return out


__all__ = ["Run", "inside", "load_policies", "make_policy", "policy_name", "saved_policy_path",
           "seed_dir", "site_preset", "site_suffix"]
