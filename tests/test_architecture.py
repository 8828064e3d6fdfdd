"""The package's layering (docs/ARCHITECTURE.md): who may import whom, and no import cycles."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

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


@pytest.mark.parametrize(("imported", "absent"), [
    ("fleet_torchrl.sim, fleet_torchrl.env", ("hydra", "omegaconf")),  # no config framework
    ("fleet_torchrl.training.spec", ("torch",)),  # a run spec is built where --help runs
])
def test_light_modules_import_nothing_heavy(imported, absent):
    code = (f"import sys, {imported}; "
            f"print(sorted(m for m in sys.modules if m.split('.')[0] in {absent!r}))")
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


def folder(mod: str) -> str:
    """The node of the folder graph a module collapses to: its top-level folder under the
    package (``sim``, ``env``, ...), a top-level module (``config``, ``store``, ``cli``)
    itself, the package's ``__init__`` ``fleet_torchrl``."""
    parts = mod.split(".")
    return parts[1] if len(parts) > 1 else parts[0]


def folder_graph() -> dict[str, dict[str, str]]:
    """folder -> {folder it imports: one import that makes the edge, ``a -> b``}."""
    graph: dict[str, dict[str, str]] = {}
    for mod, deps in sorted(modules().items()):
        edges = graph.setdefault(folder(mod), {})
        for dep in sorted(deps):
            if folder(dep) != folder(mod):
                edges.setdefault(folder(dep), f"{mod} -> {dep}")
    return graph


def find_cycles(graph: dict[str, dict[str, str]]) -> list[list[str]]:
    """One cycle (its nodes, first repeated at the end) through each strongly connected
    component of more than one node (Tarjan's algorithm, then a walk inside the component)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    comps: list[set[str]] = []

    def connect(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in graph.get(v, {}):
            if w not in index:
                connect(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = set()
            while True:
                w = stack.pop()
                comp.add(w)
                if w == v:
                    break
            comps.append(comp)

    for v in sorted(graph):
        if v not in index:
            connect(v)
    cycles = []
    for comp in comps:
        if len(comp) < 2:
            continue
        start = min(comp)
        path, seen = [start], {start}
        while True:  # inside a strongly connected component every walk can close the circle
            nxt = sorted(w for w in graph[path[-1]] if w in comp)
            back = start in nxt and len(path) > 1
            fresh = [w for w in nxt if w not in seen]
            if back or not fresh:
                w = start if back else next(w for w in nxt if w in seen)
                cycles.append(path[path.index(w):] + [w])
                break
            path.append(fresh[0])
            seen.add(fresh[0])
    return cycles


def test_no_import_cycles_between_folders():
    """Collapsed to folders (a top-level module is its own node), the imports form no circle:
    a loop between folders that no single pair of files closes (``config`` importing the
    schemas of ``experiments`` while ``experiments`` imports ``config``) is one too."""
    graph = folder_graph()
    assert {"sim", "env", "agents", "config"} <= set(graph)  # the scan sees the folders
    bad = [" -> ".join(c) + "  (" + "; ".join(graph[a][b] for a, b in zip(c, c[1:],
                                                                           strict=False)) + ")"
           for c in find_cycles(graph)]
    assert not bad, "import cycles between folders:\n" + "\n".join(bad)


def test_find_cycles_names_the_circle():
    graph = {"a": {"b": "a.x -> b.y"}, "b": {"c": ""}, "c": {"a": ""}, "d": {"a": ""}}
    assert find_cycles(graph) == [["a", "b", "c", "a"]]
    assert find_cycles({"a": {"b": ""}, "b": {}}) == []


MAX_FUNCTION_LINES = 80


def long_functions(root: Path, limit: int = MAX_FUNCTION_LINES) -> list[str]:
    """``file:line name (N lines)`` of every function or method under ``root``, nested ones
    included, longer than ``limit`` lines (``def`` line to last line, decorators apart)."""
    out = []
    for path in sorted(root.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                n = node.end_lineno - node.lineno + 1
                if n > limit:
                    out.append(f"{path.relative_to(root.parent)}:{node.lineno} {node.name} "
                               f"({n} lines)")
    return out


def test_no_function_is_longer_than_80_lines():
    bad = long_functions(PKG)
    assert not bad, (f"functions longer than {MAX_FUNCTION_LINES} lines (split them into "
                     "named steps):\n" + "\n".join(bad))


def test_long_functions_sees_methods_and_nested_functions(tmp_path):
    pkg = tmp_path / "pkg"
    pkg.mkdir()
    body = "".join(f"        x{i} = {i}\n" for i in range(80))
    (pkg / "m.py").write_text(f"class A:\n    async def m(self):\n        def inner():\n"
                              f"    {body.replace(chr(10) + '        ', chr(10) + '            ')}"
                              f"            pass\n{body}")
    got = long_functions(pkg)
    assert [g.split(" ")[:2] for g in got] == [["pkg/m.py:2", "m"], ["pkg/m.py:3", "inner"]]
