"""Agents: the policy/learner interface, the baselines, the learners and their registry."""

from .base import CHARGE, PASS, AgentConfig, Learner, Policy, as_td_module
from .baselines import HeuristicPolicy, RulePolicy
from .policy_files import POLICY_FILE, save_policy
from .registry import (
    AGENTS,
    AgentSpec,
    default_policy_dir,
    get_agent,
    load_policies,
    load_policy_file,
    make_policy,
    register,
)

__all__ = ["AGENTS", "CHARGE", "PASS", "POLICY_FILE", "AgentConfig", "AgentSpec",
           "HeuristicPolicy", "Learner", "Policy", "RulePolicy", "as_td_module",
           "default_policy_dir", "get_agent", "load_policies", "load_policy_file",
           "make_policy", "register", "save_policy"]
