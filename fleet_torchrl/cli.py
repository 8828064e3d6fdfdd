"""What every command shares: one convention, Hydra overrides, for all of them.

Every command (``fleet-train``, ``fleet-evaluate``, ..., ``python -m fleet_torchrl.<command>``)
is a Hydra app, so all of them take ``key=value`` overrides, list their options with
``--help``, print their config with ``--cfg job`` and complete on TAB once Hydra's completion
is installed for them (``eval "$(fleet-train -sc install=bash)"``). Hydra's completion needs
one executable per app (it asks the executable itself, ``fleet-train -sc query=...``): hence
one console script per command rather than one ``fleet`` with subcommands.

:func:`hydra_command` makes the entry point of a command from its Hydra task function. Hydra
composes the config once; the task validates it once (``to_config``). What would otherwise end
in a traceback or in Hydra's many-line report ends in one line ``error: ...`` and exit code 2:

* a bad value or an unknown key (:class:`~fleet_torchrl.utils.checks.ConfigError`, raised by
  the task's validation inside :func:`~fleet_torchrl.utils.cli.user_errors`);
* an unknown option, a value of the wrong type, a malformed override (Hydra and OmegaConf
  errors raised while composing, before any job runs);
* a launcher plugin or an optional extra that is not installed, with the line that installs
  it (``hydra/launcher=ray`` without the ray extra, ``hydra/launcher=slurm`` without the
  cluster extra, Gymnasium without the gym extra).

Errors raised inside a job keep their traceback: they are the program's, not the user's.
Commands import their heavy packages (torch, TorchRL) inside the task, so ``--help`` and tab
completion answer in well under a second (docs/BENCHMARKS.md).
"""

from __future__ import annotations

import os
import re
import sys
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from typing import Any

from .config import (
    GROUPS,
    Config,
    mark_multirun,
    one_line,
    register_configs,
    to_config,
    without_hydra,
)

# launcher options (hydra/launcher=...) and the extra of pyproject.toml that provides them
LAUNCHER_EXTRAS = {"ray": "ray", "ray_aws": "ray", "ray_cluster": "ray",
                   "submitit_local": "cluster", "submitit_slurm": "cluster", "slurm": "cluster"}
# modules an extra provides
MODULE_EXTRAS = {"ray": "ray", "hydra_plugins.hydra_ray_launcher": "ray",
                 "submitit": "cluster", "hydra_plugins.hydra_submitit_launcher": "cluster",
                 "gymnasium": "gym", "stable_baselines3": "gym"}


def install_line(extra: str) -> str:
    """How to install an optional extra, for a user of the package and in a checkout."""
    return (f"pip install 'fleet_torchrl[{extra}]' (in a checkout: pip install -e '.[{extra}]',"
            f" or make install EXTRAS=dev,cluster,gym,{extra})" if extra == "ray" else
            f"pip install 'fleet_torchrl[{extra}]' (in a checkout: pip install -e '.[{extra}]')")


def missing_extra(exc: BaseException) -> str | None:
    """The one-line message for an error that a missing launcher plugin or extra causes, or
    None: Hydra cannot find the config of a launcher an extra provides, or a module of an
    extra cannot be imported."""
    if isinstance(exc, ModuleNotFoundError) and exc.name:
        for module, extra in MODULE_EXTRAS.items():
            if exc.name == module or exc.name.startswith(module + "."):
                return f"{exc.name} is not installed: it is in the {extra} extra: " \
                       f"{install_line(extra)}"
        return None
    text = f"{exc} {exc.__cause__ or ''}"
    m = re.search(r"hydra/launcher/([A-Za-z0-9_]+)", text)
    if m and ("Could not find" in text or "Could not load" in text):
        for name in (m.group(1), *re.findall(r"hydra/launcher=([A-Za-z0-9_]+)", " ".join(
                sys.argv[1:]))):
            extra = LAUNCHER_EXTRAS.get(name)
            if extra is not None:
                return (f"hydra/launcher={name} needs its Hydra launcher plugin, in the "
                        f"{extra} extra: {install_line(extra)}")
    for module, extra in MODULE_EXTRAS.items():
        if f"No module named '{module.split('.')[0]}" in text:
            return f"{module} is not installed: it is in the {extra} extra: " \
                   f"{install_line(extra)}"
    return None


def raised_in_a_job(exc: BaseException) -> bool:
    """Whether ``exc`` comes from a job (its traceback passes Hydra's ``run_job``), not from
    composing the config or parsing the command line."""
    tb = exc.__traceback__
    while tb is not None:
        if tb.tb_frame.f_code.co_name == "run_job":
            return True
        tb = tb.tb_next
    return False


# what to pick for a setting that is null unless an option sets it
NULL_HINTS = {"site.ranges": "site=randomized (a site distribution), then override its fields"}


def override_error(exc: BaseException) -> str | None:
    """The one-line message for an override OmegaConf fails on with an internal error
    (``AssertionError``, ``AttributeError``) while Hydra applies it: one that sets a field
    below, or a value into, a structured setting that is null in this config
    (``site.ranges.t_c=[20,40]`` without ``site=randomized``); None for anything else."""
    tb, line = exc.__traceback__, None
    while tb is not None:
        if tb.tb_frame.f_code.co_name == "_apply_overrides_to_config":
            override = tb.tb_frame.f_locals.get("override")
            line = getattr(override, "input_line", None)
        tb = tb.tb_next
    if line is None:
        return None
    key = line.split("=", 1)[0].lstrip("+~")
    parts = key.split(".")
    null = next((".".join(parts[:k]) for k in range(1, len(parts) + 1)
                 if ".".join(parts[:k]) in NULL_HINTS), ".".join(parts[:-1]) or key)
    hint = NULL_HINTS.get(null, "an option of its group that sets it")
    return f"{line} cannot be applied: {null} is null in this config; choose {hint}"


def name_too_long(exc: OSError) -> str | None:
    """The one-line message for a name of the command line longer than a file name may be
    (Hydra looks ``<key>=...`` up as a config file of ``conf/``); None for another error."""
    import errno

    if exc.errno != errno.ENAMETOOLONG:
        return None
    name = os.path.basename(os.fsdecode(exc.filename or "")) or "a name"
    shown = name if len(name) <= 40 else f"{name[:40]}..."
    return (f"{shown!r} ({len(os.fsencode(name))} bytes) is too long a name: allowed a "
            "setting or option of at most 255 bytes")


def check_environment() -> None:
    """What a command reads from its environment is valid, else one line and exit code 2
    before Hydra starts: ``FLEET_TORCHRL_RUN_PID`` (:func:`~fleet_torchrl.config.run_pid`)."""
    from .config import run_pid
    from .utils.cli import user_errors

    with user_errors():
        run_pid()


def group_value_error(exc: BaseException) -> str | None:
    """The one-line message for an override Hydra's defaults list refuses with a
    ``ValueError`` while composing: no key (``=0.5``), or a config group given a value that
    names no option (``site=null``, ``~agent=1``); None for anything else."""
    tb, override, repo = exc.__traceback__, None, None
    while tb is not None:
        local = tb.tb_frame.f_locals
        if hasattr(local.get("override"), "input_line"):
            override, repo = local["override"], local.get("repo")
        tb = tb.tb_next
    if override is None:
        return None
    line, key = override.input_line, override.key_or_group
    if not key:
        return f"{line} is invalid: an override is key=value, with a key"
    try:
        options = sorted(repo.get_group_options(key)) if repo is not None else []
    except Exception:  # noqa: BLE001 (the options are a hint only)
        options = []
    allowed = f"allowed one of {', '.join(options)}" if options else "allowed an option name"
    return f"{line} is invalid: {key} is a config group; {allowed}"


@contextmanager
def one_line_errors() -> Iterator[None]:
    """Hydra's composition errors and missing extras as ``error: ...`` and exit code 2.

    Hydra reports an error of the command line in many lines (and exit code 1) unless
    ``HYDRA_FULL_ERROR`` is set, in which case it re-raises it: set here, so that the error
    reaches this handler whole."""
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    saved = os.environ.get("HYDRA_FULL_ERROR")
    os.environ["HYDRA_FULL_ERROR"] = "1"
    try:
        yield
    except (AssertionError, AttributeError) as e:  # OmegaConf's, on an override it cannot apply
        msg = None if raised_in_a_job(e) else override_error(e)
        if msg is None:
            raise
        print(f"error: {msg}", file=sys.stderr)
        sys.exit(2)
    except ValueError as e:  # Hydra's defaults list, on a group override it cannot apply
        msg = None if raised_in_a_job(e) else group_value_error(e)
        if msg is None:
            raise
        print(f"error: {msg}", file=sys.stderr)
        sys.exit(2)
    except (HydraException, OmegaConfBaseException, ImportError) as e:
        hint = missing_extra(e)
        if hint is None and (isinstance(e, ImportError) or raised_in_a_job(e)):
            raise
        print(f"error: {hint or one_line(e)}", file=sys.stderr)
        sys.exit(2)
    except OSError as e:  # (after Hydra's own, some of which are OSErrors)
        # Hydra looks a too long key up as a config file while composing
        msg = None if raised_in_a_job(e) else name_too_long(e)
        if msg is None:
            raise
        print(f"error: {msg}", file=sys.stderr)
        sys.exit(2)
    finally:
        if saved is None:
            os.environ.pop("HYDRA_FULL_ERROR", None)
        else:
            os.environ["HYDRA_FULL_ERROR"] = saved


# the config ValidateFirst validated for the run this process is about to start
_VALIDATED: list[Config] = []


def validated(dcfg: Any, groups: Iterable[str] = GROUPS) -> Config:
    """The task's typed config: the one :class:`ValidateFirst` checked before the run
    started (a single run), else validated now (a job of a multirun) for ``groups``, the
    groups the command reads (its module's ``GROUPS``)."""
    return _VALIDATED.pop() if _VALIDATED else to_config(dcfg, groups)


def command_groups(job_name: str) -> tuple[str, ...]:
    """The groups the command ``job_name`` reads: ``GROUPS`` of its module (every group of
    the root config for a command that declares none)."""
    import importlib

    try:
        module = importlib.import_module(f"{__package__}.{job_name}")
    except ImportError:  # an app of another package (a test's)
        return GROUPS
    return tuple(getattr(module, "GROUPS", GROUPS))


def groups_help(app_name: str) -> str:
    """``${fleet_groups:...}`` of the help template: the groups the command of a console
    script (``fleet-train``) reads; the others compose, but it neither reads nor checks
    them."""
    job = str(app_name).removeprefix("fleet-").replace("-", "_")
    read = command_groups(job)
    if tuple(read) == GROUPS:
        return ""
    return (f"\n== Groups {app_name} reads ==\n{', '.join(read)}, seed\n(it ignores the "
            "settings of the others; every command checks the run settings: site, state, "
            "mdp, agent, network, train)\n")


def _callback_base() -> type:
    from hydra.experimental.callback import Callback

    return Callback


def preflight(job_name: str, cfg: Config, run_dir: str | None) -> None:
    """The command's own checks before it starts (``preflight(cfg, run_dir)`` of the module
    ``fleet_torchrl.<job name>``, if it has one): every path it will write, a checkpoint to
    resume. Raises what :data:`~fleet_torchrl.utils.cli.USER_ERRORS` lists."""
    check = command_hook(job_name, "preflight")
    if check is not None:
        check(cfg, run_dir)


class _JobConfig:
    """``config`` as Hydra's ``run_job`` will see it: the Hydra singleton set to it and its
    ``hydra.runtime.output_dir`` resolved (``${hydra:runtime.output_dir}`` in a setting, as
    the grid's ``train.out_dir``, resolves to where the job will run). Restores the
    singleton on exit."""

    def __init__(self, config: Any, dir_key: str, subdir_key: str | None = None) -> None:
        self.config, self.dir_key, self.subdir_key = config, dir_key, subdir_key
        self.run_dir: str | None = None

    def __enter__(self) -> _JobConfig:
        from hydra.core.hydra_config import HydraConfig
        from omegaconf import OmegaConf, open_dict, read_write

        self._saved = HydraConfig.instance().cfg
        HydraConfig.instance().set_config(self.config)
        try:
            run_dir = str(OmegaConf.select(self.config, self.dir_key))
            if self.subdir_key is not None:
                run_dir = os.path.join(run_dir, str(OmegaConf.select(self.config,
                                                                     self.subdir_key)))
        except Exception:  # noqa: BLE001 (not resolvable here: the job meets it itself)
            return self
        self.run_dir = run_dir
        with read_write(self.config.hydra.runtime), open_dict(self.config.hydra.runtime):
            self.config.hydra.runtime.output_dir = os.path.abspath(run_dir)
        HydraConfig.instance().set_config(self.config)
        return self

    def __exit__(self, *exc: Any) -> None:
        from hydra.core.hydra_config import HydraConfig

        if self._saved is not None:
            HydraConfig.instance().set_config(self._saved)


def command_hook(job_name: str, hook: str) -> Callable[..., Any] | None:
    """The function ``hook`` of the module ``fleet_torchrl.<job name>``, if there is one:
    ``preflight``, ``output_paths`` (what a job writes outside its run folder), ``claim``
    (what a single run holds before Hydra writes its run folder)."""
    import importlib

    try:
        module = importlib.import_module(f"{__package__}.{job_name}")
    except ImportError:  # an app of another package (a test's) has none
        return None
    return getattr(module, hook, None)


def _check_job(config: Any, dir_key: str, subdir_key: str | None = None,
               label: str = "", run_preflight: bool = True,
               outputs: list[tuple[str, str, str]] | None = None,
               claim: bool = False) -> Config | None:
    """Validate one job's composed config and run its command's preflight, the job's run
    folder included, before anything is written; a bad value ends here in one line and exit
    code 2. Returns the typed config if it can be handed to the task as it is (one that
    refers to the run folder, resolved here ahead of ``run_job``, is validated again
    there), None otherwise. ``outputs`` collects ``(what, absolute path, label)`` of what
    the job writes outside its run folder (its command's ``output_paths``); ``claim``: hold
    the run folder now (its command's ``claim``), a single run's only; a multirun's job whose
    command claims its folder is refused if another process holds that folder now."""
    import copy

    from omegaconf.errors import OmegaConfBaseException

    from .utils.cli import USER_ERRORS, single_line
    from .utils.paths import check_not_held, check_output

    prefix = f"{label}: " if label else ""
    handed: Config | None = None
    groups = command_groups(str(config.hydra.job.name))
    try:
        try:  # as the task will get it (unless it refers to where the job runs)
            handed = to_config(without_hydra(config), groups)
        except OmegaConfBaseException:
            handed = None
        job_cfg = copy.deepcopy(config)
        with _JobConfig(job_cfg, dir_key, subdir_key) as job:
            if job.run_dir is not None:  # Hydra makes it, .hydra/ written or not
                check_output(f"hydra.{dir_key.split('.', 1)[1]}", job.run_dir, "dir")
            cfg = handed if handed is not None else to_config(without_hydra(job_cfg), groups)
            if run_preflight:
                preflight(str(job_cfg.hydra.job.name), cfg, job.run_dir)
            paths = command_hook(str(job_cfg.hydra.job.name), "output_paths")
            if outputs is not None and paths is not None:
                outputs += [(what, os.path.abspath(p), label) for what, p in paths(cfg)]
            hold = command_hook(str(job_cfg.hydra.job.name), "claim")
            if hold is not None and job.run_dir is not None:
                if claim:
                    hold(cfg, job.run_dir)
                else:  # a multirun's job holds its folder in its own process: in use now?
                    check_not_held(job.run_dir)
    except OmegaConfBaseException:  # resolvable in the run only: the task validates
        return None
    except USER_ERRORS as e:  # a bad value: one line, exit code 2, no run folder
        print(f"error: {prefix}{single_line(e)}", file=sys.stderr)
        sys.exit(2)
    except Exception:  # noqa: BLE001 (the task meets it again, with its traceback)
        return None
    return handed


def check_subdir(config: Any) -> None:
    """Raise :class:`~fleet_torchrl.utils.checks.ConfigError` for a ``hydra.sweep.subdir``
    that is empty or ``.``: every job of the multirun would run in the sweep's folder itself,
    one job's files over another's."""
    from omegaconf import OmegaConf

    from .utils.checks import ConfigError

    sweep = OmegaConf.to_container(config.hydra.sweep, resolve=False)
    subdir = sweep.get("subdir") if isinstance(sweep, dict) else None
    if isinstance(subdir, str) and subdir.strip() in ("", "."):
        raise ConfigError(f"hydra.sweep.subdir={subdir!r} is invalid: allowed a folder of "
                          "its own per job, e.g. ${hydra:job.num}")


class ValidateFirst(_callback_base()):
    """Hydra callback (``hydra.callbacks.validate`` in ``conf/config.yaml``): a config is
    validated, and every path its command will write checked (the command's ``preflight``:
    outputs, a checkpoint to resume), before Hydra creates a run folder or writes
    ``.hydra/``, so bad input ends in one line and exit code 2 with nothing written (a
    refused resume does not first overwrite the run's ``.hydra/overrides.yaml``). A single
    run then holds its run folder where its command says so (``claim``: a training's lock),
    still before ``.hydra/`` is written, and its typed config is handed to the task
    (:func:`validated`). A multirun checks every job this way before launching any (Hydra's
    basic sweeper: the jobs it will make; another sweeper: its base config), and refuses two
    jobs that would write one output (a training's publish folder, an ``eval.out``)."""

    def on_run_start(self, config: Any, **kwargs: Any) -> None:
        _VALIDATED.clear()
        cfg = _check_job(config, "hydra.run.dir", claim=True)
        if cfg is not None:
            _VALIDATED.append(cfg)

    def on_multirun_start(self, config: Any, **kwargs: Any) -> None:
        from hydra.core.global_hydra import GlobalHydra

        from .experiments.launch import sweep_jobs
        from .utils.cli import user_errors
        from .utils.paths import check_output

        with _JobConfig(config, "hydra.sweep.dir") as top, user_errors():
            if top.run_dir is not None:
                check_output("hydra.sweep.dir", top.run_dir, "dir")
            check_subdir(config)
        jobs = sweep_jobs(config)
        if jobs is None:  # another sweeper (the table's checks its own jobs): the base config
            _check_job(config, "hydra.sweep.dir", run_preflight=False)
            return
        loader = GlobalHydra.instance().config_loader()
        outputs: list[tuple[str, str, str]] = []
        for num, overrides in enumerate(jobs[0]):
            job_cfg = loader.load_sweep_config(config, list(overrides))
            from omegaconf import open_dict

            with open_dict(job_cfg):
                job_cfg.hydra.job.id = f"{job_cfg.hydra.job.name}_{num}"
                job_cfg.hydra.job.num = num
            label = " ".join(o for o in overrides
                             if o.split("=", 1)[0].lstrip("+~") in jobs[1]) or f"job {num}"
            _check_job(job_cfg, "hydra.sweep.dir", "hydra.sweep.subdir", label, outputs=outputs)
        shared_output(outputs)


def shared_output(outputs: list[tuple[str, str, str]]) -> None:
    """Exit with one line and code 2 if two jobs of a multirun would write one output
    (``(what, absolute path, job label)`` each): only the last to finish would survive."""
    seen: dict[str, tuple[str, str]] = {}
    for what, path, label in outputs:
        if path in seen:
            first_what, first = seen[path]
            print(f"error: jobs {first} and {label} would both write {what} {path}: one "
                  f"would replace the other's; give each job its own {first_what}"
                  + (" (train.out_dir, or no train.out_dir: each seed publishes to its own "
                     "folder)" if first_what == "publish folder" else ""), file=sys.stderr)
            sys.exit(2)
        seen[path] = (what, label)


class CheckRunDir(_callback_base()):
    """Hydra callback of the file tools (``conf/compare.yaml``, ...: ``hydra.callbacks``),
    which write no ``.hydra/`` but whose run folder Hydra still makes: ``hydra.run.dir``
    (``hydra.sweep.dir`` of a multirun) checked like any output (empty, too long a name,
    under ``/proc``) before Hydra makes it, in one line and exit code 2."""

    def on_run_start(self, config: Any, **kwargs: Any) -> None:
        self._check(config, "hydra.run.dir")

    def on_multirun_start(self, config: Any, **kwargs: Any) -> None:
        self._check(config, "hydra.sweep.dir")

    @staticmethod
    def _check(config: Any, key: str) -> None:
        from .utils.cli import user_errors
        from .utils.paths import check_output

        with _JobConfig(config, key) as job, user_errors():
            if job.run_dir is not None:
                check_output(key, job.run_dir, "dir")


def hydra_command(task: Callable[[Any], Any], config_name: str = "config",
                  config_path: str = "conf") -> Callable[[], Any]:
    """The entry point of a command (console script and ``python -m``): Hydra's app of
    ``task`` on ``fleet_torchrl/<config_path>/<config_name>.yaml``, the schemas registered
    first, its errors one line each. ``task`` must be defined in a module of this package's
    top level (Hydra finds ``config_path`` beside it and names the job after that module).
    Hydra's tab completion offers every group of ``config_path``: a command that takes none
    of the model's groups has a folder of its own (``tool_conf``)."""
    import hydra
    from omegaconf import OmegaConf

    app = hydra.main(version_base="1.3", config_path=config_path,
                     config_name=config_name)(task)

    def main() -> Any:
        from .utils.cli import user_errors

        with user_errors():  # an agent from outside that cannot be imported: one line
            register_configs()
        if not OmegaConf.has_resolver("fleet_groups"):
            OmegaConf.register_new_resolver("fleet_groups", groups_help)
        mark_multirun(sys.argv[1:])
        check_environment()
        with one_line_errors():
            return app()

    main.__doc__ = task.__doc__
    main.__module__ = task.__module__
    return main


__all__ = ["LAUNCHER_EXTRAS", "MODULE_EXTRAS", "CheckRunDir", "ValidateFirst", "hydra_command",
           "install_line", "missing_extra", "one_line_errors", "validated"]
