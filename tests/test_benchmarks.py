"""The repository's development tools (benchmarks/, outside the package): the A/B benchmark
of two source trees runs each tree in its own process; the planner study runs; the
training-collection benchmark pairs runs that do the same work."""

from __future__ import annotations

import importlib.util
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _tool(name: str):
    """A module of benchmarks/ (a folder of scripts, not an installed package)."""
    spec = importlib.util.spec_from_file_location(name, ROOT / "benchmarks" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


bench_ab = _tool("bench_ab")


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


def test_the_planner_study_rows_pair_the_planner_with_its_base():
    """The study behind the planner's defaults (docs/PLANNER.md) runs from benchmarks/: one
    row per site and setting, the planner paired with the heuristic on the same sites."""
    planner_study = _tool("planner_study")
    setting = dict(rollouts=4, horizon=40, energy_value=0.02, confidence=1.5)
    rows = planner_study.study([setting], sites={"default": {}}, n_sims=4, ticks=200,
                               log=lambda *a: None)
    assert len(rows) == 1 and rows[0]["site"] == "default" and rows[0]["rollouts"] == 4
    assert 0 <= rows[0]["changed_share"] <= 1 and rows[0]["us_per_decision"] > 0
    table = planner_study.markdown(rows).splitlines()
    assert len(table) == 3 and table[2].startswith("| default | 4 | 40 | 0.02 | 1.5 |")


def test_the_collector_benchmark_pairs_runs_that_do_the_same_work(capsys):
    """benchmarks/bench_collector.py: DQN rounds stepped by the
    training loop and collected by TorchRL's Collector, alternated; the two did the same
    work (frames, gradient steps, epsilon and weights, checked bit for bit) or it fails."""
    import torch

    bench = _tool("bench_collector")
    assert bench.main(["0"]) == 2 and bench.main(["x"]) == 2  # the usage line
    assert "usage" in capsys.readouterr().err
    threads = torch.get_num_threads()
    assert bench.main(["2", "1", "4", "5", "2"]) == 0
    assert torch.get_num_threads() == threads  # its 2 threads do not outlive it
    out = [line for line in capsys.readouterr().out.splitlines() if "[torchrl]" not in line]
    assert [line.split()[2] for line in out[:4]] == ["loop", "collector", "collector", "loop"]
    assert all(float(line.split()[3]) > 0 for line in out[:4])
    assert out[4].startswith("loop") and out[5].startswith("collector")
    assert out[6].startswith("collector / loop: median") and "2 pair(s)" in out[6]
