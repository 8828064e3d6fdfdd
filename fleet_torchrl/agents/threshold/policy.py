"""Threshold policies on the ``partial`` state (``agent=threshold``), decided in the kernel.

A threshold policy charges the vehicle at ``D`` iff one of three rules holds (socs in
percent, ``TC`` the charger's remaining time as a share of ``T_C + 1``, as in the
``partial`` encoding):

* ``soc_D <= low`` (the rule-based benchmark is this alone, ``low = 40``);
* the charger is free, ``soc_D <= free_upper``, ``soc_D <= others + margin`` (``others``:
  the lowest soc of the vehicles on neither ``D`` nor ``C``) and ``others <= others_below``:
  charge early while the charger idles (the heuristic is ``free_upper = 60``,
  ``margin = 0``);
* the charger is busy but frees soon, ``0 < TC <= busy_tc``, and ``soc_D <= busy_upper``:
  queue for a charger that is about to be free.

A rule that is ``None`` is off. The class contains the rule and the heuristic; its six
numbers are what the direct policy search's ``threshold`` class searches over
(:mod:`fleet_torchrl.agents.search`), and it reads the charger's remaining time, which the
200-cell table does only as free or busy. The kernel of :mod:`fleet_torchrl.sim.kernel`
decides with the same float32 comparisons (:func:`threshold_kernel_policy`), so an
evaluation of a threshold policy runs without one Python iteration per decision.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch
from torch import Tensor

from ...sim.fused import THRESHOLD, KernelPolicy
from ..base import Policy
from .config import ThresholdAgentConfig

# the order of a kernel row (sim/kernel.py: THR_*)
FIELDS = ("low", "free_upper", "margin", "others_below", "busy_tc", "busy_upper")


def threshold_row(low: float, free_upper: float | None = None, margin: float = 0.0,
                  others_below: float | None = None, busy_tc: float | None = None,
                  busy_upper: float | None = None) -> Tensor:
    """The float32 kernel row of a threshold policy: socs / 100 and ``busy_tc`` as the
    features are normalised; an unused rule is a comparison that never (or, for the
    ``others_below`` and ``margin`` conditions, always) holds."""
    inf = math.inf
    row = [low / 100.0,
           -inf if free_upper is None else free_upper / 100.0,
           margin / 100.0,
           inf if others_below is None else others_below / 100.0,
           -1.0 if busy_tc is None else float(busy_tc),
           -inf if busy_upper is None else busy_upper / 100.0]
    return torch.from_numpy(np.asarray(row, dtype=np.float32))


def threshold_kernel_policy(**kw: Any) -> KernelPolicy:
    """A :class:`KernelPolicy` of one threshold policy (see :func:`threshold_row`)."""
    return KernelPolicy(THRESHOLD, thresholds=threshold_row(**kw)[None])


def threshold_actions(rows: Tensor, obs: Tensor) -> Tensor:
    """Actions ``[..., n]`` of threshold rows ``[..., 6]`` (one per leading index, broadcast
    against ``obs [..., n, 3]``): the comparisons the kernel makes, in float32."""
    f0, f1, f2 = obs[..., 0], obs[..., 1], obs[..., 2]
    t = rows.to(obs.dtype)[..., None, :]
    free = (f2 == 0) & (f0 <= t[..., 1]) & (f0 <= f1 + t[..., 2]) & (f1 <= t[..., 3])
    busy = (f2 > 0) & (f2 <= t[..., 4]) & (f0 <= t[..., 5])
    return ((f0 <= t[..., 0]) | free | busy).long()


class ThresholdPolicy(Policy):
    """A threshold policy on the ``partial`` encoding (module docstring); ``theta`` is its
    float32 kernel row, so :meth:`forward` and the kernel compare the same numbers."""

    name = "threshold"
    encoding = "partial"
    map_tc_values = (0.0, 0.2, 0.5, 0.8)

    def __init__(self, low: float = 40.0, free_upper: float | None = None, margin: float = 0.0,
                 others_below: float | None = None, busy_tc: float | None = None,
                 busy_upper: float | None = None) -> None:
        super().__init__()
        self.register_buffer("theta", threshold_row(low, free_upper, margin, others_below,
                                                    busy_tc, busy_upper))

    @classmethod
    def from_config(cls, agent: ThresholdAgentConfig) -> ThresholdPolicy:
        return cls(**{f: getattr(agent, f) for f in FIELDS})

    @classmethod
    def from_row(cls, row: Tensor) -> ThresholdPolicy:
        """The policy of a kernel row (e.g. a member of the search's threshold class)."""
        pol = cls()
        pol.theta.copy_(row.to(torch.float32).reshape(-1))
        return pol

    def settings(self) -> dict[str, float | None]:
        """The six settings in the units of :class:`ThresholdAgentConfig` (``None``: off)."""
        t = self.theta.double().tolist()
        def soc(x: float, off: float) -> float | None:
            return None if x == off else round(100.0 * x, 4)
        return {"low": round(100.0 * t[0], 4), "free_upper": soc(t[1], -math.inf),
                "margin": round(100.0 * t[2], 4), "others_below": soc(t[3], math.inf),
                "busy_tc": None if t[4] < 0 else round(t[4], 6),
                "busy_upper": soc(t[5], -math.inf)}

    def forward(self, obs: Tensor) -> Tensor:
        return threshold_actions(self.theta, obs)

    def kernel_policy(self) -> KernelPolicy:
        return KernelPolicy(THRESHOLD, thresholds=self.theta[None].clone())


__all__ = ["FIELDS", "ThresholdAgentConfig", "ThresholdPolicy", "threshold_actions",
           "threshold_kernel_policy", "threshold_row"]
