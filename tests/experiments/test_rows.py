"""The experiments' candidate and row types, and the sweep cache's key version."""

from __future__ import annotations

import math

import pytest
import torch

from fleet_torchrl.experiments.rows import POINT_FIELDS, TABLE_FIELDS, Candidate, Row


def _res(trips: list[float], failure_rate: float = 0.0, queue: float = 3.0,
         policy: str = "p") -> dict:
    """An evaluation result as evaluate_with returns it (the fields the rows read)."""
    t = torch.tensor(trips, dtype=torch.float64)
    return {"policy": policy, "seed": 0, "n_sims": len(trips), "ticks": 100,
            "site": {"name": "default"}, "trips_mean": float(t.mean()),
            "trips_std": float(t.std()), "queue_mean": queue, "failure_rate": failure_rate,
            "records": {"trips": t}}


RULE = _res([100.0, 102.0, 98.0, 100.0])
HEUR = _res([104.0, 105.0, 101.0, 102.0])


def test_a_baseline_row_renders_as_the_table_and_the_sweeps_wrote_it():
    row = Row.of("heuristic", {None: HEUR}, RULE, HEUR)
    d = row.table_dict()
    assert list(d) == list(TABLE_FIELDS[:-2])  # no improvement columns: none ran
    assert d["seeds"] == [] and d["gain_per_seed"] == [] and d["train_time_s"] == []
    assert d["gain_pct"] == pytest.approx(3.0) and d["gain_min"] == d["gain_pct"]
    assert d["gain_vs_heuristic_pct"] == 0.0 and d["objective"] == ""
    line = row.table_markdown()
    assert line.startswith("| heuristic | - | - | - | 103.00 | 3.00 | 0.000 | +3.00 | ")
    assert line.endswith(" | - | +0.00 | - | - |")
    s = row.sweep_dict("p_c", 0.8)
    assert list(s) == ["policy", "seeds", "gain_per_seed", "trips_mean", "trips_std",
                       "queue_mean", "failure_rate", "failure_rate_max", "gain_pct",
                       "gain_ci95", "improvement_pct", "improvement_ci95", "improvement_sims",
                       "improvement_seed", "param", "value", "share_of_best_known_pct"]
    assert set(s) == set(POINT_FIELDS)
    assert s["failure_rate_max"] == 0.0 and s["param"] == "p_c" and s["value"] == 0.8


def test_a_learned_row_is_the_mean_over_its_seeds():
    per_seed = {0: _res([101.0, 103.0, 99.0, 101.0], 0.0), 1: _res([103.0, 105.0, 101.0, 103.0],
                                                                   0.5)}
    row = Row.of("dqn", per_seed, RULE, HEUR, objective="trips", trained_on="this site",
                 train_time_s=[60.0, None])
    assert row.seeds == [0, 1] and row.gain_per_seed == pytest.approx([1.0, 3.0])
    assert row.gain_pct == pytest.approx(2.0) and row.gain_min == pytest.approx(1.0)
    assert row.failure_rate == 0.25 and row.failure_rate_max == 0.5
    line = row.improved({"improvement_pct": 1.5, "improvement_ci95": 0.25}).table_markdown()
    assert line.startswith("| dqn | trips | this site | 0, 1 | 102.00 | 3.00 | 0.250 | +2.00 | ")
    assert line.endswith(" | 12.71 | +1.00, +3.00 | -0.97 | 1.0 min max | +1.50 ± 0.25 |")
    d = row.table_dict()
    assert list(d) == list(TABLE_FIELDS) and d["improvement_pct"] == 1.5
    # a table.json row reads back into the same line (the report's tests write table.md so)
    assert Row.from_table_dict(d).table_markdown() == line


def test_one_seed_has_no_interval_and_best_known_lists_its_improvement_first():
    one = Row.of("specialist_dqn", {3: _res([101.0, 101.0, 101.0, 101.0])}, RULE)
    assert math.isnan(one.gain_ci95)
    assert "| - |" in Row.of("x", {0: HEUR}, RULE, HEUR).table_markdown()  # no interval
    assert one.sweep_dict("t_c", 30)["gain_ci95"] is None
    top = Row.of("best_known", {None: HEUR}, RULE)
    top.seeds = [3]
    d = top.sweep_dict("t_c", 30, best_known=True)
    assert list(d)[3:7] == ["improvement_pct", "improvement_ci95", "improvement_sims",
                            "improvement_seed"]
    assert d["gain_ci95"] is not None and d["seeds"] == [3]
    # no rule at the point: no gains
    assert Row.of("heuristic", {None: HEUR}, None).sweep_dict("p_c", 0.5)["gain_pct"] is None


def test_a_candidate_says_what_it_is_and_its_seeds(tmp_path):
    c = Candidate("dqn_partial", "learned", files={0: tmp_path / "a", 1: tmp_path / "b"})
    assert c.seeds == [0, 1]
    assert Candidate("search_table", "search").seeds == []
    with pytest.raises(ValueError, match="kind='trained'"):
        Candidate("x", "trained")  # type: ignore[arg-type]


def test_the_sweep_cache_key_carries_a_version(monkeypatch):
    """The same inputs give the same key; raising CACHE_VERSION changes it (and the twin's)."""
    from fleet_torchrl.config import compose_config
    from fleet_torchrl.experiments import sweep_keys

    cfg = compose_config(["sweep.search=false", "sweep.specialist=false",
                          "sweep.policies=[rule,heuristic]"])
    planner = compose_config(["agent=planner"]).agent
    args = (cfg.sweep, cfg.table, cfg.eval, cfg.site, {}, {}, planner)
    key, twin = sweep_keys.point_key(*args), sweep_keys.twin_key(*args)
    assert key == sweep_keys.point_key(*args) and twin == sweep_keys.twin_key(*args)
    assert key != twin  # the twin leaves the site's name out
    other = compose_config(["sweep.search=false", "sweep.specialist=false",
                            "sweep.policies=[rule,heuristic]", "sweep.pick_sims=7"])
    assert sweep_keys.point_key(other.sweep, *args[1:]) != key
    monkeypatch.setattr(sweep_keys, "CACHE_VERSION", sweep_keys.CACHE_VERSION + 1)
    assert sweep_keys.point_key(*args) != key and sweep_keys.twin_key(*args) != twin
