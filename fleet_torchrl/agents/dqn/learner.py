"""Deep Q-learning on TorchRL (MODEL §3): the ``make_*`` factories and the learner.

Pieces, each from TorchRL: an ``MLP`` Q-network wrapped in a ``QValueActor`` (categorical
actions), ``EGreedyModule`` exploration, a ``TensorDictReplayBuffer`` on ``LazyTensorStorage``
(optionally a ``PrioritizedSampler``), ``DQNLoss`` (MSE, optional double DQN) with a TD(0)
value estimator that bootstraps on ``terminated`` only, ``HardUpdate`` of the target network
every ``network.target_update`` gradient steps (or ``SoftUpdate`` with ``network.tau > 0``),
and Adam with ``weight_decay`` as the L2 term, its learning rate optionally decayed
(``network.lr_decay``) over the run's gradient steps.

Anchoring (``agent.anchor``, MODEL §3.5). With ``anchor=heuristic`` the greedy policy is the
queue-aware heuristic except where the Q-network prefers the other action by more than
``agent.anchor_margin`` (in the Q-network's units, i.e. scaled rewards): the learner only
overrides a strong baseline where it has learned a clear advantage, a baseline-constrained
policy improvement (residual policy learning, SPIBB). With margin 0 it is the plain greedy
policy (except on an exact tie of the two Q-values, where it takes the heuristic's action);
with an infinite margin, the heuristic (the default one, its parameters saved with the
policy). Exploration is epsilon-greedy around the
anchored greedy policy; the Q-learning itself is unchanged (off-policy max backups).

Semi-Markov discounting and n-step returns. Each stored transition carries
``steps_to_next_obs``, the exponent of the discount to its bootstrap state, which TorchRL's
TD(0) estimator applies as ``gamma ** steps_to_next_obs``: the number of decisions
(``mdp.reward=thesis``, ``gamma`` per decision) or of ticks (``throughput``, ``gamma_tick`` per
tick; :func:`fleet_torchrl.env.discount_exponent`). :func:`n_step` folds up to
``agent.n_steps`` consecutive steps of a round's ``[sites, steps]`` batch into one transition
(discounting each reward by the exponents before it); a window stops at the end of an
episode, before a truncated step, and at the end of the round.
"""

from __future__ import annotations

from dataclasses import asdict
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase, TensorDictSequential
from torch import Tensor, nn
from torchrl.data import (
    Categorical,
    Composite,
    LazyTensorStorage,
    PrioritizedSampler,
    TensorDictReplayBuffer,
    TensorSpec,
)
from torchrl.modules import EGreedyModule, QValueActor, SafeSequential
from torchrl.objectives import DQNLoss, HardUpdate, SoftUpdate

from ...env import MDPConfig, discount_exponent
from ...utils.checks import (
    ConfigError,
    check_choice,
    check_known_fields,
    check_range,
    check_types,
    deferred_validation,
)
from ..base import INT, REAL, STR, Learner, Policy, check_spec_fields, relu_mlp
from ..baselines.policy import HeuristicPolicy
from .config import ANCHORS, DQNAgentConfig, NetworkConfig


def make_qnet(net: NetworkConfig, n_obs: int) -> nn.Module:
    """MLP ``n_obs -> [width] * depth (ReLU) -> 2`` with an identity output
    (:func:`~fleet_torchrl.agents.base.relu_mlp`)."""
    return relu_mlp(n_obs, 2, net.width, net.depth)


class DQNPolicy(Policy):
    """Greedy policy of a Q-network (ties -> pass), usable by the evaluation protocol;
    with ``anchor="heuristic"`` the heuristic's action unless Q prefers the other one by more
    than ``anchor_margin`` (module docstring)."""

    name = "dqn"
    map_tc_values = (0.0, 0.2, 0.4, 0.6, 0.8, 1.0)

    def __init__(self, network: NetworkConfig, n_obs: int, encoding: str,
                 anchor: str = "none", anchor_margin: float = 0.0,
                 anchor_params: dict[str, float] | None = None) -> None:
        super().__init__()
        self.network, self.n_obs = network, n_obs
        self.qnet = make_qnet(network, n_obs)
        self.encoding = encoding
        self.name = f"dqn_{encoding}"
        if anchor not in ANCHORS:
            raise ValueError(f"anchor={anchor!r} is invalid: allowed one of {', '.join(ANCHORS)}")
        self.anchor, self.anchor_margin = anchor, float(anchor_margin)
        if anchor != "none":  # the heuristic of MODEL §3, with its parameters fixed here
            self.base = HeuristicPolicy(**(anchor_params or {}))

    def policy_spec(self) -> dict[str, Any]:
        out = {"network": asdict(self.network), "n_obs": self.n_obs, "encoding": self.encoding}
        if self.anchor != "none":
            b = self.base
            out.update(anchor=self.anchor, anchor_margin=self.anchor_margin,
                       anchor_params={"threshold": b.threshold, "upper": b.upper,
                                      "others_below": b.others_below})
        return out

    size_fields = "spec.network.width and spec.network.depth"

    @classmethod
    def check_policy_spec(cls, spec: dict[str, Any]) -> None:
        check_spec_fields(spec, {"network": ((dict,), "a dict of network settings"),
                                 "n_obs": INT, "encoding": STR, "anchor": STR,
                                 "anchor_margin": REAL,
                                 "anchor_params": ((dict, type(None)), "a dict or null")},
                          required=("network", "n_obs", "encoding"))
        net = spec["network"]
        check_known_fields(NetworkConfig, net, "spec.network")
        with deferred_validation():
            cfg = NetworkConfig(**net)
        check_types(cfg, "spec.network")
        cfg.validate("spec.network")
        check_range("spec.n_obs", spec["n_obs"], 1, 100_000)
        check_choice("spec.anchor", spec.get("anchor", "none"), ANCHORS)
        margin = spec.get("anchor_margin", 0.0)
        if not margin >= 0:  # an infinite margin is the heuristic itself
            raise ConfigError(f"spec.anchor_margin={margin} is invalid: allowed a number >= 0")
        params = spec.get("anchor_params") or {}
        check_spec_fields(params, dict.fromkeys(("threshold", "upper", "others_below"), REAL),
                          path="spec.anchor_params")
        for key, value in params.items():
            check_range(f"spec.anchor_params.{key}", value, 0.0, 100.0)

    @classmethod
    def from_policy_spec(cls, spec: dict[str, Any]) -> DQNPolicy:
        return cls(NetworkConfig(**spec["network"]), spec["n_obs"], spec["encoding"],
                   spec.get("anchor", "none"), spec.get("anchor_margin", 0.0),
                   spec.get("anchor_params"))

    def forward(self, obs: Tensor) -> Tensor:
        return self.actions(self.qnet(obs), obs)

    def actions(self, q: Tensor, obs: Tensor) -> Tensor:
        """The decisions of :meth:`forward` from its Q-values ``q`` of ``obs``."""
        if self.anchor == "none":
            return q.argmax(-1)
        adv = q[..., 1] - q[..., 0]
        base = self.base(obs[..., :3])
        m = self.anchor_margin
        return torch.where(adv > m, 1, torch.where(adv < -m, 0, base))


    def td_module(self, obs_key: str, action_key: str,
                  action_spec: TensorSpec) -> TensorDictModuleBase:
        """A Q-value actor over ``action_spec`` (:func:`~fleet_torchrl.agents.as_td_module`):
        writes ``action_value`` (the Q-network's), ``chosen_action_value`` (its greedy maximum,
        the backup of the project's learner) and ``action``, what TorchRL's ``DQNLoss`` takes
        as its value network. Anchored, ``action`` is then replaced by the anchored decision
        (:meth:`forward`; with ``double_dqn`` the loss's next action is that decision)."""
        actor = QValueActor(self.qnet, in_keys=[obs_key], spec=action_spec.clone(),
                            action_key=action_key)
        if self.anchor == "none":
            return actor
        return SafeSequential(actor, _AnchoredAction(self, obs_key, action_key, action_spec))


class _AnchoredAction(TensorDictModuleBase):
    """Replaces the greedy ``action`` of a Q-value actor by an anchored policy's decision
    from the ``action_value`` the actor wrote (no second forward of the Q-network)."""

    def __init__(self, policy: DQNPolicy, obs_key: str, action_key: str,
                 action_spec: TensorSpec) -> None:
        super().__init__()
        self.policy = policy
        self.in_keys = [obs_key, "action_value"]
        self.out_keys = [action_key]
        self.spec = Composite({action_key: action_spec.clone()}, shape=action_spec.shape)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        obs, q = (tensordict.get(k) for k in self.in_keys)
        tensordict.set(self.out_keys[0], self.policy.actions(q, obs))
        return tensordict


def make_actor(qnet: nn.Module) -> QValueActor:
    """Q-value actor over categorical actions (per-sample spec: two actions)."""
    return QValueActor(qnet, in_keys=["observation"], spec=Categorical(2))


def make_replay_buffer(net: NetworkConfig, prioritized: bool,
                       device: torch.device | str) -> TensorDictReplayBuffer:
    sampler = PrioritizedSampler(net.buffer_size, alpha=0.6, beta=0.4) if prioritized else None
    kw = {"sampler": sampler, "priority_key": "td_error"} if prioritized else {}
    return TensorDictReplayBuffer(storage=LazyTensorStorage(net.buffer_size, device=device),
                                  batch_size=net.batch_size, **kw)


def n_step(batch: TensorDictBase, n: int, gamma: float, expo: Tensor) -> TensorDictBase:
    """``n``-step transitions from a round's ``[B, T]`` batch (see the module docstring).

    ``expo``: ``[B, T, 1]`` discount exponent of each step. Returns the flat transitions whose
    first step is not truncated, each with the discounted sum of its window's rewards, the
    bootstrap observation and ``terminated`` of the window's last step, and
    ``steps_to_next_obs`` (the summed exponent), which TorchRL's TD(0) estimator applies as
    ``gamma ** steps_to_next_obs``.
    """
    r = batch["next", "reward"].squeeze(-1)
    e = expo.squeeze(-1).to(r.dtype)
    term = batch["next", "terminated"].squeeze(-1)
    trunc = batch["next", "truncated"].squeeze(-1)
    done = batch["next", "done"].squeeze(-1)
    b, t_len = r.shape
    t = torch.arange(t_len, device=r.device)
    ret = torch.zeros_like(r)
    ex = torch.zeros_like(r)
    last = t.expand(b, t_len).clone()
    alive = ~trunc
    for i in range(n):
        idx = (t + i).clamp(max=t_len - 1)
        ok = alive & ((t + i) < t_len) & ~trunc[:, idx]
        ret = ret + ok * torch.pow(gamma, ex) * r[:, idx]
        ex = ex + ok * e[:, idx]
        last = torch.where(ok, idx, last)
        alive = ok & ~done[:, idx]
    nxt_obs = batch["next", "observation"]
    nxt_obs = nxt_obs.gather(1, last[..., None].expand(-1, -1, nxt_obs.shape[-1]))
    out = batch.select("observation", "action").clone()
    out.set(("next", "observation"), nxt_obs)
    out.set(("next", "reward"), ret.unsqueeze(-1))
    out.set(("next", "terminated"), term.gather(1, last).unsqueeze(-1))
    out.set(("next", "done"), out["next", "terminated"].clone())
    out.set(("next", "truncated"), torch.zeros_like(out["next", "terminated"]))
    out.set("steps_to_next_obs", ex.unsqueeze(-1))
    return out[~trunc]


class DQNLearner(Learner):
    """Everything DQN learns with; ``state_dict`` covers networks, target, epsilon, the
    optimiser and its schedule (the replay buffer is a separate checkpoint component).

    A round collects ``agent.steps_per_round`` environment steps of all sites (a site whose
    episode ends starts the next one at once), folds them into n-step transitions for the
    replay buffer, then makes ``agent.updates_per_round`` gradient steps.
    """

    collects = True  # its rounds come from TorchRL's Collector (fleet_torchrl.training.collect)
    KEYS = ("observation", "action", "ticks", ("next", "observation"), ("next", "reward"),
            ("next", "done"), ("next", "terminated"), ("next", "truncated"), ("next", "ticks"))

    @classmethod
    def from_context(cls, c: Any) -> DQNLearner:
        return cls(c.agent, c.network, c.n_obs, c.state, c.action_spec, c.mdp, c.device,
                   total_updates=c.rounds * c.agent.updates_per_round)

    def __init__(self, agent: DQNAgentConfig, net: NetworkConfig, n_obs: int, encoding: str,
                 action_spec: TensorSpec, mdp: MDPConfig, device: torch.device | str,
                 total_updates: int = 0) -> None:
        super().__init__()
        self.greedy = DQNPolicy(net, n_obs, encoding, agent.anchor,
                                agent.anchor_margin).to(device)
        self.qnet = self.greedy.qnet
        self.steps_per_round = agent.steps_per_round
        self.updates_per_round = agent.updates_per_round
        self.reset_each_round = agent.reset_each_round
        self.mdp = mdp
        self.gamma = mdp.discount
        self.n_steps = agent.n_steps
        self.reward_scale = agent.reward_scale
        self.actor = make_actor(self.qnet)
        self.egreedy = EGreedyModule(action_spec.clone(), eps_init=agent.eps_start,
                                     eps_end=agent.eps_end,
                                     annealing_num_steps=agent.eps_decay_frames)
        self.explore = TensorDictSequential(self.actor, self.egreedy)
        self.anchored = agent.anchor != "none"
        self.loss = DQNLoss(self.actor, loss_function="l2", delay_value=True,
                            double_dqn=agent.double_dqn, action_space="categorical")
        self.loss.make_value_estimator(gamma=self.gamma)
        if net.tau > 0:
            self.target_updater = SoftUpdate(self.loss, tau=net.tau)
        else:
            self.target_updater = HardUpdate(self.loss,
                                             value_network_update_interval=net.target_update)
        self.optimizer = torch.optim.Adam(self.loss.value_network_params.values(True, True),
                                          lr=net.lr, weight_decay=net.weight_decay)
        factor = net.lr_factor(total_updates)
        self.scheduler = (torch.optim.lr_scheduler.LambdaLR(self.optimizer, factor)
                          if factor is not None else None)
        self.buffer = make_replay_buffer(net, agent.prioritized, device)
        self.grad_clip = net.grad_clip
        self.prioritized = agent.prioritized
        self._steps: list[TensorDictBase] = []

    # ------------------------------------------------------------------ Learner
    def exploration(self) -> float:
        return float(self.egreedy.eps)

    def policy(self) -> DQNPolicy:
        return self.greedy

    def act(self, td: TensorDictBase) -> TensorDictBase:
        """Epsilon-greedy actions, then epsilon advances by their frames (``td.numel()``):
        the next step acts with the annealed value, whether the training loop or a
        ``Collector`` (:mod:`fleet_torchrl.training.collect`) steps the environment."""
        if self.anchored:  # epsilon-greedy around the anchored greedy policy
            with torch.no_grad():
                td.set("action", self.greedy(td["observation"]))
            td = self.egreedy(td)
        else:
            td = self.explore(td)
        e = self.egreedy  # EGreedyModule.step(n) loops n times: one closed-form step instead
        e.eps.data.copy_(torch.maximum(e.eps_end, e.eps - td.numel() * (e.eps_init - e.eps_end)
                                       / e.annealing_num_steps))
        return td

    def checkpoint_components(self) -> dict[str, Any]:
        return {"replay_buffer": self.buffer}

    def start_round(self, round_idx: int) -> None:
        self._steps = []

    def observe(self, td: TensorDictBase, learn: torch.Tensor) -> None:
        """Keep the step for the round's n-step folding (epsilon advanced when it acted).
        Truncated steps are left out when folding (their next observation is no decision
        state, see :mod:`fleet_torchrl.training`)."""
        self._steps.append(td.select(*self.KEYS).clone())

    def update(self) -> dict[str, float]:
        """Store the round's transitions, then its gradient steps; logs the mean loss, the
        learning rate, the mean gradient norm (before clipping) and the mean greedy Q-value
        of the last batch (scaled reward units)."""
        if self._steps:
            self.store(torch.stack(self._steps, dim=1))
            self._steps = []
        loss, grad_norm, q_mean = self.train_steps(self.updates_per_round)
        return {"loss/td": loss, "loss/grad_norm": grad_norm, "train/q_mean": q_mean,
                "train/lr": float(self.optimizer.param_groups[0]["lr"]),
                "train/buffer_size": len(self.buffer)}

    def store(self, batch: TensorDictBase) -> None:
        """Fold a ``[B, T]`` batch of steps into n-step transitions in the replay buffer."""
        trans = n_step(batch, self.n_steps, self.gamma, discount_exponent(batch, self.mdp))
        if self.reward_scale != 1.0:  # same greedy policy, larger Q-differences
            trans.set(("next", "reward"), trans["next", "reward"] * self.reward_scale)
        self.buffer.extend(trans)

    def train_steps(self, steps: int) -> tuple[float, float, float]:
        """``steps`` gradient steps; returns the mean loss, the mean gradient norm before
        clipping and the mean greedy Q of the last batch (all nan if the buffer is too
        small). The norm is measured without touching the gradients, so logging it changes
        no number of the run."""
        nan = float("nan")
        if len(self.buffer) < self.buffer.batch_size or steps == 0:
            return nan, nan, nan
        total = 0.0
        norms = torch.zeros((), device=self.optimizer.param_groups[0]["params"][0].device)
        params = list(self.loss.value_network_params.values(True, True))
        for _ in range(steps):
            sample = self.buffer.sample()
            loss = self.loss(sample)["loss"]
            self.optimizer.zero_grad(set_to_none=True)
            loss.backward()
            if self.grad_clip > 0:
                norm = torch.nn.utils.clip_grad_norm_(params, self.grad_clip)
            else:
                norm = torch.nn.utils.get_total_norm(
                    [p.grad for p in params if p.grad is not None])
            norms += norm.detach()
            self.optimizer.step()
            if self.scheduler is not None:
                self.scheduler.step()
            self.target_updater.step()
            if self.prioritized:
                self.buffer.update_tensordict_priority(sample)
            total += float(loss.detach())
        with torch.no_grad():
            q_mean = float(self.qnet(sample["observation"]).max(-1).values.mean())
        return total / steps, float(norms) / steps, q_mean

    def extra_state(self):  # optimiser, target-copy counter, schedule
        out = {"optimizer": (self.optimizer.state_dict, self.optimizer.load_state_dict),
               "target_counter": (lambda: getattr(self.target_updater, "counter", 0),
                                  self._set_target_counter)}
        if self.scheduler is not None:
            out["scheduler"] = (self.scheduler.state_dict, self.scheduler.load_state_dict)
        return out

    def _set_target_counter(self, counter: int) -> None:
        if hasattr(self.target_updater, "counter"):
            self.target_updater.counter = counter
