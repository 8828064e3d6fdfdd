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
    from fleet_torchrl.train import publish_folder

    cfg = compose_config(overrides)
    return publish_folder(cfg).as_posix(), _recipe(cfg)


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


# ------------------------------------------------------------- its claims hold
def _options_table() -> dict[str, tuple[list[str], str]]:
    """The README's table of config groups: group -> (its options, its notes)."""
    rows = re.findall(r"^\| `(\w+)` \| ([^|]*) \| ([^|]*) \|$", README.read_text(), flags=re.M)
    return {g: (re.findall(r"`([^`]+)`", opts), notes) for g, opts, notes in rows}


@pytest.mark.parametrize("group", ["site", "state", "agent"])
def test_readme_lists_every_packaged_option_of_a_group(group):
    from fleet_torchrl.config import CONF_DIR

    listed = _options_table()[group][0]
    packaged = sorted(p.stem for p in (CONF_DIR / group).glob("*.yaml"))
    assert sorted(listed) == packaged, (group, listed, packaged)


def test_readme_option_notes_name_real_fields():
    """Every example of the options table with a value composes as written, an agent's
    field beside the agent it belongs to (``agent.threshold=40`` alone read as a setting of
    ``agent=threshold``, which has none, composes with the default ``agent=rule``), and every
    bare ``group.field`` is a field of its group."""
    from dataclasses import fields

    from fleet_torchrl.config import Config, compose_config

    checked = 0
    for group, (_, notes) in _options_table().items():
        for item in re.findall(r"`([^`]+)`", notes):
            words = item.split()
            if any("=" in w for w in words):
                if group == "agent":
                    assert words[0].startswith("agent="), f"{item}: which agent's field?"
                compose_config(words)
            elif re.fullmatch(rf"{group}\.\w+", item):
                schema = {f.name: f for f in fields(Config)}[group].default_factory
                assert item.split(".")[1] in {f.name for f in fields(schema)}, item
            else:
                continue
            checked += 1
    assert checked >= 15, checked


def _make_targets() -> dict[str, tuple[str, list[str]]]:
    """What each make target runs, from the Makefile: target -> (command, fixed arguments)."""
    out = {}
    target = None
    for line in (README.parent / "Makefile").read_text().splitlines():
        m = re.match(r"^([\w-]+):", line)
        if m:
            target = m.group(1)
            continue
        m = re.search(r"\$\(PY\) -m fleet_torchrl\.(\w+) (.*)\$\(ARGS\)", line)
        if m and target and target not in out:
            out[target] = (m.group(1), shlex.split(m.group(2)))
    return out


def _readme_invocations() -> list[tuple[str, str, list[str]]]:
    """Every command line of the README that passes overrides: ``make <target> ARGS="..."``,
    ``fleet-<command> ...`` and ``python -m fleet_torchrl.<command> ...``, in its bash
    blocks and its inline code, read as the user's shell reads it: (the line, the command,
    its arguments, make's fixed ones first)."""
    text = README.read_text()
    blocks = re.findall(r"```bash\n(.*?)```", text, flags=re.S)
    lines = [ln for b in blocks for ln in re.sub(r"\\\n\s*", " ", b).splitlines()]
    prose = re.sub(r"```.*?```", "", text, flags=re.S)
    lines += re.findall(r"`((?:make [\w-]+ ARGS=|fleet-|(?:\.venv/bin/)?python -m fleet_)"
                        r"[^`]*)`", prose)
    targets = _make_targets()
    found = []
    for line in lines:
        words = shlex.split(line, comments=True)
        if not words:
            continue
        if words[0] == "make" and len(words) > 2 and words[2].startswith("ARGS="):
            command, fixed = targets[words[1]]
            found.append((line, command, [*fixed, *shlex.split(words[2][len("ARGS="):])]))
        elif words[0].split("/")[-1].startswith("fleet-") and "-sc" not in words:
            found.append((line, words[0].split("/")[-1][len("fleet-"):].replace("-", "_"),
                          words[1:]))
        elif words[0].split("/")[-1] == "python" and words[1:2] == ["-m"] and \
                words[2].startswith("fleet_torchrl."):
            found.append((line, words[2].split(".")[1], words[3:]))
    # Hydra's own flags (--help, -m) aside, placeholders (<time>) as words; a line with no
    # override left (`fleet-compare`'s name in prose) shows none to check
    found = [(line, c, [re.sub(r"<(\w+)>", r"\1", a) for a in args if not a.startswith("-")])
             for line, c, args in found]
    return [(line, c, args) for line, c, args in found if any("=" in a for a in args)]


def _compose_example(command: str, args: list[str]) -> None:
    """Compose ``args`` as ``command`` would (each value of a sweep in turn), and validate
    the result into its typed config; runs nothing."""
    import itertools

    from hydra import compose, initialize_config_dir
    from hydra.core.override_parser.overrides_parser import OverridesParser

    from fleet_torchrl.config import (
        CONF_DIR,
        TOOL_SCHEMAS,
        register_configs,
        to_config,
        to_tool_config,
        without_hydra,
    )

    args = [a for a in args if a != "..."]
    parsed = OverridesParser.create().parse_overrides(args)
    choices = [list(o.sweep_string_iterator()) if o.is_sweep_override() else [o.input_line]
               for o in parsed]
    keys = [o.key_or_group for o in parsed]
    register_configs()
    name = command if command in TOOL_SCHEMAS else "config"
    # a tool with a folder of its own (compare: tool_conf/, so that completion offers only
    # its settings) composes from there
    own = CONF_DIR.parent / "tool_conf"
    conf_dir = own if (own / f"{name}.yaml").is_file() else CONF_DIR
    with initialize_config_dir(config_dir=str(conf_dir), version_base="1.3"):
        for combo in itertools.product(*choices):
            overrides = [o if "=" in o else f"{k}={o}" for k, o in zip(keys, combo,
                                                                     strict=True)]
            # a ${hydra:...} path (the grid's job folders) resolves inside a run only
            extra = ["train.out_dir=null"] if "+experiment=grid" in overrides else []
            dcfg = compose(config_name=name, overrides=[*overrides, *extra],
                           return_hydra_config=True)
            if name == "config":
                to_config(without_hydra(dcfg))
            else:
                to_tool_config(without_hydra(dcfg), TOOL_SCHEMAS[name])


INVOCATIONS = _readme_invocations()


def test_readme_invocations_were_found():
    commands = {c for _, c, _ in INVOCATIONS}
    assert len(INVOCATIONS) >= 40, len(INVOCATIONS)
    assert {"train", "evaluate", "table", "sweeps", "compare", "sweeps_summary", "bench",
            "objective"} <= commands, commands


@pytest.mark.parametrize("line, command, args", INVOCATIONS,
                         ids=[f"{i}:{c}" for i, (_, c, _) in enumerate(INVOCATIONS)])
def test_readme_invocation_composes(line, command, args, tmp_path, monkeypatch):
    """Every override the README shows is one the command takes: composed through Hydra
    and validated (a key no config has, such as agent.threshold, fails here); nothing runs.
    A launcher whose plugin is not installed is skipped; the README's own recipes file
    (``recipes=mine``) is made as conf/README.md describes, and a saved policy it names as
    an empty file (the config checks that it exists; reading it is the run's business)."""
    import importlib.util

    for launcher, plugin in (("ray", "hydra_plugins.hydra_ray_launcher"),
                             ("slurm", "hydra_plugins.hydra_submitit_launcher"),
                             ("submitit_local", "hydra_plugins.hydra_submitit_launcher")):
        if any(a.startswith(f"hydra/launcher={launcher}") for a in args) and \
                importlib.util.find_spec(plugin.split(".")[0]) is not None and \
                importlib.util.find_spec(plugin) is None:
            pytest.skip(f"{plugin} is not installed")
    monkeypatch.chdir(tmp_path)
    if "recipes=mine" in args:
        (tmp_path / "conf" / "recipes").mkdir(parents=True)
        (tmp_path / "conf" / "recipes" / "mine.yaml").write_text(
            "defaults: [default, _self_]\n"
            "wide:\n  overrides: [agent=dqn, network.width=256]\n")
    for a in args:
        key, _, value = a.partition("=")
        if key in ("agent.base", "agent.policy") and value.startswith("results/"):
            path = tmp_path / value
            path = path if path.suffix == ".pt" else path / "policy.pt"
            path.parent.mkdir(parents=True, exist_ok=True)
            path.touch()
    _compose_example(command, args)


def test_readme_states_the_launchers_default_parallelism():
    """The README's ``hydra.launcher.n_jobs=N`` (the default, not an alternative given
    "with ...") is the local launcher's, and "N at a time" says that number."""
    import yaml

    from fleet_torchrl.config import CONF_DIR

    n_jobs = yaml.safe_load((CONF_DIR / "hydra" / "launcher" / "local.yaml").read_text())
    n_jobs = n_jobs["n_jobs"]
    text = re.sub(r"\s+", " ", README.read_text())
    claims = re.findall(r"(with )?`hydra\.launcher\.n_jobs=(\d+)`(: (\w+) at a time)?", text)
    defaults = [(int(n), words) for alt, n, _, words in claims if not alt]
    assert defaults, "the README states no launcher default"
    numbers = {"one": 1, "two": 2, "three": 3, "four": 4}
    for n, words in defaults:
        assert n == n_jobs and (not words or numbers[words] == n_jobs), (n, words, n_jobs)
    assert f"{['', 'one', 'two', 'three', 'four'][n_jobs]} at a time" in text


def test_readme_promises_no_start_up_time_for_help():
    """How long ``--help`` takes depends on the machine and its load (docs/BENCHMARKS.md
    measures it); the README makes no such promise."""
    text = re.sub(r"\s+", " ", README.read_text())
    for sentence in re.findall(r"[^.]*--help[^.]*", text):
        assert not re.search(r"\bseconds?\b|\b\d+(\.\d+)? ?s\b|\bms\b", sentence), sentence


def test_a_wrong_key_in_an_invocation_fails_to_compose():
    """The check the README's invocations go through refuses a key no config has."""
    from hydra.errors import ConfigCompositionException

    _compose_example("train", ["agent=tabular", "train.max_episodes=8"])
    with pytest.raises(ConfigCompositionException):
        _compose_example("train", ["agent=threshold", "agent.threshold=40"])
