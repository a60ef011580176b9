"""How every ``lightprobe`` command ends (CONVENTIONS.md): 0 success, 2 bad arguments or bad
input (one line naming the file or parameter at fault), 1 other failures, 130 on Ctrl-C.

Each command module's ``main(argv)`` wraps its body in :func:`run_command`, which turns an
:class:`~lightprobe.core.errors.InputError` into ``lightprobe: error: ...`` on stderr and exit 2.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from typing import Any

from .errors import InputError

__all__ = ["run_command"]


def run_command(fn: Callable[..., Any], *args: Any, **kwargs: Any) -> int:
    """Run a command body, mapping InputError to exit 2 and a one-line message."""
    try:
        return int(fn(*args, **kwargs) or 0)
    except InputError as e:
        print(f"lightprobe: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
