"""One base exception for every error dynslam raises on purpose.

Each error keeps a built-in base as well (``ConfigError`` is also a ``ValueError``, ``BackendError`` a
``RuntimeError``) so code written against those keeps working. ``exit_code`` is what the command line
turns it into: 2 for a usage or input error (a bad path, config value, file), 1 for a failure while
running (the back end, the network).
"""
from __future__ import annotations

EXIT_RUNTIME_FAILURE = 1
EXIT_USAGE = 2
EXIT_INTERRUPTED = 130   # 128 + SIGINT, what shells report for Ctrl-C


class DynslamError(Exception):
    """Base of every deliberate dynslam error; the message says what is wrong and where."""

    exit_code = EXIT_USAGE


class RuntimeFailure(DynslamError):
    """A failure while running, not a fault of the input: exit status 1."""

    exit_code = EXIT_RUNTIME_FAILURE
