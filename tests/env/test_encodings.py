"""State encodings on a hand-built state."""

from __future__ import annotations

import pytest
import torch

from fleet_torchrl.env.encodings import get_encoding
from fleet_torchrl.sim import C, D, Site, SiteConfig


def test_encodings_on_a_hand_built_state():
    site = Site(SiteConfig())
    s = site.state(pos=torch.tensor([[D, C], [C, 5], [7, 8]]),
                   soc=torch.tensor([[38.0, 50.0], [70.0, 90.0], [60.0, 45.0]]),
                   left=torch.tensor([[0, 0], [9, 0], [0, 0]]))
    part = get_encoding("partial")(site, s)
    assert torch.allclose(part[0], torch.tensor([0.38, 0.60, 10 / 31]))
    # site 1: nobody at D, finished vehicle stuck at C counts as busy: 1 / (T_C + 1)
    assert torch.allclose(part[1], torch.tensor([0.0, 0.45, 1 / 31]))
    full = get_encoding("all")(site, s)
    assert full.shape == (2, 16)
    assert torch.allclose(full[0, [D, C, 7]], torch.tensor([0.38, 0.70, 0.60]))
    assert full[0, [2, 3, 4, 5, 6, 8]].abs().sum() == 0
    assert full[0, -1] == pytest.approx(10 / 31)
    lone = Site(SiteConfig(n_vehicles=1)).state(pos=torch.tensor([[D]]),
                                                soc=torch.tensor([[50.0]]))
    assert torch.allclose(get_encoding("partial")(site, lone), torch.tensor([[0.5, 1.0, 0.0]]))


def test_partial_site_is_partial_plus_the_sites_own_parameters():
    from fleet_torchrl.sim import SiteRanges

    one = SiteConfig(n_vehicles=4, p_c=0.6, t_c=20).validate()
    site = Site(one)
    s, _ = site.init_state(0, torch.arange(32))
    full = get_encoding("partial_site")(site, s)
    assert full.shape == (32, 6)
    assert torch.equal(full[:, :3], get_encoding("partial")(site, s))
    assert torch.allclose(full[:, 3:], torch.tensor([4 / 15, 0.6, 20 / 35]).expand(32, 3))
    mixed = SiteConfig(ranges=SiteRanges(n_vehicles=[1, 5], p_c=[0.0, 0.9],
                                         t_c=[10, 50])).validate()
    site = Site(mixed)
    s, _ = site.init_state(0, torch.arange(64))
    obs = get_encoding("partial_site")(site, s)
    p = s.params
    assert torch.allclose(obs[:, 3], p.n_vehicles / 15.0)
    assert torch.allclose(obs[:, 4], p.p_c.float())
    assert torch.allclose(obs[:, 5], p.t_c / (p.t_c + 15.0))
    # TC is each site's own share of its T_C: a vehicle entering C (T_C ticks left) reads
    # (T_C + 1) / (T_C + 1) = 1 on every site; then 1 / (T_C + 1) when it has 0 left
    s.pos[0], s.left[0] = 1, p.t_c
    assert torch.allclose(get_encoding("partial_site")(site, s)[:, 2], torch.ones(64))
    s.left[0] = 0
    assert torch.allclose(get_encoding("partial")(site, s)[:, 2], 1.0 / (p.t_c + 1.0))


def test_all_site_is_all_plus_the_sites_own_parameters():
    from fleet_torchrl.sim import SiteRanges

    mixed = SiteConfig(ranges=SiteRanges(n_vehicles=[1, 5], p_c=[0.0, 0.9],
                                         t_c=[10, 50])).validate()
    site = Site(mixed)
    s, _ = site.init_state(3, torch.arange(64))
    obs = get_encoding("all_site")(site, s)
    assert obs.shape == (64, 15 + 4) and get_encoding("all_site").size(site) == 19
    assert torch.equal(obs[:, :16], get_encoding("all")(site, s))
    assert torch.equal(obs[:, 16:], get_encoding("partial_site")(site, s)[:, 3:])
    p = s.params
    assert torch.allclose(obs[:, 16], p.n_vehicles / 15.0)
    assert torch.allclose(obs[:, 18], p.t_c / (p.t_c + 15.0))
    assert p.n_vehicles.unique().numel() > 1  # (the sites differ: the features do)


def test_partial_all_site_is_partial_then_all_then_the_site():
    from fleet_torchrl.sim import SiteRanges

    mixed = SiteConfig(ranges=SiteRanges(n_vehicles=[1, 5], p_c=[0.0, 0.9],
                                         t_c=[10, 50])).validate()
    site = Site(mixed)
    s, _ = site.init_state(5, torch.arange(32))
    enc = get_encoding("partial_all_site")
    obs = enc(site, s)
    assert obs.shape == (32, 3 + 16 + 3) and enc.size(site) == 22
    assert torch.equal(obs[:, :3], get_encoding("partial")(site, s))
    assert torch.equal(obs[:, 3:], get_encoding("all_site")(site, s))


def test_env_specs_of_every_encoding_on_a_site_distribution():
    from torchrl.envs.utils import check_env_specs

    from fleet_torchrl.env import FleetChargingEnv
    from fleet_torchrl.sim import SiteRanges

    mixed = SiteConfig(ranges=SiteRanges(n_vehicles=[1, 5], p_c=[0.0, 0.9],
                                         t_c=[10, 50])).validate()
    for name in ("partial", "all", "partial_site", "all_site", "partial_all_site"):
        env = FleetChargingEnv(mixed, name, num_sites=8, seed=0)
        check_env_specs(env, seed=0)


@pytest.mark.parametrize("site_cfg", [
    SiteConfig(), SiteConfig(n_vehicles=1), SiteConfig(n_vehicles=5, t_c=50),
    SiteConfig(t_c=10, p_c=0.0), "randomized"], ids=["default", "nv1", "nv5_tc50", "tc10",
                                                     "randomized"])
def test_the_compiled_partial_state_is_the_tensor_encoding_bit_for_bit(site_cfg, monkeypatch):
    """On the CPU ``partial`` comes from one kernel pass (sim/fused.py: partial_features);
    along random episodes (vehicles queueing, charging, parked) it equals the tensor
    operations' float32 values exactly."""
    from fleet_torchrl.env import FleetChargingEnv
    from fleet_torchrl.env import encodings as enc
    from fleet_torchrl.sim import SiteRanges
    from fleet_torchrl.sim.fused import partial_features

    if site_cfg == "randomized":
        site_cfg = SiteConfig(ranges=SiteRanges(n_vehicles=[1, 5], p_c=[0.0, 0.9],
                                                t_c=[10, 50])).validate()
    env = FleetChargingEnv(site_cfg, num_sites=64, seed=3)
    env.reset()
    g = torch.Generator().manual_seed(0)
    seen_busy = 0
    for _ in range(40):
        fast = partial_features(env.state)
        assert fast is not None
        with monkeypatch.context() as m:
            m.setattr(enc, "partial_features", lambda s: None)
            slow = enc.ENCODINGS["partial"](env.site, env.state)
        assert fast.dtype == slow.dtype == torch.float32
        assert torch.equal(fast, slow)
        assert torch.equal(enc.ENCODINGS["partial"](env.site, env.state), slow)
        seen_busy += int((slow[:, 2] > 0).sum())
        act = torch.randint(0, 2, (64,), generator=g)
        td = env.step(env.current().set("action", act))
        if td["next", "done"].any():
            env.reset(td["next"].select("done").set("_reset", td["next", "done"]))
    # the charger's feature was exercised (one vehicle is never at C when one is at D)
    assert seen_busy > 0 or site_cfg.n_vehicles == 1
