"""The person at the simulated tripod: follows the levelling guidance, correcting most of the error.

An instruction names a leg and the tilt it addresses (``"raise the right leg (roll +1.20 deg)"`` or
``"lower the front leg (pitch +0.80 deg)"``, as :func:`appliance.acquisition.procedures.level_guidance`
says); the person removes ``gain`` of that component of the head's tilt.  The head plane's slope
(``tilt_north_deg``, ``tilt_east_deg`` of :class:`SimWorld`) is changed accordingly.
"""

from __future__ import annotations

import math

from appliance.sim.world import SimWorld


class SimLeveller:
    def __init__(self, world: SimWorld, gain: float = 0.7) -> None:
        self.world, self.gain = world, gain
        self.heard: list[str] = []

    def instruct(self, instruction: str) -> None:
        self.heard.append(instruction)
        w = self.world
        with w.lock:
            h = math.radians(w.head_heading_deg)
            gn, ge = math.tan(math.radians(w.tilt_north_deg)), math.tan(math.radians(w.tilt_east_deg))
            fwd = gn * math.cos(h) + ge * math.sin(h)  # slope along the optical axis
            right = -gn * math.sin(h) + ge * math.cos(h)  # slope towards the right-hand side
            if "(roll" in instruction:
                right *= 1.0 - self.gain
            else:
                fwd *= 1.0 - self.gain
            gn = fwd * math.cos(h) - right * math.sin(h)
            ge = fwd * math.sin(h) + right * math.cos(h)
            w.tilt_north_deg, w.tilt_east_deg = math.degrees(math.atan(gn)), math.degrees(math.atan(ge))
