"""The rule and the heuristic decide as documented."""

from __future__ import annotations

import torch

from fleet_torchrl.agents import HeuristicPolicy, RulePolicy


def test_baseline_decisions():
    obs = torch.tensor([[0.40, 0.5, 0.0], [0.41, 0.5, 0.0], [0.55, 0.6, 0.0], [0.55, 0.6, 0.3],
                        [0.55, 0.5, 0.0], [0.65, 0.9, 0.0]])
    assert RulePolicy()(obs).tolist() == [1, 0, 0, 0, 0, 0]
    assert HeuristicPolicy()(obs).tolist() == [1, 1, 1, 0, 0, 0]
    # charge early only while another vehicle is at most 55: the third row's other is at 60
    assert HeuristicPolicy(others_below=55)(obs).tolist() == [1, 1, 0, 0, 0, 0]
    assert HeuristicPolicy(upper=70, others_below=95)(obs).tolist() == [1, 1, 1, 0, 0, 1]
