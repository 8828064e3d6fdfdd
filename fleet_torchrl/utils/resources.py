"""Memory checked before it is allocated.

Settings that pass their range checks can still ask for more memory than the machine has
(``network.width=65536 network.depth=64``: a terabyte of weights; ``eval.n_sims=1e8``: tens
of gigabytes of per-simulation state and records). Allocating first ends in a traceback
from deep inside torch, or in the kernel's OOM killer taking the process (and perhaps a
neighbour's). So each allocation of a size a user chooses is estimated from the sizes
beforehand (the estimators sit beside the code that allocates) and compared here with what
this machine has available: :func:`check_memory` raises a one-line
:class:`~fleet_torchrl.utils.checks.ConfigError` naming the setting.

The estimates are deliberately rough (within a factor of about two, on the high side): they
exist to refuse what cannot fit, not to pack a machine to its last page.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from .checks import ConfigError


def _read_int(path: str) -> int | None:
    try:
        text = Path(path).read_text().strip()
    except OSError:
        return None
    return int(text) if text.isdigit() else None


def _meminfo_available() -> int | None:
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):  # not on this platform
        return None


def _cgroup_available() -> int | None:
    """What a cgroup memory limit leaves (v2, then v1), or None without a limit."""
    for limit_f, usage_f in (("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory.current"),
                             ("/sys/fs/cgroup/memory/memory.limit_in_bytes",
                              "/sys/fs/cgroup/memory/memory.usage_in_bytes")):
        limit, usage = _read_int(limit_f), _read_int(usage_f)
        if limit is not None and limit < 1 << 60:  # "max" or a huge v1 value: no limit
            return max(0, limit - (usage or 0))
    return None


def available_memory() -> int | None:
    """Bytes this process may still allocate: the machine's available memory
    (``MemAvailable``), or what a cgroup limit leaves if that is less; None where neither
    can be read (then nothing is refused)."""
    found = [m for m in (_meminfo_available(), _cgroup_available()) if m is not None]
    return min(found) if found else None


def gib(nbytes: float) -> str:
    """A byte count for people: ``1.5 GiB``, ``820 MiB``, ``12 TiB``."""
    for unit, size in (("TiB", 1 << 40), ("GiB", 1 << 30), ("MiB", 1 << 20)):
        if nbytes >= size:
            return f"{nbytes / size:.3g} {unit}"
    return f"{nbytes / 1024:.3g} KiB"


def check_memory(setting: str, value: Any, nbytes: float, what: str) -> None:
    """Raise :class:`ConfigError` if ``nbytes`` (an estimate of what ``setting = value``
    makes the run allocate for ``what``) exceeds the memory available here."""
    avail = available_memory()
    if avail is None or nbytes <= avail:
        return
    raise ConfigError(f"{setting}={value} is invalid: {what} would need about {gib(nbytes)} "
                      f"of memory, more than the {gib(avail)} available here; lower it")


__all__ = ["available_memory", "check_memory", "gib"]
