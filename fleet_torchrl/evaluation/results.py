"""Evaluation results: summaries, paired comparison, result files and tables (MODEL §4).

A result is a plain dict (JSON-ready) made by :func:`~fleet_torchrl.evaluation.protocol.
evaluate_policy`: the summary, the per-simulation records and the setup.
"""

from __future__ import annotations

import functools
import hashlib
import math
import os
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from ..sim import Site
from ..utils.checks import ConfigError
from ..utils.paths import check_output
from ..utils.runinfo import csv_text, file_sha256, read_json, write_json, write_text


@functools.cache
def t95(dof: int) -> float:
    """The two-sided 95 % quantile of Student's t with ``dof`` degrees of freedom, for any
    ``dof`` (a table that stops somewhere and falls back to the normal's 1.96 makes the
    intervals of a few more seeds or simulations too narrow: 11 % at 11 dof). scipy is
    imported here, not at import time, to keep the commands' start-up short."""
    from scipy import stats

    if dof < 1:
        raise ValueError(f"Student's t needs at least 1 degree of freedom, got {dof}")
    return float(stats.t.ppf(0.975, dof))


def seed_interval(values: list[float]) -> dict[str, Any]:
    """Mean over training seeds with the half-width of its 95 % interval (Student's t, so
    three seeds give a wide, honest interval); ``nan`` half-width for a single seed."""
    x = torch.tensor(values, dtype=torch.float64)
    n = x.numel()
    if n == 0:
        raise ValueError("no values to summarise")
    half = t95(n - 1) * _std(x) / math.sqrt(n) if n > 1 else float("nan")
    return {"mean": float(x.mean()), "ci95": half, "min": float(x.min()), "max": float(x.max()),
            "n": n}


def _std(x: Tensor) -> float:
    return float(x.double().std(unbiased=True)) if x.numel() > 1 else 0.0


def summarize(records: dict[str, Tensor]) -> dict[str, float]:
    trips, queue = records["trips"].double(), records["queue"].double()
    return {
        "trips_mean": float(trips.mean()),
        "trips_std": _std(trips),
        "queue_mean": float(queue.mean()),
        "queue_std": _std(queue),
        "failure_rate": float(records["failed"].double().mean()),
        "ticks_survived_mean": float(records["ticks_survived"].double().mean()),
    }


# ------------------------------------------------------------------------- strata
def site_strata(site_cfg: Any, n_sims: int, seed: int) -> dict[str, Tensor]:
    """The marginal strata of an evaluation set on a site distribution (MODEL §1.6): for each
    drawn parameter, one ``[n_sims]`` bool mask per value of an integer range of at most five
    values, else per third of its range (``"t_c:10-23.3333"``); a single site is one stratum,
    ``"all"``. Each simulation lies in one stratum per drawn parameter."""
    if not site_cfg.randomized:
        return {"all": torch.ones(n_sims, dtype=torch.bool)}
    p = Site(site_cfg).draw_params(seed, torch.arange(n_sims))
    out: dict[str, Tensor] = {}
    for name in site_cfg.ranges.varied():
        lo, hi = getattr(site_cfg.ranges, name)
        values = getattr(p, name).cpu().double()
        if name != "p_c" and hi - lo + 1 <= 5:
            for v in range(int(lo), int(hi) + 1):
                out[f"{name}={v}"] = values == v
            continue
        cuts = [lo + (hi - lo) * k / 3 for k in range(4)]
        for a, b in zip(cuts[:-1], cuts[1:], strict=True):
            last = b == cuts[-1]
            out[f"{name}:{a:g}-{b:g}"] = (values >= a) & ((values <= b) if last else (values < b))
    return out


def paired_trips(result: dict[str, Any], baseline: dict[str, Any]) -> tuple[Tensor, Tensor]:
    """The per-simulation trips of two results on the same sites (float64, paired by index)."""
    return (torch.tensor(result["records"]["trips"], dtype=torch.float64),
            torch.tensor(baseline["records"]["trips"], dtype=torch.float64))


def worst_stratum_gain(result: dict[str, Any], baseline: dict[str, Any],
                       strata: dict[str, Tensor]) -> tuple[float, str]:
    """The lowest paired trips gain (%) of ``result`` over ``baseline`` in any stratum (each
    stratum's total trips over the baseline's), and that stratum's name."""
    a, b = paired_trips(result, baseline)
    worst = (math.inf, "")
    for name, m in strata.items():
        if bool(m.any()):
            g = 100.0 * (float(a[m].sum()) / max(float(b[m].sum()), 1.0) - 1.0)
            worst = min(worst, (g, name))
    return worst


def strata_below(result: dict[str, Any], baseline: dict[str, Any],
                 strata: dict[str, Tensor]) -> list[str]:
    """The strata in which ``result`` is significantly below ``baseline``: the upper end of
    the paired difference's 95 % interval (per simulation's trips, same sites; Student's t,
    as :func:`gain_over`) under 0."""
    a, b = paired_trips(result, baseline)
    out = []
    for name, m in strata.items():
        d = (a - b)[m]
        n = d.numel()
        if n >= 2 and float(d.mean() + t95(n - 1) * d.std() / n ** 0.5) < 0:
            out.append(name)
    return out


# ------------------------------------------------------------------------- comparison
PAIRING_KEYS = ("seed", "n_sims", "ticks", "site")


def pairing_difference(result: dict[str, Any], baseline: dict[str, Any]) -> str | None:
    """What keeps two results from being paired simulation by simulation (``"seed differs
    (1 vs 0)"``, ``"site differs (p_c: 0.6 vs 0.8)"``, ``"the baseline names no site"``),
    or None: they must come from the same seed, number of simulations, ticks and site. A
    result that names no site pairs with nothing (two such would compare equal)."""
    for who, res in (("the result", result), ("the baseline", baseline)):
        if res.get("site") is None:
            return f"{who} names no site (a result records the site it ran)"
    for key in PAIRING_KEYS:
        x, y = result.get(key), baseline.get(key)
        if x == y:
            continue
        if key != "site":
            return f"{key} differs ({_short(x)} vs {_short(y)})"
        if isinstance(x, dict) and isinstance(y, dict):
            fields = [k for k in dict.fromkeys([*x, *y]) if x.get(k) != y.get(k)]
            shown = ", ".join(f"{k}: {_short(x.get(k))} vs {_short(y.get(k))}"
                              for k in fields[:3])
            more = f" and {len(fields) - 3} more" if len(fields) > 3 else ""
            return f"site differs ({shown}{more})"
        return "site differs"
    return None


def gain_over(result: dict[str, Any], baseline: dict[str, Any]) -> dict[str, Any]:
    """Trips gain of ``result`` over ``baseline`` in percent of the baseline's mean.

    ``gain_pct`` is the mean paired difference over the baseline's mean (equal to the
    difference of means); ``gain_ci95`` is the half-width of its 95% confidence interval
    from the paired differences (paired t: Student's t with ``n - 1`` degrees of freedom,
    which the normal's 1.96 understates at few simulations, by 17 % at 8).
    ``per_sim_gain_pct`` is each simulation's trips as % over the baseline's mean (the
    box-plot quantity of MODEL §5).
    Both results must come from the same seed, number of simulations, ticks and site
    (:func:`pairing_difference`).
    """
    differs = pairing_difference(result, baseline)
    if differs:
        raise ValueError(f"cannot pair {result.get('policy')} with {baseline.get('policy')}: "
                         f"{differs}")
    a, b = paired_trips(result, baseline)
    base_mean = float(b.mean())
    if base_mean <= 0:
        raise ValueError(f"cannot express a gain over {baseline.get('policy')}: it completed no "
                         "trips (mean 0), so a percentage of its trips is undefined")
    diff = a - b
    n = diff.numel()
    half = t95(n - 1) * _std(diff) / math.sqrt(n) if n > 1 else float("nan")
    return {
        "policy": result["policy"],
        "baseline": baseline["policy"],
        "gain_pct": 100.0 * float(diff.mean()) / base_mean,
        "gain_ci95": 100.0 * half / base_mean,
        "per_sim_gain_pct": (100.0 * (a / base_mean - 1.0)).tolist(),
    }


def compare(path_a: str | Path, path_b: str | Path) -> dict[str, Any]:
    """Pairwise comparison of two result files written by :func:`save_result`."""
    return gain_over(load_result(path_a), load_result(path_b))


def paired_interval(diff: Tensor) -> tuple[float, float]:
    """The mean of paired differences and the half-width of its 95 % interval (paired t,
    Student's t with ``n - 1`` degrees of freedom; ``nan`` for a single simulation)."""
    n = diff.numel()
    half = t95(n - 1) * _std(diff) / math.sqrt(n) if n > 1 else float("nan")
    return float(diff.double().mean()), half


Z95 = 1.959963984540054  # the standard normal's two-sided 95 % quantile


def paired_failure_difference(failed: Tensor, base_failed: Tensor) -> dict[str, float]:
    """The difference of two failure rates on the same sites and its 95 % interval.

    ``failure_diff`` is the result's failure rate minus the baseline's, ``(n10 - n01) / n``
    with ``n10`` the sites where only the result failed and ``n01`` those where only the
    baseline did (sites where both or neither failed say nothing about the difference,
    as in McNemar's test). The interval is Agresti and Min's (2005) for matched proportions:
    the Wald interval after adding 1/2 to each of the four cells of the paired 2 x 2 table,
    ``d ± 1.96 sqrt((p10 + p01 - d**2) / (n + 2))`` with ``p10 = (n10 + 1/2) / (n + 2)``,
    ``p01 = (n01 + 1/2) / (n + 2)`` and ``d = p10 - p01``, cut to [-1, 1]. Unlike the plain
    Wald interval (the paired t over 0/±1 differences) it does not shrink to 0 ± 0 when no
    site's outcome differs, and it covers close to 95 % at a few hundred sites and rare
    failures."""
    a, b = failed.bool(), base_failed.bool()
    n = a.numel()
    n10, n01 = int((a & ~b).sum()), int((~a & b).sum())
    m = n + 2
    p10, p01 = (n10 + 0.5) / m, (n01 + 0.5) / m
    d = p10 - p01
    half = Z95 * math.sqrt((p10 + p01 - d * d) / m)
    return {"failure_diff": (n10 - n01) / n, "failure_diff_lo": max(d - half, -1.0),
            "failure_diff_hi": min(d + half, 1.0), "only_result_failed": n10,
            "only_baseline_failed": n01}


def paired_comparison(result: dict[str, Any], baseline: dict[str, Any]) -> dict[str, Any]:
    """``result`` against ``baseline`` on the same sites (:func:`pairing_difference`), in
    trips, queue and failures, each with a paired 95 % interval:

    * ``gain_pct`` ± ``gain_ci95``: the trips gain in % of the baseline's mean
      (:func:`gain_over`, paired t);
    * ``queue_diff`` ± ``queue_diff_ci95``: the mean over sites of the result's queue events
      minus the baseline's (paired t, in queue events per simulation);
    * ``failure_diff`` in [``failure_diff_lo``, ``failure_diff_hi``]: the result's failure
      rate minus the baseline's (:func:`paired_failure_difference`);

    with both sides' means (``trips_mean``, ``baseline_trips_mean``, ...) and ``trips_diff``,
    each site's trips minus the baseline's (the figure's quantity). A figure that is not
    finite (a damaged file that passed no :func:`load_result`) raises ``ValueError``."""
    g = gain_over(result, baseline)
    ra, rb = result["records"], baseline["records"]

    def records(rec: dict[str, Any], key: str) -> Tensor:
        return torch.tensor([float(v) for v in rec[key]], dtype=torch.float64)

    ta, tb = records(ra, "trips"), records(rb, "trips")
    qa, qb = records(ra, "queue"), records(rb, "queue")
    fa, fb = records(ra, "failed") != 0, records(rb, "failed") != 0
    q_diff, q_half = paired_interval(qa - qb)
    row = {"policy": result["policy"], "baseline": baseline["policy"], "n_sims": ta.numel(),
           "trips_mean": float(ta.mean()), "baseline_trips_mean": float(tb.mean()),
           "gain_pct": g["gain_pct"], "gain_ci95": g["gain_ci95"],
           "queue_mean": float(qa.mean()), "baseline_queue_mean": float(qb.mean()),
           "queue_diff": q_diff, "queue_diff_ci95": q_half,
           "failure_rate": float(fa.double().mean()),
           "baseline_failure_rate": float(fb.double().mean()),
           **paired_failure_difference(fa, fb)}
    single = ta.numel() == 1  # one site: no interval of the trips or the queue
    for key, value in row.items():
        if isinstance(value, float) and not math.isfinite(value) and not (
                single and key in ("gain_ci95", "queue_diff_ci95")):
            raise ValueError(f"cannot compare {result['policy']} with {baseline['policy']}: "
                             f"{key} is {value} (the records are not counts of a simulation)")
    row["trips_diff"] = (ta - tb).tolist()
    return row


COMPARISON_KIND = "fleet-compare"  # the ``kind`` of a comparison file (compare ``out=``)


def compare_results(paths: list[str | Path], baseline: str | Path) -> dict[str, Any]:
    """Every result file of ``paths`` against the ``baseline`` file, each a row of
    :func:`paired_comparison` (with its ``file`` and a ``label``: the policy's name, with
    the file's name where two rows would share it). Every file must pair with the baseline
    (same seed, simulations, ticks and site): one that does not is refused in one line
    naming it and what differs. Labels are unique (a file given twice is numbered)."""
    if not paths:
        raise ValueError("no result files to compare")
    base = load_result(baseline)
    results = []
    for path in paths:
        res = load_result(path)
        differs = pairing_difference(res, base)
        if differs:
            raise ValueError(f"{path} cannot be paired with the baseline {baseline}: {differs}")
        results.append(res)
    rows = [{**paired_comparison(res, base), "file": str(path)}
            for path, res in zip(paths, results, strict=True)]
    names = [r["policy"] for r in rows]
    for r in rows:
        r["label"] = r["policy"] if names.count(r["policy"]) == 1 else \
            f"{r['policy']} ({Path(r['file']).name})"
    labels = [r["label"] for r in rows]
    for i, r in enumerate(rows):  # the same file twice: numbered
        if labels.count(r["label"]) > 1:
            r["label"] = f"{r['label']} #{i + 1}"
    tb = torch.tensor([float(v) for v in base["records"]["trips"]], dtype=torch.float64)
    qb = torch.tensor([float(v) for v in base["records"]["queue"]], dtype=torch.float64)
    fb = torch.tensor([float(v) != 0 for v in base["records"]["failed"]], dtype=torch.float64)
    return {"kind": COMPARISON_KIND, "baseline": {
                "policy": base["policy"], "file": str(baseline), "trips_mean": float(tb.mean()),
                "queue_mean": float(qb.mean()), "failure_rate": float(fb.mean())},
            "seed": base["seed"], "n_sims": base["n_sims"], "ticks": base["ticks"],
            "site": base["site"], "rows": rows}


def _cell(value: Any, fmt: str) -> str:
    return "n/a" if value is None or (isinstance(value, float) and math.isnan(value)) \
        else fmt.format(value)


def format_comparison(comparison: dict[str, Any]) -> str:
    """A Markdown table of :func:`compare_results`: the baseline's row, then one row per
    result with its paired differences from the baseline and their 95 % intervals."""
    b = comparison["baseline"]
    head = ["policy", "trips mean", "gain % trips", "± 95% CI", "queue mean", "queue diff",
            "± 95% CI", "failure rate", "failure diff", "95% CI"]
    lines = ["| " + " | ".join(head) + " |",
             "|" + "|".join("---" if i == 0 else "---:" for i in range(len(head))) + "|",
             f"| {_md(b['policy'])} (baseline) | {b['trips_mean']:.2f} | | | "
             f"{b['queue_mean']:.2f} | | | {b['failure_rate']:.3f} | | |"]
    for r in comparison["rows"]:
        cells = [_md(r["label"]), _cell(r["trips_mean"], "{:.2f}"), _cell(r["gain_pct"], "{:+.2f}"),
                 _cell(r["gain_ci95"], "{:.2f}"), _cell(r["queue_mean"], "{:.2f}"),
                 _cell(r["queue_diff"], "{:+.2f}"), _cell(r["queue_diff_ci95"], "{:.2f}"),
                 _cell(r["failure_rate"], "{:.3f}"), _cell(r["failure_diff"], "{:+.3f}"),
                 f"[{r['failure_diff_lo']:+.3f}, {r['failure_diff_hi']:+.3f}]"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _md(text: str) -> str:
    return text.replace("|", "\\|")


COMPARISON_FIELDS = ("label", "policy", "file", "n_sims", "trips_mean", "gain_pct", "gain_ci95",
                     "queue_mean", "queue_diff", "queue_diff_ci95", "failure_rate",
                     "failure_diff", "failure_diff_lo", "failure_diff_hi", "baseline",
                     "baseline_trips_mean", "baseline_queue_mean", "baseline_failure_rate")


def comparison_paths(path: str | Path) -> tuple[Path, Path, Path]:
    """The files of a comparison written to ``path``: the JSON, the CSV and the figure."""
    path = Path(path)
    return path, path.with_suffix(".csv"), path.with_suffix(".png")


def check_comparison_path(path: str | Path, overwrite: bool = False,
                          inputs: tuple[str | Path, ...] = (), setting: str = "out") -> Path:
    """Fail early, in one line naming ``setting``, unless a comparison can be written to
    ``path`` (``.json``) and beside it (``.csv``, ``.png``): every check of
    :func:`check_result_path`; no file among them may be one of ``inputs`` (the results
    compared, or their CSV); an existing one is replaced only with ``overwrite``, and an
    existing JSON only if it is a comparison (never a result or some other file)."""
    from ..utils.checks import ConfigError

    path = check_output(setting, path, "file", suffix=".json")
    files = comparison_paths(path)
    for f in files[1:]:
        check_output(setting, f, "file")
    taken = {Path(os.path.abspath(x)).resolve() for i in inputs
             for x in (Path(i), Path(i).with_suffix(".csv"))}
    for f in files:
        if Path(os.path.abspath(f)).resolve() in taken:
            raise ConfigError(f"{setting}={path} is invalid: it would replace {f}, a file "
                              "being compared; allowed a new path")
    for f in files:
        if not f.exists() and not f.is_symlink():
            continue
        if not overwrite:
            raise ConfigError(f"{setting}={path} is invalid: {f} exists; allowed a new path, "
                              "or overwrite=true to replace that comparison")
    if path.exists():
        try:
            kind = read_json(path).get("kind") if path.is_file() else None
        except (OSError, ValueError, AttributeError):
            kind = None
        if kind != COMPARISON_KIND:
            raise ConfigError(f"{setting}={path} is invalid: {path} exists and is no "
                              "comparison fleet-compare wrote (overwrite=true replaces only "
                              "those); allowed a new path")
    return path


def save_comparison(comparison: dict[str, Any], path: str | Path) -> tuple[Path, Path, Path]:
    """Write a comparison of :func:`compare_results`: the figure (``.png``, the paired
    differences in trips per site of each result), the table (``.csv``, one row per result),
    then the JSON (every row with its per-site differences, the setup, and the SHA-256 of
    the CSV and the figure), each atomically. The JSON is written last, so it is the unit's
    commit: a CSV or figure left by a killed or concurrent writer is told apart by its
    hash."""
    from ..utils.plotting import plot_paired_differences, save_figure

    path, csv_path, png_path = comparison_paths(path)
    if path.suffix != ".json":
        raise ValueError(f"a comparison path must end in .json, got {path}")
    b = comparison["baseline"]["policy"]
    fig = plot_paired_differences(
        {r["label"]: r["trips_diff"] for r in comparison["rows"]}, b,
        f"paired differences vs {b} ({comparison['n_sims']} sites x {comparison['ticks']} "
        f"ticks, eval.seed={comparison['seed']})")
    save_figure(fig, png_path)
    text = csv_text(comparison["rows"], COMPARISON_FIELDS)
    write_text(csv_path, text)
    write_json(path, _no_nan({**comparison, "csv": csv_path.name,
                              "csv_sha256": hashlib.sha256(text.encode()).hexdigest(),
                              "figure": png_path.name, "figure_sha256": file_sha256(png_path)}))
    return path, csv_path, png_path


def _no_nan(obj: Any) -> Any:
    """``obj`` with every NaN as None (JSON has no NaN: an interval of one site)."""
    if isinstance(obj, dict):
        return {k: _no_nan(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_no_nan(v) for v in obj]
    return None if isinstance(obj, float) and math.isnan(obj) else obj


# ------------------------------------------------------------------------- files
CSV_FIELDS = ("sim", "trips", "queue", "failed", "ticks_survived")


def record_rows(result: dict[str, Any]) -> list[dict[str, Any]]:
    rec = result["records"]
    return [{"sim": i, "trips": t, "queue": q, "failed": int(f), "ticks_survived": s}
            for i, (t, q, f, s) in enumerate(zip(rec["trips"], rec["queue"], rec["failed"],
                                                 rec["ticks_survived"], strict=True))]


def check_result_path(path: str | Path, setting: str = "eval.out",
                      overwrite: bool | None = None) -> Path:
    """Fail early, in one line naming ``setting``, if a result cannot be written to ``path``
    (and its ``.csv``): wrong suffix, a folder in the way, a folder that cannot be created or
    written, a pseudo file system (:func:`fleet_torchrl.utils.paths.check_output`).

    With ``overwrite`` given (a command's ``eval.overwrite``), what is there already is
    checked too: a path that is no regular file (a FIFO, a device), a file that is not an
    evaluation result (an unrelated JSON, a policy's ``train_summary.json``) or a CSV beside
    it that is not a result's rows is refused; an existing result is refused unless
    ``overwrite`` is true. A result CSV without its JSON (a write killed between the two) may
    be replaced."""
    path = check_output(setting, path, "file", suffix=".json")
    csv_path = path.with_suffix(".csv")
    check_output(setting, csv_path, "file")
    if overwrite is None:
        return path
    for p in (path, csv_path):
        if os.path.lexists(p) and not p.is_file():
            raise ConfigError(f"{setting}={path} is invalid: {p} exists and is not a regular "
                              "file (a FIFO, a device, a dangling link); choose another path")
    if path.is_file():
        try:
            load_result(path)
        except ValueError as e:
            why = str(e).removeprefix(f"{path} ")
            if not why.startswith("is "):  # not even text
                why = f"is not an evaluation result ({why})"
            raise ConfigError(f"{setting}={path} is invalid: the file there {why}; it is "
                              "kept: choose another path") from None
        if not overwrite:
            raise ConfigError(f"{setting}={path} already holds an evaluation result: it is "
                              "kept; eval.overwrite=true replaces it, or choose another path")
    elif csv_path.is_file() and not _is_result_csv(csv_path):
        raise ConfigError(f"{setting}={path} is invalid: {csv_path} beside it is not an "
                          "evaluation's CSV; it is kept: choose another path")
    return path


def _is_result_csv(path: Path) -> bool:
    """Whether ``path`` starts with the header :func:`save_result` writes."""
    try:
        with open(path, encoding="utf-8", errors="replace") as f:
            return f.readline().rstrip("\r\n") == ",".join(CSV_FIELDS)
    except OSError:
        return False


def save_result(result: dict[str, Any], path: str | Path) -> tuple[Path, Path]:
    """Write the per-simulation CSV (same stem, ``.csv``), then the result JSON, each
    atomically. The JSON is the unit's commit: it names its CSV (``csv``) and records its
    SHA-256 (``csv_sha256``), so a CSV left by a killed or a concurrent writer beside
    another run's JSON is told apart (:func:`check_result_pair`)."""
    path = Path(path)
    if path.suffix != ".json":
        raise ValueError(f"a result path must end in .json, got {path}")
    csv_path = path.with_suffix(".csv")
    text = csv_text(record_rows(result), CSV_FIELDS)
    write_text(csv_path, text)  # the hash is of what this writer wrote, not read back
    write_json(path, {**result, "csv": csv_path.name,
                      "csv_sha256": hashlib.sha256(text.encode()).hexdigest()})
    return path, csv_path


def check_result_pair(path: str | Path) -> dict[str, Any]:
    """The result at ``path`` after checking that the CSV beside it is the one it was
    written with (the name the JSON gives it and its hash); a mismatched pair raises
    ``ValueError``. What every reader of a result's CSV calls first."""
    path = Path(path)
    res = load_result(path)
    csv_path = path.with_suffix(".csv")
    want = res.get("csv_sha256")
    if res.get("csv", csv_path.name) != csv_path.name:
        raise ValueError(f"{path} names its CSV {res.get('csv')!r}, not {csv_path.name} (a "
                         "renamed or copied file?): evaluate again")
    if want is None or not csv_path.is_file() or file_sha256(csv_path) != want:
        raise ValueError(f"{csv_path} does not belong to {path} (a killed or concurrent write"
                         "?): evaluate again")
    return res


RECORD_KEYS = ("trips", "queue", "failed", "ticks_survived")
# the most a simulation's trips, queue events or ticks survived may be in a result file: the
# protocol's 10**9 ticks at most, a trip or a queue event at most once per tick and vehicle
# in any site this project simulates; more is a damaged or forged file, not a result
RECORD_LIMIT = 10**9
SEED_LIMIT = 2**32 - 1  # eval.seed's range (EvalConfig)
N_SIMS_LIMIT = 10**8  # eval.n_sims's
TICKS_LIMIT = 10**9  # eval.ticks's
NAME_LIMIT = 200  # characters of a policy's name


def _short(value: Any) -> str:
    """``repr(value)`` cut to 40 characters (a forged file's value is quoted, not dumped)."""
    if isinstance(value, (dict, list)):  # a container's items are not quoted
        return ("{}" if isinstance(value, dict) else "[]") if not value else \
            ("{...}" if isinstance(value, dict) else "[...]")
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def _whole(value: Any, hi: int, lo: int = 0) -> bool:
    """Whether ``value`` is a whole number in ``[lo, hi]`` (an int, or a float without a
    fraction; never a bool, NaN, inf or an integer too large for a float)."""
    if isinstance(value, bool):
        return False
    if isinstance(value, int):
        return lo <= value <= hi
    return isinstance(value, float) and math.isfinite(value) and value.is_integer() and \
        lo <= value <= hi


def _depth(node: Any, limit: int) -> bool:
    """Whether nested JSON ``node`` is at most ``limit`` levels deep (iterative: a forged
    file's depth cannot exhaust the stack)."""
    stack = [(node, 0)]
    while stack:
        x, d = stack.pop()
        if isinstance(x, (dict, list)):
            if d >= limit:
                return False
            stack.extend((v, d + 1) for v in (x.values() if isinstance(x, dict) else x))
    return True


def load_result(path: str | Path) -> dict[str, Any]:
    """A result file, checked against the schema :func:`save_result` writes, so that a damaged,
    foreign or forged file is refused in one line rather than compared into ``+nan %``, a
    300-digit gain or a pair of files that name no site:

    * a JSON object with ``policy`` (a name of at most 200 printable characters), ``seed``
      (an integer in [0, 2**32 - 1]), ``n_sims`` (in [1, 10**8]), ``ticks`` (in [1, 10**9]),
      ``site`` (the site's description, a non-empty object) and ``records``;
    * ``records`` holds ``n_sims`` values for each of ``trips``, ``queue``, ``failed`` and
      ``ticks_survived``: whole numbers in [0, 10**9] (``failed``: true/false or 0/1).

    The summary figures (``trips_mean``, ...) are not read: everything compared is computed
    from the records."""
    res = read_json(path)
    if not isinstance(res, dict):
        raise ValueError(f"{path} is not an evaluation result (a JSON object expected, got "
                         f"{type(res).__name__})")
    missing = [k for k in ("policy", "seed", "n_sims", "ticks", "records", "site")
               if k not in res]
    if missing:
        raise ValueError(f"{path} is not an evaluation result (missing {', '.join(missing)})")

    def bad(what: str) -> ValueError:
        return ValueError(f"{path} is not an evaluation result ({what})")

    name = res["policy"]
    if not isinstance(name, str) or not name.strip() or len(name) > NAME_LIMIT or \
            not name.isprintable():
        raise bad(f"policy={_short(name)}: allowed a name of 1 to {NAME_LIMIT} printable "
                  "characters")
    n, rec = res["n_sims"], res["records"]
    for key, lo, hi in (("seed", 0, SEED_LIMIT), ("n_sims", 1, N_SIMS_LIMIT),
                        ("ticks", 1, TICKS_LIMIT)):
        if not isinstance(res[key], int) or not _whole(res[key], hi, lo):
            raise bad(f"{key}={_short(res[key])}: allowed an integer in [{lo}, {hi}]")
    site = res["site"]
    if not isinstance(site, dict) or not site or not _depth(site, 4):
        raise bad(f"site={_short(site)}: allowed the description of the site it ran, a "
                  "JSON object as fleet-evaluate writes it")
    if not isinstance(rec, dict) or not isinstance(rec.get("trips"), list):
        raise bad("records.trips missing")
    for key in RECORD_KEYS:
        values = rec.get(key)
        if not isinstance(values, list) or len(values) != n:
            length = len(values) if isinstance(values, list) else type(values).__name__
            raise bad(f"records.{key} holds {length} values for n_sims={n}")
        if key == "failed":
            ok = (v in (0, 1) and (isinstance(v, bool) or _whole(v, 1)) for v in values)
            allowed = "true or false"
        else:
            ok = (_whole(v, RECORD_LIMIT) for v in values)
            allowed = "a whole number in [0, 10**9]"
        i = next((i for i, good in enumerate(ok) if not good), None)
        if i is not None:
            raise bad(f"records.{key}[{i}]={_short(values[i])}: allowed {allowed}")
    return res


def format_table(rows: list[dict[str, Any]]) -> str:
    """A Markdown table of summary rows (with gain columns when present)."""
    cols = [("policy", "policy", "{}"), ("trips_mean", "trips mean", "{:.2f}"),
            ("trips_std", "trips std", "{:.2f}"), ("queue_mean", "queue mean", "{:.2f}"),
            ("queue_std", "queue std", "{:.2f}"), ("failure_rate", "failure rate", "{:.3f}")]
    if any("gain_pct" in r for r in rows):
        cols += [("gain_pct", "gain % vs rule", "{:+.2f}"), ("gain_ci95", "± 95% CI", "{:.2f}")]
    lines = ["| " + " | ".join(c[1] for c in cols) + " |",
             "|" + "|".join("---" if i == 0 else "---:" for i in range(len(cols))) + "|"]
    for r in rows:
        cells = [fmt.format(r[k]) if r.get(k) is not None else "" for k, _, fmt in cols]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)
