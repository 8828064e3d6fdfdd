"""Collect the points of a sweep into ``results/sweeps/<name>.{csv,json,png}``.

    fleet-sweeps-summary name=pc [out=results/sweeps]

Lists failed points (``.error`` files) and the expected points that never ran (by default
those of the packaged experiment ``conf/experiment/sweep_<name>.yaml``).
"""

from __future__ import annotations

from pathlib import Path

from ..utils.plotting import plot_sweep, save_figure
from ..utils.runinfo import read_json, write_csv, write_json
from .sweeps import POINT_FIELDS, point_value


def expected_points(name: str) -> list[str] | None:
    """The point names (``p_c=0.4``, ...) of the packaged sweep ``sweep_<name>``: its swept
    ``sweep.value`` list and its ``sweep.param``; None for a sweep the package does not
    define (then no point is reported missing)."""
    import yaml

    path = Path(__file__).resolve().parent.parent / "conf" / "experiment" / f"sweep_{name}.yaml"
    if not path.is_file():
        return None
    exp = yaml.safe_load(path.read_text())
    param = exp["sweep"]["param"]
    values = str(exp["hydra"]["sweeper"]["params"]["sweep.value"]).split(",")
    return [f"{param}={point_value(param, float(v))}" for v in values]


def summarize(name: str, out: Path, expect: list[str] | None = None) -> dict:
    folder = out / name
    if not folder.is_dir():
        raise FileNotFoundError(f"no sweep results in {folder}; run `make sweep-{name}` first")
    rows, done = [], []
    for f in sorted(folder.glob("*.json")):
        point = read_json(f)
        if not isinstance(point, dict) or not isinstance(point.get("rows"), list) or not all(
                isinstance(r, dict) and {"param", "value", "policy"} <= r.keys()
                for r in point["rows"]):
            raise ValueError(f"{f} is not a sweep point's result (rows of param, value, "
                             "policy); move it out of the sweep's folder")
        rows += point["rows"]
        done.append(f.stem)
    failed = sorted(f.stem for f in folder.glob("*.error"))
    missing = [v for v in (expect or []) if v not in done and v not in failed]
    if not rows:
        raise FileNotFoundError(f"no finished point in {folder}")
    params = sorted({r["param"] for r in rows})
    if len(params) > 1:
        raise ValueError(f"{folder} mixes the sweeps of {', '.join(params)}: a sweep varies "
                         "one parameter; give each its own sweep.name")
    param = params[0]
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
