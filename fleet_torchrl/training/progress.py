"""The run state of a training run: a small typed object that checkpoints itself."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, fields
from typing import Any

from ..env.objectives import OBJECTIVES

# what a guarded selection takes off a snapshot below the heuristic somewhere: more than any
# objective's score spans (trips and queue ticks per site stay far below 1e6; float64 keeps
# the difference between two penalised scores exact to 1e-6), so such a snapshot ranks below
# every one that is not. An offset rather than a third rank key: ``Progress.best`` is a
# ``(failure rate, score)`` pair in every saved checkpoint, which a resume must still read.
GUARD_PENALTY = 1e9


def selection_score(select: str, objective: str, res: dict[str, Any],
                    worst_gain: float | None = None, below: Sequence[str] = ()) -> float:
    """What ranks two evaluations with the same failure rate (``train.select``): the mean
    trips (``trips``), or the score of the objective being learned (``objective``, the
    agent's :meth:`~fleet_torchrl.agents.base.AgentConfig.objective`): the thesis reward
    costs queue ticks, so fewer of them win; the throughput reward and the direct search
    count trips, so more of them win. ``robust``: the worst paired gain over the heuristic
    in any stratum of the selection set (``worst_gain``, see
    :func:`~fleet_torchrl.evaluation.worst_stratum_gain`), so a snapshot that loses to the
    heuristic anywhere ranks below one that never does. ``guarded``: the ``objective`` score,
    but a snapshot significantly below the heuristic in some stratum (``below``, their names,
    :func:`~fleet_torchrl.evaluation.strata_below`) ranks below every one that is not."""
    if select == "guarded":
        return selection_score("objective", objective, res) - (GUARD_PENALTY if below else 0.0)
    if select == "robust":
        assert worst_gain is not None, "select=robust needs the worst stratum gain"
        return float(worst_gain)
    if select == "objective" and objective in OBJECTIVES:
        return OBJECTIVES[objective].snapshot_score(res)
    return float(res["trips_mean"])  # (the direct search's objective is "trips")


@dataclass
class EvalEntry:
    """One periodic evaluation of the greedy policy (on the training-evaluation set)."""

    round: int
    frames: int
    trips: float
    queue: float
    failure_rate: float
    gain_pct: float
    wall_s: float = 0.0


@dataclass
class Progress:
    """Counters, early-stopping state and the evaluation history of one run.

    ``best`` is ``(failure rate, score)`` of the best evaluation so far: a lower failure
    rate wins, then a higher score (the mean trips, the objective's own score with
    ``train.select=objective``, or the worst stratum's gain over the heuristic with
    ``robust``; see :func:`selection_score`).
    """

    round: int = 0
    frames: int = 0
    episodes: int = 0
    best: tuple[float, float] | None = None
    best_round: int | None = None
    evals_since_best: int = 0
    stopped_early: bool = False
    wall_s: float = 0.0
    history: list[EvalEntry] = field(default_factory=list)

    def is_better(self, failure_rate: float, score: float) -> bool:
        if self.best is None:
            return True
        return (-failure_rate, score) > (-self.best[0], self.best[1])

    def best_entry(self) -> EvalEntry | None:
        if self.best_round is None:
            return None
        return next((h for h in self.history if h.round == self.best_round), None)

    # checkpoint protocol (torchrl.checkpoint calls these)
    def state_dict(self) -> dict[str, Any]:
        return asdict(self)

    def load_state_dict(self, state: dict[str, Any]) -> None:
        for f in fields(self):
            setattr(self, f.name, state[f.name])
        self.best = tuple(self.best) if self.best is not None else None
        self.history = [EvalEntry(**h) for h in self.history]
