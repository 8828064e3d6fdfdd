"""Config composition (every option of every group) and validation messages."""

from __future__ import annotations

import subprocess
import sys

import pytest

from fleet_torchrl.config import CONF_DIR, Config, ConfigError, compose_config


def group_options(group: str) -> list[str]:
    return sorted(p.stem for p in (CONF_DIR / group).glob("*.yaml"))


@pytest.mark.parametrize("group", ["site", "state", "agent", "eval", "mdp"])
def test_every_option_composes_and_validates(group):
    options = group_options(group)
    assert options, f"conf/{group} is empty"
    for opt in options:
        cfg = compose_config([f"{group}={opt}"])
        assert isinstance(cfg, Config)


def test_defaults_are_the_spec_values():
    cfg = compose_config([])
    s = cfg.site
    assert (s.n_nodes, s.n_vehicles, s.p_c, s.t_c, s.soc_low) == (15, 3, 0.8, 30, 30.0)
    assert (s.e_move, s.e_idle, s.e_charge, s.closed_node, s.xi) == (0.5, 0.02, 40.0, 9, 10.0)
    assert (cfg.mdp.p_f, cfg.mdp.p_q, cfg.mdp.gamma, cfg.mdp.tau_e) == (50.0, 1.0, 0.9, 3000)
    assert cfg.mdp.reward == "thesis"  # the throughput objective is an opt-in extension
    assert cfg.site.leave_when_full  # owner decision: the charger stops on a full battery
    assert cfg.agent.name == "rule" and cfg.agent.threshold == 40.0
    assert (cfg.eval.n_sims, cfg.eval.ticks) == (1000, 10000)


def test_site_variants():
    assert compose_config(["site=five_vehicles"]).site.n_vehicles == 5
    assert compose_config(["site=no_closure"]).site.p_c == 0.0
    slow = compose_config(["site=slow_charger"]).site
    assert slow.t_c == 50 and slow.e_charge == 40.0


@pytest.mark.parametrize("override, field", [
    ("site.n_vehicles=14", "site.n_vehicles"),
    ("site.n_vehicles=0", "site.n_vehicles"),
    ("site.p_c=1.5", "site.p_c"),
    ("site.p_c=-0.1", "site.p_c"),
    ("site.t_c=0", "site.t_c"),
    ("site.n_nodes=4", "site.n_nodes"),
    ("site.n_nodes=100", "site.n_nodes"),
    ("site.closed_node=2", "site.closed_node"),
    ("site.closed_node=15", "site.closed_node"),
    ("site.xi=80", "site.xi"),
    ("agent.threshold=101", "agent.threshold"),
    ("agent=heuristic agent.upper=-1", "agent.upper"),
    ("agent=heuristic agent.others_below=120", "agent.others_below"),
    ("state.name=foo", "state.name"),
    ("mdp.gamma=1.5", "mdp.gamma"),
    ("mdp.reward=trips", "mdp.reward"),
    ("mdp.gamma_tick=1.5", "mdp.gamma_tick"),
    ("mdp.rho=-0.1", "mdp.rho"),
    ("agent=dqn network.grad_clip=-1", "network.grad_clip"),
    ("objective.n_sites=0", "objective.n_sites"),
    ("objective.seed=-1", "objective.seed"),
    ("eval.n_sims=0", "eval.n_sims"),
    ("table.seeds=0", "table.seeds"),
    ("eval.backend=gpu", "eval.backend"),
    ("agent=dqn network.lr_decay=step", "network.lr_decay"),
    ("agent=dqn network.tau=1.5", "network.tau"),
    ("agent=dqn agent.n_steps=0", "agent.n_steps"),
    ("agent=dqn agent.reward_scale=0", "agent.reward_scale"),
    ("eval.device=gpu0", "eval.device"),
    ("train.select=queue", "train.select"),
    ("agent=search agent.elite=64", "agent.elite"),
    ("agent=search agent.policy_class=tree", "agent.policy_class"),
    ("agent=search agent.init=random", "agent.init"),
    ("agent=search agent.p_min=0.6", "agent.p_min"),
    ("agent=search agent.smoothing=0", "agent.smoothing"),
    ("agent=search agent.p_min=0.5", "agent.p_min"),
    ("sweep.planner_overrides=['agent=dqn']", "sweep.planner_overrides[0]"),
    ("+sweep.searches.search_x=['site.p_c=0.1']", "sweep.searches.search_x[0]"),
    ("+sweep.searches.mine=['agent.tc_bins=3']", "sweep.searches.mine"),
    ("sweep.improve=[nope]", "sweep.improve[0]"),
])
def test_bad_values_name_the_field(override, field):
    with pytest.raises(ConfigError) as e:
        compose_config(override.split())
    msg = str(e.value)
    assert msg.startswith(f"{field}=") and "allowed" in msg and "\n" not in msg


def test_typos_and_wrong_types_are_rejected_by_the_schema():
    from hydra.errors import ConfigCompositionException

    with pytest.raises(ConfigCompositionException, match="Could not override 'site.n_vehicle'"):
        compose_config(["site.n_vehicle=3"])
    with pytest.raises(ConfigCompositionException, match="site.n_vehicles=three"):
        compose_config(["site.n_vehicles=three"])


def test_cli_reports_one_line_error_and_exit_code(tmp_path):
    r = subprocess.run([sys.executable, "-m", "fleet_torchrl.evaluate", "site.p_c=2"],
                       capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert r.returncode == 2
    assert r.stderr.strip().splitlines()[-1] == "error: site.p_c=2.0 is invalid: allowed [0.0, 1.0]"


def test_unknown_keys_added_with_plus_are_rejected():
    with pytest.raises(ConfigError, match=r"^site.pc is not a setting of site \(allowed: "):
        compose_config(["+site.pc=0.5"])
    with pytest.raises(ConfigError, match="^train.eval_sim is not a setting of train"):
        compose_config(["+train.eval_sim=3"])


@pytest.mark.parametrize("override, expected", [
    ("site=nope", "error: In 'config': Could not find 'site/nope'; allowed in 'site': default, "
                  "five_vehicles, no_closure, randomized, slow_charger"),
    ("site.n_vehicles=abc", "error: Error merging override site.n_vehicles=abc: Value 'abc' of "
                            "type 'str' could not be converted to Integer"),
    ("agent=nope", "error: In 'config': Could not find 'agent/nope'; allowed in 'agent': dqn, "
                   "heuristic, imitation, planner, rule, search, tabular, threshold"),
    ("+site.pc=0.5", "error: site.pc is not a setting of site (allowed: closed_node, e_charge, "
                     "e_idle, e_move, leave_when_full, n_nodes, n_vehicles, name, p_c, ranges, "
                     "soc_low, t_c, xi)"),
])
def test_hydra_level_errors_are_one_line_with_exit_code_2(override, expected, tmp_path):
    r = subprocess.run([sys.executable, "-m", "fleet_torchrl.evaluate", override],
                       capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert r.returncode == 2, r.stderr
    assert r.stderr.strip().splitlines() == [expected]


@pytest.mark.parametrize("option", ["agent=schema_agent_rule", "agent=base_rule",
                                    "site=schema_site", "network=schema_network"])
def test_schemas_are_no_options(option):
    """The schemas the YAML options extend are stored outside the groups: choosing one is an
    unknown option, not a config with the schema's defaults."""
    from hydra.errors import MissingConfigException

    with pytest.raises(MissingConfigException, match="Could not find"):
        compose_config([option])


def test_help_lists_only_real_options():
    from fleet_torchrl.config import register_configs

    register_configs()
    r = subprocess.run([sys.executable, "-m", "fleet_torchrl.evaluate", "--help"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    groups = r.stdout.split("== Config ==")[0]
    assert "agent: dqn, heuristic, imitation, planner, rule, search, tabular, threshold" in groups
    assert "schema" not in groups and "base_" not in groups


def test_the_recipes_live_in_one_place():
    """The learned runs are the recipes group only: the table, its preview (make quick) and
    the benchmark read them; no schema or experiment carries its own list."""
    from fleet_torchrl.experiments.config import TableConfig

    cfg = compose_config([])
    assert list(cfg.recipes) == ["tabular", "dqn_partial", "dqn_all", "tabular_throughput",
                                 "dqn_partial_throughput", "imitation", "generalist",
                                 "search_crowded", "search_slow", "dqn_fast", "generalist_dqn",
                                 "search", "search_mlp"]
    assert not hasattr(TableConfig(), "train")
    quick = compose_config(["+experiment=quick"])
    assert quick.recipes == cfg.recipes and quick.table.preview and not cfg.table.preview
    for name in ("tabular", "dqn_partial", "search_mlp"):  # overrides mentioned in the docs
        assert cfg.recipes[name].overrides[0].startswith("agent=")
    text = (CONF_DIR / "experiment" / "quick.yaml").read_text()
    assert "agent=" not in text and "max_episodes" not in text


def test_some_of_the_recipes():
    cfg = compose_config(["table.only=[search,tabular]"])
    assert cfg.table.names(cfg.recipes) == ["tabular", "search"]  # the recipes' order
    assert compose_config([]).table.names(cfg.recipes) == list(cfg.recipes)


@pytest.mark.parametrize("override, field", [
    ("table.only=[nope]", "table.only[0]"),
    ("table.only=[]", "table.only"),
    ("recipes.tabular.overrides=[]", "recipes.tabular.overrides"),
    ("recipes.tabular.overrides=['seed=3']", "recipes.tabular.overrides[0]"),
    ("recipes.search.preview=['train.out_dir=x']", "recipes.search.preview[0]"),
    ("recipes.search.preview=['hydra.run.dir=x']", "recipes.search.preview[0]"),
])
def test_bad_recipes_and_table_selections_name_the_field(override, field):
    with pytest.raises(ConfigError) as e:
        compose_config([override])
    assert str(e.value).startswith(f"{field}=") and "allowed" in str(e.value)


def test_run_names_tell_runs_apart():
    from fleet_torchrl.store import policy_name

    def name(*over):
        cfg = compose_config(list(over))
        return policy_name(cfg)

    assert name("agent=tabular") == "tabular"
    assert name("agent=tabular", "mdp.reward=throughput") == "tabular_throughput"
    assert name("agent=dqn", "state=all") == "dqn_all"
    assert name("agent=search") == "search"
    assert name("agent=search", "mdp.reward=throughput") == "search"  # trips either way
    assert name("agent=search", "agent.policy_class=mlp") == "search_mlp"


# names that become parts of paths: run folders, policy names, sweep folders, figures
NAME_LONG = "a" * 65


@pytest.mark.parametrize("override, field", [
    ("site.name=../eval/default", "site.name"),
    ("site.name=/../../../../tmp/x", "site.name"),
    ("site.name=a/b", "site.name"),
    ("site.name=..", "site.name"),
    ("site.name=.hidden", "site.name"),
    ("site.name=a..b", "site.name"),
    ("site.name='a b'", "site.name"),
    ("site.name=-x", "site.name"),
    (f"site.name={NAME_LONG}", "site.name"),
    ("sweep.name=../x", "sweep.name"),
    ("sweep.name=x/y", "sweep.name"),
    ("sweep.name=.", "sweep.name"),
    (f"sweep.name={NAME_LONG}", "sweep.name"),
    ("maps.planner_sites=[../eval/default]", "maps.planner_sites[0]"),
    ("maps.planner_sites=[default,/etc/x]", "maps.planner_sites[1]"),
])
def test_names_that_become_path_parts_are_plain_names(override, field):
    with pytest.raises(ConfigError) as e:
        compose_config([override])
    msg = str(e.value)
    assert msg.startswith(f"{field}=") and "\n" not in msg, msg
    assert "allowed a name of letters, digits" in msg and "at most 64 characters" in msg, msg


def test_a_recipe_name_is_a_short_folder_name():
    from fleet_torchrl.experiments.config import Recipe, validate_recipes

    ok = {"r" * 64: Recipe(overrides=["agent=tabular"])}
    assert validate_recipes(ok, ("rule",)) == ok
    for bad, shown in (("r" * 65, "r" * 65), ("r" * 300, "r" * 40 + "... (300 characters)"),
                       ("../x", "../x"), ("a.b", "a.b")):
        with pytest.raises(ConfigError) as e:
            validate_recipes({bad: Recipe(overrides=["agent=tabular"])}, ("rule",))
        assert str(e.value).startswith(f"recipes.{shown} is invalid: allowed a name of ")
        assert "at most 64 characters" in str(e.value) and "\n" not in str(e.value)


def test_the_packaged_names_are_plain_names():
    """Every packaged site preset, recipe, sweep and map site passes the name check (and a
    user's own site name like the docs' my_site)."""
    from fleet_torchrl.utils.paths import is_name

    sites = group_options("site")
    assert {"default", "five_vehicles", "no_closure", "randomized", "slow_charger"} <= set(sites)
    for site in sites:
        assert compose_config([f"site={site}"]).site.name == site
    assert compose_config(["site.name=my_site"]).site.name == "my_site"
    cfg = compose_config([])
    assert all(is_name(n) for n in [*sites, *cfg.recipes, *cfg.maps.planner_sites])
    for sweep in ("pc", "tc", "nv"):
        assert compose_config([f"+experiment=sweep_{sweep}"]).sweep.name == sweep


def test_a_site_name_of_the_python_api_is_one_path_part():
    """In Python a site's name is a display name (``p_c=0.5``, ``sweep point``), still never
    more than one part of a path."""
    from fleet_torchrl.sim import SiteConfig

    for good in ("p_c=0.5", "sweep point", "default", "x" * 64):
        assert SiteConfig(name=good).name == good
    for bad in ("", "../x", "a/b", "a\\b", "..", ".x", "x" * 65, "a\nb", "a..b"):
        with pytest.raises(ConfigError) as e:
            SiteConfig(name=bad)
        assert str(e.value).startswith("site.name=") and "\n" not in str(e.value), bad


# The schemas whose fields check their own ranges in code (the fields' declarations are the
# rule, utils/checks.py: ranged), and the numeric fields checked in code by reason.
UNDECLARED_MODULES: dict[str, str] = {}
RANGE_IN_CODE = {
    ("TabularAgentConfig", "eps_end"): "its bound is eps_start",
    ("DQNAgentConfig", "eps_end"): "its bound is eps_start",
    ("NetworkConfig", "batch_size"): "its bound is buffer_size",
    ("SearchAgentConfig", "elite"): "its bound is population - 1",
    ("SearchAgentConfig", "sigma_init"): "null stands for the policy class's default",
    ("SearchAgentConfig", "sigma_min"): "its bound is sigma_init",
    ("ImitationAgentConfig", "beta_end"): "its bound is beta_start",
    ("ImitationAgentConfig", "iterate_from"): "its bound is rounds",
    ("ImitationAgentConfig", "batch_size"): "its bound is capacity",
    ("ImitationAgentConfig", "gap_floor"): "its bound is gap_cap",
    ("Config", "seed"): "the root's, checked by config.validate",
    ("SiteConfig", "n_vehicles"): "its bound is n_nodes - 2",
    ("SiteConfig", "closed_node"): "its bound is n_nodes - 1",
    ("SiteConfig", "xi"): "its bound is 100 - soc_low",
    ("SiteRanges", "n_vehicles"): "a [low, high] pair, bounded by the site's nodes",
    ("SiteRanges", "p_c"): "a [low, high] pair with low <= high",
    ("SiteRanges", "t_c"): "a [low, high] pair with low <= high",
    ("SweepConfig", "value"): "its bounds and kind are those of sweep.param",
}
NUMERIC = ("int", "float", "list[int]", "list[float]")


def _schemas() -> list[type]:
    """Every schema the root config registers, with the dataclasses nested in them."""
    from dataclasses import fields, is_dataclass

    from fleet_torchrl.agents.config import AGENT_SCHEMAS, NetworkConfig
    from fleet_torchrl.config import TOOL_SCHEMAS
    from fleet_torchrl.sim.config import SiteRanges

    roots = [Config, NetworkConfig, *AGENT_SCHEMAS.values(), *TOOL_SCHEMAS.values(), SiteRanges]
    roots += [f.default_factory for f in fields(Config)
              if is_dataclass(f.default_factory)]  # the groups: SiteConfig, TrainConfig, ...
    return list(dict.fromkeys(roots))


def test_every_numeric_field_declares_its_range_or_says_why_not():
    from dataclasses import fields

    from fleet_torchrl.utils.checks import declared_ranges

    schemas = [s for s in _schemas() if s.__module__ not in UNDECLARED_MODULES]
    names = {s.__name__ for s in schemas}
    assert {"SiteConfig", "MDPConfig", "TrainConfig", "EvalConfig", "SweepConfig",
            "BenchConfig", "SiteRanges", "Config"} <= names
    missing = []
    for schema in schemas:
        declared = declared_ranges(schema)
        for f in fields(schema):
            numeric = str(f.type).removesuffix(" | None") in NUMERIC
            if numeric and f.name not in declared and (schema.__name__, f.name) not in \
                    RANGE_IN_CODE:
                missing.append(f"{schema.__name__}.{f.name}")
    assert not missing, f"numeric fields without a declared range: {missing}"
    stale = [k for k in RANGE_IN_CODE if k[0] not in names or k[1] in declared_ranges(
        next(s for s in schemas if s.__name__ == k[0]))]
    assert not stale, f"RANGE_IN_CODE lists fields that declare a range: {stale}"


def test_validate_checks_every_declared_field():
    """Each schema's validate runs its fields' declarations: a field set out of its range
    after construction is refused by name."""
    from fleet_torchrl.utils.checks import declared_ranges

    checked = 0
    for schema in _schemas():
        for name, r in declared_ranges(schema).items():
            obj = schema()
            bad = "no-such-option" if r.choices is not None else float("nan")
            setattr(obj, name, [bad] if r.each else bad)
            with pytest.raises(ConfigError, match=rf"\.{name}(\[0\])?=.* is invalid: allowed "):
                obj.validate()
            checked += 1
    assert checked >= 40
