"""The evaluation cache (fleet_torchrl/evaluation/cache.py): a policy's fingerprint follows
what it decides with, a cached evaluation is the evaluation, a damaged entry is recomputed."""

from __future__ import annotations

import json
import logging

import torch

from fleet_torchrl.agents.base import GuardedPolicy
from fleet_torchrl.agents.baselines import HeuristicPolicy, RulePolicy
from fleet_torchrl.agents.imitation import ImitationPolicy
from fleet_torchrl.agents.planner import PlannerPolicy
from fleet_torchrl.evaluation import evaluate_policy
from fleet_torchrl.evaluation.cache import EvalCache, key_of, policy_fingerprint
from fleet_torchrl.sim import SiteConfig


def test_fingerprint_follows_weights_settings_and_classes_not_names():
    torch.manual_seed(0)
    a = ImitationPolicy(3, "partial", 8, 1)
    b = ImitationPolicy(3, "partial", 8, 1)
    b.load_state_dict(a.state_dict())
    b.name = "renamed"
    assert policy_fingerprint(a) == policy_fingerprint(b)
    with torch.no_grad():
        next(b.parameters())[0, 0] += 1e-6  # one weight, one ulp-ish step
    assert policy_fingerprint(a) != policy_fingerprint(b)
    assert policy_fingerprint(RulePolicy()) != policy_fingerprint(HeuristicPolicy())
    assert policy_fingerprint(GuardedPolicy(a)) != policy_fingerprint(a)
    # a planner: its base and its settings both count
    p = PlannerPolicy(HeuristicPolicy(), rollouts=4, horizon=20)
    assert policy_fingerprint(p) == policy_fingerprint(
        PlannerPolicy(HeuristicPolicy(), rollouts=4, horizon=20))
    assert policy_fingerprint(p) != policy_fingerprint(
        PlannerPolicy(HeuristicPolicy(), rollouts=4, horizon=21))
    assert policy_fingerprint(p) != policy_fingerprint(
        PlannerPolicy(RulePolicy(), rollouts=4, horizon=20))


def test_a_cached_evaluation_is_the_evaluation(tmp_path):
    site = SiteConfig()
    pol = HeuristicPolicy()
    cache = EvalCache(tmp_path)
    calls = []

    def run():
        calls.append(1)
        return evaluate_policy(pol, site, 6, 300, 3)

    first = cache.evaluate(pol, site, 6, 300, 3, run, name="heuristic")
    # another name for the same policy, the same site under another name: a hit
    again = cache.evaluate(HeuristicPolicy(), SiteConfig(name="p_c=0.8"), 6, 300, 3, run,
                           name="h2")
    assert len(calls) == 1 and (cache.hits, cache.misses) == (1, 1)
    assert again["records"] == first["records"] and again["trips_mean"] == first["trips_mean"]
    assert again["policy"] == "h2" and again["site"]["name"] == "p_c=0.8"
    fresh = evaluate_policy(pol, site, 6, 300, 3)
    assert fresh["records"] == again["records"]
    # another seed, another site or other ticks: computed
    cache.evaluate(pol, site, 6, 300, 4, lambda: evaluate_policy(pol, site, 6, 300, 4))
    other = SiteConfig(p_c=0.4)
    cache.evaluate(pol, other, 6, 300, 3, lambda: evaluate_policy(pol, other, 6, 300, 3))
    assert cache.misses == 3 and len(list(tmp_path.glob("*/*.json"))) == 3


def test_a_damaged_entry_is_recomputed_with_a_warning(tmp_path, caplog):
    cache = EvalCache(tmp_path)
    parts = ["x", 1]
    assert cache.get_or_compute(parts, lambda: {"v": 1}) == {"v": 1}
    path = cache.path(key_of(*parts))
    path.write_text('{"key": "cut sh')
    with caplog.at_level(logging.WARNING):
        assert cache.get_or_compute(parts, lambda: {"v": 2}) == {"v": 2}
    assert "cannot be used" in caplog.text and json.loads(path.read_text())["value"] == {"v": 2}
    # an entry of another key (copied by hand) is not taken either
    other = cache.path(key_of("y"))
    other.parent.mkdir(parents=True, exist_ok=True)
    other.write_text(path.read_text())
    assert cache.get_or_compute(["y"], lambda: {"v": 3}) == {"v": 3}
    # no folder: no cache
    off = EvalCache(None)
    assert off.get_or_compute(parts, lambda: {"v": 4}) == {"v": 4} and off.misses == 0
