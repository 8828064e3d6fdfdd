"""Assemble ``docs/report.md`` from result files only: ``make report``.

    python -m fleet_torchrl.report [--results results] [--out docs/report.md]

Sections: how and where the results were made (machine, commit, wall time of each step from
``results/timings.json``), the main comparison (``results/table``), policy maps
(``results/policy_maps``), the three generalisation sweeps (``results/sweeps``) and the grid
search (``results/grid``). Figures are copied next to the report (``docs/figures/``). A missing
part is reported as not run, with the target that makes it; nothing is retrained.
"""

from __future__ import annotations

import shutil
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from ..utils.runinfo import git_commit, read_json

SWEEPS = (("pc", "closure probability p_c"), ("tc", "charging ticks T_C"),
          ("nv", "number of vehicles N_V"))


def _copy(src: Path, figures: Path, name: str, report_dir: Path) -> str:
    figures.mkdir(parents=True, exist_ok=True)
    dst = figures / name
    shutil.copyfile(src, dst)
    return dst.relative_to(report_dir).as_posix()


def _sweep_pivot(rows: list[dict[str, Any]]) -> str:
    policies = list(dict.fromkeys(r["policy"] for r in rows))
    values = sorted({r["value"] for r in rows})
    cell = {(r["value"], r["policy"]): r for r in rows}
    head = "| " + rows[0]["param"] + " | " + " | ".join(policies) + " |"
    lines = [head, "|---:|" + "---:|" * len(policies)]
    for v in values:
        cells = []
        for p in policies:
            r = cell.get((v, p))
            if r is None or r["gain_pct"] is None:
                cells.append("")
            else:
                worst = r.get("failure_rate_max", r["failure_rate"])
                fail = (f", fail {r['failure_rate']:.3f}" if r["failure_rate"] > 0 else "")
                if worst > r["failure_rate"]:
                    fail += f" (worst seed {worst:.3f})"
                share = r.get("share_of_best_known_pct")
                share = (f" ({share:.0f} %)" if share is not None and p != "best_known"
                         else "")
                ci = "" if r.get("gain_ci95") is None else f" ± {r['gain_ci95']:.2f}"
                seeds = r.get("gain_per_seed") or []
                per_seed = (" [" + "/".join(f"{g:+.2f}" for g in seeds) + "]"
                            if len(seeds) > 1 else "")
                cells.append(f"{r['gain_pct']:+.2f}{ci}{per_seed}{share}{fail}")
        lines.append(f"| {v} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _improvement_table(rows: list[dict[str, Any]]) -> str:
    rows = [r for r in rows if r.get("improvement_pct") is not None]
    if not rows:
        return ""
    lines = [f"| {rows[0]['param']} | policy | one-step improvement | sites |",
             "|---:|---|---:|---:|"]
    for r in sorted(rows, key=lambda r: (r["value"], r["policy"])):
        ci = "" if r.get("improvement_ci95") is None else f" ± {r['improvement_ci95']:.2f}"
        seed = f" (seed {r['improvement_seed']})" if r.get("improvement_seed") is not None \
            else ""
        lines.append(f"| {r['value']} | {r['policy']}{seed} | {r['improvement_pct']:+.2f}{ci} "
                     f"| {r.get('improvement_sims')} |")
    return "\n".join(lines)


def build(results: Path, out: Path) -> str:
    """The report's markdown: its heading, then one section per experiment, each read from
    the result files under ``results`` (figures copied beside ``out``)."""
    report_dir = out.parent
    figures = report_dir / "figures"
    parts = ["# fleet_torchrl: results report", "",
             f"Generated {datetime.now(UTC).isoformat(timespec='seconds')} from the "
             f"files under `{results}/` by `make report` (commit `{git_commit() or 'unknown'}`)."
             " Every number below is read from those files; regenerate with `make report`. "
             "What the numbers mean, and why the learned policies fall short of the thesis's "
             "gains on this site model: [TRAINING.md](TRAINING.md).", ""]
    for section in (_timings, _table, _maps, _sweeps, _grid):
        parts += section(results, figures, report_dir)
    return "\n".join(parts).rstrip() + "\n"


def _timings(results: Path, figures: Path, report_dir: Path) -> list[str]:
    """How the results were made (``timings.json``)."""
    parts: list[str] = []
    timings = results / "timings.json"
    if timings.exists():
        t = read_json(timings)
        machine = next(iter(t.values()))["machine"]
        parts += ["## How it was made", "", f"Machine: {machine}.", "",
                  "| step | wall time | finished (UTC) | exit |", "|---|---:|---|---:|"]
        parts += [f"| `make {k}` | {v['wall_s'] / 60:.1f} min | {v['finished']} | "
                  f"{v['exit_code']} |" for k, v in t.items()]
        parts += ["", "Each step's last run; a rerun reuses the saved policies and cached "
                  "searches whose settings match, so it can be much shorter than a run from an "
                  "empty `results/` (those are in [BENCHMARKS.md](BENCHMARKS.md)).", ""]

    return parts


def _table(results: Path, figures: Path, report_dir: Path) -> list[str]:
    """The main comparison (``table/``)."""
    table = results / "table" / "table.md"
    if not table.exists():
        return ["## Main comparison (MODEL §5 item 1)", "", "Not run yet: `make table`.", ""]
    body = table.read_text().splitlines()
    parts = ["## Main comparison (MODEL §5 item 1)", "", body[0].lstrip("# ") + ".", "",
             *body[1:], ""]
    info = results / "table" / "run_info.json"
    if info.exists():
        tt = read_json(info).get("train_time_s", {})
        parts += ["Training wall time per run: " + ", ".join(
            f"{k} {v / 60:.1f} min" if v is not None else f"{k} (n/a)"
            for k, v in tt.items()), ""]
    for name, title in (("boxplot.png", "box plot"), ("learning_curves.png", "learning curves")):
        fig = results / "table" / name
        if fig.exists():
            parts += [f"![{title}]({_copy(fig, figures, name, report_dir)})", ""]
    return parts


def _maps(results: Path, figures: Path, report_dir: Path) -> list[str]:
    """The policy maps (``policy_maps/``)."""
    parts: list[str] = []
    parts += ["## Policy maps (MODEL §5 item 2)", "",
              "Action over `soc_D` (y) x lowest soc of the other vehicles (x); orange = charge.",
              ""]
    maps = sorted((results / "policy_maps").glob("*.png"))
    if maps:
        for m in maps:
            parts += [f"### {m.stem}", "",
                      f"![{m.stem}]({_copy(m, figures, f'policy_map_{m.name}', report_dir)})", ""]
    else:
        parts += ["Not run yet: `make policy-maps`.", ""]

    return parts


def _sweeps(results: Path, figures: Path, report_dir: Path) -> list[str]:
    """The generalisation sweeps (``sweeps/``)."""
    parts: list[str] = []
    parts += ["## Generalisation sweeps (MODEL §5 item 3)", "",
              "Policies trained on the default site and the `generalist` (trained on the "
              "site distribution, MODEL §3.5), evaluated on changed sites, beside the point's "
              "own searches (`search_threshold`, `search_table`: MODEL §3.4, classes that "
              "read the charger's remaining time), the rollout planner over the heuristic "
              "(`planner`, MODEL §3.6) and over the point's best search where that search "
              "beats the heuristic on the pick set (`planner_search`), and "
              "`best_known`: the best of all of them on the point's pick set (sites apart "
              "from the evaluation's; MODEL §5). "
              "Cells: trips gain over the rule in % ± 95% CI, in brackets the share of "
              "`best_known`'s gain, and the failure rate when not zero.", ""]
    for name, label in SWEEPS:
        js = results / "sweeps" / f"{name}.json"
        parts += [f"### {label}", ""]
        if not js.exists():
            parts += [f"Not run yet: `make sweep-{name}`.", ""]
            continue
        s = read_json(js)
        point = next(iter(sorted((results / "sweeps" / name).glob("*.json"))), None)
        if point is not None:
            ev = read_json(point).get("meta", {}).get("config", {}).get("eval", {})
            if ev:
                parts += [f"{ev['n_sims']} simulations x {ev['ticks']} ticks per point, "
                          f"seed {ev['seed']}.", ""]
        parts += [_sweep_pivot(s["rows"]), ""]
        imp = _improvement_table(s["rows"])
        if imp:
            parts += ["One step of policy improvement (the planner over the policy, paired "
                      "with its own records on the first sites of the evaluation; the "
                      "heuristic's is the `planner` row on every site, a search's the "
                      "`planner_search` row), in points of gain over "
                      "the rule ± 95% CI: where it is significantly positive the policy is not "
                      "optimal on that site.", "", imp, ""]
        png = results / "sweeps" / f"{name}.png"
        if png.exists():
            parts += [f"![sweep {name}]({_copy(png, figures, f'sweep_{name}.png', report_dir)})",
                      ""]
        if s.get("failed") or s.get("missing"):
            parts += [f"Incomplete: failed {s.get('failed')}, missing {s.get('missing')}.", ""]

    return parts


def _grid(results: Path, figures: Path, report_dir: Path) -> list[str]:
    """The grid search (``grid/``)."""
    head = ["## Grid search over the DQN network (MODEL §5 item 4)", ""]
    grid = results / "grid" / "summary.md"
    if not grid.exists():
        return [*head, "Not run yet: `make grid`.", ""]
    return [*head, *grid.read_text().splitlines()[1:], ""]
