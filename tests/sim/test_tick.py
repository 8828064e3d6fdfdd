"""The tick rules of the site model on hand-built states (MODEL §1)."""

from __future__ import annotations

import pytest
import torch

from fleet_torchrl.sim import BYPASS, C, D, M, Site, SiteConfig

OPEN, CLOSED = torch.tensor([False]), torch.tensor([True])
E_MOVE, E_IDLE, GAIN = 0.5, 0.02, 40.0 / 30


def positions(s):
    return s.pos[:, 0].tolist()


def socs(s):
    return s.soc[:, 0].tolist()


def test_moves_only_into_an_empty_node(site, make_state):
    s = make_state([(5, 80.0), (7, 80.0)])
    out = site.tick(s, OPEN)
    assert positions(s) == [6, 8]
    assert socs(s) == pytest.approx([80 - E_MOVE, 80 - E_MOVE])
    assert not out.arrived.item() and not out.queue.item() and not out.failed.item()
    assert s.tick.item() == 1


def test_no_bumper_to_bumper_moves(site, make_state):
    # 6 frees its node in this tick, but 5 saw it occupied at the start of the tick
    s = make_state([(5, 80.0), (6, 80.0), (7, 80.0)])
    site.tick(s, OPEN)
    assert positions(s) == [5, 6, 8]
    assert socs(s) == pytest.approx([80 - E_IDLE, 80 - E_IDLE, 80 - E_MOVE])
    site.tick(s, OPEN)
    assert positions(s) == [5, 7, 9]


def test_merge_priority_to_the_bypass(site, make_state):
    s = make_state([(BYPASS, 80.0), (C, 80.0, 0)])
    site.tick(s, OPEN)
    assert positions(s) == [M, C]
    assert socs(s) == pytest.approx([80 - E_MOVE, 80 - E_IDLE])  # done charging, stuck: idle


def test_charger_leaves_when_bypass_is_empty(site, make_state):
    s = make_state([(C, 80.0, 0), (6, 80.0)])
    site.tick(s, OPEN)
    assert positions(s) == [M, 7]


def test_nobody_enters_an_occupied_merge(site, make_state):
    s = make_state([(BYPASS, 80.0), (C, 80.0, 0), (M, 80.0), (4, 80.0)])
    site.tick(s, OPEN)
    assert positions(s) == [BYPASS, C, M, 5]


def test_closure_blocks_entering_x_only(site, make_state):
    s = make_state([(8, 80.0), (9, 80.0)])
    site.tick(s, CLOSED)  # 9 leaves X (closure only stops entering), 8 waits: X was occupied
    assert positions(s) == [8, 10]
    site.tick(s, CLOSED)  # X empty but closed
    assert positions(s) == [8, 11]
    site.tick(s, OPEN)
    assert positions(s) == [9, 12]


def test_charging_gain_clock_and_cap(site, make_state):
    s = make_state([(C, 50.0, 5)])
    site.tick(s, OPEN)
    assert positions(s) == [C] and s.left.item() == 4
    assert socs(s) == pytest.approx([50 + GAIN])
    s = make_state([(C, 99.5, 3)])
    site.tick(s, OPEN)
    assert socs(s) == [100.0]


def test_full_charge_adds_e_charge_then_leaves(site, make_state):
    s = make_state([(D, 50.0)], charge=True)
    site.tick(s, OPEN)
    assert positions(s) == [C] and s.left.item() == 30
    assert socs(s) == pytest.approx([50 - E_MOVE])
    for _ in range(30):
        site.tick(s, OPEN)
        assert positions(s) == [C]
    assert s.left.item() == 0
    assert socs(s) == pytest.approx([50 - E_MOVE + 40.0], abs=1e-4)
    site.tick(s, OPEN)
    assert positions(s) == [M]


@pytest.mark.parametrize("leave_when_full", [True, False])
def test_a_full_battery_ends_the_charge(make_state, leave_when_full):
    """MODEL §1 step 4: at soc 100 the charger stops (ticks left 0) and the vehicle leaves as
    soon as it can; with ``leave_when_full=false`` it stays for all of its ``T_C`` ticks."""
    site = Site(SiteConfig(leave_when_full=leave_when_full))
    s = make_state([(C, 90.0, 20)])
    for k in range(1, 8):  # 90 + 7 * 4/3 = 99.33: still charging
        site.tick(s, OPEN)
        assert positions(s) == [C] and s.left.item() == 20 - k
    site.tick(s, OPEN)  # tick 8 reaches 100
    assert socs(s) == [100.0]
    assert s.left.item() == (0 if leave_when_full else 12)
    site.tick(s, OPEN)
    if leave_when_full:
        assert positions(s) == [M] and socs(s) == [100.0 - E_MOVE]
    else:  # charging on a full battery: no gain, no loss, the charger stays busy
        assert positions(s) == [C] and socs(s) == [100.0] and s.left.item() == 11


def test_charge_energy_is_kept_when_t_c_changes(make_state):
    site = Site(SiteConfig(t_c=10))
    s = make_state([(C, 40.0, 10)], site=site)
    for _ in range(10):
        site.tick(s, OPEN)
    assert socs(s) == pytest.approx([80.0], abs=1e-4)


def test_pass_goes_to_the_bypass_and_forgets_the_decision(site, make_state):
    s = make_state([(D, 80.0)], charge=False)
    site.tick(s, OPEN)
    assert positions(s) == [BYPASS]


def test_trip_counted_and_decision_needed_on_arrival_at_d(site, make_state):
    s = make_state([(14, 80.0), (5, 80.0)], charge=True)
    out = site.tick(s, OPEN)
    assert positions(s) == [D, 6]
    assert out.arrived.item()
    assert not s.charge.item()  # the newcomer has not decided


def test_no_arrival_while_d_is_occupied(site, make_state):
    s = make_state([(14, 80.0), (D, 80.0, 0), (C, 80.0, 10)], charge=True)
    out = site.tick(s, OPEN)
    assert positions(s) == [14, D, C]
    assert not out.arrived.item()


def test_queue_tick_when_charger_busy(site, make_state):
    s = make_state([(D, 35.0), (C, 60.0, 10)], charge=True)
    out = site.tick(s, OPEN)
    assert out.queue.item()
    assert positions(s) == [D, C]
    assert socs(s)[0] == pytest.approx(35 - E_IDLE)


def test_queue_tick_when_charger_occupied_by_a_finished_vehicle(site, make_state):
    # the finished vehicle cannot leave (bypass has priority): D still cannot enter C
    s = make_state([(D, 35.0), (C, 90.0, 0), (BYPASS, 60.0)], charge=True)
    out = site.tick(s, OPEN)
    assert out.queue.item()


def test_no_queue_tick_when_entering_or_passing(site, make_state):
    s = make_state([(D, 35.0)], charge=True)
    assert not site.tick(s, OPEN).queue.item()
    s = make_state([(D, 35.0), (BYPASS, 70.0), (M, 70.0), (4, 70.0)], charge=False)
    out = site.tick(s, OPEN)
    assert positions(s)[0] == D  # blocked, but it chose to pass: not a queue tick
    assert not out.queue.item()


def test_failure_below_soc_low(site, make_state):
    s = make_state([(5, 30.4), (10, 90.0)])
    out = site.tick(s, OPEN)
    assert out.failed.item()
    s = make_state([(5, 30.6)])
    assert not site.tick(s, OPEN).failed.item()


def test_inactive_sites_do_not_change(site, make_state):
    s = make_state([(5, 80.0), (C, 50.0, 4)], charge=True)
    before = s.clone()
    out = site.tick(s, OPEN, active=torch.tensor([False]))
    for name in ("pos", "soc", "left", "charge", "tick"):
        assert torch.equal(getattr(s, name), getattr(before, name)), name
    assert not (out.arrived | out.queue | out.failed).any()


def test_batch_is_independent_sites(site, make_state):
    a = make_state([(14, 50.0), (3, 70.0), (C, 40.0, 2)])
    b = make_state([(D, 35.0), (C, 60.0, 1), (8, 90.0)], charge=True)
    both = make_state([(14, 50.0), (3, 70.0), (C, 40.0, 2)])
    for name in ("pos", "soc", "left"):
        setattr(both, name, torch.cat([getattr(a, name), getattr(b, name)], dim=1))
    both.charge = torch.tensor([False, True])
    both.tick = torch.zeros(2, dtype=torch.int64)
    closed = torch.tensor([False, True])
    for _ in range(5):
        oa, ob = site.tick(a, closed[:1]), site.tick(b, closed[1:])
        ob_ = site.tick(both, closed)
        assert torch.equal(both.pos, torch.cat([a.pos, b.pos], 1))
        assert torch.allclose(both.soc, torch.cat([a.soc, b.soc], 1))
        assert ob_.queue.tolist() == [oa.queue.item(), ob.queue.item()]


def test_the_kernel_reads_the_sites_tick_rules_through_one_public_method(site):
    """``Site.kernel_constants``: the successor and occupancy-check tables, the geometry and
    the energy the compiled kernel reads, built once per device from the site's own rules."""
    from fleet_torchrl.sim import SiteConfig

    tables, geo, energy = site.kernel_constants()
    n = site.n_nodes
    assert tables.shape == (2, 2 * (n + 1)) and tables.dtype == torch.int64
    succ, check = tables
    assert int(succ[D]) == BYPASS and int(succ[n + 1 + D]) == C  # pass or charge at D
    assert int(check[C]) == (1 << M) | (1 << BYPASS)  # leaving C: merge priority to B
    cfg = SiteConfig()
    assert geo.tolist() == [n + 1, 1 << cfg.closed_node, int(cfg.leave_when_full)]
    assert energy.tolist() == pytest.approx([-cfg.e_idle, -cfg.e_move, cfg.soc_low])
    assert site.kernel_constants()[0] is tables  # built once
