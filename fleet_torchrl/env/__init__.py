"""The decision process (MODEL §2) on top of the simulator: state encodings and the batched
TorchRL environment. Imports ``sim`` and TorchRL, no configuration framework. The schemas
import at once; the rest on first use (:mod:`fleet_torchrl.utils.lazy`)."""

from typing import TYPE_CHECKING

from ..utils.lazy import lazy_exports
from .config import MDPConfig, StateConfig

__getattr__, __dir__ = lazy_exports(__name__, {
    **{n: ".encodings" for n in ("ENCODINGS", "Encoding", "charger_time", "get_encoding")},
    **{n: ".fleet_env" for n in ("FleetChargingEnv", "discount_exponent", "step_ticks")}})

if TYPE_CHECKING:
    from .encodings import ENCODINGS, Encoding, charger_time, get_encoding
    from .fleet_env import FleetChargingEnv, discount_exponent, step_ticks

__all__ = ["ENCODINGS", "Encoding", "FleetChargingEnv", "MDPConfig", "StateConfig",
           "charger_time", "discount_exponent", "get_encoding", "step_ticks"]
