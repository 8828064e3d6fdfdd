"""Schema of the training schedule (the ``train`` group)."""

from __future__ import annotations

from dataclasses import dataclass

from ..utils.checks import check_choice, check_device, check_range, validate_on_init

SELECTIONS = ("objective", "trips", "robust", "guarded")


@dataclass
class TrainConfig:
    """Training schedule, periodic evaluation, early stopping, checkpoints, logging."""

    max_episodes: int = 10_000  # N_E: budget of rounds x num_sites (one episode per site/round)
    eval_every: int = 2  # rounds between evaluations of the greedy policy
    eval_sims: int = 500  # evaluation sites (fixed common random numbers)
    eval_ticks: int = 3000
    eval_seed: int = 1_000_003  # distinct from the final evaluation's seed
    select: str = "objective"  # snapshot selection after failures: objective | trips | robust
                               # | guarded
    patience: int = 0  # evaluations without improvement before stopping (0 = never stop)
    checkpoint_every: int = 5  # rounds between checkpoints
    out_dir: str | None = None  # best policy goes here; default results/policies/<run name>
    device: str = "cpu"
    threads: int = 0  # torch CPU threads; 0 = torch's default
    tensorboard: bool = True
    progress: bool = True

    def __post_init__(self) -> None:
        validate_on_init(self)

    def validate(self, path: str = "train") -> TrainConfig:
        check_range(f"{path}.max_episodes", self.max_episodes, 1, None)
        check_range(f"{path}.eval_every", self.eval_every, 1, None)
        check_range(f"{path}.eval_sims", self.eval_sims, 1, 10**7)
        check_range(f"{path}.eval_ticks", self.eval_ticks, 1, 10**8)
        check_range(f"{path}.eval_seed", self.eval_seed, 0, 2**32 - 1)
        check_choice(f"{path}.select", self.select, SELECTIONS)
        check_range(f"{path}.patience", self.patience, 0, None)
        check_range(f"{path}.checkpoint_every", self.checkpoint_every, 1, None)
        check_range(f"{path}.threads", self.threads, 0, 1024)
        check_device(f"{path}.device", self.device)
        return self
