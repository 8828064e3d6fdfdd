"""Deferral to the heuristic (``train.defer``): the decision rule, its policy files, the
validation points, the calibration of the margin, the fingerprints and a training run."""

from __future__ import annotations

import pytest
import torch

from fleet_torchrl.agents import load_policy_file, save_policy
from fleet_torchrl.agents.baselines import HeuristicPolicy
from fleet_torchrl.agents.imitation import ImitationPolicy, defer_to_heuristic
from fleet_torchrl.config import compose_config
from fleet_torchrl.sim import SiteConfig, SiteRanges
from fleet_torchrl.training.deferral import calibrate_deferral, validation_points
from fleet_torchrl.utils.checks import ConfigError


def constant_logit(value: float, n_obs: int = 3, encoding: str = "partial") -> ImitationPolicy:
    """A student whose logit is ``value`` on every state."""
    pol = ImitationPolicy(n_obs, encoding, hidden=4, depth=1)
    for p in pol.parameters():
        p.data.zero_()
    last = [m for m in pol.net.modules() if isinstance(m, torch.nn.Linear)][-1]
    last.bias.data.fill_(value)
    return pol


def partial_obs(n: int = 4000) -> torch.Tensor:
    g = torch.Generator().manual_seed(0)
    obs = torch.rand(n, 3, generator=g)
    obs[:, 2] = (torch.rand(n, generator=g) < 0.5).float()  # the charger free or busy
    return obs


def test_the_heuristic_decides_where_the_logit_is_within_the_margin():
    obs = partial_obs()
    h = HeuristicPolicy()(obs)
    assert 0 < int(h.sum()) < len(h)  # both actions occur
    assert torch.equal(_with_margin(constant_logit(0.4), 0.5)(obs), h)  # unsure: heuristic
    assert _with_margin(constant_logit(0.6), 0.5)(obs).eq(1).all()  # sure: charge
    assert _with_margin(constant_logit(-0.6), 0.5)(obs).eq(0).all()  # sure: pass
    assert _with_margin(constant_logit(-0.5), 0.5)(obs).equal(h)  # the bounds defer
    assert constant_logit(0.0)(obs).eq(0).all()  # no margin: a zero logit passes
    # per state: the rule of defer_to_heuristic
    logit = torch.linspace(-1, 1, len(obs))
    act = defer_to_heuristic(logit, obs, 0.3)
    assert torch.equal(act[logit > 0.3], torch.ones_like(act[logit > 0.3]))
    assert torch.equal(act[logit < -0.3], torch.zeros_like(act[logit < -0.3]))
    mid = logit.abs() <= 0.3
    assert torch.equal(act[mid], h[mid])


def _with_margin(pol: ImitationPolicy, m: float) -> ImitationPolicy:
    pol.set_defer_margin(m)
    return pol


def test_a_policy_file_keeps_its_margin_and_older_files_have_none(tmp_path):
    pol = _with_margin(constant_logit(0.2, 6, "partial_site"), 0.3)
    save_policy(tmp_path / "policy.pt", pol, "imitation")
    back = load_policy_file(tmp_path)
    assert back.defer_margin == 0.3 and back.policy_spec()["defer_margin"] == 0.3
    obs = torch.rand(100, 6)
    assert torch.equal(back(obs), HeuristicPolicy()(obs[:, :3]))
    plain = constant_logit(0.2)
    assert "defer_margin" not in plain.policy_spec()  # files without it: the network alone
    assert ImitationPolicy.from_policy_spec(plain.policy_spec()).defer_margin == 0.0


@pytest.mark.parametrize("margin, encoding, match", [
    (-0.1, "partial", "allowed a number >= 0"),
    (float("nan"), "partial", "allowed a number >= 0"),
    (0.2, "all", "needs an encoding that starts with the partial state's features"),
])
def test_bad_margins_are_refused(margin, encoding, match):
    with pytest.raises(ValueError, match=match):
        ImitationPolicy(3 if encoding == "partial" else 15, encoding, 4, 1, defer_margin=margin)


def test_validation_points_vary_one_drawn_parameter_at_a_time():
    dist = compose_config(["site=randomized"]).site
    pts = validation_points(dist, 5)
    assert [n for n, _ in pts] == [
        "n_vehicles=1", "n_vehicles=2", "n_vehicles=3", "n_vehicles=4", "n_vehicles=5",
        "p_c=0", "p_c=0.225", "p_c=0.45", "p_c=0.675", "p_c=0.9",
        "t_c=10", "t_c=20", "t_c=30", "t_c=40", "t_c=50"]
    for name, s in pts:
        assert s.ranges is None and not s.randomized
        others = {k: getattr(s, k) for k in ("n_vehicles", "p_c", "t_c")
                  if not name.startswith(k)}
        assert others == {k: getattr(dist, k) for k in others}  # the site's own values
    few = SiteConfig(ranges=SiteRanges(n_vehicles=[1, 2]))
    assert [n for n, _ in validation_points(few, 5)] == ["n_vehicles=1", "n_vehicles=2"]
    one = SiteConfig(t_c=20)
    assert validation_points(one, 5) == [("default", one)]


SMALL = dict(sims=12, ticks=600, seed=5, points=2)


def test_the_calibration_takes_the_smallest_margin_not_below_the_heuristic():
    """Always charging (logit +5) is far below the heuristic; a margin above 5 is the
    heuristic itself (equal on every site: not below)."""
    site = SiteConfig()
    rec = calibrate_deferral(constant_logit(5.0), site, [1.0, 10.0, 20.0], **SMALL)
    assert rec["margin"] == 10.0 and rec["clear"]
    assert [c["margin"] for c in rec["candidates"]] == [0.0, 1.0, 10.0]  # stops at the first
    assert rec["candidates"][0]["below"] == ["default"] == rec["candidates"][1]["below"]
    assert rec["candidates"][2]["below"] == []
    assert rec["candidates"][2]["mean_gain_vs_heuristic_pct"] == pytest.approx(0.0)
    assert rec["candidates"][0]["mean_gain_vs_heuristic_pct"] < -1.0
    # the policy given is left as it was
    pol = constant_logit(5.0)
    calibrate_deferral(pol, site, [10.0], **SMALL)
    assert pol.defer_margin == 0.0


def test_without_a_clear_margin_the_least_below_one_is_kept_and_reported():
    dist = SiteConfig(ranges=SiteRanges(n_vehicles=[1, 5]))
    rec = calibrate_deferral(constant_logit(5.0), dist, [1.0, 2.0], **SMALL)
    assert not rec["clear"] and rec["margin"] == 0.0  # a tie in points below: the smaller
    assert all(c["below"] for c in rec["candidates"])
    assert rec["points"] == ["n_vehicles=1", "n_vehicles=5"]


def test_the_deferral_settings_are_outside_the_training_fingerprint():
    from fleet_torchrl.training import result_fingerprint, training_fingerprint
    from fleet_torchrl.training.checkpoint import fingerprint_diff

    base = ["agent=imitation", "state=partial_site"]
    plain, deferring = compose_config(base), compose_config([*base, "train.defer=heuristic"])
    assert training_fingerprint(plain) == training_fingerprint(deferring)
    assert result_fingerprint(plain) == training_fingerprint(plain)  # neutral: saved runs
    diff = fingerprint_diff(result_fingerprint(plain), result_fingerprint(deferring))
    assert diff and all(d.startswith("deferral") for d in diff)
    other = compose_config([*base, "train.defer=heuristic", "train.defer_margins=[0.5]"])
    assert result_fingerprint(other) != result_fingerprint(deferring)


@pytest.mark.parametrize("overrides, field", [
    (["agent=dqn", "train.defer=heuristic"], "train.defer="),
    (["agent=imitation", "state=all", "train.defer=heuristic"], "train.defer="),
    (["agent=imitation", "train.defer=sometimes"], "train.defer="),
    (["agent=imitation", "train.defer_margins=[0]"], "train.defer_margins[0]="),
    (["agent=imitation", "train.defer_margins=[]"], "train.defer_margins="),
    (["agent=imitation", "train.defer_points=1"], "train.defer_points="),
    (["agent=imitation", "train.defer_sims=1"], "train.defer_sims="),
])
def test_bad_deferral_settings_are_one_line_config_errors(overrides, field):
    with pytest.raises(ConfigError) as e:
        compose_config(overrides)
    msg = str(e.value)
    assert msg.startswith(field) and "allowed" in msg and "\n" not in msg, msg


TINY = ["agent=imitation", "site.n_vehicles=5", "agent.num_sites=16", "agent.steps_per_round=6",
        "agent.rounds=2", "agent.beta_rounds=1", "agent.hidden=16", "agent.updates_per_round=20",
        "agent.batch_size=32", "agent.expert.rollouts=4", "agent.expert.horizon=40",
        "train.eval_every=1", "train.eval_sims=16", "train.eval_ticks=500",
        "train.progress=false", "train.tensorboard=false", "mdp.tau_e=400",
        "train.defer=heuristic", "train.defer_sims=8", "train.defer_ticks=400"]


def _train(overrides, tmp, resume=False):
    from fleet_torchrl.training import RunSpec, Trainer

    cfg = compose_config([*overrides, f"train.out_dir={tmp}/policy",
                          f"resume={str(resume).lower()}"])
    tr = Trainer(RunSpec.of(cfg), tmp, resume=cfg.resume)
    return cfg, tr, tr.run()


def test_a_run_publishes_its_calibrated_margin_and_resumes_to_recalibrate(tmp_path):
    """The published policy carries the margin its summary records; the finished run resumed
    under other deferral settings trains nothing, calibrates again and publishes the same
    weights with the new margin; the table reuses a policy only under its own settings."""
    from fleet_torchrl.experiments.table import reusable

    cfg, tr, s = _train([*TINY, "train.defer_margins=[0.5,100]"], tmp_path)
    rec = s["deferral"]
    assert rec["margin"] in (0.0, 0.5, 100.0) and rec["points"] == ["default"]
    pol = load_policy_file(tmp_path / "policy")
    assert pol.defer_margin == rec["margin"]
    assert s["fingerprint"]["deferral"]["defer_margins"] == [0.5, 100.0]
    assert reusable(tmp_path / "policy", cfg)
    # other candidates: a margin that leaves every decision to the heuristic, or none
    cfg2, tr2, s2 = _train([*TINY, "train.defer_margins=[100]"], tmp_path, resume=True)
    assert s2["resumed"] and s2["rounds"] == s["rounds"] == 2
    assert [h["trips"] for h in s2["history"]] == [h["trips"] for h in s["history"]]
    pol2 = load_policy_file(tmp_path / "policy")
    assert pol2.defer_margin == s2["deferral"]["margin"] in (0.0, 100.0)
    for a, b in zip(pol.state_dict().values(), pol2.state_dict().values(), strict=True):
        assert torch.equal(a, b)  # the same snapshot
    assert reusable(tmp_path / "policy", cfg2) and not reusable(tmp_path / "policy", cfg)
