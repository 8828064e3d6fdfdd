"""The compiled kernel (sim/kernel.py through sim/fused.py) against the eager torch tick, bit
for bit: records, states, events, rewards, in-kernel policies, and the CUDA target under
numba's CUDA simulator. No test here skips: the kernel needs no system compiler."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest
import torch
from tensordict.nn import TensorDictModule
from torch import Tensor

from fleet_torchrl.agents.base import Policy
from fleet_torchrl.agents.baselines import HeuristicPolicy, RulePolicy
from fleet_torchrl.agents.dqn import DQNPolicy, NetworkConfig
from fleet_torchrl.agents.search import SearchPolicy
from fleet_torchrl.agents.tabular import TabularQPolicy
from fleet_torchrl.agents.threshold import ThresholdPolicy
from fleet_torchrl.env import FleetChargingEnv
from fleet_torchrl.env.config import MDPConfig
from fleet_torchrl.evaluation import EvalConfig, simulate
from fleet_torchrl.sim import Site, SiteConfig, SiteRanges, fused
from fleet_torchrl.utils.checks import ConfigError

CONFIGS = {
    "default": SiteConfig(),
    "fixed_length_charges": SiteConfig(leave_when_full=False),
    "one_vehicle": SiteConfig(n_vehicles=1),
    "five_vehicles": SiteConfig(n_vehicles=5),
    "t_c_10": SiteConfig(t_c=10),
    "t_c_50": SiteConfig(t_c=50),
    "never_closed": SiteConfig(p_c=0.0),
    "p_c_0.9": SiteConfig(p_c=0.9),
    "eight_nodes": SiteConfig(n_nodes=8, closed_node=6),
}


class HashPolicy(Policy):
    """Random-looking actions that are a pure function of each observation row's bits (a
    stateful generator would draw differently when called once per tick vs once per
    decision epoch)."""

    name = "hash"

    def __init__(self, encoding: str = "partial") -> None:
        super().__init__()
        self.encoding = encoding

    def forward(self, obs: Tensor) -> Tensor:
        x = obs.contiguous().view(torch.int32).to(torch.int64).sum(-1)
        return ((x * 2654435761) >> 11) & 1


def tiny_dqn(encoding: str, n_obs: int) -> DQNPolicy:
    torch.manual_seed(0)
    return DQNPolicy(NetworkConfig(name=encoding, width=8, depth=1), n_obs, encoding)


def random_tabular() -> TabularQPolicy:
    pol = TabularQPolicy()
    g = torch.Generator().manual_seed(3)
    pol.q.copy_(torch.randn(pol.q.shape, generator=g))
    pol.q[::7] = 0.0  # ties: pass, in the kernel as in argmax
    return pol


def random_table(n_tc: int = 2) -> SearchPolicy:
    pol = SearchPolicy("table", n_tc=n_tc)
    g = torch.Generator().manual_seed(n_tc)
    pol.charge.copy_((torch.rand(pol.charge.shape, generator=g) < 0.4).long())
    return pol


# policies the kernel can decide with, each a different path through sim/kernel.py: decide
IN_KERNEL = {
    "rule": RulePolicy(),
    "rule_35": RulePolicy(35.0),
    "heuristic": HeuristicPolicy(),
    "heuristic_others_below": HeuristicPolicy(40.0, 65.0, others_below=75.0),
    "threshold_busy": ThresholdPolicy(38.0, 70.0, 5.0, 90.0, busy_tc=0.3, busy_upper=55.0),
    "threshold_free": ThresholdPolicy(42.0, free_upper=80.0, margin=100.0),
    "tabular": random_tabular(),
    "table": random_table(2),
    "table_5_tc_bins": random_table(5),
}


def bits(t: Tensor) -> Tensor:
    return t.view(torch.int32) if t.dtype == torch.float32 else t


def assert_same_records(cfg: SiteConfig, policy: Policy, n_sims: int = 64, ticks: int = 800,
                        seed: int = 5) -> dict[str, Tensor]:
    """Eager, fused with a forward pass per decision epoch, and (where it has one) the
    policy inside the kernel: the same records."""
    eager = simulate(policy, cfg, n_sims, ticks, seed, fused=False)
    runs = [simulate(policy, cfg, n_sims, ticks, seed, fused=True, in_kernel=False)]
    if policy.kernel_policy() is not None:
        runs.append(simulate(policy, cfg, n_sims, ticks, seed, fused=True))
    for fast in runs:
        for k in eager:
            assert torch.equal(eager[k], fast[k]), k
    return eager


@pytest.mark.parametrize("name", list(CONFIGS))
def test_simulate_records_identical_on_every_site(name):
    assert_same_records(CONFIGS[name], RulePolicy())


@pytest.mark.parametrize("policy", [
    HashPolicy(),
    HashPolicy("all"),
    tiny_dqn("partial", 3),
    tiny_dqn("all", SiteConfig().n_nodes + 1),
    *IN_KERNEL.values(),
], ids=["hash", "hash_all", "dqn_partial", "dqn_all", *IN_KERNEL])
@pytest.mark.parametrize("name", ["default", "p_c_0.9", "five_vehicles"])
def test_simulate_records_identical_for_every_policy(name, policy):
    assert_same_records(CONFIGS[name], policy, n_sims=48, ticks=500)


@pytest.mark.parametrize("name", ["t_c_10", "t_c_50", "one_vehicle"])
@pytest.mark.parametrize("policy", ["heuristic_others_below", "threshold_busy",
                                    "table_5_tc_bins"])
def test_in_kernel_policies_on_other_sites(name, policy):
    """The charger's remaining time is scaled by each site's T_C in the kernel too."""
    assert_same_records(CONFIGS[name], IN_KERNEL[policy], n_sims=32, ticks=600)


@pytest.mark.parametrize("name", ["default", "t_c_50", "fixed_length_charges"])
def test_simulate_failing_sites_identical(name):
    rec = assert_same_records(CONFIGS[name], RulePolicy(threshold=32), ticks=1500)
    assert rec["failed"].any()  # a failed site stops in the fused loop, counts stop in both
    assert (rec["ticks_survived"][rec["failed"]] < 1500).all()


def test_the_kernel_is_not_skipped_anywhere():
    """The kernel builds from the numba wheel: nothing falls back to the eager path on the
    CPU, whatever compilers the machine has."""
    assert fused.available("cpu") and fused.use_fused("cpu")
    env = FleetChargingEnv(num_sites=2)
    assert env.fused


def eager_rewards(mdp: MDPConfig, out_seq: list, active_seq: list) -> tuple[Tensor, Tensor]:
    """The step rewards of both objectives accumulated tick by tick in float32, as a
    learner of MODEL §2 defines them (the cross-check of env/objectives.py's tables)."""
    b = active_seq[0].shape[0]
    cost, acc, disc = torch.zeros(b), torch.zeros(b), torch.ones(b)
    n = torch.zeros(b, dtype=torch.int64)
    for o, was in zip(out_seq, active_seq, strict=True):
        cost -= torch.where(o.failed, mdp.p_f, torch.where(o.queue, mdp.p_q, 0.0))
        acc += disc * (o.arrived.float() - mdp.rho * was - mdp.p_f * o.failed.float())
        disc = torch.where(was, disc * mdp.gamma_tick, disc)
        n += was
    return torch.where(n > 0, cost / n.clamp(min=1), 0.0), acc


@pytest.mark.parametrize("gamma_tick,p_q", [(0.998, 1.0), (0.97, 0.37)])
def test_advance_matches_the_eager_tick_loop_state_for_state(gamma_tick, p_q):
    """Round after round (sites at D charge, or pass on every third site), the kernel and
    the eager tick agree on the state, the events and both objectives' rewards; the site
    drains fast enough that some sites fail and many queue."""
    site = Site(SiteConfig(p_c=0.9, t_c=25, e_move=1.2))
    b = 300
    idx = torch.arange(b)
    s, needs = site.init_state(11, idx)
    site.decide(s, needs, idx % 3 != 0)
    h = site.site_hash(11, idx)
    ref = s.clone()
    seen = {"queue": 0, "queued": 0, "failed": 0, "arrived": 0}
    alive = torch.ones(b, dtype=torch.bool)
    for r in range(12):
        active = alive & (idx % 7 != r % 7)
        limit = ref.tick + 5 + (idx * (r + 1)) % 40  # per-site tick limits
        ev = fused.advance(site, s, h, limit, active)
        run = active.clone()
        n, trips, queue = (torch.zeros(b, dtype=torch.int64) for _ in range(3))
        failed, arrived, queued = (torch.zeros(b, dtype=torch.bool) for _ in range(3))
        outs, acts = [], []
        while bool(run.any()):
            was = run.clone()
            o = site.tick(ref, site.closures_hashed(h, ref.tick, ref.params), run)
            outs.append(o)
            acts.append(was)
            n += run
            trips += o.arrived
            queue += o.queue
            failed |= o.failed
            arrived = torch.where(was, o.arrived, arrived)
            queued = torch.where(was, o.queue, queued)
            run &= ~(o.arrived | o.failed | (ref.tick >= limit))
        for f in ("pos", "soc", "left", "charge", "tick"):
            assert torch.equal(bits(getattr(ref, f)), bits(getattr(s, f))), (r, f)
        assert torch.equal(ev.ticks, n) and torch.equal(ev.trips, trips)
        assert torch.equal(ev.queue, queue) and torch.equal(ev.failed, failed)
        assert torch.equal(ev.arrived, arrived) and torch.equal(ev.queued, queued)
        assert (ev.ticks[~active] == 0).all() and (ev.ticks[active] >= 1).all()
        for reward in ("thesis", "throughput"):
            mdp = MDPConfig(reward=reward, gamma_tick=gamma_tick, p_q=p_q)
            want = eager_rewards(mdp, outs, acts)[0 if reward == "thesis" else 1]
            got = mdp.objective.reward(ev, mdp)
            assert torch.equal(bits(got), bits(want)), (r, reward)
        seen["queue"] = max(seen["queue"], int(ev.queue.max()))
        for k in ("queued", "failed", "arrived"):
            seen[k] += int(getattr(ev, k).sum())
        alive &= ~ev.failed
        site.decide(s, ev.arrived, idx % 3 != 0)
        site.decide(ref, ev.arrived, idx % 3 != 0)
    assert seen["queue"] > 1 and seen["queued"] and seen["failed"] and seen["arrived"], seen


@pytest.mark.parametrize("reward,cfg", [("thesis", SiteConfig()),
                                        ("throughput", SiteConfig(n_vehicles=5, t_c=10))])
def test_env_rollouts_identical(reward, cfg):
    policy = TensorDictModule(HashPolicy(), in_keys=["observation"], out_keys=["action"])
    mdp = MDPConfig(reward=reward, tau_e=200)
    rollouts = []
    for use_fused in (False, True):
        env = FleetChargingEnv(cfg, "partial", 16, mdp, seed=3, fused=use_fused)
        assert env.fused is use_fused
        rollouts.append(env.rollout(150, policy, break_when_any_done=False))
    eager, fast = rollouts
    keys = list(eager.keys(True, True))
    assert ("next", "reward") in keys and ("next", "observation") in keys
    for k in keys:
        assert torch.equal(bits(eager[k]), bits(fast[k])), k
    assert eager["next", "terminated"].any() and eager["next", "truncated"].any()


def test_backend_switch():
    assert fused.use_fused("cpu", None) and fused.use_fused("cpu", True)
    assert not fused.use_fused("cpu", False) and not fused.use_fused("cuda", False)
    if not torch.cuda.is_available():
        assert not fused.use_fused("cuda", None)  # announced once, the eager loop serves
        with pytest.raises(RuntimeError, match="eager"):
            fused.use_fused("cuda", True)
    assert EvalConfig(backend="eager").validate().backend == "eager"
    with pytest.raises(ConfigError, match="eval.backend"):
        EvalConfig(backend="jit").validate()


def test_a_forked_child_runs_the_kernel():
    """A child forked from a process whose kernel thread pool is running runs the kernel
    too, with the same records (GNU OpenMP's pool would hang there: sim/fused.py uses
    numba's workqueue layer)."""
    if not hasattr(os, "fork"):
        pytest.skip("no fork on this platform")
    a = simulate(RulePolicy(), SiteConfig(), 256, 300, 0)  # starts the pool here
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: same records, then exit without pytest's teardown
        try:
            b = simulate(RulePolicy(), SiteConfig(), 256, 300, 0)
            ok = all(torch.equal(a[k], b[k]) for k in a)
            os.write(w, b"1" if ok else b"0")
        finally:
            os._exit(0)
    os.close(w)
    _, status = os.waitpid(pid, 0)
    assert os.read(r, 1) == b"1" and status == 0


CUDASIM = textwrap.dedent("""
    import os, sys, torch
    assert os.environ.get("NUMBA_ENABLE_CUDASIM") == "1"
    from fleet_torchrl.agents.baselines import HeuristicPolicy
    from fleet_torchrl.agents.search import SearchPolicy
    from fleet_torchrl.env.encodings import get_encoding
    from fleet_torchrl.sim import Site, SiteConfig, SiteRanges, fused
    cfgs = [SiteConfig(), SiteConfig(n_vehicles=5, t_c=10, p_c=0.9),
            SiteConfig(name="randomized", ranges=SiteRanges(n_vehicles=[1, 5], t_c=[10, 50]))]
    table = SearchPolicy("table", n_tc=4)
    table.charge.copy_(torch.arange(table.charge.numel()) % 3 == 0)
    for cfg in cfgs:
        for pol in (HeuristicPolicy().kernel_policy(), table.kernel_policy(), None):
            site = Site(cfg)
            idx = torch.arange(6)
            runs = []
            for target in (None, "cuda"):
                s, needs = site.init_state(2, idx)
                site.decide(s, needs, torch.ones(6, dtype=torch.bool))
                h = site.site_hash(2, idx)
                evs = [fused.advance(site, s, h, 120, None, pol, target=target)
                       for _ in range(3)]
                runs.append((s, evs))
            (a, ea), (b, eb) = runs
            for f in ("pos", "soc", "left", "charge", "tick"):
                x, y = getattr(a, f), getattr(b, f)
                if x.dtype == torch.float32:
                    x, y = x.view(torch.int32), y.view(torch.int32)
                assert torch.equal(x, y), (cfg.name, f)
            for e1, e2 in zip(ea, eb):
                for f in ("ticks", "trips", "queue", "arrived", "failed", "queued"):
                    assert torch.equal(getattr(e1, f), getattr(e2, f)), (cfg.name, f)
    print("same")
""")


@pytest.mark.slow
def test_the_cuda_kernel_under_the_simulator_equals_the_cpu_kernel():
    """The CUDA target, compiled from the same functions, under numba's CUDA simulator (CI
    has no GPU; tests/test_cuda.py runs it on a real one)."""
    env = {**os.environ, "NUMBA_ENABLE_CUDASIM": "1"}
    r = subprocess.run([sys.executable, "-c", CUDASIM], capture_output=True, text=True,
                       env=env, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    assert r.stdout.strip().endswith("same")


def test_the_parallel_and_serial_kernels_give_the_same_call():
    """One call's named arguments (sim/kernel.py ``KernelArgs``, as sim/fused.py builds them)
    through both CPU entry points: chunks of sites on every core, and one core, write the
    same states and events; inactive sites run no tick and get zero events."""
    from fleet_torchrl.sim import kernel, kernel_cache

    cfg = SiteConfig(name="randomized", ranges=SiteRanges(n_vehicles=[1, 5], t_c=[10, 50]))
    site, idx = Site(cfg), torch.arange(200)
    pol = HeuristicPolicy().kernel_policy()
    runs = []
    for entry in ("advance_parallel", "advance_serial"):
        s, needs = site.init_state(1, idx)
        site.decide(s, needs, torch.ones(200, dtype=torch.bool))
        before = s.tick.clone()
        active = (idx % 7 != 0).numpy()
        counts, flags = np.empty((3, 200), np.int64), np.empty((3, 200), np.bool_)
        cpu = torch.device("cpu")
        args = fused._kernel_call(
            *fused._state_groups(fused._state_arrays(s), site.site_hash(1, idx).numpy()),
            fused._constants_group(site, cpu), np.full(1, 300, np.int64), active,
            fused._policy_group(pol, cpu), counts, flags)
        named = kernel.KernelArgs(*(g(*a) for g, a in zip(
            (kernel.State, kernel.Params, kernel.Constants, kernel.Run, kernel.Policy,
             kernel.Out), args, strict=True)))  # each group has its fields, in order
        assert named.out.counts is counts and named.run.active is active
        assert named.state.pos.shape == (5, 200) and named.policy.kind == fused.THRESHOLD
        kernel_cache.call(entry, *args)
        runs.append((s, counts, flags))
    (a, ca, fa), (b, cb, fb) = runs
    for f in ("pos", "soc", "left", "charge", "tick"):
        assert torch.equal(bits(getattr(a, f)), bits(getattr(b, f))), f
    assert np.array_equal(ca, cb) and np.array_equal(fa, fb)
    assert (ca[:, ::7] == 0).all() and not fa[:, ::7].any()
    assert torch.equal(a.tick[::7], before[::7]) and (ca[0, idx % 7 != 0] > 0).all()


def test_objective_tables_grow_exactly():
    """Steps longer than any before extend the running-sum tables with the same float32
    sums (a 5000-tick step: the throughput table of its first 4999 ticks)."""
    mdp = MDPConfig(reward="throughput", gamma_tick=0.999)
    obj = mdp.objective
    ev = fused.Events(ticks=torch.tensor([3, 5000]), trips=torch.tensor([1, 0]),
                      queue=torch.tensor([0, 0]), arrived=torch.tensor([True, False]),
                      failed=torch.tensor([False, False]), queued=torch.tensor([False, False]))
    got = obj.reward(ev, mdp)
    acc, d = np.float32(0), np.float32(1)
    for _ in range(4999):
        acc = np.float32(acc + np.float32(d * np.float32(-np.float32(mdp.rho))))
        d = np.float32(d * np.float32(mdp.gamma_tick))
    last = np.float32(np.float32(0.0) - np.float32(mdp.rho))
    want = np.float32(acc + np.float32(d * last))
    assert got[1].item() == float(want)


def test_a_damaged_kernel_cache_is_found_by_its_hash_and_rebuilt(tmp_path, monkeypatch,
                                                                   caplog):
    """The manifest records each cached kernel file's SHA-256; a file that no longer matches
    (a flipped byte that would still load) clears the cache with one warning line; files
    it does not list (a signature compiled since) are not judged."""
    from fleet_torchrl.sim import kernel_cache as kernel

    cleared = []
    monkeypatch.setattr(kernel, "cache_dir", lambda: tmp_path)
    monkeypatch.setattr(kernel, "clear_cache", lambda: cleared.append(1))
    (tmp_path / "kernel.advance_serial-1.py311.1.nbc").write_bytes(b"machine code")
    assert kernel.verify_cache() and not cleared  # no manifest yet: nothing to judge
    kernel.write_manifest()
    (tmp_path / "kernel.advance_serial-1.py311.2.nbc").write_bytes(b"new signature")
    assert kernel.verify_cache() and not cleared
    (tmp_path / "kernel.advance_serial-1.py311.1.nbc").write_bytes(b"machine coDe")
    with caplog.at_level("WARNING"):
        assert not kernel.verify_cache()
    assert cleared == [1] and not (tmp_path / kernel.MANIFEST).exists()
    warned = [r.getMessage() for r in caplog.records if "hash check" in r.getMessage()]
    assert len(warned) == 1 and "\n" not in warned[0] and ".1.nbc" in warned[0]
    (tmp_path / kernel.MANIFEST).write_text("{not json")  # a damaged manifest: rebuilt too
    assert not kernel.verify_cache() and cleared == [1, 1]


@pytest.mark.slow
def test_a_corrupt_cached_kernel_is_rebuilt_with_one_warning(tmp_path):
    """End to end, in fresh processes on a cache of their own: a flipped byte in a cached
    kernel file, then an unreadable one; each next run warns once, rebuilds the cache and
    gives the same trips (the first through the hash check, the second, without a
    manifest, through the load that fails)."""
    code = ("from fleet_torchrl.evaluation import evaluate_policy\n"
            "from fleet_torchrl.agents.baselines import RulePolicy\n"
            "from fleet_torchrl.sim import SiteConfig\n"
            "r = evaluate_policy(RulePolicy(), SiteConfig(), n_sims=8, ticks=300, seed=0)\n"
            "print('TRIPS', sum(r['records']['trips']))\n")
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache")}

    def run():
        r = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                           text=True, timeout=300)
        assert r.returncode == 0, r.stderr
        return r.stdout.split("TRIPS")[-1].strip(), [ln for ln in r.stderr.splitlines()
                                                      if "kernel" in ln]

    trips, warned = run()
    assert warned == []
    for how in ("flip", "garble"):
        f = sorted((tmp_path / "cache").rglob("kernel.advance_serial*.nbc"))[0]
        raw = bytearray(f.read_bytes())
        if how == "flip":
            raw[len(raw) // 2] ^= 0x01
        else:
            for i in range(200, len(raw), 997):
                raw[i] ^= 0xFF
            next((tmp_path / "cache").rglob("fleet_torchrl_kernel.sha256.json")).unlink()
        f.write_bytes(bytes(raw))
        again, warned = run()
        assert again == trips and len(warned) == 1 and "compiling the kernel again" in \
            warned[0], warned


def test_the_kernel_uses_the_cores_the_machine_leaves_idle(monkeypatch):
    """A parallel call waits for its slowest thread: on a busy machine the kernel runs on the
    cores the load average leaves idle (at least one), on a quiet one on all of them."""
    from fleet_torchrl.sim import fused

    monkeypatch.setattr(fused.os, "cpu_count", lambda: 2)
    for load, cores in ((1.0, 2), (1.4, 2), (2.0, 1), (5.0, 1), (0.0, 2)):
        monkeypatch.setattr(fused.os, "getloadavg", lambda load=load: (load, load, load))
        monkeypatch.setitem(fused._LOAD, "at", -1e9)  # read it again
        assert fused._idle_cores() == cores, load
