"""A miniature sweep end to end through Hydra multirun."""

from __future__ import annotations

import csv
import subprocess
import sys

import pytest

from fleet_torchrl import sweeps_summary


@pytest.mark.slow
def test_miniature_sweep_end_to_end(tmp_path, saved_policies):
    root = saved_policies
    out = tmp_path / "sweeps"
    cmd = [sys.executable, "-m", "fleet_torchrl.sweeps", "-m", "+experiment=sweep_pc",
           "sweep.value=0.4,0.8", "eval.n_sims=16", "eval.ticks=400",
           "sweep.policies=[rule,heuristic,tabular,dqn_partial]",
           f"table.policies_dir={root}", f"sweep.out={out}",
           f"hydra.sweep.dir={tmp_path / 'multirun'}"]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert sorted(p.name for p in (out / "pc").glob("*.json")) == ["p_c=0.4.json", "p_c=0.8.json"]
    assert sweeps_summary.main(["pc", "--out", str(out), "--expect", "p_c=0.4", "p_c=0.8"]) == 0
    rows = list(csv.DictReader((out / "pc.csv").open()))
    assert set(rows[0]) == {"param", "value", "policy", "trips_mean", "trips_std", "queue_mean",
                            "failure_rate", "gain_pct", "gain_ci95"}
    assert len(rows) == 8 and {r["policy"] for r in rows} == {"rule", "heuristic", "tabular",
                                                              "dqn_partial"}
    assert all(float(r["gain_pct"]) == 0.0 for r in rows if r["policy"] == "rule")
    assert (out / "pc.png").stat().st_size > 1000 and (out / "pc.json").exists()
    # a rerun skips the finished points; a point that cannot run is reported, not fatal
    r2 = subprocess.run(cmd[:5] + ["sweep.value=0.8"] + cmd[6:], capture_output=True,
                        text=True, timeout=300)
    assert "exists, skipping" in r2.stdout
    bad = cmd[:5] + ["sweep.value=0.6"] + [c for c in cmd[6:] if "policies_dir" not in c] + [
        f"table.policies_dir={tmp_path / 'nowhere'}"]
    r3 = subprocess.run(bad, capture_output=True, text=True, timeout=300)
    assert r3.returncode == 0 and (out / "pc" / "p_c=0.6.error").exists()
    assert sweeps_summary.main(["pc", "--out", str(out)]) == 1  # failed point reported
