"""Agents: the policy/learner interface, the baselines, the learners and their registry."""

from .base import CHARGE, PASS, AgentConfig, Learner, Policy, as_td_module
from .baselines import HeuristicPolicy, RulePolicy
from .policy_files import POLICY_FILE, save_policy
from .registry import AGENTS, AgentSpec, LearnerContext, get_agent, load_policy_file, register

__all__ = ["AGENTS", "CHARGE", "PASS", "POLICY_FILE", "AgentConfig", "AgentSpec",
           "HeuristicPolicy", "Learner", "LearnerContext", "Policy", "RulePolicy",
           "as_td_module", "get_agent", "load_policy_file", "register", "save_policy"]
