"""Output paths checked before the work starts.

A command that computes for minutes and then cannot write its result has wasted those
minutes, and one that fails on a temp file's name (``/proc/.x.csv.l4e4p52p.tmp``) does not
say which setting to change. Every command therefore checks each path it will write before
it starts (:func:`check_output`): a file path must not be a folder, a folder must not be a
file, the nearest folder that exists must be writable, and nothing goes under the kernel's
pseudo file systems (``/proc``, ``/sys``, ``/dev``), no file or folder name is longer than
the file system allows (the run folder would be made first, then the write fail). The error
names the setting.

Names that become parts of paths (``site.name``, recipe and sweep names) are names, never
paths (:func:`check_name`): one component, so that what is computed from them stays inside
the folder it is computed under. A computed path that still leads out of its root, through a
symbolic link, is refused unless the user allows it (:func:`check_inside`).
"""

from __future__ import annotations

import os
import re
from pathlib import Path

from .checks import ConfigError, SetupError

PSEUDO = (Path("/proc"), Path("/sys"), Path("/dev"))  # no results there, whoever runs

# a name that becomes a path part: one component, no hidden or parent folder, short enough
# that the folder names made of it (``<agent>_<state>_<site>``, ``train_<recipe>_seed<s>``)
# stay far below the file system's limit on a name (255 bytes)
NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]*")
NAME_MAX = 64
NAME_RULE = (f"a name of letters, digits, '_', '.' and '-', starting with a letter or digit, "
             f"without '..', at most {NAME_MAX} characters")
NAME_MAX_BYTES = 255  # a file or folder name, where the file system does not say
PATH_MAX_BYTES = 4096  # a whole path, likewise
# what a temporary file beside a result adds to its name (runinfo.write_json: ``.<name>.``,
# 8 random characters, ``.tmp``)
TMP_EXTRA = 14


def is_name(value: object, pattern: re.Pattern[str] = NAME) -> bool:
    """Whether ``value`` is a string :func:`check_name` accepts."""
    return isinstance(value, str) and len(value) <= NAME_MAX and ".." not in value and \
        pattern.fullmatch(value) is not None


def check_name(setting: str, value: object, pattern: re.Pattern[str] = NAME,
               rule: str = NAME_RULE) -> str:
    """Raise :class:`ConfigError` (one line naming ``setting`` and :data:`NAME_RULE`) unless
    ``value`` is a name that can become one part of a path: never ``/``, ``..`` or a hidden
    name, never longer than :data:`NAME_MAX` characters. Returns the name."""
    if not is_name(value, pattern):
        shown = repr(value) if not isinstance(value, str) or len(value) <= 80 else \
            repr(value[:40] + "...") + f" ({len(value)} characters)"
        raise ConfigError(f"{setting}={shown} is invalid: allowed {rule}")
    return value  # type: ignore[return-value]


# a display name that may still become one part of a path (a site's name in the Python API:
# ``p_c=0.5``, ``sweep point``): never a separator, a control character, '..' or hidden
LABEL = re.compile(r"[^./\\\x00-\x1f\x7f][^/\\\x00-\x1f\x7f]*")
LABEL_RULE = (f"a name without '/', '\\', '..' or control characters, not starting with '.', "
              f"at most {NAME_MAX} characters")


def check_label(setting: str, value: object) -> str:
    """:func:`check_name` with :data:`LABEL`'s wider rule (spaces and ``=`` allowed)."""
    return check_name(setting, value, LABEL, LABEL_RULE)


def _limit(folder: Path, name: str, default: int) -> int:
    """The file system's limit ``name`` (``PC_NAME_MAX``, ``PC_PATH_MAX``) at ``folder``."""
    try:
        return int(os.pathconf(folder, name))
    except (OSError, ValueError, AttributeError):  # not known here, or not POSIX
        return default


def _check_lengths(setting: str, path: str | os.PathLike, kind: str) -> None:
    """Raise :class:`ConfigError` if a name in ``path`` (or the whole path) is longer than
    the file system takes; a file's own name also leaves room for its temporary file."""
    absolute = os.path.abspath(os.fspath(path))
    folder = Path(absolute)
    while folder != folder.parent:  # the nearest folder that exists, without a stat that fails
        try:
            if folder.is_dir():
                break
        except OSError:
            pass
        folder = folder.parent
    name_max = _limit(folder, "PC_NAME_MAX", NAME_MAX_BYTES)
    parts = Path(os.fspath(path)).parts
    for k, part in enumerate(parts):
        room = name_max - (TMP_EXTRA if kind == "file" and k == len(parts) - 1 else 0)
        size = len(os.fsencode(part))
        if size > room and part != os.sep:
            shown = part if len(part) <= 40 else part[:40] + "..."
            what = "file name" if kind == "file" and k == len(parts) - 1 else "folder name"
            raise ConfigError(f"{setting}: the {what} {shown!r} is {size} bytes long: allowed "
                              f"at most {room} bytes (the file system's limit is {name_max})")
    path_max = _limit(folder, "PC_PATH_MAX", PATH_MAX_BYTES)
    size = len(os.fsencode(absolute)) + (TMP_EXTRA if kind == "file" else NAME_MAX_BYTES)
    if size > path_max:
        raise ConfigError(f"{setting}: the path is {len(os.fsencode(absolute))} bytes long: "
                          f"allowed a shorter one (the file system's limit is {path_max}, "
                          "files inside included)")


def check_inside(setting: str, path: str | os.PathLike, root: str | os.PathLike,
                 allow: str | None = None) -> Path:
    """``path``, computed under ``root`` from names, if it resolves inside ``root``; else
    raise :class:`ConfigError` (one line): a symbolic link on the way leads out of ``root``.
    ``allow`` says how the user lets it be followed (e.g. ``table.follow_symlinks=true``)."""
    p, top = Path(path), Path(root)
    try:
        resolved, home = p.resolve(), top.resolve()
    except (OSError, RuntimeError) as e:  # a symlink loop
        raise ConfigError(f"{setting}: {os.fspath(p)} cannot be resolved: {e}") from None
    if resolved == home or home in resolved.parents:
        return p
    how = f"; to follow it, {allow}" if allow else ""
    raise ConfigError(f"{setting}: {os.fspath(p)} leads to {resolved}, outside "
                      f"{os.fspath(top)}, and is not followed{how}")


def _fmt(setting: str, path: str | os.PathLike) -> str:
    return f"{setting}={os.fspath(path)} is invalid"


def check_output(setting: str, path: str | os.PathLike, kind: str = "file",
                 suffix: str | None = None) -> Path:
    """Raise :class:`ConfigError` (one line naming ``setting``) unless ``path`` can be
    written as a ``kind`` (``"file"`` or ``"dir"``): not empty, no name in it longer than
    the file system takes (a file's with room for its temporary file), not under ``/proc``,
    ``/sys`` or ``/dev``; a file path that is no folder (with ``suffix`` if given), a folder
    path that is no file; and the nearest existing folder on the way writable. Returns the
    path."""
    if kind not in ("file", "dir"):
        raise ValueError(f"kind must be 'file' or 'dir', not {kind!r}")
    if not os.fspath(path):  # Path("") would be "." (Hydra's run folder: the working one)
        raise ConfigError(f"{setting}='' is invalid: allowed a path")
    p = Path(path)
    _check_lengths(setting, p, kind)
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


def _in_use(run_dir: str | os.PathLike, holder: str) -> SetupError:
    """The one-line refusal of a folder another process holds (``holder``: what its lock
    file says, e.g. ``process 1234``)."""
    return SetupError(f"{os.fspath(run_dir)} is in use by {holder or 'another process'}: a run "
                      "already trains there; stop it first, or give this run another folder")


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
        holder = f.read().strip()
        f.close()
        raise _in_use(run_dir, holder) from None
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


def check_not_held(run_dir: str | os.PathLike) -> None:
    """Raise :class:`SetupError` if another process holds ``run_dir``
    (:func:`hold_run_dir`), without taking or creating anything: a multirun's job holds its
    folder only in its own process, after Hydra has written ``.hydra/`` there, so the
    launching command asks first whether a job's folder is in use."""
    try:
        import fcntl
    except ImportError:  # not POSIX
        return
    key = Path(run_dir).resolve() / LOCK
    if Path(run_dir).resolve() in _HELD or not key.is_file():
        return
    try:
        f = open(key)  # noqa: SIM115 - closed below
    except OSError:
        return
    try:
        fcntl.flock(f.fileno(), fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        raise _in_use(run_dir, f.read().strip()) from None
    except OSError:  # no locks on this file system
        pass
    finally:
        f.close()


def release_run_dir(run_dir: str | os.PathLike) -> None:
    """Let go of a folder :func:`hold_run_dir` held (nothing if it holds none)."""
    f = _HELD.pop(Path(run_dir).resolve(), None)
    if f is not None:
        f.close()


__all__ = ["LABEL", "LABEL_RULE", "LOCK", "NAME", "NAME_MAX", "NAME_RULE", "PSEUDO",
           "check_input_dir", "check_inside", "check_label", "check_name", "check_not_held",
           "check_output", "hold_run_dir", "is_name", "release_run_dir"]
