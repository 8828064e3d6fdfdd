"""A learner's rounds collected through TorchRL's ``Collector``.

A learner with ``steps_per_round = n`` plays ``n`` steps of all sites per round, a site whose
episode ends starting its next one at once: what a ``Collector`` of the batched environment
does with ``frames_per_batch = num_sites * n`` (``env.step_and_maybe_reset`` at each step).
For a learner that ``collects`` (DQN), :meth:`~fleet_torchrl.training.Trainer.collect_round`
runs its rounds through one (:class:`CollectedRounds`): the collector steps the environment
with the learner's exploring policy (:class:`ExplorationPolicy`, ``learner.act`` as a
TensorDict module), and the round's ``[num_sites, n]`` batch then goes to the learner step by
step (``learner.observe``) and to its ``update`` (for DQN: n-step folding into the replay
buffer, then the ``DQNLoss`` gradient steps). The steps, random draws and numbers are those
of the training loop's own stepping, bit for bit (``benchmarks/bench_collector.py`` checks
it and measures both).

Rounds start where the last one ended, or from fresh resets (``reset_each_round``, or no
round before). The collector is built at the first round a process plays, after any
checkpoint was loaded: its own first reset is then that round's reset, or, when a resumed run
goes on in the middle of episodes, the environment's loaded state is put back and the round
starts from the checkpoint's next step.

Learners whose ``observe`` needs what ``act`` saw beyond the step (the tabular learner updates
its table between two steps, the imitation learner labels each step from the site's state as
it acts) step the environment in :meth:`~fleet_torchrl.training.Trainer.play_round`.
"""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

__all__ = ["CollectedRounds", "ExplorationPolicy"]


class ExplorationPolicy(TensorDictModuleBase):
    """``learner.act`` as the policy of a ``Collector``: reads ``observation``, writes
    ``action`` (only: the learner's other outputs, Q-values, stay out of the collected batch).
    The collector takes its ``out_keys`` as its output (``use_buffers=False``) and so never
    calls it outside a step, which would draw random numbers and advance exploration."""

    def __init__(self, learner: Any, obs_key: str = "observation",
                 action_key: str = "action") -> None:
        super().__init__()
        self.__dict__["learner"] = learner  # not a submodule: its weights are the learner's
        self.in_keys = [obs_key]
        self.out_keys = [action_key]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        obs_key, action_key = self.in_keys[0], self.out_keys[0]
        acted = self.learner.act(tensordict.select(obs_key))
        return tensordict.set(action_key, acted.get(action_key))


class CollectedRounds:
    """The rounds of a learner with ``steps_per_round = n`` through one ``Collector`` of
    ``env`` (``frames_per_batch = env.num_sites * n``). ``start``: the root tensordict where
    the first round goes on (a resumed run's next step; the environment's state then stays
    as it is), or ``None`` to start from fresh resets."""

    def __init__(self, env: Any, learner: Any, start: TensorDictBase | None = None) -> None:
        from torchrl.collectors import Collector

        steps = learner.steps_per_round
        if not steps or steps < 1:
            raise ValueError(f"steps_per_round={steps!r} is invalid for collected rounds: "
                             "allowed an integer >= 1")
        self.env, self.learner, self.steps = env, learner, int(steps)
        # (cloned: a state_dict holds the live buffers, which the collector's reset changes)
        kept = None if start is None else {k: v.clone() for k, v in env.state_dict().items()}
        self.collector = Collector(env, ExplorationPolicy(learner),
                                   frames_per_batch=env.num_sites * self.steps,
                                   total_frames=-1, use_buffers=False, track_traj_ids=False)
        if kept is not None:  # the collector reset the sites: put the loaded ones back
            env.load_state_dict(kept)
            self.collector._carrier.update(start)
        self._batches = iter(self.collector)
        self._unused_reset = start is None  # the collector's own reset starts the first round

    @property
    def next_root(self) -> TensorDictBase:
        """The root tensordict of the next step (where the next round goes on)."""
        return self.collector._carrier

    def play(self, stats: Any, fresh: bool) -> TensorDictBase:
        """Collect one round (from fresh resets if ``fresh``) and hand its steps to the
        learner (``learner.observe``, every site learning from each step that is not
        truncated) and to ``stats`` (``EpisodeStats.add``); returns the collected batch."""
        if fresh and not self._unused_reset:
            self.collector.reset()
        self._unused_reset = False
        batch = next(self._batches)
        live = torch.ones(self.env.num_sites, dtype=torch.bool, device=batch.device)
        for t in range(self.steps):
            td = batch[:, t]
            self.learner.observe(td, live & ~td["next", "truncated"].squeeze(-1))
            stats.add(td, live)
        return batch

    def shutdown(self) -> None:
        self.collector.shutdown()
