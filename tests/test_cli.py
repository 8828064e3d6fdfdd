"""The commands: one console script each, one convention (Hydra overrides), a fast --help,
one validation per run, one-line errors with install hints for missing extras."""

from __future__ import annotations

import importlib
import json
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPTS = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
COMMANDS = ("train", "evaluate", "compare", "table", "sweeps", "sweeps_summary", "grid",
            "policy_maps", "objective", "report", "bench")
HEAVY = ("torch", "torchrl", "tensordict", "numba", "scipy", "matplotlib")


def test_every_command_has_its_console_script():
    """fleet-<command> -> fleet_torchrl.<command>:main, for every command module; each is a
    Hydra app (the one convention), so Hydra's tab completion can ask it."""
    assert {f"fleet-{c.replace('_', '-')}" for c in COMMANDS} == set(SCRIPTS)
    for name, target in SCRIPTS.items():
        module, func = target.split(":")
        assert module == f"fleet_torchrl.{name.removeprefix('fleet-').replace('-', '_')}"
        main = getattr(importlib.import_module(module), func)
        assert callable(main) and main.__module__ == module, name
    modules = {p.stem for p in (ROOT / "fleet_torchrl").glob("*.py")} - {
        "__init__", "cli", "config", "store", "table_sweep"}  # table_sweep: make table's sweeper
    assert modules == set(COMMANDS)  # a new command module needs its script


_HELP = """
import sys, time
t0 = time.perf_counter()
sys.argv = [{name!r}, "--help"]
from {module} import main
try:
    main()
except SystemExit as e:
    assert not e.code, e.code
print("SECONDS", time.perf_counter() - t0)
print("HEAVY", sorted(m for m in sys.modules if m.split(".")[0] in {heavy!r}))
"""


@pytest.mark.parametrize("name", sorted(SCRIPTS))
def test_help_is_fast_and_imports_no_heavy_package(name, tmp_path):
    """What a console script runs for --help: the help of a Hydra app, without torch,
    TorchRL, numba or matplotlib (about 5 s of imports on a 2-core CPU), and no run folder."""
    module = SCRIPTS[name].split(":")[0]
    r = subprocess.run([sys.executable, "-c", _HELP.format(name=name, module=module,
                                                            heavy=HEAVY)],
                       capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "== Config ==" in r.stdout and "Override anything in the config" in r.stdout
    heavy = r.stdout.split("HEAVY ")[1].strip()
    assert heavy == "[]", heavy
    assert not list(tmp_path.iterdir())  # no outputs/ for a --help
    groups = getattr(importlib.import_module(module), "GROUPS", None)
    if groups is not None:  # the groups it reads, listed (the table: its own, not train's)
        assert f"== Groups {name} reads ==\n{', '.join(groups)}, seed\n" in r.stdout


def test_a_command_checks_only_the_groups_it_reads():
    """A setting of a group a command does not read is composed and ignored (a bad sweep
    value does not stop an evaluation); the command that reads it refuses it."""
    from fleet_torchrl import evaluate, sweeps, train
    from fleet_torchrl.config import GROUPS, compose_config
    from fleet_torchrl.utils.checks import ConfigError

    bad = ["sweep.param=bogus", "maps.out=", "objective.n_sites=0", "bench.repeats=0"]
    for groups in (evaluate.GROUPS, train.GROUPS):
        cfg = compose_config(bad, groups=groups)
        assert cfg.sweep.param == "bogus" and cfg.bench.repeats == 0
    with pytest.raises(ConfigError, match="sweep.param"):
        compose_config(bad[:1], groups=sweeps.GROUPS)
    with pytest.raises(ConfigError, match="bench.repeats"):
        compose_config(bad[-1:])  # every group by default (the library's, the tests')
    assert set(train.GROUPS) < set(GROUPS) and set(evaluate.GROUPS) < set(GROUPS)
    with pytest.raises(ConfigError, match="eval.n_sims"):  # what a command reads: checked
        compose_config(["eval.n_sims=0"], groups=evaluate.GROUPS)


def test_tools_list_their_own_settings_only():
    r = subprocess.run([sys.executable, "-m", "fleet_torchrl.compare", "--help"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.startswith("fleet-compare: ") and "baseline: null" in r.stdout
    assert "agent:" not in r.stdout  # the model's groups are not a file tool's


def test_a_bad_value_is_one_line_and_leaves_no_run_folder(tmp_path):
    r = subprocess.run([sys.executable, "-m", "fleet_torchrl.evaluate", "site.p_c=2"],
                       capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert r.returncode == 2
    assert r.stderr.strip().splitlines() == [
        "error: site.p_c=2.0 is invalid: allowed [0.0, 1.0]"]
    assert not (tmp_path / "outputs").exists()


def test_a_run_validates_its_config_once(tmp_path, monkeypatch, command):
    """Hydra composes the command line; the config is validated once (before the run
    folder exists) and the task takes that validated config."""
    import fleet_torchrl.config as config
    from fleet_torchrl import evaluate

    calls = []
    real = config.validate
    monkeypatch.setattr(config, "validate",
                        lambda cfg, *groups: calls.append(1) or real(cfg, *groups))
    monkeypatch.setattr(config, "compose_config", lambda *a: pytest.fail("composed again"))
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "rule.json"
    assert command(evaluate.main, "eval.n_sims=4", "eval.ticks=50", "eval.progress=false",
                   f"eval.out={out}", f"hydra.run.dir={tmp_path / 'run'}") == 0
    assert len(calls) == 1
    assert json.loads(out.read_text())["n_sims"] == 4


def test_a_value_only_the_run_can_resolve_is_validated_by_the_run(tmp_path):
    """``${hydra:runtime.output_dir}`` exists only once the run folder does: such a config
    is left to the task's validation, not refused before the run."""
    r = subprocess.run([sys.executable, "-m", "fleet_torchrl.evaluate",
                        "train.out_dir=${hydra:runtime.output_dir}/policy", "eval.n_sims=2",
                        "eval.ticks=20", "eval.progress=false"],
                       capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    assert list((tmp_path / "outputs" / "evaluate").glob("*/*/eval.json"))


_BLOCKED = """
import sys
sys.modules[{plugin!r}] = None  # as if its extra were not installed
sys.argv = ["fleet-sweeps", "-m", "+experiment=sweep_pc", "hydra/launcher={launcher}"]
from fleet_torchrl.sweeps import main
main()
"""


@pytest.mark.parametrize("launcher, plugin, extra", [
    ("ray", "hydra_plugins.hydra_ray_launcher", "ray"),
    ("ray_cluster", "hydra_plugins.hydra_ray_launcher", "ray"),
    ("slurm", "hydra_plugins.hydra_submitit_launcher", "cluster"),
    ("submitit_local", "hydra_plugins.hydra_submitit_launcher", "cluster"),
])
def test_a_missing_launcher_plugin_names_its_extra(launcher, plugin, extra, tmp_path):
    r = subprocess.run([sys.executable, "-c", _BLOCKED.format(plugin=plugin,
                                                               launcher=launcher)],
                       capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert r.returncode == 2, r.stderr[-2000:]
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: hydra/launcher={launcher} needs")
    assert f"pip install 'fleet_torchrl[{extra}]'" in lines[0]
    assert not (tmp_path / "multirun").exists()


def test_a_missing_module_of_an_extra_names_it():
    from fleet_torchrl.cli import missing_extra

    msg = missing_extra(ModuleNotFoundError("No module named 'gymnasium'", name="gymnasium"))
    assert "gym extra" in msg and "pip install 'fleet_torchrl[gym]'" in msg
    assert "ray extra" in missing_extra(ModuleNotFoundError("x", name="ray.util"))
    assert missing_extra(ModuleNotFoundError("x", name="numpyy")) is None


def test_run_folders_name_the_agent_state_and_site_and_never_collide(tmp_path):
    """Two runs started together (in the same second) get folders of their own: the folder
    names what ran and the process that ran it."""
    import re

    cmd = [sys.executable, "-m", "fleet_torchrl.evaluate", "agent=heuristic",
           "site=five_vehicles", "eval.n_sims=2", "eval.ticks=20", "eval.progress=false"]
    procs = [subprocess.Popen(cmd, cwd=tmp_path, stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True) for _ in range(2)]
    for p in procs:
        _, err = p.communicate(timeout=300)
        assert p.returncode == 0, err[-2000:]
    runs = sorted((tmp_path / "outputs" / "evaluate" / "heuristic_partial_five_vehicles"
                   ).iterdir())
    assert len(runs) == 2 and all((r / "eval.json").is_file() for r in runs)
    pids = {str(p.pid) for p in procs}
    for r in runs:
        m = re.fullmatch(r"\d{4}-\d\d-\d\d_\d\d-\d\d-\d\d_(\d+)", r.name)
        assert m and m.group(1) in pids, r.name


def test_the_readme_and_the_makefile_name_every_command():
    readme = (ROOT / "README.md").read_text()
    commands = readme.split("## Commands")[1].split("\n## ")[0]
    for name in SCRIPTS:
        assert f"`{name}`" in commands, name
    assert 'eval "$(.venv/bin/fleet-train -sc install=bash)"' in commands
    quick = readme.split("## Quickstart")[1].split("\n## ")[0]
    block = quick.split("```bash\n")[1].split("```")[0]
    assert [ln.split("#")[0].strip() for ln in block.strip().splitlines()] == [
        "make table", "make test"]  # the Quickstart stays two commands


def test_a_multiruns_jobs_share_one_sweep_folder(tmp_path):
    """The joblib workers of a multirun resolve the sweep folder again: they use the launching
    command's process id, so every job lands in one folder (the grid's summary read half of
    its runs when each worker named the folder after itself)."""
    cmd = [sys.executable, "-m", "fleet_torchrl.evaluate", "-m", "agent=heuristic,rule",
           "eval.n_sims=2", "eval.ticks=20", "eval.progress=false", "hydra/launcher=local",
           "hydra.launcher.n_jobs=2"]
    r = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    sweeps = list((tmp_path / "multirun" / "evaluate").iterdir())
    assert len(sweeps) == 1, sweeps
    assert sorted(p.name for p in sweeps[0].iterdir() if p.is_dir()) == ["0", "1"]


def test_the_evaluation_log_names_the_site_fields_changed_from_its_preset(tmp_path, caplog):
    """A preset with a field overridden is not the preset: the summary line says what
    changed (``site 'default' with p_c=0.5``), a preset as it stands is named alone."""
    import logging

    from fleet_torchrl import evaluate
    from fleet_torchrl.config import compose_config

    base = ["eval.n_sims=2", "eval.ticks=20", "eval.progress=false"]
    for i, (overrides, want) in enumerate((
            (["site.p_c=0.5"], "on site 'default' with p_c=0.5, seed"),
            (["site=five_vehicles"], "on site 'five_vehicles', seed"))):
        caplog.clear()
        with caplog.at_level(logging.INFO, logger="fleet_torchrl.evaluate"):
            evaluate.run(compose_config([*base, *overrides]), tmp_path / f"r{i}.json")
        said = [r.getMessage() for r in caplog.records if " sims x " in r.getMessage()]
        assert len(said) == 1 and want in said[0], said
