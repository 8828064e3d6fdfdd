"""The agent interface: a :class:`Policy` is what gets evaluated, a :class:`Learner` what gets
trained. Every agent (baseline or learner) is one entry of :mod:`fleet_torchrl.agents.registry`.

A policy maps a batch of encoded observations ``[B, F]`` to actions ``[B]`` (int64,
``0 = pass``, ``1 = charge``) and names the state encoding it reads (``encoding``), so the
evaluation loop and the environment build the right features. A learned policy also says how
to rebuild itself from a policy file (:meth:`Policy.policy_spec` /
:meth:`Policy.from_policy_spec`; not ``spec``: TorchRL reads a module's ``spec`` attribute as
its output spec, and a method of that name breaks ``Collector`` on a wrapped policy).

A learner owns everything that changes while training (tables or networks, optimiser,
replay buffer, exploration schedule) and is driven by the one training loop of
:mod:`fleet_torchrl.training`: per round ``start_round``, then for every environment step
``act`` and ``observe``, then ``update``.
"""

from __future__ import annotations

import inspect
import numbers
from abc import ABC, abstractmethod
from collections.abc import Callable
from typing import Any, ClassVar

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import Tensor, nn

from ..env.encodings import get_encoding
from ..sim import D, Site, SiteState
from ..sim.fused import KernelPolicy
from ..sim.rollout import DecisionContext
from ..utils.checks import ConfigError

PASS, CHARGE = 0, 1
INT = ((numbers.Integral,), "an integer")
REAL = ((numbers.Real,), "a number")
STR = ((str,), "a string")


class Policy(nn.Module):
    """Base class: ``forward(obs [B, F]) -> action [B] (int64)``."""

    name: str = "policy"
    encoding: str = "partial"
    #: ``TC`` values of the panels of its policy map (free / busy by default)
    map_tc_values: ClassVar[tuple[float, ...]] = (0.0, 0.5)
    #: whether it can defer to the heuristic where it is unsure (``set_defer_margin``:
    #: a classifier's logit; ``train.defer``)
    can_defer: ClassVar[bool] = False
    #: whether it decides from the site's state (:meth:`decide` only, no :meth:`forward` of
    #: an observation): the rollout planner, a guarded policy
    decides_from_state: ClassVar[bool] = False

    def policy_spec(self) -> dict[str, Any]:
        """Constructor arguments a policy file stores to rebuild this policy (JSON-ready)."""
        return {}

    def decide(self, site: Site, state: SiteState, ctx: DecisionContext) -> Tensor:
        """Actions ``[B]`` for the sites of ``state`` (those in ``ctx.need`` are used, the
        others pass): the policy's encoding of the state, then one batched :meth:`forward`
        over the deciding sites' rows only. In a planner's rollouts half the batch has
        finished its horizon or failed while the rest still decide (measured: 51 % of the
        rows deciding at ``N_V`` = 4), so a network base forwards half the rows it did. A
        policy that works on the site itself (the rollout planner) overrides this."""
        obs = get_encoding(self.encoding)(site, state)
        need = ctx.need
        if bool(need.all()):
            return self(obs)
        rows = need.nonzero().squeeze(1)
        act = self(obs[rows])
        out = act.new_zeros(obs.shape[0])
        out[rows] = act
        return out

    def kernel_policy(self) -> KernelPolicy | None:
        """The same decisions as :meth:`forward`, taken inside the compiled kernel (the
        rule, the heuristic, threshold policies, action tables over the ``partial`` state;
        tests check every one against ``forward``), or ``None``: the simulation then
        stops at each decision epoch for a batched forward pass (networks)."""
        return None

    @classmethod
    def from_policy_spec(cls, spec: dict[str, Any]) -> Policy:
        """The policy :meth:`policy_spec` describes (its weights are loaded afterwards)."""
        return cls(**spec)

    @classmethod
    def from_agent(cls, agent: Any) -> Policy:
        """A baseline's policy from its ``agent`` config: ``from_config(agent)`` where the
        class has one, else its constructor with the config's fields of the same names."""
        make = getattr(cls, "from_config", None)
        if make is not None:
            return make(agent)
        params = inspect.signature(cls.__init__).parameters
        return cls(**{k: getattr(agent, k) for k in params if k != "self" and hasattr(agent, k)})

    def td_module(self, obs_key: str, action_key: str, action_spec: Any) -> TensorDictModuleBase:
        """This policy as a TensorDict module (:func:`as_td_module`): a :class:`PolicyModule`;
        a policy with Q-values returns a Q-value actor over ``action_spec``."""
        return PolicyModule(self, obs_key, action_key)

    #: the spec fields that size its tensors (named where a spec asks for too many)
    size_fields: ClassVar[str] = "spec"

    @classmethod
    def check_policy_spec(cls, spec: dict[str, Any]) -> None:
        """Raise :class:`~fleet_torchrl.utils.checks.ConfigError` (one line naming
        ``spec.<field>``) for a spec read from a file that :meth:`from_policy_spec` must not
        build: an unknown field, a value of the wrong type or out of range. Nothing is
        allocated here. The base class checks the fields against its constructor's
        parameters (names only, those without a default required); a learner's policy
        checks their types and ranges too."""
        params = [p for p in inspect.signature(cls.__init__).parameters.values()
                  if p.name != "self" and p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)]
        check_spec_fields(spec, {p.name: ((object,), "a value") for p in params},
                          required=tuple(p.name for p in params if p.default is p.empty))

    def check_loaded(self) -> str | None:
        """After its weights are loaded from a file: the first entry they hold that this
        policy cannot decide with (an action outside {0, 1}, a negative count), described
        in a few words, or None."""
        return None


def check_spec_fields(spec: Any, allowed: dict[str, tuple[tuple[type, ...], str]],
                      required: tuple[str, ...] = (), path: str = "spec") -> None:
    """Raise :class:`~fleet_torchrl.utils.checks.ConfigError` unless ``spec`` is a dict whose
    keys are among ``allowed`` (``{key: (types, the types in words)}``; a bool is no
    number), each of its type, with every ``required`` key present."""
    if not isinstance(spec, dict):
        raise ConfigError(f"{path} must be a dict, not {type(spec).__name__}")
    for key in spec:
        if key not in allowed:
            names = ", ".join(allowed) or "none"
            raise ConfigError(f"{path}.{str(key)[:40]} is not a field of this policy's spec "
                              f"(allowed: {names})")
    for key in required:
        if key not in spec:
            raise ConfigError(f"{path}.{key} is missing")
    for key, value in spec.items():
        types, words = allowed[key]
        ok = isinstance(value, types) and (bool in types or not isinstance(value, bool))
        if not ok:
            raise ConfigError(f"{path}.{key}={repr(value)[:40]} is invalid: allowed {words}")


def relu_mlp(n_in: int, n_out: int, width: int, depth: int) -> nn.Module:
    """The learners' network: ``n_in -> [width] * depth (ReLU) -> n_out``, identity output.
    The ReLUs work in place (the same values and gradients; a forward of 8000 rows at 3 x 128
    takes 17 % less time without their copies, docs/BENCHMARKS.md)."""
    from torchrl.modules import MLP

    return MLP(in_features=n_in, out_features=n_out, num_cells=[width] * depth,
               activation_class=nn.ReLU, activation_kwargs={"inplace": True})


class PolicyModule(TensorDictModuleBase):
    """A :class:`Policy` as a TensorDict module: reads ``in_keys[0]``, writes its actions to
    ``out_keys[0]`` in place. What ``TensorDictModule`` does for one tensor in and one out,
    without its per-call conversion of every output (``TensorDict.from_any``, which looks for
    pandas on disk at each call): environment collection at B = 1024 makes about 20 % more
    decisions per second with it (docs/BENCHMARKS.md).

    It writes no Q-values: TorchRL's ``DQNLoss`` (which asks its value network for its
    ``action_space``) is refused with one line naming the policy; a DQN policy's
    :func:`as_td_module` is a Q-value actor instead."""

    def __init__(self, policy: Policy, obs_key: str = "observation",
                 action_key: str = "action") -> None:
        super().__init__()
        self.module = policy
        self.in_keys = [obs_key]
        self.out_keys = [action_key]

    @property
    def action_space(self) -> str:
        raise ValueError(f"a {self.module.name} policy has no Q-values: DQNLoss (and every "
                         "Q-value loss) needs as_td_module of a dqn policy")

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        tensordict.set(self.out_keys[0], self.module(tensordict.get(self.in_keys[0])))
        return tensordict


class SiteStateModule(PolicyModule):
    """A policy that decides from the site's state (``Policy.decides_from_state``: the
    rollout planner, a guarded policy) as a TensorDict module bound to the environment it
    acts in: each call decides for every site of ``env`` at its current state, which is the
    state the TensorDict's observation encodes when ``env`` is stepped in this process
    (``env.rollout``, a ``Collector`` of ``env`` itself; not a collector of copies in other
    processes, which hold states of their own)."""

    def __init__(self, policy: Policy, env: Any, obs_key: str = "observation",
                 action_key: str = "action") -> None:
        super().__init__(policy, obs_key, action_key)
        for attr in ("site", "state", "num_sites"):
            if not hasattr(env, attr):
                raise ValueError(f"as_td_module(env=...) needs a FleetChargingEnv, not a "
                                 f"{type(env).__name__}")
        self.__dict__["env"] = env  # not a submodule: the env is not the module's to move

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        env = self.env
        if tuple(tensordict.batch_size) != (env.num_sites,):
            raise ValueError(f"a {self.module.name} policy bound to an env of "
                             f"{env.num_sites} sites got a batch of "
                             f"{tuple(tensordict.batch_size)}: it decides for its env's sites")
        need = torch.ones(env.num_sites, dtype=torch.bool, device=env.device)
        ctx = DecisionContext(need, torch.arange(env.num_sites, device=env.device),
                              getattr(env, "fused", None))
        act = self.module.decide(env.site, env.state, ctx).to(torch.int64)
        tensordict.set(self.out_keys[0], act)
        return tensordict


def as_td_module(policy: Policy, obs_key: str = "observation", action_key: str = "action",
                 action_spec: Any = None, env: Any = None) -> TensorDictModuleBase:
    """Wrap a policy as a TorchRL/TensorDict module (for ``env.rollout``, ``Collector``).

    A policy that has Q-values (DQN: :meth:`Policy.td_module`) becomes a Q-value actor that
    also writes ``action_value`` and ``chosen_action_value`` and carries ``action_spec``
    (default: one site's action, ``env.action_spec_unbatched``), what TorchRL's ``DQNLoss``
    takes; a policy that decides from the site's state needs ``env``, the environment it
    acts in (:class:`SiteStateModule`); every other policy a :class:`PolicyModule`."""
    if policy.decides_from_state:
        if env is None:
            raise ValueError(f"a {policy.name} policy decides from the site's state, not from "
                             "an observation: pass the environment it acts in, "
                             "as_td_module(policy, env=env)")
        return SiteStateModule(policy, env, obs_key, action_key)
    if action_spec is None:
        from torchrl.data import Categorical

        action_spec = Categorical(2, dtype=torch.int64)
    return policy.td_module(obs_key, action_key, action_spec)


class Learner(nn.Module, ABC):
    """What the training loop needs from a learner; ``state_dict`` is its checkpoint.

    ``steps_per_round``: environment steps per round, every site resetting itself when its
    episode ends (``None``: one episode per site, sites that are done stop learning and the
    round ends when all are done; ``0``: no environment step, the learner simulates what it
    needs itself in ``update``, as the direct policy search does). ``reset_each_round``:
    whether a round starts from fresh resets (with ``steps_per_round`` set, ``False`` lets
    episodes run on across rounds). ``collects``: with ``steps_per_round`` set, a round's
    steps come from TorchRL's ``Collector`` (:mod:`fleet_torchrl.training.collect`), which
    needs an ``observe`` that reads nothing ``act`` left behind but the step itself.
    """

    steps_per_round: int | None = None
    reset_each_round: bool = True
    collects: bool = False
    evaluate_start: bool = False  # True: the training loop also evaluates the start policy
    # the TensorBoard tag of exploration(): epsilon for the Q-learners, the search's spread
    exploration_tag: ClassVar[str] = "train/epsilon"

    @classmethod
    def from_context(cls, context: Any) -> Learner:
        """The learner a :class:`~fleet_torchrl.agents.registry.LearnerContext` describes
        (the agent's and the other groups' configs, seed, budget, device, environment): how
        the registry builds the learner its schema's ``learner_type`` names."""
        raise NotImplementedError(f"{cls.__name__}.from_context: a learner builds itself "
                                  "from a LearnerContext")

    def start_round(self, round_idx: int) -> None:  # noqa: B027 (optional hook)
        """Called before the first step of round ``round_idx`` (0-based)."""

    @abstractmethod
    def act(self, td: TensorDictBase) -> TensorDictBase:
        """Write exploring actions for ``td["observation"]`` into ``td["action"]``."""

    @abstractmethod
    def observe(self, td: TensorDictBase, learn: Tensor) -> None:
        """One environment step of all sites (``td`` holds ``next``); learn from the sites
        selected by the ``[B]`` bool ``learn``."""

    @abstractmethod
    def update(self) -> dict[str, float]:
        """End of a round: learn from what was observed; returns scalars to log."""

    @abstractmethod
    def policy(self) -> Policy:
        """The current greedy policy (shares parameters with the learner)."""

    @abstractmethod
    def exploration(self) -> float:
        """The current exploration (epsilon, or what :attr:`exploration_tag` names), for
        logging."""

    def checkpoint_components(self) -> dict[str, Any]:
        """Objects with ``state_dict``/``load_state_dict`` that a checkpoint needs besides the
        learner itself (e.g. a replay buffer)."""
        return {}

    def extra_state(self) -> dict[str, tuple[Callable[[], Any], Callable[[Any], None]]]:
        """What the learner's own ``state_dict`` carries beside its tensors (optimiser,
        learning-rate schedule, counters, random generators): ``{key: (get, set)}``, saved
        under ``_<key>`` and restored after the tensors, so that a resumed run continues
        exactly; a key absent from a loaded dict is left as it is."""
        return {}

    def state_dict(self, *args, **kwargs):
        sd = super().state_dict(*args, **kwargs)
        for key, (get, _) in self.extra_state().items():
            sd[f"_{key}"] = get()
        return sd

    def load_state_dict(self, state_dict, strict: bool = True, assign: bool = False):
        state_dict = dict(state_dict)
        extra = self.extra_state()
        values = {k: state_dict.pop(f"_{k}") for k in extra if f"_{k}" in state_dict}
        out = super().load_state_dict(state_dict, strict=strict, assign=assign)
        for key, value in values.items():
            extra[key][1](value)
        return out


class GuardedPolicy(Policy):
    """A policy with a policy-independent safety line: the vehicle at ``D`` charges whenever
    its battery is below the site's reserve floor (:meth:`Site.reserve_floor`: one more lap
    moving every tick plus waiting behind every other vehicle's full charge), whatever the
    policy says; otherwise the policy decides. A learned policy trained on one site can
    pass a nearly empty vehicle on another; this guard, reported wherever it is used, is
    what keeps such a run from failing (it changes nothing where the policy already
    charges below the floor, as the rule and the heuristic do on every site of the sweeps
    but the slowest, most crowded ones)."""

    def __init__(self, policy: Policy) -> None:
        super().__init__()
        self.policy = policy
        self.name = policy.name
        self.encoding = policy.encoding

    decides_from_state = True

    def forward(self, obs: Tensor) -> Tensor:
        raise TypeError("a guarded policy decides from the site's state: call decide()")

    def decide(self, site: Site, state: SiteState, ctx: DecisionContext) -> Tensor:
        return guard_actions(site, state, self.policy.decide(site, state, ctx))


def guard_actions(site: Site, state: SiteState, act: Tensor) -> Tensor:
    """``act`` with *charge* wherever the vehicle at ``D`` is below the site's reserve floor
    (:class:`GuardedPolicy`)."""
    soc_d = (state.soc * (state.pos == D)).sum(0)
    return torch.where(soc_d < site.reserve_floor(state.params), 1, act).to(act.dtype)
