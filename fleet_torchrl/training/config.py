"""Schema of the training schedule (the ``train`` group)."""

from __future__ import annotations

from dataclasses import dataclass

from ..utils.checks import ConfigError, check_device, check_fields, ranged, validate_on_init

SELECTIONS = ("objective", "trips", "robust", "guarded")
DEFERRALS = ("none", "heuristic")
# settings applied after training, to the best snapshot (training/deferral.py): a finished
# run's checkpoint resumes under other values of them, its published policy does not
DEFERRAL_SETTINGS = ("defer", "defer_margins", "defer_points", "defer_sims", "defer_ticks")


@dataclass
class TrainConfig:
    """Training schedule, periodic evaluation, early stopping, checkpoints, logging."""

    # N_E: budget of rounds x num_sites (one episode per site/round)
    max_episodes: int = ranged(10_000, 1, 10**9)
    eval_every: int = ranged(2, 1, 10**6)  # rounds between evaluations of the greedy policy
    eval_sims: int = ranged(500, 1, 10**7)  # evaluation sites (fixed common random numbers)
    eval_ticks: int = ranged(3000, 1, 10**8)
    eval_seed: int = ranged(1_000_003, 0, 2**32 - 1)  # distinct from the final evaluation's seed
    # snapshot selection after failures: objective | trips | robust | guarded
    select: str = ranged("objective", choices=SELECTIONS)
    # evaluations without improvement before stopping (0 = never stop)
    patience: int = ranged(0, 0, 10**6)
    checkpoint_every: int = ranged(5, 1, 10**6)  # rounds between checkpoints
    # best policy goes here; default <table.policies_dir>/<run name>/seed<seed>
    out_dir: str | None = None
    # replace a policy already published in the publish folder (else such a run is refused)
    overwrite: bool = False
    device: str = "cpu"
    threads: int = ranged(0, 0, 1024)  # torch CPU threads; 0 = torch's default
    tensorboard: bool = True
    progress: bool = True
    # deferral to the heuristic (a classifier's policy, agent=imitation on a partial* state):
    # where the logit lies within [-m, m] the heuristic decides; m is calibrated after
    # training on validation sites: the first of 0, then defer_margins, at which the policy is
    # not significantly below the heuristic at any validation point (training/deferral.py)
    defer: str = ranged("none", choices=DEFERRALS)  # none | heuristic
    defer_margins: list[float] = ranged(lo=0, hi=100, lo_open=True, each=True,
                                        default_factory=lambda: [0.1, 0.2, 0.3, 0.5, 1.0])
    defer_points: int = ranged(5, 2, 50)  # values per drawn parameter of a site distribution
    defer_sims: int = ranged(500, 2, 10**7)  # validation sites per point (seed eval_seed)
    defer_ticks: int = ranged(10_000, 1, 10**8)

    def __post_init__(self) -> None:
        validate_on_init(self)

    def validate(self, path: str = "train") -> TrainConfig:
        margins = self.defer_margins
        if not isinstance(margins, (list, tuple)) or not 1 <= len(margins) <= 16:
            raise ConfigError(f"{path}.defer_margins={self.defer_margins!r} is invalid: allowed "
                              "a list of 1 to 16 margins in (0, 100]")
        check_fields(self, path)
        check_device(f"{path}.device", self.device)
        return self
