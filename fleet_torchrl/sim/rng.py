"""Counter-based random numbers: every draw is a pure function of integers.

MODEL §1 asks for *common random numbers*: a site's initial state and its closure draws
must depend only on ``(seed, site index, tick)``, never on what a policy did before.
A stateful generator cannot give that once sites diverge, so every draw here is a hash
of its integer coordinates (a 32-bit xorshift-multiply finaliser from Chris Wellons' hash
prospector, ``[16 21f0aaad 15 735a2d97 15]``, applied once per
coordinate).  Both multipliers are below 2**31, so every product of a 32-bit value with them
stays below 2**63: the arithmetic is exact and identical on every device and in every torch
build (no reliance on signed-overflow wrap-around).
"""

from __future__ import annotations

import torch
from torch import Tensor

M32 = 0xFFFFFFFF
_C1 = 0x21F0AAAD
_C2 = 0x735A2D97

# Stream identifiers keep the independent uses of one coordinate apart.
STREAM_CLOSURE = 1
STREAM_INIT_POS = 2
STREAM_INIT_SOC = 3
STREAM_TRAINING = 4  # derives the environment's seed: training never replays evaluation sites
STREAM_SEARCH = 5  # the sites of each generation of the direct policy search
STREAM_SITE = 6  # the parameters of each site drawn from a site distribution
STREAM_PLANNER = 7  # the futures a rollout planner imagines (never the site's own closures)


def training_seed(seed: int) -> int:
    """The seed the environment uses for training seed ``seed``: a 32-bit hash of it, so the
    training sites are not the evaluation protocol's sites for any small evaluation seed."""
    return int(hash_ints(seed, STREAM_TRAINING))


def _mix(x: Tensor) -> Tensor:
    """Finaliser on 32-bit values held in int64 (products stay below 2**63)."""
    x = x ^ (x >> 16)
    x = (x * _C1) & M32
    x = x ^ (x >> 15)
    x = (x * _C2) & M32
    return x ^ (x >> 15)


def hash_ints(*coords: Tensor | int, device: torch.device | str | None = None) -> Tensor:
    """Hash broadcastable integer coordinates to uniform 32-bit integers (int64 tensor)."""
    h: Tensor | None = None
    for c in coords:
        c = torch.as_tensor(c, dtype=torch.int64, device=device) & M32
        h = _mix(c ^ 0x9E3779B9) if h is None else _mix(((h + 0x9E3779B9) & M32) ^ c)
    assert h is not None, "hash_ints needs at least one coordinate"
    return h


def combine_below(ha: Tensor, hb: Tensor, p: float) -> Tensor:
    """Bernoulli(p) draws from two hashes with one mixing round over their broadcast.

    A ``[T, B]`` block as ``combine_below(hash(tick)[:, None], hash(seed, site)[None, :], p)``
    costs one mix per element instead of one per coordinate; the comparison is on the 32-bit
    integer (``h < p * 2**32``), exact on every device.
    """
    return mix_below(ha, hb, int(round(p * (1 << 32))))


def mix_below(ha: Tensor, hb: Tensor, threshold: Tensor | int) -> Tensor:
    """:func:`combine_below` with an integer threshold, one for all or one per element
    (broadcast): the draw is ``mix(ha ^ hb) < threshold``, so ``threshold = round(p * 2**32)``
    is Bernoulli(p)."""
    return _mix(ha ^ hb) < threshold


def uniform(*coords: Tensor | int, device: torch.device | str | None = None) -> Tensor:
    """Uniform float32 in [0, 1) from integer coordinates (24 random bits, exact in float32)."""
    return (hash_ints(*coords, device=device) >> 8).to(torch.float32) * (1.0 / (1 << 24))
