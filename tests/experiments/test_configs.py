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
        values = str(dcfg.hydra.sweeper.params["sweep.value"]).split(",")
        assert len(values) >= 5 and cfg.sweep.name == name.removeprefix("sweep_")


def test_cluster_launcher_configs_are_documented():
    for name, base in (("slurm", "submitit_slurm"), ("ray_cluster", "ray")):
        text = (CONF_DIR / "hydra" / "launcher" / f"{name}.yaml").read_text()
        assert text.startswith("#") and f"hydra/launcher={name}" in text
        assert yaml.safe_load(text)["defaults"] == [base]
