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
``queue_ticks`` and ``ticks`` (cumulative since the site's reset) for logging, and
``is_init``, true where a reset started a site's episode (the key TorchRL's ``InitTracker``
adds, so that its collectors take any policy as it is).

Bad input is refused, not guessed at (:func:`check_actions`, the one rule of this environment
and both Gymnasium/SB3 adapters): an action is ``0`` (pass) or ``1`` (charge), one per site,
given as integers or booleans (a float only if it is exactly ``0.0`` or ``1.0``); anything
else (``2``, ``-1``, ``0.7``, NaN, a missing action, the wrong number of actions) raises a
one-line ``ValueError`` naming the value. ``num_sites`` is an integer >= 1 and a seed an
integer in ``[0, 2**32 - 1]`` (the counter-based random numbers hash 32 bits of it: a larger
seed would silently alias a smaller one).

A site that has terminated (failed) is reset before its next step: a step of it is refused
with a one-line ``ValueError`` (:meth:`FleetChargingEnv.ended`). ``step_and_maybe_reset``,
``rollout`` and TorchRL's collectors reset done sites (``_reset`` mask) and so never meet it;
a loop that plays each site's episode to its end passes TorchRL's partial-step mask
``"_step"`` (the sites still running), and the others stay as they are (reward 0, their
flags as they stand). Observations always lie inside their spec, ``Bounded(0, 1)``. A
loaded state (:meth:`FleetChargingEnv.load_state_dict`) is checked first: every entry's
type, shape and range, NaN and inf refused.
"""

from __future__ import annotations

import numbers
from dataclasses import fields
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from ..sim import Site, SiteConfig, SiteParams, rng
from ..sim import fused as _fused
from ..sim.rollout import advance, advance_eager
from .config import MDPConfig
from .encodings import get_encoding

#: the action rule of the environment and both adapters (:func:`check_actions`)
ACTION_RULE = "0 (pass) or 1 (charge), as integers or booleans"
MAX_SEED = 2**32 - 1  # the random numbers hash 32 bits of a seed (sim/rng.py)
_MAX_REDRAWS = 100
_NO_LIMIT = 1 << 62  # tick limit of the run to the first decision (none)


def _first_bad(t: torch.Tensor) -> Any:
    """The first value of ``t`` that is neither 0 nor 1 (NaN included), as a Python number."""
    bad = ~((t == 0) | (t == 1))
    v = t[bad].reshape(-1)[0].item()
    return f"{v:g}" if isinstance(v, float) else v


def check_actions(action: Any, n: int, name: str = "action") -> torch.Tensor:
    """The actions of ``n`` sites as an int64 tensor ``[n]``, or a one-line ``ValueError``.

    The one rule of :class:`FleetChargingEnv`, ``FleetGymEnv`` and ``FleetVecEnv``: one
    action per site (shape ``[n]``, ``[n, 1]``, or a scalar for one site), each ``0``
    (pass) or ``1`` (charge), given as integers or booleans; a float is accepted only when it
    is exactly ``0.0`` or ``1.0`` (what a network's argmax cast to float gives). ``2``,
    ``-1``, ``0.7``, NaN, a string or a missing action are refused, never read as "charge"
    or rounded."""
    if action is None:
        raise ValueError(f"no {name} given: allowed {ACTION_RULE}, one per site ({n})")
    t = action
    if not isinstance(t, torch.Tensor):
        try:
            arr = np.asarray(action)
        except (TypeError, ValueError):
            arr = None
        if arr is None or arr.dtype.kind not in "biuf":
            raise ValueError(f"{name}={action!r} is invalid: allowed {ACTION_RULE}")
        t = torch.as_tensor(arr)
    if not (t.dtype == torch.bool or t.dtype.is_floating_point or t.dtype in _INT_DTYPES):
        raise ValueError(f"{name} of dtype {t.dtype} is invalid: allowed {ACTION_RULE}")
    shape = tuple(t.shape)
    ok = (t.dim() == 0 and n == 1) or (t.dim() >= 1 and shape[0] == n and t.numel() == n)
    if not ok:
        raise ValueError(f"{name} of shape {list(shape)} is invalid for {n} site(s): allowed "
                         f"one action per site, shape [{n}] or [{n}, 1]")
    t = t.reshape(n)
    if t.dtype == torch.bool:
        return t.to(torch.int64)
    if not bool(((t == 0) | (t == 1)).all()):
        raise ValueError(f"{name}={_first_bad(t)} is invalid: allowed {ACTION_RULE}")
    return t.to(torch.int64)


_INT_DTYPES = tuple(getattr(torch, n) for n in ("uint8", "int8", "int16", "int32", "int64",
                                                 "uint16", "uint32", "uint64")
                    if hasattr(torch, n))


def check_seed(seed: Any, name: str = "seed") -> int:
    """``seed`` as an int in ``[0, 2**32 - 1]``, or a one-line ``ValueError``
    (:class:`~fleet_torchrl.utils.checks.ConfigError`)."""
    from ..utils.checks import ConfigError

    if isinstance(seed, torch.Tensor) and seed.numel() == 1 and not seed.dtype.is_floating_point:
        seed = seed.item()
    if not isinstance(seed, numbers.Integral) or isinstance(seed, bool) or \
            not 0 <= int(seed) <= MAX_SEED:
        raise ConfigError(f"{name}={seed!r} is invalid: allowed an integer in [0, {MAX_SEED}]")
    return int(seed)


def check_num_sites(num_sites: Any) -> int:
    """``num_sites`` as an int >= 1, or a one-line ``ValueError`` (``ConfigError``)."""
    from ..utils.checks import ConfigError

    if not isinstance(num_sites, numbers.Integral) or isinstance(num_sites, bool) or \
            int(num_sites) < 1:
        raise ConfigError(f"num_sites={num_sites!r} is invalid: allowed an integer >= 1")
    return int(num_sites)


def check_env_memory(site: SiteConfig, num_sites: int) -> None:
    """Refuse ``num_sites`` sites that would not fit in memory, before allocating them."""
    from ..sim.config import site_bytes
    from ..utils.resources import check_memory

    check_memory("num_sites", num_sites, 2 * num_sites * site_bytes(site),
                 "the environment's sites")


def check_env_device(device: Any) -> None:
    """``device`` is a torch device this machine has (``cpu``, ``cuda``, ``cuda:N``, ``mps``),
    or a one-line ``ValueError`` (``ConfigError``) naming ``device`` and what is allowed or
    available here, not torch's own error at the first tensor."""
    from ..utils.checks import check_device

    check_device("device", str(device) if isinstance(device, torch.device) else device)


def check_site_starts(site: SiteConfig, num_sites: int, mdp: MDPConfig | None = None,
                      seed: int = 0, encoding: str = "partial") -> None:
    """Start the first episodes of a training environment of ``num_sites`` sites (on the
    CPU, the same draws as on any device): a site whose initial states keep failing before
    their first decision is refused here, in one line
    (:class:`~fleet_torchrl.utils.checks.ConfigError`), before a run starts."""
    FleetChargingEnv(site=site, encoding=encoding, num_sites=num_sites, mdp=mdp,
                     seed=seed).reset()


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
        num_sites = check_num_sites(num_sites)
        seed = check_seed(seed)
        site = SiteConfig.coerce(site)
        mdp = MDPConfig.coerce(mdp)
        check_env_memory(site, num_sites)
        check_env_device(device)
        super().__init__(device=device, batch_size=torch.Size([num_sites]))
        self.fused = _fused.use_fused(self.device, fused)
        self.site_cfg = site
        self.mdp = mdp
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
            # True where an episode starts (what TorchRL's InitTracker adds): a Collector
            # then needs no transform for any policy, and warns of none
            is_init=Categorical(2, shape=(b, 1), dtype=torch.bool, device=dev),
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
        self._seed = rng.training_seed(seed)
        # episode counter of every slot: with the seed, the whole state a checkpoint needs
        self.register_buffer("episodes", torch.zeros(b, dtype=torch.int64, device=dev))
        self._arange = torch.arange(b, device=dev)
        self._hash = torch.zeros(b, dtype=torch.int64, device=dev)
        self._trips = torch.zeros(b, dtype=torch.int64, device=dev)
        self._queue = torch.zeros(b, dtype=torch.int64, device=dev)
        self.state, _ = self.site.init_state(self._seed, self._arange)

    def __repr__(self) -> str:
        """What the environment simulates, in a few short lines: batch, site, encoding,
        objective, device and backend."""
        c, m = self.site_cfg, self.mdp
        site = (f"site={c.name!r} (n_nodes={c.n_nodes}, n_vehicles={c.n_vehicles}, "
                f"p_c={c.p_c}, t_c={c.t_c}, soc_low={c.soc_low}, e_move={c.e_move})")
        if c.randomized:
            drawn = ", ".join(f"{k}={getattr(c.ranges, k)}" for k in c.ranges.varied())
            site += f",\n    drawn per site: {drawn}"
        n_obs = self.observation_spec["observation"].shape[-1]
        terms = (f"gamma={m.gamma}, p_f={m.p_f}, p_q={m.p_q}" if m.reward == "thesis" else
                 f"gamma_tick={m.gamma_tick}, rho={m.rho}, p_f={m.p_f}")
        return (f"{type(self).__name__}(batch_size=[{self.num_sites}], device={self.device}, "
                f"backend={'fused' if self.fused else 'eager'},\n"
                f"    {site},\n"
                f"    encoding={self.encoding.name!r} ({n_obs} features), "
                f"reward={m.reward!r} (tau_e={m.tau_e}, {terms}))")

    # ------------------------------------------------------------------ TorchRL hooks
    def _set_seed(self, seed: int | None) -> None:
        self._seed = rng.training_seed(check_seed(seed) if seed is not None else 0)
        self.episodes.zero_()

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        mask = None
        if tensordict is not None and "_reset" in tensordict.keys():
            mask = tensordict.get("_reset").reshape(self.num_sites)
        if mask is None:
            mask = torch.ones(self.num_sites, dtype=torch.bool, device=self.device)
        self._start_episodes(mask)
        td = self._observe()
        td.set("is_init", mask.unsqueeze(-1).clone())
        return td

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        b = self.num_sites
        s, m = self.state, self.mdp
        action = check_actions(tensordict.get("action", None), b).to(self.device)
        stepping = self._stepping(tensordict)
        if stepping is None:
            self.site.decide(s, torch.ones(b, dtype=torch.bool, device=self.device), action)
            # every site to its next decision, failure or tau_e (one kernel call, or tick by
            # tick)
            ev = advance(self.site, s, self._hash, m.tau_e, fused=self.fused)
            terminated = ev.failed
            reward = m.objective.reward(ev, m)
        else:  # a partial step (TorchRL's "_step"): the other sites stay as they are
            self.site.decide(s, stepping, action)
            run = _fused.advance if self.fused else advance_eager
            ev = run(self.site, s, self._hash, m.tau_e, active=stepping)
            terminated = torch.where(stepping, ev.failed, self.ended())
            reward = torch.where(stepping, m.objective.reward(ev, m), 0.0)
        self._trips += ev.trips
        self._queue += ev.queue
        truncated = (s.tick >= m.tau_e) & ~terminated
        td = self._observe()
        td.set("reward", reward.unsqueeze(-1))
        td.set("terminated", terminated.unsqueeze(-1))
        td.set("truncated", truncated.unsqueeze(-1))
        td.set("done", (terminated | truncated).unsqueeze(-1))
        td.set("is_init", torch.zeros_like(terminated).unsqueeze(-1))
        return td

    def ended(self) -> torch.Tensor:
        """Which sites have terminated (failed) and not been reset since: ``[B]`` bool. A
        failed site has a vehicle below ``soc_low``; every other state has none."""
        return (self.state.soc < self.site.soc_low).any(0)

    def _stepping(self, tensordict: TensorDictBase) -> torch.Tensor | None:
        """The sites this step advances: those of TorchRL's partial-step mask ``"_step"``
        (``rollout(break_when_all_done=True)`` writes it; a loop that plays each site's
        episode to its end sets it to the sites still running), None for all of them.
        A terminated site that was not reset is refused with a one-line ``ValueError``:
        stepping it would run a failed site on (its soc below zero, its observation outside
        the observation spec)."""
        mask = tensordict.get("_step", None)
        if mask is not None:
            mask = torch.as_tensor(mask, device=self.device).to(torch.bool).reshape(
                self.num_sites)
        ended = self.ended()
        if mask is not None:
            ended = ended & mask
        if bool(ended.any()):
            sites = ended.nonzero().reshape(-1).tolist()
            which = ", ".join(map(str, sites[:5])) + (", ..." if len(sites) > 5 else "")
            raise ValueError(
                f"site(s) {which} of {self.num_sites} terminated and were not reset: reset "
                "them before their next step (env.reset(td) with a '_reset' mask of the done "
                "sites, as step_and_maybe_reset and TorchRL's collectors do) or leave them "
                "out of it with a '_step' mask")
        if mask is None or bool(mask.all()):
            return None
        return mask

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
        self.check_state_dict(state_dict)  # before anything is changed
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
            if key.startswith("site.params."):
                obj, attr = self.state.params, key.removeprefix("site.params.")
            elif key in ("site.hash", "site.trips", "site.queue"):
                obj, attr = self, "_" + key.removeprefix("site.")
            else:
                obj, attr = self.state, key.removeprefix("site.")
            # (the dtype of the entry it replaces: an int32 soc counter would reach the kernel)
            setattr(obj, attr, v.to(dev, getattr(obj, attr).dtype).clone())
        return super().load_state_dict(state_dict, strict=strict, assign=assign)

    def _state_bounds(self) -> dict[str, tuple[str, tuple[int, ...], float, float]]:
        """Each entry of :meth:`state_dict`: its kind (``int``, ``float``, ``bool``), shape
        and bounds. A failed site's soc lies below ``soc_low`` by at most one tick's cost
        (both at most 100): every soc is in ``[-100, 100]``."""
        v, b = self.state.pos.shape
        cfg = self.site_cfg
        t_c_max = max(cfg.t_c, *(cfg.ranges.t_c or ())) if cfg.ranges is not None else cfg.t_c
        vb, bb = (v, b), (b,)
        return {
            "episodes": ("int", bb, 0, 2**62), "site.pos": ("int", vb, 0, self.site.park),
            "site.soc": ("float", vb, -100.0, 100.0), "site.left": ("int", vb, 0, t_c_max),
            "site.charge": ("bool", bb, 0, 1), "site.tick": ("int", bb, 0, 2**62),
            "site.params.n_vehicles": ("int", bb, 1, v),
            "site.params.t_c": ("int", bb, 1, t_c_max),
            "site.params.gain": ("float", bb, 0.0, 100.0),
            "site.params.closure": ("int", bb, 0, 2**32),
            "site.params.p_c": ("float", bb, 0.0, 1.0),
            "site.hash": ("int", bb, 0, 2**32 - 1), "site.trips": ("int", bb, 0, 2**62),
            "site.queue": ("int", bb, 0, 2**62), "seed": ("int", (), 0, MAX_SEED)}

    def check_state_dict(self, state_dict: dict) -> None:
        """Refuse, in one line (``ValueError``) naming the entry, a state that is not one of
        this environment's: an entry of another type or shape, NaN or inf, a value out of
        its range (a negative seed, a soc above 100, a vehicle on no node). Entries that are
        absent are not checked (:meth:`load_state_dict` decides about them)."""
        for key, (kind, shape, lo, hi) in self._state_bounds().items():
            if key not in state_dict:
                continue
            v = state_dict[key]
            name = f"state_dict[{key!r}]"
            if key == "seed" and isinstance(v, numbers.Integral) and not isinstance(v, bool):
                v = torch.tensor(int(v))
            if not isinstance(v, torch.Tensor):
                raise ValueError(f"{name}={v!r:.60} is invalid: allowed a tensor of {kind} "
                                 f"values, shape {list(shape)}")
            ok_kind = {"bool": v.dtype == torch.bool,
                       "float": v.dtype.is_floating_point,
                       "int": v.dtype in _INT_DTYPES}[kind]
            if not ok_kind or tuple(v.shape) != shape:
                raise ValueError(f"{name} of dtype {v.dtype} and shape {list(v.shape)} is "
                                 f"invalid: allowed {kind} values, shape {list(shape)}")
            if kind == "bool" or v.numel() == 0:
                continue
            w = v.detach().to("cpu", torch.float64 if kind == "float" else torch.int64)
            bad = ~torch.isfinite(w) | (w < lo) | (w > hi) if kind == "float" else \
                (w < lo) | (w > hi)
            if bool(bad.any()):
                first = w[bad].reshape(-1)[0].item()
                raise ValueError(f"{name} holds {first:g}: allowed finite values in "
                                 f"[{lo:g}, {hi:g}]" if kind == "float" else
                                 f"{name} holds {first}: allowed integers in [{lo}, {hi}]")

    def current(self) -> TensorDictBase:
        """The observation and counters of the sites as they stand (no step, no reset)."""
        return self._observe()

    # ------------------------------------------------------------------ internals
    def _observe(self) -> TensorDictBase:
        # inside Bounded(0, 1) always: a failed site's last observation may read a soc
        # below zero (a vehicle that fails on a tick costing more than soc_low)
        return TensorDict(
            {
                "observation": self.encoding(self.site, self.state).clamp_(0.0, 1.0),
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
        from ..utils.checks import ConfigError

        raise ConfigError(f"the site cannot start its episodes: {_MAX_REDRAWS} initial "
                          "states in a row failed before their first decision; raise site.xi "
                          "or lower site.e_move, site.e_idle")
