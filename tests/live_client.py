"""A strict Foxglove WebSocket client for the live view's tests and bench: it subscribes once to every
channel as it is advertised (never again), and keeps every message, every status the server sends
(a refused subscription is one: "Unknown channel ID") and every channel it was told of."""

from __future__ import annotations

import asyncio
import json
import struct
import threading
import time
from collections import Counter

SUBPROTOCOL = "foxglove.sdk.v1"


class StrictClient(threading.Thread):
    """Connects to ``ws://127.0.0.1:port`` as soon as the port accepts (retrying a refused connection
    until ``connect_timeout_s``), then runs until :attr:`stop` is set or the server closes."""

    def __init__(self, port: int, connect_timeout_s: float = 120.0, subprotocols: tuple[str, ...] = (SUBPROTOCOL,)
                 ) -> None:
        super().__init__(daemon=True)
        self.url = f"ws://127.0.0.1:{port}"
        self.connect_timeout_s = connect_timeout_s
        self.subprotocols = list(subprotocols)
        self.connected = threading.Event()
        self.stop = threading.Event()
        self.closed = threading.Event()
        self.server_info: dict = {}
        self.channels: dict[int, dict] = {}
        self.subscribed: set[int] = set()
        self.messages: list[tuple[str, int, bytes]] = []  # topic, log time, payload
        self.statuses: list[dict] = []
        self.error: BaseException | None = None

    def run(self) -> None:
        try:
            asyncio.run(self._run())
        except BaseException as exc:  # surfaced by the test
            self.error = exc
        finally:
            self.connected.set()
            self.closed.set()

    async def _connect(self):
        import websockets

        deadline = time.monotonic() + self.connect_timeout_s
        while True:
            try:
                return await websockets.connect(self.url, subprotocols=self.subprotocols, max_size=None)
            except OSError:
                if time.monotonic() > deadline:
                    raise
                await asyncio.sleep(0.005)

    async def _run(self) -> None:
        import websockets

        ws = await self._connect()
        async with ws:
            self.connected.set()
            subscriptions: dict[int, int] = {}
            while not self.stop.is_set():
                try:
                    raw = await asyncio.wait_for(ws.recv(), 0.1)
                except TimeoutError:
                    continue
                except websockets.ConnectionClosed:
                    return
                if isinstance(raw, str):
                    await self._on_text(ws, json.loads(raw), subscriptions)
                elif raw[0] == 1:  # message data: opcode, subscription id (u32), log time (u64), payload
                    sub_id, log_time = struct.unpack_from("<IQ", raw, 1)
                    topic = self.channels[subscriptions[sub_id]]["topic"]
                    self.messages.append((topic, log_time, bytes(raw[13:])))

    async def _on_text(self, ws, msg: dict, subscriptions: dict[int, int]) -> None:
        if msg["op"] == "serverInfo":
            self.server_info = msg
        elif msg["op"] == "status":
            self.statuses.append(msg)
        elif msg["op"] == "advertise":
            subs = []
            for ch in msg["channels"]:
                self.channels[ch["id"]] = ch
                if ch["id"] in self.subscribed:
                    continue
                self.subscribed.add(ch["id"])
                sub_id = len(subscriptions) + 1
                subscriptions[sub_id] = ch["id"]
                subs.append({"id": sub_id, "channelId": ch["id"]})
            if subs:
                await ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))

    def refused(self) -> list[str]:
        """The server's statuses refusing a subscription."""
        return [s["message"] for s in self.statuses if "Unknown channel" in s.get("message", "")]

    def counts(self) -> Counter:
        return Counter(topic for topic, _, _ in list(self.messages))

    def payloads(self, topic: str) -> list[bytes]:
        return [data for tp, _, data in list(self.messages) if tp == topic]

    def finish(self, timeout_s: float = 30.0) -> None:
        """Stop (if the server has not closed the connection already) and wait for the thread."""
        self.stop.set()
        self.join(timeout_s)
