"""Exceptions of simuscene: every one carries the C++ message and its hint.

``Error`` is the base class. ``ConfigError`` and ``InputError`` are also ``ValueError``s (a bad config
key or value; a bad array, scene entry, mask or record), ``MissingFileError`` is also a
``FileNotFoundError`` (its ``filename`` names the file). Ctrl-C during a long call raises
``KeyboardInterrupt`` once the call has stopped cleanly.
"""

from __future__ import annotations

import errno
from typing import Optional

__all__ = ["Error", "ConfigError", "InputError", "MissingFileError"]


class Error(Exception):
    """An error of the toolkit: ``message`` names the file, key, record or object; ``hint`` says what to do."""

    def __init__(self, message: str, hint: str = "", filename: Optional[str] = None) -> None:
        super().__init__(message)
        self.message = message
        self.hint = hint

    def __str__(self) -> str:
        return f"{self.message} (hint: {self.hint})" if self.hint else self.message


class ConfigError(Error, ValueError):
    """A config file, key or value was refused (unknown key, wrong type, value out of its domain)."""


class InputError(Error, ValueError):
    """An input was refused: an array of the wrong shape or dtype, a malformed scene, a bad record."""


class MissingFileError(Error, FileNotFoundError):
    """A file the call needs does not exist; ``filename`` is its path."""

    def __init__(self, message: str, hint: str = "", filename: Optional[str] = None) -> None:
        Error.__init__(self, message, hint, filename)
        self.errno = errno.ENOENT
        self.strerror = message
        self.filename = filename

    def __str__(self) -> str:
        return Error.__str__(self)
