"""The decision process (MODEL §2) on top of the simulator: state encodings and the batched
TorchRL environment. Imports ``sim`` and TorchRL, no configuration framework."""

from .config import MDPConfig, StateConfig
from .encodings import ENCODINGS, Encoding, charger_time, get_encoding
from .fleet_env import FleetChargingEnv, discount_exponent, step_ticks

__all__ = ["ENCODINGS", "Encoding", "FleetChargingEnv", "MDPConfig", "StateConfig",
           "charger_time", "discount_exponent", "get_encoding", "step_ticks"]
