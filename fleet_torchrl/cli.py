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
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

from .config import Config, one_line, register_configs, to_config, without_hydra

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
    except (HydraException, OmegaConfBaseException, ImportError) as e:
        hint = missing_extra(e)
        if hint is None and (isinstance(e, ImportError) or raised_in_a_job(e)):
            raise
        print(f"error: {hint or one_line(e)}", file=sys.stderr)
        sys.exit(2)
    finally:
        if saved is None:
            os.environ.pop("HYDRA_FULL_ERROR", None)
        else:
            os.environ["HYDRA_FULL_ERROR"] = saved


# the config ValidateFirst validated for the run this process is about to start
_VALIDATED: list[Config] = []


def validated(dcfg: Any) -> Config:
    """The task's typed config: the one :class:`ValidateFirst` checked before the run
    started (a single run), else validated now (a job of a multirun)."""
    return _VALIDATED.pop() if _VALIDATED else to_config(dcfg)


def _callback_base() -> type:
    from hydra.experimental.callback import Callback

    return Callback


class ValidateFirst(_callback_base()):
    """Hydra callback (``hydra.callbacks.validate`` in ``conf/config.yaml``): a single run's
    config is validated before Hydra creates its run folder, so a bad value ends in one line
    and exit code 2 without leaving an empty ``outputs/<command>/...`` behind; the task then
    takes this config (:func:`validated`) instead of validating it again. A config that can
    only be resolved inside the run (``${hydra:runtime.output_dir}``) is left to the task."""

    def on_run_start(self, config: Any, **kwargs: Any) -> None:
        from omegaconf.errors import OmegaConfBaseException

        from .utils.cli import USER_ERRORS

        _VALIDATED.clear()
        try:
            cfg = to_config(without_hydra(config))
        except OmegaConfBaseException:  # resolvable in the run only: the task validates
            return
        except USER_ERRORS as e:  # a bad value: one line, exit code 2, no run folder
            print(f"error: {e}", file=sys.stderr)
            sys.exit(2)
        except Exception:  # noqa: BLE001 (the task meets it again, with its traceback)
            return
        _VALIDATED.append(cfg)


def hydra_command(task: Callable[[Any], Any], config_name: str = "config"
                  ) -> Callable[[], Any]:
    """The entry point of a command (console script and ``python -m``): Hydra's app of
    ``task`` on ``fleet_torchrl/conf/<config_name>.yaml``, the schemas registered first, its
    errors one line each. ``task`` must be defined in a module of this package's top level
    (Hydra finds ``conf/`` beside it and names the job after that module)."""
    import hydra

    app = hydra.main(version_base="1.3", config_path="conf", config_name=config_name)(task)

    def main() -> Any:
        register_configs()
        with one_line_errors():
            return app()

    main.__doc__ = task.__doc__
    main.__module__ = task.__module__
    return main


__all__ = ["LAUNCHER_EXTRAS", "MODULE_EXTRAS", "ValidateFirst", "hydra_command",
           "install_line", "missing_extra", "one_line_errors", "validated"]
