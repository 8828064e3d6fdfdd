"""The package ships its configs: a wheel holds every YAML of ``fleet_torchrl/conf``."""

from __future__ import annotations

import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from fleet_torchrl.config import CONF_DIR

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_wheel_contains_every_config(tmp_path):
    src = tmp_path / "src"  # build from a copy: no build/ folder in the checkout
    shutil.copytree(ROOT / "fleet_torchrl", src / "fleet_torchrl",
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
    assert "fleet_torchrl/sim/site.py" in names and "fleet_torchrl/agents/registry.py" in names
