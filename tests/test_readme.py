"""The README's Python examples run as written; its training commands publish where they
should."""

from __future__ import annotations

import dataclasses
import json
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[1] / "README.md"
BLOCKS = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)


def test_readme_has_python_examples():
    assert len(BLOCKS) >= 2 and any("action_spec_unbatched" in b for b in BLOCKS)


@pytest.mark.slow
@pytest.mark.parametrize("index", range(len(BLOCKS)))
def test_readme_python_example_runs(index, tmp_path):
    r = subprocess.run([sys.executable, "-c", BLOCKS[index]], cwd=tmp_path,
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]


# ------------------------------------------------------------- where its trainings publish
def _readme_commands(target: str) -> list[list[str]]:
    """The overrides of every ``make <target> ARGS="..."`` and ``python -m
    fleet_torchrl.<target> ...`` of the README (code blocks and inline), continuation lines
    joined; Hydra's own ``hydra.*`` overrides left out."""
    text = re.sub(r"\\\n\s*", " ", README.read_text())
    found = [m for m in re.findall(rf'make {target} ARGS="([^"]*)"', text)]
    found += [m for m in re.findall(rf"-m fleet_torchrl\.{target} ([^`#\n]*)", text)]
    return [[a for a in shlex.split(args) if not a.startswith(("hydra.", "hydra/"))]
            for args in found]


def _recipe(cfg) -> tuple:
    """What a policy is trained for, from the config itself (not from its name): agent and
    its variant, state, the objective it maximises, every site setting."""
    variant = {"search": ("policy_class",), "dqn": ("anchor",)}.get(cfg.agent.name, ())
    return (cfg.agent.name, tuple(getattr(cfg.agent, f) for f in variant), cfg.state.name,
            cfg.agent.objective(cfg.mdp), json.dumps(dataclasses.asdict(cfg.site),
                                                     sort_keys=True))


def _published(overrides: list[str]) -> tuple[str, tuple]:
    from fleet_torchrl.config import compose_config
    from fleet_torchrl.store import default_policy_dir

    cfg = compose_config(overrides)
    return default_policy_dir(cfg).as_posix(), _recipe(cfg)


def test_every_readme_training_command_publishes_to_its_own_recipes_folder():
    """No README training command publishes into the folder of another recipe (the
    generalist command used to replace the default-site throughput DQN); each folder is the
    one its evaluation looks up. Computed from the configs, nothing is trained."""
    commands = _readme_commands("train")
    assert len(commands) >= 9, commands  # the parse found the README's commands
    where = {" ".join(o): _published(o) for o in commands if "-m" not in o}
    folders: dict[str, tuple] = {}
    for cmd, (folder, recipe) in where.items():
        assert folder.startswith("results/policies/"), cmd
        assert folders.setdefault(folder, recipe) == recipe, (
            f"{cmd!r} publishes to {folder}, the folder of another recipe")
    generalist = next(f for c, (f, _) in where.items() if "agent.anchor=heuristic" in c)
    assert generalist == "results/policies/dqn_partial_throughput_anchored_randomized/seed0"
    assert where["agent=dqn mdp.reward=throughput"][0] == \
        "results/policies/dqn_partial_throughput/seed0"
    assert where["agent=search site=five_vehicles"][0] == \
        "results/policies/search_five_vehicles/seed0"
    # the evaluations the README shows of learned policies find a folder a command fills
    learned = [o for o in _readme_commands("evaluate")
               if any(a in o for a in ("agent=dqn", "agent=tabular", "agent=search"))
               and not any(a.startswith("agent.policy=") for a in o)]
    assert learned, "the README evaluates no learned policy"
    for o in learned:
        assert _published(o)[0] in folders, o


def test_readme_grid_runs_publish_into_their_job_folders():
    """``make grid`` trains through Hydra's multirun: each job keeps its policy in its own
    job folder (never results/policies/), whatever the README adds to the grid."""
    from omegaconf import OmegaConf

    from fleet_torchrl.config import CONF_DIR

    grid = OmegaConf.load(CONF_DIR / "experiment" / "grid.yaml")
    assert OmegaConf.to_container(grid)["train"]["out_dir"] == \
        "${hydra:runtime.output_dir}/policy"
    grids = _readme_commands("grid")
    assert grids and not any(a.startswith("train.out_dir") for o in grids for a in o)


def test_table_runs_keep_their_folders_and_share_one_only_with_their_recipe():
    """``make table`` publishes run ``<key>`` to ``results/policies/<key>/seed<s>/`` (kept
    as it was); a README ``make train`` whose name is such a key trains that key's recipe."""
    from fleet_torchrl.config import compose_config
    from fleet_torchrl.experiments.table import run_overrides
    from fleet_torchrl.store import seed_dir

    cfg = compose_config([])
    table = {}
    for key, recipe in cfg.recipes.items():
        # (a teacher's bases are other recipes' files, which exist once the table ran)
        run = compose_config([o for o in run_overrides(key, 1, cfg)
                              if not o.startswith("agent.expert.bases=")])
        assert Path(run.train.out_dir) == seed_dir("results/policies", key, 1)
        table[key] = _recipe(compose_config(recipe.overrides))
    assert {"generalist", "dqn_partial_throughput", "search_mlp"} <= table.keys()
    for o in _readme_commands("train"):
        folder, recipe = _published(o)
        key = Path(folder).name
        assert key not in table or table[key] == recipe, (o, key)


def test_readme_quoting_of_a_list_override_with_equals_signs_reaches_hydra_intact():
    """The README's example, read as the user's shell reads it, passed through make (dry run:
    the recipe line as make's shell would run it) and composed: the list arrives whole."""
    import shutil

    from fleet_torchrl.config import compose_config

    want = ["agent.rollouts=32", "agent.horizon=300"]
    line = next(ln for ln in README.read_text().splitlines()
                if ln.startswith("make sweep-pc ARGS=") and "planner_overrides" in ln)
    user = shlex.split(line)  # what the user's shell hands to make
    if shutil.which("make") is not None:
        r = subprocess.run(["make", "-n", "-C", str(README.parent), *user[1:]],
                           capture_output=True, text=True, timeout=60)
        assert r.returncode == 0, r.stderr
        recipe = next(ln for ln in r.stdout.splitlines() if "fleet_torchrl.sweeps -m" in ln)
        arg = next(a for a in shlex.split(recipe) if a.startswith("sweep.planner_overrides="))
        cfg = compose_config(["+experiment=sweep_pc", arg])
        assert cfg.sweep.planner_overrides == want
    sweeps = [o for o in _readme_commands("sweeps")
              if any(a.startswith("sweep.planner_overrides=") for a in o)]
    assert sweeps, "the README shows no python -m form of the quoting"
    for o in sweeps:
        cfg = compose_config([a for a in o if a != "-m"])
        assert cfg.sweep.planner_overrides == want
