"""Every experiment config composes; cluster launcher configs are documented."""

from __future__ import annotations

import pytest
import yaml
from hydra import compose, initialize_config_dir

from fleet_torchrl.config import CONF_DIR, to_config

EXPERIMENTS = sorted(p.stem for p in (CONF_DIR / "experiment").glob("*.yaml"))


@pytest.mark.parametrize("name", EXPERIMENTS)
def test_every_experiment_config_composes(name):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        dcfg = compose(config_name="config", overrides=[f"+experiment={name}"],
                       return_hydra_config=True)
        # typed validation; ${hydra:...} resolves only inside a run
        extra = ["train.out_dir=null"] if name == "grid" else []
        cfg = to_config(compose(config_name="config",
                                overrides=[f"+experiment={name}", *extra]))
    if name.startswith("sweep_"):
        assert cfg.eval.n_sims == 500 and cfg.eval.ticks == 10_000
        assert dcfg.hydra.launcher._target_.endswith("JoblibLauncher")
        assert dcfg.hydra.launcher.n_jobs == 2
        values = str(dcfg.hydra.sweeper.params["sweep.value"]).split(",")
        assert len(values) >= 5 and cfg.sweep.name == name.removeprefix("sweep_")


def test_cluster_launcher_configs_are_documented():
    for name, base in (("slurm", "submitit_slurm"), ("ray_cluster", "ray")):
        text = (CONF_DIR / "hydra" / "launcher" / f"{name}.yaml").read_text()
        assert text.startswith("#") and f"hydra/launcher={name}" in text
        assert yaml.safe_load(text)["defaults"] == [base]


def _plugin(name: str) -> bool:
    import importlib.util

    return importlib.util.find_spec(name) is not None


LAUNCHERS = [
    ("local", "JoblibLauncher", "hydra_plugins.hydra_joblib_launcher"),
    ("slurm", "SlurmLauncher", "hydra_plugins.hydra_submitit_launcher"),
    ("submitit_local", "LocalLauncher", "hydra_plugins.hydra_submitit_launcher"),
    ("ray_cluster", "RayLauncher", "hydra_plugins.hydra_ray_launcher"),
]
# what installs each launcher plugin (pyproject.toml: a dependency, or an extra)
PLUGIN_INSTALL = {
    "hydra_plugins.hydra_joblib_launcher": "a dependency: pip install -e .",
    "hydra_plugins.hydra_submitit_launcher": "the cluster extra: pip install -e '.[cluster]'",
    "hydra_plugins.hydra_ray_launcher": "the ray extra: pip install -e '.[ray]'",
}


def test_skip_messages_name_the_extra_pyproject_declares():
    """A skipped launcher test says what to install; the Ray plugin is in the ray extra, the
    submitit one in the cluster extra (a hint naming the wrong extra sends users astray)."""
    import tomllib

    project = tomllib.loads((CONF_DIR.parents[1] / "pyproject.toml").read_text())["project"]
    for plugin, hint in PLUGIN_INSTALL.items():
        dist = plugin.split(".")[1].replace("_", "-")
        if "extra" in hint:
            extra = hint.split("the ")[1].split(" extra")[0]
            assert any(r.startswith(dist) for r in project["optional-dependencies"][extra])
        else:
            assert any(r.startswith(dist) for r in project["dependencies"])


@pytest.mark.parametrize("launcher, target, plugin", LAUNCHERS)
@pytest.mark.parametrize("name", [n for n in EXPERIMENTS if n != "policy_maps"])
def test_every_experiment_composes_with_every_launcher(name, launcher, target, plugin):
    """A launcher given on the command line replaces the experiment's local one whole: no
    joblib setting (n_jobs) leaks into a Slurm or Ray launcher config."""
    if not _plugin(plugin.split(".")[0]) or not _plugin(plugin):
        pytest.skip(f"{plugin} is not installed ({PLUGIN_INSTALL[plugin]})")
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        dcfg = compose(config_name="config", return_hydra_config=True,
                       overrides=[f"+experiment={name}", f"hydra/launcher={launcher}"])
    assert dcfg.hydra.launcher._target_.endswith(target)
    assert ("n_jobs" in dcfg.hydra.launcher) == (launcher == "local")


def test_slurm_preset_fits_the_longest_training_and_activates_the_environment():
    """A Slurm job outlives the longest training (the generalist's, about 85 min on 2 cores)
    with margin, and its set-up puts it on the submitting command's Python environment."""
    import sys
    from pathlib import Path

    from omegaconf import OmegaConf

    from fleet_torchrl.config import activate_line, register_configs

    if not _plugin("hydra_plugins.hydra_submitit_launcher"):
        pytest.skip(f"hydra_submitit_launcher is not installed "
                    f"({PLUGIN_INSTALL['hydra_plugins.hydra_submitit_launcher']})")
    register_configs()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        dcfg = compose(config_name="config", return_hydra_config=True,
                       overrides=["hydra/launcher=slurm"])
    launcher = OmegaConf.to_container(dcfg.hydra.launcher, resolve=True)
    assert launcher["timeout_min"] >= 120
    activate = Path(sys.prefix) / "bin" / "activate"
    if activate.is_file():  # a virtual environment, as the suite runs in
        assert launcher["setup"] == [f"source {activate}"]
    else:
        assert launcher["setup"] == [f'export PATH={Path(sys.prefix) / "bin"}:"$PATH"']
    assert launcher["setup"] == [activate_line()]


def test_activate_line_sources_a_virtual_environment_or_puts_its_bin_on_path(
        tmp_path, monkeypatch):
    import sys

    from fleet_torchrl.config import activate_line

    prefix = tmp_path / "my env"
    monkeypatch.setattr(sys, "prefix", str(prefix))
    assert activate_line() == f"export PATH='{prefix}/bin':\"$PATH\""  # no venv: bin/ first
    (prefix / "bin").mkdir(parents=True)
    (prefix / "bin" / "activate").write_text("")
    assert activate_line() == f"source '{prefix}/bin/activate'"  # quoted for the shell
