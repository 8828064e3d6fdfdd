"""An independent numpy reference of the site model (MODEL §1), for tests and benchmarks.

It was written from the description in ``docs/MODEL.md`` §1, not from
:mod:`fleet_torchrl.sim.site`: occupancy is a per-site boolean array ``[B, N]`` and every rule
of the tick is its own explicit mask, so that it can cross-check the torch simulator (and any
faster variant of it) tick by tick. It shares only the interface with the torch version: the
state layout (``[V, B]`` vehicle arrays, ``[B]`` site arrays) and float32 energy arithmetic
performed in the same order (add the tick's delta, then cap at 100), so that states can be
compared bit for bit. Initial states are taken from the torch
:class:`~fleet_torchrl.sim.site.Site` (common random numbers, MODEL §1.4); so are the closure
draws of :func:`simulate_reference`, while :func:`env_steps_reference` computes its own with
:func:`closure_draws` (tested equal to the torch draws).

Vectorised over sites; nothing here is meant to be fast.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, fields

import numpy as np
import torch

from .config import SiteConfig
from .site import Site, SiteState

NODE_D, NODE_C, NODE_B, NODE_M = 0, 1, 2, 3  # decision, charger, bypass, merge (MODEL §1.1)
F32 = np.float32


@dataclass
class ReferenceState:
    """State of ``B`` sites as numpy arrays, with the shapes and dtypes of ``SiteState``."""

    pos: np.ndarray  # [V, B] int64 node of each vehicle
    soc: np.ndarray  # [V, B] float32 battery level
    left: np.ndarray  # [V, B] int64 charging ticks left
    charge: np.ndarray  # [B] bool decision of the vehicle on D
    tick: np.ndarray  # [B] int64 ticks run so far

    @classmethod
    def from_torch(cls, s: SiteState) -> ReferenceState:
        """A numpy copy of a torch :class:`SiteState`."""
        return cls(**{f.name: getattr(s, f.name).detach().cpu().numpy().copy()
                      for f in fields(cls)})

    def to_torch(self, site: Site) -> SiteState:
        """A torch (CPU) copy of this state, as a state of ``site`` (its parameters)."""
        return site.state(**{f.name: torch.from_numpy(getattr(self, f.name).copy())
                             for f in fields(self)})

    def copy(self) -> ReferenceState:
        return ReferenceState(**{f.name: getattr(self, f.name).copy() for f in fields(self)})

    def differences(self, other: SiteState | ReferenceState) -> list[str]:
        """Names of the fields that differ from ``other``'s (soc compared bit for bit)."""
        if isinstance(other, SiteState):
            other = ReferenceState.from_torch(other)
        out = []
        for f in fields(self):
            mine, theirs = getattr(self, f.name), getattr(other, f.name)
            if mine.dtype == F32:  # bit-identical, not merely equal in value
                mine, theirs = mine.view(np.uint32), theirs.astype(F32).view(np.uint32)
            if mine.shape != theirs.shape or not np.array_equal(mine, theirs):
                out.append(f.name)
        return out


class ReferenceSite:
    """The tick rules of MODEL §1.2, one explicit numpy mask per rule."""

    def __init__(self, cfg: SiteConfig) -> None:
        if cfg.randomized:
            raise ValueError("the numpy reference simulates one site: a site distribution "
                             "(site.ranges) is checked against single sites instead "
                             "(tests/sim/test_distribution.py)")
        self.cfg = cfg
        self.n_nodes = cfg.n_nodes
        self.closed_node = cfg.closed_node
        # energy deltas as float32 of the Python values, as the torch version stores them
        self.d_idle, self.d_move = F32(-cfg.e_idle), F32(-cfg.e_move)
        self.d_charge = F32(cfg.e_charge / cfg.t_c)
        self.soc_low = F32(cfg.soc_low)
        # next node when passing (the charging variant differs only on D): MODEL §1.1 table
        nxt = np.arange(1, cfg.n_nodes + 1, dtype=np.int64)  # road: k -> k + 1
        nxt[NODE_D], nxt[NODE_C], nxt[NODE_B] = NODE_B, NODE_M, NODE_M
        nxt[cfg.n_nodes - 1] = NODE_D  # the last road node leads back to D
        self.next_node = nxt

    def occupancy(self, pos: np.ndarray) -> np.ndarray:
        """``[B, N]`` bool: which nodes hold a vehicle."""
        occ = np.zeros((pos.shape[1], self.n_nodes), dtype=bool)
        occ[np.arange(pos.shape[1])[None, :], pos] = True
        return occ

    def targets(self, pos: np.ndarray, charge: np.ndarray) -> np.ndarray:
        """Step 2: ``[V, B]`` next node of every vehicle (D: C if it charges, else B)."""
        return np.where((pos == NODE_D) & charge[None, :], NODE_C, self.next_node[pos])

    def moves(self, pos: np.ndarray, left: np.ndarray, target: np.ndarray,
              closed: np.ndarray) -> np.ndarray:
        """Step 3: ``[V, B]`` bool, who moves (target free at the start, not a closed X,
        not charging; M admits one vehicle, the one from B before the one from C)."""
        occ = self.occupancy(pos)
        sites = np.arange(pos.shape[1])[None, :]
        free = ~occ[sites, target]
        open_ = ~(closed[None, :] & (target == self.closed_node))
        charging = (pos == NODE_C) & (left > 0)
        move = free & open_ & ~charging
        bypass_enters_m = (move & (pos == NODE_B)).any(0)
        return move & ~((pos == NODE_C) & bypass_enters_m[None, :])

    def energy(self, soc: np.ndarray, charging: np.ndarray, move: np.ndarray) -> np.ndarray:
        """Step 4: new ``soc`` (float32: add the tick's delta, then cap at 100)."""
        delta = np.where(charging, self.d_charge, np.where(move, self.d_move, self.d_idle))
        return np.minimum(soc + delta.astype(F32), F32(100.0))

    def charger(self, left: np.ndarray, charging: np.ndarray, soc: np.ndarray,
                entered_c: np.ndarray) -> np.ndarray:
        """Steps 4-5: charging ticks left after the tick."""
        left = left - charging
        if self.cfg.leave_when_full:
            left = np.where(charging & (soc == F32(100.0)), 0, left)
        return np.where(entered_c, self.cfg.t_c, left)

    def tick(self, state: ReferenceState, closed: np.ndarray) -> dict[str, np.ndarray]:
        """Advance every site by one tick, in place; ``closed``: ``[B]`` bool (step 1).

        Returns ``arrived`` (a trip: a move from N-1 into D, a decision is needed),
        ``queue`` and ``failed``, each ``[B]`` bool.
        """
        pos, left, charge = state.pos, state.left, state.charge
        closed = np.asarray(closed, dtype=bool)
        target = self.targets(pos, charge)
        move = self.moves(pos, left, target, closed)
        charging = (pos == NODE_C) & (left > 0)
        soc = self.energy(state.soc, charging, move)
        entered_c = move & (target == NODE_C)
        on_d = pos == NODE_D
        queue = charge & (on_d & ~move).any(0)  # it wants C (charge) and did not get there
        arrived = (move & (pos == self.n_nodes - 1)).any(0)
        state.left = self.charger(left, charging, soc, entered_c)
        state.soc = soc
        state.pos = np.where(move, target, pos)
        # the decision belongs to the vehicle on D; MODEL §1.5 clears it when one arrives
        state.charge = charge & ~arrived
        state.tick = state.tick + 1
        failed = (soc < self.soc_low).any(0)
        return {"arrived": arrived, "queue": queue, "failed": failed}

    @staticmethod
    def decide(state: ReferenceState, mask: np.ndarray, charge: np.ndarray) -> None:
        """Step 8: record the decision ``charge`` ([B], bool or 0/1) of the sites in ``mask``."""
        state.charge = np.where(np.asarray(mask, bool), np.asarray(charge).astype(bool),
                                state.charge)


def partial_obs(state: ReferenceState, t_c: int) -> np.ndarray:
    """The ``partial`` encoding (MODEL §2.4) as float32 ``[B, 3]``: soc_D, lowest soc of the
    vehicles on neither D nor C (100 if none), TC; socs scaled by float32(0.01) and TC by
    float32(1 / (T_C + 1)), as the torch encoding does."""
    pos, soc = state.pos, state.soc
    soc_d = np.where(pos == NODE_D, soc, F32(0.0)).sum(0, dtype=F32)
    others = np.where(pos > NODE_C, soc, F32(100.0)).min(0)
    tc = np.where(pos == NODE_C, state.left + 1, 0).sum(0).astype(F32)
    scale = np.array([0.01, 0.01, 1.0 / (t_c + 1)], dtype=F32)
    return np.stack([soc_d, others, tc], axis=1).astype(F32) * scale


def rule_policy(obs: np.ndarray, threshold: float = 40.0) -> np.ndarray:
    """The rule (MODEL §3): charge iff ``soc_D / 100 <= threshold / 100``, compared in
    float32 as torch compares a float32 tensor with a Python float. ``[B]`` int64."""
    return (obs[:, 0] <= F32(threshold / 100.0)).astype(np.int64)


def simulate_reference(policy_fn: Callable[[np.ndarray], np.ndarray], cfg: SiteConfig,
                       n_sims: int, ticks: int, seed: int) -> dict[str, np.ndarray]:
    """The evaluation protocol (MODEL §4) on the reference site.

    Initial states and closures come from the torch ``Site`` (common random numbers), so the
    result is comparable with :func:`fleet_torchrl.evaluation.simulate` under the same seed.
    ``policy_fn`` maps the ``partial`` observation ``[B, 3]`` to actions ``[B]``. A failed site
    keeps moving but stops counting. Returns per-simulation ``trips``, ``queue``, ``failed``
    and ``ticks_survived``.
    """
    site, ref = Site(cfg), ReferenceSite(cfg)
    idx = torch.arange(n_sims, dtype=torch.int64)
    s0, needs = site.init_state(seed, idx)
    closed = site.closures(seed, idx, torch.arange(ticks)[:, None]).numpy()  # [T, B]
    state = ReferenceState.from_torch(s0)
    ref.decide(state, needs.numpy(), policy_fn(partial_obs(state, cfg.t_c)))
    trips = np.zeros(n_sims, dtype=np.int64)
    queue = np.zeros(n_sims, dtype=np.int64)
    survived = np.zeros(n_sims, dtype=np.int64)
    alive = np.ones(n_sims, dtype=bool)
    for t in range(ticks):
        out = ref.tick(state, closed[t])
        survived += alive
        trips += out["arrived"] & alive
        queue += out["queue"] & alive
        alive &= ~out["failed"]
        if out["arrived"].any():
            ref.decide(state, out["arrived"], policy_fn(partial_obs(state, cfg.t_c)))
    return {"trips": trips, "queue": queue, "failed": ~alive, "ticks_survived": survived}


def env_steps_reference(policy_fn: Callable[[np.ndarray], np.ndarray], cfg: SiteConfig,
                        n_sites: int, steps: int, seed: int) -> dict[str, np.ndarray]:
    """Decision epochs of the environment (MODEL §2.1) on the reference site, for benchmarks
    and cross-checks: every site decides, then runs tick by tick until its next decision or
    its failure while the sites that are done wait (frozen). Sites are drawn as evaluation
    sites ``0 .. n_sites-1`` of ``seed`` and never reset. Returns ``ticks`` and ``trips``
    per site and step, ``[steps, B]``.
    """
    site, ref = Site(cfg), ReferenceSite(cfg)
    idx = torch.arange(n_sites, dtype=torch.int64)
    s0, needs = site.init_state(seed, idx)
    state = ReferenceState.from_torch(s0)
    site_hash = site.site_hash(seed, idx).numpy().astype(np.uint64)

    def closed_now() -> np.ndarray:  # X closed in each site's own current tick (MODEL §1.4)
        return closure_draws(site_hash, state.tick, cfg.p_c)

    alive = np.ones(n_sites, dtype=bool)
    # a site without a vehicle on D first runs to its first decision (not counted)
    pending = ~needs.numpy()
    while pending.any():
        out = _masked_tick(ref, state, closed_now(), pending)
        alive &= ~out["failed"]
        pending &= ~(out["arrived"] | out["failed"])
    ticks = np.zeros((steps, n_sites), dtype=np.int64)
    trips = np.zeros((steps, n_sites), dtype=np.int64)
    for k in range(steps):
        ref.decide(state, alive, policy_fn(partial_obs(state, cfg.t_c)))
        active = alive.copy()
        while active.any():
            out = _masked_tick(ref, state, closed_now(), active)
            ticks[k] += active
            trips[k] += out["arrived"] & active
            alive &= ~(out["failed"] & active)
            active &= ~(out["arrived"] | out["failed"])
    return {"ticks": ticks, "trips": trips}


def _masked_tick(ref: ReferenceSite, state: ReferenceState, closed: np.ndarray,
                 active: np.ndarray) -> dict[str, np.ndarray]:
    """One tick of the ``active`` sites; the others keep their state exactly."""
    before = state.copy()
    out = ref.tick(state, closed)
    for name in ("pos", "soc", "left", "charge", "tick"):
        new, old = getattr(state, name), getattr(before, name)
        setattr(state, name, np.where(active, new, old))
    return {k: v & active for k, v in out.items()}


_M32 = np.uint64(0xFFFFFFFF)


def _mix32(x: np.ndarray) -> np.ndarray:
    """The 32-bit finaliser of the common random numbers (MODEL §1.5), in numpy uint64."""
    x = x ^ (x >> np.uint64(16))
    x = (x * np.uint64(0x21F0AAAD)) & _M32
    x = x ^ (x >> np.uint64(15))
    x = (x * np.uint64(0x735A2D97)) & _M32
    return x ^ (x >> np.uint64(15))


def closure_draws(site_hash: np.ndarray, ticks: np.ndarray, p_c: float) -> np.ndarray:
    """Whether ``X`` is closed for each site in its tick ``ticks``: the draw of MODEL §1.5,
    ``mix(site_hash ^ mix(t ^ 0x9E3779B9)) < p_c * 2**32``, computed here in numpy."""
    if p_c <= 0.0:
        return np.zeros(np.shape(ticks), dtype=bool)
    t = (np.asarray(ticks).astype(np.uint64) & _M32) ^ np.uint64(0x9E3779B9)
    return _mix32(site_hash ^ _mix32(t)) < np.uint64(int(round(p_c * (1 << 32))))
