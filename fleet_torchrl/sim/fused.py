"""The fused, event-driven advance: every site runs its own ticks to its next event.

:meth:`Site.tick` costs ~40 tensor operations per tick whatever the batch, and a caller that
needs a decision only when a vehicle reaches ``D`` (every few ticks per site) pays them on
every tick, plus a host sync per tick to know whether it is done. :func:`advance` instead runs
each active site on its own, in one call of the compiled kernel of
:mod:`fleet_torchrl.sim.kernel` (numba: every core of the CPU, or one CUDA thread per site),
up to the first of

* an **arrival** at ``D`` (a decision is needed), unless a policy decides inside the kernel
  (``policy``: the rule, the heuristic, a threshold policy or an action table, see
  :class:`KernelPolicy`), in which case the site decides on the spot and runs on;
* a **failure** (some ``soc < SoC_low`` after the tick);
* its **tick limit** (the site's tick counter reaches ``max_ticks``);

at least one tick per active site. It returns per-site :class:`Events` (ticks, trips, queue
ticks, what the last tick brought); the rewards are the objectives' business
(:mod:`fleet_torchrl.env.objectives`). The kernel is the tick of
:mod:`fleet_torchrl.sim.site` rule for rule and **bit-identical** to it
(``tests/sim/test_fused.py``, on both targets).

Backends (:func:`use_fused`): on the CPU the kernel is always there (numba is a dependency
with its own LLVM; no system compiler) and compiled once per machine (numba's on-disk cache);
on CUDA it runs when numba-cuda finds the GPU. ``fused=False`` keeps the eager tensor tick
everywhere (the reference the kernel is tested against). On the CPU the batch is spread over
``torch.get_num_threads()`` cores (numba's ``prange``) by numba's ``workqueue`` threading
layer (unless ``NUMBA_THREADING_LAYER`` says otherwise): its threads sleep between calls,
where an OpenMP pool spins and starves torch's own threads (measured: an evaluation that
stops at every decision for a forward pass ran 10x slower beside a spinning pool). It
survives a fork (tests/sim/test_fused.py); it is not re-entrant, so calls from several
Python threads take turns.
"""

from __future__ import annotations

import logging
import os
import threading
from dataclasses import dataclass

import numba
import torch
from torch import Tensor

from . import kernel as _k
from .site import Site, SiteState

log = logging.getLogger(__name__)

NONE, THRESHOLD, TABLE = _k.NONE, _k.THRESHOLD, _k.TABLE
N_THRESHOLD = _k.N_THRESHOLD
_THREADS_PER_BLOCK = 128
_MIN_PARALLEL = 64  # sites below which one core is faster than waking the pool
_pool_lock = threading.Lock()  # the workqueue layer runs one parallel call at a time
if "NUMBA_THREADING_LAYER" not in os.environ:
    numba.config.THREADING_LAYER = "workqueue"


@dataclass
class KernelPolicy:
    """A policy the kernel decides with, row ``rows[b]`` for site ``b`` (``None``: row 0).

    ``kind``: :data:`THRESHOLD` (``thresholds[r]``: the six float32 thresholds of
    :mod:`fleet_torchrl.sim.kernel`, on the normalised ``partial`` features) or
    :data:`TABLE` (``table[r]``: one action per cell of the discretised ``partial`` state,
    ``n_tc`` charger bins). Built by :mod:`fleet_torchrl.agents.lowering`.
    """

    kind: int
    thresholds: Tensor | None = None  # [R, 6] float32
    table: Tensor | None = None  # [R, cells] int8
    n_tc: int = 2
    rows: Tensor | None = None  # [B] int64

    def arrays(self, b: int, device: torch.device) -> tuple[Tensor, Tensor, Tensor]:
        """``(rows, thresholds, table)`` as the kernel reads them, on ``device``."""
        rows = (torch.zeros(b, dtype=torch.int64, device=device) if self.rows is None
                else self.rows.to(device, torch.int64).expand(b).contiguous())
        thr = (torch.zeros(1, N_THRESHOLD, dtype=torch.float32) if self.thresholds is None
               else self.thresholds.to(torch.float32))
        tab = (torch.zeros(1, 1, dtype=torch.int8) if self.table is None
               else self.table.to(torch.int8))
        return rows, thr.to(device).contiguous(), tab.to(device).contiguous()


@dataclass
class Events:
    """Per site (``[B]``), over the ticks of one :func:`advance` (zeros for inactive sites)."""

    ticks: Tensor  # int64 ticks run
    trips: Tensor  # int64 arrivals at D
    queue: Tensor  # int64 queue ticks
    arrived: Tensor  # bool: the last tick brought a vehicle to D
    failed: Tensor  # bool: the last tick failed the site
    queued: Tensor  # bool: the last tick was a queue tick


def available(device: torch.device | str = "cpu") -> bool:
    """Whether the compiled kernel runs on ``device`` (always on the CPU)."""
    device = torch.device(device)
    if device.type == "cpu":
        return True
    if device.type != "cuda":
        return False
    try:
        from numba import cuda

        return bool(cuda.is_available())
    except Exception:  # noqa: BLE001 (numba-cuda missing or broken: the eager path serves)
        return False


_warned: set[str] = set()


def use_fused(device: torch.device | str, fused: bool | None = None) -> bool:
    """The backend switch of the callers: ``fused=None`` (auto) uses the kernel wherever it
    runs (always on the CPU, on CUDA with numba-cuda), ``False`` never, ``True`` always
    (raising where it cannot run). The eager tick loop is the fallback, announced once."""
    if fused is False:
        return False
    device = torch.device(device)
    ok = available(device)
    if fused is True and not ok:
        raise RuntimeError(f"the compiled kernel cannot run on {device} (numba-cuda finds no "
                           "GPU): use the eager backend (eval.backend=eager, fused=False)")
    if not ok and device.type not in _warned:
        _warned.add(device.type)
        log.warning("the compiled kernel does not run on %s: using the eager tick loop "
                    "(several times slower)", device)
    return ok


def _site_constants(site: Site, device: torch.device) -> tuple[Tensor, ...]:
    """``succ``, ``check``, ``geo`` and ``energy`` of a site as the kernel reads them."""
    key = ("_kernel_constants", device)
    cached = site.__dict__.get(key)
    if cached is None:
        d_idle, d_move = float(site._delta[0]), float(site._delta[1])
        geo = torch.tensor([site._stride, site._closed_bit, int(site.leave_when_full)],
                           dtype=torch.int64)
        energy = torch.tensor([d_idle, d_move, site.soc_low], dtype=torch.float32)
        cached = tuple(t.to(device).contiguous()
                       for t in (site._succ, site._check, geo, energy))
        site.__dict__[key] = cached
    return cached


def _contiguous(s: SiteState) -> None:
    for name, dtype in (("pos", torch.int64), ("soc", torch.float32), ("left", torch.int64),
                        ("charge", torch.bool), ("tick", torch.int64)):
        t = getattr(s, name)
        if t.dtype != dtype or not t.is_contiguous():
            setattr(s, name, t.to(dtype).contiguous())
    p = s.params
    for name, dtype in (("n_vehicles", torch.int64), ("t_c", torch.int64),
                        ("gain", torch.float32), ("closure", torch.int64)):
        t = getattr(p, name)
        if t.dtype != dtype or not t.is_contiguous():
            setattr(p, name, t.to(dtype).contiguous())


def advance(site: Site, state: SiteState, site_hash: Tensor, max_ticks: Tensor | int,
            active: Tensor | None = None, policy: KernelPolicy | None = None,
            target: str | None = None) -> Events:
    """Run each active site (``active``: ``[B]`` bool, ``None`` = all) tick after tick, in
    place, until an arrival at ``D`` (none with an in-kernel ``policy``, which decides and
    runs on), a failure, or its tick counter reaching ``max_ticks`` (an int or ``[B]``);
    at least one tick per active site. ``site_hash``: :meth:`Site.site_hash` of each site
    (its closure stream), as :meth:`Site.closures_hashed` draws them.

    The caller decides for a site whose ``D`` holds an undecided vehicle before advancing
    it. The tensors stay where they are: CPU tensors run on the CPU kernel, CUDA tensors on
    the CUDA kernel. ``target="cuda"`` on CPU tensors runs the CUDA kernel under numba's
    CUDA simulator (``NUMBA_ENABLE_CUDASIM=1``; tests).
    """
    dev = state.pos.device
    _contiguous(state)
    b = state.pos.shape[1]
    if state.pos.shape[0] > _k.MAXV:
        raise ValueError(f"the kernel handles at most {_k.MAXV} vehicles per site")
    kw = dict(dtype=torch.int64, device=dev)
    limit = (torch.as_tensor(max_ticks, **kw).expand(b).contiguous())
    act = (torch.ones(b, dtype=torch.bool, device=dev) if active is None
           else active.to(dev, torch.bool).contiguous())
    hsh = site_hash.to(dev, torch.int64).contiguous()
    pol = policy or KernelPolicy(NONE)
    rows, thr, tab = pol.arrays(b, dev)
    succ, check, geo, energy = _site_constants(site, dev)
    ints = torch.empty(3, b, **kw)
    flags = torch.empty(3, b, dtype=torch.bool, device=dev)
    p = state.params
    args = [state.pos, state.soc, state.left, state.charge, state.tick, hsh, limit, act,
            p.n_vehicles, p.t_c, p.gain, p.closure, succ, check, geo, energy, pol.kind, rows,
            thr, tab, int(pol.n_tc), ints[0], ints[1], ints[2], flags[0], flags[1], flags[2]]
    if target == "cuda" or dev.type == "cuda":
        _launch_cuda(args, b, simulated=dev.type != "cuda")
    else:
        _launch_cpu(args, b)
    return Events(ticks=ints[0], trips=ints[1], queue=ints[2], arrived=flags[0],
                  failed=flags[1], queued=flags[2])


def _launch_cpu(args: list, b: int) -> None:
    arrays = [a.numpy() if isinstance(a, Tensor) else a for a in args]
    threads = min(torch.get_num_threads(), numba.config.NUMBA_NUM_THREADS)
    if threads > 1 and b >= _MIN_PARALLEL:
        with _pool_lock:
            numba.set_num_threads(threads)
            _k.advance_parallel(*arrays)
    else:
        _k.advance_serial(*arrays)


def _launch_cuda(args: list, b: int, simulated: bool) -> None:
    from numba import cuda

    kernel = _k.cuda_kernel()
    blocks = (b + _THREADS_PER_BLOCK - 1) // _THREADS_PER_BLOCK
    if simulated:  # numba's CUDA simulator works on host arrays in place
        if not numba.config.ENABLE_CUDASIM:
            raise RuntimeError("target='cuda' on CPU tensors needs NUMBA_ENABLE_CUDASIM=1")
        kernel[blocks, _THREADS_PER_BLOCK](*[a.numpy() if isinstance(a, Tensor) else a
                                             for a in args])
        return
    stream = cuda.external_stream(torch.cuda.current_stream().cuda_stream)
    kernel[blocks, _THREADS_PER_BLOCK, stream](*[cuda.as_cuda_array(a) if isinstance(a, Tensor)
                                                 else a for a in args])


__all__ = ["NONE", "TABLE", "THRESHOLD", "Events", "KernelPolicy", "advance", "available",
           "use_fused"]
