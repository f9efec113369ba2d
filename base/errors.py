"""The project's one error for bad user input, and the checks every reader shares.

Bad input raises :class:`InputError`, whose message names the file, the column or frame, and what was
expected; the command-line shell (``base.cli``) prints it on one line and exits with status 2.
"""
from __future__ import annotations

import os
from pathlib import Path


class InputError(ValueError):
    """Bad user input.  The message names the file, the column or frame, and what was expected."""


def require_file(path: str | os.PathLike, what: str = "file", key: str | None = None) -> Path:
    """``path`` as a Path; InputError ("<path>: <what> not found", with the config ``key`` that named it)
    when it is not an existing file."""
    path = Path(path)
    if not path.is_file():
        where = f"{key}={path}" if key else str(path)
        raise InputError(f"{where}: {what} not found")
    return path
