"""The fused, event-driven advance: every site runs its own ticks up to its next decision.

:meth:`Site.tick` costs ~40 tensor operations per tick whatever the batch; a caller that needs
a decision only when a vehicle reaches ``D`` (every few ticks per site) pays them on every
tick, plus a host sync per tick to know whether it is done. :func:`advance` instead runs, for
each active site on its own, the ticks up to the first of

* an **arrival** (a vehicle moved from ``N-1`` into ``D``: the site needs a decision),
* a **failure** (some ``soc < SoC_low`` after the tick),
* its **tick limit** (the site's tick counter reaches ``max_ticks``),

in one call of a small C kernel (at least one tick per active site), accumulating per site
the ticks run, trips, queue ticks and the step reward of both objectives of
:mod:`fleet_torchrl.env.fleet_env`. The caller then does one batched policy forward for the
sites at a decision and calls again: one Python iteration per decision epoch, not per tick.

The kernel is the tick of :mod:`fleet_torchrl.sim.site` rule for rule and **bit-identical** to
it (``tests/sim/test_fused.py``): the same closure hash (:mod:`fleet_torchrl.sim.rng`'s 32-bit
finaliser in ``uint64`` arithmetic), the same float32 energy arithmetic (one add of the tick's
delta, then the cap at 100; compiled with ``-ffp-contract=off``, so no fused multiply-add), the
same float32 order of operations for the rewards as ``FleetChargingEnv._step``'s eager loop.

It is plain C (no torch headers), compiled with ``gcc`` at first use (about a second) and
loaded with :mod:`ctypes`; it works on the data pointers of contiguous **CPU** tensors, which
it updates in place. The shared library is cached under ``$FLEET_TORCHRL_CACHE``, else
``$XDG_CACHE_HOME/fleet_torchrl`` or ``~/.cache/fleet_torchrl`` (a temp dir if that is not
writable), keyed by a hash of the source and flags, and written atomically, so each machine
compiles it once. On any other device (CUDA) callers fall back to the eager tick loop:
:func:`use_fused` makes that choice.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import platform
import subprocess
import tempfile
import threading
import weakref
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

from .site import Site, SiteState

_SOURCE = r"""
#include <stdint.h>

/* 32-bit finaliser of fleet_torchrl.sim.rng._mix on values < 2**32 held in uint64. */
static inline uint64_t mix32(uint64_t x) {
    x ^= x >> 16;
    x = (x * 0x21F0AAADull) & 0xFFFFFFFFull;
    x ^= x >> 15;
    x = (x * 0x735A2D97ull) & 0xFFFFFFFFull;
    return x ^ (x >> 15);
}

#define MAXV 64

typedef struct {
    int64_t stride, closed_bit, closures_on, t_c, lwf, stop_on_arrival;
    uint64_t threshold;
    const int64_t *succ, *check;
    float dtab[3], soc_low, p_f, p_q, rho, gamma_tick;
} params_t;

/* One site from its state (vehicles in p, lf, e) until an arrival at D, a failure or the
   tick limit (at least one tick). Inlined with a constant nv for small fleets. */
static inline __attribute__((always_inline)) void run_site(
    const params_t *P, const int64_t nv, int64_t *p, int64_t *lf, float *e, int *ch_io,
    int64_t *t_io, const int64_t lim, const uint64_t hs, int64_t *o_ticks, int64_t *o_trips,
    int64_t *o_queue, uint8_t *o_arrived, uint8_t *o_failed, float *o_cost, float *o_disc)
{
    int ch = *ch_io;
    int64_t t = *t_io;
    int64_t n = 0, trips = 0, queue = 0;
    float cost = 0.0f, acc = 0.0f, disc = 1.0f;
    int arrived = 0, failed = 0;
    const int64_t *succ = P->succ, *check = P->check;
    for (;;) {
        /* occupancy at the start of the tick; a closed X counts as occupied */
        int64_t occ = 0;
        for (int64_t v = 0; v < nv; ++v) occ |= (int64_t)1 << p[v];
        const int occ_d = (int)(occ & 1);
        if (P->closures_on) {
            const uint64_t ht = mix32((((uint64_t)t) & 0xFFFFFFFFull) ^ 0x9E3779B9ull);
            occ |= (mix32(hs ^ ht) < P->threshold) ? P->closed_bit : 0;
        }
        const int64_t off = ch ? P->stride : 0;
        int into_c = 0;
        arrived = 0;
        failed = 0;
        for (int64_t v = 0; v < nv; ++v) {  /* branch-free: the compiler emits cmovs */
            const int64_t idx = p[v] + off;
            const int64_t tgt = succ[idx];
            const int charging = lf[v] > 0;  /* a charging vehicle has no target */
            const int move = ((check[idx] & occ) == 0) & !charging;
            float s = e[v] + P->dtab[charging * 2 + move];  /* 0 idle, 1 move, 2 charge */
            s = (s > 100.0f) ? 100.0f : s;
            e[v] = s;
            int64_t l = lf[v] - charging;
            l = (P->lwf & charging & (s >= 100.0f)) ? 0 : l;
            const int enter_c = move & (tgt == 1);
            lf[v] = enter_c ? P->t_c : l;
            into_c |= enter_c;
            arrived |= move & (tgt == 0);
            p[v] = move ? tgt : p[v];
            failed |= s < P->soc_low;
        }
        const int q = occ_d & ch & !into_c;
        ch &= !arrived;  /* the newcomer at D has not decided yet */
        t += 1;
        n += 1;
        trips += arrived;
        queue += q;
        /* thesis: cost -= (failed ? p_f : queue ? p_q : 0), as the eager loop in float32 */
        cost = cost - (failed ? P->p_f : (q ? P->p_q : 0.0f));
        /* throughput: acc += disc * ((arrived - rho) - p_f * failed); disc *= gamma_tick */
        {
            float r = (float)arrived - P->rho;
            r = r - P->p_f * (float)failed;
            const float term = disc * r;
            acc = acc + term;
            disc = disc * P->gamma_tick;
        }
        if ((arrived & (int)P->stop_on_arrival) | failed | (t >= lim)) break;
    }
    *ch_io = ch;
    *t_io = t;
    *o_ticks = n; *o_trips = trips; *o_queue = queue;
    *o_arrived = (uint8_t)arrived; *o_failed = (uint8_t)failed;
    *o_cost = cost; *o_disc = acc;
}

/* Advance every active site until an arrival at D, a failure or its tick limit (at least
   one tick). State arrays are [V, B] (vehicle-major) and [B]; outputs are [B]. With
   site_nv non-NULL every site has its own fleet size (its first site_nv[b] vehicles; the
   others are parked and untouched), closure threshold, T_C and charging gain. Returns the
   total number of site-ticks run. */
int64_t fleet_advance(
    int64_t nb, int64_t nv, int64_t stride,
    int64_t *pos, float *soc, int64_t *left, uint8_t *charge, int64_t *tick,
    const int64_t *site_hash, const int64_t *limit, int64_t limit_stride,
    const uint8_t *active, const int64_t *succ, const int64_t *check,
    int64_t closed_bit, int64_t closures_on, uint64_t threshold,
    float d_idle, float d_move, float d_charge, float soc_low, int64_t t_c,
    int64_t leave_when_full, int64_t stop_on_arrival,
    float p_f, float p_q, float rho, float gamma_tick,
    const int64_t *site_nv, const int64_t *site_thr, const int64_t *site_tc,
    const float *site_gain,
    int64_t *out_ticks, int64_t *out_trips, int64_t *out_queue,
    uint8_t *out_arrived, uint8_t *out_failed, float *out_cost, float *out_disc)
{
    params_t P;
    P.stride = stride; P.closed_bit = closed_bit; P.closures_on = closures_on != 0;
    P.t_c = t_c; P.lwf = leave_when_full != 0; P.stop_on_arrival = stop_on_arrival != 0;
    P.threshold = threshold; P.succ = succ; P.check = check;
    P.dtab[0] = d_idle; P.dtab[1] = d_move; P.dtab[2] = d_charge;
    P.soc_low = soc_low; P.p_f = p_f; P.p_q = p_q; P.rho = rho; P.gamma_tick = gamma_tick;
    int64_t total = 0;
    for (int64_t b = 0; b < nb; ++b) {
        if (active && !active[b]) {
            out_ticks[b] = 0; out_trips[b] = 0; out_queue[b] = 0;
            out_arrived[b] = 0; out_failed[b] = 0; out_cost[b] = 0.0f; out_disc[b] = 0.0f;
            continue;
        }
        params_t Q = P;
        int64_t nvb = nv;
        if (site_nv) {  /* a site of a distribution: its own parameters */
            nvb = site_nv[b];
            Q.threshold = (uint64_t)site_thr[b];
            Q.closures_on = site_thr[b] != 0;
            Q.t_c = site_tc[b];
            Q.dtab[2] = site_gain[b];
        }
        int64_t p[MAXV], lf[MAXV];
        float e[MAXV];
        for (int64_t v = 0; v < nvb; ++v) {
            p[v] = pos[v * nb + b]; lf[v] = left[v * nb + b]; e[v] = soc[v * nb + b];
        }
        int ch = charge[b] != 0;
        int64_t t = tick[b];
        const int64_t lim = limit[b * limit_stride];
        const uint64_t hs = (uint64_t)site_hash[b] & 0xFFFFFFFFull;
#define RUN(NV) run_site(&Q, NV, p, lf, e, &ch, &t, lim, hs, out_ticks + b, out_trips + b, \
                         out_queue + b, out_arrived + b, out_failed + b, out_cost + b, \
                         out_disc + b)
        switch (nvb) {  /* constant fleet sizes unroll the vehicle loops */
            case 1: RUN(1); break;
            case 2: RUN(2); break;
            case 3: RUN(3); break;
            case 4: RUN(4); break;
            case 5: RUN(5); break;
            case 6: RUN(6); break;
            default: RUN(nvb); break;
        }
#undef RUN
        for (int64_t v = 0; v < nvb; ++v) {
            pos[v * nb + b] = p[v]; left[v * nb + b] = lf[v]; soc[v * nb + b] = e[v];
        }
        charge[b] = (uint8_t)ch;
        tick[b] = t;
        total += out_ticks[b];
    }
    return total;
}
"""

_FLAGS = ["-O2", "-std=c99", "-fPIC", "-shared", "-ffp-contract=off", "-fno-fast-math"]
_MAX_VEHICLES = 64

_lock = threading.Lock()
_lib: ctypes.CDLL | None = None
_load_error: Exception | None = None
#: gcc runs in this process (tests check that the kernel compiles once)
compilations = 0


def _cache_dirs() -> list[Path]:
    """Where the library is looked for and built: ``$FLEET_TORCHRL_CACHE`` if set, else the
    user cache dir; then a per-user temp dir (when the first is not writable)."""
    if os.environ.get("FLEET_TORCHRL_CACHE"):
        first = Path(os.environ["FLEET_TORCHRL_CACHE"])
    else:
        base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"),
                                                                 ".cache")
        first = Path(base) / "fleet_torchrl"
    uid = os.getuid() if hasattr(os, "getuid") else "user"
    return [first, Path(tempfile.gettempdir()) / f"fleet_torchrl-{uid}"]


def _key() -> str:
    text = "\n".join([_SOURCE, " ".join(_FLAGS), platform.machine(), platform.system()])
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def library_path() -> Path | None:
    """The cached shared library if one exists (in the first cache dir that has it)."""
    name = f"fused_tick_{_key()}.so"
    for d in _cache_dirs():
        if (d / name).is_file():
            return d / name
    return None


def _compile() -> Path:
    """Compile the kernel into the first writable cache dir (temp name, then rename)."""
    global compilations
    name = f"fused_tick_{_key()}.so"
    errors = []
    for d in _cache_dirs():
        try:
            d.mkdir(parents=True, exist_ok=True)
            fd, tmp_src = tempfile.mkstemp(suffix=".c", dir=d)
            with os.fdopen(fd, "w") as f:
                f.write(_SOURCE)
            tmp_so = tmp_src[:-2] + ".so"
            try:
                compilations += 1
                res = subprocess.run(["gcc", *_FLAGS, "-o", tmp_so, tmp_src],
                                     capture_output=True, text=True)
                if res.returncode != 0:
                    raise RuntimeError(f"gcc failed: {res.stderr.strip()}")
                os.replace(tmp_so, d / name)  # atomic: a concurrent loader sees all or nothing
            finally:
                for f in (tmp_src, tmp_so):
                    if os.path.exists(f):
                        os.unlink(f)
            return d / name
        except (OSError, RuntimeError) as exc:
            errors.append(f"{d}: {exc}")
    raise RuntimeError("cannot build the fused tick kernel: " + "; ".join(errors))


def load() -> ctypes.CDLL:
    """The compiled kernel (compiled on first use on this machine, then cached)."""
    global _lib, _load_error
    if _lib is not None:
        return _lib
    with _lock:
        if _lib is None:
            path = library_path() or _compile()
            lib = ctypes.CDLL(str(path))
            fn = lib.fleet_advance
            i64, ptr, f32 = ctypes.c_int64, ctypes.c_void_p, ctypes.c_float
            fn.argtypes = ([i64] * 3 + [ptr] * 5 + [ptr, ptr, i64] + [ptr] * 3
                           + [i64, i64, ctypes.c_uint64] + [f32] * 4 + [i64] * 3 + [f32] * 4
                           + [ptr] * 4 + [ptr] * 7)
            fn.restype = i64
            _lib = lib
    return _lib


def _reset_for_tests() -> None:
    """Forget the loaded library (the next :func:`load` looks in the cache dirs again)."""
    global _lib, _load_error
    _lib, _load_error = None, None


def available() -> bool:
    """Whether the kernel can be used here (compiles it on first call)."""
    global _load_error
    if _lib is not None:
        return True
    if _load_error is not None:
        return False
    try:
        load()
        return True
    except (OSError, RuntimeError) as exc:
        _load_error = exc
        return False


def use_fused(device: torch.device | str, fused: bool | None = None) -> bool:
    """The backend switch of the callers: ``fused=None`` (auto) uses the kernel on CPU when
    it builds, ``False`` never, ``True`` on CPU always (raising if it cannot be built). Any
    device but the CPU uses the eager tick loop, whatever ``fused`` says."""
    if torch.device(device).type != "cpu" or fused is False:
        return False
    if fused is None:
        return available()
    load()
    return True


@dataclass
class AdvanceOutcome:
    """Per site (``[B]``), over the ticks of one :func:`advance` (zeros for inactive sites)."""

    ticks: Tensor  # int64 ticks run
    trips: Tensor  # int64 arrivals at D (at most one, the last tick, with stop_on_arrival)
    queue: Tensor  # int64 queue ticks
    arrived: Tensor  # bool: the last tick brought a vehicle to D (a decision is needed)
    failed: Tensor  # bool: the last tick failed the site
    cost: Tensor  # float32 thesis: sum of -p_f (failure tick) or -p_q (queue tick)
    discounted: Tensor  # float32 throughput: sum_k gamma_tick^k (trip_k - rho - p_f fail_k)


def _ready(s: SiteState) -> None:
    """Make the state's tensors contiguous CPU tensors of the dtypes the kernel reads."""
    for name, dtype in (("pos", torch.int64), ("soc", torch.float32), ("left", torch.int64),
                        ("charge", torch.bool), ("tick", torch.int64)):
        t = getattr(s, name)
        if t.device.type != "cpu":
            raise ValueError("the fused advance runs on CPU tensors only (use the eager path)")
        if t.dtype != dtype or not t.is_contiguous():
            setattr(s, name, t.to(dtype).contiguous())


class _Prepared:
    """The constant arguments of the kernel for one :class:`Site` (built once per site)."""

    def __init__(self, site: Site) -> None:
        closures_on = site.p_c > 0.0
        d_idle, d_move, d_charge, _ = site._delta.tolist()
        self.succ = site._succ.cpu().contiguous()
        self.check = site._check.cpu().contiguous()
        self.head = (site._stride,)
        self.tables = (self.succ.data_ptr(), self.check.data_ptr(), site._closed_bit,
                       int(closures_on), int(round(site.p_c * (1 << 32))) if closures_on else 0,
                       d_idle, d_move, d_charge, float(site.soc_low), int(site.t_c),
                       int(site.leave_when_full))


_prepared: weakref.WeakKeyDictionary[Site, _Prepared] = weakref.WeakKeyDictionary()


def advance(site: Site, state: SiteState, site_hash: Tensor, max_ticks: Tensor | int,
            active: Tensor | None = None, *, stop_on_arrival: bool = True, p_f: float = 0.0,
            p_q: float = 0.0, rho: float = 0.0, gamma_tick: float = 1.0) -> AdvanceOutcome:
    """Run each active site (``active``: ``[B]`` bool, ``None`` = all) tick after tick, in
    place, until a vehicle arrives at ``D`` (unless ``stop_on_arrival`` is False), the site
    fails, or its tick counter reaches ``max_ticks`` (an int or ``[B]`` int64); at least one
    tick per active site. ``site_hash`` is :meth:`Site.site_hash` of each site (its closure
    stream); tick ``t`` of a site is closed as in :meth:`Site.closures_hashed`.

    The caller must decide for a site whose ``D`` holds an undecided vehicle before it is
    advanced (as before :meth:`Site.tick`). CPU tensors only (see :func:`use_fused`).
    ``p_f``, ``p_q``, ``rho``, ``gamma_tick`` only shape the reward accumulators.
    """
    lib = load()
    prep = _prepared.get(site)
    if prep is None:
        prep = _prepared[site] = _Prepared(site)
    _ready(state)
    v, b = state.pos.shape
    if v > _MAX_VEHICLES:
        raise ValueError(f"the fused advance handles at most {_MAX_VEHICLES} vehicles")
    hsh = site_hash
    if hsh.dtype != torch.int64 or not hsh.is_contiguous():
        hsh = hsh.to(torch.int64).contiguous()
    if isinstance(max_ticks, Tensor):
        lim = max_ticks.to(torch.int64).expand(b).contiguous()
        stride = 1
    else:
        lim = torch.full((1,), int(max_ticks), dtype=torch.int64)
        stride = 0
    act = None
    if active is not None:
        act = active if active.dtype == torch.bool else active.to(torch.bool)
        act = act.contiguous()
    par = state.params
    if par is not None:
        for name, dtype in (("n_vehicles", torch.int64), ("closure", torch.int64),
                            ("t_c", torch.int64), ("gain", torch.float32)):
            t = getattr(par, name)
            if t.dtype != dtype or not t.is_contiguous():
                setattr(par, name, t.to(dtype).contiguous())
        per_site = (par.n_vehicles.data_ptr(), par.closure.data_ptr(), par.t_c.data_ptr(),
                    par.gain.data_ptr())
    else:
        per_site = (None, None, None, None)
    ints = torch.empty(3, b, dtype=torch.int64)
    flags = torch.empty(2, b, dtype=torch.bool)
    floats = torch.empty(2, b, dtype=torch.float32)
    ip, fp, flp = ints.data_ptr(), flags.data_ptr(), floats.data_ptr()
    lib.fleet_advance(
        b, v, *prep.head,
        state.pos.data_ptr(), state.soc.data_ptr(), state.left.data_ptr(),
        state.charge.data_ptr(), state.tick.data_ptr(),
        hsh.data_ptr(), lim.data_ptr(), stride, None if act is None else act.data_ptr(),
        *prep.tables, int(stop_on_arrival),
        float(p_f), float(p_q), float(rho), float(gamma_tick), *per_site,
        ip, ip + 8 * b, ip + 16 * b, fp, fp + b, flp, flp + 4 * b,
    )
    return AdvanceOutcome(ticks=ints[0], trips=ints[1], queue=ints[2], arrived=flags[0],
                          failed=flags[1], cost=floats[0], discounted=floats[1])
