"""Running a bridge's asyncio side until the service's stop event is set."""

from __future__ import annotations

import asyncio
import contextlib
import threading
from collections.abc import Awaitable, Callable


def run_until(main: Callable[[asyncio.Event], Awaitable[int]], stop: threading.Event) -> int:
    """``asyncio.run(main(done))`` where ``done`` is set once ``stop`` is: the service's
    stop is a thread event (signals, the agent hosting it), the bridge's I/O is asyncio."""

    async def wrapper() -> int:
        done = asyncio.Event()
        loop = asyncio.get_running_loop()

        def relay() -> None:
            stop.wait()
            loop.call_soon_threadsafe(done.set)

        threading.Thread(target=relay, name="uma-vrpn-stop", daemon=True).start()
        return await main(done)

    return asyncio.run(wrapper())


async def wait_for_event(event: asyncio.Event, seconds: float) -> None:
    """Until ``event`` is set or ``seconds`` have passed, whichever comes first."""
    with contextlib.suppress(TimeoutError):
        await asyncio.wait_for(event.wait(), seconds)
