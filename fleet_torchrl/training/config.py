"""Schema of the training schedule (the ``train`` group)."""

from __future__ import annotations

from dataclasses import dataclass, field

from ..utils.checks import ConfigError, check_choice, check_device, check_range, validate_on_init

SELECTIONS = ("objective", "trips", "robust", "guarded")
DEFERRALS = ("none", "heuristic")
# settings applied after training, to the best snapshot (training/deferral.py): a finished
# run's checkpoint resumes under other values of them, its published policy does not
DEFERRAL_SETTINGS = ("defer", "defer_margins", "defer_points", "defer_sims", "defer_ticks")


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
    # best policy goes here; default <table.policies_dir>/<run name>/seed<seed>
    out_dir: str | None = None
    # replace a policy already published in the publish folder (else such a run is refused)
    overwrite: bool = False
    device: str = "cpu"
    threads: int = 0  # torch CPU threads; 0 = torch's default
    tensorboard: bool = True
    progress: bool = True
    # deferral to the heuristic (a classifier's policy, agent=imitation on a partial* state):
    # where the logit lies within [-m, m] the heuristic decides; m is calibrated after
    # training on validation sites: the first of 0, then defer_margins, at which the policy is
    # not significantly below the heuristic at any validation point (training/deferral.py)
    defer: str = "none"  # none | heuristic
    defer_margins: list[float] = field(default_factory=lambda: [0.1, 0.2, 0.3, 0.5, 1.0])
    defer_points: int = 5  # values per drawn parameter of a site distribution
    defer_sims: int = 500  # validation sites per point (seed eval_seed)
    defer_ticks: int = 10_000

    def __post_init__(self) -> None:
        validate_on_init(self)

    def validate(self, path: str = "train") -> TrainConfig:
        check_range(f"{path}.max_episodes", self.max_episodes, 1, 10**9)
        check_range(f"{path}.eval_every", self.eval_every, 1, 10**6)
        check_range(f"{path}.eval_sims", self.eval_sims, 1, 10**7)
        check_range(f"{path}.eval_ticks", self.eval_ticks, 1, 10**8)
        check_range(f"{path}.eval_seed", self.eval_seed, 0, 2**32 - 1)
        check_choice(f"{path}.select", self.select, SELECTIONS)
        check_range(f"{path}.patience", self.patience, 0, 10**6)
        check_range(f"{path}.checkpoint_every", self.checkpoint_every, 1, 10**6)
        check_range(f"{path}.threads", self.threads, 0, 1024)
        check_device(f"{path}.device", self.device)
        check_choice(f"{path}.defer", self.defer, DEFERRALS)
        margins = self.defer_margins
        if not isinstance(margins, (list, tuple)) or not 1 <= len(margins) <= 16:
            raise ConfigError(f"{path}.defer_margins={self.defer_margins!r} is invalid: allowed "
                              "a list of 1 to 16 margins in (0, 100]")
        for i, m in enumerate(self.defer_margins):
            check_range(f"{path}.defer_margins[{i}]", m, 1e-9, 100.0, allowed="(0, 100]")
        check_range(f"{path}.defer_points", self.defer_points, 2, 50)
        check_range(f"{path}.defer_sims", self.defer_sims, 2, 10**7)
        check_range(f"{path}.defer_ticks", self.defer_ticks, 1, 10**8)
        return self
