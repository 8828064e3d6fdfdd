"""The A/B benchmark of two source trees runs each tree in its own process."""

from __future__ import annotations

from pathlib import Path

from fleet_torchrl.experiments import bench_ab

ROOT = Path(__file__).resolve().parents[2]


def test_ab_of_a_tree_against_itself(capsys):
    assert bench_ab.main([]) == 2  # no trees: the usage line
    assert bench_ab.main([str(ROOT), str(ROOT), "1", "8"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert len(out) == 4 and all("decisions/s" in line for line in out)
    assert out[-1].startswith(str(ROOT)) and "median ratio" in out[-1]


def test_ab_of_the_planner_over_a_network(capsys):
    assert bench_ab.main([str(ROOT), str(ROOT), "1", "2", "nope"]) == 2
    assert "allowed one of env, planner" in capsys.readouterr().err
    assert bench_ab.main([str(ROOT), str(ROOT), "1", "2", "planner"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert len(out) == 4 and all("decisions/s" in line for line in out)
    assert "numpy reference" not in out[0] and "median ratio" not in out[-1]
    assert float(out[-1].split("median ")[1].split()[0]) > 0  # the planner decided
