"""Output paths checked before the work starts.

A command that computes for minutes and then cannot write its result has wasted those
minutes, and one that fails on a temp file's name (``/proc/.x.csv.l4e4p52p.tmp``) does not
say which setting to change. Every command therefore checks each path it will write before
it starts (:func:`check_output`): a file path must not be a folder, a folder must not be a
file, the nearest folder that exists must be writable, and nothing goes under the kernel's
pseudo file systems (``/proc``, ``/sys``, ``/dev``). The error names the setting.
"""

from __future__ import annotations

import os
from pathlib import Path

from .checks import ConfigError, SetupError

PSEUDO = (Path("/proc"), Path("/sys"), Path("/dev"))  # no results there, whoever runs


def _fmt(setting: str, path: str | os.PathLike) -> str:
    return f"{setting}={os.fspath(path)} is invalid"


def check_output(setting: str, path: str | os.PathLike, kind: str = "file",
                 suffix: str | None = None) -> Path:
    """Raise :class:`ConfigError` (one line naming ``setting``) unless ``path`` can be
    written as a ``kind`` (``"file"`` or ``"dir"``): not under ``/proc``, ``/sys`` or
    ``/dev``; a file path that is no folder (with ``suffix`` if given), a folder path that
    is no file; and the nearest existing folder on the way writable. Returns the path."""
    if kind not in ("file", "dir"):
        raise ValueError(f"kind must be 'file' or 'dir', not {kind!r}")
    p = Path(path)
    if not os.fspath(p):
        raise ConfigError(f"{setting}='' is invalid: allowed a path")
    resolved = Path(os.path.abspath(p))
    try:
        resolved = p.resolve()
    except (OSError, RuntimeError):  # a symlink loop: the checks below report it
        pass
    for root in PSEUDO:
        if resolved == root or root in resolved.parents:
            raise ConfigError(f"{_fmt(setting, path)}: {root} is the kernel's, not a place "
                              "to write files")
    if suffix is not None and p.suffix != suffix:
        raise ConfigError(f"{_fmt(setting, path)}: allowed a path ending in {suffix}")
    if kind == "file" and p.is_dir():
        raise ConfigError(f"{_fmt(setting, path)}: it is a folder; allowed a file path")
    if kind == "dir" and p.exists() and not p.is_dir():
        raise ConfigError(f"{_fmt(setting, path)}: it is a file; allowed a folder")
    folder = p if kind == "dir" else p.parent
    folder = Path(os.path.abspath(folder))
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    if not folder.is_dir():
        raise ConfigError(f"{_fmt(setting, path)}: {folder} is a file, not a folder")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise ConfigError(f"{_fmt(setting, path)}: {folder} is not writable")
    return p


def check_input_dir(setting: str, path: str | os.PathLike) -> Path:
    """Raise :class:`ConfigError` unless ``path`` is an existing folder."""
    p = Path(path)
    if not p.exists():
        raise ConfigError(f"{_fmt(setting, path)}: no such folder")
    if not p.is_dir():
        raise ConfigError(f"{_fmt(setting, path)}: it is a file; allowed a folder")
    return p


LOCK = ".lock"
_HELD: dict[Path, object] = {}  # the folders this process holds, by resolved path


def hold_run_dir(run_dir: str | os.PathLike) -> None:
    """Hold ``run_dir`` for this process: an exclusive advisory lock on ``<run_dir>/.lock``
    that lasts until :func:`release_run_dir` or the end of the process, however it ends. A
    second process training in the same folder, e.g. a training left behind by a killed
    ``make table`` beside the one that resumes it, would write the same checkpoint and
    logs; it stops here instead, naming the process that holds the folder. This process may
    hold a folder again (a run resumed in the same process). Where the file system has no
    locks, or the platform no ``fcntl``, the folder is not held."""
    try:
        import fcntl
    except ImportError:  # not POSIX
        return
    key = Path(run_dir).resolve()
    if key in _HELD:
        return
    f = open(key / LOCK, "a+")  # noqa: SIM115 - held open while the folder is held
    try:
        fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        f.seek(0)
        holder = f.read().strip() or "another process"
        f.close()
        raise SetupError(f"{os.fspath(run_dir)} is in use by {holder}: a run already trains "
                         "there; stop it first, or give this run another folder") from None
    except OSError:  # no locks on this file system
        f.close()
        return
    me = f"process {os.getpid()}\n"
    f.seek(0)
    if f.read() != me:  # a folder this process held before stays untouched
        f.seek(0)
        f.truncate()
        f.write(me)
        f.flush()
    _HELD[key] = f


def release_run_dir(run_dir: str | os.PathLike) -> None:
    """Let go of a folder :func:`hold_run_dir` held (nothing if it holds none)."""
    f = _HELD.pop(Path(run_dir).resolve(), None)
    if f is not None:
        f.close()


__all__ = ["LOCK", "PSEUDO", "check_input_dir", "check_output", "hold_run_dir",
           "release_run_dir"]
