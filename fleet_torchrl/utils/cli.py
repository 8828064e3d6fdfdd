"""What every command line shares: bad input ends in one line on stderr and exit code 2."""

from __future__ import annotations

import sys
from collections.abc import Iterator
from contextlib import contextmanager

from .checks import ConfigError

USER_ERRORS = (ConfigError, FileNotFoundError, ValueError, IsADirectoryError, PermissionError)


@contextmanager
def user_errors() -> Iterator[None]:
    """Turn a bad config value, a missing file or an unreadable file into ``error: ...``.

    Programming errors still raise with their traceback.
    """
    try:
        yield
    except USER_ERRORS as e:
        print(f"error: {e}", file=sys.stderr)
        sys.exit(2)
