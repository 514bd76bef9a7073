"""A FLIR/Directed Perception PTU twin on a pty: the ASCII protocol, limits, motion and missed steps.

Moves take ``distance / speed`` of simulated time.  With ``miss_step_every = N`` every Nth move
stops ``miss_positions`` short of its target (a stalled stepper), as a real unit does silently: its
position query then tells the truth, and the driver notices.  With ``stall_at_deg`` the pan axis
cannot pass that angle (an obstacle): a move across it ends there.
"""

from __future__ import annotations

import logging
import threading

from appliance.sim.pty_port import PtyPort
from appliance.sim.world import SimWorld

log = logging.getLogger(__name__)


class PtuTwin:
    def __init__(
        self,
        world: SimWorld,
        port: PtyPort,
        arcsec_per_position: float = 92.5714,
        min_position: int = -3090,
        max_position: int = 3090,
        speed_positions_s: int = 1000,
        miss_step_every: int = 0,
        miss_positions: int = 20,
        silent: bool = False,
        stall_at_deg: float | None = None,
    ) -> None:
        self.world, self.port = world, port
        self.res = arcsec_per_position
        self.lo, self.hi = min_position, max_position
        self.speed = speed_positions_s
        self.miss_every, self.miss_positions = miss_step_every, miss_positions
        self.silent = silent
        self.stall_position = None if stall_at_deg is None else round(stall_at_deg * 3600.0 / arcsec_per_position)
        self.position = 0
        self.terse = False
        self.echo = True
        self.moves = 0
        self._pending_s = 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="ptu-twin", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5.0)

    def _set_position(self, p: int) -> None:
        self.position = p
        with self.world.lock:
            self.world.stage_deg = p * self.res / 3600.0

    def handle(self, cmd: str) -> str:
        """The reply line to one command (pure apart from the twin's state)."""
        c = cmd.strip().upper()
        if c == "ED":
            self.echo = False
            return "*"
        if c == "EE":
            self.echo = True
            return "*"
        if c == "FT":
            self.terse = True
            return "*"
        if c in ("FV", "CI", "CV", "A", "R", "H"):
            if c == "A":
                self.world.clock.sleep(self._pending_s)
                self._pending_s = 0.0
            if c == "R":
                self._set_position(0)
            return "*"
        if c == "PR":
            return f"* {self.res}"
        if c == "PN":
            return f"* {self.lo}"
        if c == "PX":
            return f"* {self.hi}"
        if c == "PP":
            return f"* {self.position}"
        if c.startswith("PS"):
            try:
                v = int(c[2:])
            except ValueError:
                return "! Illegal argument"
            if v <= 0:
                return "! Illegal speed"
            self.speed = v
            return "*"
        if c.startswith("PP"):
            try:
                target = int(c[2:])
            except ValueError:
                return "! Illegal argument"
            if not self.lo <= target <= self.hi:
                return f"! Maximum allowable Pan position is {self.hi}" if target > self.hi else \
                    f"! Minimum allowable Pan position is {self.lo}"
            self.moves += 1
            reached = target
            if self.miss_every and self.moves % self.miss_every == 0:
                step = self.miss_positions if target > self.position else -self.miss_positions
                reached = target - step
                log.info("ptu twin: move %d to %d stalls at %d", self.moves, target, reached)
            s = self.stall_position
            if s is not None and min(self.position, target) < s < max(self.position, target):
                reached = s
                log.info("ptu twin: move %d to %d stopped by an obstacle at %d", self.moves, target, s)
            self._pending_s = abs(target - self.position) / self.speed
            self._set_position(reached)
            return "*"
        return f"! Illegal command {c[:8]}"

    def _run(self) -> None:
        buf = b""
        while not self._stop.is_set():
            data = self.port.read(64, 0.05)
            if not data:
                continue
            buf += data
            while True:
                cut = min((i for i in (buf.find(b" "), buf.find(b"\n"), buf.find(b"\r")) if i >= 0), default=-1)
                if cut < 0:
                    break
                cmd, buf = buf[:cut].decode("ascii", errors="replace"), buf[cut + 1 :]
                if not cmd.strip():
                    continue
                reply = self.handle(cmd)
                if self.silent:
                    continue
                echo = (cmd + " ") if self.echo else ""
                self.port.write((echo + reply + "\r\n").encode("ascii"))
