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
everywhere (the reference the kernel is tested against).

On the CPU a call with enough work (:func:`_worth_threads`) spreads the sites over
``torch.get_num_threads()`` cores with numba's ``prange``, as many as the machine's load
leaves idle (:func:`_idle_cores`: on a busy machine one core is several times faster).
Threading layer (unless ``NUMBA_THREADING_LAYER`` says otherwise): OpenMP where the machine
has it, else numba's ``workqueue``; measured on this project's 2-core machine, waking an
OpenMP pool costs ~6 us and the workqueue ~170 us. An OpenMP pool spins after each call and
then starves torch's own threads (an evaluation stopping at every decision for a forward pass
ran 10x slower), so its spin is cut short (``GOMP_SPINCOUNT``, set before numba loads its
OpenMP runtime; torch's is loaded already). GNU OpenMP does not survive a fork: a forked child
of a process whose pool has run uses the one-core kernel. Calls from several Python threads
take turns.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from dataclasses import dataclass

import numba
import numpy as np
import torch
from torch import Tensor

from . import kernel as _k
from . import kernel_cache
from .site import Site, SiteState

log = logging.getLogger(__name__)

NONE, THRESHOLD, TABLE = _k.NONE, _k.THRESHOLD, _k.TABLE
N_THRESHOLD = _k.N_THRESHOLD
_THREADS_PER_BLOCK = 128
_MIN_PARALLEL = 64  # sites below which one core is faster than waking the pool
_pool_lock = threading.Lock()  # one parallel call at a time (the workqueue is not re-entrant)
_pool = {"pid": None}  # the process whose numba thread pool has run
if "NUMBA_THREADING_LAYER" not in os.environ:
    numba.config.THREADING_LAYER_PRIORITY = ["omp", "workqueue", "tbb"]
    os.environ.setdefault("GOMP_SPINCOUNT", "10000")


@dataclass
class KernelPolicy:
    """A policy the kernel decides with, row ``rows[b]`` for site ``b`` (``None``: row 0).

    ``kind``: :data:`THRESHOLD` (``thresholds[r]``: the six float32 thresholds of
    :mod:`fleet_torchrl.sim.kernel`, on the normalised ``partial`` features) or
    :data:`TABLE` (``table[r]``: one action per cell of the discretised ``partial`` state,
    ``n_tc`` charger bins). Built by a policy's ``kernel_policy()`` (threshold, search and
    tabular policies).
    """

    kind: int
    thresholds: Tensor | None = None  # [R, 6] float32
    table: Tensor | None = None  # [R, cells] int8
    n_tc: int = 2
    rows: Tensor | None = None  # [B] int64

    def numpy_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`arrays` on the CPU as numpy views (cached)."""
        cached = self.__dict__.get("_numpy")
        if cached is None:
            cached = self.__dict__["_numpy"] = tuple(
                t.numpy() for t in self.arrays(torch.device("cpu")))
        return cached

    def arrays(self, device: torch.device) -> tuple[Tensor, Tensor, Tensor]:
        """``(rows, thresholds, table)`` as the kernel reads them, on ``device`` (cached:
        a policy is lowered once and used for many calls)."""
        cached = self.__dict__.get("_arrays")
        if cached is None or cached[0].device != device:
            rows = (torch.zeros(1, dtype=torch.int64) if self.rows is None
                    else self.rows.to(torch.int64).reshape(-1))
            thr = (torch.zeros(1, N_THRESHOLD) if self.thresholds is None
                   else self.thresholds).to(torch.float32)
            tab = (torch.zeros(1, 1) if self.table is None else self.table).to(torch.int8)
            cached = tuple(t.to(device).contiguous() for t in (rows, thr, tab))
            self.__dict__["_arrays"] = cached
        return cached


_NO_POLICY = KernelPolicy(NONE)


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


def _all_active(device: torch.device) -> Tensor:
    key = ("active", device)
    if key not in _CONSTANTS:
        _CONSTANTS[key] = torch.ones(1, dtype=torch.bool, device=device)
    return _CONSTANTS[key]


_CONSTANTS: dict[tuple, Tensor] = {}
_CPU = torch.device("cpu")
_LIMITS: dict[int, np.ndarray] = {}  # one-value tick limits as the CPU kernel reads them


_STATE = (("pos", torch.int64), ("soc", torch.float32), ("left", torch.int64),
          ("charge", torch.bool), ("tick", torch.int64))
_PARAMS = (("n_vehicles", torch.int64), ("t_c", torch.int64), ("gain", torch.float32),
           ("closure", torch.int64))


def _contiguous(s: SiteState) -> None:
    for obj, spec in ((s, _STATE), (s.params, _PARAMS)):
        for name, dtype in spec:
            t = getattr(obj, name)
            if t.dtype != dtype or not t.is_contiguous():
                setattr(obj, name, t.to(dtype).contiguous())


def _constants_group(site: Site, device: torch.device) -> tuple:
    """The kernel's :class:`~fleet_torchrl.sim.kernel.Constants` of ``site`` (numpy views on
    the CPU), built once per device."""
    key = ("_kernel_constants_group", device)
    cached = site.__dict__.get(key)
    if cached is None:
        tables, geo, energy = (_view(t) for t in site.kernel_constants(device))
        cached = site.__dict__[key] = tuple(_k.Constants(tables=tables, geo=geo, energy=energy))
    return cached


def _policy_group(pol: KernelPolicy, device: torch.device) -> tuple:
    """The kernel's :class:`~fleet_torchrl.sim.kernel.Policy` of ``pol``, built once per
    device."""
    cached = pol.__dict__.get("_group")
    if cached is None or cached[0] != device:
        rows, thresholds, table = (pol.numpy_arrays() if device.type == "cpu"
                                   else pol.arrays(device))
        cached = pol.__dict__["_group"] = (device, tuple(_k.Policy(
            kind=int(pol.kind), rows=rows, thresholds=thresholds, table=table,
            n_tc=int(pol.n_tc))))
    return cached[1]


def _view(t: Tensor) -> np.ndarray | Tensor:
    """A tensor as the kernel takes it: a numpy view on the CPU, the tensor elsewhere."""
    return t.numpy() if t.device.type == "cpu" else t


_last_view: list = [None, None]  # the tensor of the last _numpy_of call, and its view


def _numpy_of(t: Tensor, dtype: torch.dtype) -> np.ndarray:
    """A numpy view of a CPU tensor as ``dtype`` (the last one is remembered: callers pass
    the same closure hashes call after call)."""
    if _last_view[0] is t:
        return _last_view[1]
    out = t.to(dtype).reshape(-1).contiguous().numpy()
    if t.dtype == dtype and t.is_contiguous():
        _last_view[0], _last_view[1] = t, out
    return out


def _state_tensors(s: SiteState) -> tuple[Tensor, ...]:
    p = s.params
    return (s.pos, s.soc, s.left, s.charge, s.tick, p.n_vehicles, p.t_c, p.gain, p.closure)


def _state_groups(views, site_hash) -> tuple[tuple, tuple]:
    """The kernel's :class:`~fleet_torchrl.sim.kernel.State` and
    :class:`~fleet_torchrl.sim.kernel.Params` from the views of a state's tensors
    (:func:`_state_tensors` order) and the sites' closure hashes."""
    pos, soc, left, charge, tick, n_veh, t_c, gain, closure = views
    return (tuple(_k.State(pos=pos, soc=soc, left=left, charge=charge, tick=tick)),
            tuple(_k.Params(site_hash=site_hash, n_veh=n_veh, t_c=t_c, gain=gain,
                            closure=closure)))


def _kernel_call(state: tuple, params: tuple, constants: tuple, limit, active, policy: tuple,
                 counts, flags) -> tuple[tuple, ...]:
    """The arguments of one kernel call: the groups of
    :class:`~fleet_torchrl.sim.kernel.KernelArgs`, in its order, as plain tuples (the entry
    points name them again). Plain because numba types a plain tuple of arrays in its
    dispatcher's C fast path and a named one in Python (~7 us a call), and a named tuple
    costs a Python call to build (~0.5 us): the groups that last (``state``, ``params``,
    ``constants``, ``policy``) are built by name once and cached, the call's own
    ``Run(limit, active)`` and ``Out(counts, flags)`` are plain pairs."""
    return state, params, constants, (limit, active), policy, (counts, flags)


def _cpu_state_groups(s: SiteState, views: list[np.ndarray], site_hash: np.ndarray
                      ) -> tuple[tuple, tuple]:
    """:func:`_state_groups` of a CPU state from its views (:func:`_state_arrays`), cached
    while they and the hashes stay the same objects (the callers pass the same closure hashes
    call after call)."""
    cached = s.__dict__.get("_kernel_groups")
    if cached is None or cached[0] is not views or cached[1] is not site_hash:
        cached = (views, site_hash, *_state_groups(views, site_hash))
        s.__dict__["_kernel_groups"] = cached
    return cached[2], cached[3]


def _state_arrays(s: SiteState) -> list[np.ndarray]:
    """Numpy views of a CPU state's tensors, cached on the state while its tensors stay the
    same objects (the kernel updates them in place; the eager tick replaces some)."""
    tensors = _state_tensors(s)
    cached = s.__dict__.get("_kernel_views")
    if cached is not None and all(a is b for a, b in zip(cached[0], tensors, strict=True)):
        return cached[1]
    _contiguous(s)
    tensors = _state_tensors(s)
    arrays = [t.numpy() for t in tensors]
    s.__dict__["_kernel_views"] = (tensors, arrays)
    return arrays


_FEATURES = {"ok": True}  # the features kernel runs here (False after it could not be built)


def partial_features(state: SiteState) -> Tensor | None:
    """The ``partial`` state of every site of a CPU state (``[B, 3]`` float32, bit-identical
    to the tensor encoding of :mod:`fleet_torchrl.env.encodings`) from one kernel pass, or
    ``None`` where the kernel does not apply (other devices; a machine where it cannot be
    built, where the caller's tensor operations serve)."""
    if state.pos.device.type != "cpu" or not _FEATURES["ok"]:
        return None
    arrays = _state_arrays(state)
    pos, soc, left, t_c = arrays[0], arrays[1], arrays[2], arrays[6]
    out = np.empty((pos.shape[1], 3), dtype=np.float32)
    try:
        kernel_cache.call("partial_features", pos, soc, left, t_c, out)
    except Exception:  # noqa: BLE001 (SetupError, said once by kernel_cache.call: fall back)
        _FEATURES["ok"] = False
        return None
    return torch.from_numpy(out)


def _check_lengths(b: int, **arrays) -> None:
    for name, a in arrays.items():
        if a.shape[0] not in (1, b):
            raise ValueError(f"{name} must hold one value or one per site ({b}), not "
                             f"{a.shape[0]}")


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
    if state.pos.shape[0] > _k.MAXV:
        raise ValueError(f"the kernel handles at most {_k.MAXV} vehicles per site")
    pol = policy or _NO_POLICY
    if state.pos.device.type == "cpu" and target is None:
        return _advance_cpu(site, state, site_hash, max_ticks, active, pol)
    return _advance_device(site, state, site_hash, max_ticks, active, pol, target)


def _advance_cpu(site: Site, state: SiteState, site_hash: Tensor, max_ticks: Tensor | int,
                 active: Tensor | None, pol: KernelPolicy) -> Events:
    """:func:`advance` on CPU tensors: numpy views (cached where they can be) straight into
    the numba kernel, a few microseconds of Python per call."""
    views = _state_arrays(state)
    tick = views[4]
    b = tick.shape[0]
    if isinstance(max_ticks, Tensor):
        limit = max_ticks.to(torch.int64).reshape(-1).contiguous().numpy()
    else:
        limit = _LIMITS.get(max_ticks)
        if limit is None:
            limit = np.full(1, max_ticks, dtype=np.int64)
            if len(_LIMITS) < 256:
                _LIMITS[max_ticks] = limit
    act = (_k.ALL_ACTIVE if active is None
           else active.to(torch.bool).reshape(-1).contiguous().numpy())
    hsh = _numpy_of(site_hash, torch.int64)
    policy = _policy_group(pol, _CPU)
    _check_lengths(b, max_ticks=limit, active=act, policy_rows=policy[1],  # its rows
                   site_hash=hsh)
    ints = np.empty((3, b), dtype=np.int64)
    flags = np.empty((3, b), dtype=np.bool_)
    args = _kernel_call(*_cpu_state_groups(state, views, hsh), _constants_group(site, _CPU), limit,
                        act, policy, ints, flags)
    threads = min(torch.get_num_threads(), numba.config.NUMBA_NUM_THREADS, _idle_cores())
    forked = _pool["pid"] not in (None, os.getpid())  # a child of a process with a pool
    if threads > 1 and not forked and _worth_threads(b, limit, tick, pol):
        with _pool_lock:
            numba.set_num_threads(threads)
            _pool["pid"] = os.getpid()
            kernel_cache.call("advance_parallel", *args)
    else:
        kernel_cache.call("advance_serial", *args)
    i, f = [torch.from_numpy(r) for r in ints], [torch.from_numpy(r) for r in flags]
    return Events(ticks=i[0], trips=i[1], queue=i[2], arrived=f[0], failed=f[1], queued=f[2])


# site-ticks a call must promise before it wakes the thread pool (a site-tick: ~20 ns on one
# core; waking the pool: ~6 us with OpenMP, ~170 us with the workqueue)
_PARALLEL_WORK = 4_000 if numba.config.THREADING_LAYER_PRIORITY[0] == "omp" else 50_000
_TICKS_PER_DECISION = 10  # a site stopping at its next decision runs about this many ticks


_LOAD = {"at": -1.0, "cores": 1}


def _idle_cores() -> int:
    """Cores this process may use for one call: the machine's, less the load of the other
    runnable processes (the 1-minute load average, which counts this one; read at most once a
    second). A parallel call waits for its slowest thread, and on a busy machine one of them
    is often not running: measured on the 2-core VM with two other jobs running, environment
    collection at B = 1024 made 95 000 decisions/s on two threads and 510 000 on one."""
    now = time.monotonic()
    if now - _LOAD["at"] > 1.0:
        cores = os.cpu_count() or 1
        try:
            busy = os.getloadavg()[0] - 1.0
        except (AttributeError, OSError):  # no load average on this platform
            busy = 0.0
        _LOAD.update(at=now, cores=max(1, int(cores - max(busy, 0.0) + 0.5)))
    return int(_LOAD["cores"])


def _worth_threads(b: int, limit: np.ndarray, tick: np.ndarray, pol: KernelPolicy) -> bool:
    if b < _MIN_PARALLEL:
        return False
    if pol.kind == NONE:
        return b * _TICKS_PER_DECISION >= _PARALLEL_WORK
    span = int(limit.mean()) - int(tick.mean()) if limit.shape[0] > 1 else \
        int(limit[0]) - int(tick.min())
    return b * max(span, 1) >= _PARALLEL_WORK


def _advance_device(site: Site, state: SiteState, site_hash: Tensor, max_ticks: Tensor | int,
                    active: Tensor | None, pol: KernelPolicy, target: str | None) -> Events:
    """:func:`advance` with the CUDA kernel: on CUDA tensors, or on CPU tensors under numba's
    CUDA simulator (``target="cuda"``)."""
    from numba import cuda

    dev = state.pos.device
    simulated = dev.type != "cuda"
    if simulated and not numba.config.ENABLE_CUDASIM:
        raise RuntimeError("target='cuda' on CPU tensors needs NUMBA_ENABLE_CUDASIM=1")
    _contiguous(state)
    b = state.pos.shape[1]
    kw = dict(dtype=torch.int64, device=dev)
    limit = torch.as_tensor(max_ticks, **kw).reshape(-1).contiguous()
    act = (_all_active(dev) if active is None else
           active.to(dev, torch.bool).reshape(-1).contiguous())
    hsh = site_hash.to(dev, torch.int64).contiguous()
    policy = _policy_group(pol, dev)
    _check_lengths(b, max_ticks=limit, active=act, policy_rows=policy[1],  # its rows
                   site_hash=hsh)
    ints = torch.empty(3, b, **kw)
    flags = torch.empty(3, b, dtype=torch.bool, device=dev)
    args = _kernel_call(*_state_groups(_state_tensors(state), hsh), _constants_group(site, dev),
                        limit, act, policy, ints, flags)
    # numba's CUDA simulator works on host arrays in place
    view = (lambda a: a.numpy()) if simulated else cuda.as_cuda_array
    args = tuple(tuple(view(a) if isinstance(a, Tensor) else a for a in group)
                 for group in args)
    kernel = _k.cuda_kernel()
    blocks = (b + _THREADS_PER_BLOCK - 1) // _THREADS_PER_BLOCK
    if simulated:
        kernel[blocks, _THREADS_PER_BLOCK](*args)
    else:
        stream = cuda.external_stream(torch.cuda.current_stream().cuda_stream)
        kernel[blocks, _THREADS_PER_BLOCK, stream](*args)
    return Events(ticks=ints[0], trips=ints[1], queue=ints[2], arrived=flags[0],
                  failed=flags[1], queued=flags[2])


__all__ = ["NONE", "TABLE", "THRESHOLD", "Events", "KernelPolicy", "advance", "available",
           "use_fused"]
