"""Waiting for a condition in tests: the one polling loop every test folder uses (a uniquely named
module on the tests' path). ``timeout`` is a hang guard, never a performance bound."""
from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from typing import Any


def wait_until(pred: Callable[[], Any], timeout: float, interval: float = 0.05) -> bool:
    """Poll ``pred`` every ``interval`` s until it is true or ``timeout`` s have passed; its last value."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(interval)
    return bool(pred())


async def async_wait_until(pred: Callable[[], Any], timeout: float, interval: float = 0.01) -> bool:
    """:func:`wait_until` for a coroutine: the loop runs while it waits."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        await asyncio.sleep(interval)
    return bool(pred())
