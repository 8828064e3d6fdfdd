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
def gain_over(result: dict[str, Any], baseline: dict[str, Any]) -> dict[str, Any]:
    """Trips gain of ``result`` over ``baseline`` in percent of the baseline's mean.

    ``gain_pct`` is the mean paired difference over the baseline's mean (equal to the
    difference of means); ``gain_ci95`` is the half-width of its 95% confidence interval
    from the paired differences (paired t: Student's t with ``n - 1`` degrees of freedom,
    which the normal's 1.96 understates at few simulations, by 17 % at 8).
    ``per_sim_gain_pct`` is each simulation's trips as % over the baseline's mean (the
    box-plot quantity of MODEL §5).
    Both results must come from the same seed, number of simulations, ticks and site.
    """
    for key in ("seed", "n_sims", "ticks", "site"):
        if result.get(key) != baseline.get(key):
            detail = "" if key == "site" else f" ({result.get(key)} vs {baseline.get(key)})"
            raise ValueError(f"cannot pair {result.get('policy')} with {baseline.get('policy')}: "
                             f"{key} differs{detail}")
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


def load_result(path: str | Path) -> dict[str, Any]:
    """A result file, checked: a JSON object with its setup and one record per simulation,
    every trip count a finite number >= 0 (a damaged or foreign file is refused in one line
    rather than compared into ``+nan %``)."""
    res = read_json(path)
    if not isinstance(res, dict):
        raise ValueError(f"{path} is not an evaluation result (a JSON object expected, got "
                         f"{type(res).__name__})")
    missing = [k for k in ("policy", "seed", "n_sims", "ticks", "records") if k not in res]
    if missing:
        raise ValueError(f"{path} is not an evaluation result (missing {', '.join(missing)})")
    n, rec = res["n_sims"], res["records"]
    if not isinstance(n, int) or isinstance(n, bool) or n < 1:
        raise ValueError(f"{path} is not an evaluation result (n_sims={n!r}: allowed an "
                         "integer >= 1)")
    if not isinstance(rec, dict) or not isinstance(rec.get("trips"), list):
        raise ValueError(f"{path} is not an evaluation result (records.trips missing)")
    for key in RECORD_KEYS:
        values = rec.get(key)
        if values is None and key != "trips":
            continue
        if not isinstance(values, list) or len(values) != n:
            length = len(values) if isinstance(values, list) else type(values).__name__
            raise ValueError(f"{path} is not an evaluation result (records.{key} holds "
                             f"{length} values for n_sims={n})")
        if not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
                   and v >= 0 for v in values if key != "failed"):
            raise ValueError(f"{path} is not an evaluation result (records.{key} holds a value "
                             "that is not a finite number >= 0)")
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
