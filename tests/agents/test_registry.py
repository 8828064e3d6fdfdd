"""The agent registry: every entry is complete, and a new learner plugs in with one entry."""

from __future__ import annotations

from dataclasses import dataclass

import pytest
import torch
from hydra.core.config_store import ConfigStore

from fleet_torchrl.agents import (
    AGENTS,
    AgentConfig,
    AgentSpec,
    Learner,
    Policy,
    load_policy_file,
    register,
)
from fleet_torchrl.agents.config import AGENT_SCHEMAS, BUILTIN_SCHEMAS
from fleet_torchrl.config import CONF_DIR, ConfigError, compose_config
from fleet_torchrl.evaluate import policy_of
from fleet_torchrl.store import policy_name


def test_every_agent_has_a_config_file_and_a_schema():
    """The package's own agents each have their packaged YAML (and every packaged YAML is
    one of them); an agent added from outside (an entry point, a user's conf/agent, a
    register call) needs none, so it does not fail this test."""
    assert {p.stem for p in (CONF_DIR / "agent").glob("*.yaml")} == set(BUILTIN_SCHEMAS)
    for name in BUILTIN_SCHEMAS:
        spec = AGENTS[name]
        cfg = compose_config([f"agent={name}"])
        assert isinstance(cfg.agent, spec.schema) and cfg.agent.name == name
    for name, spec in AGENTS.items():
        assert issubclass(spec.policy_class, Policy), name
        assert (spec.make_policy is None) != (spec.make_learner is None), name
    assert {n for n, s in AGENTS.items() if s.trainable} >= {"tabular", "dqn"}
    assert {n for n, s in AGENTS.items() if not s.trainable} >= {"rule", "heuristic"}


def test_run_names_follow_the_accepted_states():
    assert policy_name(compose_config(["agent=tabular"])) == "tabular"
    assert policy_name(compose_config(["agent=dqn", "state=all"])) == "dqn_all"


# a learner written outside the package: one schema, one policy, one learner, one entry
@dataclass
class FloorAgentConfig(AgentConfig):
    name: str = "floor"
    num_sites: int = 4
    policy: str | None = None


class FloorPolicy(Policy):
    name = "floor"

    def __init__(self) -> None:
        super().__init__()
        self.register_buffer("threshold", torch.tensor(0.0))

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return (obs[..., 0] <= self.threshold).long()


class FloorLearner(Learner):
    """Charges below the lowest soc_D it has seen (learns something checkable)."""

    steps_per_round = 6

    def __init__(self) -> None:
        super().__init__()
        self.greedy = FloorPolicy()
        self.greedy.threshold.fill_(1.0)
        self.frames = 0

    def act(self, td):
        return td.set("action", self.greedy(td["observation"]))

    def observe(self, td, learn):
        self.frames += int(learn.sum())
        seen = td["observation"][learn][:, 0]
        if seen.numel():
            self.greedy.threshold.copy_(torch.minimum(self.greedy.threshold, seen.min()))

    def update(self):
        return {"loss/td": 0.0}

    def policy(self):
        return self.greedy

    def exploration(self):
        return 0.0


@pytest.fixture
def floor_agent():
    spec = register(AgentSpec("floor", FloorAgentConfig, FloorPolicy,
                              make_learner=lambda ctx: FloorLearner()))
    ConfigStore.instance().store(group="agent", name="floor", node=FloorAgentConfig)
    yield spec
    del AGENTS["floor"]
    AGENT_SCHEMAS.pop("floor", None)


def test_a_new_learner_trains_saves_and_evaluates_through_the_registry(tmp_path,
                                                                       floor_agent):
    from fleet_torchrl.training import RunSpec, Trainer

    cfg = compose_config(["agent=floor", "train.max_episodes=8", "train.eval_every=1",
                          "train.eval_sims=8", "train.eval_ticks=200", "train.progress=false",
                          "train.tensorboard=false", f"train.out_dir={tmp_path / 'pol'}"])
    trainer = Trainer(RunSpec.of(cfg), tmp_path / "run")
    summary = trainer.run()
    assert summary["name"] == "floor_partial" and summary["rounds"] == 2
    assert summary["frames"] == trainer.learner.frames == 2 * 6 * 4  # every step learned from
    saved = load_policy_file(tmp_path / "pol")
    assert isinstance(saved, FloorPolicy)
    assert 0.3 <= float(saved.threshold) < 1.0  # a soc_D it saw, not the initial 1.0
    cfg = compose_config(["agent=floor", f"agent.policy={tmp_path / 'pol'}"])
    assert isinstance(policy_of(cfg), FloorPolicy)


def test_a_policy_file_of_another_agent_is_refused(tmp_path):
    """agent=tabular with a DQN's policy file must not be evaluated and labelled tabular."""
    from fleet_torchrl.agents import save_policy
    from fleet_torchrl.agents.dqn import DQNPolicy, NetworkConfig

    save_policy(tmp_path / "dqn" / "policy.pt", DQNPolicy(NetworkConfig(width=4, depth=1), 3,
                                                          "partial"), "dqn")
    cfg = compose_config(["agent=tabular", f"agent.policy={tmp_path / 'dqn'}"])
    with pytest.raises(ValueError, match="holds a DQNPolicy, not a policy of agent=tabular"):
        policy_of(cfg)
    ok = compose_config(["agent=dqn", f"agent.policy={tmp_path / 'dqn'}"])
    assert isinstance(policy_of(ok), DQNPolicy)


def test_names_carry_the_objective_and_make_table_policies_are_found(tmp_path):
    from fleet_torchrl.agents import save_policy
    from fleet_torchrl.agents.tabular import TabularQPolicy

    thr = compose_config(["agent=dqn", "mdp.reward=throughput"])
    assert policy_name(thr) == "dqn_partial_throughput"
    # make table saves per seed: evaluating agent=tabular finds the lowest seed's policy
    save_policy(tmp_path / "tabular" / "seed1" / "policy.pt", TabularQPolicy(), "tabular")
    cfg = compose_config(["agent=tabular", f"table.policies_dir={tmp_path}"])
    assert isinstance(policy_of(cfg), TabularQPolicy)


def test_the_makefile_timing_wrapper_exists():
    import importlib
    import re

    from fleet_torchrl.config import CONF_DIR

    makefile = (CONF_DIR.parents[1] / "Makefile").read_text()
    module = re.search(r"^TIMED\s*:=\s*\$\(PY\) -m (\S+)", makefile, re.M).group(1)
    assert callable(importlib.import_module(module).main)


def test_site_presets_read_without_hydra_are_the_composed_sites():
    """:func:`site_preset` reads conf/site/*.yaml itself (the registry sits below the config
    layer); it must give exactly the site Hydra composes, or names would drift."""
    from fleet_torchrl.store import site_preset

    names = sorted(p.stem for p in (CONF_DIR / "site").glob("*.yaml"))
    assert {"default", "five_vehicles", "randomized"} <= set(names)
    for name in names:
        assert site_preset(name) == compose_config([f"site={name}"]).site, name
    assert site_preset("nowhere") is None


@pytest.mark.parametrize("overrides, name", [
    (["agent=tabular"], "tabular"),
    (["agent=tabular", "mdp.reward=throughput"], "tabular_throughput"),
    (["agent=dqn", "state=all"], "dqn_all"),
    (["agent=dqn", "mdp.reward=throughput"], "dqn_partial_throughput"),
    (["agent=dqn", "mdp.reward=throughput", "agent.anchor=heuristic"],
     "dqn_partial_throughput_anchored"),
    (["agent=dqn", "site=randomized", "mdp.reward=throughput"],
     "dqn_partial_throughput_randomized"),
    (["agent=dqn", "site=randomized", "mdp.reward=throughput", "agent.anchor=heuristic"],
     "dqn_partial_throughput_anchored_randomized"),
    (["agent=dqn", "site=randomized", "state=partial_site"], "dqn_partial_site_randomized"),
    (["agent=search", "site=five_vehicles"], "search_five_vehicles"),
    (["agent=search", "agent.policy_class=mlp", "site=slow_charger"],
     "search_mlp_slow_charger"),
    (["agent=search", "mdp.reward=throughput"], "search"),  # it maximises trips anyway
    # budgets and network settings are the same recipe trained longer or wider
    (["agent=dqn", "state=all", "network.width=128", "train.max_episodes=99"], "dqn_all"),
])
def test_run_names_say_agent_state_objective_and_site(overrides, name):
    cfg = compose_config(overrides)
    assert policy_name(cfg) == name


def test_a_changed_site_field_gets_its_own_name():
    """``site.p_c=0.6`` is not the default site: its policy must not land in ``search/``."""
    def name(*o):
        cfg = compose_config(["agent=search", *o])
        return policy_name(cfg)

    a, b = name("site.p_c=0.6"), name("site.p_c=0.7")
    assert a.startswith("search_default-") and b.startswith("search_default-") and a != b
    assert name("site.p_c=0.6") == a  # a pure function of the settings
    assert name("site.p_c=0.8") == "search"  # the default's own value: the default site
    five = name("site=five_vehicles", "site.p_c=0.6")
    assert five.startswith("search_five_vehicles-") and five != "search_five_vehicles"
    assert name("site=randomized", "site.ranges.t_c=[20,40]").startswith("search_randomized-")
    # a preset with the default's values under another name is still named for its preset
    assert name("site=five_vehicles", "site.n_vehicles=3") != "search"


def test_evaluating_on_another_site_says_how(tmp_path):
    from fleet_torchrl.agents import save_policy
    from fleet_torchrl.agents.tabular import TabularQPolicy

    save_policy(tmp_path / "tabular" / "policy.pt", TabularQPolicy(), "tabular")
    cfg = compose_config(["agent=tabular", "site=five_vehicles",
                          f"table.policies_dir={tmp_path}"])
    with pytest.raises(FileNotFoundError, match=r"tabular_five_vehicles.*agent\.policy=.*"
                                                r"tabular$"):
        policy_of(cfg)
    cfg = compose_config(["agent=tabular", "site=five_vehicles",
                          f"agent.policy={tmp_path / 'tabular'}"])
    assert isinstance(policy_of(cfg), TabularQPolicy)


def test_site_label_names_a_preset_and_the_fields_changed_from_it():
    from fleet_torchrl.sim import SiteConfig, SiteRanges
    from fleet_torchrl.store import site_label, site_preset

    assert site_label(SiteConfig()) == "'default'"
    assert site_label(site_preset("five_vehicles")) == "'five_vehicles'"
    assert site_label(SiteConfig(p_c=0.5, t_c=20)) == "'default' with p_c=0.5, t_c=20"
    assert site_label(SiteConfig(name="mine", p_c=0.5)) == "'mine'"  # no packaged preset
    randomized = site_preset("randomized")
    narrowed = SiteConfig(name="randomized", ranges=SiteRanges(
        n_vehicles=randomized.ranges.n_vehicles, p_c=randomized.ranges.p_c, t_c=[20, 40]))
    assert site_label(narrowed) == "'randomized' with ranges.t_c=[20, 40]"


def test_a_site_preset_is_found_by_name_only():
    """``site_preset`` reads conf/site/<name>.yaml for a plain name only: a name that walks
    out of conf/site (another group's YAML, an absolute path) names no preset."""
    from fleet_torchrl.store import site_preset

    assert site_preset("five_vehicles") is not None
    for bad in ("../eval/default", "../site/default", "/etc/hostname", "..", ".hidden", ""):
        assert site_preset(bad) is None, bad


def _linked_policies(tmp_path):
    """``results/policies`` whose ``tabular`` is a symbolic link to a folder outside it."""
    from fleet_torchrl.agents import save_policy
    from fleet_torchrl.agents.tabular import TabularQPolicy

    save_policy(tmp_path / "elsewhere" / "tabular" / "policy.pt", TabularQPolicy(), "tabular")
    root = tmp_path / "results" / "policies"
    root.mkdir(parents=True)
    (root / "tabular").symlink_to(tmp_path / "elsewhere" / "tabular")
    return root


def test_a_policy_folder_linked_out_of_the_policies_is_not_followed(tmp_path):
    """A policy folder under ``table.policies_dir`` that is a symbolic link out of it is
    neither read (evaluation, the experiments' policies by name) nor written (training) unless
    ``table.follow_symlinks=true``; ``agent.policy=<path>`` reads it as named."""
    from fleet_torchrl.agents.tabular import TabularQPolicy
    from fleet_torchrl.store import load_policies, saved_policy_path
    from fleet_torchrl.train import publish_folder

    root = _linked_policies(tmp_path)
    cfg = compose_config(["agent=tabular", f"table.policies_dir={root}"])
    for call in (lambda: policy_of(cfg), lambda: load_policies(root, ["tabular"], "cpu"),
                 lambda: saved_policy_path(root, "tabular"), lambda: publish_folder(cfg)):
        with pytest.raises(ConfigError, match="outside .*table.follow_symlinks=true") as e:
            call()
        assert "\n" not in str(e.value) and str(tmp_path / "elsewhere") in str(e.value)
    ok = compose_config(["agent=tabular", f"table.policies_dir={root}",
                         "table.follow_symlinks=true"])
    assert isinstance(policy_of(ok), TabularQPolicy)
    assert isinstance(load_policies(root, ["tabular"], "cpu", True)["tabular"], TabularQPolicy)
    assert publish_folder(ok) == root / "tabular" / "seed0"
    named = compose_config(["agent=tabular", f"agent.policy={root / 'tabular'}"])
    assert isinstance(policy_of(named), TabularQPolicy)


def test_a_seed_or_policy_file_linked_out_is_not_followed_but_a_linked_root_is(tmp_path):
    """The check is of every computed path under the root: a seed folder or a policy file
    that is a link out is refused too; the policies' folder itself may be a link (the user
    named it), and links that stay inside it are followed."""
    from fleet_torchrl.agents import save_policy
    from fleet_torchrl.agents.tabular import TabularQPolicy
    from fleet_torchrl.store import saved_policy_path, seed_dir

    save_policy(tmp_path / "out" / "policy.pt", TabularQPolicy(), "tabular")
    root = tmp_path / "policies"
    (root / "seeded").mkdir(parents=True)
    (root / "seeded" / "seed0").symlink_to(tmp_path / "out")
    (root / "filed").mkdir()
    (root / "filed" / "policy.pt").symlink_to(tmp_path / "out" / "policy.pt")
    for name in ("seeded", "filed"):
        with pytest.raises(ConfigError, match="table.follow_symlinks"):
            saved_policy_path(root, name)
    with pytest.raises(ConfigError, match="table.follow_symlinks"):
        seed_dir(root, "seeded", 0)
    assert saved_policy_path(root, "seeded", follow_symlinks=True).is_file()
    save_policy(root / "real" / "policy.pt", TabularQPolicy(), "tabular")
    (root / "alias").symlink_to(root / "real")  # inside: followed
    assert saved_policy_path(root, "alias") == root / "alias" / "policy.pt"
    (tmp_path / "linked_root").symlink_to(root)
    assert saved_policy_path(tmp_path / "linked_root", "real").is_file()
    with pytest.raises(ConfigError):  # a name that walks out (never a plain name)
        saved_policy_path(root, "../out")
