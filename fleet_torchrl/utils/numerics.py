"""CPU floating-point mode for the networks.

A Q-network trained with L2 weight decay ends with weights of dead ReLU units decayed into
the subnormal range (measured: 15 % of one layer of a trained DQN-all network), and x86 CPUs
multiply subnormals about 100x slower than normal numbers: a 500 x 16 -> 64 -> 64 -> 64 -> 2
forward pass took 2 ms instead of 0.14 ms. :func:`flush_denormals` sets the CPU to flush
them to zero (what GPUs do by default). No quantity of the simulator comes near the
subnormal range (soc is 0-100 in steps of 1e-2), so its results do not change.
"""

from __future__ import annotations

import torch


def flush_denormals() -> bool:
    """Flush subnormal floats to zero on this thread's CPU; ``False`` where unsupported."""
    return bool(torch.set_flush_denormal(True))
