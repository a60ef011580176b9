"""Errors shared by every stage of the probe.

`InputError` is raised for bad input a user can fix (a file, a parameter, a request field). The CLI
turns it into exit code 2 and a one-line message; the HTTP API turns it into a 4xx JSON error.
Its message must name the file or parameter at fault.
"""

from __future__ import annotations

__all__ = ["InputError", "LightprobeError"]


class LightprobeError(Exception):
    """Base class of the project's own errors."""


class InputError(LightprobeError, ValueError):
    """Bad input from a user: the message names the file or parameter at fault."""

    def __init__(self, message: str, *, param: str | None = None) -> None:
        super().__init__(message)
        self.param = param
