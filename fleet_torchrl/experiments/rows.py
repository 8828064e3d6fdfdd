"""What an experiment's row is, and what it measured: one candidate type and one row result
shared by the main table (:mod:`~fleet_torchrl.experiments.table`) and the generalisation
sweeps (:mod:`~fleet_torchrl.experiments.sweeps`).

* :class:`Candidate`: a row before it is evaluated: its name, its kind (a baseline, a saved
  learned policy, a policy trained at the point, a search, a planner), how it is built (by
  name, from policy files, or trained from a :class:`~fleet_torchrl.training.spec.RunSpec`
  per seed) and its seeds.
* :class:`Row`: a row's figures, built in one place (:meth:`Row.of`) from the evaluation
  results of its seeds, and rendered by the writers (:meth:`Row.table_dict`,
  :meth:`Row.sweep_dict`, :meth:`Row.table_markdown`): the table's JSON, CSV and markdown
  and the sweep points' JSON come from these alone.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from ..evaluation import gain_over, seed_interval
from ..training.spec import RunSpec

Kind = Literal["baseline", "learned", "search", "specialist", "planner", "best_known"]
KINDS = ("baseline", "learned", "search", "specialist", "planner", "best_known")

# the table's columns (table.csv, table.json) and a sweep point's (its JSON, the summary CSV)
TABLE_FIELDS = ("policy", "objective", "trained_on", "seeds", "trips_mean", "trips_std",
                "queue_mean", "failure_rate", "gain_pct", "gain_ci95", "gain_min",
                "gain_per_seed", "gain_vs_heuristic_pct", "train_time_s", "improvement_pct",
                "improvement_ci95")
POINT_FIELDS = ("param", "value", "policy", "seeds", "trips_mean", "trips_std", "queue_mean",
                "failure_rate", "failure_rate_max", "gain_pct", "gain_ci95", "gain_per_seed",
                "share_of_best_known_pct", "improvement_pct", "improvement_ci95",
                "improvement_sims", "improvement_seed")
IMPROVEMENT_FIELDS = POINT_FIELDS[-4:]
_FIGURES = ("trips_mean", "trips_std", "queue_mean", "failure_rate")


@dataclass
class Candidate:
    """One row of an experiment before it is evaluated.

    ``kind``: what the row is (:data:`KINDS`). How it is built: ``files`` (a saved learned
    policy: ``{seed: policy file}``), ``specs`` (trained where it is needed: ``{seed: run
    spec}``, seed None for a single run such as a search), ``base`` (a planner: the row its
    rollouts follow); a baseline is built by its name. ``seeds``: its training seeds (empty
    for a single policy)."""

    name: str
    kind: Kind
    files: dict[int | None, Path] = field(default_factory=dict)
    specs: dict[int | None, RunSpec] = field(default_factory=dict)
    base: str | None = None
    objective: str = ""  # the table's learned rows: the objective its recipe trains on
    trained_on: str = ""  # the table's learned rows: where its recipe trains

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"candidate {self.name}: kind={self.kind!r} is invalid: allowed "
                             f"{', '.join(KINDS)}")

    @property
    def seeds(self) -> list[int]:
        return [s for s in (self.specs or self.files) if s is not None]


@dataclass
class Row:
    """A row's figures (see the module docstring). Several seeds: every figure the mean over
    the seeds, the gain with its 95 % interval across seeds (Student's t; nan for one seed)
    and each seed's gain, the worst seed's failure rate; one policy: its figures, the paired
    gain over the rule and its interval over the simulations."""

    policy: str
    seeds: list[int]
    trips_mean: float
    trips_std: float
    queue_mean: float
    failure_rate: float
    failure_rate_max: float
    gain_pct: float | None
    gain_ci95: float | None
    gain_min: float | None
    gain_per_seed: list[float]
    gain_vs_heuristic_pct: float | None = None
    objective: str = ""
    trained_on: str = ""
    train_time_s: list[float | None] = field(default_factory=list)
    improvement_pct: float | None = None
    improvement_ci95: float | None = None
    improvement_sims: int | None = None
    improvement_seed: int | None = None
    share_of_best_known_pct: float | None = None

    @classmethod
    def of(cls, name: str, results: dict[int | None, dict[str, Any]],
           rule: dict[str, Any] | None, heuristic: dict[str, Any] | None = None,
           **extra: Any) -> Row:
        """The row of ``name`` from its evaluation results ``{seed: result}`` (one policy:
        ``{None: result}``), with its gains over ``rule`` (None: no gains) and
        ``heuristic``; ``extra``: the fields a candidate brings (objective, trained on,
        training times)."""
        seeds = [s for s in results if s is not None]
        per = list(results.values())
        if not seeds:
            res = per[0]
            g = gain_over(res, rule) if rule is not None else {"gain_pct": None,
                                                               "gain_ci95": None}
            figures = {k: res[k] for k in _FIGURES}
            gain = {"gain_pct": g["gain_pct"], "gain_ci95": g["gain_ci95"],
                    "gain_min": g["gain_pct"], "gain_per_seed": [],
                    "failure_rate_max": res["failure_rate"],
                    "gain_vs_heuristic_pct": None if heuristic is None
                    else gain_over(res, heuristic)["gain_pct"]}
            return cls(policy=name, seeds=[], **figures, **gain, **extra)
        gains = [gain_over(res, rule)["gain_pct"] for res in per] if rule is not None else []
        gi = seed_interval(gains) if gains else {"mean": None, "ci95": None, "min": None}
        vs_heur = [gain_over(res, heuristic)["gain_pct"] for res in per] if heuristic else []
        return cls(policy=name, seeds=seeds,
                   **{k: sum(r[k] for r in per) / len(per) for k in _FIGURES},
                   failure_rate_max=max(r["failure_rate"] for r in per),
                   gain_pct=gi["mean"], gain_ci95=gi["ci95"], gain_min=gi["min"],
                   gain_per_seed=gains,
                   gain_vs_heuristic_pct=sum(vs_heur) / len(vs_heur) if vs_heur else None,
                   **extra)

    def improved(self, imp: dict[str, Any]) -> Row:
        """This row with what one step of policy improvement adds (``improvement_*``)."""
        for k in IMPROVEMENT_FIELDS:
            if k in imp:
                setattr(self, k, imp[k])
        return self

    # ------------------------------------------------------------------ the writers' forms
    def table_dict(self) -> dict[str, Any]:
        """The table's row (``table.json``; the CSV's columns :data:`TABLE_FIELDS`): the
        improvement columns only where one step of improvement ran."""
        out = {"policy": self.policy, "objective": self.objective,
               "trained_on": self.trained_on, "seeds": list(self.seeds),
               **{k: getattr(self, k) for k in _FIGURES},
               "gain_pct": self.gain_pct, "gain_ci95": self.gain_ci95,
               "gain_min": self.gain_min, "gain_per_seed": list(self.gain_per_seed),
               "gain_vs_heuristic_pct": self.gain_vs_heuristic_pct,
               "train_time_s": list(self.train_time_s)}
        if self.improvement_pct is not None:
            out.update(improvement_pct=self.improvement_pct,
                       improvement_ci95=self.improvement_ci95)
        return out

    def sweep_dict(self, param: str, value: float | int, best_known: bool = False
                   ) -> dict[str, Any]:
        """A sweep point's row (its JSON; the summary CSV's columns :data:`POINT_FIELDS`):
        no interval for a single training seed; ``best_known``: the row that names the best
        policy known at the point (its improvement columns empty, listed first)."""
        imp = {k: getattr(self, k) for k in IMPROVEMENT_FIELDS}
        ci = None if len(self.seeds) == 1 and not best_known else self.gain_ci95
        head = {"policy": self.policy, "seeds": list(self.seeds),
                "gain_per_seed": list(self.gain_per_seed)}
        body = {**{k: getattr(self, k) for k in _FIGURES},
                "failure_rate_max": self.failure_rate_max,
                "gain_pct": self.gain_pct, "gain_ci95": ci}
        rows = {**head, **imp, **body} if best_known else {**head, **body, **imp}
        return {**rows, "param": param, "value": value,
                "share_of_best_known_pct": self.share_of_best_known_pct}

    def table_markdown(self) -> str:
        """The row's line of ``table.md``."""
        seeds = ", ".join(map(str, self.seeds)) or "-"
        per_seed = ", ".join(f"{g:+.2f}" for g in self.gain_per_seed) or "-"
        times = [t for t in self.train_time_s if t is not None]
        ttime = f"{max(times) / 60:.1f} min max" if times else ("n/a" if self.seeds else "-")
        ci = "-" if math.isnan(self.gain_ci95) else f"{self.gain_ci95:.2f}"  # one seed: none
        imp = ("-" if self.improvement_pct is None else
               f"{self.improvement_pct:+.2f} ± {self.improvement_ci95:.2f}")
        return (f"| {self.policy} | {self.objective or '-'} | {self.trained_on or '-'} | "
                f"{seeds} | {self.trips_mean:.2f} | {self.queue_mean:.2f} | "
                f"{self.failure_rate:.3f} | {self.gain_pct:+.2f} | {ci} | {per_seed} | "
                f"{self.gain_vs_heuristic_pct:+.2f} | {ttime} | {imp} |")

    @classmethod
    def from_table_dict(cls, d: dict[str, Any]) -> Row:
        """A row of ``table.json`` back (the writers' inverse)."""
        return cls(**{k: d.get(k, None) for k in ("policy", "trips_mean", "trips_std",
                                                  "queue_mean", "failure_rate", "gain_pct",
                                                  "gain_ci95", "gain_vs_heuristic_pct",
                                                  "improvement_pct", "improvement_ci95")},
                   seeds=list(d.get("seeds", [])), gain_min=d.get("gain_min"),
                   gain_per_seed=list(d.get("gain_per_seed", [])),
                   failure_rate_max=d["failure_rate"], objective=d.get("objective") or "",
                   trained_on=d.get("trained_on") or "",
                   train_time_s=list(d.get("train_time_s", [])))


__all__ = ["IMPROVEMENT_FIELDS", "KINDS", "POINT_FIELDS", "TABLE_FIELDS", "Candidate", "Row"]
