"""Agents: the policy/learner interface, the baselines, the learners and their registry.

One subpackage per agent (``agents/<agent>/``): its schema (``config.py``, free of torch)
beside its implementation. The schemas (collected in ``agents/config.py``) import at once;
the rest on first use (:mod:`fleet_torchrl.utils.lazy`). docs/ADD_A_POLICY.md adds one."""

from typing import TYPE_CHECKING

from ..utils.lazy import lazy_exports
from .config import AgentConfig

__getattr__, __dir__ = lazy_exports(__name__, {
    **{n: ".base" for n in ("CHARGE", "PASS", "Learner", "Policy", "as_td_module")},
    **{n: ".baselines" for n in ("HeuristicPolicy", "RulePolicy")},
    **{n: ".policy_files" for n in ("POLICY_FILE", "save_policy")},
    **{n: ".registry" for n in ("AGENTS", "AgentSpec", "LearnerContext", "get_agent",
                                "load_policy_file", "register")}})

if TYPE_CHECKING:
    from .base import CHARGE, PASS, Learner, Policy, as_td_module
    from .baselines import HeuristicPolicy, RulePolicy
    from .policy_files import POLICY_FILE, save_policy
    from .registry import AGENTS, AgentSpec, LearnerContext, get_agent, load_policy_file, register

__all__ = ["AGENTS", "CHARGE", "PASS", "POLICY_FILE", "AgentConfig", "AgentSpec",
           "HeuristicPolicy", "Learner", "LearnerContext", "Policy", "RulePolicy",
           "as_td_module", "get_agent", "load_policy_file", "register", "save_policy"]
