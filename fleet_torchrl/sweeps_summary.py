"""Collect the points of a sweep into ``results/sweeps/<name>.{csv,json,png}``.

    python -m fleet_torchrl.sweeps_summary pc [--out results/sweeps]

Lists failed points (``.error`` files) and, with ``--expect``, points that never ran.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .cli import user_errors
from .plotting import plot_sweep, save_figure
from .runinfo import read_json, write_csv, write_json
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
    write_csv(out / f"{name}.csv", rows, POINT_FIELDS)
    summary = {"sweep": name, "param": param, "rows": rows, "failed": failed,
               "missing": missing}
    write_json(out / f"{name}.json", summary)
    fig = plot_sweep(rows, param, f"sweep {name}: policies trained on the default site")
    save_figure(fig, out / f"{name}.png")
    return summary


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("name")
    p.add_argument("--out", default="results/sweeps")
    p.add_argument("--expect", nargs="*", default=None,
                   help="point names expected, e.g. p_c=0.0 p_c=0.2 (reported if missing)")
    a = p.parse_args(argv)
    with user_errors():
        s = summarize(a.name, Path(a.out), a.expect)
    n_points = len({r["value"] for r in s["rows"]})
    print(f"[sweep {a.name}] {n_points} points -> {a.out}/{a.name}.csv, .json, .png")
    for label, items in (("failed", s["failed"]), ("missing", s["missing"])):
        if items:
            print(f"[sweep {a.name}] {label}: {', '.join(items)} (rerun the target to retry)")
    return 1 if s["failed"] or s["missing"] else 0


if __name__ == "__main__":
    sys.exit(main())
