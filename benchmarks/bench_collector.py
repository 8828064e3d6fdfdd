"""Training throughput of DQN stepped by the training loop itself against the same training
collected through TorchRL's ``Collector`` (:mod:`fleet_torchrl.training.collect`, what
training uses); a development tool of this repository, not part of the package.

    python benchmarks/bench_collector.py [REPEATS] [ROUNDS] [NUM_SITES] [STEPS] [UPDATES]

Both ways train the DQN of the table's ``dqn_partial`` recipe (``agent=dqn state=partial``:
the learner's and the network's defaults) on the default site, from the same seed, on 2
threads: ``loop``, ``Trainer.play_round`` stepping the environment (``learner.act``,
``env.step_and_maybe_reset``, ``learner.observe``), and ``collector``, a ``Collector`` with
the learner's exploring policy and ``frames_per_batch = NUM_SITES x STEPS``
(:class:`fleet_torchrl.training.collect.CollectedRounds`), feeding the same replay buffer and
``DQNLoss`` updates (``learner.update``). A pair of runs builds each way's environment
and learner and plays one warm-up round of each (the replay buffer fills, the kernel loads),
then times ``ROUNDS`` rounds of each, alternating round by round (a change of the machine's
load hits both): decisions (environment steps of every site) per second, the learner's
``UPDATES`` gradient steps per round included. Each pair prints its two figures, then come
the medians and their spread. Both ways must do the same work: the frames, the
gradient steps, epsilon and the Q-network's weights at the end of each pair of runs are
compared (bit for bit) and a difference ends the benchmark with exit code 1.

Defaults: 5 repeats of 4 rounds of the recipe's 256 sites x 40 steps, 200 updates.
"""

from __future__ import annotations

import statistics
import sys
import time
from types import SimpleNamespace
from typing import Any

import torch

THREADS = 2


def make(num_sites: int, steps: int, updates: int, rounds: int, seed: int = 0
         ) -> tuple[Any, Any]:
    """The environment and the DQN learner of the recipe (defaults but the schedule)."""
    from fleet_torchrl.agents.config import DQNAgentConfig, NetworkConfig
    from fleet_torchrl.agents.dqn import DQNLearner
    from fleet_torchrl.env import FleetChargingEnv, MDPConfig

    torch.manual_seed(seed)
    agent = DQNAgentConfig(num_sites=num_sites, steps_per_round=steps,
                           updates_per_round=updates)
    net, mdp = NetworkConfig(), MDPConfig()
    env = FleetChargingEnv(encoding="partial", num_sites=num_sites, mdp=mdp, seed=seed)
    learner = DQNLearner(agent, net, env.observation_spec["observation"].shape[-1], "partial",
                         env.action_spec, mdp, env.device,
                         total_updates=(rounds + 1) * updates)
    return env, learner


def play_rounds(env: Any, learner: Any, collects: bool) -> Any:
    """``Trainer.play_round`` on ``env`` and ``learner`` (the trainer's own methods, on the
    attributes they read; no evaluation, checkpoint or run folder), collecting through the
    ``Collector`` (``Trainer.collect_round``) or stepping the environment itself."""
    from fleet_torchrl.training.trainer import Trainer

    learner.collects = collects
    trainer = Trainer.__new__(Trainer)
    trainer.env, trainer.learner, trainer.device = env, learner, env.device
    trainer.progress = SimpleNamespace(round=0)
    trainer._next = trainer._episode_reward = trainer._collected = None

    def play() -> dict[str, float]:
        out = trainer.play_round()
        trainer.progress.round += 1
        return out

    return play


WAYS = {"loop": False, "collector": True}  # learner.collects


def run_pair(rounds: int, num_sites: int, steps: int, updates: int, loop_first: bool
             ) -> tuple[dict[str, float], dict[str, dict[str, Any]]]:
    """Both ways side by side: each builds its environment and learner and plays one
    warm-up round, then their ``rounds`` timed rounds alternate (the order flipping each
    round), so that a change of the machine's load hits both alike. Returns each way's
    decisions (environment steps of every site) per second of its timed rounds, and what it
    did (frames, gradient steps, epsilon, the Q-network's weights). Each way keeps its own
    global random state, as if it ran alone."""
    order = list(WAYS) if loop_first else list(reversed(list(WAYS)))
    play, rng, frames, spent = {}, {}, {}, {}
    learners = {}
    for way in order:
        env, learners[way] = make(num_sites, steps, updates, rounds)
        play[way] = play_rounds(env, learners[way], WAYS[way])
        frames[way], spent[way] = play[way]()["frames"], 0.0
        rng[way] = torch.get_rng_state()
    for r in range(rounds):
        for way in (order if r % 2 == 0 else order[::-1]):
            torch.set_rng_state(rng[way])
            t0 = time.perf_counter()
            frames[way] += play[way]()["frames"]
            spent[way] += time.perf_counter() - t0
            rng[way] = torch.get_rng_state()
    fps = {way: (frames[way] - num_sites * steps) / spent[way] for way in order}
    work = {way: {"frames": frames[way], "updates": _gradient_steps(lrn),
                  "epsilon": lrn.exploration(),
                  "weights": {k: v.clone() for k, v in lrn.qnet.state_dict().items()}}
            for way, lrn in learners.items()}
    return fps, work


def _gradient_steps(learner: Any) -> int:
    """The optimiser's steps so far (Adam counts them per parameter)."""
    state = learner.optimizer.state_dict()["state"]
    return int(state[0]["step"]) if state else 0


def same_work(a: dict[str, Any], b: dict[str, Any]) -> bool:
    return (a["frames"] == b["frames"] and a["updates"] == b["updates"]
            and a["epsilon"] == b["epsilon"]
            and all(torch.equal(v, b["weights"][k]) for k, v in a["weights"].items()))


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    try:
        values = [int(a) for a in args]
    except ValueError:
        values = [0]
    repeats, rounds, num_sites, steps, updates = (values + [5, 4, 256, 40, 200][len(args):])[:5]
    if len(args) > 5 or min(repeats, rounds, num_sites, steps) < 1 or updates < 0:
        print("usage: bench_collector.py [REPEATS] [ROUNDS] [NUM_SITES] [STEPS] [UPDATES] "
              "(integers >= 1; UPDATES >= 0)", file=sys.stderr)
        return 2
    threads = torch.get_num_threads()
    torch.set_num_threads(THREADS)
    try:
        return _pairs(repeats, rounds, num_sites, steps, updates)
    finally:
        torch.set_num_threads(threads)


def _pairs(repeats: int, rounds: int, num_sites: int, steps: int, updates: int) -> int:
    """``repeats`` pairs of runs; print each figure, then the medians."""
    fps: dict[str, list[float]] = {way: [] for way in WAYS}
    for r in range(repeats):
        rates, works = run_pair(rounds, num_sites, steps, updates, loop_first=r % 2 == 0)
        for way, rate in rates.items():
            fps[way].append(rate)
            print(f"repeat {r + 1}: {way:9s} {rate:8.0f} decisions/s", flush=True)
        if not same_work(works["loop"], works["collector"]):
            print("error: the loop and the collector did different work", file=sys.stderr)
            return 1
    med = {way: statistics.median(v) for way, v in fps.items()}
    for way, v in fps.items():
        print(f"{way:9s} median {med[way]:8.0f} decisions/s (min {min(v):.0f}, max {max(v):.0f})")
    ratios = [c / lo for c, lo in zip(fps["collector"], fps["loop"], strict=True)]
    print(f"collector / loop: median {statistics.median(ratios):.3f} (min {min(ratios):.3f}, "
          f"max {max(ratios):.3f}) over {repeats} pair(s) of runs; {THREADS} threads, "
          f"{num_sites} sites x {steps} steps, {updates} updates per round, {rounds} rounds")
    return 0


if __name__ == "__main__":
    sys.exit(main())
