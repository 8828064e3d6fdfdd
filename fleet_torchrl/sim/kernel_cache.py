"""The on-disk cache of the compiled kernel (:mod:`fleet_torchrl.sim.kernel`), and the one way
to run a CPU kernel (:func:`call`): numba caches every compiled function beside
``kernel.py`` (``__pycache__``, or ``NUMBA_CACHE_DIR``) and checks a cached kernel's source
stamp, not its bytes. A damaged file either fails to load or, a flipped byte in the machine
code, loads and runs. So this module keeps a manifest of the SHA-256 of each cached data file
(``.nbc``, written once per compiled signature) beside them, checks it before the first
kernel call of a process and rebuilds the cache when a file differs or cannot be loaded.
"""

from __future__ import annotations

from . import kernel as _kernel

CACHED = (*_kernel.DEVICE_FUNCTIONS, "advance_parallel", "advance_serial", "partial_features")
MANIFEST = "fleet_torchrl_kernel.sha256.json"
_called: set[str] = set()  # the kernels that have run in this process
_verified: list[bool] = []  # the manifest was checked in this process


def _log():
    import logging

    return logging.getLogger(__name__)


def cache_dir():
    """The folder numba caches the kernel module's functions in (None if caching is off)."""
    from pathlib import Path

    try:
        return Path(_kernel.advance_serial._cache._cache_path)
    except AttributeError:
        return None


def _cache_files(folder) -> dict[str, str]:
    """SHA-256 of every data file (``.nbc``) of the kernel module's functions in ``folder``."""
    import hashlib

    out = {}
    for f in sorted(folder.glob("kernel.*.nbc")):
        try:
            out[f.name] = hashlib.sha256(f.read_bytes()).hexdigest()
        except OSError:
            continue
    return out


def write_manifest() -> None:
    """Record the hash of every cached kernel file (after a kernel ran from them)."""
    import json
    import os

    folder = cache_dir()
    if folder is None or not folder.is_dir():
        return
    tmp = folder / f".{MANIFEST}.{os.getpid()}.tmp"
    try:
        tmp.write_text(json.dumps(_cache_files(folder), indent=0, sort_keys=True))
        os.replace(tmp, folder / MANIFEST)
    except OSError:  # a read-only cache: nothing recorded, nothing to check later
        tmp.unlink(missing_ok=True)


def verify_cache() -> bool:
    """Check the cached kernel files against the manifest; on a mismatch clear the cache (it
    is compiled afresh) with a one-line warning. Returns whether the cache was intact (or
    had no manifest). Files the manifest does not list (another process compiled a new
    signature since) are not judged."""
    import json

    folder = cache_dir()
    if folder is None or not (folder / MANIFEST).is_file():
        return True
    try:
        want = json.loads((folder / MANIFEST).read_text())
        if not isinstance(want, dict):
            raise ValueError("not a manifest")
    except (OSError, ValueError):
        bad = [MANIFEST]
    else:
        have = _cache_files(folder)
        bad = [name for name, digest in want.items() if name in have and have[name] != digest]
    if not bad:
        return True
    _log().warning("the compiled kernel's cache failed its hash check (%s in %s): cleared, "
                   "compiling the kernel again", bad[0], folder)
    clear_cache()
    try:
        (folder / MANIFEST).unlink()
    except OSError:
        pass
    return False


def clear_cache() -> None:
    """Empty the on-disk cache of this module's compiled functions (each index rewritten
    empty, so nothing stale or damaged is read again; the next call compiles and caches
    afresh). A cache that cannot be written is switched off for this process."""
    from numba.core.caching import NullCache

    for name in CACHED:
        disp = getattr(_kernel, name)
        try:
            disp._cache.flush()
        except (OSError, AttributeError):
            disp._cache = NullCache()


def call(name: str, *args) -> None:
    """Run the CPU kernel ``name`` (``advance_parallel``, ``advance_serial``). Its first call
    in a process checks the on-disk cache's hashes (:func:`verify_cache`), then loads the
    kernel from it (or compiles it); a damaged cache file that fails that load would fail
    every later run too. So a first call that fails clears the cache, says so in one warning
    line and compiles again; if that fails as well, a
    :class:`~fleet_torchrl.utils.checks.SetupError` says which backend to use instead."""
    kernel = getattr(_kernel, name)
    if name in _called:
        kernel(*args)
        return
    if not _verified:
        _verified.append(verify_cache())
    try:
        kernel(*args)
    except Exception as first:  # noqa: BLE001 (a cache that cannot be loaded: rebuild it)
        from ..utils.checks import SetupError, exception_line

        _log().warning("the compiled kernel's cache could not be loaded (%s): cleared, "
                       "compiling the kernel again", exception_line(first))
        clear_cache()
        try:
            kernel(*args)
        except Exception as e:  # noqa: BLE001
            raise SetupError(f"the compiled kernel cannot be built here ({exception_line(e)}); "
                             "use the eager backend "
                             "(eval.backend=eager, FleetChargingEnv(fused=False))") from None
    _called.add(name)
    write_manifest()


__all__ = ["CACHED", "MANIFEST", "cache_dir", "call", "clear_cache", "verify_cache",
           "write_manifest"]
