"""How much the live view still has to deliver, read from the kernel's TCP tables.

foxglove-sdk queues each client's messages and writes them to the client's socket from its own
threads; it says nothing of how far it got, and stopping the server drops whatever is still queued.
What the kernel holds for a connection is visible in ``/proc/net/tcp`` (and ``tcp6``): its
``tx_queue``, the bytes written but not yet acknowledged by the client.  A server whose every
connection has had nothing unacknowledged for a while has handed its clients everything queued
(the SDK's writer loop, once the kernel takes data, leaves nothing behind for long).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

#: the kernel's TCP connection tables (IPv4, IPv6)
TCP_TABLES = (Path("/proc/net/tcp"), Path("/proc/net/tcp6"))
#: ``st`` of an established connection in those tables
ESTABLISHED = "01"
#: nothing unacknowledged for this long counts as drained (s)
QUIET_S = 0.25
POLL_S = 0.02


def unsent_bytes(port: int, tables: tuple[Path, ...] = TCP_TABLES) -> int | None:
    """Bytes written to the established connections whose local port is ``port`` and not yet
    acknowledged by their peers; None when no table can be read (not Linux)."""
    total, read_any = 0, False
    for table in tables:
        try:
            lines = table.read_text().splitlines()[1:]
        except OSError:
            continue
        read_any = True
        for line in lines:
            fields = line.split()
            if len(fields) < 5 or fields[3] != ESTABLISHED:
                continue
            if int(fields[1].rsplit(":", 1)[1], 16) == port:
                total += int(fields[4].split(":", 1)[0], 16)
    return total if read_any else None


def wait_drained(port: int, timeout_s: float, busy: Callable[[], bool],
                 clock: Callable[[], float] = time.monotonic, sleep: Callable[[float], None] = time.sleep) -> bool:
    """Wait until nothing is left to deliver on ``port``, at most ``timeout_s`` seconds: True at once
    when ``busy()`` says no client is subscribed, or when the connections on ``port`` have held no
    unacknowledged byte for :data:`QUIET_S`; False at the timeout (also where the tables cannot be read)."""
    deadline = clock() + timeout_s
    quiet_since: float | None = None
    while busy():
        now = clock()
        if unsent_bytes(port) == 0:
            quiet_since = now if quiet_since is None else quiet_since
            if now - quiet_since >= QUIET_S:
                return True
        else:
            quiet_since = None
        if now >= deadline:
            return False
        sleep(POLL_S)
    return True
