"""Collect the points of a sweep into ``results/sweeps/<name>.{csv,json,png}``.

    python -m fleet_torchrl.sweeps_summary pc [--out results/sweeps]

Lists failed points (``.error`` files) and, with ``--expect``, points that never ran.
"""

from __future__ import annotations

from pathlib import Path

from ..utils.plotting import plot_sweep, save_figure
from ..utils.runinfo import read_json, write_csv, write_json
from .sweeps import POINT_FIELDS


def summarize(name: str, out: Path, expect: list[str] | None = None) -> dict:
    folder = out / name
    if not folder.is_dir():
        raise FileNotFoundError(f"no sweep results in {folder}; run `make sweep-{name}` first")
    rows, done = [], []
    for f in sorted(folder.glob("*.json")):
        rows += read_json(f)["rows"]
        done.append(f.stem)
    failed = sorted(f.stem for f in folder.glob("*.error"))
    missing = [v for v in (expect or []) if v not in done and v not in failed]
    if not rows:
        raise FileNotFoundError(f"no finished point in {folder}")
    param = rows[0]["param"]
    rows.sort(key=lambda r: (r["value"], r["policy"]))
    write_csv(out / f"{name}.csv", [{**r, "seeds": " ".join(map(str, r.get("seeds", []))),
                                     "gain_per_seed": " ".join(f"{g:.4f}" for g in
                                                               r.get("gain_per_seed", []))}
                                    for r in rows], POINT_FIELDS)
    summary = {"sweep": name, "param": param, "rows": rows, "failed": failed,
               "missing": missing}
    write_json(out / f"{name}.json", summary)
    fig = plot_sweep(rows, param, f"sweep {name}: learners of the default site, the "
                                  "generalist, the planner, the best known policy")
    save_figure(fig, out / f"{name}.png")
    return summary
