"""Atomic file writes and the provenance record every run stores beside its results."""

from __future__ import annotations

import functools
import glob
import hashlib
import json
import os
import platform
import re
import subprocess
import sys
import tempfile
from collections.abc import Callable
from dataclasses import asdict, is_dataclass
from datetime import UTC, datetime
from importlib import metadata
from pathlib import Path
from typing import Any

PROJECT = "fleet_torchrl"
PACKAGES = (PROJECT, "torch", "torchrl", "tensordict", "hydra-core", "omegaconf", "tensorboard",
            "numpy", "scipy")
PACKAGE_DIR = Path(__file__).resolve().parents[1]  # .../fleet_torchrl


class WriteError(OSError):
    """A file that cannot be written, named by its own path (never the temp file's) in one
    line; the commands report it like a bad value."""


def current_umask() -> int:
    """The process's file-creation mask (read from ``/proc/self/status`` where there is
    one: setting and restoring it with ``os.umask`` would race with other threads)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _host_key() -> str:
    """This machine in a temp file's name (8 hex digits of its host name): a writer on
    another machine sharing the file system is never judged by this machine's processes."""
    return hashlib.sha256(platform.node().encode()).hexdigest()[:8]


def temp_prefix(path: str | os.PathLike, pid: int | None = None) -> str:
    """The start of the name of a temp file :func:`atomic_write` writes ``path`` through:
    ``.<name>.<pid>-<host key>.`` (then ``mkstemp``'s random part and ``.tmp``)."""
    return f".{Path(path).name}.{os.getpid() if pid is None else pid}-{_host_key()}."


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OSError):  # another user's process (or no way to tell): alive
        return True
    return True


def remove_stale_temps(folder: str | os.PathLike, name: str | None = None) -> list[Path]:
    """Remove the temp files in ``folder`` (of the target ``name`` only, if given) whose
    writer is gone: written by :func:`atomic_write` in a process of this machine that no
    longer runs (killed mid-write, ``kill -9``). A writer that still runs, one of another
    machine and any other file stay. Returns what was removed."""
    folder = Path(folder)
    key = _host_key()
    pattern = re.compile(r"\.(?P<name>.+)\.(?P<pid>\d+)-(?P<host>[0-9a-f]{8})\.[^.]+\.tmp")
    removed = []
    try:
        entries = list(folder.glob(f".{glob.escape(name) if name else '*'}.*.tmp"))
    except OSError:
        return removed
    for p in entries:
        m = pattern.fullmatch(p.name)
        if m is None or m["host"] != key or (name is not None and m["name"] != name):
            continue
        pid = int(m["pid"])
        if pid == os.getpid() or _alive(pid):
            continue
        try:
            p.unlink()
            removed.append(p)
        except OSError:
            pass
    return removed


def atomic_write(path: str | os.PathLike, write: Callable[[Any], None], mode: str = "w") -> Path:
    """Write via ``write(fileobj)`` to a temp file in the same folder, then rename over ``path``.

    A crash mid-write leaves the previous file intact and no partial file behind; a temp
    file left by a killed writer (``kill -9``: no cleanup runs) carries its process id in
    its name (:func:`temp_prefix`), and the next write of the same target removes it
    (:func:`remove_stale_temps`). The file gets the mode any new file of the user gets
    (``0o666`` less the umask): ``mkstemp`` makes its temp file ``0o600``, which would leave
    results unreadable to the rest of a team sharing a file system. A failure to write
    raises :class:`WriteError` naming ``path``.
    """
    path = Path(path)
    if path.exists() and path.is_dir():
        raise IsADirectoryError(f"cannot write {path}: it is a directory")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        remove_stale_temps(path.parent, path.name)
        fd, tmp = tempfile.mkstemp(prefix=temp_prefix(path), suffix=".tmp", dir=path.parent)
    except OSError as e:
        raise WriteError(f"cannot write {path}: {e.strerror or e}") from None
    try:
        os.fchmod(fd, 0o666 & ~current_umask())
        with os.fdopen(fd, mode) as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as e:
        if os.path.exists(tmp):
            os.unlink(tmp)
        if isinstance(e, OSError) and not isinstance(e, WriteError):
            raise WriteError(f"cannot write {path}: {e.strerror or e}") from None
        raise
    return path


def file_sha256(path: str | os.PathLike) -> str:
    """The SHA-256 of a file's bytes (hex)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def write_json(path: str | os.PathLike, obj: Any) -> Path:
    return atomic_write(path, lambda f: json.dump(to_jsonable(obj), f, indent=2, sort_keys=False))


def write_text(path: str | os.PathLike, text: str) -> Path:
    return atomic_write(path, lambda f: f.write(text))


def csv_text(rows: list[dict[str, Any]], fields: tuple[str, ...]) -> str:
    """Rows (dicts) as CSV text with the given columns."""
    import csv
    import io

    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=fields, lineterminator="\n", extrasaction="ignore")
    w.writeheader()
    w.writerows(rows)
    return buf.getvalue()


def write_csv(path: str | os.PathLike, rows: list[dict[str, Any]], fields: tuple[str, ...]
              ) -> Path:
    """Rows (dicts) as CSV with the given columns, written atomically."""
    return write_text(path, csv_text(rows, fields))


def read_json(path: str | os.PathLike) -> Any:
    """The JSON at ``path``; a missing file raises ``FileNotFoundError``, anything that is no
    JSON this project reads (bad syntax, not UTF-8, nested thousands deep, an integer of
    thousands of digits) ``ValueError`` in one line naming ``path``."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no such result file: {path}")
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise ValueError(f"{path} is not valid JSON ({e.msg} at line {e.lineno})") from None
    except UnicodeDecodeError:
        raise ValueError(f"{path} is not valid JSON (not UTF-8 text)") from None
    except RecursionError:  # thousands of nested [ or {: no file of this project's
        raise ValueError(f"{path} is not valid JSON of this project (nested too deeply)"
                         ) from None
    except ValueError as e:  # an integer of more digits than Python converts
        reason = str(e).split(";")[0].strip() or type(e).__name__
        raise ValueError(f"{path} is not valid JSON of this project ({reason})") from None


def to_jsonable(obj: Any) -> Any:
    if is_dataclass(obj) and not isinstance(obj, type):
        return to_jsonable(asdict(obj))
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if hasattr(obj, "tolist"):  # tensors, numpy
        return obj.tolist()
    try:
        from omegaconf import DictConfig, ListConfig, OmegaConf

        if isinstance(obj, (DictConfig, ListConfig)):
            return OmegaConf.to_container(obj, resolve=True)
    except ImportError:  # pragma: no cover
        pass
    return obj


def _git(args: list[str], cwd: Path) -> str | None:
    r = subprocess.run(["git", *args], cwd=cwd, capture_output=True, text=True, timeout=5)
    return r.stdout.strip() if r.returncode == 0 else None


def is_project_checkout(top: Path, package_dir: Path = PACKAGE_DIR) -> bool:
    """Whether the git work tree ``top`` is this project's checkout holding the code that
    runs: its ``pyproject.toml`` names the project and ``package_dir`` is its package folder.
    An installed package can sit inside some other repository (a virtualenv in a user's own
    project), whose commit says nothing about this code."""
    import tomllib

    try:
        meta = tomllib.loads((top / "pyproject.toml").read_text())
    except (OSError, tomllib.TOMLDecodeError):
        return False
    name = str(meta.get("project", {}).get("name", "")).replace("-", "_").lower()
    return name == PROJECT and (top / PROJECT).resolve() == package_dir.resolve()


@functools.lru_cache(maxsize=8)
def git_commit(package_dir: str | os.PathLike | None = None) -> str | None:
    """The commit of the project's own checkout that holds the running package (with
    ``-dirty`` if its tracked files have changes), or None: the package is installed from a
    wheel, git is missing, or the repository around it is another project's
    (:func:`is_project_checkout`)."""
    pkg = Path(package_dir) if package_dir else PACKAGE_DIR
    try:
        top = _git(["rev-parse", "--show-toplevel"], pkg)
        if top is None or not is_project_checkout(Path(top), pkg):
            return None
        sha = _git(["rev-parse", "HEAD"], pkg)
        if sha is None:
            return None
        dirty = _git(["status", "--porcelain", "--untracked-files=no"], pkg)
        return sha + ("-dirty" if dirty else "")
    except (OSError, subprocess.SubprocessError):
        return None


def project_version() -> str | None:
    """The installed version of this package (its distribution metadata), or None."""
    return package_versions().get(PROJECT)


@functools.lru_cache(maxsize=1)
def _package_versions() -> tuple[tuple[str, str | None], ...]:
    out = []
    for p in PACKAGES:
        try:
            out.append((p, metadata.version(p)))
        except metadata.PackageNotFoundError:
            out.append((p, None))
    return tuple(out)


def package_versions() -> dict[str, str | None]:
    """Versions of the stack (looked up once per process)."""
    return dict(_package_versions())


@functools.lru_cache(maxsize=1)
def cpu_model() -> str | None:
    """The CPU's model name (``/proc/cpuinfo``, else what :mod:`platform` knows), or None."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip() or None
    except (OSError, IndexError):
        pass
    return platform.processor() or None


def machine_info() -> dict[str, Any]:
    """The machine a result was made on: platform, processor, CPU model and count, and what
    decides a CPU's floating-point sums: the vector instructions torch's own kernels use
    (where torch is already imported: looking it up never imports it; and the
    ``ATEN_CPU_CAPABILITY`` asked for) and oneMKL's code branch (``MKL_CBWR``; unset: oneMKL
    picks one per CPU). DQN and imitation training are chaotic: the same seed on a CPU where
    oneMKL takes another branch trains another network (docs/TRAINING.md, "Why DQN runs
    differ across machines")."""
    info: dict[str, Any] = {"platform": platform.platform(), "processor": platform.machine(),
                            "cpu_model": cpu_model(), "cpus": os.cpu_count(),
                            "mkl_cbwr": os.environ.get("MKL_CBWR"),
                            "aten_cpu_capability": os.environ.get("ATEN_CPU_CAPABILITY")}
    torch = sys.modules.get("torch")
    if torch is not None:
        try:
            info["torch_cpu_capability"] = torch.backends.cpu.get_cpu_capability()
        except (AttributeError, RuntimeError):  # an old or partial torch
            pass
    return info


def machine_summary() -> str:
    """:func:`machine_info` in one line, e.g. ``x86_64 (AMD EPYC), 2 CPUs, Linux-...``."""
    m = machine_info()
    model = f" ({m['cpu_model']})" if m["cpu_model"] else ""
    return f"{m['processor']}{model}, {m['cpus']} CPUs, {m['platform']}"


def run_info(config: Any = None, seed: int | None = None) -> dict[str, Any]:
    """Provenance: time, command line, the package's version and its own git commit (None
    outside a checkout of this project), versions, machine, config and seed."""
    info = {
        "created": datetime.now(UTC).isoformat(timespec="seconds"),
        "argv": sys.argv,
        "version": project_version(),
        "git_commit": git_commit(),
        "python": platform.python_version(),
        "packages": package_versions(),
        "machine": machine_info(),
    }
    if seed is not None:
        info["seed"] = seed
    if config is not None:
        info["config"] = to_jsonable(config)
    return info
