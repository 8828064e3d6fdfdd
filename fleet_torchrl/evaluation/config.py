"""Schema of the evaluation protocol (the ``eval`` group)."""

from __future__ import annotations

from dataclasses import dataclass

from ..utils.checks import check_device, check_range


@dataclass
class EvalConfig:
    """Evaluation protocol of MODEL §4 (thesis: 1000 simulations x 10 000 ticks)."""

    n_sims: int = 1000
    ticks: int = 10000
    seed: int = 0
    out: str | None = None  # result JSON path; the per-simulation CSV is written beside it
    device: str = "cpu"
    chunk: int = 256  # ticks of closure draws generated at once
    progress: bool = True

    def validate(self, path: str = "eval") -> EvalConfig:
        check_range(f"{path}.n_sims", self.n_sims, 1, 10**8)
        check_range(f"{path}.ticks", self.ticks, 1, 10**9)
        check_range(f"{path}.seed", self.seed, 0, 2**32 - 1)
        check_range(f"{path}.chunk", self.chunk, 1, 1_000_000)
        check_device(f"{path}.device", self.device)
        return self
