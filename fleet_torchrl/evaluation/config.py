"""Schema of the evaluation protocol (the ``eval`` group)."""

from __future__ import annotations

from dataclasses import dataclass

from ..utils.checks import check_device, check_fields, ranged, validate_on_init

BACKENDS = ("auto", "eager", "fused")


def fused_switch(backend: str) -> bool | None:
    """The ``fused`` argument of :func:`~fleet_torchrl.evaluation.protocol.simulate` for an
    ``eval.backend`` value."""
    return {"auto": None, "eager": False, "fused": True}[backend]


@dataclass
class EvalConfig:
    """Evaluation protocol of MODEL §4 (thesis: 1000 simulations x 10 000 ticks)."""

    n_sims: int = ranged(1000, 1, 10**8)
    ticks: int = ranged(10000, 1, 10**9)
    seed: int = ranged(0, 0, 2**32 - 1)
    out: str | None = None  # result JSON path; the per-simulation CSV is written beside it
    overwrite: bool = False  # replace an existing result at ``out`` (else the run is refused)
    device: str = "cpu"
    chunk: int = ranged(256, 1, 1_000_000)  # ticks of closure draws generated at once
    progress: bool = True
    # auto: the compiled event loop on CPU (sim/fused.py), else eager; eager: one tensor tick
    # at a time; fused: the compiled loop on CPU (other devices run eager). Same records.
    backend: str = ranged("auto", choices=BACKENDS)

    def __post_init__(self) -> None:
        validate_on_init(self)

    def validate(self, path: str = "eval") -> EvalConfig:
        check_fields(self, path)
        check_device(f"{path}.device", self.device)
        return self


# a simulation's records in a result (four Python ints in lists, a CSV row, a JSON entry)
RECORD_BYTES = 1500


def eval_bytes(site_bytes: int, n_sims: int, sites_per_sim: int = 1) -> int:
    """Memory of an evaluation of ``n_sims`` simulations (``sites_per_sim`` sites in flight
    for each: more for a planner, whose futures are sites too) with its records."""
    return n_sims * (site_bytes * sites_per_sim + RECORD_BYTES)
