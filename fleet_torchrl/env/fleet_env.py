"""The decision process of MODEL §2 as a batched TorchRL environment.

One environment step is one *decision epoch* per site: the action (``0`` pass, ``1`` charge)
applies to the vehicle waiting at ``D``; the site then runs tick by tick until the next vehicle
reaches ``D`` (a new decision), the site fails (``terminated``) or the episode's tick budget
``tau_e`` runs out (``truncated``). Sites finish at different ticks; a site that is done for
this step is frozen (it does not advance) while the others go on.

Reward, ``mdp.reward`` (MODEL §2): the simulator reports each step's events (its ticks,
trips, queue ticks, and what its last tick brought) and the objective of
:mod:`fleet_torchrl.env.objectives` turns them into the reward and the discount exponent of
the step (:func:`discount_exponent`): ``thesis`` (default), the mean cost of the step's
ticks, discounted per decision; ``throughput``, a semi-Markov, differential trip reward,
discounted per tick.

Every site's episode ``k`` uses site index ``k * B + b`` in the common random numbers of
:mod:`fleet_torchrl.sim.rng` under ``rng.training_seed(seed)``, so the whole stream of initial
states and closures is a pure function of the seed (:meth:`set_seed`) and the batch size, and
never coincides with the sites of the evaluation protocol (which uses its seed directly).
After a reset a site runs until its first decision; in the rare case that it fails before
any vehicle reaches ``D`` (only possible with a tiny ``xi``), it is redrawn with its next
episode index.

Backends (``fused``, same observations, rewards and flags bit for bit): by default a step
is ONE call of the compiled kernel of :mod:`fleet_torchrl.sim.fused`, which runs every site
to its next decision, failure or ``tau_e`` (``fused=None``/``True``); ``fused=False`` runs
the eager loop of :meth:`Site.tick` calls, one per tick with a host sync per tick.

The environment's ``state_dict`` holds everything that evolves: the episode counter of every
slot (a buffer), the training seed, and the sites themselves (vehicles, decisions, tick
counts, closure hashes, per-episode counters), so a checkpoint continues the stream of
training sites exactly, also in the middle of episodes.

Besides ``observation`` the environment reports per-episode counters ``trips``,
``queue_ticks`` and ``ticks`` (cumulative since the site's reset) for logging.
"""

from __future__ import annotations

from dataclasses import fields

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from ..sim import Site, SiteConfig, SiteParams, rng
from ..sim import fused as _fused
from ..sim.rollout import advance, advance_eager
from .config import MDPConfig
from .encodings import get_encoding

_MAX_REDRAWS = 100
_NO_LIMIT = 1 << 62  # tick limit of the run to the first decision (none)


def step_ticks(td: TensorDictBase) -> torch.Tensor:
    """Ticks of each step of a rollout or batch: ``next.ticks - ticks`` (``[..., 1]``)."""
    return td.get(("next", "ticks")) - td.get("ticks")


def discount_exponent(td: TensorDictBase, mdp: MDPConfig) -> torch.Tensor:
    """The exponent of ``mdp.discount`` for each transition (float, ``[..., 1]``), as the
    objective says: 1 per decision (``thesis``) or the step's ticks (``throughput``,
    ``gamma_tick^dt``)."""
    return mdp.objective.exponent(step_ticks(td))


class FleetChargingEnv(EnvBase):
    """Batched charging-site MDP (``batch_size=[num_sites]``).

    ``fused``: ``None`` (default) steps with the compiled kernel wherever it runs (always on
    the CPU, on CUDA with numba-cuda), ``True`` forces it, ``False`` uses the eager tick
    loop (:func:`fleet_torchrl.sim.fused.use_fused`).
    """

    _batch_locked = True

    def __init__(self, site: SiteConfig | None = None, encoding: str = "partial",
                 num_sites: int = 1, mdp: MDPConfig | None = None, seed: int = 0,
                 device: str | torch.device = "cpu", fused: bool | None = None) -> None:
        super().__init__(device=device, batch_size=torch.Size([num_sites]))
        self.fused = _fused.use_fused(self.device, fused)
        self.site_cfg = site or SiteConfig()
        self.mdp = mdp or MDPConfig()
        self.site = Site(self.site_cfg, self.device)
        self.encoding = get_encoding(encoding)
        self.num_sites = b = num_sites
        n_feat = self.encoding.size(self.site)
        dev = self.device
        self.observation_spec = Composite(
            observation=Bounded(0.0, 1.0, shape=(b, n_feat), dtype=torch.float32, device=dev),
            trips=Unbounded(shape=(b, 1), dtype=torch.int64, device=dev),
            queue_ticks=Unbounded(shape=(b, 1), dtype=torch.int64, device=dev),
            ticks=Unbounded(shape=(b, 1), dtype=torch.int64, device=dev),
            shape=(b,), device=dev,
        )
        self.action_spec = Categorical(2, shape=(b,), dtype=torch.int64, device=dev)
        self.reward_spec = Unbounded(shape=(b, 1), dtype=torch.float32, device=dev)
        self.done_spec = Composite(
            done=Categorical(2, shape=(b, 1), dtype=torch.bool, device=dev),
            terminated=Categorical(2, shape=(b, 1), dtype=torch.bool, device=dev),
            truncated=Categorical(2, shape=(b, 1), dtype=torch.bool, device=dev),
            shape=(b,), device=dev,
        )
        self._seed = rng.training_seed(int(seed))
        # episode counter of every slot: with the seed, the whole state a checkpoint needs
        self.register_buffer("episodes", torch.zeros(b, dtype=torch.int64, device=dev))
        self._arange = torch.arange(b, device=dev)
        self._hash = torch.zeros(b, dtype=torch.int64, device=dev)
        self._trips = torch.zeros(b, dtype=torch.int64, device=dev)
        self._queue = torch.zeros(b, dtype=torch.int64, device=dev)
        self.state, _ = self.site.init_state(self._seed, self._arange)

    # ------------------------------------------------------------------ TorchRL hooks
    def _set_seed(self, seed: int | None) -> None:
        self._seed = rng.training_seed(int(seed) if seed is not None else 0)
        self.episodes.zero_()

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        mask = None
        if tensordict is not None and "_reset" in tensordict.keys():
            mask = tensordict.get("_reset").reshape(self.num_sites)
        if mask is None:
            mask = torch.ones(self.num_sites, dtype=torch.bool, device=self.device)
        self._start_episodes(mask)
        return self._observe()

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        b = self.num_sites
        s, m = self.state, self.mdp
        self.site.decide(s, torch.ones(b, dtype=torch.bool, device=self.device),
                         tensordict.get("action").reshape(b))
        # every site to its next decision, failure or tau_e (one kernel call, or tick by tick)
        ev = advance(self.site, s, self._hash, m.tau_e, fused=self.fused)
        self._trips += ev.trips
        self._queue += ev.queue
        terminated = ev.failed
        truncated = (s.tick >= m.tau_e) & ~terminated
        td = self._observe()
        td.set("reward", m.objective.reward(ev, m).unsqueeze(-1))
        td.set("terminated", terminated.unsqueeze(-1))
        td.set("truncated", truncated.unsqueeze(-1))
        td.set("done", (terminated | truncated).unsqueeze(-1))
        return td

    # ------------------------------------------------------------------ checkpoints
    _DYNAMIC = ("pos", "soc", "left", "charge", "tick")

    _PARAMS = tuple(f.name for f in fields(SiteParams))  # a distribution's per-site draws

    def state_dict(self, *args, **kwargs):
        sd = super().state_dict(*args, **kwargs)
        for name in self._DYNAMIC:
            sd[f"site.{name}"] = getattr(self.state, name).clone()
        for name in self._PARAMS:  # the parameters of the sites in flight (drawn or not)
            sd[f"site.params.{name}"] = getattr(self.state.params, name).clone()
        sd.update({"site.hash": self._hash.clone(), "site.trips": self._trips.clone(),
                   "site.queue": self._queue.clone(),
                   "seed": torch.tensor(self._seed, dtype=torch.int64)})
        return sd

    def load_state_dict(self, state_dict, strict: bool = True, assign: bool = False):
        """Restore what :meth:`state_dict` wrote. ``strict=False`` (what TorchRL's
        ``EnvCreator``, and so ``ParallelEnv``, pass, with every tensor left out of the dict)
        keeps the current value of each entry that is missing; ``strict=True`` refuses a dict
        that lacks any, as ``nn.Module`` does, except the sites' drawn parameters, which are
        kept if absent either way."""
        state_dict = dict(state_dict)
        dev = self.device
        required = [f"site.{name}" for name in self._DYNAMIC]
        required += ["site.hash", "site.trips", "site.queue", "seed"]
        params = [f"site.params.{name}" for name in self._PARAMS]
        own = required + params
        missing = [key for key in required if key not in state_dict]
        if strict and missing:
            raise RuntimeError(f"missing key(s) in the state_dict of {type(self).__name__}: "
                               f"{', '.join(missing)}")
        value = {key: state_dict.pop(key) for key in own if key in state_dict}
        for key, v in value.items():
            if key == "seed":
                self._seed = int(v)
                continue
            v = v.to(dev).clone()
            if key.startswith("site.params."):
                setattr(self.state.params, key.removeprefix("site.params."), v)
            elif key in ("site.hash", "site.trips", "site.queue"):
                setattr(self, "_" + key.removeprefix("site."), v)
            else:
                setattr(self.state, key.removeprefix("site."), v)
        return super().load_state_dict(state_dict, strict=strict, assign=assign)

    def current(self) -> TensorDictBase:
        """The observation and counters of the sites as they stand (no step, no reset)."""
        return self._observe()

    # ------------------------------------------------------------------ internals
    def _observe(self) -> TensorDictBase:
        return TensorDict(
            {
                "observation": self.encoding(self.site, self.state),
                "trips": self._trips.unsqueeze(-1).clone(),
                "queue_ticks": self._queue.unsqueeze(-1).clone(),
                "ticks": self.state.tick.unsqueeze(-1).clone(),
            },
            batch_size=self.batch_size, device=self.device,
        )

    def _start_episodes(self, mask: torch.Tensor) -> None:
        """Draw new initial states for the sites in ``mask`` and run them to a decision."""
        todo = mask.clone()
        for _ in range(_MAX_REDRAWS):
            site_idx = self.episodes * self.num_sites + self._arange
            self.episodes += todo
            new, needs = self.site.init_state(self._seed, site_idx)
            self.state.update_(todo, new)
            self._hash = torch.where(todo, self.site.site_hash(self._seed, site_idx), self._hash)
            self._trips.masked_fill_(todo, 0)
            self._queue.masked_fill_(todo, 0)
            running = todo & ~needs
            failed = torch.zeros_like(todo)
            if bool(running.any()):  # every new site to its first decision or failure
                run = _fused.advance if self.fused else advance_eager
                out = run(self.site, self.state, self._hash, _NO_LIMIT, active=running)
                self._trips += out.trips
                self._queue += out.queue
                failed = out.failed
            if not bool(failed.any()):
                return
            todo = failed
        raise RuntimeError(f"{_MAX_REDRAWS} initial states in a row failed before their first "
                           "decision: raise site.xi or lower the energy costs")
