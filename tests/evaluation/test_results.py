"""Result files, paired comparison and the compare command."""

from __future__ import annotations

import csv
import json

import pytest
import torch

from fleet_torchrl.agents import HeuristicPolicy, RulePolicy
from fleet_torchrl.evaluation import (
    compare,
    evaluate_policy,
    gain_over,
    load_result,
    save_result,
)
from fleet_torchrl.sim import SiteConfig


def test_result_files_and_pairwise_comparison(tmp_path):
    site = SiteConfig()
    rule = evaluate_policy(RulePolicy(), site, 40, 2000, seed=0)
    heur = evaluate_policy(HeuristicPolicy(), site, 40, 2000, seed=0)
    for key in ("policy", "n_sims", "ticks", "seed", "trips_mean", "trips_std", "queue_mean",
                "queue_std", "failure_rate", "ticks_survived_mean", "site"):
        assert key in rule
    js, cs = save_result(rule, tmp_path / "rule.json")
    save_result(heur, tmp_path / "heur.json")
    assert load_result(js)["trips_mean"] == rule["trips_mean"]
    rows = list(csv.DictReader(cs.open()))
    assert len(rows) == 40 and set(rows[0]) == {"sim", "trips", "queue", "failed",
                                                "ticks_survived"}
    g = compare(tmp_path / "heur.json", js)
    diff = torch.tensor(heur["records"]["trips"]) - torch.tensor(rule["records"]["trips"])
    assert g["gain_pct"] == pytest.approx(100 * diff.double().mean().item() / rule["trips_mean"])
    assert g["gain_ci95"] > 0 and len(g["per_sim_gain_pct"]) == 40
    assert gain_over(rule, rule)["gain_pct"] == 0.0
    bad = dict(rule, seed=1)
    with pytest.raises(ValueError, match="seed differs"):
        gain_over(heur, bad)
    other_site = evaluate_policy(RulePolicy(), SiteConfig(p_c=0.6), 40, 2000, seed=0)
    with pytest.raises(ValueError, match="site differs"):
        gain_over(heur, other_site)
    with pytest.raises(FileNotFoundError):
        load_result(tmp_path / "missing.json")
    (tmp_path / "junk.json").write_text("{not json")
    with pytest.raises(ValueError, match="not valid JSON"):
        load_result(tmp_path / "junk.json")


def test_compare_cli(tmp_path, command, capsys):
    from fleet_torchrl.compare import main

    site = SiteConfig()
    save_result(evaluate_policy(RulePolicy(), site, 20, 800, seed=0), tmp_path / "r.json")
    save_result(evaluate_policy(HeuristicPolicy(), site, 20, 800, seed=0), tmp_path / "h.json")
    assert command(main, f"result={tmp_path / 'h.json'}", f"baseline={tmp_path / 'r.json'}") == 0
    assert "heuristic vs rule: +" in capsys.readouterr().out
    assert command(main, f"result={tmp_path / 'h.json'}",
                   f"baseline={tmp_path / 'nope.json'}") == 2
    assert command(main, f"result={tmp_path / 'h.json'}") == 2  # no baseline: one line


def test_gain_over_a_baseline_without_trips_is_a_clear_error():
    from fleet_torchrl.evaluation import gain_over

    base = {"policy": "stuck", "seed": 0, "n_sims": 2, "ticks": 10, "site": {},
            "records": {"trips": [0, 0]}}
    res = {**base, "policy": "rule", "records": {"trips": [3, 4]}}
    with pytest.raises(ValueError, match="stuck.*completed no trips"):
        gain_over(res, base)


def test_bad_output_paths_fail_before_the_simulation(tmp_path):
    """A directory in the way or a folder that cannot be written: one line, exit 2, at once
    (1000 x 10 000 would take seconds; the error comes before any simulation, and before
    Hydra makes the run folder)."""
    import subprocess
    import sys
    import time

    (tmp_path / "taken.json").mkdir()
    for out, msg in ((tmp_path / "taken.json", "it is a folder"),
                     (tmp_path / "x.txt", "allowed a path ending in .json")):
        t0 = time.perf_counter()
        r = subprocess.run([sys.executable, "-m", "fleet_torchrl.evaluate", "eval.n_sims=100000",
                            f"eval.out={out}", f"hydra.run.dir={tmp_path / 'run'}"],
                           capture_output=True, text=True, timeout=120)
        assert r.returncode == 2 and msg in r.stderr.strip().splitlines()[-1], r.stderr
        assert r.stderr.count("error:") == 1 and time.perf_counter() - t0 < 60
        assert not (tmp_path / "run").exists()
    from fleet_torchrl.evaluation.results import check_result_path

    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    try:
        if not __import__("os").access(locked, __import__("os").W_OK):  # not as root
            with pytest.raises(ValueError, match="is not writable"):
                check_result_path(locked / "r.json")
    finally:
        locked.chmod(0o700)


def test_result_json_and_csv_are_one_unit(tmp_path, monkeypatch):
    """The JSON names its CSV's hash: a CSV written by a killed or a concurrent writer beside
    another run's JSON is detected."""
    from fleet_torchrl.evaluation import check_result_pair
    from fleet_torchrl.evaluation import results as results_mod

    site = SiteConfig()
    rule = evaluate_policy(RulePolicy(), site, 8, 500, seed=0)
    heur = evaluate_policy(HeuristicPolicy(), site, 8, 500, seed=0)
    js, _ = save_result(rule, tmp_path / "r.json")
    assert check_result_pair(js)["trips_mean"] == rule["trips_mean"]

    def killed(*args, **kwargs):  # the writer dies between the CSV and the JSON
        raise KeyboardInterrupt

    monkeypatch.setattr(results_mod, "write_json", killed)
    with pytest.raises(KeyboardInterrupt):
        save_result(heur, js)
    assert load_result(js)["policy"] == "rule"  # the old JSON is intact ...
    with pytest.raises(ValueError, match="does not belong to"):
        check_result_pair(js)  # ... and the new CSV beside it is told apart


def test_strata_of_a_site_distribution_and_the_worst_stratum_gain():
    from fleet_torchrl.evaluation import site_strata, worst_stratum_gain
    from fleet_torchrl.sim import Site, SiteRanges

    assert list(site_strata(SiteConfig(), 10, 0)) == ["all"]
    cfg = SiteConfig(ranges=SiteRanges(n_vehicles=[2, 4], t_c=[10, 40])).validate()
    strata = site_strata(cfg, 600, 5)
    assert list(strata) == ["n_vehicles=2", "n_vehicles=3", "n_vehicles=4", "t_c:10-20",
                            "t_c:20-30", "t_c:30-40"]
    p = Site(cfg).draw_params(5, torch.arange(600))
    for name in ("n_vehicles", "t_c"):  # each simulation in exactly one stratum per parameter
        own = torch.stack([m for k, m in strata.items() if k.startswith(name)])
        assert (own.sum(0) == 1).all()
    assert torch.equal(strata["n_vehicles=3"], p.n_vehicles == 3)
    assert torch.equal(strata["t_c:30-40"], p.t_c >= 30)
    base = {"records": {"trips": [100] * 600}}
    better = {"records": {"trips": [101] * 600}}
    worse_on_4 = {"records": {"trips": torch.where(p.n_vehicles == 4, 99, 102).tolist()}}
    assert worst_stratum_gain(better, base, strata) == pytest.approx((1.0, "n_vehicles=2"))
    g, where = worst_stratum_gain(worse_on_4, base, strata)
    assert where == "n_vehicles=4" and g == pytest.approx(-1.0)


def test_strata_below_flags_only_a_significant_loss_and_guarded_selection_ranks_it_last():
    """``strata_below``: where the paired difference's 95 % interval lies under 0; a loss
    within the noise is not flagged. ``train.select=guarded`` ranks a flagged snapshot below
    every unflagged one, whatever their objective scores."""
    from fleet_torchrl.evaluation import site_strata, strata_below
    from fleet_torchrl.sim import Site, SiteRanges
    from fleet_torchrl.training.progress import selection_score

    cfg = SiteConfig(ranges=SiteRanges(n_vehicles=[2, 4])).validate()
    strata = site_strata(cfg, 300, 1)
    on_4 = Site(cfg).draw_params(1, torch.arange(300)).n_vehicles == 4
    noise = torch.where(torch.arange(300) % 2 == 0, 3, -3)
    base = {"records": {"trips": (100 + noise).tolist()}}
    loses_on_4 = {"records": {"trips": (100 + noise - 2 * on_4).tolist()}}
    noisy = {"records": {"trips": (100 + 2 * noise.roll(1)).tolist()}}  # mean 0, spread 6
    assert strata_below(base, base, strata) == []
    assert strata_below(loses_on_4, base, strata) == ["n_vehicles=4"]
    assert strata_below(noisy, base, strata) == []
    res = {"trips_mean": 400.0, "queue_mean": 10.0}
    flagged = selection_score("guarded", "trips", {**res, "trips_mean": 500.0},
                              below=["n_vehicles=4"])
    assert selection_score("guarded", "trips", res) == selection_score("objective", "trips", res)
    assert flagged < selection_score("guarded", "trips", res)


# two-sided 95 % quantiles of Student's t from published tables (not from scipy)
T_TABLE = {1: 12.7062047, 7: 2.3646243, 10: 2.2281389, 11: 2.2009852, 29: 2.0452296,
           999: 1.9623414}


def test_t_quantiles_are_students_for_any_degrees_of_freedom():
    from fleet_torchrl.evaluation.results import t95

    for dof, t in T_TABLE.items():
        assert t95(dof) == pytest.approx(t, abs=1e-6), dof
    with pytest.raises(ValueError, match="degree of freedom"):
        t95(0)


@pytest.mark.parametrize("n", [2, 11, 12, 30])
def test_seed_interval_is_a_student_t_interval(n):
    """12 seeds used the normal's 1.96 (the old table stopped at 10 dof): 11 % too narrow."""
    from fleet_torchrl.evaluation import seed_interval

    values = [1.0 + 0.37 * ((7 * k) % 5) - 0.1 * k for k in range(n)]
    x = torch.tensor(values, dtype=torch.float64)
    half = T_TABLE[n - 1] * float(x.std()) / n ** 0.5
    out = seed_interval(values)
    assert out["ci95"] == pytest.approx(half, rel=1e-6)
    assert out["mean"] == pytest.approx(float(x.mean())) and out["n"] == n


def test_paired_gain_interval_is_a_paired_t_interval(tmp_path, capsys, command):
    """At 8 simulations ``compare`` printed ±3.60 with 1.96 where the paired t gives ±4.34."""
    from fleet_torchrl.compare import main

    other = {"queue": [0] * 8, "failed": [False] * 8, "ticks_survived": [10] * 8}
    base = {"policy": "rule", "seed": 0, "n_sims": 8, "ticks": 10, "site": {"name": "s"},
            "records": {"trips": [100, 102, 98, 101, 99, 103, 97, 100], **other}}
    res = {**base, "policy": "better",
           "records": {"trips": [104, 101, 99, 108, 97, 107, 99, 106], **other}}
    diff = torch.tensor(res["records"]["trips"], dtype=torch.float64) - torch.tensor(
        base["records"]["trips"], dtype=torch.float64)
    # baseline mean 100 trips: the half-width in % of it is the half-width in trips
    want = T_TABLE[7] * float(diff.std()) / 8 ** 0.5
    assert gain_over(res, base)["gain_ci95"] == pytest.approx(want, rel=1e-6)
    for name, r in (("a", res), ("b", base)):
        (tmp_path / f"{name}.json").write_text(json.dumps(r))
    assert command(main, f"result={tmp_path / 'a.json'}", f"baseline={tmp_path / 'b.json'}") == 0
    assert f"(95% CI ± {want:.2f})" in capsys.readouterr().out


def test_a_result_names_its_csv_and_a_renamed_pair_is_told_apart(tmp_path):
    from fleet_torchrl.evaluation import check_result_pair

    res = evaluate_policy(RulePolicy(), site_cfg=SiteConfig(), n_sims=3, ticks=50, seed=0)
    js, cs = save_result(res, tmp_path / "a.json")
    assert json.loads(js.read_text())["csv"] == "a.csv"
    (tmp_path / "b.json").write_bytes(js.read_bytes())  # a copy beside a copied CSV
    (tmp_path / "b.csv").write_bytes(cs.read_bytes())
    with pytest.raises(ValueError, match="names its CSV 'a.csv'"):
        check_result_pair(tmp_path / "b.json")


def test_temp_files_of_a_gone_writer_go_with_the_next_write(tmp_path):
    """A temp file carries its writer's process id: the next write of the same target
    removes the ones whose process is gone, never a live writer's nor another target's."""
    import os
    import subprocess
    import sys

    from fleet_torchrl.utils.runinfo import temp_prefix, write_json

    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    dead = tmp_path / f"{temp_prefix(tmp_path / 'r.json', gone.pid)}abc.tmp"
    live = tmp_path / f"{temp_prefix(tmp_path / 'r.json', os.getppid())}abc.tmp"
    other = tmp_path / f"{temp_prefix(tmp_path / 'q.json', gone.pid)}abc.tmp"
    for p in (dead, live, other):
        p.write_text("partial")
    write_json(tmp_path / "r.json", {"a": 1})
    assert not dead.exists() and live.exists() and other.exists()
