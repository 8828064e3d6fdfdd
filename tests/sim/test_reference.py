"""The torch site against the independent numpy reference of MODEL §1 (sim/reference.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fleet_torchrl.agents.baselines import RulePolicy
from fleet_torchrl.env.encodings import get_encoding
from fleet_torchrl.evaluation import simulate
from fleet_torchrl.sim import BYPASS, C, D, M, Site, SiteConfig
from fleet_torchrl.sim.reference import (
    ReferenceSite,
    ReferenceState,
    partial_obs,
    rule_policy,
    simulate_reference,
)

CONFIGS = {
    "default": SiteConfig(),
    "fixed_length_charges": SiteConfig(leave_when_full=False),
    "five_vehicles": SiteConfig(n_vehicles=5),
    "t_c_10": SiteConfig(t_c=10),
    "never_closed": SiteConfig(p_c=0.0),
    "p_c_0.9": SiteConfig(p_c=0.9),
    "eight_nodes": SiteConfig(n_nodes=8, closed_node=6),
}
OPEN = np.array([False])
encode = get_encoding("partial")


def one_site(vehicles: list[tuple], charge: bool = False) -> ReferenceState:
    """A reference state of one site from ``(node, soc[, charging ticks left])`` per vehicle."""
    return ReferenceState(
        pos=np.array([[v[0]] for v in vehicles], dtype=np.int64),
        soc=np.array([[v[1]] for v in vehicles], dtype=np.float32),
        left=np.array([[v[2] if len(v) > 2 else 0] for v in vehicles], dtype=np.int64),
        charge=np.array([charge]),
        tick=np.zeros(1, dtype=np.int64),
    )


def merge_conflicts(r: ReferenceState) -> np.ndarray:
    """``[B]`` bool: M is free and both B and a finished vehicle on C want to enter it."""
    on_b, on_m = (r.pos == BYPASS).any(0), (r.pos == M).any(0)
    done_on_c = ((r.pos == C) & (r.left == 0)).any(0)
    return on_b & done_on_c & ~on_m


@pytest.mark.parametrize("name", list(CONFIGS))
def test_tick_by_tick_against_the_reference(name):
    cfg = CONFIGS[name].validate()
    site, ref = Site(cfg), ReferenceSite(cfg)
    n_sites, ticks = 256, 300
    gen = torch.Generator().manual_seed(sorted(CONFIGS).index(name))
    s, needs = site.init_state(7, torch.arange(n_sites) + 1000)
    r = ReferenceState.from_torch(s)
    counts = {"arrived": 0, "queue": 0, "failed": 0, "full": 0, "merge": 0}
    for t in range(ticks):
        counts["merge"] += int(merge_conflicts(r).sum())
        charge = torch.rand(n_sites, generator=gen) < 0.5
        site.decide(s, needs, charge)
        ref.decide(r, needs.numpy(), charge.numpy())
        closed = torch.rand(n_sites, generator=gen) < cfg.p_c
        out = site.tick(s, closed)
        out_ref = ref.tick(r, closed.numpy())
        assert r.differences(s) == [], f"{name}: state differs after tick {t}"
        for key in ("arrived", "queue", "failed"):
            assert np.array_equal(getattr(out, key).numpy(), out_ref[key]), (name, t, key)
            counts[key] += int(out_ref[key].sum())
        counts["full"] += int((r.soc == 100.0).sum())
        obs = partial_obs(r, cfg.t_c).view(np.uint32)
        assert np.array_equal(obs, encode(site, s).numpy().view(np.uint32)), (name, t)
        needs = out.arrived
    # the random run exercised every rule that the comparison is meant to check
    assert min(counts.values()) > 0, counts


def test_protocol_matches_simulate_with_the_rule():
    cfg = SiteConfig()
    expected = simulate(RulePolicy(), cfg, 64, 2000, seed=0)
    got = simulate_reference(rule_policy, cfg, 64, 2000, seed=0)
    for key in ("trips", "queue", "failed", "ticks_survived"):
        assert np.array_equal(expected[key].numpy(), got[key]), key
    assert got["trips"].min() > 0 and got["queue"].sum() > 0


def test_protocol_matches_simulate_with_failures():
    # a rule that charges too late: some sites fail, and then stop counting
    cfg = SiteConfig()
    expected = simulate(RulePolicy(threshold=37.5), cfg, 64, 2000, seed=1)
    got = simulate_reference(lambda obs: rule_policy(obs, 37.5), cfg, 64, 2000, seed=1)
    for key in ("trips", "queue", "failed", "ticks_survived"):
        assert np.array_equal(expected[key].numpy(), got[key]), key
    assert 0 < got["failed"].sum() < 64


def test_rule_decisions_match_the_torch_rule_at_the_threshold():
    forty = np.float32(40.0)
    edge = [np.nextafter(forty, np.float32(0)), forty, np.nextafter(forty, np.float32(100))]
    soc = np.concatenate([np.array(edge), np.linspace(39.9, 40.1, 2001, dtype=np.float32)])
    state = ReferenceState(pos=np.zeros((1, soc.size), np.int64), soc=soc[None, :],
                           left=np.zeros((1, soc.size), np.int64),
                           charge=np.zeros(soc.size, bool), tick=np.zeros(soc.size, np.int64))
    site = Site(SiteConfig())
    obs_torch = encode(site, state.to_torch(site))
    obs = partial_obs(state, site.t_c)
    assert np.array_equal(obs_torch.numpy().view(np.uint32), obs.view(np.uint32))
    assert np.array_equal(RulePolicy()(obs_torch).numpy(), rule_policy(obs))
    assert rule_policy(obs)[:3].tolist() == [1, 1, 0]  # 40 charges, the next float32 does not


# ------------------------------------------------------------ the reference on its own


def test_reference_merge_priority_to_the_bypass():
    ref = ReferenceSite(SiteConfig())
    r = one_site([(BYPASS, 80.0), (C, 80.0, 0)])
    ref.tick(r, OPEN)
    assert r.pos[:, 0].tolist() == [M, C]  # B enters M, the finished vehicle on C waits
    assert r.soc[:, 0].tolist() == [np.float32(80) - np.float32(0.5),
                                    np.float32(80) - np.float32(0.02)]
    ref.tick(r, OPEN)
    assert r.pos[:, 0].tolist() == [4, C]  # M was occupied at the start of the tick
    ref.tick(r, OPEN)
    assert r.pos[:, 0].tolist() == [5, M]


@pytest.mark.parametrize("leave_when_full", [True, False])
def test_reference_leave_when_full(leave_when_full):
    cfg = SiteConfig(leave_when_full=leave_when_full)
    ref = ReferenceSite(cfg)
    r = one_site([(C, 99.5, 5)])
    ref.tick(r, OPEN)
    assert r.soc[0, 0] == 100.0 and r.pos[0, 0] == C  # capped at 100, still on C
    assert r.left[0, 0] == (0 if leave_when_full else 4)
    ref.tick(r, OPEN)
    assert r.pos[0, 0] == (M if leave_when_full else C)


def test_reference_queue_trip_and_failure():
    ref = ReferenceSite(SiteConfig())
    # the vehicle on D wants C, which is busy: a queue tick; the last road node completes a trip
    r = one_site([(D, 35.0), (C, 60.0, 3), (14, 31.0)], charge=True)
    out = ref.tick(r, OPEN)
    assert out["queue"][0] and not out["arrived"][0] and not out["failed"][0]
    assert r.pos[:, 0].tolist() == [D, C, 14]  # 14 -> D is blocked by the vehicle on D
    r = one_site([(C, 60.0, 3), (14, 30.01)])
    out = ref.tick(r, OPEN)
    assert out["arrived"][0] and r.pos[:, 0].tolist() == [C, D]
    assert out["failed"][0]  # 30.01 - 0.5 < 30


def test_reference_closed_x_admits_no_vehicle():
    cfg = SiteConfig()
    ref = ReferenceSite(cfg)
    x = cfg.closed_node
    r = one_site([(x - 1, 80.0), (x, 80.0)])
    ref.tick(r, np.array([True]))
    assert r.pos[:, 0].tolist() == [x - 1, x + 1]  # a vehicle on X may still leave it
    ref.tick(r, np.array([True]))
    assert r.pos[:, 0].tolist() == [x - 1, x + 2]
    ref.tick(r, OPEN)
    assert r.pos[:, 0].tolist() == [x, x + 3]


def test_env_steps_of_the_reference_match_the_torch_simulator():
    """Decision epochs as the environment runs them (decide, then tick the sites that have not
    reached their next decision, the others frozen): the reference and the torch simulator
    agree on every step's ticks and trips, including sites that fail."""
    from fleet_torchrl.agents import RulePolicy
    from fleet_torchrl.env import get_encoding
    from fleet_torchrl.sim.reference import env_steps_reference, rule_policy

    cfg, b, steps, seed = SiteConfig(), 64, 30, 5
    ref = env_steps_reference(lambda o: rule_policy(o, 33.0), cfg, b, steps, seed)
    site, encode, rule = Site(cfg), get_encoding("partial"), RulePolicy(33.0)
    idx = torch.arange(b)
    s, needs = site.init_state(seed, idx)
    h = site.site_hash(seed, idx)
    alive = torch.ones(b, dtype=torch.bool)
    pending = ~needs
    while pending.any():
        out = site.tick(s, site.closures_hashed(h, s.tick, s.params), pending)
        alive &= ~out.failed
        pending &= ~(out.arrived | out.failed)
    for k in range(steps):
        site.decide(s, alive, rule(encode(site, s)))
        active = alive.clone()
        ticks = torch.zeros(b, dtype=torch.int64)
        trips = torch.zeros(b, dtype=torch.int64)
        while active.any():
            out = site.tick(s, site.closures_hashed(h, s.tick, s.params), active)
            ticks += active
            trips += out.arrived & active
            alive &= ~(out.failed & active)
            active &= ~(out.arrived | out.failed)
        assert np.array_equal(ticks.numpy(), ref["ticks"][k]), k
        assert np.array_equal(trips.numpy(), ref["trips"][k]), k
    assert not alive.all()  # threshold 33 fails some sites: frozen failed sites are covered


def test_numpy_closure_draws_are_the_torch_ones():
    from fleet_torchrl.sim.reference import closure_draws

    site = Site(SiteConfig(p_c=0.37))
    idx = torch.arange(500)
    ticks = torch.randint(0, 2**31, (500,), generator=torch.Generator().manual_seed(1))
    expected = site.closures(9, idx, ticks).numpy()
    got = closure_draws(site.site_hash(9, idx).numpy().astype(np.uint64), ticks.numpy(), 0.37)
    assert np.array_equal(got, expected) and 0.3 < got.mean() < 0.45
