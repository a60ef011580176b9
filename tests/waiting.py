"""Waits on events, with a guard against a hang only.

A test waits for what it needs to see (a discovery event, a merge, a frame), never for a time to
pass. Each wait has one generous limit, ``HANG_S``, 10x or more of what the wait takes on a
loaded 2-core machine, so it can only fail on a hang, and then says so."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator, Callable
from typing import Any

__all__ = ["HANG_S", "discovered", "hang_guard"]

HANG_S = 60.0


@contextlib.asynccontextmanager
async def hang_guard(what: str, seconds: float = HANG_S) -> AsyncIterator[None]:
    """Fail with "hung: WHAT" if the block has not finished after ``seconds``."""
    try:
        async with asyncio.timeout(seconds):
            yield
    except TimeoutError:
        raise AssertionError(f"hung: {what} (nothing after {seconds:g} s)") from None


async def discovered(discovery: Any, predicate: Callable[[dict[str, Any]], bool], what: str,
                     seconds: float = HANG_S) -> dict[str, Any]:
    """``discovery.wait_for(predicate)``, failing with "hung: WHAT" after ``seconds``."""
    try:
        return dict(await discovery.wait_for(predicate, within=seconds))
    except TimeoutError:
        raise AssertionError(f"hung: {what} (no such discovery event after {seconds:g} s)") from None
