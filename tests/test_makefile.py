"""The make targets pass their arguments on (dry runs: nothing is executed)."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _dry(*args: str) -> str:
    if shutil.which("make") is None:
        pytest.skip("make is not installed")
    r = subprocess.run(["make", "-n", "-C", str(ROOT), *args], capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 0, r.stderr
    return r.stdout


def test_tensorboard_takes_args():
    out = _dry("tensorboard", "ARGS=--port 6007 --bind_all")
    assert ("tensorboard --logdir_spec outputs:outputs,multirun:multirun --port 6007 "
            "--bind_all") in out


def test_quick_runs_the_table_with_the_quick_preset():
    assert "fleet_torchrl.table +experiment=quick" in _dry("quick")
