"""fleet-compare: several results against a baseline in trips, queue and failures with paired
intervals (checked by hand on tiny made-up results), the files and the figure of ``out=``,
the robust axis of the box plots, and tab completion offering only compare's settings."""

from __future__ import annotations

import csv
import hashlib
import json
import math
import os
import subprocess
import sys

import pytest

from fleet_torchrl.evaluation.results import (
    compare_results,
    format_comparison,
    paired_comparison,
    paired_failure_difference,
)

T3 = 3.1824463  # Student's t, two-sided 95 %, 3 degrees of freedom (published tables)
SITE = {"name": "tiny", "p_c": 0.8}


def result(policy, trips, queue, failed, seed=0, ticks=50, site=SITE):
    n = len(trips)
    return {"policy": policy, "seed": seed, "n_sims": n, "ticks": ticks, "site": dict(site),
            "records": {"trips": trips, "queue": queue, "failed": failed,
                        "ticks_survived": [ticks] * n}}


BASE = result("rule", [10, 12, 8, 10], [5, 3, 4, 4], [False] * 4)
BETTER = result("better", [11, 12, 9, 12], [4, 3, 2, 3], [True, False, False, False])
WORSE = result("worse", [9, 11, 8, 8], [6, 3, 5, 4], [False] * 4)


@pytest.fixture
def files(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    for r in (BASE, BETTER, WORSE):
        (tmp_path / f"{r['policy']}.json").write_text(json.dumps(r))
    return tmp_path


def test_trips_queue_and_failures_against_a_baseline_by_hand():
    """Trips: differences 1, 0, 1, 2 (mean 1, sd sqrt(2/3)); baseline mean 10, so +10 % ±
    t(3) sqrt(2/3) / 2 * 10 %. Queue: differences -1, 0, -2, -1, the same spread. Failures:
    the result failed on one site, the baseline on none (Agresti-Min by hand below)."""
    row = paired_comparison(BETTER, BASE)
    half = T3 * math.sqrt(2 / 3) / 2
    assert row["trips_mean"] == 11.0 and row["baseline_trips_mean"] == 10.0
    assert row["gain_pct"] == pytest.approx(10.0)
    assert row["gain_ci95"] == pytest.approx(10 * half, rel=1e-6)
    assert row["queue_mean"] == 3.0 and row["baseline_queue_mean"] == 4.0
    assert row["queue_diff"] == pytest.approx(-1.0)
    assert row["queue_diff_ci95"] == pytest.approx(half, rel=1e-6)
    assert row["failure_rate"] == 0.25 and row["baseline_failure_rate"] == 0.0
    assert row["failure_diff"] == 0.25
    # one discordant site of 4: cells + 1/2 over n + 2 = 6: p10 = 1.5/6, p01 = 0.5/6
    p10, p01 = 1.5 / 6, 0.5 / 6
    d = p10 - p01
    h = 1.959964 * math.sqrt((p10 + p01 - d * d) / 6)
    assert row["failure_diff_lo"] == pytest.approx(d - h, abs=1e-6)  # -0.2756
    assert row["failure_diff_hi"] == pytest.approx(d + h, abs=1e-6)  # +0.6090
    assert row["failure_diff_lo"] == pytest.approx(-0.27564, abs=1e-4)
    assert row["trips_diff"] == [1.0, 0.0, 1.0, 2.0]


def test_the_failure_interval_does_not_shrink_to_nothing_without_a_difference():
    import torch

    none = torch.zeros(100, dtype=torch.bool)
    f = paired_failure_difference(none, none)
    assert f["failure_diff"] == 0.0
    assert f["failure_diff_hi"] == pytest.approx(1.959964 / 102, rel=1e-5)
    assert f["failure_diff_lo"] == pytest.approx(-1.959964 / 102, rel=1e-5)
    both = torch.ones(100, dtype=torch.bool)  # both failed everywhere: no difference either
    assert paired_failure_difference(both, both)["failure_diff"] == 0.0
    all_only_result = paired_failure_difference(both, none)
    assert all_only_result["failure_diff"] == 1.0 and all_only_result["failure_diff_hi"] == 1.0
    assert 0.9 < all_only_result["failure_diff_lo"] < 1.0


def test_several_results_in_one_table(files):
    comp = compare_results(["better.json", "worse.json"], "rule.json")
    assert [r["label"] for r in comp["rows"]] == ["better", "worse"]
    assert comp["baseline"] == {"policy": "rule", "file": "rule.json", "trips_mean": 10.0,
                                "queue_mean": 4.0, "failure_rate": 0.0}
    worse = comp["rows"][1]
    assert worse["gain_pct"] == pytest.approx(-10.0)  # differences -1, -1, 0, -2
    assert worse["queue_diff"] == pytest.approx(0.5)  # 1, 0, 1, 0
    assert worse["failure_diff"] == 0.0
    lines = format_comparison(comp).splitlines()
    assert len(lines) == 5 and lines[2].startswith("| rule (baseline) | 10.00 |")
    assert lines[3].startswith("| better | 11.00 | +10.00 | 12.99 | 3.00 | -1.00 | 1.30 | "
                               "0.250 | +0.250 | [-0.276, +0.609] |")
    assert lines[4].startswith("| worse | 9.00 | -10.00 |")
    # the same policy twice: told apart by file, the same file twice by number
    twice = compare_results(["better.json", "better.json"], "rule.json")
    assert [r["label"] for r in twice["rows"]] == ["better (better.json) #1",
                                                   "better (better.json) #2"]


@pytest.mark.parametrize("change,what", [
    ({"seed": 1}, "seed differs (1 vs 0)"),
    ({"ticks": 60}, "ticks differs (60 vs 50)"),
    ({"site": {**SITE, "p_c": 0.6}}, "site differs (p_c: 0.6 vs 0.8)"),
])
def test_a_file_that_does_not_pair_is_named_with_what_differs(files, change, what):
    (files / "other.json").write_text(json.dumps({**WORSE, **change}))
    with pytest.raises(ValueError) as e:
        compare_results(["better.json", "other.json"], "rule.json")
    msg = str(e.value)
    assert msg.startswith("other.json cannot be paired with the baseline rule.json: ")
    assert what in msg and "\n" not in msg


def test_compare_writes_its_table_and_figure_and_never_overwrites(files, command, capsys):
    from fleet_torchrl.compare import main

    args = ["results=[better.json,worse.json]", "baseline=rule.json", "out=cmp/c.json"]
    assert command(main, *args) == 0
    out = capsys.readouterr().out
    assert "| better | 11.00 | +10.00 |" in out and "wrote cmp/c.json, cmp/c.csv, cmp/c.png" in out
    js = json.loads((files / "cmp" / "c.json").read_text())
    assert js["kind"] == "fleet-compare" and js["n_sims"] == 4 and js["site"] == SITE
    assert [r["trips_diff"] for r in js["rows"]] == [[1, 0, 1, 2], [-1, -1, 0, -2]]
    text = (files / "cmp" / "c.csv").read_text()
    assert js["csv_sha256"] == hashlib.sha256(text.encode()).hexdigest()
    rows = list(csv.DictReader(text.splitlines()))
    assert [r["label"] for r in rows] == ["better", "worse"]
    assert float(rows[0]["gain_pct"]) == pytest.approx(10.0)
    assert float(rows[1]["queue_diff"]) == pytest.approx(0.5)
    png = (files / "cmp" / "c.png").read_bytes()
    assert png.startswith(b"\x89PNG") and js["figure_sha256"] == hashlib.sha256(png).hexdigest()
    assert not [p for p in (files / "cmp").iterdir() if p.name.endswith(".tmp")]

    before = {p.name: p.stat().st_mtime_ns for p in (files / "cmp").iterdir()}
    assert command(main, *args) == 2  # exists: refused, nothing rewritten
    err = capsys.readouterr().err
    assert "out=cmp/c.json is invalid" in err and "overwrite=true" in err
    assert {p.name: p.stat().st_mtime_ns for p in (files / "cmp").iterdir()} == before
    assert command(main, "result=worse.json", "baseline=rule.json", "out=cmp/c.json",
                   "overwrite=true") == 0
    assert [r["policy"] for r in json.loads((files / "cmp" / "c.json").read_text())["rows"]] \
        == ["worse"]
    # overwrite=true never replaces what is compared, nor a file that is no comparison
    for out in ("rule.json", "better.json"):
        assert command(main, "result=worse.json", "baseline=rule.json", f"out={out}",
                       "overwrite=true") == 2
        assert json.loads((files / out).read_text())["records"]
    (files / "other.json").write_text('{"mine": 1}')
    assert command(main, "result=worse.json", "baseline=rule.json", "out=other.json",
                   "overwrite=true") == 2
    assert "no comparison" in capsys.readouterr().err
    assert (files / "other.json").read_text() == '{"mine": 1}'


def test_compare_prints_without_out_and_writes_nothing(files, command, capsys):
    from fleet_torchrl.compare import main

    before = sorted(os.listdir(files))
    assert command(main, "result=better.json", "baseline=rule.json") == 0
    out = capsys.readouterr().out
    assert "better vs rule: +10.00 % trips (95% CI ± 12.99), queue -1.00 (± 1.30)" in out
    assert sorted(os.listdir(files)) == before


def test_the_settings_of_compare_are_validated():
    from fleet_torchrl.experiments.config import CompareConfig
    from fleet_torchrl.utils.checks import ConfigError

    assert CompareConfig(results=["a.json", "b.json"], baseline="r.json").validate().files() \
        == ["a.json", "b.json"]
    assert CompareConfig(result="a.json", baseline="r.json").validate().files() == ["a.json"]
    for kw, msg in (({"result": "a", "results": ["b"]}, "results="),
                    ({"results": []}, "results=[]"), ({"result": "a", "out": ""}, "out=''"),
                    ({"result": "a", "baseline": None}, "baseline=null")):
        with pytest.raises(ConfigError, match=msg.replace("[", r"\[").replace("]", r"\]")):
            CompareConfig(**{"baseline": "r.json", **kw}).validate()


# ---------------------------------------------------------------- the figures' robust axis
def _rows(outlier: bool):
    import random

    rng = random.Random(0)
    rows = {f"p{i}": [rng.gauss(0.5 * i, 2.0) for _ in range(200)] for i in range(5)}
    if outlier:  # a policy that fails in most simulations: tens of % below every other row
        rows["fails"] = [rng.gauss(-50.0, 5.0) for _ in range(200)]
    return rows


def test_the_axis_limits_ignore_an_outlier_row():
    import numpy as np

    from fleet_torchrl.utils.plotting import robust_limits

    lo, hi = robust_limits(_rows(outlier=True))
    assert (lo, hi) == pytest.approx(robust_limits(_rows(outlier=False)))
    assert -8 < lo < -4 and 5 < hi < 10
    pooled = np.concatenate([np.array(v) for v in _rows(outlier=True).values()])
    assert np.percentile(pooled, 1) < -40  # pooled quantiles would have kept it


def test_the_axis_limits_ignore_a_rows_own_outliers_and_keep_the_baseline():
    from fleet_torchrl.utils.plotting import robust_limits, whisker_span

    row = [1.0, 2.0, 2.0, 3.0, 3.0, 3.0, 4.0, 4.0, 5.0, -60.0]  # one failed simulation
    assert whisker_span(row) == (1.0, 5.0)
    # the whiskers 1 to 5, the baseline's 0 kept in view, a margin of 0.5
    assert robust_limits([row]) == pytest.approx((-0.5, 5.5))
    # rows at 10 to 12: 0 lies beyond three widths (6) of them, so it is not kept
    assert robust_limits([[10.0, 11.0, 12.0]] * 3) == pytest.approx((9.5, 12.5))
    assert robust_limits([[2.0, 3.0, 4.0]] * 3) == pytest.approx((-0.5, 4.5))
    lo, hi = robust_limits([[0.0, 1.0], [-50.0, -49.0]])  # two rows: nothing typical, both
    assert lo < -50 and hi > 1
    assert robust_limits([]) == (-1.0, 1.0)


def test_the_box_plots_mark_and_count_what_lies_beyond_the_axis():
    import matplotlib.pyplot as plt

    from fleet_torchrl.utils.plotting import (
        plot_gain_boxplot,
        plot_paired_differences,
        robust_limits,
    )

    rows = _rows(outlier=True)
    fig = plot_gain_boxplot(rows, "t")
    ax = fig.axes[0]
    assert ax.get_ylim() == pytest.approx(robust_limits(rows))
    labels = [t.get_text() for t in ax.get_xticklabels()]
    assert labels[-1].startswith("fails\n200 below, median -")
    assert float(labels[-1].rsplit(" ", 1)[1]) == pytest.approx(-50, abs=1.5)
    below = sum(1 for v in rows["p0"] if v < ax.get_ylim()[0])
    assert (f"{below} below" in labels[0]) == (below > 0)
    plt.close(fig)
    fig = plot_paired_differences({"a": [1.0, 2.0, 3.0], "b": [-1.0, 0.0, 40.0]}, "rule", "t")
    ax = fig.axes[0]
    assert ax.get_ylabel() == "trips minus rule's, per site"
    assert [t.get_text() for t in ax.get_xticklabels()] == ["a", "b"]  # 40 is a whisker here
    plt.close(fig)


# ---------------------------------------------------------------- tab completion
def _complete(line: str) -> list[str]:
    r = subprocess.run([sys.executable, "-m", "fleet_torchrl.compare", "-sc", "query=bash"],
                       env={**os.environ, "COMP_LINE": line}, capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0, r.stderr
    return r.stdout.split()


def test_completion_offers_only_what_compare_accepts():
    """Hydra's completion offers every group of the app's config folder: compare's own
    folder has none of the model's (agent=, site= ... were offered, then refused)."""
    words = _complete("fleet-compare ")
    # (Hydra offers a list-typed setting as "results.")
    for setting in ("result=", "results.", "baseline=", "out=", "overwrite="):
        assert setting in words, words
    assert not [w for w in words if w.split("=")[0] in ("agent", "site", "state", "eval",
                                                         "train", "mdp", "network")], words
    assert _complete("fleet-compare agent=") == []
    assert _complete("fleet-compare res") == ["result=", "results."]
