"""Distillation of the rollout planner (``agent=imitation``): DAgger onto a small network.

The rollout planner (:mod:`fleet_torchrl.agents.planner`) decides well where the heuristic
does not (``N_V`` = 5: +8 % over the rule against the heuristic's +3 %), but each of its
decisions simulates ``2 K`` futures of ``H`` ticks. This learner trains a small classifier
on an encoding of the state (``partial``, ``all`` or their ``_site`` variants) to take
the planner's decisions, so that planner-like decisions cost one forward pass.

**DAgger** (Ross, Gordon and Bagnell, 2011). A round plays ``agent.steps_per_round``
decisions of ``agent.num_sites`` sites of the training environment (episodes run on across
rounds). At every decision the expert, a :class:`~fleet_torchrl.agents.planner.PlannerPolicy`
built from ``agent.expert`` (the planner's own settings, base policy included), decides on
the site's full state (``env.site``, ``env.state``: the planner needs more than the
encoding shows), and that decision is the state's label. Each site then acts with the
expert's decision with probability ``beta`` and with the student's otherwise; ``beta`` goes
linearly from ``agent.beta_start`` (1: the first round follows the expert) to
``agent.beta_end`` (0: later rounds visit the states the student's own decisions lead to)
over ``agent.beta_rounds`` rounds. Every labelled ``(observation, expert action)`` pair goes
into one aggregated data set (a TorchRL replay buffer on a ``LazyTensorStorage`` of
``agent.capacity`` pairs, the oldest overwritten when full); each round ends with
``agent.updates_per_round`` Adam steps of the logistic (cross-entropy) loss on minibatches
of ``agent.batch_size`` drawn from all of it. The student charges iff its logit is positive
(a tie passes).

**Expert iteration** (Anthony, Tian and Barber, 2017; ``agent.iterate_from`` = ``k`` >= 1):
from round ``k`` on, the teacher is the planner over the student itself, a frozen copy taken
when each round begins, instead of over ``agent.expert.base``. Each label is then one step
of policy improvement over the current student, so the student is not held to the quality
of one step over a fixed base: where the best base is far from the best policy (a crowded
site, the whole site distribution) the student and its teacher climb together. The first
``k`` rounds, taught by the planner over ``agent.expert.base``, give the student a base worth
improving on. Such a teacher runs the student's network in every future (about 1-1.5 ms
per label instead of 0.1-0.4 ms for a base that decides inside the kernel).

The planner's futures have their own random streams, labelled by the site's index in the
environment's stream of training sites (``episode * num_sites + slot``: a new label every
episode), so a label depends on the state, that index and the planner's seed alone.

**Cost-sensitive labels** (``agent.label_weight=gap``; AggreVaTe, Ross and Bagnell, 2014):
a pair's weight in the loss is the planner's estimate of what the wrong action would cost
(``PlannerPolicy.last_gap``: the difference of the two actions' mean scores, a failure in
more futures counting as ``gap_cap``), clipped to ``[agent.gap_floor, agent.gap_cap]``. The
uniform loss spends the network on near-ties, where the planner's label is mostly its gate
keeping the base's action and either action costs little; weighted, the student fits the
decisions that carry the value. Over a site distribution that also moves the loss between
sites: sites whose decisions carry little (few vehicles, fast chargers) get little of it.
``agent.label_weight=site_gap`` keeps each site's share: a pair's clipped stake is divided by
the mean clipped stake of the round's pairs from the same site (same index in the stream of
training sites), so the weights move the loss between one site's decisions only.

Logged each round: ``loss/imitation`` (mean loss of the round's steps), ``train/agreement``
(the share of the round's states on which the student, as it was before the round's
update, decides as the expert: held-out agreement on the states it visits; with
``label_weight=gap`` also ``train/weighted_agreement``, the same weighted by stake), ``train/beta``
and ``train/dataset_size``.

Cost: the planner labels every visited state, ``2 K H`` site-ticks each (about 70-100 us of
one core at ``K`` = 16, ``H`` = 200): the budget is ``rounds x steps_per_round x num_sites``
labels; the gradient steps are cheap beside them.
"""

from __future__ import annotations

import copy
import math
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from torch import Tensor, nn
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

from ...sim import Site, SiteState, rng
from ...sim.rollout import DecisionContext
from ...utils.checks import ConfigError, check_range
from ..base import INT, REAL, STR, Learner, Policy, check_spec_fields, guard_actions, relu_mlp
from ..baselines.policy import HeuristicPolicy
from ..planner.policy import PlannerPolicy
from .config import ImitationAgentConfig


class ImitationPolicy(Policy):
    """A classifier network over an encoding: charge iff its logit is positive (ties pass).

    Where it decides on the site itself (the evaluation protocol, the training loop's
    selection, the planner's rollouts over it) it keeps the policy-independent safety line
    of :class:`~fleet_torchrl.agents.base.GuardedPolicy`: a vehicle below the site's reserve
    floor charges. A classifier's rare errors sit exactly there, where a mislabelled pass
    ends a site (measured: the generalist student failed about 1 % of the sites of the site
    distribution without it); its teacher never leaves a charge there either.

    With ``defer_margin`` m > 0 (calibrated by ``train.defer=heuristic``) the heuristic decides
    wherever the logit lies within ``[-m, m]`` (:func:`defer_to_heuristic`)."""

    name = "imitation"
    map_tc_values = (0.0, 0.2, 0.4, 0.6, 0.8, 1.0)
    can_defer = True

    def __init__(self, n_obs: int = 3, encoding: str = "partial", hidden: int = 128,
                 depth: int = 3, defer_margin: float = 0.0) -> None:
        super().__init__()
        self.n_obs, self.hidden, self.depth = int(n_obs), int(hidden), int(depth)
        self.encoding = encoding
        self.net = relu_mlp(self.n_obs, 1, self.hidden, self.depth)
        self.set_defer_margin(defer_margin)

    def set_defer_margin(self, margin: float) -> None:
        """Deferral to the heuristic (:func:`defer_to_heuristic`): where the logit lies within
        ``[-margin, margin]`` the heuristic of MODEL §3 decides; 0 = the network alone."""
        margin = float(margin)
        if not (0.0 <= margin < math.inf):
            raise ValueError(f"defer_margin={margin!r} is invalid: allowed a number >= 0")
        if margin > 0 and not defers_on(self.encoding):
            raise ValueError(f"defer_margin={margin!r} needs an encoding that starts with the "
                             f"partial state's features (partial, partial_site, "
                             f"partial_all_site), not {self.encoding!r}")
        self.defer_margin = margin

    def policy_spec(self) -> dict[str, Any]:
        spec = {"n_obs": self.n_obs, "encoding": self.encoding, "hidden": self.hidden,
                "depth": self.depth}
        if self.defer_margin > 0:  # files without it decide with the network alone
            spec["defer_margin"] = self.defer_margin
        return spec

    size_fields = "spec.hidden and spec.depth"

    @classmethod
    def check_policy_spec(cls, spec: dict[str, Any]) -> None:
        check_spec_fields(spec, {"n_obs": INT, "encoding": STR, "hidden": INT, "depth": INT,
                                 "defer_margin": REAL})
        check_range("spec.n_obs", spec.get("n_obs", 3), 1, 100_000)
        check_range("spec.hidden", spec.get("hidden", 128), 1, 4096)
        check_range("spec.depth", spec.get("depth", 3), 0, 16)
        margin = spec.get("defer_margin", 0.0)
        if not 0.0 <= margin < math.inf:
            raise ConfigError(f"spec.defer_margin={margin} is invalid: allowed a number >= 0")

    def logits(self, obs: Tensor) -> Tensor:
        """``[B]`` logit of *charge*."""
        return self.net(obs).squeeze(-1)

    def forward(self, obs: Tensor) -> Tensor:
        logit = self.logits(obs)
        if self.defer_margin > 0:
            return defer_to_heuristic(logit, obs, self.defer_margin)
        return (logit > 0).long()

    def decide(self, site: Site, state: SiteState, ctx: DecisionContext) -> Tensor:
        return guard_actions(site, state, super().decide(site, state, ctx))


def defers_on(encoding: str) -> bool:
    """Whether an encoding starts with the ``partial`` state's three features (the heuristic
    reads them), so a student on it can defer to the heuristic."""
    return encoding.startswith("partial")


def defer_to_heuristic(logit: Tensor, obs: Tensor, margin: float) -> Tensor:
    """A classifier's decisions with deferral to the heuristic of MODEL §3 (its default
    thresholds): *charge* where ``logit > margin``, *pass* where ``logit < -margin``, and the
    heuristic's action on the ``partial`` features ``obs[..., :3]`` in between, where the
    network is least sure. A safe-policy-improvement device (the baseline decides where the
    learned policy is uncertain): the margin is calibrated per run on validation sites
    (``train.defer``, :mod:`fleet_torchrl.training.deferral`)."""
    base = HeuristicPolicy()(obs[..., :3])
    return torch.where(logit > margin, 1, torch.where(logit < -margin, 0, base)).long()


class _Ref:
    """Holds an object outside the module tree (the expert, the environment): their
    weights and state are not the learner's and stay out of its ``state_dict``."""

    def __init__(self, obj: Any) -> None:
        self.obj = obj


class ImitationLearner(Learner):
    """DAgger around an :class:`ImitationPolicy` (module docstring). ``state_dict`` covers
    the student, the optimiser and the generator of the mixing draws; the data set is a
    separate checkpoint component (its own generator for the minibatches inside)."""

    reset_each_round = False  # episodes run on: a round's states are not all near a reset

    @classmethod
    def from_context(cls, c: Any) -> ImitationLearner:
        """The teacher is the planner ``agent.expert`` describes, over its bases."""
        if c.env is None:
            raise ValueError("agent=imitation labels the states of the training environment: "
                             "build it with LearnerContext(env=...)")
        expert = PlannerPolicy.from_agent(c.agent.expert).to(c.device)
        return cls(c.agent, expert, c.env, c.n_obs, c.state, c.seed, c.device)

    def __init__(self, agent: ImitationAgentConfig, expert: Policy, env: Any, n_obs: int,
                 encoding: str, seed: int = 0, device: torch.device | str = "cpu") -> None:
        super().__init__()
        self.agent = agent
        self.student = ImitationPolicy(n_obs, encoding, agent.hidden, agent.depth).to(device)
        self._expert, self._env = _Ref(expert), _Ref(env)
        self._first_expert: _Ref | None = None  # the configured teacher, under expert iteration
        self.steps_per_round = agent.steps_per_round
        self.updates_per_round = agent.updates_per_round
        self.optimizer = torch.optim.Adam(self.student.parameters(), lr=agent.lr,
                                          weight_decay=agent.weight_decay)
        total, floor = max(agent.rounds * agent.updates_per_round, 1), agent.lr_final
        self.scheduler = torch.optim.lr_scheduler.LambdaLR(
            self.optimizer, lambda k: floor + (1 - floor) * 0.5 * (1 + math.cos(
                math.pi * min(k / total, 1.0))))
        seeds = [int(rng.hash_ints(seed, k, rng.STREAM_TRAINING)) for k in (1, 2)]
        self.mix_gen = torch.Generator().manual_seed(seeds[0])  # who acts, per site and step
        self.data = TensorDictReplayBuffer(
            storage=LazyTensorStorage(agent.capacity, device=device),
            batch_size=agent.batch_size, generator=torch.Generator().manual_seed(seeds[1]))
        self.beta = agent.beta(0)
        self._label: Tensor | None = None
        self._weight: Tensor | None = None
        self._obs: list[Tensor] = []
        self._labels: list[Tensor] = []
        self._weights: list[Tensor] = []
        self._index: Tensor | None = None  # the sites' indices in the training stream
        self._sites: list[Tensor] = []
        self._agree, self._seen = 0, 0
        self._wagree, self._wseen = 0.0, 0.0

    @property
    def expert(self) -> Policy:
        return self._expert.obj

    @property
    def env(self) -> Any:
        return self._env.obj

    # ------------------------------------------------------------------ Learner
    def policy(self) -> ImitationPolicy:
        return self.student

    def exploration(self) -> float:
        return self.beta  # the share of decisions not taken by the student

    def checkpoint_components(self) -> dict[str, Any]:
        return {"dataset": self.data}

    def start_round(self, round_idx: int) -> None:
        self.beta = self.agent.beta(round_idx)
        k = self.agent.iterate_from
        if k and round_idx >= k:  # expert iteration: the planner over the student as it is
            if self._first_expert is None:
                self._first_expert = self._expert
            first = self._first_expert.obj
            frozen = copy.deepcopy(self.student).eval().requires_grad_(False)
            self._expert = _Ref(PlannerPolicy(frozen, first.rollouts, first.horizon,
                                              first.energy_value, first.confidence,
                                              first.seed))
        self._obs, self._labels, self._weights, self._sites = [], [], [], []
        self._agree, self._seen = 0, 0
        self._wagree, self._wseen = 0.0, 0.0

    @property
    def weighted(self) -> bool:
        """Whether labels weigh by the planner's stakes (``agent.label_weight`` ``gap`` or
        ``site_gap``)."""
        return self.agent.label_weight != "uniform"

    @property
    def per_site(self) -> bool:
        """Whether stakes are normalised within each site (``label_weight=site_gap``)."""
        return self.agent.label_weight == "site_gap"

    @staticmethod
    def site_normalised(weight: Tensor, site: Tensor) -> Tensor:
        """``weight`` over the mean weight of the pairs with the same ``site``: each
        site's pairs keep their summed weight equal to their count."""
        _, group = torch.unique(site, return_inverse=True)
        total = torch.zeros(int(group.max()) + 1, dtype=weight.dtype,
                            device=weight.device).index_add_(0, group, weight)
        count = torch.bincount(group).to(weight.dtype)
        return weight / (total / count).clamp(min=1e-12)[group]

    def label_weights(self) -> Tensor:
        """``[B]`` float32 weights of the labels :meth:`expert_actions` just gave: the
        planner's stake of each decision clipped to ``[gap_floor, gap_cap]``, over
        ``gap_cap`` (in ``(0, 1]``; a failure in more futures weighs 1)."""
        gap = getattr(self.expert, "last_gap", None)
        if gap is None:
            raise TypeError(f"agent.label_weight={self.agent.label_weight} needs a teacher "
                            "that reports its stakes (the rollout planner)")
        a = self.agent
        return (gap.clamp(a.gap_floor, a.gap_cap) / a.gap_cap).float()

    @torch.no_grad()
    def expert_actions(self) -> Tensor:
        """The expert's decision (``[B]`` int64) for every site of the environment as it
        stands: the planner on the sites' full states, each labelled by its index in the
        environment's stream of training sites (a new label every episode)."""
        env = self.env
        b = env.num_sites
        slot = torch.arange(b, device=env.device)
        index = (env.episodes - 1).clamp(min=0) * b + slot
        self._index = index
        need = torch.ones(b, dtype=torch.bool, device=env.device)
        return self.expert.decide(env.site, env.state,
                                  DecisionContext(need, index, env.fused)).long()

    def act(self, td: TensorDictBase) -> TensorDictBase:
        obs = td["observation"]
        label = self.expert_actions().to(obs.device)
        with torch.no_grad():
            student = self.student(obs)
        self._agree += int((student == label).sum())
        self._seen += label.numel()
        mine = torch.rand(label.shape, generator=self.mix_gen) >= self.beta
        self._label = label
        if self.weighted:
            self._weight = w = self.label_weights().to(obs.device)
            self._wagree += float((w * (student == label)).sum())
            self._wseen += float(w.sum())
        return td.set("action", torch.where(mine.to(obs.device), student, label))

    def observe(self, td: TensorDictBase, learn: Tensor) -> None:
        """Keep the step's ``(observation, expert action)`` pairs of the sites in ``learn``."""
        assert self._label is not None, "observe() without act()"
        self._obs.append(td["observation"][learn])
        self._labels.append(self._label[learn])
        if self.weighted:
            assert self._weight is not None
            self._weights.append(self._weight[learn])
        if self.per_site:
            assert self._index is not None
            self._sites.append(self._index.to(learn.device)[learn])
        self._label, self._weight = None, None

    def update(self) -> dict[str, float]:
        """Add the round's pairs to the data set, then the round's gradient steps."""
        if self._obs:
            obs, label = torch.cat(self._obs), torch.cat(self._labels)
            if label.numel():
                pairs = {"observation": obs, "label": label}
                if self.weighted:  # only then: data sets saved before it keep their keys
                    weight = torch.cat(self._weights)
                    if self.per_site:
                        weight = self.site_normalised(weight, torch.cat(self._sites))
                    pairs["weight"] = weight
                self.data.extend(TensorDict(pairs, batch_size=[label.numel()]))
            self._obs, self._labels, self._weights, self._sites = [], [], [], []
        out = {"loss/imitation": self.train_steps(self.updates_per_round),
               "train/beta": self.beta, "train/dataset_size": len(self.data)}
        if self._seen:
            out["train/agreement"] = self._agree / self._seen
        if self._wseen > 0:
            out["train/weighted_agreement"] = self._wagree / self._wseen
        return out

    def loss(self, batch: TensorDictBase) -> Tensor:
        """The logistic loss of the student on a batch of labelled pairs: the mean of the
        pairs' cross-entropy, weighted by their ``weight`` under ``label_weight`` ``gap`` or
        ``site_gap``."""
        per = nn.functional.binary_cross_entropy_with_logits(
            self.student.logits(batch["observation"]), batch["label"].float(),
            reduction="none")
        if not self.weighted:
            return per.mean()
        w = batch["weight"]
        return (w * per).sum() / w.sum().clamp(min=1e-12)

    def train_steps(self, steps: int) -> float:
        """``steps`` Adam steps of the logistic loss on minibatches of the data set (each
        pair weighted by its stake under ``label_weight=gap``, the batch's loss divided by
        its summed weight); returns the mean loss (nan with no data)."""
        if len(self.data) == 0 or steps == 0:
            return float("nan")
        total = torch.zeros(())
        for _ in range(steps):
            loss = self.loss(self.data.sample())
            self.optimizer.zero_grad(set_to_none=True)
            loss.backward()
            self.optimizer.step()
            self.scheduler.step()
            total += loss.detach()
        return float(total) / steps

    # ------------------------------------------------------------------ checkpoint
    def extra_state(self):  # optimiser, schedule, the generator of the expert mixing
        return {"optimizer": (self.optimizer.state_dict, self.optimizer.load_state_dict),
                "scheduler": (self.scheduler.state_dict, self.scheduler.load_state_dict),
                "mix_gen": (self.mix_gen.get_state,
                            lambda state: self.mix_gen.set_state(state.cpu()))}


__all__ = ["ImitationAgentConfig", "ImitationLearner", "ImitationPolicy"]
