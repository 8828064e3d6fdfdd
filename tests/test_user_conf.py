"""The users' own config folder: YAML in ./conf extends the packaged groups, no flag needed."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path

import pytest

from fleet_torchrl.config import compose_config

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def user_conf(tmp_path, monkeypatch):
    """A working directory with a conf/ of a site variant, an agent preset, an experiment,
    recipes, and a file named like a packaged option."""
    files = {
        "site/crowded.yaml": "defaults: [default, _self_]\nname: crowded\nn_vehicles: 5\n"
                             "p_c: 0.5\n",
        "site/default.yaml": "name: default\nn_vehicles: 7\n",  # the package's name: not read
        "agent/dqn_single.yaml": "defaults: [dqn, _self_]\ndouble_dqn: false\n",
        "experiment/short.yaml": "# @package _global_\ndefaults:\n  - override /agent: tabular\n"
                                 "train:\n  max_episodes: 512\n",
        "recipes/mine.yaml": "defaults: [default, _self_]\nwide:\n  overrides: [agent=dqn, "
                             "state=all, network.width=256]\n",
    }
    for name, text in files.items():
        path = tmp_path / "conf" / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    monkeypatch.chdir(tmp_path)
    return tmp_path


def test_user_configs_extend_the_packaged_groups(user_conf):
    cfg = compose_config(["site=crowded", "agent=dqn_single"])
    assert (cfg.site.name, cfg.site.n_vehicles, cfg.site.p_c, cfg.site.t_c) == (
        "crowded", 5, 0.5, 30)  # the rest from the packaged default site
    assert cfg.agent.name == "dqn" and cfg.agent.double_dqn is False
    assert cfg.agent.n_steps == 3  # the packaged dqn preset underneath
    short = compose_config(["+experiment=short"])
    assert short.agent.name == "tabular" and short.train.max_episodes == 512
    mine = compose_config(["recipes=mine", "table.only=[wide,search]"])
    assert mine.recipes["wide"].overrides[-1] == "network.width=256"
    assert mine.table.names(mine.recipes) == ["search", "wide"]
    assert compose_config([]).site.n_vehicles == 3  # a packaged name stays the package's


def test_a_misspelt_field_in_a_user_config_is_rejected(user_conf):
    from hydra.errors import ConfigCompositionException

    (user_conf / "conf" / "site" / "typo.yaml").write_text("name: typo\nn_vehicle: 4\n")
    with pytest.raises(ConfigCompositionException):
        compose_config(["site=typo"])


def test_help_lists_the_users_options(user_conf):
    r = subprocess.run([sys.executable, "-m", "fleet_torchrl.evaluate", "--help"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    own = r.stdout.split("Your own, from ./conf")[1].split("== Config ==")[0]
    assert "site: crowded" in own and "agent: dqn_single" in own
    assert "experiment: short" in own and "recipes: mine" in own
    assert "default" not in own  # shadowed by the package: not an option of yours


def test_without_a_conf_folder_nothing_changes(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    r = subprocess.run([sys.executable, "-m", "fleet_torchrl.evaluate", "--help"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and "Your own" not in r.stdout
    assert "not available" not in r.stderr  # no warning about the absent ./conf


def test_the_committed_example_site(monkeypatch):
    monkeypatch.chdir(ROOT)
    cfg = compose_config(["site=my_site"])
    default = dataclasses.asdict(compose_config([]).site)
    changed = {k: v for k, v in dataclasses.asdict(cfg.site).items() if default[k] != v}
    assert changed == {"name": "my_site", "n_vehicles": 4, "p_c": 0.6}
    assert "site/my_site.yaml" in (ROOT / "conf" / "README.md").read_text()
