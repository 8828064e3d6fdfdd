"""Range checks for configuration values, free of any configuration framework.

Every schema validates its own fields with these helpers; a failure raises
:class:`ConfigError` with one line naming the field, its value and what is allowed.
"""

from __future__ import annotations

import math
from typing import Any


class ConfigError(ValueError):
    """A configuration value outside its allowed range (message names the field)."""


def _fmt(v: Any) -> str:
    return repr(v) if isinstance(v, str) else f"{v}"


def check_range(path: str, value: Any, lo: float | None = None, hi: float | None = None,
                allowed: str | None = None) -> None:
    """Raise :class:`ConfigError` unless ``lo <= value <= hi`` (and finite)."""
    bad = value is None or (isinstance(value, float) and not math.isfinite(value))
    bad = bad or (lo is not None and value < lo) or (hi is not None and value > hi)
    if bad:
        if allowed is None:
            lo_s = "-inf" if lo is None else _fmt(lo)
            hi_s = "inf" if hi is None else _fmt(hi)
            allowed = f"[{lo_s}, {hi_s}]"
        raise ConfigError(f"{path}={_fmt(value)} is invalid: allowed {allowed}")


def check_choice(path: str, value: Any, choices: tuple[str, ...] | list[str]) -> None:
    if value not in choices:
        raise ConfigError(f"{path}={_fmt(value)} is invalid: allowed one of {', '.join(choices)}")


def check_device(path: str, device: str) -> None:
    """A torch device string that exists on this machine."""
    import torch

    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError):
        raise ConfigError(
            f"{path}={_fmt(device)} is invalid: allowed cpu, cuda, cuda:N, mps") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f"{path}={_fmt(device)} is invalid: CUDA is not available here; use cpu")
    if dev.type not in ("cpu", "cuda", "mps"):
        raise ConfigError(f"{path}={_fmt(device)} is invalid: allowed cpu, cuda, cuda:N, mps")
