"""What the package ships and declares: a wheel holds every YAML of ``fleet_torchrl/conf``;
dependency ranges, licence and Python versions in pyproject.toml; optional extras that say
what to install; the provenance a run records (the package's version, its own commit)."""

from __future__ import annotations

import shutil
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import pytest

from fleet_torchrl.config import CONF_DIR

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_wheel_contains_every_config(tmp_path):
    src = tmp_path / "src"  # build from a copy: no build/ folder in the checkout
    for package in ("fleet_torchrl", "hydra_plugins"):
        shutil.copytree(ROOT / package, src / package,
                        ignore=shutil.ignore_patterns("__pycache__"))
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, src / name)
    r = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation",
                        "-q", "-w", str(tmp_path), str(src)], capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    (wheel,) = tmp_path.glob("fleet_torchrl-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    expected = {f"fleet_torchrl/conf/{p.relative_to(CONF_DIR)}" for p in CONF_DIR.rglob("*.yaml")}
    assert len(expected) >= 20
    assert expected <= names, sorted(expected - names)
    # compare's own config folder (no model groups for its completion to offer)
    assert "fleet_torchrl/tool_conf/compare.yaml" in names
    assert "fleet_torchrl/sim/site.py" in names and "fleet_torchrl/agents/registry.py" in names
    # the table's sweeper, where Hydra looks for plugins; hydra_plugins stays a namespace
    assert "hydra_plugins/fleet_torchrl_table/table_sweeper.py" in names
    assert "hydra_plugins/__init__.py" not in names
    assert not any(n.startswith("conf/") for n in names)  # the users' folder is not shipped
    entry_points = next(n for n in names if n.endswith(".dist-info/entry_points.txt"))
    scripts = zipfile.ZipFile(wheel).read(entry_points).decode()
    assert "fleet-train = fleet_torchrl.train:main" in scripts


# ---------------------------------------------------------------------- pyproject
PROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())


def _requirements(names: list[str]) -> dict[str, str]:
    """``{distribution: specifier}`` of requirement strings (markers and comments aside)."""
    import re

    out = {}
    for r in names:
        m = re.match(r"\s*([A-Za-z0-9_.\-]+)(\[[^\]]*\])?\s*(.*)", r.split(";")[0])
        out[m.group(1).lower().replace("_", "-")] = m.group(3).strip()
    return out


def test_dependencies_are_ranges_with_upper_bounds_that_admit_the_tested_stack():
    """No exact pins; torch and torchrl keep an upper bound (a newer torch is a multi-GB
    download, and torchrl 0.14 pins tensordict 0.14); the installed stack satisfies them."""
    from importlib.metadata import version

    from packaging.requirements import Requirement

    deps = PROJECT["project"]["dependencies"]
    reqs = _requirements(deps)
    assert not [r for r in deps if "==" in r], deps
    for name in ("torch", "torchrl", "tensordict", "scipy"):
        assert "<" in reqs[name] and ">=" in reqs[name], (name, reqs[name])
        assert Requirement(f"{name}{reqs[name]}").specifier.contains(version(name)), name
    assert not Requirement(f"torch{reqs['torch']}").specifier.contains("2.15.0")


def test_joblib_is_capped_only_by_the_ray_extra():
    """joblib 1.6 needs cloudpickle>=3, which hydra-ray-launcher excludes: only users of the
    ray extra take the cap (the joblib launcher itself runs with joblib 1.6)."""
    from packaging.requirements import Requirement

    core = _requirements(PROJECT["project"]["dependencies"])
    assert Requirement(f"joblib{core['joblib']}").specifier.contains("1.4.2")
    assert Requirement(f"joblib{core['joblib']}").specifier.contains("1.6.0")
    ray = _requirements(PROJECT["project"]["optional-dependencies"]["ray"])
    assert not Requirement(f"joblib{ray['joblib']}").specifier.contains("1.6.0")
    assert not Requirement(f"cloudpickle{ray['cloudpickle']}").specifier.contains("3.0")
    for extra, deps in PROJECT["project"]["optional-dependencies"].items():
        if extra != "ray":
            assert "joblib" not in _requirements(deps), extra


def test_licence_is_an_spdx_string_and_python_versions_are_declared():
    from packaging.specifiers import SpecifierSet
    from packaging.version import Version

    project = PROJECT["project"]
    assert project["license"] == "MIT"  # SPDX expression (PEP 639), not a table
    assert project["license-files"] == ["LICENSE"]
    licence = (ROOT / "LICENSE").read_text()
    assert licence.startswith("MIT License") and "WITHOUT WARRANTY OF ANY KIND" in licence
    build = _requirements(PROJECT["build-system"]["requires"])
    assert Version("77") in SpecifierSet(build["setuptools"])  # the first to read it
    assert not SpecifierSet(build["setuptools"]).contains("76")
    py = SpecifierSet(project["requires-python"])
    assert all(py.contains(v) for v in ("3.11.0", "3.12.0", "3.13.0"))
    assert not py.contains("3.14.0") and not py.contains("3.10.0")
    classifiers = set(project["classifiers"])
    assert {f"Programming Language :: Python :: 3.{m}" for m in (11, 12, 13)} <= classifiers
    assert not any(c.startswith("License ::") for c in classifiers)  # not with an SPDX one


# ---------------------------------------------------------------------- optional extras
def test_gym_adapter_without_the_extra_says_what_to_install():
    """Without Gymnasium, importing the adapter ends in one line naming the extra."""
    code = "import sys; sys.modules['gymnasium'] = None; import fleet_torchrl.env.gym"
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode != 0
    last = r.stderr.strip().splitlines()[-1]
    assert last.startswith("ImportError: fleet_torchrl.env.gym needs Gymnasium")
    assert "pip install 'fleet_torchrl[gym]'" in last
    assert "During handling" not in r.stderr  # no chained gymnasium traceback


# ---------------------------------------------------------------------- provenance
def _git(cwd: Path, *args: str) -> str:
    return subprocess.run(["git", "-c", "user.email=t@t", "-c", "user.name=t", *args],
                          cwd=cwd, capture_output=True, text=True, check=True).stdout.strip()


def _repo(root: Path, name: str, package: str | None) -> Path:
    """A committed git repository whose pyproject names ``name``, holding ``package/``."""
    root.mkdir(parents=True)
    (root / "pyproject.toml").write_text(f'[project]\nname = "{name}"\nversion = "1"\n')
    if package:
        (root / package).mkdir()
        (root / package / "__init__.py").write_text("")
    _git(root, "init", "-q")
    _git(root, "add", ".")
    _git(root, "commit", "-q", "-m", "init")
    return root


def test_run_info_records_the_package_version_and_this_checkouts_commit():
    from importlib.metadata import version

    from fleet_torchrl.utils.runinfo import run_info

    info = run_info()
    assert info["version"] == version("fleet_torchrl") == info["packages"]["fleet_torchrl"]
    head = _git(ROOT, "rev-parse", "HEAD")
    assert info["git_commit"] in (head, f"{head}-dirty")


def test_run_info_records_what_decides_the_cpus_floating_point_sums(monkeypatch):
    """DQN training diverges where oneMKL takes another code branch, so a run records the CPU
    model, oneMKL's pinned branch (``MKL_CBWR``) and torch's vector instructions."""
    import torch

    from fleet_torchrl.utils.runinfo import machine_info, machine_summary, run_info

    monkeypatch.setenv("MKL_CBWR", "COMPATIBLE")
    m = run_info()["machine"]
    assert m["mkl_cbwr"] == "COMPATIBLE"
    assert m["torch_cpu_capability"] == torch.backends.cpu.get_cpu_capability()
    monkeypatch.delenv("MKL_CBWR")
    assert machine_info()["mkl_cbwr"] is None
    if m["cpu_model"]:
        assert f"({m['cpu_model']})" in machine_summary()


def test_git_commit_is_only_the_projects_own(tmp_path):
    """An installed copy inside another repository (a user's project with its virtualenv)
    records no commit; so does one inside a clone of this project that is not that clone's
    package folder (a wheel installed in its .venv); a checkout records its HEAD."""
    from fleet_torchrl.utils.runinfo import git_commit

    other = _repo(tmp_path / "other", "someone_else", None)
    installed = other / ".venv" / "lib" / "site-packages" / "fleet_torchrl"
    installed.mkdir(parents=True)
    assert git_commit(installed) is None
    clone = _repo(tmp_path / "clone", "fleet_torchrl", "fleet_torchrl")
    wheel = clone / ".venv" / "lib" / "site-packages" / "fleet_torchrl"
    wheel.mkdir(parents=True)
    assert git_commit(wheel) is None
    head = _git(clone, "rev-parse", "HEAD")
    assert git_commit(clone / "fleet_torchrl") == head
    (clone / "fleet_torchrl" / "__init__.py").write_text("x = 1\n")  # a tracked change
    git_commit.cache_clear()
    assert git_commit(clone / "fleet_torchrl") == f"{head}-dirty"
    assert git_commit(tmp_path) is None  # no repository at all
