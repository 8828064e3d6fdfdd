"""What every command line shares: bad input ends in one line on stderr and exit code 2."""

from __future__ import annotations

import sys
from collections.abc import Iterator
from contextlib import contextmanager

from .checks import ConfigError, SetupError
from .runinfo import WriteError

# what a user can act on: a bad value, a missing or unreadable file, a path that cannot be
# written, a machine that cannot run what was asked (the message says what instead)
USER_ERRORS = (ConfigError, FileNotFoundError, ValueError, IsADirectoryError, PermissionError,
               NotADirectoryError, WriteError, SetupError)


@contextmanager
def user_errors() -> Iterator[None]:
    """Turn a bad config value, a missing file or an unreadable file into ``error: ...``.

    Programming errors still raise with their traceback.
    """
    try:
        yield
    except USER_ERRORS as e:
        print(f"error: {single_line(e)}", file=sys.stderr)
        sys.exit(2)


def single_line(exc: BaseException) -> str:
    """An error's message on one line (a message that spans lines is joined with ``; ``)."""
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    return "; ".join(lines) or type(exc).__name__
