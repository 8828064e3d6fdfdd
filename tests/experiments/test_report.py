"""The report from fixture results."""

from __future__ import annotations

import json

from fleet_torchrl import report
from fleet_torchrl.config import compose_config
from fleet_torchrl.experiments.table import rows_markdown


def test_report_from_fixture_results(tmp_path, command):
    res = tmp_path / "results"
    (res / "table").mkdir(parents=True)
    row = {"policy": "rule", "objective": "", "seeds": [], "trips_mean": 1135.0,
           "trips_std": 13.8, "queue_mean": 500.0, "failure_rate": 0.0, "gain_pct": 0.0,
           "gain_ci95": 0.0, "gain_min": 0.0, "gain_per_seed": [], "gain_vs_heuristic_pct": -2.2,
           "train_time_s": []}
    learned = {**row, "policy": "dqn_all", "objective": "thesis", "trained_on": "this site",
               "seeds": [0, 1, 2],
               "gain_pct": 2.5, "gain_ci95": 0.4, "gain_per_seed": [2.3, 2.5, 2.7],
               "train_time_s": [100.0, 110.0, None]}
    (res / "table" / "table.md").write_text(rows_markdown([row, learned], compose_config([])))
    (res / "table" / "boxplot.png").write_bytes(b"\x89PNG fake")
    (res / "table" / "learning_curves.png").write_bytes(b"\x89PNG fake")
    (res / "sweeps").mkdir()
    pts = [{"param": "p_c", "value": v, "policy": p, "trips_mean": 1.0, "trips_std": 0.1,
            "queue_mean": 0.0, "failure_rate": 0.0, "gain_pct": g, "gain_ci95": 0.3}
           for v in (0.0, 0.8) for p, g in (("rule", 0.0), ("tabular", 1.5))]
    (res / "sweeps" / "pc.json").write_text(json.dumps({"rows": pts, "failed": [],
                                                        "missing": []}))
    (res / "timings.json").write_text(json.dumps({"table": {
        "wall_s": 1500.0, "exit_code": 0, "finished": "2026-11-22T05:00:00+00:00",
        "machine": "x86_64, 2 CPUs"}}))
    out = tmp_path / "docs" / "report.md"
    assert command(report.main, f"results={res}", f"out={out}") == 0
    text = out.read_text()
    assert "| dqn_all | thesis | this site | 0, 1, 2 |" in text and "+2.30, +2.50, +2.70" in text
    assert "| 0.8 | +0.00 ± 0.30 | +1.50 ± 0.30 |" in text
    assert "[TRAINING.md](TRAINING.md)" in text
    assert "`make table` | 25.0 min" in text
    assert "Not run yet: `make sweep-tc`" in text and "Not run yet: `make grid`" in text
    assert (tmp_path / "docs" / "figures" / "boxplot.png").exists()
    assert (tmp_path / "docs" / "figures" / "learning_curves.png").exists()
    before = out.read_text()
    (res / "table" / "table.md").unlink()  # no main comparison: refuse, keep the report
    assert command(report.main, f"results={res}", f"out={out}") == 2
    assert out.read_text() == before
    assert command(report.main, f"results={tmp_path / 'none'}", f"out={out}") == 2
