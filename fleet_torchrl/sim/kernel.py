"""The compiled simulation kernel: every site runs its own ticks, compiled by numba.

One source, two targets. The functions below up to :func:`run_site_range` are plain Python in the
subset numba compiles for both the CPU (``numba.njit``, cached on disk per machine) and
CUDA (``numba.cuda.jit(device=True)``, built by :func:`cuda_kernel` from the same Python
functions with their calls rebound to the device versions). Nothing here knows torch; the
callers (:mod:`fleet_torchrl.sim.fused`) pass numpy views of the state tensors (CPU) or
CUDA array views (GPU), which the kernel updates in place.

What one call does, per active site ``b``, on its own (a thread on the GPU, ``prange`` over
chunks of sites on the CPU): it runs the tick of :mod:`fleet_torchrl.sim.site`, rule for rule and
bit for bit (the same closure hash, the same float32 energy arithmetic: add the tick's
delta, then cap at 100; numba does not contract ``a * b + c`` into a fused multiply-add
without ``fastmath``), until the first of

* a **failure** (some ``soc < SoC_low`` after the tick),
* its **tick limit** (its tick counter reaches ``limit[b]``),
* an **arrival** at ``D`` when no policy runs inside the kernel (``kind == NONE``): the
  caller decides (a network's batched forward pass) and calls again.

With a policy inside the kernel (``THRESHOLD`` or ``TABLE``, row ``pol_row[b]`` of the
policy arrays) an arrival is decided on the spot from the ``partial`` features, computed
as :class:`fleet_torchrl.env.encodings.Partial` computes them in float32, and the site runs
on: a whole evaluation is one call. The policies are the rule, the heuristic and the
threshold class (:class:`fleet_torchrl.agents.threshold.ThresholdPolicy` lowers them) and
any action table over the discretised ``partial`` state (tabular Q-learning, the search's
table classes); each policy class builds its arrays (``Policy.kernel_policy``) and tests
check that every one decides exactly as its torch ``forward``.

Per site the call returns **events**, not rewards: ticks run, trips (arrivals at ``D``),
queue ticks, and whether its last tick brought an arrival, a failure or a queue tick. The
objectives of :mod:`fleet_torchrl.env.objectives` turn them into rewards.

A call's arrays travel as named groups (:class:`KernelArgs`, built by
:mod:`fleet_torchrl.sim.fused`): the sites' :class:`State` (updated in place), their
:class:`Params`, the site's :class:`Constants`, the :class:`Run` (tick limit, active
sites), the :class:`Policy` and the :class:`Out` events. ``Run``'s arrays and the policy's
``rows`` hold one value per site or one for all (length 1). Per-site parameters are always
present (a single site is a batch of equal values).
"""

from __future__ import annotations

import types
from typing import NamedTuple

import numba
import numpy as np
from numba import get_thread_id, njit, prange

from .config import MAX_NODES

M32 = 0xFFFFFFFF
GOLDEN = 0x9E3779B9
C1 = 0x21F0AAAD
C2 = 0x735A2D97

# policy kinds inside the kernel
NONE, THRESHOLD, TABLE = 0, 1, 2
# columns of a threshold row (float32, socs and TC as the partial features: / 100, / T_C+1)
THR_LOW, THR_FREE_UPPER, THR_MARGIN, THR_OTHERS_BELOW, THR_BUSY_TC, THR_BUSY_UPPER = range(6)
N_THRESHOLD = 6
N_SOC_BINS = 10
MAXV = MAX_NODES - 2  # vehicles per site at most (distinct nodes other than C)
MAX_THREADS = numba.config.NUMBA_NUM_THREADS  # scratch rows of the parallel kernel

F32_100 = np.float32(100.0)
F32_0 = np.float32(0.0)
F32_SOC_SCALE = np.float32(0.01)
F32_BINS = np.float32(N_SOC_BINS)
F32_BIN_EPS = np.float32(1e-4)
ALL_ACTIVE = np.ones(1, dtype=np.bool_)  # ``active`` of a call that runs every site


class State(NamedTuple):
    """The sites' state, which a call updates in place (``V`` vehicle rows, ``B`` sites)."""

    pos: np.ndarray  # int64 [V, B]: each vehicle's node
    soc: np.ndarray  # float32 [V, B]: each vehicle's soc
    left: np.ndarray  # int64 [V, B]: charging ticks left (0: not charging)
    charge: np.ndarray  # bool [B]: the vehicle at D charges
    tick: np.ndarray  # int64 [B]: the site's tick counter


class Params(NamedTuple):
    """Each site's own values (``[B]``)."""

    site_hash: np.ndarray  # int64: its closure stream (Site.site_hash)
    n_veh: np.ndarray  # int64: fleet size (the vehicle rows beyond it are parked, untouched)
    t_c: np.ndarray  # int64: ticks of a charging session
    gain: np.ndarray  # float32: soc a charging tick adds
    closure: np.ndarray  # int64: X is closed in a tick iff its 32-bit draw is below (0: never)


class Constants(NamedTuple):
    """The tick rules' constants (:meth:`fleet_torchrl.sim.site.Site.kernel_constants`)."""

    tables: np.ndarray  # int64 [2, 2 * stride]: successor, then the bits checked, per node
    geo: np.ndarray  # int64 [stride, closed node's bit, leave when full]
    energy: np.ndarray  # float32 [soc change idle, moving, failure line soc_low]


class Run(NamedTuple):
    """Which sites run and how far (one value per site, or one for all)."""

    limit: np.ndarray  # int64: the tick counter a site stops at
    active: np.ndarray  # bool: an inactive site runs no tick and gets zero events


class Policy(NamedTuple):
    """The policy deciding inside the kernel (``kind == NONE``: none, stop at arrivals)."""

    kind: int  # NONE, THRESHOLD or TABLE
    rows: np.ndarray  # int64: each site's row (one value per site, or one for all)
    thresholds: np.ndarray  # float32 [R, N_THRESHOLD]: columns THR_*
    table: np.ndarray  # int8 [R, cells]: action per cell of the discretised partial state
    n_tc: int  # charger bins of a table


class Out(NamedTuple):
    """Each site's events over the call (``[3, B]``, written by it)."""

    counts: np.ndarray  # int64 rows: ticks run, trips (arrivals at D), queue ticks
    flags: np.ndarray  # bool rows: the last tick brought an arrival, a failure, a queue tick


class KernelArgs(NamedTuple):
    """Everything one call of the kernel reads and writes. The entry points take its groups
    as plain tuples, in this order (:func:`fleet_torchrl.sim.fused._kernel_call`: numba's
    dispatcher types a named tuple in Python, ~7 us a call), and name them with
    :func:`named`."""

    state: State
    params: Params
    constants: Constants
    run: Run
    policy: Policy
    out: Out


def mix32(x):
    """The 32-bit finaliser of :func:`fleet_torchrl.sim.rng._mix` on int64 values < 2**32
    (products stay below 2**63)."""
    x = x ^ (x >> 16)
    x = (x * C1) & M32
    x = x ^ (x >> 15)
    x = (x * C2) & M32
    return x ^ (x >> 15)


def closed_now(hs, t, threshold):
    """Whether ``X`` is closed in tick ``t`` of the site with closure hash ``hs``."""
    if threshold <= 0:
        return False
    ht = mix32((t & M32) ^ GOLDEN)
    return mix32(hs ^ ht) < threshold


def soc_bin(f):
    """Bin of a normalised soc feature: ``int(f * 10 + 1e-4)`` clamped to [0, 9], in
    float32 as :func:`fleet_torchrl.agents.tabular.state_index`."""
    k = int(f * F32_BINS + F32_BIN_EPS)
    if k < 0:
        k = 0
    if k > N_SOC_BINS - 1:
        k = N_SOC_BINS - 1
    return k


def scaled_features(soc_d, others, tc_raw, t_c):
    """The ``partial`` features in float32 from a site's soc at ``D``, its lowest other soc
    (neither at ``D`` nor at ``C``) and its charger's ticks left + 1 (0 if free): the values
    of the tensor encoding bit for bit (what :func:`decide` and :func:`partial_features`
    both read)."""
    return (soc_d * F32_SOC_SCALE, others * F32_SOC_SCALE,
            np.float32(tc_raw) * np.float32(1.0 / (t_c + 1.0)))


def decide(PL, E, nv, t_c, kind, row, pol_thr, pol_table, n_tc):
    """The in-kernel policy's action (True = charge) for the vehicle at ``D`` of a site whose
    vehicles are ``PL`` (nodes, charging ticks left) and ``E`` (soc): the ``partial``
    features in float32, then the threshold rule or the table lookup."""
    soc_d = F32_0
    others = F32_100
    tc_raw = 0
    for v in range(nv):
        p = PL[0, v]
        if p == 0:
            soc_d = E[v]
        elif p == 1:
            tc_raw = PL[1, v] + 1
        elif E[v] < others:
            others = E[v]
    f0, f1, f2 = scaled_features(soc_d, others, tc_raw, t_c)
    if kind == THRESHOLD:
        if f0 <= pol_thr[row, THR_LOW]:
            return True
        if (tc_raw == 0 and f0 <= pol_thr[row, THR_FREE_UPPER]
                and f0 <= f1 + pol_thr[row, THR_MARGIN]
                and f1 <= pol_thr[row, THR_OTHERS_BELOW]):
            return True
        return (tc_raw > 0 and f2 <= pol_thr[row, THR_BUSY_TC]
                and f0 <= pol_thr[row, THR_BUSY_UPPER])
    # TABLE: cell (soc_D bin * 10 + others bin) * n_tc + TC bin; TC bin 0 = free, then
    # n_tc - 1 equal shares of (0, 1]
    tc_bin = 0
    if tc_raw > 0:
        tc_bin = 1
        if n_tc > 2:
            k = int(f2 * np.float32(n_tc - 1))
            if k > n_tc - 2:
                k = n_tc - 2
            tc_bin = 1 + k
    cell = (soc_bin(f0) * N_SOC_BINS + soc_bin(f1)) * n_tc + tc_bin
    return pol_table[row, cell] != 0


def named(state, params, constants, run, policy, out):
    """The plain tuples an entry point receives as the named :class:`KernelArgs` (a
    relabelling at compile time, no work at run time)."""
    return KernelArgs(State(*state), Params(*params), Constants(*constants), Run(*run),
                      Policy(*policy), Out(*out))


def tick_vehicles(PL, E, nv, seen, off, tables, g, tcb, lwf, d_idle, d_move, soc_low):
    """One tick of a site's ``nv`` vehicles (scratch rows ``PL``: nodes, ticks left, and
    ``E``: soc, updated): each moves to its successor unless an occupancy bit it checks is
    in ``seen`` (``off``: the charging half of ``tables`` when the vehicle at ``D``
    charges), charges, or idles, and its soc changes in float32, capped at 100. Returns the
    occupancy bits that flipped, and whether a vehicle entered ``C``, one arrived at ``D``,
    and some soc fell below ``soc_low``."""
    into_c = False
    arrived = False
    failed = False
    moved = 0
    for v in range(nv):  # branch-free: selects, not jumps (moves follow closures)
        p = PL[0, v]
        idx = p + off
        tgt = tables[0, idx]
        charging = PL[1, v] > 0  # a charging vehicle has no target
        move = ((tables[1, idx] & seen) == 0) & ~charging
        s = E[v] + (g if charging else (d_move if move else d_idle))
        s = F32_100 if s > F32_100 else s
        E[v] = s
        lf = PL[1, v] - charging
        # the charger ends the session on a full battery
        lf = 0 if lwf & charging & (s >= F32_100) else lf
        enter_c = move & (tgt == 1)
        PL[1, v] = tcb if enter_c else lf
        into_c |= enter_c
        arrived |= move & (tgt == 0)
        moved ^= ((1 << p) ^ (1 << tgt)) if move else 0  # no two movers share a node
        PL[0, v] = tgt if move else p
        failed |= s < soc_low
    return moved, into_c, arrived, failed


def run_site_range(b0, b1, a, PL, E):
    """Run each active site ``b0 <= b < b1`` of the call ``a`` (:class:`KernelArgs`) from its
    state to a failure, its tick limit, or (``kind == NONE``) an arrival at ``D``, at least
    one tick (:func:`tick_vehicles`); an inactive site gets zero events. ``PL`` (int64,
    rows: nodes, ticks left) and ``E`` (soc): scratch rows for a site's vehicles (local
    copies the compiler keeps in registers; the state arrays are written back at the end).
    A CUDA thread runs one site (``b1 = b0 + 1``).

    Speed notes, measured: a range of sites per call, not one, because numba
    reference-counts every array passed to a call (or sliced), or bound to a variable that
    outlives a block, with atomic operations (~0.2 us per site and call with the two dozen
    arrays here, as much as the ticks of a decision epoch). So the groups are unpacked into
    local names once per call, and the loop over sites passes no array to a helper."""
    pos, soc, left, charge, tick = a.state
    site_hash, n_veh, t_c, gain, closure = a.params
    stride, closed_bit, lwf = a.constants.geo[0], a.constants.geo[1], a.constants.geo[2] != 0
    d_idle, d_move, soc_low = a.constants.energy[0], a.constants.energy[1], a.constants.energy[2]
    tables = a.constants.tables
    limit, active = a.run
    kind, pol_row, pol_thr, pol_table, n_tc = a.policy
    counts, flags = a.out
    for b in range(b0, b1):
        if not active[b % active.shape[0]]:
            for k in range(3):
                counts[k, b] = 0
                flags[k, b] = False
            continue
        nv, tcb, g, thr = n_veh[b], t_c[b], gain[b], closure[b]
        hs = site_hash[b] & M32
        lim = limit[b % limit.shape[0]]
        row = pol_row[b % pol_row.shape[0]]
        ch = charge[b]
        t = tick[b]
        occ = 0  # occupancy bits, kept up to date move by move
        for v in range(nv):
            PL[0, v] = pos[v, b]
            PL[1, v] = left[v, b]
            E[v] = soc[v, b]
            occ |= 1 << PL[0, v]
        n = trips = queue = 0
        while True:
            occ_d = (occ & 1) != 0
            seen = occ  # what every vehicle checks: the tick's start, a closed X occupied
            if closed_now(hs, t, thr):
                seen |= closed_bit
            moved, into_c, arrived, failed = tick_vehicles(
                PL, E, nv, seen, stride if ch else 0, tables, g, tcb, lwf, d_idle, d_move,
                soc_low)
            occ ^= moved
            q = occ_d & ch & ~into_c
            if arrived:
                ch = False  # the newcomer at D has not decided yet
            t += 1
            n += 1
            trips += arrived
            queue += q
            if arrived and not failed and kind != NONE:
                ch = decide(PL, E, nv, tcb, kind, row, pol_thr, pol_table, n_tc)
            if failed or t >= lim or (arrived and kind == NONE):
                break
        for v in range(nv):
            pos[v, b] = PL[0, v]
            left[v, b] = PL[1, v]
            soc[v, b] = E[v]
        charge[b], tick[b] = ch, t
        counts[0, b], counts[1, b], counts[2, b] = n, trips, queue
        flags[0, b], flags[1, b], flags[2, b] = arrived, failed, q


_jit = njit(cache=True, nogil=True)
_inline = njit(cache=True, nogil=True, inline="always")
mix32 = _jit(mix32)
closed_now = _jit(closed_now)
soc_bin = _jit(soc_bin)
scaled_features = _inline(scaled_features)
decide = _inline(decide)
named = _inline(named)
tick_vehicles = _inline(tick_vehicles)
run_site_range = _jit(run_site_range)
# the device functions, callees first: what cuda_kernel rebinds to their CUDA versions
DEVICE_FUNCTIONS = ("mix32", "closed_now", "soc_bin", "scaled_features", "decide", "named",
                    "tick_vehicles", "run_site_range")
CHUNK = 64  # sites per run_site_range call of the parallel kernel


@njit(cache=True, parallel=True, nogil=True)
def advance_parallel(state, params, constants, run, policy, out):
    """Every site of the batch, chunks of sites spread over the machine's cores (numba's
    threading layer); each thread keeps a site's vehicles in its own scratch rows. The
    arguments: the groups of :class:`KernelArgs` as plain tuples. numba's parallel loop
    takes arrays and scalars into its body, not tuples of arrays: the groups are taken
    apart before it and named again inside it."""
    pos, soc, left, charge, tick = state
    site_hash, n_veh, t_c, gain, closure = params
    tables, geo, energy = constants
    limit, active = run
    kind, rows, thresholds, table, n_tc = policy
    counts, flags = out
    PL = np.empty((MAX_THREADS, 2, MAXV), np.int64)
    E = np.empty((MAX_THREADS, MAXV), np.float32)
    nb = pos.shape[1]
    for c in prange((nb + CHUNK - 1) // CHUNK):
        k = get_thread_id()
        a = named((pos, soc, left, charge, tick), (site_hash, n_veh, t_c, gain, closure),
                  (tables, geo, energy), (limit, active), (kind, rows, thresholds, table, n_tc),
                  (counts, flags))
        run_site_range(c * CHUNK, min(nb, (c + 1) * CHUNK), a, PL[k], E[k])


@njit(cache=True, nogil=True)
def advance_serial(state, params, constants, run, policy, out):
    """The same on one core (small batches, short calls, one thread asked for)."""
    a = named(state, params, constants, run, policy, out)
    PL = np.empty((2, MAXV), np.int64)
    E = np.empty(MAXV, np.float32)
    run_site_range(0, a.state.pos.shape[1], a, PL, E)


def advance_cuda(state, params, constants, run, policy, out):
    """The CUDA kernel: one thread per site, its vehicles in thread-local arrays. Compiled
    only by :func:`cuda_kernel` (its names ``cuda``, ``int64``, ``float32`` and the device
    functions are bound there)."""
    a = named(state, params, constants, run, policy, out)
    b = cuda.grid(1)  # noqa: F821 (bound by cuda_kernel)
    if b < a.state.pos.shape[1]:
        PL = cuda.local.array((2, MAXV), int64)  # noqa: F821
        E = cuda.local.array(MAXV, float32)  # noqa: F821
        run_site_range(b, b + 1, a, PL, E)


@njit(cache=True, nogil=True)
def partial_features(pos, soc, left, t_c, out):
    """The ``partial`` state of every site (``out[b]``: soc at ``D``, lowest soc neither at
    ``D`` nor at ``C``, the charger's ``TC``; float32, the features :func:`decide` reads) in
    one pass over the vehicles: what the environment observes after each step, without a
    dozen tensor operations. ``t_c``: one value or one per site."""
    nv, nb = pos.shape
    one = t_c.shape[0] == 1
    for b in range(nb):
        soc_d = F32_0
        others = F32_100
        tc_raw = 0
        for v in range(nv):
            p = pos[v, b]
            if p == 0:
                soc_d = soc[v, b]
            elif p == 1:
                tc_raw += left[v, b] + 1
            elif soc[v, b] < others:
                others = soc[v, b]
        out[b, 0], out[b, 1], out[b, 2] = scaled_features(soc_d, others, tc_raw,
                                                          t_c[0] if one else t_c[b])


_cuda: dict[str, object] = {}


def cuda_kernel():
    """The CUDA kernel (one thread per site) built from the same Python functions as the CPU
    kernel, each call rebound to its device version. Built once per process."""
    if "advance" in _cuda:
        return _cuda["advance"]
    from numba import cuda

    glb = dict(globals())
    glb.update(cuda=cuda, int64=numba.int64, float32=numba.float32)
    for name in DEVICE_FUNCTIONS:
        py = globals()[name].py_func
        fn = types.FunctionType(py.__code__, glb, name, py.__defaults__, py.__closure__)
        glb[name] = cuda.jit(device=True)(fn)
    kernel = types.FunctionType(advance_cuda.__code__, glb, "advance_cuda")
    _cuda["advance"] = cuda.jit(kernel)
    return _cuda["advance"]
