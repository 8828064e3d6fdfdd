"""The package's layering (docs/ARCHITECTURE.md): who may import whom, and no import cycles."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import fleet_torchrl

PKG = Path(fleet_torchrl.__file__).resolve().parent
# lower rank = lower layer; a module imports only from its own layer or lower ones
# experiments/ takes resolved run specs and typed schemas: it sits below the root config
# (which composes its schemas, experiments/config.py); the commands and the table's sweeper
# (table_sweep.py, the launcher layer) compose and pass them in
RANK = {"utils": 0, "sim": 1, "env": 2, "agents": 3, "evaluation": 4, "store": 4,
        "training": 5, "experiments": 6, "config": 7}
COMMAND_RANK = 8  # the thin command modules and the table's sweeper at the top of the package


def module_name(path: Path) -> str:
    parts = path.relative_to(PKG.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports(path: Path) -> set[str]:
    """``fleet_torchrl`` modules a module imports anywhere: at module level, inside functions
    and in ``TYPE_CHECKING`` blocks (a type-checking import is still a dependency: a type
    checker follows it, and it can close an import circle)."""
    tree = ast.parse(path.read_text())
    mod = module_name(path)
    package = mod if path.name == "__init__.py" else mod.rsplit(".", 1)[0]
    out: set[str] = set()
    for node in tree.body:
        for sub in ast.walk(node):
            if isinstance(sub, ast.ImportFrom):
                if sub.level:
                    base = package.split(".")
                    base = base[: len(base) - sub.level + 1]
                    target = ".".join(base + ([sub.module] if sub.module else []))
                else:
                    target = sub.module or ""
                if target.startswith("fleet_torchrl"):
                    if not mod.startswith(target + "."):  # `from . import x`: x, not the parent
                        out.add(target)
                    out.update(f"{target}.{a.name}" for a in sub.names
                               if (PKG.parent / f"{target}.{a.name}".replace(".", "/")).exists()
                               or (PKG.parent / (f"{target}.{a.name}".replace(".", "/") + ".py"))
                               .exists())
            elif isinstance(sub, ast.Import):
                out.update(a.name for a in sub.names if a.name.startswith("fleet_torchrl"))
    return out


def rank(mod: str) -> int:
    parts = mod.split(".")
    if len(parts) == 1:
        return -1  # the package itself
    return RANK.get(parts[1], COMMAND_RANK)


def modules() -> dict[str, set[str]]:
    return {module_name(p): imports(p) for p in PKG.rglob("*.py")}


def test_layers_import_only_downwards():
    bad = []
    for mod, deps in modules().items():
        for dep in deps:
            # the root config composes every layer's schema module
            schema = mod == "fleet_torchrl.config" and dep.endswith(".config")
            if rank(dep) > rank(mod) and not schema:
                bad.append(f"{mod} -> {dep}")
    assert not bad, bad


def test_no_import_cycles():
    graph = modules()
    state: dict[str, int] = {}

    def visit(node: str, path: list[str]) -> None:
        state[node] = 1
        for dep in graph.get(node, ()):
            if state.get(dep) == 1:
                raise AssertionError(" -> ".join(path[path.index(dep):] + [dep]))
            if dep in graph and not state.get(dep):
                visit(dep, path + [dep])
        state[node] = 2

    for node in graph:
        if not state.get(node):
            visit(node, [node])


def test_simulator_and_environment_import_no_config_framework():
    code = ("import sys, fleet_torchrl.sim, fleet_torchrl.env; "
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('hydra', 'omegaconf')))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "[]"


def test_type_checking_imports_are_dependencies_too():
    """The scan sees a ``TYPE_CHECKING`` import (the agents once reached up to the root
    config that way, closing a circle through the registry)."""
    import tempfile

    with tempfile.TemporaryDirectory(dir=PKG) as d:
        probe = Path(d) / "probe.py"
        probe.write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n"
                         "    from fleet_torchrl.config import Config\n")
        assert "fleet_torchrl.config" in imports(probe)


HEAVY = ("torch", "torchrl", "tensordict", "numba", "scipy", "matplotlib", "tensorboard")


def test_composing_any_config_imports_no_heavy_package():
    """--help and tab completion compose a config: every schema module, every group option
    and experiment compose without torch, TorchRL or the plotting stack (each takes seconds
    to import; torch and TorchRL together about 5 s on a 2-core CPU)."""
    code = f"""
import sys
from hydra import compose, initialize_config_dir
from fleet_torchrl.config import CONF_DIR, register_configs
register_configs()
options = [f"{{g.name}}={{p.stem}}" for g in CONF_DIR.iterdir() if g.is_dir()
           and g.name not in ("hydra", "experiment") for p in g.glob("*.yaml")]
options += [f"+experiment={{p.stem}}" for p in (CONF_DIR / "experiment").glob("*.yaml")]
with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
    for o in options:
        compose(config_name="config", overrides=[o])
print(len(options), sorted(m for m in sys.modules if m.split(".")[0] in {HEAVY!r}))
"""
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    count, heavy = r.stdout.split(" ", 1)
    assert int(count) >= 20 and heavy.strip() == "[]", r.stdout


def test_experiments_take_resolved_specs_and_never_compose():
    """experiments/ sits below the root config: the commands and the table's sweeper
    (``fleet_torchrl.table_sweep``) compose and pass run specs and typed schemas in; no
    module of experiments/ imports ``fleet_torchrl.config`` (the folder loop
    config -> experiments.config -> ... -> config) or calls ``compose_config``."""
    bad = [f"{mod} -> {dep}" for mod, deps in modules().items()
           if mod.startswith("fleet_torchrl.experiments") for dep in deps
           if dep == "fleet_torchrl.config"]
    assert not bad, bad
    calls = [str(p.relative_to(PKG)) for p in (PKG / "experiments").rglob("*.py")
             if "compose_config" in p.read_text()]
    assert not calls, calls


def test_no_function_of_the_experiments_is_longer_than_80_lines():
    long = []
    for p in (PKG / "experiments").rglob("*.py"):
        for node in ast.walk(ast.parse(p.read_text())):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                n = node.end_lineno - node.lineno + 1
                if n > 80:
                    long.append(f"{p.name}:{node.name} ({n} lines)")
    assert not long, long
