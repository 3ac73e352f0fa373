"""Shutdown signals on an asyncio loop, as uvicorn handles them: SIGINT and SIGTERM call a
handler on the event loop (the daemon's and the supervisor's ``handle_signal``: the first
sets an event and draining starts, a second SIGINT forces)."""

from __future__ import annotations

import asyncio
import contextlib
import signal
import threading
from collections.abc import Callable, Iterator

HANDLED_SIGNALS = (signal.SIGINT, signal.SIGTERM)


@contextlib.contextmanager
def shutdown_signals(handler: Callable[[int], None], *, enabled: bool = True) -> Iterator[None]:
    """While inside, SIGINT and SIGTERM call ``handler(signal number)`` on the running loop.
    Nothing is installed when not ``enabled`` or off the main thread (only it may)."""
    loop = asyncio.get_running_loop()
    if not enabled or threading.current_thread() is not threading.main_thread():
        yield
        return
    for sig in HANDLED_SIGNALS:
        loop.add_signal_handler(sig, handler, sig)
    try:
        yield
    finally:
        for sig in HANDLED_SIGNALS:
            loop.remove_signal_handler(sig)


__all__ = ["HANDLED_SIGNALS", "shutdown_signals"]
