"""A userspace TCP proxy for link faults where the kernel has no ``sch_netem``: it
forwards every connection made to ``--listen`` to ``--target`` and, on commands read from
stdin, delays what it carries, stalls it or cuts it.

    python -m tests.agent_helpers.tcp_proxy --listen 127.0.0.1:7447 --target 10.0.0.1:7447

stdin: ``delay MS`` (every byte, both ways, is held MS ms; 0 ends it), ``rate KBPS`` (each
direction of each connection carries at most KBPS kilobytes per second; 0 ends the cap),
``stall`` (nothing is forwarded; the bytes wait, and TCP's flow control holds the senders),
``resume``, ``cut``
(every open connection is closed; new ones are accepted).  Each command is acknowledged by
``{"event": "ack", "command": ...}`` on stdout; ``{"event": "ready"}`` once it listens.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import sys
import time


class Link:
    """The state every connection of the proxy follows."""

    def __init__(self) -> None:
        self.delay_s = 0.0
        self.bytes_per_s = 0.0  # 0: no cap
        self.flowing = asyncio.Event()
        self.flowing.set()
        self.writers: set[asyncio.StreamWriter] = set()

    def cut(self) -> None:
        for w in list(self.writers):
            w.close()
        self.writers.clear()


async def pump(link: Link, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
    """One direction: read, hold each chunk until its time and while stalled, write."""
    queue: asyncio.Queue[tuple[float, bytes] | None] = asyncio.Queue()

    async def read() -> None:
        with contextlib.suppress(ConnectionError, OSError):
            while data := await reader.read(65536):
                await queue.put((time.monotonic() + link.delay_s, data))
        await queue.put(None)

    reading = asyncio.create_task(read())
    free_at = time.monotonic()  # when the capped link is free to send again
    try:
        while (item := await queue.get()) is not None:
            due, data = item
            if link.bytes_per_s:
                free_at = max(free_at, time.monotonic()) + len(data) / link.bytes_per_s
                due = max(due, free_at)
            await asyncio.sleep(max(0.0, due - time.monotonic()))
            await link.flowing.wait()
            writer.write(data)
            await writer.drain()
    except (ConnectionError, OSError):
        pass
    finally:
        reading.cancel()
        writer.close()


async def serve(args: argparse.Namespace) -> None:
    link = Link()
    t_host, t_port = args.target.rsplit(":", 1)

    async def on_client(c_reader: asyncio.StreamReader, c_writer: asyncio.StreamWriter
                        ) -> None:
        try:
            s_reader, s_writer = await asyncio.open_connection(t_host, int(t_port))
        except OSError:
            c_writer.close()
            return
        link.writers |= {c_writer, s_writer}
        await asyncio.gather(pump(link, c_reader, s_writer), pump(link, s_reader, c_writer))
        link.writers -= {c_writer, s_writer}

    l_host, l_port = args.listen.rsplit(":", 1)
    server = await asyncio.start_server(on_client, l_host, int(l_port))
    print(json.dumps({"event": "ready"}), flush=True)
    loop = asyncio.get_running_loop()
    async with server:
        while line := await loop.run_in_executor(None, sys.stdin.readline):
            words = line.split()
            if not words:
                continue
            if words[0] == "delay":
                link.delay_s = float(words[1]) / 1000.0
            elif words[0] == "rate":
                link.bytes_per_s = float(words[1]) * 1000.0
            elif words[0] == "stall":
                link.flowing.clear()
            elif words[0] == "resume":
                link.flowing.set()
            elif words[0] == "cut":
                link.cut()
            print(json.dumps({"event": "ack", "command": words[0]}), flush=True)


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--listen", required=True, help="HOST:PORT to accept connections on")
    ap.add_argument("--target", required=True, help="HOST:PORT to forward them to")
    asyncio.run(serve(ap.parse_args()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
